//! `cargo xtask bench compare`: dex2hoi against the PyTorch reference of the same architecture
//! (`bench/torch_reference.py`) on this machine, one after the other in one invocation.
//!
//! 1. A virtual environment with torch and numpy under `target/bench/venv` (made once; it sees
//!    the system's packages, so an installed torch is reused, else pip fetches it from PyPI).
//! 2. dex2hoi's reference dump (`target/bench/reference/*.safetensors`: randomised weights,
//!    inputs, output), its sampling and training benchmarks (`target/bench/{sample,train}.json`).
//! 3. The reference: it checks its forward against dex2hoi's output (1e-4), then measures the
//!    same figures with the same thread count (`target/bench/torch.json`).
//! 4. A table of both, with ratios and each side's share of its own large-matmul rate, printed
//!    and written to `target/bench/compare.md`.

use std::path::{Path, PathBuf};
use std::process::Command;

use anyhow::{Context, Result, bail};
use serde_json::Value;

use crate::{cargo, run};

/// Runs the whole comparison.
pub fn compare(root: &Path) -> Result<()> {
    let python = virtual_environment(root)?;
    cargo(root, &["bench", "--locked", "-p", "dex2hoi-sample", "--bench", "reference"])?;
    cargo(root, &["bench", "--locked", "-p", "dex2hoi-sample", "--bench", "sample"])?;
    cargo(root, &["bench", "--locked", "-p", "dex2hoi-train", "--bench", "train"])?;
    let threads = std::env::var("RAYON_NUM_THREADS")
        .ok()
        .and_then(|v| v.parse::<usize>().ok())
        .unwrap_or_else(|| std::thread::available_parallelism().map_or(1, |n| n.get()));
    let bench = root.join("target/bench");
    let torch_json = bench.join("torch.json");
    eprintln!("\n==> bench/torch_reference.py --threads {threads}");
    let status = Command::new(&python)
        .arg(root.join("bench/torch_reference.py"))
        .args(["--threads", &threads.to_string(), "--out"])
        .arg(&torch_json)
        .current_dir(root)
        .status()
        .with_context(|| format!("cannot run {}", python.display()))?;
    if !status.success() {
        bail!("the PyTorch reference failed ({status}); its output above says why");
    }
    let ours = (read_json(&bench.join("sample.json"))?, read_json(&bench.join("train.json"))?);
    let table = table(&ours.0, &ours.1, &read_json(&torch_json)?, threads);
    println!("\n{table}");
    let path = bench.join("compare.md");
    let temporary = bench.join("compare.md.tmp");
    std::fs::write(&temporary, &table).with_context(|| format!("writing {}", path.display()))?;
    std::fs::rename(&temporary, &path).with_context(|| format!("writing {}", path.display()))?;
    eprintln!("wrote {}", path.display());
    Ok(())
}

/// The environment's Python, made on first use.
fn virtual_environment(root: &Path) -> Result<PathBuf> {
    let venv = root.join("target/bench/venv");
    let python = venv.join("bin/python");
    if !python.exists() {
        eprintln!("\n==> python3 -m venv --system-site-packages {}", venv.display());
        run(Command::new("python3").args(["-m", "venv", "--system-site-packages"]).arg(&venv))?;
    }
    let has_torch = Command::new(&python)
        .args(["-c", "import torch, numpy"])
        .status()
        .is_ok_and(|s| s.success());
    if !has_torch {
        eprintln!(
            "\n==> pip install torch numpy (PyPI's torch also fetches its CUDA libraries: several GB, once)"
        );
        run(Command::new(&python).args(["-m", "pip", "install", "--quiet", "torch", "numpy"]))?;
    }
    Ok(python)
}

fn read_json(path: &Path) -> Result<Value> {
    let text = std::fs::read_to_string(path)
        .with_context(|| format!("reading {} (written by the benchmark before)", path.display()))?;
    serde_json::from_str(&text).with_context(|| format!("{} is not JSON", path.display()))
}

/// A number at `path` in `value`, if present.
fn number(value: &Value, path: &[&str]) -> Option<f64> {
    path.iter().try_fold(value, |v, key| v.get(key))?.as_f64()
}

fn seconds(value: Option<f64>) -> String {
    value.map_or("-".into(), |s| format!("{s:.3} s"))
}

fn share(gflops: Option<f64>, matmul: Option<f64>) -> String {
    match (gflops, matmul) {
        (Some(g), Some(m)) if m > 0.0 => format!("{:.0}%", 100.0 * g / m),
        _ => "-".into(),
    }
}

/// `baseline / ours` as a speed-up, `1.45x` (more than 1: dex2hoi is faster).
fn speedup(ours: Option<f64>, baseline: Option<f64>) -> String {
    match (ours, baseline) {
        (Some(o), Some(b)) if o > 0.0 => format!("{:.2}x", b / o),
        _ => "-".into(),
    }
}

fn mib(value: Option<f64>) -> String {
    value.map_or("-".into(), |m| format!("{m:.0} MiB"))
}

/// The comparison table (Markdown).
fn table(sample: &Value, train: &Value, torch: &Value, threads: usize) -> String {
    let (our_matmul, torch_matmul) =
        (number(sample, &["matmul_gflops"]), number(torch, &["matmul_gflops"]));
    let version = torch.get("torch").and_then(Value::as_str).unwrap_or("?");
    let mut out = format!(
        "dex2hoi vs PyTorch {version} (CPU, {threads} threads, one invocation; medians)\n\n\
         large matmul (1024^3 f32): dex2hoi {:.1} GFLOP/s, PyTorch {:.1} GFLOP/s\n\n\
         | figure | dex2hoi | PyTorch eager | PyTorch inference_mode | PyTorch compile | speed-up vs best PyTorch |\n\
         |---|---|---|---|---|---|\n",
        our_matmul.unwrap_or(0.0),
        torch_matmul.unwrap_or(0.0),
    );
    for preset in ["small", "paper"] {
        let ours = number(sample, &[preset, "seconds_per_sample"]);
        let our_share = share(number(sample, &[preset, "gflops"]), our_matmul);
        let mode = |m: &str| number(torch, &[preset, "sample", m, "seconds"]);
        let mode_share =
            |m: &str| share(number(torch, &[preset, "sample", m, "gflops"]), torch_matmul);
        let best = ["eager", "inference_mode", "compile"]
            .iter()
            .filter_map(|m| mode(m))
            .min_by(f64::total_cmp);
        let diff = number(torch, &[preset, "max_abs_diff"]);
        out.push_str(&format!(
            "| 60-frame sample, `{preset}` (forward max diff {}) | {} ({our_share}) | {} ({}) | {} ({}) | {} ({}) | {} |\n",
            diff.map_or("-".into(), |d| format!("{d:.1e}")),
            seconds(ours),
            seconds(mode("eager")),
            mode_share("eager"),
            seconds(mode("inference_mode")),
            mode_share("inference_mode"),
            seconds(mode("compile")),
            mode_share("compile"),
            speedup(ours, best),
        ));
    }
    let ours = number(train, &["small", "mse_only_seconds"]);
    let theirs = number(torch, &["train_small", "seconds"]);
    out.push_str(&format!(
        "| training step, `small`, 32 x 60 frames, L_diff only | {} (forward {}, backward {}) | {} (forward {}, backward {}) | | | {} |\n",
        seconds(ours),
        seconds(number(train, &["small", "mse_only_forward_seconds"])),
        seconds(number(train, &["small", "mse_only_backward_seconds"])),
        seconds(theirs),
        seconds(number(torch, &["train_small", "forward"])),
        seconds(number(torch, &["train_small", "backward"])),
        speedup(ours, theirs),
    ));
    let full = number(train, &["small", "full_seconds"]);
    out.push_str(&format!(
        "\n- dex2hoi, full objective: {} per step ({} of L_diff only)\n",
        seconds(full),
        match (full, ours) {
            (Some(f), Some(o)) if o > 0.0 => format!("{:.2}x", f / o),
            _ => "-".into(),
        }
    ));
    out.push_str(&format!(
        "- dex2hoi, 300-frame autoregressive generation, `small`: {:.2}x real time with 50 DDIM steps, {:.2}x with 10\n",
        number(sample, &["small", "realtime_factor_300"]).unwrap_or(0.0),
        number(sample, &["small", "realtime_factor_300_10_steps"]).unwrap_or(0.0),
    ));
    out.push_str(&format!(
        "- peak resident memory, sampling `small` / `paper`: dex2hoi {} / {}, PyTorch {} / {}; training step `small`: dex2hoi {}, PyTorch {}\n",
        mib(number(sample, &["small", "peak_memory_mib"])),
        mib(number(sample, &["paper", "peak_memory_mib"])),
        mib(number(torch, &["small", "peak_rss_mb"])),
        mib(number(torch, &["paper", "peak_rss_mb"])),
        mib(number(train, &["small", "peak_memory_mib"])),
        mib(number(torch, &["train_small", "peak_rss_mb"])),
    ));
    out
}
