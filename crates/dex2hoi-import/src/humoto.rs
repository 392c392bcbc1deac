//! HUMOTO (docs/CONVENTIONS.md, "HUMOTO"), from either of its two forms:
//! - **the published release**: one folder per sequence holding `<seq>.glb` (and `<seq>.fbx`, a
//!   PNG), with `animations.json` (each sequence's `short_script`) in the root or its parent.
//!   The GLB holds the 65-joint `mixamorig:*` skin under an `Armature` node (scale 0.01), the
//!   body's node animation, and one mesh node per object with its own animation; Y up (glTF).
//! - **the authors' pickle** `<seq>.pkl` (+ `<seq>.yaml`), made from the FBX by their Blender
//!   scripts with the `up_bone` rig: per frame `{bone: [qw,qx,qy,qz, lx,ly,lz]}` where every
//!   bone's rest frame is `Rx(+90 deg)` of the Z-up world, so each quaternion is the bone's
//!   parent-relative rotation in Y-up axes and each location a translation in its parent's
//!   (Y-up) axes from the rest offset (`Hips`: from the rest hips); objects as Z-up world poses;
//!   `object_models` (meshes) or `humoto_objects/<name>/<name>.obj`.
//!
//! Both are read onto HUMOTO's character ([`Skeleton::humoto_character`]; the GLB's own bind
//! pose when it has one). The few animated bone translations are folded into rotations
//! ([`crate::rig`]). One keyframe is one frame at 30 fps: the files' time stamps step by 1/24 s,
//! a mark left by Blender, not the capture rate (docs/FORMATS.md, "HUMOTO").
//!
//! The paper keeps clips with at most two moving objects; static objects (furniture the
//! person never moves) are left out of the sequence.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use glam::{Mat3, Mat4, Vec3};

use dex2hoi_data::{Sequence, SequenceObject};
use dex2hoi_repr::rotation::{geodesic_angle, quaternion_from_wxyz, quaternion_to_matrix};
use dex2hoi_repr::skeleton::MIXAMO_PREFIX;
use dex2hoi_repr::{Mesh, Skeleton};

use crate::error::{ImportError, Result};
use crate::glb::GlbScene;
use crate::pickle::read_pickle;
use crate::rig::{FoldedRig, PosedRig, orthonormalised};
use crate::source::{Context, Item, Outcome, PrepareOptions, Skipped, SplitRule};
use crate::value::Field;
use crate::yaml::top_level_text;

pub use crate::source::{PickleRig, Scripts};

/// HUMOTO's frame rate: one keyframe of the GLB (and one row of the pickle) per 1/30 s.
pub const FPS: f32 = 30.0;

/// The most moving objects a clip may have (the paper's filter).
pub const MAX_MOVING_OBJECTS: usize = 2;

/// An object moves when its centre travels this far from where it starts (metres) ...
pub const MOVING_DISTANCE: f32 = 0.02;
/// ... or turns this far (radians, about 6 degrees): more than capture jitter.
pub const MOVING_ANGLE: f32 = 0.1;

/// The file that holds the published texts.
pub const SCRIPTS_FILE: &str = "animations.json";

/// A folded rig whose joints end further than this on average from the data's (metres) is
/// reported: HUMOTO's captured stretch leaves well under a millimetre.
const FOLD_WARNING: f32 = 0.005;

/// The most node poses a GLB is sampled into (keyframes times nodes), per keyframe its tracks
/// store or node it has: each frame poses every node, and a file of many nodes and one long
/// track would otherwise ask for gigabytes. HUMOTO's published GLBs sample 0.6 to 1.6 poses per
/// stored keyframe (about 70 nodes, about 200 tracks of up to 900 keyframes), so 16 leaves a
/// wide margin.
pub const POSES_PER_STORED_KEYFRAME: usize = 16;

/// Every sequence below the root (outside the object folder): a `.glb`, or a `.pkl`, per
/// folder and name; the GLB when both are there (it is the published source). The id is the
/// file name without its extension, which is the folder name in the published layout.
pub fn discover(options: &PrepareOptions) -> Result<(Vec<Item>, Vec<Skipped>)> {
    let rule = SplitRule::new(options)?;
    let mut files = Vec::new();
    collect_sequences(&options.root, &mut files)?;
    let mut chosen: BTreeMap<(PathBuf, String), PathBuf> = BTreeMap::new();
    for path in files {
        let stem = path.file_stem().unwrap_or_default().to_string_lossy().into_owned();
        let folder = path.parent().map(Path::to_path_buf).unwrap_or_default();
        let entry = chosen.entry((folder, stem)).or_insert_with(|| path.clone());
        if path.extension().is_some_and(|e| e == "glb") {
            *entry = path;
        }
    }
    let mut items = Vec::new();
    let mut skipped = Vec::new();
    for ((_, id), path) in chosen {
        match rule.split(&id) {
            Some(split) => items.push(Item { id, path, split }),
            None => skipped.push(Skipped { id, reason: "not listed in the split file".into() }),
        }
    }
    items.sort_by(|a, b| a.id.cmp(&b.id).then_with(|| a.path.cmp(&b.path)));
    Ok((items, skipped))
}

fn collect_sequences(dir: &Path, out: &mut Vec<PathBuf>) -> Result<()> {
    for entry in std::fs::read_dir(dir).map_err(ImportError::io(dir))? {
        let path = entry.map_err(ImportError::io(dir))?.path();
        if path.is_dir() {
            if path.file_name().is_some_and(|n| n != "humoto_objects") {
                collect_sequences(&path, out)?;
            }
        } else if path.extension().is_some_and(|e| e == "pkl" || e == "glb") {
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

/// Reads one HUMOTO sequence (at 30 fps, in the project's axes) from its GLB or its pickle.
pub fn load(item: &Item, context: &Context) -> Result<Outcome> {
    let motion = if item.path.extension().is_some_and(|e| e == "glb") {
        read_glb(&item.path)?
    } else {
        read_pickle_motion(&item.path, context)?
    };
    let text = script(item, context)?;
    assemble(item, context, motion, text)
}

/// A HUMOTO motion as read, before the protocol's object filter.
struct Motion {
    skeleton: Skeleton,
    folded: FoldedRig,
    /// Every object with a pose per frame, in the project's axes, and how to get its mesh.
    objects: Vec<ObjectTrack>,
}

struct ObjectTrack {
    name: String,
    rotations: Vec<Mat3>,
    translations: Vec<Vec3>,
    mesh: MeshSource,
}

enum MeshSource {
    /// A mesh read from the sequence's own file (GLB mesh node, pickle `object_models`).
    Embedded(Box<dyn FnOnce() -> Result<Mesh> + Send>),
    /// `humoto_objects/<name>/<name>.obj`.
    File(PathBuf),
}

/// The sequence's text: its `short_script` in `animations.json` (in the root or its parent, as
/// published), else in `<seq>.yaml` beside its file.
fn script(item: &Item, context: &Context) -> Result<String> {
    let scripts = context.humoto_scripts.get_or_init(|| read_scripts(&context.options.root));
    let scripts = scripts
        .as_ref()
        .map_err(|e| ImportError::format(SCRIPTS_FILE, "texts", "a readable file", e))?;
    let yaml_path = item.path.with_extension("yaml");
    if let Some((file, scripts)) = scripts {
        if let Some(text) = scripts.get(&item.id) {
            return Ok(text.clone());
        }
        if !yaml_path.is_file() {
            return Err(ImportError::missing(
                file.display(),
                format!("{}'s short_script", item.id),
                "the sequence's text (or a .yaml beside its file)",
            ));
        }
    }
    let yaml = std::fs::read_to_string(&yaml_path).map_err(ImportError::io(&yaml_path))?;
    let yaml_name = yaml_path.display().to_string();
    top_level_text(&yaml, &yaml_name)?
        .remove("short_script")
        .map(|t| t.trim().to_string())
        .filter(|t| !t.is_empty())
        .ok_or_else(|| ImportError::missing(&yaml_name, "short_script", "the sequence's text"))
}

fn read_scripts(root: &Path) -> std::result::Result<Scripts, String> {
    let candidates = [Some(root.join(SCRIPTS_FILE)), root.parent().map(|p| p.join(SCRIPTS_FILE))];
    let Some(path) = candidates.into_iter().flatten().find(|p| p.is_file()) else {
        return Ok(None);
    };
    #[derive(serde::Deserialize)]
    struct Entry {
        #[serde(rename = "fileName")]
        file_name: String,
        short_script: String,
    }
    let bytes = std::fs::read(&path).map_err(|e| format!("{}: {e}", path.display()))?;
    let entries: Vec<Entry> = serde_json::from_slice(&bytes).map_err(|e| {
        format!(
            "{}: expected a JSON list of {{\"fileName\", \"short_script\", ...}}: {e}",
            path.display()
        )
    })?;
    let scripts = entries
        .into_iter()
        .filter(|e| !e.short_script.trim().is_empty())
        .map(|e| (e.file_name, e.short_script.trim().to_string()))
        .collect();
    Ok(Some((path, scripts)))
}

/// The body and objects of a published GLB.
fn read_glb(path: &Path) -> Result<Motion> {
    let scene = GlbScene::read(path)?;
    let source = scene.source_name().to_string();
    let times = scene.keyframe_times();
    let poses = times.len().saturating_mul(scene.nodes.len());
    let stored = scene.stored_keyframes() + scene.nodes.len();
    if poses > stored.saturating_mul(POSES_PER_STORED_KEYFRAME) {
        return Err(ImportError::format(
            &source,
            "animation",
            format!(
                "at most {POSES_PER_STORED_KEYFRAME} node poses per stored keyframe or node \
                 ({stored})"
            ),
            format!("{} keyframes of {} nodes", times.len(), scene.nodes.len()),
        ));
    }
    let builtin = Skeleton::humoto_character();
    let skin = scene
        .skins
        .iter()
        .find(|s| s.joints.iter().any(|&j| scene.nodes[j].name.starts_with(MIXAMO_PREFIX)))
        .ok_or_else(|| ImportError::missing(&source, "skin", "a skin of `mixamorig:*` joints"))?;
    let mut order = Vec::with_capacity(builtin.joint_count());
    let mut missing = Vec::new();
    for name in builtin.joint_names() {
        let full = format!("{MIXAMO_PREFIX}{name}");
        match skin.joints.iter().position(|&j| scene.nodes[j].name == full) {
            Some(k) => order.push(k),
            None => missing.push(full),
        }
    }
    if !missing.is_empty() {
        return Err(ImportError::format(
            &source,
            "skin joints",
            "the 65 bones of the Mixamo rig (docs/CONVENTIONS.md, \"Mixamo 65\")",
            format!("no {}", missing.join(", ")),
        ));
    }
    // The bind pose: each joint's world matrix when the skin was bound.
    let bind: Vec<Mat4> = order.iter().map(|&k| skin.inverse_bind_matrices[k].inverse()).collect();
    if bind.iter().any(|m| !m.is_finite()) {
        return Err(ImportError::format(
            &source,
            "inverse bind matrices",
            "invertible",
            "singular",
        ));
    }
    let rest: Vec<Vec3> = bind.iter().map(|m| m.w_axis.truncate()).collect();
    let rest_rotations: Vec<Mat3> =
        bind.iter().map(|m| orthonormalised(Mat3::from_mat4(*m))).collect();
    let offsets = builtin
        .parents()
        .iter()
        .enumerate()
        .map(|(j, p)| p.map_or(rest[j], |p| rest[j] - rest[p]))
        .collect();
    let skeleton = builtin.with_rest_offsets(offsets)?;
    let nodes: Vec<usize> = order.iter().map(|&k| skin.joints[k]).collect();
    let frames = times.len();
    let joints = nodes.len();
    let mut world_rotations = Vec::with_capacity(frames * joints);
    let mut positions = Vec::with_capacity(frames * joints);
    let object_nodes: Vec<usize> = (0..scene.nodes.len())
        .filter(|&n| scene.nodes[n].mesh.is_some() && scene.nodes[n].skin.is_none())
        .filter(|n| !nodes.contains(n))
        .collect();
    let mut object_poses: Vec<Vec<(Vec3, glam::Quat, Vec3)>> = vec![Vec::new(); object_nodes.len()];
    for &time in &times {
        let world = scene.world_matrices(time);
        for (j, &node) in nodes.iter().enumerate() {
            let m = world[node];
            positions.push(m.w_axis.truncate());
            world_rotations
                .push(orthonormalised(Mat3::from_mat4(m)) * rest_rotations[j].transpose());
        }
        for (k, &node) in object_nodes.iter().enumerate() {
            object_poses[k].push(world[node].to_scale_rotation_translation());
        }
    }
    if positions.iter().any(|p| !p.is_finite()) {
        return Err(ImportError::format(&source, "joint positions", "finite", "NaN or infinity"));
    }
    let folded = PosedRig { skeleton: skeleton.clone(), world_rotations, positions }.fold();
    let mut objects = Vec::with_capacity(object_nodes.len());
    for (node, poses) in object_nodes.into_iter().zip(object_poses) {
        let name = scene.nodes[node].name.clone();
        let scale = poses[0].0;
        if poses.iter().any(|(s, ..)| !s.abs_diff_eq(scale, 1e-4 * scale.abs().max_element()))
            || scale.min_element() <= 0.0
        {
            return Err(ImportError::format(
                &source,
                format!("object node `{name}`"),
                "a constant positive scale",
                "a scale that changes or flips",
            ));
        }
        let (vertices, faces) = scene.mesh(scene.nodes[node].mesh.unwrap_or_default()).clone();
        let mesh_name = format!("{source}[{name}]");
        objects.push(ObjectTrack {
            name,
            rotations: poses.iter().map(|(_, r, _)| Mat3::from_quat(*r)).collect(),
            translations: poses.iter().map(|(.., t)| *t).collect(),
            mesh: MeshSource::Embedded(Box::new(move || {
                let vertices = vertices.into_iter().map(|v| v * scale).collect();
                Ok(Mesh::new(vertices, faces, &mesh_name)?)
            })),
        });
    }
    Ok(Motion { skeleton, folded, objects })
}

/// The body and objects of an authors' pickle (`up_bone` rig).
fn read_pickle_motion(path: &Path, context: &Context) -> Result<Motion> {
    let options = &context.options;
    let source_name = path.display().to_string();
    if options.pickle_rig != PickleRig::UpBone {
        return Err(ImportError::invalid(
            "--humoto-rig",
            "up_bone: a pickle made with the mixamo_bone rig keeps Mixamo's own bone frames, \
             which the pickle does not store; read the sequence's published .glb instead",
            options.pickle_rig.name(),
        ));
    }
    let bytes = std::fs::read(path).map_err(ImportError::io(path))?;
    let (value, _) = read_pickle(&bytes, &source_name)?;
    let root = Field::root(&source_name, "", &value);
    let skeleton = Skeleton::humoto_character();
    let joints = skeleton.joint_count();
    let parents = skeleton.parents();
    let offsets = skeleton.rest_offsets();
    let armature = root.get("armature", "the bone transforms per frame")?.items()?;
    let frames = armature.len();
    if frames == 0 {
        return Err(ImportError::format(&source_name, "`armature`", "at least one frame", 0));
    }
    let mut world_rotations = Vec::with_capacity(frames * joints);
    let mut positions = Vec::with_capacity(frames * joints);
    for frame in &armature {
        let first = world_rotations.len();
        for (j, name) in skeleton.joint_names().iter().enumerate() {
            let prefixed = format!("{MIXAMO_PREFIX}{name}");
            let key = if frame.has(&prefixed) { prefixed } else { name.clone() };
            let values = seven(&frame.get(&key, "the bone's [qw,qx,qy,qz, x,y,z]")?)?;
            // `up_bone`: the rotation and location are already in Y-up parent axes.
            let (local, location) = pose(&values);
            let (world, position) = match parents[j] {
                Some(p) => {
                    let parent = world_rotations[first + p];
                    let parent_position: Vec3 = positions[first + p];
                    (parent * local, parent_position + parent * (offsets[j] + location))
                }
                None => (local, offsets[0] + location),
            };
            world_rotations.push(world);
            positions.push(position);
        }
    }
    let folded = PosedRig { skeleton: skeleton.clone(), world_rotations, positions }.fold();
    let to_y_up = options.up_axis().to_y_up();
    let objects_field = root.get("objects", "the object poses per frame")?;
    let models = root.has("object_models").then(|| root.get("object_models", "")).transpose()?;
    let folder = objects_dir(options);
    let mut objects = Vec::new();
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
            // Object poses are Z-up world poses: the world turns, the mesh frame stays.
            rotations.push(to_y_up * r);
            translations.push(to_y_up * t);
        }
        let mesh = match models.as_ref().filter(|m| m.has(&name)) {
            Some(models) => {
                let mesh = embedded_mesh(&models.get(&name, "the object's model")?);
                MeshSource::Embedded(Box::new(move || mesh))
            }
            None => MeshSource::File(folder.join(&name).join(format!("{name}.obj"))),
        };
        objects.push(ObjectTrack { name, rotations, translations, mesh });
    }
    Ok(Motion { skeleton, folded, objects })
}

/// The protocol's object filter, the meshes, and the sequence.
fn assemble(item: &Item, context: &Context, motion: Motion, text: String) -> Result<Outcome> {
    let Motion { skeleton, folded, objects: tracks } = motion;
    let frames = folded.root_positions.len();
    let mut moving = Vec::new();
    let mut static_count = 0;
    for track in tracks {
        if track.rotations.len() != frames {
            return Err(ImportError::format(
                item.path.display(),
                format!("object `{}`", track.name),
                format!("{frames} poses (one per body frame)"),
                track.rotations.len(),
            ));
        }
        let (r0, t0) = (track.rotations[0], track.translations[0]);
        let travels = track.translations.iter().any(|t| t.distance(t0) > MOVING_DISTANCE);
        let turns = track.rotations.iter().any(|r| geodesic_angle(r0, *r) > MOVING_ANGLE);
        if travels || turns {
            moving.push(track);
        } else {
            static_count += 1;
        }
    }
    if moving.len() > MAX_MOVING_OBJECTS {
        let names: Vec<&str> = moving.iter().map(|t| t.name.as_str()).collect();
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
    let mut objects: Vec<SequenceObject> = Vec::with_capacity(moving.len());
    for track in moving {
        let mesh = match track.mesh {
            MeshSource::Embedded(build) => {
                context.mesh_from(&item.path.join(&track.name), build)?
            }
            MeshSource::File(path) => context.mesh(&path)?,
        };
        objects.push(mesh.object(
            &track.name,
            &track.rotations,
            &track.translations,
            Mat3::IDENTITY,
        ));
    }
    let mut warnings = Vec::new();
    let (max_error, joint) = folded.max_error;
    if folded.mean_error > FOLD_WARNING {
        warnings.push(format!(
            "the rig's animated bone translations could not all be folded into rotations: \
             the joints end {:.1} mm from the file's on average ({} up to {:.1} cm)",
            folded.mean_error * 1000.0,
            skeleton.joint_names()[joint],
            max_error * 100.0,
        ));
    }
    Ok(Outcome::Sequence {
        sequence: Box::new(Sequence {
            skeleton,
            fps: FPS,
            local_rotations: folded.local_rotations,
            root_positions: folded.root_positions,
            objects,
            texts: vec![text],
            action: None,
            source_id: format!("humoto/{}", item.id),
        }),
        warnings,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::glb::glb_bytes;

    #[test]
    fn a_long_track_over_many_nodes_is_refused_before_sampling() {
        // One track of 2,000 keyframes and 2,000 nodes: 4 million poses asked of a 40 kB file
        // (scaled up, gigabytes of megabytes). The check comes first, before the skin's: this
        // file has none.
        let (frames, nodes) = (2000, 2000);
        let mut bin: Vec<u8> = (0..frames).flat_map(|k| (k as f32 / 30.0).to_le_bytes()).collect();
        bin.extend((0..frames * 3).flat_map(|_| 0.5f32.to_le_bytes()));
        let json = format!(
            r#"{{"asset":{{"version":"2.0"}},"nodes":[{}],
            "buffers":[{{"byteLength":{total}}}],
            "bufferViews":[{{"buffer":0,"byteLength":{times}}},
                           {{"buffer":0,"byteOffset":{times},"byteLength":{values}}}],
            "accessors":[{{"bufferView":0,"componentType":5126,"count":{frames},"type":"SCALAR",
                           "min":[0],"max":[{last}]}},
                         {{"bufferView":1,"componentType":5126,"count":{frames},"type":"VEC3"}}],
            "animations":[{{"channels":[{{"sampler":0,"target":{{"node":0,"path":"translation"}}}}],
                            "samplers":[{{"input":0,"output":1}}]}}]}}"#,
            vec!["{}"; nodes].join(","),
            total = frames * 16,
            times = frames * 4,
            values = frames * 12,
            last = (frames - 1) as f32 / 30.0,
        );
        let dir = std::env::temp_dir().join(format!("dex2hoi-humoto-poses-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("many_nodes.glb");
        std::fs::write(&path, glb_bytes(&json, &bin)).unwrap();
        let started = std::time::Instant::now();
        let error = read_glb(&path).err().expect("refused").to_string();
        assert!(error.contains("many_nodes.glb") && error.contains("node poses"), "{error}");
        assert!(started.elapsed().as_secs_f32() < 2.0);
        std::fs::remove_dir_all(&dir).ok();
    }
}
