//! Training batches: clips as normalised, masked feature tensors, texts as tokens (with word
//! dropout), and the contrastive and action targets; and the random draw of a step's batch.

use candle_core::Tensor;
use rand::Rng;
use rand_chacha::ChaCha8Rng;

use dex2hoi_data::dataset::{Dataset, Split};
use dex2hoi_data::features::ProcessedSequence;
use dex2hoi_model::text::{UNKNOWN, words};

use crate::error::{EvalError, Result};

use super::{Evaluator, MotionClip};

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

/// The texts of a sequence that have at least one word.
fn usable_texts(sequence: &ProcessedSequence) -> Vec<&str> {
    sequence.texts.iter().map(String::as_str).filter(|t| !words(t).is_empty()).collect()
}

/// The training sequences with at least one text that has a word.
pub(super) fn usable_sequences(dataset: &Dataset) -> Vec<&ProcessedSequence> {
    dataset
        .splits
        .get(&Split::Train)
        .map(|s| s.iter().filter(|q| !usable_texts(q).is_empty()).collect())
        .unwrap_or_default()
}

impl Evaluator {
    /// Normalised features and mask of clips, padded to the longest (at most `clip_frames`).
    ///
    /// # Shapes
    /// - returns `[clips, frames, 3J + 20]` and `[clips, frames]`
    pub(super) fn clip_tensors(&self, clips: &[MotionClip]) -> Result<(Tensor, Tensor)> {
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

    pub(super) fn tokenize(&self, texts: &[&str]) -> Result<Vec<Vec<u32>>> {
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
}
