//! Summaries over replications and samples: the mean with its 95% interval, runtime, and
//! quantiles.

/// The normal quantile of a two-sided 95% interval, as in T2M's `get_metric_statistics`.
pub const CONFIDENCE_Z: f64 = 1.96;

/// Mean and population standard deviation (`ddof = 0`, numpy's default). `NaN`s for no values.
fn mean_std(values: &[f64]) -> (f64, f64) {
    if values.is_empty() {
        return (f64::NAN, f64::NAN);
    }
    let n = values.len() as f64;
    let mean = values.iter().sum::<f64>() / n;
    let variance = values.iter().map(|v| (v - mean) * (v - mean)).sum::<f64>() / n;
    (mean, variance.sqrt())
}

/// The mean over replications and the half-width of its 95% interval,
/// `1.96 * std / sqrt(n)`, exactly as T2M's `get_metric_statistics`: `std` is numpy's default
/// population standard deviation (`ddof = 0`), so one value gives a half-width of 0.
/// `(NaN, NaN)` for no values.
pub fn mean_interval(values: &[f64]) -> (f64, f64) {
    let (mean, std) = mean_std(values);
    (mean, CONFIDENCE_Z * std / (values.len() as f64).sqrt())
}

/// Runtime per sample: the mean and the population standard deviation (`ddof = 0`) of the
/// seconds each sample took (the paper times a 60-frame sample). `(NaN, NaN)` for no values.
pub fn runtime(seconds: &[f64]) -> (f64, f64) {
    mean_std(seconds)
}

/// The `q`-quantile of some values (`0 <= q <= 1`, linear between the nearest ranks, numpy's
/// default); `None` for none.
pub fn quantile(values: &[f64], q: f64) -> Option<f64> {
    if values.is_empty() {
        return None;
    }
    let mut sorted = values.to_vec();
    sorted.sort_by(f64::total_cmp);
    let rank = q.clamp(0.0, 1.0) * (sorted.len() - 1) as f64;
    let (below, above) = (rank.floor() as usize, rank.ceil() as usize);
    Some(sorted[below] + (sorted[above] - sorted[below]) * (rank - below as f64))
}
