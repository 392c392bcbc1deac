//! Multi-head scaled dot-product attention after the projections, with a key mask, as one
//! operation with its backward pass. Composed ([`crate::layers::Attention`] on other devices) it
//! is about fifteen graph nodes: head splits and transposes copied to contiguous memory, two
//! batched products, the scale, the mask, the softmax and the merge of the heads, each with a
//! zeroed gradient in the backward pass. Here the heads are read where the projections put
//! them and the attention weights are recomputed in the backward pass rather than stored.

use candle_core::{CpuStorage, CustomOp3, Layout, Shape, Tensor};
use rayon::prelude::*;

use crate::kernel::{Real, by_dtype, dot, op_error, simd, values};
use crate::matmul::{Strided, Threads, product_into};

/// What the composite adds to the scores of a masked key (`(mask - 1) * 1e9`).
const MASKED: f64 = -1e9;

/// `softmax(Q K^T / sqrt(head) + mask) V` per head, heads merged.
#[derive(Debug, Clone, Copy)]
pub(super) struct Attention {
    pub(super) heads: usize,
}

/// The sizes of one call.
#[derive(Debug, Clone, Copy)]
struct Sizes {
    query_frames: usize,
    key_frames: usize,
    latent: usize,
    head: usize,
}

impl Attention {
    fn sizes(
        &self,
        name: &str,
        q_layout: &Layout,
        kv_layout: &Layout,
        mask_layout: &Layout,
    ) -> candle_core::Result<Sizes> {
        let (sequences, query_frames, latent) = q_layout.shape().dims3()?;
        let (kv_sequences, key_frames, kv_width) = kv_layout.shape().dims3()?;
        if self.heads == 0
            || !latent.is_multiple_of(self.heads)
            || kv_sequences != sequences
            || kv_width != 2 * latent
            || mask_layout.dims() != [sequences, key_frames]
        {
            return Err(op_error(
                name,
                format!(
                    "queries [N, Tq, latent], keys and values [N, Tk, 2 latent], a mask [N, Tk] \
                     and {} heads dividing latent; got {:?}, {:?}, {:?}",
                    self.heads,
                    q_layout.dims(),
                    kv_layout.dims(),
                    mask_layout.dims()
                ),
            ));
        }
        Ok(Sizes { query_frames, key_frames, latent, head: latent / self.heads })
    }
}

/// One sequence's views of its projections (`queries` `[Tq, latent]`, `keys_values`
/// `[Tk, 2 latent]`), head by head, read in place by [`product_into`]; and the attention
/// weights of the head last loaded.
struct Head<'a, T> {
    s: Sizes,
    queries: &'a [T],
    keys_values: &'a [T],
    mask: &'a [T],
    /// `[Tq, Tk]`: the attention weights.
    weights: Vec<T>,
}

impl<'a, T: Real> Head<'a, T> {
    fn new(s: Sizes, queries: &'a [T], keys_values: &'a [T], mask: &'a [T]) -> Self {
        let weights = vec![T::default(); s.query_frames * s.key_frames];
        Self { s, queries, keys_values, mask, weights }
    }

    /// Head `h`'s queries, `[Tq, head]`.
    fn queries(&self, h: usize) -> Strided<'a, T> {
        let Sizes { query_frames, latent, head, .. } = self.s;
        let data = &self.queries[h * head..];
        Strided::rows_apart(data, query_frames, head, latent)
    }

    /// Head `h`'s keys (`values` false) or values, `[Tk, head]`.
    fn keys_or_values(&self, h: usize, values: bool) -> Strided<'a, T> {
        let Sizes { key_frames, latent, head, .. } = self.s;
        let data = &self.keys_values[usize::from(values) * latent + h * head..];
        Strided::rows_apart(data, key_frames, head, 2 * latent)
    }

    /// The attention weights, `[Tq, Tk]`.
    fn weights(&self) -> Strided<'_, T> {
        let (rows, columns) = (self.s.query_frames, self.s.key_frames);
        Strided::row_major(&self.weights, rows, columns)
    }

    /// Computes head `h`'s attention weights under the mask.
    #[inline(always)]
    fn load(&mut self, h: usize) {
        let Sizes { key_frames, head, .. } = self.s;
        let scale = T::of(1.0 / (head as f64).sqrt());
        let (queries, keys) = (self.queries(h), self.keys_or_values(h, false));
        let views = (queries, keys.transposed());
        product_into(&mut self.weights, key_frames, views, scale, false, Threads::Calling);
        for row in self.weights.chunks_exact_mut(key_frames) {
            for (r, &m) in row.iter_mut().zip(self.mask) {
                *r = *r + (m - T::of(1.0)) * T::of(-MASKED);
            }
            let largest = row.iter().copied().fold(row[0], |a, b| if b > a { b } else { a });
            for r in row.iter_mut() {
                *r = (*r - largest).fast_exp();
            }
            let inverse = T::of(1.0) / dot(row, None);
            for r in row.iter_mut() {
                *r = *r * inverse;
            }
        }
    }
}

fn forward<T: Real>(
    op: &Attention,
    (q, q_layout): (&CpuStorage, &Layout),
    (kv, kv_layout): (&CpuStorage, &Layout),
    (mask, mask_layout): (&CpuStorage, &Layout),
) -> candle_core::Result<(CpuStorage, Shape)> {
    let name = "attention";
    let s = op.sizes(name, q_layout, kv_layout, mask_layout)?;
    let (queries, keys_values, mask) = (
        values::<T>(name, q, q_layout)?,
        values::<T>(name, kv, kv_layout)?,
        values::<T>(name, mask, mask_layout)?,
    );
    let (query_rows, key_rows) = (s.query_frames * s.latent, s.key_frames * 2 * s.latent);
    let mut out = vec![T::default(); queries.len()];
    if query_rows > 0 && s.key_frames > 0 {
        out.par_chunks_mut(query_rows).enumerate().for_each(|(n, out)| {
            let queries = &queries[n * query_rows..][..query_rows];
            let keys_values = &keys_values[n * key_rows..][..key_rows];
            let mask = &mask[n * s.key_frames..][..s.key_frames];
            let mut head = Head::new(s, queries, keys_values, mask);
            simd(
                #[inline(always)]
                || {
                    for h in 0..op.heads {
                        head.load(h);
                        let values = head.keys_or_values(h, true);
                        let out = &mut out[h * s.head..];
                        let views = (head.weights(), values);
                        product_into(out, s.latent, views, T::of(1.0), false, Threads::Calling);
                    }
                },
            )
        });
    }
    Ok((T::storage(out), q_layout.shape().clone()))
}

impl CustomOp3 for Attention {
    fn name(&self) -> &'static str {
        "attention"
    }

    fn cpu_fwd(
        &self,
        q: &CpuStorage,
        q_layout: &Layout,
        kv: &CpuStorage,
        kv_layout: &Layout,
        mask: &CpuStorage,
        mask_layout: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        by_dtype!(
            self.name(),
            q,
            forward(self, (q, q_layout), (kv, kv_layout), (mask, mask_layout))
        )
    }

    fn bwd(
        &self,
        q: &Tensor,
        kv: &Tensor,
        mask: &Tensor,
        _: &Tensor,
        grad: &Tensor,
    ) -> candle_core::Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
        // One output holds both gradients, the queries' first, then the keys' and values'. The
        // mask (`[N, Tk]`, small) travels in the operation: an operation has at most three inputs.
        let mask = mask.flatten_all()?.to_dtype(candle_core::DType::F64)?.to_vec1::<f64>()?;
        let backward = AttentionBackward { attention: *self, mask };
        let both = q.apply_op3_no_bwd(kv, &grad.contiguous()?, &backward)?;
        let grad_q = both.narrow(0, 0, q.elem_count())?.reshape(q.shape())?;
        let grad_kv = both.narrow(0, q.elem_count(), kv.elem_count())?.reshape(kv.shape())?;
        Ok((Some(grad_q), Some(grad_kv), None))
    }
}

/// The gradients of [`Attention`] with respect to the queries and to the keys and values,
/// flattened one after the other; its inputs are the queries, the keys and values and the
/// output's gradient. With `P` the attention weights (recomputed), `G` the output's
/// gradient and `c = 1 / sqrt(head)`: `dV = P^T G`, `dP = G V^T`,
/// `dS = P * (dP - rowsum(dP * P))`, `dQ = c dS K`, `dK = c dS^T Q` (the mask gets none).
#[derive(Debug, Clone)]
struct AttentionBackward {
    attention: Attention,
    /// The key mask, `[N, Tk]` flattened.
    mask: Vec<f64>,
}

fn backward<T: Real>(
    op: &AttentionBackward,
    (q, q_layout): (&CpuStorage, &Layout),
    (kv, kv_layout): (&CpuStorage, &Layout),
    (grad, grad_layout): (&CpuStorage, &Layout),
) -> candle_core::Result<(CpuStorage, Shape)> {
    let name = "attention-backward";
    let (sequences, key_frames, _) = kv_layout.shape().dims3()?;
    let mask_layout = Layout::contiguous((sequences, key_frames));
    let s = op.attention.sizes(name, q_layout, kv_layout, &mask_layout)?;
    let (queries, keys_values, grad) = (
        values::<T>(name, q, q_layout)?,
        values::<T>(name, kv, kv_layout)?,
        values::<T>(name, grad, grad_layout)?,
    );
    if grad.len() != queries.len() || op.mask.len() != sequences * key_frames {
        return Err(op_error(name, "a gradient of the output's shape and a mask [N, Tk]"));
    }
    let mask: Vec<T> = op.mask.iter().map(|&m| T::of(m)).collect();
    let (query_rows, key_rows) = (s.query_frames * s.latent, s.key_frames * 2 * s.latent);
    let mut out = vec![T::default(); queries.len() + keys_values.len()];
    if query_rows > 0 && s.key_frames > 0 {
        let (grad_q, grad_kv) = out.split_at_mut(queries.len());
        let scale = T::of(1.0 / (s.head as f64).sqrt());
        let (tq, tk, d) = (s.query_frames, s.key_frames, s.head);
        grad_q
            .par_chunks_mut(query_rows)
            .zip(grad_kv.par_chunks_mut(key_rows))
            .enumerate()
            .for_each(|(n, (grad_q, grad_kv))| {
                let queries = &queries[n * query_rows..][..query_rows];
                let keys_values = &keys_values[n * key_rows..][..key_rows];
                let grad = &grad[n * query_rows..][..query_rows];
                let mask = &mask[n * tk..][..tk];
                let mut head = Head::new(s, queries, keys_values, mask);
                let mut grad_scores = vec![T::default(); tq * tk];
                let one = T::of(1.0);
                simd(
                    #[inline(always)]
                    || {
                        for h in 0..op.attention.heads {
                            head.load(h);
                            let output_grad = Strided::rows_apart(&grad[h * d..], tq, d, s.latent);
                            let (keys, values) =
                                (head.keys_or_values(h, false), head.keys_or_values(h, true));
                            // dV = P^T G.
                            let views = (head.weights().transposed(), output_grad);
                            let into = &mut grad_kv[s.latent + h * d..];
                            product_into(into, 2 * s.latent, views, one, false, Threads::Calling);
                            // dP = G V^T, then dS = P (dP - rowsum(dP P)), scaled by c.
                            let views = (output_grad, values.transposed());
                            product_into(&mut grad_scores, tk, views, one, false, Threads::Calling);
                            let rows = grad_scores.chunks_exact_mut(tk);
                            for (ds, p) in rows.zip(head.weights.chunks_exact(tk)) {
                                let weighted = dot(ds, Some(p));
                                for (ds, &p) in ds.iter_mut().zip(p) {
                                    *ds = p * (*ds - weighted) * scale;
                                }
                            }
                            // dQ = c dS K, dK = c dS^T Q.
                            let scores_grad = Strided::row_major(&grad_scores, tq, tk);
                            let into = &mut grad_q[h * d..];
                            product_into(
                                into,
                                s.latent,
                                (scores_grad, keys),
                                one,
                                false,
                                Threads::Calling,
                            );
                            let views = (scores_grad.transposed(), head.queries(h));
                            let into = &mut grad_kv[h * d..];
                            product_into(into, 2 * s.latent, views, one, false, Threads::Calling);
                        }
                    },
                )
            });
    }
    Ok((T::storage(out), Shape::from(queries.len() + keys_values.len())))
}

impl CustomOp3 for AttentionBackward {
    fn name(&self) -> &'static str {
        "attention-backward"
    }

    fn cpu_fwd(
        &self,
        q: &CpuStorage,
        q_layout: &Layout,
        kv: &CpuStorage,
        kv_layout: &Layout,
        grad: &CpuStorage,
        grad_layout: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        by_dtype!(
            self.name(),
            q,
            backward(self, (q, q_layout), (kv, kv_layout), (grad, grad_layout))
        )
    }
}
