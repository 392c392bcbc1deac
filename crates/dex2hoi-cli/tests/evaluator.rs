//! `dex2hoi evaluator train` end to end: a procedural dataset, a short training, the files, and
//! bad input.

mod common;
use common::dex2hoi;

#[test]
fn evaluator_train_writes_the_evaluator_and_refuses_bad_input() {
    let dir = std::env::temp_dir().join(format!("dex2hoi-cli-evaluator-{}", std::process::id()));
    std::fs::remove_dir_all(&dir).ok();
    std::fs::create_dir_all(&dir).unwrap();
    let data = dir.join("data");
    let out = dir.join("evaluator");
    let (data, out_path) = (data.to_str().unwrap(), out.to_str().unwrap());
    let made = dex2hoi(&["data", "synth", "--out", data, "--sequences", "16", "--seed", "4"]);
    assert!(made.status.success(), "{}", String::from_utf8_lossy(&made.stderr));

    let config = dir.join("evaluator.json");
    std::fs::write(&config, r#"{ "latent": 32, "layers": 1, "clip_frames": 30, "embedding": 16 }"#)
        .unwrap();
    let config = config.to_str().unwrap();
    let trained = dex2hoi(&[
        "evaluator",
        "train",
        "--data",
        data,
        "--out",
        out_path,
        "--config",
        config,
        "--steps",
        "20",
        "--seed",
        "3",
    ]);
    assert!(trained.status.success(), "{}", String::from_utf8_lossy(&trained.stderr));
    let stdout = String::from_utf8_lossy(&trained.stdout);
    assert!(stdout.contains("trained 20 steps: loss"), "{stdout}");
    assert!(stdout.contains("no held-out retrieval"), "{stdout}");
    assert!(out.join("evaluator.safetensors").is_file());
    let stats = std::fs::read_to_string(out.join("stats.json")).unwrap();
    assert!(stats.contains("\"feature_size\""), "{stats}");
    let loaded = dex2hoi_eval::evaluator::Evaluator::load(&out, &candle_core::Device::Cpu).unwrap();
    assert_eq!(loaded.config().steps, 20);
    assert_eq!(loaded.config().seed, 3);
    assert_eq!(loaded.config().latent, 32);

    let failed = |args: &[&str], needle: &str| {
        let output = dex2hoi(args);
        let stderr = String::from_utf8_lossy(&output.stderr);
        assert!(!output.status.success(), "{args:?} succeeded");
        assert!(stderr.contains(needle), "{args:?}: {stderr}");
    };
    let missing = dir.join("no-such-dataset");
    let missing = missing.to_str().unwrap();
    failed(&["evaluator", "train", "--data", missing, "--out", out_path], "no-such-dataset");
    failed(&["evaluator", "train", "--data", data, "--out", out_path, "--steps", "0"], "--steps");
    let bad_config = dir.join("bad.json");
    std::fs::write(&bad_config, r#"{ "latent": 30, "heads": 4 }"#).unwrap();
    failed(
        &[
            "evaluator",
            "train",
            "--data",
            data,
            "--out",
            out_path,
            "--config",
            bad_config.to_str().unwrap(),
        ],
        "heads",
    );
    std::fs::write(&bad_config, r#"{ "width": 3 }"#).unwrap();
    failed(
        &[
            "evaluator",
            "train",
            "--data",
            data,
            "--out",
            out_path,
            "--config",
            bad_config.to_str().unwrap(),
        ],
        "bad.json",
    );
    failed(&["evaluator", "train", "--data", data], "--out");
    std::fs::remove_dir_all(&dir).ok();
}
