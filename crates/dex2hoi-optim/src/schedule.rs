//! Schedules over the steps of a run: the learning rate and the random stream of each step.

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

use crate::config::OptimizerConfig;

/// The learning rate at a step (0-based): linear warm-up to the peak, then cosine decay to
/// `final_learning_rate_ratio` of the peak at the last step.
pub fn learning_rate(config: &OptimizerConfig, step: usize, total_steps: usize) -> f64 {
    let warm = if config.warmup_steps == 0 {
        1.0
    } else {
        ((step + 1) as f64 / config.warmup_steps as f64).min(1.0)
    };
    let decay_steps = total_steps.saturating_sub(config.warmup_steps).max(1);
    let progress = (step.saturating_sub(config.warmup_steps) as f64 / decay_steps as f64).min(1.0);
    let ratio = config.final_learning_rate_ratio;
    let cosine = ratio + (1.0 - ratio) * 0.5 * (1.0 + (std::f64::consts::PI * progress).cos());
    config.learning_rate * warm * cosine
}

/// The random stream of a step: a ChaCha8 generator seeded by the run's seed with the step as
/// its stream, so that the generator state of a checkpoint is its step number.
pub fn step_rng(seed: u64, step: usize) -> ChaCha8Rng {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    rng.set_stream(step as u64);
    rng
}
