//! The hand-relative object representation (paper Sec. 3.1, Eq. 2-4).
//!
//! Per object and frame, 18 numbers:
//! `[r_obj (6), delta_L (3), delta_R (3), p_G (3), alpha (3)]` — the object's rotation in the
//! 6D form, its position in the left and the right wrist frame
//! (`delta = R_w^T (p_obj - p_w)`, Eq. 3), its world position, and three mixture logits whose
//! softmax weighs the left-wrist, right-wrist and global estimates of the position (Eq. 4).
//!
//! [`mixture_targets`] turns hand-object proximity into the ground-truth mixture weights that
//! `L_mix` (Eq. 8) supervises.

use std::ops::Range;

use candle_core::{D, Tensor};
use glam::{Mat3, Vec3};

use crate::error::{ReprError, Result};
use crate::rotation::tensor::{leading_dims, leading_dims_matrix, rotate, rotate_inverse};
use crate::rotation::{matrix_to_sixd, sixd_to_matrix, tensor as rot_tensor};
use crate::sdf::MeshQuery;
use crate::skeleton::JointGroups;

/// Numbers per object and frame.
pub const OBJECT_FEATURE_SIZE: usize = 18;
/// Where the object's 6D rotation sits in the 18 numbers.
pub const ROTATION_RANGE: Range<usize> = 0..6;
/// The offset in the left wrist frame.
pub const LEFT_OFFSET_RANGE: Range<usize> = 6..9;
/// The offset in the right wrist frame.
pub const RIGHT_OFFSET_RANGE: Range<usize> = 9..12;
/// The global position.
pub const GLOBAL_POSITION_RANGE: Range<usize> = 12..15;
/// The mixture logits `alpha = [left, right, global]`.
pub const MIXTURE_RANGE: Range<usize> = 15..18;

/// A wrist's world position and rotation, from forward kinematics.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct WristPose {
    /// World position.
    pub position: Vec3,
    /// World rotation (local to world).
    pub rotation: Mat3,
}

/// Both wrists at one frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Wrists {
    /// The left wrist.
    pub left: WristPose,
    /// The right wrist.
    pub right: WristPose,
}

impl Wrists {
    /// Both wrists at a frame of forward kinematics, by the skeleton's groups.
    pub fn from_fk(fk: &crate::fk::FkOutput, frame: usize, groups: &JointGroups) -> Self {
        let wrist = |joint: usize| WristPose {
            position: fk.position(frame, joint),
            rotation: fk.rotation(frame, joint),
        };
        Self { left: wrist(groups.left_wrist), right: wrist(groups.right_wrist) }
    }
}

/// An object's pose: the rotation and position of its bounding-box-centred frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ObjectPose {
    /// Rotation (object to world).
    pub rotation: Mat3,
    /// World position of the object frame's origin.
    pub position: Vec3,
}

/// The 18 numbers of one object at one frame, by name.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HandRelativeObject {
    /// `r_obj`: the object rotation in the 6D form (first two rows).
    pub rotation_6d: [f32; 6],
    /// `delta_L`: the object position in the left wrist frame.
    pub left_offset: Vec3,
    /// `delta_R`: the object position in the right wrist frame.
    pub right_offset: Vec3,
    /// `p_G`: the object position in world coordinates.
    pub global_position: Vec3,
    /// `alpha`: logits of the left, right and global branches.
    pub mixture_logits: [f32; 3],
}

/// `delta = R_w^T (p_obj - p_w)` (Eq. 3).
pub fn wrist_offset(object_position: Vec3, wrist: WristPose) -> Vec3 {
    wrist.rotation.transpose() * (object_position - wrist.position)
}

/// A numerically stable softmax of three logits.
pub fn softmax3(logits: [f32; 3]) -> [f32; 3] {
    let max = logits[0].max(logits[1]).max(logits[2]);
    let e = logits.map(|l| (l - max).exp());
    let sum = e[0] + e[1] + e[2];
    e.map(|x| x / sum)
}

impl HandRelativeObject {
    /// Encodes an object pose against the two wrists with the given mixture logits (Eq. 2-3).
    pub fn encode(object: ObjectPose, wrists: Wrists, mixture_logits: [f32; 3]) -> Self {
        Self {
            rotation_6d: matrix_to_sixd(object.rotation),
            left_offset: wrist_offset(object.position, wrists.left),
            right_offset: wrist_offset(object.position, wrists.right),
            global_position: object.position,
            mixture_logits,
        }
    }

    /// `[w_L, w_R, w_G] = softmax(alpha)`.
    pub fn mixture_weights(&self) -> [f32; 3] {
        softmax3(self.mixture_logits)
    }

    /// The object position through the softmax mixture (Eq. 4):
    /// `w_L (p_L + R_L delta_L) + w_R (p_R + R_R delta_R) + w_G p_G`.
    pub fn decode_position(&self, wrists: Wrists) -> Vec3 {
        let [w_left, w_right, w_global] = self.mixture_weights();
        let from_left = wrists.left.position + wrists.left.rotation * self.left_offset;
        let from_right = wrists.right.position + wrists.right.rotation * self.right_offset;
        from_left * w_left + from_right * w_right + self.global_position * w_global
    }

    /// The object rotation (Gram-Schmidt decode of the 6D form).
    pub fn decode_rotation(&self) -> Mat3 {
        sixd_to_matrix(self.rotation_6d)
    }

    /// The 18 numbers in feature order.
    pub fn to_array(&self) -> [f32; OBJECT_FEATURE_SIZE] {
        let mut out = [0.0; OBJECT_FEATURE_SIZE];
        out[ROTATION_RANGE].copy_from_slice(&self.rotation_6d);
        out[LEFT_OFFSET_RANGE].copy_from_slice(&self.left_offset.to_array());
        out[RIGHT_OFFSET_RANGE].copy_from_slice(&self.right_offset.to_array());
        out[GLOBAL_POSITION_RANGE].copy_from_slice(&self.global_position.to_array());
        out[MIXTURE_RANGE].copy_from_slice(&self.mixture_logits);
        out
    }

    /// Reads the 18 numbers back.
    pub fn from_slice(values: &[f32]) -> Result<Self> {
        if values.len() != OBJECT_FEATURE_SIZE {
            return Err(ReprError::invalid(
                "object features",
                format!("{OBJECT_FEATURE_SIZE} numbers"),
                values.len(),
            ));
        }
        let v3 = |r: Range<usize>| Vec3::from_slice(&values[r]);
        Ok(Self {
            rotation_6d: values[ROTATION_RANGE].try_into().expect("6 numbers"),
            left_offset: v3(LEFT_OFFSET_RANGE),
            right_offset: v3(RIGHT_OFFSET_RANGE),
            global_position: v3(GLOBAL_POSITION_RANGE),
            mixture_logits: values[MIXTURE_RANGE].try_into().expect("3 numbers"),
        })
    }
}

/// How hand proximity becomes mixture targets.
///
/// The rule: a hand *holds* the object at a frame when the nearest of its joints (wrist and
/// every finger joint) is within [`contact_distance`](Self::contact_distance) of the object's
/// surface (signed distance, so penetration counts as contact). Left only gives `(1, 0, 0)`,
/// right only `(0, 1, 0)`, both `(0.5, 0.5, 0)`, neither `(0, 0, 1)`. With
/// [`free_at_rest`](Self::free_at_rest) (off by default), a frame on which the object stands
/// still on its support ([`resting_frames`]) counts as neither hand holding it, touched or not.
/// The one-hot targets are then averaged over a centred window of `2 * smoothing_radius + 1`
/// frames (shrunk at the ends), so that a hand-over becomes a ramp of a few frames instead of a
/// jump the model cannot fit.
/// Finally each weight is lifted to at least `probability_floor` (and the three renormalised)
/// and stored as centred logarithms: `softmax` of the stored logits gives the weights back
/// exactly, and the logits stay finite (about -6.9 for the floor of 1e-3).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MixtureTargetConfig {
    /// Distance in metres under which a hand joint counts as touching. Default 0.03 m: joints sit
    /// inside the fingers, about 1 cm under the skin, and grasp annotations in GRAB and HOIDiNi
    /// use a few centimetres; 3 cm catches real grasps without flagging a hand hovering nearby.
    pub contact_distance: f32,
    /// Half-width of the temporal smoothing window in frames. Default 2 (0.1 s at 20 fps).
    pub smoothing_radius: usize,
    /// The least weight a branch gets before the logarithm. Default 1e-3.
    pub probability_floor: f32,
    /// Whether an object standing still on its support is held by no hand, even with a hand
    /// on it (steadied, about to be lifted, just put down): the global branch then places it
    /// exactly, and a hand that moves while touching it does not carry it off the table
    /// through the hand-relative decoding. Beyond the paper, which decides by proximity alone.
    /// Default false, the paper's rule: a model fine-tuned on such targets lifted the vessel of
    /// a pour half as often, but its hands went into the objects they touch on 8% of frames
    /// instead of 5% (`docs/results/long-generations.md`, "Steadied objects held by no hand").
    pub free_at_rest: bool,
}

impl Default for MixtureTargetConfig {
    fn default() -> Self {
        Self {
            contact_distance: 0.03,
            smoothing_radius: 2,
            probability_floor: 1e-3,
            free_at_rest: false,
        }
    }
}

/// How far (metres) an object's lowest point may be from its support's height and still stand
/// on it ([`resting_frames`]).
pub const REST_HEIGHT_M: f32 = 0.01;
/// How far (metres) an object may move to a neighbouring frame and still stand still.
pub const REST_STEP_M: f32 = 0.002;
/// How much an object may turn to a neighbouring frame and still stand still: the Frobenius
/// norm of the difference of the rotation matrices (0.01, about 0.4 degrees).
pub const REST_TURN: f32 = 0.01;

/// Per frame, whether the object stands still on its support: its lowest point within
/// [`REST_HEIGHT_M`] of the height it had on the first frame (where it stood at the start),
/// and neither its position nor its rotation changing to the frames before and after by more
/// than [`REST_STEP_M`] and [`REST_TURN`].
pub fn resting_frames(mesh: &MeshQuery, poses: &[ObjectPose]) -> Vec<bool> {
    let Some(first) = poses.first() else {
        return Vec::new();
    };
    let support = mesh.lowest_height(first.rotation, first.position);
    let still = |a: &ObjectPose, b: &ObjectPose| {
        let turn =
            (0..3).map(|c| (a.rotation.col(c) - b.rotation.col(c)).length_squared()).sum::<f32>();
        a.position.distance(b.position) <= REST_STEP_M && turn.sqrt() <= REST_TURN
    };
    (0..poses.len())
        .map(|t| {
            let pose = &poses[t];
            let on_support =
                (mesh.lowest_height(pose.rotation, pose.position) - support).abs() <= REST_HEIGHT_M;
            let before = t.checked_sub(1).is_none_or(|s| still(&poses[s], pose));
            let after = poses.get(t + 1).is_none_or(|next| still(pose, next));
            on_support && before && after
        })
        .collect()
}

/// The nearest signed distance from world points (a hand's joints) to an object's surface: the
/// points are moved into the object frame, `R^T (p - t)`, and queried against the mesh.
/// `f32::INFINITY` when there are no points.
pub fn nearest_signed_distance(
    object_mesh: &MeshQuery,
    object: ObjectPose,
    points: impl IntoIterator<Item = Vec3>,
) -> f32 {
    let to_object = object.rotation.transpose();
    points
        .into_iter()
        .map(|p| object_mesh.signed_distance(to_object * (p - object.position)))
        .fold(f32::INFINITY, f32::min)
}

/// The nearest signed distance of each hand (wrist and finger joints, from the skeleton's
/// groups) to an object at one frame: `(left, right)`, the input of [`mixture_targets`].
pub fn hand_distances(
    object_mesh: &MeshQuery,
    object: ObjectPose,
    joint_positions: &[Vec3],
    groups: &JointGroups,
) -> (f32, f32) {
    let hand = |joints: &[usize]| {
        nearest_signed_distance(object_mesh, object, joints.iter().map(|&j| joint_positions[j]))
    };
    (hand(&groups.left_hand), hand(&groups.right_hand))
}

/// Ground-truth mixture logits per frame from the nearest signed distance of each hand to the
/// object (see [`MixtureTargetConfig`] for the rule).
pub fn mixture_targets(
    left_hand_distance: &[f32],
    right_hand_distance: &[f32],
    config: &MixtureTargetConfig,
) -> Result<Vec<[f32; 3]>> {
    mixture_targets_at_rest(left_hand_distance, right_hand_distance, &[], config)
}

/// [`mixture_targets`] with, per frame, whether the object stands still on its support
/// ([`resting_frames`]; empty: never), which [`MixtureTargetConfig::free_at_rest`] reads.
pub fn mixture_targets_at_rest(
    left_hand_distance: &[f32],
    right_hand_distance: &[f32],
    resting: &[bool],
    config: &MixtureTargetConfig,
) -> Result<Vec<[f32; 3]>> {
    if !resting.is_empty() && resting.len() != left_hand_distance.len() {
        return Err(ReprError::invalid(
            "resting frames",
            "one flag per frame, or none",
            format!("{} flags for {} frames", resting.len(), left_hand_distance.len()),
        ));
    }
    if left_hand_distance.len() != right_hand_distance.len() {
        return Err(ReprError::invalid(
            "hand distances",
            "one left and one right distance per frame",
            format!("{} left, {} right", left_hand_distance.len(), right_hand_distance.len()),
        ));
    }
    let floor = config.probability_floor;
    let floor_ok = floor > 0.0 && floor < 1.0 / 3.0;
    if !floor_ok || !config.contact_distance.is_finite() {
        return Err(ReprError::invalid(
            "mixture target config",
            "a probability floor in (0, 1/3) and a finite contact distance",
            format!("{config:?}"),
        ));
    }
    let one_hot: Vec<[f32; 3]> = left_hand_distance
        .iter()
        .zip(right_hand_distance)
        .enumerate()
        .map(|(t, (&left, &right))| {
            if config.free_at_rest && resting.get(t).copied().unwrap_or(false) {
                return [0.0, 0.0, 1.0];
            }
            // NaN distances (no object) compare false: no contact.
            let left = left <= config.contact_distance;
            let right = right <= config.contact_distance;
            match (left, right) {
                (true, false) => [1.0, 0.0, 0.0],
                (false, true) => [0.0, 1.0, 0.0],
                (true, true) => [0.5, 0.5, 0.0],
                (false, false) => [0.0, 0.0, 1.0],
            }
        })
        .collect();
    let frames = one_hot.len();
    let radius = config.smoothing_radius;
    Ok((0..frames)
        .map(|t| {
            let window = t.saturating_sub(radius)..(t + radius + 1).min(frames);
            let count = window.len() as f32;
            let mut mean = [0.0f32; 3];
            for w in &one_hot[window] {
                for k in 0..3 {
                    mean[k] += w[k] / count;
                }
            }
            let lifted = mean.map(|w| w.max(floor));
            let sum: f32 = lifted.iter().sum();
            let logs = lifted.map(|w| (w / sum).ln());
            let centre = logs.iter().sum::<f32>() / 3.0;
            logs.map(|l| l - centre)
        })
        .collect())
}

/// A numerically stable softmax over the last dimension with a backward pass (candle's fused
/// `softmax_last_dim` has none). The subtracted maximum is a constant for the gradient, which
/// does not change the result.
pub fn tensor_softmax(logits: &Tensor) -> Result<Tensor> {
    let max = logits.max_keepdim(D::Minus1)?.detach();
    let exp = logits.broadcast_sub(&max)?.exp()?;
    let sum = exp.sum_keepdim(D::Minus1)?;
    Ok(exp.broadcast_div(&sum)?)
}

fn check_features(features: &Tensor) -> Result<Vec<usize>> {
    leading_dims(features, OBJECT_FEATURE_SIZE, "object features")
}

/// `softmax(alpha)` of object features.
///
/// # Shapes
/// - `features`: `[..., 18]`
/// - returns: `[..., 3]` (left, right, global)
pub fn tensor_mixture_weights(features: &Tensor) -> Result<Tensor> {
    check_features(features)?;
    tensor_softmax(&features.narrow(D::Minus1, MIXTURE_RANGE.start, 3)?)
}

/// The object rotation of object features.
///
/// # Shapes
/// - `features`: `[..., 18]`
/// - returns: `[..., 3, 3]`
pub fn tensor_decode_rotation(features: &Tensor) -> Result<Tensor> {
    check_features(features)?;
    rot_tensor::sixd_to_matrix(&features.narrow(D::Minus1, ROTATION_RANGE.start, 6)?)
}

/// Wrist poses as tensors, for the batched decode.
#[derive(Debug, Clone)]
pub struct TensorWrists {
    /// Left wrist positions `[..., 3]`.
    pub left_position: Tensor,
    /// Left wrist rotations `[..., 3, 3]`.
    pub left_rotation: Tensor,
    /// Right wrist positions `[..., 3]`.
    pub right_position: Tensor,
    /// Right wrist rotations `[..., 3, 3]`.
    pub right_rotation: Tensor,
}

impl TensorWrists {
    /// Picks the wrists out of FK outputs.
    ///
    /// # Shapes
    /// - `positions`: `[..., joints, 3]`; `rotations`: `[..., joints, 3, 3]`
    /// - fields: `[..., 3]` and `[..., 3, 3]`
    pub fn from_fk(
        positions: &Tensor,
        rotations: &Tensor,
        left_wrist: usize,
        right_wrist: usize,
    ) -> Result<Self> {
        let joint_axis = positions.rank() - 2;
        let pick = |t: &Tensor, j: usize| -> Result<Tensor> {
            Ok(t.narrow(joint_axis, j, 1)?.squeeze(joint_axis)?)
        };
        Ok(Self {
            left_position: pick(positions, left_wrist)?,
            left_rotation: pick(rotations, left_wrist)?,
            right_position: pick(positions, right_wrist)?,
            right_rotation: pick(rotations, right_wrist)?,
        })
    }
}

/// The object position through the softmax mixture of Eq. 4, differentiable in the features
/// and in the wrists.
///
/// # Shapes
/// - `features`: `[..., 18]`
/// - `wrists`: positions `[..., 3]`, rotations `[..., 3, 3]`, same leading dimensions
/// - returns: `[..., 3]`
pub fn tensor_decode_position(features: &Tensor, wrists: &TensorWrists) -> Result<Tensor> {
    let leading = check_features(features)?;
    for (what, t) in [
        ("left wrist position", &wrists.left_position),
        ("right wrist position", &wrists.right_position),
    ] {
        if leading_dims(t, 3, what)? != leading {
            return Err(ReprError::invalid(
                what,
                format!("leading dimensions {leading:?}"),
                format!("{:?}", t.dims()),
            ));
        }
    }
    for (what, t) in [
        ("left wrist rotation", &wrists.left_rotation),
        ("right wrist rotation", &wrists.right_rotation),
    ] {
        if leading_dims_matrix(t, what)? != leading {
            return Err(ReprError::invalid(
                what,
                format!("leading dimensions {leading:?}"),
                format!("{:?}", t.dims()),
            ));
        }
    }
    let weights = tensor_mixture_weights(features)?;
    let weight = |k: usize| weights.narrow(D::Minus1, k, 1);
    let part = |r: Range<usize>| features.narrow(D::Minus1, r.start, r.len());
    let from_left =
        (&wrists.left_position + rotate(&wrists.left_rotation, &part(LEFT_OFFSET_RANGE)?)?)?;
    let from_right =
        (&wrists.right_position + rotate(&wrists.right_rotation, &part(RIGHT_OFFSET_RANGE)?)?)?;
    let global = part(GLOBAL_POSITION_RANGE)?;
    let position = (from_left.broadcast_mul(&weight(0)?)?
        + from_right.broadcast_mul(&weight(1)?)?)?
    .add(&global.broadcast_mul(&weight(2)?)?)?;
    Ok(position)
}

/// The wrist offsets of Eq. 3 for object positions, `R_w^T (p_obj - p_w)`.
///
/// # Shapes
/// - `object_position`, `wrist_position`: `[..., 3]`; `wrist_rotation`: `[..., 3, 3]`
/// - returns: `[..., 3]`
pub fn tensor_wrist_offset(
    object_position: &Tensor,
    wrist_position: &Tensor,
    wrist_rotation: &Tensor,
) -> Result<Tensor> {
    rotate_inverse(wrist_rotation, &(object_position - wrist_position)?)
}
