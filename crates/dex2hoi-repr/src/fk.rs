//! Forward kinematics: local joint rotations and a root position to global joint positions and
//! rotations, `G_i = G_parent(i) [R_i | offset_i]` (REFERENCE section 3). The CPU version works
//! on `glam` types; [`tensor_forward_kinematics`] is the batched, differentiable candle version
//! that the training losses go through (paper Sec. 3.3).
//!
//! The root position is the world position of the root joint (the pelvis), not a displacement
//! from the rest pose: the identity pose with `root = rest_offsets[0]` gives the rest joints.

use candle_core::{DType, Tensor};
use glam::{Mat3, Vec3};
use rayon::prelude::*;

use crate::error::{ReprError, Result};
use crate::rotation::tensor::{leading_dims, leading_dims_matrix, require_float, rotate};
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
    positions
        .par_chunks_mut(joints)
        .zip(rotations.par_chunks_mut(joints))
        .zip(local_rotations.par_chunks(joints))
        .zip(root_positions.par_iter())
        .for_each(|(((positions, rotations), local), root)| {
            forward_kinematics_frame(skeleton, local, *root, positions, rotations);
        });
    Ok(FkOutput { frames, joints, positions, rotations })
}

/// The rest offsets of a skeleton as a `[J, 3]` tensor.
pub fn rest_offsets_tensor(
    skeleton: &Skeleton,
    dtype: DType,
    device: &candle_core::Device,
) -> Result<Tensor> {
    let flat: Vec<f32> = skeleton.rest_offsets().iter().flat_map(|v| v.to_array()).collect();
    Ok(Tensor::from_vec(flat, (skeleton.joint_count(), 3), device)?.to_dtype(dtype)?)
}

/// Batched, differentiable forward kinematics.
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
    let batch: usize = leading.iter().product();
    let dtype = local_rotations.dtype();
    let device = local_rotations.device();
    // Joint-major so that each joint's rotations are one contiguous block.
    let local = local_rotations.reshape((batch, joints, 3, 3))?.transpose(0, 1)?.contiguous()?;
    let root = root_positions.reshape((batch, 3))?.to_dtype(dtype)?;
    let offsets = rest_offsets_tensor(skeleton, dtype, device)?;
    let mut rotations: Vec<Tensor> = Vec::with_capacity(joints);
    let mut positions: Vec<Tensor> = Vec::with_capacity(joints);
    for (joint, parent) in skeleton.parents().iter().enumerate() {
        let local_rotation = local.get(joint)?;
        match parent {
            None => {
                rotations.push(local_rotation);
                positions.push(root.clone());
            }
            Some(p) => {
                let parent_rotation = &rotations[*p];
                let offset = offsets.get(joint)?.reshape((1, 3))?;
                let position = (&positions[*p] + rotate(parent_rotation, &offset)?)?;
                rotations.push(parent_rotation.matmul(&local_rotation)?);
                positions.push(position);
            }
        }
    }
    let mut position_shape = leading.clone();
    position_shape.extend([joints, 3]);
    let mut rotation_shape = leading;
    rotation_shape.extend([joints, 3, 3]);
    let positions = Tensor::stack(&positions, 1)?.reshape(position_shape)?;
    let rotations = Tensor::stack(&rotations, 1)?.reshape(rotation_shape)?;
    Ok((positions, rotations))
}
