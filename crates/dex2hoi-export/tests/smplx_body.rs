//! The SMPL-X body mesh in `motion.glb` from a user's model file (here the fixture model of
//! `common::smplx_fixture`): the skinned vertices the GLB's own data give (inverse bind
//! matrices, weights, node animation) equal numpy's linear blend skinning of the model with
//! the npz's parameters, the npz's `joints` equal the model's kinematics, the validator is
//! clean, and a broken model file is a clear error that writes nothing.

mod common;

use std::path::Path;
use std::process::Command;

use dex2hoi_export::{
    Body, ExportMotion, ExportOptions, PreviewOptions, SmplxMesh, Surface, export_all,
    render_preview,
};
use dex2hoi_repr::Skeleton;

use common::gltf::{node_worlds, parse_glb, skinned_vertices};
use common::smplx_fixture::Spoil;
use common::write_smplx_model;

/// Tolerance of the comparison with numpy (metres).
const TOLERANCE: f64 = 1e-4;

fn read_npy(path: &Path) -> (Vec<u64>, Vec<f64>) {
    let bytes = std::fs::read(path).expect("numpy output");
    let npy = npyz::NpyFile::new(&bytes[..]).expect("npy");
    let shape = npy.shape().to_vec();
    (shape, npy.into_vec::<f64>().expect("f64"))
}

/// Runs numpy's SMPL-X linear blend skinning (`tools/smplx_lbs.py`: no pose blend shapes, the
/// four largest weights renormalised) of the model with the npz's parameters, which writes
/// `(T, V, 3)` vertices and `(T, 55, 3)` joints into `out`; `false` when python or numpy is
/// missing outside CI.
fn numpy_lbs(model: &Path, motion: &Path, out: &Path) -> bool {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tools/smplx_lbs.py");
    let output = match Command::new("python3").arg(script).arg(model).arg(motion).arg(out).output()
    {
        Ok(output) => output,
        Err(error) if !common::in_ci() => {
            println!("skipped: python3 is not available ({error})");
            return false;
        }
        Err(error) => panic!("CI needs python3 for the numpy check: {error}"),
    };
    if output.status.code() == Some(3) {
        assert!(!common::in_ci(), "CI needs numpy (scripts/setup.sh)");
        println!("skipped: numpy is not installed");
        return false;
    }
    assert!(
        output.status.success(),
        "numpy LBS failed:\n{}{}",
        String::from_utf8_lossy(&output.stdout),
        String::from_utf8_lossy(&output.stderr)
    );
    println!("{}", String::from_utf8_lossy(&output.stdout));
    true
}

#[test]
fn the_skinned_smplx_mesh_of_the_glb_equals_numpy_lbs_and_the_npz_joints_its_kinematics() {
    let dir = common::scratch_dir("smplx-body");
    let model = dir.join("SMPLX_NEUTRAL.npz");
    write_smplx_model(&model, Spoil::None);
    // The directory form finds the same file.
    let betas = [0.8, -0.5, 0.3];
    let mesh = SmplxMesh::load(&dir, &betas).expect("the fixture model loads");
    assert_eq!(mesh.path, model);
    assert_eq!(mesh.skeleton.joint_count(), 52);
    assert!(mesh.weights.iter().all(|w| (w.iter().sum::<f32>() - 1.0).abs() < 1e-6));
    // The shape changes the skeleton: shape 0 grows the body.
    let zero = SmplxMesh::load(&model, &[]).expect("zero betas");
    let height = |m: &SmplxMesh| m.skeleton.rest_positions()[15].y;
    assert!(height(&mesh) > height(&zero) + 0.01, "{} vs {}", height(&mesh), height(&zero));

    let frames = 5;
    let motion = common::wavy_motion(&mesh.skeleton, frames, 1);
    let meshes = common::object_meshes();
    let export = ExportMotion {
        body: Some(Body::Smplx(&mesh)),
        ..common::export(&mesh.skeleton, &motion, &meshes[..1], "lift")
    };
    let out = dir.join("export");
    let files = export_all(&out, &export, &ExportOptions::default()).expect("exported");

    let (json, bin) = parse_glb(&std::fs::read(&files.glb).expect("glb"));
    let nodes = json["nodes"].as_array().expect("nodes");
    assert_eq!(json["skins"][0]["joints"].as_array().expect("joints").len(), 55);
    assert_eq!(nodes[52]["name"], "jaw");
    assert_eq!(json["meshes"][0]["name"], "smplx");
    assert_eq!(json["scenes"][0]["extras"]["body"], "smplx");
    let body_node = nodes.iter().position(|n| n.get("skin").is_some()).expect("a skinned node");
    let worlds = node_worlds(&json, &bin, frames);
    let glb_vertices = skinned_vertices(&json, &bin, body_node, &worlds);
    assert_eq!(glb_vertices[0].len(), mesh.vertices.len());
    // The preview draws the model's own mesh where the GLB's skin puts it.
    let preview = render_preview(&export, &PreviewOptions::default()).expect("rendered");
    let capsules = ExportMotion { body: None, ..export.clone() };
    let capsules = render_preview(&capsules, &PreviewOptions::default()).expect("rendered");
    assert_ne!(preview.frames, capsules.frames, "the mesh, not the capsules");
    for (t, vertices) in glb_vertices.iter().enumerate() {
        let centre = vertices.iter().copied().sum::<glam::Vec3>() / vertices.len() as f32;
        let pixel = preview.frame_views[t][0].project(centre).expect("in front");
        let surface = preview.surface_at(t, pixel.x as u32, pixel.y as u32);
        assert_eq!(surface, Some(Surface::Body), "frame {t}: the mesh's centre");
    }

    if !numpy_lbs(&model, &files.npz, &dir) {
        return;
    }
    let (shape, numpy_vertices) = read_npy(&dir.join("numpy_vertices.npy"));
    assert_eq!(shape, [frames as u64, mesh.vertices.len() as u64, 3]);
    let mut worst_vertex = 0.0f64;
    for (t, vertices) in glb_vertices.iter().enumerate() {
        for (v, vertex) in vertices.iter().enumerate() {
            for axis in 0..3 {
                let theirs = numpy_vertices[(t * vertices.len() + v) * 3 + axis];
                worst_vertex = worst_vertex.max((f64::from(vertex[axis]) - theirs).abs());
            }
        }
    }
    println!("GLB skinned mesh vs numpy LBS: worst {worst_vertex:.2e} m over {frames} frames");
    assert!(worst_vertex < TOLERANCE, "GLB vertices differ from numpy LBS by {worst_vertex} m");

    // The npz's joints are the model's kinematics (its 52 of 55 joints).
    let (_, numpy_joints) = read_npy(&dir.join("numpy_joints.npy"));
    let to55 = dex2hoi_repr::skeleton::smplx52_to_55();
    let mut worst_joint = 0.0f64;
    for t in 0..frames {
        for (j, &model_joint) in to55.iter().enumerate() {
            let ours = motion.joints.position(t, j);
            for axis in 0..3 {
                let theirs = numpy_joints[(t * 55 + model_joint) * 3 + axis];
                worst_joint = worst_joint.max((f64::from(ours[axis]) - theirs).abs());
            }
        }
    }
    println!("npz joints vs the model's kinematics: worst {worst_joint:.2e} m");
    assert!(worst_joint < TOLERANCE, "npz joints differ from the model's by {worst_joint} m");

    assert!(common::validator_is_clean(&files.glb, "smplx-body") || !common::in_ci());
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_broken_model_file_is_a_clear_error_and_writes_nothing() {
    let dir = common::scratch_dir("smplx-broken");
    let cases = [
        (Spoil::Missing("weights"), "weights"),
        (Spoil::Missing("f"), "`f`"),
        (Spoil::Missing("J_regressor"), "J_regressor"),
        (Spoil::WeightsShape, "`weights` has shape"),
        (Spoil::FaceIndex, "vertex indices below"),
    ];
    for (spoil, expected) in cases {
        let path = dir.join(format!("{spoil:?}.npz").replace(['(', ')', '"'], ""));
        write_smplx_model(&path, spoil);
        let error = SmplxMesh::load(&path, &[]).expect_err("refused").to_string();
        assert!(error.contains(expected), "{spoil:?}: {error}");
        assert!(error.contains(&path.display().to_string()), "{spoil:?} names the file: {error}");
    }
    // Too many betas, and a directory without a model.
    let good = dir.join("good.npz");
    write_smplx_model(&good, Spoil::None);
    let error = SmplxMesh::load(&good, &[0.0; 11]).expect_err("11 betas").to_string();
    assert!(error.contains("at most 10"), "{error}");
    let empty = dir.join("empty");
    std::fs::create_dir_all(&empty).expect("dir");
    let error = SmplxMesh::load(&empty, &[]).expect_err("no model").to_string();
    assert!(error.contains("SMPLX_NEUTRAL.npz"), "{error}");
    // A Mixamo motion cannot wear the SMPL-X body, and a motion on another skeleton is refused
    // before anything is written.
    let mesh = SmplxMesh::load(&good, &[]).expect("loads");
    assert!(mesh.fits(&Skeleton::mixamo()).is_err());
    let builtin = Skeleton::smplx();
    let motion = common::wavy_motion(&builtin, 2, 0);
    let export = ExportMotion {
        body: Some(Body::Smplx(&mesh)),
        ..common::export(&builtin, &motion, &[], "")
    };
    let out = dir.join("out");
    let error = export_all(&out, &export, &ExportOptions::default()).expect_err("wrong skeleton");
    assert!(error.to_string().contains("the body's own skeleton"), "{error}");
    assert!(!out.exists(), "nothing written");
    let _ = std::fs::remove_dir_all(&dir);
}
