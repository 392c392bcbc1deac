//! `--device cpu|cuda[:N]`: where `train`, `sample`, `evaluate` and `evaluator train` compute.
//! A run-time choice: it is stored in no configuration and no checkpoint.

use std::fmt;
use std::str::FromStr;

use anyhow::{Context, Result, bail};
use candle_core::Device;
use clap::Args;

/// The device option shared by the commands that compute.
#[derive(Debug, Clone, Copy, Args)]
pub struct DeviceArgs {
    /// Where to compute: `cpu`, or `cuda` / `cuda:N` for the N-th NVIDIA GPU (a build with the
    /// `cuda` feature: `cargo xtask build-cuda`).
    #[arg(long, value_name = "cpu|cuda[:N]", default_value_t = DeviceChoice::Cpu)]
    pub device: DeviceChoice,
}

impl DeviceArgs {
    /// Opens the chosen device.
    pub fn open(&self) -> Result<Device> {
        self.device.open()
    }
}

/// A device by name.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum DeviceChoice {
    /// The CPU (all cores).
    #[default]
    Cpu,
    /// The NVIDIA GPU of this ordinal.
    Cuda(usize),
}

impl FromStr for DeviceChoice {
    type Err = String;

    fn from_str(s: &str) -> std::result::Result<Self, Self::Err> {
        match s {
            "cpu" => Ok(Self::Cpu),
            "cuda" => Ok(Self::Cuda(0)),
            _ => s
                .strip_prefix("cuda:")
                .and_then(|n| n.parse().ok())
                .map(Self::Cuda)
                .ok_or_else(|| format!("`{s}` is not a device: expected cpu, cuda or cuda:N")),
        }
    }
}

impl fmt::Display for DeviceChoice {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Cpu => write!(f, "cpu"),
            Self::Cuda(n) => write!(f, "cuda:{n}"),
        }
    }
}

impl DeviceChoice {
    /// Opens the device, with an error that says what to do when this build has no CUDA or
    /// the GPU cannot be opened.
    pub fn open(self) -> Result<Device> {
        match self {
            Self::Cpu => Ok(Device::Cpu),
            Self::Cuda(ordinal) => {
                if !candle_core::utils::cuda_is_available() {
                    bail!(
                        "--device {self}: this dex2hoi was built without CUDA support; build the \
                         GPU binary with `cargo xtask build-cuda` (it runs only where the NVIDIA \
                         driver is installed)"
                    );
                }
                dex2hoi_model::cuda_device::open_cuda(ordinal).with_context(|| {
                    format!(
                        "--device {self}: could not open the GPU (is there a GPU {ordinal}? the \
                         driver must support CUDA 13.0, i.e. version 580 or newer)"
                    )
                })
            }
        }
    }
}

/// A hint for an error that came from the GPU running out of memory, if it did.
pub fn out_of_memory_hint(error: &anyhow::Error) -> Option<&'static str> {
    error.chain().any(|cause| cause.to_string().contains("OUT_OF_MEMORY")).then_some(
        "the GPU ran out of memory: use a smaller `training.batch_size` or model, or another GPU \
         (--device cuda:N)",
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn devices_parse_by_name() {
        assert_eq!("cpu".parse(), Ok(DeviceChoice::Cpu));
        assert_eq!("cuda".parse(), Ok(DeviceChoice::Cuda(0)));
        assert_eq!("cuda:3".parse(), Ok(DeviceChoice::Cuda(3)));
        for bad in ["gpu", "cuda:", "cuda:x", "CPU", "cuda:-1"] {
            assert!(bad.parse::<DeviceChoice>().is_err(), "{bad}");
        }
        assert_eq!(DeviceChoice::Cuda(2).to_string(), "cuda:2");
    }

    #[test]
    fn out_of_memory_is_recognised() {
        let oom = anyhow::anyhow!("DriverError(CUDA_ERROR_OUT_OF_MEMORY, \"out of memory\")")
            .context("training step");
        assert!(out_of_memory_hint(&oom).is_some());
        assert!(out_of_memory_hint(&anyhow::anyhow!("no such file")).is_none());
    }
}
