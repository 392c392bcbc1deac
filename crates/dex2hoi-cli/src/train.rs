//! `dex2hoi train`: train a model on a prepared dataset into a run directory.

use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

use anyhow::{Context, Result, bail};
use clap::Args;

use dex2hoi_data::dataset::Dataset;
use dex2hoi_sample::RunFiles;
use dex2hoi_train::checkpoint::Fresh;
use dex2hoi_train::{RunStart, TrainConfig, TrainOptions, train};

use crate::device::DeviceArgs;

/// Arguments of `dex2hoi train`.
#[derive(Debug, Args)]
pub struct TrainArgs {
    /// Training configuration (TOML; presets in `configs/`). With `--resume` the run's own
    /// `config.toml` is used when this is left out, with `--init-from` the model's.
    #[arg(long)]
    config: Option<PathBuf>,
    /// The dataset directory (`dex2hoi data synth` or `dex2hoi data prepare`).
    #[arg(long)]
    data: PathBuf,
    /// The run directory: config, statistics, checkpoint, metrics, loss curve.
    #[arg(long)]
    out: PathBuf,
    /// Train for this many steps in all (overrides `training.steps`).
    #[arg(long)]
    steps: Option<usize>,
    /// Continue the run in `--out` from its checkpoint, bit for bit.
    #[arg(long, conflicts_with = "init_from")]
    resume: bool,
    /// Start a new run from the EMA weights of a trained model (a packed model such as the
    /// shipped one, or a run directory or its checkpoint) instead of the seed: fine-tuning. The
    /// optimiser and step count start afresh; the model's network, text encoder and vocabulary
    /// must be those of the configuration and dataset.
    #[arg(long, value_name = "MODEL")]
    init_from: Option<PathBuf>,
    /// With `--init-from`: a part of the model that starts from this run's seed instead of the
    /// model's weights (`text-encoder`: the built-in text encoder, with this configuration's
    /// `[text]` settings and this dataset's words; the denoiser is the model's).
    #[arg(long, value_enum, requires = "init_from")]
    fresh: Option<FreshPart>,
    /// Keep a snapshot every N steps in `--out/snapshots/step-NNNNNN/` (each a run directory
    /// that `sample` and `evaluate` take as `--run`), for metrics against training steps.
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(usize))]
    snapshot_every: Option<usize>,
    #[command(flatten)]
    device: DeviceArgs,
}

/// Runs `dex2hoi train`.
pub fn run(args: TrainArgs) -> Result<()> {
    let device = args.device.open()?;
    let init_from = args
        .init_from
        .as_ref()
        .map(|path| if path.is_dir() { RunFiles::new(path).checkpoint } else { path.clone() });
    let mut config = match (&args.config, args.resume, &init_from) {
        (Some(path), _, _) => TrainConfig::load(path)?,
        (None, true, _) => TrainConfig::load(&RunFiles::new(&args.out).config)
            .context("reading the configuration of the run to resume")?,
        (None, false, Some(model)) => TrainConfig::from_model_file(model)
            .context("reading the training configuration stored in the model to start from")?,
        (None, false, None) => bail!("--config FILE is required (presets are in configs/)"),
    };
    if let Some(steps) = args.steps {
        if steps == 0 {
            bail!("--steps must be at least 1");
        }
        config.training.steps = steps;
    }
    let dataset = Dataset::load(&args.data)
        .with_context(|| format!("loading the dataset {}", args.data.display()))?;
    let stop = Arc::new(AtomicBool::new(false));
    {
        let stop = Arc::clone(&stop);
        ctrlc::set_handler(move || {
            if stop.swap(true, Ordering::SeqCst) {
                eprintln!("\nsecond Ctrl-C: leaving without a checkpoint");
                std::process::exit(130);
            }
            eprintln!("\nCtrl-C: stopping after this step and writing the checkpoint");
        })
        .context("installing the Ctrl-C handler")?;
    }
    let bar = indicatif::ProgressBar::new(config.training.steps as u64);
    bar.set_style(
        indicatif::ProgressStyle::with_template(
            "{spinner} step {pos}/{len} [{bar:30}] loss {msg} {per_sec} eta {eta}",
        )
        .context("progress bar template")?
        .progress_chars("=> "),
    );
    println!(
        "training a latent-{} model with {} layers on {} for {} steps on {} -> {}",
        config.model.latent,
        config.model.layers,
        args.data.display(),
        config.training.steps,
        args.device.device,
        args.out.display()
    );
    if let Some(model) = &init_from {
        println!("starting from the EMA weights of {}", model.display());
    }
    let weights = &config.training.action_weights;
    if !weights.is_empty() {
        let listed: Vec<String> = weights.iter().map(|(a, w)| format!("{a} x{w}")).collect();
        println!("windows drawn by action: {}, every other action x1", listed.join(", "));
    }
    let start = match (&init_from, args.resume) {
        (Some(model), _) => {
            RunStart::InitialisedFrom(model, args.fresh.map_or(Fresh::Nothing, Fresh::from))
        }
        (None, true) => RunStart::Resume,
        (None, false) => RunStart::Fresh,
    };
    let options =
        TrainOptions { start, stop: &stop, snapshot_every: args.snapshot_every, device: &device };
    let total_steps = config.training.steps;
    let summary = train(&args.out, config, &dataset, &args.data, options, &mut |report, total| {
        bar.set_length(total as u64);
        bar.set_position(report.step as u64);
        bar.set_message(format!("{:.4}", report.loss));
    });
    bar.finish_and_clear();
    let summary = summary?;
    if let Some(bridged) = &summary.initialisation {
        if bridged.words_carried + bridged.words_new > 0 {
            println!(
                "vocabulary: {} words carried over from the model, {} new (started as its \
                 unknown word)",
                bridged.words_carried, bridged.words_new
            );
        }
        if !bridged.fresh.is_empty() {
            println!(
                "started afresh from this run's seed ({} tensors): {}",
                bridged.fresh.len(),
                bridged.fresh.join(", ")
            );
        }
        if !bridged.kept.is_empty() {
            println!(
                "new in this model, trained from their initialisation: {}",
                bridged.kept.join(", ")
            );
        }
    }
    let files = RunFiles::new(&args.out);
    if summary.interrupted {
        bail!(
            "stopped at step {} of {} (checkpoint written to {}); continue with --resume",
            summary.steps,
            total_steps,
            files.checkpoint.display()
        );
    }
    if summary.steps_before > 0 {
        println!(
            "trained {} steps ({} in all with those of the model it started from)",
            summary.steps,
            summary.steps.saturating_add(summary.steps_before)
        );
    } else {
        println!("trained {} steps", summary.steps);
    }
    if let Some(last) = &summary.last {
        let terms: Vec<String> =
            last.terms.iter().map(|(t, v)| format!("{} {v:.4}", t.name())).collect();
        println!("last step: loss {:.4} ({})", last.loss, terms.join(", "));
    }
    println!("checkpoint: {}", files.checkpoint.display());
    println!("metrics:    {}", files.metrics.display());
    println!("loss curve: {}", files.loss_curve.display());
    Ok(())
}

/// `--fresh`: what a fine-tuning run trains from its own seed ([`Fresh`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
enum FreshPart {
    /// The built-in text encoder.
    TextEncoder,
}

impl From<FreshPart> for Fresh {
    fn from(part: FreshPart) -> Self {
        match part {
            FreshPart::TextEncoder => Fresh::TextEncoder,
        }
    }
}
