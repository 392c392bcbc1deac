//! Trained parameters by checkpoint name.

use candle_core::{DType, Tensor, Var};

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
    pub(crate) fn decays(&self) -> bool {
        self.var.rank() >= 2
    }

    pub(crate) fn values(&self) -> Result<Vec<f32>> {
        Ok(self.var.as_tensor().flatten_all()?.to_dtype(DType::F32)?.to_vec1()?)
    }

    /// Optimiser state for this parameter from a tensor of its size (a checkpoint's): `f32`, the
    /// parameter's shape, on its device.
    pub(crate) fn state_from(&self, tensor: &Tensor) -> Result<Tensor> {
        Ok(tensor.to_dtype(DType::F32)?.reshape(self.var.shape())?.to_device(self.var.device())?)
    }
}

/// Whether the parameters live on the CPU, where the optimiser updates them with host loops
/// rather than tensor operations (an empty list counts as the CPU).
pub(crate) fn on_cpu(parameters: &[Parameter]) -> bool {
    parameters.first().is_none_or(|p| p.var.device().is_cpu())
}

/// The variables of a var map as parameters named `prefix + name`, sorted by name (the order
/// of optimiser state and checkpoints).
pub fn parameters_of(vars: &candle_nn::VarMap, prefix: &str) -> Vec<Parameter> {
    let data = vars.data().lock().expect("the var map lock is not poisoned");
    let mut out: Vec<Parameter> = data
        .iter()
        .map(|(name, var)| Parameter { name: format!("{prefix}{name}"), var: var.clone() })
        .collect();
    out.sort_by(|a, b| a.name.cmp(&b.name));
    out
}
