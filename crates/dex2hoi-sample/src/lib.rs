//! Inference for dex2hoi: everything between a trained run on disk and a generated motion.
//!
//! - [`files`]: the run directory's schema (`config.toml`, `dataset.json`, `stats.json`,
//!   `checkpoint.safetensors`), which `dex2hoi-train` writes and this crate reads;
//! - [`run`]: loading a run on any device with its EMA or raw weights and its text encoder;
//! - [`model_file`]: a run packed into one file for shipping (EMA weights, f16 or f32), which
//!   [`TrainedRun::load`] reads like a run directory;
//! - [`denoiser`]: the model as a `dex2hoi_diffusion::Denoiser` for one window;
//! - [`generate`]: autoregressive generation over prefix-conditioned windows (paper Sec. 3.2)
//!   with a prompt timeline, and decoding to rotations, joints and object poses;
//! - [`rest`], [`seams`]: the sampler's rules beyond the paper, objects at rest and windows
//!   that carry on from their prefix;
//! - [`scene`], [`timeline`], [`request`]: objects and their places, prompts by time, and
//!   [`sample`], which turns a request into a motion.
//!
//! ```no_run
//! use candle_core::Device;
//! use dex2hoi_diffusion::SamplerConfig;
//! use dex2hoi_sample::{Prompt, SampleRequest, SceneObject, TrainedRun, Weights, sample};
//!
//! let run = TrainedRun::load("runs/demo".as_ref(), Weights::Ema, &Device::Cpu)?;
//! let request = SampleRequest {
//!     prompts: vec![Prompt { start_frame: 0, text: "The person picks up the mug.".into() }],
//!     objects: vec![SceneObject::parse("mug", None)?],
//!     frames: std::num::NonZeroUsize::new(120).unwrap(),
//!     seed: 0,
//!     sampler: SamplerConfig::default(),
//!     table_height: dex2hoi_sample::DEFAULT_TABLE_HEIGHT,
//!     free_objects: Default::default(),
//!     seams: Default::default(),
//!     progress: None,
//! };
//! let motion = sample(&run, &request)?;
//! println!("{} frames in {:.1} s", motion.frames, motion.seconds);
//! # Ok::<(), dex2hoi_sample::SampleError>(())
//! ```

pub mod config;
pub mod denoiser;
mod error;
pub mod files;
pub mod generate;
pub mod model_file;
pub mod prefix;
pub mod request;
pub mod rest;
pub mod run;
pub mod scene;
pub mod seams;
pub mod text;
pub mod timeline;

pub use config::{RunConfig, TextConfig, default_diffusion_steps};
pub use denoiser::{ModelDenoiser, WindowCondition, sample_window};
/// The normaliser a [`Generation`] takes (`dex2hoi_data::normalise`).
pub use dex2hoi_data::normalise::Normaliser;
pub use error::{Result, SampleError};
pub use files::{
    RunFiles, STEP_KEY, STEPS_BEFORE_KEY, TRAIN_CONFIG_KEY, VOCABULARY_KEY, trained_steps,
};
pub use generate::{
    Conditioning, GeneratedMotion, Generation, ProgressHook, TimedText, WindowProgress, generate,
    generate_motion,
};
pub use model_file::{PackSummary, PackedPrecision, pack_run};
pub use prefix::PrefixEncoding;
pub use request::{SampleRequest, SampledMotion, sample, standing_prefix};
pub use run::{TrainedRun, Weights};
pub use scene::{
    DEFAULT_OBJECT_DEPTH, DEFAULT_OBJECT_SIDE, DEFAULT_TABLE_HALF_EXTENTS, DEFAULT_TABLE_HEIGHT,
    DEFAULT_TABLE_NEAR_EDGE, ON_TABLE_TOLERANCE_M, SceneObject, SceneTable, SequenceScene,
    default_lone_object_side, default_pair_sides,
};
pub use text::{TextModule, unknown_words_warning};
pub use timeline::{Prompt, parse_timeline};
