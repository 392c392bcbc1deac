//! The exponential moving average of the weights, which sampling uses.

use crate::error::Result;
use crate::parameter::Parameter;
use rayon::prelude::*;

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
        // Parameters in parallel, each element as before (independent of the thread count).
        self.values.par_iter_mut().zip(parameters).try_for_each(|(average, parameter)| {
            let values = parameter.values()?;
            for (a, v) in average.iter_mut().zip(values) {
                *a = d * *a + (1.0 - d) * v;
            }
            Ok(())
        })
    }
}
