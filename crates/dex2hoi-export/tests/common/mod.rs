//! Motions shared by the integration tests.
#![allow(dead_code)]

use std::path::{Path, PathBuf};
use std::process::Command;

use serde_json::Value;

use glam::{Mat3, Vec3};

use dex2hoi_data::features::DecodedMotion;
use dex2hoi_export::{ExportMotion, ExportObject};
use dex2hoi_repr::mesh::box_mesh;
use dex2hoi_repr::rotation::axis_angle_to_matrix;
use dex2hoi_repr::{Mesh, Skeleton, forward_kinematics};
use dex2hoi_synth::{self as synth, SynthSequence};

pub mod gltf;
pub use dex2hoi_testkit::smplx_fixture;

/// Writes the fixture SMPL-X model ([`smplx_fixture`]) on the built-in skeleton.
pub fn write_smplx_model(path: &Path, spoil: smplx_fixture::Spoil) {
    let skeleton = Skeleton::smplx();
    let mesh = dex2hoi_export::body_mesh(&skeleton);
    let bound = smplx_fixture::BoundMesh {
        vertices: &mesh.vertices,
        joints: &mesh.joints,
        bone_ends: &mesh.bone_ends,
        faces: &mesh.faces,
    };
    smplx_fixture::write_smplx_model(
        path,
        &skeleton.rest_positions(),
        skeleton.parents(),
        bound,
        spoil,
    );
}

/// An empty scratch directory for one test.
pub fn scratch_dir(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("dex2hoi-export-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).expect("a scratch directory");
    dir
}

/// Whether the test runs in CI, where optional tools must be present.
pub fn in_ci() -> bool {
    std::env::var_os("CI").is_some_and(|v| !v.is_empty() && v != "0" && v != "false")
}

/// A smooth, deterministic, far-from-rest motion: every joint turns by up to about 1 rad about
/// an axis of its own, the root walks forward.
pub fn wavy_motion(skeleton: &Skeleton, frames: usize, objects: usize) -> DecodedMotion {
    let joints = skeleton.joint_count();
    let local_rotations: Vec<Mat3> = (0..frames)
        .flat_map(|t| {
            (0..joints).map(move |j| {
                let phase = t as f32 * 0.21 + j as f32 * 0.7;
                axis_angle_to_matrix(Vec3::new(
                    0.9 * (phase * 1.3).sin(),
                    0.7 * (phase + 1.0).cos(),
                    0.5 * (phase * 0.7 + 2.0).sin(),
                ))
            })
        })
        .collect();
    let root_positions: Vec<Vec3> = (0..frames)
        .map(|t| {
            skeleton.rest_offsets()[0]
                + Vec3::new(0.02 * t as f32, 0.01 * (t as f32).sin(), 0.03 * t as f32)
        })
        .collect();
    let joints_fk = forward_kinematics(skeleton, &local_rotations, &root_positions).expect("FK");
    let object_poses = |slot: usize| {
        (slot < objects).then(|| {
            (0..frames)
                .map(|t| {
                    let rotation =
                        axis_angle_to_matrix(Vec3::new(0.1, 0.3 * t as f32, slot as f32));
                    let position = Vec3::new(0.3 - 0.6 * slot as f32, 0.9 + 0.01 * t as f32, 0.45);
                    (rotation, position)
                })
                .unzip()
        })
    };
    DecodedMotion {
        local_rotations,
        root_positions,
        joints: joints_fk,
        objects: [object_poses(0), object_poses(1)],
    }
}

/// Object meshes of the wavy motion's slots.
pub fn object_meshes() -> [Mesh; 2] {
    [box_mesh(Vec3::new(0.05, 0.08, 0.04)), dex2hoi_data::catalogue::cylinder_mesh(0.04, 0.1, 16)]
}

/// An export of the wavy motion with `objects.len()` objects in slots 0, 1.
pub fn export<'a>(
    skeleton: &'a Skeleton,
    motion: &'a DecodedMotion,
    meshes: &'a [Mesh],
    text: &str,
) -> ExportMotion<'a> {
    let names = ["mug", "tall box"];
    ExportMotion {
        skeleton,
        fps: 20.0,
        prompts: vec![(0, text.into())],
        motion,
        objects: meshes
            .iter()
            .enumerate()
            .map(|(slot, mesh)| ExportObject { name: names[slot].into(), mesh, slot })
            .collect(),
        body: None,
    }
}

/// A procedural sequence (character at a table with its objects) as a decoded motion.
pub fn synth_motion(index: usize) -> (SynthSequence, DecodedMotion) {
    let synth = synth::generate(index, 7, 20.0).expect("a procedural sequence");
    let sequence = &synth.sequence;
    let fk =
        forward_kinematics(&sequence.skeleton, &sequence.local_rotations, &sequence.root_positions)
            .expect("FK");
    let poses = |slot: usize| {
        sequence.objects.get(slot).map(|o| (o.rotations.clone(), o.translations.clone()))
    };
    let motion = DecodedMotion {
        local_rotations: sequence.local_rotations.clone(),
        root_positions: sequence.root_positions.clone(),
        joints: fk,
        objects: [poses(0), poses(1)],
    };
    (synth, motion)
}

/// The export of a procedural sequence.
pub fn synth_export<'a>(synth: &'a SynthSequence, motion: &'a DecodedMotion) -> ExportMotion<'a> {
    let sequence = &synth.sequence;
    ExportMotion {
        skeleton: &sequence.skeleton,
        fps: sequence.fps,
        prompts: vec![(0, sequence.texts[0].clone())],
        motion,
        objects: sequence
            .objects
            .iter()
            .enumerate()
            .map(|(slot, o)| ExportObject { name: o.name.clone(), mesh: &o.mesh, slot })
            .collect(),
        body: None,
    }
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
        Err(why) if !in_ci() => {
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

/// Runs the Khronos validator on a GLB and asserts no errors or warnings, one animation and a
/// skin; `false` when the validator cannot run here (outside CI).
pub fn validator_is_clean(path: &Path, name: &str) -> bool {
    let Some(report) = validate(path) else { return false };
    let issues = &report["issues"];
    let messages: Vec<String> = issues["messages"]
        .as_array()
        .map(|m| {
            m.iter().map(|i| format!("{} {} {}", i["severity"], i["code"], i["pointer"])).collect()
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
    true
}
