//! The evaluator's motion encoder and action head, made of operations with a backward pass.
//!
//! The motion encoder projects each frame's features to the latent width, adds a learned
//! position embedding, runs pre-norm transformer blocks whose attention ignores padding frames,
//! and mean-pools the normalised tokens of the valid frames (the model crate's
//! [`TransformerEncoder`] and [`masked_mean`], shared with the built-in text encoder). Its pooled vector feeds both the
//! contrastive projection and the action head (one shared trunk: a second encoder would double
//! the cost on the CPU for little gain on datasets of this size).

use candle_core::Tensor;
use candle_nn::{VarBuilder, init::Init};

use dex2hoi_model::layers::{Dense, dense};
use dex2hoi_model::transformer::{BlockConfig, TransformerEncoder, masked_mean};

use crate::error::{EvalError, Result};

use super::EvaluatorConfig;

/// The motion encoder (see the module documentation).
pub struct MotionEncoder {
    input: Dense,
    positions: Tensor,
    blocks: TransformerEncoder,
    projection: Dense,
    action: Option<ActionHead>,
}

impl std::fmt::Debug for MotionEncoder {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("MotionEncoder")
            .field("blocks", &self.blocks.len())
            .field("action_head", &self.action.is_some())
            .finish()
    }
}

impl MotionEncoder {
    /// An encoder of `feature_size`-wide frames with an action head over `labels` labels (none
    /// when `labels` is 0); parameters under `vb`.
    pub fn new(
        config: &EvaluatorConfig,
        feature_size: usize,
        labels: usize,
        vb: VarBuilder<'_>,
    ) -> Result<Self> {
        let latent = config.latent;
        let block = BlockConfig::plain(latent, config.heads, 2 * latent, 0.0);
        let blocks = TransformerEncoder::new(&block, config.layers, vb.pp("blocks"))?;
        Ok(Self {
            input: dense(feature_size, latent, vb.pp("input"))?,
            positions: vb.get_with_hints(
                (config.clip_frames, latent),
                "positions",
                Init::Randn { mean: 0.0, stdev: 0.02 },
            )?,
            blocks,
            projection: dense(latent, config.embedding, vb.pp("projection"))?,
            action: if labels > 0 {
                Some(ActionHead::new(latent, labels, vb.pp("action"))?)
            } else {
                None
            },
        })
    }

    /// The pooled representation of a batch of clips.
    ///
    /// # Shapes
    /// - `features`: `[batch, frames, feature_size]` with `frames <= clip_frames`
    /// - `mask`: `[batch, frames]`, 1 for a frame of the clip and 0 for padding
    /// - returns `[batch, latent]`
    pub fn forward(&self, features: &Tensor, mask: &Tensor) -> Result<Tensor> {
        let (_, frames, _) = features.dims3()?;
        let longest = self.positions.dims()[0];
        if frames == 0 || frames > longest {
            return Err(EvalError::invalid(
                "motion encoder input",
                format!("1 to {longest} frames"),
                frames,
            ));
        }
        let x =
            self.input.forward(features)?.broadcast_add(&self.positions.narrow(0, 0, frames)?)?;
        Ok(masked_mean(&self.blocks.forward(&x, Some(mask), None)?, mask)?)
    }

    /// The contrastive embedding (before L2 normalisation) of pooled representations.
    ///
    /// # Shapes
    /// - `pooled`: `[batch, latent]`; returns `[batch, embedding]`
    pub fn embed(&self, pooled: &Tensor) -> Result<Tensor> {
        Ok(self.projection.forward(pooled)?)
    }

    /// The action head, when the training data had action labels.
    pub fn action_head(&self) -> Option<&ActionHead> {
        self.action.as_ref()
    }
}

/// The action classifier on the pooled motion representation: one hidden SiLU layer (its
/// output is the feature vector of FID, Diversity and MultiModality by label) and the logits.
pub struct ActionHead {
    hidden: Dense,
    logits: Dense,
}

impl ActionHead {
    /// A head from `latent`-wide representations to `labels` logits.
    pub fn new(latent: usize, labels: usize, vb: VarBuilder<'_>) -> Result<Self> {
        Ok(Self {
            hidden: dense(latent, latent, vb.pp("hidden"))?,
            logits: dense(latent, labels, vb.pp("logits"))?,
        })
    }

    /// The penultimate-layer features.
    ///
    /// # Shapes
    /// - `pooled`: `[batch, latent]`; returns `[batch, latent]`
    pub fn features(&self, pooled: &Tensor) -> Result<Tensor> {
        Ok(self.hidden.forward(pooled)?.silu()?)
    }

    /// The label logits of features.
    ///
    /// # Shapes
    /// - `features`: `[batch, latent]`; returns `[batch, labels]`
    pub fn forward(&self, features: &Tensor) -> Result<Tensor> {
        Ok(self.logits.forward(features)?)
    }
}
