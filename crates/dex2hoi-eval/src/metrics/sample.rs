//! One motion with its objects as the physical metrics read it, and the checks of its arrays.

use dex2hoi_data::MAX_OBJECTS;
use dex2hoi_repr::{MeshQuery, ObjectPose, Skeleton};
use glam::{Mat3, Vec3};

use crate::error::{EvalError, Result};

/// One motion with its objects, borrowed, as the physical metrics read it.
#[derive(Debug, Clone, Copy)]
pub struct MotionSample<'a> {
    /// The skeleton of `joints` (its groups name the hand and foot joints).
    pub skeleton: &'a Skeleton,
    /// `[T, J, 3]` joint positions in metres, Y up, floor at `y = 0`.
    pub joints: &'a [f32],
    /// `[T, 2, 3, 3]` object rotations (object to world), each matrix **row-major** as
    /// [`ProcessedSequence::object_rotations`](dex2hoi_data::features::ProcessedSequence::object_rotations) stores them.
    pub object_rotations: &'a [f32],
    /// `[T, 2, 3]` object positions (the origin of the mesh's frame in the world).
    pub object_positions: &'a [f32],
    /// Which object slots hold an object.
    pub present: [bool; MAX_OBJECTS],
    /// The mesh of each present slot, in its own frame (`None` for an empty slot).
    pub objects: [Option<&'a MeshQuery>; MAX_OBJECTS],
    /// `[T, 2, 3]` mixture weights (left, right, global) per slot, or logits (only their
    /// argmax is used); `None` for motions without a model, such as the ground truth.
    pub mixture_weights: Option<&'a [f32]>,
}

impl MotionSample<'_> {
    /// Checks every array against the skeleton and returns the number of frames `T`.
    ///
    /// # Errors
    /// No frames, lengths that do not match `[T, J, 3]`, `[T, 2, 3, 3]`, `[T, 2, 3]`, a present
    /// slot without a mesh, non-finite numbers.
    pub fn frames(&self) -> Result<usize> {
        let joints = self.skeleton.joint_count();
        let frames = joint_frames(self.joints, joints, "sample joint positions")?;
        let arrays = [
            ("object rotations", self.object_rotations, MAX_OBJECTS * 9, "[T, 2, 3, 3]"),
            ("object positions", self.object_positions, MAX_OBJECTS * 3, "[T, 2, 3]"),
        ];
        for (what, values, per_frame, shape) in arrays {
            check_array(what, values, frames * per_frame, shape, frames)?;
        }
        if let Some(weights) = self.mixture_weights {
            check_array("mixture weights", weights, frames * MAX_OBJECTS * 3, "[T, 2, 3]", frames)?;
        }
        for slot in 0..MAX_OBJECTS {
            if self.present[slot] && self.objects[slot].is_none() {
                return Err(EvalError::invalid(
                    "motion sample objects",
                    "a mesh for every present slot",
                    format!("slot {slot} present without a mesh"),
                ));
            }
        }
        Ok(frames)
    }

    /// The position of joint `j` at frame `t` (indices already checked).
    pub(super) fn joint(&self, t: usize, j: usize) -> Vec3 {
        let base = (t * self.skeleton.joint_count() + j) * 3;
        Vec3::from_slice(&self.joints[base..base + 3])
    }

    /// The pose of slot `slot` at frame `t` (indices already checked).
    pub(super) fn object_pose(&self, t: usize, slot: usize) -> ObjectPose {
        let base = (t * MAX_OBJECTS + slot) * 9;
        let rotation = rotation_from_rows(&self.object_rotations[base..base + 9]);
        let base = (t * MAX_OBJECTS + slot) * 3;
        ObjectPose { rotation, position: Vec3::from_slice(&self.object_positions[base..base + 3]) }
    }

    /// The present slots with their meshes.
    pub(super) fn present_objects(&self) -> impl Iterator<Item = (usize, &MeshQuery)> + '_ {
        (0..MAX_OBJECTS)
            .filter(|&slot| self.present[slot])
            .filter_map(|slot| self.objects[slot].map(|mesh| (slot, mesh)))
    }
}

/// The number of frames of `[T, J, 3]` joint positions, checked (at least one frame, finite).
pub(super) fn joint_frames(joints: &[f32], joint_count: usize, what: &str) -> Result<usize> {
    let per_frame = joint_count * 3;
    if per_frame == 0 || joints.is_empty() || !joints.len().is_multiple_of(per_frame) {
        return Err(EvalError::invalid(
            what,
            format!("[T, {joint_count}, 3] with T >= 1"),
            format!("{} numbers", joints.len()),
        ));
    }
    let frames = joints.len() / per_frame;
    check_array(what, joints, frames * per_frame, "[T, J, 3]", frames)?;
    Ok(frames)
}

/// Checks an array's length and that it is finite.
pub(super) fn check_array(
    what: &str,
    values: &[f32],
    expected: usize,
    shape: &str,
    frames: usize,
) -> Result<()> {
    if values.len() != expected {
        return Err(EvalError::invalid(
            what,
            format!("{shape} with T = {frames} ({expected} numbers)"),
            format!("{} numbers", values.len()),
        ));
    }
    if let Some(i) = values.iter().position(|v| !v.is_finite()) {
        return Err(EvalError::invalid(what, "finite numbers", format!("{} at {i}", values[i])));
    }
    Ok(())
}

/// A rotation from its 9 numbers stored row-major, as object rotations are
/// ([`ProcessedSequence`](dex2hoi_data::features::ProcessedSequence), [`MotionSample`]).
///
/// # Panics
/// Fewer than 9 numbers (callers slice exactly 9).
pub(crate) fn rotation_from_rows(rows: &[f32]) -> Mat3 {
    Mat3::from_cols_slice(rows).transpose()
}
