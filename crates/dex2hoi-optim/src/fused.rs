//! AdamW and the EMA of the weights as one CUDA kernel per parameter tensor
//! (`fused_adamw.cu`, compiled at run time by NVRTC; PyTorch calls this `fused=True`).
//!
//! The tensor-operation path launches about twenty elementwise kernels per parameter tensor,
//! each with an allocation, and reads the gradient norm back before it can compute the clipping
//! factor. This path launches one kernel per tensor that updates the parameter, both moments and
//! the average in place, and computes the clipping factor on the device from the squared norm;
//! the norm is read back once, after every kernel is queued.
//!
//! Why `unsafe`: launching a kernel is, since the compiler cannot check its arguments against the
//! kernel's signature; one launch, checked by hand (its `SAFETY` comment).
#![allow(unsafe_code)]

use candle_core::Tensor;

use crate::error::Result;
use crate::parameter::Parameter;

/// The scalars of one fused update, shared by every parameter but the weight decay.
#[derive(Debug, Clone, Copy)]
#[cfg_attr(not(feature = "cuda"), allow(dead_code, reason = "read by the CUDA build's launch"))]
pub(crate) struct FusedScalars {
    /// The global norm clip; infinity when the configuration does not clip.
    pub clip: f64,
    pub beta1: f32,
    pub beta2: f32,
    /// `lr / (1 - beta1^t)`.
    pub step_size: f32,
    /// `1 / sqrt(1 - beta2^t)`.
    pub inverse_root_correction2: f32,
    pub epsilon: f32,
    /// `d` of `ema = d ema + (1 - d) value`.
    pub ema_decay: f32,
}

/// Whether the fused kernel can update these parameters: a CUDA build, every parameter an `f32`
/// tensor on a GPU.
pub(crate) fn available(parameters: &[Parameter]) -> bool {
    cfg!(feature = "cuda")
        && !parameters.is_empty()
        && parameters
            .iter()
            .all(|p| p.var.device().is_cuda() && p.var.dtype() == candle_core::DType::F32)
}

/// The kernel of `fused_adamw.cu` on one GPU, looked up once for all of an update's launches.
#[cfg(feature = "cuda")]
pub(crate) struct Kernel {
    stream: std::sync::Arc<candle_core::cuda_backend::cudarc::driver::CudaStream>,
    function: candle_core::cuda_backend::cudarc::driver::CudaFunction,
}

#[cfg(not(feature = "cuda"))]
pub(crate) struct Kernel;

#[cfg(not(feature = "cuda"))]
impl Kernel {
    pub(crate) fn load(_: &Tensor) -> Result<Self> {
        Err(failure("the fused AdamW update needs the CUDA build".into()))
    }

    pub(crate) fn launch(
        &self,
        _: [&Tensor; 5],
        _: &Tensor,
        _: FusedScalars,
        _: f32,
    ) -> Result<()> {
        Err(failure("the fused AdamW update needs the CUDA build".into()))
    }
}

#[cfg(feature = "cuda")]
impl Kernel {
    /// The kernel on the GPU that `on` (any tensor of the update) is on, compiled at the first
    /// call of the process.
    pub(crate) fn load(on: &Tensor) -> Result<Self> {
        let device = on.device().as_cuda_device()?;
        let function = device.get_or_load_custom_func(FUNCTION, MODULE, ptx()?)?;
        Ok(Self { stream: device.cuda_stream(), function: function.into_cuda_function() })
    }

    /// One parameter's update in place: `value`, `first`, `second` and `average` (contiguous
    /// `f32` tensors of one size on the kernel's GPU) from `gradient` (the same size) and the
    /// squared global gradient norm `squared_norm` (one element). `keep` is
    /// `1 - lr * weight_decay`.
    pub(crate) fn launch(
        &self,
        [value, first, second, average, gradient]: [&Tensor; 5],
        squared_norm: &Tensor,
        s: FusedScalars,
        keep: f32,
    ) -> Result<()> {
        use candle_core::cuda_backend::WrapErr;
        use candle_core::cuda_backend::cudarc::driver::{LaunchConfig, PushKernelArg};

        const THREADS: u32 = 256;
        const MOST_BLOCKS: u32 = 4096;
        let n = value.elem_count();
        let guards = [value, first, second, average, gradient, squared_norm].map(|t| {
            let (storage, layout) = t.storage_and_layout();
            (storage, layout.clone(), t.elem_count())
        });
        let mut views = Vec::with_capacity(guards.len());
        for (k, (storage, layout, count)) in guards.iter().enumerate() {
            let expected = if k == 5 { 1 } else { n };
            let (candle_core::Storage::Cuda(storage), Some((start, end))) =
                (&**storage, layout.contiguous_offsets())
            else {
                return Err(failure(
                    "the fused AdamW update needs contiguous tensors on a GPU".into(),
                ));
            };
            if *count != expected {
                return Err(failure(format!(
                    "the fused AdamW update got {count} elements in argument {k}, expected {expected}"
                )));
            }
            views.push(storage.as_cuda_slice::<f32>()?.slice(start..end));
        }
        let elements = u32::try_from(n).map_err(|_| {
            failure(format!("the fused AdamW update got a parameter of {n} elements"))
        })?;
        let config = LaunchConfig {
            grid_dim: (elements.div_ceil(THREADS).clamp(1, MOST_BLOCKS), 1, 1),
            block_dim: (THREADS, 1, 1),
            shared_mem_bytes: 0,
        };
        let mut builder = self.stream.launch_builder(&self.function);
        for view in &views {
            builder.arg(view);
        }
        builder
            .arg(&s.clip)
            .arg(&s.beta1)
            .arg(&s.beta2)
            .arg(&s.step_size)
            .arg(&s.inverse_root_correction2)
            .arg(&s.epsilon)
            .arg(&keep)
            .arg(&s.ema_decay)
            .arg(&elements);
        // SAFETY: the arguments match the kernel's signature in `fused_adamw.cu` one for one (five
        // arrays of `elements` floats, one of one float, a double, seven floats, an unsigned int),
        // every array was checked to hold as many elements as the kernel indexes, and the device
        // runs all of dex2hoi's work on one stream, so no other kernel touches them meanwhile.
        unsafe { builder.launch(config) }.w()?;
        Ok(())
    }
}

/// An error of the fused update, as candle's.
fn failure(message: String) -> crate::error::OptimError {
    candle_core::Error::Msg(message).into()
}

#[cfg(feature = "cuda")]
const MODULE: &str = "dex2hoi_fused_adamw";
#[cfg(feature = "cuda")]
const FUNCTION: &str = "adamw_ema_f32";

/// The kernel's PTX, compiled once per process.
#[cfg(feature = "cuda")]
fn ptx() -> Result<&'static str> {
    use std::sync::OnceLock;
    static PTX: OnceLock<std::result::Result<String, String>> = OnceLock::new();
    PTX.get_or_init(|| {
        candle_core::cuda_backend::cudarc::nvrtc::compile_ptx(include_str!("fused_adamw.cu"))
            .map(|ptx| ptx.to_src())
            .map_err(|e| e.to_string())
    })
    .as_deref()
    .map_err(|e| failure(format!("compiling fused_adamw.cu: {e}")))
}
