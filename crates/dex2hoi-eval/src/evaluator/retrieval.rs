//! Held-out checks of an evaluator: top-1 text retrieval and action accuracy on evaluation
//! windows of a split.

use dex2hoi_data::features::ProcessedSequence;

use crate::error::{EvalError, Result};

use super::{Evaluator, MotionClip};

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

impl Evaluator {
    /// The first `clip_frames` frames of each sequence (the whole sequence when shorter): the
    /// windows of the held-out retrieval and accuracy. Takes a slice of sequences or any
    /// iterator of references to them (such as a filtered split).
    ///
    /// # Shapes
    /// - returns `[sequences]` clips of `min(frames, clip_frames)` frames each
    pub fn evaluation_windows<'a>(
        &self,
        sequences: impl IntoIterator<Item = &'a ProcessedSequence>,
    ) -> Result<Vec<MotionClip>> {
        sequences
            .into_iter()
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
}
