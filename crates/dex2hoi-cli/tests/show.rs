//! `dex2hoi data show` end to end: a procedural sequence by index and by id, the real HUMOTO
//! release prepared and shown (skipped when `../shared/realdata` is absent, failing under
//! `CI=1`), a sequence dressed in an SMPL-X model's body (`--smplx-model`, `--betas`), and bad
//! input.

use std::path::{Path, PathBuf};

use dex2hoi_data::dataset::Dataset;

mod common;
use common::{dex2hoi, succeed};

fn temp_dir(name: &str) -> PathBuf {
    common::temp_dir("show", name)
}

/// The four files, each non-trivial, and the npz's frame count.
fn check_files(out: &Path, frames: usize) {
    for file in ["motion.npz", "motion.glb", "motion.bvh", "preview.gif", "preview.png"] {
        let size = std::fs::metadata(out.join(file)).map(|m| m.len()).unwrap_or(0);
        assert!(size > 1000, "{file}: {size} bytes");
    }
    let bvh = std::fs::read_to_string(out.join("motion.bvh")).unwrap();
    assert!(bvh.contains(&format!("Frames: {frames}")), "the BVH has {frames} frames");
}

#[test]
fn a_procedural_sequence_is_shown_by_index_and_by_id() {
    let data = temp_dir("synth");
    let data_arg = data.to_str().unwrap();
    succeed(&["data", "synth", "--out", data_arg, "--sequences", "80", "--seed", "3"]);
    let dataset = Dataset::load(&data).unwrap();
    let test = &dataset.splits[&dex2hoi_data::dataset::Split::Test][0];
    let out = temp_dir("synth-out");
    let stdout = succeed(&[
        "data",
        "show",
        data_arg,
        "--sequence",
        &test.source_id,
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(stdout.contains(&test.source_id) && stdout.contains("test split"), "{stdout}");
    assert!(stdout.contains(&test.texts[0]), "{stdout}");
    check_files(&out, test.frames);
    // Index 0 of the test split is the same sequence.
    let by_index = temp_dir("synth-index");
    let stdout = succeed(&[
        "data",
        "show",
        data_arg,
        "--sequence",
        "0",
        "--split",
        "test",
        "--no-caption",
        "--out",
        by_index.to_str().unwrap(),
    ]);
    assert!(stdout.contains(&test.source_id), "{stdout}");
    assert_eq!(
        std::fs::read(out.join("motion.npz")).unwrap(),
        std::fs::read(by_index.join("motion.npz")).unwrap()
    );
    // Without the caption only the preview differs (it loses its caption band).
    let gif_size = |dir: &Path| std::fs::metadata(dir.join("preview.gif")).unwrap().len();
    assert_ne!(gif_size(&out), gif_size(&by_index));
    // Unknown ids and indices name the dataset and what is accepted; nothing is written.
    let nowhere = temp_dir("synth-nowhere");
    for wanted in ["no-such-sequence", "80"] {
        let run = dex2hoi(&[
            "data",
            "show",
            data_arg,
            "--sequence",
            wanted,
            "--out",
            nowhere.to_str().unwrap(),
        ]);
        assert!(!run.status.success());
        let stderr = String::from_utf8_lossy(&run.stderr);
        assert!(
            stderr.contains(data_arg) && stderr.contains(wanted) && stderr.contains("below 80"),
            "{stderr}"
        );
        assert!(!nowhere.exists());
    }
    for dir in [data, out, by_index] {
        std::fs::remove_dir_all(dir).ok();
    }
}

#[test]
fn the_real_humoto_release_is_prepared_and_shown() {
    let Some(glb) = common::humoto_glb() else { return };
    let data = temp_dir("humoto");
    let stdout = common::prepare_humoto(&glb, data.to_str().unwrap());
    // Every sequence of the folder is read or skipped for a stated reason, none fails.
    assert!(stdout.contains("failed 0, warnings 0") && !stdout.contains("read 0 "), "{stdout}");
    let out = temp_dir("humoto-out");
    let stdout = succeed(&[
        "data",
        "show",
        data.to_str().unwrap(),
        "--sequence",
        "examining_cutting_board-141",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(stdout.contains("cutting_board") && stdout.contains("lifts the cutting board"));
    // 235 frames at 30 fps are 157 at 20 fps.
    check_files(&out, 157);
    // The shown joints are the prepared ones: the sequence is decoded on its own body (the
    // character's bind pose), not on the symmetrised built-in skeleton (up to 3 mm off).
    let dataset = Dataset::load(&data).unwrap();
    let sequence = dataset.splits.values().flatten().find(|s| s.source_id.ends_with("-141"));
    let stored = &sequence.unwrap().joint_positions;
    let mut npz = dex2hoi_import::npy::Npz::open(&out.join("motion.npz")).unwrap();
    let value = npz.read("joints", "joints").unwrap();
    let (shown, shape) =
        dex2hoi_import::Field::root("motion.npz", "joints", &value).numbers_any_shape().unwrap();
    assert_eq!(shape, [157, 65, 3]);
    let worst =
        shown.iter().zip(stored).map(|(a, b)| (a - f64::from(*b)).abs()).fold(0.0, f64::max);
    assert!(worst < 1e-4, "data show's joints are {worst} m from the prepared ones");
    // The shown GLB drops onto the HUMOTO character by bone name: in Mixamo's bone frames, each
    // bone's rotation relative to its parent at the first frame is the published file's.
    let published = glb.join("examining_cutting_board-141/examining_cutting_board-141.glb");
    let worst = common::worst_bone_rotation_gap(&published, &out.join("motion.glb"));
    println!("parent-relative bone rotations, shown vs published GLB, frame 0: worst {worst} rad");
    assert!(worst < 1e-3, "a bone's rotation is {worst} rad from the published file's");
    for dir in [data, out] {
        std::fs::remove_dir_all(dir).ok();
    }
}

#[test]
fn an_smplx_model_gives_the_glb_its_body_and_every_file_its_skeleton() {
    let data = temp_dir("smplx-data");
    let data_arg = data.to_str().unwrap();
    succeed(&["data", "synth", "--out", data_arg, "--sequences", "20", "--seed", "1"]);
    // The fixture model, in the `smplx` package's layout `models/smplx/SMPLX_NEUTRAL.npz`.
    let models = temp_dir("smplx-models");
    std::fs::create_dir_all(models.join("smplx")).unwrap();
    common::write_smplx_model(&models.join("smplx/SMPLX_NEUTRAL.npz"));
    let show = |out: &Path, extra: &[&str]| {
        let mut args = vec!["data", "show", data_arg, "--sequence", "0", "--out"];
        args.push(out.to_str().unwrap());
        args.extend_from_slice(extra);
        dex2hoi(&args)
    };
    let out = temp_dir("smplx-out");
    let run = show(&out, &["--smplx-model", models.to_str().unwrap(), "--betas", "0.5,-0.3"]);
    assert!(run.status.success(), "{}", String::from_utf8_lossy(&run.stderr));
    let json = common::glb_json(&out.join("motion.glb"));
    assert_eq!(json["meshes"][0]["name"], "smplx");
    assert_eq!(json["skins"][0]["joints"].as_array().unwrap().len(), 55);
    let extras_betas: Vec<f64> = json["scenes"][0]["extras"]["betas"]
        .as_array()
        .unwrap()
        .iter()
        .map(|b| b.as_f64().unwrap())
        .collect();
    assert!((extras_betas[0] - 0.5).abs() < 1e-6 && (extras_betas[1] + 0.3).abs() < 1e-6);
    // The npz carries the betas (padded to the layer's ten) and the model's pelvis.
    let mut npz = dex2hoi_import::npy::Npz::open(&out.join("motion.npz")).unwrap();
    let value = npz.read("betas", "betas").unwrap();
    let (betas, shape) =
        dex2hoi_import::Field::root("motion.npz", "betas", &value).numbers_any_shape().unwrap();
    assert_eq!(shape[1], 10);
    assert!((betas[0] - 0.5).abs() < 1e-6 && (betas[1] + 0.3).abs() < 1e-6);
    // Without a model the GLB keeps the capsule body.
    let plain = temp_dir("smplx-plain");
    assert!(show(&plain, &[]).status.success());
    assert_eq!(common::glb_json(&plain.join("motion.glb"))["meshes"][0]["name"], "body");
    // A missing model and --betas alone are clear errors that write nothing.
    let nowhere = temp_dir("smplx-nowhere");
    let missing = models.join("nothing-here.npz");
    let run = show(&nowhere, &["--smplx-model", missing.to_str().unwrap()]);
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert!(!run.status.success() && stderr.contains("nothing-here.npz"), "{stderr}");
    let run = show(&nowhere, &["--betas", "1"]);
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert!(!run.status.success() && stderr.contains("--smplx-model"), "{stderr}");
    assert!(!nowhere.exists());
    for dir in [data, models, out, plain] {
        std::fs::remove_dir_all(dir).ok();
    }
}
