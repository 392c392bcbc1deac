//! `dex2hoi sample`: generate a motion with a trained run and export it (npz, glb, bvh, gif).

mod long_generation;

use std::num::NonZeroUsize;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

use anyhow::{Context, Result, bail};
use clap::Args;

use crate::body::{BodyArgs, LoadedBody};
use crate::device::DeviceArgs;
use crate::model::ModelSource;
use crate::sampling::{FreeObjectsArg, SamplingArgs, SeamsArg};
use dex2hoi_data::dataset::Dataset;
use dex2hoi_export::{
    ExportMotion, ExportObject, ExportOptions, PreviewOptions, TableBox, export_all,
};
use dex2hoi_sample::{
    DEFAULT_TABLE_HEIGHT, Prompt, SampleError, SampleRequest, SceneObject, SceneTable,
    SequenceScene, parse_timeline, rest::FreeObjects, sample, seams::Seams, unknown_words_warning,
};

use long_generation::{
    AvailableMemory, FrameCost, GenerationShape, GenerationWatch, check_length, install_ctrl_c,
};

/// Frames `sample` generates unless told.
const DEFAULT_FRAMES: NonZeroUsize = NonZeroUsize::new(120).expect("120 is not zero");

/// Arguments of `dex2hoi sample`.
#[derive(Debug, Args)]
pub struct SampleArgs {
    /// The model: a run directory written by `dex2hoi train` (its EMA weights) or a file
    /// written by `dex2hoi model pack`. Default: the file named by `DEX2HOI_MODEL`, else the
    /// model shipped with dex2hoi.
    #[arg(long)]
    run: Option<PathBuf>,
    /// The prompt (or use --timeline; with --sequence, the sequence's first description by
    /// default).
    #[arg(long)]
    text: Option<String>,
    /// A timeline file: one `SECONDS TEXT` line per prompt, the first at 0.
    #[arg(long, conflicts_with = "text")]
    timeline: Option<PathBuf>,
    /// An object: a catalogue name (mug, bottle, box, ball, bowl, book, can, plate; with
    /// --data, first the names of that dataset's objects) or an OBJ/PLY file, optionally
    /// `@x,y,z` (metres; +Z ahead, +X left, +Y up). Once or twice. Unplaced, it stands on the
    /// table in front: one object on the side of the hand the (first) prompt names, else in
    /// the middle; two objects one on each side, the one the first named hand holds on that
    /// hand's side (else the first on the left).
    #[arg(long = "object", required_unless_present = "sequence", conflicts_with = "sequence")]
    objects: Vec<String>,
    /// A dataset directory (`data prepare`, `data synth`) whose objects --object can name and
    /// whose sequences --sequence can name: for a model trained on real data, whose objects
    /// are not in the built-in catalogue.
    #[arg(long)]
    data: Option<PathBuf>,
    /// Start from the scene of this sequence of --data (its source id, or the part after the
    /// source's prefix, as `data show` takes it): its objects where they are on its first frame, no table; its first
    /// description unless --text or --timeline is given; its length unless --frames is.
    #[arg(long, requires = "data")]
    sequence: Option<String>,
    /// Frames to generate (at the run's frame rate; at least 1; default 120, or the length of
    /// --sequence). A length whose motion and exports would not fit in the memory available is
    /// refused before any work.
    #[arg(long)]
    frames: Option<NonZeroUsize>,
    /// Seed of the noise: the same seed gives the same motion.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    #[command(flatten)]
    sampling: SamplingArgs,
    /// The objects no hand holds (by the model's mixture): at rest where they were put down,
    /// standing on their support, or as the model generates them (the paper's sampler).
    /// Default: at rest with a model trained on the procedural data, where every object goes
    /// back down on the surface it started on; as generated with one trained on captured data.
    #[arg(long, value_enum)]
    free_objects: Option<FreeObjectsArg>,
    /// How each window of the generation (two seconds at 20 fps) joins the frames before it:
    /// continuous (each window's body carries on from the motion before it, with no jump) or
    /// as the model generates them (the paper's sampler).
    #[arg(long, value_enum, default_value_t = Seams::sample_default().into())]
    seams: SeamsArg,
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
    let generating = Arc::new(AtomicBool::new(false));
    let stop = install_ctrl_c(Arc::clone(&generating))?;
    let device = args.device.open()?;
    if args.objects.len() > 2 {
        bail!("the model takes at most two objects, got {}", args.objects.len());
    }
    let sampler = args.sampling.config()?;
    if !(args.table_height.is_finite() && (0.3..=1.5).contains(&args.table_height)) {
        bail!("--table-height must be between 0.3 and 1.5 m, got {}", args.table_height);
    }
    let dataset = match &args.data {
        Some(dir) => Some(Dataset::load(dir).with_context(|| format!("--data {}", dir.display()))?),
        None => None,
    };
    let scene = match (&args.sequence, &dataset) {
        (Some(id), Some(dataset)) => Some(SequenceScene::of(dataset, id).with_context(|| {
            format!("--sequence in {}", args.data.as_deref().unwrap_or(Path::new("")).display())
        })?),
        _ => None,
    };
    let objects = match &scene {
        Some(scene) => scene.objects.clone(),
        None => args
            .objects
            .iter()
            .map(|spec| {
                SceneObject::parse(spec, dataset.as_ref())
                    .with_context(|| format!("--object `{spec}`"))
            })
            .collect::<Result<Vec<_>>>()?,
    };
    let frames = args
        .frames
        .or_else(|| scene.as_ref().and_then(|s| NonZeroUsize::new(s.frames)))
        .unwrap_or(DEFAULT_FRAMES);
    let source = ModelSource::resolve(args.run.as_deref());
    let run = source.load(&device)?;
    let body = args.body.load(&run.skeleton)?;
    let fps = run.manifest.fps;
    let preview = PreviewOptions::default();
    let cost = FrameCost {
        stream_features: run.config.model.stream_features(),
        joints: body.as_ref().map_or(&run.skeleton, |b| b.skeleton()).joint_count(),
        objects: objects.len(),
        preview_width: preview.width,
        preview_height: preview.height,
    };
    if let Some(dataset) = &dataset
        && dataset.manifest.skeleton != run.manifest.skeleton
    {
        bail!(
            "--data {} is on the {} skeleton, the model on {}",
            args.data.as_deref().unwrap_or(Path::new("")).display(),
            dataset.manifest.skeleton,
            run.manifest.skeleton
        );
    }
    check_length(frames.get(), fps, &cost, &AvailableMemory::of_this_machine())?;
    println!("sampling with {} ({} training steps)", source.describe(), run.step);
    let prompts = match (&args.text, &args.timeline, scene.as_ref().and_then(|s| s.texts.first())) {
        (Some(text), None, _) | (None, None, Some(text)) => {
            vec![Prompt { start_frame: 0, text: text.clone() }]
        }
        (None, Some(path), _) => {
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
        if let Some(warning) = unknown_words_warning(&unknown) {
            eprintln!("warning: {warning} (`dex2hoi model info` lists the words it knows)");
        }
    }
    let shape = GenerationShape {
        fps,
        window_frames: run.config.model.predicted_frames,
        steps: sampler.steps,
    };
    let watch = Arc::new(GenerationWatch::start(shape, Arc::clone(&stop))?);
    let request = SampleRequest {
        prompts: prompts.clone(),
        objects,
        frames,
        seed: args.seed,
        sampler,
        table_height: args.table_height,
        free_objects: args
            .free_objects
            .map_or_else(|| FreeObjects::sample_default(&run.manifest.source), Into::into),
        seams: args.seams.into(),
        progress: Some(watch.hook()),
    };
    if let Some(mesh) = &body {
        mesh.fits(&run.skeleton)?;
    }
    generating.store(true, Ordering::SeqCst);
    let sampled = sample(&run, &request);
    generating.store(false, Ordering::SeqCst);
    watch.finish();
    let sampled = match sampled {
        Err(SampleError::Interrupted { frames_done, frames }) => bail!(
            "interrupted (Ctrl-C) after {frames_done} of {frames} frames: nothing written to {}",
            args.out.display()
        ),
        // A Ctrl-C after the last window: the generation is whole, but it was asked to stop.
        Ok(_) if stop.load(Ordering::SeqCst) => bail!(
            "interrupted (Ctrl-C) as the generation ended: nothing written to {}",
            args.out.display()
        ),
        other => other.context("generating")?,
    };
    if watch.was_announced() {
        eprintln!("rendering the preview of {} frames and writing the outputs", sampled.frames);
    }
    // On a character, the root path scaled to its height.
    let mut motion = sampled.motion;
    if let Some(body) = &body {
        motion.root_positions = body.root_positions(&run.skeleton, &motion.root_positions);
    }
    let export = ExportMotion {
        skeleton: body.as_ref().map_or(&run.skeleton, |b| b.skeleton()),
        fps,
        prompts: prompts.iter().map(|p| (p.start_frame, p.text.clone())).collect(),
        motion: &motion,
        objects: sampled
            .objects
            .iter()
            .map(|(slot, o)| ExportObject { name: o.name.clone(), mesh: &o.mesh, slot: *slot })
            .collect(),
        body: body.as_ref().map(LoadedBody::as_body),
    };
    // The table, when an object stands on it: a sequence's furniture is not in the data (only
    // the objects that move are), and a placed object may stand on the floor.
    let table = match scene {
        Some(_) => None,
        None => SceneTable::under(&sampled.objects, args.table_height),
    };
    let options = ExportOptions {
        preview: PreviewOptions {
            table: table.map(|t| TableBox {
                height: t.height,
                centre: t.centre,
                half_extents: t.half_extents,
            }),
            caption: !args.no_caption,
            ..preview
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
