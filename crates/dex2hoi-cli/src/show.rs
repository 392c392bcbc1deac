//! `dex2hoi data show DIR --sequence ID|INDEX --out DIR`: one sequence of a dataset as the
//! user would see a generated motion (motion.npz, motion.glb, motion.bvh, preview.gif), decoded
//! from the stored features through the dataset's skeleton: how to look at what `prepare` or
//! `synth` produced.

use std::path::PathBuf;

use anyhow::{Context, Result, bail};
use clap::{Args, ValueEnum};

use dex2hoi_data::dataset::{Dataset, Split};
use dex2hoi_data::features::{ObjectDecoding, ProcessedSequence};
use dex2hoi_export::{ExportMotion, ExportObject, ExportOptions, PreviewOptions, export_all};

use crate::body::BodyArgs;

/// A dataset split on the command line.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum SplitArg {
    /// The training split.
    Train,
    /// The test split.
    Test,
}

/// Arguments of `dex2hoi data show`.
#[derive(Debug, Args)]
pub struct ShowArgs {
    /// The dataset directory.
    dir: PathBuf,
    /// The sequence: its source id (`humoto/examining_cutting_board-141`, or without the
    /// dataset prefix) or its index in the split (train first, then test, without --split).
    #[arg(long)]
    sequence: String,
    /// Look only in this split.
    #[arg(long, value_enum)]
    split: Option<SplitArg>,
    /// Leave the prompt off the preview's frames.
    #[arg(long)]
    no_caption: bool,
    #[command(flatten)]
    body: BodyArgs,
    /// Output directory (created; the five files are written atomically).
    #[arg(long)]
    out: PathBuf,
}

/// The sequences in the order `--sequence INDEX` counts them.
fn candidates(dataset: &Dataset, split: Option<SplitArg>) -> Vec<(Split, &ProcessedSequence)> {
    let splits = match split {
        Some(SplitArg::Train) => vec![Split::Train],
        Some(SplitArg::Test) => vec![Split::Test],
        None => Split::ALL.to_vec(),
    };
    splits
        .into_iter()
        .flat_map(|s| dataset.splits.get(&s).into_iter().flatten().map(move |q| (s, q)))
        .collect()
}

/// Runs `dex2hoi data show`.
pub fn run(args: ShowArgs) -> Result<()> {
    let dataset = Dataset::load(&args.dir)
        .with_context(|| format!("reading the dataset in {}", args.dir.display()))?;
    let sequences = candidates(&dataset, args.split);
    let wanted = args.sequence.as_str();
    let found = sequences.iter().find(|(_, s)| s.is_named(wanted));
    let (split, sequence) = match (found, wanted.parse::<usize>()) {
        (Some(found), _) => *found,
        (None, Ok(index)) if index < sequences.len() => sequences[index],
        _ => bail!(
            "{}: no sequence `{wanted}` among {} (give a source id such as `{}`, or an index \
             below {})",
            args.dir.display(),
            if args.split.is_some() { "the split's sequences" } else { "the dataset's sequences" },
            sequences.first().map_or("", |(_, s)| s.source_id.as_str()),
            sequences.len()
        ),
    };
    let manifest = &dataset.manifest;
    let body = args.body.load(&manifest.builtin_skeleton()?)?;
    // The sequence's own body (a subject's proportions), as `prepare` measured it.
    let (skeleton, mut motion) = sequence
        .decode(&manifest.builtin_skeleton()?, ObjectDecoding::GlobalOnly)
        .with_context(|| format!("decoding {}", sequence.source_id))?;
    let mut objects = Vec::new();
    for (slot, name) in sequence.object_names.iter().enumerate() {
        let Some(name) = name else { continue };
        let asset = dataset.asset(name).with_context(|| {
            format!("{}: object `{name}` has no asset in the dataset", args.dir.display())
        })?;
        objects.push(ExportObject { name: name.clone(), mesh: &asset.mesh, slot });
    }
    if let Some(body) = &body {
        body.fits(&skeleton)?;
        motion.root_positions = body.root_positions(&skeleton, &motion.root_positions);
    }
    let export = ExportMotion {
        // With a model, its skeleton replaces the sequence's (the pelvis path stays; a
        // character's is scaled to its height).
        skeleton: body.as_ref().map_or(&skeleton, |b| b.skeleton()),
        fps: manifest.fps,
        prompts: sequence.texts.first().map(|t| (0, t.clone())).into_iter().collect(),
        motion: &motion,
        objects,
        body: body.as_ref().map(crate::body::LoadedBody::as_body),
    };
    let options = ExportOptions {
        preview: PreviewOptions { caption: !args.no_caption, ..PreviewOptions::default() },
    };
    let files = export_all(&args.out, &export, &options)
        .with_context(|| format!("exporting to {}", args.out.display()))?;
    println!(
        "{} ({} split, {} frames at {} fps, {}): \"{}\"",
        sequence.source_id,
        split.name(),
        sequence.frames,
        manifest.fps,
        match sequence.object_names.iter().flatten().collect::<Vec<_>>().as_slice() {
            [] => "no object".to_string(),
            names => names.iter().map(|n| n.as_str()).collect::<Vec<_>>().join(" and "),
        },
        export.text()
    );
    for path in [&files.npz, &files.glb, &files.bvh, &files.gif, &files.png] {
        println!("  {}", path.display());
    }
    Ok(())
}
