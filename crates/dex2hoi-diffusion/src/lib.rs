//! Diffusion for dex2hoi (paper Sec. 3.2; docs/CONVENTIONS.md, "Diffusion schedule"): the cosine
//! schedule of improved DDPM with `T = 1000` steps, forward noising with a timestep per sample, and
//! samplers for a model that predicts the clean sample `x0` — DDPM with the fixed small (posterior)
//! variance and DDIM with a configurable `eta`, both respaced to `K` steps, with classifier-free
//! guidance computed in one batched call of the model.
//!
//! The samplers only see a [`Denoiser`]: anything that maps noisy samples and timesteps to
//! `x0`, with a per-row switch to the null condition. This crate knows nothing of our network:
//! `dex2hoi-sample` adapts the model to the trait and runs autoregressive generation.

mod error;
mod sampler;
mod schedule;

pub use error::{DiffusionError, Result};
pub use sampler::{
    DEFAULT_GUIDANCE, Denoiser, SamplerConfig, SamplerKind, gaussian, guided, sample,
    sample_timesteps,
};
pub use schedule::{CosineSchedule, DEFAULT_DIFFUSION_STEPS};
