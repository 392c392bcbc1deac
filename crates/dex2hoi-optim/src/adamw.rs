//! AdamW with decoupled weight decay and global gradient-norm clipping.

use candle_core::backprop::GradStore;
use candle_core::{DType, Tensor};
use rayon::prelude::*;

use crate::config::OptimizerConfig;
use crate::error::Result;
use crate::parameter::Parameter;

/// What one update did.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct UpdateReport {
    /// The learning rate used.
    pub learning_rate: f64,
    /// The global gradient norm before clipping.
    pub gradient_norm: f64,
}

/// AdamW state: first and second moments per parameter and the number of updates.
#[derive(Debug, Clone)]
pub struct AdamW {
    config: OptimizerConfig,
    /// First moments per parameter.
    pub first: Vec<Vec<f32>>,
    /// Second moments per parameter.
    pub second: Vec<Vec<f32>>,
    /// Updates done.
    pub updates: usize,
}

impl AdamW {
    /// Zero moments for the parameters.
    pub fn new(config: OptimizerConfig, parameters: &[Parameter]) -> Self {
        let zeros: Vec<Vec<f32>> =
            parameters.iter().map(|p| vec![0.0; p.var.elem_count()]).collect();
        Self { config, first: zeros.clone(), second: zeros, updates: 0 }
    }

    /// One update from the gradients of a backward pass; a parameter without a gradient (not
    /// used by the loss) gets a zero gradient and still decays.
    pub fn update(
        &mut self,
        parameters: &[Parameter],
        gradients: &GradStore,
        learning_rate: f64,
    ) -> Result<UpdateReport> {
        let grads: Vec<Option<Vec<f32>>> = parameters
            .iter()
            .map(|p| {
                gradients
                    .get(p.var.as_tensor())
                    .map(|g| -> Result<Vec<f32>> {
                        Ok(g.flatten_all()?.to_dtype(DType::F32)?.to_vec1()?)
                    })
                    .transpose()
            })
            .collect::<Result<_>>()?;
        let squared: f64 = grads
            .iter()
            .flatten()
            .map(|g| g.iter().map(|&v| f64::from(v) * f64::from(v)).sum::<f64>())
            .sum();
        let gradient_norm = squared.sqrt();
        let scale = match self.config.gradient_clip {
            Some(clip) if gradient_norm > clip => (clip / (gradient_norm + 1e-6)) as f32,
            _ => 1.0,
        };
        self.updates += 1;
        let c = &self.config;
        let (beta1, beta2) = (c.beta1 as f32, c.beta2 as f32);
        let correction1 = 1.0 - c.beta1.powi(self.updates as i32);
        let correction2 = 1.0 - c.beta2.powi(self.updates as i32);
        let step_size = (learning_rate / correction1) as f32;
        let root_correction2 = correction2.sqrt() as f32;
        let epsilon = c.epsilon as f32;
        // Parameters update in parallel (each element as before, so the result does not
        // depend on the thread count); the variables are set afterwards, in order.
        let updated: Vec<Vec<f32>> = parameters
            .par_iter()
            .zip(self.first.par_iter_mut())
            .zip(self.second.par_iter_mut())
            .zip(grads.par_iter())
            .map(|(((parameter, first), second), gradient)| -> Result<Vec<f32>> {
                let mut values = parameter.values()?;
                let decay =
                    if parameter.decays() { (learning_rate * c.weight_decay) as f32 } else { 0.0 };
                let gradient = gradient.as_deref();
                for n in 0..values.len() {
                    let g = gradient.map_or(0.0, |g| g[n] * scale);
                    first[n] = beta1 * first[n] + (1.0 - beta1) * g;
                    second[n] = beta2 * second[n] + (1.0 - beta2) * g * g;
                    let denominator = second[n].sqrt() / root_correction2 + epsilon;
                    values[n] = values[n] * (1.0 - decay) - step_size * first[n] / denominator;
                }
                Ok(values)
            })
            .collect::<Result<_>>()?;
        for (parameter, values) in parameters.iter().zip(updated) {
            let shape = parameter.var.shape().clone();
            let tensor = Tensor::from_vec(values, shape, parameter.var.device())?
                .to_dtype(parameter.var.dtype())?;
            parameter.var.set(&tensor)?;
        }
        Ok(UpdateReport { learning_rate, gradient_norm })
    }
}
