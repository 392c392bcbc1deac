//! The optimiser's settings, the `[optimizer]` table of a training configuration.

use serde::{Deserialize, Serialize};

/// AdamW with linear warm-up and cosine decay, gradient clipping and EMA weights.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct OptimizerConfig {
    /// Peak learning rate (default 2e-4).
    pub learning_rate: f64,
    /// Adam `beta_1` (default 0.9).
    pub beta1: f64,
    /// Adam `beta_2` (default 0.999).
    pub beta2: f64,
    /// Adam `epsilon` (default 1e-8).
    pub epsilon: f64,
    /// Decoupled weight decay on matrices (rank >= 2; default 0.01).
    pub weight_decay: f64,
    /// Steps of linear warm-up from 0 (default 100).
    pub warmup_steps: usize,
    /// The learning rate at the last step as a share of the peak, reached by cosine decay
    /// (default 0.1).
    pub final_learning_rate_ratio: f64,
    /// Global gradient-norm clip (default 1); `None` does not clip.
    pub gradient_clip: Option<f64>,
    /// EMA decay of the sampling weights (default 0.999), warmed up as
    /// `min(decay, (1 + step) / (10 + step))`.
    pub ema_decay: f64,
    /// On a GPU, AdamW and the EMA as one CUDA kernel per parameter tensor (default true);
    /// false runs them as a few elementwise tensor operations per parameter. The CPU always
    /// updates with its parallel host loops. The two GPU paths agree to within 2e-7
    /// (relative) after three updates, not to the bit.
    pub fused: bool,
}

impl Default for OptimizerConfig {
    fn default() -> Self {
        Self {
            learning_rate: 2e-4,
            beta1: 0.9,
            beta2: 0.999,
            epsilon: 1e-8,
            weight_decay: 0.01,
            warmup_steps: 100,
            final_learning_rate_ratio: 0.1,
            gradient_clip: Some(1.0),
            ema_decay: 0.999,
            fused: true,
        }
    }
}
