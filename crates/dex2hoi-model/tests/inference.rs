//! The no-grad inference path: every fused operation equals the composite operations it
//! replaces (1e-5), and `InferenceModel` equals `Model::forward` (1e-4) for every variant of
//! Table 3 with randomised weights, on odd sizes too.

use candle_core::{D, DType, Device, Tensor};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use dex2hoi_model::layers::{layer_norm, softmax};
use dex2hoi_model::{
    BodyFusion, InferenceModel, Model, ModelConfig, ModelInput, ObjectRepresentation, ObjectStart,
    Prediction, PromptState, SeededVarMap, StreamLayout, fused,
};

fn random(shape: &[usize], rng: &mut ChaCha8Rng) -> Tensor {
    let n: usize = shape.iter().product();
    let v: Vec<f32> = (0..n).map(|_| rng.random_range(-1.0..1.0)).collect();
    Tensor::from_vec(v, shape, &Device::Cpu).unwrap()
}

fn max_difference(a: &Tensor, b: &Tensor) -> f32 {
    assert_eq!(a.dims(), b.dims());
    if a.elem_count() == 0 {
        return 0.0;
    }
    (a - b).unwrap().abs().unwrap().flatten_all().unwrap().max(0).unwrap().to_scalar().unwrap()
}

fn swap_halves(t: &Tensor) -> Tensor {
    let half = t.dim(0).unwrap() / 2;
    Tensor::cat(&[t.narrow(0, half, half).unwrap(), t.narrow(0, 0, half).unwrap()], 0).unwrap()
}

#[test]
fn layer_norm_equals_the_composite() {
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    for shape in [[3, 7, 13], [1, 1, 1], [2, 33, 64], [0, 4, 8]] {
        let x = (random(&shape, &mut rng) * 3.0).unwrap();
        assert!(max_difference(&fused::layer_norm(&x).unwrap(), &layer_norm(&x).unwrap()) < 1e-5);
    }
}

#[test]
fn adaln_equals_the_composite_with_and_without_swapped_halves() {
    let mut rng = ChaCha8Rng::seed_from_u64(2);
    let (n, t, l, column) = (4, 9, 24, 10);
    let x = random(&[n, t, l], &mut rng);
    let table = random(&[n, column + 2 * l + 5], &mut rng);
    let shift = table.narrow(1, column, l).unwrap().unsqueeze(1).unwrap();
    let scale = table.narrow(1, column + l, l).unwrap().unsqueeze(1).unwrap();
    let modulate = |x: &Tensor, shift: &Tensor, scale: &Tensor| {
        layer_norm(x)
            .unwrap()
            .broadcast_mul(&(scale + 1.0).unwrap())
            .unwrap()
            .broadcast_add(shift)
            .unwrap()
    };
    let expected = modulate(&x, &shift, &scale);
    assert!(max_difference(&fused::adaln(&x, &table, column, false).unwrap(), &expected) < 1e-5);
    let swapped = modulate(&swap_halves(&x), &swap_halves(&shift), &swap_halves(&scale));
    assert!(max_difference(&fused::adaln(&x, &table, column, true).unwrap(), &swapped) < 1e-5);
    // A table too narrow for the column, and an odd batch to swap, are refused.
    assert!(fused::adaln(&x, &table, column + 6, false).is_err());
    let odd = random(&[3, t, l], &mut rng);
    assert!(fused::adaln(&odd, &random(&[3, 2 * l], &mut rng), 0, true).is_err());
}

#[test]
fn bias_silu_and_residual_equal_the_composite() {
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    for rows in [1, 17, 70] {
        let y = (random(&[rows, 37], &mut rng) * 4.0).unwrap();
        let x = random(&[rows, 37], &mut rng);
        let b = random(&[37], &mut rng);
        let plain = y.broadcast_add(&b).unwrap();
        assert!(max_difference(&fused::bias(&y, &b, false).unwrap(), &plain) < 1e-6);
        assert!(max_difference(&fused::bias(&y, &b, true).unwrap(), &plain.silu().unwrap()) < 1e-5);
        let sum = (&x + &plain).unwrap();
        assert!(max_difference(&fused::residual(&x, &y, &b).unwrap(), &sum) < 1e-6);
    }
    let y = random(&[3, 8], &mut rng);
    assert!(fused::bias(&y, &random(&[7], &mut rng), false).is_err());
    // A strided (non-contiguous) input is refused rather than misread.
    assert!(fused::bias(&y.t().unwrap(), &random(&[3], &mut rng), false).is_err());
}

#[test]
fn product_equals_candles_matmul_on_and_off_the_pool_and_at_odd_sizes() {
    let mut rng = ChaCha8Rng::seed_from_u64(4);
    let single = rayon::ThreadPoolBuilder::new().num_threads(1).build().unwrap();
    let pair = rayon::ThreadPoolBuilder::new().num_threads(2).build().unwrap();
    // Whole and partial panels of 64 columns, whole and partial chunks of 48 rows.
    for (rows, inner, columns) in
        [(1, 1, 1), (17, 37, 5), (70, 256, 768), (3, 129, 33), (240, 64, 1), (120, 512, 200)]
    {
        let x = random(&[rows, inner], &mut rng);
        let w = random(&[inner, columns], &mut rng);
        let expected = x.matmul(&w).unwrap();
        let packed = fused::PackedMatrix::new(&w).unwrap();
        assert_eq!(packed.dims(), (inner, columns));
        // On the global pool's threads, on a pool of two, on a pool of one.
        let outside = fused::product(&x, &packed).unwrap();
        let inside = pair.install(|| fused::product(&x, &packed).unwrap());
        let alone = single.install(|| fused::product(&x, &packed).unwrap());
        for got in [outside, inside, alone] {
            assert!(max_difference(&got, &expected) < 1e-4, "{rows} x {inner} x {columns}");
        }
    }
    // Leading dimensions are rows; empty products are zeros or empty.
    let x = random(&[2, 3, 7], &mut rng);
    let w = random(&[7, 4], &mut rng);
    let packed = |w: &Tensor| fused::PackedMatrix::new(w).unwrap();
    let expected = x.reshape((6, 7)).unwrap().matmul(&w).unwrap().reshape((2, 3, 4)).unwrap();
    assert!(max_difference(&fused::product(&x, &packed(&w)).unwrap(), &expected) < 1e-5);
    let none = Tensor::zeros((4, 0), DType::F32, &Device::Cpu).unwrap();
    let no_inner = packed(&Tensor::zeros((0, 3), DType::F32, &Device::Cpu).unwrap());
    let zeros = fused::product(&none, &no_inner).unwrap();
    assert_eq!(zeros.dims(), [4, 3]);
    assert_eq!(zeros.abs().unwrap().sum_all().unwrap().to_scalar::<f32>().unwrap(), 0.0);
    let no_columns = packed(&Tensor::zeros((7, 0), DType::F32, &Device::Cpu).unwrap());
    assert_eq!(fused::product(&x, &no_columns).unwrap().dims(), [2, 3, 0]);
    let empty = Tensor::zeros((0, 7), DType::F32, &Device::Cpu).unwrap();
    assert_eq!(fused::product(&empty, &packed(&w)).unwrap().dims(), [0, 4]);
    // A weight of the wrong height is refused rather than misread; a strided weight is packed
    // as the matrix it is (here a transposed one), and a strided input is refused.
    assert!(fused::product(&x, &packed(&random(&[6, 4], &mut rng))).is_err());
    let wt = random(&[4, 7], &mut rng);
    let x2 = random(&[5, 7], &mut rng);
    let expected = x2.matmul(&wt.t().unwrap().contiguous().unwrap()).unwrap();
    let got = fused::product(&x2, &packed(&wt.t().unwrap())).unwrap();
    assert!(max_difference(&got, &expected) < 1e-5);
    assert!(fused::product(&x2.t().unwrap(), &packed(&random(&[5, 3], &mut rng))).is_err());
}

/// The composite attention on already projected queries, keys and values.
fn composite_attention(q: &Tensor, k: &Tensor, v: &Tensor, heads: usize) -> Tensor {
    let (n, tq, l) = q.dims3().unwrap();
    let split = |x: &Tensor| {
        let (n, t, _) = x.dims3().unwrap();
        x.reshape((n, t, heads, l / heads)).unwrap().transpose(1, 2).unwrap().contiguous().unwrap()
    };
    let (q, k, v) = (split(q), split(k), split(v));
    let scores = (q.matmul(&k.transpose(2, 3).unwrap().contiguous().unwrap()).unwrap()
        / ((l / heads) as f64).sqrt())
    .unwrap();
    let attended = softmax(&scores).unwrap().matmul(&v).unwrap();
    attended.transpose(1, 2).unwrap().contiguous().unwrap().reshape((n, tq, l)).unwrap()
}

#[test]
fn attention_equals_the_composite_for_self_and_cross_layouts() {
    let mut rng = ChaCha8Rng::seed_from_u64(4);
    // Query and key counts equal and not, heads of one to 64 channels, one key.
    let cases = [
        (2, 7, 7, 12, 3),
        (2, 8, 21, 64, 2),
        (4, 60, 60, 64, 4),
        (2, 8, 13, 32, 2),
        (1, 5, 11, 16, 1),
        (3, 1, 1, 8, 2),
        (2, 4, 4, 8, 1),
    ];
    for (n, tq, tk, l, heads) in cases {
        let bias = random(&[3 * l], &mut rng);
        let (bq, bk, bv) = (
            bias.narrow(0, 0, l).unwrap(),
            bias.narrow(0, l, l).unwrap(),
            bias.narrow(0, 2 * l, l).unwrap(),
        );
        // Self-attention: queries, keys and values side by side in one tensor.
        if tq == tk {
            let qkv = (random(&[n, tq, 3 * l], &mut rng) * 2.0).unwrap();
            let part = |k: usize, b: &Tensor| {
                qkv.narrow(D::Minus1, k * l, l).unwrap().broadcast_add(b).unwrap()
            };
            let expected = composite_attention(&part(0, &bq), &part(1, &bk), &part(2, &bv), heads);
            let op = fused::Attention { heads, latent: l, query_column: 0, key_column: l };
            let got = fused::attention(&qkv, &qkv, &bias, op).unwrap();
            assert!(max_difference(&got, &expected) < 1e-5, "self {n} {tq} {l} {heads}");
        }
        // Cross-attention: queries alone, keys and values side by side.
        let q = random(&[n, tq, l], &mut rng);
        let kv = random(&[n, tk, 2 * l], &mut rng);
        let expected = composite_attention(
            &q.broadcast_add(&bq).unwrap(),
            &kv.narrow(2, 0, l).unwrap().broadcast_add(&bk).unwrap(),
            &kv.narrow(2, l, l).unwrap().broadcast_add(&bv).unwrap(),
            heads,
        );
        let op = fused::Attention { heads, latent: l, query_column: 0, key_column: 0 };
        let got = fused::attention(&q, &kv, &bias, op).unwrap();
        assert!(max_difference(&got, &expected) < 1e-5, "cross {n} {tq} {tk} {l} {heads}");
    }
    // Heads that do not divide the width, and a bias of the wrong size, are refused.
    let q = random(&[1, 3, 12], &mut rng);
    let kv = random(&[1, 3, 24], &mut rng);
    let op = |heads| fused::Attention { heads, latent: 12, query_column: 0, key_column: 0 };
    assert!(fused::attention(&q, &kv, &random(&[36], &mut rng), op(5)).is_err());
    assert!(fused::attention(&q, &kv, &random(&[35], &mut rng), op(3)).is_err());
    // No keys to attend to is refused rather than divided by a zero sum.
    let no_keys = random(&[1, 0, 24], &mut rng);
    assert!(fused::attention(&q, &no_keys, &random(&[36], &mut rng), op(3)).is_err());
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
        // Odd sizes: three heads of 8, an odd window.
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
fn the_inference_model_equals_the_composite_forward_for_every_variant() {
    let clocked = ModelConfig { prompt_clock: true, ..ModelConfig::tiny() };
    let absolute = ModelConfig { object_start: ObjectStart::Absolute, ..clocked.clone() };
    let from_prefix = ModelConfig { object_start: ObjectStart::FromPrefix, ..clocked.clone() };
    let settled = ModelConfig { settled_objects: true, ..from_prefix.clone() };
    let single = ModelConfig { stream_layout: StreamLayout::Single, ..settled.clone() };
    let start_token = ModelConfig { start_in_prefix: true, ..settled.clone() };
    let start_token_single = ModelConfig { start_in_prefix: true, ..single.clone() };
    let reach_token = ModelConfig { reach_in_prefix: true, ..settled.clone() };
    let reach_token_single = ModelConfig { reach_in_prefix: true, ..single.clone() };
    let variants = variants().into_iter().chain([clocked, absolute, from_prefix, settled, single]);
    let tokens = [start_token, start_token_single, reach_token, reach_token_single];
    for cfg in variants.chain(tokens) {
        let vars = SeededVarMap::new(0);
        let model = Model::new(&cfg, vars.builder(DType::F32, &Device::Cpu)).unwrap();
        vars.randomise_zero_parameters(9).unwrap();
        let inference = InferenceModel::new(&model).unwrap();
        assert!(inference.is_fused());
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let batch = 3;
        let d = cfg.stream_features();
        let noisy = random(&[batch, 2, cfg.predicted_frames, d], &mut rng);
        let prefix = random(&[batch, 2, cfg.prefix_frames, d], &mut rng);
        let text = random(&[batch, cfg.text_embedding], &mut rng);
        let bps = random(&[batch, 2, cfg.bps_points * 3], &mut rng);
        let presence = Tensor::new(&[[1f32, 1.0], [1.0, 0.0], [1.0, 1.0]], &Device::Cpu).unwrap();
        let timesteps = Tensor::new(&[0u32, 411, 999], &Device::Cpu).unwrap();
        let elapsed = Tensor::new(&[0f32, 37.0, 500.0], &Device::Cpu).unwrap();
        let start = random(&[batch, 2, d], &mut rng);
        let settled = Tensor::new(&[[1f32, 0.0], [0.0, 0.0], [1.0, 1.0]], &Device::Cpu).unwrap();
        let reach = random(&[batch, 2, d], &mut rng);
        let input = ModelInput {
            noisy: &noisy,
            prefix: &prefix,
            timesteps: &timesteps,
            text: &text,
            bps: &bps,
            presence: &presence,
            frame_mask: None,
            elapsed: cfg.prompt_clock.then_some(&elapsed),
            object_start: (!cfg.object_start.is_off() || cfg.start_in_prefix).then_some(&start),
            settled: cfg.settled_objects.then_some(&settled),
            reach: cfg.reach_in_prefix.then_some(&reach),
        };
        let expected = model.forward(&input, None).unwrap();
        let scale = expected.abs().unwrap().flatten_all().unwrap().max(0).unwrap();
        assert!(scale.to_scalar::<f32>().unwrap() > 0.1, "{cfg:?}: the randomised model does work");
        let prompt = PromptState {
            elapsed: input.elapsed,
            object_start: input.object_start,
            settled: input.settled,
            reach: input.reach,
        };
        let condition = inference.prepare(&text, &bps, &presence, prompt, &prefix).unwrap();
        let got = inference.forward(&prefix, &noisy, &timesteps, &condition).unwrap();
        let difference = max_difference(&got, &expected);
        assert!(difference < 1e-4, "{cfg:?}: {difference}");
        // Rows are split over the pool's threads (one group of rows per thread, none with
        // fewer rows than threads): any grouping gives the same result.
        for threads in [1, 2, 3, 4] {
            let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
            let grouped = pool
                .install(|| inference.forward(&prefix, &noisy, &timesteps, &condition))
                .unwrap();
            let difference = max_difference(&grouped, &got);
            assert!(difference < 1e-5, "{cfg:?}, {threads} threads: {difference}");
        }
        // The same prepared condition serves every step.
        let timesteps = Tensor::new(&[5u32, 6, 7], &Device::Cpu).unwrap();
        let again = inference.forward(&prefix, &noisy, &timesteps, &condition).unwrap();
        let expected = model.forward(&ModelInput { timesteps: &timesteps, ..input }, None).unwrap();
        assert!(max_difference(&again, &expected) < 1e-4, "{cfg:?}");
        // Wrong shapes are refused with the composite's errors, before the rows are split.
        assert!(inference.forward(&noisy, &noisy, &timesteps, &condition).is_err());
        let two = |t: &Tensor| t.narrow(0, 0, 2).unwrap();
        let pair = rayon::ThreadPoolBuilder::new().num_threads(2).build().unwrap();
        let mismatched = pair.install(|| {
            inference.forward(&two(&prefix), &two(&noisy), &two(&timesteps), &condition)
        });
        assert!(mismatched.is_err(), "{cfg:?}: a condition of 3 rows for 2 is refused");
    }
}

#[test]
fn other_dtypes_run_the_composite_model() {
    let cfg = ModelConfig::tiny();
    let vars = SeededVarMap::new(0);
    let model = Model::new(&cfg, vars.builder(DType::F64, &Device::Cpu)).unwrap();
    vars.randomise_zero_parameters(9).unwrap();
    let inference = InferenceModel::new(&model).unwrap();
    assert!(!inference.is_fused());
    let mut rng = ChaCha8Rng::seed_from_u64(6);
    let d = cfg.stream_features();
    let f64 = |t: Tensor| t.to_dtype(DType::F64).unwrap();
    let noisy = f64(random(&[1, 2, cfg.predicted_frames, d], &mut rng));
    let prefix = f64(random(&[1, 2, cfg.prefix_frames, d], &mut rng));
    let text = f64(random(&[1, cfg.text_embedding], &mut rng));
    let bps = f64(random(&[1, 2, cfg.bps_points * 3], &mut rng));
    let presence = f64(Tensor::new(&[[1f32, 1.0]], &Device::Cpu).unwrap());
    let timesteps = Tensor::new(&[3u32], &Device::Cpu).unwrap();
    let condition =
        inference.prepare(&text, &bps, &presence, PromptState::default(), &prefix).unwrap();
    let got = inference.forward(&prefix, &noisy, &timesteps, &condition).unwrap();
    let input = ModelInput {
        noisy: &noisy,
        prefix: &prefix,
        timesteps: &timesteps,
        text: &text,
        bps: &bps,
        presence: &presence,
        frame_mask: None,
        elapsed: None,
        object_start: None,
        settled: None,
        reach: None,
    };
    let expected = model.forward(&input, None).unwrap();
    let difference = (got - expected).unwrap().abs().unwrap().max_all().unwrap();
    assert_eq!(difference.to_scalar::<f64>().unwrap(), 0.0);
}
