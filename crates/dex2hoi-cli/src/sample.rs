//! `dex2hoi sample`: generate a motion with a trained run and export it (npz, glb, bvh, gif).

use std::num::NonZeroUsize;
use std::path::PathBuf;

use anyhow::{Context, Result, bail};
use clap::Args;
use glam::Vec2;

use crate::body::BodyArgs;
use crate::device::DeviceArgs;
use crate::model::ModelSource;
use crate::sampling::SamplingArgs;
use dex2hoi_export::{
    ExportMotion, ExportObject, ExportOptions, PreviewOptions, TableBox, export_all,
};
use dex2hoi_sample::{
    DEFAULT_TABLE_HEIGHT, DEFAULT_TABLE_NEAR_EDGE, Prompt, SampleRequest, SceneObject,
    parse_timeline, sample,
};

/// Arguments of `dex2hoi sample`.
#[derive(Debug, Args)]
pub struct SampleArgs {
    /// The model: a run directory written by `dex2hoi train` (its EMA weights) or a file
    /// written by `dex2hoi model pack`. Default: the file named by `DEX2HOI_MODEL`, else the
    /// model shipped with dex2hoi.
    #[arg(long)]
    run: Option<PathBuf>,
    /// The prompt (or use --timeline).
    #[arg(long)]
    text: Option<String>,
    /// A timeline file: one `SECONDS TEXT` line per prompt, the first at 0.
    #[arg(long, conflicts_with = "text")]
    timeline: Option<PathBuf>,
    /// An object: a catalogue name (mug, bottle, box, ball, bowl, book, can, plate) or an
    /// OBJ/PLY file, optionally `@x,y,z` (metres; +Z ahead, +X left, +Y up). Once or twice.
    /// Unplaced, it stands on the table in front: one object on the side of the hand the
    /// (first) prompt names, else in the middle; two objects side by side, the first on the
    /// left.
    #[arg(long = "object", required = true)]
    objects: Vec<String>,
    /// Frames to generate (at the run's frame rate; at least 1).
    #[arg(long, default_value = "120")]
    frames: NonZeroUsize,
    /// Seed of the noise: the same seed gives the same motion.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    #[command(flatten)]
    sampling: SamplingArgs,
    /// Height of the table the objects stand on (metres).
    #[arg(long, default_value_t = DEFAULT_TABLE_HEIGHT)]
    table_height: f32,
    /// Leave the prompt off the preview's frames.
    #[arg(long)]
    no_caption: bool,
    #[command(flatten)]
    body: BodyArgs,
    /// Output directory for motion.npz, motion.glb, motion.bvh, preview.gif and preview.png.
    #[arg(long)]
    out: PathBuf,
    #[command(flatten)]
    device: DeviceArgs,
}

/// Runs `dex2hoi sample`.
pub fn run(args: SampleArgs) -> Result<()> {
    let device = args.device.open()?;
    if args.objects.len() > 2 {
        bail!("the model takes at most two objects, got {}", args.objects.len());
    }
    let sampler = args.sampling.config()?;
    if !(args.table_height.is_finite() && (0.3..=1.5).contains(&args.table_height)) {
        bail!("--table-height must be between 0.3 and 1.5 m, got {}", args.table_height);
    }
    let objects = args
        .objects
        .iter()
        .map(|spec| SceneObject::parse(spec).with_context(|| format!("--object `{spec}`")))
        .collect::<Result<Vec<_>>>()?;
    let body = args.body.load()?;
    let source = ModelSource::resolve(args.run.as_deref());
    let run = source.load(&device)?;
    println!("sampling with {} ({} training steps)", source.describe(), run.step);
    let fps = run.manifest.fps;
    let prompts = match (&args.text, &args.timeline) {
        (Some(text), None) => vec![Prompt { start_frame: 0, text: text.clone() }],
        (None, Some(path)) => {
            let text = std::fs::read_to_string(path)
                .with_context(|| format!("reading the timeline {}", path.display()))?;
            parse_timeline(&text, fps, &path.display().to_string())?
        }
        _ => bail!("give the prompt with --text TEXT or --timeline FILE"),
    };
    if prompts.iter().any(|p| p.text.trim().is_empty()) {
        bail!("the prompt is empty");
    }
    if let Some(vocabulary) = run.text.vocabulary() {
        let all_prompts: Vec<&str> = prompts.iter().map(|p| p.text.as_str()).collect();
        let unknown = vocabulary.unknown_words(&all_prompts.join("\n"));
        if !unknown.is_empty() {
            eprintln!(
                "warning: the model's text encoder never saw {}: each reads as the unknown-word \
                 token (`dex2hoi model info` lists the words it knows)",
                unknown.iter().map(|w| format!("`{w}`")).collect::<Vec<_>>().join(", ")
            );
        }
    }
    let request = SampleRequest {
        prompts: prompts.clone(),
        objects,
        frames: args.frames,
        seed: args.seed,
        sampler,
        table_height: args.table_height,
    };
    if let Some(mesh) = &body {
        mesh.fits(&run.skeleton)?;
    }
    let sampled = sample(&run, &request).context("generating")?;
    let export = ExportMotion {
        skeleton: body.as_ref().map_or(&run.skeleton, |mesh| &mesh.skeleton),
        fps,
        prompts: prompts.iter().map(|p| (p.start_frame, p.text.clone())).collect(),
        motion: &sampled.motion,
        objects: sampled
            .objects
            .iter()
            .map(|(slot, o)| ExportObject { name: o.name.clone(), mesh: &o.mesh, slot: *slot })
            .collect(),
        body: body.as_ref(),
    };
    let half_depth = 0.3;
    let options = ExportOptions {
        preview: PreviewOptions {
            table: Some(TableBox {
                height: args.table_height,
                centre: Vec2::new(0.0, DEFAULT_TABLE_NEAR_EDGE + half_depth),
                half_extents: Vec2::new(0.55, half_depth),
            }),
            caption: !args.no_caption,
            ..PreviewOptions::default()
        },
    };
    let files = export_all(&args.out, &export, &options)
        .with_context(|| format!("exporting to {}", args.out.display()))?;
    let duration = sampled.frames as f64 / f64::from(fps);
    println!(
        "generated {} frames ({duration:.1} s at {fps} fps) in {:.2} s: {:.2}x real time",
        sampled.frames,
        sampled.seconds,
        duration / sampled.seconds
    );
    for path in [&files.npz, &files.glb, &files.bvh, &files.gif, &files.png] {
        println!("  {}", path.display());
    }
    Ok(())
}
