//! Real motion capture end to end: HUMOTO's public subset (from `../shared/realdata`; skipped
//! when absent, failing under `CI=1`) prepared with its licence and its character's start pose,
//! a tiny Mixamo-65 model trained on it, sampled from a test sequence's scene and with an
//! object of the data's catalogue, evaluated, and packed with the licence.

use std::path::{Path, PathBuf};

use dex2hoi_data::dataset::{Dataset, Split};

mod common;
use common::dex2hoi;

fn temp_dir(name: &str) -> PathBuf {
    common::temp_dir("humoto", name)
}

fn succeed(args: &[&str]) -> String {
    let run = dex2hoi(args);
    assert!(run.status.success(), "{args:?}:\n{}", String::from_utf8_lossy(&run.stderr));
    String::from_utf8_lossy(&run.stdout).into_owned()
}

fn fail(args: &[&str]) -> String {
    let run = dex2hoi(args);
    assert!(!run.status.success(), "{args:?} should fail");
    String::from_utf8_lossy(&run.stderr).into_owned()
}

/// A motion.npz array's numbers and shape.
fn npz_array(path: &Path, name: &str) -> (Vec<f64>, Vec<usize>) {
    let mut npz = dex2hoi_import::npy::Npz::open(path).unwrap();
    let value = npz.read(name, name).unwrap();
    dex2hoi_import::Field::root("motion.npz", name, &value).numbers_any_shape().unwrap()
}

#[test]
fn humoto_is_prepared_trained_on_sampled_evaluated_and_packed_with_its_licence() {
    let realdata = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../../shared/realdata/humoto");
    let glb = realdata.join("glb");
    if !glb.is_dir() {
        assert!(std::env::var("CI").as_deref() != Ok("1"), "CI needs {}", glb.display());
        eprintln!("skipped: no real HUMOTO samples at {}", glb.display());
        return;
    }
    let dir = temp_dir("all");
    std::fs::create_dir_all(&dir).unwrap();
    let path = |name: &str| dir.join(name).to_str().unwrap().to_string();
    let (data, run, evaluator) = (path("data"), path("run"), path("evaluator"));

    // Prepared: the licence beside the release is found and kept; the start pose is one of the
    // training sequences' first frames, standing on the floor.
    let stdout = succeed(&[
        "data",
        "prepare",
        "--format",
        "humoto",
        "--root",
        glb.to_str().unwrap(),
        "--out",
        &data,
    ]);
    assert!(stdout.contains("Adobe Research License v1.1.pdf"), "{stdout}");
    let dataset = Dataset::load(Path::new(&data)).unwrap();
    let manifest = &dataset.manifest;
    assert_eq!((manifest.skeleton.as_str(), manifest.format_version), ("mixamo65", 4));
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
    // With a prompt of one's own and an object of the data's catalogue, on the default table.
    let object = manifest.objects[0].as_str();
    let own = path("own");
    succeed(&[
        "sample",
        "--run",
        &run,
        "--data",
        &data,
        "--object",
        object,
        "--text",
        "The subject lifts the object.",
        "--frames",
        "8",
        "--ddim-steps",
        "2",
        "--out",
        &own,
    ]);
    assert_eq!(npz_array(&Path::new(&own).join("motion.npz"), "joints").1, [8, 65, 3]);
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
