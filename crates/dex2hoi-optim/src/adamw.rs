//! AdamW with decoupled weight decay and global gradient-norm clipping.

use candle_core::backprop::GradStore;
use candle_core::{DType, Tensor};
use rayon::prelude::*;

use crate::config::OptimizerConfig;
use crate::ema::Ema;
use crate::error::Result;
use crate::fused::{self, FusedScalars};
use crate::parameter::{Parameter, on_cpu};

/// What one update did.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct UpdateReport {
    /// The learning rate used.
    pub learning_rate: f64,
    /// The global gradient norm before clipping.
    pub gradient_norm: f64,
}

/// AdamW state: first and second moments per parameter (`f32` tensors of the parameter's
/// shape, on its device) and the number of updates.
#[derive(Debug, Clone)]
pub struct AdamW {
    config: OptimizerConfig,
    first: Vec<Tensor>,
    second: Vec<Tensor>,
    /// Updates done.
    pub updates: usize,
}

/// The constants of one update, shared by every parameter.
#[derive(Debug, Clone, Copy)]
struct UpdateConstants {
    beta1: f32,
    beta2: f32,
    /// `lr / (1 - beta1^t)`.
    step_size: f32,
    /// `sqrt(1 - beta2^t)`.
    root_correction2: f32,
    epsilon: f32,
    /// The gradient's clipping factor.
    scale: f32,
}

impl AdamW {
    /// Zero moments for the parameters, on their devices.
    pub fn new(config: OptimizerConfig, parameters: &[Parameter]) -> Result<Self> {
        // Two allocations, not one shared: the fused update writes the moments in place.
        let zeros = || {
            parameters
                .iter()
                .map(|p| Tensor::zeros(p.var.shape(), DType::F32, p.var.device()))
                .collect::<candle_core::Result<Vec<_>>>()
        };
        Ok(Self { config, first: zeros()?, second: zeros()?, updates: 0 })
    }

    /// The first and second moments of parameter `k` (`f32`, the parameter's shape and device).
    pub fn moments(&self, k: usize) -> (&Tensor, &Tensor) {
        (&self.first[k], &self.second[k])
    }

    /// Replaces the moments of parameter `k` (restoring a checkpoint); they are moved to the
    /// parameter's device as `f32`.
    pub fn set_moments(
        &mut self,
        k: usize,
        parameter: &Parameter,
        first: &Tensor,
        second: &Tensor,
    ) -> Result<()> {
        self.first[k] = parameter.state_from(first)?.copy()?;
        self.second[k] = parameter.state_from(second)?.copy()?;
        Ok(())
    }

    /// One update of the parameters and then of their moving average `average`, as
    /// [`AdamW::update`] and [`Ema::update`] (with `ema_decay` at `step`) would do them; the
    /// average is left as it was when the gradient norm is not finite.
    ///
    /// On a GPU with [`OptimizerConfig::fused`] (the default) both run as one CUDA kernel per
    /// parameter tensor, the clipping factor computed on the device; a non-finite norm then
    /// leaves the parameters and moments as they were too.
    pub fn update_with_average(
        &mut self,
        average: &mut Ema,
        parameters: &[Parameter],
        gradients: &GradStore,
        learning_rate: f64,
        (ema_decay, step): (f64, usize),
    ) -> Result<UpdateReport> {
        if self.config.fused && fused::available(parameters) {
            return self.update_fused(
                average,
                parameters,
                gradients,
                learning_rate,
                (ema_decay, step),
            );
        }
        let report = self.update(parameters, gradients, learning_rate)?;
        if report.gradient_norm.is_finite() {
            average.update(parameters, ema_decay, step)?;
        }
        Ok(report)
    }

    /// The fused path of [`AdamW::update_with_average`]: the squared gradient norm summed on
    /// the device, one kernel per parameter, and one read of the norm after all are queued.
    fn update_fused(
        &mut self,
        average: &mut Ema,
        parameters: &[Parameter],
        gradients: &GradStore,
        learning_rate: f64,
        (ema_decay, step): (f64, usize),
    ) -> Result<UpdateReport> {
        let gradients: Vec<Tensor> = parameters
            .iter()
            .map(|p| match gradients.get(p.var.as_tensor()) {
                Some(g) => g.detach().to_dtype(DType::F32)?.contiguous(),
                None => Tensor::zeros(p.var.shape(), DType::F32, p.var.device()),
            })
            .collect::<candle_core::Result<_>>()?;
        let squares: Vec<Tensor> =
            gradients.iter().map(|g| g.sqr()?.sum_all()).collect::<candle_core::Result<_>>()?;
        let squared_norm = Tensor::stack(&squares, 0)?.sum_all()?;
        let u = self.advance(learning_rate, 1.0);
        let scalars = FusedScalars {
            clip: self.config.gradient_clip.unwrap_or(f64::INFINITY),
            beta1: u.beta1,
            beta2: u.beta2,
            step_size: u.step_size,
            inverse_root_correction2: (1.0 / f64::from(u.root_correction2)) as f32,
            epsilon: u.epsilon,
            ema_decay: Ema::decay_at(ema_decay, step),
        };
        let weight_decay = (learning_rate * self.config.weight_decay) as f32;
        let kernel = fused::Kernel::load(&squared_norm)?;
        for (k, (parameter, gradient)) in parameters.iter().zip(&gradients).enumerate() {
            let keep = if parameter.decays() { 1.0 - weight_decay } else { 1.0 };
            let arrays = [
                parameter.var.as_tensor(),
                &self.first[k],
                &self.second[k],
                average.value(k),
                gradient,
            ];
            kernel.launch(arrays, &squared_norm, scalars, keep)?;
        }
        let squared: f32 = squared_norm.to_scalar()?;
        Ok(UpdateReport { learning_rate, gradient_norm: f64::from(squared).sqrt() })
    }

    /// One update from the gradients of a backward pass; a parameter without a gradient (not
    /// used by the loss) gets a zero gradient and still decays.
    ///
    /// On the CPU the update is a parallel loop over host copies (one pass per parameter, each
    /// element in a fixed order, so it does not depend on the thread count); on other devices
    /// it is a few elementwise tensor operations per parameter on the device, and the only
    /// transfer to the host is the gradient norm.
    pub fn update(
        &mut self,
        parameters: &[Parameter],
        gradients: &GradStore,
        learning_rate: f64,
    ) -> Result<UpdateReport> {
        self.update_on(parameters, gradients, learning_rate, on_cpu(parameters))
    }

    /// [`AdamW::update`] with the path chosen: the host loop, or the tensor operations (which
    /// run on any device, the CPU included: the tests compare the two there).
    #[doc(hidden)]
    pub fn update_on(
        &mut self,
        parameters: &[Parameter],
        gradients: &GradStore,
        learning_rate: f64,
        on_cpu: bool,
    ) -> Result<UpdateReport> {
        let grads: Vec<Option<&Tensor>> =
            parameters.iter().map(|p| gradients.get(p.var.as_tensor())).collect();
        // On the host path the gradients are copied to the host once, for the norm and the loop.
        let (host_grads, gradient_norm) = if on_cpu {
            let host: Vec<Option<Vec<f32>>> = grads
                .iter()
                .map(|g| {
                    g.map(|g| Ok(g.flatten_all()?.to_dtype(DType::F32)?.to_vec1()?)).transpose()
                })
                .collect::<Result<_>>()?;
            let squared: f64 = host
                .iter()
                .flatten()
                .map(|g| g.iter().map(|&v| f64::from(v) * f64::from(v)).sum::<f64>())
                .sum();
            (host, squared.sqrt())
        } else {
            (Vec::new(), device_norm(&grads)?)
        };
        let scale = match self.config.gradient_clip {
            Some(clip) if gradient_norm > clip => (clip / (gradient_norm + 1e-6)) as f32,
            _ => 1.0,
        };
        let constants = self.advance(learning_rate, scale);
        let c = &self.config;
        let weight_decay = (learning_rate * c.weight_decay) as f32;
        let decay_of = move |p: &Parameter| if p.decays() { weight_decay } else { 0.0 };
        if on_cpu {
            self.update_on_host(parameters, &host_grads, constants, &decay_of)?;
        } else {
            for (k, parameter) in parameters.iter().enumerate() {
                let (first, second, value) = update_on_device(
                    parameter,
                    &self.first[k],
                    &self.second[k],
                    grads[k],
                    constants,
                    decay_of(parameter),
                )?;
                self.first[k] = first;
                self.second[k] = second;
                parameter.var.set(&value)?;
            }
        }
        Ok(UpdateReport { learning_rate, gradient_norm })
    }

    /// Counts one more update and returns its constants; `scale` is the gradient's clipping
    /// factor.
    fn advance(&mut self, learning_rate: f64, scale: f32) -> UpdateConstants {
        self.updates += 1;
        let c = &self.config;
        let correction1 = 1.0 - c.beta1.powi(self.updates as i32);
        let correction2 = 1.0 - c.beta2.powi(self.updates as i32);
        UpdateConstants {
            beta1: c.beta1 as f32,
            beta2: c.beta2 as f32,
            step_size: (learning_rate / correction1) as f32,
            root_correction2: correction2.sqrt() as f32,
            epsilon: c.epsilon as f32,
            scale,
        }
    }

    fn update_on_host(
        &mut self,
        parameters: &[Parameter],
        grads: &[Option<Vec<f32>>],
        u: UpdateConstants,
        decay_of: &(dyn Fn(&Parameter) -> f32 + Sync),
    ) -> Result<()> {
        // Parameters update in parallel (each element as before, so the result does not
        // depend on the thread count); the variables are set afterwards, in order.
        let updated: Vec<[Vec<f32>; 3]> = parameters
            .par_iter()
            .zip(self.first.par_iter())
            .zip(self.second.par_iter())
            .zip(grads.par_iter())
            .map(|(((parameter, first), second), gradient)| -> Result<[Vec<f32>; 3]> {
                let mut values = parameter.values()?;
                let mut first: Vec<f32> = first.flatten_all()?.to_vec1()?;
                let mut second: Vec<f32> = second.flatten_all()?.to_vec1()?;
                let decay = decay_of(parameter);
                let gradient = gradient.as_deref();
                for n in 0..values.len() {
                    let g = gradient.map_or(0.0, |g| g[n] * u.scale);
                    first[n] = u.beta1 * first[n] + (1.0 - u.beta1) * g;
                    second[n] = u.beta2 * second[n] + (1.0 - u.beta2) * g * g;
                    let denominator = second[n].sqrt() / u.root_correction2 + u.epsilon;
                    values[n] = values[n] * (1.0 - decay) - u.step_size * first[n] / denominator;
                }
                Ok([values, first, second])
            })
            .collect::<Result<_>>()?;
        for (k, (parameter, [values, first, second])) in parameters.iter().zip(updated).enumerate()
        {
            let (shape, device) = (parameter.var.shape().clone(), parameter.var.device());
            self.first[k] = Tensor::from_vec(first, shape.clone(), device)?;
            self.second[k] = Tensor::from_vec(second, shape.clone(), device)?;
            let tensor =
                Tensor::from_vec(values, shape, device)?.to_dtype(parameter.var.dtype())?;
            parameter.var.set(&tensor)?;
        }
        Ok(())
    }
}

/// The global gradient norm computed on the device (one scalar comes back to the host).
fn device_norm(grads: &[Option<&Tensor>]) -> Result<f64> {
    let squares: Vec<Tensor> = grads
        .iter()
        .flatten()
        .map(|g| g.to_dtype(DType::F32)?.sqr()?.sum_all())
        .collect::<candle_core::Result<_>>()?;
    if squares.is_empty() {
        return Ok(0.0);
    }
    let total: f32 = Tensor::stack(&squares, 0)?.sum_all()?.to_scalar()?;
    Ok(f64::from(total).sqrt())
}

/// One parameter's AdamW update as tensor operations on its device: the new first and second
/// moments and the new value (in the parameter's dtype). Same formula as the host loop.
///
/// Every input is detached first: the parameter is a variable and the gradient may come out of
/// the backward graph, and a result that tracked them would keep that step's whole graph
/// alive in the moments, one more step's worth at every update (seen: a GPU out of memory
/// after 74 steps).
fn update_on_device(
    parameter: &Parameter,
    first: &Tensor,
    second: &Tensor,
    gradient: Option<&Tensor>,
    u: UpdateConstants,
    decay: f32,
) -> Result<(Tensor, Tensor, Tensor)> {
    let gradient = match gradient {
        Some(g) => g.detach().to_dtype(DType::F32)?.affine(f64::from(u.scale), 0.0)?,
        None => first.zeros_like()?,
    };
    let (first, second) = (first.detach(), second.detach());
    let first = (first.affine(f64::from(u.beta1), 0.0)?
        + gradient.affine(f64::from(1.0 - u.beta1), 0.0)?)?;
    let second = (second.affine(f64::from(u.beta2), 0.0)?
        + gradient.sqr()?.affine(f64::from(1.0 - u.beta2), 0.0)?)?;
    let denominator =
        second.sqrt()?.affine(1.0 / f64::from(u.root_correction2), f64::from(u.epsilon))?;
    let value = parameter.var.as_tensor().detach().to_dtype(DType::F32)?;
    let value = (value.affine(f64::from(1.0 - decay), 0.0)?
        - (first.affine(f64::from(u.step_size), 0.0)? / denominator)?)?;
    Ok((first, second, value.to_dtype(parameter.var.dtype())?))
}
