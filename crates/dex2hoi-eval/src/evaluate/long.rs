//! The long-generation protocol, beside the paper's: long motions generated as `dex2hoi sample`
//! generates them (from the standing pose, no motion prefix), from each test sequence's
//! first-frame object placements and prompt, judged against the whole ground-truth sequence
//! ([`metrics::long_generation`]), per task family and pooled. Three sets:
//! - **as in the data**: the placements and the first text of each sequence;
//! - **moved placements**: each sequence with one object that one hand moves, the object put in
//!   the middle (even sequences) or as far across the body from that hand (odd ones), so the
//!   hand can only come from the words;
//! - **held-out phrasings**: the placements as in the data, the prompt the sequence's first
//!   description in the phrasings held out of training (sequences without one are left out).

use std::num::NonZeroUsize;

use glam::Vec3;
use serde::{Deserialize, Serialize};

use dex2hoi_data::MAX_OBJECTS;
use dex2hoi_data::dataset::Dataset;
use dex2hoi_data::features::ProcessedSequence;
use dex2hoi_data::layout::slot_bps;
use dex2hoi_diffusion::SamplerConfig;
use dex2hoi_repr::{MeshQuery, ObjectPose};
use dex2hoi_sample::rest::{FreeObjects, ObjectsAtRest};
use dex2hoi_sample::seams::Seams;
use dex2hoi_sample::{Conditioning, TrainedRun, generate_motion, standing_prefix};

use crate::error::Result;
use crate::evaluator::MotionClip;
use crate::metrics::{self, HandsUsed, LongCounts, ObjectCourse};

use super::generation::Progress;
use super::physical::{ObjectMeshes, clip_sample};

/// Frames of a long generation by default: ten seconds at the procedural dataset's 20 fps.
pub const DEFAULT_LONG_FRAMES: usize = 200;
/// Sideways distance from the middle of an object moved across the body, at least (metres).
pub const ACROSS_THE_BODY_M: f32 = 0.12;
/// Seed offset of the long generations, far from the paper protocol's.
const LONG_SEED_OFFSET: u64 = 2_000_000_011;
/// Seed offset between the protocol's sets.
const SET_STRIDE: u64 = 100_003;

/// Which long-generation set.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum LongSetKind {
    /// The test sequences' placements and first texts.
    AsInData,
    /// The lone object of one-handed tasks moved to the middle or across the body.
    Moved,
    /// The phrasings held out of training.
    HeldOut,
}

impl LongSetKind {
    /// Every set, in report order.
    pub const ALL: [LongSetKind; 3] = [Self::AsInData, Self::Moved, Self::HeldOut];

    /// The set's name in reports.
    pub fn title(self) -> &'static str {
        match self {
            Self::AsInData => "placements and texts as in the data",
            Self::Moved => "the lone object moved to the middle or across the body",
            Self::HeldOut => "phrasings held out of training",
        }
    }
}

/// The long-generation scores of one group of generations (or of their ground truths).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LongScores {
    /// Share of generations that do the task as asked.
    pub as_asked: Option<f64>,
    /// Share of objects moved if and only if the ground truth moves them.
    pub moved: Option<f64>,
    /// Share of the moved objects held by the ground truth's hands.
    pub hands: Option<f64>,
    /// Share of the moved objects that travel to the ground truth's side.
    pub travel: Option<f64>,
    /// Share of objects lifted again unasked.
    pub lifted_again: Option<f64>,
    /// Median over objects of the worst distance off the support while untouched, cm.
    pub off_support_cm: Option<f64>,
    /// Median over objects of the deepest sinking while untouched, cm.
    pub sinking_cm: Option<f64>,
    /// Median over objects of the highest floating while untouched, cm.
    pub floating_cm: Option<f64>,
    /// Median speed of untouched objects, cm/s.
    pub untouched_speed_cm_s: Option<f64>,
    /// Median start jump, cm.
    pub start_jump_cm: Option<f64>,
    /// Median over the seams between windows of the body's jump (the mean over its joints), cm.
    #[serde(default)]
    pub body_seam_jump_cm: Option<f64>,
    /// Median over the seams and objects of an object's jump, cm.
    #[serde(default)]
    pub object_seam_jump_cm: Option<f64>,
    /// Median over generations of the lowest joint's change in height, first to last frame, cm.
    #[serde(default)]
    pub floor_drift_cm: Option<f64>,
}

impl LongScores {
    fn of(counts: &LongCounts) -> Self {
        let cm = |m: Option<f64>| m.map(|m| m * 100.0);
        let [off, sink, float, speed, jump, body_seam, object_seam, floor] =
            metrics::long_medians(counts);
        Self {
            as_asked: counts.as_asked_share(),
            moved: counts.moved_share(),
            hands: counts.hands_share(),
            travel: counts.travel_share(),
            lifted_again: counts.lifted_again_share(),
            off_support_cm: cm(off),
            sinking_cm: cm(sink),
            floating_cm: cm(float),
            untouched_speed_cm_s: cm(speed),
            start_jump_cm: cm(jump),
            body_seam_jump_cm: cm(body_seam),
            object_seam_jump_cm: cm(object_seam),
            floor_drift_cm: cm(floor),
        }
    }
}

/// One task family's (or all families') row of a set.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LongRow {
    /// The action label, or "all".
    pub family: String,
    /// Generations in the row.
    pub generations: usize,
    /// The generated motions.
    pub model: LongScores,
    /// The ground truth judged the same way (against itself).
    pub truth: LongScores,
}

/// One set of the protocol.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LongSet {
    /// Which set.
    pub kind: LongSetKind,
    /// All families first, then one row per family.
    pub rows: Vec<LongRow>,
}

/// The long-generation protocol's results.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LongProtocol {
    /// Frames generated per motion.
    pub frames: usize,
    /// Frames of each window the sampler generates: the seams are its multiples.
    #[serde(default)]
    pub window: usize,
    /// The sets that had sequences.
    pub sets: Vec<LongSet>,
}

/// How the long-generation protocol runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct LongOptions {
    /// Frames per generation ([`DEFAULT_LONG_FRAMES`] by default).
    pub frames: NonZeroUsize,
}

impl Default for LongOptions {
    fn default() -> Self {
        Self { frames: NonZeroUsize::new(DEFAULT_LONG_FRAMES).expect("a positive default") }
    }
}

/// One generation to make: a test sequence (and its index among those evaluated), where its
/// objects start and its prompt.
struct LongCase<'a> {
    index: usize,
    sequence: &'a ProcessedSequence,
    placed: [Option<ObjectPose>; MAX_OBJECTS],
    prompt: &'a str,
}

/// The cases of a set; the moved set reads the hands of the ground truth's courses.
fn cases<'a>(
    kind: LongSetKind,
    sequences: &[&'a ProcessedSequence],
    truth_courses: &[[Option<ObjectCourse>; MAX_OBJECTS]],
) -> Vec<LongCase<'a>> {
    let mut out = Vec::new();
    for (k, (&sequence, courses)) in sequences.iter().zip(truth_courses).enumerate() {
        let mut placed = sequence.object_poses_at(0);
        let prompt = match kind {
            LongSetKind::AsInData | LongSetKind::Moved => sequence.texts[0].as_str(),
            LongSetKind::HeldOut => match sequence.held_out_texts.first() {
                Some(text) => text.as_str(),
                None => continue,
            },
        };
        if kind == LongSetKind::Moved {
            // One object, moved by exactly one hand: put where that hand would not take it
            // for being nearest.
            let present: Vec<usize> = (0..MAX_OBJECTS).filter(|&s| placed[s].is_some()).collect();
            let [slot] = present[..] else { continue };
            let side = match courses[slot].as_ref().map(|c| c.hands) {
                Some(HandsUsed { left: true, right: false }) => 1.0,
                Some(HandsUsed { left: false, right: true }) => -1.0,
                _ => continue,
            };
            let Some(pose) = placed[slot].as_mut() else { continue };
            pose.position.x =
                if k % 2 == 0 { 0.0 } else { -side * pose.position.x.abs().max(ACROSS_THE_BODY_M) };
        }
        out.push(LongCase { index: k, sequence, placed, prompt });
    }
    out
}

/// The support height of each slot: the lowest point of the object where it was placed.
fn support_heights(
    placed: &[Option<ObjectPose>; MAX_OBJECTS],
    meshes: [Option<&MeshQuery>; MAX_OBJECTS],
) -> [f32; MAX_OBJECTS] {
    std::array::from_fn(|slot| match (placed[slot], meshes[slot]) {
        (Some(pose), Some(mesh)) => mesh.lowest_height(pose.rotation, pose.position),
        _ => 0.0,
    })
}

/// Where each object was placed (the origin for an empty slot, which is not judged).
fn positions(placed: &[Option<ObjectPose>; MAX_OBJECTS]) -> [Vec3; MAX_OBJECTS] {
    placed.map(|p| p.map_or(Vec3::ZERO, |p| p.position))
}

/// Runs the protocol on `sequences` (the test split's, in order).
#[allow(clippy::too_many_arguments)] // the run, its data and how to sample them
pub(super) fn evaluate_long(
    run: &TrainedRun,
    dataset: &Dataset,
    sequences: &[&ProcessedSequence],
    meshes: &ObjectMeshes<'_>,
    options: LongOptions,
    (sampler, free_objects, seams): (SamplerConfig, FreeObjects, Seams),
    seed: u64,
    progress: &mut dyn FnMut(usize, usize),
) -> Result<LongProtocol> {
    let start = run.manifest.start_pose()?;
    let fps = dataset.manifest.fps;
    let config = &run.config.model;
    // The generations' windows; the ground truth is measured at the same seams.
    let window = config.predicted_frames;
    // The ground truth of every sequence, judged once.
    let truths: Vec<MotionClip> = sequences
        .iter()
        .map(|s| MotionClip::from_processed(s, 0, s.frames))
        .collect::<Result<_>>()?;
    let mut truth_courses = Vec::with_capacity(sequences.len());
    let mut truth_counts = Vec::with_capacity(sequences.len());
    for (sequence, truth) in sequences.iter().zip(&truths) {
        let slots = meshes.of(sequence)?;
        let placed = sequence.object_poses_at(0);
        let sample = clip_sample(truth, &run.skeleton, slots, None);
        let courses = metrics::object_courses(&sample, support_heights(&placed, slots), fps)?;
        let counts = metrics::judge_courses(&courses, &courses, positions(&placed))?;
        truth_counts.push(counts.with_seams(&metrics::seam_course(&sample, window)?));
        truth_courses.push(courses);
    }
    let all_cases: Vec<(usize, LongSetKind, Vec<LongCase<'_>>)> = LongSetKind::ALL
        .into_iter()
        .enumerate()
        .map(|(k, kind)| (k, kind, cases(kind, sequences, &truth_courses)))
        .filter(|(.., cases)| !cases.is_empty())
        .collect();
    let mut progress = Progress::new(all_cases.iter().map(|(.., c)| c.len()).sum(), progress);
    let mut sets = Vec::new();
    for (set_index, kind, cases) in all_cases {
        let mut judged: Vec<(Option<&str>, LongCounts, LongCounts)> = Vec::new();
        for (k, case) in cases.iter().enumerate() {
            let sequence = case.sequence;
            let slots = meshes.of(sequence)?;
            let prefix = standing_prefix(run, &start, case.placed)?;
            let conditioning = Conditioning {
                prefix,
                bps: slot_bps(&dataset.objects, dataset.slot_assets(sequence)?, config.bps_points)?,
                present: sequence.object_present,
                prompts: vec![(0, case.prompt)],
                root_start: start.root(),
                skeleton: &run.skeleton,
                free_objects: (free_objects == FreeObjects::AtRest)
                    .then_some(ObjectsAtRest { meshes: slots }),
                seams,
                progress: None,
            };
            let seed = seed
                .wrapping_add(LONG_SEED_OFFSET)
                .wrapping_add(set_index as u64 * SET_STRIDE + k as u64);
            let generated = generate_motion(run, &conditioning, options.frames, seed, sampler)?;
            let clip = MotionClip::from_decoded(&generated.motion)?;
            let sample = clip_sample(&clip, &run.skeleton, slots, None);
            let ours = metrics::object_courses(&sample, support_heights(&case.placed, slots), fps)?;
            let counts =
                metrics::judge_courses(&ours, &truth_courses[case.index], positions(&case.placed))?
                    .with_seams(&metrics::seam_course(&sample, window)?);
            judged.push((sequence.action.as_deref(), counts, truth_counts[case.index].clone()));
            progress.clip_done();
        }
        sets.push(LongSet { kind, rows: rows(&judged) });
    }
    Ok(LongProtocol { frames: options.frames.get(), window, sets })
}

/// All families pooled, then one row per family (in order of first appearance).
fn rows(judged: &[(Option<&str>, LongCounts, LongCounts)]) -> Vec<LongRow> {
    let mut families: Vec<&str> = Vec::new();
    for (family, ..) in judged {
        let family = family.unwrap_or("unlabelled");
        if !families.contains(&family) {
            families.push(family);
        }
    }
    let row = |name: &str, filter: &dyn Fn(Option<&str>) -> bool| {
        let (model, truth, generations) = judged
            .iter()
            .filter(|(family, ..)| filter(*family))
            .fold((LongCounts::default(), LongCounts::default(), 0), |(m, t, n), (_, a, b)| {
                (m.merge(a), t.merge(b), n + 1)
            });
        LongRow {
            family: name.into(),
            generations,
            model: LongScores::of(&model),
            truth: LongScores::of(&truth),
        }
    };
    let mut out = vec![row("all", &|_| true)];
    for family in families {
        out.push(row(family, &|f| f.unwrap_or("unlabelled") == family));
    }
    out
}

fn percent(share: Option<f64>) -> String {
    share.map_or("-".into(), |s| format!("{:.0}%", s * 100.0))
}

fn number(value: Option<f64>, digits: usize) -> String {
    value.map_or("-".into(), |v| format!("{v:.digits$}"))
}

impl LongProtocol {
    /// The protocol's section of `report.md`: one table per set, the model's figure with the
    /// ground truth's in brackets.
    pub fn markdown(&self) -> String {
        let mut out = format!(
            "\n## Long generations\n\n{} frames generated from the standing pose, each test \
             sequence's first-frame object placements and a prompt (no motion prefix), judged \
             against the whole ground-truth sequence; the ground truth's own figure in \
             brackets. As asked: every object moved if and only if the ground truth moves it, \
             with the same hands, to the same side. Lifted again: objects lifted more times \
             than in the ground truth. Off support, sinking, floating: per object the worst \
             distance of its lowest point from where it stood, on frames where no hand is \
             within 15 cm (medians over objects). Start jump: from where an object was placed \
             to the first generated frame. Seam jumps: on the first frame of each window of \
             {} frames after the first, how far the body (the mean over its joints) and each \
             object move from the frame before; the ground truth at the same frames. Floor \
             drift: the lowest joint's change in height from the first frame to the last \
             (median over generations).\n",
            self.frames, self.window
        );
        for set in &self.sets {
            out.push_str(&format!(
                "\n### {}\n\n| Family | Generations | As asked ↑ | Moved ↑ | Hands ↑ | Side ↑ | Lifted again ↓ | Off support (cm) ↓ | Sinking (cm) ↓ | Floating (cm) ↓ | Untouched speed (cm/s) ↓ | Start jump (cm) ↓ | Seam jump, body (cm) ↓ | Seam jump, objects (cm) ↓ | Floor drift (cm) ↓ |\n|{}\n",
                set.kind.title(),
                "---|".repeat(15)
            ));
            for row in &set.rows {
                let (m, t) = (&row.model, &row.truth);
                let share =
                    |a: Option<f64>, b: Option<f64>| format!("{} ({})", percent(a), percent(b));
                let cm =
                    |a: Option<f64>, b: Option<f64>| format!("{} ({})", number(a, 2), number(b, 2));
                out.push_str(&format!(
                    "| {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} |\n",
                    row.family,
                    row.generations,
                    share(m.as_asked, t.as_asked),
                    share(m.moved, t.moved),
                    share(m.hands, t.hands),
                    share(m.travel, t.travel),
                    share(m.lifted_again, t.lifted_again),
                    cm(m.off_support_cm, t.off_support_cm),
                    cm(m.sinking_cm, t.sinking_cm),
                    cm(m.floating_cm, t.floating_cm),
                    cm(m.untouched_speed_cm_s, t.untouched_speed_cm_s),
                    cm(m.start_jump_cm, t.start_jump_cm),
                    cm(m.body_seam_jump_cm, t.body_seam_jump_cm),
                    cm(m.object_seam_jump_cm, t.object_seam_jump_cm),
                    cm(m.floor_drift_cm, t.floor_drift_cm),
                ));
            }
        }
        out
    }
}
