//! Opening a GPU for dex2hoi: one stream for all of its work, without candle's per-allocation
//! event tracking, and a memory pool that keeps what it has.
//!
//! `candle_core::Device::new_cuda` gives each host thread its own stream (CUDA's per-thread
//! default stream), so cudarc records an event on every buffer at every use and waits on it from
//! the other streams: two driver calls per argument of every kernel, for nothing when one thread
//! does the work. Here the device gets one stream of its own, which every thread that uses the
//! device shares; one stream orders all work by itself, so the tracking is turned off. The
//! stream-ordered pool's release threshold is raised from 0 (hand freed memory back to the
//! driver at every synchronisation) to the largest value (keep it for the next step's
//! allocations of the same sizes).
#![allow(unsafe_code)]

use candle_core::Device;

use crate::error::Result;

/// Opens GPU `ordinal` as described in the module documentation. In a build without CUDA it
/// returns candle's error for asking a GPU of such a build.
pub fn open_cuda(ordinal: usize) -> Result<Device> {
    let device = Device::new_cuda_with_stream(ordinal)?;
    #[cfg(feature = "cuda")]
    tune(device.as_cuda_device()?)?;
    Ok(device)
}

#[cfg(feature = "cuda")]
fn tune(device: &candle_core::CudaDevice) -> Result<()> {
    use candle_core::cuda_backend::WrapErr;
    use candle_core::cuda_backend::cudarc::driver::sys;

    // SAFETY: every tensor of this device is made and used on its one stream (module
    // documentation), which is the synchronisation cudarc's events would otherwise provide.
    unsafe { device.disable_event_tracking() };
    let context = device.cuda_stream().context().clone();
    context.bind_to_thread().w()?;
    let mut pool = std::mem::MaybeUninit::<sys::CUmemoryPool>::uninit();
    // SAFETY: the context is bound to this thread and `pool` is a valid place for the handle,
    // which the driver writes when it returns success (checked before it is read).
    unsafe { sys::cuDeviceGetDefaultMemPool(pool.as_mut_ptr(), context.cu_device()).result() }
        .w()?;
    // SAFETY: written by the successful call above.
    let pool = unsafe { pool.assume_init() };
    let mut threshold = u64::MAX;
    // SAFETY: the release threshold attribute takes a `cuuint64_t`, which `threshold` is; the
    // driver only reads it during the call.
    unsafe {
        sys::cuMemPoolSetAttribute(
            pool,
            sys::CUmemPool_attribute::CU_MEMPOOL_ATTR_RELEASE_THRESHOLD,
            (&raw mut threshold).cast(),
        )
        .result()
    }
    .w()?;
    Ok(())
}
