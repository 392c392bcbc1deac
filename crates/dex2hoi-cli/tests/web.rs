//! The web page (`cargo xtask web`, which `cargo xtask ci` runs before the tests) driven in
//! headless Chromium by `crates/dex2hoi-web/page/tests/drive.mjs`: it loads, generates with a
//! fixed prompt, object and seed the joints that this binary's `sample` writes (to 1e-4 m),
//! draws the figure in its 3D view, answers an empty prompt and a broken mesh with an error
//! and no motion, and warns of words the model never saw. Skipped without the built site, Node.js, Chromium or the page's npm
//! packages; failing under `CI=1`. The screenshots stay in `target/web-test/` to be looked at.

use std::path::{Path, PathBuf};
use std::process::Command;

use serde_json::Value;

mod common;
use common::{npz_array, succeed};

const PROMPT: &str =
    "The person picks up the mug with the right hand and puts it down to the left.";
const SEED: u64 = 3;
/// Seconds of motion the page is asked for: 160 frames at the shipped model's 20 fps.
const SECONDS: f32 = 8.0;
const FRAMES: usize = 160;

fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

/// What the test needs, or why it is skipped (a failure under CI).
fn prerequisites() -> Option<(PathBuf, PathBuf)> {
    let root = root();
    let site = root.join("target/web");
    let driver = root.join("crates/dex2hoi-web/page/tests/drive.mjs");
    let chromium = std::env::var_os("CHROMIUM").map_or("/usr/bin/chromium".into(), PathBuf::from);
    let missing = [
        (site.join("index.html"), "the web site (cargo xtask web)"),
        (site.join("pkg/dex2hoi_web_bg.wasm"), "the web site's module (cargo xtask web)"),
        (
            root.join("crates/dex2hoi-web/page/node_modules/playwright-core/package.json"),
            "the page's npm packages (cargo xtask web runs npm ci)",
        ),
        (chromium, "Chromium (scripts/setup.sh)"),
    ]
    .into_iter()
    .find(|(path, _)| !path.exists());
    let node = Command::new("node").arg("--version").output().is_ok_and(|o| o.status.success());
    let why = match (missing, node) {
        (Some((path, what)), _) => format!("no {what} at {}", path.display()),
        (None, false) => "no Node.js".to_string(),
        (None, true) => return Some((site, driver)),
    };
    assert!(!common::in_ci(), "CI needs {why}");
    println!("skipped: {why}");
    None
}

#[test]
fn the_page_generates_what_the_binary_generates_and_shows_errors() {
    let Some((site, driver)) = prerequisites() else { return };
    let out = root().join("target/web-test");
    std::fs::remove_dir_all(&out).ok();
    let request = serde_json::json!({
        "prompt": PROMPT, "object": "mug", "seed": SEED, "seconds": SECONDS,
        "unknownWordsPrompt": "Juggle the mug with the right hand.",
    });
    let run = Command::new("node")
        .arg(&driver)
        .arg(&site)
        .arg(&out)
        .arg(request.to_string())
        .output()
        .expect("node runs");
    assert!(run.status.success(), "drive.mjs:\n{}", String::from_utf8_lossy(&run.stderr));
    let report: Value = serde_json::from_slice(&run.stdout).expect("drive.mjs prints JSON");
    println!(
        "page: ready in {} s; {FRAMES} frames in {} s (generation {} s)",
        report["loadSeconds"],
        report["result"]["elapsedSeconds"],
        report["result"]["generationSeconds"]
    );
    assert_eq!(report["consoleErrors"], serde_json::json!([]), "{report}");
    assert_eq!(report["generateState"], "done", "{}", report["generateMessage"]);

    // The page's joints are the binary's.
    let native = out.join("native");
    let seed = SEED.to_string();
    let frames = FRAMES.to_string();
    let out_arg = native.to_str().unwrap();
    let args = ["sample", "--text", PROMPT, "--object", "mug", "--seed", &seed];
    succeed(&[&args[..], &["--frames", &frames, "--out", out_arg]].concat());
    let (expected, shape) = npz_array(&native.join("motion.npz"), "joints");
    assert_eq!(shape, [FRAMES, 52, 3]);
    let result = &report["result"];
    assert_eq!(result["frames"], FRAMES);
    assert_eq!(result["jointCount"], 52);
    let page: Vec<f64> =
        result["joints"].as_array().unwrap().iter().map(|v| v.as_f64().unwrap()).collect();
    assert_eq!(page.len(), expected.len());
    let worst =
        page.iter().zip(&expected).map(|(a, b)| (a - f64::from(*b)).abs()).fold(0.0f64, f64::max);
    println!("page against binary: worst joint difference {worst:.2e} m");
    assert!(worst < 1e-4, "the page's joints differ from the binary's by {worst} m");

    // The view draws the figure: a good part of the canvas changes from the empty scene.
    let changed = report["changedPixelShare"].as_f64().unwrap();
    assert!(changed > 0.01, "only {changed} of the view changed with a motion in it");
    assert_eq!(report["downloadsShown"], true);

    // Errors are shown, with no motion.
    let empty = &report["emptyPrompt"];
    assert_eq!(empty["state"], "error", "{empty}");
    assert!(empty["message"].as_str().unwrap().contains("empty prompt"), "{empty}");
    let broken = &report["badMesh"];
    assert_eq!(broken["state"], "error", "{broken}");
    assert!(broken["message"].as_str().unwrap().contains("broken.obj"), "{broken}");
    // Words the model never saw: a motion, with the warning `sample` prints.
    let unknown = &report["unknownWords"];
    assert_eq!(unknown["state"], "done", "{unknown}");
    assert_eq!(unknown["frames"], 20, "{unknown}");
    let message = unknown["message"].as_str().unwrap();
    assert!(message.contains("never saw `juggle`"), "{message}");
    for case in [empty, broken] {
        assert_eq!(case["playerShown"], false, "{case}");
        assert_eq!(case["downloadsShown"], false, "{case}");
        assert_eq!(case["result"], Value::Null, "{case}");
    }
}
