//! A linear layer's bias and activation after its product, `act(y + bias)` with `act` the
//! identity or SiLU, as one operation with its backward pass. Composed, it is a broadcast add
//! (and a SiLU) whose backward passes each allocate a zeroed gradient, add into it and reduce
//! the bias gradient in a single-threaded strided sum.

use candle_core::{CpuStorage, CustomOp1, CustomOp2, CustomOp3, Layout, Shape, Tensor};
use rayon::prelude::*;

use super::{ROWS_PER_TASK, Real, map_rows, op_error, simd, values};

/// The activation after a bias.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Activation {
    /// `y + bias`.
    Identity,
    /// `SiLU(y + bias)`, `z / (1 + e^-z)`.
    Silu,
}

/// `act(y + bias)` over the last dimension.
#[derive(Debug, Clone, Copy)]
pub(super) struct BiasActivation(pub(super) Activation);

#[inline(always)]
fn sigmoid<T: Real>(z: T) -> T {
    T::of(1.0) / (T::of(1.0) + (T::of(0.0) - z).fast_exp())
}

fn forward<T: Real>(
    activation: Activation,
    (y, y_layout): (&CpuStorage, &Layout),
    (bias, bias_layout): (&CpuStorage, &Layout),
) -> candle_core::Result<(CpuStorage, Shape)> {
    let name = "bias-activation";
    let y_values = values::<T>(name, y, y_layout)?;
    let bias = values::<T>(name, bias, bias_layout)?;
    let width = y_layout.dims().last().copied().unwrap_or(1);
    if bias.len() != width {
        return Err(op_error(name, format!("a bias of {width}, got {}", bias.len())));
    }
    let out = map_rows(
        width,
        [y_values],
        #[inline(always)]
        |rows, out| {
            for ((o, &y), &b) in out.iter_mut().zip(rows[0]).zip(bias) {
                let z = y + b;
                *o = match activation {
                    Activation::Identity => z,
                    Activation::Silu => z * sigmoid(z),
                };
            }
        },
    );
    Ok((T::storage(out), y_layout.shape().clone()))
}

impl CustomOp2 for BiasActivation {
    fn name(&self) -> &'static str {
        "bias-activation"
    }

    fn cpu_fwd(
        &self,
        y: &CpuStorage,
        y_layout: &Layout,
        bias: &CpuStorage,
        bias_layout: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        by_dtype!(self.name(), y, forward(self.0, (y, y_layout), (bias, bias_layout)))
    }

    fn bwd(
        &self,
        y: &Tensor,
        bias: &Tensor,
        _: &Tensor,
        grad: &Tensor,
    ) -> candle_core::Result<(Option<Tensor>, Option<Tensor>)> {
        let grad = grad.contiguous()?;
        let grad_z = match self.0 {
            Activation::Identity => grad,
            Activation::Silu => y.apply_op3_no_bwd(bias, &grad, &SiluBackward)?,
        };
        let grad_bias = grad_z.apply_op1_no_bwd(&ColumnSums)?;
        Ok((Some(grad_z), Some(grad_bias)))
    }
}

/// The gradient of `SiLU(y + bias)` with respect to `y`: `g s (1 + z (1 - s))` with
/// `z = y + bias`, `s = sigmoid(z)`.
#[derive(Debug, Clone, Copy)]
struct SiluBackward;

fn silu_backward<T: Real>(
    (y, y_layout): (&CpuStorage, &Layout),
    (bias, bias_layout): (&CpuStorage, &Layout),
    (grad, grad_layout): (&CpuStorage, &Layout),
) -> candle_core::Result<(CpuStorage, Shape)> {
    let name = "silu-backward";
    let y_values = values::<T>(name, y, y_layout)?;
    let bias = values::<T>(name, bias, bias_layout)?;
    let grad = values::<T>(name, grad, grad_layout)?;
    let width = y_layout.dims().last().copied().unwrap_or(1);
    if grad.len() != y_values.len() || bias.len() != width {
        return Err(op_error(name, "a gradient of the input's shape and a bias of its width"));
    }
    let out = map_rows(
        width,
        [y_values, grad],
        #[inline(always)]
        |rows, out| {
            for (((o, &y), &g), &b) in out.iter_mut().zip(rows[0]).zip(rows[1]).zip(bias) {
                let z = y + b;
                let s = sigmoid(z);
                *o = g * s * (T::of(1.0) + z * (T::of(1.0) - s));
            }
        },
    );
    Ok((T::storage(out), y_layout.shape().clone()))
}

impl CustomOp3 for SiluBackward {
    fn name(&self) -> &'static str {
        "silu-backward"
    }

    fn cpu_fwd(
        &self,
        y: &CpuStorage,
        y_layout: &Layout,
        bias: &CpuStorage,
        bias_layout: &Layout,
        grad: &CpuStorage,
        grad_layout: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        by_dtype!(
            self.name(),
            y,
            silu_backward((y, y_layout), (bias, bias_layout), (grad, grad_layout))
        )
    }
}

/// The sums over every row of a `[..., features]` tensor, `[features]`: partial sums of fixed
/// blocks of rows in parallel, added in block order, so the result does not depend on the
/// thread count or scheduling (the bit-exact resume of training relies on that).
#[derive(Debug, Clone, Copy)]
pub(super) struct ColumnSums;

/// Rows per partial sum of [`ColumnSums`].
const ROWS_PER_PARTIAL: usize = 4 * ROWS_PER_TASK;

pub(super) fn column_sums<T: Real>(x: &[T], width: usize) -> Vec<T> {
    if width == 0 {
        return Vec::new();
    }
    let partials: Vec<Vec<T>> = x
        .par_chunks(width * ROWS_PER_PARTIAL)
        .map(|block| {
            simd(
                #[inline(always)]
                || {
                    let mut sums = vec![T::default(); width];
                    for row in block.chunks_exact(width) {
                        for (s, &v) in sums.iter_mut().zip(row) {
                            *s = *s + v;
                        }
                    }
                    sums
                },
            )
        })
        .collect();
    let mut total = vec![T::default(); width];
    for partial in partials {
        for (t, p) in total.iter_mut().zip(partial) {
            *t = *t + p;
        }
    }
    total
}

fn column_sums_op<T: Real>(
    storage: &CpuStorage,
    layout: &Layout,
) -> candle_core::Result<(CpuStorage, Shape)> {
    let x = values::<T>("column-sums", storage, layout)?;
    let width = layout.dims().last().copied().unwrap_or(1);
    Ok((T::storage(column_sums(x, width)), Shape::from(width)))
}

impl CustomOp1 for ColumnSums {
    fn name(&self) -> &'static str {
        "column-sums"
    }

    fn cpu_fwd(
        &self,
        storage: &CpuStorage,
        layout: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        by_dtype!(self.name(), storage, column_sums_op(storage, layout))
    }
}
