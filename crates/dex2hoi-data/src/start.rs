//! The pose every generation from scratch starts from: the person standing at the canonical
//! origin, facing +Z, nobody holding anything.
//!
//! On the built-in SMPL-X body it is the default character's relaxed stance
//! ([`StartPose::smplx_standing`]), the first frame of every procedural sequence. A dataset of
//! real motion capture brings its own ([`StartPose::typical_first_frame`], stored in the
//! manifest by `data prepare`): a Mixamo model starts from its data's character standing as
//! its sequences begin, which no pose built by hand for another skeleton would match.

use glam::Vec3;
use serde::{Deserialize, Serialize};

use dex2hoi_repr::rotation::{matrix_to_sixd, sixd_to_matrix};
use dex2hoi_repr::{Skeleton, forward_kinematics};

use crate::character::{Hand, PELVIS_HEIGHT, Poser};
use crate::error::{DataError, Result};
use crate::layout::{FeatureLayout, ROOT_FEATURE_SIZE};
use crate::processed::ProcessedSequence;

/// A standing pose on a skeleton: the joints' local rotations and the root's height.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StartPose {
    /// Where the pose comes from: a sequence's source id, or `builtin` for the default
    /// character's stance.
    pub source: String,
    /// `[6J]`: each joint's rotation relative to its parent (the root's to the canonical
    /// frame), as 6D features.
    pub rotations: Vec<f32>,
    /// Height of the root joint above the floor (metres) on the dataset's built-in skeleton,
    /// at which the pose's lowest joint is as high as in the sequence it comes from.
    pub root_height: f32,
}

impl StartPose {
    /// The default character of the procedural dataset standing relaxed, hands hanging, on
    /// the built-in SMPL-X skeleton.
    pub fn smplx_standing() -> Self {
        let poser = Poser::new(Vec3::new(0.0, PELVIS_HEIGHT, 0.0));
        let idle = [poser.idle_hand(Hand::Left), poser.idle_hand(Hand::Right)];
        let local = poser.pose(0.0, 0.0, &idle);
        Self {
            source: "builtin".into(),
            rotations: local.iter().flat_map(|r| matrix_to_sixd(*r)).collect(),
            root_height: PELVIS_HEIGHT,
        }
    }

    /// The most typical first frame of `sequences`: the one whose joints (canonical frame) are
    /// nearest, in the mean over the others, to the other first frames' (a medoid, so always a
    /// pose someone stood in), put on `skeleton` with its lowest joint at the height it had.
    pub fn typical_first_frame(
        sequences: &[ProcessedSequence],
        skeleton: &Skeleton,
    ) -> Result<Self> {
        let joints = skeleton.joint_count();
        if sequences.is_empty() {
            return Err(DataError::invalid("start pose", "at least one sequence", 0));
        }
        if let Some(other) = sequences.iter().find(|s| s.joints != joints || s.frames == 0) {
            return Err(DataError::invalid(
                format!("start pose from {}", other.source_id),
                format!("a sequence of at least one frame on {joints} joints"),
                format!("{} frames on {} joints", other.frames, other.joints),
            ));
        }
        let first_frames: Vec<&[f32]> =
            sequences.iter().map(|s| &s.joint_positions[..joints * 3]).collect();
        let mean_distance = |a: &[f32]| -> f64 {
            first_frames
                .iter()
                .map(|b| {
                    a.chunks_exact(3)
                        .zip(b.chunks_exact(3))
                        .map(|(p, q)| f64::from(Vec3::from_slice(p).distance(Vec3::from_slice(q))))
                        .sum::<f64>()
                })
                .sum()
        };
        let medoid = first_frames
            .iter()
            .map(|f| mean_distance(f))
            .enumerate()
            .min_by(|(_, a), (_, b)| a.total_cmp(b))
            .map(|(k, _)| k)
            .expect("at least one sequence");
        let sequence = &sequences[medoid];
        let rotations = sequence.body[..6 * joints].to_vec();
        let lowest = |positions: &[f32]| {
            positions.chunks_exact(3).map(|p| p[1]).fold(f32::INFINITY, f32::min)
        };
        let data_lowest = lowest(first_frames[medoid]);
        let root = sequence.root_start;
        let on_skeleton =
            Self { source: sequence.source_id.clone(), rotations, root_height: root.y };
        let fk = on_skeleton.forward_kinematics(skeleton)?;
        let ours_lowest = fk.iter().map(|p| p.y).fold(f32::INFINITY, f32::min);
        Ok(Self { root_height: root.y + data_lowest - ours_lowest, ..on_skeleton })
    }

    /// The root's position in the canonical frame.
    pub fn root(&self) -> Vec3 {
        Vec3::new(0.0, self.root_height, 0.0)
    }

    /// Checks that the pose fits `skeleton` (named `context` in the error).
    pub fn check(&self, skeleton: &Skeleton, context: &str) -> Result<()> {
        let joints = skeleton.joint_count();
        if self.rotations.len() != 6 * joints {
            return Err(DataError::invalid(
                context,
                format!("a start pose of 6 x {joints} rotation numbers"),
                self.rotations.len(),
            ));
        }
        if !(self.rotations.iter().all(|v| v.is_finite())
            && self.root_height.is_finite()
            && self.root_height > 0.0)
        {
            return Err(DataError::invalid(
                context,
                "finite rotations and a root above the floor",
                format!("root height {}", self.root_height),
            ));
        }
        Ok(())
    }

    /// The joints' world positions on `skeleton`.
    fn forward_kinematics(&self, skeleton: &Skeleton) -> Result<Vec<Vec3>> {
        self.check(skeleton, "start pose")?;
        let local = self.local_rotations();
        let fk = forward_kinematics(skeleton, &local, &[self.root()])?;
        Ok((0..skeleton.joint_count()).map(|j| fk.position(0, j)).collect())
    }

    fn local_rotations(&self) -> Vec<glam::Mat3> {
        self.rotations
            .chunks_exact(6)
            .map(|c| sixd_to_matrix([c[0], c[1], c[2], c[3], c[4], c[5]]))
            .collect()
    }

    /// One frame of features for this pose on `skeleton` with objects at the given poses
    /// (canonical frame) and nobody holding them: the starting state of generation. Returns
    /// the body row `[6J + 3]` and the object rows `[2, 18]` (zeros for an empty slot).
    pub fn features(
        &self,
        skeleton: &Skeleton,
        objects: [Option<dex2hoi_repr::ObjectPose>; crate::MAX_OBJECTS],
    ) -> Result<(Vec<f32>, Vec<f32>)> {
        use dex2hoi_repr::object_repr::{
            HandRelativeObject, MixtureTargetConfig, Wrists, mixture_targets,
        };
        self.check(skeleton, "start pose")?;
        let layout = FeatureLayout::of_skeleton(skeleton);
        let fk = forward_kinematics(skeleton, &self.local_rotations(), &[self.root()])?;
        // One frame: the joint rotations, then a zero root displacement (the frame is the start).
        let mut body = self.rotations.clone();
        body.extend([0.0; ROOT_FEATURE_SIZE]);
        debug_assert_eq!(body.len(), layout.body_width());
        let wrists = Wrists::from_fk(&fk, 0, skeleton.groups());
        // Nobody holds anything: the mixture target of "neither hand".
        let free =
            mixture_targets(&[f32::INFINITY], &[f32::INFINITY], &MixtureTargetConfig::default())?
                [0];
        let mut rows = vec![0.0f32; layout.objects_width()];
        for (slot, pose) in objects.iter().enumerate() {
            if let Some(pose) = pose {
                let encoded = HandRelativeObject::encode(*pose, wrists, free).to_array();
                rows[layout.object_row(0, slot)].copy_from_slice(&encoded);
            }
        }
        Ok((body, rows))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_builtin_stance_reproduces_its_rotations_and_stands_on_the_floor() {
        let skeleton = Skeleton::smplx();
        let start = StartPose::smplx_standing();
        start.check(&skeleton, "test").unwrap();
        let (body, _) = start.features(&skeleton, [None, None]).unwrap();
        assert_eq!(&body[..start.rotations.len()], &start.rotations[..]);
        assert!(body[start.rotations.len()..].iter().all(|v| *v == 0.0));
        let lowest = start
            .forward_kinematics(&skeleton)
            .unwrap()
            .iter()
            .map(|p| p.y)
            .fold(f32::INFINITY, f32::min);
        assert!((0.0..0.12).contains(&lowest), "lowest joint at {lowest} m");
    }

    /// A one-frame sequence on `skeleton` with its root at `root` and some joints turned.
    fn first_frame(
        skeleton: &Skeleton,
        id: &str,
        root: Vec3,
        turns: &[(&str, f32)],
    ) -> ProcessedSequence {
        let mut local = vec![glam::Mat3::IDENTITY; skeleton.joint_count()];
        for (name, angle) in turns {
            local[skeleton.joint_index(name).unwrap()] = glam::Mat3::from_rotation_x(*angle);
        }
        let sequence = crate::Sequence {
            skeleton: skeleton.clone(),
            fps: 20.0,
            local_rotations: local,
            root_positions: vec![root],
            objects: Vec::new(),
            texts: vec!["standing".into()],
            action: None,
            source_id: id.into(),
        };
        crate::features::process_sequence(&sequence, &[], &Default::default()).unwrap()
    }

    #[test]
    fn the_typical_first_frame_is_a_medoid_put_on_the_floor_of_the_skeleton() {
        let skeleton = Skeleton::mixamo();
        let hips = skeleton.rest_offsets()[0];
        let sequences = [
            first_frame(&skeleton, "a", hips, &[("LeftArm", 0.1)]),
            first_frame(&skeleton, "b", hips, &[("LeftArm", 0.2)]),
            first_frame(&skeleton, "c", hips, &[("LeftArm", 0.3)]),
            // Crouching: far from the others.
            first_frame(
                &skeleton,
                "crouch",
                hips * 0.7,
                &[("LeftUpLeg", -1.2), ("RightUpLeg", -1.2)],
            ),
        ];
        let start = StartPose::typical_first_frame(&sequences, &skeleton).unwrap();
        assert_eq!(start.source, "b", "the pose nearest the others");
        let chosen = &sequences[1];
        assert_eq!(start.rotations, chosen.body[..6 * skeleton.joint_count()]);
        let lowest = |points: &[Vec3]| points.iter().map(|p| p.y).fold(f32::INFINITY, f32::min);
        let data: Vec<Vec3> =
            chosen.joint_positions.chunks_exact(3).map(Vec3::from_slice).collect();
        // On the data's own skeleton the pose stands as it stood.
        let ours = start.forward_kinematics(&skeleton).unwrap();
        assert!((lowest(&ours) - lowest(&data)).abs() < 1e-5);
        // On a shorter skeleton the root comes down until the feet are where they were.
        let short: Vec<Vec3> = skeleton.rest_offsets().iter().map(|o| *o * 0.9).collect();
        let short = skeleton.with_rest_offsets(short).unwrap();
        let on_short = StartPose::typical_first_frame(&sequences, &short).unwrap();
        assert!(on_short.root_height < start.root_height - 0.05);
        let ours = on_short.forward_kinematics(&short).unwrap();
        assert!((lowest(&ours) - lowest(&data)).abs() < 1e-5);
        assert!(StartPose::typical_first_frame(&[], &skeleton).is_err());
    }

    #[test]
    fn a_pose_for_another_skeleton_is_refused() {
        let start = StartPose::smplx_standing();
        let error = start.check(&Skeleton::mixamo(), "manifest").unwrap_err().to_string();
        assert!(error.contains("6 x 65"), "{error}");
    }
}
