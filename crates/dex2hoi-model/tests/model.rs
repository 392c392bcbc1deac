//! The networks: shapes of every variant, the zero start, information flow between the
//! streams, seeding, bad inputs, and a finite-difference check of the gradient of every
//! parameter of the full model.

use candle_core::{DType, Device, Tensor};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use dex2hoi_data::FeatureLayout;
use dex2hoi_model::{
    BodyFusion, Model, ModelConfig, ModelInput, ObjectRepresentation, ObjectStart, Prediction,
    SeededVarMap, StreamLayout,
};
use dex2hoi_repr::object_repr::{
    GLOBAL_POSITION_RANGE, LEFT_OFFSET_RANGE, MIXTURE_RANGE, RIGHT_OFFSET_RANGE, ROTATION_RANGE,
};

struct Inputs {
    noisy: Tensor,
    prefix: Tensor,
    timesteps: Tensor,
    text: Tensor,
    bps: Tensor,
    presence: Tensor,
    mask: Tensor,
    elapsed: Tensor,
    start: Tensor,
    settled: Tensor,
}

impl Inputs {
    fn random(cfg: &ModelConfig, batch: usize, dtype: DType, seed: u64) -> Self {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut t = |shape: &[usize]| {
            let n: usize = shape.iter().product();
            let v: Vec<f64> = (0..n).map(|_| rng.random_range(-1.0..1.0)).collect();
            Tensor::from_vec(v, shape, &Device::Cpu).unwrap().to_dtype(dtype).unwrap()
        };
        let d = cfg.stream_features();
        let noisy = t(&[batch, 2, cfg.predicted_frames, d]);
        let prefix = t(&[batch, 2, cfg.prefix_frames, d]);
        let text = t(&[batch, cfg.text_embedding]);
        let bps = t(&[batch, 2, cfg.bps_points * 3]);
        let start = t(&[batch, 2, d]);
        let presence: Vec<f64> =
            (0..batch).flat_map(|b| [1.0, if b % 2 == 0 { 1.0 } else { 0.0 }]).collect();
        let mut mask = vec![1.0f64; batch * cfg.window_frames()];
        mask[cfg.window_frames() - 1] = 0.0; // the last frame of the first sample is padding
        Self {
            noisy,
            prefix,
            timesteps: Tensor::from_vec(
                (0..batch as u32).map(|b| 100 + 300 * b).collect::<Vec<_>>(),
                batch,
                &Device::Cpu,
            )
            .unwrap(),
            text,
            bps,
            presence: Tensor::from_vec(presence, (batch, 2), &Device::Cpu)
                .unwrap()
                .to_dtype(dtype)
                .unwrap(),
            mask: Tensor::from_vec(mask, (batch, cfg.window_frames()), &Device::Cpu)
                .unwrap()
                .to_dtype(dtype)
                .unwrap(),
            elapsed: Tensor::from_vec(
                (0..batch).map(|b| 30.0 * b as f64 + 5.0).collect::<Vec<_>>(),
                batch,
                &Device::Cpu,
            )
            .unwrap()
            .to_dtype(dtype)
            .unwrap(),
            start,
            // Sample 0's object A set down again, nothing else.
            settled: Tensor::from_vec(
                (0..batch * 2).map(|k| f32::from(u8::from(k == 0))).collect::<Vec<_>>(),
                (batch, 2),
                &Device::Cpu,
            )
            .unwrap()
            .to_dtype(dtype)
            .unwrap(),
        }
    }

    fn view(&self) -> ModelInput<'_> {
        ModelInput {
            noisy: &self.noisy,
            prefix: &self.prefix,
            timesteps: &self.timesteps,
            text: &self.text,
            bps: &self.bps,
            presence: &self.presence,
            frame_mask: Some(&self.mask),
            // Read by the variants with the prompt clock, the object start and the memory of
            // set-down objects, ignored by the others.
            elapsed: Some(&self.elapsed),
            object_start: Some(&self.start),
            settled: Some(&self.settled),
            reach: None,
        }
    }
}

fn build(cfg: &ModelConfig, seed: u64, dtype: DType) -> (Model, SeededVarMap) {
    let vars = SeededVarMap::new(seed);
    let model = Model::new(cfg, vars.builder(dtype, &Device::Cpu)).unwrap();
    (model, vars)
}

/// Replaces every parameter (the zero-initialised ones too) by random values, so that every
/// gradient is non-trivial.
fn randomise(vars: &SeededVarMap, seed: u64) {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let data = vars.var_map().data().lock().unwrap();
    let mut names: Vec<&String> = data.keys().collect();
    names.sort();
    for name in names {
        let var = &data[name];
        let v: Vec<f64> = (0..var.elem_count()).map(|_| rng.random_range(-0.3..0.3)).collect();
        let t =
            Tensor::from_vec(v, var.shape(), &Device::Cpu).unwrap().to_dtype(var.dtype()).unwrap();
        var.set(&t).unwrap();
    }
}

fn variants() -> Vec<ModelConfig> {
    let tiny = ModelConfig::tiny();
    vec![
        tiny.clone(),
        ModelConfig { body_fusion: BodyFusion::Average, ..tiny.clone() },
        ModelConfig { stream_layout: StreamLayout::Single, ..tiny.clone() },
        ModelConfig { object_representation: ObjectRepresentation::GlobalOnly, ..tiny },
    ]
}

/// The last prefix frame under every predicted frame, the body from stream A in both streams.
fn last_prefix_frame(cfg: &ModelConfig, prefix: &Tensor) -> Tensor {
    let last = prefix.narrow(2, cfg.prefix_frames - 1, 1).unwrap();
    let body = last.narrow(1, 0, 1).unwrap().narrow(3, 0, cfg.body_features()).unwrap();
    let body = Tensor::cat(&[&body, &body], 1).unwrap();
    let objects =
        last.narrow(3, cfg.body_features(), cfg.stream_features() - cfg.body_features()).unwrap();
    let last = Tensor::cat(&[&body, &objects], 3).unwrap();
    let (b, s, _, d) = last.dims4().unwrap();
    last.broadcast_as((b, s, cfg.predicted_frames, d)).unwrap().contiguous().unwrap()
}

/// What the residual head adds: the last prefix frame, on every channel or (world variant) with
/// the hand-relative channels of the object zeroed.
fn prefix_part(cfg: &ModelConfig, prefix: &Tensor) -> Tensor {
    let mut last = last_prefix_frame(cfg, prefix);
    if cfg.prediction == Prediction::PrefixResidualPlacement {
        // Written out channel by channel: root joint 0..6, root displacement 6J..6J + 3, the
        // object's rotation (its first six numbers) and world position (numbers 12..15).
        let joints = cfg.joints;
        let body = 6 * joints + 3;
        let keep = |c: usize| {
            c < 6
                || (6 * joints..body).contains(&c)
                || (body..body + 6).contains(&c)
                || (body + 12..body + 15).contains(&c)
        };
        let mut values =
            last.to_dtype(DType::F64).unwrap().flatten_all().unwrap().to_vec1::<f64>().unwrap();
        let width = cfg.stream_features();
        for row in values.chunks_mut(width) {
            for (c, v) in row.iter_mut().enumerate() {
                if !keep(c) {
                    *v = 0.0;
                }
            }
        }
        last = Tensor::from_vec(values, last.dims(), last.device())
            .unwrap()
            .to_dtype(last.dtype())
            .unwrap();
    }
    if cfg.prediction == Prediction::PrefixResidualCleanFingers {
        // The world head's channels without SMPL-X's finger joints 22..52 (`cfg.joints` is 52).
        assert_eq!(cfg.joints, 52);
        let world = ModelConfig { prediction: Prediction::PrefixResidualWorld, ..cfg.clone() };
        let world = prefix_part(&world, prefix);
        let mut values =
            world.to_dtype(DType::F64).unwrap().flatten_all().unwrap().to_vec1::<f64>().unwrap();
        for row in values.chunks_mut(cfg.stream_features()) {
            row[6 * 22..6 * 52].fill(0.0);
        }
        return Tensor::from_vec(values, world.dims(), world.device())
            .unwrap()
            .to_dtype(world.dtype())
            .unwrap();
    }
    if cfg.prediction == Prediction::PrefixResidualWorld {
        let layout = cfg.layout();
        let mut values =
            last.to_dtype(DType::F64).unwrap().flatten_all().unwrap().to_vec1::<f64>().unwrap();
        let width = layout.stream_width();
        for row in values.chunks_mut(width) {
            for part in [LEFT_OFFSET_RANGE, RIGHT_OFFSET_RANGE, MIXTURE_RANGE] {
                row[layout.object_part_range(part)].fill(0.0);
            }
        }
        last = Tensor::from_vec(values, last.dims(), last.device())
            .unwrap()
            .to_dtype(last.dtype())
            .unwrap();
    }
    last
}

const PREDICTIONS: [Prediction; 5] = [
    Prediction::Absolute,
    Prediction::PrefixResidual,
    Prediction::PrefixResidualWorld,
    Prediction::PrefixResidualPlacement,
    Prediction::PrefixResidualCleanFingers,
];
/// The heads that add (part of) the last prefix frame.
const RESIDUALS: [Prediction; 4] = [
    Prediction::PrefixResidual,
    Prediction::PrefixResidualWorld,
    Prediction::PrefixResidualPlacement,
    Prediction::PrefixResidualCleanFingers,
];

#[test]
fn every_variant_runs_and_starts_at_zero_or_at_the_prefix() {
    for base in variants() {
        for prediction in PREDICTIONS {
            let cfg = ModelConfig { prediction, ..base.clone() };
            let (model, _) = build(&cfg, 0, DType::F32);
            let inputs = Inputs::random(&cfg, 3, DType::F32, 1);
            let out = model.forward(&inputs.view(), None).unwrap();
            assert_eq!(out.dims(), &[3, 2, cfg.predicted_frames, cfg.stream_features()]);
            // Zero-initialised heads: the untrained model predicts zeros, or with a residual
            // head the last prefix frame (stream A's body in both streams) where it adds it.
            let start = match prediction {
                Prediction::Absolute => out.zeros_like().unwrap(),
                _ => prefix_part(&cfg, &inputs.prefix),
            };
            if prediction == Prediction::PrefixResidualPlacement {
                // A finger joint's rotation (the last joint) starts at zero, the root's at the
                // prefix.
                let channel = |c: usize| start.narrow(3, c, 1).unwrap().abs().unwrap();
                let max = |t: Tensor| t.max_all().unwrap().to_scalar::<f32>().unwrap();
                assert_eq!(max(channel(6 * cfg.joints - 1)), 0.0);
                assert!(max(channel(0)) > 0.0);
            }
            if prediction == Prediction::PrefixResidualCleanFingers {
                // The first finger joint's rotation starts at zero, the right wrist's at the
                // prefix.
                let channel = |c: usize| start.narrow(3, c, 1).unwrap().abs().unwrap();
                let max = |t: Tensor| t.max_all().unwrap().to_scalar::<f32>().unwrap();
                assert_eq!(max(channel(6 * 22)), 0.0);
                assert!(max(channel(6 * 21)) > 0.0);
            }
            if prediction == Prediction::PrefixResidualWorld {
                // The test would pass vacuously if the hand-relative channels were not zero here.
                let offsets = start
                    .narrow(3, cfg.layout().object_part_range(LEFT_OFFSET_RANGE).start, 6)
                    .unwrap();
                let last = last_prefix_frame(&cfg, &inputs.prefix)
                    .narrow(3, cfg.layout().object_part_range(LEFT_OFFSET_RANGE).start, 6)
                    .unwrap();
                assert_eq!(
                    offsets.abs().unwrap().max_all().unwrap().to_scalar::<f32>().unwrap(),
                    0.0
                );
                assert!(last.abs().unwrap().max_all().unwrap().to_scalar::<f32>().unwrap() > 0.0);
            }
            let max = (out - start).unwrap().abs().unwrap().max_all().unwrap();
            assert_eq!(max.to_scalar::<f32>().unwrap(), 0.0, "{cfg:?}");
        }
    }
}

#[test]
fn the_residual_head_adds_the_last_prefix_frame_to_the_same_network() {
    for base in variants() {
        for prediction in RESIDUALS {
            let absolute = ModelConfig { prediction: Prediction::Absolute, ..base.clone() };
            let residual = ModelConfig { prediction, ..base.clone() };
            let (a, vars_a) = build(&absolute, 0, DType::F64);
            let (r, vars_r) = build(&residual, 0, DType::F64);
            randomise(&vars_a, 9);
            randomise(&vars_r, 9);
            let inputs = Inputs::random(&residual, 2, DType::F64, 4);
            let out_a = a.forward(&inputs.view(), None).unwrap();
            let out_r = r.forward(&inputs.view(), None).unwrap();
            let expected = (out_a + prefix_part(&residual, &inputs.prefix)).unwrap();
            let diff = (out_r - expected).unwrap().abs().unwrap().max_all().unwrap();
            assert!(diff.to_scalar::<f64>().unwrap() < 1e-12, "{residual:?}");
        }
    }
    for prediction in RESIDUALS {
        let no_prefix = ModelConfig { prediction, prefix_frames: 0, ..ModelConfig::tiny() };
        let error = no_prefix.validate().unwrap_err().to_string();
        assert!(error.contains("prefix_frames"), "{error}");
    }
    // Which joints are fingers comes from the skeleton of `joints` joints.
    let unknown = ModelConfig {
        prediction: Prediction::PrefixResidualCleanFingers,
        joints: 40,
        ..ModelConfig::tiny()
    };
    let error = unknown.validate().unwrap_err().to_string();
    assert!(error.contains("joints") && error.contains("65"), "{error}");
}

#[test]
fn the_body_is_shared_and_streams_talk_to_each_other() {
    for cfg in variants() {
        let (model, vars) = build(&cfg, 0, DType::F64);
        randomise(&vars, 5);
        let inputs = Inputs::random(&cfg, 2, DType::F64, 2);
        let out = model.forward(&inputs.view(), None).unwrap();
        let body = cfg.body_features();
        let a = out.narrow(1, 0, 1).unwrap().narrow(3, 0, body).unwrap();
        let b = out.narrow(1, 1, 1).unwrap().narrow(3, 0, body).unwrap();
        let diff = (a - b).unwrap().abs().unwrap().max_all().unwrap().to_scalar::<f64>().unwrap();
        assert_eq!(diff, 0.0, "one body for both streams");
        // Changing stream B's frames changes stream A's object prediction (cross-attention, or
        // the shared single stream); sample 0 has both objects.
        let mut changed = Inputs::random(&cfg, 2, DType::F64, 2);
        let b_frames = changed.noisy.narrow(1, 1, 1).unwrap();
        changed.noisy =
            Tensor::cat(&[&changed.noisy.narrow(1, 0, 1).unwrap(), &(b_frames + 0.5).unwrap()], 1)
                .unwrap();
        let out2 = model.forward(&changed.view(), None).unwrap();
        let object_a = |o: &Tensor| o.get(0).unwrap().get(0).unwrap().narrow(1, body, 18).unwrap();
        let delta = (object_a(&out) - object_a(&out2))
            .unwrap()
            .abs()
            .unwrap()
            .max_all()
            .unwrap()
            .to_scalar::<f64>()
            .unwrap();
        assert!(delta > 1e-6, "{:?}: stream A ignores stream B", cfg.stream_layout);
    }
}

#[test]
fn seeds_decide_the_parameters_and_the_dropout() {
    let cfg = ModelConfig { dropout: 0.2, ..ModelConfig::tiny() };
    let values = |seed| {
        let (_, vars) = build(&cfg, seed, DType::F32);
        let data = vars.var_map().data().lock().unwrap();
        data["blocks.0.self_attention.query.weight"]
            .as_tensor()
            .flatten_all()
            .unwrap()
            .to_vec1::<f32>()
            .unwrap()
    };
    assert_eq!(values(1), values(1));
    assert_ne!(values(1), values(2));
    let (model, vars) = build(&cfg, 1, DType::F32);
    randomise(&vars, 3);
    let inputs = Inputs::random(&cfg, 2, DType::F32, 4);
    let run = |rng: Option<&mut ChaCha8Rng>| {
        model.forward(&inputs.view(), rng).unwrap().flatten_all().unwrap().to_vec1::<f32>().unwrap()
    };
    let eval = run(None);
    assert_eq!(eval, run(None));
    let train = run(Some(&mut ChaCha8Rng::seed_from_u64(9)));
    assert_eq!(train, run(Some(&mut ChaCha8Rng::seed_from_u64(9))));
    assert_ne!(train, eval);
}

#[test]
fn bad_inputs_and_configs_are_refused() {
    let cfg = ModelConfig::tiny();
    let (model, _) = build(&cfg, 0, DType::F32);
    let inputs = Inputs::random(&cfg, 2, DType::F32, 1);
    let short = inputs.noisy.narrow(2, 0, 3).unwrap();
    let error = model.forward(&ModelInput { noisy: &short, ..inputs.view() }, None).unwrap_err();
    assert!(error.to_string().contains("noisy"), "{error}");
    let text = inputs.text.narrow(1, 0, 3).unwrap();
    assert!(model.forward(&ModelInput { text: &text, ..inputs.view() }, None).is_err());
    assert!(ModelConfig { heads: 3, ..cfg.clone() }.validate().is_err());
    assert!(ModelConfig { dropout: 1.0, ..cfg.clone() }.validate().is_err());
    assert!(ModelConfig::preset("huge").is_err());
    assert_eq!(ModelConfig::preset("paper").unwrap().latent, 512);
    let json = serde_json::to_string(&ModelConfig::small()).unwrap();
    assert_eq!(serde_json::from_str::<ModelConfig>(&json).unwrap(), ModelConfig::small());
    assert!(
        serde_json::from_str::<ModelConfig>(&json.replace("\"latent\"", "\"latency\"")).is_err()
    );
}

/// Finite differences against the backward pass for a few entries of every parameter and of
/// the noisy input, in f64, for each variant.
#[test]
fn gradients_of_every_parameter_match_finite_differences() {
    for cfg in variants().into_iter().chain(with_prompt_state()) {
        let cfg = ModelConfig {
            joints: 2,
            prefix_frames: 2,
            predicted_frames: 3,
            bps_points: 4,
            text_embedding: 5,
            latent: 8,
            feed_forward: 12,
            ..cfg
        };
        let (model, vars) = build(&cfg, 0, DType::F64);
        randomise(&vars, 11);
        let inputs = Inputs::random(&cfg, 2, DType::F64, 12);
        let count = 2 * 2 * cfg.predicted_frames * cfg.stream_features();
        let weights: Vec<f64> = (0..count).map(|i| ((i as f64) * 0.37 + 0.1).sin()).collect();
        let weights = Tensor::from_vec(
            weights,
            (2, 2, cfg.predicted_frames, cfg.stream_features()),
            &Device::Cpu,
        )
        .unwrap();
        let loss = |model: &Model, inputs: &Inputs| -> f64 {
            (model.forward(&inputs.view(), None).unwrap() * &weights)
                .unwrap()
                .sum_all()
                .unwrap()
                .to_scalar::<f64>()
                .unwrap()
        };
        let out =
            (model.forward(&inputs.view(), None).unwrap() * &weights).unwrap().sum_all().unwrap();
        let grads = out.backward().unwrap();
        let data = vars.var_map().data().lock().unwrap();
        let mut names: Vec<&String> = data.keys().collect();
        names.sort();
        let mut rng = ChaCha8Rng::seed_from_u64(13);
        for name in names {
            let var = &data[name];
            let grad = grads.get(var.as_tensor()).unwrap_or_else(|| panic!("{name}: no gradient"));
            let grad: Vec<f64> = grad.flatten_all().unwrap().to_vec1().unwrap();
            let base: Vec<f64> = var.as_tensor().flatten_all().unwrap().to_vec1().unwrap();
            for _ in 0..2 {
                let i = rng.random_range(0..base.len());
                let h = 1e-6;
                let at = |delta: f64| {
                    let mut v = base.clone();
                    v[i] += delta;
                    var.set(&Tensor::from_vec(v, var.shape(), &Device::Cpu).unwrap()).unwrap();
                    loss(&model, &inputs)
                };
                let numeric = (at(h) - at(-h)) / (2.0 * h);
                var.set(&Tensor::from_vec(base.clone(), var.shape(), &Device::Cpu).unwrap())
                    .unwrap();
                let error = (numeric - grad[i]).abs();
                assert!(
                    error <= 1e-6 + 1e-5 * numeric.abs().max(grad[i].abs()),
                    "{:?} {name}[{i}]: analytic {} vs numeric {numeric}",
                    cfg.stream_layout,
                    grad[i]
                );
            }
        }
    }
}

/// Reads a checkpoint file and builds the model stored under `model.`.
fn load_file(
    path: &std::path::Path,
    expected: Option<&ModelConfig>,
) -> dex2hoi_model::Result<(Model, SeededVarMap)> {
    let (tensors, metadata) = dex2hoi_model::checkpoint::read_tensors(path, &Device::Cpu)?;
    Model::from_checkpoint(path, &tensors, &metadata, "model.", expected, DType::F32, &Device::Cpu)
}

#[test]
fn checkpoints_round_trip_and_refuse_mismatches() {
    use dex2hoi_model::checkpoint::{
        model_metadata, named_parameters, read_tensors, write_tensors,
    };
    let dir = std::env::temp_dir().join(format!("dex2hoi-ckpt-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let cfg = ModelConfig::tiny();
    let (model, vars) = build(&cfg, 0, DType::F32);
    randomise(&vars, 21);
    let path = dir.join("model.safetensors");
    write_tensors(&path, &named_parameters(&vars, "model."), &model_metadata(&cfg)).unwrap();
    let (loaded, _) = load_file(&path, Some(&cfg)).unwrap();
    let inputs = Inputs::random(&cfg, 2, DType::F32, 22);
    let output = |m: &Model| {
        m.forward(&inputs.view(), None).unwrap().flatten_all().unwrap().to_vec1::<f32>().unwrap()
    };
    let (a, b) = (output(&model), output(&loaded));
    assert_eq!(a, b);
    // Another configuration is refused, naming the file.
    let other = ModelConfig { layers: 3, ..cfg.clone() };
    let error = load_file(&path, Some(&other)).unwrap_err().to_string();
    assert!(
        error.contains("model.safetensors") && error.contains("model configuration"),
        "{error}"
    );
    // A parameter of the wrong shape, a missing one, an extra one.
    let (mut tensors, metadata) = read_tensors(&path, &Device::Cpu).unwrap();
    let key = "model.blocks.0.self_attention.query.weight".to_string();
    let original = tensors[&key].clone();
    tensors.insert(key.clone(), Tensor::zeros((3, 3), DType::F32, &Device::Cpu).unwrap());
    write_tensors(&path, &tensors, &metadata).unwrap();
    let error = load_file(&path, None).unwrap_err().to_string();
    assert!(error.contains(&key) && error.contains("shape"), "{error}");
    tensors.remove(&key);
    write_tensors(&path, &tensors, &metadata).unwrap();
    assert!(load_file(&path, None).unwrap_err().to_string().contains(&key));
    tensors.insert(key, original);
    tensors
        .insert("model.blocks.9.extra".into(), Tensor::zeros(2, DType::F32, &Device::Cpu).unwrap());
    write_tensors(&path, &tensors, &metadata).unwrap();
    assert!(load_file(&path, None).unwrap_err().to_string().contains("blocks.9.extra"));
    // No configuration in the metadata, or a corrupt file.
    write_tensors(&path, &named_parameters(&vars, "model."), &Default::default()).unwrap();
    assert!(load_file(&path, None).is_err());
    let mut broken = model_metadata(&cfg);
    broken.insert(dex2hoi_model::checkpoint::CONFIG_KEY.into(), "{\"latent\": 3}".into());
    write_tensors(&path, &named_parameters(&vars, "model."), &broken).unwrap();
    assert!(load_file(&path, None).is_err());
    std::fs::write(&path, b"not a checkpoint").unwrap();
    assert!(load_file(&path, None).unwrap_err().to_string().contains("model.safetensors"));
    std::fs::remove_dir_all(&dir).ok();
}

/// The tiny model with the prompt clock, and with the object start, both readings, and the
/// memory of set-down objects, in both stream layouts.
fn with_prompt_state() -> [ModelConfig; 5] {
    let clocked = ModelConfig { prompt_clock: true, ..ModelConfig::tiny() };
    let absolute = ModelConfig { object_start: ObjectStart::Absolute, ..clocked.clone() };
    let from_prefix = ModelConfig { object_start: ObjectStart::FromPrefix, ..clocked.clone() };
    let settled = ModelConfig { settled_objects: true, ..from_prefix.clone() };
    let single = ModelConfig { stream_layout: StreamLayout::Single, ..settled.clone() };
    [clocked, absolute, from_prefix, settled, single]
}

const LAYOUTS: [StreamLayout; 2] = [StreamLayout::Dual, StreamLayout::Single];

#[test]
fn the_object_start_reads_each_objects_rotation_and_world_position_at_the_prompts_start() {
    let readings = [ObjectStart::Absolute, ObjectStart::FromPrefix];
    for (object_start, layout) in readings.into_iter().flat_map(|r| LAYOUTS.map(|l| (r, l))) {
        let cfg = ModelConfig { object_start, stream_layout: layout, ..ModelConfig::tiny() };
        let (model, vars) = build(&cfg, 3, DType::F32);
        // Sample 0 holds two objects, sample 1 one (its slot B empty).
        let inputs = Inputs::random(&cfg, 2, DType::F32, 4);
        let error = model
            .forward(&ModelInput { object_start: None, ..inputs.view() }, None)
            .unwrap_err()
            .to_string();
        assert!(error.contains("object_start"), "{object_start:?}, {layout:?}: required: {error}");
        let short = inputs.start.narrow(2, 0, 5).unwrap();
        let refused =
            model.forward(&ModelInput { object_start: Some(&short), ..inputs.view() }, None);
        assert!(refused.is_err());
        let features = FeatureLayout::new(cfg.joints);
        // The start rows with `value` added to channel `channel` of stream `stream`'s row.
        let moved = |stream: usize, channel: usize, value: f32| {
            let mut rows: Vec<f32> = inputs.start.flatten_all().unwrap().to_vec1().unwrap();
            let d = cfg.stream_features();
            for sample in 0..2 {
                rows[(sample * 2 + stream) * d + channel] += value;
            }
            Tensor::from_vec(rows, (2, 2, d), &Device::Cpu).unwrap()
        };
        let run = |start: &Tensor| {
            model.forward(&ModelInput { object_start: Some(start), ..inputs.view() }, None).unwrap()
        };
        // Per sample and stream, the largest change between two outputs.
        let changed = |a: &Tensor, b: &Tensor| -> Vec<f32> {
            let d = (a - b).unwrap().abs().unwrap();
            d.flatten_from(2).unwrap().max(2).unwrap().flatten_all().unwrap().to_vec1().unwrap()
        };
        let position = features.object_part_range(GLOBAL_POSITION_RANGE).start;
        let rotation = features.object_part_range(ROTATION_RANGE).start;
        // Zero-initialised output layer: nothing changes until it is trained.
        assert!(
            changed(&run(&inputs.start), &run(&moved(0, position, 1.0))).iter().all(|&c| c == 0.0)
        );
        randomise(&vars, 11);
        let base = run(&inputs.start);
        for channel in [position, rotation + 2] {
            // Slot A's object at the start: every stream of both samples reads it.
            let a = changed(&base, &run(&moved(0, channel, 1.0)));
            assert!(
                a.iter().all(|&c| c > 1e-4),
                "{object_start:?}, {layout:?}, channel {channel}: {a:?}"
            );
            // Slot B's: read where the slot holds an object (sample 0), not where it is empty
            // (sample 1, whose output is the same to the bit).
            let b = changed(&base, &run(&moved(1, channel, 1.0)));
            assert!(
                b[0] > 1e-4 && b[1] > 1e-4,
                "{object_start:?}, {layout:?}, channel {channel}: {b:?}"
            );
            assert_eq!(&b[2..], &[0.0, 0.0], "{object_start:?}, {layout:?}, channel {channel}");
        }
        // The body's rows, the hand-relative channels and the mixture are not read.
        let body = changed(&base, &run(&moved(0, 0, 1.0)));
        let mixture = features.object_part_range(MIXTURE_RANGE).start;
        let hands = changed(&base, &run(&moved(0, mixture, 1.0)));
        assert!(
            body.iter().chain(&hands).all(|&c| c == 0.0),
            "{object_start:?}, {layout:?}: {body:?} {hands:?}"
        );
    }
}

/// From the prefix, the object start reads the start less the last prefix frame's placement:
/// with that placement at zero both readings give the same output (the same weights), and
/// otherwise not.
#[test]
fn the_object_start_from_the_prefix_is_the_start_less_the_last_prefix_frame() {
    for stream_layout in LAYOUTS {
        let models = [ObjectStart::Absolute, ObjectStart::FromPrefix].map(|object_start| {
            let cfg = ModelConfig { object_start, stream_layout, ..ModelConfig::tiny() };
            let (model, vars) = build(&cfg, 3, DType::F32);
            randomise(&vars, 11);
            model
        });
        let cfg = models[0].config().clone();
        let mut inputs = Inputs::random(&cfg, 2, DType::F32, 4);
        let difference = |inputs: &Inputs| {
            let [a, b] = models.each_ref().map(|m| m.forward(&inputs.view(), None).unwrap());
            (a - b).unwrap().abs().unwrap().max_all().unwrap().to_scalar::<f32>().unwrap()
        };
        assert!(difference(&inputs) > 1e-4, "{stream_layout:?}");
        let features = FeatureLayout::new(cfg.joints);
        let (d, tp) = (cfg.stream_features(), cfg.prefix_frames);
        let mut prefix: Vec<f32> = inputs.prefix.flatten_all().unwrap().to_vec1().unwrap();
        for row in prefix.chunks_exact_mut(d).skip(tp - 1).step_by(tp) {
            for part in [ROTATION_RANGE, GLOBAL_POSITION_RANGE] {
                row[features.object_part_range(part)].fill(0.0);
            }
        }
        inputs.prefix = Tensor::from_vec(prefix, inputs.prefix.dims(), &Device::Cpu).unwrap();
        assert_eq!(difference(&inputs), 0.0, "{stream_layout:?}");
    }
}

/// With the start (or reach) frame in the prefix the network is the same, reading a prefix
/// whose first frame is the rows given for it: to the bit the plain model (the same weights)
/// given that prefix, while the prefix-residual head still adds the real last prefix frame.
#[test]
fn the_start_or_reach_frame_in_the_prefix_is_the_first_prefix_token() {
    for (stream_layout, reach) in LAYOUTS.into_iter().flat_map(|l| [(l, false), (l, true)]) {
        let plain = ModelConfig { stream_layout, ..ModelConfig::tiny() };
        let cfg = ModelConfig { start_in_prefix: !reach, reach_in_prefix: reach, ..plain.clone() };
        assert!(cfg.prediction.adds_prefix(), "the residual head is part of what is checked");
        let [(model, vars), (reference, reference_vars)] =
            [&cfg, &plain].map(|c| build(c, 3, DType::F32));
        randomise(&vars, 11);
        randomise(&reference_vars, 11);
        let inputs = Inputs::random(&cfg, 2, DType::F32, 4);
        // The token's rows: the object start's for the start frame, their own for the reach.
        let (view, without, name) = if reach {
            let view =
                ModelInput { object_start: None, reach: Some(&inputs.start), ..inputs.view() };
            (view, ModelInput { reach: None, ..view }, "reach")
        } else {
            (inputs.view(), ModelInput { object_start: None, ..inputs.view() }, "object_start")
        };
        let error = model.forward(&without, None).unwrap_err().to_string();
        assert!(error.contains(name), "{stream_layout:?}: required: {error}");
        let tp = cfg.prefix_frames;
        let with_token = Tensor::cat(
            &[&inputs.start.unsqueeze(2).unwrap(), &inputs.prefix.narrow(2, 1, tp - 1).unwrap()],
            2,
        )
        .unwrap();
        let difference = |a: &Tensor, b: &Tensor| {
            (a - b).unwrap().abs().unwrap().max_all().unwrap().to_scalar::<f32>().unwrap()
        };
        let got = model.forward(&view, None).unwrap();
        let read = reference.forward(&ModelInput { prefix: &with_token, ..view }, None).unwrap();
        // The residual head adds the last frame, the same in both prefixes.
        assert_eq!(difference(&got, &read), 0.0, "{stream_layout:?} {name}");
        let plain_out = reference.forward(&view, None).unwrap();
        assert!(difference(&got, &plain_out) > 1e-4, "{stream_layout:?}: the {name} is read");
    }
    // The first prefix frame is the token, the last the frame the window continues.
    for reach in [false, true] {
        let one = ModelConfig {
            start_in_prefix: !reach,
            reach_in_prefix: reach,
            prefix_frames: 1,
            ..ModelConfig::tiny()
        };
        let error = one.validate().unwrap_err().to_string();
        assert!(error.contains("prefix_frames"), "{error}");
    }
    // One token at a time.
    let both = ModelConfig { start_in_prefix: true, reach_in_prefix: true, ..ModelConfig::tiny() };
    let error = both.validate().unwrap_err().to_string();
    assert!(error.contains("reach_in_prefix"), "{error}");
    // Left out of a configuration when off; absent reads as off.
    let written = serde_json::to_string(&ModelConfig::tiny()).unwrap();
    assert!(!written.contains("start_in_prefix"), "{written}");
    assert!(!written.contains("reach_in_prefix"), "{written}");
    let read: ModelConfig = serde_json::from_str(&written).unwrap();
    assert!(!read.start_in_prefix && !read.reach_in_prefix);
}

#[test]
fn the_memory_of_set_down_objects_reads_each_present_objects_flag() {
    for stream_layout in LAYOUTS {
        let cfg = ModelConfig { settled_objects: true, stream_layout, ..ModelConfig::tiny() };
        let (model, vars) = build(&cfg, 3, DType::F32);
        // Sample 0 holds two objects, sample 1 one (its slot B empty).
        let inputs = Inputs::random(&cfg, 2, DType::F32, 4);
        let error = model
            .forward(&ModelInput { settled: None, ..inputs.view() }, None)
            .unwrap_err()
            .to_string();
        assert!(error.contains("settled"), "{stream_layout:?}: required: {error}");
        let one = Tensor::zeros((2, 1), DType::F32, &Device::Cpu).unwrap();
        assert!(model.forward(&ModelInput { settled: Some(&one), ..inputs.view() }, None).is_err());
        let run = |flags: [f32; 4]| {
            let settled = Tensor::from_vec(flags.to_vec(), (2, 2), &Device::Cpu).unwrap();
            model.forward(&ModelInput { settled: Some(&settled), ..inputs.view() }, None).unwrap()
        };
        // Per sample, the largest change between two outputs.
        let changed = |a: &Tensor, b: &Tensor| -> Vec<f32> {
            let d = (a - b).unwrap().abs().unwrap();
            d.flatten_from(1).unwrap().max(1).unwrap().to_vec1().unwrap()
        };
        let none = [0.0; 4];
        // Zero-initialised output layer: nothing changes until it is trained.
        assert!(changed(&run(none), &run([1.0; 4])).iter().all(|&c| c == 0.0));
        randomise(&vars, 11);
        let base = run(none);
        // Slot A's flag is read in both samples, slot B's only where the slot holds an
        // object (sample 0; sample 1's output is the same to the bit).
        let a = changed(&base, &run([1.0, 0.0, 1.0, 0.0]));
        assert!(a.iter().all(|&c| c > 1e-4), "{stream_layout:?}: {a:?}");
        let b = changed(&base, &run([0.0, 1.0, 0.0, 1.0]));
        assert!(b[0] > 1e-4 && b[1] == 0.0, "{stream_layout:?}: {b:?}");
    }
}

#[test]
fn the_prompt_clock_reads_the_elapsed_frames_up_to_its_limit() {
    let cfg = ModelConfig { prompt_clock: true, ..ModelConfig::tiny() };
    let (model, vars) = build(&cfg, 3, DType::F32);
    let inputs = Inputs::random(&cfg, 2, DType::F32, 4);
    // Required with the clock, refused with a wrong shape.
    let error = model
        .forward(&ModelInput { elapsed: None, ..inputs.view() }, None)
        .unwrap_err()
        .to_string();
    assert!(error.contains("elapsed"), "{error}");
    let elapsed = |values: [f32; 2]| Tensor::new(&values, &Device::Cpu).unwrap();
    let one = Tensor::new(&[3f32], &Device::Cpu).unwrap();
    assert!(model.forward(&ModelInput { elapsed: Some(&one), ..inputs.view() }, None).is_err());
    let run = |values: [f32; 2]| {
        let e = elapsed(values);
        model.forward(&ModelInput { elapsed: Some(&e), ..inputs.view() }, None).unwrap()
    };
    let difference = |a: &Tensor, b: &Tensor| {
        (a - b).unwrap().abs().unwrap().max_all().unwrap().to_scalar::<f32>().unwrap()
    };
    // Zero-initialised output layer: the clock changes nothing until it is trained.
    assert_eq!(difference(&run([0.0, 0.0]), &run([100.0, 7.0])), 0.0);
    randomise(&vars, 11);
    assert!(difference(&run([0.0, 0.0]), &run([100.0, 7.0])) > 1e-3, "the clock is read");
    // It stops at CLOCK_FRAMES: later readings are the same, negative ones read as 0.
    let limit = dex2hoi_model::CLOCK_FRAMES as f32;
    assert_eq!(difference(&run([limit, limit]), &run([limit + 50.0, 1e6])), 0.0);
    assert_eq!(difference(&run([0.0, 0.0]), &run([-5.0, -1.0])), 0.0);
}
