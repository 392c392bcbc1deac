//! `dex2hoi evaluate` end to end on a tiny run and a tiny evaluator: the report files, the
//! table's rows and columns, the embeddings dump, and bad input.

use std::path::Path;

mod common;
use common::dex2hoi;

fn ok(output: &std::process::Output) -> String {
    assert!(output.status.success(), "{}", String::from_utf8_lossy(&output.stderr));
    String::from_utf8_lossy(&output.stdout).into_owned()
}

#[test]
fn evaluate_writes_the_report_and_refuses_bad_input() {
    let dir = std::env::temp_dir().join(format!("dex2hoi-cli-evaluate-{}", std::process::id()));
    std::fs::remove_dir_all(&dir).ok();
    let config =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../../configs/tiny.toml").display().to_string();
    let (data, run, evaluator, out) =
        (dir.join("data"), dir.join("run"), dir.join("evaluator"), dir.join("report"));
    let (data, run, evaluator, out) = (
        data.to_str().unwrap(),
        run.to_str().unwrap(),
        evaluator.to_str().unwrap(),
        out.to_str().unwrap(),
    );
    // 80 sequences: every tenth block of eight is a test sequence, so 8 test sequences.
    ok(&dex2hoi(&["data", "synth", "--out", data, "--sequences", "80", "--seed", "6"]));
    ok(&dex2hoi(&["train", "--config", &config, "--data", data, "--out", run, "--steps", "3"]));
    ok(&dex2hoi(&["evaluator", "train", "--data", data, "--out", evaluator, "--steps", "3"]));
    // `dex2hoi evaluate` of the run into `out`, with more options.
    let evaluate_into = |out: &str, options: &[&str]| {
        let mut args =
            vec!["evaluate", "--run", run, "--data", data, "--evaluator", evaluator, "--out", out];
        args.extend_from_slice(options);
        dex2hoi(&args)
    };
    let stdout = ok(&evaluate_into(
        out,
        &[
            "--replications",
            "2",
            "--sequences",
            "4",
            "--ddim-steps",
            "2",
            "--multimodality",
            "2,2,1",
            "--dump-embeddings",
        ],
    ));
    let report = std::fs::read_to_string(dir.join("report/report.md")).unwrap();
    assert_eq!(stdout.lines().next(), report.lines().next());
    // The main table, then "## Objects", "## Grasp" and "## Instruction following" tables.
    let sections: Vec<&str> = report.split("\n## ").collect();
    assert_eq!(sections.len(), 4, "{report}");
    let rows: Vec<&str> = sections[0].lines().filter(|l| l.starts_with('|')).collect();
    assert_eq!(rows.len(), 4, "header, separator, ground truth, run:\n{report}");
    assert!(rows[0].contains("FID") && rows[0].contains("Foot sliding (mm/frame)"), "{report}");
    assert!(rows[2].starts_with("| Ground truth |"), "{report}");
    assert!(rows[3].starts_with("| Dex2HOI (this run) |"), "{report}");
    let columns = rows[0].matches('|').count();
    assert_eq!(rows[1].matches('|').count(), columns, "the separator has one cell per column");
    assert_eq!(rows[2].matches('|').count(), columns);
    assert_eq!(rows[3].matches('|').count(), columns);
    assert!(report.contains("4 test sequences") && report.contains("2 replications"), "{report}");
    let objects: Vec<&str> = sections[1].lines().filter(|l| l.starts_with('|')).collect();
    assert!(sections[1].starts_with("Objects") && objects.len() == 4, "{report}");
    assert!(
        objects[0].contains("Start jump")
            && objects[0].contains("Untouched")
            && objects[0].contains("Start turn")
            && objects[0].contains("Untouched turning")
            && objects[0].contains("Sinking"),
        "{report}"
    );
    let grasp: Vec<&str> = sections[2].lines().filter(|l| l.starts_with('|')).collect();
    assert!(sections[2].starts_with("Grasp") && grasp.len() == 4, "{report}");
    assert!(grasp[0].contains("Fingertip distance") && grasp[0].contains("Fingertip error"));
    // The ground truth against itself: no fingertip error.
    assert!(grasp[2].starts_with("| Ground truth |") && grasp[2].ends_with("| 0.0 ± 0.0 |"));
    let instruction: Vec<&str> = sections[3].lines().filter(|l| l.starts_with('|')).collect();
    assert!(sections[3].starts_with("Instruction following"), "{report}");
    assert!(instruction[0].contains("Objects moved") && instruction[0].contains("Holding hand"));
    // All clips first, then each task family of the four test sequences.
    assert!(instruction.len() >= 4 && instruction[2].starts_with("| all | 4 |"), "{report}");
    for row in &instruction {
        assert_eq!(row.matches('|').count(), instruction[0].matches('|').count(), "{row}");
    }
    let json: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.join("report/report.json")).unwrap()).unwrap();
    let fid = json["rows"][0]["fid"]["mean"].as_f64().unwrap();
    assert_eq!(fid, 0.0, "the ground truth against itself");
    assert!(json["rows"][1]["fid"]["mean"].as_f64().unwrap() > 0.0);
    assert_eq!(json["instruction"][0]["group"], "all");
    // The "all" group's R-precision is the overall one, for the run and for the ground truth.
    for (row, column) in [(1, "r_precision_top3"), (0, "truth_r_precision_top3")] {
        assert_eq!(
            json["instruction"][0][column]["mean"], json["rows"][row]["r_precision"][2]["mean"],
            "{column}"
        );
    }
    assert!(instruction[0].contains("R-prec. top-3"), "{report}");
    let turn = &json["rows"][0]["physical"]["object_start_turn_deg"];
    assert!(
        turn["mean"].as_f64().unwrap() < 0.5,
        "the ground truth does not turn at its start: {turn}"
    );
    assert_eq!(json["instruction"].as_array().unwrap().len(), instruction.len() - 2);
    let physical = &json["rows"][1]["physical"];
    assert!(physical["fingertip_error_mm"]["mean"].as_f64().unwrap() > 0.0, "{physical}");
    let runtime = &json["rows"][1]["runtime_seconds"];
    assert!(runtime[0].as_f64().unwrap() > 0.0, "{runtime}");
    let npz = std::fs::read(dir.join("report/embeddings.npz")).unwrap();
    assert_eq!(&npz[..2], b"PK");
    // The clips are there too: 4 clips of the evaluator's frames, 52 joints, 2 object slots.
    let mut archive = npyz::npz::NpzArchive::new(std::io::Cursor::new(npz)).unwrap();
    let shape = |archive: &mut npyz::npz::NpzArchive<_>, name: &str| -> Vec<u64> {
        archive.by_name(name).unwrap().unwrap_or_else(|| panic!("{name}")).shape().to_vec()
    };
    let joints = shape(&mut archive, "generated_joints");
    assert!(joints[0] == 4 && joints[1] > 0 && joints[2..] == [52, 3], "{joints:?}");
    let frames = joints[1];
    assert_eq!(shape(&mut archive, "ground_truth_object_rotations"), [4, frames, 2, 3, 3]);
    assert_eq!(shape(&mut archive, "generated_object_positions"), [4, frames, 2, 3]);
    assert_eq!(shape(&mut archive, "actions"), [4]);
    // The setup: the weights' steps and the sampler, in the JSON and the markdown.
    let setup = &json["setup"];
    assert_eq!(setup["model_step"], 3, "{setup}");
    assert_eq!(
        (setup["sampler"].as_str(), setup["denoising_steps"].as_u64()),
        (Some("ddim"), Some(2))
    );
    assert_eq!(setup["guidance"].as_f64(), Some(2.0), "{setup}");
    assert!(
        report.contains(
            "Weights after 3 training steps; sampler: DDIM (eta 0), 2 steps, guidance 2, seed 0."
        ),
        "{report}"
    );

    // DDPM without guidance, recorded as such.
    let ddpm = dir.join("reports/ddpm");
    ok(&evaluate_into(
        ddpm.to_str().unwrap(),
        &[
            "--replications",
            "1",
            "--sequences",
            "2",
            "--sampler",
            "ddpm",
            "--denoising-steps",
            "2",
            "--guidance",
            "1",
            "--multimodality",
            "0,1,1",
        ],
    ));
    let json: serde_json::Value =
        serde_json::from_slice(&std::fs::read(ddpm.join("report.json")).unwrap()).unwrap();
    assert_eq!(json["setup"]["sampler"], "ddpm");
    assert!(json["setup"]["eta"].is_null() && json["setup"]["guidance"].is_null(), "{json}");
    // `evaluate` samples as the paper does unless told otherwise.
    assert_eq!(json["setup"]["objects_at_rest"], false);
    assert_eq!(json["setup"]["continuous_seams"], false);

    // The long-generation protocol beside the paper's, with the sampler's rules: a table
    // per set in report.md, the numbers in report.json; the ground truth does its own task as
    // asked, once, with nothing off its support.
    let long = dir.join("long");
    ok(&evaluate_into(
        long.to_str().unwrap(),
        &[
            "--replications",
            "1",
            "--sequences",
            "4",
            "--ddim-steps",
            "2",
            "--multimodality",
            "0,1,1",
            "--long",
            "--long-frames",
            "30",
            "--free-objects",
            "at-rest",
            "--seams",
            "continuous",
        ],
    ));
    let report = std::fs::read_to_string(long.join("report.md")).unwrap();
    assert!(report.contains("\n## Long generations\n"), "{report}");
    // The sampler's rules beyond the paper are in the report.
    assert!(report.contains("seed 0, objects at rest, continuous seams"), "{report}");
    let json: serde_json::Value =
        serde_json::from_slice(&std::fs::read(long.join("report.json")).unwrap()).unwrap();
    assert_eq!(json["format"], 3);
    assert_eq!(json["setup"]["objects_at_rest"], true);
    assert_eq!(json["setup"]["continuous_seams"], true);
    assert_eq!(json["long"]["frames"], 30);
    // The tiny run's windows of 8 frames: seams at frames 8, 16 and 24.
    assert_eq!(json["long"]["window"], 8);
    let sets = json["long"]["sets"].as_array().unwrap();
    let kinds: Vec<&str> = sets.iter().map(|s| s["kind"].as_str().unwrap()).collect();
    assert_eq!(kinds, ["as-in-data", "moved", "held-out"], "{json}");
    assert_eq!(report.matches("\n### ").count(), 3, "{report}");
    for set in sets {
        let all = &set["rows"][0];
        assert_eq!(all["family"], "all");
        assert_eq!(all["truth"]["as_asked"].as_f64(), Some(1.0), "{set}");
        assert_eq!(all["truth"]["lifted_again"].as_f64(), Some(0.0), "{set}");
        assert!(all["truth"]["off_support_cm"].as_f64().unwrap() < 0.01, "{set}");
        assert!(all["truth"]["floor_drift_cm"].as_f64().unwrap() < 0.01, "{set}");
        assert!(all["model"]["body_seam_jump_cm"].as_f64().unwrap() >= 0.0, "{set}");
        let share = all["model"]["as_asked"].as_f64().unwrap();
        assert!((0.0..=1.0).contains(&share), "{set}");
    }
    // The paper's protocol alone has no long section.
    assert!(!std::fs::read_to_string(ddpm.join("report.md")).unwrap().contains("Long"));
    // --long-frames needs --long.
    let bad = evaluate_into(long.to_str().unwrap(), &["--long-frames", "30"]);
    assert!(!bad.status.success());

    // compare: one series from a report directory, one from a directory of them.
    std::fs::rename(dir.join("report"), dir.join("reports/ddim")).unwrap();
    let compared = dir.join("compare");
    let stdout = ok(&dex2hoi(&[
        "compare",
        "--series",
        &format!("one={}", ddpm.display()),
        "--series",
        &format!("both={}", dir.join("reports").display()),
        "--out",
        compared.to_str().unwrap(),
    ]));
    let markdown = std::fs::read_to_string(compared.join("comparison.md")).unwrap();
    assert_eq!(stdout.lines().next(), markdown.lines().next());
    let tables: Vec<&str> = markdown.split("\n## ").skip(1).collect();
    assert_eq!(tables.len(), 2, "{markdown}");
    assert!(tables[0].starts_with("one\n") && tables[1].starts_with("both\n"), "{markdown}");
    let rows = |table: &str| table.lines().filter(|l| l.starts_with('|')).count();
    assert_eq!(rows(tables[0]), 4, "header, separator, one step, ground truth:\n{markdown}");
    assert_eq!(rows(tables[1]), 5, "two reports of step 3:\n{markdown}");
    assert!(tables[1].contains("| 3 | ") && tables[1].contains("| ground truth | "), "{markdown}");
    // The DDIM report (in "both") was evaluated differently from the first (DDPM) one.
    let warning = markdown.split("**Not comparable with the first report**").nth(1).unwrap();
    assert!(warning.contains("reports/ddim") && !warning.contains("reports/ddpm`,"), "{markdown}");
    let png = std::fs::read(compared.join("comparison.png")).unwrap();
    assert_eq!(&png[1..4], b"PNG");
    // A report without the setup (an older dex2hoi's), an empty directory, a malformed series.
    let old = dir.join("old");
    std::fs::create_dir_all(&old).unwrap();
    std::fs::write(old.join("report.json"), r#"{"rows": []}"#).unwrap();
    let series = format!("old={}", old.display());
    let bad = dex2hoi(&["compare", "--series", &series, "--out", compared.to_str().unwrap()]);
    let stderr = String::from_utf8_lossy(&bad.stderr);
    assert!(!bad.status.success() && stderr.contains("older dex2hoi"), "{stderr}");
    assert!(stderr.contains(&old.join("report.json").display().to_string()), "{stderr}");
    std::fs::remove_file(old.join("report.json")).unwrap();
    let bad = dex2hoi(&["compare", "--series", &series, "--out", compared.to_str().unwrap()]);
    assert!(String::from_utf8_lossy(&bad.stderr).contains("no report.json"));
    let bad = dex2hoi(&["compare", "--series", "nolabel", "--out", compared.to_str().unwrap()]);
    assert_eq!(bad.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&bad.stderr).contains("expected LABEL=DIR"));
    let out = dir.join("reports/ddim");
    let out = out.to_str().unwrap();

    // Bad input: a missing evaluator, a missing run, zero replications.
    let bad = dex2hoi(&[
        "evaluate",
        "--run",
        run,
        "--data",
        data,
        "--evaluator",
        "/nonexistent/eval",
        "--out",
        out,
    ]);
    assert!(!bad.status.success());
    assert!(String::from_utf8_lossy(&bad.stderr).contains("/nonexistent/eval"));
    let bad = dex2hoi(&[
        "evaluate",
        "--run",
        "/nonexistent/run",
        "--data",
        data,
        "--evaluator",
        evaluator,
        "--out",
        out,
    ]);
    assert!(String::from_utf8_lossy(&bad.stderr).contains("/nonexistent/run"));
    let bad = dex2hoi(&[
        "evaluate",
        "--run",
        run,
        "--data",
        data,
        "--evaluator",
        evaluator,
        "--out",
        out,
        "--replications",
        "0",
    ]);
    assert!(String::from_utf8_lossy(&bad.stderr).contains("--replications"));
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn evaluate_parses_the_multimodality_protocol() {
    // Parsing comes before anything is loaded, so the paths need not exist.
    let with = |extra: &[&str]| {
        let mut args = vec![
            "evaluate",
            "--run",
            "/nonexistent/run",
            "--data",
            "/nonexistent/data",
            "--evaluator",
            "/nonexistent/eval",
            "--out",
            "/nonexistent/out",
        ];
        args.extend_from_slice(extra);
        dex2hoi(&args)
    };
    for (value, reason) in [
        ("2,2", "PROMPTS,REPEATS,PAIRS"),
        ("2,two,1", "PROMPTS,REPEATS,PAIRS"),
        ("2,2,3", "between 1 and the generations per prompt (2)"),
        ("2,4,0", "between 1 and the generations per prompt (4)"),
    ] {
        let bad = with(&["--multimodality", value]);
        let stderr = String::from_utf8_lossy(&bad.stderr);
        assert_eq!(bad.status.code(), Some(2), "{value}: a usage error\n{stderr}");
        assert!(
            stderr.contains(&format!("invalid value '{value}' for '--multimodality")),
            "{stderr}"
        );
        assert!(stderr.contains(reason), "{value}: {stderr}");
    }
    let both = with(&["--multimodality", "2,2,1", "--paper-multimodality"]);
    assert_eq!(both.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&both.stderr).contains("cannot be used with"));
    // The default does not conflict with --paper-multimodality: parsing passes, the run is
    // missing.
    let paper = with(&["--paper-multimodality"]);
    assert_eq!(paper.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&paper.stderr).contains("/nonexistent/run"));
    // The sampler's options are checked before anything is loaded.
    for (extra, reason) in [
        (["--ddim-steps", "0"], "--denoising-steps (--ddim-steps) must be at least 1"),
        (["--guidance", "-1"], "--guidance must be a non-negative number, got -1"),
        (["--guidance", "NaN"], "--guidance must be a non-negative number, got NaN"),
    ] {
        let bad = with(&extra);
        let stderr = String::from_utf8_lossy(&bad.stderr);
        assert_eq!(bad.status.code(), Some(1), "{extra:?}: {stderr}");
        assert!(stderr.contains(reason) && !stderr.contains("/nonexistent"), "{stderr}");
    }
    let bad = with(&["--sampler", "euler"]);
    assert_eq!(bad.status.code(), Some(2), "an unknown sampler is a usage error");
    // The default shown is the library's.
    let help = ok(&dex2hoi(&["evaluate", "--help"]));
    let default = dex2hoi_eval::metrics::MultimodalityProtocol::default();
    assert!(help.contains(&format!("[default: {default}]")), "{help}");
    assert!(help.contains("[default: 8,4,3]"), "{help}");
}
