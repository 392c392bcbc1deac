//! The training loop (docs/CONVENTIONS.md, "Embedding metrics"): symmetric InfoNCE plus the action cross-entropy,
//! AdamW with warm-up and cosine decay, one seeded batch stream per step.

use std::path::Path;

use candle_core::{DType, Device, Tensor};
use serde::{Deserialize, Serialize};

use dex2hoi_data::dataset::Dataset;
use dex2hoi_optim::{AdamW, Parameter, learning_rate, parameters_of, step_rng};

use crate::error::{EvalError, Result};

use super::batching::usable_sequences;
use super::{Evaluator, EvaluatorConfig, TrainingBatch, loss};

/// Salt of the training batches' random streams.
const BATCH_SEED_SALT: u64 = 0x6576_616c_6261_7463;

/// What training did, saved with the evaluator.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TrainingSummary {
    /// Optimiser steps.
    pub steps: usize,
    /// Mean total loss over the first tenth of the steps (at least one).
    pub first_loss: f64,
    /// Mean total loss over the last tenth of the steps (at least one).
    pub final_loss: f64,
    /// Training sequences used.
    pub sequences: usize,
}

/// The terms of the training loss.
#[derive(Debug, Clone)]
pub struct EvaluatorLoss {
    /// `contrastive + classification_weight * classification`, a scalar.
    pub total: Tensor,
    /// The symmetric InfoNCE, a scalar.
    pub contrastive: Tensor,
    /// The action cross-entropy, a scalar (when the batch has labels).
    pub classification: Option<Tensor>,
}

impl Evaluator {
    /// Every trained parameter, sorted by name: `motion.*` then `text.*`.
    pub fn parameters(&self) -> Vec<Parameter> {
        let mut parameters = parameters_of(self.motion_vars.var_map(), "motion.");
        parameters.extend(parameters_of(self.text_vars.var_map(), "text."));
        parameters
    }

    /// The training loss of a batch.
    pub fn loss(&self, batch: &TrainingBatch) -> Result<EvaluatorLoss> {
        let pooled = self.motion.forward(&batch.features, &batch.mask)?;
        let motion = loss::l2_normalise(&self.motion.embed(&pooled)?)?;
        let text = loss::l2_normalise(&self.text.encode_ids(&batch.tokens)?)?;
        let contrastive =
            loss::contrastive_loss(&motion, &text, &batch.text_targets, self.config.temperature)?;
        let classification = match (self.motion.action_head(), &batch.actions) {
            (Some(head), Some(targets)) if targets.labelled > 0 => {
                let logits = head.forward(&head.features(&pooled)?)?;
                Some(loss::classification_loss(
                    &logits,
                    &targets.one_hot,
                    &targets.weights,
                    targets.labelled,
                )?)
            }
            _ => None,
        };
        let total = match &classification {
            Some(c) => (&contrastive + (c * self.config.classification_weight)?)?,
            None => contrastive.clone(),
        };
        Ok(EvaluatorLoss { total, contrastive, classification })
    }
}

/// Trains an evaluator on the training split of `dataset` (see the module documentation);
/// `progress` is called after every step with the steps done and the step's total loss.
pub fn train_evaluator(
    dataset: &Dataset,
    dataset_path: &Path,
    config: &EvaluatorConfig,
    device: &Device,
    progress: &mut dyn FnMut(usize, f64),
) -> Result<Evaluator> {
    let mut evaluator = Evaluator::initialise(dataset, dataset_path, config, DType::F32, device)?;
    let sequences = usable_sequences(dataset);
    let parameters = evaluator.parameters();
    let optimizer_config = config.optimizer();
    let mut optimizer = AdamW::new(optimizer_config.clone(), &parameters)?;
    let mut losses = Vec::with_capacity(config.steps);
    for step in 0..config.steps {
        let mut rng = step_rng(config.seed ^ BATCH_SEED_SALT, step);
        let batch = evaluator.draw_batch(&sequences, &mut rng)?;
        let loss = evaluator.loss(&batch)?;
        let value = loss.total.to_dtype(DType::F64)?.to_scalar::<f64>()?;
        if !value.is_finite() {
            return Err(EvalError::invalid(
                format!("evaluator loss at step {}", step + 1),
                "a finite number",
                value,
            ));
        }
        let gradients = loss.total.backward()?;
        optimizer.update(
            &parameters,
            &gradients,
            learning_rate(&optimizer_config, step, config.steps),
        )?;
        losses.push(value);
        progress(step + 1, value);
    }
    let tenth = (config.steps / 10).max(1);
    let mean = |values: &[f64]| values.iter().sum::<f64>() / values.len() as f64;
    evaluator.training = Some(TrainingSummary {
        steps: config.steps,
        first_loss: mean(&losses[..tenth]),
        final_loss: mean(&losses[losses.len() - tenth..]),
        sequences: sequences.len(),
    });
    Ok(evaluator)
}
