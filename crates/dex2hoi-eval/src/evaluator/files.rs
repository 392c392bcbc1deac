//! Saving and loading an evaluator directory: `evaluator.safetensors` (weights `motion.*` and
//! `text.*`, metadata) and `stats.json`.

use std::collections::BTreeMap;
use std::path::Path;

use candle_core::{DType, Device};
use serde::Serialize;

use dex2hoi_data::files::write_atomically;
use dex2hoi_model::checkpoint::{
    FORMAT_KEY, assign_parameters, named_parameters, read_tensors, write_tensors,
};
use dex2hoi_model::init::{parameter_budget, with_parameter_budget};
use dex2hoi_model::text::Vocabulary;

use crate::error::{EvalError, Result};

use super::{ClipStats, Evaluator, EvaluatorConfig, TrainingSummary, clip_feature_size};

/// The file of the weights and metadata in an evaluator directory.
pub const EVALUATOR_FILE: &str = "evaluator.safetensors";
/// The file of the feature statistics in an evaluator directory.
pub const STATS_FILE: &str = "stats.json";
/// The evaluator format this code writes and reads.
pub const EVALUATOR_FORMAT: &str = "dex2hoi-evaluator-1";
/// Metadata key of the [`EvaluatorConfig`] (JSON).
pub const CONFIG_KEY: &str = "dex2hoi.evaluator_config";
/// Metadata key of the vocabulary (JSON list of words, without the special tokens).
pub const VOCABULARY_KEY: &str = "dex2hoi.vocabulary";
/// Metadata key of the action labels (JSON list; empty without an action head).
pub const LABELS_KEY: &str = "dex2hoi.labels";
/// Metadata key of the skeleton name.
pub const SKELETON_KEY: &str = "dex2hoi.skeleton";
/// Metadata key of the joint count.
pub const JOINTS_KEY: &str = "dex2hoi.joints";
/// Metadata key of the frame rate.
pub const FPS_KEY: &str = "dex2hoi.fps";
/// Metadata key of the [`TrainingSummary`] (JSON).
pub const TRAINING_KEY: &str = "dex2hoi.training";

/// A value as JSON for the metadata of `path`.
fn to_json<T: Serialize + ?Sized>(path: &Path, key: &str, value: &T) -> Result<String> {
    serde_json::to_string(value).map_err(|e| EvalError::file(path, key, "JSON", e))
}

impl Evaluator {
    /// Writes `evaluator.safetensors` and `stats.json` into `dir` (created if needed), each
    /// atomically.
    pub fn save(&self, dir: &Path) -> Result<()> {
        std::fs::create_dir_all(dir)
            .map_err(EvalError::io(dir, "creating the evaluator directory"))?;
        let file = dir.join(EVALUATOR_FILE);
        let stats = serde_json::to_vec_pretty(&self.stats)
            .map_err(|e| EvalError::file(dir.join(STATS_FILE), "statistics", "JSON", e))?;
        write_atomically(&dir.join(STATS_FILE), &stats)?;
        let mut tensors = named_parameters(&self.motion_vars, "motion.");
        tensors.extend(named_parameters(&self.text_vars, "text."));
        let metadata = BTreeMap::from([
            (FORMAT_KEY.to_string(), EVALUATOR_FORMAT.to_string()),
            (CONFIG_KEY.to_string(), to_json(&file, CONFIG_KEY, &self.config)?),
            (
                VOCABULARY_KEY.to_string(),
                to_json(&file, VOCABULARY_KEY, &self.text.vocabulary().words())?,
            ),
            (LABELS_KEY.to_string(), to_json(&file, LABELS_KEY, &self.labels)?),
            (SKELETON_KEY.to_string(), self.skeleton.clone()),
            (JOINTS_KEY.to_string(), self.joints.to_string()),
            (FPS_KEY.to_string(), self.fps.to_string()),
            (TRAINING_KEY.to_string(), to_json(&file, TRAINING_KEY, &self.training)?),
        ]);
        write_tensors(&file, &tensors, &metadata)?;
        Ok(())
    }

    /// Reads an evaluator written by [`Evaluator::save`], refusing a file of another format, a
    /// missing or malformed entry, weights that do not fit the configuration, or statistics of
    /// another size. `dir` is the evaluator directory (or its `evaluator.safetensors`); the
    /// weights are placed on `device`.
    pub fn load(dir: &Path, device: &Device) -> Result<Self> {
        let (dir, path) = if dir.is_file() {
            (dir.parent().unwrap_or(Path::new(".")), dir.to_path_buf())
        } else {
            (dir, dir.join(EVALUATOR_FILE))
        };
        let (tensors, metadata) = read_tensors(&path, device)?;
        let entry = |key: &str| {
            metadata
                .get(key)
                .ok_or_else(|| EvalError::file(&path, key, "an entry in the metadata", "nothing"))
        };
        let format = entry(FORMAT_KEY)?;
        if format != EVALUATOR_FORMAT {
            return Err(EvalError::file(&path, FORMAT_KEY, EVALUATOR_FORMAT, format));
        }
        fn parse<T: serde::de::DeserializeOwned>(path: &Path, key: &str, text: &str) -> Result<T> {
            serde_json::from_str(text)
                .map_err(|e| EvalError::file(path, key, "a valid JSON entry", e))
        }
        let config: EvaluatorConfig = parse(&path, CONFIG_KEY, entry(CONFIG_KEY)?)?;
        config
            .validate()
            .map_err(|e| EvalError::file(&path, CONFIG_KEY, "a valid configuration", e))?;
        let words: Vec<String> = parse(&path, VOCABULARY_KEY, entry(VOCABULARY_KEY)?)?;
        let labels: Vec<String> = parse(&path, LABELS_KEY, entry(LABELS_KEY)?)?;
        let training: Option<TrainingSummary> = parse(&path, TRAINING_KEY, entry(TRAINING_KEY)?)?;
        let skeleton = entry(SKELETON_KEY)?.clone();
        let joints: usize = entry(JOINTS_KEY)?
            .parse()
            .map_err(|e| EvalError::file(&path, JOINTS_KEY, "a joint count", e))?;
        let fps: f32 = entry(FPS_KEY)?
            .parse()
            .map_err(|e| EvalError::file(&path, FPS_KEY, "a frame rate", e))?;
        let stats_path = dir.join(STATS_FILE);
        let stats_text = std::fs::read_to_string(&stats_path)
            .map_err(EvalError::io(&stats_path, "reading the evaluator statistics"))?;
        let stats: ClipStats = parse(&stats_path, "statistics", &stats_text)?;
        // The joint count sizes the input layer, whose weights must be in the file: a count
        // past its values is refused before the width is computed from it.
        let elements = tensors.values().map(|t| t.elem_count()).fold(0usize, usize::saturating_add);
        if joints > elements {
            return Err(EvalError::file(
                &path,
                JOINTS_KEY,
                format!("at most the {elements} values of the file's tensors"),
                joints,
            ));
        }
        let width = clip_feature_size(joints);
        if stats.feature_size != width || stats.mean.len() != width || stats.std.len() != width {
            return Err(EvalError::file(
                &stats_path,
                "feature size",
                format!("{width} channels ({joints} joints)"),
                format!(
                    "{} ({} means, {} deviations)",
                    stats.feature_size,
                    stats.mean.len(),
                    stats.std.len()
                ),
            ));
        }
        if let Some(c) = stats.std.iter().position(|s| !(s.is_finite() && *s > 0.0)) {
            return Err(EvalError::file(
                &stats_path,
                "std",
                "positive deviations",
                format!("channel {c}"),
            ));
        }
        // The sizes come from the file: the networks may take no more values than its tensors
        // hold (each weight must be there), so a hostile configuration (a latent width of 10^9)
        // is refused instead of allocated.
        let (evaluator, refused) = with_parameter_budget(parameter_budget(elements), || {
            Self::build(
                config,
                Vocabulary::from_words(words),
                labels,
                stats,
                (skeleton, joints, fps),
                DType::F32,
                device,
            )
        });
        if let Some(refused) = refused {
            return Err(EvalError::file(
                &path,
                CONFIG_KEY,
                format!("sizes within the {elements} values of the file's tensors"),
                refused,
            ));
        }
        let mut evaluator = evaluator?;
        assign_parameters(&evaluator.motion_vars, &tensors, "motion.", &path)?;
        assign_parameters(&evaluator.text_vars, &tensors, "text.", &path)?;
        if let Some(stray) =
            tensors.keys().find(|k| !k.starts_with("motion.") && !k.starts_with("text."))
        {
            return Err(EvalError::file(
                &path,
                stray,
                "only motion.* and text.* weights",
                "another tensor",
            ));
        }
        evaluator.training = training;
        evaluator.origin = Some(path);
        Ok(evaluator)
    }
}
