//! The sampler options that `sample` and `evaluate` share; their defaults are
//! `SamplerConfig::default()`'s. The sampler's rules beyond the paper, what happens to the
//! objects no hand holds (`FreeObjectsArg`) and how windows join (`SeamsArg`), are options of
//! each, with defaults of their own.

use anyhow::{Result, bail};
use clap::{Args, ValueEnum};

use dex2hoi_diffusion::{SamplerConfig, SamplerKind};
use dex2hoi_sample::rest::FreeObjects;
use dex2hoi_sample::seams::Seams;

/// The reverse process (docs/CONVENTIONS.md, "Diffusion schedule").
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum Sampler {
    /// DDIM with the default configuration's noise scale (0: deterministic).
    Ddim,
    /// Ancestral DDPM with the posterior variance, on the respaced steps.
    Ddpm,
}

impl Sampler {
    /// The sampler of `SamplerConfig::default()`.
    fn default_kind() -> Self {
        match SamplerConfig::default().kind {
            SamplerKind::Ddim { .. } => Self::Ddim,
            SamplerKind::Ddpm => Self::Ddpm,
        }
    }

    fn kind(self) -> SamplerKind {
        match (self, SamplerConfig::default().kind) {
            (Self::Ddim, default @ SamplerKind::Ddim { .. }) => default,
            (Self::Ddim, SamplerKind::Ddpm) => SamplerKind::Ddim { eta: 0.0 },
            (Self::Ddpm, _) => SamplerKind::Ddpm,
        }
    }
}

/// What happens to the objects no hand holds.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum FreeObjectsArg {
    /// As the model generates them (the paper's sampler).
    AsGenerated,
    /// Kept where they were put down, standing on their support (beyond the paper).
    AtRest,
}

impl From<FreeObjects> for FreeObjectsArg {
    fn from(free: FreeObjects) -> Self {
        match free {
            FreeObjects::AsGenerated => Self::AsGenerated,
            FreeObjects::AtRest => Self::AtRest,
        }
    }
}

impl From<FreeObjectsArg> for FreeObjects {
    fn from(free: FreeObjectsArg) -> Self {
        match free {
            FreeObjectsArg::AsGenerated => Self::AsGenerated,
            FreeObjectsArg::AtRest => Self::AtRest,
        }
    }
}

/// How each window of a generation joins the frames before it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum SeamsArg {
    /// As the model generates them (the paper's sampler).
    AsGenerated,
    /// Each window's body carries on from its prefix: its root from where the prefix leads, its
    /// pose offset fading over a quarter of the window (beyond the paper).
    Continuous,
}

impl From<Seams> for SeamsArg {
    fn from(seams: Seams) -> Self {
        match seams {
            Seams::AsGenerated => Self::AsGenerated,
            Seams::Continuous => Self::Continuous,
        }
    }
}

impl From<SeamsArg> for Seams {
    fn from(seams: SeamsArg) -> Self {
        match seams {
            SeamsArg::AsGenerated => Self::AsGenerated,
            SeamsArg::Continuous => Self::Continuous,
        }
    }
}

/// How to sample.
#[derive(Debug, Clone, Args)]
pub struct SamplingArgs {
    /// The reverse process.
    #[arg(long, value_enum, default_value_t = Sampler::default_kind())]
    sampler: Sampler,
    /// Denoising steps: the 1000 training steps respaced to this many (DDIM and DDPM alike).
    #[arg(long, visible_alias = "ddim-steps", default_value_t = SamplerConfig::default().steps)]
    denoising_steps: usize,
    /// Classifier-free guidance scale (0 or 1 turns guidance off).
    #[arg(
        long,
        allow_negative_numbers = true,
        default_value_t = SamplerConfig::default().guidance.unwrap_or(1.0)
    )]
    guidance: f64,
}

impl SamplingArgs {
    /// The sampler configuration, or an error naming the option that cannot be used.
    pub fn config(&self) -> Result<SamplerConfig> {
        if self.denoising_steps == 0 {
            bail!("--denoising-steps (--ddim-steps) must be at least 1");
        }
        if !self.guidance.is_finite() || self.guidance < 0.0 {
            bail!("--guidance must be a non-negative number, got {}", self.guidance);
        }
        let guidance = (self.guidance != 0.0 && self.guidance != 1.0).then_some(self.guidance);
        Ok(SamplerConfig { kind: self.sampler.kind(), steps: self.denoising_steps, guidance })
    }
}
