//! The CUDA side of the forward-kinematics operations (`fk.rs`, [`crate::fk::FkOp`]): one
//! kernel launch for a pass over a whole batch of frames (`fk.cu`, compiled at run time by
//! NVRTC), where the composite FK launches several hundred small kernels forward and more
//! backward.
//!
//! Why `unsafe`: launching a kernel is, since the compiler cannot check its arguments against the
//! kernel's signature; three launches, each checked by hand (their `SAFETY` comments).
#![allow(unsafe_code)]

use candle_core::cuda_backend::WrapErr;
use candle_core::cuda_backend::cudarc::driver::{
    CudaSlice, CudaView, LaunchArgs, LaunchConfig, PushKernelArg,
};
use candle_core::{CudaDevice, CudaStorage, Layout, Shape, Storage, StorageRef, Tensor};

use crate::cuda_kernel::{KernelSource, contiguous_f32, kernel_count};

static SOURCE: KernelSource = KernelSource::new("dex2hoi_fk", "fk.cu", include_str!("fk.cu"));
/// The operation as errors name it.
const FK: &str = "dex2hoi FK";
const THREADS: u32 = 128;

/// The skeleton and bodies of one FK operation, as the kernels read them.
pub(crate) struct FkBodies<'a> {
    /// Each joint's parent (a parent precedes its children).
    pub parents: &'a [Option<usize>],
    /// The rest offsets, `[samples * joints]`, uploaded at each pass; empty when
    /// `device_offsets` holds them.
    pub offsets: &'a [[f32; 3]],
    /// The rest offsets already on the GPU, `[samples, joints, 3]` `f32` contiguous.
    pub device_offsets: Option<&'a Tensor>,
    /// Consecutive frames that share one sample's offsets (`usize::MAX`: one set for all).
    pub frames_per_sample: usize,
}

/// What both passes read: the frames' local rotations and roots, the skeleton's parents and the
/// rest offsets on the GPU, and the kernels' sizes, checked against one another.
struct Frames<'a> {
    device: &'a CudaDevice,
    local: CudaView<'a, f32>,
    root: CudaView<'a, f32>,
    parents: CudaSlice<i32>,
    offsets: Offsets<'a>,
    batch: usize,
    joints: usize,
    /// `frames_per_sample` (0 for one set of offsets), the joint count and the batch, as the
    /// kernels take them.
    sizes: (u32, u32, u32),
}

impl<'a> Frames<'a> {
    fn new(
        bodies: &FkBodies<'a>,
        (local, local_layout): (&'a CudaStorage, &Layout),
        (root, root_layout): (&'a CudaStorage, &Layout),
    ) -> candle_core::Result<Self> {
        let device = &local.device;
        let joints = bodies.parents.len();
        let batch = root_layout.shape().elem_count() / 3;
        Ok(Self {
            device,
            local: contiguous_f32(
                FK,
                (local, local_layout),
                batch * joints * 9,
                "local rotations",
            )?,
            root: contiguous_f32(FK, (root, root_layout), batch * 3, "root positions")?,
            parents: parents(device, bodies)?,
            offsets: Offsets::of(device, bodies)?,
            batch,
            joints,
            sizes: sizes(bodies, batch)?,
        })
    }

    /// The kernels' first seven arguments, shared by both passes: local rotations, roots,
    /// parents, `offsets` (this batch's, from [`Offsets::view`]), frames per sample, joint
    /// count, batch.
    fn push<'b>(&'b self, offsets: &'b CudaView<'_, f32>, builder: &mut LaunchArgs<'b>) {
        let (frames_per_sample, joints, batch) = &self.sizes;
        builder
            .arg(&self.local)
            .arg(&self.root)
            .arg(&self.parents)
            .arg(offsets)
            .arg(frames_per_sample)
            .arg(joints)
            .arg(batch);
    }
}

/// The forward pass: `[batch, joints, 3]` positions, or `[batch, joints, 3, 3]` rotations when
/// `width` is 9.
pub(crate) fn forward(
    bodies: &FkBodies<'_>,
    local: (&CudaStorage, &Layout),
    root: (&CudaStorage, &Layout),
    width: usize,
) -> candle_core::Result<(CudaStorage, Shape)> {
    let frames = Frames::new(bodies, local, root)?;
    let (device, batch, joints) = (frames.device, frames.batch, frames.joints);
    let offsets = frames.offsets.view()?;
    let packed = device.alloc_zeros::<f32>(batch * joints * 12)?;
    let out = device.alloc_zeros::<f32>(batch * joints * width)?;
    let function = SOURCE.function(device, "fk_forward_f32")?;
    let (width_arg, from) = (width as u32, if width == 3 { 9u32 } else { 0 });
    let mut builder = function.builder();
    frames.push(&offsets, &mut builder);
    builder.arg(&packed).arg(&out).arg(&width_arg).arg(&from);
    // SAFETY: the arguments are those of `fk_forward_f32` in `fk.cu`, in order; `Frames::new`
    // checked the local rotations and roots to hold `batch` frames and the offsets to hold every
    // sample's, and the scratch and output were allocated here at the sizes the kernel indexes.
    unsafe { builder.launch(per_frame(batch)) }.w()?;
    let shape = if width == 3 {
        Shape::from((batch, joints, 3))
    } else {
        Shape::from((batch, joints, 3, 3))
    };
    Ok((CudaStorage::wrap_cuda_slice(out, device.clone()), shape))
}

/// The backward pass: the `[batch, joints, 3, 3]` gradient of the local rotations from the
/// gradient of the positions (`width` 3) or of the rotations (`width` 9).
pub(crate) fn backward(
    bodies: &FkBodies<'_>,
    local: (&CudaStorage, &Layout),
    root: (&CudaStorage, &Layout),
    (grad, grad_layout): (&CudaStorage, &Layout),
    width: usize,
) -> candle_core::Result<(CudaStorage, Shape)> {
    let shape = local.1.shape().clone();
    let frames = Frames::new(bodies, local, root)?;
    let (device, batch, joints) = (frames.device, frames.batch, frames.joints);
    let grad = contiguous_f32(FK, (grad, grad_layout), batch * joints * width, "output gradient")?;
    let offsets = frames.offsets.view()?;
    let packed = device.alloc_zeros::<f32>(batch * joints * 12)?;
    let state = device.alloc_zeros::<f32>(batch * joints * 12)?;
    let out = device.alloc_zeros::<f32>(batch * joints * 9)?;
    let function = SOURCE.function(device, "fk_backward_f32")?;
    let width_arg = width as u32;
    let mut builder = function.builder();
    frames.push(&offsets, &mut builder);
    builder.arg(&packed).arg(&state).arg(&grad).arg(&width_arg).arg(&out);
    // SAFETY: the arguments are those of `fk_backward_f32` in `fk.cu`, in order; `Frames::new`
    // checked the inputs to hold `batch` frames of `joints` joints and the offsets every
    // sample's, the gradient was checked to hold `width` numbers per joint, and the two scratches
    // and the output were allocated here at the sizes the kernel indexes.
    unsafe { builder.launch(per_frame(batch)) }.w()?;
    Ok((CudaStorage::wrap_cuda_slice(out, device.clone()), shape))
}

/// `[batch, joints, 3]` summed over joints to `[batch, 3]`.
pub(crate) fn sum_over_joints(
    storage: &CudaStorage,
    layout: &Layout,
) -> candle_core::Result<(CudaStorage, Shape)> {
    let device = &storage.device;
    let (batch, joints, _) = layout.shape().dims3()?;
    let values = contiguous_f32(FK, (storage, layout), batch * joints * 3, "position gradient")?;
    let out = device.alloc_zeros::<f32>(batch * 3)?;
    let function = SOURCE.function(device, "fk_sum_over_joints_f32")?;
    let (batch_arg, joints_arg) = (count(batch, "frames")?, count(joints, "joints")?);
    let mut builder = function.builder();
    builder.arg(&values).arg(&batch_arg).arg(&joints_arg).arg(&out);
    // SAFETY: the arguments are those of `fk_sum_over_joints_f32` in `fk.cu`, in order; `values`
    // holds `batch * joints * 3` numbers and `out` `batch * 3`, one thread each.
    unsafe { builder.launch(per_frame(batch * 3)) }.w()?;
    Ok((CudaStorage::wrap_cuda_slice(out, device.clone()), Shape::from((batch, 3))))
}

/// The rest offsets as the kernels read them: the GPU tensor where it is, or an upload.
enum Offsets<'a> {
    Resident(StorageRef<'a>, &'a Layout, usize),
    Uploaded(CudaSlice<f32>),
}

impl<'a> Offsets<'a> {
    fn of(device: &CudaDevice, bodies: &FkBodies<'a>) -> candle_core::Result<Self> {
        Ok(match bodies.device_offsets {
            Some(tensor) => {
                let (storage, layout) = tensor.storage_and_layout();
                Self::Resident(storage, layout, tensor.elem_count())
            }
            None => {
                let flat: Vec<f32> = bodies.offsets.iter().flatten().copied().collect();
                Self::Uploaded(device.clone_htod(&flat)?)
            }
        })
    }

    fn view(&self) -> candle_core::Result<CudaView<'_, f32>> {
        match self {
            Self::Resident(storage, layout, count) => {
                let Storage::Cuda(storage) = &**storage else {
                    candle_core::bail!("dex2hoi FK on the GPU: the rest offsets are not on the GPU")
                };
                contiguous_f32(FK, (storage, layout), *count, "rest offsets")
            }
            Self::Uploaded(slice) => Ok(slice.slice(..)),
        }
    }
}

/// The parents on the device, `-1` for the root.
fn parents(device: &CudaDevice, bodies: &FkBodies<'_>) -> candle_core::Result<CudaSlice<i32>> {
    let parents: Vec<i32> = bodies.parents.iter().map(|p| p.map_or(-1, |p| p as i32)).collect();
    device.clone_htod(&parents)
}

/// The kernels' `frames_per_sample` (0 for one set of offsets), joint count and batch, checked
/// against the offsets: every frame's sample must have its offsets.
fn sizes(bodies: &FkBodies<'_>, batch: usize) -> candle_core::Result<(u32, u32, u32)> {
    let joints = bodies.parents.len();
    let samples = match bodies.device_offsets {
        Some(tensor) => {
            if tensor.dims() != [tensor.dim(0)?, joints, 3] {
                candle_core::bail!(
                    "dex2hoi FK on the GPU: rest offsets of shape {:?}",
                    tensor.dims()
                )
            }
            tensor.dim(0)?
        }
        None => bodies.offsets.len() / joints.max(1),
    };
    let frames_per_sample = if bodies.frames_per_sample == usize::MAX {
        0
    } else {
        if batch != samples * bodies.frames_per_sample {
            candle_core::bail!(
                "dex2hoi FK on the GPU: {batch} frames for {samples} samples of {} frames",
                bodies.frames_per_sample
            )
        }
        count(bodies.frames_per_sample, "frames per sample")?
    };
    if bodies.parents.iter().enumerate().any(|(j, p)| p.is_some_and(|p| p >= j)) {
        candle_core::bail!("dex2hoi FK on the GPU: a parent must precede its children")
    }
    Ok((frames_per_sample, count(joints, "joints")?, count(batch, "frames")?))
}

fn count(n: usize, what: &str) -> candle_core::Result<u32> {
    kernel_count(FK, n, what)
}

fn per_frame(threads: usize) -> LaunchConfig {
    LaunchConfig {
        grid_dim: ((threads as u32).div_ceil(THREADS).max(1), 1, 1),
        block_dim: (THREADS, 1, 1),
        shared_mem_bytes: 0,
    }
}
