//! Real motion capture end to end: HUMOTO's public subset (from `../shared/realdata`; skipped
//! when absent, failing under `CI=1`) prepared with its licence and its character's start pose,
//! a tiny Mixamo-65 model trained on it, sampled from a test sequence's scene and with an
//! object of the data's catalogue, evaluated, and packed with the licence; and motions put on
//! the Mixamo character inside a HUMOTO GLB (`--character`), imported into Blender (skipped
//! without Blender's `bpy`, failing under `CI=1`) to 1 mm.

use std::path::{Path, PathBuf};

use dex2hoi_data::dataset::{Dataset, Split};

mod common;
use common::{dex2hoi, fail, npz_array, succeed};

fn temp_dir(name: &str) -> PathBuf {
    common::temp_dir("humoto", name)
}

#[test]
fn humoto_is_prepared_trained_on_sampled_evaluated_and_packed_with_its_licence() {
    let Some(glb) = common::humoto_glb() else { return };
    let realdata = glb.parent().unwrap();
    let dir = temp_dir("all");
    std::fs::create_dir_all(&dir).unwrap();
    let path = |name: &str| dir.join(name).to_str().unwrap().to_string();
    let (data, run, evaluator) = (path("data"), path("run"), path("evaluator"));

    // Prepared: the licence beside the release is found and kept; the start pose is one of the
    // training sequences' first frames, standing on the floor.
    let stdout = common::prepare_humoto(&glb, &data);
    assert!(stdout.contains("Adobe Research License v1.1.pdf"), "{stdout}");
    let dataset = Dataset::load(Path::new(&data)).unwrap();
    let manifest = &dataset.manifest;
    assert_eq!(
        (manifest.skeleton.as_str(), manifest.format_version),
        ("mixamo65", dex2hoi_data::dataset::FORMAT_VERSION)
    );
    assert_eq!(manifest.mixture_targets, dex2hoi_data::features::MixtureTargets::Proximity);
    let start = manifest.start_pose().unwrap();
    assert!(
        dataset.splits[&Split::Train].iter().any(|s| s.source_id == start.source),
        "the start pose comes from the training split: {}",
        start.source
    );
    assert!((0.75..1.0).contains(&start.root_height), "hips at {} m", start.root_height);
    let licence = manifest.licence.as_ref().expect("the licence is kept");
    let published = std::fs::read(realdata.join("Adobe Research License v1.1.pdf")).unwrap();
    assert_eq!(licence.bytes().unwrap(), published);

    // The SMPL-X presets name the preset for this skeleton; a 65-joint tiny model trains.
    let presets = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../configs");
    let tiny = presets.join("tiny.toml");
    let stderr =
        fail(&["train", "--config", tiny.to_str().unwrap(), "--data", &data, "--out", &run]);
    assert!(stderr.contains("mixamo65") && stderr.contains("humoto"), "{stderr}");
    let tiny65 = dir.join("tiny65.toml");
    let text = std::fs::read_to_string(&tiny).unwrap();
    std::fs::write(&tiny65, text.replace("joints = 52", "joints = 65")).unwrap();
    succeed(&[
        "train",
        "--config",
        tiny65.to_str().unwrap(),
        "--data",
        &data,
        "--out",
        &run,
        "--steps",
        "3",
    ]);

    // Sampled from a test sequence's scene: its objects where they stand, its script, its
    // length unless told.
    let test = &dataset.splits[&Split::Test][0];
    let id = test.source_id.rsplit_once('/').unwrap().1;
    let scene = path("scene");
    let stdout = succeed(&[
        "sample",
        "--run",
        &run,
        "--data",
        &data,
        "--sequence",
        id,
        "--frames",
        "12",
        "--ddim-steps",
        "2",
        "--out",
        &scene,
    ]);
    assert!(stdout.contains("generated 12 frames"), "{stdout}");
    let npz = Path::new(&scene).join("motion.npz");
    assert_eq!(npz_array(&npz, "joints").1, [12, 65, 3]);
    let objects = test.object_names.iter().flatten().count();
    assert_eq!(npz_array(&npz, "object_translations").1, [objects, 12, 3]);
    // With a prompt of one's own and an object of the data's catalogue, on the default table;
    // then on the character inside a HUMOTO GLB, whose skinned mesh motion.glb carries.
    let object = manifest.objects[0].as_str();
    let sample_own = |out: &str, more: &[&str]| {
        let mut args = vec!["sample", "--run", &run, "--data", &data, "--object", object];
        args.extend(["--text", "The subject lifts the object.", "--frames", "8"]);
        args.extend(["--ddim-steps", "2", "--out", out]);
        args.extend(more);
        succeed(&args);
        assert_eq!(npz_array(&Path::new(out).join("motion.npz"), "joints").1, [8, 65, 3]);
    };
    let own = path("own");
    sample_own(&own, &[]);
    let character = glb.join("examining_cutting_board-141/examining_cutting_board-141.glb");
    let dressed = path("dressed");
    sample_own(&dressed, &["--character", character.to_str().unwrap()]);
    let json = common::glb_json(&Path::new(&dressed).join("motion.glb"));
    assert_eq!(json["scenes"][0]["extras"]["body"], "character");
    // Without --data the data's objects are unknown, and the error lists the catalogue.
    let stderr = fail(&["sample", "--run", &run, "--object", object, "--text", "x", "--out", &own]);
    assert!(stderr.contains(object) && stderr.contains("mug"), "{stderr}");

    // Evaluated with an evaluator trained on the same data.
    succeed(&["evaluator", "train", "--data", &data, "--out", &evaluator, "--steps", "3"]);
    let report = path("report");
    succeed(&[
        "evaluate",
        "--run",
        &run,
        "--data",
        &data,
        "--evaluator",
        &evaluator,
        "--out",
        &report,
        "--replications",
        "1",
        "--sequences",
        "2",
        "--ddim-steps",
        "2",
    ]);
    assert!(Path::new(&report).join("report.md").is_file());

    // Packed, the model carries the licence, and gives it back byte for byte.
    let packed = path("model.safetensors");
    succeed(&["model", "pack", "--run", &run, "--out", &packed]);
    let stdout = succeed(&["model", "info", "--run", &packed]);
    assert!(stdout.contains("Adobe Research License v1.1.pdf"), "{stdout}");
    let written = dir.join("licence.pdf");
    succeed(&["model", "licence", "--run", &packed, "--out", written.to_str().unwrap()]);
    assert_eq!(std::fs::read(&written).unwrap(), published);
    std::fs::remove_dir_all(&dir).ok();
}

/// The HUMOTO character's GLB that the character tests dress motions in.
fn humoto_character() -> Option<PathBuf> {
    let glb = common::humoto_glb()?;
    Some(glb.join("examining_cutting_board-141/examining_cutting_board-141.glb"))
}

#[test]
fn a_sequence_put_on_the_humoto_character_plays_in_blender_as_the_npz_says() {
    let Some(character) = humoto_character() else { return };
    let character_arg = character.to_str().unwrap();
    let glb = character.parent().unwrap().parent().unwrap();
    let dir = temp_dir("character");
    std::fs::create_dir_all(&dir).unwrap();
    let path = |name: &str| dir.join(name).to_str().unwrap().to_string();
    let (data, out) = (path("data"), path("out"));
    common::prepare_humoto(glb, &data);
    // `data show` of the cutting-board sequence on a character file, into `out`.
    let show_on = |character: &str, out: &str| {
        let sequence = "examining_cutting_board-141";
        dex2hoi(&[
            "data",
            "show",
            &data,
            "--sequence",
            sequence,
            "--character",
            character,
            "--out",
            out,
        ])
    };
    assert!(show_on(character_arg, &out).status.success());
    let npz = Path::new(&out).join("motion.npz");
    assert_eq!(npz_array(&npz, "joints").1, [157, 65, 3]);
    // The file drops onto the character's rig: its bone names, and at the first frame each
    // bone's rotation relative to its parent is the published animation's.
    let glb_file = Path::new(&out).join("motion.glb");
    let worst = common::worst_bone_rotation_gap(&character, &glb_file);
    assert!(worst < 1e-3, "a bone's rotation is {worst} rad from the published file's");
    // Blender plays the bones where the npz has the joints, and skins the character as a
    // linear blend skinning of the character file (read by Blender) by the npz's pose does.
    if let Some(python) = common::blender_python() {
        let script =
            Path::new(env!("CARGO_MANIFEST_DIR")).join("../dex2hoi-export/tools/blender_check.py");
        let output = std::process::Command::new(python)
            .arg(script)
            .arg(&out)
            .args(["--character", character_arg, "--frames", "0,60,150"])
            .output()
            .expect("Blender's python runs");
        let stdout = String::from_utf8_lossy(&output.stdout);
        assert!(output.status.success(), "{stdout}{}", String::from_utf8_lossy(&output.stderr));
        let line = stdout.lines().rev().find(|l| l.starts_with('{')).expect("a JSON report");
        let report: serde_json::Value = serde_json::from_str(line).unwrap();
        println!("{report}");
        let number = |file: &str, key: &str| report[file][key].as_f64().unwrap();
        assert!(number("glb", "mesh_vertices") > 10_000.0, "{report}");
        for (file, key, bound) in [
            ("glb", "joint_error", 1e-3),
            ("glb", "rest_mesh_error", 1e-4),
            ("glb", "mesh_error", 1e-3),
            ("bvh", "joint_error", 1e-3),
        ] {
            assert!(number(file, key) < bound, "{file} {key}: {report}");
        }
    }
    // An SMPL-X motion cannot wear a Mixamo character, nor can anything wear a file that is
    // not one.
    let stderr = fail(&[
        "sample",
        "--text",
        "The person picks up the mug.",
        "--object",
        "mug",
        "--frames",
        "4",
        "--character",
        character_arg,
        "--out",
        &path("smplx"),
    ]);
    assert!(stderr.contains("mixamo65") && stderr.contains("smplx52"), "{stderr}");
    let licence = glb.parent().unwrap().join("Adobe Research License v1.1.pdf");
    let refused = show_on(licence.to_str().unwrap(), &path("not-a-character"));
    let stderr = String::from_utf8_lossy(&refused.stderr);
    assert!(!refused.status.success());
    assert!(stderr.contains("--character") && stderr.contains("glTF"), "{stderr}");
    assert!(!Path::new(&path("not-a-character")).exists());
    std::fs::remove_dir_all(&dir).ok();
}
