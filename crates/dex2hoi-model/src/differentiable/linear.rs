//! A linear layer, `act(x W + bias)` with `act` the identity or SiLU, as one operation with its
//! backward pass.
//! Composed, a linear layer is four graph nodes over the whole token tensor (two reshapes, the
//! product, the broadcast add; a fifth with SiLU), and candle's backward pass allocates a
//! zeroed gradient for each, adds into it, and reduces the bias gradient in a single-threaded
//! strided sum.

use candle_core::{CpuStorage, CustomOp1, CustomOp2, CustomOp3, Layout, Shape, Storage, Tensor};
use rayon::prelude::*;

use crate::kernel::{ROWS_PER_TASK, Real, by_dtype, map_rows, op_error, rows_of, simd, values};
use crate::matmul::{Strided, Threads, product_into};

/// The activation after a bias.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Activation {
    /// `y + bias`.
    Identity,
    /// `SiLU(y + bias)`, `z / (1 + e^-z)`.
    Silu,
}

#[inline(always)]
fn sigmoid<T: Real>(z: T) -> T {
    T::of(1.0) / (T::of(1.0) + (T::of(0.0) - z).fast_exp())
}

/// `act(y + bias)` over the last dimension of `y` (the product of [`Linear`]).
fn forward<T: Real>(
    activation: Activation,
    (y, y_layout): (&CpuStorage, &Layout),
    (bias, bias_layout): (&CpuStorage, &Layout),
) -> candle_core::Result<(CpuStorage, Shape)> {
    let name = "linear";
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

/// The gradient with respect to `z = y + bias` of `act(z)`, given the output's.
fn grad_before_activation(
    activation: Activation,
    y: &Tensor,
    bias: &Tensor,
    grad: &Tensor,
) -> candle_core::Result<Tensor> {
    let grad = grad.contiguous()?;
    match activation {
        Activation::Identity => Ok(grad),
        Activation::Silu => y.contiguous()?.apply_op3_no_bwd(bias, &grad, &SiluBackward),
    }
}

/// `op(a) @ op(b)`, `op` the identity or the transpose, for 2-D tensors: the linear layer's
/// forward product and the two of its backward pass, through gemm on the pool's threads
/// ([`product_into`]). Not `Tensor::matmul`: candle asks for its thread count on every
/// product, which on Linux reads and parses `/proc/cpuinfo` each time (2.4% of a `small`
/// training step in perf), and zero-fills its output first.
#[derive(Debug, Clone, Copy)]
struct Product {
    transpose_lhs: bool,
    transpose_rhs: bool,
}

fn product_op<T: Real>(
    op: Product,
    (a, a_layout): (&CpuStorage, &Layout),
    (b, b_layout): (&CpuStorage, &Layout),
) -> candle_core::Result<(CpuStorage, Shape)> {
    let name = "linear-product";
    let view = |storage, layout: &Layout, transpose| -> candle_core::Result<Strided<'_, T>> {
        let (rows, columns) = layout.shape().dims2()?;
        let matrix = Strided::row_major(values::<T>(name, storage, layout)?, rows, columns);
        Ok(if transpose { matrix.transposed() } else { matrix })
    };
    let (lhs, rhs) = (view(a, a_layout, op.transpose_lhs)?, view(b, b_layout, op.transpose_rhs)?);
    if lhs.columns != rhs.rows {
        return Err(op_error(
            name,
            format!("[{}, {}] @ [{}, {}]", lhs.rows, lhs.columns, rhs.rows, rhs.columns),
        ));
    }
    let size = lhs
        .rows
        .checked_mul(rhs.columns)
        .ok_or_else(|| op_error(name, "a size that fits in usize"))?;
    let mut out = vec![T::default(); size];
    product_into(&mut out, rhs.columns, (lhs, rhs), T::of(1.0), false, Threads::Pool);
    Ok((T::storage(out), Shape::from((lhs.rows, rhs.columns))))
}

impl CustomOp2 for Product {
    fn name(&self) -> &'static str {
        "linear-product"
    }

    fn cpu_fwd(
        &self,
        a: &CpuStorage,
        a_layout: &Layout,
        b: &CpuStorage,
        b_layout: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        by_dtype!(self.name(), a, product_op(*self, (a, a_layout), (b, b_layout)))
    }
}

/// `op(a) @ op(b)` (see [`Product`]); no backward pass.
///
/// # Shapes
/// - `a`: `[m, k]` (`[k, m]` transposed); `b`: `[k, n]` (`[n, k]` transposed); returns `[m, n]`
pub(super) fn product(
    a: &Tensor,
    b: &Tensor,
    transpose_lhs: bool,
    transpose_rhs: bool,
) -> candle_core::Result<Tensor> {
    a.contiguous()?.apply_op2_no_bwd(&b.contiguous()?, &Product { transpose_lhs, transpose_rhs })
}

/// A linear layer `act(x W + bias)` over the last dimension of `x`, `W` stored
/// `[input, output]`. With SiLU the product is computed before the operation ([`product`], on
/// tensors detached from the graph) and handed to it: it is also the input of the SiLU's
/// backward pass. Without an activation the operation computes `x W + bias` itself, the bias
/// written first and the product added to it by gemm, with no separate pass over the output.
#[derive(Debug, Clone)]
pub(super) struct Linear {
    /// `x W`, `[rows, output]` (rows: `x`'s leading dimensions flattened), with SiLU only.
    pub(super) product: Option<Tensor>,
    pub(super) activation: Activation,
}

/// `x W + bias` for `x` `[rows, input]` and `W` `[input, output]`: each output row starts as
/// the bias and gemm adds the product to it.
fn biased_product<T: Real>(
    (x, x_layout): (&CpuStorage, &Layout),
    (w, w_layout): (&CpuStorage, &Layout),
    (bias, bias_layout): (&CpuStorage, &Layout),
    rows: usize,
) -> candle_core::Result<(CpuStorage, Shape)> {
    let name = "linear";
    let (x, w, bias) = (
        values::<T>(name, x, x_layout)?,
        values::<T>(name, w, w_layout)?,
        values::<T>(name, bias, bias_layout)?,
    );
    let (input, output) = w_layout.shape().dims2()?;
    if bias.len() != output {
        return Err(op_error(name, format!("a bias of {output}, got {}", bias.len())));
    }
    let size =
        rows.checked_mul(output).ok_or_else(|| op_error(name, "a size that fits in usize"))?;
    let mut out = Vec::with_capacity(size);
    for _ in 0..rows {
        out.extend_from_slice(bias);
    }
    let views = (Strided::row_major(x, rows, input), Strided::row_major(w, input, output));
    product_into(&mut out, output, views, T::of(1.0), true, Threads::Pool);
    Ok((T::storage(out), Shape::from((rows, output))))
}

impl CustomOp3 for Linear {
    fn name(&self) -> &'static str {
        "linear"
    }

    fn cpu_fwd(
        &self,
        x: &CpuStorage,
        x_layout: &Layout,
        w: &CpuStorage,
        w_layout: &Layout,
        bias: &CpuStorage,
        bias_layout: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        let (input, output) = w_layout.shape().dims2()?;
        let x_dims = x_layout.dims();
        let rows = rows_of(self.name(), x_dims)?;
        let product_dims = self.product.as_ref().map(Tensor::dims);
        if x_dims.last() != Some(&input) || product_dims.is_some_and(|d| d != [rows, output]) {
            return Err(op_error(
                self.name(),
                format!(
                    "x [..., {input}] and its product [{rows}, {output}]; got {x_dims:?} and {product_dims:?}"
                ),
            ));
        }
        let (out, _) = match &self.product {
            None => by_dtype!(
                self.name(),
                x,
                biased_product((x, x_layout), (w, w_layout), (bias, bias_layout), rows)
            )?,
            Some(product) => {
                let (storage, product_layout) = product.storage_and_layout();
                let Storage::Cpu(product) = &*storage else {
                    return Err(op_error(self.name(), "a product on the CPU"));
                };
                by_dtype!(
                    self.name(),
                    product,
                    forward(self.activation, (product, product_layout), (bias, bias_layout))
                )?
            }
        };
        let mut shape = x_dims.to_vec();
        *shape.last_mut().expect("x has the input dimension") = output;
        Ok((out, Shape::from(shape)))
    }

    fn bwd(
        &self,
        x: &Tensor,
        w: &Tensor,
        bias: &Tensor,
        _: &Tensor,
        grad: &Tensor,
    ) -> candle_core::Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
        let (input, output) = w.dims2()?;
        let rows = rows_of(self.name(), x.dims())?;
        let grad = grad.reshape((rows, output))?;
        let grad_z = match &self.product {
            Some(product) => grad_before_activation(self.activation, product, bias, &grad)?,
            None => grad.contiguous()?,
        };
        let grad_x = product(&grad_z, &w.detach(), false, true)?.reshape(x.shape())?;
        let x = x.detach().contiguous()?.reshape((rows, input))?;
        let grad_w = product(&x, &grad_z, true, false)?;
        let grad_bias = grad_z.apply_op1_no_bwd(&ColumnSums)?;
        Ok((Some(grad_x), Some(grad_w), Some(grad_bias)))
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
struct ColumnSums;

/// Rows per partial sum of [`ColumnSums`].
const ROWS_PER_PARTIAL: usize = 4 * ROWS_PER_TASK;

fn column_sums<T: Real>(x: &[T], width: usize) -> Vec<T> {
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
