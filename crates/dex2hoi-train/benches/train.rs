//! `cargo xtask bench train`: the median seconds of one training step (forward, objective,
//! backward, AdamW, EMA) for a batch of 32 windows of 60 frames with the `small` preset, (a)
//! with `L_diff` only and (b) with the full objective, on a procedural dataset built in the
//! run, with the peak resident memory of each. Written to `target/bench/train.json` as
//! `{"small": {"mse_only_seconds": a, "full_seconds": b, ...}}` (also the parts of (a) and
//! the peaks).

use std::path::Path;
use std::time::Instant;

use dex2hoi_testkit::memory::{peak_memory_mib, reset_peak_memory};
use dex2hoi_train::{TrainConfig, Trainer};

fn median(mut values: Vec<f64>) -> f64 {
    values.sort_by(f64::total_cmp);
    values[values.len() / 2]
}

/// The median step time and the median of each part.
fn median_step(trainer: &mut Trainer, runs: usize) -> (f64, [f64; 5]) {
    trainer.step(0).expect("a warm-up step");
    let mut times = Vec::new();
    let mut parts = Vec::new();
    for _ in 0..runs {
        let start = Instant::now();
        let report = trainer.step(0).expect("a training step");
        times.push(start.elapsed().as_secs_f64());
        let t = report.timing;
        parts.push([t.batch, t.forward, t.objective, t.backward, t.update]);
    }
    let part = |k: usize| median(parts.iter().map(|p| p[k]).collect());
    (median(times), [part(0), part(1), part(2), part(3), part(4)])
}

fn main() {
    // As `dex2hoi` does, before anything starts a thread.
    dex2hoi_model::candle_threads::run_inline();
    let runs: usize =
        std::env::var("DEX2HOI_BENCH_RUNS").ok().and_then(|v| v.parse().ok()).unwrap_or(7);
    println!(
        "dex2hoi training benchmark: small preset, batch 32 x 60 frames, median of {runs} steps\n"
    );
    let dataset = dex2hoi_synth::build_dataset(48, 3, 20.0, &|_| {}).expect("a procedural dataset");
    let mut config = TrainConfig::preset("small").expect("the small preset");
    config.training.batch_size = 32;
    let mut results = Vec::new();
    for (label, mse_only) in [("mse_only", true), ("full", false)] {
        config.loss.mse_only = mse_only;
        let mut trainer = Trainer::new(
            config.clone(),
            &dataset,
            Path::new("procedural"),
            &candle_core::Device::Cpu,
        )
        .expect("a trainer");
        reset_peak_memory();
        let (seconds, parts) = median_step(&mut trainer, runs);
        let peak = peak_memory_mib();
        println!(
            "  {label:<9} {seconds:>7.3} s per step (batch {:.3}, forward {:.3}, objective {:.3}, \
             backward {:.3}, update {:.3}), peak {peak:.0} MiB",
            parts[0], parts[1], parts[2], parts[3], parts[4]
        );
        results.push((seconds, parts, peak));
    }
    println!("\n  full / mse_only = {:.2}x", results[1].0 / results[0].0);
    let (mse, full) = (&results[0], &results[1]);
    let json = format!(
        "{{\"small\": {{\"mse_only_seconds\": {:.4}, \"full_seconds\": {:.4}, \
         \"mse_only_forward_seconds\": {:.4}, \"mse_only_backward_seconds\": {:.4}, \
         \"mse_only_update_seconds\": {:.4}, \"peak_memory_mib\": {:.1}, \
         \"full_peak_memory_mib\": {:.1}}}}}\n",
        mse.0, full.0, mse.1[1], mse.1[3], mse.1[4], mse.2, full.2
    );
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../target/bench");
    std::fs::create_dir_all(&dir).expect("target/bench");
    let temporary = dir.join("train.json.tmp");
    std::fs::write(&temporary, &json).expect("writing train.json");
    std::fs::rename(&temporary, dir.join("train.json")).expect("renaming train.json");
}
