//! Reading a whole published dataset into the dex2hoi dataset format: discover the sequences,
//! read each one in parallel (one bad sequence is reported, never fatal), resample to the
//! target frame rate, extract features and targets, build the object assets and assemble the
//! dataset with its statistics. The [`PrepareReport`] says what was read and what was
//! skipped or failed, and why.

use std::collections::{BTreeMap, BTreeSet};
use std::path::PathBuf;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, OnceLock};

use rayon::prelude::*;

use dex2hoi_data::catalogue::{BPS_RADIUS, BPS_SEED};
use dex2hoi_data::dataset::{BpsSettings, DataLicence, Dataset, Split};
use dex2hoi_data::features::{ObjectAsset, ProcessedSequence, TargetConfig, process_sequence};
use dex2hoi_data::window::resample;
use dex2hoi_data::{Sequence, SequenceObject};
use dex2hoi_repr::bps::DEFAULT_BPS_POINTS;
use dex2hoi_repr::{BpsBasis, Mesh, MeshQuery, Skeleton};

use crate::error::{ImportError, Result};
use crate::{grab, himo, humoto};

pub use crate::source::{
    CentredMesh, Context, HandPoseSource, Item, Outcome, PrepareOptions, Skipped, SourceFormat,
    SplitRule, hash_split, read_prompts, read_split_file,
};

/// What a run read, skipped and failed on.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct PrepareReport {
    /// Sequences found.
    pub found: usize,
    /// Sequences read, per split.
    pub read: BTreeMap<Split, usize>,
    /// Frames written, per split.
    pub frames: BTreeMap<Split, usize>,
    /// Sequences the protocol leaves out (too many objects, not in the split file, ...).
    pub skipped: Vec<Skipped>,
    /// Sequences that could not be read (a missing key, a wrong shape, a truncated file, a
    /// NaN, a refused pickle, a body lying down), with the error.
    pub failed: Vec<Skipped>,
    /// Sequences read with a doubt (feet away from the floor, rig stretch left over).
    pub warnings: Vec<Skipped>,
    /// Distinct objects in the dataset.
    pub objects: usize,
    /// The licence file kept in the dataset.
    pub licence: Option<PathBuf>,
}

impl PrepareReport {
    /// A human-readable summary, one line per skipped or failed sequence.
    pub fn summary(&self) -> String {
        let mut lines = Vec::new();
        let read: usize = self.read.values().sum();
        let splits: Vec<String> = self
            .read
            .iter()
            .map(|(s, n)| {
                format!("{} {n} ({} frames)", s.name(), self.frames.get(s).copied().unwrap_or(0))
            })
            .collect();
        lines.push(format!(
            "found {} sequences: read {read} ({}), skipped {}, failed {}, warnings {}; {} objects",
            self.found,
            if splits.is_empty() { "none".to_string() } else { splits.join(", ") },
            self.skipped.len(),
            self.failed.len(),
            self.warnings.len(),
            self.objects
        ));
        for s in &self.skipped {
            lines.push(format!("skipped {}: {}", s.id, s.reason));
        }
        for s in &self.failed {
            lines.push(format!("failed {}: {}", s.id, s.reason));
        }
        for s in &self.warnings {
            lines.push(format!("warning {}: {}", s.id, s.reason));
        }
        match &self.licence {
            Some(path) => lines.push(format!(
                "licence {}: kept in the dataset, in every run trained on it and every model \
                 packed from one (`dex2hoi model licence`)",
                path.display()
            )),
            None => lines.push(
                "licence: none found beside the data (give it with --licence FILE, so that it \
                 travels with the dataset and the models trained on it)"
                    .to_string(),
            ),
        }
        lines.join("\n")
    }
}

/// A prepared dataset (`None` when no sequence could be read) and the report.
#[derive(Debug)]
pub struct Prepared {
    /// The dataset.
    pub dataset: Option<Dataset>,
    /// What was read, skipped and failed.
    pub report: PrepareReport,
}

/// The BPS radius for a set of objects: the synthetic dataset's 0.25 m ball when every object
/// fits in it, else 1.1 times the largest half-diagonal, rounded up to 5 cm, so that every
/// object lies inside the basis.
pub fn bps_radius<'a>(meshes: impl IntoIterator<Item = &'a Mesh>) -> f32 {
    let largest = meshes
        .into_iter()
        .map(|m| {
            let (lo, hi) = m.bounding_box();
            (hi - lo).length() * 0.5
        })
        .fold(0.0f32, f32::max);
    let needed = (largest * 1.1 / 0.05).ceil() * 0.05;
    needed.max(BPS_RADIUS)
}

fn discover(context: &Context) -> Result<(Vec<Item>, Vec<Skipped>)> {
    match context.options.format {
        SourceFormat::Grab => grab::discover(&context.options),
        SourceFormat::Humoto => humoto::discover(&context.options),
        SourceFormat::Himo => himo::discover(&context.options),
    }
}

fn load(item: &Item, context: &Context) -> Result<Outcome> {
    match context.options.format {
        SourceFormat::Grab => grab::load(item, context),
        SourceFormat::Humoto => humoto::load(item, context),
        SourceFormat::Himo => himo::load(item, context),
    }
}

type QueryCell = Arc<OnceLock<Result<(Mesh, Arc<MeshQuery>), String>>>;

/// The signed-distance query of each object, built once per object name from the first mesh
/// seen under that name.
#[derive(Default)]
struct Queries {
    cells: Mutex<BTreeMap<String, QueryCell>>,
}

impl Queries {
    fn get(&self, object: &SequenceObject) -> Result<Arc<MeshQuery>> {
        let cell = {
            let mut cells = self.cells.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
            cells.entry(object.name.clone()).or_default().clone()
        };
        cell.get_or_init(|| {
            MeshQuery::new(&object.mesh)
                .map(|q| (object.mesh.clone(), Arc::new(q)))
                .map_err(|e| e.to_string())
        })
        .as_ref()
        .map(|(_, q)| q.clone())
        .map_err(|message| {
            ImportError::format(&object.name, "object mesh", "a mesh with faces", message)
        })
    }

    fn meshes(self) -> BTreeMap<String, Mesh> {
        let cells = self.cells.into_inner().unwrap_or_else(std::sync::PoisonError::into_inner);
        cells
            .into_iter()
            .filter_map(|(name, cell)| {
                cell.get().and_then(|r| r.as_ref().ok()).map(|(mesh, _)| (name, mesh.clone()))
            })
            .collect()
    }
}

/// A body is upright when its head stands at least this share of its rest height above the
/// pelvis on the median frame (a body read with the wrong up axis lies down or stands on its
/// head).
pub const UPRIGHT_SHARE: f32 = 0.5;

/// The feet touch the floor (height 0) when the lower foot joint's median height lies in this
/// range (metres): a foot joint sits a few centimetres up; seated or lying clips lift it more.
pub const FLOOR_RANGE: std::ops::RangeInclusive<f32> = -0.10..=0.30;

/// Checks from the data that a read sequence stands up in the project's Y-up world: the head
/// above the pelvis (else an error: the up axis is wrong) and the feet near the floor (else a
/// warning, with the numbers).
pub fn check_posture(sequence: &Sequence) -> Result<Vec<String>> {
    let skeleton = &sequence.skeleton;
    let fk = dex2hoi_repr::fk::forward_kinematics(
        skeleton,
        &sequence.local_rotations,
        &sequence.root_positions,
    )?;
    let rest = skeleton.rest_positions();
    let head = (0..rest.len()).max_by(|&a, &b| rest[a].y.total_cmp(&rest[b].y)).unwrap_or(0);
    let rest_height = rest[head].y - rest[0].y;
    let groups = skeleton.groups();
    let feet: Vec<usize> = groups.left_foot.iter().chain(&groups.right_foot).copied().collect();
    let mut heights = Vec::with_capacity(fk.frames);
    let mut floors = Vec::with_capacity(fk.frames);
    for frame in 0..fk.frames {
        heights.push(fk.position(frame, head).y - fk.position(frame, 0).y);
        floors.push(feet.iter().map(|&j| fk.position(frame, j).y).fold(f32::INFINITY, f32::min));
    }
    let height = median(&mut heights);
    let floor = median(&mut floors);
    // NaN heights (no frame) fail too.
    if height.is_nan() || height < UPRIGHT_SHARE * rest_height {
        return Err(ImportError::format(
            &sequence.source_id,
            "posture",
            format!(
                "the head ({}) above the pelvis by at least {:.2} m on the median frame",
                skeleton.joint_names()[head],
                UPRIGHT_SHARE * rest_height
            ),
            format!(
                "{height:.2} m: the body lies down or stands on its head, so the up axis is most \
                 likely wrong (see --up-axis)"
            ),
        ));
    }
    let mut warnings = Vec::new();
    if !FLOOR_RANGE.contains(&floor) {
        warnings.push(format!(
            "the lower foot is {floor:.2} m above the floor (y = 0) on the median frame, \
             expected {:.2} to {:.2} m: check the up axis and the root translation",
            FLOOR_RANGE.start(),
            FLOOR_RANGE.end()
        ));
    }
    Ok(warnings)
}

fn median(values: &mut [f32]) -> f32 {
    if values.is_empty() {
        return f32::NAN;
    }
    values.sort_by(f32::total_cmp);
    values[values.len() / 2]
}

/// One sequence read into features, with its warnings; or the reason it was skipped.
type ReadOne = std::result::Result<(ProcessedSequence, Vec<String>), String>;

/// Reads one sequence into features.
fn read_one(
    item: &Item,
    context: &Context,
    queries: &Queries,
    config: &TargetConfig,
) -> Result<ReadOne> {
    let (sequence, mut warnings) = match load(item, context)? {
        Outcome::Sequence { sequence, warnings } => (*sequence, warnings),
        Outcome::Skipped(reason) => return Ok(Err(reason)),
    };
    warnings.extend(check_posture(&sequence)?);
    let fps = context.options.fps;
    let sequence =
        if (sequence.fps - fps).abs() > 1e-3 { resample(&sequence, fps)? } else { sequence };
    let object_queries: Vec<Arc<MeshQuery>> =
        sequence.objects.iter().map(|o| queries.get(o)).collect::<Result<_>>()?;
    let refs: Vec<&MeshQuery> = object_queries.iter().map(Arc::as_ref).collect();
    Ok(Ok((process_sequence(&sequence, &refs, config)?, warnings)))
}

/// Reads a published dataset into a dex2hoi dataset. `progress(done, total)` is called as
/// sequences finish (from several threads).
pub fn prepare(
    options: PrepareOptions,
    progress: &(dyn Fn(usize, usize) + Sync),
) -> Result<Prepared> {
    if !(options.fps > 0.0 && options.fps <= 240.0) {
        return Err(ImportError::invalid("--fps", "a frame rate in (0, 240]", options.fps));
    }
    if !options.root.is_dir() {
        return Err(ImportError::Io {
            path: options.root.clone(),
            source: std::io::Error::new(std::io::ErrorKind::NotFound, "not a directory"),
        });
    }
    let context = Context::new(options)?;
    let (items, mut skipped) = discover(&context)?;
    let total = items.len();
    let done = AtomicUsize::new(0);
    let queries = Queries::default();
    let config = TargetConfig::with_mixture_targets(context.options.mixture_targets);
    let results: Vec<Result<ReadOne>> = items
        .par_iter()
        .map(|item| {
            let result = read_one(item, &context, &queries, &config);
            progress(done.fetch_add(1, Ordering::Relaxed) + 1, total);
            result
        })
        .collect();
    let mut report = PrepareReport { found: total + skipped.len(), ..Default::default() };
    let mut splits: BTreeMap<Split, Vec<ProcessedSequence>> = BTreeMap::new();
    for (item, result) in items.iter().zip(results) {
        match result {
            Ok(Ok((sequence, warnings))) => {
                report.warnings.extend(
                    warnings.into_iter().map(|reason| Skipped { id: item.id.clone(), reason }),
                );
                splits.entry(item.split).or_default().push(sequence)
            }
            Ok(Err(reason)) => skipped.push(Skipped { id: item.id.clone(), reason }),
            Err(error) => {
                report.failed.push(Skipped { id: item.id.clone(), reason: error.to_string() })
            }
        }
    }
    report.skipped = skipped;
    for (split, sequences) in &splits {
        report.read.insert(*split, sequences.len());
        report.frames.insert(*split, sequences.iter().map(|s| s.frames).sum());
    }
    if splits.is_empty() {
        return Ok(Prepared { dataset: None, report });
    }
    // Only the objects of sequences that made it into the dataset.
    let used: BTreeSet<String> =
        splits.values().flatten().flat_map(|s| s.object_names.iter().flatten().cloned()).collect();
    let meshes: Vec<(String, Mesh)> =
        queries.meshes().into_iter().filter(|(name, _)| used.contains(name)).collect();
    let radius = bps_radius(meshes.iter().map(|(_, m)| m));
    let basis = BpsBasis::new(DEFAULT_BPS_POINTS, radius, BPS_SEED)?;
    let assets: Vec<ObjectAsset> = meshes
        .into_par_iter()
        .enumerate()
        .map(|(k, (name, mesh))| Ok(ObjectAsset::new(&name, mesh, &basis, k as u64)?))
        .collect::<Result<_>>()?;
    report.objects = assets.len();
    let bps = BpsSettings { points: DEFAULT_BPS_POINTS, radius, seed: BPS_SEED };
    let skeleton = Skeleton::builtin(context.options.format.skeleton_kind());
    let mut dataset = Dataset::assemble(
        context.options.format.name(),
        &skeleton,
        context.options.fps,
        splits,
        assets,
        bps,
        None,
        context.options.mixture_targets,
    )?
    .with_typical_start_pose()?;
    report.licence = context.options.licence_file();
    dataset.manifest.licence = report.licence.as_deref().map(DataLicence::read).transpose()?;
    Ok(Prepared { dataset: Some(dataset), report })
}

#[cfg(test)]
mod tests {
    use glam::Vec3;

    use super::*;

    #[test]
    fn bps_radius_holds_every_object() {
        let cube = |half: f32| {
            let v = [
                Vec3::new(-half, -half, -half),
                Vec3::new(half, half, half),
                Vec3::new(half, -half, half),
            ];
            Mesh::new(v.to_vec(), vec![[0, 1, 2]], "cube").unwrap()
        };
        assert_eq!(bps_radius([&cube(0.05)]), BPS_RADIUS);
        let big = cube(0.5);
        let radius = bps_radius([&cube(0.05), &big]);
        assert!(radius >= 0.5 * 3f32.sqrt() && radius < 1.05, "{radius}");
    }
}
