//! SMPL-X bodies of GRAB and HIMO: rest skeletons from a user-supplied model file and body shape
//! (docs/CONVENTIONS.md, "Rest offsets": `J = J_regressor @ (v_template + shapedirs . betas)`), the
//! hand PCA components of the model, and axis-angle parameters to the local rotations of the
//! 52-joint skeleton.
//!
//! SMPL-X rotates the body about the rest pelvis `J_0`: the posed pelvis is `J_0 + transl`.

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex, OnceLock};

use glam::{Mat3, Vec3};

use dex2hoi_repr::Skeleton;
use dex2hoi_repr::rotation::axis_angle_to_matrix;
use dex2hoi_repr::smplx_model::SmplxModel;

use crate::error::{ImportError, Result};
use crate::npy::Npz;
use crate::value::Field;

/// Finger joints per hand (MANO's 15: index, middle, pinky, ring, thumb, three each).
pub const HAND_JOINTS: usize = 15;

/// One SMPL-X model file, loaded once, with the skeletons of the body shapes asked for.
pub struct SmplxBody {
    path: PathBuf,
    model: SmplxModel,
    hand_components: OnceLock<Result<[HandComponents; 2], String>>,
    skeletons: Mutex<HashMap<Vec<u32>, Skeleton>>,
    templates: Mutex<HashMap<PathBuf, Skeleton>>,
}

impl std::fmt::Debug for SmplxBody {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SmplxBody").field("path", &self.path).finish_non_exhaustive()
    }
}

/// The PCA basis of one hand in an SMPL-X model: `hands_components{l,r}` `(45, 45)` (rows are
/// components) and `hands_mean{l,r}` `(45,)`.
#[derive(Debug, Clone, PartialEq)]
pub struct HandComponents {
    /// Row-major `(45, 45)`.
    pub components: Vec<f64>,
    /// `(45,)`.
    pub mean: Vec<f64>,
}

impl HandComponents {
    /// The 45 axis-angle numbers of a hand from its PCA coefficients:
    /// `coefficients @ components[:n] (+ mean)`.
    pub fn decode(&self, coefficients: &[f64], add_mean: bool) -> Vec<f64> {
        let mut pose = if add_mean { self.mean.clone() } else { vec![0.0; 3 * HAND_JOINTS] };
        for (k, c) in coefficients.iter().enumerate() {
            for (p, value) in pose.iter_mut().enumerate() {
                *value += c * self.components[k * 3 * HAND_JOINTS + p];
            }
        }
        pose
    }
}

impl SmplxBody {
    /// Loads a model file (`SMPLX_NEUTRAL.npz` and friends).
    pub fn load(path: &Path) -> Result<Self> {
        Ok(Self {
            path: path.to_path_buf(),
            model: SmplxModel::load(path)?,
            hand_components: OnceLock::new(),
            skeletons: Mutex::new(HashMap::new()),
            templates: Mutex::new(HashMap::new()),
        })
    }

    /// The model file.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// The 52-joint skeleton of a body shape (cached per shape): rest joints from the model,
    /// offsets child minus parent, the names and groups of `Skeleton::smplx()`. Its root
    /// offset is the rest pelvis `J_0`.
    pub fn skeleton(&self, betas: &[f32]) -> Result<Skeleton> {
        let key: Vec<u32> = betas.iter().map(|b| b.to_bits()).collect();
        if let Some(skeleton) = self.lock_skeletons().get(&key) {
            return Ok(skeleton.clone());
        }
        let skeleton = Skeleton::from_smplx_joints(&self.model.rest_joints(betas)?)?;
        self.lock_skeletons().insert(key, skeleton.clone());
        Ok(skeleton)
    }

    /// The 52-joint skeleton of a subject's personalised template mesh (GRAB's `vtemp`): its
    /// rest joints by the model's `J_regressor`, as GRAB's own code builds each subject's body.
    /// Cached per file.
    pub fn skeleton_of_template(&self, template: &Path) -> Result<Skeleton> {
        let lock = || self.templates.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
        if let Some(skeleton) = lock().get(template) {
            return Ok(skeleton.clone());
        }
        let mesh = dex2hoi_repr::Mesh::load(template)?;
        let skeleton = Skeleton::from_smplx_joints(
            &self.model.joints_of(&mesh.vertices, &template.display().to_string())?,
        )?;
        lock().insert(template.to_path_buf(), skeleton.clone());
        Ok(skeleton)
    }

    fn lock_skeletons(&self) -> std::sync::MutexGuard<'_, HashMap<Vec<u32>, Skeleton>> {
        // A panic elsewhere cannot leave the cache half-written: entries are inserted whole.
        self.skeletons.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    /// The hand PCA bases `[left, right]`, read from the model file on first use.
    pub fn hand_components(&self) -> Result<&[HandComponents; 2]> {
        self.hand_components
            .get_or_init(|| read_hand_components(&self.path).map_err(|e| e.to_string()))
            .as_ref()
            .map_err(|message| {
                ImportError::format(self.path.display(), "hand PCA components", "readable", message)
            })
    }
}

fn read_hand_components(path: &Path) -> Result<[HandComponents; 2]> {
    let mut archive = Npz::open(path)?;
    let source_name = path.display().to_string();
    let mut read = |side: char| -> Result<HandComponents> {
        let key = format!("hands_components{side}");
        let value = archive.read(&key, "the hand PCA basis (45, 45)")?;
        let (components, _) =
            Field::root(&source_name, &key, &value).numbers(&[Some(45), Some(45)])?;
        let key = format!("hands_mean{side}");
        let value = archive.read(&key, "the mean hand pose (45,)")?;
        let (mean, _) = Field::root(&source_name, &key, &value).numbers(&[Some(45)])?;
        Ok(HandComponents { components, mean })
    };
    Ok([read('l')?, read('r')?])
}

/// A model loaded once, shared by the readers (the error as text, shared too).
type BodyCell = Arc<OnceLock<Result<Arc<SmplxBody>, String>>>;

/// Where SMPL-X models come from: one file for every subject, or a directory with
/// `SMPLX_MALE.npz`, `SMPLX_FEMALE.npz` and `SMPLX_NEUTRAL.npz` picked by the subject's gender.
#[derive(Debug)]
pub struct SmplxModels {
    source: PathBuf,
    loaded: Mutex<HashMap<PathBuf, BodyCell>>,
}

impl SmplxModels {
    /// Models from a file or a directory (see the type's documentation).
    pub fn new(source: &Path) -> Result<Self> {
        if !source.exists() {
            return Err(ImportError::Io {
                path: source.to_path_buf(),
                source: std::io::Error::new(std::io::ErrorKind::NotFound, "no such SMPL-X model"),
            });
        }
        Ok(Self { source: source.to_path_buf(), loaded: Mutex::new(HashMap::new()) })
    }

    /// The model file for a gender (`male`, `female`, `neutral`; anything else is neutral).
    pub fn path_for(&self, gender: &str) -> PathBuf {
        if self.source.is_file() {
            return self.source.clone();
        }
        let upper = gender.trim().to_ascii_uppercase();
        let gendered = self.source.join(format!("SMPLX_{upper}.npz"));
        if matches!(upper.as_str(), "MALE" | "FEMALE") && gendered.is_file() {
            gendered
        } else {
            self.source.join("SMPLX_NEUTRAL.npz")
        }
    }

    /// The loaded model for a gender (each file is loaded once, even from parallel readers).
    pub fn body(&self, gender: &str) -> Result<Arc<SmplxBody>> {
        let path = self.path_for(gender);
        let cell = {
            let mut loaded = self.loaded.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
            loaded.entry(path.clone()).or_default().clone()
        };
        cell.get_or_init(|| SmplxBody::load(&path).map(Arc::new).map_err(|e| e.to_string()))
            .clone()
            .map_err(|message| {
                ImportError::format(
                    path.display(),
                    "SMPL-X model",
                    "a readable model file",
                    message,
                )
            })
    }
}

/// Axis-angle SMPL-X parameters of a sequence, `T` frames.
#[derive(Debug, Clone, PartialEq)]
pub struct SmplxParams {
    /// `(T, 3)` pelvis rotation.
    pub global_orient: Vec<f64>,
    /// `(T, 63)` joints 1-21.
    pub body_pose: Vec<f64>,
    /// `(T, 45)` left fingers (absolute: the flat hand is zero).
    pub left_hand: Vec<f64>,
    /// `(T, 45)` right fingers.
    pub right_hand: Vec<f64>,
    /// `(T, 3)` translation of the body (the posed pelvis is `J_0 + transl`).
    pub transl: Vec<f64>,
}

impl SmplxParams {
    /// Number of frames.
    pub fn frames(&self) -> usize {
        self.transl.len() / 3
    }

    /// Local rotations of the 52 joints per frame, frame-major, and the world pelvis per
    /// frame, for a skeleton whose root offset is the rest pelvis. Jaw and eyes are dropped.
    pub fn to_motion(&self, skeleton: &Skeleton) -> (Vec<Mat3>, Vec<Vec3>) {
        let frames = self.frames();
        let rotation = |values: &[f64], frame: usize, width: usize, joint: usize| {
            let base = frame * width + joint * 3;
            axis_angle_to_matrix(Vec3::new(
                values[base] as f32,
                values[base + 1] as f32,
                values[base + 2] as f32,
            ))
        };
        let mut local = Vec::with_capacity(frames * 52);
        let mut roots = Vec::with_capacity(frames);
        let pelvis = skeleton.rest_offsets()[0];
        for t in 0..frames {
            local.push(rotation(&self.global_orient, t, 3, 0));
            for j in 0..21 {
                local.push(rotation(&self.body_pose, t, 63, j));
            }
            for hand in [&self.left_hand, &self.right_hand] {
                for j in 0..HAND_JOINTS {
                    local.push(rotation(hand, t, 45, j));
                }
            }
            let transl = &self.transl[t * 3..t * 3 + 3];
            roots.push(pelvis + Vec3::new(transl[0] as f32, transl[1] as f32, transl[2] as f32));
        }
        (local, roots)
    }
}

/// The up axis of a dataset's world.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum UpAxis {
    /// Already the project's convention.
    Y,
    /// Z up (GRAB, HUMOTO and HIMO capture worlds).
    Z,
}

impl UpAxis {
    /// The rotation from the dataset's world to the project's Y-up world: for Z up the rows
    /// `(1,0,0), (0,0,1), (0,-1,0)` (docs/CONVENTIONS.md, "Coordinate frames and units"), which
    /// takes +Z to +Y and a character facing -Y to facing +Z.
    pub fn to_y_up(self) -> Mat3 {
        match self {
            Self::Y => Mat3::IDENTITY,
            Self::Z => dex2hoi_repr::rotation::mat3_from_rows(Vec3::X, Vec3::Z, -Vec3::Y),
        }
    }

    /// Parses `y` or `z`.
    pub fn parse(text: &str) -> Result<Self> {
        match text.to_ascii_lowercase().as_str() {
            "y" => Ok(Self::Y),
            "z" => Ok(Self::Z),
            other => Err(ImportError::invalid("up axis", "`y` or `z`", other)),
        }
    }
}
