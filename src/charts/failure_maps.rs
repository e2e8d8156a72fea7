//! Failure maps (`bench register`, `bench calibration`): one panel per axis of trouble swept,
//! each trial's error against the value it was run at, marked by its outcome (within the
//! limit, over it and warned, over it and silent, refused), the limit a red line.

use std::path::PathBuf;

use plotters::coord::Shift;
use plotters::prelude::*;

use super::style::{
    draw_legend, frame, key_entry, mesh, write_png_chart, write_svg_chart, DrawError, Drawn, GridLines, FONT,
};
use crate::error::Result;
use crate::sweep::calibration::{CalibrationSweep, Trial};
use crate::sweep::register::RegistrationSweep;
use crate::sweep::SweepAxis;

/// A chart of a failure map's panel: x the values swept along `axis` (padded 6 % each way,
/// captioned with its name and unit), y logarithmic over `y` with `y_desc`, and a red horizontal
/// line at `limit` (the error past which a trial fails). The trials are drawn on the returned
/// chart.
pub fn failure_panel<'a, DB: DrawingBackend>(
    area: &'a DrawingArea<DB, plotters::coord::Shift>,
    axis: &SweepAxis,
    y: std::ops::Range<f64>,
    y_desc: &str,
    limit: f64,
) -> std::result::Result<
    ChartContext<'a, DB, Cartesian2d<plotters::coord::types::RangedCoordf64, LogCoord<f64>>>,
    DrawError,
> {
    let (lo, hi) =
        axis.values.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), v| (a.min(*v), b.max(*v)));
    let pad = 0.06 * (hi - lo).max(1e-12);
    let mut c = frame(area, format!("{} ({})", axis.name, axis.unit), 15, 8, [28, 52])
        .build_cartesian_2d(lo - pad..hi + pad, y.log_scale())?;
    mesh(&mut c, 11, 11, GridLines::Labels)
        .y_desc(y_desc)
        .y_label_formatter(&|v| format!("{v:.0e}"))
        .x_labels(6)
        .draw()?;
    c.draw_series(LineSeries::new([(lo - pad, limit), (hi + pad, limit)], RED.stroke_width(1)))?;
    Ok(c)
}

/// The colours of a failure map's markers: a trial within its limit (green dot), over it and
/// warned (orange triangle), and the method's own error estimate (grey ring).
pub const WITHIN: RGBColor = RGBColor(0, 120, 0);
/// Colour of a trial over its limit and warned (orange triangle).
pub const WARNED: RGBColor = RGBColor(220, 140, 0);
/// Colour of the method's own error estimate (grey ring).
pub const ESTIMATE: RGBColor = RGBColor(150, 150, 150);

/// The key of a failure map, drawn on `panel` at `position`: the dot (`within`), the orange
/// triangle (`warned`, where the map has warnings), the red ring of a silent failure
/// (`silent`), the cross of a refusal (drawn at the top), the grey ring (`estimate`, where the
/// method estimates its own error) and the red line (`line`).
pub fn draw_failure_key<'a, DB: DrawingBackend + 'a>(
    panel: &mut ChartContext<'a, DB, Cartesian2d<plotters::coord::types::RangedCoordf64, LogCoord<f64>>>,
    position: SeriesLabelPosition,
    within: &str,
    warned: Option<&str>,
    silent: &str,
    estimate: Option<&str>,
    line: &str,
) -> Drawn {
    key_entry(panel, within, |(x, y)| Circle::new((x + 8, y), 4, WITHIN.filled()))?;
    if let Some(warned) = warned {
        key_entry(panel, warned, |(x, y)| TriangleMarker::new((x + 8, y), 6, WARNED.filled()))?;
    }
    key_entry(panel, silent, |(x, y)| Circle::new((x + 8, y), 7, RED.stroke_width(2)))?;
    key_entry(panel, "refused (drawn at the top)", |(x, y)| {
        Cross::new((x + 8, y), 6, BLACK.stroke_width(2))
    })?;
    if let Some(estimate) = estimate {
        key_entry(panel, estimate, |(x, y)| Circle::new((x + 8, y), 6, ESTIMATE.stroke_width(1)))?;
    }
    key_entry(panel, line, |(x, y)| PathElement::new(vec![(x, y), (x + 16, y)], RED.stroke_width(1)))?;
    draw_legend(panel, position, 11)
}

/// The error drawn for a refused trial (above every other).
const CALIBRATION_REFUSED_AT: f64 = 3.0;

fn calibration_chart<DB: DrawingBackend>(root: &DrawingArea<DB, Shift>, r: &CalibrationSweep) -> Drawn {
    root.fill(&WHITE)?;
    let title = format!(
        "PSF calibration from a pinhole bracket: error against each trouble, two seeds (silent failures: {}; warned: {}; refused: {})",
        r.silent_failures, r.warned, r.refused
    );
    let root = root.titled(&title, (FONT, 17))?;
    let panels = root.split_evenly((1, r.axes.len()));
    let floor = 1e-4;
    for (i, (axis, area)) in r.axes.iter().zip(panels.iter()).enumerate() {
        let mut c = failure_panel(
            area,
            axis,
            floor..CALIBRATION_REFUSED_AT * 3.0,
            "relative L2 error of the PSF",
            r.tolerance,
        )?;
        if i == 0 {
            // The key, in the first panel's empty upper right.
            draw_failure_key(
                &mut c,
                SeriesLabelPosition::UpperRight,
                "within the tolerance",
                Some("over it, warned"),
                "over it, not warned: silent failure",
                Some("the calibration's own estimate"),
                "the tolerance",
            )?;
        }
        let own: Vec<&Trial> = r.trials.iter().filter(|t| t.axis == axis.name).collect();
        // The calibration's own estimate, as grey rings.
        c.draw_series(
            own.iter()
                .filter(|t| t.estimated.is_finite())
                .map(|t| Circle::new((t.value, t.estimated.max(floor)), 6, ESTIMATE.stroke_width(1))),
        )?;
        c.draw_series(own.iter().map(|t| -> DynElement<DB, (f64, f64)> {
            let at = (t.value, t.worst.max(floor));
            match t.outcome.as_str() {
                "refused" => {
                    Cross::new((t.value, CALIBRATION_REFUSED_AT), 6, BLACK.stroke_width(2)).into_dyn()
                }
                "silent" => Circle::new(at, 7, RED.stroke_width(2)).into_dyn(),
                "warned" => TriangleMarker::new(at, 6, WARNED.filled()).into_dyn(),
                _ => Circle::new(at, 4, WITHIN.filled()).into_dyn(),
            }
        }))?;
    }
    Ok(())
}

/// Writes `calibration.{png,svg}` at `path_for(name)`: one panel per axis, the error of each
/// trial (green dot: within the tolerance; orange triangle: over it and warned; red ring: over
/// it and silent; black cross at the top: refused), the calibration's own estimate as a grey
/// ring, the red line the tolerance. Returns the names.
pub fn write_calibration_chart(
    mut path_for: impl FnMut(&str) -> PathBuf,
    r: &CalibrationSweep,
) -> Result<Vec<String>> {
    write_png_chart(&path_for("calibration.png"), 1400, 520, |root| calibration_chart(root, r))?;
    write_svg_chart(&path_for("calibration.svg"), 1400, 520, |root| calibration_chart(root, r))?;
    Ok(vec!["calibration.png".into(), "calibration.svg".into()])
}
/// The shift error drawn for a refused trial (above every accepted one).
const REGISTRATION_REFUSED_AT: f64 = 30.0;

fn registration_chart<DB: DrawingBackend>(root: &DrawingArea<DB, Shift>, r: &RegistrationSweep) -> Drawn {
    root.fill(&WHITE)?;
    let title = format!(
        "Scan registration: shift error against each trouble, two seeds (silent failures: {}; refused: {})",
        r.silent_failures, r.refused
    );
    let root = root.titled(&title, (FONT, 18))?;
    let panels = root.split_evenly((2, 3));
    for (i, (axis, area)) in r.axes.iter().zip(panels.iter()).enumerate() {
        let mut c = failure_panel(
            area,
            axis,
            1e-4..REGISTRATION_REFUSED_AT * 3.0,
            "shift error, design samples",
            r.wrong_shift,
        )?;
        if i == 0 {
            // The key, in the first panel's empty lower right.
            draw_failure_key(
                &mut c,
                SeriesLabelPosition::LowerRight,
                "registered",
                None,
                "accepted but wrong: silent failure",
                None,
                "past the line a pose counts as wrong",
            )?;
        }
        let own = r.trials.iter().filter(|t| t.axis == axis.name);
        c.draw_series(own.map(|t| -> DynElement<DB, (f64, f64)> {
            match t.outcome.as_str() {
                "refused" => {
                    Cross::new((t.value, REGISTRATION_REFUSED_AT), 6, BLACK.stroke_width(2)).into_dyn()
                }
                "wrong" => Circle::new((t.value, t.shift_error.max(1e-4)), 7, RED.stroke_width(2)).into_dyn(),
                _ => Circle::new((t.value, t.shift_error.max(1e-4)), 4, WITHIN.filled()).into_dyn(),
            }
        }))?;
    }
    Ok(())
}

/// Writes `register.{png,svg}` at `path_for(name)`: one panel per axis, the shift error of each
/// trial (green dot: registered; red ring: accepted but wrong, a silent failure; black cross at
/// the top: refused), the red line the error past which a pose counts as wrong. Returns the
/// names.
pub fn write_registration_chart(
    mut path_for: impl FnMut(&str) -> std::path::PathBuf,
    r: &RegistrationSweep,
) -> Result<Vec<String>> {
    write_png_chart(&path_for("register.png"), 1200, 700, |root| registration_chart(root, r))?;
    write_svg_chart(&path_for("register.svg"), 1200, 700, |root| registration_chart(root, r))?;
    Ok(vec!["register.png".into(), "register.svg".into()])
}
