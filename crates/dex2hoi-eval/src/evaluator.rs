//! Learned evaluators (docs/CONVENTIONS.md, "Embedding metrics"): a contrastive text-motion model
//! and an action classifier, trained together on the training split of a dataset.
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

pub mod clip;
pub mod encoder;
pub mod loss;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use candle_core::{DType, Device, Tensor};
use rand::Rng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use dex2hoi_data::dataset::{Dataset, Manifest, Split, write_atomically};
use dex2hoi_data::features::ProcessedSequence;
use dex2hoi_model::SeededVarMap;
use dex2hoi_model::checkpoint::{
    FORMAT_KEY, assign_parameters, named_parameters, read_tensors, write_tensors,
};
use dex2hoi_model::text::{BuiltinTextConfig, BuiltinTextEncoder, UNKNOWN, Vocabulary, words};
use dex2hoi_optim::{AdamW, OptimizerConfig, Parameter, learning_rate, parameters_of, step_rng};

use crate::error::{EvalError, Result};

pub use clip::{ClipStats, MotionClip, clip_feature_size};
pub use encoder::{ActionHead, MotionEncoder};

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

/// Salt of the text encoder's parameter seed.
const TEXT_SEED_SALT: u64 = 0x6576_616c_7465_7874;
/// Salt of the training batches' random streams.
const BATCH_SEED_SALT: u64 = 0x6576_616c_6261_7463;
/// Clips embedded per forward pass outside training.
const EMBED_CHUNK: usize = 64;

/// Sizes and training settings of an evaluator. The defaults suit a 2-core CPU.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct EvaluatorConfig {
    /// Token width of both encoders (default 128).
    pub latent: usize,
    /// Transformer blocks of each encoder (default 2).
    pub layers: usize,
    /// Attention heads; must divide `latent` (default 4).
    pub heads: usize,
    /// Frames of a clip at the dataset's frame rate: longer motions are cut to their first
    /// frames, shorter ones are masked (default 60).
    pub clip_frames: usize,
    /// Longest text in words; longer texts are cut (default 48).
    pub max_tokens: usize,
    /// Width of the contrastive embeddings (default 64).
    pub embedding: usize,
    /// Softmax temperature of the cosine similarities (default 0.1).
    pub temperature: f64,
    /// Weight of the action cross-entropy next to the contrastive loss (default 1).
    pub classification_weight: f64,
    /// Share of words replaced by the unknown token in training, so that unseen words map to a
    /// trained embedding (default 0.1).
    pub word_dropout: f64,
    /// Optimiser steps (default 1000).
    pub steps: usize,
    /// Sequences per batch, capped by the training split's size (default 32).
    pub batch_size: usize,
    /// Peak learning rate of AdamW (default 1e-3).
    pub learning_rate: f64,
    /// Steps of linear warm-up (default 50), then cosine decay to a tenth.
    pub warmup_steps: usize,
    /// Decoupled weight decay on matrices (default 0.01).
    pub weight_decay: f64,
    /// Global gradient-norm clip (default 1).
    pub gradient_clip: f64,
    /// Seed of the initialisation and of the batches (default 0).
    pub seed: u64,
}

impl Default for EvaluatorConfig {
    fn default() -> Self {
        Self {
            latent: 128,
            layers: 2,
            heads: 4,
            clip_frames: 60,
            max_tokens: 48,
            embedding: 64,
            temperature: 0.1,
            classification_weight: 1.0,
            word_dropout: 0.1,
            steps: 1000,
            batch_size: 32,
            learning_rate: 1e-3,
            warmup_steps: 50,
            weight_decay: 0.01,
            gradient_clip: 1.0,
            seed: 0,
        }
    }
}

impl EvaluatorConfig {
    /// Refuses sizes and settings that cannot be used.
    pub fn validate(&self) -> Result<()> {
        let invalid = |what: &str, expected: &str, got: String| {
            Err(EvalError::invalid(format!("evaluator config {what}"), expected, got))
        };
        if self.latent == 0 || self.heads == 0 || !self.latent.is_multiple_of(self.heads) {
            return invalid(
                "latent/heads",
                "a positive latent width divisible by the heads",
                format!("latent {} with {} heads", self.latent, self.heads),
            );
        }
        if self.layers == 0 {
            return invalid("layers", "at least 1", self.layers.to_string());
        }
        if self.clip_frames < 2 {
            return invalid("clip_frames", "at least 2", self.clip_frames.to_string());
        }
        if self.max_tokens == 0 || self.embedding == 0 {
            return invalid(
                "max_tokens/embedding",
                "positive sizes",
                format!("{} and {}", self.max_tokens, self.embedding),
            );
        }
        if !(self.temperature.is_finite() && self.temperature > 0.0) {
            return invalid("temperature", "a positive number", self.temperature.to_string());
        }
        if !(self.classification_weight.is_finite() && self.classification_weight >= 0.0) {
            return invalid(
                "classification_weight",
                "a number >= 0",
                self.classification_weight.to_string(),
            );
        }
        if !(0.0..1.0).contains(&self.word_dropout) {
            return invalid("word_dropout", "a share in [0, 1)", self.word_dropout.to_string());
        }
        if self.steps == 0 {
            return invalid("steps", "at least 1", self.steps.to_string());
        }
        if self.batch_size < 2 {
            return invalid("batch_size", "at least 2", self.batch_size.to_string());
        }
        if !(self.learning_rate.is_finite() && self.learning_rate > 0.0) {
            return invalid("learning_rate", "a positive number", self.learning_rate.to_string());
        }
        if !(self.weight_decay.is_finite() && self.weight_decay >= 0.0) {
            return invalid("weight_decay", "a number >= 0", self.weight_decay.to_string());
        }
        if !(self.gradient_clip.is_finite() && self.gradient_clip > 0.0) {
            return invalid("gradient_clip", "a positive number", self.gradient_clip.to_string());
        }
        Ok(())
    }

    /// The optimiser settings of the training.
    pub fn optimizer(&self) -> OptimizerConfig {
        OptimizerConfig {
            learning_rate: self.learning_rate,
            warmup_steps: self.warmup_steps,
            weight_decay: self.weight_decay,
            gradient_clip: Some(self.gradient_clip),
            final_learning_rate_ratio: 0.1,
            ..OptimizerConfig::default()
        }
    }

    fn text_config(&self) -> BuiltinTextConfig {
        BuiltinTextConfig {
            width: self.latent,
            layers: self.layers,
            heads: self.heads,
            max_tokens: self.max_tokens,
            output: self.embedding,
        }
    }
}

/// What training did, saved with the evaluator.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TrainingSummary {
    /// Optimiser steps.
    pub steps: usize,
    /// Mean total loss over the first tenth of the steps (at least one).
    pub first_loss: f64,
    /// Mean total loss over the last tenth of the steps (at least one).
    pub final_loss: f64,
    /// Training sequences used.
    pub sequences: usize,
}

/// A training batch: normalised features with their mask, text tokens, and targets.
#[derive(Debug, Clone)]
pub struct TrainingBatch {
    /// `[batch, frames, 3J + 20]` normalised clip features.
    pub features: Tensor,
    /// `[batch, frames]`: 1 for a frame of the clip, 0 for padding.
    pub mask: Tensor,
    /// Token ids of each text (after word dropout).
    pub tokens: Vec<Vec<u32>>,
    /// `[batch, batch]`: `1 / n` where texts `i` and `j` are the same (`n` texts like `i`).
    pub text_targets: Tensor,
    /// Action targets, when the evaluator has an action head and a row has a label.
    pub actions: Option<ActionTargets>,
}

/// Action targets of a batch.
#[derive(Debug, Clone)]
pub struct ActionTargets {
    /// `[batch, labels]` one-hot rows (zeros for an unlabelled row).
    pub one_hot: Tensor,
    /// `[batch]`: 1 for a labelled row.
    pub weights: Tensor,
    /// Labelled rows.
    pub labelled: usize,
}

/// The terms of the training loss.
#[derive(Debug, Clone)]
pub struct EvaluatorLoss {
    /// `contrastive + classification_weight * classification`, a scalar.
    pub total: Tensor,
    /// The symmetric InfoNCE, a scalar.
    pub contrastive: Tensor,
    /// The action cross-entropy, a scalar (when the batch has labels).
    pub classification: Option<Tensor>,
}

/// Top-1 text retrieval from motions in batches (R-precision at 1).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Retrieval {
    /// Share of motions whose own text is the nearest of their batch (a tie with an identical
    /// text counts as a hit).
    pub top1: f64,
    /// Motions ranked.
    pub pairs: usize,
    /// Pairs per batch (chance is `1 / batch`).
    pub batch: usize,
}

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

/// The texts of a sequence that have at least one word.
fn usable_texts(sequence: &ProcessedSequence) -> Vec<&str> {
    sequence.texts.iter().map(String::as_str).filter(|t| !words(t).is_empty()).collect()
}

/// The training sequences with at least one text that has a word.
fn usable_sequences(dataset: &Dataset) -> Vec<&ProcessedSequence> {
    dataset
        .splits
        .get(&Split::Train)
        .map(|s| s.iter().filter(|q| !usable_texts(q).is_empty()).collect())
        .unwrap_or_default()
}

/// A value as JSON for the metadata of `path`.
fn to_json<T: Serialize + ?Sized>(path: &Path, key: &str, value: &T) -> Result<String> {
    serde_json::to_string(value).map_err(|e| EvalError::file(path, key, "JSON", e))
}

impl Evaluator {
    /// A freshly initialised evaluator for a dataset: vocabulary of the training texts, action
    /// labels of the training split (sorted), feature statistics of the training split, and
    /// weights from `config.seed`.
    pub fn initialise(
        dataset: &Dataset,
        dataset_path: &Path,
        config: &EvaluatorConfig,
        dtype: DType,
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
        )
    }

    fn build(
        config: EvaluatorConfig,
        vocabulary: Vocabulary,
        labels: Vec<String>,
        stats: ClipStats,
        (skeleton, joints, fps): (String, usize, f32),
        dtype: DType,
    ) -> Result<Self> {
        let device = Device::Cpu;
        let motion_vars = SeededVarMap::new(config.seed);
        let text_vars = SeededVarMap::new(config.seed ^ TEXT_SEED_SALT);
        let motion = MotionEncoder::new(
            &config,
            stats.feature_size,
            labels.len(),
            motion_vars.builder(dtype, &device),
        )?;
        let text = BuiltinTextEncoder::new(
            vocabulary,
            config.text_config(),
            text_vars.builder(dtype, &device),
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
            device,
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

    /// Every trained parameter, sorted by name: `motion.*` then `text.*`.
    pub fn parameters(&self) -> Vec<Parameter> {
        let mut parameters = parameters_of(self.motion_vars.var_map(), "motion.");
        parameters.extend(parameters_of(self.text_vars.var_map(), "text."));
        parameters
    }

    /// Normalised features and mask of clips, padded to the longest (at most `clip_frames`).
    ///
    /// # Shapes
    /// - returns `[clips, frames, 3J + 20]` and `[clips, frames]`
    fn clip_tensors(&self, clips: &[MotionClip]) -> Result<(Tensor, Tensor)> {
        if clips.is_empty() {
            return Err(EvalError::invalid("motion clips", "at least one clip", 0));
        }
        for (i, clip) in clips.iter().enumerate() {
            clip.validate(self.joints).map_err(|e| match e {
                EvalError::Invalid { what, expected, got } => {
                    EvalError::Invalid { what: format!("{what} {i}"), expected, got }
                }
                other => other,
            })?;
        }
        let frames =
            clips.iter().map(MotionClip::frames).max().unwrap_or(1).min(self.config.clip_frames);
        let width = self.stats.feature_size;
        let mut features = vec![0.0f32; clips.len() * frames * width];
        let mut mask = vec![0.0f32; clips.len() * frames];
        for (i, clip) in clips.iter().enumerate() {
            let normalised = self.stats.normalise(clip, self.joints, frames);
            let valid = normalised.len() / width;
            features[i * frames * width..i * frames * width + normalised.len()]
                .copy_from_slice(&normalised);
            mask[i * frames..i * frames + valid].fill(1.0);
        }
        let features = Tensor::from_vec(features, (clips.len(), frames, width), &self.device)?
            .to_dtype(self.dtype)?;
        let mask =
            Tensor::from_vec(mask, (clips.len(), frames), &self.device)?.to_dtype(self.dtype)?;
        Ok((features, mask))
    }

    /// A training batch of clips with their texts and action labels (indices into
    /// [`Evaluator::labels`]); with `word_dropout`, words are replaced by the unknown token at
    /// the configured rate.
    ///
    /// # Shapes
    /// - `clips`, `texts`, `actions`: `[batch]` each; the batch's features are
    ///   `[batch, min(longest clip, clip_frames), 3J + 20]`
    pub fn batch(
        &self,
        clips: &[MotionClip],
        texts: &[&str],
        actions: &[Option<usize>],
        word_dropout: Option<&mut ChaCha8Rng>,
    ) -> Result<TrainingBatch> {
        if texts.len() != clips.len() || actions.len() != clips.len() {
            return Err(EvalError::invalid(
                "training batch",
                format!("{} texts and action labels", clips.len()),
                format!("{} and {}", texts.len(), actions.len()),
            ));
        }
        let (features, mask) = self.clip_tensors(clips)?;
        let mut tokens = self.tokenize(texts)?;
        if let Some(rng) = word_dropout {
            for token in tokens.iter_mut().flatten() {
                if rng.random::<f64>() < self.config.word_dropout {
                    *token = UNKNOWN;
                }
            }
        }
        let batch = clips.len();
        let mut targets = vec![0.0f32; batch * batch];
        for i in 0..batch {
            let same: Vec<usize> = (0..batch).filter(|&j| texts[j] == texts[i]).collect();
            for &j in &same {
                targets[i * batch + j] = 1.0 / same.len() as f32;
            }
        }
        let text_targets =
            Tensor::from_vec(targets, (batch, batch), &self.device)?.to_dtype(self.dtype)?;
        let labels = self.labels.len();
        let actions = if labels > 0 && actions.iter().any(Option::is_some) {
            let mut one_hot = vec![0.0f32; batch * labels];
            let mut weights = vec![0.0f32; batch];
            for (i, action) in actions.iter().enumerate() {
                if let Some(label) = *action {
                    if label >= labels {
                        return Err(EvalError::invalid(
                            "action label",
                            format!("an index below {labels}"),
                            label,
                        ));
                    }
                    one_hot[i * labels + label] = 1.0;
                    weights[i] = 1.0;
                }
            }
            let labelled = weights.iter().filter(|w| **w > 0.0).count();
            Some(ActionTargets {
                one_hot: Tensor::from_vec(one_hot, (batch, labels), &self.device)?
                    .to_dtype(self.dtype)?,
                weights: Tensor::from_vec(weights, batch, &self.device)?.to_dtype(self.dtype)?,
                labelled,
            })
        } else {
            None
        };
        Ok(TrainingBatch { features, mask, tokens, text_targets, actions })
    }

    fn tokenize(&self, texts: &[&str]) -> Result<Vec<Vec<u32>>> {
        texts
            .iter()
            .enumerate()
            .map(|(i, text)| {
                let tokens = self.text.vocabulary().tokenize(text);
                if tokens.is_empty() {
                    Err(EvalError::invalid(
                        format!("text {i}"),
                        "a text with at least one word",
                        format!("{text:?}"),
                    ))
                } else {
                    Ok(tokens)
                }
            })
            .collect()
    }

    /// Draws the training batch of a step from `sequences`: distinct sequences, a random window
    /// of `clip_frames` frames of each (the whole sequence when shorter), one of its texts, its
    /// label.
    pub fn draw_batch(
        &self,
        sequences: &[&ProcessedSequence],
        rng: &mut ChaCha8Rng,
    ) -> Result<TrainingBatch> {
        let size = self.config.batch_size.min(sequences.len());
        if size == 0 {
            return Err(EvalError::invalid("training sequences", "at least one", 0));
        }
        let chosen = rand::seq::index::sample(rng, sequences.len(), size).into_vec();
        let mut clips = Vec::with_capacity(size);
        let mut texts = Vec::with_capacity(size);
        let mut actions = Vec::with_capacity(size);
        for index in chosen {
            let sequence = sequences[index];
            let frames = sequence.frames.min(self.config.clip_frames);
            let start = rng.random_range(0..=sequence.frames - frames);
            clips.push(MotionClip::from_processed(sequence, start, frames)?);
            let usable = usable_texts(sequence);
            if usable.is_empty() {
                return Err(EvalError::invalid(
                    format!("texts of sequence {}", sequence.source_id),
                    "at least one text with a word",
                    format!("{:?}", sequence.texts),
                ));
            }
            texts.push(usable[rng.random_range(0..usable.len())]);
            actions.push(
                sequence.action.as_ref().and_then(|a| self.labels.iter().position(|l| l == a)),
            );
        }
        self.batch(&clips, &texts, &actions, Some(rng))
    }

    /// The training loss of a batch.
    pub fn loss(&self, batch: &TrainingBatch) -> Result<EvaluatorLoss> {
        let pooled = self.motion.forward(&batch.features, &batch.mask)?;
        let motion = loss::l2_normalise(&self.motion.embed(&pooled)?)?;
        let text = loss::l2_normalise(&self.text.encode_ids(&batch.tokens)?)?;
        let contrastive =
            loss::contrastive_loss(&motion, &text, &batch.text_targets, self.config.temperature)?;
        let classification = match (self.motion.action_head(), &batch.actions) {
            (Some(head), Some(targets)) if targets.labelled > 0 => {
                let logits = head.forward(&head.features(&pooled)?)?;
                Some(loss::classification_loss(
                    &logits,
                    &targets.one_hot,
                    &targets.weights,
                    targets.labelled,
                )?)
            }
            _ => None,
        };
        let total = match &classification {
            Some(c) => (&contrastive + (c * self.config.classification_weight)?)?,
            None => contrastive.clone(),
        };
        Ok(EvaluatorLoss { total, contrastive, classification })
    }

    fn rows(tensor: &Tensor) -> Result<Vec<Vec<f32>>> {
        Ok(tensor.detach().to_dtype(DType::F32)?.to_vec2::<f32>()?)
    }

    fn pooled_chunks(
        &self,
        clips: &[MotionClip],
        head: impl Fn(&Tensor) -> Result<Tensor>,
    ) -> Result<Vec<Vec<f32>>> {
        if clips.is_empty() {
            return Ok(Vec::new());
        }
        let mut out = Vec::with_capacity(clips.len());
        for chunk in clips.chunks(EMBED_CHUNK) {
            let (features, mask) = self.clip_tensors(chunk)?;
            let pooled = self.motion.forward(&features, &mask)?;
            out.extend(Self::rows(&head(&pooled)?)?);
        }
        Ok(out)
    }

    /// Unit-length motion embeddings (their Euclidean distances rank like cosine similarity).
    ///
    /// # Shapes
    /// - returns `[clips][embedding]`
    pub fn embed_motions(&self, clips: &[MotionClip]) -> Result<Vec<Vec<f32>>> {
        self.pooled_chunks(clips, |pooled| loss::l2_normalise(&self.motion.embed(pooled)?))
    }

    /// Unit-length text embeddings; unknown words use the unknown token, a text without any
    /// word is refused.
    ///
    /// # Shapes
    /// - returns `[texts][embedding]`
    pub fn embed_texts(&self, texts: &[&str]) -> Result<Vec<Vec<f32>>> {
        let mut out = Vec::with_capacity(texts.len());
        for chunk in texts.chunks(EMBED_CHUNK) {
            let tokens = self.tokenize(chunk)?;
            out.extend(Self::rows(&loss::l2_normalise(&self.text.encode_ids(&tokens)?)?)?);
        }
        Ok(out)
    }

    fn action_head(&self) -> Result<&ActionHead> {
        self.motion.action_head().ok_or_else(|| {
            EvalError::invalid(
                "action classifier",
                "an evaluator trained on a dataset with action labels",
                "an evaluator without action labels",
            )
        })
    }

    /// The action classifier's penultimate-layer features (FID, Diversity and MultiModality by
    /// label); an error when the training data had no action labels.
    ///
    /// # Shapes
    /// - returns `[clips][latent]`
    pub fn action_features(&self, clips: &[MotionClip]) -> Result<Vec<Vec<f32>>> {
        let head = self.action_head()?;
        self.pooled_chunks(clips, |pooled| head.features(pooled))
    }

    /// The most likely action label of each clip (an index into [`Evaluator::labels`]).
    ///
    /// # Shapes
    /// - returns `[clips]`
    pub fn classify(&self, clips: &[MotionClip]) -> Result<Vec<usize>> {
        let head = self.action_head()?;
        let logits = self.pooled_chunks(clips, |pooled| head.forward(&head.features(pooled)?))?;
        Ok(logits
            .iter()
            .map(|row| {
                row.iter()
                    .enumerate()
                    .fold(
                        (0, f32::NEG_INFINITY),
                        |best, (k, &v)| if v > best.1 { (k, v) } else { best },
                    )
                    .0
            })
            .collect())
    }

    /// The first `clip_frames` frames of each sequence (the evaluation windows).
    pub fn evaluation_windows(&self, sequences: &[ProcessedSequence]) -> Result<Vec<MotionClip>> {
        sequences
            .iter()
            .map(|s| MotionClip::from_processed(s, 0, s.frames.min(self.config.clip_frames)))
            .collect()
    }

    /// Top-1 text retrieval: the clips in consecutive batches of `batch` pairs (the remainder
    /// dropped, as in R-precision; one batch of all when there are fewer), each motion ranking
    /// the texts of its batch by Euclidean distance.
    ///
    /// # Shapes
    /// - `clips`, `texts`: `[pairs]`, pair `i` a motion and its description
    pub fn retrieval(
        &self,
        clips: &[MotionClip],
        texts: &[&str],
        batch: usize,
    ) -> Result<Retrieval> {
        if clips.len() != texts.len() || clips.len() < 2 || batch < 2 {
            return Err(EvalError::invalid(
                "retrieval pairs",
                "as many texts as clips, at least 2, in batches of at least 2",
                format!("{} clips, {} texts, batches of {batch}", clips.len(), texts.len()),
            ));
        }
        let batch = batch.min(clips.len());
        let used = clips.len() / batch * batch;
        let motion = self.embed_motions(&clips[..used])?;
        let text = self.embed_texts(&texts[..used])?;
        let distance = |a: &[f32], b: &[f32]| -> f32 {
            a.iter().zip(b).map(|(x, y)| (x - y) * (x - y)).sum::<f32>()
        };
        let mut hits = 0usize;
        for group in 0..used / batch {
            for i in group * batch..(group + 1) * batch {
                let own = distance(&motion[i], &text[i]);
                let nearer = (group * batch..(group + 1) * batch)
                    .filter(|&j| j != i && texts[j] != texts[i])
                    .any(|j| distance(&motion[i], &text[j]) < own);
                hits += usize::from(!nearer);
            }
        }
        Ok(Retrieval { top1: hits as f64 / used as f64, pairs: used, batch })
    }

    /// Share of clips whose predicted label is `labels[i]` (a label the evaluator does not know
    /// counts as a miss).
    ///
    /// # Shapes
    /// - `clips`, `labels`: `[clips]`
    pub fn classification_accuracy(&self, clips: &[MotionClip], labels: &[&str]) -> Result<f64> {
        if clips.len() != labels.len() || clips.is_empty() {
            return Err(EvalError::invalid(
                "classification pairs",
                "as many labels as clips, at least one",
                format!("{} clips and {} labels", clips.len(), labels.len()),
            ));
        }
        let predicted = self.classify(clips)?;
        let hits = predicted.iter().zip(labels).filter(|(p, l)| self.labels[**p] == **l).count();
        Ok(hits as f64 / clips.len() as f64)
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
    /// another size. `dir` is the evaluator directory (or its `evaluator.safetensors`).
    pub fn load(dir: &Path) -> Result<Self> {
        let (dir, path) = if dir.is_file() {
            (dir.parent().unwrap_or(Path::new(".")), dir.to_path_buf())
        } else {
            (dir, dir.join(EVALUATOR_FILE))
        };
        let (tensors, metadata) = read_tensors(&path, &Device::Cpu)?;
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
        let mut evaluator = Self::build(
            config,
            Vocabulary::from_words(words),
            labels,
            stats,
            (skeleton, joints, fps),
            DType::F32,
        )?;
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

/// Trains an evaluator on the training split of `dataset` (see the module documentation);
/// `progress` is called after every step with the steps done and the step's total loss.
pub fn train_evaluator(
    dataset: &Dataset,
    dataset_path: &Path,
    config: &EvaluatorConfig,
    progress: &mut dyn FnMut(usize, f64),
) -> Result<Evaluator> {
    let mut evaluator = Evaluator::initialise(dataset, dataset_path, config, DType::F32)?;
    let sequences = usable_sequences(dataset);
    let parameters = evaluator.parameters();
    let optimizer_config = config.optimizer();
    let mut optimizer = AdamW::new(optimizer_config.clone(), &parameters);
    let mut losses = Vec::with_capacity(config.steps);
    for step in 0..config.steps {
        let mut rng = step_rng(config.seed ^ BATCH_SEED_SALT, step);
        let batch = evaluator.draw_batch(&sequences, &mut rng)?;
        let loss = evaluator.loss(&batch)?;
        let value = loss.total.to_dtype(DType::F64)?.to_scalar::<f64>()?;
        if !value.is_finite() {
            return Err(EvalError::invalid(
                format!("evaluator loss at step {}", step + 1),
                "a finite number",
                value,
            ));
        }
        let gradients = loss.total.backward()?;
        optimizer.update(
            &parameters,
            &gradients,
            learning_rate(&optimizer_config, step, config.steps),
        )?;
        losses.push(value);
        progress(step + 1, value);
    }
    let tenth = (config.steps / 10).max(1);
    let mean = |values: &[f64]| values.iter().sum::<f64>() / values.len() as f64;
    evaluator.training = Some(TrainingSummary {
        steps: config.steps,
        first_loss: mean(&losses[..tenth]),
        final_loss: mean(&losses[losses.len() - tenth..]),
        sequences: sequences.len(),
    });
    Ok(evaluator)
}
