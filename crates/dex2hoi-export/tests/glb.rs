//! `motion.glb`: the container and document are parsed back (header, chunks, accessors, skin,
//! animation) and the animated node transforms reproduce the joint positions; the Khronos glTF
//! validator (`tools/gltf-validator`, installed by `scripts/setup.sh`) reports no errors.

mod common;

use glam::{Mat4, Quat};

use dex2hoi_data::features::DecodedMotion;
use dex2hoi_export::{encode_glb, write_glb};
use dex2hoi_repr::Skeleton;
use dex2hoi_repr::skeleton::HUMOTO_REST_ORIENTATIONS;

use common::gltf::{component_size, components, floats, node_worlds, parse_glb};

/// The largest distance between an animated joint node and the motion's FK joint.
fn worst_joint_error(worlds: &[Vec<Mat4>], motion: &DecodedMotion, joints: usize) -> f32 {
    let mut worst = 0.0f32;
    for (t, world) in worlds.iter().enumerate() {
        for (j, matrix) in world.iter().take(joints).enumerate() {
            worst = worst.max((matrix.w_axis.truncate() - motion.joints.position(t, j)).length());
        }
    }
    worst
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
    for channel in channels {
        let sampler =
            &animation["samplers"][channel["sampler"].as_u64().expect("sampler") as usize];
        let input = floats(&json, &bin, sampler["input"].as_u64().expect("input") as usize);
        assert_eq!(input, (0..frames).map(|t| t as f32 / 20.0).collect::<Vec<_>>());
    }
    let worlds = node_worlds(&json, &bin, frames);
    let worst = worst_joint_error(&worlds, &motion, joints);
    for (t, world) in worlds.iter().enumerate() {
        let (object_rotations, object_positions) = motion.objects[1].as_ref().expect("slot 1");
        let (_, rotation, translation) = world[joints + 2].to_scale_rotation_translation();
        assert!((translation - object_positions[t]).length() < 1e-6);
        let expected = Quat::from_mat3(&object_rotations[t]);
        assert!(rotation.dot(expected).abs() > 1.0 - 1e-6);
    }
    assert!(worst < 1e-5, "animated joints differ from FK by {worst} m");
}

#[test]
fn mixamo_bones_have_mixamo_names_and_rest_frames_and_play_the_motion() {
    let skeleton = Skeleton::mixamo();
    let frames = 3;
    let motion = common::wavy_motion(&skeleton, frames, 1);
    let meshes = common::object_meshes();
    let export = common::export(&skeleton, &motion, &meshes[..1], "");
    let (json, bin) = parse_glb(&encode_glb(&export).expect("encoded"));
    let nodes = json["nodes"].as_array().expect("nodes");
    let joints = skeleton.joint_count();
    // Mixamo's names, in the skin's order.
    for (j, name) in skeleton.joint_names().iter().enumerate() {
        assert_eq!(nodes[j]["name"], format!("mixamorig:{name}"));
    }
    assert_eq!(nodes[0]["name"], "mixamorig:Hips");
    assert_eq!(nodes[10]["name"], "mixamorig:LeftHand");
    // Bind pose: each bone at its rest position in Mixamo's rest frame.
    let skin = &json["skins"][0];
    let binds = floats(&json, &bin, skin["inverseBindMatrices"].as_u64().expect("ibm") as usize);
    let rest = skeleton.rest_positions();
    for (name, [x, y, z, w]) in HUMOTO_REST_ORIENTATIONS {
        let j = skeleton.joint_index(name).expect("a Mixamo bone");
        let bind = Mat4::from_cols_slice(&binds[16 * j..16 * j + 16]).inverse();
        let (_, rotation, translation) = bind.to_scale_rotation_translation();
        assert!((translation - rest[j]).length() < 1e-5, "{name}");
        assert!(rotation.dot(Quat::from_xyzw(x, y, z, w)).abs() > 1.0 - 1e-6, "{name}");
    }
    // The nodes' own TRS is the bind pose (rest translations and rotations in the parent's
    // frame), and the animation still gives our joint positions.
    let static_nodes = {
        let mut doc = json.clone();
        doc["animations"][0]["channels"] = serde_json::json!([]);
        node_worlds(&doc, &bin, 1).remove(0)
    };
    for j in 0..joints {
        let bind = Mat4::from_cols_slice(&binds[16 * j..16 * j + 16]).inverse();
        let gap =
            (static_nodes[j] - bind).to_cols_array().iter().fold(0.0f32, |m, v| m.max(v.abs()));
        assert!(gap < 1e-5, "joint {j}: rest node transform differs from the bind pose by {gap}");
    }
    let worst = worst_joint_error(&node_worlds(&json, &bin, frames), &motion, joints);
    assert!(worst < 1e-5, "animated joints differ from FK by {worst} m");
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
        if !common::validator_is_clean(&path, name) {
            return;
        }
    }
    let _ = std::fs::remove_dir_all(&dir);
}
