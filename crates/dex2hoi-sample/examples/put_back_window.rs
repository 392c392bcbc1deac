//! Where a model puts an object back when the window before it is the ground truth's own:
//! for each inspection of a dataset's split (lift, look, put back where it stood), the
//! window whose prefix ends `--lead` frames before the ground truth starts to lower the object
//! is sampled from that sequence's own prefix, condition and memory (prompt clock, object
//! start, set-down flags and reach rows, as the training batch reads them), and the object's
//! place at the window's last frame (decoded by the mixture, Eq. 4) is compared with the ground
//! truth's, in the plane of the table. Long generations add their own drift to this; a miss
//! here is the model's from the data's context.
//!
//! ```sh
//! cargo run --release -p dex2hoi-sample --example put_back_window -- \
//!     --data /work/runs/test9-even-2000 RUN [RUN ...]
//! ```
//!
//! `--ground-truth` decodes the ground truth's own window instead of a sample (every miss 0:
//! the check of the measure). `--one-step T` decodes the model's single prediction of the
//! clean window from the ground truth noised to step `T`, as the training objective sees it;
//! `--trace` follows that prediction through the sampler's steps.

use std::path::PathBuf;

use candle_core::{Device, Tensor};
use clap::Parser;
use glam::Vec3;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

use dex2hoi_data::MAX_OBJECTS;
use dex2hoi_data::dataset::{Dataset, Split};
use dex2hoi_data::features::{ObjectDecoding, ProcessedSequence, decode_features};
use dex2hoi_data::layout::slot_bps;
use dex2hoi_data::settled::SettledObjects;
use dex2hoi_diffusion::{
    CosineSchedule, DEFAULT_GUIDANCE, Denoiser, SamplerConfig, gaussian, sample,
};
use dex2hoi_sample::{ModelDenoiser, TrainedRun, Weights, WindowCondition, sample_window};

#[derive(Parser)]
struct Args {
    /// A procedural dataset directory (`dex2hoi data synth`).
    #[arg(long)]
    data: PathBuf,
    /// The split whose inspections are sampled: `test` for what the model makes of sequences
    /// it never saw, `train` for how closely it fits those it learned from.
    #[arg(long, value_enum, default_value_t = SplitArg::Test)]
    split: SplitArg,
    /// At most this many inspections, the split's first.
    #[arg(long, default_value_t = 25)]
    limit: usize,
    /// Frames between the window's last prefix frame and the ground truth's first lowered one.
    #[arg(long, default_value_t = 5)]
    lead: usize,
    /// Samples per inspection (rows of one window's batch, seed 0).
    #[arg(long, default_value_t = 4)]
    samples: usize,
    /// Classifier-free guidance scale (0: none).
    #[arg(long, default_value_t = DEFAULT_GUIDANCE)]
    guidance: f64,
    /// Condition on the empty prompt instead of the sequence's first description.
    #[arg(long)]
    null_text: bool,
    /// Decode the ground truth's window instead of sampling one.
    #[arg(long)]
    ground_truth: bool,
    /// Instead of sampling, noise the ground truth's window to this diffusion step (seed 0)
    /// and decode the model's one prediction of the clean window from it, conditioned, without
    /// guidance: what the training objective measures at that step.
    #[arg(long, conflicts_with = "ground_truth")]
    one_step: Option<usize>,
    /// While sampling, also decode the model's conditional prediction of the clean window at
    /// every step of the sampler and print, per step, the median miss over all inspections:
    /// where along the way the put-down's end moves.
    #[arg(long, conflicts_with_all = ["ground_truth", "one_step"])]
    trace: bool,
    /// Runs or packed models.
    #[arg(required = true)]
    runs: Vec<PathBuf>,
}

/// The model as the sampler sees it, keeping each step's conditional predictions.
struct Tracing<'a> {
    inner: ModelDenoiser<'a>,
    /// Per call: the diffusion step and the conditional rows' prediction (normalised).
    steps: std::sync::Mutex<Vec<(u32, Tensor)>>,
}

impl Denoiser for Tracing<'_> {
    fn predict_x0(
        &self,
        noisy: &Tensor,
        timesteps: &Tensor,
        null_condition: &[bool],
    ) -> dex2hoi_diffusion::Result<Tensor> {
        let x0 = self.inner.predict_x0(noisy, timesteps, null_condition)?;
        let conditional = null_condition.iter().take_while(|&&null| !null).count();
        let step = timesteps.get(0)?.to_scalar::<u32>()?;
        let mut steps = self.steps.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
        steps.push((step, x0.narrow(0, 0, conditional)?));
        Ok(x0)
    }
}

#[derive(Clone, Copy, clap::ValueEnum)]
enum SplitArg {
    Train,
    Test,
}

/// How far below the held height the object counts as lowered (metres).
const LOWERED_M: f32 = 0.02;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args = Args::parse();
    let data = Dataset::load(&args.data)?;
    let split = match args.split {
        SplitArg::Train => Split::Train,
        SplitArg::Test => Split::Test,
    };
    let inspections: Vec<&ProcessedSequence> = data.splits[&split]
        .iter()
        .filter(|s| s.action.as_deref() == Some("inspect"))
        .take(args.limit)
        .collect();
    println!("{} inspections in {}", inspections.len(), args.data.display());
    let device = Device::Cpu;
    let batch = args.samples;
    let repeat = |t: Tensor| Tensor::cat(&vec![t; batch], 0);
    for run_path in &args.runs {
        let run = TrainedRun::load(run_path, Weights::Ema, &device)?;
        let c = run.config.model.clone();
        let (tp, tf, d) = (c.prefix_frames, c.predicted_frames, c.stream_features());
        let normaliser = run.normaliser()?;
        let schedule = CosineSchedule::new(run.config.diffusion_steps)?;
        let sampler = SamplerConfig {
            guidance: (args.guidance != 0.0).then_some(args.guidance),
            ..SamplerConfig::default()
        };
        let mut misses = Vec::new();
        // Per sampler step (with --trace): the step and every sample's miss at it.
        let mut trace: Vec<(u32, Vec<f32>)> = Vec::new();
        // How far, in the plane of the table, each row's object ends from the ground truth's
        // place on the window's last frame, the window being `[rows, 2, T_f, D]` denormalised
        // and starting at the window's first frame `f`.
        let misses_of = |window: &Tensor,
                         seq: &ProcessedSequence,
                         f: usize|
         -> Result<Vec<f32>, Box<dyn std::error::Error>> {
            let p = ((f + tf - 1) * MAX_OBJECTS) * 3;
            let truth = Vec3::from_slice(&seq.object_positions[p..p + 3]);
            let mut row = Vec::with_capacity(window.dims()[0]);
            for b in 0..window.dims()[0] {
                let features: Vec<f32> = window.get(b)?.flatten_all()?.to_vec1()?;
                let (body, objects) = c.layout().streams_to_frames(&features)?;
                let motion = decode_features(
                    &run.skeleton,
                    &body,
                    &objects,
                    seq.object_present,
                    seq.root_start,
                    ObjectDecoding::Mixture,
                )?;
                let Some((_, places)) = &motion.objects[0] else { continue };
                row.push((places[tf - 1] - truth).with_y(0.0).length() * 100.0);
            }
            Ok(row)
        };
        for seq in &inspections {
            let position = |t: usize| -> [Vec3; MAX_OBJECTS] {
                std::array::from_fn(|s| {
                    Vec3::from_slice(&seq.object_positions[(t * MAX_OBJECTS + s) * 3..])
                })
            };
            // The frame the held object starts down: the first below its highest by LOWERED_M
            // after it first reached that height.
            let height: Vec<f32> =
                (0..seq.frames).map(|t| position(t)[0].y - position(0)[0].y).collect();
            let top = height.iter().copied().fold(0.0, f32::max);
            let reached = height.iter().position(|&h| h > top - 0.01).unwrap_or(0);
            let Some(lowered) = (reached..seq.frames).find(|&t| height[t] < top - LOWERED_M) else {
                continue;
            };
            let f = lowered.saturating_sub(args.lead);
            if f < tp || f + tf > seq.frames {
                println!("{}: the window does not fit in the sequence", seq.source_id);
                continue;
            }
            let rows =
                |frames: std::ops::Range<usize>| -> Result<Tensor, Box<dyn std::error::Error>> {
                    let n = frames.len();
                    let t = Tensor::from_vec(seq.stream_features(frames)?, (1, 2, n, d), &device)?;
                    Ok(normaliser.normalise(&t)?)
                };
            let tracker = SettledObjects::after(f, position);
            let reach = tracker.reach_frames(f - tp);
            let reach_rows = (0..MAX_OBJECTS)
                .map(|s| Ok(rows(reach[s]..reach[s] + 1)?.narrow(1, s, 1)?))
                .collect::<Result<Vec<_>, Box<dyn std::error::Error>>>()?;
            let settled = tracker.flags();
            let text = run.text.encode(&[seq.texts[0].as_str()])?;
            let text = if args.null_text { text.zeros_like()? } else { text };
            let bps = slot_bps(&data.objects, data.slot_assets(seq)?, c.bps_points)?;
            let presence = seq.object_present.map(|p| f32::from(u8::from(p)));
            let condition = WindowCondition {
                prefix: repeat(rows(f - tp..f)?)?,
                text: repeat(text)?,
                bps: repeat(Tensor::from_vec(bps, (1, 2, c.bps_points * 3), &device)?)?,
                presence: repeat(Tensor::from_vec(presence.to_vec(), (1, 2), &device)?)?,
                elapsed: Some(Tensor::full((f - tp) as f32, batch, &device)?),
                object_start: Some(repeat(rows(0..1)?.squeeze(2)?)?),
                settled: Some(repeat(Tensor::from_vec(settled.to_vec(), (1, 2), &device)?)?),
                reach: Some(repeat(Tensor::cat(&reach_rows, 1)?.squeeze(2)?)?),
            };
            let window = if args.ground_truth {
                repeat(Tensor::from_vec(seq.stream_features(f..f + tf)?, (1, 2, tf, d), &device)?)?
            } else if let Some(step) = args.one_step {
                let mut rng = ChaCha8Rng::seed_from_u64(0);
                let clean = repeat(rows(f..f + tf)?)?;
                let noise = gaussian(clean.dims(), &mut rng, clean.dtype(), &device)?;
                let noisy = schedule.add_noise(&clean, &noise, &vec![step; batch])?;
                let steps = CosineSchedule::timestep_tensor(&vec![step; batch], &device)?;
                let denoiser = ModelDenoiser::new(&run.inference, &condition);
                normaliser.denormalise(&denoiser.predict_x0(
                    &noisy,
                    &steps,
                    &vec![false; batch],
                )?)?
            } else if args.trace {
                let mut rng = ChaCha8Rng::seed_from_u64(0);
                let denoiser = Tracing {
                    inner: ModelDenoiser::new(&run.inference, &condition),
                    steps: Default::default(),
                };
                let shape = [batch, 2, tf, d];
                let dtype = run.inference.dtype();
                let x = sample(&schedule, &denoiser, &shape, &sampler, &mut rng, dtype, &device)?;
                let steps = denoiser.steps.into_inner().unwrap_or_else(|e| e.into_inner());
                for (k, (step, x0)) in steps.iter().enumerate() {
                    let x0 = normaliser.denormalise(x0)?;
                    if trace.len() <= k {
                        trace.push((*step, Vec::new()));
                    }
                    trace[k].1.extend(misses_of(&x0, seq, f)?);
                }
                normaliser.denormalise(&x)?
            } else {
                let mut rng = ChaCha8Rng::seed_from_u64(0);
                normaliser.denormalise(&sample_window(
                    &run.inference,
                    &schedule,
                    &condition,
                    &sampler,
                    &mut rng,
                )?)?
            };
            let row = misses_of(&window, seq, f)?;
            let held = (position(f - 1)[0] - position(0)[0]).with_y(0.0).length() * 100.0;
            let shown: Vec<String> = row.iter().map(|m| format!("{m:.1}")).collect();
            println!(
                "{} held {held:.1} cm from its place: misses {} cm",
                seq.source_id,
                shown.join(" ")
            );
            misses.extend(row);
        }
        for (step, mut at) in trace {
            at.sort_by(f32::total_cmp);
            let within = at.iter().filter(|&&m| m <= 5.0).count();
            let median = at.get(at.len() / 2).copied().unwrap_or(f32::NAN);
            println!(
                "step {step:>4}: predicted end {median:.1} cm off, within 5 cm {within} of {}",
                at.len()
            );
        }
        misses.sort_by(f32::total_cmp);
        let within = misses.iter().filter(|&&m| m <= 5.0).count();
        println!(
            "{}: median miss {:.1} cm, within 5 cm {within} of {}",
            run_path.display(),
            misses.get(misses.len() / 2).copied().unwrap_or(f32::NAN),
            misses.len()
        );
    }
    Ok(())
}
