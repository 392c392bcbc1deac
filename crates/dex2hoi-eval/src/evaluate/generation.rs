//! Generation for the test split: each test sequence's own prefix, objects and one of its
//! texts condition a clip after the prefix (paper Sec. 4.2 protocol; the prefix of Sec. 3),
//! once per replication, plus the repeated generations of MultiModality.

use std::num::NonZeroUsize;

use dex2hoi_data::dataset::Dataset;
use dex2hoi_data::features::ProcessedSequence;
use dex2hoi_data::layout::slot_bps;
use dex2hoi_diffusion::SamplerConfig;
use dex2hoi_repr::Skeleton;
use dex2hoi_sample::rest::{FreeObjects, ObjectsAtRest};
use dex2hoi_sample::seams::Seams;
use dex2hoi_sample::{Conditioning, GeneratedMotion, TrainedRun, generate_motion};

use super::physical::ObjectMeshes;

use crate::error::Result;
use crate::evaluator::MotionClip;
use crate::metrics;

/// Seed offset between replications of the test clips: more than any test split's sequences,
/// so that no two (replication, sequence) pairs share a seed.
const REPLICATION_STRIDE: usize = 100_003;
/// Seed offset of the MultiModality generations, far from the test clips' seeds.
const MULTIMODALITY_OFFSET: usize = 1_000_000_007;
/// Seed offset between MultiModality prompts.
const MULTIMODALITY_PROMPT_STRIDE: usize = 1009;

/// Counts generated clips for the caller's progress callback.
pub(super) struct Progress<'p> {
    done: usize,
    total: usize,
    report: &'p mut dyn FnMut(usize, usize),
}

impl<'p> Progress<'p> {
    /// A count of `total` clips reported to `report` as (clips done, clips in all).
    pub(super) fn new(total: usize, report: &'p mut dyn FnMut(usize, usize)) -> Self {
        Self { done: 0, total, report }
    }

    pub(super) fn clip_done(&mut self) {
        self.done += 1;
        (self.report)(self.done, self.total);
    }
}

/// A generated test clip with what the physical metrics and the runtime need.
pub(super) struct GeneratedClip {
    /// The decoded motion.
    pub clip: MotionClip,
    /// `[frames, 2, 3]` mixture weights `softmax(alpha)` of the generated object features
    /// (Eq. 4).
    pub mixture_weights: Vec<f32>,
    /// Seconds the generation took.
    pub seconds: f64,
}

/// Generates clips of `frames` frames with a run, conditioned on test sequences.
pub(super) struct Generator<'a> {
    run: &'a TrainedRun,
    dataset: &'a Dataset,
    meshes: &'a ObjectMeshes<'a>,
    frames: NonZeroUsize,
    sampler: SamplerConfig,
    free_objects: FreeObjects,
    seams: Seams,
    seed: u64,
}

impl<'a> Generator<'a> {
    /// A generator of `frames`-frame clips with `sampler` and its rules for free objects and
    /// seams; `seed` is the first replication's.
    pub(super) fn new(
        run: &'a TrainedRun,
        dataset: &'a Dataset,
        meshes: &'a ObjectMeshes<'a>,
        frames: NonZeroUsize,
        (sampler, free_objects, seams): (SamplerConfig, FreeObjects, Seams),
        seed: u64,
    ) -> Self {
        Self { run, dataset, meshes, frames, sampler, free_objects, seams, seed }
    }

    /// One clip for a test sequence after its own prefix, prompted with `prompt`.
    fn generate(
        &self,
        sequence: &ProcessedSequence,
        prompt: &str,
        seed: u64,
    ) -> Result<GeneratedMotion> {
        // Continuing a test sequence: its own subject's body, like its ground truth.
        let body = sequence.skeleton(&self.run.skeleton)?;
        let mut conditioning = conditioning(self.run, self.dataset, sequence, prompt, &body)?;
        if self.free_objects == FreeObjects::AtRest {
            conditioning.free_objects = Some(ObjectsAtRest { meshes: self.meshes.of(sequence)? });
        }
        conditioning.seams = self.seams;
        Ok(generate_motion(self.run, &conditioning, self.frames, seed, self.sampler)?)
    }

    /// A replication's clip for every test sequence, sequence `k` prompted with `prompts[k]`.
    ///
    /// # Shapes
    /// - `sequences`, `prompts`: `[clips]`; returns `[clips]`
    pub(super) fn test_clips(
        &self,
        sequences: &[&ProcessedSequence],
        prompts: &[String],
        replication: usize,
        progress: &mut Progress<'_>,
    ) -> Result<Vec<GeneratedClip>> {
        let layout = self.run.config.model.layout();
        let mut clips = Vec::with_capacity(sequences.len());
        for (k, (sequence, prompt)) in sequences.iter().zip(prompts).enumerate() {
            let seed = self.seed.wrapping_add((replication * REPLICATION_STRIDE + k) as u64);
            let generated = self.generate(sequence, prompt, seed)?;
            let object_features = layout.stream_objects_to_frames(&generated.features)?;
            clips.push(GeneratedClip {
                mixture_weights: metrics::mixture_weights_from_features(&object_features)?,
                clip: MotionClip::from_decoded(&generated.motion)?,
                seconds: generated.seconds,
            });
            progress.clip_done();
        }
        Ok(clips)
    }

    /// MultiModality's generations: `repeats` clips for each of `sequences` (the first test
    /// sequences) with its replication prompt.
    ///
    /// # Shapes
    /// - `sequences`: `[prompts]`, `prompts`: at least as many; returns `[prompts][repeats]`
    pub(super) fn multimodality_clips(
        &self,
        sequences: &[&ProcessedSequence],
        prompts: &[String],
        repeats: usize,
        replication: usize,
        progress: &mut Progress<'_>,
    ) -> Result<Vec<Vec<MotionClip>>> {
        let mut groups = Vec::with_capacity(sequences.len());
        for (k, (sequence, prompt)) in sequences.iter().zip(prompts).enumerate() {
            let mut group = Vec::with_capacity(repeats);
            for repeat in 0..repeats {
                let offset = MULTIMODALITY_OFFSET
                    + replication * REPLICATION_STRIDE
                    + k * MULTIMODALITY_PROMPT_STRIDE
                    + repeat;
                let generated =
                    self.generate(sequence, prompt, self.seed.wrapping_add(offset as u64))?;
                group.push(MotionClip::from_decoded(&generated.motion)?);
                progress.clip_done();
            }
            groups.push(group);
        }
        Ok(groups)
    }
}

/// The prompt of each test sequence in a replication: its texts in turn.
pub(super) fn replication_prompts(
    sequences: &[&ProcessedSequence],
    replication: usize,
) -> Vec<String> {
    sequences.iter().map(|s| s.texts[replication % s.texts.len()].clone()).collect()
}

/// The prefix, BPS and presence of a test sequence.
fn conditioning<'a>(
    run: &TrainedRun,
    dataset: &Dataset,
    sequence: &ProcessedSequence,
    prompt: &'a str,
    skeleton: &'a Skeleton,
) -> Result<Conditioning<'a>> {
    let c = &run.config.model;
    let prefix = sequence.stream_features(0..c.prefix_frames)?;
    let bps = slot_bps(&dataset.objects, dataset.slot_assets(sequence)?, c.bps_points)?;
    Ok(Conditioning {
        prefix,
        bps,
        present: sequence.object_present,
        prompts: vec![(0, prompt)],
        root_start: sequence.root_start,
        skeleton,
        free_objects: None,
        seams: Seams::default(),
        progress: None,
    })
}
