//! The fused training operations with hand-written backward passes (layer norm, linear layer,
//! AdaLN modulation, attention, masked softmax): equal to their composites forward and backward, and their
//! gradients checked by finite differences (f64).

use candle_core::{DType, Device, Tensor, Var};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use dex2hoi_model::differentiable;
use dex2hoi_model::layers::{layer_norm_composite, softmax};

type Op = fn(&Tensor) -> Tensor;

fn random(shape: &[usize], scale: f64, rng: &mut ChaCha8Rng) -> Tensor {
    let n: usize = shape.iter().product();
    let v: Vec<f64> = (0..n).map(|_| rng.random_range(-scale..scale)).collect();
    Tensor::from_vec(v, shape, &Device::Cpu).unwrap()
}

fn max_difference(a: &Tensor, b: &Tensor) -> f64 {
    if a.elem_count() == 0 {
        return 0.0;
    }
    let d = (a.to_dtype(DType::F64).unwrap() - b.to_dtype(DType::F64).unwrap()).unwrap();
    d.abs().unwrap().flatten_all().unwrap().max(0).unwrap().to_scalar().unwrap()
}

/// `sum(op(x) * weights)` and its gradient with respect to `x`.
fn value_and_gradient(op: Op, x: &Tensor, weights: &Tensor) -> (f64, Tensor) {
    let var = Var::from_tensor(x).unwrap();
    let loss = (op(var.as_tensor()) * weights).unwrap().sum_all().unwrap();
    let grads = loss.backward().unwrap();
    let value = loss.to_dtype(DType::F64).unwrap().to_scalar::<f64>().unwrap();
    (value, grads.get(var.as_tensor()).unwrap().clone())
}

fn fused_layer_norm(x: &Tensor) -> Tensor {
    differentiable::layer_norm(x).unwrap()
}
fn composite_layer_norm(x: &Tensor) -> Tensor {
    layer_norm_composite(x).unwrap()
}
const PAIRS: [(&str, Op, Op); 1] = [("layer norm", fused_layer_norm, composite_layer_norm)];

#[test]
fn forward_and_backward_equal_the_composites() {
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    for (name, fused, composite) in PAIRS {
        for shape in [vec![3, 5, 7], vec![1, 1], vec![2, 40, 64], vec![0, 6]] {
            for (dtype, tolerance) in [(DType::F64, 1e-10), (DType::F32, 2e-5)] {
                let x = random(&shape, 3.0, &mut rng).to_dtype(dtype).unwrap();
                let w = random(&shape, 1.0, &mut rng).to_dtype(dtype).unwrap();
                if x.elem_count() == 0 {
                    // An empty batch is an empty result.
                    assert_eq!(fused(&x).dims(), x.dims());
                    continue;
                }
                assert!(max_difference(&fused(&x), &composite(&x)) < tolerance, "{name}");
                let (_, g_fused) = value_and_gradient(fused, &x, &w);
                let (_, g_composite) = value_and_gradient(composite, &x, &w);
                let difference = max_difference(&g_fused, &g_composite);
                assert!(difference < 10.0 * tolerance, "{name} {shape:?} {dtype:?}: {difference}");
            }
        }
    }
}

#[test]
fn gradients_match_finite_differences() {
    let mut rng = ChaCha8Rng::seed_from_u64(2);
    for (name, fused, _) in PAIRS {
        let shape = [2, 3, 9];
        let x = random(&shape, 2.0, &mut rng);
        let w = random(&shape, 1.0, &mut rng);
        let (_, gradient) = value_and_gradient(fused, &x, &w);
        let gradient: Vec<f64> = gradient.flatten_all().unwrap().to_vec1().unwrap();
        let base: Vec<f64> = x.flatten_all().unwrap().to_vec1().unwrap();
        let h = 1e-5;
        for k in (0..base.len()).step_by(5) {
            let at = |delta: f64| {
                let mut v = base.clone();
                v[k] += delta;
                let x = Tensor::from_vec(v, &shape, &Device::Cpu).unwrap();
                value_and_gradient(fused, &x, &w).0
            };
            let numeric = (at(h) - at(-h)) / (2.0 * h);
            assert!(
                (numeric - gradient[k]).abs() < 1e-7,
                "{name} entry {k}: {numeric} vs {}",
                gradient[k]
            );
        }
    }
}

#[test]
fn other_dtypes_and_strided_inputs() {
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let x = random(&[4, 6], 1.0, &mut rng);
    // A transposed (strided) input is made contiguous first.
    let t = x.t().unwrap();
    assert!(max_difference(&fused_layer_norm(&t), &composite_layer_norm(&t)) < 1e-10);
    // f16 is not one of the fused dtypes: the layers fall back to the composites.
    let half = x.to_dtype(DType::F16).unwrap();
    assert!(!differentiable::applies(&half));
    assert!(differentiable::layer_norm(&half).is_err());
}

/// The fused operations of the transformer block, each as a function of its inputs (the last
/// input of the attention, the mask, gets no gradient).
type BlockOp = fn(&[Tensor]) -> Tensor;

fn fused_linear(x: &[Tensor]) -> Tensor {
    differentiable::linear(&x[0], &x[1], &x[2], differentiable::Activation::Identity).unwrap()
}
/// `x W + b` over the last dimension.
fn composite_linear(x: &[Tensor]) -> Tensor {
    let (n, t, input) = x[0].dims3().unwrap();
    let flat = x[0].reshape((n * t, input)).unwrap();
    let out = flat.matmul(&x[1]).unwrap().broadcast_add(&x[2]).unwrap();
    out.reshape((n, t, x[1].dim(1).unwrap())).unwrap()
}
fn fused_linear_silu(x: &[Tensor]) -> Tensor {
    differentiable::linear(&x[0], &x[1], &x[2], differentiable::Activation::Silu).unwrap()
}
fn composite_linear_silu(x: &[Tensor]) -> Tensor {
    composite_linear(x).silu().unwrap()
}
fn fused_modulate(x: &[Tensor]) -> Tensor {
    differentiable::modulate(&x[0], &x[1]).unwrap()
}
/// AdaLN written out: `norm(x) (1 + scale) + shift`.
fn composite_modulate(x: &[Tensor]) -> Tensor {
    let latent = x[0].dim(2).unwrap();
    let modulation = x[1].unsqueeze(1).unwrap();
    let shift = modulation.narrow(2, 0, latent).unwrap();
    let scale = (modulation.narrow(2, latent, latent).unwrap() + 1.0).unwrap();
    layer_norm_composite(&x[0])
        .unwrap()
        .broadcast_mul(&scale)
        .unwrap()
        .broadcast_add(&shift)
        .unwrap()
}
const HEADS: usize = 2;
fn fused_attention(x: &[Tensor]) -> Tensor {
    differentiable::attention(&x[0], &x[1], &x[2], HEADS).unwrap()
}
/// Multi-head attention written out with candle's batched products, one head at a time.
fn composite_attention(x: &[Tensor]) -> Tensor {
    let (q, kv, mask) = (&x[0], &x[1], &x[2]);
    let latent = q.dim(2).unwrap();
    let head = latent / HEADS;
    let bias = ((mask - 1.0).unwrap() * 1e9).unwrap().unsqueeze(1).unwrap();
    let heads: Vec<Tensor> = (0..HEADS)
        .map(|h| {
            let q = q.narrow(2, h * head, head).unwrap();
            let k = kv.narrow(2, h * head, head).unwrap();
            let v = kv.narrow(2, latent + h * head, head).unwrap();
            let scores = (q.matmul(&k.t().unwrap()).unwrap() / (head as f64).sqrt()).unwrap();
            let weights = softmax(&scores.broadcast_add(&bias).unwrap()).unwrap();
            weights.matmul(&v).unwrap()
        })
        .collect();
    Tensor::cat(&heads, 2).unwrap()
}

fn fused_masked_softmax(x: &[Tensor]) -> Tensor {
    differentiable::masked_softmax(&x[0], &x[1]).unwrap()
}
/// The composite attention's softmax: the masked keys' bias added, broadcast over heads and
/// queries.
fn composite_masked_softmax(x: &[Tensor]) -> Tensor {
    let bias = ((&x[1] - 1.0).unwrap() * 1e9).unwrap().unsqueeze(1).unwrap().unsqueeze(1).unwrap();
    softmax(&x[0].broadcast_add(&bias).unwrap()).unwrap()
}

/// Name, fused, composite, the inputs' shapes for a size `(n, t, latent)`, and how many of the
/// inputs get a gradient.
type BlockCase =
    (&'static str, BlockOp, BlockOp, fn(usize, usize, usize) -> Vec<Vec<usize>>, usize);

const BLOCK_OPS: [BlockCase; 5] = [
    (
        "linear",
        fused_linear,
        composite_linear,
        |n, t, l| vec![vec![n, t, l], vec![l, l + 3], vec![l + 3]],
        3,
    ),
    (
        "linear + SiLU",
        fused_linear_silu,
        composite_linear_silu,
        |n, t, l| vec![vec![n, t, l], vec![l, 2 * l], vec![2 * l]],
        3,
    ),
    (
        "modulate",
        fused_modulate,
        composite_modulate,
        |n, t, l| vec![vec![n, t, l], vec![n, 2 * l]],
        2,
    ),
    (
        "attention",
        fused_attention,
        composite_attention,
        |n, t, l| vec![vec![n, t, l], vec![n, t + 1, 2 * l], vec![n, t + 1]],
        2,
    ),
    (
        "masked softmax",
        fused_masked_softmax,
        composite_masked_softmax,
        |n, t, l| vec![vec![n, 2, t, l + 1], vec![n, l + 1]],
        1,
    ),
];

/// Random inputs for a case; a mask (the attention's and the softmax's last input) masks each
/// sequence's last key but one.
fn block_inputs(
    case: &BlockCase,
    size: (usize, usize, usize),
    rng: &mut ChaCha8Rng,
) -> Vec<Tensor> {
    let shapes = (case.3)(size.0, size.1, size.2);
    let mut inputs: Vec<Tensor> = shapes.iter().map(|s| random(s, 2.0, rng)).collect();
    if matches!(case.0, "attention" | "masked softmax") {
        let last = shapes.len() - 1;
        let (n, keys) = (shapes[last][0], shapes[last][1]);
        let mask: Vec<f64> = (0..n * keys)
            .map(|i| if keys > 1 && i % keys == keys - 2 { 0.0 } else { 1.0 })
            .collect();
        inputs[last] = Tensor::from_vec(mask, (n, keys), &Device::Cpu).unwrap();
    }
    inputs
}

/// `sum(op(inputs) * weights)` and its gradients with respect to the first `graded` inputs.
fn block_value_and_gradients(
    op: BlockOp,
    inputs: &[Tensor],
    graded: usize,
    weights: &Tensor,
) -> (f64, Vec<Tensor>) {
    let vars: Vec<Var> = inputs[..graded].iter().map(|x| Var::from_tensor(x).unwrap()).collect();
    let mut all: Vec<Tensor> = vars.iter().map(|v| v.as_tensor().clone()).collect();
    all.extend(inputs[graded..].iter().cloned());
    let loss = (op(&all) * weights).unwrap().sum_all().unwrap();
    let grads = loss.backward().unwrap();
    let value = loss.to_dtype(DType::F64).unwrap().to_scalar::<f64>().unwrap();
    (value, vars.iter().map(|v| grads.get(v.as_tensor()).unwrap().clone()).collect())
}

#[test]
fn block_operations_equal_their_composites_forward_and_backward() {
    let mut rng = ChaCha8Rng::seed_from_u64(4);
    for case in &BLOCK_OPS {
        let (name, fused, composite, _, graded) = *case;
        for size in [(2, 5, 8), (1, 1, 4), (3, 17, 12)] {
            for (dtype, tolerance) in [(DType::F64, 1e-10), (DType::F32, 5e-5)] {
                let inputs: Vec<Tensor> = block_inputs(case, size, &mut rng)
                    .iter()
                    .map(|x| x.to_dtype(dtype).unwrap())
                    .collect();
                let out = composite(&inputs);
                let weights = random(out.dims(), 1.0, &mut rng).to_dtype(dtype).unwrap();
                let difference = max_difference(&fused(&inputs), &out);
                assert!(difference < tolerance, "{name} {size:?} {dtype:?}: {difference}");
                let (_, g_fused) = block_value_and_gradients(fused, &inputs, graded, &weights);
                let (_, g_composite) =
                    block_value_and_gradients(composite, &inputs, graded, &weights);
                for (k, (a, b)) in g_fused.iter().zip(&g_composite).enumerate() {
                    assert_eq!(a.dims(), b.dims(), "{name} input {k}");
                    let difference = max_difference(a, b);
                    assert!(
                        difference < 10.0 * tolerance,
                        "{name} {size:?} {dtype:?} input {k}: {difference}"
                    );
                }
            }
        }
    }
}

#[test]
fn block_operation_gradients_match_finite_differences() {
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    for case in &BLOCK_OPS {
        let (name, fused, _, _, graded) = *case;
        let inputs = block_inputs(case, (2, 3, 4), &mut rng);
        let out = fused(&inputs);
        let weights = random(out.dims(), 1.0, &mut rng);
        let (_, gradients) = block_value_and_gradients(fused, &inputs, graded, &weights);
        let h = 1e-5;
        for (k, gradient) in gradients.iter().enumerate() {
            let gradient: Vec<f64> = gradient.flatten_all().unwrap().to_vec1().unwrap();
            let base: Vec<f64> = inputs[k].flatten_all().unwrap().to_vec1().unwrap();
            for e in (0..base.len()).step_by(3) {
                let at = |delta: f64| {
                    let mut v = base.clone();
                    v[e] += delta;
                    let mut moved = inputs.clone();
                    moved[k] = Tensor::from_vec(v, inputs[k].dims(), &Device::Cpu).unwrap();
                    block_value_and_gradients(fused, &moved, graded, &weights).0
                };
                let numeric = (at(h) - at(-h)) / (2.0 * h);
                assert!(
                    (numeric - gradient[e]).abs() < 1e-6 * (1.0 + numeric.abs()),
                    "{name} input {k} entry {e}: {numeric} vs {}",
                    gradient[e]
                );
            }
        }
    }
}

#[test]
fn block_operations_refuse_mismatched_shapes() {
    let mut rng = ChaCha8Rng::seed_from_u64(6);
    let x = random(&[2, 3, 4], 1.0, &mut rng);
    let error = differentiable::modulate(&x, &random(&[2, 4], 1.0, &mut rng)).unwrap_err();
    assert!(error.to_string().contains("modulation [N, 2 latent]"), "{error}");
    let error = differentiable::attention(
        &x,
        &random(&[2, 3, 4], 1.0, &mut rng),
        &random(&[2, 3], 1.0, &mut rng),
        2,
    )
    .unwrap_err();
    assert!(error.to_string().contains("keys and values [N, Tk, 2 latent]"), "{error}");
    let error = differentiable::linear(
        &x,
        &random(&[4, 5], 1.0, &mut rng),
        &random(&[3], 1.0, &mut rng),
        differentiable::Activation::Silu,
    )
    .unwrap_err();
    assert!(error.to_string().contains("a bias of 5"), "{error}");
    let error = differentiable::masked_softmax(&x, &random(&[2, 3], 1.0, &mut rng)).unwrap_err();
    assert!(error.to_string().contains("a mask [N, keys]"), "{error}");
}
