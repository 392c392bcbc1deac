//! The `dex2hoi` binary end to end.

mod common;
use common::dex2hoi;

#[test]
fn synth_then_info() {
    let dir = std::env::temp_dir().join(format!("dex2hoi-cli-{}", std::process::id()));
    std::fs::remove_dir_all(&dir).ok();
    let out = dir.to_str().unwrap();
    let run = dex2hoi(&["data", "synth", "--out", out, "--sequences", "24", "--seed", "1"]);
    assert!(run.status.success(), "{}", String::from_utf8_lossy(&run.stderr));
    let stdout = String::from_utf8_lossy(&run.stdout);
    assert!(stdout.contains("wrote 24 sequences"), "{stdout}");
    for file in [
        "manifest.json",
        "train.safetensors",
        "train.json",
        "objects.safetensors",
        "stats.safetensors",
    ] {
        assert!(dir.join(file).is_file(), "{file}");
    }
    let info = dex2hoi(&["data", "info", out]);
    assert!(info.status.success(), "{}", String::from_utf8_lossy(&info.stderr));
    let text = String::from_utf8_lossy(&info.stdout);
    assert!(text.contains("train: 24 sequences"), "{text}");
    assert!(text.contains("skeleton smplx52 (52 joints)"), "{text}");
    assert!(text.contains("pick_place 3"), "{text}");
    assert!(text.contains("e.g. synth-00000"), "{text}");
    // The procedural data is posed on the built-in skeleton: one body.
    assert!(text.contains("rest skeletons: 1 distinct, rest height 1.58-1.58 m"), "{text}");
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn bad_input_gives_clear_errors() {
    let run = dex2hoi(&["data", "synth", "--out", "/tmp/never-written", "--sequences", "0"]);
    assert!(!run.status.success());
    assert!(String::from_utf8_lossy(&run.stderr).contains("--sequences must be at least 1"));
    let missing = dex2hoi(&["data", "info", "/nonexistent/dataset"]);
    assert!(!missing.status.success());
    let stderr = String::from_utf8_lossy(&missing.stderr);
    assert!(
        stderr.contains("/nonexistent/dataset") && stderr.contains("manifest.json"),
        "{stderr}"
    );
    let unknown = dex2hoi(&["data", "frobnicate"]);
    assert!(!unknown.status.success());
}

/// `--device` on every command that computes: a malformed name is refused by the parser, and
/// CUDA in a build without it says how to get the GPU build, before anything is read.
#[test]
fn devices_are_checked_before_any_work() {
    let commands: [&[&str]; 4] = [
        &["train", "--config", "configs/tiny.toml", "--data", "/nonexistent", "--out", "/tmp/x"],
        &["sample", "--text", "The person lifts the mug.", "--object", "mug", "--out", "/tmp/x"],
        &[
            "evaluate",
            "--run",
            "/nonexistent",
            "--data",
            "/nonexistent",
            "--evaluator",
            "/x",
            "--out",
            "/tmp/x",
        ],
        &["evaluator", "train", "--data", "/nonexistent", "--out", "/tmp/x"],
    ];
    for command in commands {
        let bad = dex2hoi(&[command, &["--device", "gpu"]].concat());
        assert!(!bad.status.success());
        let stderr = String::from_utf8_lossy(&bad.stderr);
        assert!(stderr.contains("expected cpu, cuda or cuda:N"), "{command:?}: {stderr}");
        if !cfg!(feature = "cuda") {
            let cuda = dex2hoi(&[command, &["--device", "cuda:0"]].concat());
            assert!(!cuda.status.success());
            let stderr = String::from_utf8_lossy(&cuda.stderr);
            assert!(
                stderr.contains("built without CUDA support")
                    && stderr.contains("cargo xtask build-cuda"),
                "{command:?}: {stderr}"
            );
        }
    }
}
