//! Multi-head scaled dot-product attention after the projections, with a key mask, as one
//! operation with its backward pass. Composed ([`crate::layers::Attention`] on other devices) it
//! is about fifteen graph nodes: head splits and transposes copied to contiguous memory, two
//! batched products, the scale, the mask, the softmax and the merge of the heads, each with a
//! zeroed gradient in the backward pass. Here the heads are read where the projections put
//! them and the attention weights are recomputed in the backward pass rather than stored.

use candle_core::{CpuStorage, CustomOp3, Layout, Shape, Tensor};
use rayon::prelude::*;

use super::{Real, op_error, simd, values};

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

/// One sequence's queries `[Tq, latent]`, keys and values `[Tk, 2 latent]` and mask `[Tk]`.
#[derive(Clone, Copy)]
struct Sequence<'a, T> {
    queries: &'a [T],
    keys_values: &'a [T],
    mask: &'a [T],
}

impl<'a, T: Real> Sequence<'a, T> {
    fn of(n: usize, s: Sizes, queries: &'a [T], keys_values: &'a [T], mask: &'a [T]) -> Self {
        Self {
            queries: &queries[n * s.query_frames * s.latent..][..s.query_frames * s.latent],
            keys_values: &keys_values[n * s.key_frames * 2 * s.latent..]
                [..s.key_frames * 2 * s.latent],
            mask: &mask[n * s.key_frames..][..s.key_frames],
        }
    }

    /// Query `i` of head `h`.
    #[inline(always)]
    fn query(&self, s: Sizes, i: usize, h: usize) -> &'a [T] {
        &self.queries[i * s.latent + h * s.head..][..s.head]
    }

    /// Key `j` of head `h`.
    #[inline(always)]
    fn key(&self, s: Sizes, j: usize, h: usize) -> &'a [T] {
        &self.keys_values[j * 2 * s.latent + h * s.head..][..s.head]
    }

    /// Value `j` of head `h`.
    #[inline(always)]
    fn value(&self, s: Sizes, j: usize, h: usize) -> &'a [T] {
        &self.keys_values[j * 2 * s.latent + s.latent + h * s.head..][..s.head]
    }

    /// Head `h`'s keys (`values = false`) or values transposed into `out`, `[head][Tk]`.
    #[inline(always)]
    fn transposed(&self, s: Sizes, h: usize, values: bool, out: &mut [T]) {
        for j in 0..s.key_frames {
            let row = if values { self.value(s, j, h) } else { self.key(s, j, h) };
            for (d, &v) in row.iter().enumerate() {
                out[d * s.key_frames + j] = v;
            }
        }
    }

    /// Head `h`'s attention weights `[Tq][Tk]` into `weights`; `keys_t` is scratch of
    /// `[head][Tk]`.
    #[inline(always)]
    fn weights(&self, s: Sizes, h: usize, keys_t: &mut [T], weights: &mut [T]) {
        self.transposed(s, h, false, keys_t);
        let scale = T::of(1.0 / (s.head as f64).sqrt());
        for (i, row) in weights.chunks_exact_mut(s.key_frames).enumerate() {
            row.fill(T::default());
            for (&q, keys) in self.query(s, i, h).iter().zip(keys_t.chunks_exact(s.key_frames)) {
                for (r, &k) in row.iter_mut().zip(keys) {
                    *r = q.mul_add(k, *r);
                }
            }
            for (r, &m) in row.iter_mut().zip(self.mask) {
                *r = r.mul_add(scale, (m - T::of(1.0)) * T::of(-MASKED));
            }
            let largest = row.iter().copied().fold(row[0], |a, b| if b > a { b } else { a });
            let mut total = T::default();
            for r in row.iter_mut() {
                *r = (*r - largest).exp();
                total = total + *r;
            }
            let inverse = T::of(1.0) / total;
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
    let mut out = vec![T::default(); queries.len()];
    if s.query_frames * s.latent > 0 && s.key_frames > 0 {
        out.par_chunks_mut(s.query_frames * s.latent).enumerate().for_each(|(n, out)| {
            let sequence = Sequence::of(n, s, queries, keys_values, mask);
            let mut keys_t = vec![T::default(); s.head * s.key_frames];
            let mut weights = vec![T::default(); s.query_frames * s.key_frames];
            simd(
                #[inline(always)]
                || {
                    for h in 0..op.heads {
                        sequence.weights(s, h, &mut keys_t, &mut weights);
                        let rows = weights.chunks_exact(s.key_frames);
                        for (out, weights) in out.chunks_exact_mut(s.latent).zip(rows) {
                            let out = &mut out[h * s.head..][..s.head];
                            for (j, &w) in weights.iter().enumerate() {
                                for (o, &v) in out.iter_mut().zip(sequence.value(s, j, h)) {
                                    *o = w.mul_add(v, *o);
                                }
                            }
                        }
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
    let mask = mask.as_slice();
    let heads = op.attention.heads;
    let mut out = vec![T::default(); queries.len() + keys_values.len()];
    if s.query_frames * s.latent > 0 && s.key_frames > 0 {
        let (grad_q, grad_kv) = out.split_at_mut(queries.len());
        let scale = T::of(1.0 / (s.head as f64).sqrt());
        grad_q
            .par_chunks_mut(s.query_frames * s.latent)
            .zip(grad_kv.par_chunks_mut(s.key_frames * 2 * s.latent))
            .enumerate()
            .for_each(|(n, (grad_q, grad_kv))| {
                let sequence = Sequence::of(n, s, queries, keys_values, mask);
                let grad = &grad[n * s.query_frames * s.latent..][..s.query_frames * s.latent];
                let mut scratch_t = vec![T::default(); s.head * s.key_frames];
                let mut weights = vec![T::default(); s.query_frames * s.key_frames];
                let mut grad_scores = vec![T::default(); s.key_frames];
                simd(
                    #[inline(always)]
                    || {
                        for h in 0..heads {
                            sequence.weights(s, h, &mut scratch_t, &mut weights);
                            sequence.transposed(s, h, true, &mut scratch_t); // values_t
                            let rows = weights.chunks_exact(s.key_frames);
                            for (i, p) in rows.enumerate() {
                                let g = &grad[i * s.latent + h * s.head..][..s.head];
                                // dP = G V^T, then dS (scaled by c).
                                grad_scores.fill(T::default());
                                let values_t = scratch_t.chunks_exact(s.key_frames);
                                for (&g, values) in g.iter().zip(values_t) {
                                    for (d, &v) in grad_scores.iter_mut().zip(values) {
                                        *d = g.mul_add(v, *d);
                                    }
                                }
                                let mut weighted = T::default();
                                for (&d, &p) in grad_scores.iter().zip(p) {
                                    weighted = d.mul_add(p, weighted);
                                }
                                for (d, &p) in grad_scores.iter_mut().zip(p) {
                                    *d = p * (*d - weighted) * scale;
                                }
                                let query = sequence.query(s, i, h);
                                let dq = &mut grad_q[i * s.latent + h * s.head..][..s.head];
                                for (j, (&ds, &p)) in grad_scores.iter().zip(p).enumerate() {
                                    for (dq, &k) in dq.iter_mut().zip(sequence.key(s, j, h)) {
                                        *dq = ds.mul_add(k, *dq);
                                    }
                                    let row = &mut grad_kv[j * 2 * s.latent..][..2 * s.latent];
                                    let (dk, dv) = row.split_at_mut(s.latent);
                                    let dk = &mut dk[h * s.head..][..s.head];
                                    for (dk, &q) in dk.iter_mut().zip(query) {
                                        *dk = ds.mul_add(q, *dk);
                                    }
                                    let dv = &mut dv[h * s.head..][..s.head];
                                    for (dv, &g) in dv.iter_mut().zip(g) {
                                        *dv = p.mul_add(g, *dv);
                                    }
                                }
                            }
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
