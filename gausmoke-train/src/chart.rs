//! Line charts a person can read without the code: a title, axes with tick marks and tick
//! labels, axis titles with units, a light grid, a legend, and optional marks along x (where
//! frames begin). Text is DejaVu Sans ([`crate::text`]).

use std::path::Path;

use crate::TrainError;
use crate::export::write_atomic;
use crate::text;
use crate::visuals::Picture;

/// Distinct colours of the series, in order (matplotlib's "tab10").
pub const SERIES_COLOURS: [[u8; 3]; 10] = [
    [31, 119, 180],
    [255, 127, 14],
    [44, 160, 44],
    [214, 39, 40],
    [148, 103, 189],
    [140, 86, 75],
    [227, 119, 194],
    [127, 127, 127],
    [188, 189, 34],
    [23, 190, 207],
];

const INK: [u8; 3] = [40, 40, 40];
const GRID: [u8; 3] = [228, 228, 228];
const MARK: [u8; 3] = [196, 206, 232];
/// The height of a line of label text, in pixels.
fn glyph() -> i64 {
    text::line_height(text::LABEL)
}

/// One curve: `(x, y)` points in order; non-finite points (and non-positive ones on a log
/// axis) break the line.
pub struct Series {
    pub label: String,
    pub points: Vec<(f64, f64)>,
}

/// What a chart shows.
pub struct Chart {
    pub title: String,
    /// Axis titles, units included, e.g. "frame" and "held-out PSNR (dB)".
    pub x_label: String,
    pub y_label: String,
    pub log_y: bool,
    pub series: Vec<Series>,
    /// x positions marked by light vertical lines (where each frame begins, on a chart of
    /// steps; the x axis's title says what they mark).
    pub marks: Vec<f64>,
}

/// "Nice" tick positions (1, 2 or 5 times a power of ten) covering `[lo, hi]`.
/// With `integers`, steps are whole numbers (frames, steps).
fn linear_ticks(lo: f64, hi: f64, target: usize, integers: bool) -> Vec<f64> {
    let span = (hi - lo).max(1e-12);
    let raw = span / target.max(1) as f64;
    let power = 10f64.powf(raw.log10().floor());
    let mut step = [1.0, 2.0, 5.0, 10.0]
        .iter()
        .map(|m| m * power)
        .find(|s| span / s <= target as f64)
        .unwrap_or(10.0 * power);
    if integers {
        step = step.max(1.0).round();
    }
    let first = (lo / step).ceil() as i64;
    let last = (hi / step).floor() as i64;
    (first..=last).map(|k| k as f64 * step).collect()
}

/// Tick label: integers plainly, small or large magnitudes in `1e-3` form.
fn tick_label(v: f64, log: bool) -> String {
    if log {
        return format!("1e{}", v.round() as i64);
    }
    if v == 0.0 {
        return "0".into();
    }
    let a = v.abs();
    if !(1e-3..1e5).contains(&a) {
        return format!("{v:.0e}");
    }
    if (v - v.round()).abs() < 1e-9 * a.max(1.0) {
        return format!("{}", v.round() as i64);
    }
    let text = format!("{v:.4}");
    text.trim_end_matches('0').trim_end_matches('.').to_string()
}

/// What a chart is drawn on: a raster [`Picture`] or an [`Svg`] document.
pub trait Canvas {
    /// A one-pixel line from `a` to `b`.
    fn line(&mut self, a: (i64, i64), b: (i64, i64), colour: [u8; 3]);
    /// A filled square of side `2 * radius + 1` centred on `centre`.
    fn dot(&mut self, centre: (i64, i64), radius: i64, colour: [u8; 3]);
    /// Text at `size` with its top-left corner at `(x, y)`; `vertical` writes it bottom to top
    /// with that corner at its bottom-left.
    fn text(&mut self, at: (i64, i64), text: &str, colour: [u8; 3], size: f32, vertical: bool);
}

impl Canvas for Picture {
    fn line(&mut self, (x0, y0): (i64, i64), (x1, y1): (i64, i64), colour: [u8; 3]) {
        let steps = (x1 - x0).abs().max((y1 - y0).abs()).max(1);
        for t in 0..=steps {
            self.put(
                x0 + (x1 - x0) * t / steps,
                y0 + (y1 - y0) * t / steps,
                colour,
            );
        }
    }

    fn dot(&mut self, (x, y): (i64, i64), radius: i64, colour: [u8; 3]) {
        for dy in -radius..=radius {
            for dx in -radius..=radius {
                self.put(x + dx, y + dy, colour);
            }
        }
    }

    fn text(
        &mut self,
        (x, y): (i64, i64),
        label: &str,
        colour: [u8; 3],
        size: f32,
        vertical: bool,
    ) {
        text::draw(self, x, y, label, colour, size, vertical);
    }
}

/// A chart as an SVG document (vector, for papers and slides), with the raster's layout.
pub struct Svg {
    width: u32,
    height: u32,
    body: String,
}

impl Svg {
    pub fn new(width: u32, height: u32) -> Self {
        Self {
            width,
            height,
            body: String::new(),
        }
    }

    /// The document's text.
    pub fn finish(&self) -> String {
        format!(
            "<svg xmlns=\"http://www.w3.org/2000/svg\" width=\"{w}\" height=\"{h}\" \
             viewBox=\"0 0 {w} {h}\" font-family=\"DejaVu Sans, sans-serif\">\n\
             <rect width=\"{w}\" height=\"{h}\" fill=\"white\"/>\n{}</svg>\n",
            self.body,
            w = self.width,
            h = self.height,
        )
    }
}

fn hex([r, g, b]: [u8; 3]) -> String {
    format!("#{r:02x}{g:02x}{b:02x}")
}

fn escape(text: &str) -> String {
    text.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
}

impl Canvas for Svg {
    fn line(&mut self, (x0, y0): (i64, i64), (x1, y1): (i64, i64), colour: [u8; 3]) {
        self.body += &format!(
            "<line x1=\"{}\" y1=\"{}\" x2=\"{}\" y2=\"{}\" stroke=\"{}\"/>\n",
            x0 as f64 + 0.5,
            y0 as f64 + 0.5,
            x1 as f64 + 0.5,
            y1 as f64 + 0.5,
            hex(colour)
        );
    }

    fn dot(&mut self, (x, y): (i64, i64), radius: i64, colour: [u8; 3]) {
        let side = 2 * radius + 1;
        self.body += &format!(
            "<rect x=\"{}\" y=\"{}\" width=\"{side}\" height=\"{side}\" fill=\"{}\"/>\n",
            x - radius,
            y - radius,
            hex(colour)
        );
    }

    fn text(
        &mut self,
        (x, y): (i64, i64),
        label: &str,
        colour: [u8; 3],
        size: f32,
        vertical: bool,
    ) {
        // SVG places text by its baseline: the raster's top plus the font's ascent.
        let ascent = text::ascent(size);
        let (transform, bx, by) = if vertical {
            (format!(" transform=\"rotate(-90 {x} {y})\""), x, y + ascent)
        } else {
            (String::new(), x, y + ascent)
        };
        self.body += &format!(
            "<text x=\"{bx}\" y=\"{by}\" font-size=\"{size}\" fill=\"{}\"{transform}>{}</text>\n",
            hex(colour),
            escape(label)
        );
    }
}

fn text_width(label: &str) -> i64 {
    text::width(label, text::LABEL)
}

/// The chart on a white `width` x `height` picture.
pub fn draw(chart: &Chart, width: u32, height: u32) -> Picture {
    let mut picture = Picture::blank(width, height, [255, 255, 255]);
    draw_on(chart, &mut picture, width, height);
    picture
}

/// The chart as an SVG document of `width` x `height`.
pub fn svg(chart: &Chart, width: u32, height: u32) -> String {
    let mut document = Svg::new(width, height);
    draw_on(chart, &mut document, width, height);
    document.finish()
}

/// Writes the chart, `width` x `height`, as `stem.png` and `stem.svg`.
pub fn save(chart: &Chart, width: u32, height: u32, stem: &Path) -> Result<(), TrainError> {
    draw(chart, width, height).save_png(&stem.with_extension("png"))?;
    write_atomic(
        &stem.with_extension("svg"),
        svg(chart, width, height).as_bytes(),
    )
}

/// Draws the chart on `canvas`, `width` x `height`.
fn draw_on(chart: &Chart, canvas: &mut impl Canvas, width: u32, height: u32) {
    let map_y = |v: f64| if chart.log_y { v.log10() } else { v };
    let usable = |&(x, y): &(f64, f64)| x.is_finite() && y.is_finite() && (!chart.log_y || y > 0.0);
    let points = || {
        chart
            .series
            .iter()
            .flat_map(|s| s.points.iter())
            .filter(|p| usable(p))
    };
    let (mut x_lo, mut x_hi, mut y_lo, mut y_hi) = (
        f64::INFINITY,
        f64::NEG_INFINITY,
        f64::INFINITY,
        f64::NEG_INFINITY,
    );
    for &(x, y) in points() {
        let y = map_y(y);
        (x_lo, x_hi, y_lo, y_hi) = (x_lo.min(x), x_hi.max(x), y_lo.min(y), y_hi.max(y));
    }
    if !x_lo.is_finite() {
        (x_lo, x_hi, y_lo, y_hi) = (0.0, 1.0, 0.0, 1.0);
    }
    if x_hi - x_lo < 1e-12 {
        (x_lo, x_hi) = (x_lo - 0.5, x_hi + 0.5);
    }
    if chart.log_y {
        (y_lo, y_hi) = (y_lo.floor(), y_hi.ceil().max(y_lo.floor() + 1.0));
    } else {
        let pad = ((y_hi - y_lo) * 0.05).max(1e-9 * y_hi.abs().max(1.0));
        (y_lo, y_hi) = (y_lo - pad, y_hi + pad);
    }
    let y_ticks: Vec<f64> = if chart.log_y {
        let decades = (y_hi - y_lo) as i64;
        let every = (decades / 6 + 1).max(1);
        (y_lo as i64..=y_hi as i64)
            .filter(|k| (k - y_lo as i64) % every == 0)
            .map(|k| k as f64)
            .collect()
    } else {
        linear_ticks(y_lo, y_hi, 6, false)
    };
    let integer_x = points().all(|&(x, _)| x.fract() == 0.0);
    let x_ticks = linear_ticks(x_lo, x_hi, 8, integer_x);
    let label_width = y_ticks
        .iter()
        .map(|&v| text_width(&tick_label(v, chart.log_y)))
        .max()
        .unwrap_or(0);
    let has_legend =
        chart.series.len() > 1 || chart.series.first().is_some_and(|s| !s.label.is_empty());
    let (left, right) = (label_width + 8 + glyph() + 10, width as i64 - 12);
    let title_height = text::line_height(text::TITLE);
    let entry = |label: &str| text_width(label) + 30;
    let legend = if has_legend {
        let widths: Vec<i64> = chart.series.iter().map(|s| entry(&s.label)).collect();
        legend_rows(&widths, right - left)
    } else {
        Vec::new()
    };
    let (top, bottom) = (
        if has_legend {
            title_height + 10 + legend.len() as i64 * (glyph() + 10)
        } else {
            title_height + 16
        },
        height as i64 - (2 * glyph() + 18),
    );
    if right - left < 20 || bottom - top < 20 {
        return;
    }
    let px = |x: f64| left + ((x - x_lo) / (x_hi - x_lo) * (right - left) as f64).round() as i64;
    let py = |y: f64| bottom - ((y - y_lo) / (y_hi - y_lo) * (bottom - top) as f64).round() as i64;

    for &v in &y_ticks {
        let y = py(v);
        canvas.line((left, y), (right, y), GRID);
        canvas.line((left - 4, y), (left, y), INK);
        let label = tick_label(v, chart.log_y);
        canvas.text(
            (left - 6 - text_width(&label), y - glyph() / 2),
            &label,
            INK,
            text::LABEL,
            false,
        );
    }
    for &v in &x_ticks {
        let x = px(v);
        canvas.line((x, top), (x, bottom), GRID);
        canvas.line((x, bottom), (x, bottom + 4), INK);
        let label = tick_label(v, false);
        canvas.text(
            (x - text_width(&label) / 2, bottom + 7),
            &label,
            INK,
            text::LABEL,
            false,
        );
    }
    canvas.line((left, top), (left, bottom), INK);
    canvas.line((left, bottom), (right, bottom), INK);
    canvas.text(
        (
            (left + right) / 2 - text_width(&chart.x_label) / 2,
            height as i64 - glyph() - 4,
        ),
        &chart.x_label,
        INK,
        text::LABEL,
        false,
    );
    canvas.text(
        (2, (top + bottom) / 2 + text_width(&chart.y_label) / 2),
        &chart.y_label,
        INK,
        text::LABEL,
        true,
    );
    canvas.text(
        (
            (width as i64 - text::width(&chart.title, text::TITLE)) / 2,
            4,
        ),
        &chart.title,
        INK,
        text::TITLE,
        false,
    );
    for &mark in chart.marks.iter().filter(|m| (x_lo..=x_hi).contains(*m)) {
        let x = px(mark);
        canvas.line((x, top), (x, bottom), MARK);
    }

    // The first series is drawn last, on top: it is the one a chart is about.
    for (s, series) in chart.series.iter().enumerate().rev() {
        let colour = SERIES_COLOURS[s % SERIES_COLOURS.len()];
        // Few points: mark each, so single frames show.
        let marked = series.points.len() <= 60;
        let mut previous: Option<(i64, i64)> = None;
        for point in &series.points {
            if !usable(point) {
                previous = None;
                continue;
            }
            let here = (px(point.0), py(map_y(point.1)));
            if let Some(p) = previous {
                canvas.line(p, here, colour);
            }
            canvas.dot(here, if marked { 2 } else { 0 }, colour);
            previous = Some(here);
        }
    }

    // Legend: rows between the title and the axes, right-aligned, so it hides no data.
    for (row, range) in legend.iter().enumerate() {
        let series = &chart.series[range.clone()];
        let mut x = right - series.iter().map(|s| entry(&s.label)).sum::<i64>();
        let y = title_height + 10 + row as i64 * (glyph() + 10);
        for (s, one) in range.clone().zip(series) {
            let colour = SERIES_COLOURS[s % SERIES_COLOURS.len()];
            for dy in glyph() / 2 - 1..glyph() / 2 + 1 {
                canvas.line((x, y + dy), (x + 16, y + dy), colour);
            }
            canvas.text((x + 20, y), &one.label, INK, text::LABEL, false);
            x += entry(&one.label);
        }
    }
}

/// The legend's entries (of `widths`, in pixels) split into rows no wider than `available`,
/// in order; an entry wider than that gets a row of its own.
fn legend_rows(widths: &[i64], available: i64) -> Vec<std::ops::Range<usize>> {
    let mut rows = Vec::new();
    let (mut start, mut used) = (0, 0);
    for (i, &width) in widths.iter().enumerate() {
        if i > start && used + width > available {
            rows.push(start..i);
            (start, used) = (i, 0);
        }
        used += width;
    }
    if start < widths.len() {
        rows.push(start..widths.len());
    }
    rows
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_legend_wraps_into_rows_that_fit() {
        let one_row = legend_rows(&[100, 100, 100], 400);
        assert!(one_row.len() == 1 && one_row[0] == (0..3), "{one_row:?}");
        assert_eq!(legend_rows(&[200, 150, 100, 300], 400), [0..2, 2..4]);
        assert_eq!(legend_rows(&[200, 150, 100, 301], 400), [0..2, 2..3, 3..4]);
        assert_eq!(legend_rows(&[500, 50], 400), [0..1, 1..2]);
        assert!(legend_rows(&[], 400).is_empty());
    }

    #[test]
    fn ticks_are_round_numbers_inside_the_range() {
        assert_eq!(
            linear_ticks(0.0, 119.0, 8, true),
            [0.0, 20.0, 40.0, 60.0, 80.0, 100.0]
        );
        assert_eq!(linear_ticks(27.3, 31.9, 6, false), [28.0, 29.0, 30.0, 31.0]);
        assert_eq!(linear_ticks(0.0, 3.0, 8, true), [0.0, 1.0, 2.0, 3.0]);
        assert_eq!(tick_label(0.2 * 3.0, false), "0.6");
        assert_eq!(tick_label(0.25, false), "0.25");
        assert_eq!(tick_label(120.0, false), "120");
        assert_eq!(tick_label(-3.0, true), "1e-3");
    }

    #[test]
    fn a_chart_has_ink_for_its_axes_text_and_each_series() {
        let chart = Chart {
            title: "held-out view".into(),
            x_label: "frame".into(),
            y_label: "PSNR (dB)".into(),
            log_y: false,
            series: vec![
                Series {
                    label: "sequential".into(),
                    points: (0..50)
                        .map(|t| (t as f64, 30.0 + (t as f64 / 7.0).sin()))
                        .collect(),
                },
                Series {
                    label: "alone".into(),
                    points: vec![(0.0, 29.0), (25.0, f64::NAN), (49.0, 28.0)],
                },
            ],
            marks: vec![10.0, 20.0],
        };
        let picture = draw(&chart, 400, 240);
        let count = |colour: [u8; 3]| picture.pixels.chunks(3).filter(|p| *p == colour).count();
        assert!(count(INK) > 500, "axes, ticks and text are drawn");
        assert!(count(SERIES_COLOURS[0]) > 100, "the first series is drawn");
        assert!(
            count(SERIES_COLOURS[1]) > 10,
            "the second series and its legend"
        );
        assert!(count(MARK) > 100, "the marks are drawn");
    }

    /// The SVG has the raster's layout: well-formed XML of the given size, the title as text,
    /// a line per grid line, tick and axis, and a dot per marked point.
    #[test]
    fn the_svg_is_well_formed_and_carries_the_chart() {
        let chart = Chart {
            title: "held-out view <dB> & frames".into(),
            x_label: "frame".into(),
            y_label: "PSNR (dB)".into(),
            log_y: false,
            series: vec![Series {
                label: "sequential".into(),
                points: (0..10).map(|t| (t as f64, 30.0 + t as f64)).collect(),
            }],
            marks: Vec::new(),
        };
        let text = svg(&chart, 400, 240);
        let doc = roxmltree::Document::parse(&text).expect("well-formed SVG");
        let root = doc.root_element();
        assert_eq!(root.tag_name().name(), "svg");
        assert_eq!(root.attribute("width"), Some("400"));
        let texts: Vec<&str> = root
            .descendants()
            .filter(|n| n.has_tag_name("text"))
            .filter_map(|n| n.text())
            .collect();
        assert!(texts.contains(&"held-out view <dB> & frames"), "{texts:?}");
        assert!(texts.contains(&"PSNR (dB)") && texts.contains(&"sequential"));
        let count = |tag: &str| root.descendants().filter(|n| n.has_tag_name(tag)).count();
        assert!(count("line") > 20, "{}", count("line"));
        // Ten marked points and the legend's swatch lines.
        assert!(count("rect") >= 11, "{}", count("rect"));
    }
}
