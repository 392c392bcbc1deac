//! The run loop: a run directory trained from the seed, resumed from its checkpoint or started
//! from a trained model, logged, checkpointed and snapshotted as it goes.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};

use candle_core::Device;

use dex2hoi_data::dataset::Dataset;
use dex2hoi_sample::RunFiles;

use crate::checkpoint::Fresh;
use crate::config::TrainConfig;
use crate::error::{Result, TrainError};
use crate::metrics::{append_metrics, read_metrics, truncate_metrics, write_static};
use crate::step::{StepReport, Trainer};

/// Where a run's weights start.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum RunStart<'a> {
    /// A new run, its parameters from the configuration's seed.
    Fresh,
    /// Continue the run in the output directory from its checkpoint, bit for bit.
    Resume,
    /// A new run from the EMA weights of this packed model or checkpoint, but for the parts
    /// started afresh ([`Trainer::initialise_from_except`]).
    InitialisedFrom(&'a Path, Fresh),
}

/// How [`train`] runs.
#[derive(Debug, Clone, Copy)]
pub struct TrainOptions<'a> {
    /// Where the weights start.
    pub start: RunStart<'a>,
    /// Set (for example by Ctrl-C) to stop after the current step with a checkpoint.
    pub stop: &'a AtomicBool,
    /// Keep a numbered snapshot every this many steps ([`SNAPSHOTS_DIR`]); a run-time choice,
    /// not part of the configuration, so a resumed run may change it.
    pub snapshot_every: Option<usize>,
    /// Where the model trains; a run-time choice, not part of the configuration or the
    /// checkpoint, so a run may be resumed on another device.
    pub device: &'a Device,
}

/// Folder of a run directory that holds its snapshots: `step-000300/` and so on, each a run
/// directory of its own (configuration, dataset manifest, statistics, checkpoint) that
/// `dex2hoi sample` and `dex2hoi evaluate` take as `--run`.
pub const SNAPSHOTS_DIR: &str = "snapshots";

/// The snapshot directory of a step.
pub fn snapshot_dir(run_dir: &Path, step: usize) -> PathBuf {
    run_dir.join(SNAPSHOTS_DIR).join(format!("step-{step:06}"))
}

/// Copies the run's checkpoint and what loading it needs into the step's snapshot directory,
/// whole or not at all (written beside it, then renamed).
fn write_snapshot(files: &RunFiles, run_dir: &Path, step: usize) -> Result<()> {
    let target = snapshot_dir(run_dir, step);
    let partial = target.with_extension("partial");
    let _ = std::fs::remove_dir_all(&partial);
    std::fs::create_dir_all(&partial)
        .map_err(TrainError::io(&partial, "creating a snapshot directory"))?;
    let copies = RunFiles::new(&partial);
    for (from, to) in [
        (&files.config, &copies.config),
        (&files.dataset, &copies.dataset),
        (&files.stats, &copies.stats),
        (&files.checkpoint, &copies.checkpoint),
    ] {
        std::fs::copy(from, to).map_err(TrainError::io(from, "copying into a snapshot"))?;
    }
    let _ = std::fs::remove_dir_all(&target);
    std::fs::rename(&partial, &target)
        .map_err(TrainError::io(&target, "moving a snapshot into place"))?;
    Ok(())
}

/// How a run ended.
#[derive(Debug, Clone, PartialEq)]
pub struct TrainSummary {
    /// Steps done in all.
    pub steps: usize,
    /// Training steps of the model the run started from (0 for a run from the seed).
    pub steps_before: usize,
    /// Whether it stopped early on request.
    pub interrupted: bool,
    /// The last step's report, if a step ran.
    pub last: Option<StepReport>,
    /// The run directory.
    pub run_dir: PathBuf,
    /// What starting from another model's weights bridged (`None` for other starts).
    pub initialisation: Option<crate::checkpoint::Initialisation>,
}

/// Trains into a run directory: writes the resolved `config.toml`, the dataset manifest and
/// statistics, then steps, logging to `metrics.jsonl`, checkpointing every
/// `checkpoint_every` steps, on a stop request and at the end (each time with the loss-curve
/// PNG), and with `snapshot_every`, keeping a numbered snapshot of those steps. A new run
/// (fresh or initialised from a model) refuses a directory that already holds a checkpoint;
/// [`RunStart::Resume`] continues one and refuses a different configuration (apart from
/// `training.steps`).
pub fn train(
    run_dir: &Path,
    config: TrainConfig,
    dataset: &Dataset,
    dataset_path: &Path,
    options: TrainOptions<'_>,
    on_step: &mut dyn FnMut(&StepReport, usize),
) -> Result<TrainSummary> {
    if options.snapshot_every == Some(0) {
        return Err(TrainError::config(
            "training options",
            "snapshot_every",
            "a positive number of steps",
            0,
        ));
    }
    let files = RunFiles::new(run_dir);
    std::fs::create_dir_all(run_dir)
        .map_err(TrainError::io(run_dir, "creating the run directory"))?;
    let exists = files.checkpoint.exists();
    let resume = options.start == RunStart::Resume;
    if exists && !resume {
        return Err(TrainError::checkpoint(
            &files.checkpoint,
            "run directory",
            "a new run directory (or --resume to continue this run)",
            "an existing checkpoint",
        ));
    }
    if resume && !exists {
        return Err(TrainError::checkpoint(
            &files.checkpoint,
            "resume",
            "a checkpoint to continue from",
            "no such file",
        ));
    }
    let mut trainer = Trainer::new(config, dataset, dataset_path, options.device)?;
    let mut last_checkpoint = 0;
    let mut initialisation = None;
    match options.start {
        RunStart::Resume => {
            trainer.restore(&files.checkpoint)?;
            last_checkpoint = trainer.steps_done();
            truncate_metrics(&files, last_checkpoint)?;
        }
        RunStart::Fresh => {
            let _ = std::fs::remove_file(&files.metrics);
        }
        RunStart::InitialisedFrom(model, fresh) => {
            initialisation = Some(trainer.initialise_from_except(model, fresh)?);
            let _ = std::fs::remove_file(&files.metrics);
        }
    }
    write_static(&files, trainer.config(), dataset)?;
    let total = trainer.config().training.steps;
    let (log_every, checkpoint_every) =
        (trainer.config().training.log_every, trainer.config().training.checkpoint_every);
    let mut last = None;
    let mut interrupted = false;
    let save = |trainer: &Trainer| -> Result<()> {
        trainer.save(&files.checkpoint)?;
        crate::plot::write_loss_curve(&files.loss_curve, &read_metrics(&files)?)
    };
    while trainer.steps_done() < total {
        if options.stop.load(Ordering::SeqCst) {
            interrupted = true;
            break;
        }
        let report = trainer.step(last_checkpoint)?;
        if report.step == 1 || report.step % log_every == 0 || report.step == total {
            append_metrics(&files, &report)?;
        }
        on_step(&report, total);
        let snapshot = options.snapshot_every.is_some_and(|n| report.step % n == 0);
        if (report.step % checkpoint_every == 0 || snapshot) && report.step < total {
            save(&trainer)?;
            last_checkpoint = report.step;
        }
        if snapshot && report.step < total {
            write_snapshot(&files, run_dir, report.step)?;
        }
        last = Some(report);
    }
    save(&trainer)?;
    let steps = trainer.steps_done();
    if options.snapshot_every.is_some_and(|n| steps % n == 0) && steps == total {
        write_snapshot(&files, run_dir, steps)?;
    }
    Ok(TrainSummary {
        steps,
        steps_before: trainer.steps_before(),
        interrupted,
        last,
        run_dir: run_dir.to_path_buf(),
        initialisation,
    })
}
