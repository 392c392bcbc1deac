//! Exports of a generated (or dataset) motion for people and other tools:
//!
//! - [`npz`]: `motion.npz`, SMPL-X-style parameters that numpy loads and the `smplx` Python
//!   package's layer takes as they are (documented in `docs/FORMATS.md`);
//! - [`glb`]: `motion.glb`, glTF 2.0 binary with the skeleton as a skin, a body skinned to it
//!   (the SMPL-X mesh of a user's model, [`smplx_body`], a user's Mixamo character,
//!   [`character`], or a capsule body) and the objects as
//!   animated nodes (Blender, three.js, Unreal's glTF importer, Unity with glTFast);
//! - [`bvh`]: `motion.bvh`, the skeleton's animation in BioVision hierarchy form;
//! - [`preview`]: `preview.gif`, an animation drawn by a small software rasteriser.
//!
//! Every writer checks its input first ([`ExportMotion::validate`]), encodes the whole file in
//! memory and writes it atomically (temporary file, then rename), so bad input leaves no file
//! behind and a crash never leaves half a file. Joint positions are recomputed from the local
//! rotations by forward kinematics, so all four files agree with each other.

pub mod body_mesh;
pub mod bvh;
pub mod character;
pub mod error;
pub mod glb;
pub mod npz;
pub mod preview;
pub mod smplx_body;

use std::collections::HashSet;
use std::path::{Path, PathBuf};

use glam::{Mat3, Vec3};

use dex2hoi_data::MAX_OBJECTS;
use dex2hoi_data::features::DecodedMotion;
use dex2hoi_repr::rotation::is_rotation;
use dex2hoi_repr::{FkOutput, Mesh, Skeleton, forward_kinematics};

pub use body_mesh::{SkinnedMesh, body_mesh};
pub use bvh::{BvhMotion, encode_bvh, parse_bvh, read_bvh, write_bvh};
pub use character::{CharacterMesh, ExtraJoint, RigBone};
pub use error::{ExportError, Result};
pub use glb::{encode_glb, write_glb};
pub use npz::{encode_npz, write_npz};
pub use preview::{
    Camera, JointState, Preview, PreviewOptions, Surface, TableBox, encode_preview_gif,
    render_preview, write_preview_gif,
};
pub use smplx_body::{SmplxMesh, resolve_model_path};

/// File name of the SMPL-X-style parameters in an export directory.
pub const NPZ_FILE: &str = "motion.npz";
/// File name of the glTF binary.
pub const GLB_FILE: &str = "motion.glb";
/// File name of the BVH animation.
pub const BVH_FILE: &str = "motion.bvh";
/// File name of the animated preview.
pub const GIF_FILE: &str = "preview.gif";
/// File name of the still sheet ([`Preview::sheet`]).
pub const PNG_FILE: &str = "preview.png";

/// How far a matrix may be from a rotation (`R^T R = I`, `det R = 1`) and still be exported.
const ROTATION_TOLERANCE: f32 = 1e-3;

/// A motion to export: the skeleton it is posed on, its frame rate and text, the decoded motion
/// and the objects of the occupied slots with their names and meshes.
#[derive(Debug, Clone)]
pub struct ExportMotion<'a> {
    /// The skeleton of the motion's local rotations.
    pub skeleton: &'a Skeleton,
    /// Frames per second.
    pub fps: f32,
    /// The descriptions the motion was generated from, each with the first frame it is in
    /// force from, in order (one at frame 0 for a single prompt; empty for none). The preview
    /// writes the one in force on each frame; the files' metadata hold them all
    /// ([`ExportMotion::text`]).
    pub prompts: Vec<(usize, String)>,
    /// Local rotations, root positions and per-slot object poses.
    pub motion: &'a DecodedMotion,
    /// The objects to export, each naming the slot of `motion.objects` that holds its poses.
    pub objects: Vec<ExportObject<'a>>,
    /// The body mesh to skin in `motion.glb` (an SMPL-X model's also puts its `betas` in
    /// `motion.npz`); `None` for the capsule body. With a mesh, `skeleton` must be the mesh's
    /// ([`Body::skeleton`]).
    pub body: Option<Body<'a>>,
}

/// A body's rest mesh skinned to the joints of its skeleton ([`Body::skin`]).
pub(crate) struct BodySkin<'a> {
    pub vertices: &'a [Vec3],
    pub faces: &'a [[u32; 3]],
    /// Four skeleton joints per vertex.
    pub joints: Vec<[u16; 4]>,
    /// Their weights.
    pub weights: Vec<[f32; 4]>,
}

/// A body mesh skinned to the motion's skeleton.
#[derive(Debug, Clone, Copy)]
pub enum Body<'a> {
    /// A user's SMPL-X model shaped by its betas.
    Smplx(&'a SmplxMesh),
    /// A user's Mixamo-rigged character.
    Character(&'a CharacterMesh),
}

impl<'a> Body<'a> {
    /// The skeleton a motion shown with this body must be posed on.
    pub fn skeleton(self) -> &'a Skeleton {
        match self {
            Self::Smplx(mesh) => &mesh.skeleton,
            Self::Character(character) => &character.skeleton,
        }
    }

    /// The file the body comes from.
    pub fn path(self) -> &'a Path {
        match self {
            Self::Smplx(mesh) => &mesh.path,
            Self::Character(character) => &character.path,
        }
    }

    /// How the GLB's extras name the body.
    pub fn kind_name(self) -> &'static str {
        match self {
            Self::Smplx(_) => "smplx",
            Self::Character(_) => "character",
        }
    }

    /// The SMPL-X body-shape coefficients, for an SMPL-X model.
    pub fn betas(self) -> Option<&'a [f32]> {
        match self {
            Self::Smplx(mesh) => Some(&mesh.betas),
            Self::Character(_) => None,
        }
    }
    /// The rest mesh with its skin as joints of [`Body::skeleton`]: vertices, faces, and per
    /// vertex four joints and weights, a skin joint the skeleton lacks (SMPL-X's jaw and eyes,
    /// a character's other bones, all at rest under their parents) taken as its nearest
    /// ancestor among the skeleton's joints, which moves it the same way.
    pub(crate) fn skin(self) -> BodySkin<'a> {
        match self {
            Self::Smplx(mesh) => {
                let head = mesh.skeleton.joint_index("head").unwrap_or(0) as u16;
                let joints = mesh.skeleton.joint_count() as u16;
                let mapped = mesh
                    .joints
                    .iter()
                    .map(|row| row.map(|j| if u16::from(j) < joints { u16::from(j) } else { head }))
                    .collect();
                BodySkin {
                    vertices: &mesh.vertices,
                    faces: &mesh.faces,
                    joints: mapped,
                    weights: mesh.weights.clone(),
                }
            }
            Self::Character(character) => {
                let joints = character.skeleton.joint_count();
                let mut ancestor: Vec<u16> = (0..joints as u16).collect();
                // Extra joints come after their parents.
                for extra in &character.extra_joints {
                    ancestor.push(ancestor[extra.parent]);
                }
                let mapped = character
                    .joints
                    .iter()
                    .map(|row| row.map(|j| ancestor[usize::from(j)]))
                    .collect();
                BodySkin {
                    vertices: &character.vertices,
                    faces: &character.faces,
                    joints: mapped,
                    weights: character.weights.clone(),
                }
            }
        }
    }
}

/// One object of an [`ExportMotion`].
#[derive(Debug, Clone)]
pub struct ExportObject<'a> {
    /// The object's name (non-empty, unique within the motion).
    pub name: String,
    /// Its mesh in the object frame (the frame that the slot's poses move).
    pub mesh: &'a Mesh,
    /// The slot of [`DecodedMotion::objects`] with its rotations and positions.
    pub slot: usize,
}

/// An [`ExportMotion`] that passed [`ExportMotion::check`], with its forward kinematics.
#[derive(Debug)]
pub(crate) struct Checked<'a> {
    pub skeleton: &'a Skeleton,
    pub fps: f32,
    pub text: String,
    pub prompts: &'a [(usize, String)],
    pub frames: usize,
    pub local_rotations: &'a [Mat3],
    pub root_positions: &'a [Vec3],
    pub fk: FkOutput,
    pub objects: Vec<CheckedObject<'a>>,
    pub body: Option<Body<'a>>,
}

impl Checked<'_> {
    /// See [`ExportMotion::prompt_at`].
    pub fn prompt_at(&self, frame: usize) -> &str {
        prompt_in_force(self.prompts, frame)
    }
}

/// The last of `prompts` (by start frame, in order) that starts at or before `frame`.
fn prompt_in_force(prompts: &[(usize, String)], frame: usize) -> &str {
    dex2hoi_data::timeline::in_force(prompts, |p| p.0, frame).map_or("", |(_, text)| text)
}

/// An object whose poses cover every frame.
#[derive(Debug)]
pub(crate) struct CheckedObject<'a> {
    pub name: &'a str,
    pub mesh: &'a Mesh,
    pub slot: usize,
    pub rotations: &'a [Mat3],
    pub positions: &'a [Vec3],
}

impl Checked<'_> {
    /// Seconds from the start of the motion to a frame.
    pub fn time(&self, frame: usize) -> f32 {
        frame as f32 / self.fps
    }
}

/// The first matrix that is not a rotation, described by `describe(index)`.
fn check_rotations(rotations: &[Mat3], describe: impl Fn(usize) -> String) -> Result<()> {
    if let Some(i) = rotations.iter().position(|r| !is_rotation(*r, ROTATION_TOLERANCE)) {
        return Err(ExportError::invalid(
            describe(i),
            format!("a rotation matrix (R^T R = I and det R = 1, to {ROTATION_TOLERANCE})"),
            format!("rows {:?}", rotations[i].transpose().to_cols_array_2d()),
        ));
    }
    Ok(())
}

fn check_positions(positions: &[Vec3], what: &str) -> Result<()> {
    if let Some(frame) = positions.iter().position(|p| !p.is_finite()) {
        return Err(ExportError::invalid(
            format!("{what} at frame {frame}"),
            "finite numbers",
            positions[frame],
        ));
    }
    Ok(())
}

fn check_mesh(mesh: &Mesh, name: &str) -> Result<()> {
    let context = || format!("mesh of object {name}");
    if mesh.faces.is_empty() {
        return Err(ExportError::invalid(context(), "at least one triangle", "none"));
    }
    if let Some(v) = mesh.vertices.iter().position(|v| !v.is_finite()) {
        return Err(ExportError::invalid(
            context(),
            "finite vertices",
            format!("vertex {v} = {}", mesh.vertices[v]),
        ));
    }
    let count = mesh.vertices.len();
    if let Some(face) = mesh.faces.iter().position(|f| f.iter().any(|&i| i as usize >= count)) {
        return Err(ExportError::invalid(
            context(),
            format!("vertex indices below {count}"),
            format!("face {face} = {:?}", mesh.faces[face]),
        ));
    }
    Ok(())
}

impl<'a> ExportMotion<'a> {
    /// The descriptions as one text, `" | "` between timeline entries.
    pub fn text(&self) -> String {
        self.prompts.iter().map(|(_, text)| text.as_str()).collect::<Vec<_>>().join(" | ")
    }

    /// The description in force at `frame` (empty when there is none).
    pub fn prompt_at(&self, frame: usize) -> &str {
        prompt_in_force(&self.prompts, frame)
    }

    /// Number of frames (the number of root positions).
    pub fn frames(&self) -> usize {
        self.motion.root_positions.len()
    }

    /// Checks everything the writers rely on: a positive finite frame rate, at least one frame,
    /// `frames * joints` local rotations that are rotations, finite root positions, objects with
    /// non-empty unique names in distinct occupied slots whose poses cover every frame, and
    /// valid meshes. Every writer runs this first; the error names the frame and joint.
    ///
    /// # Shapes
    /// - `motion.local_rotations`: `[frames * joints]`; `motion.root_positions`: `[frames]`;
    ///   each exported object's slot: `[frames]` rotations and positions
    pub fn validate(&self) -> Result<()> {
        self.check().map(|_| ())
    }

    /// The world position of every joint on every frame (forward kinematics of the validated
    /// motion), as `motion.npz` holds them in `joints`.
    ///
    /// # Shapes
    /// - returns `[frames * joints]`
    pub fn joint_positions(&self) -> Result<Vec<Vec3>> {
        Ok(self.check()?.fk.positions)
    }

    /// How each hand joint meets the objects on each frame, as the preview colours the hands
    /// ([`JointState`]; every other joint is free).
    ///
    /// # Shapes
    /// - returns `[frames * joints]`
    pub fn hand_contacts(&self) -> Result<Vec<JointState>> {
        preview::hand_states(&self.check()?)
    }

    /// [`ExportMotion::validate`], returning the motion with its forward kinematics.
    pub(crate) fn check(&self) -> Result<Checked<'_>> {
        if !(self.fps.is_finite() && self.fps > 0.0) {
            return Err(ExportError::invalid("frame rate", "a positive number", self.fps));
        }
        let frames = self.frames();
        let joints = self.skeleton.joint_count();
        if frames == 0 {
            return Err(ExportError::invalid("motion", "at least one frame", "none"));
        }
        let motion = self.motion;
        if motion.local_rotations.len() != frames * joints {
            return Err(ExportError::invalid(
                "local rotations",
                format!("{frames} frames x {joints} joints = {} matrices", frames * joints),
                motion.local_rotations.len(),
            ));
        }
        let joint_names = self.skeleton.joint_names();
        check_rotations(&motion.local_rotations, |i| {
            format!(
                "local rotation of joint {} ({}) at frame {}",
                i % joints,
                joint_names[i % joints],
                i / joints
            )
        })?;
        check_positions(&motion.root_positions, "root position")?;
        if let Some(body) = self.body {
            check_body_skeleton(body, self.skeleton)?;
        }
        let mut names = HashSet::new();
        let mut slots = HashSet::new();
        let mut objects = Vec::with_capacity(self.objects.len());
        for object in &self.objects {
            let name = object.name.as_str();
            if name.is_empty() || !names.insert(name) {
                return Err(ExportError::invalid(
                    "object names",
                    "non-empty names, each used once",
                    format!("{:?}", self.objects.iter().map(|o| &o.name).collect::<Vec<_>>()),
                ));
            }
            let slot = object.slot;
            let poses = motion.objects.get(slot).and_then(Option::as_ref);
            let Some((rotations, positions)) = poses.filter(|_| slots.insert(slot)) else {
                return Err(ExportError::invalid(
                    format!("slot of object {name}"),
                    format!("a distinct occupied slot below {MAX_OBJECTS}"),
                    slot,
                ));
            };
            if rotations.len() != frames || positions.len() != frames {
                return Err(ExportError::invalid(
                    format!("poses of object {name}"),
                    format!("{frames} rotations and positions"),
                    format!("{} and {}", rotations.len(), positions.len()),
                ));
            }
            check_rotations(rotations, |frame| {
                format!("rotation of object {name} at frame {frame}")
            })?;
            check_positions(positions, &format!("position of object {name}"))?;
            check_mesh(object.mesh, name)?;
            objects.push(CheckedObject { name, mesh: object.mesh, slot, rotations, positions });
        }
        let fk =
            forward_kinematics(self.skeleton, &motion.local_rotations, &motion.root_positions)?;
        Ok(Checked {
            skeleton: self.skeleton,
            fps: self.fps,
            text: self.text(),
            prompts: &self.prompts,
            frames,
            local_rotations: &motion.local_rotations,
            root_positions: &motion.root_positions,
            fk,
            objects,
            body: self.body,
        })
    }
}

/// Refuses a motion on another kind of skeleton than a body's (`body` names the body).
pub(crate) fn check_skeleton_kind(body: String, own: &Skeleton, motion: &Skeleton) -> Result<()> {
    if motion.kind() != own.kind() {
        return Err(ExportError::invalid(
            body,
            format!("a motion on the {} skeleton", own.kind().name()),
            format!("a {} motion", motion.kind().name()),
        ));
    }
    Ok(())
}

/// How far (metres) a motion's rest offsets may be from a body mesh's skeleton's.
const BODY_SKELETON_TOLERANCE: f32 = 1e-6;

/// A motion skinned to a body mesh must be posed on the body's own skeleton.
fn check_body_skeleton(body: Body<'_>, skeleton: &Skeleton) -> Result<()> {
    let own = body.skeleton();
    let same = skeleton.kind() == own.kind()
        && skeleton.joint_count() == own.joint_count()
        && skeleton
            .rest_offsets()
            .iter()
            .zip(own.rest_offsets())
            .all(|(a, b)| (*a - *b).abs().max_element() <= BODY_SKELETON_TOLERANCE);
    if !same {
        return Err(ExportError::invalid(
            format!("skeleton of a motion skinned to {}", body.path().display()),
            "the body's own skeleton (Body::skeleton)",
            format!("a {} skeleton with other rest offsets", skeleton.kind().name()),
        ));
    }
    Ok(())
}

/// Writes encoded bytes to `path` atomically (temporary file beside it, then rename).
pub(crate) fn write_file(path: &Path, bytes: &[u8]) -> Result<()> {
    Ok(dex2hoi_data::files::write_atomically(path, bytes)?)
}

/// Options of [`export_all`].
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ExportOptions {
    /// Size of the preview and the table it shows.
    pub preview: PreviewOptions,
}

/// The paths [`export_all`] wrote.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ExportedFiles {
    /// `motion.npz`.
    pub npz: PathBuf,
    /// `motion.glb`.
    pub glb: PathBuf,
    /// `motion.bvh`.
    pub bvh: PathBuf,
    /// `preview.gif`.
    pub gif: PathBuf,
    /// `preview.png`.
    pub png: PathBuf,
}

/// Writes [`NPZ_FILE`], [`GLB_FILE`], [`BVH_FILE`], [`GIF_FILE`] and [`PNG_FILE`] into `dir`
/// (created if missing). All five are encoded before the first is written, so bad input writes nothing;
/// each file is written atomically.
pub fn export_all(
    dir: &Path,
    motion: &ExportMotion<'_>,
    options: &ExportOptions,
) -> Result<ExportedFiles> {
    let npz = encode_npz(motion)?;
    let glb = encode_glb(motion)?;
    let bvh = encode_bvh(motion)?;
    let preview = render_preview(motion, &options.preview)?;
    let gif = preview.encode_gif()?;
    let png = preview.encode_sheet_png(&motion.text(), motion.fps)?;
    std::fs::create_dir_all(dir).map_err(|source| ExportError::Io {
        path: dir.to_path_buf(),
        action: "creating the export directory",
        source,
    })?;
    let files = ExportedFiles {
        npz: dir.join(NPZ_FILE),
        glb: dir.join(GLB_FILE),
        bvh: dir.join(BVH_FILE),
        gif: dir.join(GIF_FILE),
        png: dir.join(PNG_FILE),
    };
    write_file(&files.npz, &npz)?;
    write_file(&files.glb, &glb)?;
    write_file(&files.bvh, bvh.as_bytes())?;
    write_file(&files.gif, &gif)?;
    write_file(&files.png, &png)?;
    Ok(files)
}
