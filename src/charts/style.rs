//! The charts' shared style: every chart is drawn twice from one drawing function, once into
//! an RGB buffer written as PNG (atomically) and once as SVG; text uses DejaVu Sans, embedded
//! in the binary (`assets/fonts/`, Bitstream Vera licence), so charts look the same on every
//! machine and need no system fonts. A chart's frame ([`frame`]), its mesh and grid lines
//! ([`mesh`], [`GridLines`], [`secondary_axes`]), log axes ([`log_span`], [`log_label`]), legends
//! ([`draw_legend`], [`key_entry`], [`line_key`], [`dashed_legend`]) and the error of a failed
//! drawing are here.

use std::path::Path;

use plotters::chart::{DualCoordChartContext, MeshStyle, SecondaryMeshStyle};
use plotters::coord::ranged1d::ValueFormatter;
use plotters::coord::{CoordTranslate, Shift};
use plotters::prelude::*;
use plotters::style::FontStyle;

use crate::error::{Error, Result};
use crate::io::atomic::write_bytes;

/// The family name under which the embedded font is registered; use it in `TextStyle`s.
pub const FONT: &str = "sans-serif";

static DEJAVU_SANS: &[u8] = include_bytes!("../../assets/fonts/DejaVuSans.ttf");

/// Registers the embedded font with plotters (idempotent).
pub fn register_font() {
    static ONCE: std::sync::Once = std::sync::Once::new();
    ONCE.call_once(|| {
        // The bytes are a valid TrueType font shipped with the crate; a failure here would be
        // a packaging error, and plotters then draws no text rather than failing.
        let _ = plotters::style::register_font(FONT, FontStyle::Normal, DEJAVU_SANS);
    });
}

/// A failed drawing step of a chart (plotters' error, or a chart's own refusal), kept as its
/// message for the error that names the chart's file.
#[derive(Debug)]
pub struct DrawError(String);

impl std::fmt::Display for DrawError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.0)
    }
}

impl<E: std::error::Error + Send + Sync> From<DrawingAreaErrorKind<E>> for DrawError {
    fn from(e: DrawingAreaErrorKind<E>) -> Self {
        DrawError(e.to_string())
    }
}

impl From<&str> for DrawError {
    fn from(what: &str) -> Self {
        DrawError(what.to_string())
    }
}

/// What a drawing function returns: `?` turns plotters' errors into a [`DrawError`].
pub type Drawn = std::result::Result<(), DrawError>;

fn chart_error(path: &Path, e: impl std::fmt::Display) -> Error {
    Error::encoding(path, format!("drawing the chart failed: {e}"))
}

/// A chart's frame: `caption` in the embedded font at `caption_size` pt, `margin` pixels all
/// round and label areas `[below, left]` pixels deep.
pub fn frame<'a, 'b, DB: DrawingBackend>(
    area: &'a DrawingArea<DB, Shift>,
    caption: impl AsRef<str>,
    caption_size: u32,
    margin: u32,
    [below, left]: [u32; 2],
) -> ChartBuilder<'a, 'b, DB> {
    let mut builder = ChartBuilder::on(area);
    builder
        .caption(caption, (FONT, caption_size))
        .margin(margin)
        .x_label_area_size(below)
        .y_label_area_size(left);
    builder
}

/// The grid lines of a chart's mesh.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum GridLines {
    /// plotters' own: a line at every label and light lines between.
    Full,
    /// A line at every label only (the light lines drawn white).
    Labels,
    /// A faint line at every label only, for log axes, whose light lines crowd every decade.
    Faint,
}

/// A chart's mesh in the embedded font: tick labels at `label` pt, axis descriptions at `desc`
/// pt, and `grid`'s lines.
pub fn mesh<'a, 'b, DB, X, Y, XT, YT>(
    chart: &'b mut ChartContext<'a, DB, Cartesian2d<X, Y>>,
    label: u32,
    desc: u32,
    grid: GridLines,
) -> MeshStyle<'a, 'b, X, Y, DB>
where
    DB: DrawingBackend,
    X: Ranged<ValueType = XT> + ValueFormatter<XT>,
    Y: Ranged<ValueType = YT> + ValueFormatter<YT>,
{
    let mut mesh = chart.configure_mesh();
    mesh.label_style((FONT, label)).axis_desc_style((FONT, desc));
    match grid {
        GridLines::Full => {}
        GridLines::Labels => {
            mesh.light_line_style(WHITE);
        }
        GridLines::Faint => {
            mesh.light_line_style(TRANSPARENT).bold_line_style(BLACK.mix(0.15));
        }
    }
    mesh
}

/// The right-hand axis of a chart with two y axes, in the fonts of [`mesh`].
pub fn secondary_axes<'a, 'b, DB, CT, X, Y, XT, YT>(
    chart: &'b mut DualCoordChartContext<'a, DB, CT, Cartesian2d<X, Y>>,
    label: u32,
    desc: u32,
) -> SecondaryMeshStyle<'a, 'b, X, Y, DB>
where
    DB: DrawingBackend,
    CT: CoordTranslate,
    X: Ranged<ValueType = XT> + ValueFormatter<XT>,
    Y: Ranged<ValueType = YT> + ValueFormatter<YT>,
{
    let mut axes = chart.configure_secondary_axes();
    axes.label_style((FONT, label)).axis_desc_style((FONT, desc));
    axes
}

/// The legend sample of a line series: a line `length` pixels long in `style`.
pub fn line_key<S: Into<ShapeStyle> + Copy>(
    length: i32,
    style: S,
) -> impl Fn((i32, i32)) -> PathElement<(i32, i32)> {
    move |(x, y)| PathElement::new([(x, y), (x + length, y)], style)
}

/// A log axis's range: the positive finite `values` widened by the factor `pad` each way, or
/// `empty` when there are none. The lower end reaches down at least to the power of ten at or
/// below the smallest value: plotters labels a log axis from its first power of ten up, so
/// values in a partial decade below it would stand without a label.
pub fn log_span(
    values: impl Iterator<Item = f64>,
    pad: f64,
    empty: std::ops::Range<f64>,
) -> std::ops::Range<f64> {
    let (lo, hi) = values
        .filter(|v| v.is_finite() && *v > 0.0)
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), v| (a.min(v), b.max(v)));
    if lo.is_finite() {
        // Just under the power of ten, which plotters (ln x / ln 10, rounded up) would
        // otherwise place a decade higher.
        let decade = 10f64.powf((lo.log10() + 1e-9).floor()) * (1.0 - 1e-9);
        (lo / pad).min(decade)..hi * pad
    } else {
        empty
    }
}

/// One entry of a chart's legend that stands for no series of its own: `label` with `glyph`
/// drawn at the entry's position.
pub fn key_entry<'a, DB, CT, E>(
    chart: &mut ChartContext<'a, DB, CT>,
    label: &str,
    glyph: impl Fn((i32, i32)) -> E + 'a,
) -> Drawn
where
    DB: DrawingBackend + 'a,
    CT: plotters::coord::CoordTranslate,
    E: IntoDynElement<'a, DB, (i32, i32)>,
{
    chart.draw_series(std::iter::empty::<Circle<CT::From, i32>>())?.label(label).legend(glyph);
    Ok(())
}

/// Draws the legend of `chart`'s labelled series at `position`: labels in the embedded font at
/// `size` pt on a translucent white box with a black border.
pub fn draw_legend<'a, DB, CT>(
    chart: &mut ChartContext<'a, DB, CT>,
    position: SeriesLabelPosition,
    size: u32,
) -> Drawn
where
    DB: DrawingBackend + 'a,
    CT: plotters::coord::CoordTranslate,
{
    chart
        .configure_series_labels()
        .position(position)
        .label_font((FONT, size))
        .background_style(WHITE.mix(0.8))
        .border_style(BLACK)
        .draw()?;
    Ok(())
}

/// A log axis's label: `f(v)` where the mantissa of `v` is 1, 2 or 5, else none (plotters
/// puts a key point at every digit of a decade).
pub fn log_label(v: f64, f: impl Fn(f64) -> String) -> String {
    if !(v.is_finite() && v > 0.0) {
        return String::new();
    }
    let m = v / 10f64.powf(v.log10().floor());
    if [1.0, 2.0, 5.0, 10.0].iter().any(|k| (m - k).abs() < 1e-6 * k) {
        f(v)
    } else {
        String::new()
    }
}

/// `v` with at most six decimals and no trailing zeros.
pub fn short(v: f64) -> String {
    format!("{}", (v * 1e6).round() / 1e6)
}

/// The legend sample at `at` of a line drawn by `DashedLineSeries` with `dash` and `gap`
/// (pixels) and `style`: `length` pixels drawn the same way.
pub fn dashed_legend<'a, DB: DrawingBackend + 'a>(
    at: (i32, i32),
    style: ShapeStyle,
    dash: u32,
    gap: u32,
    length: u32,
) -> impl IntoDynElement<'a, DB, (i32, i32)> {
    let piece = |(a, b): (i32, i32)| PathElement::new(vec![(a, 0), (b, 0)], style);
    let [p, q, r] = legend_dashes(dash, gap, length);
    EmptyElement::at(at) + piece(p) + piece(q) + piece(r)
}

/// The dashes of a legend sample `length` pixels long for a line drawn by `DashedLineSeries`
/// with `dash` and `gap` (pixels): the first three, as (start, end) offsets along the sample (a
/// dash starting past the end repeats the first, so that short patterns need no more pieces).
pub fn legend_dashes(dash: u32, gap: u32, length: u32) -> [(i32, i32); 3] {
    [0, 1, 2].map(|k| {
        let a = match k * (dash + gap) {
            a if a < length => a,
            _ => 0,
        };
        (a as i32, (a + dash).min(length) as i32)
    })
}

/// Draws `draw` into a `width` x `height` RGB bitmap and writes it as an 8-bit PNG at `path`.
pub fn write_png_chart<F>(path: &Path, width: u32, height: u32, draw: F) -> Result<()>
where
    F: FnOnce(&DrawingArea<BitMapBackend<'_>, plotters::coord::Shift>) -> Drawn,
{
    register_font();
    let mut rgb = vec![255u8; (width * height * 3) as usize];
    {
        let root = BitMapBackend::with_buffer(&mut rgb, (width, height)).into_drawing_area();
        root.fill(&WHITE).map_err(|e| chart_error(path, e))?;
        draw(&root).map_err(|e| chart_error(path, e))?;
        root.present().map_err(|e| chart_error(path, e))?;
    }
    let mut bytes = Vec::new();
    {
        let mut enc = png::Encoder::new(&mut bytes, width, height);
        enc.set_color(png::ColorType::Rgb);
        enc.set_depth(png::BitDepth::Eight);
        let mut w = enc.write_header().map_err(|e| chart_error(path, e))?;
        w.write_image_data(&rgb).map_err(|e| chart_error(path, e))?;
    }
    write_bytes(path, &bytes)
}

/// Draws `draw` as an SVG document of `width` x `height` and writes it at `path`.
pub fn write_svg_chart<F>(path: &Path, width: u32, height: u32, draw: F) -> Result<()>
where
    F: FnOnce(&DrawingArea<SVGBackend<'_>, plotters::coord::Shift>) -> Drawn,
{
    register_font();
    let mut svg = String::new();
    {
        let root = SVGBackend::with_string(&mut svg, (width, height)).into_drawing_area();
        root.fill(&WHITE).map_err(|e| chart_error(path, e))?;
        draw(&root).map_err(|e| chart_error(path, e))?;
        root.present().map_err(|e| chart_error(path, e))?;
    }
    write_bytes(path, svg.as_bytes())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A legend sample repeats its line's dash pattern: dash, gap, dash; a solid line (one
    /// dash longer than the sample) fills it; a dash past the end repeats the first.
    #[test]
    fn legend_dashes_follow_the_line_pattern() {
        assert_eq!(legend_dashes(6, 4, 16), [(0, 6), (10, 16), (0, 6)]);
        assert_eq!(legend_dashes(2, 4, 18), [(0, 2), (6, 8), (12, 14)]);
        assert_eq!(legend_dashes(10_000, 1, 18), [(0, 18); 3]);
    }

    /// Every value on a log axis has a labelled key point at or below it: the STL chart's RMS
    /// errors (0.17 nm and up, padded 1.6x) and mesh times (0.32 s and up, padded 2x) stood
    /// below the first label.
    #[test]
    fn log_spans_start_at_a_labelled_power_of_ten() {
        use plotters::coord::ranged1d::Ranged;
        for (values, pad) in [(vec![0.17, 0.46, 13.1], 1.6), (vec![0.32, 3.3], 2.0), (vec![1.0, 50.0], 1.4)] {
            let span = log_span(values.iter().copied(), pad, 1e-3..1.0);
            let axis: plotters::prelude::LogCoord<f64> = span.clone().log_scale().into();
            let first = axis.key_points(30usize)[0];
            assert!(
                first <= values[0] * (1.0 + 1e-12),
                "{values:?}: range {span:?}, first key point {first}"
            );
            assert!(span.start <= values[0] / pad && span.start > values[0] / 10.0 / pad, "{span:?}");
        }
        assert_eq!(log_span([1e-3, 0.1].into_iter(), 1.5, 1.0..2.0).start, 1e-3 / 1.5);
        assert_eq!(log_span([f64::NAN].into_iter(), 1.5, 1.0..2.0), 1.0..2.0);
    }

    #[test]
    fn png_chart_has_text_and_a_line() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("c.png");
        write_png_chart(&path, 320, 240, |root| {
            let mut chart = ChartBuilder::on(root)
                .caption("y = x", (FONT, 20))
                .margin(10)
                .x_label_area_size(30)
                .y_label_area_size(30)
                .build_cartesian_2d(0.0..1.0, 0.0..1.0)?;
            chart.configure_mesh().draw()?;
            chart.draw_series(LineSeries::new((0..=10).map(|i| (i as f64 / 10.0, i as f64 / 10.0)), &RED))?;
            Ok(())
        })
        .unwrap();
        let img = image::open(&path).unwrap().to_rgb8();
        let red = img.pixels().filter(|p| p[0] > 200 && p[1] < 60 && p[2] < 60).count();
        let dark = img.pixels().filter(|p| p[0] < 80 && p[1] < 80 && p[2] < 80).count();
        assert!(red > 100, "the red line is drawn ({red} px)");
        assert!(dark > 200, "axes and caption text are drawn ({dark} px)");
        let svg_path = dir.path().join("c.svg");
        write_svg_chart(&svg_path, 320, 240, |root| {
            root.draw(&Text::new("label", (10, 10), (FONT, 12).into_font()))?;
            Ok(())
        })
        .unwrap();
        let svg = std::fs::read_to_string(&svg_path).unwrap();
        assert!(svg.starts_with("<svg") && svg.contains("label"));
    }
}
