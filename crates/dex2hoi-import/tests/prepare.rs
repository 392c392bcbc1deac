//! GRAB, HUMOTO and HIMO fixtures in their published formats, prepared into datasets: the
//! structure `dex2hoi data synth` writes, joint positions that match an independent forward
//! kinematics of the fixtures' parameters, and bad inputs reported without stopping the run.

mod common;

use std::path::Path;

use glam::{Mat3, Vec3};

use dex2hoi_data::dataset::{Dataset, Split};
use dex2hoi_data::features::ProcessedSequence;
use dex2hoi_import::npy::Npz;
use dex2hoi_import::{Field, HandPoseSource, PrepareOptions, Prepared, SourceFormat, prepare};
use dex2hoi_repr::{Skeleton, forward_kinematics};

fn run(options: PrepareOptions) -> Prepared {
    prepare(options, &|_, _| {}).unwrap()
}

fn read_expected(path: &Path) -> (Vec<f64>, Vec<usize>, Npz) {
    let mut archive = Npz::open(path).unwrap();
    let value = archive.read("joints", "joints").unwrap();
    let (values, shape) = Field::root("expected", "joints", &value).numbers_any_shape().unwrap();
    (values, shape, archive)
}

fn number_array(archive: &mut Npz, key: &str) -> (Vec<f64>, Vec<usize>) {
    let value = archive.read(key, key).unwrap();
    Field::root("expected", key, &value).numbers_any_shape().unwrap()
}

fn sequence<'a>(dataset: &'a Dataset, id: &str) -> &'a ProcessedSequence {
    dataset
        .splits
        .values()
        .flatten()
        .find(|s| s.source_id == id)
        .unwrap_or_else(|| panic!("{id} is in the dataset"))
}

fn joint(s: &ProcessedSequence, frame: usize, j: usize) -> Vec3 {
    let base = (frame * s.joints + j) * 3;
    Vec3::from_slice(&s.joint_positions[base..base + 3])
}

/// Checks the structure every prepared dataset shares with `dex2hoi data synth`, saves it and
/// loads it back.
fn check_structure(dataset: &Dataset, source: &str, skeleton: &str, joints: usize, name: &str) {
    let m = &dataset.manifest;
    assert_eq!((m.source.as_str(), m.skeleton.as_str(), m.joints), (source, skeleton, joints));
    assert_eq!(m.body_feature_size, 6 * joints + 3);
    assert_eq!(m.stream_feature_size, 6 * joints + 3 + 18);
    assert_eq!(m.fps, 20.0);
    assert_eq!(m.seed, None);
    assert!(m.splits.contains_key(&Split::Train) && m.splits.contains_key(&Split::Test));
    assert_eq!(dataset.stats.mean.len(), m.stream_feature_size);
    assert_eq!(dataset.objects.len(), m.objects.len());
    for object in &dataset.objects {
        let (lo, hi) = object.mesh.bounding_box();
        assert!(((lo + hi) * 0.5).length() < 1e-5, "{} is centred", object.name);
    }
    let dir = common::temp_dir(name);
    dataset.save(&dir).unwrap();
    let loaded = Dataset::load(&dir).unwrap();
    assert_eq!(loaded.manifest, dataset.manifest);
    assert_eq!(loaded.splits, dataset.splits);
    std::fs::remove_dir_all(&dir).ok();
}

fn grab_options(hand_pose: HandPoseSource) -> PrepareOptions {
    let fixtures = common::fixtures();
    let mut options = PrepareOptions::new(SourceFormat::Grab, &fixtures.join("grab"));
    options.smplx_model = Some(fixtures.join("smplx/SMPLX_NEUTRAL.npz"));
    options.hand_pose = hand_pose;
    options
}

/// Compares prepared object poses with the fixture's: the centre of the posed mesh's
/// bounding box and the rotation, both in the canonical frame; `source_frame` maps a target
/// frame to an expected frame (or `None` to skip it).
fn check_objects(
    s: &ProcessedSequence,
    archive: &mut Npz,
    objects: usize,
    (root_rotation, root_position): (Mat3, Vec3),
    source_frame: impl Fn(usize) -> Option<usize>,
) {
    let forward = root_rotation * Vec3::Z;
    let turn = Mat3::from_axis_angle(Vec3::Y, -forward.x.atan2(forward.z));
    for slot in 0..objects {
        let (centres, _) = number_array(archive, &format!("object{slot}_centre"));
        let (rotations, _) = number_array(archive, &format!("object{slot}_rotation"));
        let centres: Vec<Vec3> = centres
            .chunks_exact(3)
            .map(|p| Vec3::new(p[0] as f32, p[1] as f32, p[2] as f32))
            .collect();
        let centres = common::canonical(&centres, root_rotation, root_position);
        let (mut worst_position, mut worst_rotation) = (0.0f32, 0.0f32);
        for t in (0..s.frames).filter_map(|t| source_frame(t).map(|f| (t, f))) {
            let (target, source) = t;
            let base = (target * 2 + slot) * 3;
            let position = Vec3::from_slice(&s.object_positions[base..base + 3]);
            worst_position = worst_position.max(position.distance(centres[source]));
            let base = (target * 2 + slot) * 9;
            let stored: Vec<f64> =
                s.object_rotations[base..base + 9].iter().map(|v| f64::from(*v)).collect();
            let expected = turn * common::mat3_rows(&rotations[source * 9..source * 9 + 9]);
            let difference = common::mat3_rows(&stored) - expected;
            worst_rotation = worst_rotation
                .max(difference.to_cols_array().iter().fold(0.0, |m, v| m.max(v.abs())));
        }
        assert!(
            worst_position < 1e-4,
            "{} object {slot}: centre off by {worst_position} m",
            s.source_id
        );
        assert!(
            worst_rotation < 1e-4,
            "{} object {slot}: rotation off by {worst_rotation}",
            s.source_id
        );
    }
}

/// Compares prepared joints with the fixture's expected joints (every target frame).
fn check_grab_joints(dataset: &Dataset, variant: &str) {
    for (id, file) in [
        ("grab/s1/mug_pass_1", "s1_mug_pass_1"),
        ("grab/s1/mug_lift", "s1_mug_lift"),
        ("grab/s10/mug_drink_1", "s10_mug_drink_1"),
    ] {
        let path = common::fixtures().join(format!("expected/grab/{variant}/{file}.npz"));
        let (values, shape, mut archive) = read_expected(&path);
        let (root, _) = number_array(&mut archive, "root_rotation");
        let s = sequence(dataset, id);
        assert_eq!(s.frames, shape[0], "{id}: 120 -> 20 fps");
        let world: Vec<Vec3> = values
            .chunks_exact(3)
            .map(|p| Vec3::new(p[0] as f32, p[1] as f32, p[2] as f32))
            .collect();
        let expected = common::canonical(&world, common::mat3_rows(&root[..9]), world[0]);
        let mut worst = 0.0f32;
        for t in 0..s.frames {
            for j in 0..52 {
                worst = worst.max(joint(s, t, j).distance(expected[t * 52 + j]));
            }
        }
        assert!(worst < 1e-3, "{id} ({variant}): joints differ by {worst} m");
        let start = (common::mat3_rows(&root[..9]), world[0]);
        check_objects(s, &mut archive, 1, start, Some);
    }
}

#[test]
fn grab_full_hands_round_trip_and_bad_inputs_are_reported() {
    let prepared = run(grab_options(HandPoseSource::Full));
    let dataset = prepared.dataset.as_ref().expect("a dataset");
    check_structure(dataset, "grab", "smplx52", 52, "grab");
    let m = &dataset.manifest;
    assert_eq!(m.objects, vec!["mug"]);
    assert_eq!(m.hand_joints, 32);
    assert_eq!(m.splits[&Split::Train].sequences, 2);
    assert_eq!(m.splits[&Split::Test].sequences, 1, "s10 is the test subject");
    assert_eq!(m.splits[&Split::Train].actions.keys().collect::<Vec<_>>(), ["lift", "pass"]);
    let pass = sequence(dataset, "grab/s1/mug_pass_1");
    assert_eq!(pass.texts, vec!["The person is passing the mug."]);
    assert_eq!(pass.action.as_deref(), Some("pass"));
    check_grab_joints(dataset, "full");

    // Five bad files in s2, each reported with its file and reason; the run went on.
    let report = &prepared.report;
    assert_eq!(report.found, 8);
    assert_eq!(report.failed.len(), 5, "{}", report.summary());
    let reason = |stem: &str| {
        report
            .failed
            .iter()
            .find(|f| f.id == format!("s2/{stem}"))
            .map(|f| f.reason.clone())
            .unwrap_or_else(|| panic!("{stem} is reported: {}", report.summary()))
    };
    let missing = reason("mug_pass_missingkey");
    assert!(missing.contains("mug_pass_missingkey.npz") && missing.contains("`body`"), "{missing}");
    let shape = reason("mug_pass_wrongshape");
    assert!(
        shape.contains("body.params.body_pose")
            && shape.contains("expected (25, 63)")
            && shape.contains("[25, 60]"),
        "{shape}"
    );
    let nan = reason("mug_pass_nan");
    assert!(nan.contains("object.params.transl") && nan.contains("non-finite"), "{nan}");
    let class = reason("mug_pass_unknownclass");
    assert!(class.contains("refused global `fractions.Fraction`"), "{class}");
    let truncated = reason("mug_pass_truncated");
    assert!(truncated.contains("mug_pass_truncated.npz"), "{truncated}");
    let summary = report.summary();
    assert!(summary.contains("read 3") && summary.contains("failed 5"), "{summary}");
}

#[test]
fn grab_pca_hands_go_through_the_model_components() {
    let prepared = run(grab_options(HandPoseSource::Pca));
    let dataset = prepared.dataset.as_ref().expect("a dataset");
    check_grab_joints(dataset, "pca");
}

#[test]
fn grab_needs_a_model_and_bad_models_are_named() {
    let mut options = grab_options(HandPoseSource::Full);
    options.smplx_model = None;
    let error = prepare(options, &|_, _| {}).unwrap_err().to_string();
    assert!(error.contains("--smplx-model"), "{error}");
    let mut options = grab_options(HandPoseSource::Full);
    options.smplx_model = Some(common::fixtures().join("misc/arrays.npz"));
    let prepared = run(options);
    assert!(prepared.dataset.is_none());
    let reason = &prepared.report.failed[0].reason;
    assert!(reason.contains("arrays.npz") && reason.contains("v_template"), "{reason}");
}

/// Output frame `k` at 20 fps of a 30 fps sequence is source frame `1.5 k`: compare even ones.
fn check_even_frames(s: &ProcessedSequence, expected_world: &[Vec3], joints: usize, root: Mat3) {
    let expected = common::canonical(expected_world, root, expected_world[0]);
    let mut worst = 0.0f32;
    for k in (0..s.frames).step_by(2) {
        let source = k * 3 / 2;
        for j in 0..joints {
            worst = worst.max(joint(s, k, j).distance(expected[source * joints + j]));
        }
    }
    assert!(worst < 1e-3, "{}: joints differ by {worst} m", s.source_id);
}

#[test]
fn humoto_round_trip_filter_and_meshes() {
    let fixtures = common::fixtures();
    let mut options = PrepareOptions::new(SourceFormat::Humoto, &fixtures.join("humoto"));
    options.split_files = vec![fixtures.join("humoto_split.json")];
    let prepared = run(options);
    let dataset = prepared.dataset.as_ref().expect("a dataset");
    check_structure(dataset, "humoto", "mixamo65", 65, "humoto");
    let report = &prepared.report;
    assert_eq!(report.skipped.len(), 1, "{}", report.summary());
    assert!(report.skipped[0].reason.contains("3 moving objects"), "{}", report.summary());
    assert_eq!(report.failed.len(), 1, "{}", report.summary());
    assert!(report.failed[0].reason.contains("broken_truncated.pkl"), "{}", report.summary());
    // The static table is left out; the embedded spoon model is used.
    let pick = sequence(dataset, "humoto/pick_mug");
    assert_eq!(pick.object_names, [Some("mug".to_string()), None]);
    assert_eq!(pick.texts, vec!["pick up the mug from the table"]);
    let stir = sequence(dataset, "humoto/stir_bowl");
    assert_eq!(stir.object_names, [Some("bowl".to_string()), Some("spoon".to_string())]);
    assert_eq!(dataset.manifest.objects, vec!["bowl", "mug", "spoon"]);
    let spoon = dataset.objects.iter().find(|o| o.name == "spoon").unwrap();
    let (lo, hi) = spoon.mesh.bounding_box();
    assert!((hi.x - lo.x - 0.024).abs() < 1e-5, "the embedded spoon, not the folder's");

    let skeleton = Skeleton::humoto_character();
    for seq in ["pick_mug", "stir_bowl"] {
        let mut archive = Npz::open(&fixtures.join(format!("expected/humoto/{seq}.npz"))).unwrap();
        let (local, shape) = number_array(&mut archive, "local");
        let (root, _) = number_array(&mut archive, "root");
        let rotations: Vec<Mat3> = local.chunks_exact(9).map(common::mat3_rows).collect();
        let roots: Vec<Vec3> = root
            .chunks_exact(3)
            .map(|p| Vec3::new(p[0] as f32, p[1] as f32, p[2] as f32))
            .collect();
        assert_eq!(rotations.len(), shape[0] * 65);
        let fk = forward_kinematics(&skeleton, &rotations, &roots).unwrap();
        let s = sequence(dataset, &format!("humoto/{seq}"));
        assert_eq!(s.frames, (shape[0] - 1) * 2 / 3 + 1, "30 -> 20 fps");
        check_even_frames(s, &fk.positions, 65, rotations[0]);
    }
}

#[test]
fn himo_round_trip_and_three_object_sequences() {
    let fixtures = common::fixtures();
    let mut options = PrepareOptions::new(SourceFormat::Himo, &fixtures.join("himo"));
    options.smplx_model = Some(fixtures.join("smplx"));
    options.split_files = vec![fixtures.join("himo_split.json")];
    let prepared = run(options);
    let dataset = prepared.dataset.as_ref().expect("a dataset");
    check_structure(dataset, "himo", "smplx52", 52, "himo");
    let report = &prepared.report;
    assert!(report.failed.is_empty(), "{}", report.summary());
    assert_eq!(report.skipped.len(), 1);
    assert_eq!(report.skipped[0].id, "S02T001");
    assert!(report.skipped[0].reason.contains("3 objects"));
    let first = sequence(dataset, "himo/S01T001");
    assert_eq!(first.object_names, [Some("Apple".to_string()), Some("Cup".to_string())]);
    assert_eq!(
        first.texts,
        ["A person moves the apple next to the cup.", "Someone tidies the cup."]
    );
    for seq in ["S01T001", "S01T002"] {
        let path = fixtures.join(format!("expected/himo/{seq}.npz"));
        let (values, _, mut archive) = read_expected(&path);
        let (root, _) = number_array(&mut archive, "root_rotation");
        let world: Vec<Vec3> = values
            .chunks_exact(3)
            .map(|p| Vec3::new(p[0] as f32, p[1] as f32, p[2] as f32))
            .collect();
        let s = sequence(dataset, &format!("himo/{seq}"));
        check_even_frames(s, &world, 52, common::mat3_rows(&root[..9]));
        let start = (common::mat3_rows(&root[..9]), world[0]);
        check_objects(s, &mut archive, 2, start, |k| (k % 2 == 0).then_some(k * 3 / 2));
    }
    // The 3-object sequence stays readable.
    let three =
        dex2hoi_import::himo::read_sequence(&fixtures.join("himo/data"), "S02T001").unwrap();
    assert_eq!(three.objects.len(), 3);
    assert_eq!(three.objects[2].name, "Plate");
    assert_eq!(three.params.frames(), 31);
}

#[test]
fn a_wrong_up_axis_is_refused_with_the_numbers() {
    // HIMO's fixture is Y up (the format's default); read as Z up, every body lies down.
    let fixtures = common::fixtures();
    let mut options = PrepareOptions::new(SourceFormat::Himo, &fixtures.join("himo"));
    options.smplx_model = Some(fixtures.join("smplx"));
    options.up_axis = Some(dex2hoi_import::smplx::UpAxis::Z);
    let prepared = run(options);
    assert!(prepared.dataset.is_none());
    let report = &prepared.report;
    assert_eq!(report.failed.len(), 2, "{}", report.summary());
    for failed in &report.failed {
        assert!(
            failed.reason.contains("posture")
                && failed.reason.contains("up axis")
                && failed.reason.contains(" m: the body lies down"),
            "{}",
            failed.reason
        );
    }
}

#[test]
fn grab_hoidini_protocol_split_lists_intents_and_prompts() {
    let fixtures = common::fixtures();
    let mut options = grab_options(HandPoseSource::Full);
    options.split_files =
        vec![fixtures.join("grab_train_split.json"), fixtures.join("grab_test_split.json")];
    options.exclude_intents = vec!["lift".into()];
    options.prompts = Some(fixtures.join("grab_prompts.csv"));
    let prepared = run(options);
    let report = &prepared.report;
    assert!(report.failed.is_empty(), "{}", report.summary());
    let dataset = prepared.dataset.as_ref().expect("a dataset");
    // The lists decide the split; the lift sequence is left out by its intent; the s2 files
    // (the broken ones included) are not listed, so they are not even read.
    let reason = |id: &str| {
        report.skipped.iter().find(|s| s.id == id).map(|s| s.reason.clone()).unwrap_or_default()
    };
    assert!(reason("s1/mug_lift").contains("intent `lift` left out"), "{}", report.summary());
    assert!(reason("s2/mug_pass_nan").contains("not listed"), "{}", report.summary());
    assert_eq!(dataset.splits[&Split::Train].len(), 1);
    assert_eq!(dataset.splits[&Split::Test].len(), 1);
    // The prompt table's text (quoted, with a comma); a sequence it does not list keeps the
    // templates and says so.
    let pass = sequence(dataset, "grab/s1/mug_pass_1");
    assert_eq!(pass.texts, ["The person is passing a mug, carefully."]);
    let drink = sequence(dataset, "grab/s10/mug_drink_1");
    assert_eq!(drink.texts, ["The person is drinking from the mug."]);
    assert!(
        report.warnings.iter().any(|w| w.id == "s10/mug_drink_1" && w.reason.contains("no prompt")),
        "{}",
        report.summary()
    );
}

#[test]
fn bad_split_files_and_prompt_tables_are_named() {
    let dir = common::temp_dir("bad-protocol-files");
    std::fs::create_dir_all(&dir).unwrap();
    let write = |name: &str, text: &str| {
        let path = dir.join(name);
        std::fs::write(&path, text).unwrap();
        path
    };
    let cases = [
        (write("ids.json", r#"["s1/mug_pass_1"]"#), None, "`train` or `test`"),
        (
            write(
                "clash_train.json",
                r#"{"train": ["s1/mug_pass_1"], "test": ["s1/mug_pass_1.npz"]}"#,
            ),
            None,
            "one split per sequence",
        ),
        (write("no_header.json", "{}"), Some(write("p.csv", "id,text\na,b\n")), "dp_ind"),
        (
            write("ok_train.json", "[]"),
            Some(write("q.csv", "dp_ind,Prompt\n\"s1/x,oops\n")),
            "never closed",
        ),
    ];
    for (split, prompts, needle) in cases {
        let mut options = grab_options(HandPoseSource::Full);
        options.split_files = vec![split.clone()];
        options.prompts = prompts.clone();
        let error = match prepare(options, &|_, _| {}) {
            Ok(prepared) => panic!("{needle}: accepted: {}", prepared.report.summary()),
            Err(error) => error.to_string(),
        };
        let named = prompts.as_ref().unwrap_or(&split);
        assert!(
            error.contains(needle) && error.contains(&named.display().to_string()),
            "{needle}: {error}"
        );
    }
    std::fs::remove_dir_all(dir).ok();
}

#[test]
fn humoto_discovery_prefers_the_published_glb() {
    let root = common::temp_dir("humoto-discovery");
    for (folder, files) in
        [("both", ["both.glb", "both.pkl"].as_slice()), ("pickle", ["pickle.pkl"].as_slice())]
    {
        std::fs::create_dir_all(root.join(folder)).unwrap();
        for file in files {
            std::fs::write(root.join(folder).join(file), b"").unwrap();
        }
    }
    std::fs::create_dir_all(root.join("humoto_objects/mug")).unwrap();
    std::fs::write(root.join("humoto_objects/mug/mug.pkl"), b"").unwrap();
    let options = PrepareOptions::new(SourceFormat::Humoto, &root);
    let (items, skipped) = dex2hoi_import::humoto::discover(&options).unwrap();
    assert!(skipped.is_empty());
    let found: Vec<(String, String)> = items
        .iter()
        .map(|i| (i.id.clone(), i.path.file_name().unwrap().to_string_lossy().into_owned()))
        .collect();
    assert_eq!(found, [("both".into(), "both.glb".into()), ("pickle".into(), "pickle.pkl".into())]);
    std::fs::remove_dir_all(root).ok();
}
