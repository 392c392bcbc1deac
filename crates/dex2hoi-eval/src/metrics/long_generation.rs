//! Long generations as a user meets them: a motion of many seconds generated from a scene's
//! first frame and a prompt, compared with the whole ground-truth sequence of that prompt. Does
//! it do the task as asked (once), and do the objects nobody holds stay where they were put?
//! (docs/CONVENTIONS.md, "The long-generation protocol".)
//!
//! Per object, from the whole motion:
//! - **Moved**: [`instruction_following`](super::instruction_following)'s rule (travel beyond
//!   [`MOVED_TRAVEL_M`](super::MOVED_TRAVEL_M) or a rise beyond
//!   [`MOVED_RISE_M`](super::MOVED_RISE_M) from the first frame).
//! - **Hands**: which hands hold it (a joint within
//!   [`CONTACT_RADIUS_M`](super::CONTACT_RADIUS_M) of its surface) on at least [`MIN_HOLD_S`]
//!   seconds of frames: none, left, right or both over the motion.
//! - **Sideways travel**: where it ends against where it started, along the body's left axis at
//!   the first frame, as a [`Side`] (beyond [`SIDE_MARGIN_M`](super::SIDE_MARGIN_M)): put down
//!   to the left, put back, handed to the right.
//! - **Lifts**: how many times it is lifted: runs of frames with its lowest point more than
//!   [`LIFT_M`] above its support (its lowest point on the first frame), runs closer than
//!   [`PUT_DOWN_GAP_S`] merged, runs shorter than [`MIN_LIFT_S`] ignored.
//! - **Off its support**: on frames where it is untouched
//!   ([`UNTOUCHED_DISTANCE_M`](super::UNTOUCHED_DISTANCE_M) from every hand joint, on this frame
//!   and the one before), how far its lowest point is below (sinking) or above (floating) its
//!   support; the worst of each per object.
//!
//! Per motion, where the autoregressive sampler joins its windows ([`seam_course`]):
//! - **Seam jumps**: on each window's first frame, how far the body (the mean over its joints)
//!   and each object move from the frame before. Within a window the body moves a few
//!   millimetres a frame; a seam where the new window does not continue its prefix shows as a
//!   jump of centimetres.
//! - **Floor drift**: how far the lowest joint ends above or below where it started (a person
//!   who rises a little at every seam ends standing in the air).
//!
//! A generation does the task **as asked** when every object moves if and only if the ground
//! truth's does and every moved object is held by the same hands and travels to the same side.
//! An object is **lifted again unasked** when the generation lifts it more times than the ground
//! truth does.

use dex2hoi_data::MAX_OBJECTS;
use glam::Vec3;

use crate::error::{EvalError, Result};

use super::contact::{CONTACT_RADIUS_M, hand_object_distances};
use super::instruction::{Side, left_axis, moves, ratio};
use super::sample::MotionSample;
use super::{UNTOUCHED_DISTANCE_M, median};

/// Height of an object's lowest point above its support beyond which it is lifted.
pub const LIFT_M: f32 = 0.03;
/// Seconds an object must stay lifted for a lift to count.
pub const MIN_LIFT_S: f32 = 0.25;
/// Seconds an object must be down between two lifts for them to count as two.
pub const PUT_DOWN_GAP_S: f32 = 0.5;
/// Seconds of frames a hand must hold an object for it to count as a hand that holds it.
pub const MIN_HOLD_S: f32 = 0.25;

/// Which hands hold an object over a motion.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct HandsUsed {
    /// The left hand holds it.
    pub left: bool,
    /// The right hand holds it.
    pub right: bool,
}

/// What one object does over a whole motion.
#[derive(Debug, Clone, PartialEq)]
pub struct ObjectCourse {
    /// It moves ([`moves`]).
    pub moved: bool,
    /// The hands that hold it.
    pub hands: HandsUsed,
    /// Where it ends against where it started, sideways.
    pub travel: Side,
    /// How many times it is lifted.
    pub lifts: usize,
    /// The deepest its lowest point goes below its support while untouched, metres (0 if
    /// never).
    pub deepest_sink_m: f64,
    /// The highest its lowest point stays above its support while untouched, metres (0 if
    /// never).
    pub highest_float_m: f64,
    /// Its speeds on untouched frames, m/s.
    pub untouched_speeds: Vec<f64>,
    /// Its position on the first frame.
    pub first_position: Vec3,
}

/// What every present object of a motion does; `support` is each slot's support height (the
/// height its lowest point rests at), `fps` the frame rate.
///
/// # Errors
/// A sample that fails [`MotionSample::frames`], a skeleton without foot or hand joints, a frame
/// rate that is not positive, a non-finite support height.
pub fn object_courses(
    sample: &MotionSample<'_>,
    support: [f32; MAX_OBJECTS],
    fps: f32,
) -> Result<[Option<ObjectCourse>; MAX_OBJECTS]> {
    let frames = sample.frames()?;
    if !(fps.is_finite() && fps > 0.0) {
        return Err(EvalError::invalid("frame rate", "a positive number", fps));
    }
    let groups = sample.skeleton.groups();
    if groups.left_foot.is_empty() || groups.right_foot.is_empty() {
        return Err(EvalError::invalid("skeleton foot groups", "joints in both feet", "none"));
    }
    if let Some(slot) = (0..MAX_OBJECTS).find(|&s| sample.present[s] && !support[s].is_finite()) {
        return Err(EvalError::invalid(
            "support height",
            "finite numbers",
            format!("{} in slot {slot}", support[slot]),
        ));
    }
    let seconds = |s: f32| ((s * fps).round() as usize).max(1);
    let distances = hand_object_distances(sample)?;
    let axis = left_axis(sample, 0);
    let mut courses = [None, None];
    for (slot, mesh) in sample.present_objects() {
        let height = |t: usize| {
            let pose = sample.object_pose(t, slot);
            mesh.lowest_height(pose.rotation, pose.position) - support[slot]
        };
        let heights: Vec<f32> = (0..frames).map(height).collect();
        let held = |hand: usize| {
            distances.iter().filter(|d| d[slot][hand] <= CONTACT_RADIUS_M).count()
                >= seconds(MIN_HOLD_S)
        };
        let untouched = |t: usize| {
            let [l, r] = distances[t][slot];
            l.min(r) > UNTOUCHED_DISTANCE_M
        };
        let (mut deepest, mut highest, mut speeds) = (0.0f64, 0.0f64, Vec::new());
        for t in 1..frames {
            if untouched(t) && untouched(t - 1) {
                deepest = deepest.max(f64::from(-heights[t]));
                highest = highest.max(f64::from(heights[t]));
                let travel =
                    sample.object_pose(t, slot).position - sample.object_pose(t - 1, slot).position;
                speeds.push(f64::from(travel.length() * fps));
            }
        }
        let start = sample.object_pose(0, slot).position;
        let end = sample.object_pose(frames - 1, slot).position;
        courses[slot] = Some(ObjectCourse {
            moved: moves(sample, slot, frames),
            hands: HandsUsed { left: held(0), right: held(1) },
            travel: Side::of_across((end - start).dot(axis)),
            lifts: lift_count(&heights, seconds(MIN_LIFT_S), seconds(PUT_DOWN_GAP_S)),
            deepest_sink_m: deepest,
            highest_float_m: highest,
            untouched_speeds: speeds,
            first_position: start,
        });
    }
    Ok(courses)
}

/// The number of lifts in a series of heights above the support: runs above [`LIFT_M`], runs
/// separated by fewer than `gap` frames merged, merged runs shorter than `shortest` frames
/// dropped.
pub fn lift_count(heights: &[f32], shortest: usize, gap: usize) -> usize {
    let mut runs: Vec<(usize, usize)> = Vec::new();
    for (t, &h) in heights.iter().enumerate() {
        if h <= LIFT_M {
            continue;
        }
        match runs.last_mut() {
            Some((_, end)) if t - *end <= gap => *end = t,
            _ => runs.push((t, t)),
        }
    }
    runs.iter().filter(|(start, end)| end - start + 1 >= shortest).count()
}

/// What a motion does at the seams of its windows and to the floor (see the module docs).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct SeamCourse {
    /// Per seam, the mean over joints of how far each moves onto the seam's frame, metres.
    pub body_jumps_m: Vec<f64>,
    /// Per seam and present object, how far it moves onto the seam's frame, metres.
    pub object_jumps_m: Vec<f64>,
    /// How far the lowest joint is from the first frame's height on the last frame, metres.
    pub floor_drift_m: f64,
}

/// The [`SeamCourse`] of a motion generated in windows of `window` frames: its seams are the
/// frames `window`, `2 window`, ... before the last.
///
/// # Errors
/// A sample that fails [`MotionSample::frames`], a window of 0 frames.
pub fn seam_course(sample: &MotionSample<'_>, window: usize) -> Result<SeamCourse> {
    let frames = sample.frames()?;
    if window == 0 {
        return Err(EvalError::invalid("window", "at least one frame", 0));
    }
    let joints = sample.skeleton.joint_count();
    let lowest = |t: usize| (0..joints).map(|j| sample.joint(t, j).y).fold(f32::INFINITY, f32::min);
    let mut course = SeamCourse {
        floor_drift_m: f64::from((lowest(frames - 1) - lowest(0)).abs()),
        ..SeamCourse::default()
    };
    for seam in (window..frames).step_by(window) {
        let body: f32 =
            (0..joints).map(|j| (sample.joint(seam, j) - sample.joint(seam - 1, j)).length()).sum();
        course.body_jumps_m.push(f64::from(body / joints as f32));
        for (slot, _) in sample.present_objects() {
            let jump = sample.object_pose(seam, slot).position
                - sample.object_pose(seam - 1, slot).position;
            course.object_jumps_m.push(f64::from(jump.length()));
        }
    }
    Ok(course)
}

/// The long-generation counts of one generation against its ground truth (or, merged, of
/// many).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct LongCounts {
    /// Generations judged.
    pub generations: usize,
    /// Of those, generations that do the task as asked.
    pub as_asked: usize,
    /// Objects judged.
    pub objects: usize,
    /// Objects the ground truth moves.
    pub moved_in_truth: usize,
    /// Objects whose moving agrees (moved by both, or by neither).
    pub moved_agree: usize,
    /// Of the objects the ground truth moves, those held by the same hands.
    pub hands_agree: usize,
    /// Of the objects the ground truth moves, those that travel to the same side.
    pub travel_agrees: usize,
    /// Objects lifted more times than in the ground truth.
    pub lifted_again: usize,
    /// Per object, the deepest sinking while untouched, metres.
    pub deepest_sink_m: Vec<f64>,
    /// Per object, the highest floating while untouched, metres.
    pub highest_float_m: Vec<f64>,
    /// Untouched objects' speeds over every untouched frame, m/s.
    pub untouched_speeds: Vec<f64>,
    /// Per object, the distance between where it was placed and the first generated frame, m.
    pub start_jumps_m: Vec<f64>,
    /// The body's jumps at every seam ([`SeamCourse::body_jumps_m`]), metres.
    pub body_seam_jumps_m: Vec<f64>,
    /// The objects' jumps at every seam ([`SeamCourse::object_jumps_m`]), metres.
    pub object_seam_jumps_m: Vec<f64>,
    /// Per generation, the floor drift ([`SeamCourse::floor_drift_m`]), metres.
    pub floor_drifts_m: Vec<f64>,
}

impl LongCounts {
    /// Adds another generation's counts.
    pub fn merge(mut self, other: &Self) -> Self {
        self.generations += other.generations;
        self.as_asked += other.as_asked;
        self.objects += other.objects;
        self.moved_in_truth += other.moved_in_truth;
        self.moved_agree += other.moved_agree;
        self.hands_agree += other.hands_agree;
        self.travel_agrees += other.travel_agrees;
        self.lifted_again += other.lifted_again;
        self.deepest_sink_m.extend_from_slice(&other.deepest_sink_m);
        self.highest_float_m.extend_from_slice(&other.highest_float_m);
        self.untouched_speeds.extend_from_slice(&other.untouched_speeds);
        self.start_jumps_m.extend_from_slice(&other.start_jumps_m);
        self.body_seam_jumps_m.extend_from_slice(&other.body_seam_jumps_m);
        self.object_seam_jumps_m.extend_from_slice(&other.object_seam_jumps_m);
        self.floor_drifts_m.extend_from_slice(&other.floor_drifts_m);
        self
    }

    /// Adds a generation's [`SeamCourse`].
    pub fn with_seams(mut self, seams: &SeamCourse) -> Self {
        self.body_seam_jumps_m.extend_from_slice(&seams.body_jumps_m);
        self.object_seam_jumps_m.extend_from_slice(&seams.object_jumps_m);
        self.floor_drifts_m.push(seams.floor_drift_m);
        self
    }

    /// The share of generations that do the task as asked.
    pub fn as_asked_share(&self) -> Option<f64> {
        ratio(self.as_asked, self.generations)
    }

    /// The share of objects whose moving agrees with the ground truth.
    pub fn moved_share(&self) -> Option<f64> {
        ratio(self.moved_agree, self.objects)
    }

    /// The share of the moved objects held by the same hands as in the ground truth.
    pub fn hands_share(&self) -> Option<f64> {
        ratio(self.hands_agree, self.moved_in_truth)
    }

    /// The share of the moved objects that travel to the ground truth's side.
    pub fn travel_share(&self) -> Option<f64> {
        ratio(self.travel_agrees, self.moved_in_truth)
    }

    /// The share of objects lifted again unasked.
    pub fn lifted_again_share(&self) -> Option<f64> {
        ratio(self.lifted_again, self.objects)
    }

    /// Per object, the worst of its sinking and floating while untouched, metres.
    pub fn off_support_m(&self) -> Vec<f64> {
        self.deepest_sink_m.iter().zip(&self.highest_float_m).map(|(s, f)| s.max(*f)).collect()
    }
}

/// Medians of [`LongCounts`]' lists (`None` when empty): off support, sinking, floating,
/// untouched speed, start jump, the body's and the objects' seam jumps, floor drift.
pub fn long_medians(counts: &LongCounts) -> [Option<f64>; 8] {
    [
        median(&counts.off_support_m()),
        median(&counts.deepest_sink_m),
        median(&counts.highest_float_m),
        median(&counts.untouched_speeds),
        median(&counts.start_jumps_m),
        median(&counts.body_seam_jumps_m),
        median(&counts.object_seam_jumps_m),
        median(&counts.floor_drifts_m),
    ]
}

/// Judges a long generation against the whole ground-truth sequence of its prompt. Both start
/// from the same scene: `placed` is where each object was put at the start (its first-frame
/// position in the generation's conditioning), `support` each slot's support height; the two
/// motions may have different lengths.
///
/// # Errors
/// As [`object_courses`]; different present slots.
pub fn long_generation(
    generated: &MotionSample<'_>,
    truth: &MotionSample<'_>,
    placed: [Vec3; MAX_OBJECTS],
    support: [f32; MAX_OBJECTS],
    fps: f32,
) -> Result<LongCounts> {
    if generated.present != truth.present {
        return Err(EvalError::invalid(
            "generated motion",
            format!("the ground truth's objects {:?}", truth.present),
            format!("{:?}", generated.present),
        ));
    }
    let ours = object_courses(generated, support, fps)?;
    judge_courses(&ours, &object_courses(truth, support, fps)?, placed)
}

/// [`long_generation`] on the motions' [`object_courses`], so that a ground truth judged
/// against many generations is traced once.
///
/// # Errors
/// Courses of different present slots.
pub fn judge_courses(
    ours: &[Option<ObjectCourse>; MAX_OBJECTS],
    theirs: &[Option<ObjectCourse>; MAX_OBJECTS],
    placed: [Vec3; MAX_OBJECTS],
) -> Result<LongCounts> {
    let mut counts = LongCounts { generations: 1, ..LongCounts::default() };
    let mut as_asked = true;
    for slot in 0..MAX_OBJECTS {
        let (ours, theirs) = match (&ours[slot], &theirs[slot]) {
            (Some(ours), Some(theirs)) => (ours, theirs),
            (None, None) => continue,
            _ => {
                return Err(EvalError::invalid(
                    "generated motion",
                    "the ground truth's objects",
                    format!("slot {slot} present in only one of them"),
                ));
            }
        };
        counts.objects += 1;
        let moved_agree = ours.moved == theirs.moved;
        counts.moved_agree += usize::from(moved_agree);
        as_asked &= moved_agree;
        if theirs.moved {
            counts.moved_in_truth += 1;
            let hands = ours.hands == theirs.hands;
            let travel = ours.travel == theirs.travel;
            counts.hands_agree += usize::from(hands);
            counts.travel_agrees += usize::from(travel);
            as_asked &= hands && travel;
        }
        counts.lifted_again += usize::from(ours.lifts > theirs.lifts);
        counts.deepest_sink_m.push(ours.deepest_sink_m);
        counts.highest_float_m.push(ours.highest_float_m);
        counts.untouched_speeds.extend_from_slice(&ours.untouched_speeds);
        counts.start_jumps_m.push(f64::from((ours.first_position - placed[slot]).length()));
    }
    counts.as_asked = usize::from(as_asked);
    Ok(counts)
}
