//! Hand-object contact (CHOIS; docs/CONVENTIONS.md, "Physical metrics"): distances, per-frame contact, and
//! precision, recall and F1 against the ground truth.

use dex2hoi_data::MAX_OBJECTS;
use rayon::prelude::*;

use crate::error::{EvalError, Result};

use super::sample::MotionSample;

pub use dex2hoi_repr::CONTACT_RADIUS_M;

/// Per frame, per object slot, per hand (left, right): the nearest signed distance in metres
/// from the hand's joints (the skeleton groups `left_hand` / `right_hand`: wrist and fingers)
/// to the object's surface, negative inside; `f32::INFINITY` for an empty slot.
///
/// # Errors
/// A sample that fails [`MotionSample::frames`], or a skeleton without hand joints.
pub fn hand_object_distances(sample: &MotionSample<'_>) -> Result<Vec<[[f32; 2]; MAX_OBJECTS]>> {
    let frames = sample.frames()?;
    let groups = sample.skeleton.groups();
    if groups.left_hand.is_empty() || groups.right_hand.is_empty() {
        return Err(EvalError::invalid(
            "skeleton hand groups",
            "joints in both hands",
            format!("{} left, {} right", groups.left_hand.len(), groups.right_hand.len()),
        ));
    }
    Ok((0..frames)
        .into_par_iter()
        .map(|t| {
            let mut out = [[f32::INFINITY; 2]; MAX_OBJECTS];
            for (slot, mesh) in sample.present_objects() {
                let pose = sample.object_pose(t, slot);
                let to_object = pose.rotation.transpose();
                for (hand, joints) in
                    [&groups.left_hand, &groups.right_hand].into_iter().enumerate()
                {
                    out[slot][hand] = joints
                        .iter()
                        .map(|&j| {
                            mesh.signed_distance(to_object * (sample.joint(t, j) - pose.position))
                        })
                        .fold(f32::INFINITY, f32::min);
                }
            }
            out
        })
        .collect())
}

/// Hand-object contact per frame and object slot (CHOIS): `true` when a joint of either hand is
/// within `radius_m` ([`CONTACT_RADIUS_M`] = 5 cm by default) of the object's surface (or
/// inside it). Always `false` for an empty slot.
///
/// # Errors
/// A negative or non-finite radius, or the errors of [`hand_object_distances`].
pub fn hand_contact(sample: &MotionSample<'_>, radius_m: f32) -> Result<Vec<[bool; MAX_OBJECTS]>> {
    check_radius(radius_m)?;
    Ok(hand_object_distances(sample)?
        .iter()
        .map(|slots| slots.map(|[left, right]| left.min(right) <= radius_m))
        .collect())
}

fn check_radius(radius_m: f32) -> Result<()> {
    if radius_m >= 0.0 && radius_m.is_finite() {
        Ok(())
    } else {
        Err(EvalError::invalid("contact radius", "a finite distance >= 0 m", radius_m))
    }
}

/// Ground-truth contact per frame and slot from `[T, 2, 2]` flags (slot, then left and right
/// hand; as [`ProcessedSequence::hand_contact`](dex2hoi_data::features::ProcessedSequence::hand_contact)): `true` when either hand's flag is above 0.5.
///
/// # Shapes
/// - `truth_contact`: `[T, 2, 2]`.
///
/// # Errors
/// A length that is not a multiple of 4, non-finite flags.
pub fn contact_flags(truth_contact: &[f32]) -> Result<Vec<[bool; MAX_OBJECTS]>> {
    Ok(hand_flags(truth_contact)?.into_iter().map(|slots| slots.map(|[l, r]| l || r)).collect())
}

/// `[T, 2, 2]` contact numbers as booleans (above 0.5).
pub(super) fn hand_flags(truth_contact: &[f32]) -> Result<Vec<[[bool; 2]; MAX_OBJECTS]>> {
    let per_frame = MAX_OBJECTS * 2;
    if !truth_contact.len().is_multiple_of(per_frame) {
        return Err(EvalError::invalid(
            "ground-truth hand contact",
            format!("[T, {MAX_OBJECTS}, 2] flags"),
            format!("{} numbers", truth_contact.len()),
        ));
    }
    if let Some(i) = truth_contact.iter().position(|v| !v.is_finite()) {
        return Err(EvalError::invalid(
            "ground-truth hand contact",
            "finite flags",
            format!("{} at {i}", truth_contact[i]),
        ));
    }
    Ok(truth_contact
        .chunks_exact(per_frame)
        .map(|f| std::array::from_fn(|slot| [f[slot * 2] > 0.5, f[slot * 2 + 1] > 0.5]))
        .collect())
}

/// The confusion counts of per-frame, per-object contact, and the hand-object distance summed
/// over ground-truth contact frames. Counts of several motions add up with [`Self::merge`].
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct ContactCounts {
    /// Predicted contact where the ground truth has contact.
    pub true_positives: usize,
    /// Predicted contact where the ground truth has none.
    pub false_positives: usize,
    /// No predicted contact where the ground truth has contact.
    pub false_negatives: usize,
    /// Neither.
    pub true_negatives: usize,
    /// Sum over ground-truth contact frames of the nearest hand-object distance, mm.
    pub distance_sum_mm: f64,
    /// Ground-truth contact frames with a distance (slot-frames).
    pub distance_count: usize,
}

impl ContactCounts {
    /// The sum of two sets of counts.
    pub fn merge(self, other: Self) -> Self {
        Self {
            true_positives: self.true_positives + other.true_positives,
            false_positives: self.false_positives + other.false_positives,
            false_negatives: self.false_negatives + other.false_negatives,
            true_negatives: self.true_negatives + other.true_negatives,
            distance_sum_mm: self.distance_sum_mm + other.distance_sum_mm,
            distance_count: self.distance_count + other.distance_count,
        }
    }
}

/// Contact precision, recall and F1 and the mean hand-object distance on ground-truth contact
/// frames (CHOIS, docs/CONVENTIONS.md, "Physical metrics").
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ContactScores {
    /// `TP / (TP + FP)`; 0 when nothing is predicted in contact.
    pub precision: f64,
    /// `TP / (TP + FN)`; 0 when the ground truth has no contact.
    pub recall: f64,
    /// `2 P R / (P + R)`; 0 when both are 0.
    pub f1: f64,
    /// Mean over ground-truth contact slot-frames of the nearest hand joint's distance to the
    /// object's surface in mm (0 for a joint on or inside the surface); `None` without
    /// ground-truth contact or without distances.
    pub mean_distance_on_contact_mm: Option<f64>,
    /// The counts behind the scores.
    pub counts: ContactCounts,
}

impl ContactScores {
    /// Scores from counts (e.g. the counts of a whole test set merged, which avoids the
    /// undefined ratios of single motions without contact). Undefined ratios are 0, as
    /// scikit-learn's `zero_division=0`.
    pub fn from_counts(counts: ContactCounts) -> Self {
        let ratio = |a: usize, b: usize| if b == 0 { 0.0 } else { a as f64 / b as f64 };
        let precision =
            ratio(counts.true_positives, counts.true_positives + counts.false_positives);
        let recall = ratio(counts.true_positives, counts.true_positives + counts.false_negatives);
        let f1 = if precision + recall > 0.0 {
            2.0 * precision * recall / (precision + recall)
        } else {
            0.0
        };
        let mean_distance_on_contact_mm = (counts.distance_count > 0)
            .then(|| counts.distance_sum_mm / counts.distance_count as f64);
        Self { precision, recall, f1, mean_distance_on_contact_mm, counts }
    }
}

/// Confusion counts of predicted against ground-truth contact flags, over the frames of the
/// present slots only (no distances).
///
/// # Shapes
/// - `predicted`, `truth`: `[T]` of per-slot flags, the same `T`.
///
/// # Errors
/// Different frame counts.
pub fn contact_counts(
    predicted: &[[bool; MAX_OBJECTS]],
    truth: &[[bool; MAX_OBJECTS]],
    present: [bool; MAX_OBJECTS],
) -> Result<ContactCounts> {
    if predicted.len() != truth.len() {
        return Err(EvalError::invalid(
            "contact flags",
            "as many predicted frames as ground-truth frames",
            format!("{} predicted, {} ground truth", predicted.len(), truth.len()),
        ));
    }
    let mut counts = ContactCounts::default();
    for (p, g) in predicted.iter().zip(truth) {
        for slot in (0..MAX_OBJECTS).filter(|&s| present[s]) {
            match (p[slot], g[slot]) {
                (true, true) => counts.true_positives += 1,
                (true, false) => counts.false_positives += 1,
                (false, true) => counts.false_negatives += 1,
                (false, false) => counts.true_negatives += 1,
            }
        }
    }
    Ok(counts)
}

/// Contact scores of a generated motion against ground-truth contact: a slot-frame is predicted
/// in contact when a hand joint of `generated` is within `radius_m` of the object
/// ([`hand_contact`]); precision, recall and F1 over the frames of the present slots; and the
/// mean nearest hand-object distance (negative distances, i.e. inside, count as 0) on the
/// slot-frames where the ground truth has contact.
///
/// # Shapes
/// - `truth_contact`: `[T, 2, 2]` ([`ProcessedSequence::hand_contact`](dex2hoi_data::features::ProcessedSequence::hand_contact)), the same `T` as the
///   sample.
///
/// # Errors
/// A bad radius, a bad sample, ground-truth flags of another length.
pub fn contact_scores(
    generated: &MotionSample<'_>,
    truth_contact: &[f32],
    radius_m: f32,
) -> Result<ContactScores> {
    check_radius(radius_m)?;
    let distances = hand_object_distances(generated)?;
    let truth = contact_flags(truth_contact)?;
    if truth.len() != distances.len() {
        return Err(EvalError::invalid(
            "ground-truth hand contact",
            format!("[T, 2, 2] with the sample's T = {}", distances.len()),
            format!("{} frames", truth.len()),
        ));
    }
    let nearest: Vec<[f32; MAX_OBJECTS]> =
        distances.iter().map(|slots| slots.map(|[l, r]| l.min(r))).collect();
    let predicted: Vec<[bool; MAX_OBJECTS]> =
        nearest.iter().map(|slots| slots.map(|d| d <= radius_m)).collect();
    let mut counts = contact_counts(&predicted, &truth, generated.present)?;
    for (slots, flags) in nearest.iter().zip(&truth) {
        for slot in (0..MAX_OBJECTS).filter(|&s| generated.present[s] && flags[s]) {
            counts.distance_sum_mm += f64::from(slots[slot].max(0.0)) * 1000.0;
            counts.distance_count += 1;
        }
    }
    Ok(ContactScores::from_counts(counts))
}
