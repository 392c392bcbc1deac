//! Training of the dex2hoi denoiser with the paper's objective (Sec. 3.3, Eq. 8-12): training
//! windows with augmentation, the loss terms through differentiable FK and the object decode,
//! AdamW with warm-up and decay, gradient clipping, EMA weights, checkpoints that resume bit for
//! bit, and the run directory that sampling reads.

pub mod batch;
pub mod config;
pub mod error;
pub mod loss;
pub mod optim;
pub mod plot;
pub mod run;
pub mod sampling;
pub mod trainer;

pub use config::{LoopConfig, LossConfig, OptimizerConfig, TextConfig, TrainConfig};
pub use error::{Result, TrainError};
pub use loss::{LossContext, Objective, Term};
pub use run::{RunFiles, TrainedRun, Weights};
pub use trainer::{StepReport, StepTiming, TrainOptions, TrainSummary, Trainer, train};
