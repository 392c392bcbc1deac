//! The schedule against values computed independently (numpy, f64), and the samplers against a
//! Gaussian data distribution whose exact `x0` predictor is known in closed form.

use std::cell::RefCell;

use candle_core::{DType, Device, Tensor};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

use dex2hoi_diffusion::{
    CosineSchedule, Denoiser, DiffusionError, SamplerConfig, SamplerKind, gaussian, guided, sample,
    sample_timesteps,
};

#[test]
fn cosine_schedule_matches_golden_values() {
    let schedule = CosineSchedule::new(1000).unwrap();
    // numpy: betas = [min(1 - f(t+1)/f(t), 0.999)], alphas_cumprod = cumprod(1 - betas).
    let golden = [
        (0, 4.128422482196914e-05, 0.999958715775178),
        (1, 4.614175273665033e-05, 0.9999125759273678),
        (10, 8.987136245297567e-05, 0.9992789037733427),
        (100, 0.0005318991556979569, 0.9715756818078386),
        (250, 0.0013272239542118092, 0.8458879864968832),
        (500, 0.003155691441585007, 0.49228517244880304),
        (700, 0.006166650863113521, 0.20186889490464904),
        (900, 0.01974185587243449, 0.023616108794393863),
        (990, 0.18998754207369384, 0.00019671738012480358),
        (998, 0.7499993929011166, 2.4287669070348544e-06),
        (999, 0.999, 2.4287669070348567e-09),
    ];
    for (t, beta, alpha_bar) in golden {
        assert!((schedule.beta(t) - beta).abs() <= 1e-12 * beta.max(1.0), "beta {t}");
        assert!((schedule.alpha_bar(t) - alpha_bar).abs() <= 1e-9 * alpha_bar, "alpha_bar {t}");
    }
    assert!(CosineSchedule::new(1).is_err());
}

#[test]
fn noising_uses_one_timestep_per_sample() {
    let schedule = CosineSchedule::new(1000).unwrap();
    let x0 = Tensor::new(&[[1.0f32, 2.0], [3.0, 4.0]], &Device::Cpu).unwrap();
    let noise = Tensor::new(&[[0.5f32, -0.5], [1.0, 0.0]], &Device::Cpu).unwrap();
    let noisy = schedule.add_noise(&x0, &noise, &[0, 700]).unwrap().to_vec2::<f32>().unwrap();
    for (row, t) in [(0, 0), (1, 700)] {
        let (a, b) =
            (schedule.alpha_bar(t).sqrt() as f32, (1.0 - schedule.alpha_bar(t)).sqrt() as f32);
        let x = [[1.0, 2.0], [3.0, 4.0]][row];
        let n = [[0.5, -0.5], [1.0, 0.0]][row];
        for k in 0..2 {
            assert!((noisy[row][k] - (a * x[k] + b * n[k])).abs() < 1e-6);
        }
    }
    assert!(schedule.add_noise(&x0, &noise, &[0, 1000]).is_err());
    assert!(schedule.add_noise(&x0, &noise, &[0]).is_err());
    let steps = sample_timesteps(&schedule, 1000, &mut ChaCha8Rng::seed_from_u64(0));
    assert!(
        steps.iter().all(|&t| t < 1000)
            && steps.iter().any(|&t| t > 900)
            && steps.iter().any(|&t| t < 100)
    );
}

/// The DDIM step along the true `x0` is the forward noising of the same noise at the earlier
/// step; along another prediction it moves the sample by `sqrt(alpha_bar_t') - sqrt((1 -
/// alpha_bar_t') / (1 - alpha_bar_t)) sqrt(alpha_bar_t)` times the difference; a step to itself
/// changes nothing, and a step forwards is refused.
#[test]
fn a_ddim_step_along_the_clean_sample_is_the_noising_of_the_earlier_step() {
    let schedule = CosineSchedule::new(1000).unwrap();
    let device = Device::Cpu;
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let x0 = gaussian(&[4, 3, 5], &mut rng, DType::F32, &device).unwrap();
    let noise = gaussian(&[4, 3, 5], &mut rng, DType::F32, &device).unwrap();
    let (from, to) = ([999, 700, 300, 40], [500, 0, 299, 40]);
    let x_t = schedule.add_noise(&x0, &noise, &from).unwrap();
    let stepped = schedule.step_towards(&x_t, &x0, &from, &to).unwrap();
    let noised = schedule.add_noise(&x0, &noise, &to).unwrap();
    let largest = |t: Tensor| t.abs().unwrap().flatten_all().unwrap().max(0).unwrap();
    let error = largest((&stepped - &noised).unwrap()).to_scalar::<f32>().unwrap();
    assert!(error < 1e-5, "{error}");
    let shifted = (&x0 + 1.0).unwrap();
    let moved = schedule.step_towards(&x_t, &shifted, &from, &to).unwrap();
    let moved = (moved - &stepped).unwrap().to_vec3::<f32>().unwrap();
    for (row, (&t, &earlier)) in from.iter().zip(&to).enumerate() {
        let (ab, ab_to) = (schedule.alpha_bar(t), schedule.alpha_bar(earlier));
        let expected = ab_to.sqrt() - ((1.0 - ab_to) / (1.0 - ab)).sqrt() * ab.sqrt();
        for value in moved[row].iter().flatten() {
            assert!(
                (f64::from(*value) - expected).abs() < 1e-5,
                "row {row}: {value} vs {expected}"
            );
        }
    }
    let same = schedule.step_towards(&x_t, &shifted, &from, &from).unwrap();
    assert!(largest((same - &x_t).unwrap()).to_scalar::<f32>().unwrap() < 1e-6);
    assert!(schedule.step_towards(&x_t, &x0, &from, &[999, 701, 0, 0]).is_err());
    assert!(schedule.step_towards(&x_t, &x0, &from[..3], &to[..3]).is_err());
}

#[test]
fn respacing_spans_the_chain() {
    let schedule = CosineSchedule::new(1000).unwrap();
    let steps = schedule.respaced(50).unwrap();
    assert_eq!(steps.len(), 50);
    assert_eq!((steps[0], steps[49]), (999, 0));
    assert!(steps.windows(2).all(|w| w[0] > w[1]));
    assert_eq!(schedule.respaced(1000).unwrap().len(), 1000);
    assert!(schedule.respaced(0).is_err() && schedule.respaced(1001).is_err());
}

/// The exact `E[x0 | x_t]` for data `N(mean, std^2)` per dimension, with a different mean under
/// the null condition; counts its calls and remembers the last batch's null flags.
struct GaussianOracle {
    schedule: CosineSchedule,
    mean: f64,
    null_mean: f64,
    std: f64,
    calls: RefCell<usize>,
    last_null: RefCell<Vec<bool>>,
}

impl Denoiser for GaussianOracle {
    fn predict_x0(
        &self,
        noisy: &Tensor,
        timesteps: &Tensor,
        null: &[bool],
    ) -> dex2hoi_diffusion::Result<Tensor> {
        *self.calls.borrow_mut() += 1;
        *self.last_null.borrow_mut() = null.to_vec();
        let t: Vec<u32> = timesteps.to_vec1()?;
        let mut gains = Vec::new();
        let mut offsets = Vec::new();
        for (b, &step) in t.iter().enumerate() {
            let ab = self.schedule.alpha_bar(step as usize);
            let mean = if null[b] { self.null_mean } else { self.mean };
            let gain = ab.sqrt() * self.std * self.std / (ab * self.std * self.std + 1.0 - ab);
            // x0 = mean + gain (x_t - sqrt(ab) mean)
            gains.push(gain as f32);
            offsets.push((mean - gain * ab.sqrt() * mean) as f32);
        }
        let column = |v: Vec<f32>| Tensor::from_vec(v, (t.len(), 1), noisy.device());
        Ok(noisy.broadcast_mul(&column(gains)?)?.broadcast_add(&column(offsets)?)?)
    }
}

fn oracle(mean: f64, null_mean: f64, std: f64) -> GaussianOracle {
    GaussianOracle {
        schedule: CosineSchedule::new(1000).unwrap(),
        mean,
        null_mean,
        std,
        calls: RefCell::new(0),
        last_null: RefCell::new(Vec::new()),
    }
}

fn moments(t: &Tensor) -> (f64, f64) {
    let v: Vec<f32> = t.flatten_all().unwrap().to_vec1().unwrap();
    let n = v.len() as f64;
    let mean = v.iter().map(|&x| f64::from(x)).sum::<f64>() / n;
    let var = v.iter().map(|&x| (f64::from(x) - mean).powi(2)).sum::<f64>() / n;
    (mean, var.sqrt())
}

#[test]
fn samplers_recover_a_gaussian_data_distribution() {
    let schedule = CosineSchedule::new(1000).unwrap();
    // Deterministic DDIM follows the probability-flow ODE and is accurate with 50 steps. The
    // stochastic samplers plug the expected x0 into the posterior and so miss the spread of x0
    // given x_t, a loss that vanishes as the steps get small: they are checked on the full chain.
    for (kind, steps) in [
        (SamplerKind::Ddim { eta: 0.0 }, 50),
        (SamplerKind::Ddim { eta: 1.0 }, 1000),
        (SamplerKind::Ddpm, 1000),
    ] {
        let model = oracle(1.5, 1.5, 0.4);
        let config = SamplerConfig { kind, steps, guidance: None };
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let x = sample(&schedule, &model, &[512, 16], &config, &mut rng, DType::F32, &Device::Cpu)
            .unwrap();
        let (mean, std) = moments(&x);
        assert!((mean - 1.5).abs() < 0.02, "{kind:?}: mean {mean}");
        assert!((std - 0.4).abs() < 0.02, "{kind:?}: std {std}");
        assert_eq!(*model.calls.borrow(), steps, "one call per step");
    }
}

#[test]
fn guidance_extrapolates_from_the_null_condition_in_one_batch() {
    let schedule = CosineSchedule::new(1000).unwrap();
    let model = oracle(1.0, 0.0, 0.3);
    let config = SamplerConfig { guidance: Some(2.5), ..SamplerConfig::default() };
    let mut rng = ChaCha8Rng::seed_from_u64(2);
    let x =
        sample(&schedule, &model, &[256, 8], &config, &mut rng, DType::F32, &Device::Cpu).unwrap();
    assert_eq!(x.dims(), &[256, 8]);
    // The guided x0 is the exact predictor of N(0 + 2.5 (1 - 0), 0.3^2).
    let (mean, std) = moments(&x);
    assert!((mean - 2.5).abs() < 0.02, "mean {mean}");
    assert!((std - 0.3).abs() < 0.02, "std {std}");
    assert_eq!(*model.calls.borrow(), 50);
    let null = model.last_null.borrow();
    assert_eq!(null.len(), 512);
    assert!(null[..256].iter().all(|n| !n) && null[256..].iter().all(|n| *n));
}

/// The guided prediction is the null one at scale 0, the conditional one at 1, and extrapolates
/// past the conditional one beyond 1.
#[test]
fn guided_prediction_interpolates_and_extrapolates() {
    let conditional = Tensor::new(&[[1.0f32, -2.0], [0.5, 4.0]], &Device::Cpu).unwrap();
    let unconditional = Tensor::new(&[[0.0f32, 1.0], [0.5, -4.0]], &Device::Cpu).unwrap();
    let at = |scale: f64| -> Vec<Vec<f32>> {
        guided(&conditional, &unconditional, scale).unwrap().to_vec2().unwrap()
    };
    assert_eq!(at(0.0), unconditional.to_vec2::<f32>().unwrap());
    assert_eq!(at(1.0), conditional.to_vec2::<f32>().unwrap());
    assert_eq!(at(2.0), vec![vec![2.0, -5.0], vec![0.5, 12.0]]);
}

#[test]
fn sampling_is_seeded() {
    let schedule = CosineSchedule::new(1000).unwrap();
    let model = oracle(0.0, 0.0, 1.0);
    let config = SamplerConfig { kind: SamplerKind::Ddpm, steps: 10, guidance: None };
    let run = |seed| {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        sample(&schedule, &model, &[4, 3], &config, &mut rng, DType::F32, &Device::Cpu)
            .unwrap()
            .to_vec2::<f32>()
            .unwrap()
    };
    assert_eq!(run(7), run(7));
    assert_ne!(run(7), run(8));
    let a = gaussian(&[3], &mut ChaCha8Rng::seed_from_u64(3), DType::F64, &Device::Cpu).unwrap();
    assert_eq!(a.dtype(), DType::F64);
}

struct Broken;

impl Denoiser for Broken {
    fn predict_x0(
        &self,
        noisy: &Tensor,
        _: &Tensor,
        _: &[bool],
    ) -> dex2hoi_diffusion::Result<Tensor> {
        Ok(noisy.narrow(1, 0, 1)?)
    }
}

#[test]
fn bad_configurations_and_models_are_reported() {
    let schedule = CosineSchedule::new(1000).unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    let run = |config: SamplerConfig, shape: &[usize], rng: &mut ChaCha8Rng| {
        sample(&schedule, &Broken, shape, &config, rng, DType::F32, &Device::Cpu)
    };
    let error = run(SamplerConfig::default(), &[2, 3], &mut rng).unwrap_err();
    assert!(matches!(error, DiffusionError::DenoiserOutput { .. }), "{error}");
    assert!(
        run(
            SamplerConfig { kind: SamplerKind::Ddim { eta: 2.0 }, ..Default::default() },
            &[2, 3],
            &mut rng
        )
        .is_err()
    );
    assert!(run(SamplerConfig { steps: 0, ..Default::default() }, &[2, 3], &mut rng).is_err());
    assert!(
        run(SamplerConfig { guidance: Some(f64::NAN), ..Default::default() }, &[2, 3], &mut rng)
            .is_err()
    );
    assert!(run(SamplerConfig::default(), &[0, 3], &mut rng).is_err());
}

/// A model's own error type, unknown to the samplers.
#[derive(Debug)]
struct OutOfWeights;

impl std::fmt::Display for OutOfWeights {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("out of weights")
    }
}

impl std::error::Error for OutOfWeights {}

struct Failing;

impl Denoiser for Failing {
    fn predict_x0(&self, _: &Tensor, _: &Tensor, _: &[bool]) -> dex2hoi_diffusion::Result<Tensor> {
        Err(DiffusionError::denoiser(OutOfWeights))
    }
}

#[test]
fn the_models_error_comes_back_as_the_typed_source() {
    let schedule = CosineSchedule::new(1000).unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    let config = SamplerConfig::default();
    let error = sample(&schedule, &Failing, &[2, 3], &config, &mut rng, DType::F32, &Device::Cpu)
        .unwrap_err();
    assert!(matches!(error, DiffusionError::Denoiser(_)), "{error}");
    let source = std::error::Error::source(&error).expect("the model's error as the source");
    assert!(source.downcast_ref::<OutOfWeights>().is_some(), "{source:?}");
    assert_eq!(error.to_string(), "the denoiser failed: out of weights");
}
