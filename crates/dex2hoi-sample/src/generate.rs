//! Autoregressive generation of any length over prefix-conditioned windows (paper Sec. 3.2),
//! with a timeline of prompts (a text per time span, beyond the paper), and decoding the
//! generated features of a trained run into rotations, joint positions and object poses.
//!
//! Features are normalised with the dataset statistics before they reach the model and
//! denormalised after. Generated frames keep the convention of the dataset: the root
//! displacement is measured from the first frame of the whole generation, so a window's prefix
//! is simply the last `T_p` generated frames, objects included.

use std::num::NonZeroUsize;
use std::ops::ControlFlow;
use std::sync::Arc;
use web_time::Instant;

use candle_core::{DType, Tensor};
use glam::Vec3;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

use dex2hoi_data::MAX_OBJECTS;
use dex2hoi_data::features::{DecodedMotion, ObjectDecoding, decode_features};
use dex2hoi_diffusion::{CosineSchedule, SamplerConfig};
use dex2hoi_model::text::reject_empty;
use dex2hoi_model::{InferenceModel, ObjectRepresentation};
use dex2hoi_repr::Skeleton;

use dex2hoi_data::normalise::Normaliser;
use dex2hoi_data::settled::SettledObjects;
use dex2hoi_data::timeline::in_force;
use dex2hoi_repr::object_repr::GLOBAL_POSITION_RANGE;

use crate::denoiser::{WindowCondition, sample_window};
use crate::error::{Result, SampleError};
use crate::prefix::PrefixEncoding;
use crate::rest::ObjectsAtRest;
use crate::run::TrainedRun;
use crate::seams::{self, Seams};

/// A prompt that applies from a frame on (frames counted from the first generated frame).
#[derive(Debug, Clone)]
pub struct TimedText {
    /// First frame the prompt applies to.
    pub start_frame: usize,
    /// Its embedding, `[B, E]`.
    pub embedding: Tensor,
}

/// Where a generation stands after a window, as a [`ProgressHook`] sees it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct WindowProgress {
    /// Windows generated so far (at least 1).
    pub windows_done: usize,
    /// Windows the generation takes in all.
    pub windows: usize,
    /// Frames generated so far.
    pub frames_done: usize,
    /// Frames the generation produces in all.
    pub frames: usize,
}

/// Called after each window of a generation: progress reports, and a way to stop a long
/// generation cleanly between windows ([`ControlFlow::Break`] ends it with
/// [`SampleError::Interrupted`], returning no motion).
///
/// Shared (`Arc`) so that the structures holding it stay cheap to clone and need no lifetime.
#[derive(Clone)]
pub struct ProgressHook(pub Arc<dyn Fn(WindowProgress) -> ControlFlow<()> + Send + Sync>);

impl ProgressHook {
    /// A hook from a closure.
    pub fn new(hook: impl Fn(WindowProgress) -> ControlFlow<()> + Send + Sync + 'static) -> Self {
        Self(Arc::new(hook))
    }
}

impl std::fmt::Debug for ProgressHook {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("ProgressHook(..)")
    }
}

/// What an autoregressive generation needs.
#[derive(Debug, Clone)]
pub struct Generation<'a> {
    /// The network.
    pub model: &'a InferenceModel,
    /// The diffusion schedule it was trained with.
    pub schedule: &'a CosineSchedule,
    /// Feature statistics.
    pub normaliser: &'a Normaliser,
    /// The starting state: `T_p` clean frames, `[B, 2, T_p, D]` (unnormalised).
    pub initial_prefix: Tensor,
    /// Prompts by start frame; the first must start at frame 0.
    pub timeline: Vec<TimedText>,
    /// BPS features per object slot, `[B, 2, P * 3]`.
    pub bps: Tensor,
    /// Object presence, `[B, 2]`.
    pub presence: Tensor,
    /// Frames to generate after the initial prefix.
    pub frames: NonZeroUsize,
    /// Sampler settings.
    pub sampler: SamplerConfig,
    /// How each later window's prefix is rebuilt from the motion it decodes to (hand-relative
    /// objects); `None` feeds the generated features back as they are.
    pub prefix_encoding: Option<PrefixEncoding<'a>>,
    /// Keep the objects no hand holds at rest ([`crate::rest`]; needs `prefix_encoding`);
    /// `None` leaves them as generated.
    pub free_objects: Option<ObjectsAtRest<'a>>,
    /// How each window joins the frames before it ([`crate::seams`]).
    pub seams: Seams,
    /// Called after each window; `None`: the generation runs to its end unobserved.
    pub progress: Option<ProgressHook>,
}

/// Generates `frames` frames after the initial prefix, window by window: each window's prefix
/// is the last `T_p` frames so far, its prompt the timeline entry in force at its first frame.
/// The request's progress hook, if any, runs after each window and can stop the generation
/// ([`SampleError::Interrupted`]).
///
/// # Shapes
/// - returns `[B, 2, frames, D]` (unnormalised features)
pub fn generate(request: &Generation<'_>, rng: &mut ChaCha8Rng) -> Result<Tensor> {
    let c = request.model.config();
    let (tp, tf) = (c.prefix_frames, c.predicted_frames);
    if request.timeline.first().map(|t| t.start_frame) != Some(0) {
        return Err(SampleError::invalid(
            "generation",
            "timeline",
            "prompts by start frame, the first at frame 0",
            format!("{} prompts", request.timeline.len()),
        ));
    }
    if request.timeline.windows(2).any(|w| w[1].start_frame <= w[0].start_frame) {
        return Err(SampleError::invalid(
            "generation",
            "timeline",
            "increasing start frames",
            "a repeated or decreasing start",
        ));
    }
    let mut history = request.normaliser.normalise(
        &request.initial_prefix.to_dtype(DType::F32)?.to_dtype(request.model.dtype())?,
    )?;
    if history.dims().get(2) != Some(&tp) {
        return Err(SampleError::invalid(
            "generation",
            "initial prefix",
            format!("{tp} frames"),
            format!("{:?}", history.dims()),
        ));
    }
    // Objects at rest: the rule's state from the initial prefix (see `crate::rest`).
    let mut at_rest = match (&request.prefix_encoding, request.free_objects) {
        (Some(encoding), Some(rule)) => {
            Some((encoding, rule, rule.start(encoding, &request.initial_prefix, c.layout())?))
        }
        _ => None,
    };
    let batch = history.dims()[0];
    let mut produced = 0;
    let mut windows = Vec::new();
    let frames = request.frames.get();
    let total_windows = frames.div_ceil(tf.max(1));
    // The object start: the rows at the first prefix frame of each prompt's first window (for
    // the first prompt the initial prefix's first frame, as a training window at the start of
    // its sequence reads its frame 0), with the start frame of the prompt they belong to.
    let mut start: Option<(usize, Tensor)> = None;
    // The memory of set-down objects (and the reach frames): one tracker per batch row over
    // every frame of the prompt in force, from the same first frame as the object start.
    let mut memory = PromptMemory::new(batch, c.layout().stream_width(), c.reach_in_prefix);
    while produced < frames {
        // The timeline starts at frame 0 (checked above), so a prompt is always in force.
        let prompt = in_force(&request.timeline, |t| t.start_frame, produced)
            .unwrap_or(&request.timeline[0]);
        if start.as_ref().is_none_or(|(of, _)| *of != prompt.start_frame) {
            let prefix = history.narrow(2, history.dims()[2] - tp, tp)?;
            start = Some((prompt.start_frame, prefix.narrow(2, 0, 1)?.squeeze(2)?));
            memory = PromptMemory::new(batch, c.layout().stream_width(), c.reach_in_prefix);
            memory.follow(&request.normaliser.denormalise(&prefix)?, &prefix, c.layout())?;
        }
        let flags: Vec<f32> = memory.trackers.iter().flat_map(SettledObjects::flags).collect();
        // The initial prefix stands for the frames just before frame 0 of a sequence whose
        // prompt applies from its first frame, so a window whose prefix ends at generated frame
        // `produced` starts `produced - start_frame` frames into its prompt.
        let elapsed = (produced - prompt.start_frame) as f32;
        let length = history.dims()[2];
        let prefix = history.narrow(2, length - tp, tp)?;
        let condition = WindowCondition {
            reach: memory.reach(&prefix)?,
            prefix,
            text: prompt.embedding.to_dtype(request.model.dtype())?,
            bps: request.bps.to_dtype(request.model.dtype())?,
            presence: request.presence.to_dtype(request.model.dtype())?,
            elapsed: Some(
                Tensor::full(elapsed, batch, request.initial_prefix.device())?
                    .to_dtype(request.model.dtype())?,
            ),
            object_start: start.as_ref().map(|(_, rows)| rows.clone()),
            settled: Some(
                Tensor::from_vec(flags, (batch, MAX_OBJECTS), request.initial_prefix.device())?
                    .to_dtype(request.model.dtype())?,
            ),
        };
        let window =
            sample_window(request.model, request.schedule, &condition, &request.sampler, rng)?;
        let keep = tf.min(frames - produced);
        let mut window = window.narrow(2, 0, keep)?;
        if request.seams == Seams::Continuous {
            window =
                seams::carry_on(&condition.prefix, &window, c.layout(), seams::fade_frames(tf))?;
        }
        if let Some((encoding, rule, states)) = &mut at_rest {
            let settled = rule.settle(
                encoding,
                &request.normaliser.denormalise(&window)?,
                c.layout(),
                states,
            )?;
            window = request.normaliser.normalise(&settled)?;
        }
        // The reach rows as the prefix will show them: rebuilt, so that their object branches
        // agree as the data's do.
        let plain = request.normaliser.denormalise(&window)?;
        let rows = match (&request.prefix_encoding, c.reach_in_prefix) {
            (Some(encoding), true) => {
                request.normaliser.normalise(&encoding.rebuild(&plain, c.layout())?)?
            }
            _ => window.clone(),
        };
        memory.follow(&plain, &rows, c.layout())?;
        history = Tensor::cat(&[&history.narrow(2, length - tp, tp)?, &window], 2)?;
        windows.push(window);
        produced += keep;
        if let (Some(encoding), true) = (&request.prefix_encoding, produced < frames) {
            let length = history.dims()[2];
            let prefix = request.normaliser.denormalise(&history.narrow(2, length - tp, tp)?)?;
            let prefix = encoding.rebuild(&prefix, c.layout())?;
            history = request.normaliser.normalise(&prefix)?;
        }
        if let Some(hook) = &request.progress {
            let progress = WindowProgress {
                windows_done: windows.len(),
                windows: total_windows,
                frames_done: produced,
                frames,
            };
            if hook.0(progress).is_break() {
                return Err(SampleError::Interrupted { frames_done: produced, frames });
            }
        }
    }
    Ok(request.normaliser.denormalise(&Tensor::cat(&windows, 2)?)?)
}

/// What the sampler follows of the prompt in force, per batch row, from the same first frame
/// as the object start: whether each object has been set down again
/// ([`SettledObjects`]), and with the reach frame in the prefix each stream's normalised rows
/// at the last frame before its object first moved (`dex2hoi_data::settled::reach_frames`, as
/// the training batch reads the ground truth).
struct PromptMemory {
    trackers: Vec<SettledObjects>,
    /// `[B, 2, D]`: each stream's rows at the last frame followed while its object had not
    /// moved; `None` without the reach frame in the prefix.
    still_rows: Option<Vec<f32>>,
    width: usize,
}

impl PromptMemory {
    fn new(batch: usize, width: usize, reach: bool) -> Self {
        Self {
            trackers: vec![SettledObjects::new(); batch],
            still_rows: reach.then(|| vec![0.0; batch * MAX_OBJECTS * width]),
            width,
        }
    }

    /// Follows the next frames of every batch row: the objects' world positions (the
    /// global-position channels of `frames`, Eq. 2) and, with the reach frame, the frames'
    /// normalised `rows` (the same frames, as a prefix would show them).
    ///
    /// # Shapes
    /// - `frames` (unnormalised), `rows` (normalised): `[B, 2, T, D]`
    fn follow(
        &mut self,
        frames: &Tensor,
        rows: &Tensor,
        layout: dex2hoi_data::FeatureLayout,
    ) -> Result<()> {
        let positions = layout
            .object_of(frames)?
            .narrow(3, GLOBAL_POSITION_RANGE.start, GLOBAL_POSITION_RANGE.len())?
            .to_dtype(DType::F32)?;
        let length = positions.dim(2)?;
        let positions: Vec<f32> = positions.flatten_all()?.to_vec1()?;
        let rows: Option<Vec<f32>> = match self.still_rows {
            Some(_) => Some(rows.to_dtype(DType::F32)?.flatten_all()?.to_vec1()?),
            None => None,
        };
        let width = self.width;
        for (b, tracker) in self.trackers.iter_mut().enumerate() {
            for t in 0..length {
                tracker.push(std::array::from_fn(|s| {
                    Vec3::from_slice(&positions[((b * MAX_OBJECTS + s) * length + t) * 3..])
                }));
                let (Some(still), Some(rows)) = (&mut self.still_rows, &rows) else { continue };
                for (s, left) in tracker.left_at().iter().enumerate() {
                    if left.is_none() {
                        let row = (b * MAX_OBJECTS + s) * width;
                        still[row..row + width].copy_from_slice(
                            &rows[((b * MAX_OBJECTS + s) * length + t) * width..][..width],
                        );
                    }
                }
            }
        }
        Ok(())
    }

    /// The first prefix token with the reach frame in the prefix, for a window whose prefix is
    /// the last `T_p` frames followed: per stream, the rows at the last frame before its object
    /// first moved when that lies before the prefix, otherwise the prefix's first frame.
    ///
    /// # Shapes
    /// - `prefix`: `[B, 2, T_p, D]` (normalised); returns `[B, 2, D]`
    fn reach(&self, prefix: &Tensor) -> Result<Option<Tensor>> {
        let Some(still) = &self.still_rows else { return Ok(None) };
        let tp = prefix.dim(2)?;
        let first = prefix.narrow(2, 0, 1)?.squeeze(2)?;
        let mut rows: Vec<f32> = first.to_dtype(DType::F32)?.flatten_all()?.to_vec1()?;
        for (b, tracker) in self.trackers.iter().enumerate() {
            let first_prefix_frame = tracker.frames_read().saturating_sub(tp);
            for (s, &frame) in tracker.reach_frames(first_prefix_frame).iter().enumerate() {
                if frame < first_prefix_frame {
                    let row = (b * MAX_OBJECTS + s) * self.width;
                    rows[row..row + self.width].copy_from_slice(&still[row..row + self.width]);
                }
            }
        }
        Ok(Some(Tensor::from_vec(rows, first.dims(), first.device())?.to_dtype(first.dtype())?))
    }
}

/// What a generation is conditioned on besides the model.
#[derive(Debug, Clone)]
pub struct Conditioning<'a> {
    /// The initial prefix, unnormalised features `[2, T_p, D]` flattened (stream A then B); its
    /// root displacement is measured from the canonical start (`r = 0` stands at the origin).
    pub prefix: Vec<f32>,
    /// BPS per slot, `[2, P * 3]` flattened (zeros for an empty slot).
    pub bps: Vec<f32>,
    /// Which slots hold an object.
    pub present: [bool; MAX_OBJECTS],
    /// Prompts by start frame (the first at 0).
    pub prompts: Vec<(usize, &'a str)>,
    /// The root position the prefix's root displacement is measured from.
    pub root_start: Vec3,
    /// The body the motion is posed on: the run's built-in skeleton, or a test sequence's own
    /// subject when continuing that sequence.
    pub skeleton: &'a Skeleton,
    /// Keep the objects no hand holds at rest (see [`Generation::free_objects`]).
    pub free_objects: Option<ObjectsAtRest<'a>>,
    /// How each window joins the frames before it (see [`Generation::seams`]).
    pub seams: Seams,
    /// Called after each window of the generation (see [`Generation::progress`]).
    pub progress: Option<ProgressHook>,
}

/// A generated motion with its features.
#[derive(Debug, Clone)]
pub struct GeneratedMotion {
    /// Decoded rotations, FK and object poses.
    pub motion: DecodedMotion,
    /// The unnormalised features of both streams, `[2, frames, D]` flattened.
    pub features: Vec<f32>,
    /// Seconds the generation took.
    pub seconds: f64,
}

/// Generates `frames` frames after a prefix with a trained run (the weights it was loaded
/// with) and decodes them, the root measured from the conditioning's `root_start`.
pub fn generate_motion(
    run: &TrainedRun,
    conditioning: &Conditioning<'_>,
    frames: NonZeroUsize,
    seed: u64,
    sampler: SamplerConfig,
) -> Result<GeneratedMotion> {
    let started = Instant::now();
    let device = &run.device;
    let config = &run.config.model;
    let width = config.stream_features();
    let bps_width = config.bps_points * 3;
    if conditioning.prefix.len() != MAX_OBJECTS * config.prefix_frames * width
        || conditioning.bps.len() != MAX_OBJECTS * bps_width
    {
        return Err(SampleError::invalid(
            "generation",
            "conditioning",
            format!("a [2, {}, {width}] prefix and [2, {bps_width}] BPS", config.prefix_frames),
            format!("{} and {} numbers", conditioning.prefix.len(), conditioning.bps.len()),
        ));
    }
    let texts: Vec<&str> = conditioning.prompts.iter().map(|p| p.1).collect();
    reject_empty(&texts)?;
    let initial_prefix = Tensor::from_vec(
        conditioning.prefix.clone(),
        (1, MAX_OBJECTS, config.prefix_frames, width),
        device,
    )?;
    let timeline = conditioning
        .prompts
        .iter()
        .map(|&(start_frame, text)| {
            Ok(TimedText { start_frame, embedding: run.text.encode(&[text])?.to_device(device)? })
        })
        .collect::<Result<Vec<_>>>()?;
    let presence: Vec<f32> = conditioning.present.iter().map(|&p| f32::from(u8::from(p))).collect();
    let schedule = CosineSchedule::new(run.config.diffusion_steps)?;
    let normaliser = run.normaliser()?;
    let decoding = match config.object_representation {
        ObjectRepresentation::HandRelative => ObjectDecoding::Mixture,
        ObjectRepresentation::GlobalOnly => ObjectDecoding::GlobalOnly,
    };
    let generation = Generation {
        model: &run.inference,
        schedule: &schedule,
        normaliser: &normaliser,
        initial_prefix,
        timeline,
        bps: Tensor::from_vec(conditioning.bps.clone(), (1, MAX_OBJECTS, bps_width), device)?,
        presence: Tensor::from_vec(presence, (1, MAX_OBJECTS), device)?,
        frames,
        sampler,
        // Only the mixture has branches that can disagree.
        prefix_encoding: (decoding == ObjectDecoding::Mixture).then_some(PrefixEncoding {
            skeleton: conditioning.skeleton,
            root_start: conditioning.root_start,
            present: conditioning.present,
        }),
        free_objects: conditioning.free_objects,
        seams: conditioning.seams,
        progress: conditioning.progress.clone(),
    };
    if generation.free_objects.is_some() && generation.prefix_encoding.is_none() {
        return Err(SampleError::invalid(
            "generation",
            "free objects",
            "a model with the hand-relative object representation (objects at rest read its \
             mixture)",
            "a model with world positions only",
        ));
    }
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let features: Vec<f32> = generate(&generation, &mut rng)?.flatten_all()?.to_vec1()?;
    let (body_features, object_features) = config.layout().streams_to_frames(&features)?;
    let motion = decode_features(
        conditioning.skeleton,
        &body_features,
        &object_features,
        conditioning.present,
        conditioning.root_start,
        decoding,
    )?;
    Ok(GeneratedMotion { motion, features, seconds: started.elapsed().as_secs_f64() })
}

#[cfg(test)]
mod tests {
    use candle_core::Device;
    use dex2hoi_data::FeatureLayout;
    use dex2hoi_data::settled::reach_frames;

    use super::*;

    /// Where an object stands on frame `t` of batch row `b`: row 0's first object rises 2 cm
    /// a frame from frame 25 (counted as moved on frame 28), row 1's second slides 2 cm a frame
    /// from frame 12 (moved on frame 18); the others stand still.
    fn position(b: usize, t: usize, slot: usize) -> Vec3 {
        let from = |start: usize| 0.02 * t.saturating_sub(start) as f32;
        match (b, slot) {
            (0, 0) => Vec3::new(0.3, 0.8 + from(25), 0.4),
            (1, 1) => Vec3::new(-0.2 + from(12), 0.8, 0.5),
            _ => Vec3::new(0.1 * slot as f32, 0.8, 0.4),
        }
    }

    /// The sampler follows generated windows as the training batch reads a sequence: each
    /// window's reach rows are the rows of the frames [`reach_frames`] gives for its prefix.
    #[test]
    fn the_sampler_reaches_objects_on_the_frames_the_training_batch_does() {
        let layout = FeatureLayout::new(3);
        let d = layout.stream_width();
        let (batch, frames, tp, tf) = (2, 80, 10, 15);
        let global = layout.object_part_range(GLOBAL_POSITION_RANGE);
        let mut values = vec![0f32; batch * MAX_OBJECTS * frames * d];
        for b in 0..batch {
            for s in 0..MAX_OBJECTS {
                for t in 0..frames {
                    let row = &mut values[((b * MAX_OBJECTS + s) * frames + t) * d..][..d];
                    // Every row tells its batch row, stream and frame apart.
                    row.iter_mut().enumerate().for_each(|(k, v)| {
                        *v = (b * 100_000 + s * 10_000 + t * 10 + k % 7) as f32;
                    });
                    row[global.clone()].copy_from_slice(&position(b, t, s).to_array());
                }
            }
        }
        let device = Device::Cpu;
        let all = Tensor::from_vec(values, (batch, MAX_OBJECTS, frames, d), &device).unwrap();
        // The frames stand for both the unnormalised and the normalised ones (statistics 0, 1).
        let mut memory = PromptMemory::new(batch, d, true);
        let first = all.narrow(2, 0, tp).unwrap();
        memory.follow(&first, &first, layout).unwrap();
        let mut end = tp;
        let mut seen_reached = [false; 2];
        while end + tp <= frames {
            let prefix = all.narrow(2, end - tp, tp).unwrap();
            let got = memory.reach(&prefix).unwrap().unwrap();
            for b in 0..batch {
                let reached =
                    reach_frames(end - tp, end, |t| std::array::from_fn(|s| position(b, t, s)));
                for (s, &frame) in reached.iter().enumerate() {
                    seen_reached[b] |= frame < end - tp;
                    let expected = all.get(b).unwrap().get(s).unwrap().get(frame).unwrap();
                    let row = got.get(b).unwrap().get(s).unwrap();
                    let difference = (row - expected).unwrap().abs().unwrap();
                    let difference = difference.max_all().unwrap().to_scalar::<f32>().unwrap();
                    assert_eq!(difference, 0.0, "row {b}, stream {s}, prefix ending {end}");
                }
            }
            let next = tf.min(frames - end);
            let frames = all.narrow(2, end, next).unwrap();
            memory.follow(&frames, &frames, layout).unwrap();
            end += next;
        }
        // Both moving objects were reached before a later prefix began: the rows read back
        // are the reach frames', not only each prefix's own first frame.
        assert_eq!(seen_reached, [true, true]);
        // Without the reach frame nothing is kept.
        assert!(
            PromptMemory::new(batch, d, false)
                .reach(&all.narrow(2, 0, tp).unwrap())
                .unwrap()
                .is_none()
        );
    }
}
