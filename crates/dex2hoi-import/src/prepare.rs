//! Reading a whole published dataset into the dex2hoi dataset format: discover the sequences,
//! read each one in parallel (one bad sequence is reported, never fatal), resample to the
//! target frame rate, extract features and targets, build the object assets and assemble the
//! dataset with its statistics. The [`PrepareReport`] says what was read and what was
//! skipped or failed, and why.

use std::collections::{BTreeMap, BTreeSet, HashMap};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, OnceLock};

use glam::{Mat3, Vec3};
use rayon::prelude::*;

use dex2hoi_data::dataset::{BpsSettings, Dataset, Split};
use dex2hoi_data::features::{ObjectAsset, ProcessedSequence, TargetConfig, process_sequence};
use dex2hoi_data::synth::{BPS_RADIUS, BPS_SEED};
use dex2hoi_data::window::resample;
use dex2hoi_data::{Sequence, SequenceObject};
use dex2hoi_repr::bps::DEFAULT_BPS_POINTS;
use dex2hoi_repr::{BpsBasis, Mesh, MeshQuery, Skeleton, SkeletonKind};

use crate::error::{ImportError, Result};
use crate::humoto::PickleRig;
use crate::smplx::{SmplxModels, UpAxis};
use crate::{grab, himo, humoto};

/// A published dataset format.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SourceFormat {
    /// GRAB (SMPL-X, one object, 120 fps).
    Grab,
    /// HUMOTO (Mixamo, one to several objects, 30 fps).
    Humoto,
    /// HIMO (SMPL-X, two or three objects, 30 fps).
    Himo,
}

impl SourceFormat {
    /// The name used on the command line and in the manifest's `source`.
    pub fn name(self) -> &'static str {
        match self {
            Self::Grab => "grab",
            Self::Humoto => "humoto",
            Self::Himo => "himo",
        }
    }

    /// Parses [`SourceFormat::name`].
    pub fn parse(text: &str) -> Result<Self> {
        match text {
            "grab" => Ok(Self::Grab),
            "humoto" => Ok(Self::Humoto),
            "himo" => Ok(Self::Himo),
            other => Err(ImportError::invalid("format", "grab, humoto or himo", other)),
        }
    }

    /// The skeleton the format's sequences drive.
    pub fn skeleton_kind(self) -> SkeletonKind {
        match self {
            Self::Grab | Self::Himo => SkeletonKind::Smplx52,
            Self::Humoto => SkeletonKind::Mixamo65,
        }
    }

    /// The up axis of the format's capture world (docs/CONVENTIONS.md, "Datasets"): Z for GRAB
    /// and HUMOTO's pickles (HUMOTO's GLBs are Y up, as all glTF, whatever this says); Y for
    /// HIMO, whose own viewer shows its data unrotated in a Y-up viewer.
    pub fn default_up_axis(self) -> UpAxis {
        match self {
            Self::Grab | Self::Humoto => UpAxis::Z,
            Self::Himo => UpAxis::Y,
        }
    }
}

/// Where GRAB's finger rotations come from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum HandPoseSource {
    /// The 45-D axis-angle `fullpose` of `lhand` / `rhand` (flat hand mean).
    Full,
    /// The body's 24 PCA coefficients (`body.params.{left,right}_hand_pose`) decoded through
    /// the SMPL-X model's `hands_components{l,r}` plus `hands_mean{l,r}` (GRAB fitted its body
    /// model with smplx's default, `flat_hand_mean=False`).
    Pca,
}

/// Everything `prepare` needs to know.
#[derive(Debug, Clone)]
pub struct PrepareOptions {
    /// The format.
    pub format: SourceFormat,
    /// The dataset as downloaded: GRAB's root (holding `grab/` and `tools/`), HUMOTO's folder
    /// of sequence folders, HIMO's `data/` folder (or its parent).
    pub root: PathBuf,
    /// An SMPL-X model file, or a directory of `SMPLX_{MALE,FEMALE,NEUTRAL}.npz` (GRAB, HIMO).
    pub smplx_model: Option<PathBuf>,
    /// Target frame rate (20).
    pub fps: f32,
    /// GRAB's finger source.
    pub hand_pose: HandPoseSource,
    /// GRAB's text templates; `{verb}`, `{object}` and `{intent}` are filled in. Each gives
    /// one text of the sequence.
    pub text_templates: Vec<String>,
    /// HUMOTO's object folder (default: `humoto_objects` in or beside the root).
    pub objects_dir: Option<PathBuf>,
    /// Split files (see [`read_split_file`]): sequences they do not list are skipped. Without
    /// one, GRAB splits by subject (s10 is the test subject) and HUMOTO and HIMO by a seeded
    /// hash of the sequence id (one in ten in `test`).
    pub split_files: Vec<PathBuf>,
    /// GRAB: intents whose sequences are left out (HOIDiNi's benchmark leaves out `lift`).
    pub exclude_intents: Vec<String>,
    /// GRAB: a prompt table (HOIDiNi's `grab_prompts.csv`, see [`read_prompts`]); a sequence it
    /// lists takes its prompt instead of the templates.
    pub prompts: Option<PathBuf>,
    /// Seed of the hash split.
    pub seed: u64,
    /// Overrides the format's up axis.
    pub up_axis: Option<UpAxis>,
    /// The rig of HUMOTO pickles.
    pub pickle_rig: PickleRig,
}

impl PrepareOptions {
    /// Defaults for a format and a root: 20 fps, full hand poses, the default GRAB template,
    /// hash split with seed 0.
    pub fn new(format: SourceFormat, root: &Path) -> Self {
        Self {
            format,
            root: root.to_path_buf(),
            smplx_model: None,
            fps: 20.0,
            hand_pose: HandPoseSource::Full,
            text_templates: vec![grab::DEFAULT_TEMPLATE.to_string()],
            objects_dir: None,
            split_files: Vec::new(),
            exclude_intents: Vec::new(),
            prompts: None,
            seed: 0,
            up_axis: None,
            pickle_rig: PickleRig::default(),
        }
    }

    /// The up axis in effect.
    pub fn up_axis(&self) -> UpAxis {
        self.up_axis.unwrap_or(self.format.default_up_axis())
    }
}

/// One sequence found in the dataset.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Item {
    /// A stable id (`s1/mug_pass_1`, a HUMOTO or HIMO sequence name).
    pub id: String,
    /// Its main file.
    pub path: PathBuf,
    /// Its split.
    pub split: Split,
}

/// What reading one sequence gave.
#[derive(Debug)]
pub enum Outcome {
    /// A sequence at the dataset's frame rate, in the project's axes, with canonical meshes,
    /// and what the reader found doubtful about it.
    Sequence {
        /// The sequence.
        sequence: Box<Sequence>,
        /// Doubts, in words (reported, not fatal).
        warnings: Vec<String>,
    },
    /// A readable sequence that the dataset's protocol leaves out, and why.
    Skipped(String),
}

/// Shared state of the readers: the SMPL-X models and the meshes, each loaded once.
#[derive(Debug)]
pub struct Context {
    /// The options.
    pub options: PrepareOptions,
    /// The SMPL-X models (GRAB, HIMO).
    pub smplx: Option<SmplxModels>,
    /// The prompt table, by sequence id.
    pub prompts: Option<HashMap<String, String>>,
    /// HUMOTO's `animations.json`, read once.
    pub humoto_scripts: OnceLock<std::result::Result<humoto::Scripts, String>>,
    meshes: MeshCache,
}

impl Context {
    /// The context of a run; checks that GRAB and HIMO have an SMPL-X model.
    pub fn new(options: PrepareOptions) -> Result<Self> {
        let smplx = match (&options.smplx_model, options.format) {
            (Some(path), _) => Some(SmplxModels::new(path)?),
            (None, SourceFormat::Humoto) => None,
            (None, format) => {
                return Err(ImportError::invalid(
                    "--smplx-model",
                    format!(
                        "an SMPL-X model file (SMPLX_NEUTRAL.npz) or a directory of them: {} \
                         stores SMPL-X parameters whose rest joints come from the model",
                        format.name()
                    ),
                    "nothing",
                ));
            }
        };
        let prompts = options.prompts.as_deref().map(read_prompts).transpose()?;
        Ok(Self {
            options,
            smplx,
            prompts,
            humoto_scripts: OnceLock::new(),
            meshes: MeshCache::default(),
        })
    }

    /// The SMPL-X models (present for GRAB and HIMO, checked by [`Context::new`]).
    pub fn smplx(&self) -> Result<&SmplxModels> {
        self.smplx.as_ref().ok_or_else(|| ImportError::invalid("--smplx-model", "a model", "none"))
    }

    /// A mesh file loaded once and centred on its bounding box, with the old centre.
    pub fn mesh(&self, path: &Path) -> Result<Arc<CentredMesh>> {
        self.meshes.get(path, || Ok(Mesh::load(path)?))
    }

    /// A mesh built from memory once per key (HUMOTO's embedded `object_models`).
    pub fn mesh_from(
        &self,
        key: &Path,
        build: impl FnOnce() -> Result<Mesh>,
    ) -> Result<Arc<CentredMesh>> {
        self.meshes.get(key, build)
    }
}

/// A mesh centred on its bounding box and the centre it had in its file.
#[derive(Debug, Clone, PartialEq)]
pub struct CentredMesh {
    /// The centred mesh.
    pub mesh: Mesh,
    /// The bounding-box centre in the file's frame.
    pub centre: Vec3,
}

impl CentredMesh {
    /// A sequence object from poses of the file's frame (`v_world = R v_file + t`): the
    /// translations move to the centred frame, `t + R c`, then everything turns into the
    /// project's axes with `to_y_up`.
    pub fn object(
        &self,
        name: &str,
        rotations: &[Mat3],
        translations: &[Vec3],
        to_y_up: Mat3,
    ) -> SequenceObject {
        SequenceObject {
            name: name.to_string(),
            mesh: self.mesh.clone(),
            rotations: rotations.iter().map(|r| to_y_up * *r).collect(),
            translations: rotations
                .iter()
                .zip(translations)
                .map(|(r, t)| to_y_up * (*t + *r * self.centre))
                .collect(),
        }
    }
}

type MeshCell = Arc<OnceLock<Result<Arc<CentredMesh>, String>>>;

#[derive(Debug, Default)]
struct MeshCache {
    cells: Mutex<HashMap<PathBuf, MeshCell>>,
}

impl MeshCache {
    fn get(&self, key: &Path, build: impl FnOnce() -> Result<Mesh>) -> Result<Arc<CentredMesh>> {
        let cell = {
            let mut cells = self.cells.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
            cells.entry(key.to_path_buf()).or_default().clone()
        };
        cell.get_or_init(|| {
            let mut mesh = build().map_err(|e| e.to_string())?;
            let centre = mesh.recenter();
            Ok(Arc::new(CentredMesh { mesh, centre }))
        })
        .clone()
        .map_err(|message| {
            ImportError::format(key.display(), "object mesh", "a readable mesh", message)
        })
    }
}

/// A sequence left out, and why.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Skipped {
    /// The sequence id.
    pub id: String,
    /// The reason (the protocol's filter, or the error that stopped the reader).
    pub reason: String,
}

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

/// Sequences in one in ten land in `test` under the hash split.
const HASH_TEST_SHARE: u64 = 10;

/// The split of a sequence id under the seeded hash split (FNV-1a of the seed and the id): the
/// same id and seed always give the same split.
pub fn hash_split(id: &str, seed: u64) -> Split {
    let mut hash: u64 = 0xcbf2_9ce4_8422_2325;
    for byte in seed.to_le_bytes().iter().chain(id.as_bytes()) {
        hash ^= u64::from(*byte);
        hash = hash.wrapping_mul(0x0100_0000_01b3);
    }
    if hash.is_multiple_of(HASH_TEST_SHARE) { Split::Test } else { Split::Train }
}

/// A sequence id as split files and prompt tables write it: `s1/mug_pass_1`, also accepted
/// with a `.npz` ending (HOIDiNi's prompt table writes `s5/cubemedium_inspect_1.npz`).
fn listed_id(entry: &str) -> String {
    let entry = entry.trim();
    entry.strip_suffix(".npz").unwrap_or(entry).to_string()
}

/// The splits of a split file, in either form:
/// - an object `{"train": [ids], "test": [ids]}`;
/// - a JSON list of ids whose file name says its split (`train` or `test` in it, as HOIDiNi's
///   `grab_train_split.json` and `grab_test_split.json` do).
///
/// Ids are sequence ids (`s1/airplane_fly_1` for GRAB, a HUMOTO sequence name, a HIMO id).
pub fn read_split_file(path: &Path) -> Result<HashMap<String, Split>> {
    #[derive(serde::Deserialize)]
    #[serde(untagged)]
    enum SplitFile {
        Lists(BTreeMap<String, Vec<String>>),
        One(Vec<String>),
    }
    let bytes = std::fs::read(path).map_err(ImportError::io(path))?;
    let expected =
        r#"{"train": [ids], "test": [ids]}, or a list of ids in a file named for its split"#;
    let file: SplitFile = serde_json::from_slice(&bytes)
        .map_err(|e| ImportError::format(path.display(), "split file", expected, e))?;
    let lists = match file {
        SplitFile::Lists(lists) => lists,
        SplitFile::One(ids) => {
            let name = path.file_name().unwrap_or_default().to_string_lossy().to_lowercase();
            let split = match (name.contains("train"), name.contains("test")) {
                (true, false) => "train",
                (false, true) => "test",
                _ => {
                    return Err(ImportError::format(
                        path.display(),
                        "split of a list of ids",
                        "`train` or `test` (one of them) in the file name",
                        name,
                    ));
                }
            };
            BTreeMap::from([(split.to_string(), ids)])
        }
    };
    let mut splits = HashMap::new();
    for (name, ids) in lists {
        let split = match name.as_str() {
            "train" => Split::Train,
            "test" => Split::Test,
            other => {
                return Err(ImportError::format(
                    path.display(),
                    "split name",
                    "train or test",
                    other,
                ));
            }
        };
        for id in ids {
            let id = listed_id(&id);
            if let Some(other) = splits.insert(id.clone(), split).filter(|o| *o != split) {
                return Err(split_clash(path, &id, other, split));
            }
        }
    }
    Ok(splits)
}

/// The error of a sequence listed in two splits.
fn split_clash(path: &Path, id: &str, one: Split, other: Split) -> ImportError {
    ImportError::format(
        path.display(),
        format!("sequence `{id}`"),
        "one split per sequence",
        format!("both {} and {}", one.name(), other.name()),
    )
}

/// How items get their split: the split files when there are any, else the format's rule.
#[derive(Debug)]
pub struct SplitRule {
    listed: Option<HashMap<String, Split>>,
    seed: u64,
}

impl SplitRule {
    /// The rule of the options: the union of the split files (an id listed in two splits is
    /// an error naming it).
    pub fn new(options: &PrepareOptions) -> Result<Self> {
        if options.split_files.is_empty() {
            return Ok(Self { listed: None, seed: options.seed });
        }
        let mut listed: HashMap<String, Split> = HashMap::new();
        for path in &options.split_files {
            for (id, split) in read_split_file(path)? {
                if let Some(other) = listed.insert(id.clone(), split).filter(|o| *o != split) {
                    return Err(split_clash(path, &id, other, split));
                }
            }
        }
        Ok(Self { listed: Some(listed), seed: options.seed })
    }

    /// Whether split files decide.
    pub fn has_files(&self) -> bool {
        self.listed.is_some()
    }

    /// The split of an id; `None` when the split files do not list it.
    pub fn split(&self, id: &str) -> Option<Split> {
        match &self.listed {
            Some(listed) => listed.get(id).copied(),
            None => Some(hash_split(id, self.seed)),
        }
    }
}

/// A prompt table: CSV with a header naming the columns `dp_ind` (the sequence, as
/// `s5/cubemedium_inspect_1.npz`) and `Prompt` (HOIDiNi's `grab_prompts.csv`); fields may be
/// quoted (`"..."`, with `""` for a quote). Returns sequence id -> prompt.
pub fn read_prompts(path: &Path) -> Result<HashMap<String, String>> {
    let text = std::fs::read_to_string(path).map_err(ImportError::io(path))?;
    let rows = parse_csv(&text).map_err(|(line, what)| {
        ImportError::format(path.display(), format!("line {line}"), "CSV", what)
    })?;
    let Some((header, body)) = rows.split_first() else {
        return Err(ImportError::format(path.display(), "header", "`dp_ind,Prompt`", "nothing"));
    };
    let column = |name: &str| {
        header.1.iter().position(|c| c.trim().eq_ignore_ascii_case(name)).ok_or_else(|| {
            ImportError::missing(path.display(), name, "a column of the prompt table's header")
        })
    };
    let (id_column, prompt_column) = (column("dp_ind")?, column("Prompt")?);
    let mut prompts = HashMap::new();
    for (line, fields) in body {
        if fields.iter().all(|f| f.trim().is_empty()) {
            continue;
        }
        let (Some(id), Some(prompt)) = (fields.get(id_column), fields.get(prompt_column)) else {
            return Err(ImportError::format(
                path.display(),
                format!("line {line}"),
                format!("{} fields", header.1.len()),
                fields.len(),
            ));
        };
        if prompt.trim().is_empty() {
            return Err(ImportError::format(
                path.display(),
                format!("line {line}"),
                "a prompt",
                "an empty field",
            ));
        }
        prompts.insert(listed_id(id), prompt.trim().to_string());
    }
    Ok(prompts)
}

/// CSV rows, each with the line it starts on (1-based).
type CsvRows = Vec<(usize, Vec<String>)>;

/// Rows of a CSV text; `Err((line, what))` for an unclosed quote or a character after a
/// closing quote.
fn parse_csv(text: &str) -> std::result::Result<CsvRows, (usize, String)> {
    let mut rows = Vec::new();
    let mut fields = Vec::new();
    let mut field = String::new();
    let (mut line, mut row_line) = (1, 1);
    let mut chars = text.chars().peekable();
    let mut quoted = false;
    let mut after_quote = false;
    while let Some(c) = chars.next() {
        if quoted {
            match c {
                '"' if chars.peek() == Some(&'"') => {
                    chars.next();
                    field.push('"');
                }
                '"' => {
                    quoted = false;
                    after_quote = true;
                }
                '\n' => {
                    line += 1;
                    field.push(c);
                }
                _ => field.push(c),
            }
            continue;
        }
        match c {
            ',' => {
                fields.push(std::mem::take(&mut field));
                after_quote = false;
            }
            '\n' => {
                fields.push(std::mem::take(&mut field));
                rows.push((row_line, std::mem::take(&mut fields)));
                after_quote = false;
                line += 1;
                row_line = line;
            }
            '\r' if chars.peek() == Some(&'\n') => {}
            '"' if field.is_empty() && !after_quote => quoted = true,
            _ if after_quote => {
                return Err((line, format!("`{c}` after a closing quote")));
            }
            _ => field.push(c),
        }
    }
    if quoted {
        return Err((row_line, "a quote that is never closed".into()));
    }
    if !field.is_empty() || !fields.is_empty() {
        fields.push(field);
        rows.push((row_line, fields));
    }
    Ok(rows)
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
    let config = TargetConfig::default();
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
    let dataset = Dataset::assemble(
        context.options.format.name(),
        &skeleton,
        context.options.fps,
        splits,
        assets,
        bps,
        None,
    )?;
    Ok(Prepared { dataset: Some(dataset), report })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hash_split_is_stable_and_about_one_in_ten() {
        let ids: Vec<String> = (0..2000).map(|i| format!("S{i:02}T001")).collect();
        let test = ids.iter().filter(|id| hash_split(id, 0) == Split::Test).count();
        assert!((150..250).contains(&test), "{test}");
        assert_eq!(hash_split("S01T001", 0), hash_split("S01T001", 0));
        let other_seed = ids.iter().filter(|id| hash_split(id, 0) != hash_split(id, 1)).count();
        assert!(other_seed > 100, "the seed changes the split");
    }

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
