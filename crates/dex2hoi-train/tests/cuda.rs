//! The CUDA device against the CPU (built with `--features cuda`, run on a machine with an
//! NVIDIA GPU: `cargo xtask build-cuda` packs these tests): every model variant's forward, one
//! training step's loss and gradients, the GPU's own noise and batches drawn ahead, forward
//! kinematics and its gradients, layer norm, AdaLN's modulation and the masked softmax with
//! their gradients, dropout, the surface search, the fused optimiser update, and a checkpoint
//! written on the GPU sampled on both.
//! Weights are randomised or trained first: a fresh model's zero-initialised heads output
//! exact zeros, which would compare equal on any device.
#![cfg(feature = "cuda")]

use std::path::Path;
use std::sync::atomic::AtomicBool;

use candle_core::{DType, Device, Tensor, Var};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use dex2hoi_data::dataset::Dataset;
use dex2hoi_diffusion::SamplerConfig;
use dex2hoi_model::{
    BodyFusion, InferenceModel, Model, ModelConfig, ModelInput, ObjectRepresentation, Prediction,
    SeededVarMap, StreamLayout,
};
use dex2hoi_optim::{AdamW, Ema, OptimizerConfig, Parameter};
use dex2hoi_repr::fk::{tensor_forward_kinematics, tensor_forward_kinematics_per_sample};
use dex2hoi_repr::skeleton::Skeleton;
use dex2hoi_sample::{Prompt, SampleRequest, SceneObject, TrainedRun, Weights, sample};
use dex2hoi_train::batch::SurfaceCloud;
use dex2hoi_train::surface::{DeviceClouds, nearest_on_host};
use dex2hoi_train::{RunStart, TrainConfig, TrainOptions, Trainer, train};

const TOLERANCE: f32 = 1e-4;

fn gpu() -> Device {
    dex2hoi_model::cuda_device::open_cuda(0)
        .expect("a CUDA device (these tests run on a GPU machine)")
}

fn dataset() -> Dataset {
    dex2hoi_synth::build_dataset(16, 5, 20.0, &|_| {}).expect("a procedural dataset")
}

fn random(shape: &[usize], rng: &mut ChaCha8Rng) -> Tensor {
    let n: usize = shape.iter().product();
    let v: Vec<f32> = (0..n).map(|_| rng.random_range(-1.0..1.0)).collect();
    Tensor::from_vec(v, shape, &Device::Cpu).unwrap()
}

/// The largest absolute difference, relative to the larger of 1 and the reference's largest
/// magnitude.
fn relative_difference(gpu: &Tensor, cpu: &Tensor) -> f32 {
    assert_eq!(gpu.dims(), cpu.dims());
    let a: Vec<f32> =
        gpu.to_device(&Device::Cpu).unwrap().flatten_all().unwrap().to_vec1().unwrap();
    let b: Vec<f32> = cpu.flatten_all().unwrap().to_vec1().unwrap();
    let scale = b.iter().fold(1f32, |m, v| m.max(v.abs()));
    a.iter().zip(&b).fold(0f32, |m, (x, y)| m.max((x - y).abs())) / scale
}

/// Noisy window, prefix, timesteps, text, BPS and presence as a model input.
fn input<'a>(t: &[&'a Tensor]) -> ModelInput<'a> {
    ModelInput {
        noisy: t[0],
        prefix: t[1],
        timesteps: t[2],
        text: t[3],
        bps: t[4],
        presence: t[5],
        frame_mask: None,
        elapsed: None,
        object_start: None,
        settled: None,
        reach: None,
    }
}

fn variants() -> Vec<ModelConfig> {
    let tiny = ModelConfig::tiny();
    vec![
        tiny.clone(),
        ModelConfig { prediction: Prediction::Absolute, ..tiny.clone() },
        ModelConfig { prediction: Prediction::PrefixResidual, ..tiny.clone() },
        ModelConfig { prediction: Prediction::PrefixResidualWorld, ..tiny.clone() },
        ModelConfig { prediction: Prediction::PrefixResidualPlacement, ..tiny.clone() },
        ModelConfig { prediction: Prediction::PrefixResidualCleanFingers, ..tiny.clone() },
        ModelConfig { body_fusion: BodyFusion::Average, ..tiny.clone() },
        ModelConfig { stream_layout: StreamLayout::Single, ..tiny.clone() },
        ModelConfig { object_representation: ObjectRepresentation::GlobalOnly, ..tiny.clone() },
        ModelConfig {
            latent: 24,
            heads: 3,
            feed_forward: 40,
            prefix_frames: 3,
            predicted_frames: 7,
            ..tiny
        },
    ]
}

#[test]
fn every_model_variant_computes_on_the_gpu_what_it_computes_on_the_cpu() {
    let gpu = gpu();
    for cfg in variants() {
        let build = |device: &Device| {
            let vars = SeededVarMap::new(0);
            let model = Model::new(&cfg, vars.builder(DType::F32, device)).unwrap();
            vars.randomise_zero_parameters(9).unwrap();
            model
        };
        let (on_cpu, on_gpu) = (build(&Device::Cpu), build(&gpu));
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let d = cfg.stream_features();
        let noisy = random(&[3, 2, cfg.predicted_frames, d], &mut rng);
        let prefix = random(&[3, 2, cfg.prefix_frames, d], &mut rng);
        let text = random(&[3, cfg.text_embedding], &mut rng);
        let bps = random(&[3, 2, cfg.bps_points * 3], &mut rng);
        let presence = Tensor::new(&[[1f32, 1.0], [1.0, 0.0], [1.0, 1.0]], &Device::Cpu).unwrap();
        let timesteps = Tensor::new(&[0u32, 411, 999], &Device::Cpu).unwrap();
        let inputs = [&noisy, &prefix, &timesteps, &text, &bps, &presence];
        let moved: Vec<Tensor> = inputs.iter().map(|t| t.to_device(&gpu).unwrap()).collect();

        let moved_refs: Vec<&Tensor> = moved.iter().collect();
        let expected = on_cpu.forward(&input(&inputs), None).unwrap();
        let got = on_gpu.forward(&input(&moved_refs), None).unwrap();
        let difference = relative_difference(&got, &expected);
        assert!(difference < TOLERANCE, "{cfg:?}: forward differs by {difference}");
        // The sampler's no-grad model: fused on the CPU, the composite on the GPU.
        let fused = InferenceModel::new(&on_cpu).unwrap();
        let composite = InferenceModel::new(&on_gpu).unwrap();
        assert!(fused.is_fused() && !composite.is_fused());
    }
}

#[test]
fn a_training_step_on_the_gpu_gives_the_loss_and_gradients_of_the_cpu() {
    let data = dataset();
    let config = TrainConfig::preset("tiny").unwrap();
    let gpu = gpu();
    let mut trainers: Vec<Trainer> = [Device::Cpu, gpu.clone()]
        .iter()
        .map(|device| Trainer::new(config.clone(), &data, Path::new("procedural"), device).unwrap())
        .collect();
    // The same noise on both devices: drawn on the host.
    trainers[1].noise_on_host(true);
    // Three updates first, so that no layer is still at its zero initialisation; each step's
    // loss must agree on the way.
    for _ in 0..3 {
        let cpu = trainers[0].step(0).unwrap();
        let on_gpu = trainers[1].step(0).unwrap();
        let difference = (cpu.loss - on_gpu.loss).abs() / cpu.loss.abs().max(1.0);
        assert!(
            difference < f64::from(TOLERANCE),
            "step {}: {} vs {}",
            cpu.step,
            cpu.loss,
            on_gpu.loss
        );
        assert!((cpu.gradient_norm - on_gpu.gradient_norm).abs() / cpu.gradient_norm < 1e-3);
    }
    let objectives: Vec<_> = trainers.iter().map(|t| t.objective_at(3).unwrap()).collect();
    let losses: Vec<f32> = objectives
        .iter()
        .map(|o| o.total.to_device(&Device::Cpu).unwrap().to_scalar().unwrap())
        .collect();
    assert!((losses[0] - losses[1]).abs() / losses[0].abs().max(1.0) < TOLERANCE, "{losses:?}");
    let gradients: Vec<_> = objectives.iter().map(|o| o.total.backward().unwrap()).collect();
    for (p_cpu, p_gpu) in trainers[0].parameters().iter().zip(trainers[1].parameters()) {
        assert_eq!(p_cpu.name, p_gpu.name);
        assert!(p_gpu.var.device().is_cuda());
        match (gradients[0].get(p_cpu.var.as_tensor()), gradients[1].get(p_gpu.var.as_tensor())) {
            (Some(cpu), Some(on_gpu)) => {
                let difference = relative_difference(on_gpu, cpu);
                assert!(difference < TOLERANCE, "{}: gradient differs by {difference}", p_cpu.name);
            }
            (None, None) => {}
            _ => panic!("{}: a gradient on one device only", p_cpu.name),
        }
    }
}

#[test]
fn a_gpu_run_draws_its_noise_there_and_its_batches_ahead_as_its_steps_would() {
    // The GPU's defaults, noise from the device's generator and batches drawn ahead on another
    // thread, against the same run drawing each batch in its step: the same weights after
    // three steps; and a different noise from the host's.
    let data = dataset();
    let config = TrainConfig::preset("tiny").unwrap();
    let gpu = gpu();
    let run = |prefetch: bool, host_noise: bool| -> (f64, Vec<Tensor>) {
        let mut trainer =
            Trainer::new(config.clone(), &data, Path::new("procedural"), &gpu).unwrap();
        trainer.prefetch_batches(prefetch);
        trainer.noise_on_host(host_noise);
        let loss = (0..3).map(|_| trainer.step(0).unwrap().loss).last().unwrap();
        (loss, trainer.parameters().iter().map(|p| p.var.as_tensor().clone()).collect())
    };
    let (ahead, in_step, host) = (run(true, false), run(false, false), run(true, true));
    for (a, b) in ahead.1.iter().zip(&in_step.1) {
        let difference = relative_difference(a, &b.to_device(&Device::Cpu).unwrap());
        assert!(difference < 1e-6, "weights differ by {difference}");
    }
    eprintln!("losses after three steps: {} (device noise), {} (host noise)", ahead.0, host.0);
    assert!((ahead.0 - in_step.0).abs() < 1e-6 * ahead.0.abs().max(1.0));
    assert_ne!(ahead.0, host.0);
}

#[test]
fn the_surface_search_on_the_gpu_picks_the_samples_of_the_host_search() {
    // The dataset's own clouds (512 samples each) and joints around them, at odd sizes: every
    // query's sample on the GPU as near as the host's within f32 rounding, the same one almost
    // always.
    let data = dataset();
    let clouds: Vec<SurfaceCloud> = data.objects.iter().map(SurfaceCloud::of).collect();
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    let count = clouds.len();
    let slots: Vec<[Option<usize>; 2]> =
        (0..7).map(|i| [Some(i % count), (i % 3 != 0).then_some((i + 1) % count)]).collect();
    let queries = 2 * 52 + 3;
    let local = random(&[slots.len(), 2, queries, 3], &mut rng).affine(0.3, 0.0).unwrap();
    let values: Vec<f32> = local.flatten_all().unwrap().to_vec1().unwrap();
    let (host, _) = nearest_on_host(&values, &slots, &clouds, queries);
    let gpu = gpu();
    let on_gpu = DeviceClouds::new(&clouds, &gpu)
        .unwrap()
        .nearest(&local.to_device(&gpu).unwrap(), &slots)
        .unwrap()
        .0;
    let on_gpu: Vec<f32> =
        on_gpu.to_device(&Device::Cpu).unwrap().flatten_all().unwrap().to_vec1().unwrap();
    let mut same = 0;
    for (q, x) in values.chunks(3).enumerate() {
        let at = q * 3..q * 3 + 3;
        let squared = |s: &[f32]| x.iter().zip(s).map(|(a, b)| (a - b) * (a - b)).sum::<f32>();
        let (gpu_distance, host_distance) =
            (squared(&on_gpu[at.clone()]), squared(&host[at.clone()]));
        assert!((gpu_distance - host_distance).abs() <= 1e-6, "query {q}");
        same += usize::from(on_gpu[at.clone()] == host[at]);
    }
    assert!(same * 100 >= values.len() / 3 * 99, "the same sample for {same} queries");
}

#[test]
fn forward_kinematics_on_the_gpu_computes_and_differentiates_as_on_the_cpu() {
    // Both skeletons, one set of offsets and one per sample (3 samples of 7 frames), arbitrary
    // matrices: positions, rotations and the gradients of a weighted sum of both, against the
    // CPU's operation (itself checked against finite differences).
    let gpu = gpu();
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    for skeleton in [Skeleton::smplx(), Skeleton::mixamo()] {
        let joints = skeleton.joint_count();
        let local = random(&[3, 7, joints, 3, 3], &mut rng);
        let root = random(&[3, 7, 3], &mut rng);
        let rest = random(&[3, joints, 3], &mut rng).affine(0.2, 0.0).unwrap();
        let position_weights = random(&[3, 7, joints, 3], &mut rng);
        let rotation_weights = random(&[3, 7, joints, 3, 3], &mut rng);
        for per_sample in [false, true] {
            let run = |device: &Device| -> [Tensor; 4] {
                let on = |t: &Tensor| t.to_device(device).unwrap();
                let local = Var::from_tensor(&on(&local)).unwrap();
                let root = Var::from_tensor(&on(&root)).unwrap();
                let (positions, rotations) = if per_sample {
                    tensor_forward_kinematics_per_sample(&skeleton, &on(&rest), &local, &root)
                } else {
                    tensor_forward_kinematics(&skeleton, &local, &root)
                }
                .unwrap();
                let weighted = |t: &Tensor, w: &Tensor| (t * on(w)).unwrap().sum_all().unwrap();
                let loss = (weighted(&positions, &position_weights)
                    + weighted(&rotations, &rotation_weights))
                .unwrap();
                let grads = loss.backward().unwrap();
                let (of_local, of_root) = (grads.get(&local).unwrap(), grads.get(&root).unwrap());
                [positions, rotations, of_local.clone(), of_root.clone()]
            };
            let (cpu, on_gpu) = (run(&Device::Cpu), run(&gpu));
            for (name, (g, c)) in ["positions", "rotations", "local gradient", "root gradient"]
                .iter()
                .zip(on_gpu.iter().zip(&cpu))
            {
                assert!(g.device().is_cuda());
                let difference = relative_difference(g, c);
                eprintln!("FK {joints} joints, per sample {per_sample}: {name} {difference:.1e}");
                assert!(difference < TOLERANCE, "{name}: {difference}");
            }
        }
    }
}

#[test]
fn row_operations_on_the_gpu_compute_and_differentiate_as_on_the_cpu() {
    // The fused row operations (`rows.cu`: layer norm, the modulation, the masked softmax) at
    // odd sizes: rows narrower than a warp, a width between warps, one wider than a block of
    // threads; inputs offset from zero as the tokens are; a masked key per sequence. Outputs and
    // the gradients of a weighted sum against the CPU's operations (themselves checked against
    // finite differences).
    let gpu = gpu();
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    for (sequences, frames, latent) in [(3, 7, 5), (2, 9, 37), (5, 3, 301)] {
        let x = random(&[sequences, frames, latent], &mut rng).affine(3.0, 0.5).unwrap();
        let modulation = random(&[sequences, 2 * latent], &mut rng);
        let weights = random(&[sequences, frames, latent], &mut rng);
        let scores = random(&[sequences, 2, frames, latent], &mut rng).affine(4.0, 0.0).unwrap();
        let mask: Vec<f32> =
            (0..sequences * latent).map(|i| (i % latent != 1) as u8 as f32).collect();
        let mask = Tensor::from_vec(mask, (sequences, latent), &Device::Cpu).unwrap();
        let score_weights = random(&[sequences, 2, frames, latent], &mut rng);
        let run = |device: &Device| -> [Tensor; 7] {
            let x = Var::from_tensor(&x.to_device(device).unwrap()).unwrap();
            let modulation = Var::from_tensor(&modulation.to_device(device).unwrap()).unwrap();
            let weights = weights.to_device(device).unwrap();
            let normalised = dex2hoi_model::differentiable::layer_norm(&x).unwrap();
            let modulated = dex2hoi_model::differentiable::modulate(&x, &modulation).unwrap();
            let weighted = |t: &Tensor| (t * &weights).unwrap().sum_all().unwrap();
            let of_norm = weighted(&normalised).backward().unwrap();
            let of_modulation = weighted(&modulated).backward().unwrap();
            let scores = Var::from_tensor(&scores.to_device(device).unwrap()).unwrap();
            let mask = mask.to_device(device).unwrap();
            let softmax = dex2hoi_model::differentiable::masked_softmax(&scores, &mask).unwrap();
            let score_weights = score_weights.to_device(device).unwrap();
            let of_softmax = (&softmax * score_weights).unwrap().sum_all().unwrap().backward();
            let of_scores = of_softmax.unwrap().get(&scores).unwrap().clone();
            [
                normalised,
                modulated,
                of_norm.get(&x).unwrap().clone(),
                of_modulation.get(&x).unwrap().clone(),
                of_modulation.get(&modulation).unwrap().clone(),
                softmax,
                of_scores,
            ]
        };
        let (cpu, on_gpu) = (run(&Device::Cpu), run(&gpu));
        let names = [
            "layer norm",
            "modulation",
            "layer norm's input gradient",
            "modulation's token gradient",
            "modulation's gradient",
            "masked softmax",
            "masked softmax's score gradient",
        ];
        for (name, (g, c)) in names.iter().zip(on_gpu.iter().zip(&cpu)) {
            assert!(g.device().is_cuda());
            let difference = relative_difference(g, c);
            eprintln!("{sequences} x {frames} x {latent}: {name} {difference:.1e}");
            assert!(difference < TOLERANCE, "{name}: {difference}");
        }
    }
}

#[test]
fn dropout_on_the_gpu_draws_its_masks_there_from_the_step_stream() {
    // The same stream gives the same mask; another gives another; about `1 - p` of the values
    // are kept, each scaled by `1 / (1 - p)`.
    let gpu = gpu();
    let ones = Tensor::ones((64, 37, 11), DType::F32, &gpu).unwrap();
    let draw = |seed: u64| -> Vec<f32> {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let dropped = dex2hoi_model::layers::dropout(&ones, 0.25, Some(&mut rng)).unwrap();
        assert!(dropped.device().is_cuda());
        dropped.flatten_all().unwrap().to_vec1().unwrap()
    };
    let (first, again, other) = (draw(7), draw(7), draw(8));
    assert_eq!(first, again);
    assert_ne!(first, other);
    let kept = first.iter().filter(|&&v| v != 0.0).count() as f64 / first.len() as f64;
    assert!((kept - 0.75).abs() < 0.01, "kept {kept}");
    assert!(first.iter().all(|&v| v == 0.0 || (v - 1.0 / 0.75).abs() < 1e-6));
}

/// Parameters of odd sizes on `device` (one more than a block of threads, a prime, a matrix, a
/// rank-3 tensor), the same values for every call.
fn optimised_parameters(device: &Device) -> Vec<Parameter> {
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    [&[7, 13][..], &[257], &[1031], &[3, 5, 17], &[64, 96]]
        .iter()
        .enumerate()
        .map(|(k, shape)| Parameter {
            name: format!("p{k}"),
            var: Var::from_tensor(&random(shape, &mut rng).to_device(device).unwrap()).unwrap(),
        })
        .collect()
}

/// A loss of every parameter but the last (which gets no gradient), different at each step,
/// with a gradient norm well above the clip.
fn optimised_loss(parameters: &[Parameter], step: usize) -> Tensor {
    let mut total = Tensor::new(0f32, parameters[0].var.device()).unwrap();
    for (k, p) in parameters[..parameters.len() - 1].iter().enumerate() {
        let shifted = p.var.as_tensor().affine(1.0, 0.1 * (k + step) as f64).unwrap();
        let term = (shifted.sqr().unwrap().sum_all().unwrap() * (3.0 + step as f64)).unwrap();
        total = (total + term).unwrap();
    }
    total
}

#[test]
fn the_fused_optimiser_kernel_updates_as_the_tensor_operations_do() {
    let gpu = gpu();
    let config = OptimizerConfig { gradient_clip: Some(1.0), ..OptimizerConfig::default() };
    assert!(config.fused);
    let fused = optimised_parameters(&gpu);
    let composite = optimised_parameters(&gpu);
    let mut adams = [
        AdamW::new(config.clone(), &fused).unwrap(),
        AdamW::new(OptimizerConfig { fused: false, ..config }, &composite).unwrap(),
    ];
    let mut averages = [Ema::new(&fused).unwrap(), Ema::new(&composite).unwrap()];
    // A learning rate that changes between updates: the kernel reads it at every launch.
    for (step, rate) in [1e-2, 3e-3, 5e-2].into_iter().enumerate() {
        let [a, b] = &mut adams;
        let [ea, eb] = &mut averages;
        let grads = optimised_loss(&fused, step).backward().unwrap();
        let ours = a.update_with_average(ea, &fused, &grads, rate, (0.9, step)).unwrap();
        let grads = optimised_loss(&composite, step).backward().unwrap();
        let theirs = b.update_with_average(eb, &composite, &grads, rate, (0.9, step)).unwrap();
        assert!(theirs.gradient_norm > 1.0, "clipping is active: {}", theirs.gradient_norm);
        assert!((ours.gradient_norm - theirs.gradient_norm).abs() / theirs.gradient_norm < 1e-6);
    }
    for (k, (f, c)) in fused.iter().zip(&composite).enumerate() {
        let value = relative_difference(f.var.as_tensor(), c.var.as_tensor());
        let (f1, f2) = adams[0].moments(k);
        let (c1, c2) = adams[1].moments(k);
        let moments = relative_difference(f1, c1).max(relative_difference(f2, c2));
        let average = relative_difference(averages[0].value(k), averages[1].value(k));
        eprintln!("{}: value {value:.1e}, moments {moments:.1e}, average {average:.1e}", f.name);
        assert!(value < 1e-5 && moments < 1e-5 && average < 1e-5, "{}", f.name);
    }
    // The parameter without a gradient decayed like the others.
    let untouched = optimised_parameters(&Device::Cpu);
    let last = fused.len() - 1;
    assert!(
        relative_difference(fused[last].var.as_tensor(), untouched[last].var.as_tensor()) > 0.0
    );
    // A non-finite gradient norm leaves every array as it was, and is reported.
    let before: Vec<Tensor> = fused.iter().map(|p| p.var.as_tensor().copy().unwrap()).collect();
    let average_before = averages[0].value(0).copy().unwrap();
    let grads = (optimised_loss(&fused, 3) * f64::NAN).unwrap().backward().unwrap();
    let [a, _] = &mut adams;
    let [ea, _] = &mut averages;
    let report = a.update_with_average(ea, &fused, &grads, 1e-2, (0.9, 3)).unwrap();
    assert!(!report.gradient_norm.is_finite());
    for (p, b) in fused.iter().zip(&before) {
        assert_eq!(
            relative_difference(p.var.as_tensor(), &b.to_device(&Device::Cpu).unwrap()),
            0.0
        );
    }
    assert_eq!(
        relative_difference(averages[0].value(0), &average_before.to_device(&Device::Cpu).unwrap()),
        0.0
    );
}

#[test]
fn a_checkpoint_written_on_the_gpu_samples_the_same_motion_on_the_cpu() {
    let data = dataset();
    let mut config = TrainConfig::preset("tiny").unwrap();
    config.training.steps = 20;
    let dir = std::env::temp_dir().join(format!("dex2hoi-cuda-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let gpu = gpu();
    let never = AtomicBool::new(false);
    let options =
        TrainOptions { start: RunStart::Fresh, stop: &never, snapshot_every: None, device: &gpu };
    train(&dir, config, &data, Path::new("procedural"), options, &mut |_, _| {}).unwrap();
    let request = SampleRequest {
        prompts: vec![Prompt {
            start_frame: 0,
            text: data.splits.values().flatten().next().unwrap().texts[0].clone(),
        }],
        objects: vec![SceneObject::parse("mug", None).unwrap()],
        frames: std::num::NonZeroUsize::new(30).unwrap(),
        seed: 7,
        sampler: SamplerConfig { steps: 10, ..SamplerConfig::default() },
        table_height: dex2hoi_sample::DEFAULT_TABLE_HEIGHT,
        free_objects: Default::default(),
        seams: Default::default(),
        progress: None,
    };
    let motions: Vec<_> = [Device::Cpu, gpu]
        .iter()
        .map(|device| {
            let run = TrainedRun::load(&dir, Weights::Ema, device).unwrap();
            sample(&run, &request).unwrap().motion
        })
        .collect();
    let roots = |i: usize| -> Vec<f32> {
        motions[i].root_positions.iter().flat_map(|p| p.to_array()).collect()
    };
    let (cpu, on_gpu) = (roots(0), roots(1));
    assert_eq!(cpu.len(), on_gpu.len());
    let difference = cpu.iter().zip(&on_gpu).fold(0f32, |m, (a, b)| m.max((a - b).abs()));
    assert!(difference < TOLERANCE, "root positions differ by {difference} m");
    let rotations = |i: usize| -> Vec<f32> {
        motions[i].local_rotations.iter().flat_map(|m| m.to_cols_array()).collect()
    };
    let (cpu, on_gpu) = (rotations(0), rotations(1));
    let difference = cpu.iter().zip(&on_gpu).fold(0f32, |m, (a, b)| m.max((a - b).abs()));
    assert!(difference < TOLERANCE, "joint rotations differ by {difference}");
    let _ = std::fs::remove_dir_all(&dir);
}
