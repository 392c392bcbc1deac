//! Forward-only fused CPU operations of the inference path ([`crate::inference`]): each replaces
//! a chain of candle operations (one pass over memory instead of four to eight, each a fresh
//! allocation and, in candle, single-threaded) and spreads its rows over the rayon pool.
//!
//! None of them has a backward pass: training never uses them (Architecture Invariant: every
//! operation that trains has a backward pass; only the no-grad inference path may use
//! forward-only fused operations). They accept contiguous f32 tensors on the CPU; the inference
//! path uses the composite model on any other device or dtype. Each is tested equal to the
//! composite operations it replaces (`tests/fused.rs`).

use candle_core::{CpuStorage, CustomOp1, CustomOp2, CustomOp3, Layout, Shape, Tensor};
use rayon::prelude::*;

use crate::differentiable::{ROWS_PER_TASK, op_error, simd};
use crate::layers::LAYER_NORM_EPS;

/// The values of a contiguous f32 tensor.
fn values<'a>(
    op: &str,
    storage: &'a CpuStorage,
    layout: &Layout,
) -> candle_core::Result<&'a [f32]> {
    crate::differentiable::values::<f32>(op, storage, layout)
}

/// Query rows per rayon task of the attention, attended together by the blocked kernel.
const QUERY_BLOCK: usize = 4;

/// Floats per SIMD tile of the blocked attention kernel: one AVX-512 register, two AVX2 ones.
/// With [`QUERY_BLOCK`] rows that is four (eight) independent sums in flight, enough to keep
/// the FMA units busy; 8 lanes were about 10% slower for a `small` sample (session 16).
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

/// `e^x` to about 1 ulp for `x` in `[-87, 88]` (clamped outside), in plain arithmetic so that
/// loops over it vectorise (a call to libm's `expf` does not): `x = n ln 2 + r` with
/// `|r| <= ln 2 / 2`, a degree-7 expansion of `e^r` (Cephes' `expf` coefficients), times `2^n`
/// built in the exponent bits.
#[inline(always)]
pub(crate) fn exp(x: f32) -> f32 {
    const LOG2_E: f32 = std::f32::consts::LOG2_E;
    // ln 2 split in a part exact in f32 and the rest (Cody and Waite).
    const LN2_HIGH: f32 = 0.693_359_4;
    const LN2_LOW: f32 = -2.121_944_4e-4;
    // Adding and removing 1.5 * 2^23 rounds to the nearest integer in plain arithmetic
    // (`round` is a libm call on baseline x86-64, which would stop the vectorisation).
    const ROUNDING: f32 = 12_582_912.0;
    let x = x.clamp(-87.0, 88.0);
    let n = (x * LOG2_E + ROUNDING) - ROUNDING;
    let r = x - n * LN2_HIGH - n * LN2_LOW;
    let p = 1.987_569_2e-4_f32;
    let p = p * r + 1.398_199_9e-3;
    let p = p * r + 8.333_452e-3;
    let p = p * r + 4.166_579_6e-2;
    let p = p * r + 0.166_666_65;
    let p = p * r + 0.5;
    let e_r = p * r * r + r + 1.0;
    e_r * f32::from_bits(((n as i32 + 127) as u32) << 23)
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

/// A linear layer's product, `x @ weight` over the last dimension of `x`, through
/// [`crate::matmul::product`] (no thread count read from `/proc/cpuinfo` per call, one thread
/// inside a row group of the inference model).
///
/// # Shapes
/// - `x`: `[..., input]`; `weight`: `[input, output]`; output `[..., output]`
#[derive(Debug, Clone, Copy)]
pub struct Product;

impl CustomOp2 for Product {
    fn name(&self) -> &'static str {
        "fused-product"
    }

    fn cpu_fwd(
        &self,
        x_storage: &CpuStorage,
        x_layout: &Layout,
        weight_storage: &CpuStorage,
        weight_layout: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        let x = values(self.name(), x_storage, x_layout)?;
        let weight = values(self.name(), weight_storage, weight_layout)?;
        let Some((&input, leading)) = x_layout.dims().split_last() else {
            return Err(op_error(self.name(), "a non-scalar input"));
        };
        // Counted from the leading dimensions: with `input` zero the element count says nothing.
        let rows = leading
            .iter()
            .try_fold(1usize, |rows, &d| rows.checked_mul(d))
            .ok_or_else(|| op_error(self.name(), "a row count that fits in usize"))?;
        let &[weight_input, output] = weight_layout.dims() else {
            return Err(op_error(self.name(), "a weight of two dimensions"));
        };
        if weight_input != input {
            return Err(op_error(
                self.name(),
                format!("a weight of {input} rows, got {weight_input}"),
            ));
        }
        let out = crate::matmul::product(x, weight, rows, input, output);
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
/// linear layers): the projections' biases added on the fly, scores scaled by
/// `1/sqrt(head)`, softmax fused, heads merged in the output. Queries, keys and values are read
/// where the (fused) projections put them, so no head split or transposition is copied.
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

impl Attention {
    /// Each sequence's biased keys or values per head: `[N][heads][Tk][head]`, or with a
    /// `transposed_stride` `[N][heads][head][stride]` (the keys, zero-padded to `stride >= Tk`:
    /// the scores of a query are then sums of contiguous rows, which vectorise without
    /// horizontal sums).
    fn gather(
        &self,
        source: &[f32],
        (frames, width, column): (usize, usize, usize),
        bias: &[f32],
        transposed_stride: Option<usize>,
    ) -> Vec<f32> {
        let head = self.latent / self.heads;
        let sequences = source.len() / (frames * width).max(1);
        let per_head = transposed_stride.unwrap_or(frames) * head;
        let mut out = vec![0f32; sequences * self.heads * per_head];
        out.par_chunks_mut((self.heads * per_head).max(1)).enumerate().for_each(|(n, out)| {
            for h in 0..self.heads {
                let block = &mut out[h * per_head..][..per_head];
                for j in 0..frames {
                    let from = &source[(n * frames + j) * width + column + h * head..][..head];
                    for (d, (&f, &b)) in from.iter().zip(&bias[h * head..]).enumerate() {
                        let at = match transposed_stride {
                            Some(stride) => d * stride + j,
                            None => j * head + d,
                        };
                        block[at] = f + b;
                    }
                }
            }
        });
        out
    }

    /// One query row of one head: `softmax(q K^T / sqrt(head)) V` into `out`.
    ///
    /// `keys_t` is `[head][stride]`, `values` `[Tk][head]`; `scores` is scratch of `Tk`.
    #[inline(always)]
    fn attend(
        query: &[f32],
        keys_t: &[f32],
        values: &[f32],
        (stride, scale): (usize, f32),
        scores: &mut [f32],
        out: &mut [f32],
    ) {
        let frames = scores.len();
        scores.fill(0.0);
        for (&q, keys) in query.iter().zip(keys_t.chunks_exact(stride)) {
            for (s, &k) in scores.iter_mut().zip(keys) {
                *s = q.mul_add(k, *s);
            }
        }
        let largest = max(scores) * scale;
        for s in scores.iter_mut() {
            *s = exp(*s * scale - largest);
        }
        let total = sum(scores, |s| s);
        out.fill(0.0);
        for (&w, value) in scores[..frames].iter().zip(values.chunks_exact(out.len())) {
            let w = w / total;
            for (o, &v) in out.iter_mut().zip(value) {
                *o = w.mul_add(v, *o);
            }
        }
    }

    /// [`Self::attend`] for [`QUERY_BLOCK`] query rows of one head at once, register-blocked:
    /// each tile of [`LANES`] keys (or head channels) is loaded once for all the rows while
    /// their sums stay in registers. `head` and `stride` must be multiples of [`LANES`]; the
    /// zero padding keys past `Tk` never enter the softmax.
    ///
    /// `queries` is `[QUERY_BLOCK][head]`, `keys_t` `[head][stride]`, `values` `[Tk][head]`,
    /// `scores` scratch of `[QUERY_BLOCK][stride]`; `out[r]` receives row `r`.
    #[inline(always)]
    fn attend_block(
        queries: &[f32],
        keys_t: &[f32],
        values: &[f32],
        (frames, stride, scale): (usize, usize, f32),
        scores: &mut [f32],
        out: &mut [&mut [f32]; QUERY_BLOCK],
    ) {
        let head = queries.len() / QUERY_BLOCK;
        for tile in (0..stride).step_by(LANES) {
            let mut sums = [[0f32; LANES]; QUERY_BLOCK];
            for d in 0..head {
                let keys = &keys_t[d * stride + tile..][..LANES];
                for (r, sums) in sums.iter_mut().enumerate() {
                    let q = queries[r * head + d];
                    for (s, &k) in sums.iter_mut().zip(keys) {
                        *s = q.mul_add(k, *s);
                    }
                }
            }
            for (r, sums) in sums.iter().enumerate() {
                scores[r * stride + tile..][..LANES].copy_from_slice(sums);
            }
        }
        let mut inverse = [0f32; QUERY_BLOCK];
        for (r, inverse) in inverse.iter_mut().enumerate() {
            let row = &mut scores[r * stride..][..frames];
            let largest = max(row) * scale;
            for s in row.iter_mut() {
                *s = exp(*s * scale - largest);
            }
            *inverse = 1.0 / sum(row, |s| s);
        }
        for tile in (0..head).step_by(LANES) {
            let mut sums = [[0f32; LANES]; QUERY_BLOCK];
            for j in 0..frames {
                let value = &values[j * head + tile..][..LANES];
                for (r, sums) in sums.iter_mut().enumerate() {
                    let w = scores[r * stride + j];
                    for (s, &v) in sums.iter_mut().zip(value) {
                        *s = w.mul_add(v, *s);
                    }
                }
            }
            for ((out, sums), &inverse) in out.iter_mut().zip(&sums).zip(&inverse) {
                for (o, &s) in out[tile..][..LANES].iter_mut().zip(sums) {
                    *o = s * inverse;
                }
            }
        }
    }
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
            || self.query_column + l > query_width
            || self.key_column + 2 * l > kv_width
            || bias.len() != 3 * l
        {
            return Err(op_error(
                self.name(),
                format!(
                    "queries [N, Tq, >= {}], keys and values [N, Tk, >= {}], a bias of {} and heads dividing {l}; got {:?}, {:?}, {}",
                    self.query_column + l,
                    self.key_column + 2 * l,
                    3 * l,
                    q_layout.dims(),
                    kv_layout.dims(),
                    bias.len()
                ),
            ));
        }
        let head = l / self.heads;
        let scale = 1.0 / (head as f32).sqrt();
        // The keys' rows are padded to whole SIMD tiles for the blocked kernel.
        let stride = key_frames.div_ceil(LANES) * LANES;
        let source = (key_frames, kv_width, self.key_column);
        let keys_t = self.gather(keys_values, source, &bias[l..2 * l], Some(stride));
        let source = (key_frames, kv_width, self.key_column + l);
        let vals = self.gather(keys_values, source, &bias[2 * l..], None);
        let (keys_per_head, values_per_head) = (stride * head, key_frames * head);
        let keys_of =
            |n: usize, h: usize| &keys_t[(n * self.heads + h) * keys_per_head..][..keys_per_head];
        let values_of =
            |n: usize, h: usize| &vals[(n * self.heads + h) * values_per_head..][..values_per_head];
        let load_query = |row: usize, h: usize, into: &mut [f32]| {
            let q_row = &queries[row * query_width + self.query_column + h * head..][..head];
            for ((into, &x), &b) in into.iter_mut().zip(q_row).zip(&bias[h * head..]) {
                *into = x + b;
            }
        };
        // Tasks of QUERY_BLOCK rows: whole blocks of one sequence when the frames divide.
        let blocked = head.is_multiple_of(LANES) && query_frames.is_multiple_of(QUERY_BLOCK);
        let mut out = vec![0f32; sequences * query_frames * l];
        out.par_chunks_mut((l * QUERY_BLOCK).max(1)).enumerate().for_each(|(task, out)| {
            simd(
                #[inline(always)]
                || {
                    let first = task * QUERY_BLOCK;
                    let mut query = vec![0f32; QUERY_BLOCK * head];
                    let mut scores = vec![0f32; QUERY_BLOCK * stride];
                    if blocked {
                        let n = first / query_frames;
                        let sizes = (key_frames, stride, scale);
                        for h in 0..self.heads {
                            for (r, query) in query.chunks_exact_mut(head).enumerate() {
                                load_query(first + r, h, query);
                            }
                            let mut rows =
                                out.chunks_exact_mut(l).map(|o| &mut o[h * head..][..head]);
                            let mut outs: [&mut [f32]; QUERY_BLOCK] = std::array::from_fn(|_| {
                                rows.next().expect("whole blocks when the frames divide")
                            });
                            let (keys, values) = (keys_of(n, h), values_of(n, h));
                            Self::attend_block(&query, keys, values, sizes, &mut scores, &mut outs);
                        }
                    } else {
                        for (r, o) in out.chunks_exact_mut(l).enumerate() {
                            let row = first + r;
                            let n = row / query_frames.max(1);
                            for h in 0..self.heads {
                                let query = &mut query[..head];
                                load_query(row, h, query);
                                let (keys, values) = (keys_of(n, h), values_of(n, h));
                                let scores = &mut scores[..key_frames];
                                let o = &mut o[h * head..][..head];
                                Self::attend(query, keys, values, (stride, scale), scores, o);
                            }
                        }
                    }
                },
            )
        });
        Ok((CpuStorage::F32(out), Shape::from((sequences, query_frames, l))))
    }
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

/// `x @ weight` over the last dimension of `x`.
pub fn product(x: &Tensor, weight: &Tensor) -> candle_core::Result<Tensor> {
    x.apply_op2_no_bwd(weight, &Product)
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

#[cfg(test)]
mod tests {
    /// The polynomial `exp` against f64's over its whole range and the clamped ends.
    #[test]
    fn exp_is_accurate_to_a_few_ulp() {
        let mut worst = 0f64;
        for k in 0..=1_000_000 {
            let x = -87.0 + 175.0 * k as f32 / 1e6;
            let exact = (x as f64).exp();
            worst = worst.max(((super::exp(x) as f64) - exact).abs() / exact);
        }
        assert!(worst < 3e-7, "relative error {worst}");
        assert!(super::exp(-1e4) > 0.0 && super::exp(-1e4) < 1e-37);
        assert!(super::exp(1e4).is_finite());
        assert_eq!(super::exp(0.0), 1.0);
    }
}
