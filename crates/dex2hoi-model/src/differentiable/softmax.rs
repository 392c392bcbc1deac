//! The softmax of attention scores over the keys a mask keeps, as one operation with its
//! backward pass: the composite attention's on a GPU (`rows.cu`), where composed it is the
//! mask's bias added, then a maximum, a subtraction, an exponential, a sum and a division, each
//! a kernel and an allocation, and about twice as many backward. The CPU's attention has its
//! softmax inside ([`super::attention`]); the CPU side here is the reference the GPU's is tested
//! against.

use candle_core::{CpuStorage, CustomOp2, Layout, Shape, Tensor};
use rayon::prelude::*;

use crate::kernel::{Real, by_dtype, dot, op_error, values};

/// The bias of a masked key, as the composite attention adds it (`(mask - 1) 1e9`).
const MASKED: f64 = 1e9;

/// `softmax(scores + (mask - 1) 1e9)` over the last dimension, each row with the mask row of
/// its sequence.
#[derive(Debug, Clone, Copy)]
pub(super) struct MaskedSoftmax;

/// `(sequences, rows per sequence, keys)` of scores `[N, ..., keys]` masked by `[N, keys]`.
pub(super) fn sizes(
    name: &str,
    scores: &Layout,
    mask: &Layout,
) -> candle_core::Result<(usize, usize, usize)> {
    let dims = scores.dims();
    let (sequences, keys) = (dims.first().copied().unwrap_or(0), dims.last().copied().unwrap_or(0));
    if dims.len() < 2 || mask.dims() != [sequences, keys] {
        return Err(op_error(
            name,
            format!(
                "scores [N, ..., keys] and a mask [N, keys]; got {dims:?} and {:?}",
                mask.dims()
            ),
        ));
    }
    let rows = scores.shape().elem_count().checked_div(keys).unwrap_or(0);
    Ok((sequences, rows.checked_div(sequences).unwrap_or(0), keys))
}

fn forward<T: Real>(
    (scores, scores_layout): (&CpuStorage, &Layout),
    (mask, mask_layout): (&CpuStorage, &Layout),
) -> candle_core::Result<(CpuStorage, Shape)> {
    let name = "masked-softmax";
    let (_, rows_per_sequence, keys) = sizes(name, scores_layout, mask_layout)?;
    let scores = values::<T>(name, scores, scores_layout)?;
    let mask = values::<T>(name, mask, mask_layout)?;
    let mut out = vec![T::default(); scores.len()];
    if keys > 0 && rows_per_sequence > 0 {
        out.par_chunks_mut(keys).enumerate().for_each(|(row, out)| {
            let mask = &mask[row / rows_per_sequence * keys..][..keys];
            let scores = &scores[row * keys..][..keys];
            for ((o, &s), &m) in out.iter_mut().zip(scores).zip(mask) {
                *o = s + (m - T::of(1.0)) * T::of(MASKED);
            }
            let largest = out.iter().copied().fold(out[0], |a, b| if b > a { b } else { a });
            for o in out.iter_mut() {
                *o = (*o - largest).fast_exp();
            }
            let sum = dot(out, None);
            for o in out.iter_mut() {
                *o = *o / sum;
            }
        });
    }
    Ok((T::storage(out), scores_layout.shape().clone()))
}

impl CustomOp2 for MaskedSoftmax {
    fn name(&self) -> &'static str {
        "masked-softmax"
    }

    fn cpu_fwd(
        &self,
        scores: &CpuStorage,
        scores_layout: &Layout,
        mask: &CpuStorage,
        mask_layout: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        by_dtype!(self.name(), scores, forward((scores, scores_layout), (mask, mask_layout)))
    }

    #[cfg(feature = "cuda")]
    fn cuda_fwd(
        &self,
        scores: &candle_core::CudaStorage,
        scores_layout: &Layout,
        mask: &candle_core::CudaStorage,
        mask_layout: &Layout,
    ) -> candle_core::Result<(candle_core::CudaStorage, Shape)> {
        let sizes = sizes(self.name(), scores_layout, mask_layout)?;
        super::rows_cuda::masked_softmax_forward(
            (scores, scores_layout),
            (mask, mask_layout),
            sizes,
        )
    }

    fn bwd(
        &self,
        _: &Tensor,
        _: &Tensor,
        probabilities: &Tensor,
        grad: &Tensor,
    ) -> candle_core::Result<(Option<Tensor>, Option<Tensor>)> {
        let grad = probabilities.apply_op2_no_bwd(&grad.contiguous()?, &SoftmaxBackward)?;
        Ok((Some(grad), None))
    }
}

/// The gradient of a softmax with respect to its input, from its output `y`:
/// `dx = y (g - sum(g y))` per row. The mask's bias is constant: the scores' gradient is the
/// masked input's.
#[derive(Debug, Clone, Copy)]
pub(super) struct SoftmaxBackward;

fn backward<T: Real>(
    (y, y_layout): (&CpuStorage, &Layout),
    (grad, grad_layout): (&CpuStorage, &Layout),
) -> candle_core::Result<(CpuStorage, Shape)> {
    let name = "softmax-backward";
    let y = values::<T>(name, y, y_layout)?;
    let grad = values::<T>(name, grad, grad_layout)?;
    if y.len() != grad.len() {
        return Err(op_error(name, "a gradient of the probabilities' shape"));
    }
    let keys = y_layout.dims().last().copied().unwrap_or(0);
    let mut out = vec![T::default(); y.len()];
    if keys > 0 {
        out.par_chunks_mut(keys).zip(y.par_chunks(keys)).zip(grad.par_chunks(keys)).for_each(
            |((out, y), grad)| {
                let gy = dot(grad, Some(y));
                for ((o, &y), &g) in out.iter_mut().zip(y).zip(grad) {
                    *o = y * (g - gy);
                }
            },
        );
    }
    Ok((T::storage(out), y_layout.shape().clone()))
}

impl CustomOp2 for SoftmaxBackward {
    fn name(&self) -> &'static str {
        "softmax-backward"
    }

    fn cpu_fwd(
        &self,
        y: &CpuStorage,
        y_layout: &Layout,
        grad: &CpuStorage,
        grad_layout: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        by_dtype!(self.name(), y, backward((y, y_layout), (grad, grad_layout)))
    }

    #[cfg(feature = "cuda")]
    fn cuda_fwd(
        &self,
        y: &candle_core::CudaStorage,
        y_layout: &Layout,
        grad: &candle_core::CudaStorage,
        grad_layout: &Layout,
    ) -> candle_core::Result<(candle_core::CudaStorage, Shape)> {
        super::rows_cuda::softmax_backward((y, y_layout), (grad, grad_layout))
    }
}
