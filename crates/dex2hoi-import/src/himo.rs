//! HIMO (docs/CONVENTIONS.md, "HIMO"): `data/smplx/<seq>.npz` (`betas (10)`, `global_orient`,
//! `body_pose`, `lhand_pose`, `rhand_pose` (full 45-D), `transl`), `data/object_pose/<seq>.npy`
//! (a pickled dict `{name: {'transl': (T, 3), 'rot': (T, 3, 3)}}`, `v_world = rot @ v + transl`),
//! `data/text/<seq>.txt` (one description per line) and `data/object_mesh/<Name>.obj`; Z up;
//! 30 fps.
//!
//! [`read_sequence`] reads every sequence, three-object ones included; the dataset format
//! (and the paper's evaluation) holds two objects, so `prepare` keeps the 2-object split and
//! reports the 3-object sequences as skipped.

use std::path::{Path, PathBuf};

use glam::{Mat3, Vec3};

use dex2hoi_data::{MAX_OBJECTS, Sequence};

use crate::error::{ImportError, Result};
use crate::npy::{Npz, read_npy};
use crate::smplx::{HAND_JOINTS, SmplxParams};
use crate::source::{Context, Item, Outcome, PrepareOptions, Skipped, SplitRule};
use crate::value::Field;

/// HIMO's frame rate.
pub const FPS: f32 = 30.0;

/// The `data` folder: `root/data` when it exists, else `root`.
pub fn data_dir(root: &Path) -> PathBuf {
    let inner = root.join("data");
    if inner.join("smplx").is_dir() { inner } else { root.to_path_buf() }
}

/// Every `smplx/*.npz`, in name order.
pub fn discover(options: &PrepareOptions) -> Result<(Vec<Item>, Vec<Skipped>)> {
    let rule = SplitRule::new(options)?;
    let dir = data_dir(&options.root).join("smplx");
    let mut files: Vec<PathBuf> = std::fs::read_dir(&dir)
        .map_err(ImportError::io(&dir))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|e| e == "npz"))
        .collect();
    files.sort();
    let mut items = Vec::new();
    let mut skipped = Vec::new();
    for path in files {
        let id = path.file_stem().unwrap_or_default().to_string_lossy().into_owned();
        match rule.split(&id) {
            Some(split) => items.push(Item { id, path, split }),
            None => skipped.push(Skipped { id, reason: "not listed in the split file".into() }),
        }
    }
    Ok((items, skipped))
}

/// One object of a HIMO sequence, in HIMO's (Z-up) world.
#[derive(Debug, Clone, PartialEq)]
pub struct HimoObject {
    /// The name (its mesh is `object_mesh/<name>.obj`).
    pub name: String,
    /// Object-to-world rotations.
    pub rotations: Vec<Mat3>,
    /// World translations.
    pub translations: Vec<Vec3>,
}

/// A HIMO sequence as stored, any number of objects.
#[derive(Debug, Clone, PartialEq)]
pub struct HimoSequence {
    /// Body shape.
    pub betas: Vec<f32>,
    /// SMPL-X parameters.
    pub params: SmplxParams,
    /// The objects, in the order of the pose file.
    pub objects: Vec<HimoObject>,
    /// Descriptions.
    pub texts: Vec<String>,
}

/// Per-frame numbers `(T, width)`, also accepting the unflattened `(T, joints, 3)` layout.
fn per_frame(
    archive: &mut Npz,
    key: &str,
    width: usize,
    frames: Option<usize>,
) -> Result<(Vec<f64>, usize)> {
    let value = archive.read(key, &format!("(T, {width}) per-frame parameters"))?;
    let source_name = format!("{}[{key}]", archive.path().display());
    let (values, shape) = Field::root(&source_name, key, &value).numbers_any_shape()?;
    let rest: usize = shape.iter().skip(1).product();
    let frames_ok = shape.first().is_some_and(|&t| frames.is_none_or(|f| f == t));
    if shape.len() < 2 || rest != width || !frames_ok {
        let t = frames.map_or_else(|| "T".to_string(), |f| f.to_string());
        return Err(ImportError::Shape {
            source_name,
            key: key.into(),
            expected: format!("({t}, {width})"),
            got: shape,
        });
    }
    Ok((values, shape[0]))
}

/// The descriptions of a text file: one per non-empty line (a HumanML3D-style `#` annotation
/// after the sentence is dropped).
pub fn read_texts(path: &Path) -> Result<Vec<String>> {
    let text = std::fs::read_to_string(path).map_err(ImportError::io(path))?;
    let texts: Vec<String> = text
        .lines()
        .map(|l| l.split('#').next().unwrap_or("").trim().to_string())
        .filter(|l| !l.is_empty())
        .collect();
    if texts.is_empty() {
        return Err(ImportError::format(
            path.display(),
            "text",
            "at least one description",
            "none",
        ));
    }
    Ok(texts)
}

/// Reads one sequence by id from a `data` folder.
pub fn read_sequence(data: &Path, id: &str) -> Result<HimoSequence> {
    let npz_path = data.join("smplx").join(format!("{id}.npz"));
    let mut archive = Npz::open(&npz_path)?;
    let betas_value = archive.read("betas", "the body shape (10,)")?;
    let betas_name = format!("{}[betas]", npz_path.display());
    let (betas, _) = Field::root(&betas_name, "betas", &betas_value).numbers_any_shape()?;
    let (transl, frames) = per_frame(&mut archive, "transl", 3, None)?;
    let frames_opt = Some(frames);
    let (global_orient, _) = per_frame(&mut archive, "global_orient", 3, frames_opt)?;
    let (body_pose, _) = per_frame(&mut archive, "body_pose", 63, frames_opt)?;
    let (left_hand, _) = per_frame(&mut archive, "lhand_pose", 3 * HAND_JOINTS, frames_opt)?;
    let (right_hand, _) = per_frame(&mut archive, "rhand_pose", 3 * HAND_JOINTS, frames_opt)?;

    let pose_path = data.join("object_pose").join(format!("{id}.npy"));
    let pose_value = read_npy(&pose_path)?;
    let pose_name = pose_path.display().to_string();
    let poses = Field::root(&pose_name, "", &pose_value);
    let mut objects = Vec::new();
    for (name, object) in poses.entries()? {
        let (transl, _) =
            object.get("transl", "(T, 3) translations")?.numbers(&[frames_opt, Some(3)])?;
        let (rot, _) =
            object.get("rot", "(T, 3, 3) rotations")?.numbers(&[frames_opt, Some(3), Some(3)])?;
        let rotations = rot
            .chunks_exact(9)
            .map(|m| {
                let row =
                    |i: usize| Vec3::new(m[3 * i] as f32, m[3 * i + 1] as f32, m[3 * i + 2] as f32);
                dex2hoi_repr::rotation::mat3_from_rows(row(0), row(1), row(2))
            })
            .collect();
        let translations = transl
            .chunks_exact(3)
            .map(|t| Vec3::new(t[0] as f32, t[1] as f32, t[2] as f32))
            .collect();
        objects.push(HimoObject { name, rotations, translations });
    }
    let texts = read_texts(&data.join("text").join(format!("{id}.txt")))?;
    Ok(HimoSequence {
        betas: betas.into_iter().map(|b| b as f32).collect(),
        params: SmplxParams { global_orient, body_pose, left_hand, right_hand, transl },
        objects,
        texts,
    })
}

/// Reads one HIMO sequence (at 30 fps, in the project's axes); sequences with more objects
/// than the dataset format holds are skipped.
pub fn load(item: &Item, context: &Context) -> Result<Outcome> {
    let data = data_dir(&context.options.root);
    let himo = read_sequence(&data, &item.id)?;
    if himo.objects.len() > MAX_OBJECTS {
        return Ok(Outcome::Skipped(format!(
            "{} objects: the dataset format holds {MAX_OBJECTS} (the paper uses HIMO's \
             2-object split)",
            himo.objects.len()
        )));
    }
    if himo.objects.is_empty() {
        return Ok(Outcome::Skipped("no object in the pose file".into()));
    }
    // HIMO's bodies are fitted with the neutral model.
    let body = context.smplx()?.body("neutral")?;
    let skeleton = body.skeleton(&himo.betas)?;
    let (mut local_rotations, mut root_positions) = himo.params.to_motion(&skeleton);
    let to_y_up = context.options.up_axis().to_y_up();
    let joints = skeleton.joint_count();
    for t in 0..root_positions.len() {
        local_rotations[t * joints] = to_y_up * local_rotations[t * joints];
        root_positions[t] = to_y_up * root_positions[t];
    }
    let mut objects = Vec::with_capacity(himo.objects.len());
    for object in &himo.objects {
        let mesh = context.mesh(&data.join("object_mesh").join(format!("{}.obj", object.name)))?;
        objects.push(mesh.object(&object.name, &object.rotations, &object.translations, to_y_up));
    }
    Ok(Outcome::Sequence {
        sequence: Box::new(Sequence {
            skeleton,
            fps: FPS,
            local_rotations,
            root_positions,
            objects,
            texts: himo.texts,
            action: None,
            source_id: format!("himo/{}", item.id),
        }),
        warnings: Vec::new(),
    })
}
