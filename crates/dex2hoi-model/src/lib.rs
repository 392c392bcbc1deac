//! The Dex2HOI networks (paper Sec. 3.2): the dual-stream denoiser with cross-attention between
//! the streams, the Motion Fusion Network, their conditioning, and the ablation variants of the
//! paper's Table 3, built on candle from operations that all have a backward pass.

pub mod candle_threads;
pub mod checkpoint;
pub mod config;
pub mod cuda_device;
pub mod differentiable;
pub mod error;
pub mod fused;
pub mod init;
mod kernel;
pub mod layers;
mod matmul;
pub mod model;
pub mod text;
pub mod text_bert;
pub mod text_clip;
pub mod transformer;

pub use config::{
    BodyFusion, ModelConfig, ObjectRepresentation, ObjectStart, PRESETS, Prediction, StreamLayout,
};
pub use error::{ModelError, Result};
pub use init::SeededVarMap;
pub use model::inference::{InferenceModel, PreparedCondition};
pub use model::{
    CLOCK_FRAMES, Model, ModelInput, OBJECT_START_PARTS, OBJECT_START_WIDTH, PromptState,
    row_groups,
};
