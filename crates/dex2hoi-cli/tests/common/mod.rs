//! What every end-to-end test of the `dex2hoi` binary uses.

use std::process::{Command, Output};

/// Runs the binary built for these tests with arguments (no backtraces in its errors).
pub fn dex2hoi(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_dex2hoi"))
        .args(args)
        .env("RUST_BACKTRACE", "0")
        .output()
        .expect("the binary runs")
}
