//! Motions and prompts as the evaluator sees them: contrastive embeddings (R-precision,
//! MMdist) and the features FID, Diversity and MultiModality use.

use crate::error::Result;
use crate::evaluator::{Evaluator, MotionClip};

/// Which features FID, Diversity and MultiModality use (paper Sec. 4.2).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum DistributionFeatures {
    /// The action classifier's hidden layer, for an evaluator with action labels (IMoS, as the
    /// paper does on GRAB).
    Action,
    /// The contrastive motion embeddings (T2M, as the paper does on HUMOTO).
    Contrastive,
}

impl DistributionFeatures {
    /// The features an evaluator offers: action features when it was trained with labels.
    pub(super) fn of(evaluator: &Evaluator) -> Self {
        if evaluator.labels().is_empty() { Self::Contrastive } else { Self::Action }
    }

    /// The report's description of the features.
    pub(super) fn describe(self) -> &'static str {
        match self {
            Self::Action => "action classifier features (IMoS)",
            Self::Contrastive => "contrastive motion embeddings",
        }
    }

    /// The distribution features of clips.
    ///
    /// # Shapes
    /// - returns `[clips][features]`
    pub(super) fn extract(
        self,
        evaluator: &Evaluator,
        clips: &[MotionClip],
    ) -> Result<Vec<Vec<f32>>> {
        match self {
            Self::Action => evaluator.action_features(clips),
            Self::Contrastive => evaluator.embed_motions(clips),
        }
    }
}

/// A set of motion clips embedded by the evaluator.
#[derive(Debug, Clone, PartialEq)]
pub(super) struct EmbeddedMotions {
    /// Unit-length contrastive embeddings, `[clips][embedding]`.
    pub contrastive: Vec<Vec<f32>>,
    /// Action features, `[clips][latent]`; empty when the distribution features are the
    /// contrastive embeddings.
    pub action: Vec<Vec<f32>>,
    features: DistributionFeatures,
}

impl EmbeddedMotions {
    /// Embeds clips (and takes their action features when those are the distribution
    /// features).
    pub(super) fn embed(
        evaluator: &Evaluator,
        features: DistributionFeatures,
        clips: &[MotionClip],
    ) -> Result<Self> {
        let contrastive = evaluator.embed_motions(clips)?;
        let action = match features {
            DistributionFeatures::Action => evaluator.action_features(clips)?,
            DistributionFeatures::Contrastive => Vec::new(),
        };
        Ok(Self { contrastive, action, features })
    }

    /// The rows FID, Diversity and MultiModality read.
    pub(super) fn distribution(&self) -> &[Vec<f32>] {
        match self.features {
            DistributionFeatures::Action => &self.action,
            DistributionFeatures::Contrastive => &self.contrastive,
        }
    }

    /// Number of clips.
    pub(super) fn len(&self) -> usize {
        self.contrastive.len()
    }
}

/// Unit-length text embeddings of a replication's prompts.
///
/// # Shapes
/// - returns `[prompts][embedding]`
pub(super) fn embed_prompts(evaluator: &Evaluator, prompts: &[String]) -> Result<Vec<Vec<f32>>> {
    let texts: Vec<&str> = prompts.iter().map(String::as_str).collect();
    evaluator.embed_texts(&texts)
}
