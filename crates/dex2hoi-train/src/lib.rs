//! Training of the dex2hoi denoiser with the paper's objective (Sec. 3.3, Eq. 8-12): training
//! windows with augmentation, the loss terms through differentiable FK and the object decode,
//! AdamW with warm-up and decay, gradient clipping, EMA weights, checkpoints that resume bit for
//! bit, written into the run directory whose schema `dex2hoi-sample` owns. The optimiser itself
//! is `dex2hoi-optim`.

pub mod batch;
pub mod config;
pub mod error;
pub mod loss;
pub mod plot;
pub mod run;
pub mod trainer;

pub use config::{LoopConfig, LossConfig, TrainConfig};
pub use error::{Result, TrainError};
pub use loss::{LossContext, Objective, Term};
pub use run::{MetricsLine, read_metrics};
pub use trainer::{
    RunStart, SNAPSHOTS_DIR, StepReport, StepTiming, TrainOptions, TrainSummary, Trainer,
    snapshot_dir, train,
};
