//! Autoregressive generation with a (tiny, random) model: window bookkeeping, the prompt
//! timeline, seeding and bad requests.

use candle_core::{DType, Device, Tensor};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use dex2hoi_diffusion::{CosineSchedule, SamplerConfig, SamplerKind};
use dex2hoi_model::{InferenceModel, Model, ModelConfig, SeededVarMap};
use dex2hoi_sample::{Generation, Normaliser, TimedText, generate};

fn random(shape: &[usize], rng: &mut ChaCha8Rng) -> Tensor {
    let n: usize = shape.iter().product();
    Tensor::from_vec(
        (0..n).map(|_| rng.random_range(-1.0f32..1.0)).collect::<Vec<_>>(),
        shape,
        &Device::Cpu,
    )
    .unwrap()
}

fn tiny_model() -> InferenceModel {
    let cfg = ModelConfig::tiny();
    let vars = SeededVarMap::new(0);
    let model = Model::new(&cfg, vars.builder(DType::F32, &Device::Cpu)).unwrap();
    // Untrained heads predict zeros; give every parameter a value so the output depends on all
    // inputs.
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    let data = vars.var_map().data().lock().unwrap();
    let mut names: Vec<&String> = data.keys().collect();
    names.sort();
    for name in names {
        let var = &data[name];
        var.set(&random(var.dims(), &mut rng).affine(0.3, 0.0).unwrap()).unwrap();
    }
    InferenceModel::new(&model).unwrap()
}

#[test]
fn generation_runs_window_by_window_with_a_timeline() {
    let model = tiny_model();
    let cfg = model.config().clone();
    let d = cfg.stream_features();
    let schedule = CosineSchedule::new(1000).unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(2);
    let normaliser = Normaliser {
        mean: random(&[d], &mut rng),
        std: random(&[d], &mut rng).abs().unwrap().affine(1.0, 0.5).unwrap(),
    };
    let first = random(&[1, cfg.text_embedding], &mut rng);
    let second = random(&[1, cfg.text_embedding], &mut rng);
    let base = Generation {
        model: &model,
        schedule: &schedule,
        normaliser: &normaliser,
        initial_prefix: random(&[1, 2, cfg.prefix_frames, d], &mut rng),
        timeline: vec![TimedText { start_frame: 0, embedding: first.clone() }],
        bps: random(&[1, 2, cfg.bps_points * 3], &mut rng),
        presence: Tensor::new(&[[1.0f32, 1.0]], &Device::Cpu).unwrap(),
        frames: 25,
        sampler: SamplerConfig {
            kind: SamplerKind::Ddim { eta: 0.0 },
            steps: 5,
            guidance: Some(2.0),
        },
    };
    let run = |request: &Generation<'_>, seed| {
        generate(request, &mut ChaCha8Rng::seed_from_u64(seed)).unwrap()
    };
    let one = run(&base, 3);
    // 25 frames: windows of 8 starting at 0, 8, 16, 24 (the last one cut to a frame).
    assert_eq!(one.dims(), &[1, 2, 25, d]);
    assert_eq!(
        one.flatten_all().unwrap().to_vec1::<f32>().unwrap(),
        run(&base, 3).flatten_all().unwrap().to_vec1::<f32>().unwrap()
    );
    // A second prompt from frame 16 on changes frames 16.. and nothing before.
    let switched = Generation {
        timeline: vec![
            TimedText { start_frame: 0, embedding: first },
            TimedText { start_frame: 16, embedding: second },
        ],
        ..base.clone()
    };
    let two = run(&switched, 3);
    let slice = |t: &Tensor, from: usize, len: usize| {
        t.narrow(2, from, len).unwrap().flatten_all().unwrap().to_vec1::<f32>().unwrap()
    };
    assert_eq!(slice(&one, 0, 16), slice(&two, 0, 16));
    assert_ne!(slice(&one, 16, 9), slice(&two, 16, 9));
    // Bad requests.
    let mut rng = ChaCha8Rng::seed_from_u64(4);
    assert!(generate(&Generation { frames: 0, ..base.clone() }, &mut rng).is_err());
    assert!(generate(&Generation { timeline: vec![], ..base.clone() }, &mut rng).is_err());
    let late = vec![TimedText { start_frame: 5, embedding: base.timeline[0].embedding.clone() }];
    assert!(generate(&Generation { timeline: late, ..base.clone() }, &mut rng).is_err());
    let short_prefix = base.initial_prefix.narrow(2, 0, 2).unwrap();
    assert!(generate(&Generation { initial_prefix: short_prefix, ..base }, &mut rng).is_err());
}
