//! `motion.glb`: the container and document are parsed back (header, chunks, accessors, skin,
//! animation) and the animated node transforms reproduce the joint positions; the Khronos glTF
//! validator (`tools/gltf-validator`, installed by `scripts/setup.sh`) reports no errors.

mod common;

use std::path::{Path, PathBuf};
use std::process::Command;

use glam::{Mat4, Quat, Vec3};
use serde_json::Value;

use dex2hoi_export::{encode_glb, write_glb};
use dex2hoi_repr::Skeleton;

/// The JSON document and the binary chunk of a GLB, with the container checked.
fn parse_glb(bytes: &[u8]) -> (Value, Vec<u8>) {
    let word = |at: usize| u32::from_le_bytes(bytes[at..at + 4].try_into().expect("4 bytes"));
    assert_eq!(&bytes[0..4], b"glTF");
    assert_eq!(word(4), 2, "version");
    assert_eq!(word(8) as usize, bytes.len(), "total length");
    let json_length = word(12) as usize;
    assert_eq!(&bytes[16..20], b"JSON");
    assert_eq!(json_length % 4, 0);
    let json: Value = serde_json::from_slice(&bytes[20..20 + json_length]).expect("JSON chunk");
    let bin_at = 20 + json_length;
    let bin_length = word(bin_at) as usize;
    assert_eq!(&bytes[bin_at + 4..bin_at + 8], b"BIN\0");
    assert_eq!(bin_length % 4, 0);
    assert_eq!(bin_at + 8 + bin_length, bytes.len());
    (json, bytes[bin_at + 8..].to_vec())
}

fn component_size(component: u64) -> usize {
    match component {
        5121 => 1,
        5123 => 2,
        5125 | 5126 => 4,
        other => panic!("unexpected component type {other}"),
    }
}

fn components(kind: &str) -> usize {
    match kind {
        "SCALAR" => 1,
        "VEC3" => 3,
        "VEC4" => 4,
        "MAT4" => 16,
        other => panic!("unexpected accessor type {other}"),
    }
}

/// The floats of a float accessor.
fn floats(json: &Value, bin: &[u8], accessor: usize) -> Vec<f32> {
    let accessor = &json["accessors"][accessor];
    assert_eq!(accessor["componentType"], 5126);
    let view = &json["bufferViews"][accessor["bufferView"].as_u64().expect("view") as usize];
    let start = view["byteOffset"].as_u64().expect("offset") as usize;
    let length = view["byteLength"].as_u64().expect("length") as usize;
    bin[start..start + length]
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes(b.try_into().expect("4 bytes")))
        .collect()
}

#[test]
fn the_glb_document_is_complete_and_its_animation_reproduces_the_joints() {
    let skeleton = Skeleton::smplx();
    let frames = 4;
    let motion = common::wavy_motion(&skeleton, frames, 2);
    let meshes = common::object_meshes();
    let export = common::export(&skeleton, &motion, &meshes, "lift");
    let (json, bin) = parse_glb(&encode_glb(&export).expect("encoded"));
    let joints = skeleton.joint_count();

    assert_eq!(json["asset"]["version"], "2.0");
    assert_eq!(json["buffers"][0]["byteLength"].as_u64(), Some(bin.len() as u64));
    assert_eq!(json["scenes"][0]["extras"]["text"], "lift");
    let nodes = json["nodes"].as_array().expect("nodes");
    assert_eq!(nodes.len(), joints + 1 + 2);
    assert_eq!(nodes[joints]["skin"], 0);
    assert_eq!(nodes[joints + 1]["name"], "mug");
    let skin = &json["skins"][0];
    assert_eq!(skin["joints"].as_array().expect("joints").len(), joints);
    // Every accessor fits its buffer view, which fits the buffer.
    for accessor in json["accessors"].as_array().expect("accessors") {
        let view = &json["bufferViews"][accessor["bufferView"].as_u64().expect("view") as usize];
        let size = accessor["count"].as_u64().expect("count") as usize
            * component_size(accessor["componentType"].as_u64().expect("component"))
            * components(accessor["type"].as_str().expect("type"));
        assert_eq!(view["byteLength"].as_u64(), Some(size as u64));
        let end = view["byteOffset"].as_u64().expect("offset") as usize + size;
        assert!(end <= bin.len());
    }
    // POSITION bounds are exact.
    let body = &json["meshes"][0]["primitives"][0];
    let position = body["attributes"]["POSITION"].as_u64().expect("POSITION") as usize;
    let values = floats(&json, &bin, position);
    for k in 0..3 {
        let min = values.iter().skip(k).step_by(3).fold(f32::MAX, |a, &b| a.min(b));
        // serde_json's float parsing may miss the last bit of an f64; the f32 must be exact.
        assert_eq!(json["accessors"][position]["min"][k].as_f64().map(|v| v as f32), Some(min));
    }
    let weights =
        floats(&json, &bin, body["attributes"]["WEIGHTS_0"].as_u64().expect("w") as usize);
    assert!(weights.chunks_exact(4).all(|w| w.iter().sum::<f32>() == 1.0));
    // Inverse bind matrices undo the rest positions.
    let binds = floats(&json, &bin, skin["inverseBindMatrices"].as_u64().expect("ibm") as usize);
    let rest = skeleton.rest_positions();
    for j in 0..joints {
        let bind = Mat4::from_cols_slice(&binds[16 * j..16 * j + 16]);
        assert!((bind.transform_point3(rest[j])).length() < 1e-6);
    }

    // The animation: node transforms at each frame give the FK joint positions.
    let animation = &json["animations"][0];
    let channels = animation["channels"].as_array().expect("channels");
    assert_eq!(channels.len(), 1 + joints + 2 * 2);
    let mut translations: Vec<Vec<Vec3>> = nodes
        .iter()
        .map(|n| {
            let t = n.get("translation").map_or(Vec3::ZERO, |t| {
                Vec3::new(
                    t[0].as_f64().unwrap_or(0.0) as f32,
                    t[1].as_f64().unwrap_or(0.0) as f32,
                    t[2].as_f64().unwrap_or(0.0) as f32,
                )
            });
            vec![t; frames]
        })
        .collect();
    let mut rotations: Vec<Vec<Quat>> = vec![vec![Quat::IDENTITY; frames]; nodes.len()];
    for channel in channels {
        let sampler =
            &animation["samplers"][channel["sampler"].as_u64().expect("sampler") as usize];
        let input = floats(&json, &bin, sampler["input"].as_u64().expect("input") as usize);
        assert_eq!(input, (0..frames).map(|t| t as f32 / 20.0).collect::<Vec<_>>());
        let output = floats(&json, &bin, sampler["output"].as_u64().expect("output") as usize);
        let node = channel["target"]["node"].as_u64().expect("node") as usize;
        match channel["target"]["path"].as_str().expect("path") {
            "translation" => {
                translations[node] = output.chunks_exact(3).map(Vec3::from_slice).collect()
            }
            "rotation" => {
                rotations[node] = output.chunks_exact(4).map(Quat::from_slice).collect();
                assert!(rotations[node].iter().all(|q| (q.length() - 1.0).abs() < 1e-6));
            }
            other => panic!("unexpected path {other}"),
        }
    }
    let mut worst = 0.0f32;
    for t in 0..frames {
        let mut world = vec![Mat4::IDENTITY; joints];
        for j in 0..joints {
            let local = Mat4::from_rotation_translation(rotations[j][t], translations[j][t]);
            world[j] = skeleton.parents()[j].map_or(local, |p| world[p] * local);
            worst = worst.max((world[j].w_axis.truncate() - motion.joints.position(t, j)).length());
        }
        let (object_rotations, object_positions) = motion.objects[1].as_ref().expect("slot 1");
        assert!((translations[joints + 2][t] - object_positions[t]).length() < 1e-6);
        let expected = Quat::from_mat3(&object_rotations[t]);
        assert!(rotations[joints + 2][t].dot(expected).abs() > 1.0 - 1e-6);
    }
    assert!(worst < 1e-5, "animated joints differ from FK by {worst} m");
}

/// The validator's directory, or why it cannot run.
fn validator() -> Result<PathBuf, String> {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("tools/gltf-validator");
    if !dir.join("node_modules/gltf-validator").is_dir() {
        return Err(format!("{} has no node_modules (run scripts/setup.sh)", dir.display()));
    }
    match Command::new("node").arg("--version").output() {
        Ok(output) if output.status.success() => Ok(dir),
        _ => Err("node is not installed".into()),
    }
}

/// Runs the Khronos validator on a file and returns its report.
fn validate(path: &Path) -> Option<Value> {
    let dir = match validator() {
        Ok(dir) => dir,
        Err(why) if !common::in_ci() => {
            println!("skipped: the glTF validator cannot run: {why}");
            return None;
        }
        Err(why) => panic!("CI needs the glTF validator: {why}"),
    };
    let output =
        Command::new("node").arg(dir.join("validate.cjs")).arg(path).output().expect("node runs");
    let report: Value = serde_json::from_slice(&output.stdout)
        .unwrap_or_else(|e| panic!("no report ({e}): {}", String::from_utf8_lossy(&output.stderr)));
    Some(report)
}

#[test]
fn the_khronos_validator_finds_no_errors_or_warnings() {
    let dir = common::scratch_dir("glb");
    let smplx = Skeleton::smplx();
    let wavy = common::wavy_motion(&smplx, 6, 2);
    let meshes = common::object_meshes();
    let (synth, synth_motion) = common::synth_motion(5);
    let mixamo = Skeleton::mixamo();
    let mixamo_motion = common::wavy_motion(&mixamo, 1, 0);
    let cases = [
        ("wavy", common::export(&smplx, &wavy, &meshes, "two objects")),
        ("synth", common::synth_export(&synth, &synth_motion)),
        ("mixamo-one-frame", common::export(&mixamo, &mixamo_motion, &[], "")),
    ];
    for (name, export) in cases {
        let path = dir.join(format!("{name}.glb"));
        write_glb(&path, &export).expect("written");
        let Some(report) = validate(&path) else { return };
        let issues = &report["issues"];
        let messages: Vec<String> = issues["messages"]
            .as_array()
            .map(|m| {
                m.iter()
                    .map(|i| format!("{} {} {}", i["severity"], i["code"], i["pointer"]))
                    .collect()
            })
            .unwrap_or_default();
        println!(
            "{name}: {} errors, {} warnings, {} infos, {} hints",
            issues["numErrors"], issues["numWarnings"], issues["numInfos"], issues["numHints"]
        );
        assert_eq!(issues["numErrors"], 0, "{name}: {messages:#?}");
        assert_eq!(issues["numWarnings"], 0, "{name}: {messages:#?}");
        assert_eq!(report["info"]["animationCount"], 1, "{name}");
        assert_eq!(report["info"]["hasSkins"], true, "{name}");
    }
    let _ = std::fs::remove_dir_all(&dir);
}
