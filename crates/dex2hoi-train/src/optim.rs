//! AdamW (decoupled weight decay) with linear warm-up and cosine decay, global gradient-norm
//! clipping, and an exponential moving average of the weights for sampling. The state is plain
//! `f32` vectors per parameter so that a checkpoint holds it exactly and a resumed run continues
//! bit for bit.

use candle_core::backprop::GradStore;
use candle_core::{DType, Tensor, Var};

use crate::config::OptimizerConfig;
use crate::error::Result;

/// A trained parameter with its checkpoint name (`model.blocks.0...`, `text_encoder....`).
#[derive(Debug, Clone)]
pub struct Parameter {
    /// The checkpoint name.
    pub name: String,
    /// The variable.
    pub var: Var,
}

impl Parameter {
    /// Matrices (rank >= 2) decay; biases and vectors do not.
    fn decays(&self) -> bool {
        self.var.rank() >= 2
    }

    fn values(&self) -> Result<Vec<f32>> {
        Ok(self.var.as_tensor().flatten_all()?.to_dtype(DType::F32)?.to_vec1()?)
    }
}

/// The variables of a var map as parameters named `prefix + name`, sorted by name (the order
/// of optimiser state and checkpoints).
pub fn parameters_of(vars: &dex2hoi_model::SeededVarMap, prefix: &str) -> Vec<Parameter> {
    let data = vars.var_map().data().lock().expect("the var map lock is not poisoned");
    let mut out: Vec<Parameter> = data
        .iter()
        .map(|(name, var)| Parameter { name: format!("{prefix}{name}"), var: var.clone() })
        .collect();
    out.sort_by(|a, b| a.name.cmp(&b.name));
    out
}

/// The learning rate at a step (0-based): linear warm-up to the peak, then cosine decay to
/// `final_learning_rate_ratio` of the peak at the last step.
pub fn learning_rate(config: &OptimizerConfig, step: usize, total_steps: usize) -> f64 {
    let warm = if config.warmup_steps == 0 {
        1.0
    } else {
        ((step + 1) as f64 / config.warmup_steps as f64).min(1.0)
    };
    let decay_steps = total_steps.saturating_sub(config.warmup_steps).max(1);
    let progress = (step.saturating_sub(config.warmup_steps) as f64 / decay_steps as f64).min(1.0);
    let ratio = config.final_learning_rate_ratio;
    let cosine = ratio + (1.0 - ratio) * 0.5 * (1.0 + (std::f64::consts::PI * progress).cos());
    config.learning_rate * warm * cosine
}

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
        for (k, parameter) in parameters.iter().enumerate() {
            let mut values = parameter.values()?;
            let decay =
                if parameter.decays() { (learning_rate * c.weight_decay) as f32 } else { 0.0 };
            let (first, second) = (&mut self.first[k], &mut self.second[k]);
            let gradient = grads[k].as_deref();
            for n in 0..values.len() {
                let g = gradient.map_or(0.0, |g| g[n] * scale);
                first[n] = beta1 * first[n] + (1.0 - beta1) * g;
                second[n] = beta2 * second[n] + (1.0 - beta2) * g * g;
                let denominator = second[n].sqrt() / root_correction2 + epsilon;
                values[n] = values[n] * (1.0 - decay) - step_size * first[n] / denominator;
            }
            let shape = parameter.var.shape().clone();
            let tensor = Tensor::from_vec(values, shape, parameter.var.device())?
                .to_dtype(parameter.var.dtype())?;
            parameter.var.set(&tensor)?;
        }
        Ok(UpdateReport { learning_rate, gradient_norm })
    }
}

/// The exponential moving average of the parameters (the weights used for sampling).
#[derive(Debug, Clone)]
pub struct Ema {
    /// Averaged values per parameter.
    pub values: Vec<Vec<f32>>,
}

impl Ema {
    /// Starts at the parameters' current values.
    pub fn new(parameters: &[Parameter]) -> Result<Self> {
        Ok(Self { values: parameters.iter().map(Parameter::values).collect::<Result<_>>()? })
    }

    /// `ema = d ema + (1 - d) theta` with `d = min(decay, (1 + step) / (10 + step))`.
    pub fn update(&mut self, parameters: &[Parameter], decay: f64, step: usize) -> Result<()> {
        let d = decay.min((1.0 + step as f64) / (10.0 + step as f64)) as f32;
        for (average, parameter) in self.values.iter_mut().zip(parameters) {
            let values = parameter.values()?;
            for (a, v) in average.iter_mut().zip(values) {
                *a = d * *a + (1.0 - d) * v;
            }
        }
        Ok(())
    }
}
