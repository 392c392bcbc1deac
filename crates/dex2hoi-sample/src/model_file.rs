//! A packed model: everything sampling needs of a trained run in one safetensors file, for
//! shipping (docs/FORMATS.md, "Packed model").
//!
//! The file holds the run's EMA weights only (`ema.model.*`, `ema.text_encoder.*`; no raw
//! weights, no optimiser state), in f16 or f32, and in its metadata the checkpoint format and
//! model configuration (as every checkpoint), the run's `config.toml`, the dataset manifest
//! (skeleton, frame rate, BPS basis seed, object catalogue), the normalisation statistics,
//! the built-in encoder's vocabulary and the step count. [`crate::TrainedRun::load`] reads it
//! like a run directory.

use std::collections::BTreeMap;
use std::path::Path;

use candle_core::{DType, Device, Tensor};

use dex2hoi_data::dataset::{FeatureStats, Manifest};
use dex2hoi_model::checkpoint::{CONFIG_KEY, FORMAT_KEY, read_tensors, write_tensors};

use crate::config::RunConfig;
use crate::error::{Result, SampleError};
use crate::files::{
    RunFiles, STEP_KEY, TRAIN_CONFIG_KEY, VOCABULARY_KEY, parse_manifest, parse_stats, stats_json,
    trained_steps,
};

/// Metadata key that marks a packed model, with its format as the value.
pub const MODEL_FORMAT_KEY: &str = "dex2hoi.model_format";
/// The packed-model format this code writes.
pub const MODEL_FORMAT: &str = "dex2hoi-model-1";
/// Metadata key of the dataset manifest (the JSON of `dataset.json`).
pub const MANIFEST_KEY: &str = "dex2hoi.manifest";
/// Metadata key of the normalisation statistics (the JSON of `stats.json`).
pub const STATS_KEY: &str = "dex2hoi.stats";
/// The prefix of the weights a packed model keeps.
const EMA_PREFIX: &str = "ema.";

/// The floating-point type of a packed model's weights.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum PackedPrecision {
    /// Half precision: half the size; sampling reads them into f32, and a long autoregressive
    /// sample drifts from the f32 weights' by millimetres.
    F16,
    /// Single precision: the EMA weights exactly.
    #[default]
    F32,
}

impl PackedPrecision {
    fn dtype(self) -> DType {
        match self {
            Self::F16 => DType::F16,
            Self::F32 => DType::F32,
        }
    }
}

/// What [`pack_run`] wrote.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PackSummary {
    /// Numbers in the kept weights.
    pub parameters: usize,
    /// Training steps of the weights: the run's, plus those of the model it started from.
    pub step: usize,
    /// Size of the file.
    pub bytes: u64,
}

/// What a packed model's metadata says besides the checkpoint entries.
#[derive(Debug, Clone)]
pub struct PackedMetadata {
    /// The run's sampling configuration.
    pub config: RunConfig,
    /// The dataset manifest.
    pub manifest: Manifest,
    /// The normalisation statistics.
    pub stats: FeatureStats,
}

/// Packs the EMA weights and everything sampling needs of the run directory `run` into the
/// file `out` (written atomically).
pub fn pack_run(run: &Path, out: &Path, precision: PackedPrecision) -> Result<PackSummary> {
    let files = RunFiles::new(run);
    if !run.is_dir() {
        return Err(SampleError::run(run, "run", "a run directory", "no such directory"));
    }
    let config_text = std::fs::read_to_string(&files.config)
        .map_err(SampleError::io(&files.config, "reading"))?;
    let config = RunConfig::parse(&config_text, &files.config)?;
    let manifest_json =
        std::fs::read(&files.dataset).map_err(SampleError::io(&files.dataset, "reading"))?;
    parse_manifest(&manifest_json, &files.dataset)?;
    let stats = files.read_stats(config.model.stream_features())?;
    let (tensors, metadata) = read_tensors(&files.checkpoint, &Device::Cpu)?;
    let kept: BTreeMap<String, Tensor> = tensors
        .into_iter()
        .filter(|(name, _)| name.starts_with(EMA_PREFIX))
        .map(|(name, tensor)| Ok((name, tensor.to_dtype(precision.dtype())?)))
        .collect::<Result<_>>()?;
    if kept.is_empty() {
        return Err(SampleError::run(
            &files.checkpoint,
            "weights",
            "EMA weights (`ema.*`)",
            "none",
        ));
    }
    let step = trained_steps(&metadata);
    let mut packed = BTreeMap::from([
        (MODEL_FORMAT_KEY.to_string(), MODEL_FORMAT.to_string()),
        (TRAIN_CONFIG_KEY.to_string(), config_text),
        (
            MANIFEST_KEY.to_string(),
            String::from_utf8(manifest_json)
                .map_err(|e| SampleError::run(&files.dataset, "content", "UTF-8 JSON", e))?,
        ),
        (STATS_KEY.to_string(), String::from_utf8(stats_json(&stats)).expect("JSON is UTF-8")),
        (STEP_KEY.to_string(), step.to_string()),
    ]);
    for key in [FORMAT_KEY, CONFIG_KEY, VOCABULARY_KEY] {
        if let Some(value) = metadata.get(key) {
            packed.insert(key.to_string(), value.clone());
        }
    }
    write_tensors(out, &kept, &packed)?;
    let bytes = std::fs::metadata(out).map_err(SampleError::io(out, "reading the size of"))?.len();
    Ok(PackSummary { parameters: kept.values().map(Tensor::elem_count).sum(), step, bytes })
}

/// Reads the entries of a packed model's metadata (`path` names the file in errors).
pub fn read_metadata(metadata: &BTreeMap<String, String>, path: &Path) -> Result<PackedMetadata> {
    let entry = |key: &str, expected: &str| {
        metadata.get(key).ok_or_else(|| SampleError::run(path, key, expected, "nothing"))
    };
    let format = entry(MODEL_FORMAT_KEY, MODEL_FORMAT)?;
    if format != MODEL_FORMAT {
        return Err(SampleError::run(path, MODEL_FORMAT_KEY, MODEL_FORMAT, format));
    }
    // The checkpoint format and model configuration are checked where the model is built
    // (`Model::from_checkpoint`), as for any checkpoint.
    let config = RunConfig::parse(entry(TRAIN_CONFIG_KEY, "the run's config.toml")?, path)?;
    let manifest = parse_manifest(entry(MANIFEST_KEY, "the dataset manifest")?.as_bytes(), path)?;
    let stats = parse_stats(
        entry(STATS_KEY, "the normalisation statistics")?.as_bytes(),
        config.model.stream_features(),
        path,
    )?;
    Ok(PackedMetadata { config, manifest, stats })
}
