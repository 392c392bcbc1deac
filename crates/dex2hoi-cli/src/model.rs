//! Which trained model a command samples with, and `dex2hoi model` (pack a run into one file,
//! describe a model).
//!
//! The model is found in this order (README.md, "The shipped model"): `--run PATH` (a run
//! directory or a packed model file), then the file named by the `DEX2HOI_MODEL` environment
//! variable, then the model shipped with dex2hoi, compiled into the binary so that it works
//! wherever the binary goes (`cargo install` included).

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use candle_core::Device;
use clap::{Args, Subcommand};

use dex2hoi_sample::{PackedPrecision, TrainedRun, Weights, pack_run};

/// The environment variable that names a model to use when `--run` is not given.
pub const MODEL_VARIABLE: &str = "DEX2HOI_MODEL";

/// The shipped model (`crates/dex2hoi-cli/model/dex2hoi-demo.safetensors`, described in
/// README.md, "The shipped model"), a packed model file.
const BUILTIN_MODEL: &[u8] = include_bytes!("../model/dex2hoi-demo.safetensors");
/// How the shipped model is named in messages.
pub const BUILTIN_MODEL_NAME: &str = "the shipped model dex2hoi-demo";

/// Where a model comes from.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum ModelSource {
    /// A run directory or a packed model file given with `--run`.
    Run(PathBuf),
    /// A file named by `DEX2HOI_MODEL`.
    Environment(PathBuf),
    /// The model compiled into the binary.
    Builtin,
}

impl ModelSource {
    /// `--run` if given, else `DEX2HOI_MODEL` if set (and not empty), else the shipped model.
    pub fn resolve(run: Option<&Path>) -> Self {
        if let Some(run) = run {
            return Self::Run(run.to_path_buf());
        }
        match std::env::var_os(MODEL_VARIABLE) {
            Some(path) if !path.is_empty() => Self::Environment(PathBuf::from(path)),
            _ => Self::Builtin,
        }
    }

    /// Loads the model's EMA weights onto `device`.
    pub fn load(&self, device: &Device) -> Result<TrainedRun> {
        match self {
            Self::Run(path) => TrainedRun::load(path, Weights::Ema, device)
                .with_context(|| format!("loading the run {}", path.display())),
            Self::Environment(path) => TrainedRun::load(path, Weights::Ema, device)
                .with_context(|| format!("loading {MODEL_VARIABLE}={}", path.display())),
            Self::Builtin => TrainedRun::from_model_bytes(
                BUILTIN_MODEL,
                Path::new("<the shipped model>"),
                Weights::Ema,
                device,
            )
            .context("loading the shipped model"),
        }
    }

    /// How the source is named in messages.
    pub fn describe(&self) -> String {
        match self {
            Self::Run(path) => path.display().to_string(),
            Self::Environment(path) => format!("{} (from {MODEL_VARIABLE})", path.display()),
            Self::Builtin => BUILTIN_MODEL_NAME.to_string(),
        }
    }
}

/// `dex2hoi model ...`.
#[derive(Debug, Subcommand)]
pub enum ModelCommand {
    /// Pack a run's EMA weights and what sampling needs (configuration, dataset manifest,
    /// statistics, vocabulary) into one file that `--run` and `DEX2HOI_MODEL` accept.
    Pack(PackArgs),
    /// Describe a model: where it comes from, its size, training steps, data and vocabulary.
    Info(InfoArgs),
    /// How far apart the model's text encoder puts prompts: a word it passes over (the hand
    /// in "with the left hand", say) changes the embedding little, and then the motion.
    Texts(TextsArgs),
    /// Write the licence of the data a model was trained on (the file `data prepare` found
    /// beside the data, such as HUMOTO's Adobe Research License), which the model carries.
    Licence(LicenceArgs),
}

/// Arguments of `dex2hoi model licence`.
#[derive(Debug, Args)]
pub struct LicenceArgs {
    /// A run directory or packed model file (default: `DEX2HOI_MODEL`, else the shipped
    /// model).
    #[arg(long)]
    run: Option<PathBuf>,
    /// Where to write the licence file (default: its own name in the current directory).
    #[arg(long)]
    out: Option<PathBuf>,
}

/// Arguments of `dex2hoi model texts`.
#[derive(Debug, Args)]
pub struct TextsArgs {
    /// A run directory or packed model file (default: `DEX2HOI_MODEL`, else the shipped
    /// model).
    #[arg(long)]
    run: Option<PathBuf>,
    /// The prompts to compare: two or more.
    #[arg(long = "text", value_name = "TEXT", required = true)]
    texts: Vec<String>,
}

/// Arguments of `dex2hoi model pack`.
#[derive(Debug, Args)]
pub struct PackArgs {
    /// The run directory written by `dex2hoi train`.
    #[arg(long)]
    run: PathBuf,
    /// The file to write (replaced atomically).
    #[arg(long)]
    out: PathBuf,
    /// Store the weights in f16: half the size; a sample moves by a fraction of a millimetre
    /// to a few (check it on your model: the first shipped model's 160-frame sample moved by
    /// 1.8 mm in a joint, the second's by 0.4 mm); default f32, exact.
    #[arg(long)]
    f16: bool,
}

/// Arguments of `dex2hoi model info`.
#[derive(Debug, Args)]
pub struct InfoArgs {
    /// A run directory or packed model file (default: `DEX2HOI_MODEL`, else the shipped
    /// model).
    #[arg(long)]
    run: Option<PathBuf>,
}

/// Runs `dex2hoi model ...`.
pub fn run(command: ModelCommand) -> Result<()> {
    match command {
        ModelCommand::Pack(args) => {
            if args.out.is_dir() {
                bail!("--out {} is a directory; give the file to write", args.out.display());
            }
            let precision = if args.f16 { PackedPrecision::F16 } else { PackedPrecision::F32 };
            let summary = pack_run(&args.run, &args.out, precision)
                .with_context(|| format!("packing the run {}", args.run.display()))?;
            println!(
                "packed {} ({} steps, {} parameters in {precision:?}) into {} ({:.1} MB)",
                args.run.display(),
                summary.step,
                summary.parameters,
                args.out.display(),
                summary.bytes as f64 / 1e6
            );
            Ok(())
        }
        ModelCommand::Info(args) => {
            let source = ModelSource::resolve(args.run.as_deref());
            // Describing a model reads its weights and computes nothing: the host will do.
            let run = source.load(&Device::Cpu)?;
            let model = &run.config.model;
            println!("model: {}", source.describe());
            println!("  trained for {} steps", run.step);
            println!(
                "  latent {}, {} layers, {} heads, feed-forward {}, {} fusion layers, {} parameters",
                model.latent,
                model.layers,
                model.heads,
                model.feed_forward,
                model.fusion_layers,
                run.model_vars.var_map().all_vars().iter().map(|v| v.elem_count()).sum::<usize>()
            );
            let object_start = match model.object_start {
                dex2hoi_model::ObjectStart::Off => None,
                dex2hoi_model::ObjectStart::Absolute => {
                    Some("where the objects stood at the start")
                }
                dex2hoi_model::ObjectStart::FromPrefix => {
                    Some("how far the objects are from where they stood at the start")
                }
            };
            let clock = model.prompt_clock.then_some("the prompt clock");
            let settled = model
                .settled_objects
                .then_some("which objects have been moved and set down again since the start");
            let beyond: Vec<&str> = [clock, object_start, settled].into_iter().flatten().collect();
            if !beyond.is_empty() {
                println!("  the condition also reads: {}", beyond.join(", "));
            }
            if model.start_in_prefix {
                println!("  the first prefix frame: the first frame of the prompt in force");
            }
            if model.reach_in_prefix {
                println!(
                    "  the first prefix frame: per object, the last frame before it moved (the \
                     frame it was reached)"
                );
            }
            println!(
                "  data: {} ({} skeleton, {} fps); objects: {}",
                run.manifest.source,
                run.manifest.skeleton,
                run.manifest.fps,
                run.manifest.objects.join(", ")
            );
            match &run.manifest.licence {
                Some(licence) => println!(
                    "  the data's licence: {} (`dex2hoi model licence` writes it); what the \
                     licence allows for the data applies to this model",
                    licence.file_name
                ),
                None => println!("  the data's licence: none kept with the data"),
            }
            if let Some(vocabulary) = run.text.vocabulary() {
                let words = vocabulary.words();
                println!("  the text encoder knows {} words: {}", words.len(), words.join(" "));
            }
            Ok(())
        }
        ModelCommand::Texts(args) => compare_texts(&args),
        ModelCommand::Licence(args) => write_licence(&args),
    }
}

/// `dex2hoi model licence`: the data's licence file, written atomically.
fn write_licence(args: &LicenceArgs) -> Result<()> {
    let source = ModelSource::resolve(args.run.as_deref());
    let run = source.load(&Device::Cpu)?;
    let Some(licence) = &run.manifest.licence else {
        bail!(
            "{} keeps no licence of its data (`data prepare` keeps the licence file it finds \
             beside the data, or the one given with --licence)",
            source.describe()
        );
    };
    let out = args.out.clone().unwrap_or_else(|| PathBuf::from(&licence.file_name));
    let bytes = licence.bytes()?;
    dex2hoi_data::files::write_atomically(&out, &bytes)
        .with_context(|| format!("writing {}", out.display()))?;
    println!("wrote {} ({} bytes) to {}", licence.file_name, bytes.len(), out.display());
    Ok(())
}

/// `dex2hoi model texts`: each prompt's embedding norm and unknown words, then the Euclidean
/// distances between the embeddings.
fn compare_texts(args: &TextsArgs) -> Result<()> {
    if args.texts.len() < 2 {
        bail!("--text: give two or more prompts to compare, got {}", args.texts.len());
    }
    let source = ModelSource::resolve(args.run.as_deref());
    let run = source.load(&Device::Cpu)?;
    let texts: Vec<&str> = args.texts.iter().map(String::as_str).collect();
    let embeddings = run.text.encode(&texts).context("encoding the prompts")?.to_vec2::<f32>()?;
    let distance =
        |a: &[f32], b: &[f32]| a.iter().zip(b).map(|(x, y)| (x - y).powi(2)).sum::<f32>().sqrt();
    println!("model: {}", source.describe());
    for (i, (text, embedding)) in texts.iter().zip(&embeddings).enumerate() {
        let norm = embedding.iter().map(|x| x * x).sum::<f32>().sqrt();
        let unknown = run.text.vocabulary().map(|v| v.unknown_words(text)).unwrap_or_default();
        let unknown = if unknown.is_empty() {
            String::new()
        } else {
            format!(", unknown words: {}", unknown.join(" "))
        };
        println!("{:>3}  norm {norm:.3}{unknown}  {text}", i + 1);
    }
    println!("distances between the embeddings:");
    print!("   ");
    for j in 0..texts.len() {
        print!("{:>8}", j + 1);
    }
    println!();
    for (i, a) in embeddings.iter().enumerate() {
        print!("{:>3}", i + 1);
        for b in &embeddings {
            print!("{:>8.3}", distance(a, b));
        }
        println!();
    }
    Ok(())
}
