//! Loading a trained run on any device: its configuration, the dataset manifest, the
//! normalisation statistics, the network with the chosen weights and the text encoder.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use candle_core::{DType, Device, Tensor};

use dex2hoi_data::dataset::{FeatureStats, Manifest};
use dex2hoi_model::checkpoint::{assign_parameters, read_tensors, read_tensors_from_bytes};
use dex2hoi_model::text::{TextEncoder, Vocabulary};
use dex2hoi_model::{InferenceModel, Model, SeededVarMap};
use dex2hoi_repr::Skeleton;

use dex2hoi_data::normalise::Normaliser;

use crate::config::RunConfig;
use crate::error::{Result, SampleError};
use crate::files::{RunFiles, VOCABULARY_KEY, trained_steps};
use crate::model_file;
use crate::text::TextModule;

/// Which weights to load.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Weights {
    /// The exponential moving average (what sampling uses).
    Ema,
    /// The raw optimised weights.
    Raw,
}

impl Weights {
    /// The prefix of these weights' names in the checkpoint.
    fn checkpoint_prefix(self) -> &'static str {
        match self {
            Self::Ema => "ema.",
            Self::Raw => "",
        }
    }
}

/// A trained run ready to sample: configuration, manifest, statistics, model, text encoder.
pub struct TrainedRun {
    /// What sampling needs of the training configuration.
    pub config: RunConfig,
    /// The dataset manifest (skeleton, fps, BPS settings).
    pub manifest: Manifest,
    /// Normalisation statistics.
    pub stats: FeatureStats,
    /// The skeleton.
    pub skeleton: Skeleton,
    /// The network.
    pub model: Model,
    /// The network rearranged for sampling (fused operations on the CPU).
    pub inference: InferenceModel,
    /// Its parameters.
    pub model_vars: SeededVarMap,
    /// The text encoder (trained built-in one, or frozen).
    pub text: Box<dyn TextEncoder>,
    /// Training steps of the weights (with those of the model the run started from, if any).
    pub step: usize,
    /// The device the model lives on.
    pub device: Device,
}

impl std::fmt::Debug for TrainedRun {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("TrainedRun").field("step", &self.step).finish_non_exhaustive()
    }
}

/// What a run directory or a packed model file holds, read but not yet assembled.
struct RunParts {
    /// The file the weights came from (named in errors).
    origin: PathBuf,
    config: RunConfig,
    manifest: Manifest,
    stats: FeatureStats,
    tensors: BTreeMap<String, Tensor>,
    metadata: BTreeMap<String, String>,
}

impl TrainedRun {
    /// Loads a run directory, or a packed model file ([`crate::model_file`]), onto `device`.
    /// A packed model holds EMA weights only.
    pub fn load(path: &Path, weights: Weights, device: &Device) -> Result<Self> {
        if path.is_file() {
            let bytes = std::fs::read(path).map_err(SampleError::io(path, "reading"))?;
            return Self::from_model_bytes(&bytes, path, weights, device);
        }
        let files = RunFiles::new(path);
        if !path.is_dir() {
            return Err(SampleError::run(
                path,
                "run",
                "a run directory or a packed model file",
                "no such file or directory",
            ));
        }
        let config = RunConfig::load(&files.config)?;
        let manifest = files.read_manifest()?;
        let stats = files.read_stats(config.model.stream_features())?;
        let (tensors, metadata) = read_tensors(&files.checkpoint, device)?;
        let parts =
            RunParts { origin: files.checkpoint, config, manifest, stats, tensors, metadata };
        Self::assemble(parts, weights, device)
    }

    /// Loads a packed model file held in memory (`origin` names it in errors).
    pub fn from_model_bytes(
        bytes: &[u8],
        origin: &Path,
        weights: Weights,
        device: &Device,
    ) -> Result<Self> {
        if weights != Weights::Ema {
            return Err(SampleError::run(
                origin,
                "weights",
                "a run directory for the raw weights",
                "a packed model, which holds the EMA weights only",
            ));
        }
        let (tensors, metadata) = read_tensors_from_bytes(bytes, origin, device)?;
        let packed = model_file::read_metadata(&metadata, origin)?;
        let parts = RunParts {
            origin: origin.to_path_buf(),
            config: packed.config,
            manifest: packed.manifest,
            stats: packed.stats,
            tensors,
            metadata,
        };
        Self::assemble(parts, weights, device)
    }

    fn assemble(parts: RunParts, weights: Weights, device: &Device) -> Result<Self> {
        let RunParts { origin, config, manifest, stats, tensors, metadata } = parts;
        let prefix = weights.checkpoint_prefix();
        let (model, model_vars) = Model::from_checkpoint(
            &origin,
            &tensors,
            &metadata,
            &format!("{prefix}model."),
            Some(&config.model),
            DType::F32,
            device,
        )?;
        let words: Vec<String> = metadata
            .get(VOCABULARY_KEY)
            .map(|w| serde_json::from_str(w))
            .transpose()
            .map_err(|e| SampleError::run(&origin, VOCABULARY_KEY, "a word list", e))?
            .unwrap_or_default();
        // The built-in encoder's initial parameters are replaced by the checkpoint's below, so
        // their seed does not matter.
        let text = TextModule::new(
            &config.text,
            config.model.text_embedding,
            Vocabulary::from_words(words),
            0,
            device,
        )?;
        if let TextModule::Builtin { vars, .. } = &text {
            assign_parameters(vars, &tensors, &format!("{prefix}text_encoder."), &origin)?;
        }
        let step = trained_steps(&metadata);
        let skeleton = manifest.builtin_skeleton()?;
        let inference = InferenceModel::new(&model)?;
        Ok(Self {
            config,
            manifest,
            stats,
            skeleton,
            model,
            inference,
            model_vars,
            text: text.into_encoder(),
            step,
            device: device.clone(),
        })
    }

    /// The normaliser of the run's statistics, on the run's device.
    pub fn normaliser(&self) -> Result<Normaliser> {
        Ok(self.stats.normaliser(&self.device)?)
    }
}
