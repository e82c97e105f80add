//! Small PNG charts without a font dependency: line plots (loss curves) and labelled scatter
//! plots (the accuracy-vs-time Pareto plot).
//!
//! Text is drawn with a built-in 5×7 bitmap font (upper-case letters, digits and a few symbols;
//! lower-case is shown in upper case), so charts render identically everywhere and need no
//! system fonts. Axes are linear or log10; ticks are "nice" numbers (1, 2, 5 × 10ᵏ).

use std::path::Path;

/// 5×7 glyphs: each row is 5 bits, most significant bit on the left.
fn glyph(c: char) -> [u8; 7] {
    match c.to_ascii_uppercase() {
        '0' => [0x0E, 0x11, 0x13, 0x15, 0x19, 0x11, 0x0E],
        '1' => [0x04, 0x0C, 0x04, 0x04, 0x04, 0x04, 0x0E],
        '2' => [0x0E, 0x11, 0x01, 0x02, 0x04, 0x08, 0x1F],
        '3' => [0x1F, 0x02, 0x04, 0x02, 0x01, 0x11, 0x0E],
        '4' => [0x02, 0x06, 0x0A, 0x12, 0x1F, 0x02, 0x02],
        '5' => [0x1F, 0x10, 0x1E, 0x01, 0x01, 0x11, 0x0E],
        '6' => [0x06, 0x08, 0x10, 0x1E, 0x11, 0x11, 0x0E],
        '7' => [0x1F, 0x01, 0x02, 0x04, 0x08, 0x08, 0x08],
        '8' => [0x0E, 0x11, 0x11, 0x0E, 0x11, 0x11, 0x0E],
        '9' => [0x0E, 0x11, 0x11, 0x0F, 0x01, 0x02, 0x0C],
        'A' => [0x0E, 0x11, 0x11, 0x1F, 0x11, 0x11, 0x11],
        'B' => [0x1E, 0x11, 0x11, 0x1E, 0x11, 0x11, 0x1E],
        'C' => [0x0E, 0x11, 0x10, 0x10, 0x10, 0x11, 0x0E],
        'D' => [0x1C, 0x12, 0x11, 0x11, 0x11, 0x12, 0x1C],
        'E' => [0x1F, 0x10, 0x10, 0x1E, 0x10, 0x10, 0x1F],
        'F' => [0x1F, 0x10, 0x10, 0x1E, 0x10, 0x10, 0x10],
        'G' => [0x0E, 0x11, 0x10, 0x17, 0x11, 0x11, 0x0F],
        'H' => [0x11, 0x11, 0x11, 0x1F, 0x11, 0x11, 0x11],
        'I' => [0x0E, 0x04, 0x04, 0x04, 0x04, 0x04, 0x0E],
        'J' => [0x07, 0x02, 0x02, 0x02, 0x02, 0x12, 0x0C],
        'K' => [0x11, 0x12, 0x14, 0x18, 0x14, 0x12, 0x11],
        'L' => [0x10, 0x10, 0x10, 0x10, 0x10, 0x10, 0x1F],
        'M' => [0x11, 0x1B, 0x15, 0x15, 0x11, 0x11, 0x11],
        'N' => [0x11, 0x11, 0x19, 0x15, 0x13, 0x11, 0x11],
        'O' => [0x0E, 0x11, 0x11, 0x11, 0x11, 0x11, 0x0E],
        'P' => [0x1E, 0x11, 0x11, 0x1E, 0x10, 0x10, 0x10],
        'Q' => [0x0E, 0x11, 0x11, 0x11, 0x15, 0x12, 0x0D],
        'R' => [0x1E, 0x11, 0x11, 0x1E, 0x14, 0x12, 0x11],
        'S' => [0x0F, 0x10, 0x10, 0x0E, 0x01, 0x01, 0x1E],
        'T' => [0x1F, 0x04, 0x04, 0x04, 0x04, 0x04, 0x04],
        'U' => [0x11, 0x11, 0x11, 0x11, 0x11, 0x11, 0x0E],
        'V' => [0x11, 0x11, 0x11, 0x11, 0x11, 0x0A, 0x04],
        'W' => [0x11, 0x11, 0x11, 0x15, 0x15, 0x15, 0x0A],
        'X' => [0x11, 0x11, 0x0A, 0x04, 0x0A, 0x11, 0x11],
        'Y' => [0x11, 0x11, 0x11, 0x0A, 0x04, 0x04, 0x04],
        'Z' => [0x1F, 0x01, 0x02, 0x04, 0x08, 0x10, 0x1F],
        '.' => [0x00, 0x00, 0x00, 0x00, 0x00, 0x0C, 0x0C],
        ',' => [0x00, 0x00, 0x00, 0x00, 0x0C, 0x04, 0x08],
        '-' => [0x00, 0x00, 0x00, 0x1F, 0x00, 0x00, 0x00],
        '+' => [0x00, 0x04, 0x04, 0x1F, 0x04, 0x04, 0x00],
        ':' => [0x00, 0x0C, 0x0C, 0x00, 0x0C, 0x0C, 0x00],
        '=' => [0x00, 0x00, 0x1F, 0x00, 0x1F, 0x00, 0x00],
        '(' => [0x02, 0x04, 0x08, 0x08, 0x08, 0x04, 0x02],
        ')' => [0x08, 0x04, 0x02, 0x02, 0x02, 0x04, 0x08],
        '/' => [0x00, 0x01, 0x02, 0x04, 0x08, 0x10, 0x00],
        '%' => [0x18, 0x19, 0x02, 0x04, 0x08, 0x13, 0x03],
        '_' => [0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x1F],
        '*' => [0x00, 0x04, 0x15, 0x0E, 0x15, 0x04, 0x00],
        '[' => [0x0E, 0x08, 0x08, 0x08, 0x08, 0x08, 0x0E],
        ']' => [0x0E, 0x02, 0x02, 0x02, 0x02, 0x02, 0x0E],
        '|' => [0x04, 0x04, 0x04, 0x04, 0x04, 0x04, 0x04],
        '<' => [0x02, 0x04, 0x08, 0x10, 0x08, 0x04, 0x02],
        '>' => [0x08, 0x04, 0x02, 0x01, 0x02, 0x04, 0x08],
        ' ' => [0; 7],
        _ => [0x1F, 0x11, 0x11, 0x11, 0x11, 0x11, 0x1F],
    }
}

/// An RGB8 canvas.
#[derive(Debug, Clone)]
pub struct Canvas {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// Row-major RGB8.
    pub pixels: Vec<u8>,
}

impl Canvas {
    /// A white canvas.
    pub fn new(width: u32, height: u32) -> Self {
        Self {
            width,
            height,
            pixels: vec![255; (width * height * 3) as usize],
        }
    }

    /// Sets one pixel (ignored outside the canvas).
    pub fn put(&mut self, x: i64, y: i64, rgb: [u8; 3]) {
        if x < 0 || y < 0 || x >= self.width as i64 || y >= self.height as i64 {
            return;
        }
        let i = ((y as u32 * self.width + x as u32) * 3) as usize;
        self.pixels[i..i + 3].copy_from_slice(&rgb);
    }

    /// A line (Bresenham), `thickness` pixels wide.
    pub fn line(&mut self, a: (f64, f64), b: (f64, f64), rgb: [u8; 3], thickness: i64) {
        if !(a.0.is_finite() && a.1.is_finite() && b.0.is_finite() && b.1.is_finite()) {
            return;
        }
        let (mut x0, mut y0) = (a.0.round() as i64, a.1.round() as i64);
        let (x1, y1) = (b.0.round() as i64, b.1.round() as i64);
        let (dx, dy) = ((x1 - x0).abs(), -(y1 - y0).abs());
        let (sx, sy) = (if x0 < x1 { 1 } else { -1 }, if y0 < y1 { 1 } else { -1 });
        let mut err = dx + dy;
        let r = thickness / 2;
        for _ in 0..=(dx - dy).min(100_000) {
            for ox in -r..=r {
                for oy in -r..=r {
                    self.put(x0 + ox, y0 + oy, rgb);
                }
            }
            if x0 == x1 && y0 == y1 {
                break;
            }
            let e2 = 2 * err;
            if e2 >= dy {
                err += dy;
                x0 += sx;
            }
            if e2 <= dx {
                err += dx;
                y0 += sy;
            }
        }
    }

    /// A filled square marker of side `2r+1`.
    pub fn marker(&mut self, at: (f64, f64), r: i64, rgb: [u8; 3]) {
        let (x, y) = (at.0.round() as i64, at.1.round() as i64);
        for ox in -r..=r {
            for oy in -r..=r {
                self.put(x + ox, y + oy, rgb);
            }
        }
    }

    /// Text with its top-left corner at `(x, y)`, glyphs scaled by `scale`.
    pub fn text(&mut self, x: i64, y: i64, s: &str, rgb: [u8; 3], scale: i64) {
        for (k, c) in s.chars().enumerate() {
            let g = glyph(c);
            let gx = x + k as i64 * 6 * scale;
            for (row, bits) in g.iter().enumerate() {
                for col in 0..5 {
                    if bits & (0x10 >> col) != 0 {
                        for sx in 0..scale {
                            for sy in 0..scale {
                                self.put(gx + col * scale + sx, y + row as i64 * scale + sy, rgb);
                            }
                        }
                    }
                }
            }
        }
    }

    /// Width in pixels of `s` at `scale`.
    pub fn text_width(s: &str, scale: i64) -> i64 {
        s.chars().count() as i64 * 6 * scale
    }

    /// Writes the canvas as a PNG.
    pub fn save(&self, path: &Path) -> image::ImageResult<()> {
        lifegom_render::atomic_file::write_png(
            path,
            &self.pixels,
            self.width,
            self.height,
            image::ExtendedColorType::Rgb8,
        )
    }
}

/// Axis scale.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Scale {
    /// Linear.
    Linear,
    /// Base-10 logarithmic (non-positive values are dropped).
    Log10,
}

impl Scale {
    fn map(self, v: f64) -> Option<f64> {
        match self {
            Scale::Linear => v.is_finite().then_some(v),
            Scale::Log10 => (v > 0.0 && v.is_finite()).then(|| v.log10()),
        }
    }
}

/// One data series.
#[derive(Debug, Clone)]
pub struct Series {
    /// Legend label.
    pub name: String,
    /// `(x, y)` points.
    pub points: Vec<(f64, f64)>,
    /// Per-point labels (scatter plots), may be empty.
    pub labels: Vec<String>,
    /// Colour.
    pub color: [u8; 3],
}

/// How a series is drawn.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Style {
    /// Connected lines.
    Lines,
    /// Markers with their labels.
    Markers,
}

/// A chart with one x and one y axis.
#[derive(Debug, Clone)]
pub struct Chart {
    /// Title (top).
    pub title: String,
    /// X-axis label.
    pub x_label: String,
    /// Y-axis label.
    pub y_label: String,
    /// X scale.
    pub x_scale: Scale,
    /// Y scale.
    pub y_scale: Scale,
    /// The series.
    pub series: Vec<Series>,
    /// Drawing style.
    pub style: Style,
}

/// A qualitative palette (Tableau 10).
pub const PALETTE: [[u8; 3]; 6] = [
    [31, 119, 180],
    [255, 127, 14],
    [44, 160, 44],
    [214, 39, 40],
    [148, 103, 189],
    [140, 86, 75],
];

/// "Nice" tick positions covering `[lo, hi]` (about `n` of them).
pub fn nice_ticks(lo: f64, hi: f64, n: usize) -> Vec<f64> {
    if !(lo.is_finite() && hi.is_finite()) || hi <= lo {
        return vec![lo];
    }
    let raw = (hi - lo) / n.max(1) as f64;
    let mag = 10f64.powf(raw.log10().floor());
    let step = [1.0, 2.0, 5.0, 10.0]
        .iter()
        .map(|m| m * mag)
        .find(|s| *s >= raw)
        .unwrap_or(10.0 * mag);
    let first = (lo / step).ceil() * step;
    (0..)
        .map(|i| first + i as f64 * step)
        .take_while(|v| *v <= hi + step * 1e-9)
        .take(50)
        .collect()
}

fn fmt_tick(v: f64) -> String {
    let a = v.abs();
    if a == 0.0 {
        "0".into()
    } else if !(1e-3..1e5).contains(&a) {
        format!("{v:.0e}")
    } else if a >= 100.0 {
        format!("{v:.0}")
    } else if a >= 1.0 {
        format!("{v:.1}")
    } else {
        format!("{v:.3}")
    }
}

impl Chart {
    /// Draws the chart on a `width × height` canvas.
    pub fn render(&self, width: u32, height: u32) -> Canvas {
        let mut c = Canvas::new(width, height);
        let (left, right, top, bottom) = (78i64, 20i64, 34i64, 48i64);
        let (pw, ph) = (width as i64 - left - right, height as i64 - top - bottom);
        let black = [0, 0, 0];
        let grey = [225, 225, 225];
        c.text(left, 10, &self.title, black, 2);

        let mapped: Vec<Vec<(f64, f64, usize)>> = self
            .series
            .iter()
            .map(|s| {
                s.points
                    .iter()
                    .enumerate()
                    .filter_map(|(i, (x, y))| {
                        Some((self.x_scale.map(*x)?, self.y_scale.map(*y)?, i))
                    })
                    .collect()
            })
            .collect();
        let all: Vec<(f64, f64)> = mapped.iter().flatten().map(|(x, y, _)| (*x, *y)).collect();
        if all.is_empty() || pw < 10 || ph < 10 {
            c.text(left, top + 20, "NO DATA", black, 2);
            return c;
        }
        let (mut x0, mut x1) = all
            .iter()
            .fold((f64::MAX, f64::MIN), |(a, b), p| (a.min(p.0), b.max(p.0)));
        let (mut y0, mut y1) = all
            .iter()
            .fold((f64::MAX, f64::MIN), |(a, b), p| (a.min(p.1), b.max(p.1)));
        for (lo, hi) in [(&mut x0, &mut x1), (&mut y0, &mut y1)] {
            let pad = ((*hi - *lo) * 0.06).max(1e-9 + lo.abs() * 0.02);
            *lo -= pad;
            *hi += pad;
        }
        // Headroom for the legend (top right) so it never covers a point.
        let legend = (8 + 12 * self.series.len() as i64) as f64 / ph as f64;
        let legend = legend.min(0.5);
        y1 += (y1 - y0) * legend / (1.0 - legend);
        let px = |x: f64| left as f64 + (x - x0) / (x1 - x0) * pw as f64;
        let py = |y: f64| (top + ph) as f64 - (y - y0) / (y1 - y0) * ph as f64;

        // Grid and tick labels.
        for t in nice_ticks(x0, x1, 6) {
            let x = px(t);
            c.line((x, top as f64), (x, (top + ph) as f64), grey, 1);
            let label = match self.x_scale {
                Scale::Linear => fmt_tick(t),
                Scale::Log10 => fmt_tick(10f64.powf(t)),
            };
            c.text(
                x as i64 - Canvas::text_width(&label, 1) / 2,
                top + ph + 6,
                &label,
                black,
                1,
            );
        }
        for t in nice_ticks(y0, y1, 6) {
            let y = py(t);
            c.line((left as f64, y), ((left + pw) as f64, y), grey, 1);
            let label = match self.y_scale {
                Scale::Linear => fmt_tick(t),
                Scale::Log10 => fmt_tick(10f64.powf(t)),
            };
            c.text(
                left - 6 - Canvas::text_width(&label, 1),
                y as i64 - 3,
                &label,
                black,
                1,
            );
        }
        c.line(
            (left as f64, top as f64),
            (left as f64, (top + ph) as f64),
            black,
            1,
        );
        c.line(
            (left as f64, (top + ph) as f64),
            ((left + pw) as f64, (top + ph) as f64),
            black,
            1,
        );
        let xl = match self.x_scale {
            Scale::Linear => self.x_label.clone(),
            Scale::Log10 => format!("{} (LOG)", self.x_label),
        };
        c.text(
            left + pw / 2 - Canvas::text_width(&xl, 1) / 2,
            top + ph + 22,
            &xl,
            black,
            1,
        );
        let yl = match self.y_scale {
            Scale::Linear => self.y_label.clone(),
            Scale::Log10 => format!("{} (LOG)", self.y_label),
        };
        c.text(4, top - 14, &yl, black, 1);

        for (s, pts) in self.series.iter().zip(&mapped) {
            match self.style {
                Style::Lines => {
                    for w in pts.windows(2) {
                        c.line(
                            (px(w[0].0), py(w[0].1)),
                            (px(w[1].0), py(w[1].1)),
                            s.color,
                            2,
                        );
                    }
                    if pts.len() == 1 {
                        c.marker((px(pts[0].0), py(pts[0].1)), 2, s.color);
                    }
                }
                Style::Markers => {
                    for (x, y, i) in pts {
                        c.marker((px(*x), py(*y)), 3, s.color);
                        if let Some(label) = s.labels.get(*i) {
                            c.text(px(*x) as i64 + 6, py(*y) as i64 - 9, label, s.color, 1);
                        }
                    }
                }
            }
        }
        // Legend, top right inside the plot.
        for (k, s) in self.series.iter().enumerate() {
            let y = top + 6 + k as i64 * 12;
            let x = left + pw - 8 - Canvas::text_width(&s.name, 1) - 16;
            c.marker(((x + 4) as f64, (y + 3) as f64), 3, s.color);
            c.text(x + 12, y, &s.name, black, 1);
        }
        c
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn nice_ticks_are_round_and_cover_the_range() {
        let t = nice_ticks(0.0, 1.0, 5);
        let want = [0.0, 0.2, 0.4, 0.6, 0.8, 1.0];
        assert_eq!(t.len(), want.len());
        assert!(
            t.iter().zip(want).all(|(a, b)| (a - b).abs() < 1e-12),
            "{t:?}"
        );
        // (87 − 13) / 6 ≈ 12.3 rounds up to the nice step 20.
        assert_eq!(nice_ticks(13.0, 87.0, 6), vec![20.0, 40.0, 60.0, 80.0]);
        assert_eq!(nice_ticks(1.0, 1.0, 5), vec![1.0]);
    }

    #[test]
    fn chart_draws_series_in_their_colour_and_survives_bad_values() {
        let chart = Chart {
            title: "loss".into(),
            x_label: "step".into(),
            y_label: "loss".into(),
            x_scale: Scale::Linear,
            y_scale: Scale::Log10,
            series: vec![Series {
                name: "total".into(),
                points: vec![
                    (0.0, 1.0),
                    (1.0, 0.5),
                    (2.0, f64::NAN),
                    (3.0, -1.0),
                    (4.0, 0.1),
                ],
                labels: vec![],
                color: PALETTE[3],
            }],
            style: Style::Lines,
        };
        let canvas = chart.render(320, 200);
        assert_eq!(canvas.pixels.len(), 320 * 200 * 3);
        let red = canvas.pixels.chunks(3).filter(|p| p == &PALETTE[3]).count();
        assert!(red > 100, "{red} pixels of the series colour");
        let empty = Chart {
            series: vec![],
            ..chart
        };
        let canvas = empty.render(100, 80);
        assert!(canvas.pixels.contains(&0), "says NO DATA");
    }

    #[test]
    fn every_glyph_used_in_reports_is_defined() {
        for c in "0123456789ABCDEFGHIJKLMNOPQRSTUVWXYZ.,-+:=()/%_*[]|<> ".chars() {
            let g = glyph(c);
            if c != ' ' {
                assert_ne!(g, [0x1F, 0x11, 0x11, 0x11, 0x11, 0x11, 0x1F], "{c}");
                assert!(g.iter().any(|r| *r != 0), "{c}");
            }
        }
    }
}
