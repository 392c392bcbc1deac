//! The CUDA side of the row-wise fused operations, layer norm, AdaLN's modulation and the
//! attention's masked softmax, forward and backward (`rows.cu`, compiled at run time by NVRTC):
//! one kernel launch per pass (two for the modulation's backward) where the composite launches
//! about five to seven forward and twice as many backward, each with an allocation.
//!
//! Why `unsafe`: launching a kernel is, since the compiler cannot check its arguments against the
//! kernel's signature; seven launches, each checked by hand (their `SAFETY` comments).
#![allow(unsafe_code)]

use candle_core::cuda_backend::WrapErr;
use candle_core::cuda_backend::cudarc::driver::{LaunchConfig, PushKernelArg};
use candle_core::{CudaStorage, Layout, Shape};
use dex2hoi_repr::cuda_kernel::{KernelSource, contiguous_f32, kernel_count};

use crate::kernel::LAYER_NORM_EPS;

static SOURCE: KernelSource = KernelSource::new("dex2hoi_rows", "rows.cu", include_str!("rows.cu"));
/// The operations as errors name them.
const ROWS: &str = "dex2hoi's row operations";

/// A row pass's launch: one block per row, a multiple of 32 threads up to 256, no more than the
/// row needs.
fn per_row(rows: usize, width: usize) -> candle_core::Result<LaunchConfig> {
    let threads = width.div_ceil(32).clamp(1, 8) as u32 * 32;
    Ok(LaunchConfig {
        grid_dim: (count(rows, "rows")?, 1, 1),
        block_dim: (threads, 1, 1),
        shared_mem_bytes: 0,
    })
}

/// `[rows, width]` of a tensor normalised over its last dimension.
fn rows_and_width(layout: &Layout) -> (usize, usize) {
    let width = layout.dims().last().copied().unwrap_or(1);
    (if width == 0 { 0 } else { layout.shape().elem_count() / width }, width)
}

/// Layer norm's forward pass ([`super::LayerNorm`]).
pub(super) fn layer_norm_forward(
    x: &CudaStorage,
    layout: &Layout,
) -> candle_core::Result<(CudaStorage, Shape)> {
    let device = &x.device;
    let (rows, width) = rows_and_width(layout);
    let x_view = contiguous_f32(ROWS, (x, layout), rows * width, "layer norm's input")?;
    let out = device.alloc_zeros::<f32>(rows * width)?;
    if rows > 0 {
        let function = SOURCE.function(device, "layer_norm_forward_f32")?;
        let (width_arg, eps) = (count(width, "features")?, LAYER_NORM_EPS as f32);
        let mut builder = function.builder();
        builder.arg(&x_view).arg(&width_arg).arg(&eps).arg(&out);
        // SAFETY: the arguments are those of `layer_norm_forward_f32` in `rows.cu`, in order;
        // `x_view` and `out` hold `rows * width` values, one block per row.
        unsafe { builder.launch(per_row(rows, width)?) }.w()?;
    }
    Ok((CudaStorage::wrap_cuda_slice(out, device.clone()), layout.shape().clone()))
}

/// Layer norm's backward pass ([`super::LayerNormBackward`]): the input's gradient.
pub(super) fn layer_norm_backward(
    (x, x_layout): (&CudaStorage, &Layout),
    (grad, grad_layout): (&CudaStorage, &Layout),
) -> candle_core::Result<(CudaStorage, Shape)> {
    let device = &x.device;
    let (rows, width) = rows_and_width(x_layout);
    let x_view = contiguous_f32(ROWS, (x, x_layout), rows * width, "layer norm's input")?;
    let grad_view =
        contiguous_f32(ROWS, (grad, grad_layout), rows * width, "layer norm's output gradient")?;
    let out = device.alloc_zeros::<f32>(rows * width)?;
    if rows > 0 {
        let function = SOURCE.function(device, "layer_norm_backward_f32")?;
        let (width_arg, eps) = (count(width, "features")?, LAYER_NORM_EPS as f32);
        let mut builder = function.builder();
        builder.arg(&x_view).arg(&grad_view).arg(&width_arg).arg(&eps).arg(&out);
        // SAFETY: the arguments are those of `layer_norm_backward_f32` in `rows.cu`, in order;
        // the input, gradient and output hold `rows * width` values, one block per row.
        unsafe { builder.launch(per_row(rows, width)?) }.w()?;
    }
    Ok((CudaStorage::wrap_cuda_slice(out, device.clone()), x_layout.shape().clone()))
}

/// AdaLN's forward pass ([`super::modulate::Modulate`]), `sizes` being
/// `(sequences, frames, latent)`.
pub(super) fn modulate_forward(
    (x, x_layout): (&CudaStorage, &Layout),
    (modulation, modulation_layout): (&CudaStorage, &Layout),
    (sequences, frames, latent): (usize, usize, usize),
) -> candle_core::Result<(CudaStorage, Shape)> {
    let device = &x.device;
    let rows = sequences * frames;
    let x_view = contiguous_f32(ROWS, (x, x_layout), rows * latent, "the modulated tokens")?;
    let modulation_view = contiguous_f32(
        ROWS,
        (modulation, modulation_layout),
        sequences * 2 * latent,
        "the modulation",
    )?;
    let out = device.alloc_zeros::<f32>(rows * latent)?;
    if rows > 0 && latent > 0 {
        let function = SOURCE.function(device, "modulate_forward_f32")?;
        let (frames_arg, width_arg) = (count(frames, "frames")?, count(latent, "features")?);
        let eps = LAYER_NORM_EPS as f32;
        let mut builder = function.builder();
        builder
            .arg(&x_view)
            .arg(&modulation_view)
            .arg(&frames_arg)
            .arg(&width_arg)
            .arg(&eps)
            .arg(&out);
        // SAFETY: the arguments are those of `modulate_forward_f32` in `rows.cu`, in order; the
        // tokens and output hold `sequences * frames` rows of `latent`, the modulation one row of
        // `2 latent` per sequence, and row `r` reads sequence `r / frames`.
        unsafe { builder.launch(per_row(rows, latent)?) }.w()?;
    }
    Ok((CudaStorage::wrap_cuda_slice(out, device.clone()), x_layout.shape().clone()))
}

/// AdaLN's backward pass ([`super::modulate::ModulateBackward`]): the tokens' gradient, then
/// the modulation's, flattened one after the other.
pub(super) fn modulate_backward(
    (x, x_layout): (&CudaStorage, &Layout),
    (modulation, modulation_layout): (&CudaStorage, &Layout),
    (grad, grad_layout): (&CudaStorage, &Layout),
    (sequences, frames, latent): (usize, usize, usize),
) -> candle_core::Result<(CudaStorage, Shape)> {
    let device = &x.device;
    let rows = sequences * frames;
    let tokens = rows * latent;
    let x_view = contiguous_f32(ROWS, (x, x_layout), tokens, "the modulated tokens")?;
    let modulation_view = contiguous_f32(
        ROWS,
        (modulation, modulation_layout),
        sequences * 2 * latent,
        "the modulation",
    )?;
    let grad_view = contiguous_f32(ROWS, (grad, grad_layout), tokens, "the output gradient")?;
    let mut out = device.alloc_zeros::<f32>(tokens + sequences * 2 * latent)?;
    if rows > 0 && latent > 0 {
        let stats = device.alloc_zeros::<f32>(rows * 2)?;
        let (frames_arg, width_arg) = (count(frames, "frames")?, count(latent, "features")?);
        let sequences_arg = count(sequences, "sequences")?;
        let eps = LAYER_NORM_EPS as f32;
        let (mut grad_x, mut grad_modulation) = out.split_at_mut(tokens);
        let function = SOURCE.function(device, "modulate_backward_rows_f32")?;
        let mut builder = function.builder();
        builder
            .arg(&x_view)
            .arg(&modulation_view)
            .arg(&grad_view)
            .arg(&frames_arg)
            .arg(&width_arg)
            .arg(&eps)
            .arg(&mut grad_x)
            .arg(&stats);
        // SAFETY: the arguments are those of `modulate_backward_rows_f32` in `rows.cu`, in order;
        // the tokens, gradient and `grad_x` hold `sequences * frames` rows of `latent`, the
        // modulation one row of `2 latent` per sequence, `stats` two values per row.
        unsafe { builder.launch(per_row(rows, latent)?) }.w()?;
        let function = SOURCE.function(device, "modulate_backward_columns_f32")?;
        let mut builder = function.builder();
        builder
            .arg(&x_view)
            .arg(&grad_view)
            .arg(&stats)
            .arg(&sequences_arg)
            .arg(&frames_arg)
            .arg(&width_arg)
            .arg(&mut grad_modulation);
        let threads = 256u32;
        let config = LaunchConfig {
            grid_dim: (count(sequences * latent, "columns")?.div_ceil(threads), 1, 1),
            block_dim: (threads, 1, 1),
            shared_mem_bytes: 0,
        };
        // SAFETY: the arguments are those of `modulate_backward_columns_f32` in `rows.cu`, in
        // order; the tokens and gradient hold `sequences * frames` rows of `latent`, `stats` the
        // rows' statistics written by the launch before on the same stream, `grad_modulation`
        // `sequences * 2 latent` values; threads past `sequences * latent` return at once.
        unsafe { builder.launch(config) }.w()?;
    }
    let shape = Shape::from(tokens + sequences * 2 * latent);
    Ok((CudaStorage::wrap_cuda_slice(out, device.clone()), shape))
}

/// The masked softmax's forward pass ([`super::softmax::MaskedSoftmax`]), `sizes` being
/// `(sequences, rows per sequence, keys)`.
pub(super) fn masked_softmax_forward(
    (scores, scores_layout): (&CudaStorage, &Layout),
    (mask, mask_layout): (&CudaStorage, &Layout),
    (sequences, rows_per_sequence, keys): (usize, usize, usize),
) -> candle_core::Result<(CudaStorage, Shape)> {
    let device = &scores.device;
    let rows = sequences * rows_per_sequence;
    let scores_view =
        contiguous_f32(ROWS, (scores, scores_layout), rows * keys, "the attention scores")?;
    let mask_view = contiguous_f32(ROWS, (mask, mask_layout), sequences * keys, "the key mask")?;
    let out = device.alloc_zeros::<f32>(rows * keys)?;
    if rows > 0 && keys > 0 {
        let function = SOURCE.function(device, "masked_softmax_forward_f32")?;
        let (per_sequence, width) = (count(rows_per_sequence, "rows")?, count(keys, "keys")?);
        let mut builder = function.builder();
        builder.arg(&scores_view).arg(&mask_view).arg(&per_sequence).arg(&width).arg(&out);
        // SAFETY: the arguments are those of `masked_softmax_forward_f32` in `rows.cu`, in
        // order; the scores and output hold `sequences * rows_per_sequence` rows of `keys`, the
        // mask one row of `keys` per sequence, and row `r` reads sequence `r / rows_per_sequence`.
        unsafe { builder.launch(per_row(rows, keys)?) }.w()?;
    }
    Ok((CudaStorage::wrap_cuda_slice(out, device.clone()), scores_layout.shape().clone()))
}

/// A softmax's backward pass from its output ([`super::softmax::SoftmaxBackward`]).
pub(super) fn softmax_backward(
    (y, y_layout): (&CudaStorage, &Layout),
    (grad, grad_layout): (&CudaStorage, &Layout),
) -> candle_core::Result<(CudaStorage, Shape)> {
    let device = &y.device;
    let (rows, width) = rows_and_width(y_layout);
    let y_view = contiguous_f32(ROWS, (y, y_layout), rows * width, "the probabilities")?;
    let grad_view =
        contiguous_f32(ROWS, (grad, grad_layout), rows * width, "the probabilities' gradient")?;
    let out = device.alloc_zeros::<f32>(rows * width)?;
    if rows > 0 {
        let function = SOURCE.function(device, "softmax_backward_f32")?;
        let width_arg = count(width, "keys")?;
        let mut builder = function.builder();
        builder.arg(&y_view).arg(&grad_view).arg(&width_arg).arg(&out);
        // SAFETY: the arguments are those of `softmax_backward_f32` in `rows.cu`, in order; the
        // probabilities, gradient and output hold `rows * width` values, one block per row.
        unsafe { builder.launch(per_row(rows, width)?) }.w()?;
    }
    Ok((CudaStorage::wrap_cuda_slice(out, device.clone()), y_layout.shape().clone()))
}

fn count(n: usize, what: &str) -> candle_core::Result<u32> {
    kernel_count(ROWS, n, what)
}
