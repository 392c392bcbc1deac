//! Line charts as PNG: a grid of panels, each with a title, one line per series, an optional
//! horizontal reference line (a target or the ground truth's value) and its y range written at
//! the axis. Used for a run's loss curves and for metrics against training steps; drawn with the
//! project's bitmap font, so no plotting library or font file is needed.

use crate::font::{GLYPH_HEIGHT, draw_text, text_width};
use crate::{Result, encode_rgb_png};

const PANEL_WIDTH: usize = 360;
const PANEL_HEIGHT: usize = 170;
const MARGIN: usize = 12;
/// Room for the y range's labels left of the plot area (8 characters, such as `-1.23e-3`).
const AXIS_LABEL_WIDTH: usize = 68;
const TEXT_SCALE: usize = 2;
const LINE_HEIGHT: usize = (GLYPH_HEIGHT + 2) * TEXT_SCALE;
const BACKGROUND: [u8; 3] = [255, 255, 255];
const INK: [u8; 3] = [20, 20, 20];
const AXIS: [u8; 3] = [150, 150, 150];
const REFERENCE: [u8; 3] = [120, 120, 120];
/// Colours of the series, by index (a seventh series takes the first colour again).
pub const PALETTE: [[u8; 3]; 6] =
    [[200, 60, 40], [40, 100, 200], [40, 150, 60], [150, 60, 170], [220, 140, 20], [0, 150, 150]];

/// How a panel's y axis maps values.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Scale {
    /// Linear.
    Linear,
    /// Base-10 logarithmic (non-positive values are left out).
    Log,
}

/// One line of a panel: `(x, y)` points in drawing order; non-finite values are left out.
#[derive(Debug, Clone, PartialEq)]
pub struct Series {
    /// Its name in the legend.
    pub label: String,
    /// The points.
    pub points: Vec<(f64, f64)>,
}

/// One panel of a chart.
#[derive(Debug, Clone, PartialEq)]
pub struct Panel {
    /// The title above the plot area.
    pub title: String,
    /// The lines, coloured by their index (the same index, the same colour in every panel).
    pub series: Vec<Series>,
    /// A horizontal dashed line (a target, the ground truth's value).
    pub reference: Option<f64>,
    /// The y axis.
    pub scale: Scale,
}

/// A chart: panels laid out in `columns`, with a legend of the series' labels on top unless
/// `legend` is empty.
#[derive(Debug, Clone, PartialEq)]
pub struct Chart {
    /// The panels, row by row.
    pub panels: Vec<Panel>,
    /// Panels per row (at least 1).
    pub columns: usize,
    /// The legend: one label per series index (empty: no legend).
    pub legend: Vec<String>,
}

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

    /// A two-pixel-thick line; with `dash`, drawn `dash` pixels on, `dash` off.
    fn line(&mut self, (x0, y0): (f64, f64), (x1, y1): (f64, f64), colour: [u8; 3], dash: usize) {
        let steps = (x1 - x0).abs().max((y1 - y0).abs()).ceil().max(1.0) as usize;
        for k in 0..=steps {
            if dash > 0 && (k / dash) % 2 == 1 {
                continue;
            }
            let s = k as f64 / steps as f64;
            let (x, y) = (x0 + (x1 - x0) * s, y0 + (y1 - y0) * s);
            self.set(x.round() as i64, y.round() as i64, colour);
            self.set(x.round() as i64, y.round() as i64 + 1, colour);
        }
    }
}

/// A short label of a value: three decimal places from 0.01 to 1000, whole numbers up to a
/// million, scientific notation otherwise.
pub fn short_number(value: f64) -> String {
    if value == 0.0 {
        "0".into()
    } else if (0.01..1000.0).contains(&value.abs()) {
        format!("{value:.3}")
    } else if (1000.0..1e6).contains(&value.abs()) {
        format!("{value:.0}")
    } else {
        format!("{value:.2e}")
    }
}

impl Scale {
    fn map(self, value: f64) -> Option<f64> {
        let mapped = match self {
            Self::Linear => value,
            Self::Log => (value > 0.0).then(|| value.log10())?,
        };
        mapped.is_finite().then_some(mapped)
    }

    fn unmap(self, mapped: f64) -> f64 {
        match self {
            Self::Linear => mapped,
            Self::Log => 10f64.powf(mapped),
        }
    }
}

impl Series {
    /// The points that can be drawn on `scale`, with `y` mapped by it.
    fn drawable(&self, scale: Scale) -> impl Iterator<Item = (f64, f64)> + '_ {
        self.points
            .iter()
            .filter(|p| p.0.is_finite())
            .filter_map(move |&(x, y)| Some((x, scale.map(y)?)))
    }
}

impl Panel {
    /// The x range and mapped y range over every drawable point and the reference.
    fn ranges(&self) -> Option<((f64, f64), (f64, f64))> {
        let points: Vec<(f64, f64)> =
            self.series.iter().flat_map(|s| s.drawable(self.scale)).collect();
        let fold = |values: &mut dyn Iterator<Item = f64>| {
            values.fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), v| (lo.min(v), hi.max(v)))
        };
        let x = fold(&mut points.iter().map(|p| p.0));
        let reference = self.reference.and_then(|r| self.scale.map(r));
        let y = fold(&mut points.iter().map(|p| p.1).chain(reference));
        (x.0.is_finite() && y.0.is_finite()).then_some((x, y))
    }

    fn draw(&self, canvas: &mut Canvas, left: usize, top: usize) {
        canvas.text(left + MARGIN, top + 6, &self.title, INK);
        let (x0, x1) =
            ((left + MARGIN + AXIS_LABEL_WIDTH) as f64, (left + PANEL_WIDTH - MARGIN) as f64);
        let (y0, y1) =
            ((top + 6 + LINE_HEIGHT + 6) as f64, (top + PANEL_HEIGHT - 2 * MARGIN) as f64);
        canvas.line((x0, y1), (x1, y1), AXIS, 0);
        canvas.line((x0, y0), (x0, y1), AXIS, 0);
        let Some(((x_low, x_high), (y_low, y_high))) = self.ranges() else {
            canvas.text(x0 as usize + 8, y0 as usize + 8, "no data", AXIS);
            return;
        };
        // A flat series gets a visible band instead of a division by zero.
        let (y_low, y_high) = if y_high - y_low < 1e-9 {
            (y_low - 0.5 * y_low.abs().max(1e-3), y_high + 0.5 * y_high.abs().max(1e-3))
        } else {
            (y_low, y_high)
        };
        let x_span = (x_high - x_low).max(1e-9);
        let place = |x: f64, y: f64| {
            (x0 + (x1 - x0) * (x - x_low) / x_span, y1 - (y1 - y0) * (y - y_low) / (y_high - y_low))
        };
        let label_x = |text: &str| (x0 as usize).saturating_sub(4 + text_width(text, TEXT_SCALE));
        let high = short_number(self.scale.unmap(y_high));
        let low = short_number(self.scale.unmap(y_low));
        canvas.text(label_x(&high), y0 as usize, &high, AXIS);
        canvas.text(label_x(&low), y1 as usize - GLYPH_HEIGHT * TEXT_SCALE, &low, AXIS);
        // Steps and other whole numbers without decimals.
        let x_label = |x: f64| {
            if x.fract() == 0.0 && x.abs() < 1e6 { format!("{x:.0}") } else { short_number(x) }
        };
        let (first, last) = (x_label(x_low), x_label(x_high));
        canvas.text(x0 as usize, y1 as usize + 4, &first, AXIS);
        canvas.text(
            (x1 as usize).saturating_sub(text_width(&last, TEXT_SCALE)),
            y1 as usize + 4,
            &last,
            AXIS,
        );
        if let Some(reference) = self.reference.and_then(|r| self.scale.map(r)) {
            canvas.line(place(x_low, reference), place(x_high, reference), REFERENCE, 4);
        }
        for (index, series) in self.series.iter().enumerate() {
            let colour = PALETTE[index % PALETTE.len()];
            let mapped: Vec<(f64, f64)> =
                series.drawable(self.scale).map(|(x, y)| place(x, y)).collect();
            for pair in mapped.windows(2) {
                canvas.line(pair[0], pair[1], colour, 0);
            }
            // A marker on every point, so that a single point still shows.
            for &(x, y) in &mapped {
                for (dx, dy) in
                    [(-1, -1), (0, -1), (1, -1), (-1, 0), (1, 0), (-1, 1), (0, 1), (1, 1)]
                {
                    canvas.set(x.round() as i64 + dx, y.round() as i64 + dy, colour);
                }
            }
        }
    }
}

impl Chart {
    /// The chart as an RGB PNG.
    pub fn encode_png(&self) -> Result<Vec<u8>> {
        let columns = self.columns.max(1);
        let rows = self.panels.len().div_ceil(columns).max(1);
        let legend_height = if self.legend.is_empty() { 0 } else { LINE_HEIGHT + MARGIN };
        let width = columns * PANEL_WIDTH;
        let height = legend_height + rows * PANEL_HEIGHT;
        let mut canvas = Canvas { width, height, pixels: vec![BACKGROUND; width * height] };
        let mut x = MARGIN;
        for (index, label) in self.legend.iter().enumerate() {
            let colour = PALETTE[index % PALETTE.len()];
            let y = MARGIN / 2 + GLYPH_HEIGHT * TEXT_SCALE / 2;
            canvas.line((x as f64, y as f64), ((x + 16) as f64, y as f64), colour, 0);
            canvas.text(x + 22, MARGIN / 2, label, INK);
            x += 22 + text_width(label, TEXT_SCALE) + 2 * MARGIN;
        }
        for (n, panel) in self.panels.iter().enumerate() {
            let (left, top) =
                ((n % columns) * PANEL_WIDTH, legend_height + (n / columns) * PANEL_HEIGHT);
            panel.draw(&mut canvas, left, top);
        }
        let rgb: Vec<u8> = canvas.pixels.iter().flatten().copied().collect();
        encode_rgb_png(width as u32, height as u32, &rgb)
    }
}
