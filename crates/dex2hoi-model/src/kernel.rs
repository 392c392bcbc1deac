//! The shared pieces of the hand-written CPU operations, those with a backward pass
//! ([`crate::differentiable`]) and the forward-only ones of the inference path
//! ([`crate::fused`]): the float types they run in ([`Real`]), the SIMD dispatch ([`simd`]) and
//! the row-parallel map they run under, reductions in independent partial sums, a row's layer
//! normalisation and its epsilon ([`LAYER_NORM_EPS`]), a vectorisable `exp`, reading a tensor's
//! values, and their errors.

use std::ops::{Add, Div, Mul, Sub};

use candle_core::{CpuStorage, Layout};
use rayon::prelude::*;

/// The layer norm's epsilon, added to the variance (every implementation: composite, fused
/// for inference, fused with a backward pass).
pub const LAYER_NORM_EPS: f64 = 1e-6;

/// Rows per rayon task of the row-wise operations ([`crate::differentiable`] and
/// [`crate::fused`]): enough work per task to hide the scheduling cost (a few microseconds),
/// enough tasks to keep both cores busy on a 240-row batch.
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
    /// `e^self`, vectorisable in f32 (about 1 ulp, [`exp`]); libm's in f64.
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

real!(f32, F32, exp);
real!(f64, F64, f64::exp);

/// `e^x` to about 1 ulp for `x` in `[-87, 88]` (clamped outside), in plain arithmetic so that
/// loops over it vectorise (a call to libm's `expf` does not): `x = n ln 2 + r` with
/// `|r| <= ln 2 / 2`, a degree-7 expansion of `e^r` (Cephes' `expf` coefficients), times `2^n`
/// built in the exponent bits.
#[inline(always)]
pub(crate) fn exp(x: f32) -> f32 {
    const LOG2_E: f32 = std::f32::consts::LOG2_E;
    // ln 2 split in a part exact in f32 and the rest (Cody and Waite).
    const LN2_HIGH: f32 = 0.693_359_4;
    const LN2_LOW: f32 = -2.121_944_4e-4;
    // Adding and removing 1.5 * 2^23 rounds to the nearest integer in plain arithmetic
    // (`round` is a libm call on baseline x86-64, which would stop the vectorisation).
    const ROUNDING: f32 = 12_582_912.0;
    let x = x.clamp(-87.0, 88.0);
    let n = (x * LOG2_E + ROUNDING) - ROUNDING;
    let r = x - n * LN2_HIGH - n * LN2_LOW;
    let p = 1.987_569_2e-4_f32;
    let p = p * r + 1.398_199_9e-3;
    let p = p * r + 8.333_452e-3;
    let p = p * r + 4.166_579_6e-2;
    let p = p * r + 0.166_666_65;
    let p = p * r + 0.5;
    let e_r = p * r * r + r + 1.0;
    e_r * f32::from_bits(((n as i32 + 127) as u32) << 23)
}

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
pub(crate) fn rows_of(op: &str, dims: &[usize]) -> candle_core::Result<usize> {
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
pub(crate) fn map_rows<T: Real, const N: usize>(
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
pub(crate) fn mean<T: Real>(row: &[T]) -> T {
    dot(row, None) / T::of(row.len() as f64)
}

/// Independent partial sums of [`dot`]: a plain sum is one chain of dependent additions, which
/// does not vectorise.
const SUM_LANES: usize = 8;

/// `sum_k a_k b_k`, or `sum_k a_k` without `b`, in [`SUM_LANES`] partial sums (vectorised under
/// [`simd`]).
#[inline(always)]
pub(crate) fn dot<T: Real>(a: &[T], b: Option<&[T]>) -> T {
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
pub(crate) fn normalise<T: Real>(row: &[T], out: &mut [T]) -> T {
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

/// Dispatches a kernel over the dtype of `storage` (where `CpuStorage` and [`op_error`] are in
/// scope).
macro_rules! by_dtype {
    ($op:expr, $storage:expr, $kernel:ident($($arg:expr),*)) => {
        match $storage {
            CpuStorage::F32(_) => $kernel::<f32>($($arg),*),
            CpuStorage::F64(_) => $kernel::<f64>($($arg),*),
            _ => Err(op_error($op, "expects f32 or f64")),
        }
    };
}
pub(crate) use by_dtype;

#[cfg(test)]
mod tests {
    /// The polynomial `exp` against f64's over its whole range and the clamped ends.
    #[test]
    fn exp_is_accurate_to_a_few_ulp() {
        let mut worst = 0f64;
        for k in 0..=1_000_000 {
            let x = -87.0 + 175.0 * k as f32 / 1e6;
            let exact = (x as f64).exp();
            worst = worst.max(((super::exp(x) as f64) - exact).abs() / exact);
        }
        assert!(worst < 3e-7, "relative error {worst}");
        assert!(super::exp(-1e4) > 0.0 && super::exp(-1e4) < 1e-37);
        assert!(super::exp(1e4).is_finite());
        assert_eq!(super::exp(0.0), 1.0);
    }
}
