//! What dex2hoi's own CUDA kernels share on the Rust side: their source compiled to PTX by NVRTC
//! once per process ([`KernelSource`]), an input checked and viewed as the kernels read it
//! ([`contiguous_f32`]) and a size passed as a kernel's 32-bit count ([`kernel_count`]). Forward
//! kinematics here and the model's row operations use them.

use std::sync::{Arc, OnceLock};

use candle_core::cuda_backend::cudarc::driver::{CudaFunction, CudaStream, CudaView, LaunchArgs};
use candle_core::{CudaDevice, CudaStorage, Layout};

/// A CUDA source file of dex2hoi, compiled at its first use.
pub struct KernelSource {
    /// The module's name in candle's cache of loaded modules.
    pub module: &'static str,
    file: &'static str,
    source: &'static str,
    ptx: OnceLock<Result<String, String>>,
}

impl KernelSource {
    /// The source `source` of the file `file` (named in errors), loaded as module `module`.
    pub const fn new(module: &'static str, file: &'static str, source: &'static str) -> Self {
        Self { module, file, source, ptx: OnceLock::new() }
    }

    /// The PTX, compiled once per process.
    pub fn ptx(&self) -> candle_core::Result<&str> {
        self.ptx
            .get_or_init(|| {
                candle_core::cuda_backend::cudarc::nvrtc::compile_ptx(self.source)
                    .map(|ptx| ptx.to_src())
                    .map_err(|e| e.to_string())
            })
            .as_deref()
            .map_err(|e| candle_core::Error::Msg(format!("compiling {}: {e}", self.file)))
    }

    /// The kernel `name` of this source on `device`'s stream, the module loaded at its first use
    /// (candle keeps it per device).
    pub fn function(&self, device: &CudaDevice, name: &str) -> candle_core::Result<Kernel> {
        let function = device.get_or_load_custom_func(name, self.module, self.ptx()?)?;
        Ok(Kernel { function: function.into_cuda_function(), stream: device.cuda_stream() })
    }
}

/// One kernel of a [`KernelSource`], bound to the stream it launches on.
pub struct Kernel {
    function: CudaFunction,
    stream: Arc<CudaStream>,
}

impl Kernel {
    /// A launch of the kernel on its stream; the caller pushes the arguments in the kernel's
    /// order and launches (unsafe: the arguments are not checked against the source).
    pub fn builder(&self) -> LaunchArgs<'_> {
        self.stream.launch_builder(&self.function)
    }
}

/// The contiguous `f32` values of an input of the operation `op`, which must number `expected`;
/// `what` names the input in errors.
pub fn contiguous_f32<'a>(
    op: &str,
    (storage, layout): (&'a CudaStorage, &Layout),
    expected: usize,
    what: &str,
) -> candle_core::Result<CudaView<'a, f32>> {
    let Some((start, end)) = layout.contiguous_offsets() else {
        candle_core::bail!("{op} on the GPU: {what} must be contiguous")
    };
    if end - start != expected {
        candle_core::bail!(
            "{op} on the GPU: {what} hold {} values, expected {expected}",
            end - start
        )
    }
    Ok(storage.as_cuda_slice::<f32>()?.slice(start..end))
}

/// `n` as the 32-bit count a kernel of the operation `op` takes; `what` names what is counted in
/// the error when it does not fit.
pub fn kernel_count(op: &str, n: usize, what: &str) -> candle_core::Result<u32> {
    u32::try_from(n)
        .map_err(|_| candle_core::Error::Msg(format!("{op} on the GPU: {n} {what} are too many")))
}
