//! `dex2hoi evaluator train`: train the text-motion evaluator and action classifier on a
//! dataset's training split.

use std::path::PathBuf;

use anyhow::{Context, Result, bail};
use clap::{Args, Subcommand};

use dex2hoi_data::dataset::{Dataset, Split};
use dex2hoi_eval::evaluator::{EVALUATOR_FILE, EvaluatorConfig, STATS_FILE, train_evaluator};

use crate::device::DeviceArgs;

/// Pairs per batch of the held-out retrieval (R-precision's 32).
const RETRIEVAL_BATCH: usize = 32;

/// Subcommands of `dex2hoi evaluator`.
#[derive(Debug, Subcommand)]
pub enum EvaluatorCommand {
    /// Train an evaluator (contrastive text-motion model, action classifier when the dataset
    /// has action labels) on a dataset's training split.
    Train(EvaluatorTrainArgs),
}

/// Arguments of `dex2hoi evaluator train`.
#[derive(Debug, Args)]
pub struct EvaluatorTrainArgs {
    /// The dataset directory (`dex2hoi data synth` or `dex2hoi data prepare`).
    #[arg(long)]
    data: PathBuf,
    /// The evaluator directory: `evaluator.safetensors` and `stats.json` (replaced if present).
    #[arg(long)]
    out: PathBuf,
    /// Evaluator settings (JSON; every field optional, the defaults suit a 2-core CPU).
    #[arg(long)]
    config: Option<PathBuf>,
    /// Optimiser steps (overrides the configuration's `steps`).
    #[arg(long)]
    steps: Option<usize>,
    /// Seed of the initialisation and the batches (overrides the configuration's `seed`).
    #[arg(long)]
    seed: Option<u64>,
    #[command(flatten)]
    device: DeviceArgs,
}

/// Runs `dex2hoi evaluator ...`.
pub fn run(command: EvaluatorCommand) -> Result<()> {
    match command {
        EvaluatorCommand::Train(args) => train(args),
    }
}

fn train(args: EvaluatorTrainArgs) -> Result<()> {
    let device = args.device.open()?;
    let mut config = match &args.config {
        Some(path) => {
            let text = std::fs::read_to_string(path).with_context(|| {
                format!("reading the evaluator configuration {}", path.display())
            })?;
            serde_json::from_str::<EvaluatorConfig>(&text)
                .with_context(|| format!("{}: not an evaluator configuration", path.display()))?
        }
        None => EvaluatorConfig::default(),
    };
    if let Some(steps) = args.steps {
        if steps == 0 {
            bail!("--steps must be at least 1");
        }
        config.steps = steps;
    }
    if let Some(seed) = args.seed {
        config.seed = seed;
    }
    config.validate()?;
    let dataset = Dataset::load(&args.data)
        .with_context(|| format!("loading the dataset {}", args.data.display()))?;
    let m = &dataset.manifest;
    let train_count = dataset.splits.get(&Split::Train).map_or(0, Vec::len);
    println!(
        "training an evaluator (latent {}, {} layers, {}-frame clips) on {} training sequences of {} ({} at {} fps) for {} steps -> {}",
        config.latent,
        config.layers,
        config.clip_frames,
        train_count,
        args.data.display(),
        m.skeleton,
        m.fps,
        config.steps,
        args.out.display()
    );
    let bar = indicatif::ProgressBar::new(config.steps as u64);
    bar.set_style(
        indicatif::ProgressStyle::with_template(
            "{spinner} step {pos}/{len} [{bar:30}] loss {msg} {per_sec} eta {eta}",
        )
        .context("progress bar template")?
        .progress_chars("=> "),
    );
    let trained = train_evaluator(&dataset, &args.data, &config, &device, &mut |step, loss| {
        bar.set_position(step as u64);
        bar.set_message(format!("{loss:.4}"));
    });
    bar.finish_and_clear();
    let evaluator = trained?;
    evaluator
        .save(&args.out)
        .with_context(|| format!("writing the evaluator to {}", args.out.display()))?;
    println!("evaluator: {}", args.out.join(EVALUATOR_FILE).display());
    println!("statistics: {}", args.out.join(STATS_FILE).display());
    if !evaluator.labels().is_empty() {
        println!("action labels: {}", evaluator.labels().join(", "));
    }

    let summary = evaluator.training().context("the evaluator has a training summary")?;
    let mut line = format!(
        "trained {} steps: loss {:.4} (first steps {:.4})",
        summary.steps, summary.final_loss, summary.first_loss
    );
    let test: Vec<_> = dataset
        .splits
        .get(&Split::Test)
        .map(|s| {
            s.iter()
                .filter(|q| !evaluator.vocabulary().tokenize(first_text(q)).is_empty())
                .collect()
        })
        .unwrap_or_default();
    if test.len() >= 2 {
        let windows = evaluator.evaluation_windows(test.iter().copied())?;
        let texts: Vec<&str> = test.iter().map(|s| first_text(s)).collect();
        let retrieval = evaluator.retrieval(&windows, &texts, RETRIEVAL_BATCH)?;
        line += &format!(
            ", held-out top-1 retrieval {:.1}% ({} test windows in batches of {}, chance {:.1}%)",
            100.0 * retrieval.top1,
            retrieval.pairs,
            retrieval.batch,
            100.0 / retrieval.batch as f64
        );
        let labelled: Vec<(usize, &str)> = test
            .iter()
            .enumerate()
            .filter_map(|(i, s)| s.action.as_deref().map(|a| (i, a)))
            .collect();
        if !evaluator.labels().is_empty() && !labelled.is_empty() {
            let clips: Vec<_> = labelled.iter().map(|(i, _)| windows[*i].clone()).collect();
            let labels: Vec<&str> = labelled.iter().map(|(_, a)| *a).collect();
            let accuracy = evaluator.classification_accuracy(&clips, &labels)?;
            line += &format!(
                ", action accuracy {:.1}% (chance {:.1}%)",
                100.0 * accuracy,
                100.0 / evaluator.labels().len() as f64
            );
        }
    } else {
        line += ", no held-out retrieval (the dataset has fewer than 2 test sequences)";
    }
    println!("{line}");
    Ok(())
}

fn first_text(sequence: &dex2hoi_data::features::ProcessedSequence) -> &str {
    sequence.texts.first().map_or("", String::as_str)
}
