//! The evaluation report: rows of estimates over replications laid out like the paper's tables
//! (Sec. 4.2), as markdown and JSON, and the embeddings of the last replication as `.npz`.

use std::path::Path;

use serde::{Deserialize, Deserializer, Serialize};

use dex2hoi_data::MAX_OBJECTS;
use dex2hoi_diffusion::{SamplerConfig, SamplerKind};
use dex2hoi_sample::rest::FreeObjects;
use dex2hoi_sample::seams::Seams;

use crate::error::{EvalError, Result};
use crate::evaluator::MotionClip;
use crate::metrics;

use super::embedding::EmbeddedMotions;
use super::scores::DistributionScores;

/// A value over replications: the mean and the half-width of its 95% interval.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Estimate {
    /// Mean over replications (JSON writes a non-finite mean as `null`, read back as NaN).
    #[serde(deserialize_with = "finite_or_nan")]
    pub mean: f64,
    /// `1.96 std / sqrt(R)`.
    #[serde(deserialize_with = "finite_or_nan")]
    pub interval: f64,
}

/// Reads a number that `serde_json` wrote as `null` because it was not finite.
fn finite_or_nan<'de, D: Deserializer<'de>>(deserializer: D) -> Result<f64, D::Error> {
    Ok(Option::<f64>::deserialize(deserializer)?.unwrap_or(f64::NAN))
}

/// Reads an optional pair of numbers, each possibly written as `null` (see [`finite_or_nan`]).
fn optional_pair<'de, D: Deserializer<'de>>(
    deserializer: D,
) -> Result<Option<(f64, f64)>, D::Error> {
    let pair = Option::<(Option<f64>, Option<f64>)>::deserialize(deserializer)?;
    Ok(pair.map(|(a, b)| (a.unwrap_or(f64::NAN), b.unwrap_or(f64::NAN))))
}

/// The reverse process of an evaluation.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum SamplerName {
    /// DDIM.
    Ddim,
    /// Ancestral DDPM.
    Ddpm,
}

/// Which model and sampler an evaluation measured, so that reports can be compared and
/// reproduced.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EvaluationSetup {
    /// Training steps of the evaluated weights.
    pub model_step: usize,
    /// The reverse process.
    pub sampler: SamplerName,
    /// DDIM's noise scale (`None` for DDPM).
    pub eta: Option<f64>,
    /// Respaced denoising steps.
    pub denoising_steps: usize,
    /// Classifier-free guidance scale (`None`: off).
    pub guidance: Option<f64>,
    /// Seed of the first replication's noise.
    pub seed: u64,
    /// Whether the sampler kept the objects no hand holds at rest (`dex2hoi_sample::rest`;
    /// beyond the paper). Reports without it were made without the rule.
    #[serde(default)]
    pub objects_at_rest: bool,
    /// Whether each window carried on from its prefix (`dex2hoi_sample::seams`; beyond the
    /// paper). Reports without it were made without the rule.
    #[serde(default)]
    pub continuous_seams: bool,
}

impl EvaluationSetup {
    /// The setup of an evaluation of weights trained for `model_step` steps.
    pub fn new(model_step: usize, sampler: &SamplerConfig, seed: u64) -> Self {
        let (name, eta) = match sampler.kind {
            SamplerKind::Ddpm => (SamplerName::Ddpm, None),
            SamplerKind::Ddim { eta } => (SamplerName::Ddim, Some(eta)),
        };
        Self {
            model_step,
            sampler: name,
            eta,
            denoising_steps: sampler.steps,
            guidance: sampler.guidance,
            seed,
            objects_at_rest: false,
            continuous_seams: false,
        }
    }

    /// The same setup with the sampler's rules beyond the paper as they were used.
    pub fn with_rules(self, free_objects: FreeObjects, seams: Seams) -> Self {
        Self {
            objects_at_rest: free_objects == FreeObjects::AtRest,
            continuous_seams: seams == Seams::Continuous,
            ..self
        }
    }

    /// One line for the report: `DDIM (eta 0), 50 steps, guidance 2, seed 0`.
    pub fn describe(&self) -> String {
        let name = match self.sampler {
            SamplerName::Ddim => "DDIM",
            SamplerName::Ddpm => "DDPM",
        };
        let sampler = match self.eta {
            Some(eta) => format!("{name} (eta {eta})"),
            None => name.to_string(),
        };
        let guidance = self.guidance.map_or("no guidance".into(), |g| format!("guidance {g}"));
        let rules: String = [
            (self.objects_at_rest, ", objects at rest"),
            (self.continuous_seams, ", continuous seams"),
        ]
        .into_iter()
        .filter_map(|(on, rule)| on.then_some(rule))
        .collect();
        format!("{sampler}, {} steps, {guidance}, seed {}{rules}", self.denoising_steps, self.seed)
    }
}

impl Estimate {
    /// The estimate over the replications' values (T2M's `get_metric_statistics`).
    pub(super) fn of(values: &[f64]) -> Self {
        let (mean, interval) = metrics::mean_interval(values);
        Self { mean, interval }
    }
}

/// One row of the report (the ground truth or a model).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ReportRow {
    /// What the row measures.
    pub name: String,
    /// R-precision top-1, top-2, top-3.
    pub r_precision: [Estimate; 3],
    /// FID against the ground truth (0 for the ground-truth row by definition).
    pub fid: Estimate,
    /// Mean distance between matched motion and text embeddings.
    pub mm_dist: Estimate,
    /// Diversity.
    pub diversity: Estimate,
    /// MultiModality (models only).
    pub multimodality: Option<Estimate>,
    /// Physical metrics.
    pub physical: PhysicalRow,
    /// Seconds per generated clip (mean and standard deviation over all samples; models only).
    #[serde(deserialize_with = "optional_pair", default)]
    pub runtime_seconds: Option<(f64, f64)>,
}

/// The physical metrics of a row, each over replications.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PhysicalRow {
    /// Mean penetration depth, mm.
    pub penetration_depth_mm: Estimate,
    /// Share of frames with penetration, percent.
    pub penetration_frames_percent: Estimate,
    /// Contact precision against the ground truth.
    pub contact_precision: Estimate,
    /// Contact recall.
    pub contact_recall: Estimate,
    /// Contact F1.
    pub contact_f1: Estimate,
    /// Mean hand-object distance on ground-truth contact frames, mm.
    pub contact_distance_mm: Estimate,
    /// Foot sliding, mm per frame.
    pub foot_sliding_mm: Estimate,
    /// Share of one-hand holding frames where the mixture weights pick the holding hand,
    /// percent (`None` when no frame qualifies).
    pub mixture_agreement_percent: Option<Estimate>,
    /// Median distance from an object's last prefix position to its first clip position, cm.
    pub object_start_jump_cm: Option<Estimate>,
    /// Median speed of objects no hand is near, cm/s (`None` when no frame qualifies).
    pub untouched_speed_cm_s: Option<Estimate>,
    /// Median turn of the objects from their last prefix rotation to the first clip frame,
    /// degrees (`None` without objects; may be absent in format 1).
    #[serde(default)]
    pub object_start_turn_deg: Option<Estimate>,
    /// Median turning rate of objects on untouched frames, degrees per second (likewise).
    #[serde(default)]
    pub untouched_turn_deg_s: Option<Estimate>,
    /// Median over objects of the deepest drop below the height the object rested at, cm
    /// (`None` without objects; absent in reports of older versions).
    #[serde(default)]
    pub sinking_depth_cm: Option<Estimate>,
    /// Frames with an object more than 1 cm below its resting height, percent.
    #[serde(default)]
    pub sinking_frames_percent: Option<Estimate>,
    /// 5th percentile of the fingertips' signed distances to the objects the ground truth holds,
    /// on its contact frames, mm (`None` without contact; absent in older reports).
    #[serde(default)]
    pub fingertip_low_mm: Option<Estimate>,
    /// Median of the same, mm.
    #[serde(default)]
    pub fingertip_median_mm: Option<Estimate>,
    /// Mean absolute difference of the same from the ground truth's, fingertip by fingertip, mm.
    #[serde(default)]
    pub fingertip_error_mm: Option<Estimate>,
}

/// Instruction following of the generated clips against their ground truth after the same
/// prefix (`metrics::instruction_following`), for all clips or one action (task family).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct InstructionRow {
    /// `all`, or the action of the sequences.
    pub group: String,
    /// Clips per replication in the group.
    pub clips: usize,
    /// Objects the ground truth moves that the clip moves too, percent.
    pub objects_moved_percent: Option<Estimate>,
    /// Objects the ground truth leaves that the clip moves anyway, percent.
    pub unasked_moves_percent: Option<Estimate>,
    /// Ground-truth holding frames held by the same hands, percent.
    pub holding_hand_percent: Option<Estimate>,
    /// Moved objects ending on the same side of the body, percent.
    pub same_side_percent: Option<Estimate>,
    /// Median distance between the final positions of moved objects, cm.
    pub end_distance_cm: Option<Estimate>,
    /// R-precision top-3 of the group's prompts ranking the generated clips (in the batches of
    /// every group); absent in reports written before it was measured.
    #[serde(default)]
    pub r_precision_top3: Option<Estimate>,
    /// The same for the ground truth's clips.
    #[serde(default)]
    pub truth_r_precision_top3: Option<Estimate>,
}

/// The version of `report.json`'s layout that [`Report`] writes (`docs/FORMATS.md`). Format 1
/// (no `format` field) may lack the per-group R-precision, the object turns, the sinking and
/// the fingertip figures; it reads back with them `None`. Format 3 added the long-generation
/// protocol (`long`, absent when it was not run).
pub const REPORT_FORMAT: u32 = 3;

fn format_one() -> u32 {
    1
}

/// The whole report.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Report {
    /// The layout's version ([`REPORT_FORMAT`] when written; 1 when a file has none).
    #[serde(default = "format_one")]
    pub format: u32,
    /// The evaluated weights' steps and the sampler.
    pub setup: EvaluationSetup,
    /// Ground truth, then the model.
    pub rows: Vec<ReportRow>,
    /// The model's instruction following: all clips, then per action.
    pub instruction: Vec<InstructionRow>,
    /// Test sequences evaluated per replication.
    pub samples: usize,
    /// Test sequences skipped (too short for prefix + clip).
    pub skipped: usize,
    /// Replications.
    pub replications: usize,
    /// Frames per evaluated clip.
    pub clip_frames: usize,
    /// Which features FID, Diversity and MultiModality use.
    pub distribution_features: String,
    /// The MultiModality protocol.
    pub multimodality_protocol: [usize; 3],
    /// The long-generation protocol's results, when it ran.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub long: Option<super::LongProtocol>,
}

/// Embeddings of the last replication and the clips they embed, for `--dump-embeddings`.
#[derive(Debug, Clone, PartialEq)]
pub struct Embeddings {
    /// Generated motions' contrastive embeddings.
    pub generated: Vec<Vec<f32>>,
    /// Ground-truth motions' contrastive embeddings.
    pub ground_truth: Vec<Vec<f32>>,
    /// The prompts' text embeddings.
    pub texts: Vec<Vec<f32>>,
    /// The prompts.
    pub prompts: Vec<String>,
    /// Action features of the generated and ground-truth motions (empty without labels).
    pub generated_action: Vec<Vec<f32>>,
    /// Action features of the ground truth.
    pub ground_truth_action: Vec<Vec<f32>>,
    /// The generated clips.
    pub generated_clips: Vec<MotionClip>,
    /// The ground truth's clips.
    pub ground_truth_clips: Vec<MotionClip>,
    /// The test sequences' actions (task families; empty where a sequence has none).
    pub actions: Vec<String>,
}

impl ReportRow {
    /// A row from the distribution scores of every replication (R-precision, FID, MMdist,
    /// Diversity, MultiModality) and the physical metrics. MultiModality is reported only when
    /// every replication measured a finite value.
    pub(super) fn from_replications(
        name: &str,
        scores: &[DistributionScores],
        physical: PhysicalRow,
        runtime_seconds: Option<(f64, f64)>,
    ) -> Self {
        let column = |value: fn(&DistributionScores) -> f64| {
            Estimate::of(&scores.iter().map(value).collect::<Vec<_>>())
        };
        let multimodality = scores
            .iter()
            .map(|s| s.multimodality.filter(|v| v.is_finite()))
            .collect::<Option<Vec<f64>>>()
            .map(|values| Estimate::of(&values));
        Self {
            name: name.to_string(),
            r_precision: [
                column(|s| s.r_precision[0]),
                column(|s| s.r_precision[1]),
                column(|s| s.r_precision[2]),
            ],
            fid: column(|s| s.fid),
            mm_dist: column(|s| s.mm_dist),
            diversity: column(|s| s.diversity),
            multimodality,
            physical,
            runtime_seconds,
        }
    }
}

fn cell(e: &Estimate, digits: usize) -> String {
    format!("{:.*} ± {:.*}", digits, e.mean, digits, e.interval)
}

fn optional_cell(e: Option<&Estimate>, digits: usize) -> String {
    e.map_or("-".into(), |e| cell(e, digits))
}

impl Report {
    /// Reads `report.json` (any format up to [`REPORT_FORMAT`]); `path` names the file in
    /// errors.
    pub fn from_json(path: &Path, bytes: &[u8]) -> Result<Self> {
        let bad = |what: &str, expected: &str, got: String| EvalError::File {
            path: path.to_path_buf(),
            what: what.into(),
            expected: expected.into(),
            got,
        };
        let value: serde_json::Value =
            serde_json::from_slice(bytes).map_err(|e| bad("contents", "JSON", e.to_string()))?;
        let format = match value.get("format") {
            None => 1,
            Some(v) => {
                v.as_u64().ok_or_else(|| bad("format", "a version number", v.to_string()))?
            }
        };
        if format > u64::from(REPORT_FORMAT) {
            return Err(bad(
                "format",
                &format!(
                    "a report of format {REPORT_FORMAT} or older (this dex2hoi reads up to it)"
                ),
                format!("format {format}"),
            ));
        }
        if value.get("setup").is_none() {
            return Err(bad(
                "setup",
                "the evaluated step and sampler (a report of `dex2hoi evaluate`)",
                "none (written by an older dex2hoi): run `dex2hoi evaluate` again".into(),
            ));
        }
        serde_json::from_value(value)
            .map_err(|e| bad("contents", "a report of `dex2hoi evaluate`", e.to_string()))
    }

    /// The report as markdown: one table laid out like the paper's (ground truth first), then
    /// the physical metrics, with units and the protocol.
    pub fn markdown(&self, title: &str) -> String {
        let mut out = format!("# {title}\n\n");
        out.push_str(
            "| Method | R-prec. top-1 ↑ | top-2 ↑ | top-3 ↑ | FID ↓ | MMdist ↓ | Diversity → | MModality ↑ | Pen. depth (mm) ↓ | Pen. frames (%) ↓ | Contact P ↑ | Contact R ↑ | Contact F1 ↑ | Hand-obj. dist. (mm) ↓ | Foot sliding (mm/frame) ↓ | Mixture picks holding hand (%) ↑ | Runtime (s / clip) ↓ |\n",
        );
        out.push_str(&format!("|{}\n", "---|".repeat(17)));
        for row in &self.rows {
            let p = &row.physical;
            out.push_str(&format!(
                "| {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} |\n",
                row.name,
                cell(&row.r_precision[0], 3),
                cell(&row.r_precision[1], 3),
                cell(&row.r_precision[2], 3),
                cell(&row.fid, 3),
                cell(&row.mm_dist, 3),
                cell(&row.diversity, 3),
                row.multimodality.as_ref().map_or("-".into(), |e| cell(e, 3)),
                cell(&p.penetration_depth_mm, 2),
                cell(&p.penetration_frames_percent, 1),
                cell(&p.contact_precision, 3),
                cell(&p.contact_recall, 3),
                cell(&p.contact_f1, 3),
                cell(&p.contact_distance_mm, 1),
                cell(&p.foot_sliding_mm, 2),
                p.mixture_agreement_percent.as_ref().map_or("-".into(), |e| cell(e, 1)),
                row.runtime_seconds.map_or("-".into(), |(m, s)| format!("{m:.2} ± {s:.2}")),
            ));
        }
        out.push_str(&format!(
            "\n{} test sequences ({} too short skipped), {} replications (mean ± 95% interval), \
             clips of {} frames after the sequence's own prefix. FID, Diversity and MultiModality \
             on {}; R-precision and MMdist on the contrastive embeddings; MultiModality over {} \
             prompts x {} repeats x {} pairs. The ground-truth FID is 0 by definition (the same \
             clips). Runtime: mean ± standard deviation per generated clip. Weights after {} \
             training steps; sampler: {}.\n",
            self.samples,
            self.skipped,
            self.replications,
            self.clip_frames,
            self.distribution_features,
            self.multimodality_protocol[0],
            self.multimodality_protocol[1],
            self.multimodality_protocol[2],
            self.setup.model_step,
            self.setup.describe(),
        ));
        out.push_str(
            "\n## Objects\n\n| Method | Start jump (cm, median) ↓ | Untouched object speed (cm/s, median) ↓ | Start turn (°, median) ↓ | Untouched turning (°/s, median) ↓ | Sinking (cm, median deepest) ↓ | Frames sunk (%) ↓ |\n|---|---|---|---|---|---|---|\n",
        );
        for row in &self.rows {
            let p = &row.physical;
            out.push_str(&format!(
                "| {} | {} | {} | {} | {} | {} | {} |\n",
                row.name,
                optional_cell(p.object_start_jump_cm.as_ref(), 2),
                optional_cell(p.untouched_speed_cm_s.as_ref(), 2),
                optional_cell(p.object_start_turn_deg.as_ref(), 2),
                optional_cell(p.untouched_turn_deg_s.as_ref(), 2),
                optional_cell(p.sinking_depth_cm.as_ref(), 2),
                optional_cell(p.sinking_frames_percent.as_ref(), 1),
            ));
        }
        out.push_str(
            "\nStart jump: from each object's last prefix position to its first clip position \
             (the ground truth's is one frame of its own motion). Untouched: frames where every \
             hand joint is more than 15 cm from the object's surface. Start turn and untouched \
             turning: the same for the object's orientation (the angle between consecutive \
             rotations). Sinking: how far an \
             object's origin goes below the height it rested at on the sequence's first frame \
             (through the table it stood on); frames sunk: frames with an object more than 1 cm \
             below it.\n",
        );
        out.push_str(
            "\n## Grasp\n\n| Method | Fingertip distance (mm, 5th percentile) | Fingertip distance (mm, median) | Fingertip error (mm, mean) ↓ |\n|---|---|---|---|\n",
        );
        for row in &self.rows {
            let p = &row.physical;
            out.push_str(&format!(
                "| {} | {} | {} | {} |\n",
                row.name,
                optional_cell(p.fingertip_low_mm.as_ref(), 1),
                optional_cell(p.fingertip_median_mm.as_ref(), 1),
                optional_cell(p.fingertip_error_mm.as_ref(), 1),
            ));
        }
        out.push_str(
            "\nSigned distance (negative inside) of each fingertip joint to the object, on the \
             frames where the ground truth has that hand in contact with it (a hand joint within \
             5 cm); error: against the ground truth's fingertip over the same frames. A joint \
             centre sits about a finger's half thickness outside the surface it touches; the \
             penetration count starts 5 mm inside.\n",
        );
        out.push_str(
            "\n## Instruction following (generated vs ground truth after the same prefix)\n\n| Group | Clips | Objects moved (%) ↑ | Unasked moves (%) ↓ | Holding hand (%) ↑ | Same side (%) ↑ | End distance (cm, median) ↓ | R-prec. top-3 ↑ | Ground truth's R-prec. top-3 |\n|---|---|---|---|---|---|---|---|---|\n",
        );
        for row in &self.instruction {
            out.push_str(&format!(
                "| {} | {} | {} | {} | {} | {} | {} | {} | {} |\n",
                row.group,
                row.clips,
                optional_cell(row.objects_moved_percent.as_ref(), 1),
                optional_cell(row.unasked_moves_percent.as_ref(), 1),
                optional_cell(row.holding_hand_percent.as_ref(), 1),
                optional_cell(row.same_side_percent.as_ref(), 1),
                optional_cell(row.end_distance_cm.as_ref(), 1),
                optional_cell(row.r_precision_top3.as_ref(), 3),
                optional_cell(row.truth_r_precision_top3.as_ref(), 3),
            ));
        }
        out.push_str(
            "\nAn object moves when it travels more than 10 cm or rises more than 5 cm; a hand \
             holds it when one of its joints is within the contact radius (5 cm) of its surface. \
             Objects moved: of the objects the ground truth moves, those the clip moves. \
             Unasked: of those it leaves, those the clip moves. Holding hand: of the frames \
             where the ground truth holds an object, those where the clip holds it with the same \
             hands. Same side / end distance: where the moved objects end, across the body \
             (left, centre within 5 cm, right) and in cm. R-prec. top-3: of the group's prompts, \
             those whose own clip is among the 3 nearest of its batch (the batches of the table \
             above: 32 clips of every group in a seeded shuffle, fewer when the split is \
             smaller, the incomplete last one left out; a group none of whose clips was ranked \
             in some replication shows \"-\"). \"-\" where nothing qualifies.\n",
        );
        if let Some(long) = &self.long {
            out.push_str(&long.markdown());
        }
        out
    }
}

impl Embeddings {
    /// The ground truth's embeddings, with the generated side still empty (filled by
    /// [`Embeddings::set_replication`]).
    pub(super) fn of_ground_truth(
        truth: &EmbeddedMotions,
        clips: &[MotionClip],
        actions: &[Option<&str>],
    ) -> Self {
        Self {
            generated: Vec::new(),
            ground_truth: truth.contrastive.clone(),
            texts: Vec::new(),
            prompts: Vec::new(),
            generated_action: Vec::new(),
            ground_truth_action: truth.action.clone(),
            generated_clips: Vec::new(),
            ground_truth_clips: clips.to_vec(),
            actions: actions.iter().map(|a| a.unwrap_or_default().to_string()).collect(),
        }
    }

    /// Keeps a replication's generated embeddings, texts and prompts (each replication replaces
    /// the previous one's, so the last one is dumped).
    pub(super) fn set_replication(
        &mut self,
        generated: EmbeddedMotions,
        clips: Vec<MotionClip>,
        texts: Vec<Vec<f32>>,
        prompts: Vec<String>,
    ) {
        self.generated_clips = clips;
        self.generated = generated.contrastive;
        self.generated_action = generated.action;
        self.texts = texts;
        self.prompts = prompts;
    }

    /// The embeddings as an `.npz` archive (float32 arrays and the prompts as strings), with the
    /// clips: per side (`generated_`, `ground_truth_`) `joints` `[N, T, J, 3]`,
    /// `object_rotations` `[N, T, 2, 3, 3]` (row-major) and `object_positions` `[N, T, 2, 3]`
    /// in metres, the canonical frame; `object_present` `[N, 2]` (0 or 1) and the `actions`.
    pub fn npz(&self) -> Result<Vec<u8>> {
        use dex2hoi_data::npz::{NpyArray, encode_npz};
        let matrix = |name: &str, rows: &[Vec<f32>]| {
            let width = rows.first().map_or(0, Vec::len);
            NpyArray::f32(name, &[rows.len(), width], rows.iter().flatten().copied().collect())
        };
        let mut arrays = vec![
            matrix("generated_motion", &self.generated),
            matrix("ground_truth_motion", &self.ground_truth),
            matrix("text", &self.texts),
            NpyArray::text("prompts", &[self.prompts.len()], self.prompts.clone()),
        ];
        if !self.generated_action.is_empty() {
            arrays.push(matrix("generated_action", &self.generated_action));
            arrays.push(matrix("ground_truth_action", &self.ground_truth_action));
        }
        for (side, clips) in
            [("generated", &self.generated_clips), ("ground_truth", &self.ground_truth_clips)]
        {
            arrays.extend(clip_arrays(side, clips)?);
        }
        arrays.push(NpyArray::text("actions", &[self.actions.len()], self.actions.clone()));
        Ok(encode_npz(&arrays)?)
    }
}

/// The `.npz` arrays of a side's clips (see [`Embeddings::npz`]).
///
/// # Errors
/// Clips of different lengths or skeletons, which cannot share an array.
fn clip_arrays(side: &str, clips: &[MotionClip]) -> Result<Vec<dex2hoi_data::npz::NpyArray>> {
    use dex2hoi_data::npz::NpyArray;
    let frames = clips.first().map_or(0, MotionClip::frames);
    let joints = clips.first().map_or(0, |c| c.joints.len() / (3 * frames.max(1)));
    if let Some(other) =
        clips.iter().find(|c| c.frames() != frames || c.joints.len() != frames * joints * 3)
    {
        return Err(EvalError::invalid(
            format!("{side} clips"),
            format!("{frames} frames of {joints} joints each, as the first"),
            format!("{} frames of {} joint numbers", other.frames(), other.joints.len()),
        ));
    }
    let n = clips.len();
    let gather = |part: fn(&MotionClip) -> &[f32]| clips.iter().flat_map(part).copied().collect();
    let present =
        clips.iter().flat_map(|c| c.present.map(|p| if p { 1.0f32 } else { 0.0 })).collect();
    Ok(vec![
        NpyArray::f32(format!("{side}_joints"), &[n, frames, joints, 3], gather(|c| &c.joints)),
        NpyArray::f32(
            format!("{side}_object_rotations"),
            &[n, frames, MAX_OBJECTS, 3, 3],
            gather(|c| &c.object_rotations),
        ),
        NpyArray::f32(
            format!("{side}_object_positions"),
            &[n, frames, MAX_OBJECTS, 3],
            gather(|c| &c.object_positions),
        ),
        NpyArray::f32(format!("{side}_object_present"), &[n, MAX_OBJECTS], present),
    ])
}

#[cfg(test)]
mod tests {
    use super::*;

    fn estimate(mean: f64) -> Estimate {
        Estimate { mean, interval: 0.5 }
    }

    /// A report with non-finite values survives JSON (where they become `null`) as NaN.
    #[test]
    fn reports_read_back_what_they_wrote_non_finite_values_as_nan() {
        let physical = PhysicalRow {
            penetration_depth_mm: estimate(1.0),
            penetration_frames_percent: estimate(2.0),
            contact_precision: estimate(0.9),
            contact_recall: estimate(f64::NAN),
            contact_f1: estimate(0.8),
            contact_distance_mm: estimate(f64::INFINITY),
            foot_sliding_mm: estimate(0.1),
            mixture_agreement_percent: None,
            object_start_jump_cm: Some(estimate(0.7)),
            untouched_speed_cm_s: None,
            object_start_turn_deg: Some(estimate(3.0)),
            untouched_turn_deg_s: None,
            sinking_depth_cm: Some(estimate(0.2)),
            sinking_frames_percent: None,
            fingertip_low_mm: Some(estimate(-1.0)),
            fingertip_median_mm: Some(estimate(7.0)),
            fingertip_error_mm: None,
        };
        let row = ReportRow {
            name: "model".into(),
            r_precision: [estimate(0.1), estimate(0.2), estimate(0.3)],
            fid: estimate(40.0),
            mm_dist: estimate(0.8),
            diversity: estimate(f64::NAN),
            multimodality: None,
            physical,
            runtime_seconds: Some((1.5, f64::NAN)),
        };
        let sampler = SamplerConfig { kind: SamplerKind::Ddpm, steps: 20, guidance: None };
        let report = Report {
            format: REPORT_FORMAT,
            setup: EvaluationSetup::new(6000, &sampler, 3),
            rows: vec![row],
            instruction: vec![InstructionRow {
                group: "all".into(),
                clips: 4,
                objects_moved_percent: Some(estimate(50.0)),
                unasked_moves_percent: None,
                holding_hand_percent: Some(estimate(f64::NAN)),
                same_side_percent: None,
                end_distance_cm: None,
                r_precision_top3: Some(estimate(0.4)),
                truth_r_precision_top3: None,
            }],
            samples: 4,
            skipped: 1,
            replications: 2,
            clip_frames: 60,
            distribution_features: "features".into(),
            multimodality_protocol: [2, 2, 1],
            long: None,
        };
        let json = serde_json::to_string(&report).unwrap();
        assert!(json.contains("\"sampler\":\"ddpm\"") && json.contains("null"), "{json}");
        let back: Report = serde_json::from_str(&json).unwrap();
        assert_eq!(back.setup, report.setup);
        assert_eq!(back.setup.describe(), "DDPM, 20 steps, no guidance, seed 3");
        let (row, read) = (&report.rows[0], &back.rows[0]);
        assert!(read.diversity.mean.is_nan() && read.physical.contact_recall.mean.is_nan());
        assert!(read.physical.contact_distance_mm.mean.is_nan(), "infinity is written as null");
        let (runtime, std) = read.runtime_seconds.unwrap();
        assert!(runtime == 1.5 && std.is_nan());
        assert_eq!(read.fid, row.fid);
        assert_eq!(read.physical.object_start_jump_cm, row.physical.object_start_jump_cm);
        assert_eq!(read.physical.object_start_turn_deg, row.physical.object_start_turn_deg);
        assert!(back.instruction[0].holding_hand_percent.unwrap().mean.is_nan());
        assert_eq!(
            back.instruction[0].objects_moved_percent,
            report.instruction[0].objects_moved_percent
        );
        assert_eq!(back.instruction[0].r_precision_top3, report.instruction[0].r_precision_top3);
        assert_eq!(back.format, REPORT_FORMAT);
        // A format-1 report (no `format`, without the per-group R-precision and the object
        // turns) reads back without them.
        let mut older: serde_json::Value = serde_json::from_str(&json).unwrap();
        assert!(older.as_object_mut().unwrap().remove("format").is_some());
        let group = older["instruction"][0].as_object_mut().unwrap();
        assert!(group.remove("r_precision_top3").is_some());
        assert!(group.remove("truth_r_precision_top3").is_some());
        let physical = older["rows"][0]["physical"].as_object_mut().unwrap();
        assert!(physical.remove("object_start_turn_deg").is_some());
        assert!(physical.remove("untouched_turn_deg_s").is_some());
        let older_bytes = serde_json::to_vec(&older).unwrap();
        let older = Report::from_json(Path::new("old.json"), &older_bytes).unwrap();
        assert_eq!(older.format, 1);
        let mut newer: serde_json::Value = serde_json::from_str(&json).unwrap();
        newer["format"] = serde_json::json!(REPORT_FORMAT + 1);
        let error = Report::from_json(Path::new("new.json"), &serde_json::to_vec(&newer).unwrap())
            .unwrap_err()
            .to_string();
        assert!(error.contains("new.json") && error.contains("format 3"), "{error}");
        let no_setup = br#"{"rows": []}"#;
        let error = Report::from_json(Path::new("bare.json"), no_setup).unwrap_err().to_string();
        assert!(error.contains("bare.json: setup"), "{error}");
        assert_eq!(older.instruction[0].r_precision_top3, None);
        assert_eq!(older.rows[0].physical.object_start_turn_deg, None);
        assert_eq!(
            (back.samples, back.skipped, back.replications, back.clip_frames),
            (4, 1, 2, 60)
        );
        assert_eq!(back.multimodality_protocol, [2, 2, 1]);
    }
}
