//! The model as a [`Denoiser`] for one window: the samplers of `dex2hoi-diffusion` see only
//! the trait, this adapter feeds them our network with a window's condition.

use candle_core::Tensor;
use rand_chacha::ChaCha8Rng;

use dex2hoi_diffusion::{CosineSchedule, Denoiser, DiffusionError, SamplerConfig, sample};
use std::sync::Mutex;

use dex2hoi_model::{InferenceModel, PreparedCondition, PromptState};

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
    /// Frames from the start of the prompt in force to the window's first prefix frame, `[B]`
    /// (read by a model with the prompt clock).
    pub elapsed: Option<Tensor>,
    /// Both streams' normalised rows at the first frame of the prompt in force, `[B, 2, D]`
    /// (read by a model with the object start).
    pub object_start: Option<Tensor>,
    /// Whether each object has been moved and set down again since the prompt in force began,
    /// `[B, 2]` (read by a model with the memory of set-down objects).
    pub settled: Option<Tensor>,
    /// Both streams' normalised rows at the frame each stream's object was reached, `[B, 2,
    /// D]` (read by a model with the reach frame in the prefix).
    pub reach: Option<Tensor>,
}

/// The model as a [`Denoiser`] for one window. Rows beyond the condition's batch repeat it
/// (classifier-free guidance doubles the batch); rows asked for the null condition get a zero
/// text embedding. The timestep-independent part of the condition is computed at the first
/// step and reused while the rows' null flags stay the same. The model's errors reach the
/// sampler's caller as [`DiffusionError::Denoiser`], the [`dex2hoi_model::ModelError`] as its
/// source.
pub struct ModelDenoiser<'a> {
    model: &'a InferenceModel,
    condition: &'a WindowCondition,
    /// The rows' null flags, their prepared condition and their repeated prefix.
    prepared: Mutex<Option<(Vec<bool>, PreparedCondition, Tensor)>>,
}

impl<'a> ModelDenoiser<'a> {
    /// The model conditioned on a window.
    pub fn new(model: &'a InferenceModel, condition: &'a WindowCondition) -> Self {
        Self { model, condition, prepared: Mutex::new(None) }
    }

    /// The condition and the prefix of `rows` rows with the given null flags, prepared once.
    fn prepared(
        &self,
        null_condition: &[bool],
        rows: usize,
    ) -> Result<(PreparedCondition, Tensor), DiffusionError> {
        let mut cache = self.prepared.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
        if let Some((flags, prepared, prefix)) = cache.as_ref()
            && flags == null_condition
        {
            return Ok((prepared.clone(), prefix.clone()));
        }
        let times = rows / self.condition.text.dims()[0];
        let device = self.condition.text.device();
        let keep: Vec<f32> =
            null_condition.iter().map(|&null| if null { 0.0 } else { 1.0 }).collect();
        let keep =
            Tensor::from_vec(keep, (rows, 1), device)?.to_dtype(self.condition.text.dtype())?;
        let text = repeat_rows(&self.condition.text, times)?.broadcast_mul(&keep)?;
        let bps = repeat_rows(&self.condition.bps, times)?;
        let presence = repeat_rows(&self.condition.presence, times)?;
        let elapsed = self.condition.elapsed.as_ref().map(|e| repeat_rows(e, times)).transpose()?;
        let object_start =
            self.condition.object_start.as_ref().map(|s| repeat_rows(s, times)).transpose()?;
        let settled = self.condition.settled.as_ref().map(|s| repeat_rows(s, times)).transpose()?;
        let reach = self.condition.reach.as_ref().map(|r| repeat_rows(r, times)).transpose()?;
        let prompt = PromptState {
            elapsed: elapsed.as_ref(),
            object_start: object_start.as_ref(),
            settled: settled.as_ref(),
            reach: reach.as_ref(),
        };
        let prefix = repeat_rows(&self.condition.prefix, times)?;
        let prepared = self
            .model
            .prepare(&text, &bps, &presence, prompt, &prefix)
            .map_err(DiffusionError::denoiser)?;
        *cache = Some((null_condition.to_vec(), prepared.clone(), prefix.clone()));
        Ok((prepared, prefix))
    }
}

fn repeat_rows(t: &Tensor, times: usize) -> candle_core::Result<Tensor> {
    if times == 1 {
        return Ok(t.clone());
    }
    Tensor::cat(&vec![t.clone(); times], 0)
}

impl Denoiser for ModelDenoiser<'_> {
    fn predict_x0(
        &self,
        noisy: &Tensor,
        timesteps: &Tensor,
        null_condition: &[bool],
    ) -> dex2hoi_diffusion::Result<Tensor> {
        let rows = noisy.dims()[0];
        let batch = self.condition.text.dims()[0];
        if batch == 0 || !rows.is_multiple_of(batch) || null_condition.len() != rows {
            return Err(DiffusionError::invalid(
                "denoiser batch",
                format!("a multiple of the condition's {batch} rows with one null flag each"),
                format!("{rows} rows, {} flags", null_condition.len()),
            ));
        }
        let (prepared, prefix) = self.prepared(null_condition, rows)?;
        self.model.forward(&prefix, noisy, timesteps, &prepared).map_err(DiffusionError::denoiser)
    }
}

/// Samples the `T_f` predicted frames of one window (normalised features).
///
/// # Shapes
/// - returns `[B, 2, T_f, D]`
pub fn sample_window(
    model: &InferenceModel,
    schedule: &CosineSchedule,
    condition: &WindowCondition,
    config: &SamplerConfig,
    rng: &mut ChaCha8Rng,
) -> dex2hoi_diffusion::Result<Tensor> {
    let c = model.config();
    let batch = condition.text.dims()[0];
    let shape = [batch, 2, c.predicted_frames, c.stream_features()];
    let denoiser = ModelDenoiser::new(model, condition);
    sample(schedule, &denoiser, &shape, config, rng, model.dtype(), condition.text.device())
}
