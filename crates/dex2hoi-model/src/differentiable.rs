//! Fused CPU operations with hand-written backward passes, for training: layer norm, a linear
//! layer with its bias and activation, AdaLN's modulation and multi-head attention (whose
//! softmax is inside it). Composed from candle operations, each is several graph nodes, each
//! a pass over memory with a fresh allocation forward and, in candle's backward pass, a
//! zero-filled gradient added into; fused, one node, row-parallel.
//!
//! Like the FK's custom operations they run on the CPU in f32 and f64 (the finite-difference
//! gradient checks run in f64); [`crate::layers`] uses the composite operations on any other
//! device or dtype. Each is tested equal to its composite (1e-10 in f64) with every gradient
//! checked by finite differences (`tests/differentiable.rs`).

use std::ops::{Add, Div, Mul, Sub};

use candle_core::{CpuStorage, CustomOp1, CustomOp2, Layout, Shape, Tensor};
use rayon::prelude::*;

use crate::layers::LAYER_NORM_EPS;

/// Rows per rayon task of the row-wise operations (here and in [`crate::fused`]): enough work
/// per task to hide the scheduling cost (a few microseconds), enough tasks to keep both cores
/// busy on a 240-row batch.
pub(crate) const ROWS_PER_TASK: usize = 16;

/// The float types the operations run in.
pub(crate) trait Real:
    Copy
    + Send
    + Sync
    + Default
    + PartialOrd
    + Add<Output = Self>
    + Sub<Output = Self>
    + Mul<Output = Self>
    + Div<Output = Self>
    + std::iter::Sum
    + crate::matmul::Element
{
    fn of(x: f64) -> Self;
    fn sqrt(self) -> Self;
    /// `self * a + b`, one fused instruction where the CPU has FMA (see [`simd`]).
    fn mul_add(self, a: Self, b: Self) -> Self;
    /// `e^self`, vectorisable in f32 (about 1 ulp, [`crate::fused::exp`]); libm's in f64.
    fn fast_exp(self) -> Self;
    fn values(storage: &CpuStorage) -> Option<&[Self]>;
    fn storage(values: Vec<Self>) -> CpuStorage;
}

macro_rules! real {
    ($t:ty, $variant:ident, $fast_exp:expr) => {
        impl Real for $t {
            fn of(x: f64) -> Self {
                x as $t
            }
            fn sqrt(self) -> Self {
                <$t>::sqrt(self)
            }
            #[inline(always)]
            fn mul_add(self, a: Self, b: Self) -> Self {
                <$t>::mul_add(self, a, b)
            }
            #[inline(always)]
            fn fast_exp(self) -> Self {
                $fast_exp(self)
            }
            fn values(storage: &CpuStorage) -> Option<&[Self]> {
                match storage {
                    CpuStorage::$variant(v) => Some(v),
                    _ => None,
                }
            }
            fn storage(values: Vec<Self>) -> CpuStorage {
                CpuStorage::$variant(values)
            }
        }
    };
}

real!(f32, F32, crate::fused::exp);
real!(f64, F64, f64::exp);

/// Runs `kernel` compiled for the widest SIMD the CPU has (pulp's runtime dispatch: AVX2 or
/// AVX-512 with FMA on x86-64), so that the loops inlined into it are vectorised for it; the
/// workspace's default target is baseline x86-64 (SSE2), which runs anywhere. The kernel must
/// be an `#[inline(always)]` closure (and call only `#[inline(always)]` functions), or it is
/// compiled apart, for the baseline. On a CPU without AVX2 and FMA pulp runs the scalar
/// version, correct but slow (`mul_add` is then computed in software).
#[inline(always)]
pub(crate) fn simd<R>(kernel: impl FnOnce() -> R) -> R {
    pulp::Arch::new().dispatch(kernel)
}

/// The product of a shape's leading dimensions (the rows of its last dimension, also when that
/// is 0); `None` if it overflows `usize`.
pub(crate) fn leading_rows(dims: &[usize]) -> Option<usize> {
    let leading = dims.split_last().map_or(&[][..], |(_, leading)| leading);
    leading.iter().try_fold(1usize, |rows, &d| rows.checked_mul(d))
}

/// [`leading_rows`], an error of `op` when it overflows.
fn rows_of(op: &str, dims: &[usize]) -> candle_core::Result<usize> {
    leading_rows(dims).ok_or_else(|| op_error(op, "a row count that fits in usize"))
}

pub(crate) fn op_error(op: &str, message: impl std::fmt::Display) -> candle_core::Error {
    candle_core::Error::Msg(format!("{op}: {message}"))
}

/// The values of a contiguous tensor of type `T`.
pub(crate) fn values<'a, T: Real>(
    op: &str,
    storage: &'a CpuStorage,
    layout: &Layout,
) -> candle_core::Result<&'a [T]> {
    let all = T::values(storage).ok_or_else(|| op_error(op, "expects f32 or f64 tensors"))?;
    match layout.contiguous_offsets() {
        Some((start, end)) => Ok(&all[start..end]),
        None => Err(op_error(op, "expects contiguous tensors")),
    }
}

/// Applies `row_op(input rows, output row)` to every row of `width` values, in parallel, under
/// [`simd`] (so `row_op` should be an `#[inline(always)]` closure).
fn map_rows<T: Real, const N: usize>(
    width: usize,
    inputs: [&[T]; N],
    row_op: impl Fn([&[T]; N], &mut [T]) + Sync,
) -> Vec<T> {
    let mut out = vec![T::default(); inputs[0].len()];
    if width == 0 {
        return out;
    }
    let chunk = width * ROWS_PER_TASK;
    out.par_chunks_mut(chunk).enumerate().for_each(|(task, out)| {
        simd(
            #[inline(always)]
            || {
                for (k, o) in out.chunks_exact_mut(width).enumerate() {
                    let at = task * chunk + k * width;
                    row_op(std::array::from_fn(|i| &inputs[i][at..at + width]), o);
                }
            },
        )
    });
    out
}

#[inline(always)]
fn mean<T: Real>(row: &[T]) -> T {
    dot(row, None) / T::of(row.len() as f64)
}

/// Independent partial sums of [`dot`]: a plain sum is one chain of dependent additions, which
/// does not vectorise.
const SUM_LANES: usize = 8;

/// `sum_k a_k b_k`, or `sum_k a_k` without `b`, in [`SUM_LANES`] partial sums (vectorised under
/// [`simd`]).
#[inline(always)]
fn dot<T: Real>(a: &[T], b: Option<&[T]>) -> T {
    let mut lanes = [T::default(); SUM_LANES];
    let whole = a.len() / SUM_LANES * SUM_LANES;
    let mut tail = T::default();
    match b {
        Some(b) => {
            for (a, b) in a[..whole].chunks_exact(SUM_LANES).zip(b.chunks_exact(SUM_LANES)) {
                for ((lane, &a), &b) in lanes.iter_mut().zip(a).zip(b) {
                    *lane = a.mul_add(b, *lane);
                }
            }
            for (&a, &b) in a[whole..].iter().zip(&b[whole..]) {
                tail = a.mul_add(b, tail);
            }
        }
        None => {
            for a in a[..whole].chunks_exact(SUM_LANES) {
                for (lane, &a) in lanes.iter_mut().zip(a) {
                    *lane = *lane + a;
                }
            }
            for &a in &a[whole..] {
                tail = tail + a;
            }
        }
    }
    lanes.iter().fold(tail, |total, &lane| total + lane)
}

/// The normalised row and `1 / sqrt(variance + eps)`.
#[inline(always)]
fn normalise<T: Real>(row: &[T], out: &mut [T]) -> T {
    let mu = mean(row);
    for (o, &x) in out.iter_mut().zip(row) {
        *o = x - mu;
    }
    let variance = dot(out, Some(out)) / T::of(row.len() as f64);
    let inverse = T::of(1.0) / (variance + T::of(LAYER_NORM_EPS)).sqrt();
    for o in out.iter_mut() {
        *o = *o * inverse;
    }
    inverse
}

/// Dispatches a kernel over the dtype of `storage`.
macro_rules! by_dtype {
    ($op:expr, $storage:expr, $kernel:ident($($arg:expr),*)) => {
        match $storage {
            CpuStorage::F32(_) => $kernel::<f32>($($arg),*),
            CpuStorage::F64(_) => $kernel::<f64>($($arg),*),
            _ => Err(op_error($op, "expects f32 or f64")),
        }
    };
}

// After `by_dtype!`, which they use.
mod attention;
mod linear;
mod modulate;

pub use linear::Activation;

/// Layer norm over the last dimension without affine parameters, `eps = 1e-6`.
#[derive(Debug, Clone, Copy)]
struct LayerNorm;

fn layer_norm_forward<T: Real>(
    storage: &CpuStorage,
    layout: &Layout,
) -> candle_core::Result<(CpuStorage, Shape)> {
    let x = values::<T>("layer-norm", storage, layout)?;
    let width = layout.dims().last().copied().unwrap_or(1);
    let out = map_rows(
        width,
        [x],
        #[inline(always)]
        |rows, o| {
            normalise(rows[0], o);
        },
    );
    Ok((T::storage(out), layout.shape().clone()))
}

impl CustomOp1 for LayerNorm {
    fn name(&self) -> &'static str {
        "layer-norm"
    }

    fn cpu_fwd(
        &self,
        storage: &CpuStorage,
        layout: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        by_dtype!(self.name(), storage, layer_norm_forward(storage, layout))
    }

    fn bwd(&self, x: &Tensor, _: &Tensor, grad: &Tensor) -> candle_core::Result<Option<Tensor>> {
        Ok(Some(x.apply_op2_no_bwd(&grad.contiguous()?, &LayerNormBackward)?))
    }
}

/// The gradient of [`LayerNorm`] with respect to its input: with `y = (x - mean) / s`,
/// `dx = (g - mean(g) - y mean(g y)) / s`.
#[derive(Debug, Clone, Copy)]
struct LayerNormBackward;

fn layer_norm_backward<T: Real>(
    x_storage: &CpuStorage,
    x_layout: &Layout,
    g_storage: &CpuStorage,
    g_layout: &Layout,
) -> candle_core::Result<(CpuStorage, Shape)> {
    let x = values::<T>("layer-norm-backward", x_storage, x_layout)?;
    let g = values::<T>("layer-norm-backward", g_storage, g_layout)?;
    if x.len() != g.len() {
        return Err(op_error("layer-norm-backward", "a gradient of the input's shape"));
    }
    let width = x_layout.dims().last().copied().unwrap_or(1);
    let out = map_rows(
        width,
        [x, g],
        #[inline(always)]
        |rows, o| {
            let (x, g) = (rows[0], rows[1]);
            let inverse = normalise(x, o); // o = y
            let n = T::of(width as f64);
            let g_mean = mean(g);
            let gy_mean = dot(o, Some(g)) / n;
            for (o, &g) in o.iter_mut().zip(g) {
                *o = (g - g_mean - *o * gy_mean) * inverse;
            }
        },
    );
    Ok((T::storage(out), x_layout.shape().clone()))
}

impl CustomOp2 for LayerNormBackward {
    fn name(&self) -> &'static str {
        "layer-norm-backward"
    }

    fn cpu_fwd(
        &self,
        x_storage: &CpuStorage,
        x_layout: &Layout,
        g_storage: &CpuStorage,
        g_layout: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        by_dtype!(
            self.name(),
            x_storage,
            layer_norm_backward(x_storage, x_layout, g_storage, g_layout)
        )
    }
}

/// Whether the fused operations apply to `x` (the CPU, f32 or f64).
pub fn applies(x: &Tensor) -> bool {
    x.device().is_cpu() && matches!(x.dtype(), candle_core::DType::F32 | candle_core::DType::F64)
}

/// Layer norm over the last dimension, fused, with its backward pass (CPU, f32/f64 only).
pub fn layer_norm(x: &Tensor) -> candle_core::Result<Tensor> {
    x.contiguous()?.apply_op1(LayerNorm)
}

/// A linear layer, `act(x W + bias)` over the last dimension of `x` with `W` stored
/// `[input, output]`, fused, with its backward pass (CPU, f32/f64 only): one graph node where
/// the composite has four or five.
///
/// # Shapes
/// - `x`: `[..., input]`; `weight`: `[input, output]`; `bias`: `[output]`; returns
///   `[..., output]`
pub fn linear(
    x: &Tensor,
    weight: &Tensor,
    bias: &Tensor,
    activation: Activation,
) -> candle_core::Result<Tensor> {
    let input = weight.dim(0)?;
    let product = match activation {
        Activation::Silu => {
            let x_rows = x.detach().contiguous()?.reshape((rows_of("linear", x.dims())?, input))?;
            Some(linear::product(&x_rows, &weight.detach(), false, false)?)
        }
        Activation::Identity => None,
    };
    let op = linear::Linear { product, activation };
    x.contiguous()?.apply_op3(&weight.contiguous()?, &bias.contiguous()?, op)
}

/// AdaLN, `norm(x) * (1 + scale) + shift` with `(shift, scale)` the halves of each sequence's
/// modulation, fused, with its backward pass (CPU, f32/f64 only).
///
/// # Shapes
/// - `x`: `[N, T, latent]`; `modulation`: `[N, 2 latent]`; returns `x`'s shape
pub fn modulate(x: &Tensor, modulation: &Tensor) -> candle_core::Result<Tensor> {
    x.contiguous()?.apply_op2(&modulation.contiguous()?, modulate::Modulate)
}

/// Multi-head attention after the projections (`softmax(Q K^T / sqrt(head))` over the keys
/// whose mask is 1, times the values; heads merged), fused, with its backward pass (CPU,
/// f32/f64 only). The mask gets no gradient.
///
/// # Shapes
/// - `queries`: `[N, Tq, latent]`; `keys_values`: `[N, Tk, 2 latent]` (keys, then values)
/// - `mask`: `[N, Tk]`, 1 = attend, 0 = ignore; returns `[N, Tq, latent]`
pub fn attention(
    queries: &Tensor,
    keys_values: &Tensor,
    mask: &Tensor,
    heads: usize,
) -> candle_core::Result<Tensor> {
    let mask = mask.to_dtype(queries.dtype())?.contiguous()?;
    queries.contiguous()?.apply_op3(
        &keys_values.contiguous()?,
        &mask,
        attention::Attention { heads },
    )
}
