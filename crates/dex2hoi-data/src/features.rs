//! The feature pipeline (paper Sec. 3.1): from a raw [`Sequence`] to the per-frame features of
//! both streams and the targets the losses and metrics need.
//!
//! Per frame the body part is `[h (6J), r (3)]`: each joint's local rotation in the 6D form and
//! the root's displacement from the first frame's pelvis. Each object slot `s` adds
//! `o^s (18)`, the hand-relative object representation (Eq. 2-4) with ground-truth mixture
//! logits. Stream A is `[h, r, o^A]`, stream B `[h, r, o^B]`. [`crate::layout`] owns the
//! widths, the slices and the reshapes between this frame-major layout and the model's streams.
//!
//! Every sequence is first put in a canonical frame: turned about +Y so that the root faces +Z
//! at the first frame, and moved horizontally so that the first frame's pelvis is above the
//! origin (its height is kept, so the floor stays at `y = 0`).

use glam::{Mat3, Vec3};
use rayon::prelude::*;

use dex2hoi_repr::object_repr::{
    HandRelativeObject, MixtureTargetConfig, ObjectPose, Wrists, hand_distances,
    mixture_targets_at_rest, resting_frames,
};
use dex2hoi_repr::rotation::{axis_angle_to_matrix, matrix_to_sixd};
use dex2hoi_repr::{MeshQuery, Skeleton, forward_kinematics};

use crate::error::{DataError, Result};
use crate::layout::{FeatureLayout, slot_range};
use crate::sequence::{MAX_OBJECTS, Sequence};

pub use crate::processed::{ObjectAsset, ProcessedSequence, SURFACE_SAMPLES};

pub use dex2hoi_repr::object_repr::OBJECT_FEATURE_SIZE;

/// Hand-joint distance to an absent object (metres): far beyond every threshold.
pub const ABSENT_DISTANCE: f32 = 10.0;

/// Numbers per frame of the body part `[h, r]` for `joints` joints
/// ([`FeatureLayout::body_width`]).
pub fn body_feature_size(joints: usize) -> usize {
    FeatureLayout::new(joints).body_width()
}

/// Numbers per frame of one stream `[h, r, o]` ([`FeatureLayout::stream_width`]).
pub fn stream_feature_size(joints: usize) -> usize {
    FeatureLayout::new(joints).stream_width()
}

/// Which rule draws the mixture targets (the weights of Eq. 4) from the data; a dataset's
/// manifest records it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum MixtureTargets {
    /// The paper's rule: a hand within 3 cm of the object's surface holds it.
    Proximity,
    /// The paper's rule, except that an object standing still on its support is held by no
    /// hand, touched or not ([`MixtureTargetConfig::free_at_rest`]).
    FreeAtRest,
}

impl Default for MixtureTargets {
    /// [`MixtureTargetConfig`]'s default.
    fn default() -> Self {
        TargetConfig::default().mixture_targets()
    }
}

impl MixtureTargets {
    /// The rule datasets of format 4 and older were made with, whose manifests do not say.
    pub fn of_older_formats() -> Self {
        Self::Proximity
    }
}

/// Thresholds of the targets.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TargetConfig {
    /// Mixture-target rule (a hand holds an object within 3 cm, smoothed over 5 frames).
    pub mixture: MixtureTargetConfig,
    /// A hand is in contact with an object when one of its joints is within this distance of
    /// the surface. Default 0.05 m, the CHOIS contact threshold used by the contact metrics.
    pub hand_contact_distance: f32,
    /// Foot joints below these heights (ankle, toe; InterGen's 0.12 m and 0.05 m) ...
    pub foot_height: [f32; 2],
    /// ... that move less than this per frame (metres) are in contact (MDM's 0.01).
    pub foot_speed: f32,
}

impl TargetConfig {
    /// The default thresholds with the mixture targets drawn by `rule`.
    pub fn with_mixture_targets(rule: MixtureTargets) -> Self {
        let mut config = Self::default();
        config.mixture.free_at_rest = rule == MixtureTargets::FreeAtRest;
        config
    }

    /// The rule the mixture targets are drawn by.
    pub fn mixture_targets(&self) -> MixtureTargets {
        if self.mixture.free_at_rest {
            MixtureTargets::FreeAtRest
        } else {
            MixtureTargets::Proximity
        }
    }
}

impl Default for TargetConfig {
    fn default() -> Self {
        Self {
            mixture: MixtureTargetConfig::default(),
            hand_contact_distance: dex2hoi_repr::CONTACT_RADIUS_M,
            foot_height: [0.12, 0.05],
            foot_speed: 0.01,
        }
    }
}

impl ProcessedSequence {
    /// The sequence's own body ([`ProcessedSequence::skeleton`]) and its stored features
    /// decoded on it ([`decode_features`]).
    pub fn decode(
        &self,
        topology: &Skeleton,
        decoding: ObjectDecoding,
    ) -> Result<(Skeleton, DecodedMotion)> {
        let body = self.skeleton(topology)?;
        let motion = decode_features(
            &body,
            &self.body,
            &self.objects,
            self.object_present,
            self.root_start,
            decoding,
        )?;
        Ok((body, motion))
    }
}

/// The yaw (about +Y) that turns the root's forward direction at frame 0 to +Z.
fn facing_yaw(root_rotation: Mat3) -> f32 {
    let forward = root_rotation * Vec3::Z;
    forward.x.atan2(forward.z)
}

/// Puts a sequence in the canonical frame (facing +Z, first pelvis above the origin).
pub fn canonicalise(sequence: &Sequence) -> Sequence {
    let mut out = sequence.clone();
    let joints = sequence.skeleton.joint_count();
    let turn = axis_angle_to_matrix(Vec3::Y * -facing_yaw(sequence.local_rotations[0]));
    let start = sequence.root_positions[0];
    let shift = Vec3::new(start.x, 0.0, start.z);
    let to_canonical = |p: Vec3| turn * (p - shift);
    for frame in 0..sequence.frames() {
        out.local_rotations[frame * joints] = turn * sequence.local_rotations[frame * joints];
        out.root_positions[frame] = to_canonical(sequence.root_positions[frame]);
    }
    for object in &mut out.objects {
        for (rotation, translation) in object.rotations.iter_mut().zip(&mut object.translations) {
            *rotation = turn * *rotation;
            *translation = to_canonical(*translation);
        }
    }
    out
}

/// Extracts features and targets. `object_queries` holds a signed-distance query of each
/// object's canonical mesh, by slot; the sequence is validated and canonicalised first.
pub fn process_sequence(
    sequence: &Sequence,
    object_queries: &[&MeshQuery],
    config: &TargetConfig,
) -> Result<ProcessedSequence> {
    sequence.validate()?;
    if object_queries.len() != sequence.objects.len() {
        return Err(DataError::invalid(
            &sequence.source_id,
            format!("one mesh query per object ({})", sequence.objects.len()),
            object_queries.len(),
        ));
    }
    let sequence = canonicalise(sequence);
    let skeleton: &Skeleton = &sequence.skeleton;
    let frames = sequence.frames();
    let joints = skeleton.joint_count();
    let groups = skeleton.groups();
    let fk = forward_kinematics(skeleton, &sequence.local_rotations, &sequence.root_positions)?;
    let root_start = sequence.root_positions[0];

    let layout = FeatureLayout::new(joints);
    let mut body = vec![0.0f32; frames * layout.body_width()];
    body.par_chunks_mut(layout.body_width()).enumerate().for_each(|(t, row)| {
        for j in 0..joints {
            row[layout.joint_rotation_range(j)]
                .copy_from_slice(&matrix_to_sixd(sequence.local_rotations[t * joints + j]));
        }
        row[layout.root_range()]
            .copy_from_slice(&(sequence.root_positions[t] - root_start).to_array());
    });

    let hand_joints: Vec<usize> =
        groups.left_hand.iter().chain(&groups.right_hand).copied().collect();
    let hand_count = hand_joints.len();
    let wrists = |t: usize| Wrists::from_fk(&fk, t, groups);
    let mut objects = vec![0.0f32; frames * layout.objects_width()];
    let mut hand_distance = vec![ABSENT_DISTANCE; frames * MAX_OBJECTS * hand_count];
    let mut hand_contact = vec![0.0f32; frames * MAX_OBJECTS * 2];
    let mut object_rotations = vec![0.0f32; frames * MAX_OBJECTS * 9];
    let mut object_positions = vec![0.0f32; frames * MAX_OBJECTS * 3];
    let mut object_present = [false; MAX_OBJECTS];
    let mut object_names: [Option<String>; MAX_OBJECTS] = [None, None];
    for t in 0..frames {
        for slot in 0..MAX_OBJECTS {
            let rotation = sequence.objects.get(slot).map_or(Mat3::IDENTITY, |o| o.rotations[t]);
            object_rotations[slot_range(t, slot, 9)]
                .copy_from_slice(&rotation.transpose().to_cols_array());
        }
    }
    for (slot, (object, query)) in sequence.objects.iter().zip(object_queries).enumerate() {
        object_present[slot] = true;
        object_names[slot] = Some(object.name.clone());
        let poses: Vec<ObjectPose> = (0..frames)
            .map(|t| ObjectPose { rotation: object.rotations[t], position: object.translations[t] })
            .collect();
        let per_frame: Vec<(Vec<f32>, (f32, f32))> = (0..frames)
            .into_par_iter()
            .map(|t| {
                let pose = poses[t];
                let to_object = pose.rotation.transpose();
                let distances = hand_joints
                    .iter()
                    .map(|&j| {
                        query.signed_distance(to_object * (fk.position(t, j) - pose.position))
                    })
                    .collect();
                (distances, hand_distances(query, pose, fk.frame_positions(t), groups))
            })
            .collect();
        let left: Vec<f32> = per_frame.iter().map(|(_, (l, _))| *l).collect();
        let right: Vec<f32> = per_frame.iter().map(|(_, (_, r))| *r).collect();
        let resting =
            if config.mixture.free_at_rest { resting_frames(query, &poses) } else { Vec::new() };
        let logits = mixture_targets_at_rest(&left, &right, &resting, &config.mixture)?;
        for (t, (distances, (l, r))) in per_frame.into_iter().enumerate() {
            let pose = poses[t];
            let encoded = HandRelativeObject::encode(pose, wrists(t), logits[t]);
            objects[layout.object_row(t, slot)].copy_from_slice(&encoded.to_array());
            hand_distance[slot_range(t, slot, hand_count)].copy_from_slice(&distances);
            hand_contact[slot_range(t, slot, 2)].copy_from_slice(&[
                f32::from(u8::from(l <= config.hand_contact_distance)),
                f32::from(u8::from(r <= config.hand_contact_distance)),
            ]);
            object_positions[slot_range(t, slot, 3)].copy_from_slice(&pose.position.to_array());
        }
    }

    let feet = [
        (groups.left_foot[0], 0),
        (groups.left_foot[groups.left_foot.len() - 1], 1),
        (groups.right_foot[0], 0),
        (groups.right_foot[groups.right_foot.len() - 1], 1),
    ];
    let mut foot_contact = vec![0.0f32; frames * 4];
    for t in 0..frames {
        for (k, (joint, kind)) in feet.iter().enumerate() {
            let p = fk.position(t, *joint);
            let neighbour = if t + 1 < frames { t + 1 } else { t.saturating_sub(1) };
            let speed = p.distance(fk.position(neighbour, *joint));
            let low = p.y < config.foot_height[*kind];
            foot_contact[t * 4 + k] = f32::from(u8::from(low && speed < config.foot_speed));
        }
    }
    let joint_positions = fk.positions.iter().flat_map(|p| p.to_array()).collect();
    Ok(ProcessedSequence {
        frames,
        joints,
        body,
        objects,
        object_present,
        object_names,
        joint_positions,
        hand_distances: hand_distance,
        hand_contact,
        foot_contact,
        object_rotations,
        object_positions,
        root_start,
        rest_offsets: skeleton.rest_offsets().to_vec(),
        texts: sequence.texts.clone(),
        held_out_texts: Vec::new(),
        action: sequence.action.clone(),
        source_id: sequence.source_id.clone(),
    })
}

/// How object positions are decoded from object features.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ObjectDecoding {
    /// Through the softmax mixture of the wrist and global branches (Eq. 4).
    Mixture,
    /// From the global branch alone (the "without hand-relative representation" variant).
    GlobalOnly,
}

/// Motion decoded from features.
#[derive(Debug, Clone)]
pub struct DecodedMotion {
    /// Local joint rotations, frame-major `[frames * joints]`.
    pub local_rotations: Vec<Mat3>,
    /// Root positions per frame.
    pub root_positions: Vec<Vec3>,
    /// Forward kinematics of the above.
    pub joints: dex2hoi_repr::FkOutput,
    /// Per object slot, rotations and positions per frame (`None` for an empty slot).
    pub objects: [Option<(Vec<Mat3>, Vec<Vec3>)>; MAX_OBJECTS],
}

/// Decodes body and object features (as stored in a dataset or produced by the model) back into
/// joint rotations, joint positions (FK) and object poses.
///
/// # Shapes
/// - `body`: `[frames, 6J + 3]`; `objects`: `[frames, 2, 18]`
pub fn decode_features(
    skeleton: &Skeleton,
    body: &[f32],
    objects: &[f32],
    present: [bool; MAX_OBJECTS],
    root_start: Vec3,
    decoding: ObjectDecoding,
) -> Result<DecodedMotion> {
    let joints = skeleton.joint_count();
    let layout = FeatureLayout::new(joints);
    let frames = layout.frames_of(body, objects)?;
    if let Some(i) = body.iter().chain(objects).position(|v| !v.is_finite()) {
        return Err(DataError::invalid(
            "features to decode",
            "finite numbers",
            format!("a NaN at {i}"),
        ));
    }
    let mut local_rotations = Vec::with_capacity(frames * joints);
    let mut root_positions = Vec::with_capacity(frames);
    for row in body.chunks_exact(layout.body_width()) {
        for j in 0..joints {
            local_rotations.push(dex2hoi_repr::rotation::sixd_to_matrix(
                row[layout.joint_rotation_range(j)].try_into().expect("six numbers"),
            ));
        }
        root_positions.push(root_start + Vec3::from_slice(&row[layout.root_range()]));
    }
    let fk = forward_kinematics(skeleton, &local_rotations, &root_positions)?;
    let groups = skeleton.groups();
    let decoded_objects = std::array::from_fn(|slot| {
        present[slot].then(|| {
            (0..frames)
                .map(|t| {
                    let o = HandRelativeObject::from_slice(&objects[layout.object_row(t, slot)])
                        .expect("18 numbers");
                    let position = match decoding {
                        ObjectDecoding::GlobalOnly => o.global_position,
                        ObjectDecoding::Mixture => {
                            o.decode_position(Wrists::from_fk(&fk, t, groups))
                        }
                    };
                    (o.decode_rotation(), position)
                })
                .unzip()
        })
    });
    Ok(DecodedMotion { local_rotations, root_positions, joints: fk, objects: decoded_objects })
}
