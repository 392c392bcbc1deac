//! The model as a [`Denoiser`] for one window: the samplers of `dex2hoi-diffusion` see only
//! the trait, this adapter feeds them our network with a window's condition.

use candle_core::Tensor;
use rand_chacha::ChaCha8Rng;

use dex2hoi_diffusion::{CosineSchedule, Denoiser, DiffusionError, SamplerConfig, sample};
use dex2hoi_model::{Model, ModelInput};

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
) -> dex2hoi_diffusion::Result<Tensor> {
    let c = model.config();
    let batch = condition.text.dims()[0];
    let shape = [batch, 2, c.predicted_frames, c.stream_features()];
    let denoiser = ModelDenoiser { model, condition };
    sample(schedule, &denoiser, &shape, config, rng, model.dtype(), condition.text.device())
}
