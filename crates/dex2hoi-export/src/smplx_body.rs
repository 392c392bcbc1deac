//! The SMPL-X body mesh of a user's model file, ready to skin in `motion.glb`.
//!
//! The model (`SMPLX_NEUTRAL.npz` and friends; licensed, so users bring it) is shaped by
//! body-shape coefficients `betas`: `v = v_template + shapedirs[..., :n] . betas`, rest joints
//! `J = J_regressor @ v` (docs/CONVENTIONS.md, "Rest offsets"). The exported skeleton is the
//! model's own (52 joints from `J`), so `motion.npz`, `motion.bvh` and the GLB's skin agree with
//! an `smplx` layer fed the npz. The three face joints we do not animate (jaw and eyes) are kept
//! in the skin at rest, since the model's weights use them. Each vertex keeps its four largest
//! weights, renormalised (glTF's `JOINTS_0`/`WEIGHTS_0`).
//!
//! glTF skinning is linear blend skinning; the model's pose-corrective blend shapes
//! (`posedirs`) are not exported, so the GLB's mesh is the `smplx` layer's mesh without them.

use std::path::{Path, PathBuf};

use glam::Vec3;

use dex2hoi_repr::Skeleton;
use dex2hoi_repr::smplx_model::SmplxModel;

use crate::error::{ExportError, Result};

/// The file looked for in a model directory (the `smplx` package's layout puts it under
/// `smplx/`, which is looked in too).
pub const SMPLX_MODEL_FILE: &str = "SMPLX_NEUTRAL.npz";

/// Influences kept per vertex (glTF's one `JOINTS_0`/`WEIGHTS_0` set).
pub const INFLUENCES: usize = 4;

/// Joints of the SMPL-X model (body, jaw, eyes, fingers).
const MODEL_JOINTS: usize = 55;

/// The SMPL-X joints 22-24 (jaw, left eye, right eye), absent from our 52: skin joints 52-54.
const FACE_JOINTS: [usize; 3] = [22, 23, 24];

/// Names of the face joints in the skin.
pub const FACE_JOINT_NAMES: [&str; 3] = ["jaw", "left_eye_smplx", "right_eye_smplx"];

/// An SMPL-X body shaped by `betas`, its skeleton and its skin.
#[derive(Debug, Clone, PartialEq)]
pub struct SmplxMesh {
    /// The model file.
    pub path: PathBuf,
    /// The body-shape coefficients it was shaped by.
    pub betas: Vec<f32>,
    /// The model's 52-joint skeleton for these betas (names and groups of
    /// [`Skeleton::smplx`]); a motion exported with this mesh is posed on it.
    pub skeleton: Skeleton,
    /// Rest positions of the jaw and the eyes ([`FACE_JOINT_NAMES`]); their parent is the head.
    pub face_joints: [Vec3; 3],
    /// Rest vertices (metres, Y up).
    pub vertices: Vec<Vec3>,
    /// Unit vertex normals of the rest mesh (area-weighted face normals).
    pub normals: Vec<Vec3>,
    /// The model's triangles.
    pub faces: Vec<[u32; 3]>,
    /// The skin joints of each vertex: 0-51 our joints, 52-54 [`FACE_JOINT_NAMES`].
    pub joints: Vec<[u8; INFLUENCES]>,
    /// Their weights, each row summing to 1 (unused slots: joint 0, weight 0).
    pub weights: Vec<[f32; INFLUENCES]>,
}

/// The skin joint of an SMPL-X model joint: 0-21 stay, jaw and eyes become 52-54, the fingers
/// (25-54) move down by three.
fn skin_joint(model_joint: usize) -> usize {
    match model_joint {
        j if j < FACE_JOINTS[0] => j,
        j if j <= FACE_JOINTS[2] => 52 + (j - FACE_JOINTS[0]),
        j => j - FACE_JOINTS.len(),
    }
}

/// The model file of `--smplx-model FILE|DIR`: the file itself, or [`SMPLX_MODEL_FILE`] in the
/// directory or its `smplx/` folder.
pub fn resolve_model_path(path: &Path) -> Result<PathBuf> {
    if !path.is_dir() {
        return Ok(path.to_path_buf());
    }
    let candidates = [path.join(SMPLX_MODEL_FILE), path.join("smplx").join(SMPLX_MODEL_FILE)];
    candidates.iter().find(|c| c.is_file()).cloned().ok_or_else(|| {
        ExportError::invalid(
            format!("SMPL-X model directory {}", path.display()),
            format!("a model file {} or {}", candidates[0].display(), candidates[1].display()),
            "neither",
        )
    })
}

impl SmplxMesh {
    /// Loads a model file (or a directory, [`resolve_model_path`]) and shapes it by `betas` (at
    /// most as many as its `shapedirs` has; fewer leave the rest zero). The file must hold
    /// `v_template`, `shapedirs`, `J_regressor`, `kintree_table` (the SMPL-X tree), `f` and
    /// `weights`; an error names the file and the key.
    pub fn load(path: &Path, betas: &[f32]) -> Result<Self> {
        let path = resolve_model_path(path)?;
        let model = SmplxModel::load(&path)?;
        let shaped = model.shaped(betas)?;
        let skeleton = Skeleton::from_smplx_joints(&shaped.joints)?;
        let face_joints = FACE_JOINTS.map(|j| shaped.joints[j]);
        let (joints, weights) = strongest_influences(&shaped.weights, &path)?;
        let normals = vertex_normals(&shaped.vertices, &shaped.faces);
        Ok(Self {
            path,
            betas: betas.to_vec(),
            skeleton,
            face_joints,
            vertices: shaped.vertices,
            normals,
            faces: shaped.faces,
            joints,
            weights,
        })
    }

    /// Checks that a motion's skeleton can be shown with this body (an SMPL-X motion); pose it
    /// on [`SmplxMesh::skeleton`] for the export.
    pub fn fits(&self, skeleton: &Skeleton) -> Result<()> {
        let body = format!("the SMPL-X body of {}", self.path.display());
        crate::check_skeleton_kind(body, &self.skeleton, skeleton)
    }
}

/// The [`INFLUENCES`] largest weights of each vertex (ties to the lower joint), renormalised to
/// sum to 1 in `f32`, as skin joints.
///
/// # Shapes
/// - `weights`: `[vertices * 55]` row-major
#[allow(clippy::type_complexity)] // two parallel per-vertex arrays, as glTF stores them
fn strongest_influences(
    weights: &[f64],
    path: &Path,
) -> Result<(Vec<[u8; INFLUENCES]>, Vec<[f32; INFLUENCES]>)> {
    let mut joints = Vec::with_capacity(weights.len() / MODEL_JOINTS);
    let mut kept = Vec::with_capacity(weights.len() / MODEL_JOINTS);
    for (vertex, row) in weights.chunks_exact(MODEL_JOINTS).enumerate() {
        let mut order: Vec<usize> = (0..MODEL_JOINTS).collect();
        order.sort_by(|&a, &b| row[b].total_cmp(&row[a]).then(a.cmp(&b)));
        let top = &order[..INFLUENCES];
        let total: f64 = top.iter().map(|&j| row[j]).sum();
        // Weights are non-negative (the loader checks), so `total` is positive or zero.
        if total <= 0.0 {
            return Err(ExportError::invalid(
                format!("skinning weights of vertex {vertex} in {}", path.display()),
                "at least one positive weight",
                "none",
            ));
        }
        let mut vertex_joints = [0u8; INFLUENCES];
        let mut vertex_weights = [0.0f32; INFLUENCES];
        for (slot, &j) in top.iter().enumerate() {
            if row[j] > 0.0 {
                vertex_joints[slot] = skin_joint(j) as u8;
                vertex_weights[slot] = (row[j] / total) as f32;
            }
        }
        // Rounding to f32 can leave the sum a few ulps off 1; the largest weight absorbs it.
        let sum: f32 = vertex_weights.iter().sum();
        vertex_weights[0] += 1.0 - sum;
        joints.push(vertex_joints);
        kept.push(vertex_weights);
    }
    Ok((joints, kept))
}

/// Area-weighted vertex normals, unit length (`+Y` for a vertex no face uses).
pub(crate) fn vertex_normals(vertices: &[Vec3], faces: &[[u32; 3]]) -> Vec<Vec3> {
    let mut normals = vec![Vec3::ZERO; vertices.len()];
    for face in faces {
        let [a, b, c] = face.map(|i| vertices[i as usize]);
        let normal = (b - a).cross(c - a);
        for &i in face {
            normals[i as usize] += normal;
        }
    }
    normals.into_iter().map(|n| n.try_normalize().unwrap_or(Vec3::Y)).collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use dex2hoi_repr::skeleton::smplx52_to_55;

    #[test]
    fn skin_joints_put_the_face_joints_after_ours() {
        let to55 = smplx52_to_55();
        for (ours, &model) in to55.iter().enumerate() {
            assert_eq!(skin_joint(model), ours);
        }
        assert_eq!(FACE_JOINTS.map(skin_joint), [52, 53, 54]);
    }

    #[test]
    fn the_four_largest_weights_are_kept_and_renormalised() {
        let mut row = vec![0.0; MODEL_JOINTS];
        for (joint, weight) in [(3, 0.1), (22, 0.4), (30, 0.2), (1, 0.05), (7, 0.25)] {
            row[joint] = weight;
        }
        let (joints, weights) = strongest_influences(&row, Path::new("x")).unwrap();
        assert_eq!(joints[0], [52, 7, 27, 3]);
        let total = 0.4 + 0.25 + 0.2 + 0.1;
        for (got, want) in weights[0].iter().zip([0.4, 0.25, 0.2, 0.1]) {
            assert!((f64::from(*got) - want / total).abs() < 1e-6);
        }
        assert!((weights[0].iter().sum::<f32>() - 1.0).abs() <= f32::EPSILON);
        // A vertex with no weight is refused.
        assert!(strongest_influences(&[0.0; MODEL_JOINTS], Path::new("x")).is_err());
    }
}
