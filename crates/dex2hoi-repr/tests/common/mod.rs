//! Helpers shared by the integration tests.
#![allow(dead_code)]

use candle_core::{DType, Device, Tensor, Var};
use glam::{Mat3, Vec3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use dex2hoi_repr::rotation::axis_angle_to_matrix;

pub fn rng(seed: u64) -> ChaCha8Rng {
    ChaCha8Rng::seed_from_u64(seed)
}

pub fn random_vec3(rng: &mut ChaCha8Rng, scale: f32) -> Vec3 {
    Vec3::new(rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0))
        * scale
}

pub fn random_rotation(rng: &mut ChaCha8Rng, max_angle: f32) -> Mat3 {
    let axis = loop {
        let v = random_vec3(rng, 1.0);
        if v.length() > 0.1 {
            break v.normalize();
        }
    };
    axis_angle_to_matrix(axis * rng.random_range(0.0..max_angle))
}

pub fn mat3_values(m: Mat3) -> [f32; 9] {
    // Row-major, like a [3, 3] tensor.
    m.transpose().to_cols_array()
}

pub fn mats_to_tensor(mats: &[Mat3], shape: &[usize]) -> Tensor {
    let flat: Vec<f32> = mats.iter().flat_map(|m| mat3_values(*m)).collect();
    Tensor::from_vec(flat, shape, &Device::Cpu).unwrap()
}

pub fn vecs_to_tensor(vecs: &[Vec3], shape: &[usize]) -> Tensor {
    let flat: Vec<f32> = vecs.iter().flat_map(|v| v.to_array()).collect();
    Tensor::from_vec(flat, shape, &Device::Cpu).unwrap()
}

pub fn flat(t: &Tensor) -> Vec<f32> {
    t.to_dtype(DType::F32).unwrap().flatten_all().unwrap().to_vec1::<f32>().unwrap()
}

pub fn assert_close(a: &[f32], b: &[f32], tolerance: f32, what: &str) {
    assert_eq!(a.len(), b.len(), "{what}: lengths");
    for (i, (x, y)) in a.iter().zip(b).enumerate() {
        assert!((x - y).abs() <= tolerance, "{what}[{i}]: {x} vs {y}");
    }
}

/// Compares the backward pass of `f` with central finite differences, in f64, on the scalar
/// `sum(f(x) * w)` with fixed pseudo-random weights `w`.
pub fn gradient_check(
    input: &Tensor,
    f: impl Fn(&Tensor) -> dex2hoi_repr::Result<Tensor>,
    what: &str,
) {
    let input = input.to_dtype(DType::F64).unwrap();
    let var = Var::from_tensor(&input).unwrap();
    let output = f(var.as_tensor()).unwrap();
    let count = output.elem_count();
    let weights: Vec<f64> = (0..count).map(|i| ((i as f64) * 0.7 + 0.3).sin()).collect();
    let weights = Tensor::from_vec(weights, output.shape(), &Device::Cpu).unwrap();
    let scalar = |x: &Tensor| -> f64 {
        (f(x).unwrap() * &weights).unwrap().sum_all().unwrap().to_scalar::<f64>().unwrap()
    };
    let loss = (output * &weights).unwrap().sum_all().unwrap();
    let grads = loss.backward().unwrap();
    let analytic = grads
        .get(var.as_tensor())
        .unwrap_or_else(|| panic!("{what}: no gradient reached the input"))
        .flatten_all()
        .unwrap()
        .to_vec1::<f64>()
        .unwrap();
    let base = input.flatten_all().unwrap().to_vec1::<f64>().unwrap();
    let h = 1e-6;
    for i in 0..base.len() {
        let mut plus = base.clone();
        plus[i] += h;
        let mut minus = base.clone();
        minus[i] -= h;
        let at = |v: Vec<f64>| Tensor::from_vec(v, input.shape(), &Device::Cpu).unwrap();
        let numeric = (scalar(&at(plus)) - scalar(&at(minus))) / (2.0 * h);
        let error = (numeric - analytic[i]).abs();
        assert!(
            error <= 1e-6 + 1e-5 * numeric.abs().max(analytic[i].abs()),
            "{what}: d/dx[{i}] analytic {} vs numeric {numeric}",
            analytic[i]
        );
    }
}
