//! The built-in procedural dataset: a character on the default SMPL-X skeleton at a table,
//! eight objects, eight task families in which which hand holds which object changes over time.
//!
//! Each sequence is planned ([`plan::plan_task`]), then posed frame by frame: hands reach along
//! minimum-jerk paths to grasps on the object surface (the last stretch straight along the
//! surface normal), fingers curl until they touch the surface, held objects move rigidly with
//! the hand, free objects rest on the table, the torso leans as far as the reach needs, the
//! pelvis and legs stay put (feet planted) with a small idle sway. A generated sequence that
//! breaks a physical check (a held object away from the fingers, a hand joint inside an object,
//! an object in the table) is drawn again from the same random stream.

pub mod error;
pub mod plan;
pub mod text;

use glam::{Mat3, Vec3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use dex2hoi_repr::rotation::axis_angle_to_matrix;
use dex2hoi_repr::{MeshQuery, forward_kinematics};

use dex2hoi_data::catalogue::{self, BPS_RADIUS, BPS_SEED, CatalogueObject, catalogue_assets};
use dex2hoi_data::character::{Hand, HandPose, OPEN_CURL, PELVIS_HEIGHT, Poser, wrist_rotation};
use dex2hoi_data::{Sequence, SequenceObject};

pub use error::{Result, SynthError};
use plan::{
    Attachment, CLOSE_TIME, GraspStyle, Plan, Pose, Task, Timing, layout_stream, minimum_jerk,
    plan_task_laid_out,
};

/// Distance from the grasped surface to the wrist joint along the surface normal.
const PALM_GAP: f32 = 0.025;
/// Distance from the wrist back from the grasp point along the fingers.
const WRIST_BACK: f32 = 0.07;
/// How far above (or beside) the grasp the approach starts.
const APPROACH: f32 = 0.07;
/// A finger touches the surface when one of its joints is this close (joints are inside the
/// finger, about 8 mm under the skin).
const FINGER_TOUCH: f32 = 0.008;

/// A generated sequence with what the generator knows about it.
#[derive(Debug, Clone)]
pub struct SynthSequence {
    /// The motion.
    pub sequence: Sequence,
    /// The task family.
    pub task: Task,
    /// Height of the table top (world).
    pub table_height: f32,
    /// Who holds what, when (seconds).
    pub attachments: Vec<Attachment>,
    /// Descriptions in the phrasings held out of training.
    pub held_out_texts: Vec<String>,
    /// What the descriptions say: the task, its objects, hands and directions.
    pub description: text::Description<'static>,
}

/// Which sentences describe the training split's sequences (the held-out phrasings, and the
/// motions, are the same either way).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum TrainingTexts {
    /// Three drawn from the grammar (`text::describe`): synonyms and phrasings a person would
    /// write.
    #[default]
    Grammar,
    /// The task's three fixed sentences (`text::template_sentences`), 80 words in all.
    Templates,
    /// Both: the grammar's three phrasings and the task's three fixed sentences. A model that
    /// reads the fixed sentences goes on to learn the grammar's synonyms from the same
    /// motions without losing them.
    Both,
}

/// How a hand holds an object: the wrist in the object frame, the surface normal at the grasp
/// and the finger curls.
#[derive(Debug, Clone, Copy)]
struct Grasp {
    wrist: Pose,
    outward: Vec3,
    curls: [f32; 5],
}

fn grasp(
    poser: &Poser,
    hand: Hand,
    style: GraspStyle,
    object: &CatalogueObject,
    query: &MeshQuery,
) -> Grasp {
    let half = object.half_extents();
    let fingers = Vec3::Z;
    let (contact, outward) = match style {
        GraspStyle::Top => (Vec3::new(0.0, half.y, 0.0), Vec3::Y),
        GraspStyle::Side => (
            Vec3::new(hand.side() * half.x, (half.y - SIDE_GRASP_BELOW_TOP).max(0.0), 0.0),
            Vec3::X * hand.side(),
        ),
    };
    let rotation = wrist_rotation(hand, fingers, outward);
    let position = contact + outward * PALM_GAP - fingers * WRIST_BACK;
    let curls = poser.grasp_curls(
        hand,
        position,
        rotation,
        query,
        Mat3::IDENTITY,
        Vec3::ZERO,
        FINGER_TOUCH,
    );
    Grasp { wrist: Pose { rotation, position }, outward, curls }
}

/// How far below the top a side grasp holds a side taller than this (the box): centred on
/// its 20 cm face the curled hand put joints 13 mm into it; held on the upper part, as a
/// person lifts a box, they stay outside. Lower sides are held in the middle.
const SIDE_GRASP_BELOW_TOP: f32 = 0.07;

/// Height of the arc that free hand paths take over the objects on the table.
const PATH_ARC: f32 = 0.12;

/// Lifts a point of a free hand path by a half-sine arc over the path parameter.
fn arc(pose: HandPose, u: f32) -> HandPose {
    HandPose {
        position: pose.position + Vec3::Y * (PATH_ARC * (std::f32::consts::PI * u).sin()),
        ..pose
    }
}

/// Where each hand is at time `t` under a plan.
fn hand_pose(plan: &Plan, grasps: &[Grasp], idle: &[HandPose; 2], hand: Hand, t: f32) -> HandPose {
    let rest = idle[hand.index()];
    let Some((k, a)) = plan
        .attachments
        .iter()
        .enumerate()
        .find(|(_, a)| a.hand == hand && a.reach_start <= t && t <= a.retract_end)
    else {
        return rest;
    };
    let g = grasps[k];
    let at = |time: f32| {
        let object = plan.objects[a.object].1.at(time);
        let wrist = object.compose(&g.wrist);
        let outward = object.rotation * g.outward;
        (HandPose { position: wrist.position, rotation: wrist.rotation, curls: g.curls }, outward)
    };
    let open = |pose: HandPose| HandPose { curls: [OPEN_CURL; 5], ..pose };
    if t < a.start {
        let (target, outward) = at(a.start);
        let pre = HandPose { position: target.position + outward * APPROACH, ..open(target) };
        let u = minimum_jerk((t - a.reach_start) / (a.start - a.reach_start).max(1e-3));
        if u < 0.7 {
            arc(rest.lerp(&pre, u / 0.7), u / 0.7)
        } else {
            pre.lerp(&open(target), (u - 0.7) / 0.3)
        }
    } else if t <= a.end {
        let (pose, _) = at(t);
        let closing = ((t - a.start) / CLOSE_TIME).min((a.end - t) / CLOSE_TIME).clamp(0.0, 1.0);
        open(pose).lerp(&pose, minimum_jerk(closing))
    } else {
        let (target, outward) = at(a.end);
        let pre = HandPose { position: target.position + outward * APPROACH, ..open(target) };
        let u = minimum_jerk((t - a.end) / (a.retract_end - a.end).max(1e-3));
        if u < 0.3 {
            open(target).lerp(&pre, u / 0.3)
        } else {
            arc(pre.lerp(&rest, (u - 0.3) / 0.7), (u - 0.3) / 0.7)
        }
    }
}

/// A running maximum over `radius` frames on each side, then a box average over `smooth`
/// frames on each side, never below the input: a smooth lean that always reaches.
fn smooth_upper(values: &[f32], radius: usize, smooth: usize) -> Vec<f32> {
    let n = values.len();
    let dilated: Vec<f32> = (0..n)
        .map(|t| {
            values[t.saturating_sub(radius)..(t + radius + 1).min(n)]
                .iter()
                .copied()
                .fold(0.0, f32::max)
        })
        .collect();
    (0..n)
        .map(|t| {
            let window = &dilated[t.saturating_sub(smooth)..(t + smooth + 1).min(n)];
            (window.iter().sum::<f32>() / window.len() as f32).max(values[t])
        })
        .collect()
}

/// Poses a plan into a sequence at `fps`, in the character's frame.
fn realise(plan: &Plan, fps: f32, rng: &mut ChaCha8Rng, index: usize) -> Result<SynthSequence> {
    let root = Vec3::new(0.0, PELVIS_HEIGHT, 0.0);
    let poser = Poser::new(root);
    let queries: Vec<MeshQuery> =
        plan.objects.iter().map(|(o, _)| MeshQuery::new(&o.mesh())).collect::<Result<_, _>>()?;
    let grasps: Vec<Grasp> = plan
        .attachments
        .iter()
        .map(|a| grasp(&poser, a.hand, a.style, plan.objects[a.object].0, &queries[a.object]))
        .collect();
    let idle = [poser.idle_hand(Hand::Left), poser.idle_hand(Hand::Right)];
    let frames = ((plan.duration * fps).round() as usize).max(2);
    let times: Vec<f32> = (0..frames).map(|f| f as f32 / fps).collect();
    let hands: Vec<[HandPose; 2]> =
        times.iter().map(|&t| Hand::BOTH.map(|h| hand_pose(plan, &grasps, &idle, h, t))).collect();
    for (pose, &t) in hands.iter().zip(&times) {
        for hand in Hand::BOTH {
            if !poser.reachable(hand, pose[hand.index()].position) {
                return Err(SynthError::Sequence {
                    sequence: format!("synth-{index:05}"),
                    expected: "reachable hand targets".into(),
                    got: format!("{} hand at {t:.2} s", hand.word()),
                });
            }
        }
    }
    let required: Vec<f32> = hands
        .iter()
        .map(|pose| {
            Hand::BOTH
                .map(|h| poser.lean_to_reach(h, pose[h.index()].position))
                .into_iter()
                .fold(0.0, f32::max)
        })
        .collect();
    let lean = smooth_upper(&required, (0.4 * fps) as usize, (0.25 * fps) as usize);
    let phase = rng.random_range(0.0..std::f32::consts::TAU);
    let period = rng.random_range(2.5..4.0);
    let mut local_rotations = Vec::with_capacity(frames * poser.skeleton().joint_count());
    for (f, &t) in times.iter().enumerate() {
        let sway = 0.012 * (std::f32::consts::TAU * t / period + phase).sin();
        local_rotations.extend(poser.pose(lean[f], sway, &hands[f]));
    }
    // Place the whole scene somewhere in the world: turned about +Y and moved on the floor.
    let yaw = rng.random_range(-0.6..0.6);
    let turn = axis_angle_to_matrix(Vec3::Y * yaw);
    let offset = Vec3::new(rng.random_range(-0.5..0.5), 0.0, rng.random_range(-0.5..0.5));
    let joints = poser.skeleton().joint_count();
    for f in 0..frames {
        local_rotations[f * joints] = turn * local_rotations[f * joints];
    }
    let objects = plan
        .objects
        .iter()
        .map(|(object, track)| {
            let poses: Vec<Pose> = times.iter().map(|&t| track.at(t)).collect();
            SequenceObject {
                name: object.name.into(),
                mesh: object.mesh(),
                rotations: poses.iter().map(|p| turn * p.rotation).collect(),
                translations: poses.iter().map(|p| turn * p.position + offset).collect(),
            }
        })
        .collect();
    let sequence = Sequence {
        skeleton: poser.skeleton().clone(),
        fps,
        local_rotations,
        root_positions: vec![turn * root + offset; frames],
        objects,
        texts: plan.texts.clone(),
        action: Some(plan.task.label().into()),
        source_id: format!("synth-{index:05}"),
    };
    Ok(SynthSequence {
        sequence,
        task: plan.task,
        table_height: plan.table_height,
        attachments: plan.attachments.clone(),
        held_out_texts: plan.held_out_texts.clone(),
        description: plan.description,
    })
}

/// Measured physical quality of a generated sequence.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PhysicalReport {
    /// The largest, over frames where an object is firmly held (fingers closed), of the
    /// nearest distance between the holding hand's finger joints and the object surface.
    pub held_distance: f32,
    /// The deepest any hand joint goes inside any object (positive metres, 0 if none).
    pub hand_penetration: f32,
    /// The lowest point of any object relative to the table top (negative: inside the table).
    pub table_clearance: f32,
    /// The nearest any hand comes to an object it is not reaching for, holding or leaving:
    /// hands passing close to other objects would make the proximity-based mixture targets
    /// disagree with the task.
    pub stray_distance: f32,
}

/// Measures a generated sequence (see [`PhysicalReport`]).
pub fn physical_report(synth: &SynthSequence) -> Result<PhysicalReport> {
    let s = &synth.sequence;
    let fk = forward_kinematics(&s.skeleton, &s.local_rotations, &s.root_positions)?;
    let groups = s.skeleton.groups();
    let queries: Vec<MeshQuery> =
        s.objects.iter().map(|o| MeshQuery::new(&o.mesh)).collect::<Result<_, _>>()?;
    let to_object = |o: usize, f: usize, p: Vec3| {
        s.objects[o].rotations[f].transpose() * (p - s.objects[o].translations[f])
    };
    let mut report = PhysicalReport {
        held_distance: 0.0,
        hand_penetration: 0.0,
        table_clearance: f32::INFINITY,
        stray_distance: f32::INFINITY,
    };
    for f in 0..s.frames() {
        let t = f as f32 / s.fps;
        for (o, query) in queries.iter().enumerate() {
            for (hand, joints) in
                [(Hand::Left, &groups.left_hand), (Hand::Right, &groups.right_hand)]
            {
                let engaged = synth.attachments.iter().any(|a| {
                    a.hand == hand && a.object == o && a.reach_start <= t && t <= a.retract_end
                });
                for &j in joints {
                    let d = query.signed_distance(to_object(o, f, fk.position(f, j)));
                    report.hand_penetration = report.hand_penetration.max(-d);
                    if !engaged {
                        report.stray_distance = report.stray_distance.min(d);
                    }
                }
            }
            let lowest = s.objects[o]
                .mesh
                .vertices
                .iter()
                .map(|v| (s.objects[o].rotations[f] * *v + s.objects[o].translations[f]).y)
                .fold(f32::INFINITY, f32::min);
            report.table_clearance = report.table_clearance.min(lowest - synth.table_height);
        }
        for a in &synth.attachments {
            if t < a.start + CLOSE_TIME || t > a.end - CLOSE_TIME {
                continue;
            }
            let hand = match a.hand {
                Hand::Left => &groups.left_hand,
                Hand::Right => &groups.right_hand,
            };
            let nearest = hand[1..]
                .iter()
                .map(|&j| {
                    queries[a.object].signed_distance(to_object(a.object, f, fk.position(f, j)))
                })
                .fold(f32::INFINITY, f32::min);
            report.held_distance = report.held_distance.max(nearest);
        }
    }
    Ok(report)
}

/// The limits every generated sequence meets.
pub const MAX_HELD_DISTANCE: f32 = 0.02;
/// See [`MAX_HELD_DISTANCE`].
pub const MAX_HAND_PENETRATION: f32 = 0.01;
/// See [`MAX_HELD_DISTANCE`]: more than the 3 cm of the mixture-target rule.
pub const MIN_STRAY_DISTANCE: f32 = 0.04;

/// How many plans a sequence may draw before generation gives up.
const MAX_DRAWS: usize = 100;

/// How many of those keep the sequence's first layout ([`plan::layout_stream`]).
const LAYOUT_DRAWS: usize = MAX_DRAWS / 2;

/// Generates sequence `index` of the dataset with `seed` at `fps`: task family
/// `index mod 8`, everything else drawn from a random stream of `(seed, index)`.
pub fn generate(index: usize, seed: u64, fps: f32) -> Result<SynthSequence> {
    generate_with(index, seed, fps, Timing::default())
}

/// [`generate`] with the given timing around and within the task.
pub fn generate_with(index: usize, seed: u64, fps: f32, timing: Timing) -> Result<SynthSequence> {
    let mut rng =
        ChaCha8Rng::seed_from_u64(seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ index as u64);
    let task = Task::ALL[index % Task::ALL.len()];
    let mut last_problem = String::new();
    let mut layout = layout_stream(&rng);
    for attempt in 0..MAX_DRAWS {
        if attempt == LAYOUT_DRAWS {
            // The layout itself may be what no draw of the rest can realise.
            layout = layout_stream(&rng);
        }
        let plan = plan_task_laid_out(task, timing, layout.clone(), &mut rng);
        let synth = match realise(&plan, fps, &mut rng, index) {
            Ok(synth) => synth,
            Err(error) => {
                last_problem = error.to_string();
                continue;
            }
        };
        let report = physical_report(&synth)?;
        if report.held_distance <= MAX_HELD_DISTANCE
            && report.hand_penetration <= MAX_HAND_PENETRATION
            && report.table_clearance >= -1e-3
            && report.stray_distance >= MIN_STRAY_DISTANCE
        {
            return Ok(synth);
        }
        last_problem = format!("{report:?}");
    }
    Err(SynthError::Sequence {
        sequence: format!("synth-{index:05} ({})", task.label()),
        expected: format!("a physically valid sequence within {MAX_DRAWS} draws"),
        got: last_problem,
    })
}

/// Sequences come in blocks of eight (one per task family); every tenth block (indices
/// 72-79, 152-159, ...) is in the test split, so both splits hold every task.
pub fn split_of(index: usize) -> dex2hoi_data::dataset::Split {
    if (index / Task::ALL.len()) % 10 == 9 {
        dex2hoi_data::dataset::Split::Test
    } else {
        dex2hoi_data::dataset::Split::Train
    }
}

/// Generates `count` sequences with `seed` at `fps`, extracts features and targets, and
/// assembles the dataset (splits, statistics over the training split, manifest). `progress`
/// is called with the number of sequences done so far.
pub fn build_dataset(
    count: usize,
    seed: u64,
    fps: f32,
    progress: &(dyn Fn(usize) + Sync),
) -> Result<dex2hoi_data::dataset::Dataset> {
    build_dataset_with(count, seed, fps, SynthOptions::default(), progress)
}

/// What a procedural dataset may vary beyond its size, seed and frame rate.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct SynthOptions {
    /// The sentences that describe the training split.
    pub texts: TrainingTexts,
    /// How long the person stands still around the task, and how fast they do it.
    pub timing: Timing,
    /// The rule the mixture targets are drawn by.
    pub mixture_targets: dex2hoi_data::features::MixtureTargets,
}

/// [`build_dataset`] with `options`. With other [`SynthOptions::texts`] the motions and the
/// held-out phrasings are the same for a seed; with another rest or tempo
/// ([`SynthOptions::timing`]) everything but the times is.
pub fn build_dataset_with(
    count: usize,
    seed: u64,
    fps: f32,
    options: SynthOptions,
    progress: &(dyn Fn(usize) + Sync),
) -> Result<dex2hoi_data::dataset::Dataset> {
    use dex2hoi_data::dataset::{BpsSettings, Dataset, Split};
    use dex2hoi_data::features::{TargetConfig, process_sequence};
    use rayon::prelude::*;
    use std::collections::BTreeMap;
    use std::sync::atomic::{AtomicUsize, Ordering};

    if count == 0 {
        return Err(SynthError::Argument {
            argument: "--sequences",
            expected: "at least one sequence",
            got: "0".into(),
        });
    }
    let assets = catalogue_assets()?;
    let queries: Vec<MeshQuery> =
        assets.iter().map(|a| MeshQuery::new(&a.mesh)).collect::<Result<_, _>>()?;
    let done = AtomicUsize::new(0);
    let config = TargetConfig::with_mixture_targets(options.mixture_targets);
    let processed: Vec<(usize, dex2hoi_data::features::ProcessedSequence)> = (0..count)
        .into_par_iter()
        .map(|index| {
            let mut synth = generate_with(index, seed, fps, options.timing)?;
            match options.texts {
                TrainingTexts::Grammar => {}
                TrainingTexts::Templates => {
                    synth.sequence.texts = text::template_sentences(&synth.description);
                }
                TrainingTexts::Both => {
                    synth.sequence.texts.extend(text::template_sentences(&synth.description));
                }
            }
            let object_queries: Vec<&MeshQuery> = synth
                .sequence
                .objects
                .iter()
                .map(|o| {
                    catalogue::CATALOGUE.iter().position(|c| c.name == o.name).map(|k| &queries[k])
                })
                .collect::<Option<_>>()
                .ok_or_else(|| SynthError::Sequence {
                    sequence: synth.sequence.source_id.clone(),
                    expected: "catalogue objects".into(),
                    got: "an unknown object".into(),
                })?;
            let mut features = process_sequence(&synth.sequence, &object_queries, &config)?;
            features.held_out_texts = synth.held_out_texts;
            progress(done.fetch_add(1, Ordering::Relaxed) + 1);
            Ok((index, features))
        })
        .collect::<Result<_>>()?;
    let mut splits: BTreeMap<Split, Vec<dex2hoi_data::features::ProcessedSequence>> =
        BTreeMap::new();
    for (index, sequence) in processed {
        splits.entry(split_of(index)).or_default().push(sequence);
    }
    let bps = BpsSettings {
        points: dex2hoi_repr::bps::DEFAULT_BPS_POINTS,
        radius: BPS_RADIUS,
        seed: BPS_SEED,
    };
    let skeleton = dex2hoi_repr::Skeleton::smplx();
    Ok(Dataset::assemble(
        dex2hoi_data::dataset::PROCEDURAL_SOURCE,
        &skeleton,
        fps,
        splits,
        assets,
        bps,
        Some(seed),
        options.mixture_targets,
    )?)
}
