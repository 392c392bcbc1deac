//! The distribution and text-matching metrics of one replication (paper Sec. 4.2): the
//! columns of the report before the physical ones, for the generated motions and for the
//! ground truth measured the same way.

use crate::error::Result;
use crate::metrics;

use super::embedding::EmbeddedMotions;

/// One row's distribution and matching metrics in one replication.
#[derive(Debug, Clone, PartialEq)]
pub(super) struct DistributionScores {
    /// R-precision top-1, top-2, top-3 (texts ranking motions, T2M).
    pub r_precision: [f64; 3],
    /// Each clip's rank behind `r_precision` (`metrics::retrieval_ranks`; `None` in the dropped
    /// remainder), `[clips]`: the per-group R-precision of the instruction rows.
    pub ranks: Vec<Option<usize>>,
    /// FID against the ground truth's distribution features (0 for the ground truth itself,
    /// by definition).
    pub fid: f64,
    /// MMdist: mean distance between matched motion and text embeddings.
    pub mm_dist: f64,
    /// Diversity over `min(300, clips)` pairs.
    pub diversity: f64,
    /// MultiModality; `None` for the ground truth and where the protocol measures nothing.
    pub multimodality: Option<f64>,
}

impl DistributionScores {
    /// The scores of generated motions: those of [`Self::against_texts`], FID against the
    /// ground truth, and the MultiModality measured on the replication's repeated generations.
    ///
    /// # Shapes
    /// - `generated`, `truth`, `texts`: the same `[clips]`, row `i` for test sequence `i`
    pub(super) fn of_generated(
        generated: &EmbeddedMotions,
        truth: &EmbeddedMotions,
        texts: &[Vec<f32>],
        multimodality: Option<f64>,
        seed: u64,
    ) -> Result<Self> {
        Ok(Self {
            fid: metrics::fid(generated.distribution(), truth.distribution())?,
            multimodality,
            ..Self::against_texts(generated, texts, seed)?
        })
    }

    /// The scores of the ground truth: FID 0 (the same clips) and no MultiModality.
    ///
    /// # Shapes
    /// - `truth`, `texts`: the same `[clips]`
    pub(super) fn of_ground_truth(
        truth: &EmbeddedMotions,
        texts: &[Vec<f32>],
        seed: u64,
    ) -> Result<Self> {
        Self::against_texts(truth, texts, seed)
    }

    /// R-precision top-3 of the clips `member` picks by index (their texts ranking the motions
    /// of their batches, which mix the groups); `None` when none of them was ranked.
    pub(super) fn top3_of(&self, member: impl Fn(usize) -> bool) -> Option<f64> {
        let ranks = self.ranks.iter().enumerate().filter(|(i, _)| member(*i));
        metrics::top_k_shares(ranks.filter_map(|(_, rank)| *rank)).map(|shares| shares[2])
    }

    /// R-precision (batches of up to 32), MMdist and Diversity (up to 300 pairs) of motions
    /// against the prompts' text embeddings; FID 0 and no MultiModality.
    fn against_texts(motions: &EmbeddedMotions, texts: &[Vec<f32>], seed: u64) -> Result<Self> {
        let clips = motions.len();
        let ranks = metrics::retrieval_ranks(
            &motions.contrastive,
            texts,
            metrics::R_PRECISION_BATCH.min(clips),
            seed,
            metrics::Retrieval::TextToMotion,
        )?;
        Ok(Self {
            r_precision: metrics::r_precision_of_ranks(&ranks)?,
            ranks,
            fid: 0.0,
            mm_dist: metrics::matching_distance(&motions.contrastive, texts)?,
            diversity: metrics::diversity(
                motions.distribution(),
                metrics::DIVERSITY_PAIRS.min(clips),
                seed,
            )?,
            multimodality: None,
        })
    }
}
