//! `cargo xtask bench train`: the median seconds of one training step (forward, objective,
//! backward, AdamW, EMA) for a batch of 32 windows of 60 frames with the `small` preset, (a)
//! with `L_diff` only and (b) with the full objective, on a procedural dataset built in the
//! run. Written to `target/bench/train.json` as
//! `{"small": {"mse_only_seconds": a, "full_seconds": b}}`.

use std::path::Path;
use std::time::Instant;

use dex2hoi_train::{TrainConfig, Trainer};

fn median_step(trainer: &mut Trainer, runs: usize) -> f64 {
    trainer.step(0).expect("a warm-up step");
    let mut times: Vec<f64> = (0..runs)
        .map(|_| {
            let start = Instant::now();
            trainer.step(0).expect("a training step");
            start.elapsed().as_secs_f64()
        })
        .collect();
    times.sort_by(f64::total_cmp);
    times[runs / 2]
}

fn main() {
    let runs: usize =
        std::env::var("DEX2HOI_BENCH_RUNS").ok().and_then(|v| v.parse().ok()).unwrap_or(7);
    println!(
        "dex2hoi training benchmark: small preset, batch 32 x 60 frames, median of {runs} steps\n"
    );
    let dataset =
        dex2hoi_data::synth::build_dataset(48, 3, 20.0, &|_| {}).expect("a procedural dataset");
    let mut config = TrainConfig::preset("small").expect("the small preset");
    config.training.batch_size = 32;
    let mut results = Vec::new();
    for (label, mse_only) in [("mse_only", true), ("full", false)] {
        config.loss.mse_only = mse_only;
        let mut trainer =
            Trainer::new(config.clone(), &dataset, Path::new("procedural")).expect("a trainer");
        let seconds = median_step(&mut trainer, runs);
        println!("  {label:<9} {seconds:>7.3} s per step");
        results.push(seconds);
    }
    println!("\n  full / mse_only = {:.2}x", results[1] / results[0]);
    let json = format!(
        "{{\"small\": {{\"mse_only_seconds\": {:.4}, \"full_seconds\": {:.4}}}}}\n",
        results[0], results[1]
    );
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../target/bench");
    std::fs::create_dir_all(&dir).expect("target/bench");
    let temporary = dir.join("train.json.tmp");
    std::fs::write(&temporary, &json).expect("writing train.json");
    std::fs::rename(&temporary, dir.join("train.json")).expect("renaming train.json");
}
