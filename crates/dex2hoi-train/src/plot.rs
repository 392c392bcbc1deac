//! The loss curves of a run as a PNG: one panel per logged quantity (the total, then each
//! term), log-scaled, each titled with its name and its first and last values, so a run can be
//! judged at a glance without other tools.

use std::path::Path;

use dex2hoi_plot::chart::{Chart, Panel, Scale, Series, short_number};

use crate::error::{Result, TrainError};
use crate::files::write_file;
use crate::metrics::MetricsLine;

/// Draws the curves of `metrics` into a PNG (written atomically).
pub fn write_loss_curve(path: &Path, metrics: &[MetricsLine]) -> Result<()> {
    let mut series: Vec<(String, Vec<(f64, f64)>)> =
        vec![("total".into(), metrics.iter().map(|m| (m.step as f64, m.loss)).collect())];
    let mut names: Vec<&String> = metrics.iter().flat_map(|m| m.terms.keys()).collect();
    names.sort();
    names.dedup();
    let order = crate::loss::Term::ALL.map(|t| t.name());
    names.sort_by_key(|n| order.iter().position(|o| o == n).unwrap_or(usize::MAX));
    for name in names {
        let points =
            metrics.iter().filter_map(|m| m.terms.get(name).map(|v| (m.step as f64, *v))).collect();
        series.push((name.clone(), points));
    }
    let panels = series
        .into_iter()
        .map(|(name, points)| {
            let first = points.first().map_or(0.0, |p| p.1);
            let last = points.last().map_or(0.0, |p| p.1);
            Panel {
                title: format!("{name} {} > {}", short_number(first), short_number(last)),
                series: vec![Series { label: name, points }],
                reference: None,
                scale: Scale::Log,
            }
        })
        .collect();
    let chart = Chart { panels, columns: 2, legend: Vec::new() };
    let bytes = chart
        .encode_png()
        .map_err(|e| TrainError::checkpoint(path, "PNG encoding", "an encodable image", e))?;
    write_file(path, &bytes)
}
