//! f32 and f64 matrix products on the CPU, straight through `gemm` (the crate candle's CPU
//! backend calls for `Tensor::matmul`): [`product_into`] on strided views read in place (the
//! attentions' per-head products, the training linear layers' products, and under
//! [`packed_product`] the inference path's, on weights packed once at load, [`Packed`]). One
//! of the two modules of the workspace that use `unsafe` (the workspace denies it everywhere
//! else; a tidy test keeps it to them; the other sets an environment variable, `dex2hoi-cli`'s
//! `candle_threads`).
//!
//! Why not `Tensor::matmul`: candle asks for its thread count on every
//! product (`candle_core::utils::get_num_threads`), which on Linux reads and parses
//! `/proc/cpuinfo` each time unless `RAYON_NUM_THREADS` is set: tens of microseconds per call,
//! against a few hundred for a product of a `small` sample, and about 8% of its time in
//! system calls (measured with perf). It also always splits the product over every thread, also
//! inside a row group of [`crate::InferenceModel::forward`] whose neighbours already have
//! work. Called here, a product runs on one thread inside a row group ([`in_row_group`]) and
//! as its caller chooses elsewhere ([`Threads`]).
//!
//! Why `unsafe`: `gemm::gemm` takes raw pointers and strides, and safe Rust cannot call it.
//! [`product_into`], the one function that calls it, checks every length and stride (with
//! overflow-checked sizes) and that no two output elements share a place before the call, so
//! that safe callers cannot make it read or write out of bounds or race.
#![allow(unsafe_code)]

use std::cell::Cell;

use gemm::Parallelism;
use rayon::prelude::*;

thread_local! {
    /// Whether this thread runs one row group of a batch split over the pool's threads.
    static IN_ROW_GROUP: Cell<bool> = const { Cell::new(false) };
}

/// Runs `work` as one row group: every product it makes ([`product_into`], [`packed_product`])
/// runs on this thread alone (the pool's other threads run the other groups).
pub(crate) fn in_row_group<R>(work: impl FnOnce() -> R) -> R {
    /// Restores the flag however `work` ends (a panic unwinding through a rayon task too).
    struct Restore(bool);
    impl Drop for Restore {
        fn drop(&mut self) {
            IN_ROW_GROUP.with(|flag| flag.set(self.0));
        }
    }
    let _restore = Restore(IN_ROW_GROUP.with(|flag| flag.replace(true)));
    work()
}

/// The element types [`product_into`] takes: those gemm has kernels for that the model uses
/// (gemm panics on any other type; the trait is sealed so that no other can be named).
pub(crate) trait Element: Copy + 'static + sealed::Sealed {
    /// `0` (the value of an empty sum).
    const ZERO: Self;
    /// `1` (the factor of an accumulated output).
    const ONE: Self;
}

mod sealed {
    pub trait Sealed {}
    impl Sealed for f32 {}
    impl Sealed for f64 {}
}

impl Element for f32 {
    const ZERO: Self = 0.0;
    const ONE: Self = 1.0;
}

impl Element for f64 {
    const ZERO: Self = 0.0;
    const ONE: Self = 1.0;
}

/// A matrix read in place from a slice: element `(r, c)` at `r * row_stride + c * column_stride`
/// (a head's columns of a projection, or a transposed view, without copying).
#[derive(Debug, Clone, Copy)]
pub(crate) struct Strided<'a, T = f32> {
    pub data: &'a [T],
    pub rows: usize,
    pub columns: usize,
    pub row_stride: usize,
    pub column_stride: usize,
}

impl<'a, T> Strided<'a, T> {
    /// A `[rows, columns]` matrix stored row after row.
    pub(crate) fn row_major(data: &'a [T], rows: usize, columns: usize) -> Self {
        Self::rows_apart(data, rows, columns, columns)
    }

    /// A `[rows, columns]` matrix whose rows start `row_stride` values apart (the first
    /// columns of wider rows, such as one head's columns of a projection).
    pub(crate) fn rows_apart(
        data: &'a [T],
        rows: usize,
        columns: usize,
        row_stride: usize,
    ) -> Self {
        Self { data, rows, columns, row_stride, column_stride: 1 }
    }

    /// The transposed matrix, read in place.
    pub(crate) fn transposed(self) -> Self {
        Self {
            rows: self.columns,
            columns: self.rows,
            row_stride: self.column_stride,
            column_stride: self.row_stride,
            ..self
        }
    }

    /// Whether every element's index is inside `data` (overflow-checked); empty views always
    /// are.
    fn fits(&self) -> bool {
        if self.rows == 0 || self.columns == 0 {
            return true;
        }
        let last = (self.rows - 1)
            .checked_mul(self.row_stride)
            .zip((self.columns - 1).checked_mul(self.column_stride))
            .and_then(|(r, c)| r.checked_add(c));
        last.is_some_and(|last| last < self.data.len())
    }
}

/// The threads a product runs on.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Threads {
    /// The calling thread (products small enough, or callers already spread over the pool).
    Calling,
    /// Every thread of the current rayon pool; the calling thread alone inside a row group
    /// ([`in_row_group`]), whose neighbours already have work.
    Pool,
}

impl Threads {
    /// How many threads the work may spread over.
    pub(crate) fn count(self) -> usize {
        match self {
            Self::Pool if !IN_ROW_GROUP.with(Cell::get) => rayon::current_num_threads().max(1),
            _ => 1,
        }
    }

    fn parallelism(self) -> Parallelism {
        match self.count() {
            1 => Parallelism::None,
            threads => Parallelism::Rayon(threads),
        }
    }
}

/// `out = scale * lhs @ rhs`, or with `accumulate` `out += scale * lhs @ rhs`: `lhs` is
/// `[rows, inner]`, `rhs` `[inner, columns]`, both read in place; `out` holds row `r` at
/// `r * out_row_stride..` (`out_row_stride >= columns`, so that no two elements share a
/// place). The attentions' per-head products (`crate::fused::Attention` and the training
/// attention, in f64 too for its gradient checks) on the calling thread, the training linear
/// layers' on the pool.
///
/// # Panics
/// If the inner sizes differ, a view reaches past its slice, `out` is too short or its row
/// stride below `columns`, or a size overflows `usize`.
pub(crate) fn product_into<T: Element>(
    out: &mut [T],
    out_row_stride: usize,
    (lhs, rhs): (Strided<'_, T>, Strided<'_, T>),
    scale: T,
    accumulate: bool,
    threads: Threads,
) {
    let (rows, inner, columns) = (lhs.rows, lhs.columns, rhs.columns);
    assert_eq!(rhs.rows, inner, "lhs is [{rows}, {inner}], rhs has {} rows", rhs.rows);
    assert!(lhs.fits() && rhs.fits(), "a view reaches past its slice");
    assert!(out_row_stride >= columns, "out's row stride {out_row_stride} below {columns}");
    if rows == 0 || columns == 0 {
        return;
    }
    let out_end = (rows - 1)
        .checked_mul(out_row_stride)
        .and_then(|r| r.checked_add(columns))
        .expect("an output size that fits in usize");
    assert!(out_end <= out.len(), "out holds {} values, needs {out_end}", out.len());
    if inner == 0 {
        // An empty sum is zero: no call with empty or dangling pointers.
        if !accumulate {
            for row in out.chunks_mut(out_row_stride).take(rows) {
                row[..columns].fill(T::ZERO);
            }
        }
        return;
    }
    let stride = |s: usize| isize::try_from(s).expect("a stride that fits in isize");
    // SAFETY: every index gemm reads is below its slice's length: `lhs` element `(r, i)` at
    // `r * lhs.row_stride + i * lhs.column_stride` for `r < rows`, `i < inner`, and `rhs`
    // element `(i, c)` likewise, are at most the last index checked by `fits`; `out` element
    // `(r, c)` at `r * out_row_stride + c < out_end <= out.len()`, each at its own index (row
    // stride at least `columns`, column stride 1), so threads that gemm spreads the work over
    // write disjoint elements; gemm joins them before it returns. The slices are live for the
    // whole call and `out` is borrowed mutably, apart from the inputs. With `read_dst` false
    // gemm only writes `out` (alpha unused). `T` is f32 or f64 (`Element` is sealed), types
    // gemm has kernels for.
    unsafe {
        gemm::gemm(
            rows,
            columns,
            inner,
            out.as_mut_ptr(),
            1,
            stride(out_row_stride),
            accumulate,
            lhs.data.as_ptr(),
            stride(lhs.column_stride),
            stride(lhs.row_stride),
            rhs.data.as_ptr(),
            stride(rhs.column_stride),
            stride(rhs.row_stride),
            T::ONE,
            scale,
            false,
            false,
            false,
            threads.parallelism(),
        );
    }
}

/// Columns per panel of a [`Packed`] matrix: the height of gemm's f32 AVX-512 microkernel
/// (4 registers of 16 lanes), so that a panel is already in the layout gemm would copy the
/// weights into before its microkernel reads them.
const PANEL: usize = 64;

/// Rows of `x` per gemm call of [`packed_product`]: gemm copies ("packs") the weights anyway
/// when it multiplies them by more than 8 x 6 rows (its default packing threshold times its
/// AVX-512 microkernel's width). Where the microkernel differs (AVX2) gemm packs as before.
const ROW_CHUNK: usize = 48;

/// A `[inner, columns]` weight matrix rearranged once, at load time, for [`packed_product`]:
/// panel after panel of [`PANEL`] columns (the last one narrower), each `[inner, width]` row
/// after row.
///
/// Why: gemm copies the weights into this layout inside every product (the model's weights are
/// its left operand once it has transposed the problem for a row-major output), which for the
/// inference path's row groups (120 rows for `small`) takes about 13% of a `paper` sample and
/// 8% of a `small` one. Measured alone (one thread, 16 different weight matrices in turn):
/// 97 GFLOP/s packed by gemm, 112 GFLOP/s from panels, for `[120, 512] @ [512, 1536]` and
/// `[120, 256] @ [256, 768]` alike.
#[derive(Debug, Clone)]
pub(crate) struct Packed {
    data: Vec<f32>,
    inner: usize,
    columns: usize,
}

impl Packed {
    /// Rearranges a row-major `[inner, columns]` `weight`.
    ///
    /// # Panics
    /// If `weight` does not hold `inner * columns` values.
    pub(crate) fn new(weight: &[f32], inner: usize, columns: usize) -> Self {
        let size = inner.checked_mul(columns).expect("a matrix size that fits in usize");
        assert_eq!(weight.len(), size, "the weight is not [{inner}, {columns}]");
        let mut data = Vec::with_capacity(size);
        if columns > 0 {
            for start in (0..columns).step_by(PANEL) {
                let width = PANEL.min(columns - start);
                for row in weight.chunks_exact(columns) {
                    data.extend_from_slice(&row[start..start + width]);
                }
            }
        }
        Self { data, inner, columns }
    }

    /// `(inner, columns)`.
    pub(crate) fn dims(&self) -> (usize, usize) {
        (self.inner, self.columns)
    }

    /// Each panel with its first column: `[inner, width]`.
    fn panels(&self) -> impl Iterator<Item = (usize, Strided<'_, f32>)> {
        (0..self.columns).step_by(PANEL).map(|start| {
            let width = PANEL.min(self.columns - start);
            let data = &self.data[start * self.inner..][..self.inner * width];
            (start, Strided::row_major(data, self.inner, width))
        })
    }
}

/// `x @ weight` for a row-major `[rows, inner]` `x`: the row-major `[rows, columns]` product,
/// at most [`ROW_CHUNK`] rows by [`PANEL`] columns per gemm call. On the calling thread with
/// [`Threads::Calling`] or inside a row group; the chunks of rows spread evenly over the pool
/// otherwise.
///
/// # Panics
/// If `x` does not hold `rows * inner` values, or a size overflows `usize`.
pub(crate) fn packed_product(
    x: &[f32],
    rows: usize,
    weight: &Packed,
    threads: Threads,
) -> Vec<f32> {
    let (inner, columns) = weight.dims();
    let size = |a: usize, b: usize| a.checked_mul(b).expect("a matrix size that fits in usize");
    assert_eq!(x.len(), size(rows, inner), "x is not [{rows}, {inner}]");
    let mut out = vec![0f32; size(rows, columns)];
    if out.is_empty() {
        return out;
    }
    // Outside a row group the chunks spread over the pool: as many per thread (at most
    // ROW_CHUNK rows each), so that every thread has work on a many-core machine too.
    let threads = threads.count();
    let per_thread = rows.div_ceil(threads * ROW_CHUNK);
    let chunk_rows = ROW_CHUNK.min(rows.div_ceil(threads * per_thread)).max(1);
    let chunk = |(index, out): (usize, &mut [f32])| {
        let rows_here = out.len() / columns;
        let x = &x[index * chunk_rows * inner..][..rows_here * inner];
        let lhs = Strided::row_major(x, rows_here, inner);
        for (start, panel) in weight.panels() {
            product_into(&mut out[start..], columns, (lhs, panel), 1.0, false, Threads::Calling);
        }
    };
    let chunks = chunk_rows * columns;
    if threads == 1 {
        out.chunks_mut(chunks).enumerate().for_each(chunk);
    } else {
        out.par_chunks_mut(chunks).enumerate().for_each(chunk);
    }
    out
}

#[cfg(test)]
mod tests {
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    use super::{Packed, Strided, Threads, packed_product, product_into};

    /// Element `(r, c)` of a view, read by index.
    fn at(view: &Strided<'_>, r: usize, c: usize) -> f32 {
        view.data[r * view.row_stride + c * view.column_stride]
    }

    /// `product_into` against a plain triple loop: row-major, transposed and padded views,
    /// odd sizes, accumulating or not, on the calling thread or split over a pool of two, the
    /// output's padding left alone.
    #[test]
    fn product_into_equals_the_plain_sum_on_strided_views() {
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let pair = rayon::ThreadPoolBuilder::new().num_threads(2).build().expect("a pool");
        for (rows, inner, columns) in [
            (1, 1, 1),
            (7, 3, 5),
            (60, 64, 60),
            (60, 60, 64),
            (17, 33, 129),
            (3, 0, 4),
            (300, 200, 150),
        ] {
            for (transposed_lhs, transposed_rhs, accumulate, threads) in [
                (false, false, false, Threads::Calling),
                (true, false, true, Threads::Pool),
                (false, true, false, Threads::Pool),
                (true, true, true, Threads::Calling),
            ] {
                // Each operand sits inside a wider buffer, possibly transposed.
                let view = |data, rows, columns, transposed: bool, pad: usize| {
                    if transposed {
                        Strided { data, rows, columns, row_stride: 1, column_stride: rows + pad }
                    } else {
                        Strided { data, rows, columns, row_stride: columns + pad, column_stride: 1 }
                    }
                };
                let mut buffer = |len: usize| -> Vec<f32> {
                    (0..len).map(|_| rng.random_range(-1.0..1.0)).collect()
                };
                let (lhs_values, rhs_values) =
                    (buffer((rows + 3) * (inner + 3)), buffer((inner + 2) * (columns + 2)));
                let lhs = view(&lhs_values, rows, inner, transposed_lhs, 3);
                let rhs = view(&rhs_values, inner, columns, transposed_rhs, 2);
                let out_stride = columns + 1;
                let start: Vec<f32> =
                    (0..rows * out_stride).map(|_| rng.random_range(-1.0..1.0)).collect();
                let mut out = start.clone();
                pair.install(|| {
                    product_into(&mut out, out_stride, (lhs, rhs), 0.5, accumulate, threads);
                });
                for r in 0..rows {
                    for c in 0..out_stride {
                        let old = start[r * out_stride + c];
                        let expected = if c == columns {
                            old
                        } else {
                            let sum: f32 =
                                (0..inner).map(|i| at(&lhs, r, i) * at(&rhs, i, c)).sum();
                            0.5 * sum + if accumulate { old } else { 0.0 }
                        };
                        let got = out[r * out_stride + c];
                        assert!(
                            (got - expected).abs() < 1e-4,
                            "{rows}x{inner}x{columns} ({r}, {c}): {got} vs {expected}"
                        );
                    }
                }
            }
        }
        // Empty outputs write nothing.
        let mut out = vec![7f32; 3];
        let empty = Strided { data: &[], rows: 0, columns: 4, row_stride: 4, column_stride: 1 };
        let rhs =
            Strided { data: &[1.0; 12], rows: 4, columns: 3, row_stride: 3, column_stride: 1 };
        product_into(&mut out, 3, (empty, rhs), 1.0, false, Threads::Calling);
        assert_eq!(out, [7.0; 3]);
    }

    /// The thread count changes who computes which part of a product, not its sums: the same
    /// bits on pools of one and four threads (training relies on it to resume bit for bit).
    #[test]
    fn products_on_the_pool_do_not_depend_on_its_thread_count() {
        let mut rng = ChaCha8Rng::seed_from_u64(6);
        let (rows, inner, columns) = (300, 200, 150);
        let mut values =
            |len: usize| -> Vec<f32> { (0..len).map(|_| rng.random_range(-1.0..1.0)).collect() };
        let (lhs, rhs) = (values(rows * inner), values(inner * columns));
        let product = |threads: usize| {
            let pool =
                rayon::ThreadPoolBuilder::new().num_threads(threads).build().expect("a pool");
            let mut out = vec![0f32; rows * columns];
            let views = (
                Strided::row_major(&lhs[..], rows, inner),
                Strided::row_major(&rhs[..], inner, columns),
            );
            pool.install(|| product_into(&mut out, columns, views, 1.0, false, Threads::Pool));
            let packed = Packed::new(&rhs, inner, columns);
            let packed_out = pool.install(|| packed_product(&lhs, rows, &packed, Threads::Pool));
            (out, packed_out)
        };
        let (one, four) = (product(1), product(4));
        assert_eq!(one.0, four.0);
        assert_eq!(one.1, four.1);
        let largest = one.0.iter().zip(&one.1).map(|(a, b)| (a - b).abs()).fold(0f32, f32::max);
        assert!(largest < 1e-3, "packed and plain products differ by {largest}");
    }

    /// Views past their slice, a short output and overlapping output rows are refused before
    /// gemm is called.
    #[test]
    fn product_into_refuses_what_would_reach_out_of_bounds() {
        let data = [1f32; 12];
        let view = |rows, columns, row_stride| Strided {
            data: &data,
            rows,
            columns,
            row_stride,
            column_stride: 1,
        };
        let attempt = |out_len: usize, out_stride, lhs, rhs| {
            std::panic::catch_unwind(move || {
                let mut out = vec![0f32; out_len];
                product_into(&mut out, out_stride, (lhs, rhs), 1.0, false, Threads::Calling);
            })
            .is_err()
        };
        assert!(!attempt(9, 3, view(3, 4, 4), view(4, 3, 3)));
        assert!(attempt(9, 3, view(3, 4, 5), view(4, 3, 3)), "lhs past its slice");
        assert!(attempt(9, 3, view(3, 4, 4), view(4, 3, 4)), "rhs past its slice");
        assert!(attempt(8, 3, view(3, 4, 4), view(4, 3, 3)), "output too short");
        assert!(attempt(9, 2, view(3, 4, 4), view(4, 3, 3)), "output rows overlapping");
        assert!(attempt(9, 3, view(3, 4, 4), view(3, 3, 3)), "inner sizes differ");
        let huge =
            Strided { data: &data, rows: 2, columns: 1, row_stride: usize::MAX, column_stride: 1 };
        assert!(attempt(9, 3, huge, view(1, 3, 3)), "an overflowing stride");
    }
}
