//! Models end to end: `dex2hoi model pack` and `model info`, sampling from a packed file (the
//! same motion as from its run directory in f32, within 1e-3 in f16), `DEX2HOI_MODEL`, and the
//! shipped model, which `sample` uses without `--run` and which must keep giving the recorded
//! motion for a fixed seed.

use std::path::Path;
use std::process::{Command, Output};

mod common;

fn dex2hoi_with(args: &[&str], model_variable: Option<&str>) -> Output {
    let mut command = Command::new(env!("CARGO_BIN_EXE_dex2hoi"));
    command.args(args).env("RUST_BACKTRACE", "0");
    match model_variable {
        Some(value) => command.env("DEX2HOI_MODEL", value),
        None => command.env_remove("DEX2HOI_MODEL"),
    };
    command.output().expect("the binary runs")
}

fn ok(output: &Output) -> String {
    assert!(output.status.success(), "{}", String::from_utf8_lossy(&output.stderr));
    String::from_utf8_lossy(&output.stdout).into_owned()
}

fn fails(output: &Output, needle: &str) {
    assert!(!output.status.success());
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(stderr.contains(needle), "expected `{needle}` in: {stderr}");
}

/// `joints` of a motion.npz, `[T, J, 3]` flattened.
fn joints(dir: &Path) -> Vec<f32> {
    common::npz_array(&dir.join("motion.npz"), "joints").0
}

fn max_difference(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len());
    a.iter().zip(b).map(|(x, y)| (x - y).abs()).fold(0.0, f32::max)
}

/// One short sample: `--run` (or none), seed, output directory.
fn sample_args<'a>(run: Option<&'a str>, seed: &'a str, out: &'a str) -> Vec<&'a str> {
    let mut args = vec!["sample"];
    if let Some(run) = run {
        args.extend(["--run", run]);
    }
    args.extend([
        "--text",
        "The person picks up the mug with the right hand.",
        "--object",
        "mug",
        "--frames",
        "24",
        "--ddim-steps",
        "4",
        "--seed",
        seed,
        "--out",
        out,
    ]);
    args
}

#[test]
fn packed_models_sample_like_their_runs_and_are_found_by_the_variable() {
    let dir = std::env::temp_dir().join(format!("dex2hoi-cli-model-{}", std::process::id()));
    std::fs::remove_dir_all(&dir).ok();
    let config =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../../configs/tiny.toml").display().to_string();
    let path = |name: &str| dir.join(name).display().to_string();
    let (data, run) = (path("data"), path("run"));
    ok(&common::dex2hoi(&["data", "synth", "--out", &data, "--sequences", "8", "--seed", "4"]));
    ok(&common::dex2hoi(&[
        "train", "--config", &config, "--data", &data, "--out", &run, "--steps", "4",
    ]));

    let (f32_file, f16_file) = (path("model-f32.safetensors"), path("model-f16.safetensors"));
    let stdout = ok(&common::dex2hoi(&["model", "pack", "--run", &run, "--out", &f32_file]));
    assert!(stdout.contains("4 steps") && stdout.contains("F32"), "{stdout}");
    ok(&common::dex2hoi(&["model", "pack", "--run", &run, "--out", &f16_file, "--f16"]));
    let (f32_size, f16_size) =
        (std::fs::metadata(&f32_file).unwrap().len(), std::fs::metadata(&f16_file).unwrap().len());
    assert!(f16_size < f32_size * 6 / 10, "f16 {f16_size} bytes, f32 {f32_size}");
    let info = ok(&common::dex2hoi(&["model", "info", "--run", &f16_file]));
    assert!(info.contains("trained for 4 steps") && info.contains("mug"), "{info}");
    assert!(info.contains("words: "), "the built-in encoder's words are listed: {info}");

    // The run directory, its f32 file and its f16 file.
    let (from_run, from_f32, from_f16) = (path("from-run"), path("from-f32"), path("from-f16"));
    ok(&common::dex2hoi(&sample_args(Some(&run), "3", &from_run)));
    ok(&common::dex2hoi(&sample_args(Some(&f32_file), "3", &from_f32)));
    ok(&common::dex2hoi(&sample_args(Some(&f16_file), "3", &from_f16)));
    let reference = joints(&dir.join("from-run"));
    assert_eq!(reference, joints(&dir.join("from-f32")), "f32 weights are the EMA weights");
    let f16_difference = max_difference(&reference, &joints(&dir.join("from-f16")));
    println!("f16 weights: joints within {f16_difference:.2e} m of the f32 weights'");
    assert!(f16_difference < 1e-3, "{f16_difference}");

    // Without --run, DEX2HOI_MODEL names the model.
    let from_variable = path("from-variable");
    let stdout = ok(&dex2hoi_with(&sample_args(None, "3", &from_variable), Some(&f32_file)));
    assert!(stdout.contains("DEX2HOI_MODEL"), "{stdout}");
    assert_eq!(reference, joints(&dir.join("from-variable")));

    // Words the built-in encoder never saw are named.
    let warned = common::dex2hoi(&[
        "sample",
        "--run",
        &f16_file,
        "--text",
        "The person juggles the mug.",
        "--object",
        "mug",
        "--frames",
        "4",
        "--ddim-steps",
        "1",
        "--out",
        &path("warned"),
    ]);
    ok(&warned);
    let stderr = String::from_utf8_lossy(&warned.stderr);
    assert!(stderr.contains("`juggles`") && !stderr.contains("`mug`"), "{stderr}");
    // How far apart the encoder puts prompts: a symmetric table with zeros on its diagonal.
    let (a, b) = ("The person picks up the mug.", "The person juggles the mug.");
    let texts =
        ok(&common::dex2hoi(&["model", "texts", "--run", &f16_file, "--text", a, "--text", b]));
    assert!(
        texts.contains("1  norm ") && texts.contains(&format!("unknown words: juggles  {b}")),
        "{texts}"
    );
    let rows: Vec<Vec<f32>> = texts
        .lines()
        .skip_while(|line| !line.starts_with("distances"))
        .skip(2)
        .map(|line| line.split_whitespace().skip(1).map(|v| v.parse().unwrap()).collect())
        .collect();
    assert_eq!(rows.len(), 2, "{texts}");
    assert_eq!((rows[0][0], rows[1][1]), (0.0, 0.0), "{texts}");
    assert!(rows[0][1] > 0.0 && rows[0][1] == rows[1][0], "{texts}");
    let one = common::dex2hoi(&["model", "texts", "--run", &f16_file, "--text", a]);
    assert!(!one.status.success() && String::from_utf8_lossy(&one.stderr).contains("two or more"));

    // Bad input.
    let not_a_model = path("notes.txt");
    std::fs::write(&not_a_model, "not a model").unwrap();
    fails(&common::dex2hoi(&sample_args(Some(&not_a_model), "3", &path("bad"))), "notes.txt");
    fails(
        &dex2hoi_with(&sample_args(None, "3", &path("bad")), Some("/nonexistent/model")),
        "DEX2HOI_MODEL=/nonexistent/model",
    );
    fails(
        &common::dex2hoi(&["model", "pack", "--run", "/nonexistent/run", "--out", &path("x")]),
        "/nonexistent/run",
    );
    fails(&common::dex2hoi(&["model", "pack", "--run", &run, "--out", &data]), "is a directory");
    assert!(!dir.join("bad").exists() && !dir.join("x").exists(), "nothing partial is written");
    std::fs::remove_dir_all(&dir).ok();
}

/// The shipped model's joints for `sample_args(None, "11", ..)` at a few (frame, joint) pairs,
/// recorded with the shipped model, the default sampler (guidance 2.0, released objects at rest,
/// continuous seams) and the default scene (a lone object on the side of the hand the prompt
/// names). A change of the model, the sampler, the default scene or the decoding that moves them
/// is a change of what every user gets by default: record them again and say so in
/// `CHANGELOG.md`.
const RECORDED: [(usize, usize, [f32; 3]); 4] = [
    (0, 0, [0.0, 0.975, 0.0]),
    (8, 20, [0.22235897, 0.96237135, 0.025114037]),
    (16, 21, [-0.2379449, 1.0042851, 0.028775431]),
    (23, 15, [0.0062860386, 1.5701485, 0.15056646]),
];

#[test]
fn the_shipped_model_samples_without_a_run_and_gives_the_recorded_motion() {
    let dir = std::env::temp_dir().join(format!("dex2hoi-cli-shipped-{}", std::process::id()));
    std::fs::remove_dir_all(&dir).ok();
    let out = dir.join("sample").display().to_string();
    let stdout = ok(&dex2hoi_with(&sample_args(None, "11", &out), None));
    assert!(stdout.contains("the shipped model"), "{stdout}");
    let joints = joints(&dir.join("sample"));
    let mut worst = 0.0f32;
    for (frame, joint, expected) in RECORDED {
        let at = (frame * 52 + joint) * 3;
        let got = &joints[at..at + 3];
        println!("({frame}, {joint}, {got:?}),");
        worst = worst.max(max_difference(got, &expected));
    }
    // Matrix products may round differently on another CPU; 1e-4 m is far below what shows.
    assert!(worst < 1e-4, "the shipped model's motion moved by {worst} m");
    let info = ok(&dex2hoi_with(&["model", "info"], None));
    assert!(info.contains("the shipped model"), "{info}");
    // The demo preset's model reads the prompt clock beyond the paper.
    assert!(info.contains("the condition also reads: the prompt clock"), "{info}");
    std::fs::remove_dir_all(&dir).ok();
}
