//! How precisely the fingertips sit on the objects the ground truth holds (ours): the
//! generated hands' penetration comes from the spread of this distance, not from the hands
//! passing through objects (docs/results/penetration.md).

use dex2hoi_data::MAX_OBJECTS;

use crate::error::{EvalError, Result};

use super::contact::hand_flags;
use super::sample::MotionSample;

/// The signed distance in metres (negative inside) of each fingertip of each hand the ground
/// truth has in contact with an object, to that object, on the frames of that contact: for
/// every frame, present slot and hand with `truth_contact` set, the hand's fingertips
/// ([`JointGroups`](dex2hoi_repr::JointGroups)) in order. Two samples measured with the same
/// flags give their distances in the same order, so they can be compared one by one.
///
/// # Shapes
/// - `truth_contact`: `[T, 2, 2]` (slot, hand) as
///   [`ProcessedSequence::hand_contact`](dex2hoi_data::features::ProcessedSequence::hand_contact),
///   the same `T` as the sample.
///
/// # Errors
/// A bad sample, ground-truth flags of another length.
pub fn fingertip_distances(sample: &MotionSample<'_>, truth_contact: &[f32]) -> Result<Vec<f32>> {
    let frames = sample.frames()?;
    let flags = hand_flags(truth_contact)?;
    if flags.len() != frames {
        return Err(EvalError::invalid(
            "ground-truth hand contact",
            format!("[T, {MAX_OBJECTS}, 2] with the sample's T = {frames}"),
            format!("{} frames", flags.len()),
        ));
    }
    let groups = sample.skeleton.groups();
    let fingertips = [&groups.left_fingertips, &groups.right_fingertips];
    let mut distances = Vec::new();
    for (t, slots) in flags.iter().enumerate() {
        for (slot, mesh) in sample.present_objects() {
            let pose = sample.object_pose(t, slot);
            let to_object = pose.rotation.transpose();
            for (hand, tips) in fingertips.iter().enumerate() {
                if !slots[slot][hand] {
                    continue;
                }
                distances.extend(tips.iter().map(|&joint| {
                    mesh.signed_distance(to_object * (sample.joint(t, joint) - pose.position))
                }));
            }
        }
    }
    Ok(distances)
}
