//! Forward kinematics: local joint rotations and a root position to global joint positions and
//! rotations, `G_i = G_parent(i) [R_i | offset_i]` (docs/CONVENTIONS.md, "Forward kinematics"). The
//! CPU version works on `glam` types; [`tensor_forward_kinematics`] is the batched, differentiable
//! candle version that the training losses go through (paper Sec. 3.3).
//!
//! The root position is the world position of the root joint (the pelvis), not a displacement
//! from the rest pose: the identity pose with `root = rest_offsets[0]` gives the rest joints.

use std::sync::Arc;

use candle_core::{CpuStorage, CustomOp1, CustomOp2, CustomOp3, DType, Layout, Shape, Tensor};
use glam::{Mat3, Vec3};
use rayon::prelude::*;

use crate::error::{ReprError, Result};
use crate::rotation::tensor::{leading_dims, leading_dims_matrix, require_float};
use crate::skeleton::Skeleton;

/// Global joint positions and rotations for a sequence, frame-major (`[frames * joints]`).
#[derive(Debug, Clone, PartialEq)]
pub struct FkOutput {
    /// Number of frames.
    pub frames: usize,
    /// Number of joints per frame.
    pub joints: usize,
    /// World positions, `positions[frame * joints + joint]`.
    pub positions: Vec<Vec3>,
    /// World rotations, same indexing.
    pub rotations: Vec<Mat3>,
}

impl FkOutput {
    /// The world position of a joint at a frame.
    pub fn position(&self, frame: usize, joint: usize) -> Vec3 {
        self.positions[frame * self.joints + joint]
    }

    /// The world rotation of a joint at a frame.
    pub fn rotation(&self, frame: usize, joint: usize) -> Mat3 {
        self.rotations[frame * self.joints + joint]
    }

    /// The positions of one frame.
    pub fn frame_positions(&self, frame: usize) -> &[Vec3] {
        &self.positions[frame * self.joints..(frame + 1) * self.joints]
    }
}

/// Forward kinematics of one frame into caller-provided buffers of length `J`.
pub fn forward_kinematics_frame(
    skeleton: &Skeleton,
    local_rotations: &[Mat3],
    root_position: Vec3,
    positions: &mut [Vec3],
    rotations: &mut [Mat3],
) {
    for (joint, (parent, offset)) in
        skeleton.parents().iter().zip(skeleton.rest_offsets()).enumerate()
    {
        match parent {
            None => {
                rotations[joint] = local_rotations[joint];
                positions[joint] = root_position;
            }
            Some(p) => {
                let parent_rotation = rotations[*p];
                rotations[joint] = parent_rotation * local_rotations[joint];
                positions[joint] = positions[*p] + parent_rotation * *offset;
            }
        }
    }
}

/// Frames per parallel task in [`forward_kinematics`].
const FRAMES_PER_TASK: usize = 256;

/// Forward kinematics of a sequence, frames in parallel.
///
/// # Shapes
/// - `local_rotations`: `[frames * joints]`, frame-major
/// - `root_positions`: `[frames]`
pub fn forward_kinematics(
    skeleton: &Skeleton,
    local_rotations: &[Mat3],
    root_positions: &[Vec3],
) -> Result<FkOutput> {
    let joints = skeleton.joint_count();
    let frames = root_positions.len();
    if local_rotations.len() != frames * joints {
        return Err(ReprError::invalid(
            "local rotations",
            format!("{frames} frames x {joints} joints = {} matrices", frames * joints),
            local_rotations.len(),
        ));
    }
    let mut positions = vec![Vec3::ZERO; frames * joints];
    let mut rotations = vec![Mat3::IDENTITY; frames * joints];
    // One task per block of frames: a single frame is too little work to be worth a task.
    let block = joints * FRAMES_PER_TASK;
    positions
        .par_chunks_mut(block)
        .zip(rotations.par_chunks_mut(block))
        .zip(local_rotations.par_chunks(block))
        .zip(root_positions.par_chunks(FRAMES_PER_TASK))
        .for_each(|(((positions, rotations), local), roots)| {
            for (frame, root) in roots.iter().enumerate() {
                let span = frame * joints..(frame + 1) * joints;
                forward_kinematics_frame(
                    skeleton,
                    &local[span.clone()],
                    *root,
                    &mut positions[span.clone()],
                    &mut rotations[span],
                );
            }
        });
    Ok(FkOutput { frames, joints, positions, rotations })
}

/// Checks the shapes of a tensor FK call and returns the leading dimensions (without joints).
/// `rest_offsets`, when given, must be `[G, joints, 3]` with `G` the first leading dimension.
fn check_tensor_inputs(
    skeleton: &Skeleton,
    rest_offsets: Option<&Tensor>,
    local_rotations: &Tensor,
    root_positions: &Tensor,
) -> Result<Vec<usize>> {
    let joints = skeleton.joint_count();
    let mut leading = leading_dims_matrix(local_rotations, "local rotations")?;
    require_float(local_rotations, "local rotations")?;
    let root_leading = leading_dims(root_positions, 3, "root positions")?;
    if leading.last() != Some(&joints) || leading[..leading.len() - 1] != root_leading[..] {
        return Err(ReprError::invalid(
            "local rotations and root positions",
            format!("shapes [..., {joints}, 3, 3] and [..., 3] with the same leading dimensions"),
            format!("{:?} and {:?}", local_rotations.dims(), root_positions.dims()),
        ));
    }
    leading.pop();
    if let Some(rest) = rest_offsets {
        let samples = leading.first().copied();
        if samples.is_none() || rest.dims() != [samples.unwrap_or(0), joints, 3] {
            return Err(ReprError::invalid(
                "per-sample rest offsets",
                format!("shape [samples, {joints}, 3] with samples the first leading dimension"),
                format!("{:?} for rotations {:?}", rest.dims(), local_rotations.dims()),
            ));
        }
    }
    Ok(leading)
}

/// Batched, differentiable forward kinematics on the skeleton's own rest offsets.
///
/// On the CPU with `f32` or `f64` tensors this is two candle operations (positions and
/// rotations, see [`FkOp`]) with hand-written backward passes, frames in parallel; elsewhere it
/// falls back to [`tensor_forward_kinematics_composite`], built from candle's own
/// differentiable operations. Both give the same values and gradients (tested).
///
/// # Shapes
/// - `local_rotations`: `[..., joints, 3, 3]`
/// - `root_positions`: `[..., 3]`
/// - returns `(positions [..., joints, 3], rotations [..., joints, 3, 3])`
pub fn tensor_forward_kinematics(
    skeleton: &Skeleton,
    local_rotations: &Tensor,
    root_positions: &Tensor,
) -> Result<(Tensor, Tensor)> {
    operation_fk(skeleton, None, local_rotations, root_positions)
}

/// [`tensor_forward_kinematics`] with one set of rest offsets per sample (each sequence's own
/// body, see docs/FORMATS.md "rest_offsets"); the skeleton gives the topology only. The offsets
/// are data, not differentiated.
///
/// # Shapes
/// - `rest_offsets`: `[G, joints, 3]`
/// - `local_rotations`: `[G, ..., joints, 3, 3]`: every frame of sample `g` uses its offsets
/// - `root_positions`: `[G, ..., 3]`
/// - returns `(positions [G, ..., joints, 3], rotations [G, ..., joints, 3, 3])`
pub fn tensor_forward_kinematics_per_sample(
    skeleton: &Skeleton,
    rest_offsets: &Tensor,
    local_rotations: &Tensor,
    root_positions: &Tensor,
) -> Result<(Tensor, Tensor)> {
    operation_fk(skeleton, Some(rest_offsets), local_rotations, root_positions)
}

fn operation_fk(
    skeleton: &Skeleton,
    rest_offsets: Option<&Tensor>,
    local_rotations: &Tensor,
    root_positions: &Tensor,
) -> Result<(Tensor, Tensor)> {
    let leading = check_tensor_inputs(skeleton, rest_offsets, local_rotations, root_positions)?;
    let dtype = local_rotations.dtype();
    // The operation's CPU side takes both float types, its CUDA side `f32`.
    let supported = match local_rotations.device() {
        candle_core::Device::Cpu => matches!(dtype, DType::F32 | DType::F64),
        candle_core::Device::Cuda(_) => dtype == DType::F32,
        _ => false,
    };
    if !supported {
        return composite_fk(skeleton, rest_offsets, local_rotations, root_positions);
    }
    let joints = skeleton.joint_count();
    let batch: usize = leading.iter().product();
    let local = local_rotations.reshape((batch, joints, 3, 3))?.contiguous()?;
    let root = root_positions.to_dtype(dtype)?.reshape((batch, 3))?.contiguous()?;
    let op = match rest_offsets {
        None => FkOp::new(skeleton),
        Some(rest) => FkOp::per_sample(skeleton, rest, batch)?,
    };
    let positions =
        local.apply_op2(&root, FkOutputOp { op: op.clone(), output: Output::Positions })?;
    let rotations = local.apply_op2(&root, FkOutputOp { op, output: Output::Rotations })?;
    let mut rotation_shape = leading.clone();
    rotation_shape.extend([joints, 3, 3]);
    let mut position_shape = leading;
    position_shape.extend([joints, 3]);
    Ok((positions.reshape(position_shape)?, rotations.reshape(rotation_shape)?))
}

/// Forward kinematics from candle's own differentiable operations, on any device: one group
/// of operations per depth level of the tree, in a component-major layout.
///
/// # Shapes
/// - `local_rotations`: `[..., joints, 3, 3]`
/// - `root_positions`: `[..., 3]`
/// - returns `(positions [..., joints, 3], rotations [..., joints, 3, 3])`
pub fn tensor_forward_kinematics_composite(
    skeleton: &Skeleton,
    local_rotations: &Tensor,
    root_positions: &Tensor,
) -> Result<(Tensor, Tensor)> {
    composite_fk(skeleton, None, local_rotations, root_positions)
}

/// [`tensor_forward_kinematics_composite`] with per-sample rest offsets; shapes as in
/// [`tensor_forward_kinematics_per_sample`].
pub fn tensor_forward_kinematics_composite_per_sample(
    skeleton: &Skeleton,
    rest_offsets: &Tensor,
    local_rotations: &Tensor,
    root_positions: &Tensor,
) -> Result<(Tensor, Tensor)> {
    composite_fk(skeleton, Some(rest_offsets), local_rotations, root_positions)
}

fn composite_fk(
    skeleton: &Skeleton,
    rest_offsets: Option<&Tensor>,
    local_rotations: &Tensor,
    root_positions: &Tensor,
) -> Result<(Tensor, Tensor)> {
    let joints = skeleton.joint_count();
    let leading = check_tensor_inputs(skeleton, rest_offsets, local_rotations, root_positions)?;
    let batch: usize = leading.iter().product();
    let dtype = local_rotations.dtype();
    let device = local_rotations.device();
    // Component-major layout, `[9, joints, batch]` and `[3, joints, batch]`: each matrix entry
    // of a group of joints is one contiguous run, so the 3x3 products below are plain
    // same-shape multiplies and adds (a batched matmul of many tiny matrices pays a call per
    // matrix; broadcasts pay strided indexing).
    let local = local_rotations.reshape((batch, joints, 9))?.permute((2, 1, 0))?.contiguous()?;
    let root =
        root_positions.to_dtype(dtype)?.reshape((batch, 3))?.t()?.contiguous()?.unsqueeze(1)?;
    // The rest offsets of every body, `[3, joints, batch]`: the skeleton's for all, or each
    // sample's repeated over its frames.
    let rest = match rest_offsets {
        Some(rest) => rest.to_device(device)?.to_dtype(dtype)?,
        None => {
            let values: Vec<f32> =
                skeleton.rest_offsets().iter().flat_map(|o| o.to_array()).collect();
            Tensor::from_vec(values, (1, joints, 3), device)?.to_dtype(dtype)?
        }
    };
    let samples = rest.dim(0)?;
    let offsets_all = rest
        .unsqueeze(1)?
        .broadcast_as((samples, batch / samples, joints, 3))?
        .reshape((batch, joints, 3))?
        .permute((2, 1, 0))?
        .contiguous()?;
    // Joints of one depth only depend on shallower joints: one batch of operations per depth
    // level (11 for SMPL-X) instead of one per joint.
    let levels = skeleton.depth_levels();
    let index = |ids: &[usize]| -> Result<Tensor> {
        let ids: Vec<u32> = ids.iter().map(|&j| j as u32).collect();
        let count = ids.len();
        Ok(Tensor::from_vec(ids, count, device)?)
    };
    // Where each joint sits inside its level, to find parents in the previous level.
    let mut slot = vec![0usize; joints];
    for level in &levels {
        for (k, &joint) in level.iter().enumerate() {
            slot[joint] = k;
        }
    }
    let mut level_rotations: Vec<Tensor> = Vec::with_capacity(levels.len());
    let mut level_positions: Vec<Tensor> = Vec::with_capacity(levels.len());
    for (depth, level) in levels.iter().enumerate() {
        let level_index = index(level)?;
        let level_local = local.index_select(&level_index, 1)?; // [9, L, batch]
        if depth == 0 {
            level_rotations.push(level_local);
            level_positions.push(root.clone());
            continue;
        }
        let parent_slots: Vec<usize> =
            level.iter().map(|&j| skeleton.parents()[j].map_or(0, |p| slot[p])).collect();
        let parent_slots = index(&parent_slots)?;
        let parent_rotation = level_rotations[depth - 1].index_select(&parent_slots, 1)?;
        let parent_position = level_positions[depth - 1].index_select(&parent_slots, 1)?;
        let offsets = offsets_all.index_select(&level_index, 1)?; // [3, L, batch]
        let a = |i: usize, k: usize| parent_rotation.narrow(0, 3 * i + k, 1);
        let b = |k: usize, j: usize| level_local.narrow(0, 3 * k + j, 1);
        let o = |k: usize| offsets.narrow(0, k, 1);
        let mut rotation = Vec::with_capacity(9);
        let mut position = Vec::with_capacity(3);
        for i in 0..3 {
            for j in 0..3 {
                let entry = ((a(i, 0)? * b(0, j)?)? + (a(i, 1)? * b(1, j)?)?)?;
                rotation.push((entry + (a(i, 2)? * b(2, j)?)?)?);
            }
            let moved = ((a(i, 0)? * o(0)?)? + (a(i, 1)? * o(1)?)?)?;
            let moved = (moved + (a(i, 2)? * o(2)?)?)?;
            position.push((parent_position.narrow(0, i, 1)? + moved)?);
        }
        level_rotations.push(Tensor::cat(&rotation, 0)?);
        level_positions.push(Tensor::cat(&position, 0)?);
    }
    // Back from level order to joint order, and to `[batch, joints, ...]`.
    let order: Vec<usize> = levels.concat();
    let mut inverse = vec![0usize; joints];
    for (k, &joint) in order.iter().enumerate() {
        inverse[joint] = k;
    }
    let inverse = index(&inverse)?;
    let rotations = Tensor::cat(&level_rotations, 1)?.index_select(&inverse, 1)?;
    let positions = Tensor::cat(&level_positions, 1)?.index_select(&inverse, 1)?;
    let mut position_shape = leading.clone();
    position_shape.extend([joints, 3]);
    let mut rotation_shape = leading;
    rotation_shape.extend([joints, 3, 3]);
    let positions = positions.permute((2, 1, 0))?.contiguous()?.reshape(position_shape)?;
    let rotations = rotations.permute((2, 1, 0))?.contiguous()?.reshape(rotation_shape)?;
    Ok((positions, rotations))
}

/// Forward kinematics on CPU slices with an analytic backward pass, behind two candle
/// operations ([`FkOutputOp`]): one for the `[batch, joints, 3]` positions, one for the
/// `[batch, joints, 3, 3]` global rotations. Two operations rather than one packed output, so that neither pays for
/// slicing the other's gradient. The backward pass runs the chain rule of
/// `G_j = G_p R_j`, `p_j = p_p + G_p o_j` from the leaves to the root:
/// `dR_j = G_p^T dG_j`, `dG_p += dG_j R_j^T + dp_j o_j^T`, `dp_p += dp_j`; the forward pass of
/// the frame is recomputed there, which is cheaper than keeping it.
#[derive(Debug, Clone)]
pub struct FkOp {
    parents: Arc<[Option<usize>]>,
    /// The rest offsets of each sample, `[samples * joints]`: one sample for a plain skeleton.
    offsets: Arc<[[f32; 3]]>,
    /// Consecutive frames of the batch that share one sample's offsets (`usize::MAX` when
    /// every frame uses the one set).
    frames_per_sample: usize,
    /// Per-sample offsets that are on a GPU, `[samples, joints, 3]` `f32`, which the CUDA
    /// kernels read where they are (`offsets` is then empty): reading them back would stop
    /// the host until the GPU has caught up.
    #[cfg_attr(not(feature = "cuda"), allow(dead_code, reason = "read by the CUDA kernels"))]
    device_offsets: Option<Tensor>,
}

/// The float types the operation computes in, natively (no conversion copies).
trait Real:
    Copy
    + Default
    + Send
    + Sync
    + std::ops::Add<Output = Self>
    + std::ops::Mul<Output = Self>
    + std::ops::AddAssign
{
    fn from_f32(x: f32) -> Self;
    fn values(storage: &CpuStorage) -> Option<&[Self]>;
    fn into_storage(values: Vec<Self>) -> CpuStorage;
}

macro_rules! impl_real {
    ($t:ty, $variant:ident) => {
        impl Real for $t {
            fn from_f32(x: f32) -> Self {
                <$t>::from(x)
            }
            fn values(storage: &CpuStorage) -> Option<&[Self]> {
                match storage {
                    CpuStorage::$variant(v) => Some(v),
                    _ => None,
                }
            }
            fn into_storage(values: Vec<Self>) -> CpuStorage {
                CpuStorage::$variant(values)
            }
        }
    };
}

impl_real!(f32, F32);
impl_real!(f64, F64);

type M3<T> = [T; 9];

fn mat<T: Real>(values: &[T]) -> M3<T> {
    std::array::from_fn(|i| values[i])
}

fn mat_mul<T: Real>(a: &M3<T>, b: &M3<T>) -> M3<T> {
    std::array::from_fn(|k| {
        let (r, c) = (k / 3, k % 3);
        a[r * 3] * b[c] + a[r * 3 + 1] * b[3 + c] + a[r * 3 + 2] * b[6 + c]
    })
}

fn mat_vec<T: Real>(a: &M3<T>, v: &[T; 3]) -> [T; 3] {
    std::array::from_fn(|r| a[r * 3] * v[0] + a[r * 3 + 1] * v[1] + a[r * 3 + 2] * v[2])
}

fn transpose<T: Real>(a: &M3<T>) -> M3<T> {
    std::array::from_fn(|k| a[(k % 3) * 3 + k / 3])
}

/// The contiguous values of a storage of the type `T`.
fn storage_values<'a, T: Real>(
    storage: &'a CpuStorage,
    layout: &Layout,
    what: &str,
) -> candle_core::Result<&'a [T]> {
    let (start, end) = layout
        .contiguous_offsets()
        .ok_or_else(|| candle_core::Error::Msg(format!("dex2hoi FK: {what} must be contiguous")))?;
    T::values(storage).map(|v| &v[start..end]).ok_or_else(|| {
        candle_core::Error::Msg(format!("dex2hoi FK: {what} must have the dtype of the rotations"))
    })
}

/// Frames per parallel task in the FK operation.
const OP_FRAMES_PER_TASK: usize = 64;

impl FkOp {
    /// The operation for a skeleton, on its own rest offsets.
    pub fn new(skeleton: &Skeleton) -> Self {
        Self {
            parents: skeleton.parents().into(),
            offsets: skeleton.rest_offsets().iter().map(|o| o.to_array()).collect(),
            frames_per_sample: usize::MAX,
            device_offsets: None,
        }
    }

    /// The operation for a batch of `batch` frames made of `rest_offsets.dim(0)` samples of
    /// consecutive frames, each posed on its own `[joints, 3]` rest offsets.
    pub fn per_sample(skeleton: &Skeleton, rest_offsets: &Tensor, batch: usize) -> Result<Self> {
        let joints = skeleton.joint_count();
        let (samples, rest_joints, _) = rest_offsets.dims3()?;
        if rest_joints != joints || samples == 0 || !batch.is_multiple_of(samples) {
            return Err(ReprError::invalid(
                "per-sample rest offsets",
                format!("[samples, {joints}, 3] with samples dividing the {batch} frames"),
                format!("{:?}", rest_offsets.dims()),
            ));
        }
        if !rest_offsets.device().is_cpu() {
            return Ok(Self {
                parents: skeleton.parents().into(),
                offsets: Arc::from([]),
                frames_per_sample: batch / samples,
                device_offsets: Some(rest_offsets.to_dtype(DType::F32)?.contiguous()?),
            });
        }
        let values: Vec<f32> = rest_offsets.to_dtype(DType::F32)?.flatten_all()?.to_vec1()?;
        Ok(Self {
            parents: skeleton.parents().into(),
            offsets: values.chunks_exact(3).map(|o| [o[0], o[1], o[2]]).collect(),
            frames_per_sample: batch / samples,
            device_offsets: None,
        })
    }

    fn joints(&self) -> usize {
        self.parents.len()
    }

    /// The skeleton and bodies as the CUDA kernels read them.
    #[cfg(feature = "cuda")]
    fn bodies(&self) -> crate::fk_cuda::FkBodies<'_> {
        crate::fk_cuda::FkBodies {
            parents: &self.parents,
            offsets: &self.offsets,
            device_offsets: self.device_offsets.as_ref(),
            frames_per_sample: self.frames_per_sample,
        }
    }

    /// The rest offsets that frame `frame` of the batch is posed on.
    fn offsets_of_frame(&self, frame: usize) -> &[[f32; 3]] {
        let joints = self.joints();
        let sample = frame / self.frames_per_sample;
        &self.offsets[sample * joints..(sample + 1) * joints]
    }

    /// Forward pass of one frame: `local` is `joints * 9`, `out` is `joints * 12`.
    fn forward_frame<T: Real>(&self, local: &[T], root: &[T], offsets: &[[f32; 3]], out: &mut [T]) {
        for (joint, parent) in self.parents.iter().enumerate() {
            let rotation = mat(&local[joint * 9..joint * 9 + 9]);
            let (global, position) = match parent {
                None => (rotation, [root[0], root[1], root[2]]),
                Some(p) => {
                    let parent_rotation = mat(&out[p * 12..p * 12 + 9]);
                    let moved = mat_vec(&parent_rotation, &offsets[joint].map(T::from_f32));
                    let parent_position = &out[p * 12 + 9..p * 12 + 12];
                    let position = std::array::from_fn(|i| parent_position[i] + moved[i]);
                    (mat_mul(&parent_rotation, &rotation), position)
                }
            };
            out[joint * 12..joint * 12 + 9].copy_from_slice(&global);
            out[joint * 12 + 9..joint * 12 + 12].copy_from_slice(&position);
        }
    }

    /// Backward pass of one frame. `grad_rotations` (`joints * 9`) and `grad_positions`
    /// (`joints * 3`) are the output gradients (either may be absent); the gradients of the local
    /// rotations (`joints * 9`) are written to `grad_local_out`. The root's gradient is the sum
    /// of the position gradients over joints, computed by [`SumOverJoints`].
    #[allow(clippy::too_many_arguments)] // one frame's inputs, gradients and buffers
    fn backward_frame<T: Real>(
        &self,
        local: &[T],
        root: &[T],
        offsets: &[[f32; 3]],
        grad_rotations: Option<&[T]>,
        grad_positions: Option<&[T]>,
        scratch: &mut BackwardScratch<T>,
        grad_local_out: &mut [T],
    ) {
        let joints = self.joints();
        let BackwardScratch { packed, grad_global, grad_position } = scratch;
        self.forward_frame(local, root, offsets, packed);
        for j in 0..joints {
            grad_global[j] =
                grad_rotations.map_or([T::default(); 9], |g| mat(&g[j * 9..j * 9 + 9]));
            grad_position[j] =
                grad_positions.map_or([T::default(); 3], |g| std::array::from_fn(|i| g[j * 3 + i]));
        }
        for joint in (0..joints).rev() {
            let grad_local = match self.parents[joint] {
                None => grad_global[joint],
                Some(p) => {
                    let parent_rotation = mat(&packed[p * 12..p * 12 + 9]);
                    let rotation = mat(&local[joint * 9..joint * 9 + 9]);
                    let to_parent = mat_mul(&grad_global[joint], &transpose(&rotation));
                    let offset = offsets[joint].map(T::from_f32);
                    let moved = grad_position[joint];
                    for r in 0..3 {
                        for c in 0..3 {
                            grad_global[p][r * 3 + c] +=
                                to_parent[r * 3 + c] + moved[r] * offset[c];
                        }
                        grad_position[p][r] += moved[r];
                    }
                    mat_mul(&transpose(&parent_rotation), &grad_global[joint])
                }
            };
            grad_local_out[joint * 9..joint * 9 + 9].copy_from_slice(&grad_local);
        }
    }

    /// Forward pass of every frame (in parallel), keeping the positions or the rotations.
    fn forward_all<T: Real>(
        &self,
        local: &[T],
        root: &[T],
        keep: Output,
    ) -> candle_core::Result<Vec<T>> {
        let joints = self.joints();
        let batch = local.len() / (joints * 9);
        if local.len() != batch * joints * 9 || root.len() != batch * 3 {
            return Err(candle_core::Error::Msg(format!(
                "dex2hoi FK: {} local values and {} root values for {joints} joints",
                local.len(),
                root.len()
            )));
        }
        let samples = self.offsets.len() / joints;
        if self.frames_per_sample != usize::MAX && batch != samples * self.frames_per_sample {
            return Err(candle_core::Error::Msg(format!(
                "dex2hoi FK: {batch} frames for {samples} samples of {} frames",
                self.frames_per_sample
            )));
        }
        let width = keep.width();
        let mut out = vec![T::default(); batch * joints * width];
        out.par_chunks_mut(joints * width)
            .zip(local.par_chunks(joints * 9))
            .zip(root.par_chunks(3))
            .enumerate()
            .with_min_len(OP_FRAMES_PER_TASK)
            .for_each_init(
                || vec![T::default(); joints * 12],
                |packed, (frame, ((out, local), root))| {
                    self.forward_frame(local, root, self.offsets_of_frame(frame), packed);
                    for joint in 0..joints {
                        let from = joint * 12 + if keep == Output::Positions { 9 } else { 0 };
                        out[joint * width..(joint + 1) * width]
                            .copy_from_slice(&packed[from..from + width]);
                    }
                },
            );
        Ok(out)
    }

    /// Backward pass of every frame (in parallel) to the `[batch, joints * 9]` gradient of the
    /// local rotations.
    fn backward_all<T: Real>(&self, local: &[T], root: &[T], grad: &[T], of: Output) -> Vec<T> {
        let joints = self.joints();
        let batch = local.len() / (joints * 9);
        let mut grad_local = vec![T::default(); batch * joints * 9];
        grad_local
            .par_chunks_mut(joints * 9)
            .zip(local.par_chunks(joints * 9))
            .zip(root.par_chunks(3).zip(grad.par_chunks(joints * of.width())))
            .enumerate()
            .with_min_len(OP_FRAMES_PER_TASK)
            .for_each_init(
                || BackwardScratch::new(joints),
                |scratch, (frame, ((grad_local, local), (root, grad)))| {
                    let (rotations, positions) = match of {
                        Output::Positions => (None, Some(grad)),
                        Output::Rotations => (Some(grad), None),
                    };
                    let offsets = self.offsets_of_frame(frame);
                    self.backward_frame(
                        local, root, offsets, rotations, positions, scratch, grad_local,
                    );
                },
            );
        grad_local
    }
}

/// Per-task buffers of the backward pass.
struct BackwardScratch<T> {
    packed: Vec<T>,
    grad_global: Vec<M3<T>>,
    grad_position: Vec<[T; 3]>,
}

impl<T: Real> BackwardScratch<T> {
    fn new(joints: usize) -> Self {
        Self {
            packed: vec![T::default(); joints * 12],
            grad_global: vec![[T::default(); 9]; joints],
            grad_position: vec![[T::default(); 3]; joints],
        }
    }
}

/// Which output of forward kinematics an operation produces.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Output {
    Positions,
    Rotations,
}

impl Output {
    /// Numbers per joint.
    fn width(self) -> usize {
        match self {
            Self::Positions => 3,
            Self::Rotations => 9,
        }
    }
}

/// One output of forward kinematics as a candle operation: inputs `[batch, joints, 3, 3]`
/// local rotations and `[batch, 3]` roots; output `[batch, joints, 3]` positions or
/// `[batch, joints, 3, 3]` rotations (which do not depend on the roots).
#[derive(Debug, Clone)]
pub struct FkOutputOp {
    op: FkOp,
    output: Output,
}

/// Runs `$body` with `$t` bound to the storage's float type (`f32` or `f64`).
macro_rules! with_float {
    ($storage:expr, $t:ident => $body:expr) => {
        match $storage {
            CpuStorage::F64(_) => {
                type $t = f64;
                $t::into_storage($body)
            }
            _ => {
                type $t = f32;
                $t::into_storage($body)
            }
        }
    };
}

impl CustomOp2 for FkOutputOp {
    fn name(&self) -> &'static str {
        match self.output {
            Output::Positions => "dex2hoi-fk-positions",
            Output::Rotations => "dex2hoi-fk-rotations",
        }
    }

    fn cpu_fwd(
        &self,
        local_storage: &CpuStorage,
        local_layout: &Layout,
        root_storage: &CpuStorage,
        root_layout: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        let joints = self.op.joints();
        let batch = root_layout.shape().elem_count() / 3;
        let storage = with_float!(local_storage, T => self.op.forward_all(
            storage_values::<T>(local_storage, local_layout, "local rotations")?,
            storage_values::<T>(root_storage, root_layout, "root positions")?,
            self.output,
        )?);
        let shape = match self.output {
            Output::Positions => Shape::from((batch, joints, 3)),
            Output::Rotations => Shape::from((batch, joints, 3, 3)),
        };
        Ok((storage, shape))
    }

    #[cfg(feature = "cuda")]
    fn cuda_fwd(
        &self,
        local_storage: &candle_core::CudaStorage,
        local_layout: &Layout,
        root_storage: &candle_core::CudaStorage,
        root_layout: &Layout,
    ) -> candle_core::Result<(candle_core::CudaStorage, Shape)> {
        crate::fk_cuda::forward(
            &self.op.bodies(),
            (local_storage, local_layout),
            (root_storage, root_layout),
            self.output.width(),
        )
    }

    fn bwd(
        &self,
        local: &Tensor,
        root: &Tensor,
        _output: &Tensor,
        grad_output: &Tensor,
    ) -> candle_core::Result<(Option<Tensor>, Option<Tensor>)> {
        let grad = grad_output.contiguous()?;
        let backward = FkBackward { op: self.op.clone(), of: self.output };
        let grad_local = local.apply_op3_no_bwd(root, &grad, &backward)?;
        Ok(match self.output {
            // Every position moves with the root: its gradient is the sum over joints.
            Output::Positions => (Some(grad_local), Some(grad.apply_op1_no_bwd(&SumOverJoints)?)),
            Output::Rotations => (Some(grad_local), None),
        })
    }
}

/// `[batch, joints, 3]` to `[batch, 3]` by summing over joints (the root's gradient).
#[derive(Debug, Clone, Copy)]
struct SumOverJoints;

impl CustomOp1 for SumOverJoints {
    fn name(&self) -> &'static str {
        "dex2hoi-fk-sum-over-joints"
    }

    fn cpu_fwd(
        &self,
        storage: &CpuStorage,
        layout: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        let (batch, joints, _) = layout.shape().dims3()?;
        let summed = with_float!(storage, T => {
            let values = storage_values::<T>(storage, layout, "position gradient")?;
            values
                .chunks_exact(joints * 3)
                .flat_map(|frame| {
                    let mut sum = [T::default(); 3];
                    for joint in frame.chunks_exact(3) {
                        for i in 0..3 {
                            sum[i] += joint[i];
                        }
                    }
                    sum
                })
                .collect::<Vec<T>>()
        });
        Ok((summed, Shape::from((batch, 3))))
    }

    #[cfg(feature = "cuda")]
    fn cuda_fwd(
        &self,
        storage: &candle_core::CudaStorage,
        layout: &Layout,
    ) -> candle_core::Result<(candle_core::CudaStorage, Shape)> {
        crate::fk_cuda::sum_over_joints(storage, layout)
    }
}

/// The backward pass of an [`FkOutputOp`] as an operation of its own (not
/// differentiable itself): inputs local rotations, roots and the output gradient; output the
/// gradient of the local rotations, shaped like them.
#[derive(Debug, Clone)]
struct FkBackward {
    op: FkOp,
    of: Output,
}

impl CustomOp3 for FkBackward {
    fn name(&self) -> &'static str {
        "dex2hoi-fk-backward"
    }

    fn cpu_fwd(
        &self,
        local_storage: &CpuStorage,
        local_layout: &Layout,
        root_storage: &CpuStorage,
        root_layout: &Layout,
        grad_storage: &CpuStorage,
        grad_layout: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        let shape = local_layout.shape().clone();
        let storage = with_float!(local_storage, T => self.op.backward_all(
            storage_values::<T>(local_storage, local_layout, "local rotations")?,
            storage_values::<T>(root_storage, root_layout, "roots")?,
            storage_values::<T>(grad_storage, grad_layout, "output gradient")?,
            self.of,
        ));
        Ok((storage, shape))
    }

    #[cfg(feature = "cuda")]
    fn cuda_fwd(
        &self,
        local_storage: &candle_core::CudaStorage,
        local_layout: &Layout,
        root_storage: &candle_core::CudaStorage,
        root_layout: &Layout,
        grad_storage: &candle_core::CudaStorage,
        grad_layout: &Layout,
    ) -> candle_core::Result<(candle_core::CudaStorage, Shape)> {
        crate::fk_cuda::backward(
            &self.op.bodies(),
            (local_storage, local_layout),
            (root_storage, root_layout),
            (grad_storage, grad_layout),
            self.of.width(),
        )
    }
}
