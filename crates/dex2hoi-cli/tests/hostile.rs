//! `dex2hoi data prepare` on a hostile file: the 123-byte pickle the fuzzer found, whose shared
//! references nest into gigabytes, put in place of a HUMOTO `.pkl`. It is refused with an error
//! that names the file, within a small, bounded memory. Alone in its test binary, so that the
//! peak resident memory of this process's children is the command's own.

use std::path::PathBuf;

mod common;
use common::dex2hoi;

/// `crates/dex2hoi-import/tests/fixtures/pickle-bomb-123b.pkl` (the fuzzer's input).
const BOMB: &[u8] = include_bytes!("../../dex2hoi-import/tests/fixtures/pickle-bomb-123b.pkl");

/// The most resident memory the refused command may reach. Reading the bomb took 1.4 GB
/// before the pickle reader bounded its result by the file's size; a real HUMOTO pickle of
/// 1.5 MB takes about 30 MB.
const PEAK_LIMIT_MIB: i64 = 256;

fn temp_dir(name: &str) -> PathBuf {
    common::temp_dir("hostile", name)
}

#[test]
fn a_pickle_bomb_is_refused_within_bounded_memory() {
    let root = temp_dir("root");
    let sequence = root.join("bomb-1");
    std::fs::create_dir_all(&sequence).unwrap();
    std::fs::write(sequence.join("bomb-1.pkl"), BOMB).unwrap();
    std::fs::write(
        sequence.join("bomb-1.yaml"),
        "name: \"lifting a box\"\nshort_script: \"The subject lifts the box.\"\n",
    )
    .unwrap();
    let out = temp_dir("out");
    let run = dex2hoi(&[
        "data",
        "prepare",
        "--format",
        "humoto",
        "--root",
        root.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    let (stdout, stderr) =
        (String::from_utf8_lossy(&run.stdout), String::from_utf8_lossy(&run.stderr));
    assert!(!run.status.success(), "{stdout}");
    assert!(
        stdout.contains("bomb-1.pkl") && stdout.contains("MiB of memory"),
        "the failure names the file and the limit: {stdout}"
    );
    assert!(stderr.contains("nothing written") && !out.exists(), "{stderr}");
    // Linux reports the children's peak in KiB.
    let usage = nix::sys::resource::getrusage(nix::sys::resource::UsageWho::RUSAGE_CHILDREN)
        .expect("the children's resource usage");
    let peak_mib = usage.max_rss() / 1024;
    assert!(peak_mib < PEAK_LIMIT_MIB, "data prepare reached {peak_mib} MiB");
    std::fs::remove_dir_all(&root).ok();
}
