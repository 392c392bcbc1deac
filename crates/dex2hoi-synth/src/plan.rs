//! Task plans of the procedural dataset: object trajectories on and above the table, and which
//! hand holds which object when.

use glam::{Mat3, Quat, Vec3};
use rand::Rng;
use rand_chacha::ChaCha8Rng;

use dex2hoi_repr::rotation::axis_angle_to_matrix;

use dex2hoi_data::catalogue::{CATALOGUE, CatalogueObject};
use dex2hoi_data::character::Hand;

use crate::text::{Description, Phrasing, describe};

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
    /// The pace of the task: its times are the even pace's times this ([`TaskTempo`]).
    pub tempo: f32,
    /// Height of the table top.
    pub table_height: f32,
    /// Objects: catalogue entry and trajectory.
    pub objects: Vec<(&'static CatalogueObject, Track)>,
    /// Who holds what, when.
    pub attachments: Vec<Attachment>,
    /// What the descriptions say.
    pub description: Description<'static>,
    /// Descriptions in the training phrasings.
    pub texts: Vec<String>,
    /// Descriptions in the phrasings held out of training (see [`crate::text`]).
    pub held_out_texts: Vec<String>,
}

/// Descriptions in the training phrasings per sequence.
pub const TRAINING_TEXTS: usize = 3;
/// Descriptions in the held-out phrasings per sequence.
pub const HELD_OUT_TEXTS: usize = 1;

/// Seconds the person stands still before the first reach, drawn per sequence. Longer than a
/// model's prefix (1 s) in a good share of sequences: generation starts from a prefix of the
/// person standing still, and in data whose every sequence ends at rest such a prefix would
/// otherwise only ever be followed by more rest (a model trained on 0.4-0.9 s never started a
/// pick and place from the standing pose).
pub const IDLE_BEFORE_TASK: std::ops::Range<f32> = 0.4..2.5;

/// Seconds the person stands at rest after the last hand is back, drawn per sequence. Up to 8 s,
/// so that the data hold the person at rest at every time of the prompt clock a generation of
/// 10-12 s reads (`dex2hoi_model::model::CLOCK_FRAMES`): a window starting 8 s into a prompt
/// needs a sequence of at least 11 s, and with up to 4 s of rest no pick and place lasted that
/// long, so a model met those clock readings only in generation.
pub const REST_AFTER_TASK: std::ops::Range<f32> = 0.5..8.0;

/// Seconds of the short idle time ([`RestAroundTask::Short`]) before the first reach.
pub const SHORT_IDLE_BEFORE_TASK: std::ops::Range<f32> = 0.4..0.9;

/// How fast a person does the task with [`TaskTempo::Drawn`], drawn per sequence: every time of
/// the task (reaches, carries, holds, the hands' return to rest) is the even pace's times this
/// factor. People do
/// the same task faster or slower, and a sequence whose task is done early shows the person at
/// rest at prompt-clock readings that, at one pace, only ever came before the task: a model
/// met a person standing still 4 s into a lift with both hands only in its own generations,
/// and started the task again.
pub const TASK_TEMPO: std::ops::Range<f32> = 0.5..1.5;

/// How fast the person does the task.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum TaskTempo {
    /// Every sequence at the even pace (the factor 1).
    #[default]
    Even,
    /// A factor drawn from [`TASK_TEMPO`] per sequence, from a random stream of its own: a
    /// plan's places, objects and words are those of [`TaskTempo::Even`] for a seed (a
    /// generated sequence's too, unless the physical checks refuse the plan at one pace and
    /// not at the other, and draw it again). Not the default:
    /// a model trained 6000 steps on such data did fewer tasks as asked and lifted more objects
    /// again than one trained as long on the even pace (docs/results/long-generations.md,
    /// "The pace of the task").
    Drawn,
}

impl TaskTempo {
    /// The factor of a plan whose main random stream is `rng` (not advanced).
    fn factor(self, rng: &ChaCha8Rng) -> f32 {
        match self {
            Self::Drawn => {
                let mut tempo = rng.clone();
                tempo.set_stream(TEMPO_STREAM);
                tempo.random_range(TASK_TEMPO)
            }
            Self::Even => 1.0,
        }
    }
}

/// The stream number of [`TaskTempo::Drawn`]'s draw.
const TEMPO_STREAM: u64 = 2;

/// How the time around and within the task is drawn.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Timing {
    /// How long the person stands still around the task.
    pub rest: RestAroundTask,
    /// How fast they do it.
    pub tempo: TaskTempo,
}

/// How long the person stands still around the task.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum RestAroundTask {
    /// [`IDLE_BEFORE_TASK`] before the first reach and [`REST_AFTER_TASK`] after the last hand
    /// is back: a generation longer than the task learns to do it once and rest.
    #[default]
    Drawn,
    /// [`SHORT_IDLE_BEFORE_TASK`] before and none after, as the generator made sequences before
    /// it had rest (dataset format 2). The same random draws as [`RestAroundTask::Drawn`],
    /// mapped onto the shorter times, so that everything else about a sequence stays the same.
    Short,
}

impl RestAroundTask {
    /// The idle time before the first reach, from a draw in [`IDLE_BEFORE_TASK`].
    fn idle_before(self, drawn: f32) -> f32 {
        match self {
            Self::Drawn => drawn,
            Self::Short => {
                let (from, to) = (IDLE_BEFORE_TASK, SHORT_IDLE_BEFORE_TASK);
                let share = (drawn - from.start) / (from.end - from.start);
                to.start + share * (to.end - to.start)
            }
        }
    }

    /// The rest after the task, from a draw in [`REST_AFTER_TASK`].
    fn after(self, drawn: f32) -> f32 {
        match self {
            Self::Drawn => drawn,
            Self::Short => 0.0,
        }
    }
}

/// Sideways places of the object of a one-handed task towards the hand's side (metres along X
/// times `hand.side()`): from 22 cm across the body to 22 cm on the hand's own side, so that
/// which hand takes an object follows from the words and not from the object's side. Across
/// the body the object stands nearer the edge ([`ACROSS_NEARER`]), and the draws a hand cannot
/// reach are refused with the rest of the physical checks.
pub const ONE_HANDED_REACH: std::ops::Range<f32> = -0.22..0.22;

/// Sideways places where one hand puts an object down (metres along X times `hand.side()`): less
/// far across the body than [`ONE_HANDED_REACH`], since the object is set down, not taken.
/// Wide objects set down further across are mostly out of the arm's reach.
pub const ONE_HANDED_PUT_DOWN: std::ops::Range<f32> = -0.16..0.22;

/// Sideways places on a hand's own side of the table (metres along X times `hand.side()`):
/// within its comfortable reach, clear of the middle.
const SIDE_SPOT: std::ops::Range<f32> = 0.10..0.22;

/// Sideways places where a hand-over's object starts, towards the giving hand (as
/// [`ONE_HANDED_REACH`]): at most 12 cm across the body, so that the taking hand always puts it
/// down at least [`HANDOVER_TRAVEL`] further on its own side, where the words say it ends. An
/// object on the person's left is still given by either hand.
pub const HANDOVER_START: std::ops::Range<f32> = -0.12..0.22;

/// The least a hand-over moves its object sideways, towards the taking hand's side (metres):
/// past the 5 cm within which an object counts as put back where it stood.
pub const HANDOVER_TRAVEL: f32 = 0.08;

/// How much nearer the table's edge an object stands per metre across the body from the
/// middle, for the hand that reaches it (see [`ONE_HANDED_REACH`]).
const ACROSS_NEARER: f32 = 0.8;

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

/// One-handed objects that are easy to pass and hold two of: the plate and the book are
/// one-handed but too flat and wide to hand over or to hold one in each hand.
fn small_one_handed() -> Vec<&'static CatalogueObject> {
    pool(|o| o.one_handed && o.name != "plate" && o.name != "book")
}

/// The lifted waypoint between two resting poses.
fn apex(a: &Pose, b: &Pose, lift: f32) -> Pose {
    Pose { rotation: a.rotation, position: (a.position + b.position) * 0.5 + Vec3::Y * lift }
}

/// An object on the table, its index in the plan, and when the hand that fetches it arrives.
struct Placed {
    object: &'static CatalogueObject,
    rest: Pose,
    index: usize,
    grasp: f32,
}

/// Two one-handed objects side by side, the left one for the left hand.
struct Pair {
    left: &'static CatalogueObject,
    right: &'static CatalogueObject,
    left_rest: Pose,
    right_rest: Pose,
    left_index: usize,
    right_index: usize,
}

/// A plan being built: the scene every task starts from (table, idle time, main hand), the
/// clock of the next reach, the object tracks and who holds what.
///
/// Every number is drawn from `rng` or `layout`, and the order of the draws is part of the
/// dataset: the same seed gives the same sequences only while every task draws the same numbers
/// in the same order. That is why the methods below draw into named variables one at a time,
/// in the order they always have; a new draw changes every later number of the sequence.
struct Planner<'r> {
    rng: &'r mut ChaCha8Rng,
    /// The draws that decide what the words say against where the objects stand (a pick and
    /// place's side, and its object's place), from a stream of their own that
    /// [`crate::generate`] keeps over its redraws: the physical checks refuse put-downs across
    /// the body more often than on the hand's own side, and redrawing the side with the rest
    /// would make a pick and place from the middle of the table go towards the hand's side
    /// 70% of the time.
    layout: ChaCha8Rng,
    table: Table,
    /// Seconds the person stands still before the first reach.
    idle: f32,
    /// The hand of the one-handed tasks (the pouring hand, the giving hand).
    hand: Hand,
    /// When the next reach starts.
    t: f32,
    objects: Vec<(&'static CatalogueObject, Track)>,
    attachments: Vec<Attachment>,
    rest: RestAroundTask,
    /// The factor of every time of the task ([`TaskTempo`]).
    tempo: f32,
}

impl<'r> Planner<'r> {
    /// Draws the scene: the table's height and near edge, the idle time, the main hand, and
    /// the pace.
    fn start(rng: &'r mut ChaCha8Rng, layout: ChaCha8Rng, timing: Timing) -> Self {
        let (rest, tempo) = (timing.rest, timing.tempo.factor(rng));
        let height = rng.random_range(0.86..0.94);
        let near = rng.random_range(0.20..0.26);
        let idle = rest.idle_before(rng.random_range(IDLE_BEFORE_TASK));
        let hand = if rng.random_bool(0.5) { Hand::Left } else { Hand::Right };
        Self {
            rng,
            layout,
            table: Table { height, near },
            idle,
            hand,
            t: idle,
            objects: Vec::new(),
            attachments: Vec::new(),
            rest,
            tempo,
        }
    }

    /// The finished plan: it lasts until the last hand is back at rest, then the person stands
    /// at rest for a while ([`REST_AFTER_TASK`]), so that the data show the task done once and
    /// followed by rest, as a generation longer than the task should be.
    fn finish(self, task: Task, description: Description<'static>) -> Plan {
        let duration = self.attachments.iter().map(|a| a.retract_end).fold(0.0, f32::max)
            + self.rest.after(self.rng.random_range(REST_AFTER_TASK));
        let texts = describe(&description, Phrasing::Training, TRAINING_TEXTS, self.rng);
        let held_out_texts = describe(&description, Phrasing::HeldOut, HELD_OUT_TEXTS, self.rng);
        Plan {
            task,
            duration,
            tempo: self.tempo,
            table_height: self.table.height,
            objects: self.objects,
            attachments: self.attachments,
            description,
            texts,
            held_out_texts,
        }
    }

    /// A number (a height, an angle) drawn from `range`.
    fn draw(&mut self, range: std::ops::Range<f32>) -> f32 {
        self.rng.random_range(range)
    }

    /// A time of the task drawn from `range` at the even pace, at this plan's pace.
    fn seconds(&mut self, range: std::ops::Range<f32>) -> f32 {
        let even = self.rng.random_range(range);
        self.paced(even)
    }

    /// A fixed time of the task at the even pace, at this plan's pace.
    fn paced(&self, seconds: f32) -> f32 {
        seconds * self.tempo
    }

    /// A small turn of an object about the vertical.
    fn yaw(&mut self) -> f32 {
        self.rng.random_range(-0.3..0.3)
    }

    /// A place across the table on `hand`'s side, within its comfortable reach.
    fn side_x(&mut self, hand: Hand) -> f32 {
        hand.side() * self.rng.random_range(SIDE_SPOT)
    }

    fn depth(&mut self) -> f32 {
        self.table.depth(self.rng)
    }

    /// A resting pose for `object` on `hand`'s side of the table.
    fn spot_beside(&mut self, object: &CatalogueObject, hand: Hand) -> Pose {
        let x = self.side_x(hand);
        self.spot_at(object, x)
    }

    /// A resting pose for `object` at `x` across the table, at a drawn depth and turn.
    fn spot_at(&mut self, object: &CatalogueObject, x: f32) -> Pose {
        let z = self.depth();
        let yaw = self.yaw();
        self.table.rest(object, x, z, yaw)
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
        let reach = self.seconds(0.7..1.1);
        self.t + reach
    }

    /// Carries `object` through `poses` (each leg 0.6-1.0 s) starting once the fingers closed
    /// at `start`; returns the time the object comes to rest.
    fn carry(&mut self, object: usize, start: f32, poses: &[Pose]) -> f32 {
        let mut t = start + CLOSE_TIME;
        self.key(object, t, self.last_pose(object));
        for pose in poses {
            t += self.seconds(0.6..1.0);
            self.key(object, t, *pose);
        }
        t
    }

    /// Carries `object` from `from` over a point `lift` above the middle down onto `to`: the
    /// path of every move across the table top (objects never slide).
    fn carry_over(&mut self, object: usize, start: f32, from: &Pose, to: Pose, lift: f32) -> f32 {
        self.carry(object, start, &[apex(from, &to, lift), to])
    }

    /// `hand` holds `object` from `start` to `end`, reaching from `reach_start`; returns when
    /// the hand is back at rest (0.6-0.9 s after letting go at the even pace).
    fn attach(
        &mut self,
        hand: Hand,
        object: usize,
        style: GraspStyle,
        reach_start: f32,
        start: f32,
        end: f32,
    ) -> f32 {
        let retract_end = end + self.seconds(0.6..0.9);
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

    /// An object from `pool` at a place drawn from `towards_hand` (metres along X times
    /// `hand.side()`, within [`ONE_HANDED_REACH`]: across the body too), and the main hand
    /// reaching for it after the idle time.
    fn place_for_main_hand(
        &mut self,
        pool: &[&'static CatalogueObject],
        towards_hand: std::ops::Range<f32>,
    ) -> Placed {
        let object = pick(self.rng, pool);
        let towards_hand = self.rng.random_range(towards_hand);
        self.place_for_main_hand_at(object, towards_hand)
    }

    /// [`Self::place_for_main_hand`] at `towards_hand` sideways (metres along X times
    /// `hand.side()`, within [`ONE_HANDED_REACH`]).
    fn place_for_main_hand_at(
        &mut self,
        object: &'static CatalogueObject,
        towards_hand: f32,
    ) -> Placed {
        let x = self.hand.side() * towards_hand;
        let rest = self.rest_in_reach(object, x);
        let index = self.add_object(object, rest);
        let grasp = self.reach();
        Placed { object, rest, index, grasp }
    }

    /// A resting pose for `object` at `x` across the table that the main hand reaches: a drawn
    /// depth, nearer the edge across the body (the shoulder is further away there and the
    /// torso leans but does not turn).
    fn rest_in_reach(&mut self, object: &CatalogueObject, x: f32) -> Pose {
        let across = (-x * self.hand.side()).max(0.0);
        let z = self.depth() - across * ACROSS_NEARER;
        let z = z.max(self.table.near + footprint(object) + 0.04);
        let yaw = self.yaw();
        self.table.rest(object, x, z, yaw)
    }

    /// Two different small objects side by side, `spread` from the middle, the left one on
    /// the left. Objects that will be swapped cross the body, so they stay close to the near
    /// edge (`near_edge`).
    fn place_pair(&mut self, spread: std::ops::Range<f32>, near_edge: bool) -> Pair {
        let one = small_one_handed();
        let left = pick(self.rng, &one);
        let others: Vec<_> = one.iter().copied().filter(|o| o.name != left.name).collect();
        let right = pick(self.rng, &others);
        let depth = |planner: &mut Self| {
            if near_edge {
                planner.table.near + planner.rng.random_range(0.07..0.12)
            } else {
                planner.depth()
            }
        };
        let left_depth = depth(self);
        let right_depth = depth(self);
        let left_x = self.rng.random_range(spread.clone());
        let left_yaw = self.yaw();
        let left_rest = self.table.rest(left, left_x, left_depth, left_yaw);
        let right_x = -self.rng.random_range(spread);
        let right_yaw = self.yaw();
        let right_rest = self.table.rest(right, right_x, right_depth, right_yaw);
        let left_index = self.add_object(left, left_rest);
        let right_index = self.add_object(right, right_rest);
        Pair { left, right, left_rest, right_rest, left_index, right_index }
    }

    /// [`Task::PickPlace`]: the main hand moves an object a little to the side: towards its own
    /// side or across the body, each half the time whoever's hand it is and wherever the object
    /// stands. The object starts within [`ONE_HANDED_REACH`] where the put-down that way is
    /// within [`ONE_HANDED_PUT_DOWN`]: in the middle of the table either way is as likely, so
    /// that only the words tell the side (a model learns what the data lets it read: when the
    /// side followed from the hand and the object's place, the side words went unread).
    fn pick_place(&mut self) -> Description<'static> {
        let hand = self.hand;
        let distance: f32 = self.layout.random_range(0.10..0.16);
        let shift = if self.layout.random_bool(0.5) { distance } else { -distance };
        let starts = (ONE_HANDED_PUT_DOWN.start - shift).max(ONE_HANDED_REACH.start)
            ..(ONE_HANDED_PUT_DOWN.end - shift).min(ONE_HANDED_REACH.end);
        let start = self.layout.random_range(starts);
        let object = pick(self.rng, &pool(|o| o.one_handed));
        let o = self.place_for_main_hand_at(object, start);
        let x = o.rest.position.x + hand.side() * shift;
        let target = self.rest_in_reach(o.object, x);
        let lift = self.draw(0.12..0.2);
        let arrive = self.carry_over(o.index, o.grasp, &o.rest, target, lift);
        self.attach(hand, o.index, GraspStyle::Top, self.idle, o.grasp, arrive + CLOSE_TIME);
        // From the person's point of view: +X is their left.
        let towards = if target.position.x > o.rest.position.x { Hand::Left } else { Hand::Right };
        Description::PickPlace { object: o.object.name, hand, towards }
    }

    /// [`Task::Inspect`]: the main hand brings an object up in front of the chest, turns it
    /// one way and the other, and puts it back where it was.
    fn inspect(&mut self) -> Description<'static> {
        let hand = self.hand;
        let o = self.place_for_main_hand(&pool(|o| o.one_handed), ONE_HANDED_REACH);
        let held = Pose {
            rotation: o.rest.rotation,
            position: Vec3::new(hand.side() * 0.12, 1.18, self.table.near + 0.12),
        };
        let turn = |angles: Vec3| Pose {
            rotation: axis_angle_to_matrix(angles) * o.rest.rotation,
            position: held.position,
        };
        let spin = self.draw(0.8..1.3);
        let tilt = self.draw(0.3..0.6);
        let looks = [
            held,
            turn(Vec3::new(tilt, spin, 0.0)),
            turn(Vec3::new(-tilt, -spin * 0.5, tilt * 0.5)),
            held,
            o.rest,
        ];
        let arrive = self.carry(o.index, o.grasp, &looks);
        self.attach(hand, o.index, GraspStyle::Top, self.idle, o.grasp, arrive + CLOSE_TIME);
        Description::Inspect { object: o.object.name, hand }
    }

    /// [`Task::LiftBoth`]: both hands lift a wide object straight up, hold it, put it back.
    fn lift_both(&mut self) -> Description<'static> {
        let object = pick(self.rng, &pool(|o| o.two_handed));
        let x = self.rng.random_range(-0.04..0.04);
        // In the middle, just far enough from the edge for both hands to get around it.
        let z = self.table.near + footprint(object) + 0.05;
        let yaw = self.yaw() * 0.3;
        let rest = self.table.rest(object, x, z, yaw);
        let o = self.add_object(object, rest);
        let start = self.reach();
        let lift = self.draw(0.15..0.3);
        let up = Pose { rotation: rest.rotation, position: rest.position + Vec3::Y * lift };
        let arrive = self.carry(o, start, &[up, up, rest]);
        let end = arrive + CLOSE_TIME;
        self.attach(Hand::Left, o, GraspStyle::Side, self.idle, start, end);
        self.attach(Hand::Right, o, GraspStyle::Side, self.idle, start, end);
        Description::LiftBoth { object: object.name }
    }

    /// [`Task::Handover`]: the main hand brings an object to the middle, the other hand takes
    /// it there and puts it down on its own side, at least [`HANDOVER_TRAVEL`] further that way
    /// than it stood (it starts within [`HANDOVER_START`]).
    fn handover(&mut self) -> Description<'static> {
        let (hand, other) = (self.hand, self.hand.other());
        let o = self.place_for_main_hand(&small_one_handed(), HANDOVER_START);
        let middle = Pose {
            rotation: o.rest.rotation,
            position: Vec3::new(0.0, self.table.height + 0.25, self.table.near + 0.14),
        };
        let arrive = self.carry(o.index, o.grasp, &[middle]);
        // The other hand reaches while the object comes to the middle and takes it; both
        // hold it a moment before the giving hand lets go.
        let take = arrive + self.paced(0.1);
        let give_end = take + CLOSE_TIME + self.paced(0.3);
        self.attach(hand, o.index, GraspStyle::Top, self.idle, o.grasp, give_end);
        self.key(o.index, give_end, middle);
        // Sideways on the taking hand's side: where the object stood, and where it goes down.
        let stood = o.rest.position.x * other.side();
        let put_down =
            self.rng.random_range(SIDE_SPOT.start.max(stood + HANDOVER_TRAVEL)..SIDE_SPOT.end);
        let target = self.spot_at(o.object, other.side() * put_down);
        let lift = self.draw(0.08..0.15);
        // The taking hand's fingers closed while both held it: it carries on from `give_end`.
        let place = self.carry_over(o.index, give_end - CLOSE_TIME, &middle, target, lift);
        let reach_start = take - self.seconds(0.8..1.1);
        self.attach(other, o.index, GraspStyle::Side, reach_start, take, place + CLOSE_TIME);
        Description::Handover { object: o.object.name, from: hand }
    }

    /// [`Task::HoldTwo`]: each hand lifts one object (the right a little later), both are
    /// held up together, then put back.
    fn hold_two(&mut self) -> Description<'static> {
        let p = self.place_pair(0.09..0.16, false);
        let start_left = self.reach();
        let delay = self.seconds(0.0..0.4);
        let start_right = start_left + delay;
        let lift_left = self.draw(0.12..0.25);
        let lift_right = self.draw(0.12..0.25);
        let hold = self.seconds(0.8..1.4);
        let up_left = Pose { position: p.left_rest.position + Vec3::Y * lift_left, ..p.left_rest };
        let up_right =
            Pose { position: p.right_rest.position + Vec3::Y * lift_right, ..p.right_rest };
        let left_up = self.carry(p.left_index, start_left, &[up_left]);
        let right_up = self.carry(p.right_index, start_right, &[up_right]);
        // Both come down together once the later one has been up for `hold`.
        let down_at = left_up.max(right_up) + hold;
        self.key(p.left_index, down_at, up_left);
        self.key(p.right_index, down_at, up_right);
        let left_done = self.carry(p.left_index, down_at - CLOSE_TIME, &[p.left_rest]);
        let right_done = self.carry(p.right_index, down_at - CLOSE_TIME, &[p.right_rest]);
        let idle = self.idle;
        let left_end = left_done + CLOSE_TIME;
        self.attach(Hand::Left, p.left_index, GraspStyle::Top, idle, start_left, left_end);
        let right_end = right_done + CLOSE_TIME;
        let right_reach = idle + delay;
        self.attach(
            Hand::Right,
            p.right_index,
            GraspStyle::Top,
            right_reach,
            start_right,
            right_end,
        );
        Description::HoldTwo { left: p.left.name, right: p.right.name }
    }

    /// [`Task::Swap`]: the right hand parks its object far to the right, the left hand moves
    /// its object to the right spot, the right hand brings the parked object to the left spot,
    /// high over the object now standing in the middle. Each reach starts 0.9 s (at the even
    /// pace) before the previous hand lets go, so the hands overlap a little.
    fn swap(&mut self) -> Description<'static> {
        let p = self.place_pair(0.06..0.11, true);
        let park_yaw = self.yaw();
        let park = self.table.rest(p.right, -0.30, self.table.near + 0.10, park_yaw);
        let (left_spot, right_spot) = (p.left_rest.position, p.right_rest.position);
        let left_yaw = self.yaw();
        let left_to = self.table.rest(p.left, right_spot.x, right_spot.z, left_yaw);
        let right_yaw = self.yaw();
        let right_to = self.table.rest(p.right, left_spot.x, left_spot.z, right_yaw);
        let idle = self.idle;

        let start1 = self.reach();
        let parked = self.carry_over(p.right_index, start1, &p.right_rest, park, 0.12);
        let end1 = parked + CLOSE_TIME;
        let right_back =
            self.attach(Hand::Right, p.right_index, GraspStyle::Top, idle, start1, end1);

        self.t = end1 - self.paced(0.9);
        let reach2 = self.t;
        let start2 = self.reach();
        let moved = self.carry_over(p.left_index, start2, &p.left_rest, left_to, 0.14);
        let end2 = moved + CLOSE_TIME;
        self.attach(Hand::Left, p.left_index, GraspStyle::Top, reach2, start2, end2);

        // The right hand cannot reach again before it is back from parking.
        self.t = (end2 - self.paced(0.9)).max(right_back);
        let reach3 = self.t;
        let start3 = self.reach();
        let placed = self.carry_over(p.right_index, start3, &park, right_to, 0.30);
        let end3 = placed + CLOSE_TIME;
        self.attach(Hand::Right, p.right_index, GraspStyle::Top, reach3, start3, end3);
        Description::Swap { left: p.left.name, right: p.right.name }
    }

    /// [`Task::Pour`]: the other hand steadies a receiver near the edge while the main hand
    /// lifts a pourer above it, tips it towards it and puts it back.
    fn pour(&mut self) -> Description<'static> {
        let (hand, other) = (self.hand, self.hand.other());
        let pourer = pick(self.rng, &pool(|o| o.pours && o.one_handed));
        let receiver =
            pick(self.rng, &pool(|o| o.receives && o.one_handed && o.name != pourer.name));
        let source_rest = self.spot_beside(pourer, hand);
        let receiver_x = other.side() * self.rng.random_range(0.12..0.18);
        let receiver_yaw = self.yaw();
        let target_rest =
            self.table.rest(receiver, receiver_x, self.table.near + 0.12, receiver_yaw);
        let source = self.add_object(pourer, source_rest);
        let target = self.add_object(receiver, target_rest);
        let hold_start = self.reach();
        let start = hold_start + self.seconds(0.0..0.3);
        // Beside the receiver's top on the pouring hand's side, a little above it.
        let above = target_rest.position
            + Vec3::new(
                hand.side() * (footprint(receiver) + 0.05),
                receiver.half_extents().y + pourer.half_extents().y + 0.10,
                0.0,
            );
        let up = Pose { rotation: source_rest.rotation, position: above };
        // Tilt about the forward axis toward the receiver.
        let tip: f32 = self.rng.random_range(1.3..1.8);
        let tilted = Pose {
            rotation: axis_angle_to_matrix(Vec3::Z * (hand.side() * tip)) * source_rest.rotation,
            position: above,
        };
        let poured = self.carry(source, start, &[up, tilted, tilted, up, source_rest]);
        let end = poured + CLOSE_TIME;
        let reach_start = self.t;
        self.attach(hand, source, GraspStyle::Top, reach_start, start, end);
        // The steadying hand lets go only after the pourer is down.
        self.attach(
            other,
            target,
            GraspStyle::Side,
            reach_start,
            hold_start,
            end + self.paced(0.2),
        );
        Description::Pour { pourer: pourer.name, receiver: receiver.name, hand }
    }

    /// [`Task::MoveNextTo`]: the main hand moves an object from its side of the table next to
    /// another near the middle, on the side facing the hand.
    fn move_next_to(&mut self) -> Description<'static> {
        let hand = self.hand;
        let moved = pick(self.rng, &small_one_handed());
        let anchor = pick(self.rng, &pool(|o| o.one_handed && o.name != moved.name));
        let anchor_x = -hand.side() * self.rng.random_range(0.0..0.08);
        let anchor_z = self.depth();
        let anchor_yaw = self.yaw();
        let anchor_rest = self.table.rest(anchor, anchor_x, anchor_z, anchor_yaw);
        let moved_x = hand.side() * self.rng.random_range(0.16..0.24);
        let moved_z = self.depth();
        let moved_yaw = self.yaw();
        let moved_rest = self.table.rest(moved, moved_x, moved_z, moved_yaw);
        let o = self.add_object(moved, moved_rest);
        self.add_object(anchor, anchor_rest);
        // Side by side with a 3 cm gap, both standing on the table.
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
        let start = self.reach();
        let lift = self.draw(0.08..0.15);
        let arrive = self.carry_over(o, start, &moved_rest, target, lift);
        self.attach(hand, o, GraspStyle::Top, self.idle, start, arrive + CLOSE_TIME);
        Description::MoveNextTo { moved: moved.name, anchor: anchor.name, hand }
    }
}

/// Plans one sequence of a task: the scene, then the task family's object tracks and hand
/// assignments (see [`Planner`] on why the order of the random draws must not change).
pub fn plan_task(task: Task, rng: &mut ChaCha8Rng) -> Plan {
    plan_task_with(task, Timing::default(), rng)
}

/// [`plan_task`] with the given timing.
pub fn plan_task_with(task: Task, timing: Timing, rng: &mut ChaCha8Rng) -> Plan {
    let layout = layout_stream(rng);
    plan_task_laid_out(task, timing, layout, rng)
}

/// The stream of a plan's layout draws (see [`Planner`]'s `layout`): `rng`'s seed on a stream
/// of its own, so that the layout draws leave `rng`'s draws as they are.
pub fn layout_stream(rng: &ChaCha8Rng) -> ChaCha8Rng {
    let mut layout = rng.clone();
    layout.set_stream(LAYOUT_STREAM);
    layout
}

/// The stream number of [`layout_stream`].
const LAYOUT_STREAM: u64 = 1;

/// [`plan_task_with`] with the layout draws from `layout`: [`crate::generate`] passes the same
/// layout to its redraws.
pub fn plan_task_laid_out(
    task: Task,
    timing: Timing,
    layout: ChaCha8Rng,
    rng: &mut ChaCha8Rng,
) -> Plan {
    let mut planner = Planner::start(rng, layout, timing);
    let description = match task {
        Task::PickPlace => planner.pick_place(),
        Task::Inspect => planner.inspect(),
        Task::LiftBoth => planner.lift_both(),
        Task::Handover => planner.handover(),
        Task::HoldTwo => planner.hold_two(),
        Task::Swap => planner.swap(),
        Task::Pour => planner.pour(),
        Task::MoveNextTo => planner.move_next_to(),
    };
    planner.finish(task, description)
}
