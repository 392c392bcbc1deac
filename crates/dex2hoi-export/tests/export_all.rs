//! `export_all`: the five files appear together, complete, with nothing else beside them; bad
//! input is a clear error that writes nothing and leaves earlier files alone.

mod common;

use glam::{Mat3, Vec3};

use dex2hoi_export::{
    BVH_FILE, ExportMotion, ExportObject, ExportOptions, GIF_FILE, GLB_FILE, NPZ_FILE, PNG_FILE,
    export_all,
};
use dex2hoi_repr::Skeleton;

fn listing(dir: &std::path::Path) -> Vec<String> {
    let mut names: Vec<String> = std::fs::read_dir(dir)
        .map(|entries| {
            entries.map(|e| e.expect("entry").file_name().to_string_lossy().into_owned()).collect()
        })
        .unwrap_or_default();
    names.sort();
    names
}

#[test]
fn a_procedural_sequence_exports_five_complete_files() {
    let (synth, motion) = common::synth_motion(1);
    let export = common::synth_export(&synth, &motion);
    let dir = common::scratch_dir("all").join("nested/out");
    let files = export_all(&dir, &export, &ExportOptions::default()).expect("exported");
    assert_eq!(files.npz, dir.join(NPZ_FILE));
    assert_eq!(listing(&dir), [BVH_FILE, GLB_FILE, NPZ_FILE, GIF_FILE, PNG_FILE]);
    let npz = std::fs::read(&files.npz).expect("npz");
    assert_eq!(&npz[..4], b"PK\x03\x04");
    assert_eq!(&std::fs::read(&files.glb).expect("glb")[..4], b"glTF");
    assert!(std::fs::read_to_string(&files.bvh).expect("bvh").starts_with("HIERARCHY\n"));
    assert_eq!(&std::fs::read(&files.gif).expect("gif")[..6], b"GIF89a");
    assert_eq!(&std::fs::read(&files.png).expect("png")[..4], b"\x89PNG");
    let _ = std::fs::remove_dir_all(dir.parent().and_then(|d| d.parent()).expect("scratch"));
}

#[test]
fn bad_input_is_a_clear_error_and_writes_nothing() {
    let skeleton = Skeleton::smplx();
    let frames = 3;
    let good = common::wavy_motion(&skeleton, frames, 1);
    let meshes = common::object_meshes();
    let dir = common::scratch_dir("bad");
    // An earlier export stays as it was.
    let earlier = dir.join("earlier");
    export_all(
        &earlier,
        &common::export(&skeleton, &good, &meshes[..1], "ok"),
        &ExportOptions::default(),
    )
    .expect("exported");
    let before: Vec<Vec<u8>> =
        listing(&earlier).iter().map(|n| std::fs::read(earlier.join(n)).expect("read")).collect();

    let mut not_rotation = good.clone();
    not_rotation.local_rotations[4] = Mat3::from_diagonal(Vec3::new(1.0, 1.0, 2.0));
    let mut nan_root = good.clone();
    nan_root.root_positions[2].y = f32::NAN;
    let mut short_object = good.clone();
    if let Some((rotations, _)) = &mut short_object.objects[0] {
        rotations.pop();
    }
    let mut missing_rotations = good.clone();
    missing_rotations.local_rotations.truncate(10);
    let cases: Vec<(ExportMotion<'_>, &str)> = vec![
        (
            common::export(&skeleton, &not_rotation, &meshes[..1], ""),
            "joint 4 (left_knee) at frame 0",
        ),
        (common::export(&skeleton, &nan_root, &meshes[..1], ""), "root position at frame 2"),
        (common::export(&skeleton, &short_object, &meshes[..1], ""), "poses of object mug"),
        (common::export(&skeleton, &missing_rotations, &meshes[..1], ""), "156 matrices"),
        (common::export(&skeleton, &good, &meshes, ""), "slot of object tall box"),
        (
            ExportMotion {
                objects: vec![
                    ExportObject { name: "a".into(), mesh: &meshes[0], slot: 0 },
                    ExportObject { name: "a".into(), mesh: &meshes[1], slot: 1 },
                ],
                ..common::export(&skeleton, &good, &[], "")
            },
            "each used once",
        ),
        (ExportMotion { fps: f32::NAN, ..common::export(&skeleton, &good, &[], "") }, "frame rate"),
    ];
    for (case, (export, expected)) in cases.iter().enumerate() {
        let target = dir.join(format!("case{case}"));
        let error = export_all(&target, export, &ExportOptions::default()).expect_err("bad input");
        println!("case {case}: {error}");
        assert_eq!(export.validate().expect_err("invalid").to_string(), error.to_string());
        assert!(error.to_string().contains(expected), "case {case}: {error}");
        assert!(!target.exists(), "case {case} created {}", target.display());
        let error = export_all(&earlier, export, &ExportOptions::default()).expect_err("bad input");
        assert!(error.to_string().contains(expected), "case {case}: {error}");
    }
    let after: Vec<Vec<u8>> =
        listing(&earlier).iter().map(|n| std::fs::read(earlier.join(n)).expect("read")).collect();
    assert_eq!(before, after);
    assert_eq!(listing(&earlier).len(), 5);
    let _ = std::fs::remove_dir_all(&dir);
}
