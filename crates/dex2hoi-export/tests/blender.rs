//! The real-client check: `motion.glb` and `motion.bvh` imported into Blender 4.2 (the `bpy`
//! module from PyPI, installed by `scripts/setup.sh` into `target/blender-venv`) for both
//! skeletons and with and without an SMPL-X model; what Blender plays must match `motion.npz`
//! to 1 mm: bone heads against `joints` (glTF and BVH), the skinned SMPL-X mesh against an
//! `smplx`-style skinning of the npz, the objects against their poses
//! (`tools/blender_check.py` does the Blender side). Skipped without Blender, failing under
//! `CI=1`.

mod common;

use std::path::{Path, PathBuf};
use std::process::Command;

use serde_json::Value;

use dex2hoi_export::{Body, ExportMotion, ExportOptions, SmplxMesh, export_all};
use dex2hoi_repr::Skeleton;

/// What Blender may differ from our files by (metres): the 1 mm.
const JOINT_TOLERANCE: f64 = 1e-3;
/// Object rotations (radians, about 0.06 degrees).
const ROTATION_TOLERANCE: f64 = 1e-3;

/// The Python with `bpy`: `DEX2HOI_BLENDER_PYTHON`, or the virtual environment of
/// `scripts/setup.sh`.
fn blender_python() -> Option<PathBuf> {
    let python =
        std::env::var_os("DEX2HOI_BLENDER_PYTHON").map(PathBuf::from).unwrap_or_else(|| {
            Path::new(env!("CARGO_MANIFEST_DIR")).join("../../target/blender-venv/bin/python")
        });
    if python.is_file() {
        return Some(python);
    }
    assert!(!common::in_ci(), "CI needs Blender's bpy at {} (scripts/setup.sh)", python.display());
    println!("skipped: no Blender (bpy) at {} (scripts/setup.sh installs it)", python.display());
    None
}

/// Runs the Blender check on an export directory and returns its report.
fn blender_check(python: &Path, dir: &Path, model: Option<&Path>, frames: &str) -> Value {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tools/blender_check.py");
    let mut command = Command::new(python);
    command.arg(script).arg(dir).args(["--frames", frames]);
    if let Some(model) = model {
        command.arg("--model").arg(model);
    }
    let output = command.output().expect("Blender's python runs");
    let stdout = String::from_utf8_lossy(&output.stdout);
    assert!(
        output.status.success(),
        "Blender check of {} failed:\n{stdout}{}",
        dir.display(),
        String::from_utf8_lossy(&output.stderr)
    );
    let report = stdout.lines().rev().find(|l| l.starts_with('{')).expect("a JSON report");
    serde_json::from_str(report).expect("the report is JSON")
}

fn number(report: &Value, path: &[&str]) -> f64 {
    let value = path.iter().fold(report, |v, key| &v[key]);
    value.as_f64().unwrap_or_else(|| panic!("{path:?} missing in {report}"))
}

#[test]
fn blender_plays_the_glb_and_bvh_as_the_npz_says() {
    let Some(python) = blender_python() else { return };
    let dir = common::scratch_dir("blender");
    let model = dir.join("SMPLX_NEUTRAL.npz");
    common::write_smplx_model(&model, common::smplx_fixture::Spoil::None);
    let mesh = SmplxMesh::load(&model, &[1.0, -0.5]).expect("the fixture model");
    let smplx = Skeleton::smplx();
    let mixamo = Skeleton::mixamo();
    let meshes = common::object_meshes();
    let frames = 8;
    let cases: [(&str, &Skeleton, Option<&SmplxMesh>); 3] = [
        ("smplx", &smplx, None),
        ("smplx-model", &mesh.skeleton, Some(&mesh)),
        ("mixamo", &mixamo, None),
    ];
    for (name, skeleton, body) in cases {
        let motion = common::wavy_motion(skeleton, frames, 2);
        let export = ExportMotion {
            body: body.map(Body::Smplx),
            ..common::export(skeleton, &motion, &meshes, "pick up the mug")
        };
        let out = dir.join(name);
        export_all(&out, &export, &ExportOptions::default()).expect("exported");
        let report = blender_check(&python, &out, body.map(|_| model.as_path()), "0,3,7");
        println!("{name}: {report}");
        for file in ["glb", "bvh"] {
            let error = number(&report, &[file, "joint_error"]);
            assert!(error < JOINT_TOLERANCE, "{name} {file}: bone heads {error} m off");
            let bones = number(&report, &[file, "bones"]) as usize;
            let expected =
                skeleton.joint_count() + if body.is_some() && file == "glb" { 3 } else { 0 };
            assert_eq!(bones, expected, "{name} {file}");
        }
        let position = number(&report, &["glb", "object_position_error"]);
        let rotation = number(&report, &["glb", "object_rotation_error"]);
        assert!(position < JOINT_TOLERANCE, "{name}: objects {position} m off");
        assert!(rotation < ROTATION_TOLERANCE, "{name}: objects {rotation} rad off");
        if body.is_some() {
            let error = number(&report, &["glb", "mesh_error"]);
            assert!(error < JOINT_TOLERANCE, "{name}: skinned mesh {error} m off");
            assert_eq!(number(&report, &["glb", "mesh_vertices"]) as usize, mesh.vertices.len());
        }
    }
    let _ = std::fs::remove_dir_all(&dir);
}
