//! The run directory of a training run and loading a trained run for sampling.
//!
//! ```text
//! RUN/config.toml              the resolved training configuration
//! RUN/dataset.json             the manifest of the dataset trained on (skeleton, fps, BPS)
//! RUN/stats.json               the normalisation statistics {"mean": [D], "std": [D]}
//! RUN/checkpoint.safetensors   model.*, text_encoder.*, ema.*, optimizer.{first,second}.*
//! RUN/metrics.jsonl            one JSON object per logged step
//! RUN/loss.png                 the loss curves
//! ```

use std::path::{Path, PathBuf};

use candle_core::{DType, Device, Tensor};
use serde::{Deserialize, Serialize};

use dex2hoi_data::dataset::{Dataset, FeatureStats, Manifest};
use dex2hoi_diffusion::Normaliser;
use dex2hoi_model::checkpoint::{assign_parameters, config_from_metadata, read_tensors};
use dex2hoi_model::text::{TextEncoder, Vocabulary};
use dex2hoi_model::{Model, SeededVarMap};
use dex2hoi_repr::{Skeleton, SkeletonKind};

use crate::config::TrainConfig;
use crate::error::{Result, TrainError};
use crate::trainer::{StepReport, TextModule, append_line, text_module, write_file};

/// Checkpoint metadata key of the training configuration (TOML).
pub const TRAIN_CONFIG_KEY: &str = "dex2hoi.train_config";
/// Checkpoint metadata key of the step count.
pub const STEP_KEY: &str = "dex2hoi.step";
/// Checkpoint metadata key of the built-in encoder's vocabulary (JSON list of words).
pub const VOCABULARY_KEY: &str = "dex2hoi.vocabulary";

/// The files of a run directory.
#[derive(Debug, Clone)]
pub struct RunFiles {
    /// `config.toml`.
    pub config: PathBuf,
    /// `dataset.json`.
    pub dataset: PathBuf,
    /// `stats.json`.
    pub stats: PathBuf,
    /// `checkpoint.safetensors`.
    pub checkpoint: PathBuf,
    /// `metrics.jsonl`.
    pub metrics: PathBuf,
    /// `loss.png`.
    pub loss_curve: PathBuf,
}

/// `stats.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
struct StatsFile {
    mean: Vec<f32>,
    std: Vec<f32>,
}

/// One line of `metrics.jsonl`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MetricsLine {
    /// Steps done.
    pub step: usize,
    /// Weighted total.
    pub loss: f64,
    /// Learning rate.
    pub learning_rate: f64,
    /// Gradient norm before clipping.
    pub gradient_norm: f64,
    /// Seconds of the step.
    pub seconds: f64,
    /// Unweighted terms by name.
    pub terms: std::collections::BTreeMap<String, f64>,
}

impl RunFiles {
    /// The files under a directory.
    pub fn new(dir: &Path) -> Self {
        Self {
            config: dir.join("config.toml"),
            dataset: dir.join("dataset.json"),
            stats: dir.join("stats.json"),
            checkpoint: dir.join("checkpoint.safetensors"),
            metrics: dir.join("metrics.jsonl"),
            loss_curve: dir.join("loss.png"),
        }
    }

    /// Writes the configuration, manifest and statistics.
    pub fn write_static(&self, config: &TrainConfig, dataset: &Dataset) -> Result<()> {
        write_file(&self.config, config.to_toml()?.as_bytes())?;
        let manifest = serde_json::to_vec_pretty(&dataset.manifest).expect("a manifest serialises");
        write_file(&self.dataset, &manifest)?;
        let stats = StatsFile { mean: dataset.stats.mean.clone(), std: dataset.stats.std.clone() };
        write_file(&self.stats, &serde_json::to_vec(&stats).expect("statistics serialise"))
    }

    /// Appends a step to `metrics.jsonl`.
    pub fn append_metrics(&self, report: &StepReport) -> Result<()> {
        let line = MetricsLine {
            step: report.step,
            loss: report.loss,
            learning_rate: report.learning_rate,
            gradient_norm: report.gradient_norm,
            seconds: report.seconds,
            terms: report.terms.iter().map(|(t, v)| (t.name().to_string(), *v)).collect(),
        };
        append_line(
            &self.metrics,
            &serde_json::to_string(&line).expect("a metrics line serialises"),
        )
    }

    /// Reads `metrics.jsonl` (empty when absent).
    pub fn read_metrics(&self) -> Result<Vec<MetricsLine>> {
        let text = match std::fs::read_to_string(&self.metrics) {
            Ok(text) => text,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Vec::new()),
            Err(e) => return Err(TrainError::io(&self.metrics, "reading")(e)),
        };
        text.lines()
            .filter(|l| !l.trim().is_empty())
            .enumerate()
            .map(|(n, line)| {
                serde_json::from_str(line).map_err(|e| {
                    TrainError::checkpoint(
                        &self.metrics,
                        format!("line {}", n + 1),
                        "a metrics line",
                        e,
                    )
                })
            })
            .collect()
    }

    /// Drops the lines after `step` (a resumed run logs them again).
    pub fn truncate_metrics(&self, step: usize) -> Result<()> {
        let kept: Vec<String> = self
            .read_metrics()?
            .into_iter()
            .filter(|l| l.step <= step)
            .map(|l| serde_json::to_string(&l).expect("a metrics line serialises"))
            .collect();
        let mut text = kept.join("\n");
        if !text.is_empty() {
            text.push('\n');
        }
        write_file(&self.metrics, text.as_bytes())
    }
}

/// Which weights to load.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Weights {
    /// The exponential moving average (what sampling uses).
    Ema,
    /// The raw optimised weights.
    Raw,
}

/// A trained run ready to sample: configuration, manifest, statistics, model, text encoder.
pub struct TrainedRun {
    /// The training configuration.
    pub config: TrainConfig,
    /// The dataset manifest (skeleton, fps, BPS settings).
    pub manifest: Manifest,
    /// Normalisation statistics.
    pub stats: FeatureStats,
    /// The skeleton.
    pub skeleton: Skeleton,
    /// The network.
    pub model: Model,
    /// Its parameters.
    pub model_vars: SeededVarMap,
    /// The text encoder (trained built-in one, or frozen).
    pub text: Box<dyn TextEncoder>,
    /// Steps the checkpoint was trained for.
    pub step: usize,
}

impl std::fmt::Debug for TrainedRun {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("TrainedRun").field("step", &self.step).finish_non_exhaustive()
    }
}

impl TrainedRun {
    /// Loads a run directory.
    pub fn load(dir: &Path, weights: Weights, device: &Device) -> Result<Self> {
        let files = RunFiles::new(dir);
        if !dir.is_dir() {
            return Err(TrainError::checkpoint(dir, "run", "a run directory", "no such directory"));
        }
        let config = TrainConfig::load(&files.config)?;
        let manifest: Manifest = serde_json::from_slice(
            &std::fs::read(&files.dataset).map_err(TrainError::io(&files.dataset, "reading"))?,
        )
        .map_err(|e| TrainError::checkpoint(&files.dataset, "content", "a dataset manifest", e))?;
        let stats: StatsFile = serde_json::from_slice(
            &std::fs::read(&files.stats).map_err(TrainError::io(&files.stats, "reading"))?,
        )
        .map_err(|e| TrainError::checkpoint(&files.stats, "content", "mean and std lists", e))?;
        let width = config.model.stream_features();
        if stats.mean.len() != width || stats.std.len() != width {
            return Err(TrainError::checkpoint(
                &files.stats,
                "statistics",
                format!("{width} means and stds"),
                format!("{} and {}", stats.mean.len(), stats.std.len()),
            ));
        }
        let (tensors, metadata) = read_tensors(&files.checkpoint, device)?;
        let stored = config_from_metadata(&files.checkpoint, &metadata)?;
        if stored != config.model {
            return Err(TrainError::checkpoint(
                &files.checkpoint,
                "model configuration",
                "the model of config.toml",
                "another model",
            ));
        }
        let prefix = match weights {
            Weights::Ema => "ema.",
            Weights::Raw => "",
        };
        let model_vars = SeededVarMap::new(0);
        let model = Model::new(&config.model, model_vars.builder(DType::F32, device))?;
        assign_parameters(&model_vars, &tensors, &format!("{prefix}model."), &files.checkpoint)?;
        let words: Vec<String> = metadata
            .get(VOCABULARY_KEY)
            .map(|w| serde_json::from_str(w))
            .transpose()
            .map_err(|e| {
                TrainError::checkpoint(&files.checkpoint, VOCABULARY_KEY, "a word list", e)
            })?
            .unwrap_or_default();
        let text = match text_module(&config, Vocabulary::from_words(words), device)? {
            TextModule::Builtin { encoder, vars } => {
                assign_parameters(
                    &vars,
                    &tensors,
                    &format!("{prefix}text_encoder."),
                    &files.checkpoint,
                )?;
                Box::new(encoder) as Box<dyn TextEncoder>
            }
            TextModule::Frozen(encoder) => encoder,
        };
        let step = metadata.get(STEP_KEY).and_then(|s| s.parse().ok()).unwrap_or(0);
        let skeleton = Skeleton::builtin(SkeletonKind::from_name(&manifest.skeleton)?);
        Ok(Self {
            config,
            manifest,
            stats: FeatureStats { mean: stats.mean, std: stats.std },
            skeleton,
            model,
            model_vars,
            text,
            step,
        })
    }

    /// The normaliser of the run's statistics.
    pub fn normaliser(&self, device: &Device) -> Result<Normaliser> {
        let width = self.stats.mean.len();
        Ok(Normaliser {
            mean: Tensor::from_vec(self.stats.mean.clone(), width, device)?,
            std: Tensor::from_vec(self.stats.std.clone(), width, device)?,
        })
    }
}
