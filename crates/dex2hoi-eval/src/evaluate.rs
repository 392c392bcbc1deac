//! `dex2hoi evaluate`: generate for the test split of a dataset with a trained run, embed the
//! generated and ground-truth motions with an evaluator, and compute the metrics of the paper's
//! tables (Sec. 4.2) with replications (mean and 95% interval), a ground-truth row computed the
//! same way, and the runtime per sample.
//!
//! Protocol. Each test sequence long enough for the evaluator's clip (`T_p` prefix frames plus
//! `clip_frames`) is generated once per replication: its first `T_p` frames (body and objects)
//! are the observed prefix, its objects keep their BPS, one of its texts (the replication picks
//! which, in turn) is the prompt, and `clip_frames` frames are generated after the prefix; the
//! ground truth is the same `clip_frames` frames of the sequence. FID, Diversity and
//! MultiModality use the action classifier's features when the evaluator has action labels
//! (IMoS) and the contrastive motion embeddings otherwise; R-precision and MMdist use the
//! contrastive embeddings (T2M). R-precision follows T2M's code (each text ranks the motions of its batch of
//! 32, fewer when the split is smaller); Diversity uses 300 pairs, or as many as there are
//! samples when fewer; intervals use T2M's `np.std` (ddof 0). MultiModality generates
//! `repeats` samples for each of the first `prompts` sequences.
//!
//! Layout (private submodules): `generation` (conditioning and generating the clips),
//! `embedding` (clips and prompts through the evaluator), `scores` (the distribution and
//! matching metrics of a replication, one named `DistributionScores` per row), `physical` (the
//! physical metrics) and `report` (estimates over replications, markdown, JSON, `.npz`; its
//! types are re-exported here).

mod embedding;
mod generation;
mod long;
mod physical;
mod report;
mod scores;

use dex2hoi_data::dataset::{Dataset, Split};
use dex2hoi_data::features::ProcessedSequence;
use dex2hoi_diffusion::SamplerConfig;
use dex2hoi_sample::TrainedRun;
use dex2hoi_sample::rest::FreeObjects;
use dex2hoi_sample::seams::Seams;

use crate::error::{EvalError, Result};
use crate::evaluator::{Evaluator, MotionClip};
use crate::metrics;

use embedding::{DistributionFeatures, EmbeddedMotions, embed_prompts};
use generation::{Generator, Progress, replication_prompts};
use physical::{GroupScores, ObjectMeshes, Physical, Window, instruction_rows, physical_row};
use scores::DistributionScores;

pub use long::{
    ACROSS_THE_BODY_M, DEFAULT_LONG_FRAMES, LongOptions, LongProtocol, LongRow, LongScores,
    LongSet, LongSetKind,
};
pub use report::{
    Embeddings, Estimate, EvaluationSetup, InstructionRow, PhysicalRow, REPORT_FORMAT, Report,
    ReportRow, SamplerName,
};

/// How an evaluation runs.
#[derive(Debug, Clone, PartialEq)]
pub struct EvaluateOptions {
    /// Replications (different noise and prompt choice; default 3).
    pub replications: usize,
    /// At most this many test sequences (all when `None`).
    pub sequences: Option<usize>,
    /// The sampler (DDIM 50 steps, guidance `dex2hoi_diffusion::DEFAULT_GUIDANCE` by default).
    pub sampler: SamplerConfig,
    /// Seed of the first replication's noise.
    pub seed: u64,
    /// The MultiModality protocol (prompts x repeats x pairs; default 8 x 4 x 3).
    pub multimodality: metrics::MultimodalityProtocol,
    /// The long-generation protocol too, with these options (`None`: the paper's only).
    pub long: Option<LongOptions>,
    /// What happens to the objects no hand holds, in both protocols
    /// (`dex2hoi_sample::rest`).
    pub free_objects: FreeObjects,
    /// How each window joins the frames before it, in both protocols
    /// (`dex2hoi_sample::seams`).
    pub seams: Seams,
}

impl Default for EvaluateOptions {
    fn default() -> Self {
        Self {
            replications: 3,
            sequences: None,
            sampler: SamplerConfig::default(),
            seed: 0,
            multimodality: metrics::MultimodalityProtocol::default(),
            long: None,
            free_objects: FreeObjects::default(),
            seams: Seams::default(),
        }
    }
}

impl EvaluateOptions {
    /// Refuses options that cannot run, before anything is generated.
    fn validate(&self) -> Result<()> {
        if self.replications == 0 {
            return Err(EvalError::invalid("replications", "at least 1", 0));
        }
        self.multimodality.validate()
    }
}

/// The test sequences an evaluation uses.
struct TestSelection<'a> {
    /// Long enough for prefix and clip, at most the requested number, in split order.
    chosen: Vec<&'a ProcessedSequence>,
    /// Test sequences too short for prefix and clip.
    skipped: usize,
}

/// The test sequences of at least `needed` frames, at most `limit` of them; at least two (FID
/// needs two rows).
fn select_test_sequences(
    dataset: &Dataset,
    needed: usize,
    limit: Option<usize>,
) -> Result<TestSelection<'_>> {
    let test = dataset.splits.get(&Split::Test).map(Vec::as_slice).unwrap_or_default();
    let long_enough: Vec<&ProcessedSequence> = test.iter().filter(|s| s.frames >= needed).collect();
    let skipped = test.len() - long_enough.len();
    let chosen: Vec<&ProcessedSequence> =
        long_enough.into_iter().take(limit.unwrap_or(usize::MAX)).collect();
    if chosen.len() < 2 {
        return Err(EvalError::invalid(
            "test split",
            format!("at least two test sequences of {needed} frames or more (prefix + clip)"),
            format!("{} ({skipped} too short)", chosen.len()),
        ));
    }
    Ok(TestSelection { chosen, skipped })
}

/// Everything measured on the ground truth, once: it does not change between replications.
struct GroundTruth {
    clips: Vec<MotionClip>,
    embedded: EmbeddedMotions,
    physical: Vec<Physical>,
}

impl GroundTruth {
    /// Embeds and measures the window of every chosen sequence.
    fn measure(
        sequences: &[&ProcessedSequence],
        evaluator: &Evaluator,
        features: DistributionFeatures,
        (skeleton, meshes): (&dex2hoi_repr::Skeleton, &ObjectMeshes<'_>),
        window: Window,
        fps: f32,
    ) -> Result<Self> {
        let clips: Vec<MotionClip> = sequences
            .iter()
            .map(|s| MotionClip::from_processed(s, window.start, window.frames))
            .collect::<Result<_>>()?;
        let embedded = EmbeddedMotions::embed(evaluator, features, &clips)?;
        let physical = sequences
            .iter()
            .zip(&clips)
            .map(|(s, truth)| {
                physical::measure_ground_truth(s, truth, skeleton, meshes.of(s)?, window, fps)
            })
            .collect::<Result<_>>()?;
        Ok(Self { clips, embedded, physical })
    }
}

/// What the replications accumulate for the report.
#[derive(Default)]
struct Replications {
    model: Vec<DistributionScores>,
    truth: Vec<DistributionScores>,
    model_physical: Vec<Physical>,
    truth_physical: Vec<Physical>,
    runtimes: Vec<f64>,
}

/// Evaluates a run on a dataset's test split with an evaluator. `progress` gets (samples done,
/// samples in all).
pub fn evaluate(
    run: &TrainedRun,
    dataset: &Dataset,
    evaluator: &Evaluator,
    options: &EvaluateOptions,
    progress: &mut dyn FnMut(usize, usize),
) -> Result<(Report, Embeddings)> {
    options.validate()?;
    let window =
        Window { start: run.config.model.prefix_frames, frames: evaluator.config().clip_frames };
    let TestSelection { chosen, skipped } =
        select_test_sequences(dataset, window.start + window.frames, options.sequences)?;
    let meshes = ObjectMeshes::new(dataset)?;
    let features = DistributionFeatures::of(evaluator);
    let mm = options.multimodality;
    let mm_prompts = mm.prompts.min(chosen.len());
    let progress_callback = progress;
    let mut progress = Progress::new(
        options.replications * (chosen.len() + mm_prompts * mm.repeats),
        progress_callback,
    );
    // The evaluator's configuration holds at least two clip frames (`EvaluatorConfig::validate`).
    let clip_frames = std::num::NonZeroUsize::new(window.frames)
        .ok_or_else(|| EvalError::invalid("evaluator clip_frames", "at least 1", window.frames))?;
    let generator = Generator::new(
        run,
        dataset,
        &meshes,
        clip_frames,
        (options.sampler, options.free_objects, options.seams),
        options.seed,
    );
    let fps = dataset.manifest.fps;
    let truth =
        GroundTruth::measure(&chosen, evaluator, features, (&run.skeleton, &meshes), window, fps)?;

    let actions: Vec<Option<&str>> = chosen.iter().map(|s| s.action.as_deref()).collect();
    let mut embeddings = Embeddings::of_ground_truth(&truth.embedded, &truth.clips, &actions);
    let mut all = Replications::default();
    for replication in 0..options.replications {
        let prompts = replication_prompts(&chosen, replication);
        let generated = generator.test_clips(&chosen, &prompts, replication, &mut progress)?;
        let truths = truth.clips.iter().zip(&truth.physical);
        for ((clip, sequence), truth_clip) in generated.iter().zip(&chosen).zip(truths) {
            all.runtimes.push(clip.seconds);
            all.model_physical.push(physical::measure_generated(
                sequence,
                &clip.clip,
                truth_clip,
                &clip.mixture_weights,
                &run.skeleton,
                meshes.of(sequence)?,
                window,
                fps,
            )?);
        }
        all.truth_physical.extend_from_slice(&truth.physical);
        let groups = generator.multimodality_clips(
            &chosen[..mm_prompts],
            &prompts,
            mm.repeats,
            replication,
            &mut progress,
        )?;

        let seed = options.seed ^ replication as u64;
        let texts = embed_prompts(evaluator, &prompts)?;
        let clips: Vec<MotionClip> = generated.into_iter().map(|g| g.clip).collect();
        let embedded = EmbeddedMotions::embed(evaluator, features, &clips)?;
        let multimodality = multimodality(evaluator, features, &groups, &mm, seed)?;
        all.model.push(DistributionScores::of_generated(
            &embedded,
            &truth.embedded,
            &texts,
            multimodality,
            seed,
        )?);
        all.truth.push(DistributionScores::of_ground_truth(&truth.embedded, &texts, seed)?);
        embeddings.set_replication(embedded, clips, texts, prompts);
    }
    let long = match options.long {
        Some(long_options) => Some(long::evaluate_long(
            run,
            dataset,
            &chosen,
            &meshes,
            long_options,
            (options.sampler, options.free_objects, options.seams),
            options.seed,
            progress_callback,
        )?),
        None => None,
    };
    let report = Report {
        format: REPORT_FORMAT,
        setup: EvaluationSetup::new(run.step, &options.sampler, options.seed)
            .with_rules(options.free_objects, options.seams),
        rows: vec![
            ReportRow::from_replications(
                "Ground truth",
                &all.truth,
                physical_row(&all.truth_physical, chosen.len()),
                None,
            ),
            ReportRow::from_replications(
                "Dex2HOI (this run)",
                &all.model,
                physical_row(&all.model_physical, chosen.len()),
                Some(metrics::runtime(&all.runtimes)),
            ),
        ],
        instruction: instruction_rows(
            &all.model_physical,
            &actions,
            GroupScores { generated: &all.model, truth: &all.truth },
        ),
        samples: chosen.len(),
        skipped,
        replications: options.replications,
        clip_frames: window.frames,
        distribution_features: features.describe().into(),
        multimodality_protocol: [mm_prompts, mm.repeats, mm.pairs],
        long,
    };
    Ok((report, embeddings))
}

/// MultiModality of a replication's repeated generations on their distribution features;
/// `None` when the protocol measures nothing.
///
/// # Shapes
/// - `groups`: `[prompts][repeats]` clips
fn multimodality(
    evaluator: &Evaluator,
    features: DistributionFeatures,
    groups: &[Vec<MotionClip>],
    protocol: &metrics::MultimodalityProtocol,
    seed: u64,
) -> Result<Option<f64>> {
    if groups.is_empty() || !protocol.is_measured() {
        return Ok(None);
    }
    let embedded = groups
        .iter()
        .map(|group| features.extract(evaluator, group))
        .collect::<Result<Vec<_>>>()?;
    Ok(Some(metrics::multimodality(&embedded, protocol.pairs, seed)?))
}
