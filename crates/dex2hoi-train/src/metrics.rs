//! What training writes into the run directory besides the files sampling reads
//! (`dex2hoi_sample::files` owns the directory's schema): the configuration, manifest and
//! statistics at the start, and the log of `metrics.jsonl`.

use dex2hoi_data::dataset::Dataset;
use dex2hoi_sample::RunFiles;
use serde::{Deserialize, Serialize};

use crate::config::TrainConfig;
use crate::error::{Result, TrainError};
use crate::files::{append_line, write_file};
use crate::step::{StepReport, StepTiming};

/// One line of `metrics.jsonl`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MetricsLine {
    /// Steps done.
    pub step: usize,
    /// Weighted total.
    pub loss: f64,
    /// Learning rate.
    pub learning_rate: f64,
    /// Gradient norm before clipping.
    pub gradient_norm: f64,
    /// Seconds of the step.
    pub seconds: f64,
    /// Unweighted terms by name.
    pub terms: std::collections::BTreeMap<String, f64>,
    /// Where the step's time went (absent in runs written before it was logged). On a GPU the
    /// parts before a value is read back only queue work, so their split is indicative.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub timing: Option<StepTiming>,
}

/// Writes the configuration, manifest and statistics.
pub fn write_static(files: &RunFiles, config: &TrainConfig, dataset: &Dataset) -> Result<()> {
    write_file(&files.config, config.to_toml()?.as_bytes())?;
    Ok(files.write_manifest_and_stats(&dataset.manifest, &dataset.stats)?)
}

/// Appends a step to `metrics.jsonl`.
pub fn append_metrics(files: &RunFiles, report: &StepReport) -> Result<()> {
    let line = MetricsLine {
        step: report.step,
        loss: report.loss,
        learning_rate: report.learning_rate,
        gradient_norm: report.gradient_norm,
        seconds: report.seconds,
        terms: report.terms.iter().map(|(t, v)| (t.name().to_string(), *v)).collect(),
        timing: Some(report.timing),
    };
    append_line(&files.metrics, &serde_json::to_string(&line).expect("a metrics line serialises"))
}

/// Reads `metrics.jsonl` (empty when absent).
pub fn read_metrics(files: &RunFiles) -> Result<Vec<MetricsLine>> {
    let text = match std::fs::read_to_string(&files.metrics) {
        Ok(text) => text,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Vec::new()),
        Err(e) => return Err(TrainError::io(&files.metrics, "reading")(e)),
    };
    text.lines()
        .filter(|l| !l.trim().is_empty())
        .enumerate()
        .map(|(n, line)| {
            serde_json::from_str(line).map_err(|e| {
                TrainError::checkpoint(
                    &files.metrics,
                    format!("line {}", n + 1),
                    "a metrics line",
                    e,
                )
            })
        })
        .collect()
}

/// Drops the lines after `step` (a resumed run logs them again).
pub fn truncate_metrics(files: &RunFiles, step: usize) -> Result<()> {
    let kept: Vec<String> = read_metrics(files)?
        .into_iter()
        .filter(|l| l.step <= step)
        .map(|l| serde_json::to_string(&l).expect("a metrics line serialises"))
        .collect();
    let mut text = kept.join("\n");
    if !text.is_empty() {
        text.push('\n');
    }
    write_file(&files.metrics, text.as_bytes())
}
