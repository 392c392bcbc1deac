//! HUMOTO (docs/CONVENTIONS.md, "HUMOTO"): per sequence a folder `<seq>/` with the pickle
//! `<seq>.pkl` (`armature`: per frame `{bone: [qw,qx,qy,qz, lx,ly,lz]}`; `objects`:
//! `{name: [[qw,qx,qy,qz, x,y,z] per frame]}`; optional `object_models`:
//! `{name: {'mesh': (V, F)}}`) and the text `<seq>.yaml` (`short_script`); object meshes in
//! `humoto_objects/<name>/<name>.obj`; the Mixamo 65-joint rig; Z up; 30 fps.
//!
//! The paper keeps clips with at most two moving objects; static objects (furniture the
//! person never moves) are left out of the sequence.
//!
//! Reading of the armature (it differs from HUMOTO's own description of the bone frames in
//! docs/CONVENTIONS.md, "HUMOTO", and is unchecked against a real file; this is the convention
//! assumed and documented in `docs/FORMATS.md`): each bone's quaternion is its rotation
//! relative to its parent with rest frames aligned to the Z-up world, and the `Hips` location
//! is the root joint's world position in metres; the other bones' locations are their rest
//! offsets, for which the rig's own rest pose (`Skeleton::mixamo`) is used.

use std::path::{Path, PathBuf};

use glam::{Mat3, Vec3};

use dex2hoi_data::Sequence;
use dex2hoi_repr::rotation::{geodesic_angle, quaternion_from_wxyz, quaternion_to_matrix};
use dex2hoi_repr::skeleton::MIXAMO_PREFIX;
use dex2hoi_repr::{Mesh, Skeleton};

use crate::error::{ImportError, Result};
use crate::pickle::read_pickle;
use crate::prepare::{Context, Item, Outcome, PrepareOptions, Skipped, SplitRule};
use crate::value::Field;
use crate::yaml::top_level_text;

/// HUMOTO's frame rate.
pub const FPS: f32 = 30.0;

/// The most moving objects a clip may have (the paper's filter).
pub const MAX_MOVING_OBJECTS: usize = 2;

/// An object moves when its centre travels this far from where it starts (metres) ...
pub const MOVING_DISTANCE: f32 = 0.02;
/// ... or turns this far (radians, about 6 degrees): more than capture jitter.
pub const MOVING_ANGLE: f32 = 0.1;

/// Every `*.pkl` below the root (outside the object folder), in path order.
pub fn discover(options: &PrepareOptions) -> Result<(Vec<Item>, Vec<Skipped>)> {
    let rule = SplitRule::new(options)?;
    let mut files = Vec::new();
    collect_pickles(&options.root, &mut files)?;
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

fn collect_pickles(dir: &Path, out: &mut Vec<PathBuf>) -> Result<()> {
    for entry in std::fs::read_dir(dir).map_err(ImportError::io(dir))? {
        let path = entry.map_err(ImportError::io(dir))?.path();
        if path.is_dir() {
            if path.file_name().is_some_and(|n| n != "humoto_objects") {
                collect_pickles(&path, out)?;
            }
        } else if path.extension().is_some_and(|e| e == "pkl") {
            out.push(path);
        }
    }
    Ok(())
}

/// The object folder: the option, else `humoto_objects` in the root or beside it.
fn objects_dir(options: &PrepareOptions) -> PathBuf {
    if let Some(dir) = &options.objects_dir {
        return dir.clone();
    }
    let inside = options.root.join("humoto_objects");
    if inside.is_dir() {
        return inside;
    }
    options.root.parent().map_or(inside, |p| p.join("humoto_objects"))
}

/// Seven numbers `[qw,qx,qy,qz, x,y,z]` as a rotation and a position.
fn pose(values: &[f64]) -> (Mat3, Vec3) {
    let q = quaternion_from_wxyz([
        values[0] as f32,
        values[1] as f32,
        values[2] as f32,
        values[3] as f32,
    ]);
    (quaternion_to_matrix(q), Vec3::new(values[4] as f32, values[5] as f32, values[6] as f32))
}

/// The seven numbers of a bone or object at one frame.
fn seven(field: &Field<'_>) -> Result<Vec<f64>> {
    let (values, _) = field.numbers(&[Some(7)])?;
    let q = &values[..4];
    if q.iter().map(|v| v * v).sum::<f64>() < 1e-8 {
        return Err(ImportError::format(
            field.source_name(),
            format!("`{}`", field.path()),
            "a non-zero quaternion",
            "zeros",
        ));
    }
    Ok(values)
}

/// A mesh from `object_models[name]['mesh'] = (V (N, 3), F (M, 3))`.
fn embedded_mesh(field: &Field<'_>) -> Result<Mesh> {
    let mesh = field.get("mesh", "a (vertices, faces) pair")?;
    let parts = mesh.items()?;
    if parts.len() != 2 {
        return Err(ImportError::format(
            field.source_name(),
            format!("`{}`", mesh.path()),
            "a (vertices, faces) pair",
            mesh.value().type_name(),
        ));
    }
    let (vertices, _) = parts[0].numbers(&[None, Some(3)])?;
    let (faces, _) = parts[1].numbers(&[None, Some(3)])?;
    let vertices = vertices
        .chunks_exact(3)
        .map(|v| Vec3::new(v[0] as f32, v[1] as f32, v[2] as f32))
        .collect();
    let faces = faces
        .chunks_exact(3)
        .map(|f| {
            [f[0], f[1], f[2]]
                .map(|i| if i >= 0.0 && i < f64::from(u32::MAX) { i as u32 } else { u32::MAX })
        })
        .collect();
    Ok(Mesh::new(vertices, faces, &format!("{}[{}]", field.source_name(), mesh.path()))?)
}

/// Reads one HUMOTO sequence (at 30 fps, in the project's axes).
pub fn load(item: &Item, context: &Context) -> Result<Outcome> {
    let options = &context.options;
    let path = &item.path;
    let source_name = path.display().to_string();
    let bytes = std::fs::read(path).map_err(ImportError::io(path))?;
    let (value, _) = read_pickle(&bytes, &source_name)?;
    let root = Field::root(&source_name, "", &value);

    let yaml_path = path.with_extension("yaml");
    let yaml = std::fs::read_to_string(&yaml_path).map_err(ImportError::io(&yaml_path))?;
    let yaml_name = yaml_path.display().to_string();
    let text = top_level_text(&yaml, &yaml_name)?
        .remove("short_script")
        .filter(|t| !t.trim().is_empty())
        .ok_or_else(|| ImportError::missing(&yaml_name, "short_script", "the sequence's text"))?;

    let skeleton = Skeleton::mixamo();
    let joints = skeleton.joint_count();
    let to_y_up = options.up_axis().to_y_up();
    let from_y_up = to_y_up.transpose();
    let armature = root.get("armature", "the bone transforms per frame")?.items()?;
    let frames = armature.len();
    if frames == 0 {
        return Err(ImportError::format(&source_name, "`armature`", "at least one frame", 0));
    }
    let mut local_rotations = Vec::with_capacity(frames * joints);
    let mut root_positions = Vec::with_capacity(frames);
    for frame in &armature {
        for (j, name) in skeleton.joint_names().iter().enumerate() {
            let prefixed = format!("{MIXAMO_PREFIX}{name}");
            let key = if frame.has(&prefixed) { prefixed } else { name.clone() };
            let values = seven(&frame.get(&key, "the bone's [qw,qx,qy,qz, x,y,z]")?)?;
            let (rotation, location) = pose(&values);
            // A rotation in Z-up axes, conjugated into Y-up axes.
            local_rotations.push(to_y_up * rotation * from_y_up);
            if j == 0 {
                root_positions.push(to_y_up * location);
            }
        }
    }

    let objects_field = root.get("objects", "the object poses per frame")?;
    let models = root.has("object_models").then(|| root.get("object_models", "")).transpose()?;
    let mut moving = Vec::new();
    let mut static_count = 0;
    for (name, track) in objects_field.entries()? {
        let poses = track.items()?;
        if poses.len() != frames {
            return Err(ImportError::format(
                &source_name,
                format!("`{}`", track.path()),
                format!("{frames} poses (one per armature frame)"),
                poses.len(),
            ));
        }
        let mut rotations = Vec::with_capacity(frames);
        let mut translations = Vec::with_capacity(frames);
        for p in &poses {
            let (r, t) = pose(&seven(p)?);
            rotations.push(r);
            translations.push(t);
        }
        let travels = translations.iter().any(|t| t.distance(translations[0]) > MOVING_DISTANCE);
        let turns = rotations.iter().any(|r| geodesic_angle(rotations[0], *r) > MOVING_ANGLE);
        if travels || turns {
            moving.push((name, rotations, translations));
        } else {
            static_count += 1;
        }
    }
    if moving.len() > MAX_MOVING_OBJECTS {
        let names: Vec<&str> = moving.iter().map(|(n, ..)| n.as_str()).collect();
        return Ok(Outcome::Skipped(format!(
            "{} moving objects ({}): the paper keeps clips with at most {MAX_MOVING_OBJECTS}",
            moving.len(),
            names.join(", ")
        )));
    }
    if moving.is_empty() {
        return Ok(Outcome::Skipped(format!(
            "no moving object ({static_count} static): not an object interaction"
        )));
    }
    let folder = objects_dir(options);
    let mut objects = Vec::with_capacity(moving.len());
    for (name, rotations, translations) in moving {
        let embedded = models.as_ref().filter(|m| m.has(&name));
        let mesh = match embedded {
            Some(models) => {
                let key = path.join("object_models").join(&name);
                let field = models.get(&name, "the object's model")?;
                context.mesh_from(&key, || embedded_mesh(&field))?
            }
            None => context.mesh(&folder.join(&name).join(format!("{name}.obj")))?,
        };
        // Object poses are world poses (Z up): only the world turns, the mesh frame stays.
        objects.push(mesh.object(&name, &rotations, &translations, to_y_up));
    }
    Ok(Outcome::Sequence(Box::new(Sequence {
        skeleton,
        fps: FPS,
        local_rotations,
        root_positions,
        objects,
        texts: vec![text.trim().to_string()],
        action: None,
        source_id: format!("humoto/{}", item.id),
    })))
}
