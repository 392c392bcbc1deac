//! Learned evaluators (docs/CONVENTIONS.md, "Embedding metrics"): a contrastive text-motion model and an action
//! classifier, trained together on the training split of a dataset.
//!
//! - **Motion encoder** ([`MotionEncoder`]): a masked transformer over per-frame features of a
//!   clip (joint positions relative to the first frame's root on the floor, both objects' 6D
//!   rotation and position, presence flags; see [`clip`]), normalised with statistics of the
//!   training split. Clips longer than [`EvaluatorConfig::clip_frames`] are cut to their first
//!   frames, shorter ones are padded and masked.
//! - **Text encoder**: a small transformer over a word vocabulary of the training texts (the
//!   built-in encoder of `dex2hoi-model`), with its own weights: the evaluator never shares
//!   weights with a generator. A frozen pretrained encoder (CLIP, BERT) is not offered.
//! - **Objective**: symmetric InfoNCE between the L2-normalised motion and text embeddings
//!   (cosine similarity over a temperature; pairs that share a text count as positives of each
//!   other), plus, when the dataset has action labels, the cross-entropy of an action head on
//!   the same motion encoder ([`ActionHead`]); its hidden layer gives the features for FID,
//!   Diversity and MultiModality by label (IMoS protocol).
//! - **Training** draws, at every step, a batch of distinct training sequences, a random window
//!   of each and one of its texts, from a ChaCha8 stream seeded by the seed and the step, so the
//!   same seed gives the same weights.
//! - **Files** ([`Evaluator::save`]): `evaluator.safetensors` (weights `motion.*` and `text.*`;
//!   metadata: format, configuration, vocabulary, labels, skeleton, joints, fps, training
//!   summary) and `stats.json` ([`ClipStats`]). A dataset of another skeleton, joint count or
//!   frame rate is refused ([`Evaluator::check_dataset`]).
//!
//! Layout: [`config`] (sizes and settings), [`batching`] (training batches), [`training`]
//! (loss and the training loop), [`embedding`] (embeddings, action features and labels),
//! [`retrieval`] (held-out retrieval and accuracy), [`files`] (save and load), next to
//! [`clip`], [`encoder`] and [`loss`]. Their public items are re-exported here.

pub mod batching;
pub mod clip;
pub mod config;
pub mod embedding;
pub mod encoder;
pub mod files;
pub mod loss;
pub mod retrieval;
pub mod training;

use std::path::{Path, PathBuf};

use candle_core::{DType, Device};

use dex2hoi_data::dataset::{Dataset, Manifest};
use dex2hoi_model::SeededVarMap;
use dex2hoi_model::text::{BuiltinTextEncoder, Vocabulary};

use crate::error::{EvalError, Result};

pub use batching::{ActionTargets, TrainingBatch};
pub use clip::{ClipStats, MotionClip, clip_feature_size};
pub use config::EvaluatorConfig;
pub use encoder::{ActionHead, MotionEncoder};
pub use files::{
    CONFIG_KEY, EVALUATOR_FILE, EVALUATOR_FORMAT, FPS_KEY, JOINTS_KEY, LABELS_KEY, SKELETON_KEY,
    STATS_FILE, TRAINING_KEY, VOCABULARY_KEY,
};
pub use retrieval::Retrieval;
pub use training::{EvaluatorLoss, TrainingSummary, train_evaluator};

use batching::usable_sequences;

/// Salt of the text encoder's parameter seed.
const TEXT_SEED_SALT: u64 = 0x6576_616c_7465_7874;

/// A trained (or freshly initialised) evaluator.
pub struct Evaluator {
    config: EvaluatorConfig,
    motion_vars: SeededVarMap,
    text_vars: SeededVarMap,
    motion: MotionEncoder,
    text: BuiltinTextEncoder,
    stats: ClipStats,
    labels: Vec<String>,
    skeleton: String,
    joints: usize,
    fps: f32,
    training: Option<TrainingSummary>,
    origin: Option<PathBuf>,
    device: Device,
    dtype: DType,
}

impl std::fmt::Debug for Evaluator {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Evaluator")
            .field("config", &self.config)
            .field("labels", &self.labels)
            .field("skeleton", &self.skeleton)
            .field("joints", &self.joints)
            .field("fps", &self.fps)
            .field("vocabulary", &self.text.vocabulary().len())
            .field("training", &self.training)
            .finish()
    }
}

impl Evaluator {
    /// A freshly initialised evaluator for a dataset: vocabulary of the training texts, action
    /// labels of the training split (sorted), feature statistics of the training split, and
    /// weights from `config.seed`, on `device`.
    pub fn initialise(
        dataset: &Dataset,
        dataset_path: &Path,
        config: &EvaluatorConfig,
        dtype: DType,
        device: &Device,
    ) -> Result<Self> {
        config.validate()?;
        let sequences = usable_sequences(dataset);
        if sequences.is_empty() {
            return Err(EvalError::file(
                dataset_path,
                "training split",
                "at least one training sequence with a text",
                "none",
            ));
        }
        let manifest = &dataset.manifest;
        let vocabulary = Vocabulary::from_texts(
            sequences.iter().flat_map(|s| s.texts.iter().map(String::as_str)),
        );
        let labels: Vec<String> = sequences
            .iter()
            .filter_map(|s| s.action.clone())
            .collect::<std::collections::BTreeSet<_>>()
            .into_iter()
            .collect();
        let stats = ClipStats::compute(sequences.iter().copied(), manifest.joints)?;
        Self::build(
            config.clone(),
            vocabulary,
            labels,
            stats,
            (manifest.skeleton.clone(), manifest.joints, manifest.fps),
            dtype,
            device,
        )
    }

    fn build(
        config: EvaluatorConfig,
        vocabulary: Vocabulary,
        labels: Vec<String>,
        stats: ClipStats,
        (skeleton, joints, fps): (String, usize, f32),
        dtype: DType,
        device: &Device,
    ) -> Result<Self> {
        let motion_vars = SeededVarMap::new(config.seed);
        let text_vars = SeededVarMap::new(config.seed ^ TEXT_SEED_SALT);
        let motion = MotionEncoder::new(
            &config,
            stats.feature_size,
            labels.len(),
            motion_vars.builder(dtype, device),
        )?;
        let text = BuiltinTextEncoder::new(
            vocabulary,
            config.text_config(),
            text_vars.builder(dtype, device),
        )?;
        Ok(Self {
            config,
            motion_vars,
            text_vars,
            motion,
            text,
            stats,
            labels,
            skeleton,
            joints,
            fps,
            training: None,
            origin: None,
            device: device.clone(),
            dtype,
        })
    }

    /// The configuration.
    pub fn config(&self) -> &EvaluatorConfig {
        &self.config
    }

    /// The action labels (empty when the training data had none), in class order.
    pub fn labels(&self) -> &[String] {
        &self.labels
    }

    /// The text vocabulary.
    pub fn vocabulary(&self) -> &Vocabulary {
        self.text.vocabulary()
    }

    /// The feature statistics.
    pub fn stats(&self) -> &ClipStats {
        &self.stats
    }

    /// The skeleton name, joint count and frame rate of the training data.
    pub fn data_format(&self) -> (&str, usize, f32) {
        (&self.skeleton, self.joints, self.fps)
    }

    /// What training did (`None` for an untrained evaluator).
    pub fn training(&self) -> Option<&TrainingSummary> {
        self.training.as_ref()
    }

    /// Refuses a dataset whose skeleton, joint count or frame rate differ from the training
    /// data's; `path` is the dataset directory.
    pub fn check_dataset(&self, manifest: &Manifest, path: &Path) -> Result<()> {
        let file = path.join("manifest.json");
        let trained = match &self.origin {
            Some(origin) => format!(" (the evaluator {})", origin.display()),
            None => " (the evaluator's training data)".to_string(),
        };
        if manifest.skeleton != self.skeleton {
            return Err(EvalError::file(
                file,
                "skeleton",
                format!("{}{trained}", self.skeleton),
                &manifest.skeleton,
            ));
        }
        if manifest.joints != self.joints {
            return Err(EvalError::file(
                file,
                "joints",
                format!("{}{trained}", self.joints),
                manifest.joints,
            ));
        }
        if (manifest.fps - self.fps).abs() > 1e-3 {
            return Err(EvalError::file(
                file,
                "fps",
                format!("{}{trained}", self.fps),
                manifest.fps,
            ));
        }
        Ok(())
    }
}
