//! Charts for the reports and the training curves: line plots (loss and validation curves) and
//! labelled scatter plots (the accuracy-vs-time Pareto plot), one chart or several side by side,
//! saved as PNG or SVG.
//!
//! Drawing is done by `plotters`. PNGs are drawn into an RGB buffer and encoded with `image`
//! (plotters' own encoder is not built), then written atomically like every other picture of the
//! workspace. Text uses DejaVu Sans embedded in the binary (`assets/fonts`, licence alongside), so
//! a PNG looks the same on every machine and no system font is needed; an SVG names the family
//! `sans-serif` and the viewer picks its own.
//!
//! Axes are linear or log10, with ticks at "nice" numbers (1, 2, 5 × 10ᵏ). Values a scale cannot
//! show (NaN, ±inf, and non-positive values on a log axis) are skipped; a line series is broken
//! where they fall rather than joined across the gap.

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use plotters::coord::Shift;
use plotters::coord::ranged1d::{DefaultFormatting, KeyPointHint, Ranged};
use plotters::prelude::*;
use plotters::style::text_anchor::{HPos, Pos, VPos};
use plotters::style::{FontStyle, FontTransform, register_font};

/// DejaVu Sans (Bitstream Vera licence, `assets/fonts/LICENSE-DejaVu.txt`).
static DEJAVU_SANS: &[u8] = include_bytes!("../../assets/fonts/DejaVuSans.ttf");

/// The family every text style asks for; the embedded font is registered under it.
const FAMILY: &str = "sans-serif";

/// Registers the embedded font with plotters' font table, once per process. A font that cannot
/// be parsed is reported by every draw instead of panicking.
fn ensure_font() -> Result<(), String> {
    static REGISTERED: OnceLock<Result<(), String>> = OnceLock::new();
    REGISTERED
        .get_or_init(|| {
            register_font(FAMILY, FontStyle::Normal, DEJAVU_SANS)
                .map_err(|_| "the embedded DejaVu Sans font could not be parsed".to_owned())
        })
        .clone()
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
    /// The value in axis space (log10 for a log axis), or `None` when the axis cannot show it.
    fn map(self, v: f64) -> Option<f64> {
        match self {
            Scale::Linear => v.is_finite().then_some(v),
            Scale::Log10 => (v > 0.0 && v.is_finite()).then(|| v.log10()),
        }
    }
}

/// One data series.
///
/// `error_bars` and `scatter` default to empty, so a series can be written as
/// `Series { name, points, labels, color, ..Default::default() }`.
#[derive(Debug, Clone, Default)]
pub struct Series {
    /// Legend label (a series with an empty name gets no legend entry).
    pub name: String,
    /// `(x, y)` points.
    pub points: Vec<(f64, f64)>,
    /// Per-point labels, drawn next to the markers ([`Style::Markers`] and
    /// [`Style::LinesAndMarkers`]); may be empty or shorter than `points`, and empty labels are
    /// not drawn.
    pub labels: Vec<String>,
    /// Colour.
    pub color: [u8; 3],
    /// Per-point vertical error bars as absolute `(low, high)` y values (a spread across views
    /// or seeds, e.g. mean ± std or min..max); may be empty or shorter than `points`.
    pub error_bars: Vec<(f64, f64)>,
    /// Raw observations drawn as small faint dots behind the series (each view's value behind
    /// its mean, say); independent of `points`.
    pub scatter: Vec<(f64, f64)>,
}

/// How a chart's series are drawn.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Style {
    /// Connected lines (a series of one point is drawn as a marker).
    Lines,
    /// Markers with their labels.
    Markers,
    /// Connected lines with a labelled marker at every point (curves with few points).
    LinesAndMarkers,
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

/// A chart that could not be drawn or written.
#[derive(Debug, Clone)]
pub struct PlotError {
    /// The file being written; empty when drawing in memory.
    pub path: PathBuf,
    /// What went wrong.
    pub reason: String,
}

impl std::fmt::Display for PlotError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        if self.path.as_os_str().is_empty() {
            write!(f, "drawing a chart: {}", self.reason)
        } else {
            write!(f, "writing {}: {}", self.path.display(), self.reason)
        }
    }
}

impl std::error::Error for PlotError {}

impl PlotError {
    fn drawing(reason: String) -> Self {
        Self {
            path: PathBuf::new(),
            reason,
        }
    }

    /// The same error, naming `path`.
    fn at(self, path: &Path) -> Self {
        Self {
            path: path.to_path_buf(),
            reason: self.reason,
        }
    }
}

/// One or more charts laid side by side on a `width × height` picture, ready to be saved.
#[derive(Debug, Clone)]
pub struct Figure {
    /// The panels, left to right, each given an equal share of the width.
    pub panels: Vec<Chart>,
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
}

impl Chart {
    /// This chart alone as a `width × height` figure.
    pub fn render(&self, width: u32, height: u32) -> Figure {
        Figure {
            panels: vec![self.clone()],
            width,
            height,
        }
    }
}

/// `charts` side by side, left to right, on one `width × height` figure.
pub fn render_panels(charts: &[Chart], width: u32, height: u32) -> Figure {
    Figure {
        panels: charts.to_vec(),
        width,
        height,
    }
}

impl Figure {
    /// Writes the figure to `path`: SVG when the extension is `svg` (any case), PNG otherwise.
    pub fn save(&self, path: &Path) -> Result<(), PlotError> {
        let svg = path
            .extension()
            .is_some_and(|e| e.eq_ignore_ascii_case("svg"));
        if svg {
            self.save_svg(path)
        } else {
            self.save_png(path)
        }
    }

    /// Writes the figure to `png` as a PNG and next to it, with the extension `svg`, as an SVG.
    pub fn save_png_and_svg(&self, png: &Path) -> Result<(), PlotError> {
        self.save_png(png)?;
        self.save_svg(&png.with_extension("svg"))
    }

    /// Writes the figure as a PNG (atomically: a reader never sees half a file).
    pub fn save_png(&self, path: &Path) -> Result<(), PlotError> {
        let rgb = self.to_rgb().map_err(|e| e.at(path))?;
        lifegom_render::atomic_file::write_png(
            path,
            &rgb,
            self.width,
            self.height,
            image::ExtendedColorType::Rgb8,
        )
        .map_err(|e| PlotError::drawing(e.to_string()).at(path))
    }

    /// Writes the figure as an SVG (atomically).
    pub fn save_svg(&self, path: &Path) -> Result<(), PlotError> {
        let svg = self.to_svg().map_err(|e| e.at(path))?;
        lifegom_render::atomic_file::write_atomic(path, svg.as_bytes())
            .map_err(|e| PlotError::drawing(e.to_string()).at(path))
    }

    /// The figure as row-major RGB8 pixels, `width × height × 3` bytes.
    pub fn to_rgb(&self) -> Result<Vec<u8>, PlotError> {
        self.check_size()?;
        let mut rgb = vec![255u8; self.width as usize * self.height as usize * 3];
        {
            let root =
                BitMapBackend::with_buffer(&mut rgb, (self.width, self.height)).into_drawing_area();
            draw_figure(&root, &self.panels, true).map_err(PlotError::drawing)?;
            root.present()
                .map_err(|e| PlotError::drawing(e.to_string()))?;
        }
        Ok(rgb)
    }

    /// The figure as an SVG document.
    pub fn to_svg(&self) -> Result<String, PlotError> {
        self.check_size()?;
        let mut svg = String::new();
        {
            let root =
                SVGBackend::with_string(&mut svg, (self.width, self.height)).into_drawing_area();
            draw_figure(&root, &self.panels, false).map_err(PlotError::drawing)?;
            root.present()
                .map_err(|e| PlotError::drawing(e.to_string()))?;
        }
        Ok(svg)
    }

    fn check_size(&self) -> Result<(), PlotError> {
        // The backends index their buffers by these; zero would be an empty picture at best.
        if self.width == 0 || self.height == 0 {
            return Err(PlotError::drawing(format!(
                "a {}×{} picture has no pixels",
                self.width, self.height
            )));
        }
        Ok(())
    }
}

// ---------------------------------------------------------------------------------------------
// Layout constants, in pixels. Tuned by eye on 720×420 and 760×460 charts.

const TITLE_PX: i32 = 17;
const DESC_PX: i32 = 14;
const TICK_PX: i32 = 12;
const LEGEND_PX: i32 = 12;
const POINT_LABEL_PX: i32 = 11;
const MARGIN: i32 = 10;
/// The right margin is wider: the last x tick label is centred on the plot's right edge.
const MARGIN_RIGHT: i32 = 18;
/// Room below the plot for the x tick labels and the x-axis label.
const X_AREA: i32 = 44;
const MARKER_R: i32 = 4;
/// Inset of the legend box from the plot's corner.
const LEGEND_INSET: i32 = 8;
const LEGEND_ROW: i32 = 18;

type Drawn<T = ()> = Result<T, String>;

fn err(e: impl std::fmt::Display) -> String {
    e.to_string()
}

fn rgb(c: [u8; 3]) -> RGBColor {
    RGBColor(c[0], c[1], c[2])
}

/// A darker shade of `c`, so text in a light series colour (orange) stays readable on white.
fn text_color(c: [u8; 3]) -> RGBColor {
    let d = |v: u8| (f64::from(v) * 0.72) as u8;
    RGBColor(d(c[0]), d(c[1]), d(c[2]))
}

/// Horizontal metrics of the embedded font, read from its `cmap`, `hhea`, `hmtx` and `kern`
/// tables: the numbers ab_glyph itself uses.
///
/// They are needed because plotters 0.3.7's ab_glyph text drawing places each glyph's ink box
/// at the pen position, dropping the glyph's left side bearing: letters crowd and touch
/// ("T1" reads "Tl"). Bitmap text is therefore drawn one glyph at a time, each at its pen
/// position plus its side bearing, computed here.
struct FontMetrics {
    data: &'static [u8],
    /// Ascender − descender in font units: ab_glyph's pixel size is this height.
    height: f64,
    hmtx: usize,
    long_metrics: u16,
    /// The format-4 (Unicode BMP) `cmap` subtable.
    cmap: usize,
    /// Format-0 horizontal `kern` subtables: offset of the first pair, number of pairs.
    kern: Vec<(usize, usize)>,
}

fn be_u16(d: &[u8], at: usize) -> Option<u16> {
    Some(u16::from_be_bytes([*d.get(at)?, *d.get(at + 1)?]))
}

fn be_i16(d: &[u8], at: usize) -> Option<i16> {
    be_u16(d, at).map(|v| v as i16)
}

fn be_u32(d: &[u8], at: usize) -> Option<u32> {
    Some(u32::from_be_bytes([
        *d.get(at)?,
        *d.get(at + 1)?,
        *d.get(at + 2)?,
        *d.get(at + 3)?,
    ]))
}

impl FontMetrics {
    fn parse(data: &'static [u8]) -> Option<Self> {
        let table = |tag: &[u8; 4]| -> Option<usize> {
            (0..usize::from(be_u16(data, 4)?)).find_map(|i| {
                let rec = 12 + 16 * i;
                (data.get(rec..rec + 4)? == tag)
                    .then(|| be_u32(data, rec + 8).map(|o| o as usize))
                    .flatten()
            })
        };
        let hhea = table(b"hhea")?;
        let height = f64::from(be_i16(data, hhea + 4)?) - f64::from(be_i16(data, hhea + 6)?);
        let long_metrics = be_u16(data, hhea + 34)?;
        let hmtx = table(b"hmtx")?;
        let cmap = table(b"cmap")?;
        let cmap = (0..usize::from(be_u16(data, cmap + 2)?)).find_map(|i| {
            let rec = cmap + 4 + 8 * i;
            let (platform, encoding) = (be_u16(data, rec)?, be_u16(data, rec + 2)?);
            let sub = cmap + be_u32(data, rec + 4)? as usize;
            let unicode = platform == 0 || (platform == 3 && encoding == 1);
            (unicode && be_u16(data, sub)? == 4).then_some(sub)
        })?;
        let mut kern = Vec::new();
        if let Some(k) = table(b"kern")
            && be_u16(data, k) == Some(0)
        {
            let mut sub = k + 4;
            for _ in 0..be_u16(data, k + 2).unwrap_or(0) {
                let (Some(len), Some(coverage)) = (be_u16(data, sub + 2), be_u16(data, sub + 4))
                else {
                    break;
                };
                // Format 0, horizontal, neither minimum values nor cross-stream.
                if coverage >> 8 == 0 && coverage & 0x7 == 1 {
                    let pairs = usize::from(be_u16(data, sub + 6).unwrap_or(0));
                    kern.push((sub + 14, pairs));
                }
                sub += usize::from(len);
            }
        }
        (height > 0.0).then_some(Self {
            data,
            height,
            hmtx,
            long_metrics,
            cmap,
            kern,
        })
    }

    fn glyph(&self, c: char) -> u16 {
        self.lookup(c).unwrap_or(0)
    }

    fn lookup(&self, c: char) -> Option<u16> {
        let c = u16::try_from(u32::from(c)).ok()?;
        let (d, t) = (self.data, self.cmap);
        let segs = usize::from(be_u16(d, t + 6)? / 2);
        let ends = t + 14;
        let seg = (0..segs).find(|&i| be_u16(d, ends + 2 * i).is_some_and(|e| e >= c))?;
        let start = be_u16(d, ends + 2 * segs + 2 + 2 * seg)?;
        if start > c {
            return None;
        }
        let delta = be_u16(d, ends + 4 * segs + 2 + 2 * seg)?;
        let range_at = ends + 6 * segs + 2 + 2 * seg;
        let range = be_u16(d, range_at)?;
        if range == 0 {
            return Some(c.wrapping_add(delta));
        }
        let g = be_u16(
            d,
            range_at + usize::from(range) + 2 * usize::from(c - start),
        )?;
        (g != 0).then(|| g.wrapping_add(delta))
    }

    /// `(advance, left side bearing)` in font units.
    fn h_metrics(&self, g: u16) -> (f64, f64) {
        let n = self.long_metrics.max(1);
        let adv_at = self.hmtx + 4 * usize::from(g.min(n - 1));
        let lsb_at = if g < n {
            self.hmtx + 4 * usize::from(g) + 2
        } else {
            self.hmtx + 4 * usize::from(n) + 2 * usize::from(g - n)
        };
        (
            f64::from(be_u16(self.data, adv_at).unwrap_or(0)),
            f64::from(be_i16(self.data, lsb_at).unwrap_or(0)),
        )
    }

    fn kerning(&self, left: u16, right: u16) -> f64 {
        let key = (u32::from(left) << 16) | u32::from(right);
        for &(pairs, n) in &self.kern {
            let pair = |i: usize| be_u32(self.data, pairs + 6 * i);
            let (mut lo, mut hi) = (0, n);
            while lo < hi {
                let mid = (lo + hi) / 2;
                match pair(mid).map(|k| k.cmp(&key)) {
                    Some(std::cmp::Ordering::Less) => lo = mid + 1,
                    Some(std::cmp::Ordering::Greater) => hi = mid,
                    Some(std::cmp::Ordering::Equal) => {
                        return f64::from(be_i16(self.data, pairs + 6 * mid + 4).unwrap_or(0));
                    }
                    None => break,
                }
            }
        }
        0.0
    }

    /// Each glyph of `text` at `px` pixels: `(char, ink offset from the text's start)`, and the
    /// text's advance width.
    fn layout(&self, text: &str, px: f64) -> (Vec<(char, i32)>, f64) {
        let s = px / self.height;
        let mut pen = 0.0;
        let mut prev = None;
        let mut out = Vec::with_capacity(text.len());
        for c in text.chars() {
            let g = self.glyph(c);
            if let Some(p) = prev {
                pen += self.kerning(p, g) * s;
            }
            let (adv, lsb) = self.h_metrics(g);
            out.push((c, pen.round() as i32 + (lsb * s).floor() as i32));
            pen += adv * s;
            prev = Some(g);
        }
        (out, pen)
    }
}

fn font_metrics() -> Option<&'static FontMetrics> {
    static METRICS: OnceLock<Option<FontMetrics>> = OnceLock::new();
    METRICS
        .get_or_init(|| FontMetrics::parse(DEJAVU_SANS))
        .as_ref()
}

/// Where a text's anchor point is along it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Align {
    Start,
    Middle,
    End,
}

/// The extent of text above and below its baseline, as fractions of the pixel size (DejaVu's
/// ascenders and descenders at ab_glyph's scale), for boxes around labels.
const ASCENT: f64 = 0.68;
const DESCENT: f64 = 0.22;

/// Draws text on a panel, positioned by its baseline, the same way on both backends.
struct Painter<'a, DB: DrawingBackend> {
    area: &'a DrawingArea<DB, Shift>,
    /// Bitmap: draw glyph by glyph (see [`FontMetrics`]). SVG: whole strings, so the file holds
    /// searchable text and the viewer lays it out.
    glyph_by_glyph: bool,
}

impl<DB: DrawingBackend> Painter<'_, DB> {
    /// Advance width of `text` at `px` pixels.
    fn width(&self, text: &str, px: i32) -> Drawn<i32> {
        if let Some(m) = font_metrics() {
            return Ok(m.layout(text, f64::from(px)).1.ceil() as i32);
        }
        let (w, _) = self
            .area
            .estimate_text_size(text, &TextStyle::from((FAMILY, px)))
            .map_err(err)?;
        Ok(w as i32)
    }

    /// The box `text` covers when drawn by [`Painter::text`] (horizontal text only).
    fn text_box(&self, text: &str, px: i32, at: (i32, i32), align: Align) -> Drawn<Rect> {
        let w = self.width(text, px)?;
        let x0 = match align {
            Align::Start => at.0,
            Align::Middle => at.0 - w / 2,
            Align::End => at.0 - w,
        };
        let px = f64::from(px);
        Ok(Rect {
            x0,
            y0: at.1 - (ASCENT * px).ceil() as i32,
            x1: x0 + w,
            y1: at.1 + (DESCENT * px).ceil() as i32,
        })
    }

    /// Draws `text` at `px` pixels with its baseline through `at`, `align`ed there; `up` turns it
    /// to run bottom to top (a y-axis label), its baseline then being the vertical through `at`.
    fn text(
        &self,
        text: &str,
        px: i32,
        color: &RGBColor,
        at: (i32, i32),
        align: Align,
        up: bool,
    ) -> Drawn {
        if text.is_empty() {
            return Ok(());
        }
        let mut style = (FAMILY, px).into_font().color(color);
        if up {
            style = style.transform(FontTransform::Rotate270);
        }
        // Turns a text-space offset (along the text, down from it) into a pixel offset.
        let turn = |along: i32, down: i32| if up { (down, -along) } else { (along, down) };
        let metrics = font_metrics().filter(|_| self.glyph_by_glyph);
        let Some(m) = metrics else {
            let h = match align {
                Align::Start => HPos::Left,
                Align::Middle => HPos::Center,
                Align::End => HPos::Right,
            };
            // Plotters' SVG text hangs from its anchor with `dy = 0.76em` at `px / 1.24` per em;
            // ab_glyph's (the fallback) puts the baseline half the pixel size down.
            let drop = if self.glyph_by_glyph {
                f64::from(px) / 2.0
            } else {
                0.76 * f64::from(px) / 1.24
            };
            let (dx, dy) = turn(0, -(drop.round() as i32));
            let style = style.pos(Pos::new(h, VPos::Top));
            return self
                .area
                .draw_text(text, &style, (at.0 + dx, at.1 + dy))
                .map_err(err);
        };
        let (glyphs, width) = m.layout(text, f64::from(px));
        let start = match align {
            Align::Start => 0,
            Align::Middle => -(width / 2.0).round() as i32,
            Align::End => -width.round() as i32,
        };
        let style = style.pos(Pos::new(HPos::Left, VPos::Top));
        let mut buf = [0u8; 4];
        for (c, ink) in glyphs {
            if c.is_whitespace() {
                continue;
            }
            // ab_glyph puts the baseline half the pixel size below the position it is given.
            let (dx, dy) = turn(start + ink, -px / 2);
            self.area
                .draw_text(c.encode_utf8(&mut buf), &style, (at.0 + dx, at.1 + dy))
                .map_err(err)?;
        }
        Ok(())
    }
}

fn draw_figure<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    panels: &[Chart],
    glyph_by_glyph: bool,
) -> Drawn {
    ensure_font()?;
    root.fill(&WHITE).map_err(err)?;
    if panels.is_empty() {
        return Ok(());
    }
    for (area, chart) in root.split_evenly((1, panels.len())).iter().zip(panels) {
        let painter = Painter {
            area,
            glyph_by_glyph,
        };
        draw_chart(&painter, chart)?;
    }
    Ok(())
}

/// A series' points in axis space, with their index in `Series::points`.
struct Mapped {
    /// Runs of consecutive drawable points; a line is broken between runs.
    runs: Vec<Vec<(f64, f64, usize)>>,
    /// Error bars in axis space, `None` for an end the y axis cannot show.
    bars: Vec<(f64, Option<f64>, Option<f64>)>,
    scatter: Vec<(f64, f64)>,
}

impl Mapped {
    fn new(s: &Series, xs: Scale, ys: Scale) -> Self {
        let mut runs = vec![Vec::new()];
        let mut bars = Vec::new();
        for (i, &(x, y)) in s.points.iter().enumerate() {
            let (Some(mx), Some(my)) = (xs.map(x), ys.map(y)) else {
                if runs.last().is_some_and(|r| !r.is_empty()) {
                    runs.push(Vec::new());
                }
                continue;
            };
            if let Some(r) = runs.last_mut() {
                r.push((mx, my, i));
            }
            if let Some(&(lo, hi)) = s.error_bars.get(i) {
                bars.push((mx, ys.map(lo), ys.map(hi)));
            }
        }
        runs.retain(|r| !r.is_empty());
        let scatter = s
            .scatter
            .iter()
            .filter_map(|&(x, y)| Some((xs.map(x)?, ys.map(y)?)))
            .collect();
        Self {
            runs,
            bars,
            scatter,
        }
    }

    fn points(&self) -> impl Iterator<Item = &(f64, f64, usize)> {
        self.runs.iter().flatten()
    }

    fn is_empty(&self) -> bool {
        self.runs.is_empty() && self.scatter.is_empty()
    }
}

/// `[lo, hi]` of `values`, or `None` when there are none.
fn extent(values: impl Iterator<Item = f64>) -> Option<(f64, f64)> {
    values.fold(None, |acc, v| match acc {
        None => Some((v, v)),
        Some((lo, hi)) => Some((lo.min(v), hi.max(v))),
    })
}

/// `[lo, hi]` widened by `frac` of its span on each side; a single value gets a fixed margin so
/// the axis still has a span to divide.
fn padded((lo, hi): (f64, f64), frac: f64, scale: Scale) -> (f64, f64) {
    let span = hi - lo;
    let pad = if span > 1e-12 * lo.abs().max(hi.abs()).max(1e-300) {
        span * frac
    } else {
        match scale {
            // Log axes are in decades: a quarter-decade either side.
            Scale::Log10 => 0.25,
            Scale::Linear if lo == 0.0 => 1.0,
            Scale::Linear => lo.abs() * 0.05,
        }
    };
    (lo - pad, hi + pad)
}

/// A tick: its position in axis space and its label.
#[derive(Debug, Clone)]
struct Tick {
    at: f64,
    label: String,
}

/// "Nice" tick positions covering `[lo, hi]` (about `n` of them).
fn nice_ticks(lo: f64, hi: f64, n: usize) -> Vec<f64> {
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
    // The tolerance keeps a bound that is a tick but for rounding (10^log10(20)) a tick.
    let first = (lo / step - 1e-9).ceil() * step;
    (0..)
        .map(|i| first + i as f64 * step)
        .take_while(|v| *v <= hi + step * 1e-9)
        .take(50)
        .collect()
}

/// `v` written with `decimals` digits after the point, or in short scientific notation when very
/// large or small.
fn fmt_value(v: f64, decimals: usize) -> String {
    let a = v.abs();
    if a < 1e-12 {
        return "0".into();
    }
    if !(1e-3..1e6).contains(&a) {
        // "1e-4", "2.5e6": mantissa with its trailing zeros dropped.
        let s = format!("{v:.2e}");
        return match s.split_once('e') {
            Some((m, e)) if m.contains('.') => {
                format!("{}e{e}", m.trim_end_matches('0').trim_end_matches('.'))
            }
            _ => s,
        };
    }
    format!("{v:.decimals$}")
}

/// Digits after the point that tell apart values `step` apart.
fn decimals_for(step: f64) -> usize {
    if step.is_finite() && step > 0.0 {
        (-(step.log10() + 1e-9).floor()).clamp(0.0, 6.0) as usize
    } else {
        0
    }
}

fn linear_ticks(lo: f64, hi: f64, n: usize) -> Vec<Tick> {
    let t = nice_ticks(lo, hi, n);
    let step = if t.len() > 1 { t[1] - t[0] } else { hi - lo };
    let d = decimals_for(step);
    t.into_iter()
        .map(|v| Tick {
            at: v,
            label: fmt_value(v, d),
        })
        .collect()
}

/// Ticks of a log axis spanning `[lo, hi]` decades: `(labelled ticks, unlabelled grid lines)`.
///
/// Tries 1-2-5 × 10ᵏ, then whole decades (thinned when there are too many); a span too narrow for
/// three 1-2-5 ticks gets linear nice ticks instead, which look even on so short a log range.
fn log_ticks(lo: f64, hi: f64, n: usize) -> (Vec<Tick>, Vec<f64>) {
    let (k0, k1) = (lo.floor() as i32, hi.ceil() as i32);
    let at = |mults: &[f64], every: i32| -> Vec<(f64, f64)> {
        (k0..=k1)
            .filter(|k| k.rem_euclid(every) == 0)
            .flat_map(|k| mults.iter().map(move |m| m * 10f64.powi(k)))
            .map(|v| (v.log10(), v))
            .filter(|(t, _)| *t >= lo - 1e-9 && *t <= hi + 1e-9)
            .collect()
    };
    let label = |(t, v): (f64, f64)| Tick {
        at: t,
        label: fmt_value(v, decimals_for(v)),
    };
    let one_two_five = at(&[1.0, 2.0, 5.0], 1);
    if one_two_five.len() < 3 {
        let vlo = 10f64.powf(lo);
        let vhi = 10f64.powf(hi);
        let t = nice_ticks(vlo, vhi, n.min(6));
        let step = if t.len() > 1 { t[1] - t[0] } else { vhi - vlo };
        let d = decimals_for(step);
        let ticks = t
            .into_iter()
            .filter(|v| *v > 0.0)
            .map(|v| Tick {
                at: v.log10(),
                label: fmt_value(v, d),
            })
            .collect();
        return (ticks, Vec::new());
    }
    if one_two_five.len() <= n {
        let minor = at(&[3.0, 4.0, 6.0, 7.0, 8.0, 9.0], 1);
        return (
            one_two_five.into_iter().map(label).collect(),
            minor.into_iter().map(|(t, _)| t).collect(),
        );
    }
    let decades = (k1 - k0 + 1).max(1);
    let every = ((decades as usize).div_ceil(n.max(1))).max(1) as i32;
    let ticks: Vec<Tick> = at(&[1.0], every).into_iter().map(label).collect();
    let minor = if every == 1 {
        at(&[2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 9.0], 1)
            .into_iter()
            .map(|(t, _)| t)
            .collect()
    } else {
        // Unlabelled decades between the labelled ones.
        at(&[1.0], 1).into_iter().map(|(t, _)| t).collect()
    };
    (ticks, minor)
}

fn ticks_for(scale: Scale, lo: f64, hi: f64, n: usize) -> (Vec<Tick>, Vec<f64>) {
    match scale {
        Scale::Linear => (linear_ticks(lo, hi, n), Vec::new()),
        Scale::Log10 => log_ticks(lo, hi, n),
    }
}

fn axis_desc(label: &str, scale: Scale) -> String {
    match scale {
        Scale::Linear => label.to_owned(),
        Scale::Log10 if label.is_empty() => "(log scale)".to_owned(),
        Scale::Log10 => format!("{label} (log scale)"),
    }
}

/// A linear axis over `[lo, hi]` (axis space: log10 of the data on a log axis) whose grid lines
/// are exactly the ticks computed here. Plotters' own `with_key_points` cannot be used: its
/// `f64` axis has no default label formatting, so the mesh would not accept it.
#[derive(Debug, Clone)]
struct Axis {
    lo: f64,
    hi: f64,
    major: Vec<f64>,
    minor: Vec<f64>,
}

impl Ranged for Axis {
    type FormatOption = DefaultFormatting;
    type ValueType = f64;

    fn map(&self, v: &f64, limit: (i32, i32)) -> i32 {
        let f = (v - self.lo) / (self.hi - self.lo);
        if !f.is_finite() {
            return (limit.0 + limit.1) / 2;
        }
        limit.0 + (f64::from(limit.1 - limit.0) * f).round() as i32
    }

    fn key_points<H: KeyPointHint>(&self, hint: H) -> Vec<f64> {
        if hint.weight().allow_light_points() {
            self.minor.clone()
        } else {
            self.major.clone()
        }
    }

    fn range(&self) -> std::ops::Range<f64> {
        self.lo..self.hi
    }
}

/// Marker shapes, cycled over the series so that series sharing a palette colour (more than
/// six of them) still look different, and the chart survives greyscale printing.
#[derive(Debug, Clone, Copy)]
enum Shape {
    Circle,
    Square,
    Triangle,
    Diamond,
}

const SHAPES: [Shape; 4] = [
    Shape::Circle,
    Shape::Square,
    Shape::Triangle,
    Shape::Diamond,
];

fn draw_marker<DB: DrawingBackend>(
    area: &DrawingArea<DB, Shift>,
    (x, y): (i32, i32),
    shape: Shape,
    color: RGBColor,
) -> Drawn {
    let r = MARKER_R;
    let style = color.filled();
    match shape {
        Shape::Circle => area.draw(&Circle::new((x, y), r, style)),
        Shape::Square => area.draw(&Rectangle::new(
            [(x - r + 1, y - r + 1), (x + r - 1, y + r - 1)],
            style,
        )),
        Shape::Triangle => area.draw(&Polygon::new(
            vec![(x, y - r - 1), (x + r + 1, y + r), (x - r - 1, y + r)],
            style,
        )),
        Shape::Diamond => area.draw(&Polygon::new(
            vec![
                (x, y - r - 1),
                (x + r + 1, y),
                (x, y + r + 1),
                (x - r - 1, y),
            ],
            style,
        )),
    }
    .map_err(err)
}

/// An axis-aligned pixel rectangle, `[x0, x1) × [y0, y1)`.
#[derive(Debug, Clone, Copy)]
struct Rect {
    x0: i32,
    y0: i32,
    x1: i32,
    y1: i32,
}

impl Rect {
    fn around((x, y): (i32, i32), r: i32) -> Self {
        Self {
            x0: x - r,
            y0: y - r,
            x1: x + r + 1,
            y1: y + r + 1,
        }
    }

    fn grown(&self, by: i32) -> Self {
        Self {
            x0: self.x0 - by,
            y0: self.y0 - by,
            x1: self.x1 + by,
            y1: self.y1 + by,
        }
    }

    fn moved(&self, (dx, dy): (i32, i32)) -> Self {
        Self {
            x0: self.x0 + dx,
            y0: self.y0 + dy,
            x1: self.x1 + dx,
            y1: self.y1 + dy,
        }
    }

    fn overlap(&self, o: &Rect) -> i64 {
        let w = (self.x1.min(o.x1) - self.x0.max(o.x0)).max(0);
        let h = (self.y1.min(o.y1) - self.y0.max(o.y0)).max(0);
        i64::from(w) * i64::from(h)
    }

    fn contains(&self, (x, y): (i32, i32)) -> bool {
        x >= self.x0 && x < self.x1 && y >= self.y0 && y < self.y1
    }

    /// Area of `self` outside `bounds`.
    fn outside(&self, bounds: &Rect) -> i64 {
        let a = i64::from(self.x1 - self.x0) * i64::from(self.y1 - self.y0);
        a - self.overlap(bounds)
    }
}

/// Where the legend box goes inside the plot.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Corner {
    TopRight,
    TopLeft,
    BottomRight,
    BottomLeft,
}

const CORNERS: [Corner; 4] = [
    Corner::TopRight,
    Corner::TopLeft,
    Corner::BottomRight,
    Corner::BottomLeft,
];

/// The legend's box, `w × h` pixels, in `corner` of `plot`.
fn legend_rect(plot: &Rect, corner: Corner, (w, h): (i32, i32)) -> Rect {
    let x0 = match corner {
        Corner::TopRight | Corner::BottomRight => plot.x1 - LEGEND_INSET - w,
        Corner::TopLeft | Corner::BottomLeft => plot.x0 + LEGEND_INSET,
    };
    let y0 = match corner {
        Corner::TopRight | Corner::TopLeft => plot.y0 + LEGEND_INSET,
        Corner::BottomRight | Corner::BottomLeft => plot.y1 - LEGEND_INSET - h,
    };
    Rect {
        x0,
        y0,
        x1: x0 + w,
        y1: y0 + h,
    }
}

/// Everything drawn in axis space that a legend box could hide: markers, points along line
/// segments, error-bar ends, scatter dots.
fn occupied(mapped: &[Mapped], lines: bool) -> Vec<(f64, f64)> {
    let mut out = Vec::new();
    for m in mapped {
        for run in &m.runs {
            out.extend(run.iter().map(|&(x, y, _)| (x, y)));
            if lines {
                // Samples along each segment, so a line crossing a corner counts too.
                for w in run.windows(2) {
                    for k in 1..8 {
                        let f = f64::from(k) / 8.0;
                        out.push((
                            w[0].0 + (w[1].0 - w[0].0) * f,
                            w[0].1 + (w[1].1 - w[0].1) * f,
                        ));
                    }
                }
            }
        }
        for &(x, lo, hi) in &m.bars {
            out.extend(lo.map(|y| (x, y)));
            out.extend(hi.map(|y| (x, y)));
        }
        out.extend(m.scatter.iter().copied());
    }
    out
}

fn draw_chart<DB: DrawingBackend>(painter: &Painter<'_, DB>, chart: &Chart) -> Drawn {
    let area = painter.area;
    let (w, h) = area.dim_in_pixel();
    let (w, h) = (w as i32, h as i32);
    let mut top = MARGIN;
    if !chart.title.is_empty() {
        let baseline = MARGIN + (ASCENT * f64::from(TITLE_PX)).ceil() as i32;
        painter.text(
            &chart.title,
            TITLE_PX,
            &BLACK,
            (w / 2, baseline),
            Align::Middle,
            false,
        )?;
        top = baseline + (DESCENT * f64::from(TITLE_PX)).ceil() as i32 + 10;
    }

    let mapped: Vec<Mapped> = chart
        .series
        .iter()
        .map(|s| Mapped::new(s, chart.x_scale, chart.y_scale))
        .collect();
    let xs = mapped
        .iter()
        .flat_map(|m| m.points().map(|p| p.0).chain(m.scatter.iter().map(|p| p.0)));
    let ys = mapped.iter().flat_map(|m| {
        m.points()
            .map(|p| p.1)
            .chain(m.scatter.iter().map(|p| p.1))
            .chain(m.bars.iter().flat_map(|b| b.1.into_iter().chain(b.2)))
    });
    let (Some(xr), Some(yr)) = (extent(xs), extent(ys)) else {
        return painter.text(
            "no data",
            DESC_PX,
            &RGBColor(110, 110, 110),
            (w / 2, (top + h) / 2),
            Align::Middle,
            false,
        );
    };
    let lines = chart.style != Style::Markers;
    // Lines fill the width (a curve usually starts at step 0); markers need room for labels.
    let (x0, x1) = padded(xr, if lines { 0.02 } else { 0.06 }, chart.x_scale);
    let (y0, mut y1) = padded(yr, 0.06, chart.y_scale);

    // Legend entries: named series with something drawn.
    let entries: Vec<(usize, &Series)> = chart
        .series
        .iter()
        .enumerate()
        .filter(|(k, s)| !s.name.is_empty() && !mapped[*k].is_empty())
        .collect();
    let mut legend_size = (0, 0);
    if !entries.is_empty() {
        let mut text_w = 0;
        for (_, s) in &entries {
            text_w = text_w.max(painter.width(&s.name, LEGEND_PX)?);
        }
        legend_size = (text_w + 48, entries.len() as i32 * LEGEND_ROW + 8);
    }

    // The plot rectangle, before the y tick labels are known: the legend choice only needs it
    // roughly, and the y label area is measured below.
    let plot_h = h - top - MARGIN - X_AREA;
    let guess = Rect {
        x0: MARGIN + 64,
        y0: top,
        x1: w - MARGIN_RIGHT,
        y1: top + plot_h,
    };
    if guess.x1 - guess.x0 < 40 || plot_h < 40 {
        // Too small to hold axes: the title (if any) is all there is room for.
        return Ok(());
    }

    // Pick the legend corner hiding the least; if every corner hides something, raise the y
    // range so that a band at the top is empty and put the legend there.
    let mut corner = Corner::TopRight;
    if !entries.is_empty() {
        let to_px = |(x, y): (f64, f64)| {
            let fx = (x - x0) / (x1 - x0);
            let fy = (y - y0) / (y1 - y0);
            (
                guess.x0 + (fx * f64::from(guess.x1 - guess.x0)) as i32,
                guess.y1 - (fy * f64::from(guess.y1 - guess.y0)) as i32,
            )
        };
        let px: Vec<(i32, i32)> = occupied(&mapped, lines).into_iter().map(to_px).collect();
        let hidden = |c: Corner| {
            // A margin around the box: markers have a radius and labels sit beside them.
            let r = legend_rect(&guess, c, legend_size).grown(12);
            px.iter().filter(|p| r.contains(**p)).count()
        };
        if let Some((n, c)) = CORNERS.iter().map(|&c| (hidden(c), c)).min_by_key(|b| b.0) {
            corner = c;
            if n > 0 {
                let band = f64::from(legend_size.1 + LEGEND_INSET + 14) / f64::from(plot_h);
                y1 = y0 + (y1 - y0) / (1.0 - band.min(0.5));
                corner = Corner::TopRight;
            }
        }
    }

    let y_n = (plot_h / 45).clamp(2, 10) as usize;
    let (y_ticks, y_minor) = ticks_for(chart.y_scale, y0, y1, y_n);
    let mut y_label_w = 0;
    for t in &y_ticks {
        y_label_w = y_label_w.max(painter.width(&t.label, TICK_PX)?);
    }
    let y_desc_w = if chart.y_label.is_empty() {
        0
    } else {
        DESC_PX + 10
    };
    let y_area = y_label_w + 10 + y_desc_w;
    let plot_w = w - MARGIN - MARGIN_RIGHT - y_area;
    if plot_w < 40 {
        return Ok(());
    }
    let x_n = (plot_w / 85).clamp(2, 10) as usize;
    let (x_ticks, x_minor) = ticks_for(chart.x_scale, x0, x1, x_n);

    let inner = area.margin(top, MARGIN, MARGIN, MARGIN_RIGHT);
    let x_axis = Axis {
        lo: x0,
        hi: x1,
        major: x_ticks.iter().map(|t| t.at).collect(),
        minor: x_minor,
    };
    let y_axis = Axis {
        lo: y0,
        hi: y1,
        major: y_ticks.iter().map(|t| t.at).collect(),
        minor: y_minor,
    };
    let mut cc = ChartBuilder::on(&inner)
        .x_label_area_size(X_AREA)
        .y_label_area_size(y_area)
        .build_cartesian_2d(x_axis, y_axis)
        .map_err(err)?;
    // Plotters draws the grid, the axes and the tick marks; the text is drawn by `painter`
    // (transparent text is skipped by both backends).
    cc.configure_mesh()
        .label_style(TextStyle::from((FAMILY, TICK_PX)).color(&TRANSPARENT))
        .bold_line_style(RGBColor(218, 218, 218))
        .light_line_style(RGBColor(241, 241, 241))
        .axis_style(RGBColor(90, 90, 90))
        .set_all_tick_mark_size(4)
        .draw()
        .map_err(err)?;

    // From here on everything is drawn in pixels relative to `area`.
    let base = area.get_base_pixel();
    let (prx, pry) = cc.plotting_area().get_pixel_range();
    let plot = Rect {
        x0: prx.start - base.0,
        y0: pry.start - base.1,
        x1: prx.end - base.0,
        y1: pry.end - base.1,
    };
    let px = |x: f64, y: f64| {
        let (a, b) = cc.backend_coord(&(x, y));
        (a - base.0, b - base.1)
    };

    // Axis text.
    let tick_ascent = (ASCENT * f64::from(TICK_PX)).ceil() as i32;
    for t in &x_ticks {
        let (x, _) = px(t.at, y0);
        let at = (x, plot.y1 + 6 + tick_ascent);
        painter.text(&t.label, TICK_PX, &BLACK, at, Align::Middle, false)?;
    }
    for t in &y_ticks {
        let (_, y) = px(x0, t.at);
        // Digits are about 0.6 of the pixel size tall: centre them on the grid line.
        let at = (plot.x0 - 7, y + (0.3 * f64::from(TICK_PX)).round() as i32);
        painter.text(&t.label, TICK_PX, &BLACK, at, Align::End, false)?;
    }
    let x_desc = axis_desc(&chart.x_label, chart.x_scale);
    let at = ((plot.x0 + plot.x1) / 2, plot.y1 + X_AREA - 8);
    painter.text(&x_desc, DESC_PX, &BLACK, at, Align::Middle, false)?;
    let y_desc = axis_desc(&chart.y_label, chart.y_scale);
    let at = (
        MARGIN + (ASCENT * f64::from(DESC_PX)).ceil() as i32,
        (plot.y0 + plot.y1) / 2,
    );
    painter.text(&y_desc, DESC_PX, &BLACK, at, Align::Middle, true)?;

    for (s, m) in chart.series.iter().zip(&mapped) {
        let faint = rgb(s.color).mix(0.35).filled();
        for &(x, y) in &m.scatter {
            area.draw(&Circle::new(px(x, y), 2, faint)).map_err(err)?;
        }
    }
    // What point labels must not cover: error bars here, markers below.
    let mut obstacles = Vec::new();
    for (s, m) in chart.series.iter().zip(&mapped) {
        let style = rgb(s.color).stroke_width(1);
        for &(x, lo, hi) in &m.bars {
            // An end the axis cannot show (≤ 0 on a log axis) runs to the axis edge.
            let (cx, ylo) = px(x, lo.unwrap_or(y0));
            let (_, yhi) = px(x, hi.unwrap_or(y1));
            obstacles.push(Rect {
                x0: cx - 3,
                y0: yhi.min(ylo),
                x1: cx + 4,
                y1: yhi.max(ylo) + 1,
            });
            area.draw(&PathElement::new(vec![(cx, ylo), (cx, yhi)], style))
                .map_err(err)?;
            for (end, shown) in [(ylo, lo.is_some()), (yhi, hi.is_some())] {
                if shown {
                    area.draw(&PathElement::new(vec![(cx - 3, end), (cx + 3, end)], style))
                        .map_err(err)?;
                }
            }
        }
    }
    if lines {
        for (s, m) in chart.series.iter().zip(&mapped) {
            let style = rgb(s.color).stroke_width(2);
            for run in m.runs.iter().filter(|r| r.len() > 1) {
                let path: Vec<(i32, i32)> = run.iter().map(|&(x, y, _)| px(x, y)).collect();
                area.draw(&PathElement::new(path, style)).map_err(err)?;
            }
        }
    }
    // Markers: every point, except on plain lines where only a lone point (which would
    // otherwise be invisible) gets one.
    let mut labelled = Vec::new();
    for (k, (s, m)) in chart.series.iter().zip(&mapped).enumerate() {
        let shape = SHAPES[k % SHAPES.len()];
        for run in &m.runs {
            if chart.style == Style::Lines && run.len() > 1 {
                continue;
            }
            for &(x, y, i) in run {
                let p = px(x, y);
                draw_marker(area, p, shape, rgb(s.color))?;
                obstacles.push(Rect::around(p, MARKER_R + 1));
                if chart.style != Style::Lines
                    && let Some(label) = s.labels.get(i).filter(|l| !l.is_empty())
                {
                    labelled.push((p, label.as_str(), s.color));
                }
            }
        }
    }

    let legend = (!entries.is_empty()).then(|| legend_rect(&plot, corner, legend_size));
    draw_point_labels(painter, &plot, &obstacles, legend.as_ref(), &labelled)?;
    if let Some(r) = legend {
        draw_legend(painter, r, &entries, chart.style)?;
    }
    Ok(())
}

/// Draws each point label beside its marker, at the first of eight spots around it that overlaps
/// least with the labels already placed, the `obstacles` (markers, error bars) and the legend,
/// and stays inside the plot.
fn draw_point_labels<DB: DrawingBackend>(
    painter: &Painter<'_, DB>,
    plot: &Rect,
    obstacles: &[Rect],
    legend: Option<&Rect>,
    labels: &[((i32, i32), &str, [u8; 3])],
) -> Drawn {
    let mut placed: Vec<Rect> = legend.into_iter().copied().collect();
    for &((x, y), text, color) in labels {
        // The label's box with its baseline start at the origin.
        let b = painter.text_box(text, POINT_LABEL_PX, (0, 0), Align::Start)?;
        let (tw, asc, desc) = (b.x1, -b.y0, b.y1);
        // Baseline starts: right, left, above, below, then the diagonals; then the same a
        // little further out, for crowded clusters.
        let mut spots = Vec::with_capacity(16);
        for gap in [MARKER_R + 2, MARKER_R + 9] {
            let mid = y + (asc - desc) / 2;
            spots.extend([
                (x + gap + 1, mid),
                (x - gap - 1 - tw, mid),
                (x - tw / 2, y - gap - desc),
                (x - tw / 2, y + gap + asc),
                (x + gap - 1, y - gap + 1 - desc),
                (x + gap - 1, y + gap - 1 + asc),
                (x - gap + 1 - tw, y - gap + 1 - desc),
                (x - gap + 1 - tw, y + gap - 1 + asc),
            ]);
        }
        // Labels over labels (or the legend) are unreadable; over a marker or a thin error bar
        // merely untidy; outside the plot, lost.
        let cost = |&at: &(i32, i32)| {
            let r = b.moved(at);
            let on_text: i64 = placed.iter().map(|o| r.overlap(o)).sum();
            let on_marks: i64 = obstacles.iter().map(|o| r.overlap(o)).sum();
            6 * on_text + on_marks + 50 * r.outside(plot)
        };
        let Some((k, &at)) = spots.iter().enumerate().min_by_key(|(_, s)| cost(s)) else {
            continue;
        };
        let r = b.moved(at);
        placed.push(r.grown(1));
        if k >= 8 {
            // Far from its marker: a faint leader line says whose label it is.
            let near = (x.clamp(r.x0, r.x1 - 1), y.clamp(r.y0, r.y1 - 1));
            let (dx, dy) = (f64::from(near.0 - x), f64::from(near.1 - y));
            let len = dx.hypot(dy);
            if len > f64::from(MARKER_R + 2) {
                let f = f64::from(MARKER_R + 1) / len;
                let from = (x + (dx * f).round() as i32, y + (dy * f).round() as i32);
                let style = text_color(color).mix(0.6).stroke_width(1);
                painter
                    .area
                    .draw(&PathElement::new(vec![from, near], style))
                    .map_err(err)?;
            }
        }
        painter.text(
            text,
            POINT_LABEL_PX,
            &text_color(color),
            at,
            Align::Start,
            false,
        )?;
    }
    Ok(())
}

fn draw_legend<DB: DrawingBackend>(
    painter: &Painter<'_, DB>,
    r: Rect,
    entries: &[(usize, &Series)],
    style: Style,
) -> Drawn {
    let area = painter.area;
    area.draw(&Rectangle::new(
        [(r.x0, r.y0), (r.x1, r.y1)],
        WHITE.mix(0.88).filled(),
    ))
    .map_err(err)?;
    area.draw(&Rectangle::new(
        [(r.x0, r.y0), (r.x1, r.y1)],
        RGBColor(190, 190, 190).stroke_width(1),
    ))
    .map_err(err)?;
    let lift = (0.32 * f64::from(LEGEND_PX)).round() as i32;
    for (row, (k, s)) in entries.iter().enumerate() {
        let cy = r.y0 + 4 + LEGEND_ROW / 2 + row as i32 * LEGEND_ROW;
        let (sx0, sx1) = (r.x0 + 8, r.x0 + 32);
        let color = rgb(s.color);
        if style != Style::Markers {
            area.draw(&PathElement::new(
                vec![(sx0, cy), (sx1, cy)],
                color.stroke_width(2),
            ))
            .map_err(err)?;
        }
        let lone = s.points.len() == 1;
        if style != Style::Lines || lone {
            draw_marker(area, ((sx0 + sx1) / 2, cy), SHAPES[k % SHAPES.len()], color)?;
        }
        painter.text(
            &s.name,
            LEGEND_PX,
            &BLACK,
            (sx1 + 8, cy + lift),
            Align::Start,
            false,
        )?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample(style: Style, x_scale: Scale, y_scale: Scale, points: Vec<(f64, f64)>) -> Chart {
        Chart {
            title: "Loss Curve".into(),
            x_label: "step".into(),
            y_label: "loss".into(),
            x_scale,
            y_scale,
            series: vec![Series {
                name: "total".into(),
                labels: points.iter().map(|p| format!("T{}", p.0)).collect(),
                points,
                color: PALETTE[3],
                ..Default::default()
            }],
            style,
        }
    }

    fn count(rgb: &[u8], c: [u8; 3]) -> usize {
        rgb.chunks(3).filter(|p| *p == c).count()
    }

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
    fn tick_labels_are_short_and_round() {
        let labels = |t: Vec<Tick>| t.into_iter().map(|t| t.label).collect::<Vec<_>>();
        assert_eq!(
            labels(linear_ticks(0.0, 1.0, 5)),
            ["0", "0.2", "0.4", "0.6", "0.8", "1.0"]
        );
        // 3 ms .. 800 ms: 1-2-5 ticks.
        let (t, _) = log_ticks(3f64.log10(), 800f64.log10(), 8);
        assert_eq!(labels(t), ["5", "10", "20", "50", "100", "200", "500"]);
        // Ten decades: whole decades, thinned.
        let (t, _) = log_ticks(-4.0, 6.0, 6);
        assert_eq!(labels(t), ["1e-4", "0.01", "1", "100", "10000", "1e6"]);
        // Under a factor of two: linear ticks.
        let (t, _) = log_ticks(20f64.log10(), 30f64.log10(), 6);
        assert_eq!(labels(t), ["20", "22", "24", "26", "28", "30"]);
    }

    #[test]
    fn the_embedded_font_metrics_are_read() {
        let m = font_metrics().expect("DejaVu Sans parses");
        let (a, one) = (m.glyph('A'), m.glyph('1'));
        assert!(a != 0 && one != 0 && a != one);
        assert_eq!(m.glyph('\u{1F600}'), 0, "outside the BMP: .notdef");
        // DejaVu's digits advance 1303 of 2048 em units; the pixel size is ascender − descender.
        let (adv, lsb) = m.h_metrics(one);
        assert_eq!(adv, 1303.0);
        assert!(lsb > 100.0, "'1' has a wide left side bearing: {lsb}");
        let (glyphs, width) = m.layout("T1", 12.0);
        assert!((width - (m.h_metrics(m.glyph('T')).0 + 1303.0) * 12.0 / m.height).abs() < 0.5);
        // The '1' is inked past the pen position, not at it (the plotters bug worked around).
        assert!(glyphs[1].1 > (m.h_metrics(m.glyph('T')).0 * 12.0 / m.height) as i32);
        assert!(m.kerning(m.glyph('A'), m.glyph('V')) < 0.0, "AV is kerned");
    }

    #[test]
    fn a_chart_draws_its_series_in_their_colour() {
        let chart = sample(
            Style::Lines,
            Scale::Linear,
            Scale::Log10,
            vec![(0.0, 1.0), (1.0, 0.5), (2.0, 0.3), (4.0, 0.1)],
        );
        let rgb = chart.render(320, 200).to_rgb().unwrap();
        assert_eq!(rgb.len(), 320 * 200 * 3);
        let red = count(&rgb, PALETTE[3]);
        assert!(red > 100, "{red} pixels of the series colour");
        // Text (title, ticks) is anti-aliased black on white: some pixels are near black.
        let dark = rgb.chunks(3).filter(|p| p.iter().all(|c| *c < 60)).count();
        assert!(dark > 100, "{dark} dark pixels");
    }

    #[test]
    fn markers_error_bars_and_scatter_are_drawn() {
        let mut chart = sample(
            Style::Markers,
            Scale::Log10,
            Scale::Linear,
            vec![(10.0, 20.0), (100.0, 22.0), (1000.0, 23.0)],
        );
        chart.series[0].error_bars = vec![(19.0, 21.0), (-1.0, 23.0)];
        chart.series[0].scatter = vec![(10.0, 19.5), (10.0, 20.5)];
        chart.series.push(Series {
            name: "baseline".into(),
            points: vec![(1e-3, 15.0)],
            labels: vec![String::new()],
            color: PALETTE[0],
            ..Default::default()
        });
        let rgb = chart.render(500, 300).to_rgb().unwrap();
        assert!(count(&rgb, PALETTE[3]) > 60);
        assert!(count(&rgb, PALETTE[0]) > 30);
    }

    #[test]
    fn svg_holds_the_title_and_labels_in_mixed_case() {
        let chart = sample(
            Style::Markers,
            Scale::Linear,
            Scale::Linear,
            vec![(1.0, 2.0), (2.0, 3.0)],
        );
        let svg = chart.render(400, 300).to_svg().unwrap();
        assert!(svg.starts_with("<svg"), "{}", &svg[..40.min(svg.len())]);
        assert!(svg.contains("Loss Curve"));
        assert!(svg.contains("total"));
        assert!(svg.contains("T1"));
    }

    #[test]
    fn degenerate_data_does_not_panic() {
        let cases = [
            vec![],
            vec![(1.0, 1.0)],
            vec![(2.0, 5.0), (2.0, 5.0), (2.0, 5.0)],
            vec![(0.0, 0.0), (0.0, 0.0)],
            vec![
                (f64::NAN, 1.0),
                (1.0, f64::INFINITY),
                (f64::NEG_INFINITY, 2.0),
            ],
            vec![(-1.0, -1.0), (0.0, 0.0)],
            vec![(1e-300, 1e300), (1e300, 1e-300)],
            vec![(-f64::MAX, f64::MAX), (f64::MAX, -f64::MAX)],
            vec![(0.0, 1.0), (1.0, f64::NAN), (2.0, 2.0), (3.0, 3.0)],
        ];
        for points in cases {
            for style in [Style::Lines, Style::Markers, Style::LinesAndMarkers] {
                for (xs, ys) in [
                    (Scale::Linear, Scale::Linear),
                    (Scale::Log10, Scale::Log10),
                    (Scale::Linear, Scale::Log10),
                ] {
                    let chart = sample(style, xs, ys, points.clone());
                    for (w, h) in [(320, 200), (60, 40), (1, 1)] {
                        chart.render(w, h).to_rgb().unwrap();
                    }
                    chart.render(320, 200).to_svg().unwrap();
                }
            }
        }
        let empty = Chart {
            series: vec![],
            ..sample(Style::Lines, Scale::Linear, Scale::Linear, vec![])
        };
        let svg = empty.render(200, 120).to_svg().unwrap();
        assert!(svg.contains("no data"));
        assert!(render_panels(&[], 100, 100).to_rgb().is_ok());
        assert!(empty.render(0, 10).to_rgb().is_err());
    }

    #[test]
    fn nan_points_break_a_line_instead_of_joining_across() {
        let s = Series {
            points: vec![(0.0, 1.0), (1.0, f64::NAN), (2.0, 2.0), (3.0, 3.0)],
            ..Default::default()
        };
        let m = Mapped::new(&s, Scale::Linear, Scale::Linear);
        assert_eq!(m.runs.len(), 2);
        assert_eq!(m.runs[1].iter().map(|p| p.2).collect::<Vec<_>>(), [2, 3]);
    }

    #[test]
    fn panels_share_the_figure_and_files_are_written_by_extension() {
        let a = sample(
            Style::Lines,
            Scale::Linear,
            Scale::Linear,
            vec![(0.0, 1.0), (1.0, 2.0)],
        );
        let mut b = a.clone();
        b.title = "Second Panel".into();
        b.series[0].color = PALETTE[2];
        let fig = render_panels(&[a, b], 640, 240);
        let rgb = fig.to_rgb().unwrap();
        // Each colour is drawn only in its own half.
        let half = |c: [u8; 3], left: bool| {
            rgb.chunks(3)
                .enumerate()
                .filter(|(i, p)| *p == c && ((i % 640) < 320) == left)
                .count()
        };
        assert!(half(PALETTE[3], true) > 50 && half(PALETTE[3], false) == 0);
        assert!(half(PALETTE[2], false) > 50 && half(PALETTE[2], true) == 0);

        let dir = tempfile::tempdir().unwrap();
        let png = dir.path().join("fig.png");
        fig.save_png_and_svg(&png).unwrap();
        let decoded = image::open(&png).unwrap();
        assert_eq!((decoded.width(), decoded.height()), (640, 240));
        let svg = std::fs::read_to_string(dir.path().join("fig.svg")).unwrap();
        assert!(svg.contains("Second Panel"));
        fig.save(&dir.path().join("other.SVG")).unwrap();
        assert!(
            std::fs::read_to_string(dir.path().join("other.SVG"))
                .unwrap()
                .starts_with("<svg")
        );
    }

    #[test]
    fn a_failed_write_names_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let target = dir.path().join("taken.png");
        std::fs::create_dir(&target).unwrap(); // a folder cannot be replaced by a file
        let chart = sample(Style::Lines, Scale::Linear, Scale::Linear, vec![(0.0, 1.0)]);
        let e = chart.render(200, 100).save(&target).unwrap_err();
        assert_eq!(e.path, target);
        assert!(e.to_string().contains("taken.png"), "{e}");
    }
}
