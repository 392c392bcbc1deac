//! Sampling motion with the model: a [`Denoiser`] over the model for one window, and
//! autoregressive generation of any length over prefix-conditioned windows (paper Sec. 3.2),
//! with a timeline of prompts (a text per time span, beyond the paper).
//!
//! Features are normalised with the dataset statistics before they reach the model and
//! denormalised after. Generated frames keep the convention of the dataset: the root
//! displacement is measured from the first frame of the whole generation, so a window's prefix
//! is simply the last `T_p` generated frames, objects included.

use candle_core::{DType, Tensor};
use rand_chacha::ChaCha8Rng;

use dex2hoi_model::{Model, ModelInput};

use crate::error::{DiffusionError, Result};
use crate::sampler::{Denoiser, SamplerConfig, sample};
use crate::schedule::CosineSchedule;

/// Everything a window is conditioned on, for a batch of `B` samples.
#[derive(Debug, Clone)]
pub struct WindowCondition {
    /// Normalised clean prefix frames, `[B, 2, T_p, D]`.
    pub prefix: Tensor,
    /// Text embeddings, `[B, E]`.
    pub text: Tensor,
    /// BPS features per object slot, `[B, 2, P * 3]`.
    pub bps: Tensor,
    /// Object presence, `[B, 2]`.
    pub presence: Tensor,
}

/// The model as a [`Denoiser`] for one window. Rows beyond the condition's batch repeat it
/// (classifier-free guidance doubles the batch); rows asked for the null condition get a zero
/// text embedding.
pub struct ModelDenoiser<'a> {
    /// The network.
    pub model: &'a Model,
    /// The window's condition.
    pub condition: &'a WindowCondition,
}

fn repeat_rows(t: &Tensor, times: usize) -> Result<Tensor> {
    if times == 1 {
        return Ok(t.clone());
    }
    Ok(Tensor::cat(&vec![t.clone(); times], 0)?)
}

impl Denoiser for ModelDenoiser<'_> {
    fn predict_x0(
        &self,
        noisy: &Tensor,
        timesteps: &Tensor,
        null_condition: &[bool],
    ) -> Result<Tensor> {
        let rows = noisy.dims()[0];
        let batch = self.condition.text.dims()[0];
        if batch == 0 || !rows.is_multiple_of(batch) || null_condition.len() != rows {
            return Err(DiffusionError::invalid(
                "denoiser batch",
                format!("a multiple of the condition's {batch} rows with one null flag each"),
                format!("{rows} rows, {} flags", null_condition.len()),
            ));
        }
        let times = rows / batch;
        let keep: Vec<f32> =
            null_condition.iter().map(|&null| if null { 0.0 } else { 1.0 }).collect();
        let keep = Tensor::from_vec(keep, (rows, 1), noisy.device())?.to_dtype(noisy.dtype())?;
        let text = repeat_rows(&self.condition.text, times)?.broadcast_mul(&keep)?;
        let prefix = repeat_rows(&self.condition.prefix, times)?;
        let bps = repeat_rows(&self.condition.bps, times)?;
        let presence = repeat_rows(&self.condition.presence, times)?;
        let input = ModelInput {
            noisy,
            prefix: &prefix,
            timesteps,
            text: &text,
            bps: &bps,
            presence: &presence,
            frame_mask: None,
        };
        self.model.forward(&input, None).map_err(|e| DiffusionError::Denoiser {
            expected: "a prediction".into(),
            got: e.to_string(),
        })
    }
}

/// Samples the `T_f` predicted frames of one window (normalised features).
///
/// # Shapes
/// - returns `[B, 2, T_f, D]`
pub fn sample_window(
    model: &Model,
    schedule: &CosineSchedule,
    condition: &WindowCondition,
    config: &SamplerConfig,
    rng: &mut ChaCha8Rng,
) -> Result<Tensor> {
    let c = model.config();
    let batch = condition.text.dims()[0];
    let shape = [batch, 2, c.predicted_frames, c.stream_features()];
    let denoiser = ModelDenoiser { model, condition };
    sample(schedule, &denoiser, &shape, config, rng, model.dtype(), condition.text.device())
}

/// A prompt that applies from a frame on (frames counted from the first generated frame).
#[derive(Debug, Clone)]
pub struct TimedText {
    /// First frame the prompt applies to.
    pub start_frame: usize,
    /// Its embedding, `[B, E]`.
    pub embedding: Tensor,
}

/// Per-channel normalisation of stream features.
#[derive(Debug, Clone)]
pub struct Normaliser {
    /// `[D]` means.
    pub mean: Tensor,
    /// `[D]` standard deviations.
    pub std: Tensor,
}

impl Normaliser {
    /// `(x - mean) / std` over the last dimension.
    pub fn normalise(&self, x: &Tensor) -> Result<Tensor> {
        Ok(x.broadcast_sub(&self.mean)?.broadcast_div(&self.std)?)
    }

    /// `x * std + mean` over the last dimension.
    pub fn denormalise(&self, x: &Tensor) -> Result<Tensor> {
        Ok(x.broadcast_mul(&self.std)?.broadcast_add(&self.mean)?)
    }
}

/// What an autoregressive generation needs.
#[derive(Debug, Clone)]
pub struct Generation<'a> {
    /// The network.
    pub model: &'a Model,
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
    pub frames: usize,
    /// Sampler settings.
    pub sampler: SamplerConfig,
}

/// Generates `frames` frames after the initial prefix, window by window: each window's prefix
/// is the last `T_p` frames so far, its prompt the timeline entry in force at its first frame.
///
/// # Shapes
/// - returns `[B, 2, frames, D]` (unnormalised features)
pub fn generate(request: &Generation<'_>, rng: &mut ChaCha8Rng) -> Result<Tensor> {
    let c = request.model.config();
    let (tp, tf) = (c.prefix_frames, c.predicted_frames);
    if request.frames == 0 {
        return Err(DiffusionError::invalid("frames to generate", "at least 1", 0));
    }
    if request.timeline.first().map(|t| t.start_frame) != Some(0) {
        return Err(DiffusionError::invalid(
            "timeline",
            "prompts by start frame, the first at frame 0",
            format!("{} prompts", request.timeline.len()),
        ));
    }
    if request.timeline.windows(2).any(|w| w[1].start_frame <= w[0].start_frame) {
        return Err(DiffusionError::invalid(
            "timeline",
            "increasing start frames",
            "a repeated or decreasing start",
        ));
    }
    let mut history = request.normaliser.normalise(
        &request.initial_prefix.to_dtype(DType::F32)?.to_dtype(request.model.dtype())?,
    )?;
    if history.dims().get(2) != Some(&tp) {
        return Err(DiffusionError::invalid(
            "initial prefix",
            format!("{tp} frames"),
            format!("{:?}", history.dims()),
        ));
    }
    let mut produced = 0;
    let mut windows = Vec::new();
    while produced < request.frames {
        let text = request
            .timeline
            .iter()
            .rev()
            .find(|t| t.start_frame <= produced)
            .map(|t| t.embedding.clone())
            .unwrap_or_else(|| request.timeline[0].embedding.clone());
        let length = history.dims()[2];
        let condition = WindowCondition {
            prefix: history.narrow(2, length - tp, tp)?,
            text: text.to_dtype(request.model.dtype())?,
            bps: request.bps.to_dtype(request.model.dtype())?,
            presence: request.presence.to_dtype(request.model.dtype())?,
        };
        let window =
            sample_window(request.model, request.schedule, &condition, &request.sampler, rng)?;
        let keep = tf.min(request.frames - produced);
        let window = window.narrow(2, 0, keep)?;
        history = Tensor::cat(&[&history.narrow(2, length - tp, tp)?, &window], 2)?;
        windows.push(window);
        produced += keep;
    }
    request.normaliser.denormalise(&Tensor::cat(&windows, 2)?)
}
