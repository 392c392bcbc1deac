//! The evaluator's sizes and training settings.

use serde::{Deserialize, Serialize};

use dex2hoi_model::text::BuiltinTextConfig;
use dex2hoi_optim::OptimizerConfig;

use crate::error::{EvalError, Result};

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

    pub(super) fn text_config(&self) -> BuiltinTextConfig {
        BuiltinTextConfig {
            width: self.latent,
            layers: self.layers,
            heads: self.heads,
            max_tokens: self.max_tokens,
            output: self.embedding,
        }
    }
}
