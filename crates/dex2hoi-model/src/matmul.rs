//! Row-major f32 matrix products on the CPU, straight through `gemm` (the crate candle's CPU
//! backend calls for `Tensor::matmul`): the inference path's, and the per-head products of the
//! training attention (`differentiable::attention`, on the calling thread). One of the two
//! modules of the workspace that use `unsafe` (the workspace denies it everywhere else; a tidy
//! test keeps it to them; the other sets an environment variable, `dex2hoi-cli`'s
//! `candle_threads`).
//!
//! Why not `Tensor::matmul` on the inference path: candle asks for its thread count on every
//! product (`candle_core::utils::get_num_threads`), which on Linux reads and parses
//! `/proc/cpuinfo` each time unless `RAYON_NUM_THREADS` is set: tens of microseconds per call,
//! against a few hundred for a product of a `small` sample, and about 8% of its time in
//! system calls (perf, session 16). It also always splits the product over every thread, also
//! inside a row group of [`crate::InferenceModel::forward`] whose neighbours already have
//! work. Called here, the product runs on one thread inside a row group ([`in_row_group`])
//! and on every thread of the pool elsewhere.
//!
//! Why `unsafe`: `gemm::gemm` takes raw pointers and strides, and safe Rust cannot call it.
//! [`product`] checks every length (with overflow-checked sizes) before the call, so that safe
//! callers cannot make it read or write out of bounds.
#![allow(unsafe_code)]

use std::cell::Cell;

use gemm::Parallelism;

thread_local! {
    /// Whether this thread runs one row group of a batch split over the pool's threads.
    static IN_ROW_GROUP: Cell<bool> = const { Cell::new(false) };
}

/// Runs `work` as one row group: every [`product`] it makes runs on this thread alone (the
/// pool's other threads run the other groups).
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

/// `lhs @ rhs` for a row-major `[rows, inner]` `lhs` and `[inner, columns]` `rhs`: the
/// row-major `[rows, columns]` product.
///
/// # Panics
/// If `lhs` or `rhs` does not hold exactly `rows * inner` or `inner * columns` values, or a
/// size overflows `usize`.
pub(crate) fn product(
    lhs: &[f32],
    rhs: &[f32],
    rows: usize,
    inner: usize,
    columns: usize,
) -> Vec<f32> {
    let size = |a: usize, b: usize| a.checked_mul(b).expect("a matrix size that fits in usize");
    assert_eq!(lhs.len(), size(rows, inner), "lhs is not [{rows}, {inner}]");
    assert_eq!(rhs.len(), size(inner, columns), "rhs is not [{inner}, {columns}]");
    let mut out = vec![0f32; size(rows, columns)];
    if out.is_empty() || inner == 0 {
        // Nothing to read (an empty sum is zero): no call with empty or dangling pointers.
        return out;
    }
    let threads = if IN_ROW_GROUP.with(Cell::get) { 1 } else { rayon::current_num_threads() };
    let parallelism = match threads {
        1 => Parallelism::None,
        threads => Parallelism::Rayon(threads),
    };
    let (inner_stride, columns_stride) = (inner as isize, columns as isize);
    // SAFETY: `out` holds `rows * columns` values, row `r`, column `c` at `r * columns + c`
    // (row stride `columns`, column stride 1); `lhs` holds `rows * inner` values at
    // `r * inner + i`; `rhs` holds `inner * columns` values at `i * columns + c` (lengths
    // checked above, every index below them). All three are live for the whole call and `out`
    // is borrowed mutably, apart from the inputs. With `read_dst` false gemm only writes
    // `out` (`out = 1 * lhs @ rhs`; alpha, the factor of the old `out`, is unused).
    unsafe {
        gemm::gemm(
            rows,
            columns,
            inner,
            out.as_mut_ptr(),
            1,
            columns_stride,
            false,
            lhs.as_ptr(),
            1,
            inner_stride,
            rhs.as_ptr(),
            1,
            columns_stride,
            0.0,
            1.0,
            false,
            false,
            false,
            parallelism,
        );
    }
    out
}
