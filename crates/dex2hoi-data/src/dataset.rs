//! The on-disk dataset format (documented in `docs/FORMATS.md`): a directory with a JSON
//! manifest, one safetensors file and one JSON file of texts per split, the object assets and
//! the normalisation statistics. Every file is written atomically (temporary file, rename).

use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};

use candle_core::{DType, Device, Tensor};
use glam::Vec3;
use serde::{Deserialize, Serialize};

use dex2hoi_repr::object_repr::MIXTURE_RANGE;
use dex2hoi_repr::{Mesh, SkeletonKind, SurfaceSamples};

use crate::error::{DataError, Result};
use crate::features::{MixtureTargets, ObjectAsset, ProcessedSequence};
use crate::files::{io_error, temporary_path, write_atomically};
use crate::layout::{FeatureLayout, OBJECT_FEATURE_SIZE, asset_index, slot_assets};
use crate::sequence::MAX_OBJECTS;
use crate::start::StartPose;

/// The version of the format this code writes. Version 2 added each sequence's rest offsets
/// (`rest_offsets`); version 3 each sequence's held-out descriptions (`held_out_texts`, absent
/// when there are none); version 4 the manifest's `start_pose` (real data); version 5 the
/// manifest's `mixture_targets`.
pub const FORMAT_VERSION: u32 = 5;
/// The oldest version this code reads: versions 2 to 4 read as version 5 without what later
/// versions added; version 1 files are refused (prepare them again).
pub const OLDEST_READABLE_FORMAT: u32 = 2;

/// The least standard deviation a feature channel is normalised with: channels that never
/// change (the legs of a standing character) must not blow up.
pub const STD_FLOOR: f32 = 0.01;

/// `Manifest::source` of the procedural dataset (`dex2hoi-synth`).
pub const PROCEDURAL_SOURCE: &str = "synth";

/// A dataset split.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Split {
    /// Training sequences.
    Train,
    /// Held-out test sequences.
    Test,
}

impl Split {
    /// Both splits.
    pub const ALL: [Split; 2] = [Split::Train, Split::Test];

    /// The file stem of the split.
    pub fn name(self) -> &'static str {
        match self {
            Split::Train => "train",
            Split::Test => "test",
        }
    }
}

/// Counts of one split.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SplitSummary {
    /// Number of sequences.
    pub sequences: usize,
    /// Number of frames over all sequences.
    pub frames: usize,
    /// Sequences per action label.
    pub actions: BTreeMap<String, usize>,
    /// Sequences per object name (a two-object sequence counts for both).
    pub objects: BTreeMap<String, usize>,
}

/// BPS settings stored with a dataset.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct BpsSettings {
    /// Basis points.
    pub points: usize,
    /// Ball radius in metres.
    pub radius: f32,
    /// Seed of the basis.
    pub seed: u64,
}

/// `manifest.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Manifest {
    /// [`FORMAT_VERSION`] of the writer.
    pub format_version: u32,
    /// Where the data come from ([`PROCEDURAL_SOURCE`], `grab`, ...).
    pub source: String,
    /// `smplx52` or `mixamo65`.
    pub skeleton: String,
    /// Joints `J`.
    pub joints: usize,
    /// Frames per second.
    pub fps: f32,
    /// `6J + 3`.
    pub body_feature_size: usize,
    /// 18.
    pub object_feature_size: usize,
    /// `6J + 3 + 18`, the width of one stream.
    pub stream_feature_size: usize,
    /// Hand joints per frame in `hand_distances` (left hand's, then right hand's).
    pub hand_joints: usize,
    /// BPS settings.
    pub bps: BpsSettings,
    /// Names of the objects in `objects.safetensors`, in index order.
    pub objects: Vec<String>,
    /// Per split counts.
    pub splits: BTreeMap<Split, SplitSummary>,
    /// The generator's seed, when generated.
    pub seed: Option<u64>,
    /// The rule the mixture targets were drawn by (format 5; older datasets: the paper's).
    #[serde(default = "MixtureTargets::of_older_formats")]
    pub mixture_targets: MixtureTargets,
    /// The pose generation starts from, for data of real motion capture (see
    /// [`Manifest::start_pose`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub start_pose: Option<StartPose>,
    /// The licence file found beside the source data, which travels with everything made from
    /// them (runs, packed models).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub licence: Option<DataLicence>,
}

/// A licence file of the source data, kept whole inside the manifest: every run trained on the
/// data copies the manifest, and every model packed from a run carries it in its metadata, so
/// the licence reaches whoever receives the model (HUMOTO's Adobe Research License asks that
/// redistribution come with a copy of it).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DataLicence {
    /// The file's name as found beside the data.
    pub file_name: String,
    /// The file's bytes, base64 (a licence may be a PDF).
    pub base64: String,
}

impl DataLicence {
    /// Reads a licence file.
    pub fn read(path: &Path) -> Result<Self> {
        let bytes = std::fs::read(path).map_err(io_error(path, "reading the licence"))?;
        let file_name = path
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .ok_or_else(|| DataError::invalid(path.display(), "a licence file", "no file name"))?;
        Ok(Self { file_name, base64: base64::encode(bytes) })
    }

    /// The file's bytes.
    pub fn bytes(&self) -> Result<Vec<u8>> {
        base64::decode(&self.base64).map_err(|e| {
            DataError::invalid(format!("licence {}", self.file_name), "base64 bytes", e)
        })
    }
}

/// One sequence's texts and labels, in `<split>.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SequenceInfo {
    /// Source id.
    pub source_id: String,
    /// Descriptions.
    pub texts: Vec<String>,
    /// Descriptions in phrasings held out of training (see
    /// [`ProcessedSequence::held_out_texts`]).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub held_out_texts: Vec<String>,
    /// Action label.
    pub action: Option<String>,
    /// Object names per slot (`null` for an empty slot).
    pub objects: [Option<String>; MAX_OBJECTS],
}

/// Per-channel statistics of the stream features (`[6J + 3 + 18]`).
#[derive(Debug, Clone, PartialEq)]
pub struct FeatureStats {
    /// Means.
    pub mean: Vec<f32>,
    /// Standard deviations, at least [`STD_FLOOR`].
    pub std: Vec<f32>,
}

impl FeatureStats {
    /// Statistics over sequences: body channels over every frame, object channels over the
    /// frames of present objects. The mixture logits keep mean 0 and std 1: they are centred
    /// logarithms in a fixed range, read through a softmax, and that way the normalised
    /// features keep them as logits.
    pub fn compute(sequences: &[ProcessedSequence], joints: usize) -> Self {
        let layout = FeatureLayout::new(joints);
        let body = layout.body_width();
        let width = layout.stream_width();
        let mut sum = vec![0.0f64; width];
        let mut sum_sq = vec![0.0f64; width];
        let mut count = vec![0.0f64; width];
        for s in sequences {
            for t in 0..s.frames {
                for (k, &v) in s.body[layout.body_row(t)].iter().enumerate() {
                    sum[k] += f64::from(v);
                    sum_sq[k] += f64::from(v) * f64::from(v);
                    count[k] += 1.0;
                }
                for slot in 0..MAX_OBJECTS {
                    if !s.object_present[slot] {
                        continue;
                    }
                    for (k, &v) in s.objects[layout.object_row(t, slot)].iter().enumerate() {
                        sum[body + k] += f64::from(v);
                        sum_sq[body + k] += f64::from(v) * f64::from(v);
                        count[body + k] += 1.0;
                    }
                }
            }
        }
        let mut mean = vec![0.0f32; width];
        let mut std = vec![1.0f32; width];
        let mixture_channels = layout.object_part_range(MIXTURE_RANGE);
        for k in 0..width {
            let mixture = mixture_channels.contains(&k);
            if count[k] > 0.0 && !mixture {
                let m = sum[k] / count[k];
                mean[k] = m as f32;
                std[k] = ((sum_sq[k] / count[k] - m * m).max(0.0).sqrt() as f32).max(STD_FLOOR);
            }
        }
        Self { mean, std }
    }
}

/// A dataset in memory.
#[derive(Debug, Clone)]
pub struct Dataset {
    /// The manifest.
    pub manifest: Manifest,
    /// Sequences per split.
    pub splits: BTreeMap<Split, Vec<ProcessedSequence>>,
    /// Object assets in manifest order.
    pub objects: Vec<ObjectAsset>,
    /// Normalisation statistics (over the training split).
    pub stats: FeatureStats,
}

impl Dataset {
    /// Assembles a dataset from processed sequences: the statistics over the training split
    /// (the test split when there is no training split), the per-split counts and the
    /// manifest. `objects` are the assets in manifest order; `seed` is the generator's seed
    /// (`None` for data read from files).
    pub fn assemble(
        source: &str,
        skeleton: &dex2hoi_repr::Skeleton,
        fps: f32,
        splits: BTreeMap<Split, Vec<ProcessedSequence>>,
        objects: Vec<ObjectAsset>,
        bps: BpsSettings,
        seed: Option<u64>,
        mixture_targets: MixtureTargets,
    ) -> Result<Self> {
        let joints = skeleton.joint_count();
        let statistics_split = match (splits.get(&Split::Train), splits.get(&Split::Test)) {
            (Some(train), _) if !train.is_empty() => train,
            (_, Some(test)) if !test.is_empty() => test,
            _ => return Err(DataError::invalid(source, "at least one sequence", 0)),
        };
        let stats = FeatureStats::compute(statistics_split, joints);
        let summaries = splits
            .iter()
            .map(|(split, sequences)| {
                let mut actions = BTreeMap::new();
                let mut object_counts = BTreeMap::new();
                for s in sequences {
                    *actions.entry(s.action.clone().unwrap_or_default()).or_insert(0) += 1;
                    for name in s.object_names.iter().flatten() {
                        *object_counts.entry(name.clone()).or_insert(0) += 1;
                    }
                }
                let frames = sequences.iter().map(|s| s.frames).sum();
                let summary = SplitSummary {
                    sequences: sequences.len(),
                    frames,
                    actions,
                    objects: object_counts,
                };
                (*split, summary)
            })
            .collect();
        let groups = skeleton.groups();
        let layout = FeatureLayout::new(joints);
        let manifest = Manifest {
            format_version: FORMAT_VERSION,
            source: source.into(),
            skeleton: skeleton.kind().name().into(),
            joints,
            fps,
            body_feature_size: layout.body_width(),
            object_feature_size: layout.object_width(),
            stream_feature_size: layout.stream_width(),
            hand_joints: groups.left_hand.len() + groups.right_hand.len(),
            bps,
            objects: objects.iter().map(|a| a.name.clone()).collect(),
            splits: summaries,
            seed,
            mixture_targets,
            start_pose: None,
            licence: None,
        };
        Ok(Self { manifest, splits, objects, stats })
    }

    /// Stores the training split's most typical first frame as the pose generations start
    /// from ([`StartPose::typical_first_frame`]; the test split's when there is no training
    /// split): for real motion capture, whose character and stance the built-in one does not
    /// match.
    pub fn with_typical_start_pose(mut self) -> Result<Self> {
        let skeleton = self.manifest.builtin_skeleton()?;
        let sequences = match self.splits.get(&Split::Train) {
            Some(train) if !train.is_empty() => train,
            _ => self.splits.get(&Split::Test).map_or(&[][..], Vec::as_slice),
        };
        self.manifest.start_pose = Some(StartPose::typical_first_frame(sequences, &skeleton)?);
        Ok(self)
    }

    /// The layout of the dataset's features.
    pub fn layout(&self) -> FeatureLayout {
        self.manifest.layout()
    }

    /// The asset of the object named `name` (see [`asset_index`]).
    pub fn asset(&self, name: &str) -> Option<&ObjectAsset> {
        asset_index(&self.objects, name).map(|index| &self.objects[index])
    }

    /// The index into [`Dataset::objects`] of each object slot of a sequence (see
    /// [`slot_assets`]).
    pub fn slot_assets(
        &self,
        sequence: &ProcessedSequence,
    ) -> Result<[Option<usize>; MAX_OBJECTS]> {
        slot_assets(&self.objects, sequence)
    }
}

/// The bodies of a split's sequences (see [`Dataset::bodies`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BodySummary {
    /// Distinct rest skeletons.
    pub distinct: usize,
    /// The least and the greatest rest height (the vertical extent of the rest pose's joints,
    /// metres).
    pub shortest: f32,
    /// See `shortest`.
    pub tallest: f32,
}

impl Dataset {
    /// How many distinct bodies a split's sequences have, and their range of rest heights
    /// (zeros for an empty or absent split).
    pub fn bodies(&self, split: Split) -> Result<BodySummary> {
        let topology = self.manifest.builtin_skeleton()?;
        let sequences = self.splits.get(&split).map_or(&[][..], Vec::as_slice);
        let mut distinct: Vec<&[Vec3]> = Vec::new();
        for s in sequences {
            if !distinct.contains(&s.rest_offsets.as_slice()) {
                distinct.push(&s.rest_offsets);
            }
        }
        // Each distinct body's rest height, once.
        let heights = distinct
            .iter()
            .map(|offsets| {
                let rest = topology.with_rest_offsets(offsets.to_vec())?.rest_positions();
                let top = rest.iter().map(|p| p.y).fold(f32::NEG_INFINITY, f32::max);
                let bottom = rest.iter().map(|p| p.y).fold(f32::INFINITY, f32::min);
                Ok(top - bottom)
            })
            .collect::<Result<Vec<f32>>>()?;
        let shortest = heights.iter().copied().reduce(f32::min).unwrap_or(0.0);
        let tallest = heights.iter().copied().reduce(f32::max).unwrap_or(0.0);
        Ok(BodySummary { distinct: distinct.len(), shortest, tallest })
    }
}

impl Manifest {
    /// The layout of the dataset's features (from its joint count).
    pub fn layout(&self) -> FeatureLayout {
        FeatureLayout::new(self.joints)
    }

    /// The built-in skeleton of the dataset's kind: the topology every sequence shares, and the
    /// body generated motion is posed on. Each sequence's own body is
    /// [`ProcessedSequence::skeleton`].
    pub fn builtin_skeleton(&self) -> Result<dex2hoi_repr::Skeleton> {
        Ok(dex2hoi_repr::Skeleton::builtin(SkeletonKind::from_name(&self.skeleton)?))
    }

    /// The pose a generation from scratch starts from, on [`Manifest::builtin_skeleton`]:
    /// the dataset's own (written by `data prepare`), else the default character's stance on
    /// the SMPL-X body. A Mixamo dataset without one was prepared before it had one.
    pub fn start_pose(&self) -> Result<StartPose> {
        let skeleton = self.builtin_skeleton()?;
        let start = match &self.start_pose {
            Some(start) => start.clone(),
            None if skeleton.kind() == SkeletonKind::Smplx52 => StartPose::smplx_standing(),
            None => {
                return Err(DataError::invalid(
                    format!("the manifest of {} data on {}", self.source, self.skeleton),
                    "a start pose of the data's character (dataset format 4: run `dex2hoi data \
                     prepare` again)",
                    format!("none (format {})", self.format_version),
                ));
            }
        };
        start.check(&skeleton, "the manifest's start_pose")?;
        Ok(start)
    }
}

fn save_tensors(path: &Path, tensors: &HashMap<String, Tensor>) -> Result<()> {
    let temporary = temporary_path(path);
    candle_core::safetensors::save(tensors, &temporary)
        .map_err(|e| DataError::format(&temporary, "safetensors", "a writable file", e))?;
    std::fs::rename(&temporary, path).map_err(io_error(path, "renaming into place"))
}

fn f32_tensor(values: Vec<f32>, shape: &[usize]) -> Result<Tensor> {
    Ok(Tensor::from_vec(values, shape, &Device::Cpu)?)
}

fn concat<F: Fn(&ProcessedSequence) -> &[f32]>(
    sequences: &[ProcessedSequence],
    field: F,
) -> Vec<f32> {
    sequences.iter().flat_map(|s| field(s).iter().copied()).collect()
}

impl Dataset {
    /// Writes the dataset into `dir` (created if needed).
    pub fn save(&self, dir: &Path) -> Result<()> {
        std::fs::create_dir_all(dir).map_err(io_error(dir, "creating the dataset directory"))?;
        let m = &self.manifest;
        let hand = m.hand_joints;
        let object_index = |name: &Option<String>| -> i64 {
            name.as_ref()
                .and_then(|n| m.objects.iter().position(|o| o == n))
                .map_or(-1, |i| i as i64)
        };
        for (split, sequences) in &self.splits {
            let frames: usize = sequences.iter().map(|s| s.frames).sum();
            let mut offsets = vec![0i64];
            for s in sequences {
                offsets.push(offsets[offsets.len() - 1] + s.frames as i64);
            }
            let n = sequences.len();
            let mut tensors = HashMap::new();
            tensors.insert(
                "sequence_offsets".to_string(),
                Tensor::from_vec(offsets, n + 1, &Device::Cpu)?,
            );
            tensors.insert(
                "body".into(),
                f32_tensor(concat(sequences, |s| &s.body), &[frames, m.body_feature_size])?,
            );
            tensors.insert(
                "objects".into(),
                f32_tensor(
                    concat(sequences, |s| &s.objects),
                    &[frames, MAX_OBJECTS, OBJECT_FEATURE_SIZE],
                )?,
            );
            tensors.insert(
                "joint_positions".into(),
                f32_tensor(concat(sequences, |s| &s.joint_positions), &[frames, m.joints, 3])?,
            );
            tensors.insert(
                "hand_distances".into(),
                f32_tensor(concat(sequences, |s| &s.hand_distances), &[frames, MAX_OBJECTS, hand])?,
            );
            tensors.insert(
                "hand_contact".into(),
                f32_tensor(concat(sequences, |s| &s.hand_contact), &[frames, MAX_OBJECTS, 2])?,
            );
            tensors.insert(
                "foot_contact".into(),
                f32_tensor(concat(sequences, |s| &s.foot_contact), &[frames, 4])?,
            );
            tensors.insert(
                "object_rotations".into(),
                f32_tensor(
                    concat(sequences, |s| &s.object_rotations),
                    &[frames, MAX_OBJECTS, 3, 3],
                )?,
            );
            tensors.insert(
                "object_positions".into(),
                f32_tensor(concat(sequences, |s| &s.object_positions), &[frames, MAX_OBJECTS, 3])?,
            );
            let indices: Vec<i64> =
                sequences.iter().flat_map(|s| s.object_names.iter().map(object_index)).collect();
            tensors.insert(
                "object_index".into(),
                Tensor::from_vec(indices, (n, MAX_OBJECTS), &Device::Cpu)?,
            );
            let starts: Vec<f32> = sequences.iter().flat_map(|s| s.root_start.to_array()).collect();
            tensors.insert("root_start".into(), f32_tensor(starts, &[n, 3])?);
            let rest: Vec<f32> = sequences
                .iter()
                .flat_map(|s| s.rest_offsets.iter().flat_map(|o| o.to_array()))
                .collect();
            tensors.insert("rest_offsets".into(), f32_tensor(rest, &[n, m.joints, 3])?);
            save_tensors(&dir.join(format!("{}.safetensors", split.name())), &tensors)?;
            let infos: Vec<SequenceInfo> = sequences
                .iter()
                .map(|s| SequenceInfo {
                    source_id: s.source_id.clone(),
                    texts: s.texts.clone(),
                    held_out_texts: s.held_out_texts.clone(),
                    action: s.action.clone(),
                    objects: s.object_names.clone(),
                })
                .collect();
            let json = serde_json::to_vec_pretty(&infos)
                .map_err(|e| DataError::invalid("texts", "serialisable texts", e))?;
            write_atomically(&dir.join(format!("{}.json", split.name())), &json)?;
        }
        let mut tensors = HashMap::new();
        let stack = |f: &dyn Fn(&ObjectAsset) -> Vec<f32>, per: usize| -> Result<Tensor> {
            let values: Vec<f32> = self.objects.iter().flat_map(f).collect();
            f32_tensor(values, &[self.objects.len(), per, 3])
        };
        tensors.insert(
            "bps".to_string(),
            stack(&|o| o.bps.iter().flat_map(|v| v.to_array()).collect(), m.bps.points)?,
        );
        let samples = self.objects.first().map_or(0, |o| o.samples.points.len());
        tensors.insert(
            "surface_points".into(),
            stack(&|o| o.samples.points.iter().flat_map(|v| v.to_array()).collect(), samples)?,
        );
        tensors.insert(
            "surface_normals".into(),
            stack(&|o| o.samples.normals.iter().flat_map(|v| v.to_array()).collect(), samples)?,
        );
        for object in &self.objects {
            let vertices: Vec<f32> =
                object.mesh.vertices.iter().flat_map(|v| v.to_array()).collect();
            let faces: Vec<i64> = object.mesh.faces.iter().flat_map(|f| f.map(i64::from)).collect();
            tensors.insert(
                format!("vertices.{}", object.name),
                f32_tensor(vertices, &[object.mesh.vertices.len(), 3])?,
            );
            tensors.insert(
                format!("faces.{}", object.name),
                Tensor::from_vec(faces, (object.mesh.faces.len(), 3), &Device::Cpu)?,
            );
        }
        save_tensors(&dir.join("objects.safetensors"), &tensors)?;
        let mut stats = HashMap::new();
        let width = self.stats.mean.len();
        stats.insert("mean".to_string(), f32_tensor(self.stats.mean.clone(), &[width])?);
        stats.insert("std".to_string(), f32_tensor(self.stats.std.clone(), &[width])?);
        save_tensors(&dir.join("stats.safetensors"), &stats)?;
        // The manifest last: a directory with a manifest is complete.
        let json = serde_json::to_vec_pretty(m)
            .map_err(|e| DataError::invalid("manifest", "serialisable", e))?;
        write_atomically(&dir.join("manifest.json"), &json)
    }

    /// Reads the manifest of a dataset directory.
    pub fn read_manifest(dir: &Path) -> Result<Manifest> {
        let path = dir.join("manifest.json");
        let bytes = std::fs::read(&path).map_err(io_error(&path, "reading the manifest"))?;
        let manifest: Manifest = serde_json::from_slice(&bytes).map_err(|e| {
            DataError::format(&path, "manifest", "the dex2hoi dataset manifest (JSON)", e)
        })?;
        if !(OLDEST_READABLE_FORMAT..=FORMAT_VERSION).contains(&manifest.format_version) {
            let advice = if manifest.format_version < OLDEST_READABLE_FORMAT {
                "written by an older dex2hoi (without each sequence's rest skeleton): run \
                 `dex2hoi data prepare` or `dex2hoi data synth` again"
            } else {
                "written by a newer dex2hoi"
            };
            return Err(DataError::format(
                &path,
                "format_version",
                format!("{OLDEST_READABLE_FORMAT} to {FORMAT_VERSION}"),
                format!("{}, {advice}", manifest.format_version),
            ));
        }
        SkeletonKind::from_name(&manifest.skeleton)
            .map_err(|e| DataError::format(&path, "skeleton", "smplx52 or mixamo65", e))?;
        if manifest.start_pose.is_some() {
            manifest.start_pose().map_err(|e| {
                DataError::format(&path, "start_pose", "a standing pose on the skeleton", e)
            })?;
        }
        // Every reader indexes features through the layout of the joint count, so widths that
        // disagree with it would be read wrongly rather than fail.
        let layout = manifest.layout();
        let widths = (
            manifest.body_feature_size,
            manifest.object_feature_size,
            manifest.stream_feature_size,
        );
        let expected = (layout.body_width(), layout.object_width(), layout.stream_width());
        if widths != expected {
            return Err(DataError::format(
                &path,
                "feature sizes (body, object, stream)",
                format!("{expected:?} for {} joints", manifest.joints),
                format!("{widths:?}"),
            ));
        }
        Ok(manifest)
    }

    /// Loads a whole dataset directory, checking every array's shape against the manifest.
    pub fn load(dir: &Path) -> Result<Self> {
        let manifest = Self::read_manifest(dir)?;
        let m = &manifest;
        let load = |name: &str| -> Result<(PathBuf, HashMap<String, Tensor>)> {
            let path = dir.join(name);
            let tensors = candle_core::safetensors::load(&path, &Device::Cpu).map_err(|e| {
                DataError::format(&path, "safetensors", "a readable safetensors file", e)
            })?;
            Ok((path, tensors))
        };
        let get = |path: &Path,
                   tensors: &HashMap<String, Tensor>,
                   key: &str,
                   shape: &[usize]|
         -> Result<Tensor> {
            let tensor = tensors.get(key).ok_or_else(|| {
                DataError::format(path, key, format!("an array of shape {shape:?}"), "nothing")
            })?;
            if tensor.dims() != shape {
                return Err(DataError::format(
                    path,
                    key,
                    format!("shape {shape:?}"),
                    format!("{:?}", tensor.dims()),
                ));
            }
            Ok(tensor.clone())
        };
        let values = |t: Tensor| -> Result<Vec<f32>> {
            Ok(t.to_dtype(DType::F32)?.flatten_all()?.to_vec1::<f32>()?)
        };
        let mut splits = BTreeMap::new();
        for split in m.splits.keys() {
            let (path, tensors) = load(&format!("{}.safetensors", split.name()))?;
            let text_path = dir.join(format!("{}.json", split.name()));
            let bytes = std::fs::read(&text_path).map_err(io_error(&text_path, "reading texts"))?;
            let infos: Vec<SequenceInfo> = serde_json::from_slice(&bytes).map_err(|e| {
                DataError::format(&text_path, "texts", "a JSON list of sequence infos", e)
            })?;
            let n = m.splits[split].sequences;
            if infos.len() != n {
                return Err(DataError::format(&text_path, "sequences", n.to_string(), infos.len()));
            }
            let offsets_tensor = get(&path, &tensors, "sequence_offsets", &[n + 1])?;
            let offsets: Vec<i64> = offsets_tensor.to_dtype(DType::I64)?.to_vec1()?;
            let frames = offsets.last().copied().unwrap_or(0) as usize;
            if offsets.windows(2).any(|w| w[1] <= w[0]) || offsets[0] != 0 {
                return Err(DataError::format(
                    &path,
                    "sequence_offsets",
                    "increasing offsets from 0",
                    format!("{offsets:?}"),
                ));
            }
            let hand = m.hand_joints;
            let body = values(get(&path, &tensors, "body", &[frames, m.body_feature_size])?)?;
            let objects = values(get(
                &path,
                &tensors,
                "objects",
                &[frames, MAX_OBJECTS, OBJECT_FEATURE_SIZE],
            )?)?;
            let joints = values(get(&path, &tensors, "joint_positions", &[frames, m.joints, 3])?)?;
            let distances =
                values(get(&path, &tensors, "hand_distances", &[frames, MAX_OBJECTS, hand])?)?;
            let contact = values(get(&path, &tensors, "hand_contact", &[frames, MAX_OBJECTS, 2])?)?;
            let feet = values(get(&path, &tensors, "foot_contact", &[frames, 4])?)?;
            let rotations =
                values(get(&path, &tensors, "object_rotations", &[frames, MAX_OBJECTS, 3, 3])?)?;
            let positions =
                values(get(&path, &tensors, "object_positions", &[frames, MAX_OBJECTS, 3])?)?;
            let starts = values(get(&path, &tensors, "root_start", &[n, 3])?)?;
            let rest = values(get(&path, &tensors, "rest_offsets", &[n, m.joints, 3])?)?;
            let topology = m.builtin_skeleton()?;
            let mut sequences = Vec::with_capacity(n);
            for (i, info) in infos.into_iter().enumerate() {
                let (a, b) = (offsets[i] as usize, offsets[i + 1] as usize);
                let slice = |v: &[f32], per: usize| v[a * per..b * per].to_vec();
                let object_present = std::array::from_fn(|k| info.objects[k].is_some());
                sequences.push(ProcessedSequence {
                    frames: b - a,
                    joints: m.joints,
                    body: slice(&body, m.body_feature_size),
                    objects: slice(&objects, m.layout().objects_width()),
                    object_present,
                    object_names: info.objects,
                    joint_positions: slice(&joints, m.joints * 3),
                    hand_distances: slice(&distances, MAX_OBJECTS * hand),
                    hand_contact: slice(&contact, MAX_OBJECTS * 2),
                    foot_contact: slice(&feet, 4),
                    object_rotations: slice(&rotations, MAX_OBJECTS * 9),
                    object_positions: slice(&positions, MAX_OBJECTS * 3),
                    root_start: Vec3::from_slice(&starts[i * 3..i * 3 + 3]),
                    rest_offsets: rest[i * m.joints * 3..(i + 1) * m.joints * 3]
                        .chunks_exact(3)
                        .map(Vec3::from_slice)
                        .collect(),
                    texts: info.texts,
                    held_out_texts: info.held_out_texts,
                    action: info.action,
                    source_id: info.source_id,
                });
            }
            // Each body must be usable by FK (finite offsets), checked once here.
            for s in &sequences {
                s.skeleton(&topology).map_err(|e| {
                    DataError::format(&path, "rest_offsets", "finite rest offsets", e)
                })?;
            }
            splits.insert(*split, sequences);
        }
        let (path, tensors) = load("objects.safetensors")?;
        let k = m.objects.len();
        let bps = values(get(&path, &tensors, "bps", &[k, m.bps.points, 3])?)?;
        let samples =
            tensors.get("surface_points").map_or(0, |t| t.dims().get(1).copied().unwrap_or(0));
        let points = values(get(&path, &tensors, "surface_points", &[k, samples, 3])?)?;
        let normals = values(get(&path, &tensors, "surface_normals", &[k, samples, 3])?)?;
        let vec3s = |v: &[f32]| v.chunks_exact(3).map(Vec3::from_slice).collect::<Vec<_>>();
        let mut objects = Vec::with_capacity(k);
        for (i, name) in m.objects.iter().enumerate() {
            let vertex_key = format!("vertices.{name}");
            let vertices = tensors.get(&vertex_key).ok_or_else(|| {
                DataError::format(&path, &vertex_key, "an array (V, 3)", "nothing")
            })?;
            let face_key = format!("faces.{name}");
            let faces = tensors
                .get(&face_key)
                .ok_or_else(|| DataError::format(&path, &face_key, "an array (F, 3)", "nothing"))?;
            let faces: Vec<i64> = faces.to_dtype(DType::I64)?.flatten_all()?.to_vec1()?;
            let faces =
                faces.chunks_exact(3).map(|f| [f[0] as u32, f[1] as u32, f[2] as u32]).collect();
            let mesh = Mesh::new(
                vec3s(&values(vertices.clone())?),
                faces,
                &format!("{}[{name}]", path.display()),
            )?;
            objects.push(ObjectAsset {
                name: name.clone(),
                mesh,
                bps: vec3s(&bps[i * m.bps.points * 3..(i + 1) * m.bps.points * 3]),
                samples: SurfaceSamples {
                    points: vec3s(&points[i * samples * 3..(i + 1) * samples * 3]),
                    normals: vec3s(&normals[i * samples * 3..(i + 1) * samples * 3]),
                },
            });
        }
        let (path, tensors) = load("stats.safetensors")?;
        let width = m.stream_feature_size;
        let stats = FeatureStats {
            mean: values(get(&path, &tensors, "mean", &[width])?)?,
            std: values(get(&path, &tensors, "std", &[width])?)?,
        };
        Ok(Self { manifest, splits, objects, stats })
    }
}
