//! `cargo xtask fuzz`: the fuzz targets of `fuzz/` (cargo-fuzz, libFuzzer) for the readers of
//! untrusted files.
//!
//! - `fuzz NAME [SECONDS]` (NAME: `pickle`, `npy`, `glb`, `mesh`, `checkpoint`, `yaml`, or
//!   `all`): runs libFuzzer with its sanitizers for SECONDS (default 600) per target.
//!   cargo-fuzz is installed once (`cargo install cargo-fuzz`) if missing and runs on the
//!   stable toolchain with
//!   `RUSTC_BOOTSTRAP=1`. New inputs go to `target/fuzz/corpus/NAME` (the committed seeds of
//!   `fuzz/corpus/NAME` are read too); a crash, a hang (10 s) or an allocation over 2 GiB stops
//!   the run and leaves the input in `fuzz/artifacts/NAME`.
//! - `fuzz check`: what CI runs: the targets built without sanitizers and each run once over its
//!   seed corpus.

use std::path::Path;
use std::process::Command;

use anyhow::{Context, Result, bail};

/// The fuzz targets (binaries of `fuzz/Cargo.toml`).
pub const TARGETS: [&str; 6] = ["pickle", "npy", "glb", "mesh", "checkpoint", "yaml"];

/// The cargo-fuzz version installed when none is.
const CARGO_FUZZ_VERSION: &str = "0.13.2";

/// Default run time per target (seconds).
const DEFAULT_SECONDS: u64 = 600;

/// `cargo xtask fuzz ARGS`.
pub fn fuzz(root: &Path, args: &[String]) -> Result<()> {
    match args.first().map(String::as_str) {
        Some("check") => check(root),
        Some(name) => {
            let seconds = match args.get(1) {
                Some(text) => {
                    text.parse::<u64>().ok().filter(|s| *s > 0).with_context(|| {
                        format!("SECONDS must be a positive number, got `{text}`")
                    })?
                }
                None => DEFAULT_SECONDS,
            };
            let targets: Vec<&str> = match name {
                "all" => TARGETS.to_vec(),
                name if TARGETS.contains(&name) => vec![name],
                other => bail!("unknown fuzz target `{other}`; known: {}, all", TARGETS.join(", ")),
            };
            ensure_cargo_fuzz(root)?;
            for target in targets {
                run(root, target, seconds)?;
            }
            Ok(())
        }
        None => bail!(
            "usage: cargo xtask fuzz NAME|all [SECONDS] | check; targets: {}",
            TARGETS.join(", ")
        ),
    }
}

fn ensure_cargo_fuzz(root: &Path) -> Result<()> {
    let installed = Command::new("cargo")
        .args(["fuzz", "--version"])
        .output()
        .is_ok_and(|o| o.status.success());
    if !installed {
        crate::cargo(
            root,
            &["install", "cargo-fuzz", "--locked", "--version", CARGO_FUZZ_VERSION],
        )?;
    }
    Ok(())
}

fn run(root: &Path, target: &str, seconds: u64) -> Result<()> {
    let corpus = root.join("target/fuzz/corpus").join(target);
    std::fs::create_dir_all(&corpus).with_context(|| format!("creating {}", corpus.display()))?;
    let seeds = root.join("fuzz/corpus").join(target);
    let time = format!("-max_total_time={seconds}");
    let args = [
        "fuzz",
        "run",
        "--fuzz-dir",
        "fuzz",
        "--target-dir",
        "target/fuzz/sanitized",
        target,
        corpus.to_str().context("a UTF-8 path")?,
        seeds.to_str().context("a UTF-8 path")?,
        "--",
        &time,
        "-timeout=10",
        "-rss_limit_mb=2048",
        "-malloc_limit_mb=2048",
        "-print_final_stats=1",
    ];
    eprintln!("\n==> RUSTC_BOOTSTRAP=1 cargo {}", args.join(" "));
    let status = Command::new("cargo")
        .args(args)
        .env("RUSTC_BOOTSTRAP", "1")
        .current_dir(root)
        .status()
        .context("cannot run cargo fuzz")?;
    if !status.success() {
        bail!("fuzz target `{target}` found a failure: see fuzz/artifacts/{target}/ ({status})");
    }
    Ok(())
}

/// Builds the targets without sanitizers and runs each over its seed corpus once.
pub fn check(root: &Path) -> Result<()> {
    crate::cargo(
        root,
        &[
            "build",
            "--release",
            "--locked",
            "--manifest-path",
            "fuzz/Cargo.toml",
            "--target-dir",
            "target/fuzz/plain",
        ],
    )?;
    for target in TARGETS {
        let binary = root.join("target/fuzz/plain/release").join(target);
        let seeds = root.join("fuzz/corpus").join(target);
        eprintln!("\n==> {} {} -runs=0", binary.display(), seeds.display());
        let output = Command::new(&binary)
            .arg(&seeds)
            .arg("-runs=0")
            .current_dir(root)
            .output()
            .with_context(|| format!("cannot run {}", binary.display()))?;
        if !output.status.success() {
            bail!(
                "fuzz target `{target}` fails on its seed corpus:\n{}",
                String::from_utf8_lossy(&output.stderr)
            );
        }
    }
    Ok(())
}
