//! candle's elementwise operations run inline, on the thread that asks for them.
//!
//! candle 0.11 runs an elementwise operation of 64K values or more (sums, products and
//! differences of tensors, most of a backward pass's gradient sums) on its own pool of
//! `CANDLE_NUM_THREADS - 1` threads (default: one per core) beside rayon's, one operation at a
//! time behind a lock (`candle_core::utils::barrier_pool`). dex2hoi spreads its own work over
//! rayon's threads: training runs one forward and backward pass per group of windows on each
//! (`dex2hoi_train::Trainer::step`). The groups' operations then wait on that lock in turn while
//! the pool's threads spin on the cores the groups run on: on 2 cores, a `small` training step's
//! backward pass (batch 32 in two groups of 16) takes about 1.8x as long with candle's pool as
//! with `CANDLE_NUM_THREADS=1`, which leaves the pool without threads (`cargo xtask bench
//! train` measures it; `docs/BENCHMARKS.md`).
//!
//! candle reads the variable once, when its pool starts, so [`run_inline`] runs first thing
//! in `main` (the command line's and the benchmarks', which measure what it does).
//!
//! Why `unsafe`: changing the environment is `unsafe` since Rust 2024, because another thread
//! could be reading it at the same moment (the C library's `getenv` is not synchronised with
//! `setenv`). Safe Rust cannot set a variable for candle to read; [`run_inline`] sets it only
//! while the process has one thread.
#![allow(unsafe_code)]

/// The variable candle sizes its elementwise pool by (threads, with the calling one).
const VARIABLE: &str = "CANDLE_NUM_THREADS";

/// Sets `CANDLE_NUM_THREADS=1` for this process unless the environment sets it already (a
/// user's choice wins). Returns whether it did: it does only while this process has a single
/// thread, which it can tell on Linux (`/proc/self/task`); elsewhere it leaves the environment
/// alone.
pub fn run_inline() -> bool {
    if std::env::var_os(VARIABLE).is_some() || !single_threaded() {
        return false;
    }
    // SAFETY: this process has one thread (this one, checked just above), so no other thread
    // can read or write the environment while it changes; only this thread could start one,
    // and it does not until the call returns.
    unsafe { std::env::set_var(VARIABLE, "1") };
    true
}

/// Whether this process has exactly one thread (Linux: one entry in `/proc/self/task`; false
/// where that cannot be read or on other systems).
fn single_threaded() -> bool {
    std::fs::read_dir("/proc/self/task").is_ok_and(|tasks| tasks.count() == 1)
}

#[cfg(test)]
mod tests {
    #[test]
    fn leaves_the_environment_alone_beside_other_threads() {
        // The test harness runs this on a thread of its own, beside the main thread.
        let other =
            std::thread::spawn(|| std::thread::park_timeout(std::time::Duration::from_secs(5)));
        assert!(!super::single_threaded());
        let before = std::env::var_os(super::VARIABLE);
        assert!(!super::run_inline());
        assert_eq!(std::env::var_os(super::VARIABLE), before);
        other.thread().unpark();
        other.join().expect("the parked thread");
    }
}
