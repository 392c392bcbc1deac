//! `cargo xtask bench sample`: seconds per 60-frame two-object sample (20 prefix + 40 predicted
//! frames, 50 DDIM steps, guidance on, batch 1) and the real-time factor of a 300-frame
//! autoregressive generation at 20 fps, for the `small` and `paper` presets with untrained
//! weights, next to a large matmul measured in the same run. Medians; also written to
//! `target/bench/sample.json`.

use std::time::{Duration, Instant};

use candle_core::{DType, Device, Tensor};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

use dex2hoi_data::start::StartPose;
use dex2hoi_diffusion::{CosineSchedule, SamplerConfig};
use dex2hoi_model::{BodyFusion, InferenceModel, Model, ModelConfig, SeededVarMap, StreamLayout};
use dex2hoi_repr::{Skeleton, SkeletonKind};
use dex2hoi_sample::{
    Generation, Normaliser, PrefixEncoding, TimedText, WindowCondition, generate, sample_window,
};
use dex2hoi_testkit::memory::{peak_memory_mib, reset_peak_memory};

fn median(runs: usize, mut f: impl FnMut()) -> Duration {
    f();
    let mut times: Vec<Duration> = (0..runs)
        .map(|_| {
            let start = Instant::now();
            f();
            start.elapsed()
        })
        .collect();
    times.sort();
    times[runs / 2]
}

/// Multiply-adds x 2 of one forward pass on `batch` samples (linear layers and attention).
fn flops_per_forward(c: &ModelConfig, batch: usize) -> f64 {
    let (t, tf, l, ff) = (
        c.window_frames() as f64,
        c.predicted_frames as f64,
        c.latent as f64,
        c.feed_forward as f64,
    );
    let streams = if c.stream_layout == StreamLayout::Dual { 2.0 } else { 1.0 };
    let attention = |tokens: f64| 4.0 * tokens * l * l * 2.0 + 2.0 * tokens * tokens * l * 2.0;
    let feed_forward = |tokens: f64| 2.0 * tokens * l * ff * 2.0;
    let cross = if c.stream_layout == StreamLayout::Dual { attention(t) } else { 0.0 };
    let block = attention(t) + cross + feed_forward(t);
    let io = 2.0 * t * l * c.stream_features() as f64 * 2.0;
    let denoiser = streams * (c.layers as f64 * block + io);
    let fusion = if c.stream_layout == StreamLayout::Dual && c.body_fusion == BodyFusion::Network {
        c.fusion_layers as f64 * (attention(tf) + feed_forward(tf))
    } else {
        0.0
    };
    batch as f64 * (denoiser + fusion)
}

fn main() {
    // As `dex2hoi` does, before anything starts a thread.
    dex2hoi_model::candle_threads::run_inline();
    let device = Device::Cpu;
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    println!("dex2hoi sampling benchmark ({} rayon threads; medians)\n", rayon_threads());
    let a = dex2hoi_diffusion::gaussian(&[1024, 1024], &mut rng, DType::F32, &device).unwrap();
    let b = dex2hoi_diffusion::gaussian(&[1024, 1024], &mut rng, DType::F32, &device).unwrap();
    let matmul = median(9, || {
        a.matmul(&b).unwrap();
    });
    let matmul_gflops = 2.0 * 1024f64.powi(3) / matmul.as_secs_f64() / 1e9;
    println!("{:<44} {matmul_gflops:>8.1} GFLOP/s", "matmul 1024 x 1024 x 1024 (f32)");
    let schedule = CosineSchedule::new(1000).unwrap();
    let sampler = SamplerConfig::default();
    let skeleton = Skeleton::builtin(SkeletonKind::Smplx52);
    let mut json = format!("{{\"matmul_gflops\": {matmul_gflops:.3}");
    // `DEX2HOI_BENCH_PRESETS=small` (comma-separated) measures a subset, e.g. for profiling.
    let only = std::env::var("DEX2HOI_BENCH_PRESETS").ok();
    let wanted = |name: &str| only.as_deref().is_none_or(|list| list.split(',').any(|p| p == name));
    for (name, runs) in [("small", 5), ("paper", 3)].into_iter().filter(|(name, _)| wanted(name)) {
        let cfg = ModelConfig::preset(name).unwrap();
        let vars = SeededVarMap::new(0);
        let model = Model::new(&cfg, vars.builder(DType::F32, &device)).unwrap();
        // Randomised like the PyTorch reference's weights (the zero-initialised layers too).
        vars.randomise_zero_parameters(1).unwrap();
        let model = InferenceModel::new(&model).unwrap();
        let d = cfg.stream_features();
        let condition = WindowCondition {
            prefix: dex2hoi_diffusion::gaussian(
                &[1, 2, cfg.prefix_frames, d],
                &mut rng,
                DType::F32,
                &device,
            )
            .unwrap(),
            text: dex2hoi_diffusion::gaussian(
                &[1, cfg.text_embedding],
                &mut rng,
                DType::F32,
                &device,
            )
            .unwrap(),
            bps: dex2hoi_diffusion::gaussian(
                &[1, 2, cfg.bps_points * 3],
                &mut rng,
                DType::F32,
                &device,
            )
            .unwrap(),
            presence: Tensor::ones((1, 2), DType::F32, &device).unwrap(),
            elapsed: None,
            object_start: None,
            settled: None,
            reach: None,
        };
        reset_peak_memory();
        let window = median(runs, || {
            sample_window(&model, &schedule, &condition, &sampler, &mut rng).unwrap();
        });
        let seconds = window.as_secs_f64();
        let peak = peak_memory_mib();
        let gflops = flops_per_forward(&cfg, 2) * sampler.steps as f64 / seconds / 1e9;
        let normaliser = Normaliser {
            mean: Tensor::zeros(d, DType::F32, &device).unwrap(),
            std: Tensor::ones(d, DType::F32, &device).unwrap(),
        };
        let request = Generation {
            model: &model,
            schedule: &schedule,
            normaliser: &normaliser,
            initial_prefix: condition.prefix.clone(),
            timeline: vec![TimedText { start_frame: 0, embedding: condition.text.clone() }],
            bps: condition.bps.clone(),
            presence: condition.presence.clone(),
            frames: std::num::NonZeroUsize::new(300).expect("positive"),
            sampler,
            // As `dex2hoi sample` does with the hand-relative objects of these presets.
            prefix_encoding: Some(PrefixEncoding {
                skeleton: &skeleton,
                root_start: StartPose::smplx_standing().root(),
                present: [true, true],
            }),
            free_objects: None,
            seams: Default::default(),
            progress: None,
        };
        let realtime_at = |steps: usize, rng: &mut ChaCha8Rng| {
            let request =
                Generation { sampler: SamplerConfig { steps, ..sampler }, ..request.clone() };
            let start = Instant::now();
            generate(&request, rng).unwrap();
            (300.0 / 20.0) / start.elapsed().as_secs_f64()
        };
        let realtime = realtime_at(sampler.steps, &mut rng);
        let realtime_10 = realtime_at(10, &mut rng);
        println!(
            "{:<44} {seconds:>8.3} s per 60-frame sample, {gflops:.1} GFLOP/s ({:.0}% of matmul), peak {peak:.0} MiB; 300 frames at {realtime:.2}x real time ({realtime_10:.2}x with 10 steps)",
            format!("{name} (latent {}, {} layers)", cfg.latent, cfg.layers),
            100.0 * gflops / matmul_gflops
        );
        json.push_str(&format!(
            ", \"{name}\": {{\"seconds_per_sample\": {seconds:.4}, \"realtime_factor_300\": {realtime:.4}, \"realtime_factor_300_10_steps\": {realtime_10:.4}, \"gflops\": {gflops:.3}, \"peak_memory_mib\": {peak:.1}}}"
        ));
    }
    json.push('}');
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../target/bench");
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("sample.json");
    let temporary = dir.join("sample.json.tmp");
    std::fs::write(&temporary, &json).unwrap();
    std::fs::rename(&temporary, &path).unwrap();
    println!("\nwrote {}", path.display());
}

fn rayon_threads() -> usize {
    std::thread::available_parallelism().map_or(1, |n| n.get())
}
