//! `cargo xtask ablate`: the paper's Table 3 on the procedural dataset. One dataset, one
//! evaluator, every variant trained from the same seed for the same number of steps and
//! evaluated the same way; the rows of their `report.json` files make one table, written to
//! `docs/results/ablation.md`.
//!
//! Each variant's configuration is the preset parsed as TOML with the variant's `[model]` and
//! `[loss]` keys set as typed values. The work is resumable: a variant whose run finished with
//! the same configuration is reused, an interrupted one is continued with `dex2hoi train
//! --resume`, and a variant whose `report.json` is newer than its checkpoint (and than the
//! evaluator) is not evaluated again.

use std::path::Path;
use std::time::SystemTime;

use anyhow::{Context, Result, bail};
use serde::Deserialize;

use crate::{cargo, dex2hoi, path, read, train_evaluator, write};

/// A variant of Table 3: a label and the values it sets.
#[derive(Debug, Clone, Copy)]
pub struct Variant {
    /// The row's label in the table.
    pub label: &'static str,
    /// `[model]` keys and their values, spelled as `dex2hoi-model`'s `config.rs` (de)serialises
    /// its enums (`snake_case`): `object_representation` is `hand_relative` or `global_only`,
    /// `stream_layout` `dual` or `single`, `body_fusion` `network` or `average`.
    pub model: &'static [(&'static str, &'static str)],
    /// `[loss]` switches of `dex2hoi-train`'s `LossConfig` and their values.
    pub loss: &'static [(&'static str, bool)],
}

/// The variants, the full model first.
pub const VARIANTS: [Variant; 7] = [
    Variant { label: "Dex2HOI (full)", model: &[], loss: &[] },
    Variant { label: "fusion -> average", model: &[("body_fusion", "average")], loss: &[] },
    Variant { label: "single stream", model: &[("stream_layout", "single")], loss: &[] },
    Variant {
        label: "w/o mixture supervision",
        model: &[],
        loss: &[("mixture_supervision", false)],
    },
    Variant {
        label: "w/o hand-relative representation",
        model: &[("object_representation", "global_only")],
        loss: &[],
    },
    Variant { label: "w/o L_dist", model: &[], loss: &[("distance_loss", false)] },
    Variant {
        label: "MDM-style baseline (single stream, global objects, L_diff + velocity/foot/penetration)",
        model: &[("stream_layout", "single"), ("object_representation", "global_only")],
        loss: &[("mixture_supervision", false), ("distance_loss", false)],
    },
];

/// Procedural sequences of the ablation's dataset, and the seed.
const SEQUENCES: &str = "800";
const DATA_SEED: &str = "0";
/// Training steps of the shared evaluator.
const EVALUATOR_STEPS: &str = "300";
/// The evaluation every variant gets (`dex2hoi evaluate` options).
const EVALUATE_OPTIONS: [&str; 8] =
    ["--replications", "2", "--sequences", "32", "--ddim-steps", "20", "--multimodality", "4,3,2"];

/// The preset's TOML with a variant's values set: the `[model]` keys (which the preset must
/// have, as strings) and the `[loss]` switches (added, and the table with them, when absent);
/// with `steps`, also `[training] steps`. Everything else is kept as parsed (comments and key
/// order are not: the file is written back from the parsed table).
pub fn variant_config(base: &str, variant: &Variant, steps: Option<u64>) -> Result<String> {
    let mut config: toml::Table = base.parse().context("the preset is not valid TOML")?;
    let model = config
        .get_mut("model")
        .and_then(toml::Value::as_table_mut)
        .context("the preset has no [model] table")?;
    for &(key, value) in variant.model {
        match model.get(key) {
            Some(toml::Value::String(_)) => {}
            Some(other) => bail!("[model] {key} is {other}, expected a string"),
            None => bail!("the preset's [model] has no `{key}` for the variant to change"),
        }
        model.insert(key.into(), toml::Value::String(value.into()));
    }
    if !variant.loss.is_empty() {
        let loss = config
            .entry("loss")
            .or_insert_with(|| toml::Value::Table(toml::Table::new()))
            .as_table_mut()
            .context("[loss] is not a table")?;
        for &(key, value) in variant.loss {
            loss.insert(key.into(), toml::Value::Boolean(value));
        }
    }
    if let Some(steps) = steps {
        let training = config
            .get_mut("training")
            .and_then(toml::Value::as_table_mut)
            .context("the preset has no [training] table")?;
        let steps = i64::try_from(steps).context("--steps is too large")?;
        training.insert("steps".into(), toml::Value::Integer(steps));
    }
    let text = toml::to_string(&config).context("writing the variant's TOML")?;
    Ok(format!("# cargo xtask ablate: variant \"{}\"\n\n{text}", variant.label))
}

/// A number of `report.json`: serde_json writes a non-finite `f64` as `null`, read back as NaN.
#[derive(Debug, Clone, Copy, PartialEq, Deserialize)]
#[serde(from = "Option<f64>")]
pub struct Number(pub f64);

impl From<Option<f64>> for Number {
    fn from(value: Option<f64>) -> Self {
        Self(value.unwrap_or(f64::NAN))
    }
}

/// `Estimate` of `dex2hoi-eval`'s `evaluate.rs`: the mean over replications and the
/// half-width of its 95% interval.
#[derive(Debug, Clone, Copy, PartialEq, Deserialize)]
pub struct Estimate {
    /// Mean.
    pub mean: Number,
    /// Half-width of the 95% interval.
    pub interval: Number,
}

/// `PhysicalRow` of `evaluate.rs`.
#[derive(Debug, Clone, PartialEq, Deserialize)]
pub struct PhysicalRow {
    /// Mean penetration depth, mm.
    pub penetration_depth_mm: Estimate,
    /// Share of penetrating frames, percent.
    pub penetration_frames_percent: Estimate,
    /// Contact precision.
    pub contact_precision: Estimate,
    /// Contact recall.
    pub contact_recall: Estimate,
    /// Contact F1.
    pub contact_f1: Estimate,
    /// Hand-object distance on ground-truth contact frames, mm.
    pub contact_distance_mm: Estimate,
    /// Foot sliding, mm per frame.
    pub foot_sliding_mm: Estimate,
    /// Mixture agreement, percent (absent when no frame qualifies).
    pub mixture_agreement_percent: Option<Estimate>,
}

/// `ReportRow` of `evaluate.rs`.
#[derive(Debug, Clone, PartialEq, Deserialize)]
pub struct ReportRow {
    /// What the row measures.
    pub name: String,
    /// R-precision top-1, top-2, top-3.
    pub r_precision: [Estimate; 3],
    /// FID.
    pub fid: Estimate,
    /// MMdist.
    pub mm_dist: Estimate,
    /// Diversity.
    pub diversity: Estimate,
    /// MultiModality (models only).
    pub multimodality: Option<Estimate>,
    /// Physical metrics.
    pub physical: PhysicalRow,
    /// Seconds per clip, mean and standard deviation (models only).
    pub runtime_seconds: Option<(Number, Number)>,
}

/// `Report` of `evaluate.rs`, as `dex2hoi evaluate` writes it to `report.json`.
#[derive(Debug, Clone, PartialEq, Deserialize)]
pub struct Report {
    /// Ground truth, then the model.
    pub rows: Vec<ReportRow>,
    /// Test sequences evaluated per replication.
    pub samples: usize,
    /// Test sequences skipped.
    pub skipped: usize,
    /// Replications.
    pub replications: usize,
    /// Frames per evaluated clip.
    pub clip_frames: usize,
    /// Features of FID, Diversity and MultiModality.
    pub distribution_features: String,
    /// MultiModality prompts x repeats x pairs.
    pub multimodality_protocol: [usize; 3],
}

impl Report {
    /// Parses `report.json`.
    pub fn parse(json: &str) -> Result<Self> {
        let report: Self = serde_json::from_str(json).context("not a dex2hoi evaluation report")?;
        report.truth()?;
        report.model()?;
        Ok(report)
    }

    /// The ground-truth row (the first).
    pub fn truth(&self) -> Result<&ReportRow> {
        match self.rows.first() {
            Some(row) if row.name == "Ground truth" => Ok(row),
            _ => bail!("the report's first row is not the ground truth"),
        }
    }

    /// The model's row (the second).
    pub fn model(&self) -> Result<&ReportRow> {
        match self.rows.as_slice() {
            [_, model] => Ok(model),
            rows => bail!("expected two rows (ground truth, model), found {}", rows.len()),
        }
    }
}

/// The table's header, the columns of `Report::markdown` in `evaluate.rs`.
pub const TABLE_HEADER: &str = "| Method | R-prec. top-1 ↑ | top-2 ↑ | top-3 ↑ | FID ↓ | MMdist ↓ | Diversity → | MModality ↑ | Pen. depth (mm) ↓ | Pen. frames (%) ↓ | Contact P ↑ | Contact R ↑ | Contact F1 ↑ | Hand-obj. dist. (mm) ↓ | Foot sliding (mm/frame) ↓ | Mixture picks holding hand (%) ↑ | Runtime (s / clip) ↓ |";

fn cell(e: &Estimate, digits: usize) -> String {
    format!("{:.*} ± {:.*}", digits, e.mean.0, digits, e.interval.0)
}

/// One table row with `label` in the first column, formatted like `Report::markdown`.
pub fn table_row(label: &str, row: &ReportRow) -> String {
    let p = &row.physical;
    let cells = [
        label.to_string(),
        cell(&row.r_precision[0], 3),
        cell(&row.r_precision[1], 3),
        cell(&row.r_precision[2], 3),
        cell(&row.fid, 3),
        cell(&row.mm_dist, 3),
        cell(&row.diversity, 3),
        row.multimodality.as_ref().map_or("-".into(), |e| cell(e, 3)),
        cell(&p.penetration_depth_mm, 2),
        cell(&p.penetration_frames_percent, 1),
        cell(&p.contact_precision, 3),
        cell(&p.contact_recall, 3),
        cell(&p.contact_f1, 3),
        cell(&p.contact_distance_mm, 1),
        cell(&p.foot_sliding_mm, 2),
        p.mixture_agreement_percent.as_ref().map_or("-".into(), |e| cell(e, 1)),
        row.runtime_seconds.map_or("-".into(), |(m, s)| format!("{:.2} ± {:.2}", m.0, s.0)),
    ];
    format!("| {} |", cells.join(" | "))
}

/// The modification time of a file, `None` when it has none or does not exist.
fn modified(path: &Path) -> Option<SystemTime> {
    std::fs::metadata(path).and_then(|m| m.modified()).ok()
}

/// Whether `output` exists and is newer than every one of `inputs` (all of which exist).
pub fn newer_than_all(output: &Path, inputs: &[&Path]) -> bool {
    let Some(made) = modified(output) else { return false };
    inputs.iter().all(|input| modified(input).is_some_and(|t| made > t))
}

/// The ablation's options.
#[derive(Debug, Clone, PartialEq)]
pub struct Options {
    /// The preset of `configs/`.
    pub preset: String,
    /// Training steps of every variant (the preset's when `None`).
    pub steps: Option<u64>,
}

impl Options {
    /// Parses `[--preset NAME] [--steps N]`.
    pub fn parse(args: &[String]) -> Result<Self> {
        let mut options = Self { preset: "demo".into(), steps: None };
        let mut rest = args.iter();
        while let Some(flag) = rest.next() {
            match flag.as_str() {
                "--preset" => options.preset = rest.next().context("--preset NAME")?.clone(),
                "--steps" => {
                    let steps: u64 =
                        rest.next().context("--steps N")?.parse().context("--steps N")?;
                    if steps == 0 {
                        bail!("--steps must be at least 1");
                    }
                    options.steps = Some(steps);
                }
                other => bail!("unknown ablate option `{other}` (use --preset NAME, --steps N)"),
            }
        }
        Ok(options)
    }
}

/// Runs `cargo xtask ablate`.
pub fn ablate(root: &Path, args: &[String]) -> Result<()> {
    let Options { preset, steps } = Options::parse(args)?;
    let config_path = root.join(format!("configs/{preset}.toml"));
    let base = std::fs::read_to_string(&config_path)
        .with_context(|| format!("reading {}", config_path.display()))?;
    // Every variant's configuration first, so that a preset that does not fit fails at once.
    let configs: Vec<String> = VARIANTS
        .iter()
        .map(|v| variant_config(&base, v, steps))
        .collect::<Result<_>>()
        .with_context(|| format!("making the variants of {}", config_path.display()))?;
    cargo(root, &["build", "--release", "--locked", "-p", "dex2hoi-cli"])?;
    let dir = root.join("target/ablate").join(&preset);
    std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
    let data = dir.join("data");
    if !data.join("manifest.json").is_file() {
        dex2hoi(
            root,
            &[
                "data",
                "synth",
                "--out",
                &path(&data)?,
                "--sequences",
                SEQUENCES,
                "--seed",
                DATA_SEED,
            ],
        )?;
    }
    let evaluator = dir.join("evaluator");
    let evaluator_weights = evaluator.join("evaluator.safetensors");
    if !evaluator_weights.is_file() {
        train_evaluator(root, &data, &evaluator, EVALUATOR_STEPS)?;
    }
    let data_arg = path(&data)?;
    let mut reports = Vec::with_capacity(VARIANTS.len());
    for (k, (variant, config)) in VARIANTS.iter().zip(&configs).enumerate() {
        let variant_dir = dir.join(format!("variant-{k}"));
        std::fs::create_dir_all(&variant_dir)
            .with_context(|| format!("creating {}", variant_dir.display()))?;
        let run = variant_dir.join("run");
        let checkpoint = run.join("checkpoint.safetensors");
        // `config.toml` is the configuration the run in `run/` was started with; `run.done`
        // holds it again once that run has finished.
        let (config_file, done_file) =
            (variant_dir.join("config.toml"), variant_dir.join("run.done"));
        let run_arg = path(&run)?;
        if read(&done_file) == *config && checkpoint.is_file() {
            eprintln!("\n==> {}: reusing the trained run in {}", variant.label, run.display());
        } else {
            let _ = std::fs::remove_file(&done_file);
            let resume = read(&config_file) == *config && checkpoint.is_file();
            if !resume && run.exists() {
                std::fs::remove_dir_all(&run)
                    .with_context(|| format!("removing {}", run.display()))?;
            }
            write(&config_file, config)?;
            let config_arg = path(&config_file)?;
            let mut train =
                vec!["train", "--config", &config_arg, "--data", &data_arg, "--out", &run_arg];
            if resume {
                eprintln!("\n==> {}: resuming the run in {}", variant.label, run.display());
                train.push("--resume");
            }
            dex2hoi(root, &train)?;
            write(&done_file, config)?;
        }
        let report = variant_dir.join("report");
        let report_json = report.join("report.json");
        if newer_than_all(&report_json, &[&checkpoint, &evaluator_weights]) {
            eprintln!("\n==> {}: reusing the evaluation in {}", variant.label, report.display());
        } else {
            let (evaluator_arg, report_arg) = (path(&evaluator)?, path(&report)?);
            let mut evaluate = vec![
                "evaluate",
                "--run",
                &run_arg,
                "--data",
                &data_arg,
                "--evaluator",
                &evaluator_arg,
                "--out",
                &report_arg,
            ];
            evaluate.extend(EVALUATE_OPTIONS);
            dex2hoi(root, &evaluate)?;
        }
        let json = std::fs::read_to_string(&report_json)
            .with_context(|| format!("reading {}", report_json.display()))?;
        reports.push(Report::parse(&json).with_context(|| report_json.display().to_string())?);
    }
    let command = format!(
        "cargo xtask ablate --preset {preset}{}",
        steps.map(|s| format!(" --steps {s}")).unwrap_or_default()
    );
    let table = ablation_table(&command, &preset, &reports)?;
    let out = root.join("docs/results/ablation.md");
    std::fs::create_dir_all(out.parent().context("docs/results")?)?;
    write(&out, &table)?;
    println!("{table}\nwritten to {}", out.display());
    Ok(())
}

/// `docs/results/ablation.md`: a paragraph on how it was made, then the ground truth (of the
/// first report) and one row per variant.
pub fn ablation_table(command: &str, preset: &str, reports: &[Report]) -> Result<String> {
    let first = reports.first().context("no reports")?;
    if reports.len() != VARIANTS.len() {
        bail!("{} reports for {} variants", reports.len(), VARIANTS.len());
    }
    let [prompts, repeats, pairs] = first.multimodality_protocol;
    let mut out = format!(
        "# Ablation on the procedural dataset (paper Table 3)\n\nMade by `{command}`: \
         {SEQUENCES} procedural sequences (seed {DATA_SEED}), every variant trained from the \
         same seed for the same steps with the `{preset}` preset, all evaluated with one \
         evaluator ({EVALUATOR_STEPS} steps) trained on the same data: {} test sequences, {} \
         replications, 20 DDIM steps, MultiModality {prompts} x {repeats} x {pairs}. Values are \
         means with 95% intervals over the replications.\n\n{TABLE_HEADER}\n|{}\n{}\n",
        first.samples,
        first.replications,
        "---|".repeat(17),
        table_row("Ground truth", first.truth()?),
    );
    for (variant, report) in VARIANTS.iter().zip(reports) {
        out.push_str(&table_row(variant.label, report.model()?));
        out.push('\n');
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    const PRESET: &str = r#"# A preset.

[model]
joints = 52
latent = 128
dropout = 0.0
object_representation = "hand_relative"
stream_layout = "dual"
body_fusion = "network"

[text]
encoder = "builtin"
width = 64

[optimizer]
learning_rate = 1e-3

[training]
steps = 300
seed = 7
"#;

    fn parse(text: &str) -> toml::Table {
        text.parse().expect("valid TOML")
    }

    /// The keys a variant may change, with the preset's values.
    const DEFAULT_MODEL: [(&str, &str); 3] = [
        ("object_representation", "hand_relative"),
        ("stream_layout", "dual"),
        ("body_fusion", "network"),
    ];

    #[test]
    fn every_variant_sets_typed_values_and_keeps_the_rest() {
        let base = parse(PRESET);
        for variant in &VARIANTS {
            let text = variant_config(PRESET, variant, None).unwrap();
            let mut edited = parse(&text);
            let model = edited["model"].as_table().unwrap();
            for (key, default) in DEFAULT_MODEL {
                let expected = variant
                    .model
                    .iter()
                    .find(|(k, _)| *k == key)
                    .map_or(default, |(_, value)| *value);
                assert_eq!(model[key].as_str(), Some(expected), "{}: {key}", variant.label);
            }
            match edited.remove("loss") {
                None => assert!(variant.loss.is_empty(), "{}", variant.label),
                Some(loss) => {
                    let loss = loss.as_table().unwrap();
                    assert_eq!(loss.len(), variant.loss.len(), "{}", variant.label);
                    for (key, value) in variant.loss {
                        assert_eq!(loss[*key].as_bool(), Some(*value), "{}: {key}", variant.label);
                    }
                }
            }
            // Everything else, model keys the variant does not touch included, is unchanged.
            let mut expected = base.clone();
            for (key, value) in variant.model {
                expected["model"]
                    .as_table_mut()
                    .unwrap()
                    .insert((*key).into(), toml::Value::String((*value).into()));
            }
            assert_eq!(edited, expected, "{}", variant.label);
            assert!(text.contains(variant.label));
        }
    }

    #[test]
    fn the_variants_match_the_model_enums_and_the_loss_switches() {
        let spellings = [
            ("object_representation", ["hand_relative", "global_only"]),
            ("stream_layout", ["dual", "single"]),
            ("body_fusion", ["network", "average"]),
        ];
        for variant in &VARIANTS {
            for (key, value) in variant.model {
                let (_, allowed) = spellings.iter().find(|(k, _)| k == key).unwrap();
                assert!(allowed.contains(value), "{}: {key} = {value}", variant.label);
            }
            for (key, _) in variant.loss {
                assert!(["mixture_supervision", "distance_loss"].contains(key));
            }
        }
        // The full model first, then one row per change of Table 3 and the baseline.
        assert!(VARIANTS[0].model.is_empty() && VARIANTS[0].loss.is_empty());
        let labels: std::collections::HashSet<_> = VARIANTS.iter().map(|v| v.label).collect();
        assert_eq!(labels.len(), VARIANTS.len());
    }

    #[test]
    fn an_existing_loss_table_is_extended_and_steps_are_an_integer() {
        let preset = format!("{PRESET}\n[loss]\ndiffusion = 2.0\ndistance_loss = true\n");
        let baseline = &VARIANTS[6];
        let edited = parse(&variant_config(&preset, baseline, Some(1234)).unwrap());
        let loss = edited["loss"].as_table().unwrap();
        assert_eq!(loss["diffusion"].as_float(), Some(2.0));
        assert_eq!(loss["distance_loss"].as_bool(), Some(false));
        assert_eq!(loss["mixture_supervision"].as_bool(), Some(false));
        assert_eq!(edited["training"]["steps"].as_integer(), Some(1234));
        assert_eq!(edited["training"]["seed"].as_integer(), Some(7));
        assert_eq!(edited["optimizer"]["learning_rate"].as_float(), Some(1e-3));
    }

    #[test]
    fn a_preset_without_the_key_is_refused() {
        let preset = PRESET.replace("body_fusion = \"network\"\n", "");
        let error = variant_config(&preset, &VARIANTS[1], None).unwrap_err();
        assert!(error.to_string().contains("body_fusion"), "{error}");
        assert!(variant_config(&preset, &VARIANTS[2], None).is_ok());
        assert!(variant_config("[model", &VARIANTS[0], None).is_err());
    }

    #[test]
    fn the_real_presets_make_every_variant() {
        let configs = crate::workspace_root().join("configs");
        for preset in ["demo", "small", "paper"] {
            let text = std::fs::read_to_string(configs.join(format!("{preset}.toml"))).unwrap();
            for variant in &VARIANTS {
                variant_config(&text, variant, Some(10)).unwrap();
            }
        }
    }

    /// An estimate as `serde_json::to_vec_pretty` writes `evaluate.rs`'s `Estimate`.
    fn estimate(mean: f64, interval: f64) -> String {
        format!("{{ \"mean\": {mean:?}, \"interval\": {interval:?} }}")
    }

    /// A row as `evaluate.rs` serialises `ReportRow`; `contact_distance_mm` is NaN (no
    /// ground-truth contact), which serde_json writes as `null`.
    fn row(name: &str, model: bool) -> String {
        let e = estimate(0.5, 0.25);
        let optional = |some: bool| if some { e.clone() } else { "null".into() };
        format!(
            r#"{{
      "name": "{name}",
      "r_precision": [{}, {}, {}],
      "fid": {}, "mm_dist": {e}, "diversity": {e},
      "multimodality": {},
      "physical": {{
        "penetration_depth_mm": {e}, "penetration_frames_percent": {e},
        "contact_precision": {e}, "contact_recall": {e}, "contact_f1": {e},
        "contact_distance_mm": {{ "mean": null, "interval": null }},
        "foot_sliding_mm": {e},
        "mixture_agreement_percent": {}
      }},
      "runtime_seconds": {}
    }}"#,
            estimate(0.125, 0.0),
            estimate(0.25, 0.0),
            estimate(0.375, 0.0),
            if model { estimate(95.503, 0.935) } else { estimate(0.0, 0.0) },
            optional(model),
            optional(model),
            if model { "[2.67, 0.41]" } else { "null" },
        )
    }

    fn sample_report() -> String {
        format!(
            r#"{{
  "rows": [{}, {}],
  "samples": 32,
  "skipped": 1,
  "replications": 2,
  "clip_frames": 60,
  "distribution_features": "action classifier features (IMoS)",
  "multimodality_protocol": [4, 3, 2]
}}"#,
            row("Ground truth", false),
            row("Dex2HOI (this run)", true)
        )
    }

    #[test]
    fn report_json_is_read() {
        let report = Report::parse(&sample_report()).unwrap();
        assert_eq!((report.samples, report.skipped, report.replications), (32, 1, 2));
        assert_eq!(report.multimodality_protocol, [4, 3, 2]);
        let (truth, model) = (report.truth().unwrap(), report.model().unwrap());
        assert_eq!(model.name, "Dex2HOI (this run)");
        assert_eq!(model.fid.mean.0, 95.503);
        assert!(model.physical.contact_distance_mm.mean.0.is_nan());
        assert!(truth.multimodality.is_none() && truth.runtime_seconds.is_none());
        assert_eq!(model.runtime_seconds, Some((Number(2.67), Number(0.41))));

        let line = table_row("w/o L_dist", model);
        assert_eq!(line.matches('|').count(), 18, "{line}");
        assert!(line.starts_with(
            "| w/o L_dist | 0.125 ± 0.000 | 0.250 ± 0.000 | 0.375 ± 0.000 | 95.503 ± 0.935 |"
        ));
        assert!(line.ends_with("| NaN ± NaN | 0.50 ± 0.25 | 0.5 ± 0.2 | 2.67 ± 0.41 |"), "{line}");
        let truth_line = table_row("Ground truth", truth);
        assert!(truth_line.contains("| 0.500 ± 0.250 | - | 0.50 ± 0.25 |"), "{truth_line}");
        assert!(truth_line.ends_with("| - | - |"), "{truth_line}");
    }

    #[test]
    fn a_report_without_both_rows_is_refused() {
        let only_truth =
            sample_report().replacen(&format!(", {}", row("Dex2HOI (this run)", true)), "", 1);
        assert!(Report::parse(&only_truth).is_err());
        assert!(Report::parse("{}").is_err());
    }

    #[test]
    fn the_table_has_the_ground_truth_and_a_row_per_variant() {
        let report = Report::parse(&sample_report()).unwrap();
        let reports = vec![report; VARIANTS.len()];
        let table = ablation_table("cargo xtask ablate --preset demo", "demo", &reports).unwrap();
        let rows: Vec<&str> = table.lines().filter(|l| l.starts_with('|')).collect();
        assert_eq!(rows.len(), 2 + 1 + VARIANTS.len());
        assert_eq!(rows[0], TABLE_HEADER);
        assert!(rows[2].starts_with("| Ground truth |"));
        for (row, variant) in rows[3..].iter().zip(&VARIANTS) {
            assert!(row.starts_with(&format!("| {} |", variant.label)));
        }
        assert!(table.contains("32 test sequences, 2 replications"));
        assert!(table.contains("MultiModality 4 x 3 x 2"));
        assert!(ablation_table("c", "demo", &reports[..3]).is_err());
    }

    #[test]
    fn options_are_parsed() {
        let args = |a: &[&str]| a.iter().map(|s| s.to_string()).collect::<Vec<_>>();
        assert_eq!(
            Options::parse(&args(&[])).unwrap(),
            Options { preset: "demo".into(), steps: None }
        );
        assert_eq!(
            Options::parse(&args(&["--preset", "small", "--steps", "50"])).unwrap(),
            Options { preset: "small".into(), steps: Some(50) }
        );
        assert!(Options::parse(&args(&["--steps", "0"])).is_err());
        assert!(Options::parse(&args(&["--steps", "x"])).is_err());
        assert!(Options::parse(&args(&["--fast"])).is_err());
    }

    #[test]
    fn a_report_is_reused_only_when_newer_than_its_inputs() {
        let dir = std::env::temp_dir().join(format!("xtask-ablate-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let touch = |name: &str, seconds: u64| {
            let path = dir.join(name);
            let file = std::fs::File::create(&path).unwrap();
            file.set_modified(SystemTime::UNIX_EPOCH + std::time::Duration::from_secs(seconds))
                .unwrap();
            path
        };
        let checkpoint = touch("checkpoint", 2_000);
        let evaluator = touch("evaluator", 1_000);
        let report = touch("report", 3_000);
        assert!(newer_than_all(&report, &[&checkpoint, &evaluator]));
        let resumed = touch("checkpoint", 4_000);
        assert!(!newer_than_all(&report, &[&resumed, &evaluator]));
        assert!(!newer_than_all(&dir.join("missing"), &[&evaluator]));
        assert!(!newer_than_all(&report, &[&dir.join("missing")]));
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
