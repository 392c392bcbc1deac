//! `dex2hoi data prepare` end to end on GRAB, HUMOTO and HIMO fixtures written in their
//! published formats by `crates/dex2hoi-import/tests/fixtures/make_fixtures.py` (real numpy
//! and pickle; `$PYTHON`, else `python3`).

use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::OnceLock;

use dex2hoi_data::dataset::{Dataset, Split};

mod common;
use common::{dex2hoi, succeed};

fn temp_dir(name: &str) -> PathBuf {
    common::temp_dir("prepare", name)
}

fn fixtures() -> &'static Path {
    static DIR: OnceLock<PathBuf> = OnceLock::new();
    DIR.get_or_init(|| {
        let dir = temp_dir("fixtures");
        let script = Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../dex2hoi-import/tests/fixtures/make_fixtures.py");
        let python = std::env::var("PYTHON").unwrap_or_else(|_| "python3".into());
        let run = Command::new(&python).arg(&script).arg(&dir).output().expect("python runs");
        assert!(
            run.status.success(),
            "the fixture generator needs numpy and PyYAML (scripts/setup.sh):\n{}",
            String::from_utf8_lossy(&run.stderr)
        );
        dir
    })
}

fn path(p: &Path) -> &str {
    p.to_str().expect("UTF-8 temp path")
}

/// A fixture path as a string.
fn fixture(relative: &str) -> String {
    path(&fixtures().join(relative)).to_string()
}

#[test]
fn grab_is_prepared_and_bad_sequences_are_reported() {
    let grab = &fixture("grab");
    let models = &fixture("smplx");
    let model = &fixture("smplx/SMPLX_NEUTRAL.npz");
    let out = temp_dir("grab");
    // A licence given by hand travels in the manifest, byte for byte.
    let licence = temp_dir("grab-licence.txt");
    std::fs::write(&licence, "GRAB licence: research use only.\n").unwrap();
    let args = [
        "data",
        "prepare",
        "--format",
        "grab",
        "--root",
        grab,
        "--smplx-model",
        model,
        "--out",
        path(&out),
        "--text-template",
        "The person is {verb} the {object}.",
        "--text-template",
        "Someone does {intent} with a {object}.",
        "--licence",
        path(&licence),
    ];
    let stdout = succeed(&args);
    assert!(stdout.contains("read 3 (train 2 (20 frames), test 1 (10 frames))"), "{stdout}");
    assert!(stdout.contains("failed 5"), "{stdout}");
    for bad in ["missingkey", "wrongshape", "truncated", "nan", "unknownclass"] {
        let line = format!("failed s2/mug_pass_{bad}: ");
        let reported = stdout
            .lines()
            .find(|l| l.starts_with(&line))
            .unwrap_or_else(|| panic!("{line}: {stdout}"));
        assert!(reported.contains(&format!("mug_pass_{bad}.npz")), "{reported}");
    }
    assert!(stdout.contains("wrote 3 sequences"), "{stdout}");
    let dataset = Dataset::load(&out).unwrap();
    let m = &dataset.manifest;
    assert_eq!((m.source.as_str(), m.skeleton.as_str(), m.joints), ("grab", "smplx52", 52));
    assert_eq!((m.body_feature_size, m.stream_feature_size), (315, 333));
    assert_eq!(m.objects, vec!["mug"]);
    let kept = m.licence.as_ref().expect("the licence is kept");
    assert_eq!(kept.file_name, licence.file_name().unwrap().to_str().unwrap());
    assert_eq!(kept.bytes().unwrap(), std::fs::read(&licence).unwrap());
    assert_eq!(dataset.stats.mean.len(), 333);
    let test = &dataset.splits[&Split::Test][0];
    assert_eq!(test.source_id, "grab/s10/mug_drink_1");
    assert_eq!(
        test.texts,
        ["The person is drinking from the mug.", "Someone does drink with a mug."]
    );
    let info = succeed(&["data", "info", path(&out)]);
    assert!(info.contains("source grab") && info.contains("train: 2 sequences"), "{info}");
    // Each subject keeps its own body: s1's two training sequences share one, s10's differs.
    assert!(info.contains("rest skeletons: 1 distinct, rest height 1.71-1.71 m"), "{info}");
    assert!(info.contains("rest skeletons: 1 distinct, rest height 1.59-1.59 m"), "{info}");
    // The PCA hand path runs from the command line too.
    let pca = temp_dir("grab-pca");
    let args = [
        "data",
        "prepare",
        "--format",
        "grab",
        "--root",
        grab,
        "--smplx-model",
        models,
        "--hand-pose",
        "pca",
        "--out",
        path(&pca),
    ];
    succeed(&args);
    let with_pca = Dataset::load(&pca).unwrap();
    assert_ne!(with_pca.splits[&Split::Train][0].body, dataset.splits[&Split::Train][0].body);
    for dir in [out, pca] {
        std::fs::remove_dir_all(dir).ok();
    }
}

#[test]
fn humoto_and_himo_are_prepared() {
    let himo = &fixture("himo");
    let himo_split = &fixture("himo_split.json");
    let humoto = &fixture("humoto");
    let humoto_split = &fixture("humoto_split.json");
    let model = &fixture("smplx/SMPLX_NEUTRAL.npz");
    let out = temp_dir("humoto");
    let args = [
        "data",
        "prepare",
        "--format",
        "humoto",
        "--root",
        humoto,
        "--split-file",
        humoto_split,
        "--out",
        path(&out),
    ];
    let stdout = succeed(&args);
    assert!(stdout.contains("skipped tidy_three: 3 moving objects"), "{stdout}");
    assert!(stdout.contains("failed broken_truncated: "), "{stdout}");
    let dataset = Dataset::load(&out).unwrap();
    let m = &dataset.manifest;
    assert_eq!((m.skeleton.as_str(), m.joints, m.body_feature_size), ("mixamo65", 65, 393));
    assert_eq!(m.hand_joints, 42);
    assert_eq!((m.splits[&Split::Train].sequences, m.splits[&Split::Test].sequences), (1, 1));

    let out_himo = temp_dir("himo");
    let args = [
        "data",
        "prepare",
        "--format",
        "himo",
        "--root",
        himo,
        "--smplx-model",
        model,
        "--split-file",
        himo_split,
        "--out",
        path(&out_himo),
    ];
    let stdout = succeed(&args);
    assert!(stdout.contains("skipped S02T001: 3 objects"), "{stdout}");
    let dataset = Dataset::load(&out_himo).unwrap();
    assert_eq!(dataset.manifest.objects, vec!["Apple", "Cup", "Plate"]);
    assert!(dataset.splits.values().flatten().all(|s| s.object_present == [true, true]));
    for dir in [out, out_himo] {
        std::fs::remove_dir_all(dir).ok();
    }
}

#[test]
fn bad_invocations_give_clear_errors() {
    let grab = &fixture("grab");
    let himo = &fixture("himo");
    let not_a_model = &fixture("misc/arrays.npz");
    let out = temp_dir("never");
    let no_model =
        dex2hoi(&["data", "prepare", "--format", "grab", "--root", grab, "--out", path(&out)]);
    assert!(!no_model.status.success());
    assert!(
        String::from_utf8_lossy(&no_model.stderr).contains("--smplx-model is required for grab")
    );
    let missing = dex2hoi(&[
        "data",
        "prepare",
        "--format",
        "humoto",
        "--root",
        "/nonexistent/humoto",
        "--out",
        path(&out),
    ]);
    assert!(!missing.status.success());
    assert!(String::from_utf8_lossy(&missing.stderr).contains("/nonexistent/humoto"));
    let args = ["data", "prepare", "--format", "grab", "--root", grab, "--out", path(&out)];
    let no_licence = dex2hoi(
        &[&args[..], &["--smplx-model", not_a_model, "--licence", "/nonexistent/LICENSE"]].concat(),
    );
    assert!(!no_licence.status.success());
    assert!(String::from_utf8_lossy(&no_licence.stderr).contains("--licence /nonexistent/LICENSE"));
    assert!(!out.exists(), "nothing written");
    // A model that is not an SMPL-X model: every sequence fails, each reported, nothing written.
    let args = [
        "data",
        "prepare",
        "--format",
        "himo",
        "--root",
        himo,
        "--smplx-model",
        not_a_model,
        "--out",
        path(&out),
    ];
    let run = dex2hoi(&args);
    assert!(!run.status.success());
    let stdout = String::from_utf8_lossy(&run.stdout);
    assert!(stdout.contains("failed S01T001: ") && stdout.contains("v_template"), "{stdout}");
    assert!(String::from_utf8_lossy(&run.stderr).contains("nothing written"));
    assert!(!out.join("manifest.json").exists());
    let unknown =
        dex2hoi(&["data", "prepare", "--format", "amass", "--root", "/tmp", "--out", path(&out)]);
    assert!(!unknown.status.success());
}

#[test]
fn grab_as_hoidinis_benchmark_from_the_command_line() {
    let out = temp_dir("grab-hoidini");
    let args = [
        "data",
        "prepare",
        "--format",
        "grab",
        "--root",
        &fixture("grab"),
        "--smplx-model",
        &fixture("smplx/SMPLX_NEUTRAL.npz"),
        "--split-file",
        &fixture("grab_train_split.json"),
        "--split-file",
        &fixture("grab_test_split.json"),
        "--exclude-intent",
        "lift",
        "--prompts",
        &fixture("grab_prompts.csv"),
        "--out",
        path(&out),
    ];
    let stdout = succeed(&args);
    assert!(stdout.contains("read 2 (train 1"), "{stdout}");
    assert!(stdout.contains("skipped s1/mug_lift: intent `lift` left out"), "{stdout}");
    assert!(stdout.contains("warning s10/mug_drink_1: no prompt"), "{stdout}");
    let dataset = Dataset::load(&out).unwrap();
    let pass = dataset.splits[&Split::Train].iter().find(|s| s.source_id == "grab/s1/mug_pass_1");
    assert_eq!(pass.unwrap().texts, ["The person is passing a mug, carefully."]);
    std::fs::remove_dir_all(out).ok();
}
