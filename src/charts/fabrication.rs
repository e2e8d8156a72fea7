//! Charts of the fabrication stage: those of `doefab bench fab` ([`crate::sweep::fab`]),
//! efficiency against level count (predicted lines, simulated circles), STL triangles, time and
//! measured error against `max_error`, GDSII file size and time against the vertex limit; and
//! of the fabrication loop, what pre-compensation gains against the process's blur
//! ([`precompensation_gain`]).

use std::path::{Path, PathBuf};

use plotters::prelude::*;

use super::style::{
    draw_legend, frame, line_key, log_label, mesh, secondary_axes, short, write_png_chart, write_svg_chart,
    Drawn, GridLines,
};
use crate::error::{DataCause, Error, Result};
use crate::sweep::fab::{FabSweepResults, GdsSweep, QuantizationSweep, StlPoint, StlSweep};

/// Log range covering `values` (positive ones), widened by `pad` each way.
fn log_span(values: impl Iterator<Item = f64>, pad: f64) -> std::ops::Range<f64> {
    super::style::log_span(values, pad, 1e-3..1.0)
}

/// A count as `200k`, `2M`.
fn count(v: f64) -> String {
    if v >= 1e6 {
        format!("{}M", short(v / 1e6))
    } else if v >= 1e3 {
        format!("{}k", short(v / 1e3))
    } else {
        short(v)
    }
}

/// The colour of a wavelength: red, green or blue by band.
fn channel_colour(wavelength: f64) -> RGBColor {
    if wavelength >= 590e-9 {
        RGBColor(200, 0, 0)
    } else if wavelength >= 495e-9 {
        RGBColor(0, 140, 0)
    } else {
        RGBColor(0, 0, 220)
    }
}

fn quantization_chart<DB: DrawingBackend>(
    root: &DrawingArea<DB, plotters::coord::Shift>,
    q: &QuantizationSweep,
) -> Drawn {
    let log2 = |n: usize| (n as f64).log2();
    let (x0, x1) = q.points.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), p| {
        (a.min(log2(p.level_count)), b.max(log2(p.level_count)))
    });
    let y0 = q.points.iter().map(|p| p.predicted.min(p.simulated)).fold(1.0, f64::min);
    let caption = format!(
        "Quantization: order-{} efficiency vs level count, {} design at {:.0} nm (lines: Swanson; circles: \
         simulated grating; max |diff| {:.0e})",
        q.order,
        q.material,
        q.design_wavelength * 1e9,
        q.max_difference.max(1e-300)
    );
    let mut chart = frame(root, caption, 16, 12, [45, 60])
        .build_cartesian_2d(x0 - 0.3..x1 + 0.3, (y0 - 0.05).max(0.0)..1.02)?;
    mesh(&mut chart, 13, 14, GridLines::Full)
        .x_desc("level count N (log scale)")
        .y_desc("efficiency of the design order (fraction of the light)")
        .x_labels((2.0 * (x1 - x0 + 0.6)) as usize + 2)
        .x_label_formatter(&|v| {
            if (v - v.round()).abs() < 1e-9 && *v >= 0.0 {
                format!("{}", 2u64.pow(v.round() as u32))
            } else {
                String::new()
            }
        })
        .y_label_formatter(&|v| format!("{v:.2}"))
        .draw()?;
    let mut wavelengths: Vec<f64> = q.points.iter().map(|p| p.wavelength).collect();
    wavelengths.sort_by(|a, b| b.total_cmp(a));
    wavelengths.dedup();
    for l in wavelengths {
        let colour = channel_colour(l);
        let mut own: Vec<_> = q.points.iter().filter(|p| p.wavelength == l).collect();
        own.sort_by_key(|p| p.level_count);
        chart
            .draw_series(LineSeries::new(
                own.iter().map(|p| (log2(p.level_count), p.predicted)),
                colour.stroke_width(2),
            ))?
            .label(format!("{:.0} nm predicted", l * 1e9))
            .legend(line_key(18, colour.stroke_width(2)));
        chart
            .draw_series(
                own.iter()
                    .map(|p| Circle::new((log2(p.level_count), p.simulated), 6, colour.stroke_width(2))),
            )?
            .label(format!("{:.0} nm simulated", l * 1e9))
            .legend(move |(x, y)| Circle::new((x + 8, y), 5, colour.stroke_width(2)));
    }
    draw_legend(&mut chart, SeriesLabelPosition::LowerRight, 13)
}

fn stl_cost_chart<DB: DrawingBackend>(root: &DrawingArea<DB, plotters::coord::Shift>, s: &StlSweep) -> Drawn {
    let x = log_span(s.points.iter().map(|p| p.max_error * 1e9), 1.4);
    let caption = format!(
        "STL heightfield, {} x {} samples: triangles and time vs max_error",
        s.samples[0], s.samples[1]
    );
    let mut chart = frame(root, caption, 16, 12, [45, 70])
        .right_y_label_area_size(60)
        .build_cartesian_2d(
            x.clone().log_scale(),
            log_span(s.points.iter().map(|p| p.triangles as f64), 2.0).log_scale(),
        )?
        .set_secondary_coord(x.log_scale(), log_span(s.points.iter().map(|p| p.seconds), 2.0).log_scale());
    mesh(&mut chart, 13, 14, GridLines::Faint)
        .x_desc("max_error, nm (the mesher's bound)")
        .y_desc("triangles in the STL")
        .y_labels(30)
        .x_label_formatter(&|v| log_label(*v, short))
        .y_label_formatter(&|v| log_label(*v, count))
        .draw()?;
    secondary_axes(&mut chart, 13, 14)
        .y_desc("time to mesh, s (best of runs)")
        .y_labels(30)
        .y_label_formatter(&|v| log_label(*v, short))
        .draw()?;
    let tri: Vec<(f64, f64)> = s.points.iter().map(|p| (p.max_error * 1e9, p.triangles as f64)).collect();
    let secs: Vec<(f64, f64)> = s.points.iter().map(|p| (p.max_error * 1e9, p.seconds)).collect();
    chart
        .draw_series(LineSeries::new(tri.iter().copied(), BLUE.stroke_width(2)))?
        .label("triangles (left axis)")
        .legend(line_key(18, BLUE.stroke_width(2)));
    chart.draw_series(tri.iter().map(|&p| Circle::new(p, 4, BLUE.filled())))?;
    chart
        .draw_secondary_series(LineSeries::new(secs.iter().copied(), RED.stroke_width(2)))?
        .label("time (right axis)")
        .legend(line_key(18, RED.stroke_width(2)));
    chart.draw_secondary_series(secs.iter().map(|&p| TriangleMarker::new(p, 5, RED.filled())))?;
    draw_legend(&mut chart, SeriesLabelPosition::UpperRight, 13)
}

fn stl_error_chart<DB: DrawingBackend>(
    root: &DrawingArea<DB, plotters::coord::Shift>,
    s: &StlSweep,
) -> Drawn {
    let x = log_span(s.points.iter().map(|p| p.max_error * 1e9), 1.4);
    let y = log_span(
        s.points
            .iter()
            .flat_map(|p| [p.max_error, p.measured_max_error, p.measured_rms_error])
            .map(|v| v * 1e9),
        1.6,
    );
    let over = s.points.iter().filter(|p| !p.within_bound).count();
    let caption =
        format!("measured height error vs max_error (on or under the line: bound held; over: {over})");
    let mut chart =
        frame(root, caption, 16, 12, [45, 70]).build_cartesian_2d(x.clone().log_scale(), y.log_scale())?;
    mesh(&mut chart, 13, 14, GridLines::Faint)
        .x_desc("max_error, nm (the mesher's bound)")
        .y_desc("|mesh - height map| at the samples, nm")
        .y_labels(30)
        .x_label_formatter(&|v| log_label(*v, short))
        .y_label_formatter(&|v| log_label(*v, short))
        .draw()?;
    chart
        .draw_series(LineSeries::new([(x.start, x.start), (x.end, x.end)], BLACK.stroke_width(1)))?
        .label("bound: error = max_error")
        .legend(line_key(18, BLACK));
    for (colour, label, value) in [
        (BLUE, "measured max", (|p: &StlPoint| p.measured_max_error) as fn(&StlPoint) -> f64),
        (RGBColor(0, 140, 0), "measured RMS", |p: &StlPoint| p.measured_rms_error),
    ] {
        let pts: Vec<(f64, f64)> = s.points.iter().map(|p| (p.max_error * 1e9, value(p) * 1e9)).collect();
        chart
            .draw_series(LineSeries::new(pts.iter().copied(), colour.stroke_width(2)))?
            .label(label)
            .legend(line_key(18, colour.stroke_width(2)));
        chart.draw_series(pts.iter().map(|&p| Circle::new(p, 4, colour.filled())))?;
    }
    draw_legend(&mut chart, SeriesLabelPosition::UpperLeft, 13)
}

fn stl_chart<DB: DrawingBackend>(root: &DrawingArea<DB, plotters::coord::Shift>, s: &StlSweep) -> Drawn {
    let (left, right) = root.split_horizontally(root.dim_in_pixel().0 / 2);
    stl_cost_chart(&left, s)?;
    stl_error_chart(&right, s)
}

fn gds_chart<DB: DrawingBackend>(root: &DrawingArea<DB, plotters::coord::Shift>, g: &GdsSweep) -> Drawn {
    let x = log_span(g.points.iter().map(|p| p.max_vertices as f64), 1.4);
    let mb_hi = g.points.iter().map(|p| p.bytes as f64 / 1e6).fold(0.0, f64::max) * 1.15;
    let s_hi = g.points.iter().map(|p| p.seconds).fold(0.0, f64::max) * 1.15;
    let caption = format!(
        "GDSII {}-level mask set, {} x {} at {:.1} um: file size and time vs vertex limit (polygon area - \
         bitmap area: at most {} nm^2)",
        g.level_count,
        g.samples[0],
        g.samples[1],
        g.pitch * 1e6,
        g.max_area_difference
    );
    let mut chart = frame(root, caption, 16, 12, [45, 70])
        .right_y_label_area_size(60)
        .build_cartesian_2d(x.clone().log_scale(), 0.0..mb_hi.max(1e-6))?
        .set_secondary_coord(x.log_scale(), 0.0..s_hi.max(1e-6));
    mesh(&mut chart, 13, 14, GridLines::Faint)
        .x_desc("most vertices per polygon (labels: polygons written)")
        .y_desc("file size, MB")
        .x_labels(30)
        .x_label_formatter(&|v| log_label(*v, short))
        .y_label_formatter(&|v| format!("{v:.2}"))
        .draw()?;
    secondary_axes(&mut chart, 13, 14)
        .y_desc("time to trace and encode, s (best of runs)")
        .y_label_formatter(&|v| format!("{v:.2}"))
        .draw()?;
    let size: Vec<(f64, f64, usize)> =
        g.points.iter().map(|p| (p.max_vertices as f64, p.bytes as f64 / 1e6, p.polygons)).collect();
    let secs: Vec<(f64, f64)> = g.points.iter().map(|p| (p.max_vertices as f64, p.seconds)).collect();
    chart
        .draw_series(LineSeries::new(size.iter().map(|p| (p.0, p.1)), BLUE.stroke_width(2)))?
        .label("file size (left axis)")
        .legend(line_key(18, BLUE.stroke_width(2)));
    chart
        .draw_secondary_series(LineSeries::new(secs.iter().copied(), RED.stroke_width(2)))?
        .label("time (right axis)")
        .legend(line_key(18, RED.stroke_width(2)));
    chart.draw_secondary_series(secs.iter().map(|&p| TriangleMarker::new(p, 5, RED.filled())))?;
    draw_legend(&mut chart, SeriesLabelPosition::UpperRight, 13)
}

/// Writes the charts of `doefab bench fab` at `path_for(name)`: `quantization.{png,svg}`
/// (efficiency against level count, predicted and simulated, per wavelength),
/// `stl_heightfield.{png,svg}` (triangles and time, and the measured error, against
/// `max_error`) and `gds.{png,svg}` (file size and time against the vertex limit); returns
/// the names.
pub fn write_fab_sweep_charts(
    mut path_for: impl FnMut(&str) -> PathBuf,
    report: &FabSweepResults,
) -> Result<Vec<String>> {
    if report.quantization.points.is_empty() || report.stl.points.is_empty() || report.gds.points.is_empty() {
        return Err(Error::data(DataCause::Empty, "a fabrication benchmark sweep has no points to chart"));
    }
    let q = &report.quantization;
    write_png_chart(&path_for("quantization.png"), 1000, 650, |r| quantization_chart(r, q))?;
    write_svg_chart(&path_for("quantization.svg"), 1000, 650, |r| quantization_chart(r, q))?;
    let s = &report.stl;
    write_png_chart(&path_for("stl_heightfield.png"), 1400, 600, |r| stl_chart(r, s))?;
    write_svg_chart(&path_for("stl_heightfield.svg"), 1400, 600, |r| stl_chart(r, s))?;
    let g = &report.gds;
    write_png_chart(&path_for("gds.png"), 1000, 650, |r| gds_chart(r, g))?;
    write_svg_chart(&path_for("gds.svg"), 1000, 650, |r| gds_chart(r, g))?;
    Ok(["quantization", "stl_heightfield", "gds"]
        .iter()
        .flat_map(|n| [format!("{n}.png"), format!("{n}.svg")])
        .collect())
}

/// One blur width of the chart: the blur in samples, and before/after pairs of the height RMS
/// (metres) and of the PSF's relative L2 against the design's.
pub struct GainPoint {
    /// Blur of the simulated process, in design samples (standard deviation / pitch).
    pub blur_samples: f64,
    /// RMS of part - design over the aperture, before and after pre-compensation, metres.
    pub rms: [f64; 2],
    /// PSF relative L2 against the design's, before and after pre-compensation.
    pub psf: [f64; 2],
}

/// Gain of pre-compensation (before / after) in height RMS and in PSF relative L2 against the
/// process's blur, with the 2x line; PNG at `path` and SVG beside it.
pub fn precompensation_gain(path: &Path, points: &[GainPoint]) -> Result<()> {
    let rms: Vec<(f64, f64)> = points.iter().map(|p| (p.blur_samples, p.rms[0] / p.rms[1])).collect();
    let psf: Vec<(f64, f64)> = points.iter().map(|p| (p.blur_samples, p.psf[0] / p.psf[1])).collect();
    let x1 = points.iter().map(|p| p.blur_samples).fold(1.0, f64::max);
    let y1 = rms.iter().chain(&psf).map(|p| p.1).fold(2.5, f64::max) * 1.1;
    fn draw<DB: DrawingBackend>(
        root: &DrawingArea<DB, plotters::coord::Shift>,
        rms: &[(f64, f64)],
        psf: &[(f64, f64)],
        x1: f64,
        y1: f64,
    ) -> Drawn {
        let mut ch = frame(
            root,
            "pre-compensation: error of the plain mask / error of the corrected one",
            17,
            14,
            [44, 64],
        )
        .build_cartesian_2d(0.0..x1, 0.0..y1)?;
        mesh(&mut ch, 13, 14, GridLines::Full)
            .x_desc("process blur (standard deviation, design samples)")
            .y_desc("gain (before / after)")
            .draw()?;
        ch.draw_series(LineSeries::new([(0.0, 2.0), (x1, 2.0)], BLACK.mix(0.4).stroke_width(1)))?
            .label("2x")
            .legend(line_key(18, BLACK.mix(0.4)));
        ch.draw_series(LineSeries::new([(0.0, 1.0), (x1, 1.0)], BLACK.stroke_width(1)))?;
        for (data, colour, label) in [(rms, BLUE, "height RMS"), (psf, RED, "PSF relative L2")] {
            ch.draw_series(LineSeries::new(data.iter().copied(), colour.stroke_width(2)))?
                .label(label)
                .legend(line_key(18, colour.stroke_width(2)));
            ch.draw_series(data.iter().map(|&p| Circle::new(p, 4, colour.filled())))?;
        }
        draw_legend(&mut ch, SeriesLabelPosition::UpperLeft, 13)
    }
    write_png_chart(path, 900, 560, |root| draw(root, &rms, &psf, x1, y1))?;
    write_svg_chart(&path.with_extension("svg"), 900, 560, |root| draw(root, &rms, &psf, x1, y1))
}
