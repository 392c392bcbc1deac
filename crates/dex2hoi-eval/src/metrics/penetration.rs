//! Penetration of a motion into its objects (paper Sec. 4.2, CHOIS).

use rayon::prelude::*;

use crate::error::{EvalError, Result};

use super::sample::MotionSample;

pub use dex2hoi_repr::PENETRATION_TOLERANCE_M;

/// Penetration of a motion into its objects.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Penetration {
    /// Mean depth in mm over the penetrating joint-frames (0 when none penetrates).
    pub mean_depth_mm: f64,
    /// Share of frames with at least one penetrating joint.
    pub frame_share: f64,
    /// Mean over **all** frames of the frame's deepest penetration in mm (0 for a frame without
    /// one): "the mean interpenetration distance across frames" of the paper's Sec. 4.2.
    pub mean_frame_depth_mm: f64,
    /// Joint-frames deeper than the tolerance.
    pub penetrating_joint_frames: usize,
    /// Frames with at least one penetrating joint.
    pub penetrating_frames: usize,
    /// Frames of the motion.
    pub frames: usize,
    /// Sum of the depths of the penetrating joint-frames, mm.
    pub depth_sum_mm: f64,
    /// Sum over frames of the deepest penetration, mm.
    pub frame_depth_sum_mm: f64,
}

impl Penetration {
    /// The figures of several motions pooled (sums of counts and depths, then the ratios).
    pub fn pooled(items: &[Penetration]) -> Penetration {
        let mut total = Penetration {
            mean_depth_mm: 0.0,
            frame_share: 0.0,
            mean_frame_depth_mm: 0.0,
            penetrating_joint_frames: 0,
            penetrating_frames: 0,
            frames: 0,
            depth_sum_mm: 0.0,
            frame_depth_sum_mm: 0.0,
        };
        for item in items {
            total.penetrating_joint_frames += item.penetrating_joint_frames;
            total.penetrating_frames += item.penetrating_frames;
            total.frames += item.frames;
            total.depth_sum_mm += item.depth_sum_mm;
            total.frame_depth_sum_mm += item.frame_depth_sum_mm;
        }
        total.finish()
    }

    /// Fills the ratios from the sums.
    fn finish(mut self) -> Self {
        let ratio = |a: f64, b: usize| if b == 0 { 0.0 } else { a / b as f64 };
        self.mean_depth_mm = ratio(self.depth_sum_mm, self.penetrating_joint_frames);
        self.frame_share = ratio(self.penetrating_frames as f64, self.frames);
        self.mean_frame_depth_mm = ratio(self.frame_depth_sum_mm, self.frames);
        self
    }
}

/// Penetration (CHOIS; paper Sec. 4.2 "hand and body-object interpenetration"): **every joint**
/// of the skeleton (body and fingers) is moved into each present object's frame
/// (`R^T (p - t)`) and its signed distance to the mesh is taken (negative inside). A joint
/// penetrates when its depth (`-signed distance`, the deepest over the objects) exceeds
/// `tolerance_m` ([`PENETRATION_TOLERANCE_M`] = 5 mm by default); its full depth is counted.
/// Reports the mean depth over penetrating joint-frames, the share of frames with any
/// penetration and the per-frame deepest penetration averaged over all frames.
///
/// # Errors
/// A negative or non-finite tolerance, or a sample that fails [`MotionSample::frames`].
pub fn penetration(sample: &MotionSample<'_>, tolerance_m: f32) -> Result<Penetration> {
    if !(tolerance_m >= 0.0 && tolerance_m.is_finite()) {
        return Err(EvalError::invalid(
            "penetration tolerance",
            "a finite distance >= 0 m",
            tolerance_m,
        ));
    }
    let frames = sample.frames()?;
    let joint_count = sample.skeleton.joint_count();
    let per_frame: Vec<(usize, f64, f64)> = (0..frames)
        .into_par_iter()
        .map(|t| {
            let mut depth = vec![0.0f32; joint_count];
            for (slot, mesh) in sample.present_objects() {
                let pose = sample.object_pose(t, slot);
                let to_object = pose.rotation.transpose();
                for (j, d) in depth.iter_mut().enumerate() {
                    let local = to_object * (sample.joint(t, j) - pose.position);
                    *d = d.max(-mesh.signed_distance(local));
                }
            }
            let mut count = 0;
            let mut sum = 0.0;
            let mut deepest = 0.0f64;
            for &d in depth.iter().filter(|&&d| d > tolerance_m) {
                let mm = f64::from(d) * 1000.0;
                count += 1;
                sum += mm;
                deepest = deepest.max(mm);
            }
            (count, sum, deepest)
        })
        .collect();
    let mut result = Penetration::pooled(&[]);
    result.frames = frames;
    for (count, sum, deepest) in per_frame {
        result.penetrating_joint_frames += count;
        result.penetrating_frames += usize::from(count > 0);
        result.depth_sum_mm += sum;
        result.frame_depth_sum_mm += deepest;
    }
    Ok(result.finish())
}
