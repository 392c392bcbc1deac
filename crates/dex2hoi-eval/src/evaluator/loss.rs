//! The evaluator's training losses, composed of operations with a backward pass.

use candle_core::{D, Tensor};

use crate::error::Result;

/// `log(softmax(x))` over the last dimension, shifted by the (constant) row maximum.
///
/// # Shapes
/// - `x`: `[..., classes]`; returns the same shape
pub fn log_softmax(x: &Tensor) -> Result<Tensor> {
    let shifted = x.broadcast_sub(&x.max_keepdim(D::Minus1)?.detach())?;
    let normaliser = shifted.exp()?.sum_keepdim(D::Minus1)?.log()?;
    Ok(shifted.broadcast_sub(&normaliser)?)
}

/// Rows scaled to unit length (`x / sqrt(|x|^2 + 1e-12)`).
///
/// # Shapes
/// - `x`: `[rows, width]`; returns the same shape
pub fn l2_normalise(x: &Tensor) -> Result<Tensor> {
    let norm = (x.sqr()?.sum_keepdim(D::Minus1)? + 1e-12)?.sqrt()?;
    Ok(x.broadcast_div(&norm)?)
}

/// Symmetric InfoNCE between unit-length motion and text embeddings: cross-entropy of the
/// cosine similarities divided by `temperature`, motion to text and text to motion, averaged.
/// `targets[i][j]` is the share of row `i`'s probability that belongs to `j` (the identity, or
/// spread over the pairs that share a text).
///
/// # Shapes
/// - `motion`, `text`: `[batch, embedding]`, rows of unit length
/// - `targets`: `[batch, batch]`, rows summing to 1 and symmetric
/// - returns a scalar
pub fn contrastive_loss(
    motion: &Tensor,
    text: &Tensor,
    targets: &Tensor,
    temperature: f64,
) -> Result<Tensor> {
    let batch = motion.dims2()?.0 as f64;
    let logits = (motion.matmul(&text.t()?.contiguous()?)? / temperature)?;
    let motion_to_text = (log_softmax(&logits)? * targets)?.sum_all()?;
    let text_to_motion = (log_softmax(&logits.t()?.contiguous()?)? * targets)?.sum_all()?;
    Ok(((motion_to_text + text_to_motion)? * (-0.5 / batch))?)
}

/// Cross-entropy of label logits, averaged over the rows with weight 1.
///
/// # Shapes
/// - `logits`, `one_hot`: `[batch, labels]`; `weights`: `[batch]` (1 for a labelled row, 0
///   otherwise); `labelled` is the sum of `weights` (at least 1); returns a scalar
pub fn classification_loss(
    logits: &Tensor,
    one_hot: &Tensor,
    weights: &Tensor,
    labelled: usize,
) -> Result<Tensor> {
    let per_row = (log_softmax(logits)? * one_hot)?.sum(D::Minus1)?;
    Ok(((per_row * weights)?.sum_all()? * (-1.0 / labelled.max(1) as f64))?)
}
