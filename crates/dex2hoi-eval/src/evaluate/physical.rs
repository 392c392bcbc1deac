//! The physical metrics of evaluated clips (paper Sec. 4.2): penetration, contact against the
//! ground truth, foot sliding and mixture agreement (Eq. 4), how objects behave (start jump,
//! speed while untouched), how precisely fingertips sit on held objects against the ground
//! truth, and, for generated clips, instruction following against the ground truth; measured
//! per clip as counts and pooled per replication.

use dex2hoi_data::MAX_OBJECTS;
use dex2hoi_data::dataset::Dataset;
use dex2hoi_data::features::ProcessedSequence;
use dex2hoi_repr::{MeshQuery, Skeleton};
use glam::{Mat3, Vec3};

use crate::error::Result;
use crate::evaluator::MotionClip;
use crate::metrics;

use super::report::{Estimate, InstructionRow, PhysicalRow};
use super::scores::DistributionScores;

/// Where an evaluated clip sits in its test sequence: after the `start` prefix frames,
/// `frames` long.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) struct Window {
    /// First frame of the clip (the prefix length `T_p`).
    pub start: usize,
    /// Frames of the clip.
    pub frames: usize,
}

/// The meshes of a dataset's objects, prepared once for signed-distance queries.
pub(super) struct ObjectMeshes<'a> {
    dataset: &'a Dataset,
    queries: Vec<MeshQuery>,
}

impl<'a> ObjectMeshes<'a> {
    /// Prepares every object of the dataset's manifest.
    pub(super) fn new(dataset: &'a Dataset) -> Result<Self> {
        let queries =
            dataset.objects.iter().map(|a| MeshQuery::new(&a.mesh)).collect::<Result<_, _>>()?;
        Ok(Self { dataset, queries })
    }

    /// The mesh of each of a sequence's object slots (`None` for an empty slot); an object
    /// the dataset does not list is an error.
    pub(super) fn of(
        &self,
        sequence: &ProcessedSequence,
    ) -> Result<[Option<&MeshQuery>; MAX_OBJECTS]> {
        Ok(self.dataset.slot_assets(sequence)?.map(|slot| slot.map(|k| &self.queries[k])))
    }
}

/// The physical measurements of one clip, kept as counts so that a replication pools them.
#[derive(Debug, Clone, PartialEq)]
pub(super) struct Physical {
    penetration: metrics::Penetration,
    contact: metrics::ContactCounts,
    foot_sliding_mm: f64,
    /// Frames where the mixture picks the holding hand, and frames judged.
    agreement: (usize, usize),
    /// Each present object's jump from its last prefix position to the clip's first frame, m.
    start_jumps_m: Vec<f64>,
    /// Object speeds on untouched frames, m/s.
    untouched_speeds: Vec<f64>,
    /// Each present object's turn from its last prefix rotation to the clip's first frame,
    /// degrees.
    start_turns_deg: Vec<f64>,
    /// Object turning rates on untouched frames, degrees per second.
    untouched_turns_deg_s: Vec<f64>,
    /// How far the objects go below their resting heights.
    sinking: metrics::Sinking,
    /// Fingertip-object signed distances on the ground truth's contact frames, m
    /// ([`metrics::fingertip_distances`]).
    fingertips_m: Vec<f32>,
    /// The same minus the ground truth's, one by one, m (zeros for the ground truth itself).
    fingertip_errors_m: Vec<f32>,
    /// A generated clip's instruction following against its ground truth (`None` for the
    /// ground truth itself).
    instruction: Option<metrics::InstructionCounts>,
}

/// Each object's position on frame `frame` of the sequence.
pub(super) fn object_positions_at(
    sequence: &ProcessedSequence,
    frame: usize,
) -> [Vec3; MAX_OBJECTS] {
    std::array::from_fn(|slot| {
        let base = (frame * MAX_OBJECTS + slot) * 3;
        Vec3::from_slice(&sequence.object_positions[base..base + 3])
    })
}

/// Each object's rotation on frame `frame` of the sequence.
pub(super) fn object_rotations_at(
    sequence: &ProcessedSequence,
    frame: usize,
) -> [Mat3; MAX_OBJECTS] {
    std::array::from_fn(|slot| {
        let base = (frame * MAX_OBJECTS + slot) * 9;
        metrics::rotation_from_rows(&sequence.object_rotations[base..base + 9])
    })
}

/// Measures one clip against its sequence's ground-truth contact over the same frames, and its
/// fingertips against the ground truth's (`truth_fingertips_m`, measured by this function for
/// the ground truth's clip; `None` when the clip is the ground truth).
fn measure(
    sample: &metrics::MotionSample<'_>,
    sequence: &ProcessedSequence,
    window: Window,
    fps: f32,
    truth_fingertips_m: Option<&[f32]>,
) -> Result<Physical> {
    let per_frame = MAX_OBJECTS * 2;
    let truth_contact = &sequence.hand_contact
        [window.start * per_frame..(window.start + window.frames) * per_frame];
    let penetration = metrics::penetration(sample, metrics::PENETRATION_TOLERANCE_M)?;
    let contact = metrics::contact_scores(sample, truth_contact, metrics::CONTACT_RADIUS_M)?.counts;
    let foot_sliding_mm = metrics::foot_sliding(sample.joints, sample.skeleton)?;
    let agreement = match sample.mixture_weights {
        Some(weights) => metrics::mixture_agreement_counts(weights, truth_contact, sample.present)?,
        None => (0, 0),
    };
    let start_jumps_m =
        // From the last prefix frame, before `window.start`.
        metrics::object_start_jumps(sample, object_positions_at(sequence, window.start.saturating_sub(1)))?
            .into_iter()
            .flatten()
            .collect();
    let (untouched_speeds, untouched_turns_deg_s) =
        metrics::untouched_object_motion(sample, fps)?.into_iter().unzip();
    let start_turns_deg = metrics::object_start_turns(
        sample,
        object_rotations_at(sequence, window.start.saturating_sub(1)),
    )?
    .into_iter()
    .flatten()
    .collect();
    // Objects rest on the sequence's first frame, before anything moves them (the prefix
    // starts there).
    let sinking = metrics::object_sinking(sample, object_positions_at(sequence, 0))?;
    let fingertips_m = metrics::fingertip_distances(sample, truth_contact)?;
    // The same flags and slots give both clips' distances in the same order.
    let fingertip_errors_m = match truth_fingertips_m {
        Some(truth) => fingertips_m.iter().zip(truth).map(|(clip, truth)| clip - truth).collect(),
        None => vec![0.0; fingertips_m.len()],
    };
    Ok(Physical {
        penetration,
        contact,
        foot_sliding_mm,
        agreement,
        start_jumps_m,
        untouched_speeds,
        start_turns_deg,
        untouched_turns_deg_s,
        sinking,
        fingertips_m,
        fingertip_errors_m,
        instruction: None,
    })
}

/// A clip with its skeleton, meshes and mixture weights as the physical metrics read it.
pub(super) fn clip_sample<'a>(
    clip: &'a MotionClip,
    skeleton: &'a Skeleton,
    objects: [Option<&'a MeshQuery>; MAX_OBJECTS],
    weights: Option<&'a [f32]>,
) -> metrics::MotionSample<'a> {
    metrics::MotionSample {
        skeleton,
        joints: &clip.joints,
        object_rotations: &clip.object_rotations,
        object_positions: &clip.object_positions,
        present: clip.present,
        objects,
        mixture_weights: weights,
    }
}

/// Measures a ground-truth clip, with the mixture weights its own object features encode.
///
/// # Shapes
/// - `truth`: the window's `window.frames` frames of `sequence`
pub(super) fn measure_ground_truth(
    sequence: &ProcessedSequence,
    truth: &MotionClip,
    skeleton: &Skeleton,
    meshes: [Option<&MeshQuery>; MAX_OBJECTS],
    window: Window,
    fps: f32,
) -> Result<Physical> {
    let frames = window.start..window.start + window.frames;
    let objects = &sequence.objects[sequence.layout().object_frames(frames)];
    let weights = metrics::mixture_weights_from_features(objects)?;
    let sample = clip_sample(truth, skeleton, meshes, Some(&weights));
    measure(&sample, sequence, window, fps, None)
}

/// Measures a generated clip against its test sequence's ground truth over the same frames
/// (`truth`: that clip and what [`measure_ground_truth`] measured of it): contact, fingertips,
/// and instruction following.
///
/// # Shapes
/// - `mixture_weights`: `[frames, 2, 3]`; `truth`: the window's frames
#[allow(clippy::too_many_arguments)] // the clip, its ground truth and how to read them
pub(super) fn measure_generated(
    sequence: &ProcessedSequence,
    generated: &MotionClip,
    truth: (&MotionClip, &Physical),
    mixture_weights: &[f32],
    skeleton: &Skeleton,
    meshes: [Option<&MeshQuery>; MAX_OBJECTS],
    window: Window,
    fps: f32,
) -> Result<Physical> {
    let sample = clip_sample(generated, skeleton, meshes, Some(mixture_weights));
    let (truth, truth_measured) = truth;
    let truth_sample = clip_sample(truth, skeleton, meshes, None);
    let instruction = metrics::instruction_following(&sample, &truth_sample)?;
    Ok(Physical {
        instruction: Some(instruction),
        ..measure(&sample, sequence, window, fps, Some(&truth_measured.fingertips_m))?
    })
}

/// One replication's physical metrics, pooled over its clips.
struct Pooled {
    penetration: metrics::Penetration,
    contact: metrics::ContactScores,
    foot_sliding_mm: f64,
    agreement: (usize, usize),
    start_jump_m: Option<f64>,
    untouched_speed: Option<f64>,
    start_turn_deg: Option<f64>,
    untouched_turn_deg_s: Option<f64>,
    sink_depth_m: Option<f64>,
    sink_frames: (usize, usize),
    /// 5th percentile and median of the fingertip distances, m.
    fingertip_low_m: Option<f64>,
    fingertip_median_m: Option<f64>,
    /// Mean absolute fingertip error against the ground truth, m.
    fingertip_error_m: Option<f64>,
}

impl Pooled {
    /// Pools one replication's clips: counts and depth sums add up before the ratios are
    /// taken, so a clip without contact does not make a ratio undefined.
    fn of(clips: &[Physical]) -> Self {
        let penetrations: Vec<metrics::Penetration> = clips.iter().map(|p| p.penetration).collect();
        let counts =
            clips.iter().fold(metrics::ContactCounts::default(), |a, p| a.merge(p.contact));
        let fingertips: Vec<f64> =
            clips.iter().flat_map(|p| p.fingertips_m.iter().map(|&d| f64::from(d))).collect();
        let errors: Vec<f64> = clips
            .iter()
            .flat_map(|p| p.fingertip_errors_m.iter().map(|&e| f64::from(e).abs()))
            .collect();
        // The median of one per-clip list over every clip of the replication.
        let median_of = |values: fn(&Physical) -> &Vec<f64>| {
            metrics::median(
                &clips.iter().flat_map(|p| values(p).iter().copied()).collect::<Vec<_>>(),
            )
        };
        Self {
            penetration: metrics::Penetration::pooled(&penetrations),
            contact: metrics::ContactScores::from_counts(counts),
            foot_sliding_mm: clips.iter().map(|p| p.foot_sliding_mm).sum::<f64>()
                / clips.len().max(1) as f64,
            agreement: clips.iter().fold((0, 0), |a, p| (a.0 + p.agreement.0, a.1 + p.agreement.1)),
            start_jump_m: median_of(|p| &p.start_jumps_m),
            untouched_speed: median_of(|p| &p.untouched_speeds),
            start_turn_deg: median_of(|p| &p.start_turns_deg),
            untouched_turn_deg_s: median_of(|p| &p.untouched_turns_deg_s),
            sink_depth_m: median_of(|p| &p.sinking.deepest_m),
            sink_frames: clips
                .iter()
                .fold((0, 0), |a, p| (a.0 + p.sinking.frames_below, a.1 + p.sinking.frames)),
            fingertip_low_m: metrics::quantile(&fingertips, 0.05),
            fingertip_median_m: metrics::median(&fingertips),
            fingertip_error_m: (!errors.is_empty())
                .then(|| errors.iter().sum::<f64>() / errors.len() as f64),
        }
    }
}

/// The estimate over replications of a value some replications may lack (`None` unless every
/// replication has it).
fn estimate_all(values: impl IntoIterator<Item = Option<f64>>) -> Option<Estimate> {
    values.into_iter().collect::<Option<Vec<f64>>>().map(|v| Estimate::of(&v))
}

/// Pools each replication's clips (`per_replication` consecutive ones), then estimates over
/// replications.
pub(super) fn physical_row(samples: &[Physical], per_replication: usize) -> PhysicalRow {
    let pooled: Vec<Pooled> = samples.chunks(per_replication.max(1)).map(Pooled::of).collect();
    let estimate =
        |f: &dyn Fn(&Pooled) -> f64| Estimate::of(&pooled.iter().map(f).collect::<Vec<_>>());
    let judged = pooled.iter().all(|p| p.agreement.1 > 0);
    PhysicalRow {
        penetration_depth_mm: estimate(&|p| p.penetration.mean_depth_mm),
        penetration_frames_percent: estimate(&|p| 100.0 * p.penetration.frame_share),
        contact_precision: estimate(&|p| p.contact.precision),
        contact_recall: estimate(&|p| p.contact.recall),
        contact_f1: estimate(&|p| p.contact.f1),
        contact_distance_mm: estimate(&|p| {
            p.contact.mean_distance_on_contact_mm.unwrap_or(f64::NAN)
        }),
        foot_sliding_mm: estimate(&|p| p.foot_sliding_mm),
        mixture_agreement_percent: judged
            .then(|| estimate(&|p| 100.0 * p.agreement.0 as f64 / p.agreement.1 as f64)),
        object_start_jump_cm: estimate_all(
            pooled.iter().map(|p| p.start_jump_m.map(|m| 100.0 * m)),
        ),
        untouched_speed_cm_s: estimate_all(
            pooled.iter().map(|p| p.untouched_speed.map(|v| 100.0 * v)),
        ),
        object_start_turn_deg: estimate_all(pooled.iter().map(|p| p.start_turn_deg)),
        untouched_turn_deg_s: estimate_all(pooled.iter().map(|p| p.untouched_turn_deg_s)),
        sinking_depth_cm: estimate_all(pooled.iter().map(|p| p.sink_depth_m.map(|m| 100.0 * m))),
        sinking_frames_percent: estimate_all(pooled.iter().map(|p| {
            (p.sink_frames.1 > 0).then(|| 100.0 * p.sink_frames.0 as f64 / p.sink_frames.1 as f64)
        })),
        fingertip_low_mm: estimate_all(pooled.iter().map(|p| p.fingertip_low_m.map(|m| 1e3 * m))),
        fingertip_median_mm: estimate_all(
            pooled.iter().map(|p| p.fingertip_median_m.map(|m| 1e3 * m)),
        ),
        fingertip_error_mm: estimate_all(
            pooled.iter().map(|p| p.fingertip_error_m.map(|m| 1e3 * m)),
        ),
    }
}

/// The replications' distribution scores behind [`instruction_rows`]' R-precision columns.
#[derive(Clone, Copy)]
pub(super) struct GroupScores<'a> {
    /// The generated clips', one per replication.
    pub generated: &'a [DistributionScores],
    /// The ground truth's, one per replication.
    pub truth: &'a [DistributionScores],
}

/// The instruction-following rows of generated clips: all clips, then each action (task
/// family) of the sequences in turn, each pooled per replication (`per_replication`
/// consecutive clips, in the order of `actions`) and estimated over replications; with each
/// group's R-precision top-3 from the replications' `scores` of the generated clips and of the
/// ground truth.
///
/// # Shapes
/// - `samples`: `[replications * per_replication]`; `actions`: `[per_replication]`;
///   `scores`: `[replications]` each
pub(super) fn instruction_rows(
    samples: &[Physical],
    actions: &[Option<&str>],
    scores: GroupScores<'_>,
) -> Vec<InstructionRow> {
    let per_replication = actions.len().max(1);
    let mut groups: Vec<&str> = actions.iter().flatten().copied().collect();
    groups.sort_unstable();
    groups.dedup();
    let all = std::iter::once(None).chain(groups.into_iter().map(Some));
    all.map(|group| {
        let member = |action: &Option<&str>| group.is_none() || *action == group;
        let pooled: Vec<metrics::InstructionCounts> = samples
            .chunks(per_replication)
            .map(|replication| {
                replication
                    .iter()
                    .zip(actions)
                    .filter(|(_, action)| member(action))
                    .filter_map(|(p, _)| p.instruction.as_ref())
                    .fold(metrics::InstructionCounts::default(), |a, c| a.merge(c))
            })
            .collect();
        let percent = |share: fn(&metrics::InstructionCounts) -> Option<f64>| {
            estimate_all(pooled.iter().map(|c| share(c).map(|v| 100.0 * v)))
        };
        let top3 = |scores: &[DistributionScores]| {
            estimate_all(
                scores.iter().map(|s| s.top3_of(|clip| actions.get(clip).is_some_and(member))),
            )
        };
        InstructionRow {
            group: group.unwrap_or("all").to_string(),
            clips: actions.iter().filter(|a| member(a)).count(),
            objects_moved_percent: percent(metrics::InstructionCounts::moved_share),
            unasked_moves_percent: percent(metrics::InstructionCounts::unasked_share),
            holding_hand_percent: percent(metrics::InstructionCounts::holder_share),
            same_side_percent: percent(metrics::InstructionCounts::same_side_share),
            end_distance_cm: estimate_all(
                pooled.iter().map(|c| c.median_end_distance_m().map(|m| 100.0 * m)),
            ),
            r_precision_top3: top3(scores.generated),
            truth_r_precision_top3: top3(scores.truth),
        }
    })
    .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A clip with nothing measured but its (empty) instruction counts.
    fn clip() -> Physical {
        Physical {
            penetration: metrics::Penetration {
                mean_depth_mm: 0.0,
                frame_share: 0.0,
                mean_frame_depth_mm: 0.0,
                penetrating_joint_frames: 0,
                penetrating_frames: 0,
                frames: 1,
                depth_sum_mm: 0.0,
                frame_depth_sum_mm: 0.0,
            },
            contact: metrics::ContactCounts::default(),
            foot_sliding_mm: 0.0,
            agreement: (0, 0),
            start_jumps_m: Vec::new(),
            untouched_speeds: Vec::new(),
            start_turns_deg: Vec::new(),
            untouched_turns_deg_s: Vec::new(),
            sinking: metrics::Sinking::default(),
            fingertips_m: Vec::new(),
            fingertip_errors_m: Vec::new(),
            instruction: Some(metrics::InstructionCounts::default()),
        }
    }

    fn scores(ranks: Vec<Option<usize>>) -> DistributionScores {
        DistributionScores {
            r_precision: metrics::r_precision_of_ranks(&ranks).unwrap(),
            ranks,
            fid: 0.0,
            mm_dist: 0.0,
            diversity: 0.0,
            multimodality: None,
        }
    }

    #[test]
    fn each_group_gets_the_r_precision_of_its_own_clips() {
        // Clips of actions a, b, a, b: a's own motions rank 0 and 1 (both in the top 3), b's
        // rank 5 and (dropped with the incomplete batch) none; the ground truth retrieves all.
        let actions = [Some("a"), Some("b"), Some("a"), Some("b")];
        let generated = [scores(vec![Some(0), Some(5), Some(1), None])];
        let truth = [scores(vec![Some(0), Some(0), Some(2), None])];
        let samples = vec![clip(); 4];
        let rows = instruction_rows(
            &samples,
            &actions,
            GroupScores { generated: &generated, truth: &truth },
        );
        let top3 = |group: &str| {
            let row = rows.iter().find(|r| r.group == group).unwrap();
            (row.r_precision_top3.unwrap().mean, row.truth_r_precision_top3.unwrap().mean)
        };
        assert_eq!(top3("all"), (2.0 / 3.0, 1.0));
        assert_eq!(top3("a"), (1.0, 1.0));
        assert_eq!(top3("b"), (0.0, 1.0));
        assert_eq!(rows.iter().find(|r| r.group == "b").unwrap().clips, 2);
    }
}
