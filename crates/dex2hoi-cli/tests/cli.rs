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
    assert!(text.contains("mixture targets: proximity"), "{text}");
    std::fs::remove_dir_all(&dir).ok();
}

/// `data synth --mixture-targets free-at-rest`: recorded in the manifest; the same motions, and
/// mixture logits that differ where an object stands still under a hand.
#[test]
fn synth_frees_objects_at_rest_when_asked() {
    let dir = common::temp_dir("cli", "synth-mixture");
    let path = |name: &str| dir.join(name).to_str().unwrap().to_string();
    let (free, paper) = (path("free"), path("paper"));
    let args = ["data", "synth", "--sequences", "10", "--seed", "3"];
    common::succeed(&[&args[..], &["--out", &free, "--mixture-targets", "free-at-rest"]].concat());
    common::succeed(&[&args[..], &["--out", &paper]].concat());
    let manifest = |dir: &str| -> serde_json::Value {
        serde_json::from_slice(
            &std::fs::read(std::path::Path::new(dir).join("manifest.json")).unwrap(),
        )
        .unwrap()
    };
    assert_eq!(manifest(&free)["mixture_targets"], "free_at_rest");
    assert_eq!(manifest(&paper)["mixture_targets"], "proximity");
    let info = common::succeed(&["data", "info", &free]);
    assert!(info.contains("mixture targets: free at rest"), "{info}");
    let texts = |dir: &str| std::fs::read(std::path::Path::new(dir).join("train.json")).unwrap();
    assert_eq!(texts(&free), texts(&paper), "the same sequences and texts");
    let features =
        |dir: &str| std::fs::read(std::path::Path::new(dir).join("train.safetensors")).unwrap();
    assert_ne!(features(&free), features(&paper));
    let wrong =
        common::fail(&[&args[..], &["--out", &path("x"), "--mixture-targets", "near"]].concat());
    assert!(wrong.contains("proximity") && wrong.contains("free-at-rest"), "{wrong}");
    std::fs::remove_dir_all(&dir).ok();
}

/// `data synth --texts templates --rest short`: the same sequences, each task described by its
/// fixed sentences, without the rest after the task; an unknown choice is refused.
#[test]
fn synth_takes_template_texts_and_short_rest() {
    let dir = common::temp_dir("cli", "synth-options");
    let path = |name: &str| dir.join(name).to_str().unwrap().to_string();
    let (drawn, short) = (path("drawn"), path("short"));
    let args = ["data", "synth", "--sequences", "8", "--seed", "2"];
    common::succeed(&[&args[..], &["--out", &drawn]].concat());
    common::succeed(
        &[&args[..], &["--out", &short, "--texts", "templates", "--rest", "short"]].concat(),
    );
    let read = |dir: &str, file: &str| -> serde_json::Value {
        let bytes = std::fs::read(std::path::Path::new(dir).join(file)).unwrap();
        serde_json::from_slice(&bytes).unwrap()
    };
    let (drawn_texts, short_texts) = (read(&drawn, "train.json"), read(&short, "train.json"));
    let first = &short_texts[0]["texts"][0];
    assert!(first.as_str().unwrap().starts_with("The person picks up the "), "{first}");
    assert_ne!(drawn_texts[0]["texts"], short_texts[0]["texts"]);
    assert_eq!(drawn_texts[0]["held_out_texts"], short_texts[0]["held_out_texts"]);
    // No rest after the task: fewer frames.
    let frames = |dir: &str| read(dir, "manifest.json")["splits"]["train"]["frames"].as_u64();
    assert!(frames(&short).unwrap() < frames(&drawn).unwrap());
    // --texts both: the grammar's phrasings, then the fixed sentences.
    let both = path("both");
    common::succeed(&[&args[..], &["--out", &both, "--texts", "both"]].concat());
    let templates = path("templates");
    common::succeed(&[&args[..], &["--out", &templates, "--texts", "templates"]].concat());
    let texts = |dir: &str| read(dir, "train.json")[0]["texts"].as_array().unwrap().clone();
    assert_eq!(texts(&both), [texts(&drawn), texts(&templates)].concat());
    let wrong = common::fail(&[&args[..], &["--out", &path("x"), "--rest", "none"]].concat());
    assert!(
        wrong.contains("--rest") && wrong.contains("drawn") && wrong.contains("short"),
        "{wrong}"
    );
    std::fs::remove_dir_all(&dir).ok();
}

/// `data synth --tempo drawn`: the tasks at other paces, so other frames; the same families and,
/// but where the physical checks refuse a plan at one pace and not at the other, the same
/// places, objects and words as the even pace (the default); `--tempo even` is the default to
/// the byte; an unknown pace is refused with the choices.
#[test]
fn synth_draws_the_task_pace_when_asked() {
    let dir = common::temp_dir("cli", "synth-tempo");
    let path = |name: &str| dir.join(name).to_str().unwrap().to_string();
    let (default, even, drawn) = (path("default"), path("even"), path("drawn"));
    let args = ["data", "synth", "--sequences", "16", "--seed", "4"];
    common::succeed(&[&args[..], &["--out", &default]].concat());
    common::succeed(&[&args[..], &["--out", &even, "--tempo", "even"]].concat());
    common::succeed(&[&args[..], &["--out", &drawn, "--tempo", "drawn"]].concat());
    let bytes =
        |dir: &str, file: &str| std::fs::read(std::path::Path::new(dir).join(file)).unwrap();
    for file in ["train.json", "train.safetensors", "manifest.json"] {
        assert!(bytes(&default, file) == bytes(&even, file), "{file} differs");
    }
    let read = |dir: &str, file: &str| -> serde_json::Value {
        serde_json::from_slice(&bytes(dir, file)).unwrap()
    };
    let (paced, evenly) = (read(&drawn, "train.json"), read(&even, "train.json"));
    let (paced, evenly) = (paced.as_array().unwrap(), evenly.as_array().unwrap());
    assert_eq!(paced.len(), evenly.len());
    assert!(paced.iter().zip(evenly).all(|(p, e)| p["action"] == e["action"]));
    let same = paced.iter().zip(evenly).filter(|(p, e)| p == e).count();
    assert!(4 * same >= 3 * paced.len(), "{same} of {} sequences described alike", paced.len());
    let frames = |dir: &str| read(dir, "manifest.json")["splits"]["train"]["frames"].as_u64();
    assert_ne!(frames(&drawn), frames(&even), "the tasks take other times");
    let wrong = common::fail(&[&args[..], &["--out", &path("x"), "--tempo", "fast"]].concat());
    assert!(
        wrong.contains("--tempo") && wrong.contains("even") && wrong.contains("drawn"),
        "{wrong}"
    );
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
