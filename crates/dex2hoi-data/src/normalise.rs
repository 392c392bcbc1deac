//! Per-channel normalisation of features: `(x - mean) / std` on the way into a network,
//! `x * std + mean` on the way out. The one implementation of it, for the model's stream
//! features (the dataset's [`FeatureStats`]) and for any other per-channel statistics (the
//! evaluator's clip features), on host rows or on tensors; every caller gets the same bits.

use candle_core::{DType, Device, Tensor};

use crate::dataset::FeatureStats;
use crate::error::Result;

/// Normalises the leading channels of `row` in place, `(x - mean) / std`, as many as `mean`
/// and `std` hold (`row` may be longer: channels past them are left as they are).
pub fn normalise_row(row: &mut [f32], mean: &[f32], std: &[f32]) {
    for ((value, mean), std) in row.iter_mut().zip(mean).zip(std) {
        *value = (*value - mean) / std;
    }
}

/// Per-channel statistics as tensors, for normalising and denormalising features over their
/// last dimension.
#[derive(Debug, Clone)]
pub struct Normaliser {
    /// `[D]` means.
    pub mean: Tensor,
    /// `[D]` standard deviations.
    pub std: Tensor,
}

impl Normaliser {
    /// The statistics `mean` and `std` (`[D]` each) as `dtype` tensors on `device`.
    pub fn new(mean: &[f32], std: &[f32], dtype: DType, device: &Device) -> Result<Self> {
        let tensor = |values: &[f32]| -> Result<Tensor> {
            Ok(Tensor::from_slice(values, values.len(), device)?.to_dtype(dtype)?)
        };
        Ok(Self { mean: tensor(mean)?, std: tensor(std)? })
    }

    /// `(x - mean) / std` over the last dimension.
    ///
    /// # Shapes
    /// - `x`: `[..., D]`; returns the same shape
    pub fn normalise(&self, x: &Tensor) -> Result<Tensor> {
        Ok(x.broadcast_sub(&self.mean)?.broadcast_div(&self.std)?)
    }

    /// `x * std + mean` over the last dimension.
    ///
    /// # Shapes
    /// - `x`: `[..., D]`; returns the same shape
    pub fn denormalise(&self, x: &Tensor) -> Result<Tensor> {
        Ok(x.broadcast_mul(&self.std)?.broadcast_add(&self.mean)?)
    }
}

impl FeatureStats {
    /// Normalises one stream row of features in place (see [`normalise_row`]).
    ///
    /// # Shapes
    /// - `row`: `[D]`, the stream width
    pub fn normalise_row(&self, row: &mut [f32]) {
        normalise_row(row, &self.mean, &self.std);
    }

    /// The statistics as f32 tensors on `device`.
    pub fn normaliser(&self, device: &Device) -> Result<Normaliser> {
        Normaliser::new(&self.mean, &self.std, DType::F32, device)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rows_and_tensors_normalise_alike_and_round_trip() {
        let (mean, std) = ([0.5f32, -1.0, 2.0], [2.0f32, 0.25, 1.5]);
        let mut row = [1.0f32, 0.0, -3.0, 7.0];
        normalise_row(&mut row, &mean, &std);
        assert_eq!(row, [0.25, 4.0, -5.0 / 1.5, 7.0], "the fourth channel is left alone");
        let normaliser = Normaliser::new(&mean, &std, DType::F32, &Device::Cpu).unwrap();
        let x = Tensor::new(&[[1.0f32, 0.0, -3.0], [2.0, 3.0, 4.0]], &Device::Cpu).unwrap();
        let normalised = normaliser.normalise(&x).unwrap();
        assert_eq!(normalised.to_vec2::<f32>().unwrap()[0], row[..3]);
        let back = normaliser.denormalise(&normalised).unwrap().to_vec2::<f32>().unwrap();
        for (got, want) in back.iter().flatten().zip(x.to_vec2::<f32>().unwrap().iter().flatten()) {
            assert!((got - want).abs() < 1e-6, "{got} against {want}");
        }
    }
}
