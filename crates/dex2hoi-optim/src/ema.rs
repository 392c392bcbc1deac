//! The exponential moving average of the weights, which sampling uses.

use candle_core::{DType, Tensor};
use rayon::prelude::*;

use crate::error::Result;
use crate::parameter::{Parameter, on_cpu};

/// The exponential moving average of the parameters (the weights used for sampling), `f32`
/// tensors of each parameter's shape on its device.
#[derive(Debug, Clone)]
pub struct Ema {
    values: Vec<Tensor>,
}

impl Ema {
    /// Starts at the parameters' current values.
    pub fn new(parameters: &[Parameter]) -> Result<Self> {
        let values = parameters
            .iter()
            .map(|p| p.var.as_tensor().detach().to_dtype(DType::F32)?.copy())
            .collect::<candle_core::Result<_>>()?;
        Ok(Self { values })
    }

    /// The average of parameter `k`.
    pub fn value(&self, k: usize) -> &Tensor {
        &self.values[k]
    }

    /// Replaces the average of parameter `k` (restoring a checkpoint), moved to the parameter's
    /// device as `f32`.
    pub fn set_value(&mut self, k: usize, parameter: &Parameter, value: &Tensor) -> Result<()> {
        // A copy: the fused update writes the average in place.
        self.values[k] = parameter.state_from(value)?.copy()?;
        Ok(())
    }

    /// `ema = d ema + (1 - d) theta` with `d = min(decay, (1 + step) / (10 + step))`. On the CPU
    /// a parallel host loop (each element as before, independent of the thread count); on
    /// other devices one tensor expression per parameter.
    pub fn update(&mut self, parameters: &[Parameter], decay: f64, step: usize) -> Result<()> {
        self.update_on(parameters, decay, step, on_cpu(parameters))
    }

    /// The weight `d` of the old average at `step`: `min(decay, (1 + step) / (10 + step))`.
    pub(crate) fn decay_at(decay: f64, step: usize) -> f32 {
        decay.min((1.0 + step as f64) / (10.0 + step as f64)) as f32
    }

    /// [`Ema::update`] with the path chosen: the host loop, or the tensor operations (any
    /// device; the tests compare the two on the CPU).
    #[doc(hidden)]
    pub fn update_on(
        &mut self,
        parameters: &[Parameter],
        decay: f64,
        step: usize,
        on_cpu: bool,
    ) -> Result<()> {
        let d = Self::decay_at(decay, step);
        if on_cpu {
            return self.values.par_iter_mut().zip(parameters).try_for_each(
                |(average, parameter)| {
                    let mut host: Vec<f32> = average.flatten_all()?.to_vec1()?;
                    for (a, v) in host.iter_mut().zip(parameter.values()?) {
                        *a = d * *a + (1.0 - d) * v;
                    }
                    *average = Tensor::from_vec(host, average.shape(), average.device())?;
                    Ok(())
                },
            );
        }
        for (average, parameter) in self.values.iter_mut().zip(parameters) {
            // Detached: an average that tracked the variable would keep every step's
            // intermediate tensors alive.
            let value = parameter.var.as_tensor().detach().to_dtype(DType::F32)?;
            *average =
                (average.affine(f64::from(d), 0.0)? + value.affine(f64::from(1.0 - d), 0.0)?)?;
        }
        Ok(())
    }
}
