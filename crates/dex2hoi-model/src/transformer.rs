//! The one pre-norm transformer block of every network of the workspace, and the masked mean
//! pool of the sequence encoders.
//!
//! [`TransformerBlock`] is configured like burn-nn's `TransformerEncoderLayer`: plain layer norm
//! (the Motion Fusion Network, the built-in text encoder, the evaluator's motion encoder) or
//! AdaLN conditioned on an embedding (the denoiser), with an optional cross-attention to a
//! second token sequence (the other stream of the dual layout, paper Eq. 5). Every operation
//! has a backward pass (see [`crate::layers`]).

use candle_core::{D, Tensor};
use candle_nn::VarBuilder;
use rand_chacha::ChaCha8Rng;

use crate::error::{ModelError, Result};
use crate::layers::{Attention, FeedForward, Modulation, dropout, layer_norm};

/// How a block normalises the input of each sub-layer.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Norm {
    /// Layer norm without affine parameters.
    Plain,
    /// AdaLN: layer norm scaled and shifted by a projection of a condition embedding
    /// ([`Modulation`]); the projection starts at zero, so every block starts as the identity.
    Adaptive,
}

/// Sizes and variant of a [`TransformerBlock`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BlockConfig {
    /// Token width.
    pub latent: usize,
    /// Attention heads (must divide `latent`).
    pub heads: usize,
    /// Hidden width of the feed-forward layer.
    pub feed_forward: usize,
    /// Dropout on every residual branch and inside the feed-forward layer (training only).
    pub dropout: f64,
    /// Plain or adaptive layer norm.
    pub norm: Norm,
    /// Whether a cross-attention to another sequence follows the self-attention.
    pub cross_attention: bool,
}

impl BlockConfig {
    /// A plain pre-norm block (self-attention and feed-forward, no condition).
    pub fn plain(latent: usize, heads: usize, feed_forward: usize, dropout: f64) -> Self {
        Self { latent, heads, feed_forward, dropout, norm: Norm::Plain, cross_attention: false }
    }
}

/// The normalisation before a sub-layer.
#[derive(Debug, Clone)]
pub(crate) enum PreNorm {
    Plain,
    Adaptive(Modulation),
}

impl PreNorm {
    /// A norm whose parameters (AdaLN only) lie under `vb`.
    fn new(cfg: &BlockConfig, vb: VarBuilder<'_>) -> Result<Self> {
        Ok(match cfg.norm {
            Norm::Plain => Self::Plain,
            Norm::Adaptive => Self::Adaptive(Modulation::new(cfg.latent, vb)?),
        })
    }

    /// # Shapes
    /// - `x`: `[batch, frames, latent]`; `condition`: `[batch, latent]` (AdaLN only); returns
    ///   `x`'s shape
    fn forward(&self, x: &Tensor, condition: Option<&Tensor>) -> Result<Tensor> {
        match self {
            Self::Plain => layer_norm(x),
            Self::Adaptive(modulation) => {
                let condition = condition.ok_or_else(|| {
                    ModelError::shape("condition", "[batch, latent] for an AdaLN block", &[])
                })?;
                modulation.forward(x, condition)
            }
        }
    }
}

/// The cross-attention sub-layer: queries from this sequence, keys and values from the other
/// one, each normalised under its own condition.
#[derive(Debug, Clone)]
pub(crate) struct CrossAttention {
    pub(crate) norm: PreNorm,
    pub(crate) other_norm: PreNorm,
    pub(crate) attention: Attention,
}

/// The other sequence a block cross-attends to.
#[derive(Debug, Clone, Copy)]
pub struct Other<'a> {
    /// Its tokens, `[batch, other_frames, latent]` (the dual layout: the other stream's
    /// previous-layer state).
    pub tokens: &'a Tensor,
    /// Its condition embedding, `[batch, latent]` (AdaLN only).
    pub condition: Option<&'a Tensor>,
}

/// A pre-norm transformer block: `x + SA(norm(x))`, then `x + CA(norm(x), norm(other))` when
/// configured, then `x + FF(norm(x))`, with dropout on each residual branch.
///
/// Parameter names: with AdaLN `self_modulation`, `self_attention`, `cross_modulation`,
/// `cross_other_modulation`, `cross_attention`, `ff_modulation`, `feed_forward`; with plain
/// layer norm `attention`, `feed_forward` (and `cross_attention`). The two names of the
/// self-attention predate this shared block and stay: checkpoints and the seeded
/// initialisation are keyed by name.
#[derive(Debug, Clone)]
pub struct TransformerBlock {
    pub(crate) self_norm: PreNorm,
    pub(crate) self_attention: Attention,
    pub(crate) cross: Option<CrossAttention>,
    pub(crate) ff_norm: PreNorm,
    pub(crate) feed_forward: FeedForward,
    dropout: f64,
}

impl TransformerBlock {
    /// A block with its parameters under `vb`.
    pub fn new(cfg: &BlockConfig, vb: VarBuilder<'_>) -> Result<Self> {
        let (l, heads) = (cfg.latent, cfg.heads);
        let self_attention = match cfg.norm {
            Norm::Plain => "attention",
            Norm::Adaptive => "self_attention",
        };
        let cross = if cfg.cross_attention {
            Some(CrossAttention {
                norm: PreNorm::new(cfg, vb.pp("cross_modulation"))?,
                other_norm: PreNorm::new(cfg, vb.pp("cross_other_modulation"))?,
                attention: Attention::new(l, heads, vb.pp("cross_attention"))?,
            })
        } else {
            None
        };
        Ok(Self {
            self_norm: PreNorm::new(cfg, vb.pp("self_modulation"))?,
            self_attention: Attention::new(l, heads, vb.pp(self_attention))?,
            cross,
            ff_norm: PreNorm::new(cfg, vb.pp("ff_modulation"))?,
            feed_forward: FeedForward::new(l, cfg.feed_forward, vb.pp("feed_forward"))?,
            dropout: cfg.dropout,
        })
    }

    /// `condition` is required with AdaLN and ignored otherwise; `other` is required exactly
    /// when the block has a cross-attention. `mask` (1 = attend, 0 = ignore) masks the keys of
    /// both attentions; `rng` switches dropout on.
    ///
    /// # Shapes
    /// - `x`: `[batch, frames, latent]`; `condition`: `[batch, latent]`
    /// - `other`: see [`Other`], with `other_frames = frames` when `mask` is given
    /// - `mask`: `[batch, frames]`
    /// - returns `[batch, frames, latent]`
    pub fn forward(
        &self,
        x: &Tensor,
        condition: Option<&Tensor>,
        other: Option<Other<'_>>,
        mask: Option<&Tensor>,
        mut rng: Option<&mut ChaCha8Rng>,
    ) -> Result<Tensor> {
        let h = self.self_norm.forward(x, condition)?;
        let attended = self.self_attention.forward(&h, &h, mask)?;
        let mut x = (x + dropout(&attended, self.dropout, rng.as_deref_mut())?)?;
        match (&self.cross, other) {
            (Some(cross), Some(other)) => {
                let queries = cross.norm.forward(&x, condition)?;
                let keys = cross.other_norm.forward(other.tokens, other.condition)?;
                let attended = cross.attention.forward(&queries, &keys, mask)?;
                x = (x + dropout(&attended, self.dropout, rng.as_deref_mut())?)?;
            }
            (None, None) => {}
            (Some(_), None) | (None, Some(_)) => {
                return Err(ModelError::shape(
                    "other",
                    "another sequence exactly when the block has a cross-attention",
                    &[],
                ));
            }
        }
        let h = self.ff_norm.forward(&x, condition)?;
        let out = self.feed_forward.forward(&h, self.dropout, rng.as_deref_mut())?;
        Ok((x + dropout(&out, self.dropout, rng)?)?)
    }
}

/// A stack of plain pre-norm blocks and the final layer norm a pre-norm stack needs (its
/// residual stream is never normalised otherwise): the Motion Fusion Network's trunk and the
/// sequence encoders'.
#[derive(Debug, Clone)]
pub struct TransformerEncoder {
    pub(crate) blocks: Vec<TransformerBlock>,
}

impl TransformerEncoder {
    /// `count` blocks named `0`, `1`, ... under `vb`.
    pub fn new(cfg: &BlockConfig, count: usize, vb: VarBuilder<'_>) -> Result<Self> {
        let blocks =
            (0..count).map(|i| TransformerBlock::new(cfg, vb.pp(i))).collect::<Result<_>>()?;
        Ok(Self { blocks })
    }

    /// Blocks in the stack.
    pub fn len(&self) -> usize {
        self.blocks.len()
    }

    /// Whether the stack has no block (it then only normalises).
    pub fn is_empty(&self) -> bool {
        self.blocks.is_empty()
    }

    /// The normalised tokens after every block; `mask` as in [`TransformerBlock::forward`].
    ///
    /// # Shapes
    /// - `x`: `[batch, frames, latent]`; `mask`: `[batch, frames]`; returns `x`'s shape
    pub fn forward(
        &self,
        x: &Tensor,
        mask: Option<&Tensor>,
        mut rng: Option<&mut ChaCha8Rng>,
    ) -> Result<Tensor> {
        let mut x = x.clone();
        for block in &self.blocks {
            x = block.forward(&x, None, None, mask, rng.as_deref_mut())?;
        }
        layer_norm(&x)
    }
}

/// The mean of each sequence's tokens where `mask` is 1 (padding tokens do not count).
///
/// # Shapes
/// - `x`: `[batch, tokens, features]`; `mask`: `[batch, tokens]`; returns `[batch, features]`
pub fn masked_mean(x: &Tensor, mask: &Tensor) -> Result<Tensor> {
    let weights = mask.unsqueeze(D::Minus1)?;
    Ok(x.broadcast_mul(&weights)?.sum(1)?.broadcast_div(&weights.sum(1)?)?)
}
