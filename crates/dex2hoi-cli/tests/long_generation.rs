//! Long generations with the shipped model: a length that cannot fit in memory refused at once
//! with nothing written, and Ctrl-C during a long generation stopping it with nothing written.

use std::io::{BufRead, BufReader};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

mod common;
use common::{dex2hoi, temp_dir};

const PROMPT: &str = "The person picks up the mug with the right hand.";

#[test]
fn a_length_that_cannot_fit_is_refused_before_any_work() {
    let out = temp_dir("long_generation", "refused");
    let started = Instant::now();
    let output = dex2hoi(&[
        "sample",
        "--text",
        PROMPT,
        "--object",
        "mug",
        "--frames",
        "100000000",
        "--out",
        out.to_str().unwrap(),
    ]);
    let seconds = started.elapsed().as_secs_f64();
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(!output.status.success(), "{stderr}");
    assert!(seconds < 10.0, "refused after {seconds:.1} s");
    for needle in ["--frames 100000000", "58 days", "of memory", "is available", "at most --frames"]
    {
        assert!(stderr.contains(needle), "`{needle}` in: {stderr}");
    }
    assert!(!out.exists(), "{} was created", out.display());
}

#[test]
fn ctrl_c_stops_a_long_generation_and_writes_nothing() {
    use nix::sys::signal::{Signal, kill};
    use nix::unistd::Pid;

    let out = temp_dir("long_generation", "interrupted");
    // The shipped model adds 40 frames a window: 4000 frames are 100 windows, over a minute on
    // two cores with the default 50 steps, so the generation is announced after the first.
    let mut child = Command::new(env!("CARGO_BIN_EXE_dex2hoi"))
        .args([
            "sample",
            "--text",
            PROMPT,
            "--object",
            "mug",
            "--frames",
            "4000",
            "--out",
            out.to_str().unwrap(),
        ])
        .env("RUST_BACKTRACE", "0")
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .expect("the binary runs");
    let pid = Pid::from_raw(i32::try_from(child.id()).unwrap());
    // Never left running if the test fails on the way.
    let guard = std::thread::spawn(move || {
        std::thread::sleep(Duration::from_secs(120));
        kill(pid, Signal::SIGKILL).ok();
    });
    let mut stderr = BufReader::new(child.stderr.take().unwrap());
    let mut seen = String::new();
    let started = Instant::now();
    loop {
        let mut line = String::new();
        if stderr.read_line(&mut line).unwrap() == 0 {
            panic!("the generation ended without announcing itself: {seen}");
        }
        seen += &line;
        if line.starts_with("generating 4000 frames (3 min 20 s of motion) in 100 windows") {
            break;
        }
    }
    assert!(seen.contains("about "), "{seen}");
    kill(pid, Signal::SIGINT).unwrap();
    let interrupted = Instant::now();
    let mut rest = String::new();
    std::io::Read::read_to_string(&mut stderr, &mut rest).unwrap();
    let status = child.wait().unwrap();
    seen += &rest;
    assert!(!status.success(), "{seen}");
    assert!(seen.contains("Ctrl-C: stopping after this window"), "{seen}");
    assert!(seen.contains("interrupted (Ctrl-C) after"), "{seen}");
    assert!(seen.contains("nothing written"), "{seen}");
    // It stopped at the next window, not at the end of the generation.
    assert!(interrupted.elapsed() < Duration::from_secs(20), "{seen}");
    assert!(started.elapsed() < Duration::from_secs(60), "{seen}");
    assert!(!out.exists(), "{} was created", out.display());
    drop(guard);
}
