//! The sampler options that `sample` and `evaluate` share.

use anyhow::{Result, bail};
use clap::{Args, ValueEnum};

use dex2hoi_diffusion::{SamplerConfig, SamplerKind};

/// The reverse process (docs/CONVENTIONS.md, "Diffusion schedule").
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum Sampler {
    /// Deterministic DDIM (eta 0).
    Ddim,
    /// Ancestral DDPM with the posterior variance, on the respaced steps.
    Ddpm,
}

/// How to sample.
#[derive(Debug, Clone, Args)]
pub struct SamplingArgs {
    /// The reverse process.
    #[arg(long, value_enum, default_value_t = Sampler::Ddim)]
    sampler: Sampler,
    /// Denoising steps (the 1000 training steps respaced to this many; DDPM takes them too).
    #[arg(long, visible_alias = "steps", default_value_t = SamplerConfig::default().steps)]
    ddim_steps: usize,
    /// Classifier-free guidance scale (0 or 1 turns guidance off).
    #[arg(long, default_value_t = SamplerConfig::default().guidance.unwrap_or(1.0))]
    guidance: f64,
}

impl SamplingArgs {
    /// The sampler configuration, or an error naming the option that cannot be used.
    pub fn config(&self) -> Result<SamplerConfig> {
        if self.ddim_steps == 0 {
            bail!("--ddim-steps must be at least 1");
        }
        if !self.guidance.is_finite() || self.guidance < 0.0 {
            bail!("--guidance must be a non-negative number, got {}", self.guidance);
        }
        let kind = match self.sampler {
            Sampler::Ddim => SamplerKind::Ddim { eta: 0.0 },
            Sampler::Ddpm => SamplerKind::Ddpm,
        };
        let guidance = (self.guidance != 0.0 && self.guidance != 1.0).then_some(self.guidance);
        Ok(SamplerConfig { kind, steps: self.ddim_steps, guidance })
    }
}
