//! Multi-head scaled dot-product attention after the projections, with a key mask, as one
//! operation with its backward pass. Composed ([`crate::layers::Attention`] on other devices) it
//! is about fifteen graph nodes: head splits and transposes copied to contiguous memory, two
//! batched products, the scale, the mask, the softmax and the merge of the heads, each with a
//! zeroed gradient in the backward pass. Here the heads are read where the projections put
//! them and the attention weights are recomputed in the backward pass rather than stored.

use candle_core::{CpuStorage, CustomOp3, Layout, Shape, Tensor};
use rayon::prelude::*;

use super::{Real, dot, op_error, simd, values};

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

/// Rows of the register tile of [`product`].
const TILE_ROWS: usize = 4;
/// Columns of the register tile of [`product`] (two AVX registers of f32).
const TILE_COLUMNS: usize = 16;

/// `c = a b` for row-major `a` `[m, k]`, `b` `[k, n]` and `c` `[m, n]`: the small products of
/// one head (at most a few hundred rows and columns). In f32 through gemm on this thread (the
/// sequences are already spread over the threads): 1.65x faster for the forward pass of a
/// `small` batch's attention than the loop below (session 17). In f64 (the gradient checks)
/// register-blocked in tiles of
/// [`TILE_ROWS`] x [`TILE_COLUMNS`] whose sums stay in registers while the rows of `b` stream
/// past (vectorised under [`simd`]).
#[inline(always)]
fn product<T: Real>(a: &[T], b: &[T], c: &mut [T], (m, k, n): (usize, usize, usize)) {
    if let Some(out) = T::gemm_product(a, b, (m, k, n)) {
        c.copy_from_slice(&out);
        return;
    }
    for i in (0..m).step_by(TILE_ROWS) {
        let rows = TILE_ROWS.min(m - i);
        for j in (0..n).step_by(TILE_COLUMNS) {
            let columns = TILE_COLUMNS.min(n - j);
            if rows == TILE_ROWS && columns == TILE_COLUMNS {
                let mut sums = [[T::default(); TILE_COLUMNS]; TILE_ROWS];
                for p in 0..k {
                    let b_row = &b[p * n + j..][..TILE_COLUMNS];
                    for (r, sums) in sums.iter_mut().enumerate() {
                        let a = a[(i + r) * k + p];
                        for (s, &b) in sums.iter_mut().zip(b_row) {
                            *s = a.mul_add(b, *s);
                        }
                    }
                }
                for (r, sums) in sums.iter().enumerate() {
                    c[(i + r) * n + j..][..TILE_COLUMNS].copy_from_slice(sums);
                }
            } else {
                for r in i..i + rows {
                    let c_row = &mut c[r * n + j..][..columns];
                    c_row.fill(T::default());
                    for p in 0..k {
                        let a = a[r * k + p];
                        for (s, &b) in c_row.iter_mut().zip(&b[p * n + j..][..columns]) {
                            *s = a.mul_add(b, *s);
                        }
                    }
                }
            }
        }
    }
}

/// `out = x^T` for row-major `x` `[rows, columns]`.
#[inline(always)]
fn transpose<T: Real>(x: &[T], out: &mut [T], (rows, columns): (usize, usize)) {
    for (r, row) in x.chunks_exact(columns).take(rows).enumerate() {
        for (c, &v) in row.iter().enumerate() {
            out[c * rows + r] = v;
        }
    }
}

/// Copies columns `column..column + out_width` of every row of `source` (rows of `width`)
/// into the rows of `out`.
#[inline(always)]
fn gather<T: Real>(source: &[T], width: usize, column: usize, out: &mut [T]) {
    let out_width = out.len() / (source.len() / width.max(1)).max(1);
    for (o, row) in out.chunks_exact_mut(out_width.max(1)).zip(source.chunks_exact(width.max(1))) {
        o.copy_from_slice(&row[column..column + out_width]);
    }
}

/// Writes the rows of `x` into columns `column..` of the rows of `out` (rows of `width`).
/// Each head writes its own columns once, so nothing is added and the output is never read:
/// its freshly allocated pages are faulted in once, by the write. Added into, they were read
/// first, which maps the shared zero page, and written after, which faults again and flushes
/// the other cores' TLBs; the backward pass of a `small` batch's attention took 53 ms that
/// way and 35 ms this way (2 threads, session 17).
#[inline(always)]
fn scatter<T: Real>(x: &[T], out: &mut [T], width: usize, column: usize) {
    let x_width = x.len() / (out.len() / width.max(1)).max(1);
    for (o, row) in out.chunks_exact_mut(width.max(1)).zip(x.chunks_exact(x_width.max(1))) {
        o[column..column + x_width].copy_from_slice(row);
    }
}

/// One sequence's buffers for one head at a time: its queries, keys and values copied out of
/// the projections' rows, and the products of the forward and backward passes.
struct Head<T> {
    s: Sizes,
    /// `[Tq, head]`, `[Tk, head]`, `[Tk, head]`.
    queries: Vec<T>,
    keys: Vec<T>,
    values: Vec<T>,
    /// `[head, Tk]`: keys (then values) transposed.
    transposed: Vec<T>,
    /// `[Tq, Tk]`: the attention weights.
    weights: Vec<T>,
    /// `[Tq, head]`: the output (forward), the output's gradient (backward).
    out: Vec<T>,
}

impl<T: Real> Head<T> {
    fn new(s: Sizes) -> Self {
        let (q, k, d) = (s.query_frames, s.key_frames, s.head);
        Self {
            s,
            queries: vec![T::default(); q * d],
            keys: vec![T::default(); k * d],
            values: vec![T::default(); k * d],
            transposed: vec![T::default(); d * k],
            weights: vec![T::default(); q * k],
            out: vec![T::default(); q * d],
        }
    }

    /// Loads head `h` of one sequence (`queries` `[Tq, latent]`, `keys_values`
    /// `[Tk, 2 latent]`) and computes its attention weights under `mask` (`[Tk]`).
    #[inline(always)]
    fn load(&mut self, h: usize, queries: &[T], keys_values: &[T], mask: &[T]) {
        let Sizes { query_frames, key_frames, latent, head } = self.s;
        gather(queries, latent, h * head, &mut self.queries);
        gather(keys_values, 2 * latent, h * head, &mut self.keys);
        gather(keys_values, 2 * latent, latent + h * head, &mut self.values);
        transpose(&self.keys, &mut self.transposed, (key_frames, head));
        let sizes = (query_frames, head, key_frames);
        product(&self.queries, &self.transposed, &mut self.weights, sizes);
        let scale = T::of(1.0 / (head as f64).sqrt());
        for row in self.weights.chunks_exact_mut(key_frames) {
            for (r, &m) in row.iter_mut().zip(mask) {
                *r = r.mul_add(scale, (m - T::of(1.0)) * T::of(-MASKED));
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
            let mut head = Head::new(s);
            simd(
                #[inline(always)]
                || {
                    for h in 0..op.heads {
                        head.load(h, queries, keys_values, mask);
                        let sizes = (s.query_frames, s.key_frames, s.head);
                        product(&head.weights, &head.values, &mut head.out, sizes);
                        scatter(&head.out, out, s.latent, h * s.head);
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
                let mut head = Head::new(s);
                let mut grad_scores = vec![T::default(); tq * tk];
                let mut transposed = vec![T::default(); tk * tq];
                let mut result = vec![T::default(); tq.max(tk) * d];
                simd(
                    #[inline(always)]
                    || {
                        for h in 0..op.attention.heads {
                            head.load(h, queries, keys_values, mask);
                            gather(grad, s.latent, h * d, &mut head.out);
                            // dV = P^T G.
                            transpose(&head.weights, &mut transposed, (tq, tk));
                            product(&transposed, &head.out, &mut result[..tk * d], (tk, tq, d));
                            scatter(&result[..tk * d], grad_kv, 2 * s.latent, s.latent + h * d);
                            // dP = G V^T, then dS = P (dP - rowsum(dP P)), scaled by c.
                            transpose(&head.values, &mut head.transposed, (tk, d));
                            product(&head.out, &head.transposed, &mut grad_scores, (tq, d, tk));
                            let rows = grad_scores.chunks_exact_mut(tk);
                            for (ds, p) in rows.zip(head.weights.chunks_exact(tk)) {
                                let weighted = dot(ds, Some(p));
                                for (ds, &p) in ds.iter_mut().zip(p) {
                                    *ds = p * (*ds - weighted) * scale;
                                }
                            }
                            // dQ = c dS K, dK = c dS^T Q.
                            product(&grad_scores, &head.keys, &mut result[..tq * d], (tq, tk, d));
                            scatter(&result[..tq * d], grad_q, s.latent, h * d);
                            transpose(&grad_scores, &mut transposed, (tq, tk));
                            product(&transposed, &head.queries, &mut result[..tk * d], (tk, tq, d));
                            scatter(&result[..tk * d], grad_kv, 2 * s.latent, h * d);
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
