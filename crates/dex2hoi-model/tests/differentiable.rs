//! The fused layer norm and softmax with hand-written backward passes: equal to their
//! composites forward and backward, and their gradients checked by finite differences (f64).

use candle_core::{DType, Device, Tensor, Var};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use dex2hoi_model::differentiable;
use dex2hoi_model::layers::{layer_norm_composite, softmax_composite};

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
fn fused_softmax(x: &Tensor) -> Tensor {
    differentiable::softmax(x).unwrap()
}
fn composite_softmax(x: &Tensor) -> Tensor {
    softmax_composite(x).unwrap()
}

const PAIRS: [(&str, Op, Op); 2] = [
    ("layer norm", fused_layer_norm, composite_layer_norm),
    ("softmax", fused_softmax, composite_softmax),
];

#[test]
fn forward_and_backward_equal_the_composites() {
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    for (name, fused, composite) in PAIRS {
        for shape in [vec![3, 5, 7], vec![1, 1], vec![2, 40, 64], vec![0, 6]] {
            for (dtype, tolerance) in [(DType::F64, 1e-10), (DType::F32, 2e-5)] {
                let x = random(&shape, 3.0, &mut rng).to_dtype(dtype).unwrap();
                let w = random(&shape, 1.0, &mut rng).to_dtype(dtype).unwrap();
                if x.elem_count() == 0 {
                    // An empty batch is an empty result (the composite softmax refuses it).
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
    assert!(max_difference(&fused_softmax(&t), &composite_softmax(&t)) < 1e-10);
    // f16 is not one of the fused dtypes: the layers fall back to the composites.
    let half = x.to_dtype(DType::F16).unwrap();
    assert!(!differentiable::applies(&half));
    assert!(differentiable::layer_norm(&half).is_err());
}
