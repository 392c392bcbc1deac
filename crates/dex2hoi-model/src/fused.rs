//! Forward-only fused CPU operations of the inference path ([`crate::InferenceModel`]): each
//! replaces a chain of candle operations (one pass over memory instead of four to eight, each a
//! fresh allocation and, in candle, single-threaded) and spreads its rows over the rayon pool.
//!
//! None of them has a backward pass: training never uses them (Architecture Invariant: every
//! operation that trains has a backward pass; only the no-grad inference path may use
//! forward-only fused operations). They accept contiguous f32 tensors on the CPU; the inference
//! path uses the composite model on any other device or dtype. Each is tested equal to the
//! composite operations it replaces (`tests/inference.rs`).

use std::sync::Arc;

use candle_core::{CpuStorage, CustomOp1, CustomOp2, CustomOp3, Layout, Shape, Tensor};
use rayon::prelude::*;

use crate::kernel::{LAYER_NORM_EPS, ROWS_PER_TASK, exp, leading_rows, op_error, simd};
use crate::matmul::{Packed, Strided, Threads, packed_product, product_into};

/// The values of a contiguous f32 tensor.
fn values<'a>(
    op: &str,
    storage: &'a CpuStorage,
    layout: &Layout,
) -> candle_core::Result<&'a [f32]> {
    crate::kernel::values::<f32>(op, storage, layout)
}

/// Independent partial sums of the row reductions: one AVX-512 register, two AVX2 ones.
const LANES: usize = 16;

/// The last dimension and the number of rows before it.
fn rows_and_width(layout: &Layout) -> (usize, usize) {
    let width = layout.dims().last().copied().unwrap_or(1);
    (layout.shape().elem_count() / width.max(1), width)
}

/// Normalises `row` into `out` (zero mean, unit variance over the row) and returns nothing;
/// the mean and variance are computed as the composite does (two passes, mean of squares of
/// the centred values).
#[inline(always)]
fn normalise_row(row: &[f32], out: &mut [f32]) {
    let n = row.len() as f32;
    let mean = sum(row, |x| x) / n;
    for (o, &x) in out.iter_mut().zip(row) {
        *o = x - mean;
    }
    let variance = sum(out, |c| c * c);
    let inverse = 1.0 / (variance / n + LAYER_NORM_EPS as f32).sqrt();
    for o in out.iter_mut() {
        *o *= inverse;
    }
}

/// `sum_k f(values_k)` in [`LANES`] independent partial sums, so that it vectorises (a plain
/// sum is one chain of dependent additions).
#[inline(always)]
fn sum(values: &[f32], f: impl Fn(f32) -> f32) -> f32 {
    let mut lanes = [0f32; LANES];
    let chunks = values.chunks_exact(LANES);
    let tail: f32 = chunks.remainder().iter().map(|&v| f(v)).sum();
    for chunk in chunks {
        for (lane, &v) in lanes.iter_mut().zip(chunk) {
            *lane += f(v);
        }
    }
    lanes.iter().sum::<f32>() + tail
}

/// The largest of `values` (`-inf` for none), in [`LANES`] partial maxima.
#[inline(always)]
fn max(values: &[f32]) -> f32 {
    let mut lanes = [f32::NEG_INFINITY; LANES];
    let chunks = values.chunks_exact(LANES);
    let tail = chunks.remainder().iter().fold(f32::NEG_INFINITY, |m, &v| m.max(v));
    for chunk in chunks {
        for (lane, &v) in lanes.iter_mut().zip(chunk) {
            *lane = lane.max(v);
        }
    }
    lanes.iter().fold(tail, |m, &v| m.max(v))
}

/// Layer norm over the last dimension without affine parameters.
///
/// # Shapes
/// - input `[..., features]`; output the same
#[derive(Debug, Clone, Copy)]
pub struct LayerNorm;

impl CustomOp1 for LayerNorm {
    fn name(&self) -> &'static str {
        "fused-layer-norm"
    }

    fn cpu_fwd(
        &self,
        storage: &CpuStorage,
        layout: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        let x = values(self.name(), storage, layout)?;
        let (_, width) = rows_and_width(layout);
        let mut out = vec![0f32; x.len()];
        let chunk = (width * ROWS_PER_TASK).max(1);
        out.par_chunks_mut(chunk).zip(x.par_chunks(chunk)).for_each(|(out, x)| {
            simd(
                #[inline(always)]
                || {
                    for (o, row) in out.chunks_exact_mut(width).zip(x.chunks_exact(width)) {
                        normalise_row(row, o);
                    }
                },
            )
        });
        Ok((CpuStorage::F32(out), layout.shape().clone()))
    }
}

/// AdaLN (`norm(x) * (1 + scale) + shift`, [`crate::layers::Modulation`]) with the modulation
/// read from a table that holds every modulation of the model side by side: `shift` at columns
/// `column..column + latent`, `scale` right after. With `swap_halves`, output sequence `n` is
/// made of input sequence `(n + N/2) % N` and its table row (the other stream of a batch that
/// stacks both streams: the keys of the cross-attention, paper Eq. 5).
///
/// # Shapes
/// - `x`: `[N, T, latent]`; `table`: `[N, columns]`; output `[N, T, latent]`
#[derive(Debug, Clone, Copy)]
pub struct AdaLn {
    /// The first column of the shift in the table.
    pub column: usize,
    /// Whether each output sequence is the other half's.
    pub swap_halves: bool,
}

impl CustomOp2 for AdaLn {
    fn name(&self) -> &'static str {
        "fused-adaln"
    }

    fn cpu_fwd(
        &self,
        x_storage: &CpuStorage,
        x_layout: &Layout,
        table_storage: &CpuStorage,
        table_layout: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        let x = values(self.name(), x_storage, x_layout)?;
        let table = values(self.name(), table_storage, table_layout)?;
        let (sequences, frames, latent) = x_layout.shape().dims3()?;
        let (table_rows, columns) = table_layout.shape().dims2()?;
        if table_rows != sequences || self.column + 2 * latent > columns {
            return Err(op_error(
                self.name(),
                format!(
                    "a [{sequences}, >= {}] table, got {:?}",
                    self.column + 2 * latent,
                    table_layout.dims()
                ),
            ));
        }
        if self.swap_halves && !sequences.is_multiple_of(2) {
            return Err(op_error(self.name(), "an even number of sequences to swap halves"));
        }
        let sequence_width = frames * latent;
        let mut out = vec![0f32; x.len()];
        let chunk = (latent * ROWS_PER_TASK).max(1);
        out.par_chunks_mut(chunk).enumerate().for_each(|(task, out)| {
            simd(
                #[inline(always)]
                || {
                    for (k, o) in out.chunks_exact_mut(latent).enumerate() {
                        let row = task * ROWS_PER_TASK + k;
                        let (n, t) = (row / frames.max(1), row % frames.max(1));
                        let source =
                            if self.swap_halves { (n + sequences / 2) % sequences } else { n };
                        let input = &x[source * sequence_width + t * latent..][..latent];
                        let modulation = &table[source * columns + self.column..][..2 * latent];
                        let (shift, scale) = modulation.split_at(latent);
                        normalise_row(input, o);
                        for ((o, &shift), &scale) in o.iter_mut().zip(shift).zip(scale) {
                            *o = *o * (scale + 1.0) + shift;
                        }
                    }
                },
            )
        });
        Ok((CpuStorage::F32(out), x_layout.shape().clone()))
    }
}

/// A linear layer's weight `[input, output]`, rearranged once for [`product`] (panels of
/// columns in the layout gemm's microkernel reads; `crate::matmul::Packed`).
#[derive(Debug, Clone)]
pub struct PackedMatrix(Arc<Packed>);

impl PackedMatrix {
    /// Rearranges a 2-D f32 `weight` (any layout: it is read as its values say).
    pub fn new(weight: &Tensor) -> candle_core::Result<Self> {
        let (input, output) = weight.dims2()?;
        let values = weight.flatten_all()?.to_vec1::<f32>()?;
        Ok(Self(Arc::new(Packed::new(&values, input, output))))
    }

    /// `(input, output)`.
    pub fn dims(&self) -> (usize, usize) {
        self.0.dims()
    }
}

/// A linear layer's product, `x @ weight` over the last dimension of `x`, through
/// [`crate::matmul::packed_product`] (no thread count read from `/proc/cpuinfo` per call as
/// `Tensor::matmul` does, no copy of the weights per call as gemm makes, one thread inside a
/// row group of the inference model).
///
/// # Shapes
/// - input `[..., input]`; output `[..., output]`
#[derive(Debug, Clone)]
struct Product(PackedMatrix);

impl CustomOp1 for Product {
    fn name(&self) -> &'static str {
        "fused-product"
    }

    fn cpu_fwd(
        &self,
        x_storage: &CpuStorage,
        x_layout: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        let x = values(self.name(), x_storage, x_layout)?;
        let Some((&input, leading)) = x_layout.dims().split_last() else {
            return Err(op_error(self.name(), "a non-scalar input"));
        };
        let rows = leading_rows(x_layout.dims())
            .ok_or_else(|| op_error(self.name(), "a row count that fits in usize"))?;
        let (weight_input, output) = self.0.dims();
        if weight_input != input {
            return Err(op_error(
                self.name(),
                format!("a weight of {input} rows, got {weight_input}"),
            ));
        }
        if rows.checked_mul(output).is_none() {
            return Err(op_error(self.name(), "an output size that fits in usize"));
        }
        let out = packed_product(x, rows, &self.0.0, Threads::Pool);
        Ok((CpuStorage::F32(out), Shape::from([leading, &[output]].concat())))
    }
}

/// The bias and activation after a linear layer's product: `y + bias`, or `SiLU(y + bias)`.
///
/// # Shapes
/// - `y`: `[..., features]`; `bias`: `[features]`; output `y`'s shape
#[derive(Debug, Clone, Copy)]
pub struct Bias {
    /// Whether SiLU follows the bias.
    pub silu: bool,
}

impl CustomOp2 for Bias {
    fn name(&self) -> &'static str {
        "fused-bias"
    }

    fn cpu_fwd(
        &self,
        y_storage: &CpuStorage,
        y_layout: &Layout,
        bias_storage: &CpuStorage,
        bias_layout: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        let y = values(self.name(), y_storage, y_layout)?;
        let bias = values(self.name(), bias_storage, bias_layout)?;
        let (_, width) = rows_and_width(y_layout);
        if bias.len() != width {
            return Err(op_error(self.name(), format!("a bias of {width}, got {}", bias.len())));
        }
        let mut out = vec![0f32; y.len()];
        let chunk = (width * ROWS_PER_TASK).max(1);
        out.par_chunks_mut(chunk).zip(y.par_chunks(chunk)).for_each(|(out, y)| {
            simd(
                #[inline(always)]
                || {
                    for (o, row) in out.chunks_exact_mut(width).zip(y.chunks_exact(width)) {
                        for ((o, &y), &b) in o.iter_mut().zip(row).zip(bias) {
                            *o = y + b;
                        }
                        if self.silu {
                            for o in o.iter_mut() {
                                *o /= 1.0 + exp(-*o);
                            }
                        }
                    }
                },
            )
        });
        Ok((CpuStorage::F32(out), y_layout.shape().clone()))
    }
}

/// A residual branch's end: `x + (y + bias)` (the linear layer's bias, then the residual sum,
/// in the composite's order).
///
/// # Shapes
/// - `x`, `y`: `[..., features]`; `bias`: `[features]`; output `x`'s shape
#[derive(Debug, Clone, Copy)]
pub struct Residual;

impl CustomOp3 for Residual {
    fn name(&self) -> &'static str {
        "fused-residual"
    }

    fn cpu_fwd(
        &self,
        x_storage: &CpuStorage,
        x_layout: &Layout,
        y_storage: &CpuStorage,
        y_layout: &Layout,
        bias_storage: &CpuStorage,
        bias_layout: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        let x = values(self.name(), x_storage, x_layout)?;
        let y = values(self.name(), y_storage, y_layout)?;
        let bias = values(self.name(), bias_storage, bias_layout)?;
        let (_, width) = rows_and_width(x_layout);
        if y.len() != x.len() || bias.len() != width {
            return Err(op_error(
                self.name(),
                format!(
                    "x and y of one shape and a bias of {width}, got {:?}, {:?}, {}",
                    x_layout.dims(),
                    y_layout.dims(),
                    bias.len()
                ),
            ));
        }
        let mut out = vec![0f32; x.len()];
        let chunk = (width * ROWS_PER_TASK).max(1);
        out.par_chunks_mut(chunk).zip(x.par_chunks(chunk)).zip(y.par_chunks(chunk)).for_each(
            |((out, x), y)| {
                simd(
                    #[inline(always)]
                    || {
                        for ((o, x), y) in out
                            .chunks_exact_mut(width)
                            .zip(x.chunks_exact(width))
                            .zip(y.chunks_exact(width))
                        {
                            for (((o, &x), &y), &b) in o.iter_mut().zip(x).zip(y).zip(bias) {
                                *o = x + (y + b);
                            }
                        }
                    },
                )
            },
        );
        Ok((CpuStorage::F32(out), x_layout.shape().clone()))
    }
}

/// Multi-head attention after the projections ([`crate::layers::Attention`] without its
/// linear layers): scores scaled by `1/sqrt(head)`, softmax fused, heads merged in the output.
/// Queries, keys and values are read where the (fused) projections put them, each head's two
/// products straight from there (`matmul::product_into`), so no head split,
/// transposition or biased copy is made.
///
/// The projections' biases enter without being added to every row (Eq. 5's attention is
/// unchanged):
/// - the query bias `b_q` adds `b_q . k_j` to every query's score for key `j`: one row of
///   `Tk` values per head, the scores' starting value;
/// - the key bias `b_k` adds `q_i . b_k + b_q . b_k` to query `i`'s scores for every key
///   alike, which the softmax removes;
/// - the value bias `b_v` adds `b_v` to every output row (a softmax row sums to 1), added
///   while the row is normalised.
///
/// # Shapes
/// - `queries`: `[N, Tq, Cq]`, the queries at columns `query_column..query_column + latent`
/// - `keys_values`: `[N, Tk, Ckv]`, keys at `key_column..`, values right after them
/// - `bias`: `[3 latent]`, the query, key and value biases; output `[N, Tq, latent]`
#[derive(Debug, Clone, Copy)]
pub struct Attention {
    /// Heads (dividing `latent`).
    pub heads: usize,
    /// Token width.
    pub latent: usize,
    /// The first column of the queries in their tensor.
    pub query_column: usize,
    /// The first column of the keys in their tensor (the values follow).
    pub key_column: usize,
}

impl CustomOp3 for Attention {
    fn name(&self) -> &'static str {
        "fused-attention"
    }

    fn cpu_fwd(
        &self,
        q_storage: &CpuStorage,
        q_layout: &Layout,
        kv_storage: &CpuStorage,
        kv_layout: &Layout,
        bias_storage: &CpuStorage,
        bias_layout: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        let queries = values(self.name(), q_storage, q_layout)?;
        let keys_values = values(self.name(), kv_storage, kv_layout)?;
        let bias = values(self.name(), bias_storage, bias_layout)?;
        let (sequences, query_frames, query_width) = q_layout.shape().dims3()?;
        let (kv_sequences, key_frames, kv_width) = kv_layout.shape().dims3()?;
        let l = self.latent;
        if self.heads == 0
            || !l.is_multiple_of(self.heads)
            || kv_sequences != sequences
            || key_frames == 0
            || self.query_column.checked_add(l).is_none_or(|end| end > query_width)
            || l.checked_mul(2)
                .and_then(|width| self.key_column.checked_add(width))
                .is_none_or(|end| end > kv_width)
            || l.checked_mul(3) != Some(bias.len())
        {
            return Err(op_error(
                self.name(),
                format!(
                    "queries [N, Tq, >= {} + {l}], keys and values [N, Tk >= 1, >= {} + 2 x {l}], a bias of 3 x {l} and heads dividing {l}; got {:?}, {:?}, {}",
                    self.query_column,
                    self.key_column,
                    q_layout.dims(),
                    kv_layout.dims(),
                    bias.len()
                ),
            ));
        }
        let head = l / self.heads;
        let scale = 1.0 / (head as f32).sqrt();
        let (query_bias, value_bias) = (&bias[..l], &bias[2 * l..]);
        let mut out = vec![0f32; sequences * query_frames * l];
        // One task per block of a sequence's query rows, its heads one after the other: a whole
        // sequence per task where there are enough sequences for the threads (always inside a
        // row group), shorter blocks where there are not (a many-core machine).
        let threads = Threads::Pool.count();
        let per_sequence =
            if sequences >= threads { 1 } else { threads.div_ceil(sequences.max(1)) };
        let block = query_frames.div_ceil(per_sequence).max(1);
        out.par_chunks_mut((query_frames * l).max(1)).enumerate().for_each(|(n, out)| {
            out.par_chunks_mut((block * l).max(1)).enumerate().for_each(|(b, out)| {
                let rows = out.len() / l.max(1);
                let queries =
                    &queries[(n * query_frames + b * block) * query_width..][..rows * query_width];
                let keys_values =
                    &keys_values[n * key_frames * kv_width..][..key_frames * kv_width];
                let mut scores = vec![0f32; rows * key_frames];
                let mut key_scores = vec![0f32; key_frames];
                let mut inverse = vec![0f32; rows];
                for h in 0..self.heads {
                    let (query_column, key_column) =
                        (self.query_column + h * head, self.key_column + h * head);
                    let key_view = |column: usize| {
                        Strided::rows_apart(&keys_values[column..], key_frames, head, kv_width)
                    };
                    let (keys, values) = (key_view(key_column), key_view(key_column + l));
                    let query =
                        Strided::rows_apart(&queries[query_column..], rows, head, query_width);
                    // The keys transposed, read in place: `[head, Tk]`.
                    let keys_t = keys.transposed();
                    let query_bias = &query_bias[h * head..][..head];
                    simd(
                        #[inline(always)]
                        || {
                            for (j, score) in key_scores.iter_mut().enumerate() {
                                let key = &keys_values[j * kv_width + key_column..][..head];
                                *score = scale * dot(query_bias, key);
                            }
                            for row in scores.chunks_exact_mut(key_frames) {
                                row.copy_from_slice(&key_scores);
                            }
                        },
                    );
                    product_into(
                        &mut scores,
                        key_frames,
                        (query, keys_t),
                        scale,
                        true,
                        Threads::Calling,
                    );
                    simd(
                        #[inline(always)]
                        || {
                            let rows = scores.chunks_exact_mut(key_frames);
                            for (row, inverse) in rows.zip(inverse.iter_mut()) {
                                let largest = max(row);
                                for s in row.iter_mut() {
                                    *s = exp(*s - largest);
                                }
                                *inverse = 1.0 / sum(row, |s| s);
                            }
                        },
                    );
                    let weights = Strided::row_major(&scores, rows, key_frames);
                    let heads_out = &mut out[h * head..];
                    product_into(heads_out, l, (weights, values), 1.0, false, Threads::Calling);
                    let value_bias = &value_bias[h * head..][..head];
                    simd(
                        #[inline(always)]
                        || {
                            for (row, &inverse) in heads_out.chunks_mut(l).zip(&inverse) {
                                for (o, &b) in row[..head].iter_mut().zip(value_bias) {
                                    *o = o.mul_add(inverse, b);
                                }
                            }
                        },
                    );
                }
            });
        });
        Ok((CpuStorage::F32(out), Shape::from((sequences, query_frames, l))))
    }
}

/// `a . b` in [`LANES`] independent partial sums (see [`sum`]).
#[inline(always)]
fn dot(a: &[f32], b: &[f32]) -> f32 {
    let mut lanes = [0f32; LANES];
    let (chunks_a, chunks_b) = (a.chunks_exact(LANES), b.chunks_exact(LANES));
    let tail: f32 = chunks_a.remainder().iter().zip(chunks_b.remainder()).map(|(x, y)| x * y).sum();
    for (chunk_a, chunk_b) in chunks_a.zip(chunks_b) {
        for ((lane, &x), &y) in lanes.iter_mut().zip(chunk_a).zip(chunk_b) {
            *lane = x.mul_add(y, *lane);
        }
    }
    lanes.iter().sum::<f32>() + tail
}

/// `x` through [`LayerNorm`].
pub fn layer_norm(x: &Tensor) -> candle_core::Result<Tensor> {
    x.apply_op1_no_bwd(&LayerNorm)
}

/// `x` through [`AdaLn`] with the modulation at `column` of `table`.
pub fn adaln(
    x: &Tensor,
    table: &Tensor,
    column: usize,
    swap_halves: bool,
) -> candle_core::Result<Tensor> {
    x.apply_op2_no_bwd(table, &AdaLn { column, swap_halves })
}

/// `x @ weight` over the last dimension of `x` (contiguous).
pub fn product(x: &Tensor, weight: &PackedMatrix) -> candle_core::Result<Tensor> {
    x.apply_op1_no_bwd(&Product(weight.clone()))
}

/// `y + bias`, then SiLU when `silu`.
pub fn bias(y: &Tensor, bias: &Tensor, silu: bool) -> candle_core::Result<Tensor> {
    y.apply_op2_no_bwd(bias, &Bias { silu })
}

/// `x + (y + bias)`.
pub fn residual(x: &Tensor, y: &Tensor, bias: &Tensor) -> candle_core::Result<Tensor> {
    x.apply_op3_no_bwd(y, bias, &Residual)
}

/// The attention of [`Attention`].
pub fn attention(
    queries: &Tensor,
    keys_values: &Tensor,
    bias: &Tensor,
    op: Attention,
) -> candle_core::Result<Tensor> {
    queries.apply_op3_no_bwd(keys_values, bias, &op)
}
