//! Motion clips and the per-frame features the motion encoder reads.
//!
//! Per frame, `[3J + 2 * 9 + 2]` numbers: every joint's position relative to the clip's first
//! frame root projected on the floor (its X and Z subtracted, the height kept), then per object
//! slot the 6D rotation (the first two rows of the rotation matrix) and the position in the same
//! frame, then the two presence flags. Features are normalised per channel with [`ClipStats`]
//! computed on the training split; the channels of an absent object are zero after
//! normalisation, and the presence flags are left as they are.

use serde::{Deserialize, Serialize};

use dex2hoi_data::MAX_OBJECTS;
use dex2hoi_data::dataset::STD_FLOOR;
use dex2hoi_data::features::{DecodedMotion, ProcessedSequence};
use dex2hoi_data::normalise::normalise_row;

use crate::error::{EvalError, Result};

/// Numbers per object slot in a frame's features: 6D rotation and position.
pub const OBJECT_CHANNELS: usize = 9;

/// Numbers per frame of the features of a skeleton with `joints` joints.
pub fn clip_feature_size(joints: usize) -> usize {
    3 * joints + MAX_OBJECTS * OBJECT_CHANNELS + MAX_OBJECTS
}

/// A motion to evaluate: joint positions and object poses per frame, in the dataset's canonical
/// frame (metres, +Y up).
#[derive(Debug, Clone, PartialEq)]
pub struct MotionClip {
    /// `[T, J, 3]` joint positions in metres.
    pub joints: Vec<f32>,
    /// `[T, 2, 9]` object rotation matrices, row-major (ignored for an absent slot).
    pub object_rotations: Vec<f32>,
    /// `[T, 2, 3]` object positions in metres (ignored for an absent slot).
    pub object_positions: Vec<f32>,
    /// Which object slots hold an object.
    pub present: [bool; MAX_OBJECTS],
}

impl MotionClip {
    /// The window `start..start + frames` of a dataset sequence.
    pub fn from_processed(
        sequence: &ProcessedSequence,
        start: usize,
        frames: usize,
    ) -> Result<Self> {
        if frames == 0 || start + frames > sequence.frames {
            return Err(EvalError::invalid(
                format!("window of sequence {}", sequence.source_id),
                format!("at least one frame within its {} frames", sequence.frames),
                format!("frames {start}..{}", start + frames),
            ));
        }
        let joints = sequence.joints;
        let expected = [
            (sequence.joint_positions.len(), sequence.frames * joints * 3, "joint positions"),
            (
                sequence.object_rotations.len(),
                sequence.frames * MAX_OBJECTS * 9,
                "object rotations",
            ),
            (
                sequence.object_positions.len(),
                sequence.frames * MAX_OBJECTS * 3,
                "object positions",
            ),
        ];
        if let Some((got, want, what)) = expected.iter().find(|(got, want, _)| got != want) {
            return Err(EvalError::invalid(
                format!("{what} of sequence {}", sequence.source_id),
                format!("{want} numbers"),
                got,
            ));
        }
        let range =
            |width: usize, data: &[f32]| data[start * width..(start + frames) * width].to_vec();
        Ok(Self {
            joints: range(joints * 3, &sequence.joint_positions),
            object_rotations: range(MAX_OBJECTS * 9, &sequence.object_rotations),
            object_positions: range(MAX_OBJECTS * 3, &sequence.object_positions),
            present: sequence.object_present,
        })
    }

    /// A decoded (generated) motion, every frame.
    pub fn from_decoded(motion: &DecodedMotion) -> Result<Self> {
        let (frames, joints) = (motion.joints.frames, motion.joints.joints);
        if frames == 0 || motion.joints.positions.len() != frames * joints {
            return Err(EvalError::invalid(
                "decoded motion",
                format!("{frames} frames of {joints} joint positions"),
                format!("{} positions", motion.joints.positions.len()),
            ));
        }
        let joint_positions = motion.joints.positions.iter().flat_map(|p| p.to_array()).collect();
        let mut object_rotations = vec![0.0f32; frames * MAX_OBJECTS * 9];
        let mut object_positions = vec![0.0f32; frames * MAX_OBJECTS * 3];
        let mut present = [false; MAX_OBJECTS];
        for (slot, object) in motion.objects.iter().enumerate() {
            let Some((rotations, positions)) = object else { continue };
            if rotations.len() != frames || positions.len() != frames {
                return Err(EvalError::invalid(
                    format!("object slot {slot} of the decoded motion"),
                    format!("{frames} rotations and positions"),
                    format!("{} and {}", rotations.len(), positions.len()),
                ));
            }
            present[slot] = true;
            for f in 0..frames {
                let r = (f * MAX_OBJECTS + slot) * 9;
                object_rotations[r..r + 9]
                    .copy_from_slice(&rotations[f].transpose().to_cols_array());
                let p = (f * MAX_OBJECTS + slot) * 3;
                object_positions[p..p + 3].copy_from_slice(&positions[f].to_array());
            }
        }
        Ok(Self { joints: joint_positions, object_rotations, object_positions, present })
    }

    /// Number of frames `T`.
    pub fn frames(&self) -> usize {
        self.object_positions.len() / (MAX_OBJECTS * 3)
    }

    /// Checks the sizes against a skeleton of `joints` joints and that every number is finite.
    pub fn validate(&self, joints: usize) -> Result<()> {
        let frames = self.frames();
        if frames == 0
            || self.object_positions.len() != frames * MAX_OBJECTS * 3
            || self.object_rotations.len() != frames * MAX_OBJECTS * 9
            || self.joints.len() != frames * joints * 3
        {
            return Err(EvalError::invalid(
                "motion clip",
                format!(
                    "[T, {joints}, 3] joints, [T, 2, 9] rotations, [T, 2, 3] positions, T >= 1"
                ),
                format!(
                    "{} joint, {} rotation and {} position numbers",
                    self.joints.len(),
                    self.object_rotations.len(),
                    self.object_positions.len()
                ),
            ));
        }
        let finite = |data: &[f32]| data.iter().all(|v| v.is_finite());
        if !finite(&self.joints) {
            return Err(EvalError::invalid(
                "motion clip",
                "finite joint positions",
                "NaN or infinity",
            ));
        }
        for slot in (0..MAX_OBJECTS).filter(|s| self.present[*s]) {
            let slot_finite = (0..frames).all(|f| {
                let r = (f * MAX_OBJECTS + slot) * 9;
                let p = (f * MAX_OBJECTS + slot) * 3;
                finite(&self.object_rotations[r..r + 9]) && finite(&self.object_positions[p..p + 3])
            });
            if !slot_finite {
                return Err(EvalError::invalid(
                    format!("object slot {slot} of a motion clip"),
                    "finite poses",
                    "NaN or infinity",
                ));
            }
        }
        Ok(())
    }

    /// Raw (unnormalised) features of the first `frames` frames; absent slots are zeros.
    ///
    /// # Shapes
    /// - returns `[frames, 3J + 20]`
    pub fn raw_features(&self, joints: usize, frames: usize) -> Vec<f32> {
        let width = clip_feature_size(joints);
        let frames = frames.min(self.frames());
        let (origin_x, origin_z) = (self.joints[0], self.joints[2]);
        let mut out = Vec::with_capacity(frames * width);
        for f in 0..frames {
            for j in 0..joints {
                let p = &self.joints[(f * joints + j) * 3..(f * joints + j) * 3 + 3];
                out.extend_from_slice(&[p[0] - origin_x, p[1], p[2] - origin_z]);
            }
            for slot in 0..MAX_OBJECTS {
                if self.present[slot] {
                    let r = (f * MAX_OBJECTS + slot) * 9;
                    let p = (f * MAX_OBJECTS + slot) * 3;
                    out.extend_from_slice(&self.object_rotations[r..r + 6]);
                    let position = &self.object_positions[p..p + 3];
                    out.extend_from_slice(&[
                        position[0] - origin_x,
                        position[1],
                        position[2] - origin_z,
                    ]);
                } else {
                    out.extend_from_slice(&[0.0; OBJECT_CHANNELS]);
                }
            }
            out.extend(self.present.iter().map(|&p| if p { 1.0 } else { 0.0 }));
        }
        out
    }
}

/// Per-channel statistics of the clip features, computed on the training split (`stats.json`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ClipStats {
    /// Numbers per frame (`3J + 20`).
    pub feature_size: usize,
    /// Means per channel.
    pub mean: Vec<f32>,
    /// Standard deviations per channel, at least [`STD_FLOOR`].
    pub std: Vec<f32>,
}

impl ClipStats {
    /// Statistics over every frame of the sequences (each taken from its first frame): joint
    /// channels over all frames, an object's channels over the frames of sequences where it is
    /// present; the presence flags keep mean 0 and std 1.
    pub fn compute<'a>(
        sequences: impl IntoIterator<Item = &'a ProcessedSequence>,
        joints: usize,
    ) -> Result<Self> {
        let width = clip_feature_size(joints);
        let mut sum = vec![0.0f64; width];
        let mut square = vec![0.0f64; width];
        let mut count = vec![0usize; width];
        for sequence in sequences {
            let clip = MotionClip::from_processed(sequence, 0, sequence.frames)?;
            let features = clip.raw_features(joints, sequence.frames);
            for row in features.chunks_exact(width) {
                for (c, &value) in row.iter().enumerate() {
                    let slot = c.checked_sub(3 * joints).map(|k| k / OBJECT_CHANNELS);
                    if let Some(slot) = slot
                        && slot < MAX_OBJECTS
                        && !clip.present[slot]
                    {
                        continue;
                    }
                    sum[c] += f64::from(value);
                    square[c] += f64::from(value) * f64::from(value);
                    count[c] += 1;
                }
            }
        }
        let mut mean = vec![0.0f32; width];
        let mut std = vec![1.0f32; width];
        for c in 0..width - MAX_OBJECTS {
            if count[c] == 0 {
                continue;
            }
            let m = sum[c] / count[c] as f64;
            let variance = (square[c] / count[c] as f64 - m * m).max(0.0);
            mean[c] = m as f32;
            std[c] = (variance.sqrt() as f32).max(STD_FLOOR);
        }
        Ok(Self { feature_size: width, mean, std })
    }

    /// Normalised features of the first `frames` frames of a clip.
    ///
    /// # Shapes
    /// - returns `[min(frames, T), 3J + 20]`
    pub fn normalise(&self, clip: &MotionClip, joints: usize, frames: usize) -> Vec<f32> {
        let width = self.feature_size;
        let mut features = clip.raw_features(joints, frames);
        for row in features.chunks_exact_mut(width) {
            // The presence flags (the last channels) stay 0 or 1.
            let channels = width - MAX_OBJECTS;
            normalise_row(&mut row[..channels], &self.mean, &self.std);
            for slot in (0..MAX_OBJECTS).filter(|s| !clip.present[*s]) {
                let first = 3 * joints + slot * OBJECT_CHANNELS;
                row[first..first + OBJECT_CHANNELS].fill(0.0);
            }
        }
        features
    }
}
