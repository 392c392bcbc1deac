//! `dex2hoi evaluate`: the metrics of the paper's tables for a trained run on a dataset's test
//! split, with an evaluator trained by `dex2hoi evaluator train`.

use std::num::NonZeroUsize;
use std::path::PathBuf;

use anyhow::{Context, Result, bail};
use clap::Args;

use dex2hoi_data::dataset::Dataset;
use dex2hoi_data::files::write_atomically;
use dex2hoi_eval::evaluate::{DEFAULT_LONG_FRAMES, EvaluateOptions, LongOptions, evaluate};
use dex2hoi_eval::evaluator::Evaluator;
use dex2hoi_eval::metrics::MultimodalityProtocol;
use dex2hoi_sample::{TrainedRun, Weights, rest::FreeObjects, seams::Seams};

use crate::device::DeviceArgs;
use crate::sampling::{FreeObjectsArg, SamplingArgs, SeamsArg};

/// Arguments of `dex2hoi evaluate`.
#[derive(Debug, Args)]
pub struct EvaluateArgs {
    /// The run directory written by `dex2hoi train` (EMA weights).
    #[arg(long)]
    run: PathBuf,
    /// The dataset whose test split is evaluated.
    #[arg(long)]
    data: PathBuf,
    /// The evaluator directory written by `dex2hoi evaluator train` on the same kind of data.
    #[arg(long)]
    evaluator: PathBuf,
    /// Output directory: report.md, report.json (and embeddings.npz).
    #[arg(long)]
    out: PathBuf,
    /// Replications (mean and 95% interval over them).
    #[arg(long, default_value_t = 3)]
    replications: usize,
    /// Evaluate at most this many test sequences.
    #[arg(long)]
    sequences: Option<usize>,
    /// MultiModality protocol: REPEATS generations for each of the first PROMPTS test
    /// sequences, PAIRS random pairs among them (0 prompts or 1 repeat turn it off; the paper's
    /// 100,30,10 with --paper-multimodality).
    #[arg(
        long,
        value_name = "PROMPTS,REPEATS,PAIRS",
        default_value_t = MultimodalityProtocol::default(),
        conflicts_with = "paper_multimodality"
    )]
    multimodality: MultimodalityProtocol,
    /// Use the paper's MultiModality protocol (100 prompts x 30 repeats x 10 pairs).
    #[arg(long)]
    paper_multimodality: bool,
    #[command(flatten)]
    sampling: SamplingArgs,
    /// The objects no hand holds (by the model's mixture): as the model generates them (the
    /// paper's sampler), or at rest where they were put down, standing on their support.
    #[arg(long, value_enum, default_value_t = FreeObjects::default().into())]
    free_objects: FreeObjectsArg,
    /// How each window joins the frames before it: as the model generates them (the paper's
    /// sampler), or continuous (each window's body carries on from the motion before it).
    #[arg(long, value_enum, default_value_t = Seams::default().into())]
    seams: SeamsArg,
    /// Seed of the noise.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Also write the last replication's embeddings (generated, ground truth, texts), the clips
    /// they embed and the sequences' actions to embeddings.npz.
    #[arg(long)]
    dump_embeddings: bool,
    /// Also run the long-generation protocol: motions of --long-frames frames from each test
    /// sequence's first-frame placements and prompt (no motion prefix), as `dex2hoi sample`
    /// makes them, judged against the whole ground truth (task done as asked and once, objects
    /// at rest); with the lone object moved to the middle or across the body, and with the
    /// phrasings held out of training.
    #[arg(long)]
    long: bool,
    /// Frames of each long generation.
    #[arg(long, default_value_t = DEFAULT_LONG_FRAMES.try_into().expect("a positive default"), requires = "long")]
    long_frames: NonZeroUsize,
    #[command(flatten)]
    device: DeviceArgs,
}

/// Runs `dex2hoi evaluate`.
pub fn run(args: EvaluateArgs) -> Result<()> {
    let device = args.device.open()?;
    if args.replications == 0 {
        bail!("--replications must be at least 1");
    }
    let sampler = args.sampling.config()?;
    let multimodality =
        if args.paper_multimodality { MultimodalityProtocol::paper() } else { args.multimodality };
    let run = TrainedRun::load(&args.run, Weights::Ema, &device)
        .with_context(|| format!("loading the run {}", args.run.display()))?;
    let dataset = Dataset::load(&args.data)
        .with_context(|| format!("loading the dataset {}", args.data.display()))?;
    let evaluator = Evaluator::load(&args.evaluator, &device)
        .with_context(|| format!("loading the evaluator {}", args.evaluator.display()))?;
    evaluator.check_dataset(&dataset.manifest, &args.data)?;
    if run.manifest.skeleton != dataset.manifest.skeleton
        || run.manifest.fps != dataset.manifest.fps
    {
        bail!(
            "the run was trained on {} at {} fps, the dataset {} is {} at {} fps",
            run.manifest.skeleton,
            run.manifest.fps,
            args.data.display(),
            dataset.manifest.skeleton,
            dataset.manifest.fps
        );
    }
    let options = EvaluateOptions {
        replications: args.replications,
        sequences: args.sequences,
        sampler,
        seed: args.seed,
        multimodality,
        long: args.long.then_some(LongOptions { frames: args.long_frames }),
        free_objects: args.free_objects.into(),
        seams: args.seams.into(),
    };
    let bar = indicatif::ProgressBar::new(0);
    bar.set_style(
        indicatif::ProgressStyle::with_template(
            "{spinner} generating [{bar:30}] {pos}/{len} clips, {per_sec}, eta {eta}",
        )
        .context("progress bar template")?
        .progress_chars("=> "),
    );
    let result = evaluate(&run, &dataset, &evaluator, &options, &mut |done, total| {
        bar.set_length(total as u64);
        bar.set_position(done as u64);
    });
    bar.finish_and_clear();
    let (report, embeddings) = result?;
    let title = format!("Evaluation of {} on {}", args.run.display(), args.data.display());
    let markdown = report.markdown(&title);
    let json = serde_json::to_vec_pretty(&report).context("serialising the report")?;
    let npz = if args.dump_embeddings { Some(embeddings.npz()?) } else { None };
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("creating {}", args.out.display()))?;
    write_atomically(&args.out.join("report.md"), markdown.as_bytes())?;
    write_atomically(&args.out.join("report.json"), &json)?;
    if let Some(npz) = npz {
        write_atomically(&args.out.join("embeddings.npz"), &npz)?;
    }
    println!("{markdown}");
    println!("written to {}", args.out.display());
    Ok(())
}
