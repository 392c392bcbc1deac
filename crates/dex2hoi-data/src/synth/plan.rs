//! Task plans of the procedural dataset: object trajectories on and above the table, and which
//! hand holds which object when.

use glam::{Mat3, Quat, Vec3};
use rand::Rng;
use rand_chacha::ChaCha8Rng;

use dex2hoi_repr::rotation::axis_angle_to_matrix;

use super::catalogue::{CATALOGUE, CatalogueObject};
use super::pose::Hand;

/// The task families.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Task {
    /// Pick an object up with one hand and put it down elsewhere.
    PickPlace,
    /// Lift a wide object with both hands and put it down.
    LiftBoth,
    /// Pick an object up with one hand, pass it to the other, put it down.
    Handover,
    /// Pick up one object in each hand, hold both, put them down.
    HoldTwo,
    /// Hold a receiver with one hand and pour into it from an object held in the other.
    Pour,
    /// Move one object next to another with one hand.
    MoveNextTo,
    /// Pick an object up, turn it around to look at it, put it back.
    Inspect,
    /// Swap the places of two objects, one after the other.
    Swap,
}

impl Task {
    /// Every task family.
    pub const ALL: [Task; 8] = [
        Task::PickPlace,
        Task::LiftBoth,
        Task::Handover,
        Task::HoldTwo,
        Task::Pour,
        Task::MoveNextTo,
        Task::Inspect,
        Task::Swap,
    ];

    /// The action label.
    pub fn label(self) -> &'static str {
        match self {
            Task::PickPlace => "pick_place",
            Task::LiftBoth => "lift_both",
            Task::Handover => "handover",
            Task::HoldTwo => "hold_two",
            Task::Pour => "pour",
            Task::MoveNextTo => "move_next_to",
            Task::Inspect => "inspect",
            Task::Swap => "swap",
        }
    }
}

/// How a hand holds an object, in the object's frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum GraspStyle {
    /// Palm on top, fingers forward and curled down over the far side.
    Top,
    /// Palm against the object's side facing the hand, fingers forward, thumb up.
    Side,
}

/// A rigid pose.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Pose {
    /// Rotation.
    pub rotation: Mat3,
    /// Position.
    pub position: Vec3,
}

impl Pose {
    /// Composition `self * local`.
    pub fn compose(&self, local: &Pose) -> Pose {
        Pose {
            rotation: self.rotation * local.rotation,
            position: self.position + self.rotation * local.position,
        }
    }
}

/// Minimum-jerk timing `10u^3 - 15u^4 + 6u^5` on `[0, 1]`.
pub fn minimum_jerk(u: f32) -> f32 {
    let u = u.clamp(0.0, 1.0);
    u * u * u * (10.0 + u * (-15.0 + 6.0 * u))
}

/// Keyframed object motion: still before the first and after the last key, minimum-jerk
/// position and slerped rotation between keys.
#[derive(Debug, Clone, PartialEq)]
pub struct Track {
    /// `(time in seconds, pose)`, times increasing.
    pub keys: Vec<(f32, Pose)>,
}

impl Track {
    /// The pose at a time.
    pub fn at(&self, t: f32) -> Pose {
        let keys = &self.keys;
        if t <= keys[0].0 {
            return keys[0].1;
        }
        for pair in keys.windows(2) {
            let ((t0, a), (t1, b)) = (pair[0], pair[1]);
            if t <= t1 {
                let s = minimum_jerk((t - t0) / (t1 - t0).max(1e-6));
                let rotation = Quat::from_mat3(&a.rotation).slerp(Quat::from_mat3(&b.rotation), s);
                return Pose {
                    rotation: Mat3::from_quat(rotation),
                    position: a.position.lerp(b.position, s),
                };
            }
        }
        keys[keys.len() - 1].1
    }
}

/// One hand holding one object over a time interval.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Attachment {
    /// The hand.
    pub hand: Hand,
    /// Index of the object in the plan.
    pub object: usize,
    /// How it holds it.
    pub style: GraspStyle,
    /// When the hand starts reaching.
    pub reach_start: f32,
    /// When the hand arrives at the grasp (the object is still until the fingers close).
    pub start: f32,
    /// When the hand lets go (the object is still from a little before).
    pub end: f32,
    /// When the hand is back at rest.
    pub retract_end: f32,
}

/// A scene and what happens in it.
#[derive(Debug, Clone, PartialEq)]
pub struct Plan {
    /// The task family.
    pub task: Task,
    /// Seconds.
    pub duration: f32,
    /// Height of the table top.
    pub table_height: f32,
    /// Objects: catalogue entry and trajectory.
    pub objects: Vec<(&'static CatalogueObject, Track)>,
    /// Who holds what, when.
    pub attachments: Vec<Attachment>,
    /// Descriptions.
    pub texts: Vec<String>,
}

/// Seconds the fingers take to close after arriving and to open before leaving; the object
/// is still then.
pub const CLOSE_TIME: f32 = 0.25;

/// The table and the sampler of places on it (character frame: the character stands at the
/// origin facing +Z).
struct Table {
    height: f32,
    near: f32,
}

impl Table {
    /// A resting pose: upright, small yaw, bottom on the table top.
    fn rest(&self, object: &CatalogueObject, x: f32, z: f32, yaw: f32) -> Pose {
        Pose {
            rotation: axis_angle_to_matrix(Vec3::Y * yaw),
            position: Vec3::new(x, self.height + object.half_extents().y, z),
        }
    }

    fn depth(&self, rng: &mut ChaCha8Rng) -> f32 {
        self.near + rng.random_range(0.10..0.22)
    }
}

fn footprint(object: &CatalogueObject) -> f32 {
    let h = object.half_extents();
    h.x.max(h.z)
}

fn pick<'a>(rng: &mut ChaCha8Rng, pool: &[&'a CatalogueObject]) -> &'a CatalogueObject {
    pool[rng.random_range(0..pool.len())]
}

fn pool(filter: impl Fn(&CatalogueObject) -> bool) -> Vec<&'static CatalogueObject> {
    CATALOGUE.iter().filter(|o| filter(o)).collect()
}

/// The lifted waypoint between two resting poses.
fn apex(a: &Pose, b: &Pose, lift: f32) -> Pose {
    Pose { rotation: a.rotation, position: (a.position + b.position) * 0.5 + Vec3::Y * lift }
}

struct Builder<'r> {
    rng: &'r mut ChaCha8Rng,
    t: f32,
    objects: Vec<(&'static CatalogueObject, Track)>,
    attachments: Vec<Attachment>,
}

impl Builder<'_> {
    fn duration(&mut self, range: std::ops::Range<f32>) -> f32 {
        self.rng.random_range(range)
    }

    fn add_object(&mut self, object: &'static CatalogueObject, rest: Pose) -> usize {
        self.objects.push((object, Track { keys: vec![(0.0, rest)] }));
        self.objects.len() - 1
    }

    fn key(&mut self, object: usize, time: f32, pose: Pose) {
        self.objects[object].1.keys.push((time, pose));
    }

    fn last_pose(&self, object: usize) -> Pose {
        self.objects[object].1.keys.last().map(|k| k.1).expect("a first key")
    }

    /// A hand reaches for an object starting now; returns the grasp time.
    fn reach(&mut self) -> f32 {
        let reach = self.duration(0.7..1.1);
        self.t + reach
    }

    /// Carries `object` through `poses` (each leg 0.6-1.0 s) starting once the fingers closed
    /// at `start`; returns the time the object comes to rest.
    fn carry(&mut self, object: usize, start: f32, poses: &[Pose]) -> f32 {
        let mut t = start + CLOSE_TIME;
        self.key(object, t, self.last_pose(object));
        for pose in poses {
            t += self.duration(0.6..1.0);
            self.key(object, t, *pose);
        }
        t
    }

    fn attach(
        &mut self,
        hand: Hand,
        object: usize,
        style: GraspStyle,
        reach_start: f32,
        start: f32,
        end: f32,
    ) -> f32 {
        let retract_end = end + self.rng.random_range(0.6..0.9);
        self.attachments.push(Attachment {
            hand,
            object,
            style,
            reach_start,
            start,
            end,
            retract_end,
        });
        retract_end
    }
}

/// Plans one sequence of a task.
pub fn plan_task(task: Task, rng: &mut ChaCha8Rng) -> Plan {
    let table = Table { height: rng.random_range(0.86..0.94), near: rng.random_range(0.20..0.26) };
    let idle = rng.random_range(0.4..0.9);
    let mut b = Builder { rng, t: idle, objects: Vec::new(), attachments: Vec::new() };
    let hand = if b.rng.random_bool(0.5) { Hand::Left } else { Hand::Right };
    let yaw = |rng: &mut ChaCha8Rng| rng.random_range(-0.3..0.3);
    let side_x = |rng: &mut ChaCha8Rng, hand: Hand| hand.side() * rng.random_range(0.10..0.22);
    let one = pool(|o| o.one_handed && o.name != "plate" && o.name != "book");
    let texts: Vec<String>;
    match task {
        Task::PickPlace | Task::Inspect => {
            let object = pick(b.rng, &pool(|o| o.one_handed));
            let (x, z, y) = (side_x(b.rng, hand), table.depth(b.rng), yaw(b.rng));
            let rest = table.rest(object, x, z, y);
            let o = b.add_object(object, rest);
            let start = b.reach();
            let end = if task == Task::PickPlace {
                let dx = hand.side()
                    * b.rng.random_range(0.10..0.16)
                    * if b.rng.random_bool(0.5) { 1.0 } else { -1.0 };
                let target =
                    table.rest(object, (x + dx).clamp(-0.25, 0.25), table.depth(b.rng), yaw(b.rng));
                let towards = if target.position.x > rest.position.x { "left" } else { "right" };
                let lift = b.duration(0.12..0.2);
                let arrive = b.carry(o, start, &[apex(&rest, &target, lift), target]);
                texts = vec![
                    format!(
                        "The person picks up the {} with the {} hand and puts it down to the {towards}.",
                        object.name,
                        hand.word()
                    ),
                    format!(
                        "Using the {} hand, someone lifts the {} and sets it down a little to the {towards}.",
                        hand.word(),
                        object.name
                    ),
                    format!(
                        "A person moves the {} to the {towards} with the {} hand.",
                        object.name,
                        hand.word()
                    ),
                ];
                arrive + CLOSE_TIME
            } else {
                let held = Pose {
                    rotation: rest.rotation,
                    position: Vec3::new(hand.side() * 0.12, 1.18, table.near + 0.12),
                };
                let turn = |angles: Vec3| Pose {
                    rotation: axis_angle_to_matrix(angles) * rest.rotation,
                    position: held.position,
                };
                let (spin, tilt) = (b.duration(0.8..1.3), b.duration(0.3..0.6));
                let arrive = b.carry(
                    o,
                    start,
                    &[
                        held,
                        turn(Vec3::new(tilt, spin, 0.0)),
                        turn(Vec3::new(-tilt, -spin * 0.5, tilt * 0.5)),
                        held,
                        rest,
                    ],
                );
                texts = vec![
                    format!(
                        "The person picks up the {} with the {} hand, turns it around to look at it and puts it back.",
                        object.name,
                        hand.word()
                    ),
                    format!(
                        "Someone inspects the {} held in the {} hand and then returns it to the table.",
                        object.name,
                        hand.word()
                    ),
                    format!(
                        "A person lifts the {} with the {} hand, examines it from several sides and sets it down.",
                        object.name,
                        hand.word()
                    ),
                ];
                arrive + CLOSE_TIME
            };
            b.attach(hand, o, GraspStyle::Top, idle, start, end);
            b.t = end;
        }
        Task::LiftBoth => {
            let object = pick(b.rng, &pool(|o| o.two_handed));
            let rest = table.rest(
                object,
                b.rng.random_range(-0.04..0.04),
                table.near + footprint(object) + 0.05,
                yaw(b.rng) * 0.3,
            );
            let o = b.add_object(object, rest);
            let start = b.reach();
            let lift = b.duration(0.15..0.3);
            let up = Pose { rotation: rest.rotation, position: rest.position + Vec3::Y * lift };
            let arrive = b.carry(o, start, &[up, up, rest]);
            let end = arrive + CLOSE_TIME;
            b.attach(Hand::Left, o, GraspStyle::Side, idle, start, end);
            b.attach(Hand::Right, o, GraspStyle::Side, idle, start, end);
            texts = vec![
                format!(
                    "The person lifts the {} with both hands and puts it back down.",
                    object.name
                ),
                format!(
                    "Someone raises the {} using both hands, holds it for a moment and lowers it again.",
                    object.name
                ),
                format!(
                    "A person picks up the {} with two hands and sets it back on the table.",
                    object.name
                ),
            ];
        }
        Task::Handover => {
            let object = pick(b.rng, &one);
            let rest = table.rest(object, side_x(b.rng, hand), table.depth(b.rng), yaw(b.rng));
            let o = b.add_object(object, rest);
            let start = b.reach();
            let middle = Pose {
                rotation: rest.rotation,
                position: Vec3::new(0.0, table.height + 0.25, table.near + 0.14),
            };
            let arrive = b.carry(o, start, &[middle]);
            // The other hand reaches while the object comes to the middle and takes it.
            let other = hand.other();
            let take = arrive + 0.1;
            let give_end = take + CLOSE_TIME + 0.3;
            b.attach(hand, o, GraspStyle::Top, idle, start, give_end);
            b.key(o, give_end, middle);
            let target = table.rest(object, side_x(b.rng, other), table.depth(b.rng), yaw(b.rng));
            b.t = give_end;
            let lift = b.duration(0.08..0.15);
            let place = b.carry(o, give_end - CLOSE_TIME, &[apex(&middle, &target, lift), target]);
            let end = place + CLOSE_TIME;
            let reach_start = take - b.duration(0.8..1.1);
            b.attach(other, o, GraspStyle::Side, reach_start, take, end);
            texts = vec![
                format!(
                    "The person picks up the {} with the {} hand, passes it to the {} hand and puts it down on the {} side.",
                    object.name,
                    hand.word(),
                    other.word(),
                    other.word()
                ),
                format!(
                    "Someone hands the {} over from the {} hand to the {} hand.",
                    object.name,
                    hand.word(),
                    other.word()
                ),
                format!(
                    "A person lifts the {} with the {} hand, gives it to the other hand and places it to the {}.",
                    object.name,
                    hand.word(),
                    other.word()
                ),
            ];
        }
        Task::HoldTwo | Task::Swap => {
            let left_object = pick(b.rng, &one);
            let others: Vec<_> =
                one.iter().copied().filter(|o| o.name != left_object.name).collect();
            let right_object = pick(b.rng, &others);
            let spread = if task == Task::Swap { 0.06..0.11 } else { 0.09..0.16 };
            // Swapped objects cross the body: keep them close to the near edge.
            let depth = |b: &mut Builder<'_>| {
                if task == Task::Swap {
                    table.near + b.rng.random_range(0.07..0.12)
                } else {
                    table.depth(b.rng)
                }
            };
            let (left_depth, right_depth) = (depth(&mut b), depth(&mut b));
            let left_rest =
                table.rest(left_object, b.rng.random_range(spread.clone()), left_depth, yaw(b.rng));
            let right_rest =
                table.rest(right_object, -b.rng.random_range(spread), right_depth, yaw(b.rng));
            let lo = b.add_object(left_object, left_rest);
            let ro = b.add_object(right_object, right_rest);
            if task == Task::HoldTwo {
                let start_left = b.reach();
                let delay = b.duration(0.0..0.4);
                let start_right = start_left + delay;
                let (lift_left, lift_right) = (b.duration(0.12..0.25), b.duration(0.12..0.25));
                let hold = b.duration(0.8..1.4);
                let up_left =
                    Pose { position: left_rest.position + Vec3::Y * lift_left, ..left_rest };
                let up_right =
                    Pose { position: right_rest.position + Vec3::Y * lift_right, ..right_rest };
                let left_up = b.carry(lo, start_left, &[up_left]);
                let right_up = b.carry(ro, start_right, &[up_right]);
                let down_at = left_up.max(right_up) + hold;
                b.key(lo, down_at, up_left);
                b.key(ro, down_at, up_right);
                let left_done = b.carry(lo, down_at - CLOSE_TIME, &[left_rest]);
                let right_done = b.carry(ro, down_at - CLOSE_TIME, &[right_rest]);
                b.attach(Hand::Left, lo, GraspStyle::Top, idle, start_left, left_done + CLOSE_TIME);
                b.attach(
                    Hand::Right,
                    ro,
                    GraspStyle::Top,
                    idle + delay,
                    start_right,
                    right_done + CLOSE_TIME,
                );
                texts = vec![
                    format!(
                        "The person picks up the {} with the left hand and the {} with the right hand, holds both and puts them back.",
                        left_object.name, right_object.name
                    ),
                    format!(
                        "Someone lifts the {} in the left hand and the {} in the right hand at the same time and sets them down again.",
                        left_object.name, right_object.name
                    ),
                    format!(
                        "A person holds the {} and the {}, one in each hand, then returns them to the table.",
                        left_object.name, right_object.name
                    ),
                ];
            } else {
                // The right hand parks its object far to the right, the left hand moves its
                // object to the right spot, the right hand brings the parked object to the left
                // spot, high over the object now standing in the middle.
                let park = table.rest(right_object, -0.30, table.near + 0.10, yaw(b.rng));
                let left_to = table.rest(
                    left_object,
                    right_rest.position.x,
                    right_rest.position.z,
                    yaw(b.rng),
                );
                let right_to = table.rest(
                    right_object,
                    left_rest.position.x,
                    left_rest.position.z,
                    yaw(b.rng),
                );
                let start1 = b.reach();
                let parked = b.carry(ro, start1, &[apex(&right_rest, &park, 0.12), park]);
                let end1 = parked + CLOSE_TIME;
                let done1 = b.attach(Hand::Right, ro, GraspStyle::Top, idle, start1, end1);
                b.t = end1 - 0.9;
                let reach2 = b.t;
                let start2 = b.reach();
                let moved = b.carry(lo, start2, &[apex(&left_rest, &left_to, 0.14), left_to]);
                let end2 = moved + CLOSE_TIME;
                b.attach(Hand::Left, lo, GraspStyle::Top, reach2, start2, end2);
                b.t = (end2 - 0.9).max(done1);
                let reach3 = b.t;
                let start3 = b.reach();
                let placed = b.carry(ro, start3, &[apex(&park, &right_to, 0.30), right_to]);
                b.attach(Hand::Right, ro, GraspStyle::Top, reach3, start3, placed + CLOSE_TIME);
                texts = vec![
                    format!(
                        "The person swaps the places of the {} and the {}.",
                        left_object.name, right_object.name
                    ),
                    format!(
                        "Someone exchanges the positions of the {} on the left and the {} on the right.",
                        left_object.name, right_object.name
                    ),
                    format!(
                        "A person moves the {} out of the way, puts the {} in its place and the {} where the {} was.",
                        right_object.name, left_object.name, right_object.name, left_object.name
                    ),
                ];
            }
        }
        Task::Pour => {
            let pourer = pick(b.rng, &pool(|o| o.pours && o.one_handed));
            let receiver =
                pick(b.rng, &pool(|o| o.receives && o.one_handed && o.name != pourer.name));
            let other = hand.other();
            let source_rest =
                table.rest(pourer, side_x(b.rng, hand), table.depth(b.rng), yaw(b.rng));
            let target_rest = table.rest(
                receiver,
                other.side() * b.rng.random_range(0.12..0.18),
                table.near + 0.12,
                yaw(b.rng),
            );
            let so = b.add_object(pourer, source_rest);
            let ro = b.add_object(receiver, target_rest);
            let hold_start = b.reach();
            let start = hold_start + b.duration(0.0..0.3);
            let above = target_rest.position
                + Vec3::new(
                    hand.side() * (footprint(receiver) + 0.05),
                    receiver.half_extents().y + pourer.half_extents().y + 0.10,
                    0.0,
                );
            let up = Pose { rotation: source_rest.rotation, position: above };
            // Tilt about the forward axis toward the receiver.
            let tilted = Pose {
                rotation: axis_angle_to_matrix(
                    Vec3::Z * (hand.side() * b.rng.random_range(1.3..1.8)),
                ) * source_rest.rotation,
                position: above,
            };
            let poured = b.carry(so, start, &[up, tilted, tilted, up, source_rest]);
            let end = poured + CLOSE_TIME;
            b.attach(hand, so, GraspStyle::Top, b.t, start, end);
            b.attach(other, ro, GraspStyle::Side, b.t, hold_start, end + 0.2);
            texts = vec![
                format!(
                    "The person holds the {} with the {} hand and pours from the {} with the {} hand.",
                    receiver.name,
                    other.word(),
                    pourer.name,
                    hand.word()
                ),
                format!(
                    "Someone pours from the {} into the {}, steadying the {} with the {} hand.",
                    pourer.name,
                    receiver.name,
                    receiver.name,
                    other.word()
                ),
                format!(
                    "A person lifts the {} with the {} hand, tips it over the {} and puts it back.",
                    pourer.name,
                    hand.word(),
                    receiver.name
                ),
            ];
        }
        Task::MoveNextTo => {
            let moved = pick(b.rng, &one);
            let anchor = pick(b.rng, &pool(|o| o.one_handed && o.name != moved.name));
            let anchor_rest = table.rest(
                anchor,
                -hand.side() * b.rng.random_range(0.0..0.08),
                table.depth(b.rng),
                yaw(b.rng),
            );
            let moved_rest = table.rest(
                moved,
                hand.side() * b.rng.random_range(0.16..0.24),
                table.depth(b.rng),
                yaw(b.rng),
            );
            let mo = b.add_object(moved, moved_rest);
            b.add_object(anchor, anchor_rest);
            let gap = footprint(moved) + footprint(anchor) + 0.03;
            let target = Pose {
                position: anchor_rest.position
                    + Vec3::new(
                        hand.side() * gap,
                        moved.half_extents().y - anchor.half_extents().y,
                        0.0,
                    ),
                ..moved_rest
            };
            let start = b.reach();
            let lift = b.duration(0.08..0.15);
            let arrive = b.carry(mo, start, &[apex(&moved_rest, &target, lift), target]);
            b.attach(hand, mo, GraspStyle::Top, idle, start, arrive + CLOSE_TIME);
            texts = vec![
                format!(
                    "The person moves the {} next to the {} with the {} hand.",
                    moved.name,
                    anchor.name,
                    hand.word()
                ),
                format!(
                    "Using the {} hand, someone places the {} beside the {}.",
                    hand.word(),
                    moved.name,
                    anchor.name
                ),
                format!(
                    "A person picks up the {} and puts it down next to the {}.",
                    moved.name, anchor.name
                ),
            ];
        }
    }
    let duration = b.attachments.iter().map(|a| a.retract_end).fold(0.0, f32::max)
        + b.rng.random_range(0.3..0.7);
    Plan {
        task,
        duration,
        table_height: table.height,
        objects: b.objects,
        attachments: b.attachments,
        texts,
    }
}
