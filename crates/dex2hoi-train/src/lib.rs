//! Training of the dex2hoi denoiser with the paper's objective (Sec. 3.3, Eq. 8-12): training
//! windows with augmentation, the loss terms through differentiable FK and the object decode,
//! AdamW with warm-up and decay, gradient clipping, EMA weights, checkpoints that resume bit for
//! bit, written into the run directory whose schema `dex2hoi-sample` owns. The optimiser itself
//! is `dex2hoi-optim`.

pub mod batch;
pub mod checkpoint;
pub mod config;
pub mod error;
mod files;
pub mod loss;
pub mod metrics;
pub mod plot;
pub mod run;
pub mod step;
pub mod surface;

pub use config::{LoopConfig, LossConfig, TrainConfig};
pub use error::{Result, TrainError};
pub use loss::{LossContext, Objective, Term};
pub use metrics::{MetricsLine, read_metrics};
pub use run::{RunStart, SNAPSHOTS_DIR, TrainOptions, TrainSummary, snapshot_dir, train};
pub use step::{StepReport, StepTiming, Trainer};
pub use surface::SurfaceSearch;
