//! `dex2hoi data prepare`: read a downloaded GRAB, HUMOTO or HIMO dataset as published and
//! write it in the dex2hoi dataset format, with a progress bar and a summary of what was read,
//! skipped and why.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result, bail};
use clap::{Args, ValueEnum};

use dex2hoi_import::humoto::PickleRig;
use dex2hoi_import::smplx::UpAxis;
use dex2hoi_import::{HandPoseSource, PrepareOptions, SourceFormat, prepare};

/// The published dataset formats.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum FormatArg {
    /// GRAB: `ROOT/grab/s1..s10/*.npz` and `ROOT/tools/` (SMPL-X, 120 fps, split s1-s9 / s10).
    Grab,
    /// HUMOTO: sequence folders `<seq>/<seq>.glb` as published (texts from animations.json),
    /// or the authors' `<seq>/<seq>.pkl` + `.yaml` (objects in `humoto_objects/`).
    Humoto,
    /// HIMO: `data/{smplx,object_pose,text,object_mesh}` (2-object sequences).
    Himo,
}

/// Where GRAB's finger rotations come from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum HandPoseArg {
    /// The 45-D MANO `fullpose` of `lhand` / `rhand`.
    Full,
    /// The body's 24 PCA coefficients through the model's `hands_components`.
    Pca,
}

/// The up axis of the source world.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum UpAxisArg {
    /// Y up (no conversion).
    Y,
    /// Z up (the default of GRAB and HUMOTO's pickles).
    Z,
}

/// The rig of HUMOTO pickles (the authors' Blender scripts transfer the motion to one).
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum PickleRigArg {
    /// `up_bone`: every bone's rest frame is Rx(+90 deg) (read).
    UpBone,
    /// `mixamo_bone`: Mixamo's own bone frames (refused: read the published .glb instead).
    MixamoBone,
}

/// Arguments of `dex2hoi data prepare`.
#[derive(Debug, Args)]
pub struct PrepareArgs {
    /// The dataset's format.
    #[arg(long, value_enum)]
    format: FormatArg,
    /// The dataset as downloaded: GRAB's root (holding grab/ and tools/), HUMOTO's folder of
    /// sequence folders, HIMO's data/ folder (or its parent).
    #[arg(long)]
    root: PathBuf,
    /// SMPL-X model file (SMPLX_NEUTRAL.npz) or a directory of SMPLX_{MALE,FEMALE,NEUTRAL}.npz
    /// (required for GRAB and HIMO).
    #[arg(long)]
    smplx_model: Option<PathBuf>,
    /// Output dataset directory (created; existing dataset files are replaced).
    #[arg(long)]
    out: PathBuf,
    /// Frames per second of the prepared dataset.
    #[arg(long, default_value_t = 20.0)]
    fps: f32,
    /// GRAB: where the finger rotations come from.
    #[arg(long, value_enum, default_value_t = HandPoseArg::Full)]
    hand_pose: HandPoseArg,
    /// GRAB: a text template ({verb}, {object}, {intent} are filled in); repeat for several
    /// texts per sequence. Default: "The person is {verb} the {object}."
    #[arg(long = "text-template")]
    text_templates: Vec<String>,
    /// HUMOTO: the object mesh folder (default: humoto_objects in or beside the root).
    #[arg(long)]
    objects: Option<PathBuf>,
    /// A split file, repeatable: JSON {"train": [ids], "test": [ids]}, or a JSON list of ids
    /// in a file whose name says its split (HOIDiNi's grab_train_split.json and
    /// grab_test_split.json, ids like s1/airplane_fly_1). Unlisted sequences are skipped.
    /// Without one, GRAB splits by subject (s10 tests) and HUMOTO and HIMO by a seeded hash.
    #[arg(long = "split-file")]
    split_files: Vec<PathBuf>,
    /// GRAB: leave out the sequences of an intent (repeatable; HOIDiNi's benchmark leaves out
    /// `lift`).
    #[arg(long = "exclude-intent")]
    exclude_intents: Vec<String>,
    /// GRAB: a prompt table, CSV with the columns dp_ind and Prompt (HOIDiNi's
    /// grab_prompts.csv); a listed sequence takes its prompt instead of the templates.
    #[arg(long)]
    prompts: Option<PathBuf>,
    /// Seed of the hash split.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Override the up axis of the source world (default: z for GRAB and HUMOTO's pickles, y
    /// for HIMO; HUMOTO's GLBs are always Y up).
    #[arg(long, value_enum)]
    up_axis: Option<UpAxisArg>,
    /// HUMOTO pickles: the rig the authors' scripts transferred them to.
    #[arg(long, value_enum, default_value_t = PickleRigArg::UpBone)]
    humoto_rig: PickleRigArg,
    /// The data's licence file, kept in the dataset, in every run trained on it and in every
    /// model packed from one (default: a file named like `*licen[cs]e*` in --root or its
    /// parent, such as HUMOTO's `Adobe Research License v1.1.pdf`).
    #[arg(long)]
    licence: Option<PathBuf>,
    /// How the mixture targets (which hand holds an object, Eq. 4) are drawn.
    #[arg(long, value_enum, default_value_t = crate::MixtureTargetsArg::default())]
    mixture_targets: crate::MixtureTargetsArg,
}

/// Runs `dex2hoi data prepare`.
pub fn run(args: PrepareArgs) -> Result<()> {
    let format = match args.format {
        FormatArg::Grab => SourceFormat::Grab,
        FormatArg::Humoto => SourceFormat::Humoto,
        FormatArg::Himo => SourceFormat::Himo,
    };
    if args.smplx_model.is_none() && format != SourceFormat::Humoto {
        bail!(
            "--smplx-model is required for {}: its SMPL-X parameters need the model's rest joints \
             (give SMPLX_NEUTRAL.npz or a directory of SMPLX_*.npz)",
            format.name()
        );
    }
    let mut options = PrepareOptions::new(format, &args.root);
    options.smplx_model = args.smplx_model;
    options.fps = args.fps;
    options.hand_pose = match args.hand_pose {
        HandPoseArg::Full => HandPoseSource::Full,
        HandPoseArg::Pca => HandPoseSource::Pca,
    };
    if !args.text_templates.is_empty() {
        options.text_templates = args.text_templates;
    }
    options.objects_dir = args.objects;
    options.split_files = args.split_files;
    options.exclude_intents = args.exclude_intents;
    options.prompts = args.prompts;
    options.seed = args.seed;
    options.up_axis = args.up_axis.map(|a| match a {
        UpAxisArg::Y => UpAxis::Y,
        UpAxisArg::Z => UpAxis::Z,
    });
    options.pickle_rig = match args.humoto_rig {
        PickleRigArg::UpBone => PickleRig::UpBone,
        PickleRigArg::MixamoBone => PickleRig::MixamoBone,
    };
    if let Some(path) = &args.licence
        && !path.is_file()
    {
        bail!("--licence {}: no such file", path.display());
    }
    options.licence = args.licence;
    options.mixture_targets = args.mixture_targets.into();

    let start = Instant::now();
    let bar = indicatif::ProgressBar::new(0);
    bar.set_style(
        indicatif::ProgressStyle::with_template(
            "{spinner} reading [{bar:40}] {pos}/{len} sequences, {per_sec}, eta {eta}",
        )
        .context("progress bar template")?
        .progress_chars("=> "),
    );
    let prepared = prepare(options, &|done, total| {
        bar.set_length(total as u64);
        bar.set_position(done as u64);
    })
    .with_context(|| format!("preparing {} from {}", format.name(), args.root.display()))?;
    bar.finish_and_clear();
    println!("{}", prepared.report.summary());
    let Some(dataset) = prepared.dataset else {
        bail!("no sequence of {} could be read: nothing written", args.root.display());
    };
    dataset
        .save(&args.out)
        .with_context(|| format!("writing the dataset to {}", args.out.display()))?;
    let m = &dataset.manifest;
    let sequences: usize = m.splits.values().map(|s| s.sequences).sum();
    let frames: usize = m.splits.values().map(|s| s.frames).sum();
    println!(
        "wrote {sequences} sequences ({frames} frames at {} fps, skeleton {}, {} objects) to {} in \
         {:.1} s",
        m.fps,
        m.skeleton,
        m.objects.len(),
        args.out.display(),
        start.elapsed().as_secs_f64()
    );
    Ok(())
}
