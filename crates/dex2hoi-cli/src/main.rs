//! `dex2hoi`: the command line of dex2hoi.
//!
//! - `dex2hoi data synth --out DIR [--sequences N] [--seed S] [--fps F]`: generate the built-in
//!   procedural dataset.
//! - `dex2hoi data info DIR`: summarise a dataset directory.
//! - `dex2hoi data prepare --format grab|humoto|himo --root DIR [--smplx-model FILE] --out DIR`:
//!   read a downloaded real dataset as published into the dataset format.
//! - `dex2hoi data show DIR --sequence ID|INDEX --out DIR [--smplx-model FILE|DIR]`: export one
//!   sequence of a dataset (npz, glb, bvh, preview gif and png) to look at it.
//! - `dex2hoi train --config FILE --data DIR --out RUN [--steps N] [--resume]`: train.
//!   `train`, `sample`, `evaluate` and `evaluator train` take `--device cpu|cuda[:N]`.
//! - `dex2hoi sample [--run RUN|MODEL] --text TEXT --object NAME|FILE... --out DIR
//!   [--smplx-model FILE|DIR [--betas B,...]]`: generate and export (with the shipped model
//!   unless a run or `DEX2HOI_MODEL` says otherwise).
//! - `dex2hoi model pack --run RUN --out FILE`, `dex2hoi model info [--run RUN|MODEL]`: pack a
//!   run into one model file, describe a model.
//! - `dex2hoi evaluator train --data DIR --out EVAL [--steps N] [--seed S]`: train the
//!   text-motion evaluator and action classifier.
//! - `dex2hoi evaluate --run RUN --data DIR --evaluator EVAL --out DIR [--sampler ddim|ddpm]`:
//!   the paper's metrics.
//! - `dex2hoi compare --series LABEL=DIR... --out DIR`: evaluation reports against training
//!   steps, as a table and a chart.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result, bail};
use clap::{Parser, Subcommand};

use dex2hoi_data::dataset::{Dataset, Split};
use dex2hoi_data::features::MixtureTargets;

mod body;
mod compare;
mod device;
mod evaluate;
mod evaluator;
mod model;
mod prepare;
mod sample;
mod sampling;
mod show;
mod train;

#[derive(Debug, Parser)]
#[command(
    name = "dex2hoi",
    version,
    about = "Text-driven dexterous human-object interaction generation (Dex2HOI)"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Datasets: generate the procedural one, inspect any.
    Data {
        #[command(subcommand)]
        command: DataCommand,
    },
    /// Train a model on a dataset into a run directory (Ctrl-C stops with a checkpoint).
    Train(train::TrainArgs),
    /// Generate a motion and export it (npz, glb, bvh, preview gif); the shipped model
    /// unless `--run` or `DEX2HOI_MODEL` names another.
    Sample(sample::SampleArgs),
    /// Models: pack a run into one file, describe a model.
    Model {
        #[command(subcommand)]
        command: model::ModelCommand,
    },
    /// Evaluate a run on a dataset's test split: the metrics of the paper's tables.
    Evaluate(evaluate::EvaluateArgs),
    /// Compare evaluation reports against training steps: a table of the headline metrics and a
    /// chart of every metric, one line per run.
    Compare(compare::CompareArgs),
    /// Learned evaluators: train the text-motion model and action classifier on a dataset.
    Evaluator {
        #[command(subcommand)]
        command: evaluator::EvaluatorCommand,
    },
}

#[derive(Debug, Subcommand)]
enum DataCommand {
    /// Generate the built-in procedural dataset of bimanual one- and two-object interactions.
    Synth {
        /// Output dataset directory (created; existing dataset files are replaced).
        #[arg(long)]
        out: PathBuf,
        /// Number of sequences (every tenth goes to the test split).
        #[arg(long, default_value_t = 2000)]
        sequences: usize,
        /// Random seed: the same seed gives the same files.
        #[arg(long, default_value_t = 0)]
        seed: u64,
        /// Frames per second.
        #[arg(long, default_value_t = 20.0)]
        fps: f32,
        /// The sentences that describe the sequences: three from the grammar's phrasings, or
        /// the task's three fixed template sentences (80 words in all; the same motions).
        #[arg(long, value_enum, default_value_t = SynthTexts::Grammar)]
        texts: SynthTexts,
        /// How long the person stands still around the task: 0.4-2.5 s before and 0.5-8 s
        /// after (drawn), or 0.4-0.9 s before and none after (short; otherwise the same
        /// sequences).
        #[arg(long, value_enum, default_value_t = SynthRest::Drawn)]
        rest: SynthRest,
        /// How fast the person does the task: at the even pace, or at a pace drawn per
        /// sequence (every time of the task 0.5-1.5 times the even pace's; otherwise the same
        /// sequences, but where the physical checks refuse a plan at one pace and not at the
        /// other).
        #[arg(long, value_enum, default_value_t = SynthTempo::Even)]
        tempo: SynthTempo,
        /// How the mixture targets (which hand holds an object, Eq. 4) are drawn.
        #[arg(long, value_enum, default_value_t = MixtureTargetsArg::default())]
        mixture_targets: MixtureTargetsArg,
    },
    /// Print a summary of a dataset directory: counts per split, task and object, frames, texts.
    Info {
        /// The dataset directory.
        dir: PathBuf,
    },
    /// Read a downloaded GRAB, HUMOTO or HIMO dataset as published and write it as a dataset.
    Prepare(prepare::PrepareArgs),
    /// Export one sequence of a dataset (motion.npz, motion.glb, motion.bvh, preview.gif) as
    /// the dataset's features decode it, to look at what `prepare` or `synth` produced.
    Show(show::ShowArgs),
}

fn main() -> std::process::ExitCode {
    // Before anything starts a thread: candle reads it once, when its pool starts.
    dex2hoi_model::candle_threads::run_inline();
    match run(Cli::parse().command) {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(error) => {
            eprintln!("Error: {error:?}");
            if let Some(hint) = device::out_of_memory_hint(&error) {
                eprintln!("hint: {hint}");
            }
            std::process::ExitCode::FAILURE
        }
    }
}

fn run(command: Command) -> Result<()> {
    match command {
        Command::Data {
            command:
                DataCommand::Synth { out, sequences, seed, fps, texts, rest, tempo, mixture_targets },
        } => {
            let options = dex2hoi_synth::SynthOptions {
                texts: texts.into(),
                timing: dex2hoi_synth::plan::Timing { rest: rest.into(), tempo: tempo.into() },
                mixture_targets: mixture_targets.into(),
            };
            synth(&out, sequences, seed, fps, options)
        }
        Command::Data { command: DataCommand::Info { dir } } => info(&dir),
        Command::Data { command: DataCommand::Prepare(args) } => prepare::run(args),
        Command::Data { command: DataCommand::Show(args) } => show::run(args),
        Command::Train(args) => train::run(args),
        Command::Sample(args) => sample::run(args),
        Command::Model { command } => model::run(command),
        Command::Evaluate(args) => evaluate::run(args),
        Command::Compare(args) => compare::run(args),
        Command::Evaluator { command } => evaluator::run(command),
    }
}

/// `data synth --texts`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
enum SynthTexts {
    /// Three of the grammar's phrasings per sequence.
    Grammar,
    /// The task's three fixed sentences.
    Templates,
    /// The grammar's three phrasings and the task's three fixed sentences.
    Both,
}

impl From<SynthTexts> for dex2hoi_synth::TrainingTexts {
    fn from(texts: SynthTexts) -> Self {
        match texts {
            SynthTexts::Grammar => Self::Grammar,
            SynthTexts::Templates => Self::Templates,
            SynthTexts::Both => Self::Both,
        }
    }
}

/// `data synth --mixture-targets`, `data prepare --mixture-targets`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub(crate) enum MixtureTargetsArg {
    /// The paper's: a hand within 3 cm of an object's surface holds it.
    Proximity,
    /// The paper's, except that an object standing still on its support is held by no hand,
    /// touched or not (steadied, about to be lifted, just put down).
    FreeAtRest,
}

impl Default for MixtureTargetsArg {
    fn default() -> Self {
        match MixtureTargets::default() {
            MixtureTargets::Proximity => Self::Proximity,
            MixtureTargets::FreeAtRest => Self::FreeAtRest,
        }
    }
}

impl From<MixtureTargetsArg> for MixtureTargets {
    fn from(rule: MixtureTargetsArg) -> Self {
        match rule {
            MixtureTargetsArg::Proximity => Self::Proximity,
            MixtureTargetsArg::FreeAtRest => Self::FreeAtRest,
        }
    }
}

/// `data synth --tempo`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
enum SynthTempo {
    /// The even pace.
    Even,
    /// A pace drawn per sequence.
    Drawn,
}

impl From<SynthTempo> for dex2hoi_synth::plan::TaskTempo {
    fn from(tempo: SynthTempo) -> Self {
        match tempo {
            SynthTempo::Drawn => Self::Drawn,
            SynthTempo::Even => Self::Even,
        }
    }
}

/// `data synth --rest`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
enum SynthRest {
    /// Drawn rest before and after the task.
    Drawn,
    /// A short idle time before, none after.
    Short,
}

impl From<SynthRest> for dex2hoi_synth::plan::RestAroundTask {
    fn from(rest: SynthRest) -> Self {
        match rest {
            SynthRest::Drawn => Self::Drawn,
            SynthRest::Short => Self::Short,
        }
    }
}

fn synth(
    out: &Path,
    sequences: usize,
    seed: u64,
    fps: f32,
    options: dex2hoi_synth::SynthOptions,
) -> Result<()> {
    if sequences == 0 {
        bail!("--sequences must be at least 1");
    }
    if !(fps > 0.0 && fps <= 240.0) {
        bail!("--fps must be in (0, 240], got {fps}");
    }
    let start = Instant::now();
    let bar = indicatif::ProgressBar::new(sequences as u64);
    bar.set_style(
        indicatif::ProgressStyle::with_template(
            "{spinner} generating [{bar:40}] {pos}/{len} sequences, {per_sec}, eta {eta}",
        )
        .context("progress bar template")?
        .progress_chars("=> "),
    );
    let dataset = dex2hoi_synth::build_dataset_with(sequences, seed, fps, options, &|done| {
        bar.set_position(done as u64)
    })
    .context("generating the procedural dataset")?;
    bar.finish_and_clear();
    let generated = start.elapsed();
    dataset.save(out).with_context(|| format!("writing the dataset to {}", out.display()))?;
    let frames: usize = dataset.manifest.splits.values().map(|s| s.frames).sum();
    println!(
        "wrote {} sequences ({frames} frames at {fps} fps) to {} in {:.1} s (generation {:.1} s)",
        sequences,
        out.display(),
        start.elapsed().as_secs_f64(),
        generated.as_secs_f64()
    );
    Ok(())
}

fn info(dir: &Path) -> Result<()> {
    let dataset =
        Dataset::load(dir).with_context(|| format!("reading the dataset in {}", dir.display()))?;
    let m = &dataset.manifest;
    println!("dataset {} (format {}, source {})", dir.display(), m.format_version, m.source);
    println!(
        "skeleton {} ({} joints), {} fps, stream features {} = body {} + object {}",
        m.skeleton,
        m.joints,
        m.fps,
        m.stream_feature_size,
        m.body_feature_size,
        m.object_feature_size
    );
    println!("objects: {}", m.objects.join(", "));
    println!("BPS: {} points in a {} m ball (seed {})", m.bps.points, m.bps.radius, m.bps.seed);
    let rule = match m.mixture_targets {
        MixtureTargets::Proximity => "proximity (a hand within 3 cm holds an object)",
        MixtureTargets::FreeAtRest => {
            "free at rest (a hand within 3 cm holds an object, unless it stands still on its support)"
        }
    };
    println!("mixture targets: {rule}");
    for split in Split::ALL {
        let Some(summary) = m.splits.get(&split) else { continue };
        println!(
            "\n{}: {} sequences, {} frames ({:.1} min)",
            split.name(),
            summary.sequences,
            summary.frames,
            summary.frames as f32 / m.fps / 60.0
        );
        let tasks: Vec<String> = summary.actions.iter().map(|(a, n)| format!("{a} {n}")).collect();
        println!("  tasks:   {}", tasks.join(", "));
        let objects: Vec<String> =
            summary.objects.iter().map(|(o, n)| format!("{o} {n}")).collect();
        println!("  objects: {}", objects.join(", "));
        if let Some(sequences) = dataset.splits.get(&split) {
            let two = sequences.iter().filter(|s| s.object_present.iter().all(|p| *p)).count();
            println!("  two-object sequences: {two}, one-object: {}", sequences.len() - two);
            let bodies = dataset.bodies(split)?;
            println!(
                "  rest skeletons: {} distinct, rest height {:.2}-{:.2} m",
                bodies.distinct, bodies.shortest, bodies.tallest
            );
            for s in sequences.iter().take(3) {
                println!(
                    "  e.g. {}: \"{}\"",
                    s.source_id,
                    s.texts.first().map(String::as_str).unwrap_or("")
                );
            }
        }
    }
    Ok(())
}
