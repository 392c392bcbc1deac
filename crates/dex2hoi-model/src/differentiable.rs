//! Fused CPU operations with hand-written backward passes, for training: layer norm, a linear
//! layer with its bias and activation, AdaLN's modulation and multi-head attention (whose
//! softmax is inside it). Composed from candle operations, each is several graph nodes, each
//! a pass over memory with a fresh allocation forward and, in candle's backward pass, a
//! zero-filled gradient added into; fused, one node, row-parallel.
//!
//! Like the FK's custom operations they run on the CPU in f32 and f64 (the finite-difference
//! gradient checks run in f64). The row-wise ones, layer norm and the modulation, also run on
//! a GPU in f32 (`rows.cu`, the CUDA build); [`crate::layers`] uses the composite operations on
//! any other device or dtype. Each is tested equal to its composite (1e-10 in f64) with every gradient
//! checked by finite differences (`tests/differentiable.rs`).

use candle_core::{CpuStorage, CustomOp1, CustomOp2, DType, Layout, Shape, Tensor};

use crate::kernel::{Real, by_dtype, dot, map_rows, mean, normalise, op_error, rows_of, values};

mod attention;
mod linear;
mod modulate;
#[cfg(feature = "cuda")]
mod rows_cuda;
mod softmax;

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

    #[cfg(feature = "cuda")]
    fn cuda_fwd(
        &self,
        storage: &candle_core::CudaStorage,
        layout: &Layout,
    ) -> candle_core::Result<(candle_core::CudaStorage, Shape)> {
        rows_cuda::layer_norm_forward(storage, layout)
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

    #[cfg(feature = "cuda")]
    fn cuda_fwd(
        &self,
        x_storage: &candle_core::CudaStorage,
        x_layout: &Layout,
        g_storage: &candle_core::CudaStorage,
        g_layout: &Layout,
    ) -> candle_core::Result<(candle_core::CudaStorage, Shape)> {
        rows_cuda::layer_norm_backward((x_storage, x_layout), (g_storage, g_layout))
    }
}

/// Whether the fused operations apply to `x` (the CPU, f32 or f64).
pub fn applies(x: &Tensor) -> bool {
    x.device().is_cpu() && matches!(x.dtype(), DType::F32 | DType::F64)
}

/// Whether the row-wise fused operations, [`layer_norm`], [`modulate`] and [`masked_softmax`],
/// apply to `x`: where [`applies`] says, and on a GPU in f32 in the CUDA build.
pub fn applies_per_row(x: &Tensor) -> bool {
    applies(x) || (cfg!(feature = "cuda") && x.device().is_cuda() && x.dtype() == DType::F32)
}

/// Layer norm over the last dimension, fused, with its backward pass (CPU, f32/f64; GPU, f32).
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
/// modulation, fused, with its backward pass (CPU, f32/f64; GPU, f32).
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

/// The softmax over the last dimension of attention scores after adding `(mask - 1) 1e9`, the
/// masked keys' bias, fused, with its backward pass (CPU, f32/f64; GPU, f32): the composite
/// attention's on a GPU. The mask gets no gradient.
///
/// # Shapes
/// - `scores`: `[N, ..., keys]`; `mask`: `[N, keys]`, 1 = attend, 0 = ignore; returns `scores`'
///   shape
pub fn masked_softmax(scores: &Tensor, mask: &Tensor) -> candle_core::Result<Tensor> {
    let mask = mask.to_dtype(scores.dtype())?.contiguous()?;
    scores.contiguous()?.apply_op2(&mask, softmax::MaskedSoftmax)
}
