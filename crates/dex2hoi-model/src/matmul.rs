//! Row-major f32 matrix products on the CPU, straight through `gemm` (the crate candle's CPU
//! backend calls for `Tensor::matmul`). This is the one module of the workspace that uses
//! `unsafe` (the workspace denies it everywhere else; a tidy test keeps it to this file).
//!
//! Why not `Tensor::matmul` on the inference path: candle asks for its thread count on every
//! product (`candle_core::utils::get_num_threads`), which on Linux reads and parses
//! `/proc/cpuinfo` each time unless `RAYON_NUM_THREADS` is set: tens of microseconds per call,
//! against a few hundred for a product of a `small` sample, and about 8% of its time in
//! system calls (perf, session 16). It also always splits the product over every thread, also
//! inside a rayon task whose neighbours already have work. Called here, the product runs on
//! one thread inside a rayon task and on every thread of the pool outside one.
//!
//! Why `unsafe`: `gemm::gemm` takes raw pointers and strides, and safe Rust cannot call it.
//! [`product`] checks every length before the call, so that safe callers cannot make it read
//! or write out of bounds.
#![allow(unsafe_code)]

use gemm::Parallelism;

/// `lhs @ rhs` for a row-major `[rows, inner]` `lhs` and `[inner, columns]` `rhs`: the
/// row-major `[rows, columns]` product.
///
/// # Panics
/// If `lhs` or `rhs` does not hold exactly `rows * inner` or `inner * columns` values.
pub(crate) fn product(
    lhs: &[f32],
    rhs: &[f32],
    rows: usize,
    inner: usize,
    columns: usize,
) -> Vec<f32> {
    assert_eq!(lhs.len(), rows * inner, "lhs is not [{rows}, {inner}]");
    assert_eq!(rhs.len(), inner * columns, "rhs is not [{inner}, {columns}]");
    let mut out = vec![0f32; rows * columns];
    if out.is_empty() || inner == 0 {
        // Nothing to read (an empty sum is zero): no call with empty or dangling pointers.
        return out;
    }
    let parallelism = match rayon::current_thread_index() {
        // Inside a rayon task: the pool's other threads have tasks of their own.
        Some(_) => Parallelism::None,
        None => match rayon::current_num_threads() {
            1 => Parallelism::None,
            threads => Parallelism::Rayon(threads),
        },
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
