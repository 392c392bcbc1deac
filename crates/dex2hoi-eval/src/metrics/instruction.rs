//! Instruction following and object behaviour: does a generated clip do what its ground truth
//! does after the same prefix, and do its objects behave like objects? Everything here reads
//! only joints, object poses and meshes, so it applies to every dataset
//! (docs/CONVENTIONS.md, "Instruction following").
//!
//! - **Moved**: an object moves in a clip when it travels more than [`MOVED_TRAVEL_M`] from
//!   where it starts or rises more than [`MOVED_RISE_M`]. Per object: does the generated clip
//!   move the objects the ground truth moves, and leave the ones it leaves?
//! - **Holding hand**: per frame, the hands holding an object are those with a joint within
//!   [`CONTACT_RADIUS_M`] of its surface (the contact metric's rule): none, left, right or both.
//!   Over the frames where the ground truth holds an object, the share where the generated clip
//!   holds it with the same hands.
//! - **Where it ends**: for each object the ground truth moves, the distance between the two
//!   clips' final object positions, and whether both end on the same side of the body (left,
//!   centre within [`SIDE_MARGIN_M`], right, along the body's left axis at the clip's start).
//! - **Start jump**: the distance from an object's last prefix position to its first generated
//!   position (the ground truth's is one frame of its own motion).
//! - **Untouched speed**: the speed of objects on frames where every hand joint is more than
//!   [`UNTOUCHED_DISTANCE_M`] from them (and was on the frame before): in the data they stand
//!   still.
//! - **Start turn** and **untouched turning**: the same two for the object's orientation, the
//!   angle between consecutive rotations (degrees, and degrees per second).

use dex2hoi_data::MAX_OBJECTS;
use glam::{DVec3, Mat3, Vec3};

use crate::error::{EvalError, Result};

use super::contact::{CONTACT_RADIUS_M, hand_object_distances};
use super::sample::MotionSample;

/// The sides across the body and the half-width of their centre band: the data's, which training
/// reads too.
pub use dex2hoi_data::processed::{SIDE_MARGIN_M, Side};
/// Travel and rise from the clip's first frame beyond which an object has moved: the rule the
/// condition's memory of set-down objects reads too.
pub use dex2hoi_data::settled::{MOVED_RISE_M, MOVED_TRAVEL_M};
/// Hand-to-surface distance beyond which an object counts as untouched.
pub const UNTOUCHED_DISTANCE_M: f32 = 0.15;
/// Drop below the resting height beyond which an object counts as sunk into its support (a
/// centimetre: a generated object put down again lands within a few millimetres of its old
/// height when it lands well).
pub const SINK_TOLERANCE_M: f32 = 0.01;

/// How far a clip's objects go below their resting heights: how deep each one sinks at worst,
/// and on how many frames any sinks more than [`SINK_TOLERANCE_M`].
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Sinking {
    /// Per present object, the largest drop of its origin below its resting height, metres
    /// (0 when it never goes below).
    pub deepest_m: Vec<f64>,
    /// Frames on which an object is more than the tolerance below its resting height.
    pub frames_below: usize,
    /// Frames judged.
    pub frames: usize,
}

/// Which hands hold an object on a frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Holder {
    /// No hand within the contact radius.
    None,
    /// Only the left hand.
    Left,
    /// Only the right hand.
    Right,
    /// Both hands.
    Both,
}

impl Holder {
    fn of(left: bool, right: bool) -> Self {
        match (left, right) {
            (false, false) => Self::None,
            (true, false) => Self::Left,
            (false, true) => Self::Right,
            (true, true) => Self::Both,
        }
    }
}

/// The instruction-following counts of one clip (or, merged, of many).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct InstructionCounts {
    /// Objects the ground truth moves.
    pub moved_in_truth: usize,
    /// Of those, objects the generated clip moves too.
    pub moved_in_both: usize,
    /// Objects the ground truth leaves where they are.
    pub still_in_truth: usize,
    /// Of those, objects the generated clip moves anyway.
    pub moved_unasked: usize,
    /// Object-frames where the ground truth holds the object.
    pub held_frames: usize,
    /// Of those, frames where the generated clip holds it with the same hands.
    pub same_holder_frames: usize,
    /// Of the objects the ground truth moves, those that end on the same side of the body in
    /// both clips.
    pub same_side: usize,
    /// Final-position distance of each object the ground truth moves, metres.
    pub end_distances_m: Vec<f64>,
}

impl InstructionCounts {
    /// Adds another clip's counts.
    pub fn merge(mut self, other: &Self) -> Self {
        self.moved_in_truth += other.moved_in_truth;
        self.moved_in_both += other.moved_in_both;
        self.still_in_truth += other.still_in_truth;
        self.moved_unasked += other.moved_unasked;
        self.held_frames += other.held_frames;
        self.same_holder_frames += other.same_holder_frames;
        self.same_side += other.same_side;
        self.end_distances_m.extend_from_slice(&other.end_distances_m);
        self
    }

    /// Share of the objects the ground truth moves that the generated clip moves (`None`
    /// without any).
    pub fn moved_share(&self) -> Option<f64> {
        ratio(self.moved_in_both, self.moved_in_truth)
    }

    /// Share of the objects the ground truth leaves that the generated clip moves.
    pub fn unasked_share(&self) -> Option<f64> {
        ratio(self.moved_unasked, self.still_in_truth)
    }

    /// Holding-hand agreement: share of the ground truth's holding frames held by the same
    /// hands.
    pub fn holder_share(&self) -> Option<f64> {
        ratio(self.same_holder_frames, self.held_frames)
    }

    /// Share of moved objects that end on the same side.
    pub fn same_side_share(&self) -> Option<f64> {
        ratio(self.same_side, self.moved_in_truth)
    }

    /// Median final-position distance of the moved objects, metres.
    pub fn median_end_distance_m(&self) -> Option<f64> {
        median(&self.end_distances_m)
    }
}

/// `part / whole`, `None` for an empty whole.
pub(super) fn ratio(part: usize, whole: usize) -> Option<f64> {
    (whole > 0).then(|| part as f64 / whole as f64)
}

/// The median of some values (`None` for none; the mean of the middle two for an even count).
pub fn median(values: &[f64]) -> Option<f64> {
    if values.is_empty() {
        return None;
    }
    let mut sorted = values.to_vec();
    sorted.sort_by(f64::total_cmp);
    let middle = sorted.len() / 2;
    Some(if sorted.len().is_multiple_of(2) {
        (sorted[middle - 1] + sorted[middle]) / 2.0
    } else {
        sorted[middle]
    })
}

/// Whether an object moves over a clip: travel beyond [`MOVED_TRAVEL_M`] or rise beyond
/// [`MOVED_RISE_M`] from its first frame.
pub(super) fn moves(sample: &MotionSample<'_>, slot: usize, frames: usize) -> bool {
    let start = sample.object_pose(0, slot).position;
    (0..frames).any(|t| {
        let p = sample.object_pose(t, slot).position;
        (p - start).length() > MOVED_TRAVEL_M || p.y - start.y > MOVED_RISE_M
    })
}

/// The side of the body a point is on, judged on the body of `frame`: the left axis runs from
/// the right foot group's first joint to the left's, flattened onto the floor.
pub(super) fn side(body: &MotionSample<'_>, frame: usize, point: Vec3) -> Side {
    Side::of_across((point - body.joint(frame, 0)).dot(left_axis(body, frame)))
}

/// The body's left axis on `frame`: from the right foot group's first joint to the left's,
/// flattened onto the floor (callers check that both feet have joints).
pub(super) fn left_axis(body: &MotionSample<'_>, frame: usize) -> Vec3 {
    let groups = body.skeleton.groups();
    let left = body.joint(frame, groups.left_foot[0]) - body.joint(frame, groups.right_foot[0]);
    Vec3::new(left.x, 0.0, left.z).normalize_or_zero()
}

/// Compares a generated clip with its ground truth over the same frames (moved objects,
/// holding hands, where moved objects end).
///
/// # Shapes
/// - both samples: the same `T` frames and the same present slots
///
/// # Errors
/// Samples that fail [`MotionSample::frames`], different frame counts or present slots, a
/// skeleton without foot or hand joints.
pub fn instruction_following(
    generated: &MotionSample<'_>,
    truth: &MotionSample<'_>,
) -> Result<InstructionCounts> {
    let frames = truth.frames()?;
    if generated.frames()? != frames || generated.present != truth.present {
        return Err(EvalError::invalid(
            "generated clip",
            format!("the ground truth's {frames} frames and objects {:?}", truth.present),
            format!("{} frames and objects {:?}", generated.frames()?, generated.present),
        ));
    }
    let groups = truth.skeleton.groups();
    if groups.left_foot.is_empty() || groups.right_foot.is_empty() {
        return Err(EvalError::invalid("skeleton foot groups", "joints in both feet", "none"));
    }
    let holders = |sample: &MotionSample<'_>| -> Result<Vec<[Holder; MAX_OBJECTS]>> {
        Ok(hand_object_distances(sample)?
            .iter()
            .map(|slots| {
                slots.map(|[l, r]| Holder::of(l <= CONTACT_RADIUS_M, r <= CONTACT_RADIUS_M))
            })
            .collect())
    };
    let (generated_holders, truth_holders) = (holders(generated)?, holders(truth)?);
    let mut counts = InstructionCounts::default();
    for slot in (0..MAX_OBJECTS).filter(|&s| truth.present[s]) {
        let (truth_moves, generated_moves) =
            (moves(truth, slot, frames), moves(generated, slot, frames));
        if truth_moves {
            counts.moved_in_truth += 1;
            counts.moved_in_both += usize::from(generated_moves);
            let last = frames - 1;
            let (ours, theirs) = (
                generated.object_pose(last, slot).position,
                truth.object_pose(last, slot).position,
            );
            counts.end_distances_m.push(f64::from((ours - theirs).length()));
            counts.same_side += usize::from(side(truth, 0, ours) == side(truth, 0, theirs));
        } else {
            counts.still_in_truth += 1;
            counts.moved_unasked += usize::from(generated_moves);
        }
        for (ours, theirs) in generated_holders.iter().zip(&truth_holders) {
            if theirs[slot] != Holder::None {
                counts.held_frames += 1;
                counts.same_holder_frames += usize::from(ours[slot] == theirs[slot]);
            }
        }
    }
    Ok(counts)
}

/// How far each present object jumps between its last prefix position and the clip's first
/// frame, metres (`None` for an empty slot).
///
/// # Errors
/// A sample that fails [`MotionSample::frames`], a non-finite prefix position.
pub fn object_start_jumps(
    sample: &MotionSample<'_>,
    prefix_last: [Vec3; MAX_OBJECTS],
) -> Result<[Option<f64>; MAX_OBJECTS]> {
    sample.frames()?;
    if let Some(slot) = (0..MAX_OBJECTS).find(|&s| sample.present[s] && !prefix_last[s].is_finite())
    {
        return Err(EvalError::invalid(
            "last prefix object position",
            "finite numbers",
            format!("{} in slot {slot}", prefix_last[slot]),
        ));
    }
    Ok(std::array::from_fn(|slot| {
        sample.present[slot]
            .then(|| f64::from((sample.object_pose(0, slot).position - prefix_last[slot]).length()))
    }))
}

/// How far the objects sink below the height they rested at (`resting`: each object's
/// position before anything moved it, such as the first frame of the sequence): the drop of the
/// object's origin below that height on every clip frame. Objects rest on a support (a table, the
/// floor), and nothing should take them through it; a generated object that goes down where the
/// ground truth's stays is pushed into the table.
///
/// # Errors
/// A sample that fails [`MotionSample::frames`], a non-finite resting position.
pub fn object_sinking(sample: &MotionSample<'_>, resting: [Vec3; MAX_OBJECTS]) -> Result<Sinking> {
    let frames = sample.frames()?;
    if let Some(slot) = (0..MAX_OBJECTS).find(|&s| sample.present[s] && !resting[s].is_finite()) {
        return Err(EvalError::invalid(
            "resting object position",
            "finite numbers",
            format!("{} in slot {slot}", resting[slot]),
        ));
    }
    let present: Vec<usize> = (0..MAX_OBJECTS).filter(|&s| sample.present[s]).collect();
    let mut sinking = Sinking { deepest_m: vec![0.0; present.len()], frames, ..Sinking::default() };
    for t in 0..frames {
        let mut below = false;
        for (k, &slot) in present.iter().enumerate() {
            let drop = resting[slot].y - sample.object_pose(t, slot).position.y;
            sinking.deepest_m[k] = sinking.deepest_m[k].max(f64::from(drop));
            below |= drop > SINK_TOLERANCE_M;
        }
        sinking.frames_below += usize::from(below);
    }
    Ok(sinking)
}

/// The speed (m/s) of every present object on every frame where it is untouched: every hand
/// joint farther than [`UNTOUCHED_DISTANCE_M`] from its surface on this frame and the one
/// before. Speed is the displacement from the previous frame times `fps`.
///
/// # Errors
/// A sample that fails [`MotionSample::frames`], a frame rate that is not positive.
pub fn untouched_object_speeds(sample: &MotionSample<'_>, fps: f32) -> Result<Vec<f64>> {
    Ok(untouched_object_motion(sample, fps)?.into_iter().map(|(speed, _)| speed).collect())
}

/// The turning rate (degrees per second) of every present object on every frame where it is
/// untouched, by [`untouched_object_speeds`]' rule: the angle between its rotations on this
/// frame and the one before, times `fps`.
///
/// # Errors
/// As [`untouched_object_speeds`].
pub fn untouched_object_turn_rates(sample: &MotionSample<'_>, fps: f32) -> Result<Vec<f64>> {
    Ok(untouched_object_motion(sample, fps)?.into_iter().map(|(_, turn)| turn).collect())
}

/// [`untouched_object_speeds`] and [`untouched_object_turn_rates`] together, from one search
/// of the hand-object distances: `(m/s, degrees/s)` per untouched object and frame.
///
/// # Errors
/// As [`untouched_object_speeds`].
pub fn untouched_object_motion(sample: &MotionSample<'_>, fps: f32) -> Result<Vec<(f64, f64)>> {
    if !(fps.is_finite() && fps > 0.0) {
        return Err(EvalError::invalid("frame rate", "a positive number", fps));
    }
    let distances = hand_object_distances(sample)?;
    let untouched = |t: usize, slot: usize| {
        let [l, r] = distances[t][slot];
        l.min(r) > UNTOUCHED_DISTANCE_M
    };
    let rate = f64::from(fps);
    let mut motion = Vec::new();
    for t in 1..distances.len() {
        for slot in (0..MAX_OBJECTS).filter(|&s| sample.present[s]) {
            if untouched(t, slot) && untouched(t - 1, slot) {
                let (before, after) =
                    (sample.object_pose(t - 1, slot), sample.object_pose(t, slot));
                let travel = f64::from((after.position - before.position).length());
                motion.push((travel * rate, turn_degrees(before.rotation, after.rotation) * rate));
            }
        }
    }
    Ok(motion)
}

/// The angle in degrees of the rotation taking `from` to `to`: `atan2(sin, cos)` of the
/// relative rotation `to from^T` in `f64`, its trace giving the cosine and its antisymmetric
/// part the sine. (`acos` of the trace alone would read rounding as hundredths of a degree of
/// turn: it is ill-conditioned near 0.)
pub fn turn_degrees(from: Mat3, to: Mat3) -> f64 {
    let relative = to.as_dmat3() * from.as_dmat3().transpose();
    let (x, y, z) = (relative.x_axis, relative.y_axis, relative.z_axis);
    let cos = (x.x + y.y + z.z - 1.0) / 2.0;
    // Columns: `y.z` is row 2 of column 1, so this is (R21 - R12, R02 - R20, R10 - R01).
    let sin = DVec3::new(y.z - z.y, z.x - x.z, x.y - y.x).length() / 2.0;
    sin.atan2(cos).to_degrees()
}

/// How far each present object turns between its last prefix rotation and the clip's first
/// frame, degrees (`None` for an empty slot).
///
/// # Errors
/// A sample that fails [`MotionSample::frames`], a non-finite prefix rotation.
pub fn object_start_turns(
    sample: &MotionSample<'_>,
    prefix_last: [Mat3; MAX_OBJECTS],
) -> Result<[Option<f64>; MAX_OBJECTS]> {
    sample.frames()?;
    if let Some(slot) = (0..MAX_OBJECTS).find(|&s| sample.present[s] && !prefix_last[s].is_finite())
    {
        return Err(EvalError::invalid(
            "last prefix object rotation",
            "finite numbers",
            format!("{} in slot {slot}", prefix_last[slot]),
        ));
    }
    Ok(std::array::from_fn(|slot| {
        sample.present[slot]
            .then(|| turn_degrees(prefix_last[slot], sample.object_pose(0, slot).rotation))
    }))
}
