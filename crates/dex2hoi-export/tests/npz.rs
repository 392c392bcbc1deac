//! `motion.npz`: read back in Rust (keys, shapes, dtypes, values) and in numpy, where the
//! SMPL-X parameters are put through SMPL-X-style forward kinematics and must give the joints.

mod common;

use std::process::Command;

use glam::Vec3;
use npyz::npz::NpzArchive;

use dex2hoi_export::{encode_npz, write_npz};
use dex2hoi_repr::Skeleton;
use dex2hoi_repr::rotation::matrix_to_axis_angle;

fn read_f32(
    archive: &mut NpzArchive<std::io::Cursor<Vec<u8>>>,
    name: &str,
) -> (Vec<u64>, Vec<f32>) {
    let array =
        archive.by_name(name).expect("readable").unwrap_or_else(|| panic!("{name} missing"));
    assert_eq!(array.dtype().descr(), "'<f4'", "{name}");
    (array.shape().to_vec(), array.into_vec::<f32>().expect("f32 data"))
}

fn read_strings(
    archive: &mut NpzArchive<std::io::Cursor<Vec<u8>>>,
    name: &str,
) -> (Vec<u64>, Vec<String>) {
    let array =
        archive.by_name(name).expect("readable").unwrap_or_else(|| panic!("{name} missing"));
    assert!(array.dtype().descr().starts_with("'<U"), "{name}: {}", array.dtype().descr());
    (array.shape().to_vec(), array.into_vec::<String>().expect("strings"))
}

#[test]
fn smplx_npz_holds_the_smplx_layer_parameters_and_the_motion() {
    let skeleton = Skeleton::smplx();
    let frames = 6;
    let motion = common::wavy_motion(&skeleton, frames, 2);
    let meshes = common::object_meshes();
    let export = common::export(&skeleton, &motion, &meshes, "A person lifts the mug — twice.");
    let bytes = encode_npz(&export).expect("encoded");
    let mut archive = NpzArchive::new(std::io::Cursor::new(bytes)).expect("a zip archive");

    let (shape, transl) = read_f32(&mut archive, "transl");
    assert_eq!(shape, [frames as u64, 3]);
    let pelvis_rest = skeleton.rest_offsets()[0];
    for t in 0..frames {
        let expected = motion.root_positions[t] - pelvis_rest;
        assert!((Vec3::from_slice(&transl[3 * t..]) - expected).length() < 1e-6);
    }
    let (shape, body_pose) = read_f32(&mut archive, "body_pose");
    assert_eq!(shape, [frames as u64, 63]);
    let (_, global_orient) = read_f32(&mut archive, "global_orient");
    let (shape, left) = read_f32(&mut archive, "left_hand_pose");
    assert_eq!(shape, [frames as u64, 45]);
    let (_, right) = read_f32(&mut archive, "right_hand_pose");
    let joints = skeleton.joint_count();
    let aa = |t: usize, j: usize| matrix_to_axis_angle(motion.local_rotations[t * joints + j]);
    let close =
        |values: &[f32], expected: Vec3| (Vec3::from_slice(values) - expected).length() < 1e-6;
    for t in 0..frames {
        assert!(close(&global_orient[3 * t..], aa(t, 0)));
        for j in 1..=21 {
            assert!(close(&body_pose[63 * t + 3 * (j - 1)..], aa(t, j)), "body joint {j}");
        }
        for k in 0..15 {
            // 52-joint order: left hand 22..37, right hand 37..52 (SMPL-X 25..40, 40..55).
            assert!(close(&left[45 * t + 3 * k..], aa(t, 22 + k)), "left hand joint {k}");
            assert!(close(&right[45 * t + 3 * k..], aa(t, 37 + k)), "right hand joint {k}");
        }
    }
    for (name, width) in [("jaw_pose", 3), ("leye_pose", 3), ("reye_pose", 3), ("expression", 10)] {
        let (shape, values) = read_f32(&mut archive, name);
        assert_eq!(shape, [frames as u64, width]);
        assert!(values.iter().all(|&v| v == 0.0));
    }
    let (shape, positions) = read_f32(&mut archive, "joints");
    assert_eq!(shape, [frames as u64, joints as u64, 3]);
    for (i, p) in motion.joints.positions.iter().enumerate() {
        assert!((Vec3::from_slice(&positions[3 * i..]) - *p).length() < 1e-5);
    }
    let (shape, rotations) = read_f32(&mut archive, "local_rotations");
    assert_eq!(shape, [frames as u64, joints as u64, 3, 3]);
    // Row-major: entry (row 0, column 1) of frame 0, joint 5.
    assert_eq!(rotations[5 * 9 + 1], motion.local_rotations[5].col(1).x);
    let (shape, object_rotations) = read_f32(&mut archive, "object_rotations");
    assert_eq!(shape, [2, frames as u64, 3, 3]);
    let second = motion.objects[1].as_ref().expect("slot 1").0[3];
    assert_eq!(object_rotations[(frames + 3) * 9 + 2], second.col(2).x);
    let (shape, _) = read_f32(&mut archive, "object_translations");
    assert_eq!(shape, [2, frames as u64, 3]);
    let (shape, names) = read_strings(&mut archive, "object_names");
    assert_eq!((shape, names), (vec![2], vec!["mug".to_string(), "tall box".to_string()]));
    let (shape, text) = read_strings(&mut archive, "text");
    assert_eq!((shape, text), (vec![], vec!["A person lifts the mug — twice.".to_string()]));
    let (_, fps) = read_f32(&mut archive, "fps");
    assert_eq!(fps, [20.0]);
    let (_, kind) = read_strings(&mut archive, "skeleton");
    assert_eq!(kind, ["smplx52"]);
}

#[test]
fn mixamo_npz_has_the_motion_but_no_smplx_parameters() {
    let skeleton = Skeleton::mixamo();
    let motion = common::wavy_motion(&skeleton, 3, 0);
    let export = common::export(&skeleton, &motion, &[], "");
    let mut archive =
        NpzArchive::new(std::io::Cursor::new(encode_npz(&export).expect("encoded"))).expect("zip");
    let names: Vec<String> = archive.array_names().map(String::from).collect();
    for absent in ["global_orient", "body_pose", "transl", "left_hand_pose"] {
        assert!(!names.iter().any(|n| n == absent), "{absent} in {names:?}");
    }
    let (shape, _) = read_f32(&mut archive, "poses");
    assert_eq!(shape, [3, 65, 3]);
    let (shape, _) = read_f32(&mut archive, "object_rotations");
    assert_eq!(shape, [0, 3, 3, 3]);
    let (shape, names) = read_strings(&mut archive, "joint_names");
    assert_eq!(shape, [65]);
    assert_eq!(names[0], "Hips");
}

/// Loads the archive with numpy (no pickle), checks every key's shape and dtype, and runs
/// SMPL-X-style forward kinematics on the SMPL-X parameters: rotations about the rest pelvis
/// plus `transl`, children by `parents` and `rest_offsets`. Exit code 3: numpy is missing.
const NUMPY_CHECK: &str = r#"
import sys
try:
    import numpy as np
except ImportError:
    sys.exit(3)
path, kind, T, K, text = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4]), sys.argv[5]
d = np.load(path)
J = len(d["joint_names"])
f32 = np.dtype("<f4")
common = {"rest_offsets": (J, 3), "local_rotations": (T, J, 3, 3), "poses": (T, J, 3),
          "root_positions": (T, 3), "joints": (T, J, 3), "fps": (),
          "object_rotations": (K, T, 3, 3), "object_translations": (K, T, 3)}
smplx = {"global_orient": (T, 3), "body_pose": (T, 63), "left_hand_pose": (T, 45),
         "right_hand_pose": (T, 45), "transl": (T, 3), "jaw_pose": (T, 3), "leye_pose": (T, 3),
         "reye_pose": (T, 3), "expression": (T, 10), "pelvis_rest": (3,)}
for key, shape in common.items():
    assert d[key].shape == shape and d[key].dtype == f32, (key, d[key].shape, d[key].dtype)
assert d["parents"].dtype == np.dtype("<i8") and d["parents"][0] == -1
assert d["object_slots"].shape == (K,) and d["object_slots"].dtype == np.dtype("<i8")
assert d["object_names"].dtype.kind == "U" and d["object_names"].shape == (K,)
assert str(d["text"]) == text, (str(d["text"]), text)
assert str(d["skeleton"]) == kind
assert float(d["fps"]) == 20.0

def rodrigues(v):
    theta = np.linalg.norm(v, axis=-1, keepdims=True)[..., None]
    k = v / np.maximum(theta[..., 0], 1e-12)
    K = np.zeros(v.shape[:-1] + (3, 3))
    K[..., 0, 1], K[..., 0, 2], K[..., 1, 2] = -k[..., 2], k[..., 1], -k[..., 0]
    K = K - np.swapaxes(K, -1, -2)
    return np.eye(3) + np.sin(theta) * K + (1 - np.cos(theta)) * K @ K

R = d["local_rotations"].astype(np.float64)
assert np.abs(rodrigues(d["poses"].astype(np.float64)) - R).max() < 1e-5
if kind == "smplx52":
    for key, shape in smplx.items():
        assert d[key].shape == shape and d[key].dtype == f32, (key, d[key].shape, d[key].dtype)
    names = list(d["joint_names"])
    assert names[21] == "right_wrist" and names[22] == "left_index1" and names[37] == "right_index1"
    full = np.concatenate([d["global_orient"][:, None], d["body_pose"].reshape(T, 21, 3),
                           d["left_hand_pose"].reshape(T, 15, 3),
                           d["right_hand_pose"].reshape(T, 15, 3)], axis=1).astype(np.float64)
    R = rodrigues(full)
    parents, offsets = d["parents"], d["rest_offsets"].astype(np.float64)
    G, P = np.zeros((T, J, 3, 3)), np.zeros((T, J, 3))
    for j in range(J):
        if parents[j] < 0:
            G[:, j], P[:, j] = R[:, j], d["transl"] + d["pelvis_rest"]
        else:
            p = parents[j]
            G[:, j] = G[:, p] @ R[:, j]
            P[:, j] = P[:, p] + G[:, p] @ offsets[j]
    error = np.abs(P - d["joints"]).max()
    assert error < 1e-4, error
else:
    assert "body_pose" not in d.files and "transl" not in d.files
print("numpy check passed:", kind, sorted(d.files))
"#;

fn numpy_check(path: &std::path::Path, kind: &str, frames: usize, objects: usize, text: &str) {
    let args =
        [path.to_str().expect("utf-8 path"), kind, &frames.to_string(), &objects.to_string(), text];
    let output = match Command::new("python3").arg("-c").arg(NUMPY_CHECK).args(args).output() {
        Ok(output) => output,
        Err(error) if !common::in_ci() => {
            println!("skipped: python3 is not available ({error})");
            return;
        }
        Err(error) => panic!("CI needs python3 for the numpy check: {error}"),
    };
    if output.status.code() == Some(3) {
        assert!(!common::in_ci(), "CI needs numpy for the numpy check (scripts/setup.sh)");
        println!("skipped: numpy is not installed");
        return;
    }
    assert!(
        output.status.success(),
        "numpy check failed:\n{}{}",
        String::from_utf8_lossy(&output.stdout),
        String::from_utf8_lossy(&output.stderr)
    );
    println!("{}", String::from_utf8_lossy(&output.stdout));
}

#[test]
fn numpy_loads_the_npz_and_smplx_kinematics_reproduce_the_joints() {
    let dir = common::scratch_dir("numpy");
    let meshes = common::object_meshes();
    let smplx = Skeleton::smplx();
    let motion = common::wavy_motion(&smplx, 7, 2);
    let text = "Someone pours from the bottle into the bowl.";
    let path = dir.join("smplx.npz");
    write_npz(&path, &common::export(&smplx, &motion, &meshes, text)).expect("written");
    numpy_check(&path, "smplx52", 7, 2, text);

    let mixamo = Skeleton::mixamo();
    let motion = common::wavy_motion(&mixamo, 4, 1);
    let path = dir.join("mixamo.npz");
    write_npz(&path, &common::export(&mixamo, &motion, &meshes[..1], "")).expect("written");
    numpy_check(&path, "mixamo65", 4, 1, "");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn the_same_motion_gives_the_same_bytes() {
    let skeleton = Skeleton::smplx();
    let motion = common::wavy_motion(&skeleton, 3, 1);
    let meshes = common::object_meshes();
    let export = common::export(&skeleton, &motion, &meshes[..1], "x");
    assert_eq!(encode_npz(&export).expect("first"), encode_npz(&export).expect("second"));
}
