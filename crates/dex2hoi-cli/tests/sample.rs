//! `dex2hoi sample` end to end on a tiny run: the four files for one and two objects (a
//! catalogue name and a user's OBJ), two unplaced objects placed by the hands the prompt names,
//! a timeline, the same seed giving the same files, and bad input refused without writing
//! anything.

use std::path::Path;

mod common;
use common::dex2hoi;

fn ok(output: &std::process::Output) -> String {
    assert!(output.status.success(), "{}", String::from_utf8_lossy(&output.stderr));
    String::from_utf8_lossy(&output.stdout).into_owned()
}

fn fails(output: &std::process::Output, needle: &str) {
    assert!(!output.status.success());
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(stderr.contains(needle), "expected `{needle}` in: {stderr}");
}

#[test]
fn sample_exports_four_files_and_refuses_bad_input() {
    let dir = std::env::temp_dir().join(format!("dex2hoi-cli-sample-{}", std::process::id()));
    std::fs::remove_dir_all(&dir).ok();
    let config =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../../configs/tiny.toml").display().to_string();
    let data = dir.join("data");
    let run = dir.join("run");
    let (data, run) = (data.to_str().unwrap(), run.to_str().unwrap());
    ok(&dex2hoi(&["data", "synth", "--out", data, "--sequences", "8", "--seed", "4"]));
    ok(&dex2hoi(&["train", "--config", &config, "--data", data, "--out", run, "--steps", "3"]));

    // One prompt with the mug, 12 frames, seed 5, into `out`, with `extra` options.
    let sample_mug = |out: &Path, extra: &[&str]| {
        let mut args = vec![
            "sample",
            "--run",
            run,
            "--text",
            "A person picks up the mug with the right hand.",
            "--object",
            "mug",
            "--frames",
            "12",
            "--ddim-steps",
            "3",
            "--seed",
            "5",
        ];
        args.extend_from_slice(extra);
        args.extend(["--out", out.to_str().unwrap()]);
        ok(&dex2hoi(&args))
    };
    let one = dir.join("one");
    let stdout = sample_mug(&one, &[]);
    assert!(stdout.contains("generated 12 frames") && stdout.contains("real time"), "{stdout}");
    for file in ["motion.npz", "motion.glb", "motion.bvh", "preview.gif", "preview.png"] {
        assert!(one.join(file).metadata().unwrap().len() > 100, "{file}");
    }
    // The same seed gives the same motion.
    // Whether `extra` options give the default motion (`one`'s) with the same seed.
    let default_motion = std::fs::read(one.join("motion.npz")).unwrap();
    let gives_the_default = |name: &str, extra: &[&str]| {
        let out = dir.join(name);
        sample_mug(&out, extra);
        std::fs::read(out.join("motion.npz")).unwrap() == default_motion
    };
    // The same seed gives the same motion.
    assert!(gives_the_default("again", &[]));
    // Objects at rest: with a model of the procedural data `sample` keeps the objects no hand
    // holds where they stand unless told otherwise; as generated, the same seed gives another
    // motion.
    assert!(gives_the_default("resting", &["--free-objects", "at-rest"]));
    assert!(!gives_the_default("generated", &["--free-objects", "as-generated"]));
    // Continuous seams are `sample`'s default; the paper's sampler gives another motion.
    assert!(gives_the_default("continuous", &["--seams", "continuous"]));
    assert!(!gives_the_default("jumping", &["--seams", "as-generated"]));
    fails(&dex2hoi(&["sample", "--run", run, "--text", "x", "--seams", "smooth"]), "--seams");

    // Two objects, one from the user's OBJ file, placed explicitly; a timeline.
    let obj = dir.join("cube.obj");
    std::fs::write(
        &obj,
        "v -0.04 -0.04 -0.04\nv 0.04 -0.04 -0.04\nv 0.04 0.04 -0.04\nv -0.04 0.04 -0.04\n\
         v -0.04 -0.04 0.04\nv 0.04 -0.04 0.04\nv 0.04 0.04 0.04\nv -0.04 0.04 0.04\n\
         f 1 3 2\nf 1 4 3\nf 5 6 7\nf 5 7 8\nf 1 2 6\nf 1 6 5\nf 2 3 7\nf 2 7 6\nf 3 4 8\nf 3 8 7\nf 4 1 5\nf 4 5 8\n",
    )
    .unwrap();
    let timeline = dir.join("timeline.txt");
    std::fs::write(
        &timeline,
        "# seconds text\n0 The person picks up the bowl.\n0.3 The person hands it over.\n",
    )
    .unwrap();
    let two = dir.join("two");
    let object = format!("{}@-0.15,0.94,0.4", obj.display());
    ok(&dex2hoi(&[
        "sample",
        "--run",
        run,
        "--timeline",
        timeline.to_str().unwrap(),
        "--object",
        "bowl",
        "--object",
        &object,
        "--frames",
        "10",
        "--ddim-steps",
        "2",
        "--out",
        two.to_str().unwrap(),
    ]));
    let glb = std::fs::read(two.join("motion.glb")).unwrap();
    assert!(glb.windows(4).any(|w| w == b"cube"), "the user's object is in the scene");
    assert!(glb.windows(4).any(|w| w == b"bowl"), "the catalogue object is in the scene");

    // Two unplaced objects: the one the named hand holds stands on that hand's side (-X is the
    // person's right), whichever is given first.
    let pour = dir.join("pour");
    ok(&dex2hoi(&[
        "sample",
        "--run",
        run,
        "--text",
        "The person holds the bowl with the left hand and pours from the bottle with the right hand.",
        "--object",
        "bottle",
        "--object",
        "bowl",
        "--frames",
        "4",
        "--ddim-steps",
        "1",
        "--out",
        pour.to_str().unwrap(),
    ]));
    let (places, shape) = common::npz_array(&pour.join("motion.npz"), "object_translations");
    let frames = shape[1];
    let (bottle_x, bowl_x) = (places[0], places[frames * 3]);
    assert!(bottle_x < -0.1 && bowl_x > 0.1, "bottle at x {bottle_x}, bowl at x {bowl_x}");

    // With the user's SMPL-X model the GLB carries its skinned mesh on its skeleton.
    let model = dir.join("SMPLX_NEUTRAL.npz");
    common::write_smplx_model(&model);
    let dressed = dir.join("dressed");
    sample_mug(&dressed, &["--smplx-model", model.to_str().unwrap(), "--betas=-1,0.5"]);
    let glb = std::fs::read(dressed.join("motion.glb")).unwrap();
    assert!(glb.windows(7).any(|w| w == b"\"smplx\""), "the SMPL-X mesh is in the GLB");

    // Bad input: nothing is written.
    let bad = dir.join("bad");
    let bad_out = bad.to_str().unwrap();
    let base = ["sample", "--run", run, "--frames", "4", "--ddim-steps", "1", "--out", bad_out];
    let with = |extra: &[&str]| {
        let mut args: Vec<&str> = base.to_vec();
        args.extend_from_slice(extra);
        dex2hoi(&args)
    };
    fails(&with(&["--text", "hi", "--object", "teapot"]), "catalogue object");
    fails(&with(&["--text", "hi", "--object", "/nonexistent/thing.obj"]), "/nonexistent/thing.obj");
    let empty = dir.join("empty.obj");
    std::fs::write(&empty, "v 0 0 0\n").unwrap();
    fails(&with(&["--text", "hi", "--object", empty.to_str().unwrap()]), "empty.obj");
    fails(&with(&["--text", "   ", "--object", "mug"]), "empty");
    fails(
        &with(&["--text", "hi", "--object", "mug", "--object", "can", "--object", "box"]),
        "at most two",
    );
    fails(
        &dex2hoi(&[
            "sample",
            "--run",
            "/nonexistent/run",
            "--text",
            "hi",
            "--object",
            "mug",
            "--out",
            bad_out,
        ]),
        "/nonexistent/run",
    );
    fails(
        &with(&["--text", "hi", "--object", "mug", "--smplx-model", "/nonexistent/SMPLX.npz"]),
        "/nonexistent/SMPLX.npz",
    );
    // The frame count is typed: zero is refused where it is parsed.
    fails(&with(&["--text", "hi", "--object", "mug", "--frames", "0"]), "--frames");
    assert!(!bad.exists(), "nothing partial is written");
    std::fs::remove_dir_all(&dir).ok();
}
