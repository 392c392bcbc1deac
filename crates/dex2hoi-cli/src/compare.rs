//! `dex2hoi compare`: evaluation reports of one or more runs side by side, against the training
//! steps of the evaluated weights: a markdown table of the headline metrics per run and a PNG
//! with one panel per metric, one line per run, and the ground truth's value as a dashed line.

use std::path::{Path, PathBuf};
use std::str::FromStr;

use anyhow::{Context, Result, bail};
use clap::Args;

use dex2hoi_data::files::write_atomically;
use dex2hoi_eval::evaluate::{InstructionRow, Report, ReportRow};
use dex2hoi_plot::chart::{Chart, Panel, Scale, Series};

/// One run's evaluations: `LABEL=DIR`.
#[derive(Debug, Clone, PartialEq)]
pub struct SeriesSpec {
    label: String,
    dir: PathBuf,
}

impl FromStr for SeriesSpec {
    type Err = String;

    fn from_str(text: &str) -> Result<Self, Self::Err> {
        match text.split_once('=') {
            Some((label, dir)) if !label.trim().is_empty() && !dir.is_empty() => {
                Ok(Self { label: label.trim().to_string(), dir: PathBuf::from(dir) })
            }
            _ => Err(format!("expected LABEL=DIR, got `{text}`")),
        }
    }
}

/// Arguments of `dex2hoi compare`.
#[derive(Debug, Args)]
pub struct CompareArgs {
    /// A run's evaluations as LABEL=DIR: DIR holds `report.json` (one evaluation) or
    /// subdirectories that do (one per snapshot, as `dex2hoi evaluate --out` wrote them).
    /// Repeat for each run.
    #[arg(long = "series", required = true, value_name = "LABEL=DIR")]
    series: Vec<SeriesSpec>,
    /// Output directory: comparison.md and comparison.png.
    #[arg(long)]
    out: PathBuf,
    /// The title of comparison.md.
    #[arg(long, default_value = "Metrics against training steps")]
    title: String,
}

/// A metric as the comparison reads it from a report's model row (and its first instruction
/// row) or ground-truth row.
struct Metric {
    /// Column and panel title, with its unit.
    name: &'static str,
    /// Decimals in the table.
    digits: usize,
    /// In the markdown table (the plot has every metric).
    headline: bool,
    value: fn(&ReportRow, Option<&InstructionRow>) -> Option<f64>,
}

const METRICS: [Metric; 27] = [
    Metric {
        name: "R-prec. top-1",
        digits: 3,
        headline: false,
        value: |r, _| Some(r.r_precision[0].mean),
    },
    Metric {
        name: "R-prec. top-2",
        digits: 3,
        headline: false,
        value: |r, _| Some(r.r_precision[1].mean),
    },
    Metric {
        name: "R-prec. top-3",
        digits: 3,
        headline: true,
        value: |r, _| Some(r.r_precision[2].mean),
    },
    Metric { name: "FID", digits: 1, headline: true, value: |r, _| Some(r.fid.mean) },
    Metric { name: "MMdist", digits: 3, headline: false, value: |r, _| Some(r.mm_dist.mean) },
    Metric { name: "Diversity", digits: 2, headline: false, value: |r, _| Some(r.diversity.mean) },
    Metric {
        name: "MModality",
        digits: 2,
        headline: false,
        value: |r, _| r.multimodality.map(|e| e.mean),
    },
    Metric {
        name: "Pen. frames (%)",
        digits: 1,
        headline: true,
        value: |r, _| Some(r.physical.penetration_frames_percent.mean),
    },
    Metric {
        name: "Pen. depth (mm)",
        digits: 1,
        headline: true,
        value: |r, _| Some(r.physical.penetration_depth_mm.mean),
    },
    Metric {
        name: "Contact P",
        digits: 3,
        headline: false,
        value: |r, _| Some(r.physical.contact_precision.mean),
    },
    Metric {
        name: "Contact R",
        digits: 3,
        headline: false,
        value: |r, _| Some(r.physical.contact_recall.mean),
    },
    Metric {
        name: "Contact F1",
        digits: 3,
        headline: true,
        value: |r, _| Some(r.physical.contact_f1.mean),
    },
    Metric {
        name: "Hand-obj. dist. (mm)",
        digits: 1,
        headline: false,
        value: |r, _| Some(r.physical.contact_distance_mm.mean),
    },
    Metric {
        name: "Foot sliding (mm/frame)",
        digits: 3,
        headline: false,
        value: |r, _| Some(r.physical.foot_sliding_mm.mean),
    },
    Metric {
        name: "Mixture picks holder (%)",
        digits: 1,
        headline: false,
        value: |r, _| r.physical.mixture_agreement_percent.map(|e| e.mean),
    },
    Metric {
        name: "Start jump (cm)",
        digits: 2,
        headline: true,
        value: |r, _| r.physical.object_start_jump_cm.map(|e| e.mean),
    },
    Metric {
        name: "Untouched speed (cm/s)",
        digits: 2,
        headline: true,
        value: |r, _| r.physical.untouched_speed_cm_s.map(|e| e.mean),
    },
    Metric {
        name: "Sinking (cm)",
        digits: 2,
        headline: true,
        value: |r, _| r.physical.sinking_depth_cm.map(|e| e.mean),
    },
    Metric {
        name: "Frames sunk (%)",
        digits: 1,
        headline: false,
        value: |r, _| r.physical.sinking_frames_percent.map(|e| e.mean),
    },
    Metric {
        name: "Fingertip low (mm)",
        digits: 1,
        headline: false,
        value: |r, _| r.physical.fingertip_low_mm.map(|e| e.mean),
    },
    Metric {
        name: "Fingertip error (mm)",
        digits: 1,
        headline: false,
        value: |r, _| r.physical.fingertip_error_mm.map(|e| e.mean),
    },
    Metric {
        name: "Objects moved (%)",
        digits: 1,
        headline: true,
        value: |_, i| i?.objects_moved_percent.map(|e| e.mean),
    },
    Metric {
        name: "Unasked moves (%)",
        digits: 1,
        headline: true,
        value: |_, i| i?.unasked_moves_percent.map(|e| e.mean),
    },
    Metric {
        name: "Holding hand (%)",
        digits: 1,
        headline: true,
        value: |_, i| i?.holding_hand_percent.map(|e| e.mean),
    },
    Metric {
        name: "Same side (%)",
        digits: 1,
        headline: true,
        value: |_, i| i?.same_side_percent.map(|e| e.mean),
    },
    Metric {
        name: "End distance (cm)",
        digits: 1,
        headline: true,
        value: |_, i| i?.end_distance_cm.map(|e| e.mean),
    },
    Metric {
        name: "Runtime (s/clip)",
        digits: 3,
        headline: false,
        value: |r, _| r.runtime_seconds.map(|(mean, _)| mean),
    },
];

/// A report with where it came from.
struct Loaded {
    path: PathBuf,
    report: Report,
}

impl Loaded {
    fn read(path: &Path) -> Result<Self> {
        let bytes = std::fs::read(path).with_context(|| format!("reading {}", path.display()))?;
        let report = Report::from_json(path, &bytes)?;
        Ok(Self { path: path.to_path_buf(), report })
    }

    fn row(&self, ground_truth: bool) -> Result<&ReportRow> {
        let row = if ground_truth { self.report.rows.first() } else { self.report.rows.get(1) };
        row.with_context(|| {
            format!("{}: expected a ground-truth row and a model row", self.path.display())
        })
    }

    fn value(&self, metric: &Metric, ground_truth: bool) -> Result<Option<f64>> {
        let instruction = if ground_truth { None } else { self.report.instruction.first() };
        Ok((metric.value)(self.row(ground_truth)?, instruction).filter(|v| v.is_finite()))
    }

    /// What makes two evaluations comparable: the sampler and seed, the test sequences and
    /// replications, the clip length, the distribution features and the MultiModality protocol.
    fn protocol(&self) -> String {
        let r = &self.report;
        format!(
            "{}; {} x {}; {} frames; {}; {:?}",
            r.setup.describe(),
            r.samples,
            r.replications,
            r.clip_frames,
            r.distribution_features,
            r.multimodality_protocol
        )
    }
}

/// The reports of one series, by training step.
fn read_series(spec: &SeriesSpec) -> Result<Vec<Loaded>> {
    let single = spec.dir.join("report.json");
    let mut reports = if single.is_file() {
        vec![Loaded::read(&single)?]
    } else {
        let entries = std::fs::read_dir(&spec.dir)
            .with_context(|| format!("reading the directory {}", spec.dir.display()))?;
        let mut paths = Vec::new();
        for entry in entries {
            let path = entry.with_context(|| format!("listing {}", spec.dir.display()))?.path();
            if path.join("report.json").is_file() {
                paths.push(path.join("report.json"));
            }
        }
        paths.sort();
        paths.iter().map(|p| Loaded::read(p)).collect::<Result<Vec<_>>>()?
    };
    if reports.is_empty() {
        bail!(
            "{}: no report.json in it or in its subdirectories (series `{}`)",
            spec.dir.display(),
            spec.label
        );
    }
    reports.sort_by_key(|r| r.report.setup.model_step);
    Ok(reports)
}

fn cell(value: Option<f64>, digits: usize) -> String {
    value.map_or("–".into(), |v| format!("{v:.digits$}"))
}

/// A report's cells of `metrics` in the model row or the ground-truth row.
fn cells(loaded: &Loaded, metrics: &[&Metric], ground_truth: bool) -> Result<String> {
    let cells = metrics
        .iter()
        .map(|m| Ok(cell(loaded.value(m, ground_truth)?, m.digits)))
        .collect::<Result<Vec<_>>>()?;
    Ok(cells.join(" | "))
}

/// The ground truth's values of every metric in a report.
fn ground_truth(loaded: &Loaded) -> Result<Vec<Option<f64>>> {
    METRICS.iter().map(|m| loaded.value(m, true)).collect()
}

/// Relative difference under which two ground-truth figures are the same: the evaluator's
/// encoders computed in another floating-point order (another build) move them by about 1e-8.
const GROUND_TRUTH_TOLERANCE: f64 = 1e-6;

/// Whether two reports' ground-truth figures agree (within [`GROUND_TRUTH_TOLERANCE`]).
fn same_ground_truth(a: &[Option<f64>], b: &[Option<f64>]) -> bool {
    a.len() == b.len()
        && a.iter().zip(b).all(|pair| match pair {
            (Some(a), Some(b)) => (a - b).abs() <= GROUND_TRUTH_TOLERANCE * a.abs().max(b.abs()),
            (None, None) => true,
            _ => false,
        })
}

/// The markdown: per series, a table of the headline metrics by step and its first report's
/// ground truth; then the reports that were evaluated differently from the first one.
fn markdown(title: &str, series: &[(SeriesSpec, Vec<Loaded>)]) -> Result<String> {
    let headline: Vec<&Metric> = METRICS.iter().filter(|m| m.headline).collect();
    let mut out = format!("# {title}\n");
    for (spec, reports) in series {
        let first = reports.first().context("a series without reports")?;
        let report = &first.report;
        out.push_str(&format!(
            "\n## {}\n\n{} test sequences x {} replication{}, {}; from `{}`.\n\n| steps | {} |\n|---|{}\n",
            spec.label,
            report.samples,
            report.replications,
            if report.replications == 1 { "" } else { "s" },
            report.setup.describe(),
            spec.dir.display(),
            headline.iter().map(|m| m.name).collect::<Vec<_>>().join(" | "),
            "---|".repeat(headline.len()),
        ));
        for loaded in reports {
            let step = loaded.report.setup.model_step;
            out.push_str(&format!("| {step} | {} |\n", cells(loaded, &headline, false)?));
        }
        out.push_str(&format!("| ground truth | {} |\n", cells(first, &headline, true)?));
    }
    let all: Vec<&Loaded> = series.iter().flat_map(|(_, reports)| reports).collect();
    let first = all.first().context("no reports")?;
    let (protocol, truth) = (first.protocol(), ground_truth(first)?);
    let mut differing = Vec::new();
    for loaded in &all {
        if loaded.protocol() != protocol || !same_ground_truth(&ground_truth(loaded)?, &truth) {
            differing.push(format!("`{}`", loaded.path.display()));
        }
    }
    if !differing.is_empty() {
        out.push_str(&format!(
            "\n**Not comparable with the first report** (`{}`): evaluated with another sampler, \
             seed, set of test sequences, replications, clip length or MultiModality protocol, \
             or against another ground truth: {}.\n",
            first.path.display(),
            differing.join(", ")
        ));
    }
    out.push_str(
        "\nMeans over replications; `dex2hoi evaluate`'s report.md of each row has the 95% \
         intervals and every other metric. comparison.png plots every metric against the steps, \
         the first report's ground truth dashed.\n",
    );
    Ok(out)
}

/// The chart: a panel per metric, a line per series, the first report's ground truth dashed.
fn chart(series: &[(SeriesSpec, Vec<Loaded>)]) -> Result<Chart> {
    let first = series.first().and_then(|(_, reports)| reports.first()).context("no reports")?;
    let mut panels = Vec::with_capacity(METRICS.len());
    for metric in &METRICS {
        let mut lines = Vec::with_capacity(series.len());
        for (spec, reports) in series {
            let mut points = Vec::with_capacity(reports.len());
            for loaded in reports {
                if let Some(value) = loaded.value(metric, false)? {
                    points.push((loaded.report.setup.model_step as f64, value));
                }
            }
            lines.push(Series { label: spec.label.clone(), points });
        }
        panels.push(Panel {
            title: metric.name.to_string(),
            series: lines,
            reference: first.value(metric, true)?,
            scale: Scale::Linear,
        });
    }
    Ok(Chart {
        panels,
        columns: 3,
        legend: series.iter().map(|(spec, _)| spec.label.clone()).collect(),
    })
}

/// Runs `dex2hoi compare`.
pub fn run(args: CompareArgs) -> Result<()> {
    let series = args
        .series
        .iter()
        .map(|spec| Ok((spec.clone(), read_series(spec)?)))
        .collect::<Result<Vec<_>>>()?;
    let markdown = markdown(&args.title, &series)?;
    let png = chart(&series)?.encode_png()?;
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("creating {}", args.out.display()))?;
    write_atomically(&args.out.join("comparison.md"), markdown.as_bytes())?;
    write_atomically(&args.out.join("comparison.png"), &png)?;
    println!("{markdown}");
    println!("written to {}", args.out.display());
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::same_ground_truth;

    #[test]
    fn ground_truths_agree_within_float_noise_only() {
        let truth = [Some(0.299_627_583_032_407), Some(20.657_415_406), None, Some(0.0)];
        // The figures of the same evaluation by a build whose kernels sum in another order.
        let rebuilt = [Some(0.299_627_587_846_073), Some(20.657_415_421), None, Some(0.0)];
        assert!(same_ground_truth(&truth, &rebuilt));
        let other_data = [Some(0.3), Some(20.657_415_406), None, Some(0.0)];
        assert!(!same_ground_truth(&truth, &other_data));
        let missing = [Some(0.299_627_583_032_407), None, None, Some(0.0)];
        assert!(!same_ground_truth(&truth, &missing));
        assert!(!same_ground_truth(&truth, &truth[..3]));
    }
}
