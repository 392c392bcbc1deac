//! The cosine noise schedule (Nichol and Dhariwal 2021, as MDM uses it).

use candle_core::{DType, Device, Tensor};

use crate::error::{DiffusionError, Result};

/// The number of diffusion steps of the paper and MDM.
pub const DEFAULT_DIFFUSION_STEPS: usize = 1000;

/// Offset `s` of the cosine schedule.
const COSINE_OFFSET: f64 = 0.008;
/// The largest beta (avoids a singular last step).
const MAX_BETA: f64 = 0.999;

/// `beta_t = min(1 - f(t+1)/f(t), 0.999)` with `f(t) = cos^2(((t/T) + s)/(1 + s) * pi/2)`, and
/// `alpha_bar_t = prod_{i <= t} (1 - beta_i)`, in `f64`. (candle's own `SquaredcosCapV2` divides
/// integers and is wrong; this is computed here and golden-tested.)
#[derive(Debug, Clone, PartialEq)]
pub struct CosineSchedule {
    betas: Vec<f64>,
    alphas_cumprod: Vec<f64>,
}

impl CosineSchedule {
    /// The schedule with `steps` diffusion steps.
    pub fn new(steps: usize) -> Result<Self> {
        if steps < 2 {
            return Err(DiffusionError::invalid("diffusion steps", "at least 2", steps));
        }
        let f = |t: usize| {
            let x = (t as f64 / steps as f64 + COSINE_OFFSET) / (1.0 + COSINE_OFFSET);
            (x * std::f64::consts::FRAC_PI_2).cos().powi(2)
        };
        let betas: Vec<f64> = (0..steps).map(|t| (1.0 - f(t + 1) / f(t)).min(MAX_BETA)).collect();
        let mut product = 1.0;
        let alphas_cumprod = betas
            .iter()
            .map(|beta| {
                product *= 1.0 - beta;
                product
            })
            .collect();
        Ok(Self { betas, alphas_cumprod })
    }

    /// Number of steps `T`.
    pub fn steps(&self) -> usize {
        self.betas.len()
    }

    /// `beta_t`.
    pub fn beta(&self, t: usize) -> f64 {
        self.betas[t]
    }

    /// `alpha_bar_t`.
    pub fn alpha_bar(&self, t: usize) -> f64 {
        self.alphas_cumprod[t]
    }

    fn check_timesteps(&self, timesteps: &[usize]) -> Result<()> {
        match timesteps.iter().find(|&&t| t >= self.steps()) {
            Some(t) => {
                Err(DiffusionError::invalid("timestep", format!("below {}", self.steps()), t))
            }
            None => Ok(()),
        }
    }

    /// A `[batch, 1, ..., 1]` tensor of per-sample coefficients, broadcastable against `like`.
    fn per_sample(&self, values: Vec<f64>, like: &Tensor) -> Result<Tensor> {
        let mut shape = vec![values.len()];
        shape.extend(std::iter::repeat_n(1, like.rank().saturating_sub(1)));
        Ok(Tensor::from_vec(values, shape, like.device())?.to_dtype(like.dtype())?)
    }

    /// Forward noising `x_t = sqrt(alpha_bar_t) x0 + sqrt(1 - alpha_bar_t) noise`, one timestep
    /// per sample.
    ///
    /// # Shapes
    /// - `x0`, `noise`: `[batch, ...]`; `timesteps`: `batch` values
    /// - returns `[batch, ...]`
    pub fn add_noise(&self, x0: &Tensor, noise: &Tensor, timesteps: &[usize]) -> Result<Tensor> {
        self.check_timesteps(timesteps)?;
        if x0.dims().first() != Some(&timesteps.len()) || x0.dims() != noise.dims() {
            return Err(DiffusionError::invalid(
                "noising inputs",
                format!("x0 and noise of one shape with {} rows", timesteps.len()),
                format!("{:?} and {:?}", x0.dims(), noise.dims()),
            ));
        }
        let signal =
            self.per_sample(timesteps.iter().map(|&t| self.alpha_bar(t).sqrt()).collect(), x0)?;
        let scale = self.per_sample(
            timesteps.iter().map(|&t| (1.0 - self.alpha_bar(t)).sqrt()).collect(),
            x0,
        )?;
        Ok((x0.broadcast_mul(&signal)? + noise.broadcast_mul(&scale)?)?)
    }

    /// The deterministic DDIM step (eta 0) from `x_t` to an earlier step `t'` along a
    /// prediction `x0` of the clean sample, one pair of steps per sample:
    /// `x_t' = sqrt(alpha_bar_t') x0 + sqrt(1 - alpha_bar_t') eps`, where
    /// `eps = (x_t - sqrt(alpha_bar_t) x0) / sqrt(1 - alpha_bar_t)` is the noise the prediction
    /// implies (DDIM, Song et al. 2021, Eq. 12). With the true `x0` it gives the forward
    /// noising of the same noise at `t'`; with a model's prediction, the input the sampler
    /// would reach.
    ///
    /// # Shapes
    /// - `x_t`, `x0`: `[batch, ...]`; `from`, `to`: `batch` values, each `to` at most its `from`
    /// - returns `[batch, ...]`
    pub fn step_towards(
        &self,
        x_t: &Tensor,
        x0: &Tensor,
        from: &[usize],
        to: &[usize],
    ) -> Result<Tensor> {
        self.check_timesteps(from)?;
        self.check_timesteps(to)?;
        if x_t.dims().first() != Some(&from.len())
            || x_t.dims() != x0.dims()
            || to.len() != from.len()
        {
            return Err(DiffusionError::invalid(
                "DDIM step inputs",
                format!("x_t and x0 of one shape with {} rows, as many target steps", from.len()),
                format!("{:?}, {:?} and {} target steps", x_t.dims(), x0.dims(), to.len()),
            ));
        }
        if let Some((t, earlier)) = from.iter().zip(to).find(|(t, earlier)| earlier > t) {
            return Err(DiffusionError::invalid(
                "DDIM target step",
                format!("at most the step it starts from, {t}"),
                earlier,
            ));
        }
        let per_pair = |f: &dyn Fn(f64, f64) -> f64| -> Vec<f64> {
            from.iter()
                .zip(to)
                .map(|(&t, &earlier)| f(self.alpha_bar(t), self.alpha_bar(earlier)))
                .collect()
        };
        // x_t' = a x_t + b x0 with eps substituted: a = sqrt((1 - ab') / (1 - ab)),
        // b = sqrt(ab') - a sqrt(ab). A step to itself is the identity (a = 1, b = 0).
        let ratio = |ab: f64, ab_to: f64| ((1.0 - ab_to) / (1.0 - ab)).sqrt();
        let of_x_t = self.per_sample(per_pair(&ratio), x_t)?;
        let of_x0 = self
            .per_sample(per_pair(&|ab, ab_to| ab_to.sqrt() - ratio(ab, ab_to) * ab.sqrt()), x0)?;
        Ok((x_t.broadcast_mul(&of_x_t)? + x0.broadcast_mul(&of_x0)?)?)
    }

    /// Timesteps as a `[batch]` `u32` tensor, the form denoisers take.
    pub fn timestep_tensor(timesteps: &[usize], device: &Device) -> Result<Tensor> {
        let values: Vec<u32> = timesteps.iter().map(|&t| t as u32).collect();
        Ok(Tensor::from_vec(values, timesteps.len(), device)?.to_dtype(DType::U32)?)
    }

    /// `K` timesteps spread evenly over `[0, T)`, descending, starting at `T - 1` and ending at
    /// 0 (the respacing of improved DDPM).
    pub fn respaced(&self, count: usize) -> Result<Vec<usize>> {
        let steps = self.steps();
        if count == 0 || count > steps {
            return Err(DiffusionError::invalid("sampling steps", format!("1 to {steps}"), count));
        }
        if count == 1 {
            return Ok(vec![steps - 1]);
        }
        let mut out: Vec<usize> = (0..count)
            .map(|k| ((k as f64) * (steps - 1) as f64 / (count - 1) as f64).round() as usize)
            .collect();
        out.dedup();
        out.reverse();
        Ok(out)
    }
}
