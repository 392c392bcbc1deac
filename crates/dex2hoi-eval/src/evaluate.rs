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
//! samples when fewer; intervals use T2M's `np.std` (ddof 0). MultiModality generates `repeats` samples for each of the first
//! `prompts` sequences.

use serde::Serialize;

use dex2hoi_data::MAX_OBJECTS;
use dex2hoi_data::dataset::{Dataset, Split};
use dex2hoi_data::features::{OBJECT_FEATURE_SIZE, ProcessedSequence};
use dex2hoi_diffusion::SamplerConfig;
use dex2hoi_repr::MeshQuery;
use dex2hoi_sample::{Conditioning, GeneratedMotion, TrainedRun, generate_motion};

use crate::error::{EvalError, Result};
use crate::evaluator::{Evaluator, MotionClip};
use crate::metrics;

/// How an evaluation runs.
#[derive(Debug, Clone, PartialEq)]
pub struct EvaluateOptions {
    /// Replications (different noise and prompt choice; default 3).
    pub replications: usize,
    /// At most this many test sequences (all when `None`).
    pub sequences: Option<usize>,
    /// The sampler (DDIM 50 steps, guidance 2.5 by default).
    pub sampler: SamplerConfig,
    /// Seed of the first replication's noise.
    pub seed: u64,
    /// The MultiModality protocol (prompts x repeats x pairs).
    pub multimodality: metrics::MultimodalityProtocol,
}

impl Default for EvaluateOptions {
    fn default() -> Self {
        Self {
            replications: 3,
            sequences: None,
            sampler: SamplerConfig::default(),
            seed: 0,
            multimodality: metrics::MultimodalityProtocol::default(),
        }
    }
}

/// A value over replications: the mean and the half-width of its 95% interval.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Estimate {
    /// Mean over replications.
    pub mean: f64,
    /// `1.96 std / sqrt(R)`.
    pub interval: f64,
}

impl Estimate {
    fn of(values: &[f64]) -> Self {
        let (mean, interval) = metrics::mean_interval(values);
        Self { mean, interval }
    }
}

/// One row of the report (the ground truth or a model).
#[derive(Debug, Clone, PartialEq, Serialize)]
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
    pub runtime_seconds: Option<(f64, f64)>,
}

/// The physical metrics of a row, each over replications.
#[derive(Debug, Clone, PartialEq, Serialize)]
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
}

/// The whole report.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Report {
    /// Ground truth, then the model.
    pub rows: Vec<ReportRow>,
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
}

/// Embeddings of the last replication, for `--dump-embeddings`.
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
}

/// The physical measurements of one clip, kept as counts so that a replication pools them.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Physical {
    penetration: metrics::Penetration,
    contact: metrics::ContactCounts,
    foot_sliding_mm: f64,
    /// Frames where the mixture picks the holding hand, and frames judged.
    agreement: (usize, usize),
}

/// Measures one clip against its sequence's ground-truth contact over the same frames.
fn measure(
    sample: &metrics::MotionSample<'_>,
    sequence: &ProcessedSequence,
    start: usize,
    frames: usize,
) -> Result<Physical> {
    let truth_contact =
        &sequence.hand_contact[start * MAX_OBJECTS * 2..(start + frames) * MAX_OBJECTS * 2];
    let penetration = metrics::penetration(sample, metrics::PENETRATION_TOLERANCE_M)?;
    let contact = metrics::contact_scores(sample, truth_contact, metrics::CONTACT_RADIUS_M)?.counts;
    let foot_sliding_mm = metrics::foot_sliding(sample.joints, sample.skeleton)?;
    let agreement = match sample.mixture_weights {
        Some(weights) => metrics::mixture_agreement_counts(weights, truth_contact, sample.present)?,
        None => (0, 0),
    };
    Ok(Physical { penetration, contact, foot_sliding_mm, agreement })
}

fn clip_sample<'a>(
    clip: &'a MotionClip,
    skeleton: &'a dex2hoi_repr::Skeleton,
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

/// The prefix, BPS and presence of a test sequence.
fn conditioning<'a>(
    run: &TrainedRun,
    dataset: &Dataset,
    sequence: &ProcessedSequence,
    prompt: &'a str,
) -> Result<Conditioning<'a>> {
    let c = &run.config.model;
    let (body, width) = (c.body_features(), c.stream_features());
    let mut prefix = Vec::with_capacity(MAX_OBJECTS * c.prefix_frames * width);
    for slot in 0..MAX_OBJECTS {
        for t in 0..c.prefix_frames {
            prefix.extend_from_slice(&sequence.body[t * body..(t + 1) * body]);
            let o = (t * MAX_OBJECTS + slot) * OBJECT_FEATURE_SIZE;
            prefix.extend_from_slice(&sequence.objects[o..o + OBJECT_FEATURE_SIZE]);
        }
    }
    let bps_width = c.bps_points * 3;
    let mut bps = vec![0.0f32; MAX_OBJECTS * bps_width];
    for (slot, name) in sequence.object_names.iter().enumerate() {
        let Some(name) = name else { continue };
        let asset = dataset.objects.iter().find(|a| &a.name == name).ok_or_else(|| {
            EvalError::invalid(
                format!("object of {}", sequence.source_id),
                "an object of the dataset's manifest",
                name,
            )
        })?;
        let flat: Vec<f32> = asset.bps.iter().flat_map(|v| v.to_array()).collect();
        if flat.len() != bps_width {
            return Err(EvalError::invalid(
                "BPS of the dataset",
                format!("{bps_width} numbers (the run's bps_points)"),
                flat.len(),
            ));
        }
        bps[slot * bps_width..(slot + 1) * bps_width].copy_from_slice(&flat);
    }
    Ok(Conditioning {
        prefix,
        bps,
        present: sequence.object_present,
        prompts: vec![(0, prompt)],
        root_start: sequence.root_start,
    })
}

/// The generated object features `[T, 2, 18]` out of both streams' features `[2, T, D]`.
fn generated_object_features(
    generated: &GeneratedMotion,
    frames: usize,
    width: usize,
    body: usize,
) -> Vec<f32> {
    let mut out = Vec::with_capacity(frames * MAX_OBJECTS * OBJECT_FEATURE_SIZE);
    for t in 0..frames {
        for s in 0..MAX_OBJECTS {
            let row = &generated.features[(s * frames + t) * width..(s * frames + t + 1) * width];
            out.extend_from_slice(&row[body..body + OBJECT_FEATURE_SIZE]);
        }
    }
    out
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
    if options.replications == 0 {
        return Err(EvalError::invalid("replications", "at least 1", 0));
    }
    let c = &run.config.model;
    let clip = evaluator.config().clip_frames;
    let needed = c.prefix_frames + clip;
    let test = dataset.splits.get(&Split::Test).map(Vec::as_slice).unwrap_or_default();
    let long_enough: Vec<&ProcessedSequence> = test.iter().filter(|s| s.frames >= needed).collect();
    let skipped = test.len() - long_enough.len();
    let chosen: Vec<&ProcessedSequence> =
        long_enough.into_iter().take(options.sequences.unwrap_or(usize::MAX)).collect();
    if chosen.len() < 2 {
        return Err(EvalError::invalid(
            "test split",
            format!("at least two test sequences of {needed} frames or more (prefix + clip)"),
            format!("{} ({skipped} too short)", chosen.len()),
        ));
    }
    let queries: Vec<MeshQuery> =
        dataset.objects.iter().map(|a| MeshQuery::new(&a.mesh)).collect::<Result<_, _>>()?;
    let query_of = |sequence: &ProcessedSequence| -> [Option<&MeshQuery>; MAX_OBJECTS] {
        let mut out = [None; MAX_OBJECTS];
        for (slot, name) in sequence.object_names.iter().enumerate() {
            if let Some(name) = name {
                out[slot] =
                    dataset.objects.iter().position(|a| &a.name == name).map(|k| &queries[k]);
            }
        }
        out
    };
    let (width, body) = (c.stream_features(), c.body_features());
    let use_action = !evaluator.labels().is_empty();
    let mm = &options.multimodality;
    let mm_prompts = mm.prompts.min(chosen.len());
    let total = options.replications * (chosen.len() + mm_prompts * mm.repeats);
    let mut done = 0;

    let truth_clips: Vec<MotionClip> = chosen
        .iter()
        .map(|s| MotionClip::from_processed(s, c.prefix_frames, clip))
        .collect::<Result<_>>()?;
    let truth_embeddings = evaluator.embed_motions(&truth_clips)?;
    let truth_action =
        if use_action { evaluator.action_features(&truth_clips)? } else { Vec::new() };
    let truth_distribution = if use_action { &truth_action } else { &truth_embeddings };
    let truth_physical: Vec<Physical> = chosen
        .iter()
        .zip(&truth_clips)
        .map(|(s, truth)| {
            let objects = &s.objects[c.prefix_frames * MAX_OBJECTS * OBJECT_FEATURE_SIZE
                ..(c.prefix_frames + clip) * MAX_OBJECTS * OBJECT_FEATURE_SIZE];
            let weights = metrics::mixture_weights_from_features(objects)?;
            let sample = clip_sample(truth, &run.skeleton, query_of(s), Some(&weights));
            measure(&sample, s, c.prefix_frames, clip)
        })
        .collect::<Result<_>>()?;

    let mut model_values: Vec<[f64; 7]> = Vec::new();
    let mut truth_values: Vec<[f64; 6]> = Vec::new();
    let mut model_physical: Vec<Physical> = Vec::new();
    let mut truth_physical_all: Vec<Physical> = Vec::new();
    let mut runtimes = Vec::new();
    let mut last = None;
    for replication in 0..options.replications {
        let prompts: Vec<String> =
            chosen.iter().map(|s| s.texts[replication % s.texts.len()].clone()).collect();
        let mut clips = Vec::with_capacity(chosen.len());
        for (k, sequence) in chosen.iter().enumerate() {
            let seed = options.seed.wrapping_add((replication * 100_003 + k) as u64);
            let generated = generate_motion(
                run,
                &conditioning(run, dataset, sequence, &prompts[k])?,
                clip,
                seed,
                options.sampler,
            )?;
            runtimes.push(generated.seconds);
            let weights = metrics::mixture_weights_from_features(&generated_object_features(
                &generated, clip, width, body,
            ))?;
            let generated_clip = MotionClip::from_decoded(&generated.motion)?;
            let sample =
                clip_sample(&generated_clip, &run.skeleton, query_of(sequence), Some(&weights));
            model_physical.push(measure(&sample, sequence, c.prefix_frames, clip)?);
            clips.push(generated_clip);
            done += 1;
            progress(done, total);
        }
        truth_physical_all.extend_from_slice(&truth_physical);
        let text_refs: Vec<&str> = prompts.iter().map(String::as_str).collect();
        let texts = evaluator.embed_texts(&text_refs)?;
        let generated = evaluator.embed_motions(&clips)?;
        let generated_action =
            if use_action { evaluator.action_features(&clips)? } else { Vec::new() };
        let distribution = if use_action { &generated_action } else { &generated };
        let batch = metrics::R_PRECISION_BATCH.min(chosen.len());
        let seed = options.seed ^ replication as u64;
        let r = metrics::r_precision(&generated, &texts, batch, seed)?;
        let truth_r = metrics::r_precision(&truth_embeddings, &texts, batch, seed)?;
        // MultiModality: repeats of the first prompts.
        let mut groups = Vec::with_capacity(mm_prompts);
        for (k, sequence) in chosen.iter().take(mm_prompts).enumerate() {
            let mut repeats = Vec::with_capacity(mm.repeats);
            for repeat in 0..mm.repeats {
                let seed = options.seed.wrapping_add(
                    (1_000_000_007 + replication * 100_003 + k * 1009 + repeat) as u64,
                );
                let generated = generate_motion(
                    run,
                    &conditioning(run, dataset, sequence, &prompts[k])?,
                    clip,
                    seed,
                    options.sampler,
                )?;
                repeats.push(MotionClip::from_decoded(&generated.motion)?);
                done += 1;
                progress(done, total);
            }
            groups.push(if use_action {
                evaluator.action_features(&repeats)?
            } else {
                evaluator.embed_motions(&repeats)?
            });
        }
        let multimodality = if mm_prompts > 0 && mm.repeats > 1 {
            metrics::multimodality(&groups, mm.pairs, seed)?
        } else {
            f64::NAN
        };
        model_values.push([
            r[0],
            r[1],
            r[2],
            metrics::fid(distribution, truth_distribution)?,
            metrics::matching_distance(&generated, &texts)?,
            metrics::diversity(distribution, metrics::DIVERSITY_PAIRS.min(chosen.len()), seed)?,
            multimodality,
        ]);
        truth_values.push([
            truth_r[0],
            truth_r[1],
            truth_r[2],
            0.0,
            metrics::matching_distance(&truth_embeddings, &texts)?,
            metrics::diversity(
                truth_distribution,
                metrics::DIVERSITY_PAIRS.min(chosen.len()),
                seed,
            )?,
        ]);
        last = Some(Embeddings {
            generated,
            ground_truth: truth_embeddings.clone(),
            texts,
            prompts,
            generated_action,
            ground_truth_action: truth_action.clone(),
        });
    }
    let column = |values: &[[f64; 7]], k: usize| {
        Estimate::of(&values.iter().map(|v| v[k]).collect::<Vec<_>>())
    };
    let truth_column =
        |k: usize| Estimate::of(&truth_values.iter().map(|v| v[k]).collect::<Vec<_>>());
    let per_replication = chosen.len();
    let model_row = ReportRow {
        name: "Dex2HOI (this run)".into(),
        r_precision: [column(&model_values, 0), column(&model_values, 1), column(&model_values, 2)],
        fid: column(&model_values, 3),
        mm_dist: column(&model_values, 4),
        diversity: column(&model_values, 5),
        multimodality: model_values
            .iter()
            .all(|v| v[6].is_finite())
            .then(|| column(&model_values, 6)),
        physical: physical_row(&model_physical, per_replication),
        runtime_seconds: Some(metrics::runtime(&runtimes)),
    };
    let truth_row = ReportRow {
        name: "Ground truth".into(),
        r_precision: [truth_column(0), truth_column(1), truth_column(2)],
        fid: truth_column(3),
        mm_dist: truth_column(4),
        diversity: truth_column(5),
        multimodality: None,
        physical: physical_row(&truth_physical_all, per_replication),
        runtime_seconds: None,
    };
    let report = Report {
        rows: vec![truth_row, model_row],
        samples: chosen.len(),
        skipped,
        replications: options.replications,
        clip_frames: clip,
        distribution_features: if use_action {
            "action classifier features (IMoS)".into()
        } else {
            "contrastive motion embeddings".into()
        },
        multimodality_protocol: [mm_prompts, mm.repeats, mm.pairs],
    };
    let embeddings = last.ok_or_else(|| EvalError::invalid("replications", "at least 1", 0))?;
    Ok((report, embeddings))
}

/// One replication's physical metrics, pooled over its clips.
struct Pooled {
    penetration: metrics::Penetration,
    contact: metrics::ContactScores,
    foot_sliding_mm: f64,
    agreement: (usize, usize),
}

/// Pools each replication's clips (counts and depths), then estimates over replications.
fn physical_row(samples: &[Physical], per_replication: usize) -> PhysicalRow {
    let pooled: Vec<Pooled> = samples
        .chunks(per_replication.max(1))
        .map(|r| {
            let penetrations: Vec<metrics::Penetration> = r.iter().map(|p| p.penetration).collect();
            let counts =
                r.iter().fold(metrics::ContactCounts::default(), |a, p| a.merge(p.contact));
            Pooled {
                penetration: metrics::Penetration::pooled(&penetrations),
                contact: metrics::ContactScores::from_counts(counts),
                foot_sliding_mm: r.iter().map(|p| p.foot_sliding_mm).sum::<f64>()
                    / r.len().max(1) as f64,
                agreement: r.iter().fold((0, 0), |a, p| (a.0 + p.agreement.0, a.1 + p.agreement.1)),
            }
        })
        .collect();
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
    }
}

fn cell(e: &Estimate, digits: usize) -> String {
    format!("{:.*} ± {:.*}", digits, e.mean, digits, e.interval)
}

impl Report {
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
             clips). Runtime: mean ± standard deviation per generated clip.\n",
            self.samples,
            self.skipped,
            self.replications,
            self.clip_frames,
            self.distribution_features,
            self.multimodality_protocol[0],
            self.multimodality_protocol[1],
            self.multimodality_protocol[2],
        ));
        out
    }
}

impl Embeddings {
    /// The embeddings as an `.npz` archive (float32 arrays and the prompts as strings).
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
        Ok(encode_npz(&arrays)?)
    }
}
