//! Embedding with a trained evaluator: unit-length motion and text embeddings, action features
//! and action labels, in chunks.

use candle_core::{DType, Tensor};

use crate::error::{EvalError, Result};

use super::{ActionHead, Evaluator, MotionClip, loss};

/// Clips embedded per forward pass outside training.
const EMBED_CHUNK: usize = 64;

impl Evaluator {
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
}
