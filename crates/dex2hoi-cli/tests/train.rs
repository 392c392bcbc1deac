//! `dex2hoi train` end to end: a procedural dataset, a short tiny run, a resume, bad input.

use std::path::Path;

mod common;
use common::dex2hoi;

fn config() -> String {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../configs/tiny.toml").display().to_string()
}

#[test]
fn train_then_resume() {
    let dir = std::env::temp_dir().join(format!("dex2hoi-cli-train-{}", std::process::id()));
    std::fs::remove_dir_all(&dir).ok();
    let data = dir.join("data");
    let run = dir.join("run");
    let (data, run_path) = (data.to_str().unwrap(), run.to_str().unwrap());
    let made = dex2hoi(&["data", "synth", "--out", data, "--sequences", "16", "--seed", "2"]);
    assert!(made.status.success(), "{}", String::from_utf8_lossy(&made.stderr));

    let trained = dex2hoi(&[
        "train",
        "--config",
        &config(),
        "--data",
        data,
        "--out",
        run_path,
        "--steps",
        "12",
    ]);
    assert!(trained.status.success(), "{}", String::from_utf8_lossy(&trained.stderr));
    let stdout = String::from_utf8_lossy(&trained.stdout);
    assert!(stdout.contains("trained 12 steps"), "{stdout}");
    for file in [
        "config.toml",
        "dataset.json",
        "stats.json",
        "checkpoint.safetensors",
        "metrics.jsonl",
        "loss.png",
    ] {
        assert!(run.join(file).is_file(), "{file}");
    }
    let resolved = std::fs::read_to_string(run.join("config.toml")).unwrap();
    assert!(resolved.contains("steps = 12"), "{resolved}");
    let metrics = std::fs::read_to_string(run.join("metrics.jsonl")).unwrap();
    assert!(metrics.lines().count() >= 2 && metrics.contains("\"diffusion\""), "{metrics}");
    let png = std::fs::read(run.join("loss.png")).unwrap();
    assert_eq!(&png[1..4], b"PNG");

    // A fresh run into the same directory is refused; --resume continues it.
    let again = dex2hoi(&["train", "--config", &config(), "--data", data, "--out", run_path]);
    assert!(!again.status.success());
    assert!(String::from_utf8_lossy(&again.stderr).contains("--resume"));
    let resumed = dex2hoi(&[
        "train",
        "--data",
        data,
        "--out",
        run_path,
        "--resume",
        "--steps",
        "16",
        "--snapshot-every",
        "2",
    ]);
    assert!(resumed.status.success(), "{}", String::from_utf8_lossy(&resumed.stderr));
    assert!(String::from_utf8_lossy(&resumed.stdout).contains("trained 16 steps"));
    // Snapshots of the resumed steps, each a run that `sample` takes.
    for step in [14, 16] {
        let snapshot = run.join(format!("snapshots/step-{step:06}"));
        assert!(snapshot.join("checkpoint.safetensors").is_file(), "{}", snapshot.display());
    }
    assert!(!run.join("snapshots/step-000012").exists(), "none before the option was given");
    let sampled = dex2hoi(&[
        "sample",
        "--run",
        run.join("snapshots/step-000014").to_str().unwrap(),
        "--text",
        "A person picks up the mug.",
        "--object",
        "mug",
        "--frames",
        "4",
        "--ddim-steps",
        "1",
        "--out",
        dir.join("from-snapshot").to_str().unwrap(),
    ]);
    assert!(sampled.status.success(), "{}", String::from_utf8_lossy(&sampled.stderr));
    let zero = dex2hoi(&[
        "train",
        "--data",
        data,
        "--out",
        run_path,
        "--resume",
        "--steps",
        "18",
        "--snapshot-every",
        "0",
    ]);
    assert!(String::from_utf8_lossy(&zero.stderr).contains("snapshot_every"));

    // Bad input: no config, no dataset, a broken config.
    let missing = dex2hoi(&["train", "--data", data, "--out", dir.join("other").to_str().unwrap()]);
    assert!(String::from_utf8_lossy(&missing.stderr).contains("--config"));
    let no_data = dex2hoi(&[
        "train",
        "--config",
        &config(),
        "--data",
        "/nonexistent/data",
        "--out",
        run_path,
    ]);
    assert!(!no_data.status.success());
    assert!(String::from_utf8_lossy(&no_data.stderr).contains("/nonexistent/data"));
    let broken = dir.join("broken.toml");
    std::fs::write(&broken, "[model]\nlatent = 'big'\n").unwrap();
    let bad = dex2hoi(&[
        "train",
        "--config",
        broken.to_str().unwrap(),
        "--data",
        data,
        "--out",
        run_path,
    ]);
    assert!(!bad.status.success());
    assert!(String::from_utf8_lossy(&bad.stderr).contains("broken.toml"));
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn fine_tune_a_packed_model() {
    let dir = std::env::temp_dir().join(format!("dex2hoi-cli-init-from-{}", std::process::id()));
    std::fs::remove_dir_all(&dir).ok();
    let path = |name: &str| dir.join(name).display().to_string();
    let made =
        dex2hoi(&["data", "synth", "--out", &path("data"), "--sequences", "8", "--seed", "2"]);
    assert!(made.status.success(), "{}", String::from_utf8_lossy(&made.stderr));
    let trained = dex2hoi(&[
        "train",
        "--config",
        &config(),
        "--data",
        &path("data"),
        "--out",
        &path("base"),
        "--steps",
        "5",
    ]);
    assert!(trained.status.success(), "{}", String::from_utf8_lossy(&trained.stderr));
    let packed = dex2hoi(&["model", "pack", "--run", &path("base"), "--out", &path("base.st")]);
    assert!(packed.status.success(), "{}", String::from_utf8_lossy(&packed.stderr));

    // No --config: the model's own training configuration; its steps count on.
    let tuned = dex2hoi(&[
        "train",
        "--init-from",
        &path("base.st"),
        "--data",
        &path("data"),
        "--out",
        &path("tuned"),
        "--steps",
        "3",
    ]);
    let stdout = String::from_utf8_lossy(&tuned.stdout);
    assert!(tuned.status.success(), "{}", String::from_utf8_lossy(&tuned.stderr));
    assert!(stdout.contains("starting from the EMA weights of"), "{stdout}");
    assert!(stdout.contains("trained 3 steps (8 in all"), "{stdout}");
    let info = dex2hoi(&["model", "info", "--run", &path("tuned")]);
    assert!(info.status.success(), "{}", String::from_utf8_lossy(&info.stderr));
    assert!(String::from_utf8_lossy(&info.stdout).contains("trained for 8 steps"));
    let repacked = dex2hoi(&["model", "pack", "--run", &path("tuned"), "--out", &path("t.st")]);
    assert!(repacked.status.success(), "{}", String::from_utf8_lossy(&repacked.stderr));
    assert!(String::from_utf8_lossy(&repacked.stdout).contains("(8 steps"));
    let resumed = dex2hoi(&[
        "train",
        "--data",
        &path("data"),
        "--out",
        &path("tuned"),
        "--resume",
        "--steps",
        "4",
    ]);
    assert!(resumed.status.success(), "{}", String::from_utf8_lossy(&resumed.stderr));
    assert!(String::from_utf8_lossy(&resumed.stdout).contains("trained 4 steps (9 in all"));
    // A run directory is a starting point too (its checkpoint).
    let from_run = dex2hoi(&[
        "train",
        "--init-from",
        &path("tuned"),
        "--data",
        &path("data"),
        "--out",
        &path("again"),
        "--steps",
        "1",
    ]);
    assert!(from_run.status.success(), "{}", String::from_utf8_lossy(&from_run.stderr));
    assert!(String::from_utf8_lossy(&from_run.stdout).contains("trained 1 steps (10 in all"));
    // The text encoder started afresh: another encoder size is then no mismatch.
    let wider = dir.join("wider-text.toml");
    let text = std::fs::read_to_string(config()).unwrap();
    let widened = text.replace(
        "[text]\nencoder = \"builtin\"\nwidth = 16",
        "[text]\nencoder = \"builtin\"\nwidth = 32",
    );
    assert_ne!(widened, text, "tiny.toml has a built-in encoder of width 16");
    std::fs::write(&wider, widened).unwrap();
    let fresh = dex2hoi(&[
        "train",
        "--init-from",
        &path("base.st"),
        "--fresh",
        "text-encoder",
        "--config",
        wider.to_str().unwrap(),
        "--data",
        &path("data"),
        "--out",
        &path("fresh-text"),
        "--steps",
        "1",
    ]);
    let stdout = String::from_utf8_lossy(&fresh.stdout);
    assert!(fresh.status.success(), "{}", String::from_utf8_lossy(&fresh.stderr));
    assert!(
        stdout.contains("started afresh from this run's seed")
            && stdout.contains("text_encoder.tokens"),
        "{stdout}"
    );
    let wider_refused = dex2hoi(&[
        "train",
        "--init-from",
        &path("base.st"),
        "--config",
        wider.to_str().unwrap(),
        "--data",
        &path("data"),
        "--out",
        &path("wider-refused"),
    ]);
    assert!(String::from_utf8_lossy(&wider_refused.stderr).contains("[text]"));
    let alone = dex2hoi(&[
        "train",
        "--fresh",
        "text-encoder",
        "--config",
        &config(),
        "--data",
        &path("data"),
        "--out",
        &path("alone"),
    ]);
    assert!(String::from_utf8_lossy(&alone.stderr).contains("--init-from"));

    // Bad input: with --resume, into a run that exists, a model of another network, no model.
    let both = dex2hoi(&[
        "train",
        "--init-from",
        &path("base.st"),
        "--resume",
        "--data",
        &path("data"),
        "--out",
        &path("tuned"),
    ]);
    assert!(String::from_utf8_lossy(&both.stderr).contains("cannot be used with"));
    let exists = dex2hoi(&[
        "train",
        "--init-from",
        &path("base.st"),
        "--data",
        &path("data"),
        "--out",
        &path("tuned"),
    ]);
    assert!(String::from_utf8_lossy(&exists.stderr).contains("--resume"));
    let bigger = dir.join("bigger.toml");
    let text = std::fs::read_to_string(config()).unwrap();
    std::fs::write(&bigger, text.replace("latent = 32", "latent = 48")).unwrap();
    assert_ne!(std::fs::read_to_string(&bigger).unwrap(), text, "tiny.toml has latent = 32");
    let other = dex2hoi(&[
        "train",
        "--init-from",
        &path("base.st"),
        "--config",
        bigger.to_str().unwrap(),
        "--data",
        &path("data"),
        "--out",
        &path("other"),
    ]);
    let stderr = String::from_utf8_lossy(&other.stderr);
    assert!(!other.status.success());
    assert!(
        stderr.contains("base.st") && stderr.contains("latent = 32 (this run: 48)"),
        "{stderr}"
    );
    let missing = dex2hoi(&[
        "train",
        "--init-from",
        &path("none.st"),
        "--data",
        &path("data"),
        "--out",
        &path("x"),
    ]);
    assert!(!missing.status.success());
    assert!(String::from_utf8_lossy(&missing.stderr).contains("none.st"));

    // One step from base.st with tiny.toml edited by `edit`, written to `{name}.toml`.
    let one_step = |name: &str, edit: &dyn Fn(String) -> String| {
        let file = dir.join(format!("{name}.toml"));
        std::fs::write(&file, edit(std::fs::read_to_string(config()).unwrap())).unwrap();
        let trained = dex2hoi(&[
            "train",
            "--init-from",
            &path("base.st"),
            "--config",
            file.to_str().unwrap(),
            "--data",
            &path("data"),
            "--out",
            &path(name),
            "--steps",
            "1",
        ]);
        (trained, file)
    };

    // Windows drawn by action: said when training starts; a label the data lacks refused.
    let weighted = |name: &str, label: &str| {
        one_step(name, &|text| format!("{text}\n[training.action_weights]\n{label} = 3.0\n")).0
    };
    let pours = weighted("pours", "pour");
    assert!(pours.status.success(), "{}", String::from_utf8_lossy(&pours.stderr));
    let stdout = String::from_utf8_lossy(&pours.stdout);
    assert!(stdout.contains("windows drawn by action: pour x3, every other action x1"), "{stdout}");
    let misspelt = weighted("misspelt", "poor");
    let stderr = String::from_utf8_lossy(&misspelt.stderr);
    assert!(!misspelt.status.success());
    assert!(stderr.contains("training.action_weights.poor") && stderr.contains("pour"), "{stderr}");

    // Windows along the model's guided prediction: trained, and refused with none to guide.
    let along = |name: &str, share: f64| {
        one_step(name, &|text| {
            text.replacen(
                "[training]\n",
                &format!(
                    "[training]\nown_prediction_share = {share}\nown_prediction_guidance = 2.0\n"
                ),
                1,
            )
        })
    };
    let (guided, _) = along("guided", 1.0);
    assert!(guided.status.success(), "{}", String::from_utf8_lossy(&guided.stderr));
    let written = std::fs::read_to_string(dir.join("guided/config.toml")).unwrap();
    assert!(written.contains("own_prediction_guidance = 2.0"), "{written}");
    let (unguided, file) = along("nothing-to-guide", 0.0);
    let stderr = String::from_utf8_lossy(&unguided.stderr);
    assert!(!unguided.status.success());
    assert!(
        stderr.contains(file.to_str().unwrap()) && stderr.contains("own_prediction_guidance"),
        "{stderr}"
    );
    std::fs::remove_dir_all(&dir).ok();
}
