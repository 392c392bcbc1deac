//! Which objects have been moved and set down again since the prompt in force began: the
//! memory of the task beyond the window's prefix that the condition of a model with
//! `settled_objects` reads (docs/CONVENTIONS.md, "Denoiser").
//!
//! A window's prefix is one second long; a task that lifts an object, holds it and puts it back
//! takes longer. From the prefix alone, a person standing beside a box that has already been
//! lifted and put back looks like one who has not started yet, so a model that reads only the
//! prefix and the prompt clock may do the task again. [`SettledObjects`] follows every frame
//! from the prompt's first one and says, per object, whether it has **moved** (the long
//! protocol's rule: travel beyond [`MOVED_TRAVEL_M`] or a rise beyond [`MOVED_RISE_M`] from
//! where it stood) and is **set down** now: over the last [`STILL_FRAMES`] frames it stayed
//! within [`STILL_M`] of where it is, at most [`SET_DOWN_HEIGHT_M`] off the height it started
//! at. Both the training batch (on the ground truth) and the sampler (on what it generated)
//! run the same tracker, frame by frame.
//!
//! The same tracker says where each object was **reached**: the last frame before it first
//! moved, whose arm pose is the one that took it and so the one that puts it back
//! ([`SettledObjects::left_at`], [`reach_frames`]; the reach frame in the prefix,
//! `reach_in_prefix`).

use std::collections::VecDeque;

use glam::Vec3;

use crate::MAX_OBJECTS;

/// Travel from the first frame beyond which an object has moved.
pub const MOVED_TRAVEL_M: f32 = 0.10;
/// Rise above the first frame beyond which an object has moved.
pub const MOVED_RISE_M: f32 = 0.05;
/// Frames an object must stay still to count as set down: half a second at the data's 20 fps,
/// longer than any pause of a held object in the procedural tasks but the hold of two objects
/// up in the air, which [`SET_DOWN_HEIGHT_M`] tells apart.
pub const STILL_FRAMES: usize = 10;
/// How far an object may move over [`STILL_FRAMES`] and still count as still.
pub const STILL_M: f32 = 0.01;
/// How far above or below the height it started at an object may stand and count as set down
/// (objects are put down on the support they were taken from).
pub const SET_DOWN_HEIGHT_M: f32 = 0.02;

/// Follows the objects of a motion frame by frame from the first frame of a prompt.
#[derive(Debug, Clone, Default)]
pub struct SettledObjects {
    start: Option<[Vec3; MAX_OBJECTS]>,
    moved: [bool; MAX_OBJECTS],
    /// Frames read so far.
    read: usize,
    /// The frame (counted from the first read) on which each object first counted as moved.
    left_at: [Option<usize>; MAX_OBJECTS],
    /// The last [`STILL_FRAMES`] positions, oldest first.
    recent: VecDeque<[Vec3; MAX_OBJECTS]>,
}

impl SettledObjects {
    /// A tracker that has seen no frame.
    pub fn new() -> Self {
        Self::default()
    }

    /// A tracker that has read `frames` frames of `position(frame)` from frame 0.
    pub fn after(frames: usize, position: impl Fn(usize) -> [Vec3; MAX_OBJECTS]) -> Self {
        let mut tracker = Self::new();
        for t in 0..frames {
            tracker.push(position(t));
        }
        tracker
    }

    /// Reads the objects' positions on the next frame (the first is where they stood when the
    /// prompt began).
    pub fn push(&mut self, positions: [Vec3; MAX_OBJECTS]) {
        let start = *self.start.get_or_insert(positions);
        for slot in 0..MAX_OBJECTS {
            let (p, s) = (positions[slot], start[slot]);
            self.moved[slot] |= (p - s).length() > MOVED_TRAVEL_M || p.y - s.y > MOVED_RISE_M;
            if self.moved[slot] && self.left_at[slot].is_none() {
                self.left_at[slot] = Some(self.read);
            }
        }
        self.read += 1;
        if self.recent.len() == STILL_FRAMES {
            self.recent.pop_front();
        }
        self.recent.push_back(positions);
    }

    /// Whether each object has moved since the first frame and is set down now; false for
    /// all before [`STILL_FRAMES`] frames have been read.
    pub fn settled(&self) -> [bool; MAX_OBJECTS] {
        let (Some(start), Some(now)) = (self.start, self.recent.back()) else {
            return [false; MAX_OBJECTS];
        };
        std::array::from_fn(|slot| {
            self.moved[slot]
                && self.recent.len() == STILL_FRAMES
                && (now[slot].y - start[slot].y).abs() <= SET_DOWN_HEIGHT_M
                && self.recent.iter().all(|p| (p[slot] - now[slot]).length() <= STILL_M)
        })
    }

    /// The frame, counted from the first one read, on which each object first counted as moved
    /// (never the first: an object stands where it starts); `None` while it has not.
    pub fn left_at(&self) -> [Option<usize>; MAX_OBJECTS] {
        self.left_at
    }

    /// How many frames have been read.
    pub fn frames_read(&self) -> usize {
        self.read
    }

    /// The frame each object was reached, as the first prefix token of a window whose prefix
    /// starts at `first_prefix_frame` and ends at the last frame read shows it: the last frame
    /// before the object first moved, when that is before `first_prefix_frame`, otherwise
    /// `first_prefix_frame` itself (the prefix still shows the object where it stood, or
    /// leaving it).
    pub fn reach_frames(&self, first_prefix_frame: usize) -> [usize; MAX_OBJECTS] {
        self.left_at.map(|left| match left {
            Some(left) => (left - 1).min(first_prefix_frame),
            None => first_prefix_frame,
        })
    }

    /// [`Self::settled`] as the condition reads it: 1 or 0 per slot.
    pub fn flags(&self) -> [f32; MAX_OBJECTS] {
        self.settled().map(|s| f32::from(u8::from(s)))
    }
}

/// [`SettledObjects::settled`] after reading `frames` frames of `position(frame)` from frame 0.
pub fn settled_after(
    frames: usize,
    position: impl Fn(usize) -> [Vec3; MAX_OBJECTS],
) -> [bool; MAX_OBJECTS] {
    SettledObjects::after(frames, position).settled()
}

/// [`SettledObjects::reach_frames`] after reading `position(frame)` from frame 0 up to, not
/// including, `prefix_end`.
pub fn reach_frames(
    first_prefix_frame: usize,
    prefix_end: usize,
    position: impl Fn(usize) -> [Vec3; MAX_OBJECTS],
) -> [usize; MAX_OBJECTS] {
    SettledObjects::after(prefix_end, position).reach_frames(first_prefix_frame)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Slot 0 follows `track`; slot 1 stands still at the origin.
    fn run(track: &[Vec3]) -> Vec<[bool; MAX_OBJECTS]> {
        let mut tracker = SettledObjects::new();
        track
            .iter()
            .map(|&p| {
                tracker.push([p, Vec3::ZERO]);
                tracker.settled()
            })
            .collect()
    }

    fn lift_and_put_back(hold_up: usize, rest: usize) -> Vec<Vec3> {
        let up = |k: usize| Vec3::new(0.0, 0.02 * k as f32, 0.0);
        let mut track = vec![Vec3::ZERO; 5];
        track.extend((0..=10).map(up));
        track.extend(std::iter::repeat_n(up(10), hold_up));
        track.extend((0..=10).rev().map(up));
        track.extend(std::iter::repeat_n(Vec3::ZERO, rest));
        track
    }

    #[test]
    fn an_object_never_moved_is_never_settled() {
        for states in run(&[Vec3::ZERO; 40]) {
            assert_eq!(states, [false, false]);
        }
    }

    #[test]
    fn lifted_and_put_back_is_settled_once_still_long_enough() {
        let track = lift_and_put_back(15, 30);
        let states = run(&track);
        let back = track.len() - 30;
        // Held still 20 cm up for 15 frames: moved, still, but not on its support.
        assert!(states[..back].iter().all(|s| !s[0]), "{states:?}");
        // Back down on the way down's last frame (`back - 1`): settled once the last
        // `STILL_FRAMES` frames are all there.
        for (k, s) in states[back..].iter().enumerate() {
            assert_eq!(s[0], k + 2 >= STILL_FRAMES, "rest frame {k}");
            assert!(!s[1]);
        }
    }

    #[test]
    fn a_slow_slide_is_not_still_and_a_small_nudge_is_not_a_move() {
        // Pushed 40 cm along the table at 2 cm a frame: moved, never still.
        let slide: Vec<Vec3> = (0..20).map(|k| Vec3::new(0.02 * k as f32, 0.0, 0.0)).collect();
        assert!(run(&slide).iter().all(|s| !s[0]));
        // Nudged 5 cm and left: still, but never moved.
        let mut nudge = vec![Vec3::ZERO; 5];
        nudge.extend(std::iter::repeat_n(Vec3::new(0.05, 0.0, 0.0), 20));
        assert!(run(&nudge).iter().all(|s| !s[0]));
        // Carried 15 cm to the side and put down there: settled.
        let mut carried = vec![Vec3::ZERO; 5];
        carried.extend((0..=15).map(|k| Vec3::new(0.01 * k as f32, 0.0, 0.0)));
        carried.extend(std::iter::repeat_n(Vec3::new(0.15, 0.0, 0.0), STILL_FRAMES));
        assert!(run(&carried).last().unwrap()[0]);
    }

    #[test]
    fn settled_after_reads_the_same_as_the_tracker() {
        let track = lift_and_put_back(3, 12);
        let states = run(&track);
        for frames in 1..=track.len() {
            assert_eq!(settled_after(frames, |t| [track[t], Vec3::ZERO]), states[frames - 1]);
        }
        assert_eq!(settled_after(0, |_| unreachable!()), [false, false]);
    }

    #[test]
    fn an_object_is_reached_on_the_last_frame_before_it_moved() {
        // Rises 2 cm a frame from frame 5: beyond 5 cm on frame 8, so reached on frame 7.
        let track = lift_and_put_back(15, 30);
        let mut tracker = SettledObjects::new();
        for &p in &track {
            tracker.push([p, Vec3::ZERO]);
        }
        assert_eq!(tracker.left_at(), [Some(8), None]);
        let reach = |first, end| reach_frames(first, end, |t| [track[t], Vec3::ZERO]);
        // Before it has moved, and while the prefix still shows it leaving: the prefix's own
        // first frame, for both objects.
        assert_eq!(reach(0, 8), [0, 0]);
        assert_eq!(reach(3, 20), [3, 3]);
        assert_eq!(reach(7, 20), [7, 7]);
        // Once it left before the prefix: the frame it was reached; the still one follows
        // the prefix.
        assert_eq!(reach(8, 20), [7, 8]);
        assert_eq!(reach(30, 50), [7, 30]);
        // Put back and still: the first departure counts, not the return.
        assert_eq!(reach(60, track.len()), [7, 60]);
    }
}
