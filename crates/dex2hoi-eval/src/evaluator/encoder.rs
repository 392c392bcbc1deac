//! The evaluator's motion encoder and action head, made of operations with a backward pass.
//!
//! The motion encoder projects each frame's features to the latent width, adds a learned
//! position embedding, runs pre-norm transformer blocks whose attention ignores padding frames,
//! and mean-pools the normalised tokens of the valid frames. Its pooled vector feeds both the
//! contrastive projection and the action head (one shared trunk: a second encoder would double
//! the cost on the CPU for little gain on datasets of this size).

use candle_core::{D, Tensor};
use candle_nn::{VarBuilder, init::Init};

use dex2hoi_model::layers::{Attention, Dense, FeedForward, dense, layer_norm};

use crate::error::{EvalError, Result};

use super::EvaluatorConfig;

struct Block {
    attention: Attention,
    feed_forward: FeedForward,
}

/// The motion encoder (see the module documentation).
pub struct MotionEncoder {
    input: Dense,
    positions: Tensor,
    blocks: Vec<Block>,
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
        let blocks = (0..config.layers)
            .map(|i| {
                let vb = vb.pp(format!("blocks.{i}"));
                Ok(Block {
                    attention: Attention::new(latent, config.heads, vb.pp("attention"))?,
                    feed_forward: FeedForward::new(latent, 2 * latent, vb.pp("feed_forward"))?,
                })
            })
            .collect::<Result<_>>()?;
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
        let mut x =
            self.input.forward(features)?.broadcast_add(&self.positions.narrow(0, 0, frames)?)?;
        for block in &self.blocks {
            let h = layer_norm(&x)?;
            x = (&x + block.attention.forward(&h, &h, Some(mask))?)?;
            let h = layer_norm(&x)?;
            x = (&x + block.feed_forward.forward(&h, 0.0, None)?)?;
        }
        let weights = mask.unsqueeze(D::Minus1)?;
        Ok(layer_norm(&x)?.broadcast_mul(&weights)?.sum(1)?.broadcast_div(&weights.sum(1)?)?)
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
