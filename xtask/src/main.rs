//! Project automation, run as `cargo xtask <command>` (a cargo alias in `.cargo/config.toml`).
//!
//! - `ci`: the checks CI runs: `scripts/setup.sh` (what the tests need), then cheapest first:
//!   format, clippy (warnings denied), the web site (which the browser test drives), tests,
//!   fuzz check.
//! - `bench [repr|sample|train]`: the benchmarks, built in the release profile; they print
//!   medians. `bench compare`: dex2hoi against the PyTorch reference (see [`compare`]).
//! - `demo`: the main job: two prompts sampled with the shipped model, exported and rendered,
//!   then the procedural dataset, a short run of the `demo` preset, the same prompts sampled
//!   with it and a short evaluation; what is up to date is reused.
//! - `ablate [--preset NAME] [--steps N]`: the paper's Table 3 on the procedural dataset: the
//!   full model, its variants and the MDM-style baseline trained with equal budgets, evaluated
//!   with one evaluator, written to `docs/results/ablation.md`; resumable (see [`ablate`]).
//! - `build-cuda`: the `cuda` build of `dex2hoi` and its CUDA tests, packed for a GPU machine
//!   (see [`cuda`]).
//! - `fuzz NAME|all [SECONDS]`, `fuzz check`: the fuzz targets of the file readers (see [`fuzz`]).
//! - `web [--serve [PORT]]`: the static web page that runs the shipped model in the browser, in
//!   `target/web/` (see [`web`]).
//! - `train|sample|evaluate ARGS...`: the release `dex2hoi` binary's subcommands, passed
//!   through, so that a checkout drives everything through xtask.

mod ablate;
mod compare;
mod cuda;
mod fuzz;
mod web;

use std::path::{Path, PathBuf};
use std::process::Command;

use anyhow::{Context, Result, bail};

const USAGE: &str = "usage: cargo xtask <command>

commands:
  ci            scripts/setup.sh, format check, clippy with warnings denied, every test, fuzz check
  bench [NAME]  run the benchmarks (all, or one of: repr, sample, train) and print their medians
  bench compare sampling and training side by side with the PyTorch reference (bench/torch_reference.py)
  ablate [--preset NAME] [--steps N]
                train and evaluate the full model and the Table 3 variants, write docs/results/ablation.md
  demo          sample and render two prompts with the shipped model, then train and evaluate a short run
  build-cuda    build the GPU binary and CUDA tests (toolkit from PyPI) and pack them into target/cuda-pack
  fuzz NAME|all [SECONDS]
                fuzz a file reader (pickle, npy, glb, mesh) with libFuzzer for SECONDS (600) each
  fuzz check    build the fuzz targets without sanitizers and run each over its seed corpus
  web [--serve [PORT]]
                build the web page (the shipped model as WebAssembly) into target/web; --serve
                serves it on http://127.0.0.1:PORT/ (8000)
  train|sample|evaluate ARGS...
                run `dex2hoi <command> ARGS...` from a release build (see `dex2hoi --help`)";

/// The benchmarks `cargo xtask bench` knows: name, package, bench target.
const BENCHES: [(&str, &str, &str); 3] = [
    ("repr", "dex2hoi-repr", "repr"),
    ("sample", "dex2hoi-sample", "sample"),
    ("train", "dex2hoi-train", "train"),
];

fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let root = workspace_root();
    match args.first().map(String::as_str) {
        Some("ci") => ci(&root),
        Some("bench") => bench(&root, args.get(1).map(String::as_str)),
        Some("demo") => demo(&root),
        Some("build-cuda") => cuda::build_cuda(&root),
        Some("ablate") => ablate::ablate(&root, &args[1..]),
        Some("fuzz") => fuzz::fuzz(&root, &args[1..]),
        Some("web") => web::web(&root, &args[1..]),
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

/// The cargo that runs xtask (`CARGO`), else the one on the `PATH`.
fn cargo_program() -> String {
    std::env::var("CARGO").unwrap_or_else(|_| "cargo".into())
}

/// Runs a command and fails if it cannot start or fails.
fn run(command: &mut Command) -> Result<()> {
    let status = command.status().with_context(|| format!("cannot run {command:?}"))?;
    if !status.success() {
        bail!("{command:?} failed ({status})");
    }
    Ok(())
}

/// Runs `cargo` with arguments in the workspace root and fails if it fails.
fn cargo(root: &Path, args: &[&str]) -> Result<()> {
    let cargo = cargo_program();
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

/// Whether this runs under CI (`CI` set, and not to `0` or `false`), as `scripts/setup.sh`
/// decides it.
fn in_ci() -> bool {
    std::env::var("CI").is_ok_and(|v| !v.is_empty() && v != "0" && v != "false")
}

fn ci(root: &Path) -> Result<()> {
    setup(root)?;
    cargo(root, &["fmt", "--all", "--", "--check"])?;
    cargo(root, &["clippy", "--workspace", "--all-targets", "--locked", "--", "-D", "warnings"])?;
    // The site the browser test drives; outside CI a machine without the web toolchain skips
    // it (and the browser test says so).
    match web::build_site(root) {
        Ok(_) => {}
        Err(error) if !in_ci() => eprintln!("\nci: the web site is not built: {error:#}"),
        Err(error) => return Err(error),
    }
    cargo(root, &["test", "--workspace", "--locked"])?;
    fuzz::check(root)?;
    eprintln!("\nci: all checks passed");
    Ok(())
}

/// Runs `scripts/setup.sh`: installs what the tests need (quiet when all is there; outside CI
/// it skips what it cannot install and says which tests will be skipped).
fn setup(root: &Path) -> Result<()> {
    let status = Command::new("bash")
        .arg(root.join("scripts/setup.sh"))
        .current_dir(root)
        .status()
        .context("cannot run bash scripts/setup.sh")?;
    if !status.success() {
        bail!("scripts/setup.sh failed ({status})");
    }
    Ok(())
}

fn bench(root: &Path, name: Option<&str>) -> Result<()> {
    if name == Some("compare") {
        return compare::compare(root);
    }
    let selected: Vec<_> = match name {
        None | Some("all") => BENCHES.to_vec(),
        Some(name) => {
            let found: Vec<_> = BENCHES.iter().copied().filter(|(n, _, _)| *n == name).collect();
            if found.is_empty() {
                let known: Vec<_> = BENCHES.iter().map(|(n, _, _)| *n).collect();
                bail!("unknown benchmark `{name}`; known: {}, compare", known.join(", "));
            }
            found
        }
    };
    for (_, package, target) in selected {
        cargo(root, &["bench", "--locked", "-p", package, "--bench", target])?;
    }
    Ok(())
}

/// Runs the release `dex2hoi` binary and fails if it fails. `DEX2HOI_MODEL` is unset: every
/// call names its run, except the demo's samples with the shipped model, which must not be
/// replaced by whatever the caller's environment names.
fn dex2hoi(root: &Path, args: &[&str]) -> Result<()> {
    let binary = root.join("target/release/dex2hoi");
    eprintln!("\n==> dex2hoi {}", args.join(" "));
    let status = Command::new(&binary)
        .env_remove("DEX2HOI_MODEL")
        .args(args)
        .current_dir(root)
        .status()
        .with_context(|| format!("cannot run {}", binary.display()))?;
    if !status.success() {
        bail!("`dex2hoi {}` failed ({status})", args.join(" "));
    }
    Ok(())
}

/// How the demo names the model shipped with dex2hoi in its messages.
const SHIPPED_MODEL: &str = "the shipped model";

/// The demo's procedural dataset: sequences and seed.
const DEMO_SEQUENCES: &str = "400";
const DEMO_SEED: &str = "0";
/// Steps of the demo's evaluator.
const DEMO_EVALUATOR_STEPS: &str = "100";

/// The two demo prompts: a name, the text and the objects.
const DEMO_PROMPTS: [(&str, &str, &[&str]); 2] = [
    (
        "one-object",
        "The person picks up the mug with the right hand and puts it down to the left.",
        &["mug"],
    ),
    (
        "two-objects",
        "The person picks up the bottle with the left hand and the can with the right hand, holds both and puts them back.",
        &["bottle", "can"],
    ),
];

/// `cargo xtask demo`: first the shipped model's motions for the two prompts (exports and
/// previews, right after the build), then the procedural dataset, a short training run, the
/// same prompts sampled with it, a small evaluator and a short evaluation of the run. A stamp
/// file beside each stage records what made it; a stage whose stamp matches is reused, and an
/// interrupted training run is resumed.
fn demo(root: &Path) -> Result<()> {
    let started = std::time::Instant::now();
    let dir = root.join("target/demo");
    std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
    cargo(root, &["build", "--release", "--locked", "-p", "dex2hoi-cli"])?;

    // The shipped model needs no training (no `--run`; README.md, "The shipped model").
    let shipped = sample_demo_prompts(root, None, &dir)?;
    println!(
        "\n==> the shipped model's motions, {:.0} s after the start: {}/preview.png",
        started.elapsed().as_secs_f64(),
        shipped[0].1
    );

    let data = dir.join("data");
    let data_stamp = format!("synth sequences={DEMO_SEQUENCES} seed={DEMO_SEED} fps=20\n");
    let data_stamp_file = dir.join("data.stamp");
    // A dataset written by an older dex2hoi (another format version) no longer loads: it is made
    // again, and so is everything trained on it.
    let loads = || {
        Command::new(root.join("target/release/dex2hoi"))
            .args(["data", "info"])
            .arg(&data)
            .output()
            .is_ok_and(|output| output.status.success())
    };
    if read(&data_stamp_file) == data_stamp && data.join("manifest.json").is_file() && loads() {
        eprintln!("\n==> reusing the dataset in {}", data.display());
    } else {
        for stale in ["data.stamp", "run.stamp", "run.pending", "evaluator.stamp"] {
            let _ = std::fs::remove_file(dir.join(stale));
        }
        dex2hoi(
            root,
            &[
                "data",
                "synth",
                "--out",
                &path(&data)?,
                "--sequences",
                DEMO_SEQUENCES,
                "--seed",
                DEMO_SEED,
            ],
        )?;
        write(&data_stamp_file, &data_stamp)?;
    }

    let config = root.join("configs/demo.toml");
    let run = dir.join("run");
    let run_stamp = format!("{data_stamp}{}", read(&config));
    let (done_file, pending_file) = (dir.join("run.stamp"), dir.join("run.pending"));
    let checkpoint = run.join("checkpoint.safetensors");
    if read(&done_file) == run_stamp && checkpoint.is_file() {
        eprintln!("\n==> reusing the trained run in {}", run.display());
    } else {
        let _ = std::fs::remove_file(&done_file);
        let resume = read(&pending_file) == run_stamp && checkpoint.is_file();
        if !resume && run.exists() {
            std::fs::remove_dir_all(&run).with_context(|| format!("removing {}", run.display()))?;
        }
        write(&pending_file, &run_stamp)?;
        let (config, run_path, data) = (path(&config)?, path(&run)?, path(&data)?);
        let mut args = vec!["train", "--config", &config, "--data", &data, "--out", &run_path];
        if resume {
            args.push("--resume");
        }
        dex2hoi(root, &args)?;
        write(&done_file, &run_stamp)?;
        let _ = std::fs::remove_file(&pending_file);
    }

    // The short run shows that training works; it has not learned much yet.
    let run_path = path(&run)?;
    let short = sample_demo_prompts(root, Some(&run_path), &dir.join("short-run"))?;
    // A small evaluator and a short metrics table, so that the demo stays short.
    let evaluator = dir.join("evaluator");
    let evaluator_stamp = format!("{data_stamp}evaluator steps={DEMO_EVALUATOR_STEPS}\n");
    let evaluator_stamp_file = dir.join("evaluator.stamp");
    if read(&evaluator_stamp_file) == evaluator_stamp
        && evaluator.join("evaluator.safetensors").is_file()
    {
        eprintln!("\n==> reusing the evaluator in {}", evaluator.display());
    } else {
        let _ = std::fs::remove_file(&evaluator_stamp_file);
        train_evaluator(root, &data, &evaluator, DEMO_EVALUATOR_STEPS)?;
        write(&evaluator_stamp_file, &evaluator_stamp)?;
    }
    let report = dir.join("evaluation");
    dex2hoi(
        root,
        &[
            "evaluate",
            "--run",
            &run_path,
            "--data",
            &path(&data)?,
            "--evaluator",
            &path(&evaluator)?,
            "--out",
            &path(&report)?,
            "--replications",
            "1",
            "--sequences",
            "12",
            "--multimodality",
            "3,3,2",
            "--ddim-steps",
            "20",
        ],
    )?;
    println!("\ndemo done in {:.0} s", started.elapsed().as_secs_f64());
    println!(
        "  metrics: {}/report.md (a short evaluation: 12 test sequences, 20 DDIM steps)",
        report.display()
    );
    println!("  training run: {}  (loss curve: {}/loss.png)", run.display(), run.display());
    for (model, outputs) in [(SHIPPED_MODEL, shipped), ("the short run", short)] {
        for (text, out) in outputs {
            println!(
                "  {model}: \"{text}\"\n    {out}/preview.gif, preview.png, motion.glb, \
                 motion.bvh, motion.npz"
            );
        }
    }
    Ok(())
}

/// Samples the demo prompts (200 frames: ten seconds; seed 1) with a run, or the shipped model
/// without one, each into its folder under `folder`; returns each prompt with its folder.
fn sample_demo_prompts(
    root: &Path,
    run: Option<&str>,
    folder: &Path,
) -> Result<Vec<(&'static str, String)>> {
    let mut outputs = Vec::new();
    for (name, text, objects) in DEMO_PROMPTS {
        let out = path(&folder.join(name))?;
        if Path::new(&out).exists() {
            std::fs::remove_dir_all(&out).with_context(|| format!("removing {out}"))?;
        }
        let mut args = vec!["sample"];
        if let Some(run) = run {
            args.extend(["--run", run]);
        }
        args.extend(["--text", text, "--frames", "200", "--seed", "1", "--out", &out]);
        for object in objects {
            args.extend(["--object", object]);
        }
        dex2hoi(root, &args)?;
        outputs.push((text, out));
    }
    Ok(outputs)
}

/// A path as a command-line argument.
fn path(p: &Path) -> Result<String> {
    p.to_str().map(str::to_owned).with_context(|| format!("{} is not a UTF-8 path", p.display()))
}

/// `dex2hoi evaluator train` on a dataset for `steps` steps into `out`.
fn train_evaluator(root: &Path, data: &Path, out: &Path, steps: &str) -> Result<()> {
    dex2hoi(
        root,
        &["evaluator", "train", "--data", &path(data)?, "--out", &path(out)?, "--steps", steps],
    )
}

/// A file's text, or nothing when it cannot be read.
fn read(path: &Path) -> String {
    std::fs::read_to_string(path).unwrap_or_default()
}

fn write(path: &Path, text: &str) -> Result<()> {
    std::fs::write(path, text).with_context(|| format!("writing {}", path.display()))
}
