//! The run directory: the files `dex2hoi train` writes and sampling and evaluation read.
//!
//! ```text
//! RUN/config.toml              the resolved training configuration (see [`crate::RunConfig`])
//! RUN/dataset.json             the manifest of the dataset trained on (skeleton, fps, BPS)
//! RUN/stats.json               the normalisation statistics {"mean": [D], "std": [D]}
//! RUN/checkpoint.safetensors   model.*, text_encoder.*, ema.*, optimizer.{first,second}.*
//! RUN/metrics.jsonl            one JSON object per logged step
//! RUN/loss.png                 the loss curves
//! ```

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use dex2hoi_data::dataset::{FeatureStats, Manifest};
use dex2hoi_data::files::write_atomically;

use crate::error::{Result, SampleError};

/// Checkpoint metadata key of the training configuration (TOML).
pub const TRAIN_CONFIG_KEY: &str = "dex2hoi.train_config";
/// Checkpoint metadata key of the step count: the run's own steps in a checkpoint, every
/// training step of the weights in a packed model.
pub const STEP_KEY: &str = "dex2hoi.step";
/// Checkpoint metadata key of the steps the initial weights of a run started from a packed model
/// (`dex2hoi train --init-from`) had been trained; absent for a run started from the seed.
pub const STEPS_BEFORE_KEY: &str = "dex2hoi.steps_before";
/// Checkpoint metadata key of the built-in encoder's vocabulary (JSON list of words).
pub const VOCABULARY_KEY: &str = "dex2hoi.vocabulary";

/// The training steps behind a checkpoint's or packed model's weights: its step count plus the
/// steps of the model its run started from, if any (0 where the metadata says nothing).
pub fn trained_steps(metadata: &std::collections::BTreeMap<String, String>) -> usize {
    let number = |key: &str| metadata.get(key).and_then(|s| s.parse::<usize>().ok()).unwrap_or(0);
    number(STEP_KEY).saturating_add(number(STEPS_BEFORE_KEY))
}

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

    /// Writes `dataset.json` and `stats.json` (atomically).
    pub fn write_manifest_and_stats(
        &self,
        manifest: &Manifest,
        stats: &FeatureStats,
    ) -> Result<()> {
        let manifest = serde_json::to_vec_pretty(manifest).expect("a manifest serialises");
        write_atomically(&self.dataset, &manifest)?;
        Ok(write_atomically(&self.stats, &stats_json(stats))?)
    }

    /// Reads `dataset.json`.
    pub fn read_manifest(&self) -> Result<Manifest> {
        let bytes =
            std::fs::read(&self.dataset).map_err(SampleError::io(&self.dataset, "reading"))?;
        parse_manifest(&bytes, &self.dataset)
    }

    /// Reads `stats.json` and checks that it has `width` means and standard deviations.
    pub fn read_stats(&self, width: usize) -> Result<FeatureStats> {
        let bytes = std::fs::read(&self.stats).map_err(SampleError::io(&self.stats, "reading"))?;
        parse_stats(&bytes, width, &self.stats)
    }
}

/// Parses the JSON of `dataset.json`; `path` names it in errors.
pub fn parse_manifest(json: &[u8], path: &Path) -> Result<Manifest> {
    serde_json::from_slice(json)
        .map_err(|e| SampleError::run(path, "content", "a dataset manifest", e))
}

/// The JSON of `stats.json`.
pub fn stats_json(stats: &FeatureStats) -> Vec<u8> {
    serde_json::to_vec(&StatsFile { mean: stats.mean.clone(), std: stats.std.clone() })
        .expect("statistics serialise")
}

/// Parses the JSON of `stats.json` and checks that it has `width` means and standard
/// deviations; `path` names it in errors.
pub fn parse_stats(json: &[u8], width: usize, path: &Path) -> Result<FeatureStats> {
    let stats: StatsFile = serde_json::from_slice(json)
        .map_err(|e| SampleError::run(path, "content", "mean and std lists", e))?;
    if stats.mean.len() != width || stats.std.len() != width {
        return Err(SampleError::run(
            path,
            "statistics",
            format!("{width} means and stds"),
            format!("{} and {}", stats.mean.len(), stats.std.len()),
        ));
    }
    Ok(FeatureStats { mean: stats.mean, std: stats.std })
}
