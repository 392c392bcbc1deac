//! The optimiser of dex2hoi, shared by the denoiser's training (`dex2hoi-train`) and the
//! evaluator's (`dex2hoi-eval`): AdamW with decoupled weight decay, linear warm-up and cosine
//! decay, global gradient-norm clipping, an exponential moving average of the weights, and the
//! per-step random stream that makes a resumed run draw what an uninterrupted one would.
//!
//! The state is `f32` tensors per parameter on the parameters' device, so that a checkpoint
//! holds it exactly and a resumed run continues bit for bit on the same device. On the CPU the
//! updates are parallel host loops; on a GPU, one CUDA kernel per parameter tensor for AdamW
//! and the EMA together (or, with `fused = false`, elementwise tensor operations).

mod adamw;
mod config;
mod ema;
mod error;
mod fused;
mod parameter;
mod schedule;

pub use adamw::{AdamW, UpdateReport};
pub use config::OptimizerConfig;
pub use ema::Ema;
pub use error::{OptimError, Result};
pub use parameter::{Parameter, parameters_of};
pub use schedule::{learning_rate, step_rng};
