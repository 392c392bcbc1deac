//! AdaLN's modulation of a layer norm, `norm(x) * (1 + scale) + shift` (paper Sec. 3.2,
//! [`crate::layers::Modulation`]), as one operation with its backward pass. Composed, it is a
//! layer norm, two narrows of the modulation, an add and two broadcasts: seven graph nodes,
//! four over the whole token tensor, each with a zeroed gradient in the backward pass.

use candle_core::{CpuStorage, CustomOp2, CustomOp3, Layout, Shape, Tensor};
use rayon::prelude::*;

use crate::kernel::{Real, by_dtype, dot, normalise, op_error, simd, values};

/// `norm(x) * (1 + scale) + shift` with `(shift, scale)` the two halves of each sequence's
/// modulation row.
#[derive(Debug, Clone, Copy)]
pub(super) struct Modulate;

/// `(sequences, frames, latent)` of a token tensor `[N, T, latent]` modulated by `[N, 2 latent]`.
fn sizes(
    name: &str,
    x_layout: &Layout,
    modulation_layout: &Layout,
) -> candle_core::Result<(usize, usize, usize)> {
    let (sequences, frames, latent) = x_layout.shape().dims3()?;
    if modulation_layout.dims() != [sequences, 2 * latent] {
        return Err(op_error(
            name,
            format!(
                "tokens [N, T, latent] and a modulation [N, 2 latent]; got {:?} and {:?}",
                x_layout.dims(),
                modulation_layout.dims()
            ),
        ));
    }
    Ok((sequences, frames, latent))
}

fn forward<T: Real>(
    (x, x_layout): (&CpuStorage, &Layout),
    (modulation, modulation_layout): (&CpuStorage, &Layout),
) -> candle_core::Result<(CpuStorage, Shape)> {
    let name = "modulate";
    let (_, frames, latent) = sizes(name, x_layout, modulation_layout)?;
    let x = values::<T>(name, x, x_layout)?;
    let modulation = values::<T>(name, modulation, modulation_layout)?;
    let mut out = vec![T::default(); x.len()];
    if latent > 0 && frames > 0 {
        out.par_chunks_mut(frames * latent).enumerate().for_each(|(n, out)| {
            let (shift, scale) = modulation[n * 2 * latent..][..2 * latent].split_at(latent);
            let x = &x[n * frames * latent..][..frames * latent];
            simd(
                #[inline(always)]
                || {
                    for (out, x) in out.chunks_exact_mut(latent).zip(x.chunks_exact(latent)) {
                        normalise(x, out);
                        for ((o, &s), &b) in out.iter_mut().zip(scale).zip(shift) {
                            *o = o.mul_add(T::of(1.0) + s, b);
                        }
                    }
                },
            )
        });
    }
    Ok((T::storage(out), x_layout.shape().clone()))
}

impl CustomOp2 for Modulate {
    fn name(&self) -> &'static str {
        "modulate"
    }

    fn cpu_fwd(
        &self,
        x: &CpuStorage,
        x_layout: &Layout,
        modulation: &CpuStorage,
        modulation_layout: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        by_dtype!(self.name(), x, forward((x, x_layout), (modulation, modulation_layout)))
    }

    #[cfg(feature = "cuda")]
    fn cuda_fwd(
        &self,
        x: &candle_core::CudaStorage,
        x_layout: &Layout,
        modulation: &candle_core::CudaStorage,
        modulation_layout: &Layout,
    ) -> candle_core::Result<(candle_core::CudaStorage, Shape)> {
        let sizes = sizes(self.name(), x_layout, modulation_layout)?;
        super::rows_cuda::modulate_forward((x, x_layout), (modulation, modulation_layout), sizes)
    }

    fn bwd(
        &self,
        x: &Tensor,
        modulation: &Tensor,
        _: &Tensor,
        grad: &Tensor,
    ) -> candle_core::Result<(Option<Tensor>, Option<Tensor>)> {
        // One output holds both gradients, the tokens' first, then the modulation's.
        let both = x.apply_op3_no_bwd(modulation, &grad.contiguous()?, &ModulateBackward)?;
        let tokens = x.elem_count();
        let grad_x = both.narrow(0, 0, tokens)?.reshape(x.shape())?;
        let grad_modulation =
            both.narrow(0, tokens, modulation.elem_count())?.reshape(modulation.shape())?;
        Ok((Some(grad_x), Some(grad_modulation)))
    }
}

/// The gradients of [`Modulate`], flattened one after the other: with `y = norm(x)`,
/// `u = g (1 + scale)` and `s = 1 / sqrt(variance + eps)`, `dx = (u - mean(u) - y mean(u y)) s`;
/// `d shift = sum_t g`, `d scale = sum_t g y` over each sequence's frames.
#[derive(Debug, Clone, Copy)]
struct ModulateBackward;

fn backward<T: Real>(
    (x, x_layout): (&CpuStorage, &Layout),
    (modulation, modulation_layout): (&CpuStorage, &Layout),
    (grad, grad_layout): (&CpuStorage, &Layout),
) -> candle_core::Result<(CpuStorage, Shape)> {
    let name = "modulate-backward";
    let (sequences, frames, latent) = sizes(name, x_layout, modulation_layout)?;
    let x = values::<T>(name, x, x_layout)?;
    let modulation = values::<T>(name, modulation, modulation_layout)?;
    let grad = values::<T>(name, grad, grad_layout)?;
    if grad.len() != x.len() {
        return Err(op_error(name, "a gradient of the tokens' shape"));
    }
    let mut out = vec![T::default(); x.len() + sequences * 2 * latent];
    if latent > 0 && frames > 0 {
        let (grad_x, grad_modulation) = out.split_at_mut(x.len());
        let n_inverse = T::of(1.0 / latent as f64);
        grad_x
            .par_chunks_mut(frames * latent)
            .zip(grad_modulation.par_chunks_mut(2 * latent))
            .enumerate()
            .for_each(|(n, (grad_x, grad_modulation))| {
                let scale = &modulation[n * 2 * latent + latent..][..latent];
                let x = &x[n * frames * latent..][..frames * latent];
                let grad = &grad[n * frames * latent..][..frames * latent];
                let (grad_shift, grad_scale) = grad_modulation.split_at_mut(latent);
                let mut u = vec![T::default(); latent];
                simd(
                    #[inline(always)]
                    || {
                        let rows = grad_x.chunks_exact_mut(latent);
                        for ((dx, x), g) in
                            rows.zip(x.chunks_exact(latent)).zip(grad.chunks_exact(latent))
                        {
                            let inverse = normalise(x, dx); // dx = y for now
                            for (((((&y, &g), &s), d_shift), d_scale), u) in dx
                                .iter()
                                .zip(g)
                                .zip(scale)
                                .zip(grad_shift.iter_mut())
                                .zip(grad_scale.iter_mut())
                                .zip(u.iter_mut())
                            {
                                *d_shift = *d_shift + g;
                                *d_scale = g.mul_add(y, *d_scale);
                                *u = g * (T::of(1.0) + s);
                            }
                            let (u_mean, uy_mean) = (dot(&u, None), dot(&u, Some(dx)));
                            let (u_mean, uy_mean) = (u_mean * n_inverse, uy_mean * n_inverse);
                            for (dx, &u) in dx.iter_mut().zip(u.iter()) {
                                *dx = (u - u_mean - *dx * uy_mean) * inverse;
                            }
                        }
                    },
                )
            });
    }
    Ok((T::storage(out), Shape::from(x.len() + sequences * 2 * latent)))
}

impl CustomOp3 for ModulateBackward {
    fn name(&self) -> &'static str {
        "modulate-backward"
    }

    fn cpu_fwd(
        &self,
        x: &CpuStorage,
        x_layout: &Layout,
        modulation: &CpuStorage,
        modulation_layout: &Layout,
        grad: &CpuStorage,
        grad_layout: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        by_dtype!(
            self.name(),
            x,
            backward((x, x_layout), (modulation, modulation_layout), (grad, grad_layout))
        )
    }

    #[cfg(feature = "cuda")]
    fn cuda_fwd(
        &self,
        x: &candle_core::CudaStorage,
        x_layout: &Layout,
        modulation: &candle_core::CudaStorage,
        modulation_layout: &Layout,
        grad: &candle_core::CudaStorage,
        grad_layout: &Layout,
    ) -> candle_core::Result<(candle_core::CudaStorage, Shape)> {
        let sizes = sizes(self.name(), x_layout, modulation_layout)?;
        super::rows_cuda::modulate_backward(
            (x, x_layout),
            (modulation, modulation_layout),
            (grad, grad_layout),
            sizes,
        )
    }
}
