//! The loss curves of a run as a PNG: one panel per logged quantity (the total, then each
//! term), log-scaled, each titled with its name and its first and last values, so a run can be
//! judged at a glance without other tools.

use std::path::Path;

use dex2hoi_export::font::draw_text;

use crate::error::{Result, TrainError};
use crate::run::MetricsLine;
use crate::trainer::write_file;

const PANEL_WIDTH: usize = 320;
const PANEL_HEIGHT: usize = 150;
const COLUMNS: usize = 2;
const MARGIN: usize = 12;
const TEXT_SCALE: usize = 2;

struct Canvas {
    width: usize,
    height: usize,
    pixels: Vec<[u8; 3]>,
}

impl Canvas {
    fn set(&mut self, x: i64, y: i64, colour: [u8; 3]) {
        if x >= 0 && y >= 0 && (x as usize) < self.width && (y as usize) < self.height {
            self.pixels[y as usize * self.width + x as usize] = colour;
        }
    }

    fn text(&mut self, x: usize, y: usize, text: &str, colour: [u8; 3]) {
        draw_text(x, y, text, TEXT_SCALE, |px, py| self.set(px as i64, py as i64, colour));
    }

    fn line(&mut self, (x0, y0): (f64, f64), (x1, y1): (f64, f64), colour: [u8; 3]) {
        let steps = (x1 - x0).abs().max((y1 - y0).abs()).ceil().max(1.0) as usize;
        for k in 0..=steps {
            let s = k as f64 / steps as f64;
            let (x, y) = (x0 + (x1 - x0) * s, y0 + (y1 - y0) * s);
            self.set(x.round() as i64, y.round() as i64, colour);
            self.set(x.round() as i64, y.round() as i64 + 1, colour);
        }
    }
}

fn short(value: f64) -> String {
    if value == 0.0 {
        "0".into()
    } else if (0.01..1000.0).contains(&value.abs()) {
        format!("{value:.3}")
    } else {
        format!("{value:.2e}")
    }
}

/// Draws the curves of `metrics` into a PNG (written atomically).
pub fn write_loss_curve(path: &Path, metrics: &[MetricsLine]) -> Result<()> {
    let mut series: Vec<(String, Vec<(usize, f64)>)> =
        vec![("total".into(), metrics.iter().map(|m| (m.step, m.loss)).collect())];
    let mut names: Vec<&String> = metrics.iter().flat_map(|m| m.terms.keys()).collect();
    names.sort();
    names.dedup();
    let order = crate::loss::Term::ALL.map(|t| t.name());
    names.sort_by_key(|n| order.iter().position(|o| o == n).unwrap_or(usize::MAX));
    for name in names {
        let points =
            metrics.iter().filter_map(|m| m.terms.get(name).map(|v| (m.step, *v))).collect();
        series.push((name.clone(), points));
    }
    let rows = series.len().div_ceil(COLUMNS);
    let mut canvas = Canvas {
        width: COLUMNS * PANEL_WIDTH,
        height: rows * PANEL_HEIGHT,
        pixels: vec![[255, 255, 255]; COLUMNS * PANEL_WIDTH * rows * PANEL_HEIGHT],
    };
    let last_step = metrics.iter().map(|m| m.step).max().unwrap_or(1).max(1) as f64;
    for (n, (name, points)) in series.iter().enumerate() {
        let (left, top) = ((n % COLUMNS) * PANEL_WIDTH, (n / COLUMNS) * PANEL_HEIGHT);
        let first = points.first().map(|p| p.1).unwrap_or(0.0);
        let last = points.last().map(|p| p.1).unwrap_or(0.0);
        canvas.text(
            left + MARGIN,
            top + 6,
            &format!("{name} {} > {}", short(first), short(last)),
            [20, 20, 20],
        );
        let (x0, x1) = ((left + MARGIN) as f64, (left + PANEL_WIDTH - MARGIN) as f64);
        let (y0, y1) = ((top + 24) as f64, (top + PANEL_HEIGHT - MARGIN) as f64);
        canvas.line((x0, y1), (x1, y1), [150, 150, 150]);
        canvas.line((x0, y0), (x0, y1), [150, 150, 150]);
        let logs: Vec<(f64, f64)> = points
            .iter()
            .filter(|p| p.1 > 0.0 && p.1.is_finite())
            .map(|&(s, v)| (s as f64, v.log10()))
            .collect();
        if logs.is_empty() {
            continue;
        }
        let low = logs.iter().map(|p| p.1).fold(f64::INFINITY, f64::min);
        let high = logs.iter().map(|p| p.1).fold(f64::NEG_INFINITY, f64::max);
        let span = (high - low).max(1e-6);
        let place = |(s, v): (f64, f64)| {
            (x0 + (x1 - x0) * s / last_step, y1 - (y1 - y0) * (v - low) / span)
        };
        for pair in logs.windows(2) {
            canvas.line(place(pair[0]), place(pair[1]), [200, 60, 40]);
        }
    }
    let mut bytes = Vec::new();
    {
        let mut encoder = png::Encoder::new(&mut bytes, canvas.width as u32, canvas.height as u32);
        encoder.set_color(png::ColorType::Rgb);
        encoder.set_depth(png::BitDepth::Eight);
        let png_error = |e: png::EncodingError| {
            TrainError::checkpoint(path, "PNG encoding", "an encodable image", e)
        };
        let mut writer = encoder.write_header().map_err(png_error)?;
        let data: Vec<u8> = canvas.pixels.iter().flatten().copied().collect();
        writer.write_image_data(&data).map_err(png_error)?;
    }
    write_file(path, &bytes)
}
