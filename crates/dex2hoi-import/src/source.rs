//! What `prepare` and the per-format readers ([`crate::grab`], [`crate::humoto`],
//! [`crate::himo`]) share: the options of a run, the [`Context`] the readers read with (the
//! SMPL-X models and the meshes, each loaded once), the [`Item`]s a reader finds and the
//! [`Outcome`] of reading one, and the split rule (split files, the seeded hash split) and
//! prompt tables that decide which sequences are read and with which text. The module is
//! private: its public items are re-exported from [`prepare`](mod@crate::prepare),
//! [`PickleRig`] and [`Scripts`] from [`crate::humoto`] and [`DEFAULT_TEMPLATE`] from
//! [`crate::grab`].

use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex, OnceLock};

use glam::{Mat3, Vec3};

use dex2hoi_data::dataset::Split;
use dex2hoi_data::features::MixtureTargets;
use dex2hoi_data::{Sequence, SequenceObject};
use dex2hoi_repr::{Mesh, SkeletonKind};

use crate::error::{ImportError, Result};
use crate::smplx::{SmplxModels, UpAxis};

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

/// GRAB's default text template ([`PrepareOptions::text_templates`]).
pub const DEFAULT_TEMPLATE: &str = "The person is {verb} the {object}.";

/// Which rig the HUMOTO authors' Blender scripts transferred a pickle's motion to.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum PickleRig {
    /// `up_bone`: every bone's rest frame is `Rx(+90 deg)` (read).
    #[default]
    UpBone,
    /// `mixamo_bone`: Mixamo's own rest frame per bone (refused: its rest frames are not in
    /// the pickle, and no such file has been seen to check a reading against).
    MixamoBone,
}

impl PickleRig {
    /// The name in the authors' scripts.
    pub fn name(self) -> &'static str {
        match self {
            Self::UpBone => "up_bone",
            Self::MixamoBone => "mixamo_bone",
        }
    }
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
    /// The data's licence file, kept in the dataset (default: the one found by
    /// [`PrepareOptions::licence_file`]).
    pub licence: Option<PathBuf>,
    /// The rule the mixture targets are drawn by.
    pub mixture_targets: MixtureTargets,
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
            text_templates: vec![DEFAULT_TEMPLATE.to_string()],
            objects_dir: None,
            split_files: Vec::new(),
            exclude_intents: Vec::new(),
            prompts: None,
            seed: 0,
            up_axis: None,
            pickle_rig: PickleRig::default(),
            licence: None,
            mixture_targets: MixtureTargets::default(),
        }
    }

    /// The licence file to keep with the dataset: the one given, else the first file (by name)
    /// in the root, then in its parent, whose name says licence or license (HUMOTO's
    /// `Adobe Research License v1.1.pdf`, a `LICENSE.md`).
    pub fn licence_file(&self) -> Option<PathBuf> {
        if let Some(path) = &self.licence {
            return Some(path.clone());
        }
        let says_licence = |path: &Path| {
            path.file_name().is_some_and(|n| {
                let name = n.to_string_lossy().to_lowercase();
                name.contains("license") || name.contains("licence")
            })
        };
        [Some(self.root.as_path()), self.root.parent()].into_iter().flatten().find_map(|dir| {
            let mut files: Vec<PathBuf> = std::fs::read_dir(dir)
                .ok()?
                .filter_map(|entry| Some(entry.ok()?.path()))
                .filter(|path| path.is_file() && says_licence(path))
                .collect();
            files.sort();
            files.into_iter().next()
        })
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

/// HUMOTO's `animations.json` of the root or its parent: sequence name -> `short_script`.
pub type Scripts = Option<(PathBuf, HashMap<String, String>)>;

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
    pub humoto_scripts: OnceLock<std::result::Result<Scripts, String>>,
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
}
