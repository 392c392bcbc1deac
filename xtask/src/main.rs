//! Project automation, run as `cargo xtask <command>` (a cargo alias in `.cargo/config.toml`).
//!
//! - `ci`: the checks CI runs, cheapest first: format, clippy (warnings denied), tests.
//! - `bench [repr|sample|train]`: the benchmarks, built in the release profile; they print
//!   medians.
//! - `train|sample|evaluate ARGS...`: the release `dex2hoi` binary's subcommands, passed
//!   through, so that a checkout drives everything through xtask.

use std::path::{Path, PathBuf};
use std::process::Command;

use anyhow::{Context, Result, bail};

const USAGE: &str = "usage: cargo xtask <command>

commands:
  ci            format check, clippy with warnings denied, then every test (optimised profile)
  bench [NAME]  run the benchmarks (all, or one of: repr, sample, train) and print their medians
  train|sample|evaluate ARGS...
                run `dex2hoi <command> ARGS...` from a release build (see `dex2hoi --help`)";

/// The benchmarks `cargo xtask bench` knows: name, package, bench target.
const BENCHES: [(&str, &str, &str); 3] = [
    ("repr", "dex2hoi-repr", "repr"),
    ("sample", "dex2hoi-diffusion", "sample"),
    ("train", "dex2hoi-train", "train"),
];

fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let root = workspace_root();
    match args.first().map(String::as_str) {
        Some("ci") => ci(&root),
        Some("bench") => bench(&root, args.get(1).map(String::as_str)),
        Some(command @ ("train" | "sample" | "evaluate")) => {
            let mut forwarded =
                vec!["run", "--release", "--quiet", "--locked", "-p", "dex2hoi-cli", "--"];
            forwarded.push(command);
            forwarded.extend(args[1..].iter().map(String::as_str));
            cargo(&root, &forwarded)
        }
        Some("help" | "--help" | "-h") | None => {
            println!("{USAGE}");
            Ok(())
        }
        Some(other) => bail!("unknown command `{other}`\n\n{USAGE}"),
    }
}

fn workspace_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).parent().expect("xtask lives in the workspace").into()
}

/// Runs `cargo` with arguments in the workspace root and fails if it fails.
fn cargo(root: &Path, args: &[&str]) -> Result<()> {
    let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
    eprintln!("\n==> cargo {}", args.join(" "));
    let status = Command::new(&cargo)
        .args(args)
        .current_dir(root)
        .status()
        .with_context(|| format!("cannot run {cargo}"))?;
    if !status.success() {
        bail!("`cargo {}` failed ({status})", args.join(" "));
    }
    Ok(())
}

fn ci(root: &Path) -> Result<()> {
    cargo(root, &["fmt", "--all", "--", "--check"])?;
    cargo(root, &["clippy", "--workspace", "--all-targets", "--locked", "--", "-D", "warnings"])?;
    cargo(root, &["test", "--workspace", "--locked"])?;
    eprintln!("\nci: all checks passed");
    Ok(())
}

fn bench(root: &Path, name: Option<&str>) -> Result<()> {
    let selected: Vec<_> = match name {
        None | Some("all") => BENCHES.to_vec(),
        Some(name) => {
            let found: Vec<_> = BENCHES.iter().copied().filter(|(n, _, _)| *n == name).collect();
            if found.is_empty() {
                let known: Vec<_> = BENCHES.iter().map(|(n, _, _)| *n).collect();
                bail!("unknown benchmark `{name}`; known: {}", known.join(", "));
            }
            found
        }
    };
    for (_, package, target) in selected {
        cargo(root, &["bench", "--locked", "-p", package, "--bench", target])?;
    }
    Ok(())
}
