//! Charts of `doefab bench psf`: error against run time for every method, precision and
//! sub-sampling, with the Pareto front of the valid runs; and the stability chart, error
//! against sub-sampling (the FFT methods' pupil grid) per method, with the runs its guard refuses marked by crosses;
//! and the stability maps of [`crate::sweep::stability`].

use std::path::PathBuf;

use plotters::coord::Shift;
use plotters::prelude::*;

use super::style::{frame, line_key, mesh, write_png_chart, write_svg_chart, Drawn, GridLines, FONT};
use crate::error::{DataCause, Error, Result};
use crate::optics::propagate::Method;
use crate::sweep::psf::{PsfSweepPoint, PsfSweepResults};
use crate::sweep::spectral::SpectralSweepResults;
use crate::sweep::stability::{StabilityMap, StabilitySweepResults, STEPPED_DOE_PITCH};

/// The series of `points` in their order of appearance, each with its colour: the methods'
/// own hues (matrix DFT blue and green, Fresnel red, angular spectrum magenta), the FFT
/// methods' paddings lighter below their own and darker above.
fn series(points: &[PsfSweepPoint]) -> Vec<(String, RGBColor)> {
    let mut out: Vec<(String, RGBColor)> = Vec::new();
    for p in points {
        if out.iter().any(|s| s.0 == p.series) {
            continue;
        }
        let own = Method::from_name(&p.method).ok().and_then(Method::default_padding);
        let shade = |c: RGBColor| {
            let f = |v: u8, t: f64| (v as f64 + (t - v as f64) * 0.55) as u8;
            // Nominal 1.25, own, 3, as run: rounded up to fast FFT sizes (1.25 runs at up to
            // 1.35, the Fresnel method's 1.5 at up to 1.55).
            match own {
                Some(own) if p.padding < own - 0.1 => RGBColor(f(c.0, 255.0), f(c.1, 255.0), f(c.2, 255.0)),
                Some(own) if p.padding > own + 0.5 => RGBColor(f(c.0, 0.0), f(c.1, 0.0), f(c.2, 0.0)),
                _ => c,
            }
        };
        let colour = match (p.method.as_str(), p.precision.as_str()) {
            ("matrix_dft", "f64") => BLUE,
            ("matrix_dft", _) => GREEN,
            ("fresnel", _) => shade(RED),
            _ => shade(MAGENTA),
        };
        out.push((p.series.clone(), colour));
    }
    out
}

/// Log range covering `values` (positive ones), padded by a factor of 2.
fn log_range(values: impl Iterator<Item = f64>) -> std::ops::Range<f64> {
    super::style::log_span(values, 2.0, 1e-6..1.0)
}

fn speed_chart<DB: DrawingBackend>(root: &DrawingArea<DB, Shift>, report: &PsfSweepResults) -> Drawn {
    let points = &report.points;
    root.fill(&WHITE)?;
    // The counts go in the legend: in the caption they ran past the chart's width.
    let caption = format!(
        "PSF: error vs run time, {} DOE samples at {:.2} um, F/{:.1}",
        report.doe_samples,
        report.doe_pitch * 1e6,
        report.f_number,
    );
    let mut chart = frame(root, caption, 18, 12, [40, 70]).build_cartesian_2d(
        log_range(points.iter().map(|p| p.seconds).chain(report.plans.iter().map(|p| p.seconds))).log_scale(),
        log_range(
            points.iter().map(|p| p.error).chain(report.plans.iter().flat_map(|p| [p.error, p.tolerance])),
        )
        .log_scale(),
    )?;
    mesh(&mut chart, 13, 13, GridLines::Full)
        .x_desc("run time, s")
        .y_desc("relative L2 vs converged reference")
        .x_label_formatter(&|v| format!("{v:.0e}"))
        .y_label_formatter(&|v| format!("{v:.0e}"))
        .draw()?;
    for (name, colour) in series(points) {
        let own: Vec<&PsfSweepPoint> = points.iter().filter(|p| p.series == name).collect();
        chart
            .draw_series(own.iter().map(|p| {
                let style = if p.violations.is_empty() { colour.filled() } else { colour.stroke_width(1) };
                Circle::new((p.seconds, p.error.max(1e-300)), 4, style)
            }))?
            .label(name)
            .legend(move |(x, y)| Circle::new((x + 8, y), 4, colour.filled()));
    }
    let front: Vec<(f64, f64)> = points.iter().filter(|p| p.pareto).map(|p| (p.seconds, p.error)).collect();
    let mut front = front;
    front.sort_by(|a, b| a.0.total_cmp(&b.0));
    chart
        .draw_series(LineSeries::new(front, BLACK.stroke_width(2)))?
        .label("Pareto front (valid runs)")
        .legend(line_key(18, BLACK.stroke_width(2)));
    // The automatic plan at each tolerance: a triangle at its run, labelled with the tolerance.
    // Tolerances whose plans chose the same configuration share one label at the first.
    let mut labelled: Vec<(String, f64, f64, Vec<String>)> = Vec::new();
    for p in &report.plans {
        let key = format!("{} {} s={}", p.method, p.precision, p.subsample);
        match labelled.iter_mut().find(|l| l.0 == key) {
            Some(l) => l.3.push(format!("{:.0e}", p.tolerance)),
            None => labelled.push((key, p.seconds, p.error, vec![format!("{:.0e}", p.tolerance)])),
        }
    }
    chart
        .draw_series(labelled.iter().map(|(_, seconds, error, tolerances)| {
            EmptyElement::at((*seconds, error.max(1e-300)))
                + TriangleMarker::new((0, 0), 7, BLACK.filled())
                + Text::new(format!("plan at {}", tolerances.join(", ")), (8, -6), (FONT, 13))
        }))?
        .label("automatic plan at a tolerance")
        .legend(|(x, y)| TriangleMarker::new((x + 8, y), 6, BLACK.filled()));
    super::style::key_entry(&mut chart, "hollow: the guard refuses the run", |(x, y)| {
        Circle::new((x + 8, y), 4, BLACK.stroke_width(1))
    })?;
    let silent = format!("silent failures: {} (plans over their tolerance)", report.silent_failures);
    super::style::key_entry(&mut chart, &silent, |(x, y)| EmptyElement::at((x, y)))?;
    let memory = report.skipped.iter().filter(|s| s.ends_with("(memory)")).count();
    let left_out = format!("left out by the budget: {}", report.skipped.len() - memory);
    super::style::key_entry(&mut chart, &left_out, |(x, y)| EmptyElement::at((x, y)))?;
    if memory > 0 {
        super::style::key_entry(&mut chart, &format!("left out for memory: {memory}"), |(x, y)| {
            EmptyElement::at((x, y))
        })?;
    }
    super::style::draw_legend(&mut chart, SeriesLabelPosition::MiddleRight, 13)?;
    Ok(())
}

fn stability_chart<DB: DrawingBackend>(root: &DrawingArea<DB, Shift>, points: &[PsfSweepPoint]) -> Drawn {
    root.fill(&WHITE)?;
    let s_max = points.iter().map(|p| p.subsample).max().unwrap_or(1) as f64;
    let mut chart = frame(root, "PSF: error vs sampling (x: guard refuses)", 20, 12, [40, 70])
        .build_cartesian_2d(0.5..s_max + 0.5, log_range(points.iter().map(|p| p.error)).log_scale())?;
    mesh(&mut chart, 13, 13, GridLines::Full)
        .x_desc("sub-samples per pixel s (FFT methods: pupil pitch = pixel pitch / s)")
        .y_desc("relative L2 vs converged reference")
        // Sub-sampling is a whole number: one label per integer, none between (a "{v:.0}"
        // label at 1.5 and at 2 both read "2").
        .x_labels(2 * s_max as usize + 1)
        .x_label_formatter(&|v| {
            if (v - v.round()).abs() < 1e-9 {
                format!("{}", v.round())
            } else {
                String::new()
            }
        })
        .y_label_formatter(&|v| format!("{v:.0e}"))
        .draw()?;
    for (name, colour) in series(points) {
        let mut own: Vec<(f64, f64, bool)> = points
            .iter()
            .filter(|p| p.series == name)
            .map(|p| (p.subsample as f64, p.error.max(1e-300), p.violations.is_empty()))
            .collect();
        own.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.total_cmp(&b.1)));
        chart
            .draw_series(LineSeries::new(own.iter().map(|&(x, y, _)| (x, y)), colour))?
            .label(name)
            .legend(line_key(18, colour));
        chart.draw_series(own.iter().map(|&(x, y, valid)| -> DynElement<DB, (f64, f64)> {
            if valid {
                Circle::new((x, y), 3, colour.filled()).into_dyn()
            } else {
                Cross::new((x, y), 6, colour.stroke_width(2)).into_dyn()
            }
        }))?;
    }
    super::style::draw_legend(&mut chart, SeriesLabelPosition::MiddleRight, 13)?;
    Ok(())
}

/// Writes `speed_accuracy.{png,svg}` and `stability.{png,svg}`, each at `path_for(name)`;
/// returns the names. A budget that left every run out gives empty axes (the caption counts
/// what was left out, the JSON names it).
pub fn write_psf_charts(
    mut path_for: impl FnMut(&str) -> PathBuf,
    report: &PsfSweepResults,
) -> Result<Vec<String>> {
    let points = &report.points;
    write_png_chart(&path_for("speed_accuracy.png"), 1000, 650, |r| speed_chart(r, report))?;
    write_svg_chart(&path_for("speed_accuracy.svg"), 1000, 650, |r| speed_chart(r, report))?;
    write_png_chart(&path_for("stability.png"), 1000, 650, |r| stability_chart(r, points))?;
    write_svg_chart(&path_for("stability.svg"), 1000, 650, |r| stability_chart(r, points))?;
    Ok(["speed_accuracy.png", "speed_accuracy.svg", "stability.png", "stability.svg"]
        .map(String::from)
        .to_vec())
}

/// The error classes of a stability map, with their colours: within a hundredth of the
/// tolerance, within a tenth, within it, over it.
fn error_class(error: f64, tolerance: f64) -> (RGBColor, &'static str) {
    if error <= 0.01 * tolerance {
        (RGBColor(0, 110, 0), "error <= tol / 100")
    } else if error <= 0.1 * tolerance {
        (RGBColor(120, 190, 0), "error <= tol / 10")
    } else if error <= tolerance {
        (RGBColor(230, 160, 0), "error <= tol")
    } else {
        (RGBColor(200, 0, 0), "error > tol")
    }
}

fn stability_map_chart<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    report: &StabilitySweepResults,
    map: &StabilityMap,
) -> Drawn {
    root.fill(&WHITE)?;
    let by_wavelength = map.y_axis == "wavelength";
    let y_of = |c: &crate::sweep::stability::MapCell| {
        if by_wavelength {
            c.wavelength * 1e9
        } else {
            c.fresnel_number
        }
    };
    let xs = map.cells.iter().map(|c| c.lens_sampling_ratio);
    // Room on the left for the legend.
    let x_range = log_range(
        xs.chain(report.paper.iter().map(|p| p.lens_sampling_ratio)).chain(std::iter::once(map.limit_x)),
    );
    let x_range = x_range.start / 8.0..x_range.end;
    let (y_lo, y_hi) =
        map.cells.iter().map(y_of).fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), v| (a.min(v), b.max(v)));
    let caption = format!(
        "{} PSF{}: error vs pupil sampling and {} (tolerance {:.0e}; silent failures: {})",
        map.method,
        if map.design == "smooth" { String::new() } else { format!(" on the {} DOE", map.design) },
        if by_wavelength { "wavelength" } else { "Fresnel number" },
        report.tolerance,
        map.silent_failures
    );
    let y_desc = if by_wavelength {
        "wavelength, nm (g = 3.5 mm, F/7)".to_string()
    } else {
        format!("Fresnel number (D/2)^2 / (lambda g), g = d_s swept, {:.0} nm", map.cells[0].wavelength * 1e9)
    };
    let mut chart = frame(root, caption, 17, 12, [45, 70])
        .build_cartesian_2d(x_range.log_scale(), y_lo - 0.08 * (y_hi - y_lo)..y_hi + 0.12 * (y_hi - y_lo))?;
    mesh(&mut chart, 13, 13, GridLines::Labels)
        .x_desc(if map.method == "matrix_dft" {
            "pupil pitch / (lambda F#)   (the matrix DFT never samples the lens phase)"
        } else {
            "pupil pitch / (lambda F#)   (the lens phase is undersampled right of 1)"
        })
        .y_desc(y_desc)
        .x_labels(8)
        .x_label_formatter(&|v| format!("{v:.2}"))
        .y_label_formatter(&|v| format!("{v:.0}"))
        .draw()?;
    let (y0, y1) = (y_lo - 0.08 * (y_hi - y_lo), y_hi + 0.12 * (y_hi - y_lo));
    chart
        .draw_series(LineSeries::new([(map.limit_x, y0), (map.limit_x, y1)], BLACK.stroke_width(2)))?
        .label(map.limit.as_str())
        .legend(line_key(18, BLACK.stroke_width(2)));
    if by_wavelength {
        for (k, p) in report.paper.iter().enumerate() {
            let x = p.lens_sampling_ratio;
            let y_text = y1 - (0.02 + 0.035 * k as f64) * (y1 - y0);
            chart.draw_series(LineSeries::new([(x, y0), (x, y1)], BLUE.stroke_width(1)))?;
            chart.draw_series(std::iter::once(Text::new(
                format!("paper {:.0} nm", p.wavelength * 1e9),
                (x, y_text),
                (FONT, 12).into_font().color(&BLUE),
            )))?;
        }
    }
    if map.design != "smooth" {
        // The DOE's own pitch on each row: left of it the pupil nests in the DOE's cells, right
        // of it the pupil is coarser and reads across the steps.
        let mut own: Vec<(f64, f64)> = Vec::new();
        for c in &map.cells {
            let at = (c.lens_sampling_ratio * STEPPED_DOE_PITCH / c.pupil_pitch, y_of(c));
            if !own.iter().any(|o| o.1 == at.1) {
                own.push(at);
            }
        }
        chart
            .draw_series(LineSeries::new(own, BLUE.stroke_width(1)))?
            .label(format!("the DOE's own {:.0} um samples (left: nested in them)", STEPPED_DOE_PITCH * 1e6))
            .legend(line_key(18, BLUE.stroke_width(1)));
    }
    for class in 0..4 {
        let tol = report.tolerance;
        let probe = [0.001 * tol, 0.05 * tol, 0.5 * tol, 2.0 * tol][class];
        let (colour, label) = error_class(probe, tol);
        let own: Vec<_> = map.cells.iter().filter(|c| error_class(c.error, tol).1 == label).collect();
        chart
            .draw_series(own.iter().map(|c| -> DynElement<DB, (f64, f64)> {
                let at = (c.lens_sampling_ratio, y_of(c));
                if c.violations.is_empty() {
                    Circle::new(at, 6, colour.filled()).into_dyn()
                } else {
                    Cross::new(at, 7, colour.stroke_width(3)).into_dyn()
                }
            }))?
            .label(label)
            .legend(move |(x, y)| Circle::new((x + 8, y), 5, colour.filled()));
    }
    chart
        .draw_series(
            map.cells
                .iter()
                .filter(|c| c.silent)
                .map(|c| Circle::new((c.lens_sampling_ratio, y_of(c)), 11, RED.stroke_width(2))),
        )?
        .label("silent failure: guard accepts, error > tol")
        .legend(|(x, y)| Circle::new((x + 8, y), 6, RED.stroke_width(2)));
    chart
        .draw_series(std::iter::empty::<Circle<(f64, f64), i32>>())?
        .label("dot: guard accepts; cross: guard refuses")
        .legend(|(x, y)| Cross::new((x + 8, y), 5, BLACK.stroke_width(2)));
    super::style::draw_legend(&mut chart, SeriesLabelPosition::UpperLeft, 12)?;
    Ok(())
}

/// Writes one chart per stability map, `stability_<map name>.{png,svg}` ([`StabilityMap::name`])
/// at `path_for(name)`;
/// returns the names.
pub fn write_stability_charts(
    mut path_for: impl FnMut(&str) -> PathBuf,
    report: &StabilitySweepResults,
) -> Result<Vec<String>> {
    let mut names = Vec::new();
    for map in &report.maps {
        if map.cells.is_empty() {
            return Err(Error::data(
                DataCause::Empty,
                format!("the {} map has no runs to chart", map.name()),
            ));
        }
        for ext in ["png", "svg"] {
            let name = format!("stability_{}.{ext}", map.name());
            let path = path_for(&name);
            if ext == "png" {
                write_png_chart(&path, 1000, 650, |r| stability_map_chart(r, report, map))?;
            } else {
                write_svg_chart(&path, 1000, 650, |r| stability_map_chart(r, report, map))?;
            }
            names.push(name);
        }
    }
    Ok(names)
}

fn spectral_chart<DB: DrawingBackend>(root: &DrawingArea<DB, Shift>, report: &SpectralSweepResults) -> Drawn {
    root.fill(&WHITE)?;
    let caption = format!(
        "Spectral samples: error vs sub-bands per band ({}, {} DOE samples; reference {} sub-bands; silent failures: {})",
        report.method, report.doe_samples, report.reference_samples, report.silent_failures
    );
    let n_max = report
        .points
        .iter()
        .map(|p| p.samples)
        .chain(report.plans.iter().filter_map(|p| p.samples))
        .max()
        .unwrap_or(1) as f64;
    let mut chart = frame(root, caption, 17, 12, [40, 70]).build_cartesian_2d(
        (0.8..n_max * 1.25).log_scale(),
        log_range(
            report
                .points
                .iter()
                .flat_map(|p| [p.error, p.estimate])
                .chain(report.plans.iter().map(|p| p.tolerance)),
        )
        .log_scale(),
    )?;
    mesh(&mut chart, 13, 13, GridLines::Full)
        .x_desc("sub-bands per band N (midpoint rule; time = N monochromatic runs)")
        .y_desc("relative L2 error of the band's PSF")
        .x_label_formatter(&|v| format!("{v:.0}"))
        .y_label_formatter(&|v| format!("{v:.0e}"))
        .draw()?;
    let colours = [RED, GREEN, BLUE, MAGENTA, CYAN, BLACK];
    for (k, (band, _, _)) in report.bands.iter().enumerate() {
        let colour = colours[k % colours.len()];
        let series: Vec<(f64, f64, f64)> = report
            .points
            .iter()
            .filter(|p| &p.band == band)
            .map(|p| (p.samples as f64, p.error, p.estimate))
            .collect();
        chart
            .draw_series(LineSeries::new(series.iter().map(|p| (p.0, p.1)), colour.stroke_width(2)))?
            .label(format!("band {band}: measured"))
            .legend(line_key(16, colour.stroke_width(2)));
        chart.draw_series(series.iter().map(|p| Circle::new((p.0, p.1), 4, colour.filled())))?;
        // The estimate's dashes, and its legend sample's.
        const DASH: u32 = 6;
        const GAP: u32 = 4;
        chart
            .draw_series(DashedLineSeries::new(
                series.iter().map(|p| (p.0, p.2)),
                DASH,
                GAP,
                colour.stroke_width(1),
            ))?
            .label(format!("band {band}: plan's estimate"))
            .legend(move |at| super::style::dashed_legend(at, colour.stroke_width(1), DASH, GAP, 16));
    }
    for p in &report.plans {
        let tol = p.tolerance;
        chart.draw_series(DashedLineSeries::new(
            [(0.8, tol), (n_max * 1.25, tol)],
            3,
            5,
            BLACK.mix(0.5).stroke_width(1),
        ))?;
        let text = match (p.samples, p.error) {
            (Some(n), Some(err)) => {
                chart.draw_series(std::iter::once(Cross::new((n as f64, err), 8, BLACK.stroke_width(2))))?;
                format!(
                    "tolerance {tol:.0e}: estimate asks {}, the run settles on N = {n} ({})",
                    p.rule_samples.map_or("-".into(), |r| r.to_string()),
                    if p.meets_tolerance { "meets" } else { "MISSES" }
                )
            }
            _ if p.not_scored.is_some() => {
                format!("tolerance {tol:.0e}: the run outgrew the reference, not scored")
            }
            _ => format!("tolerance {tol:.0e}: plan refuses"),
        };
        chart.draw_series(std::iter::once(Text::new(text, (0.9, tol * 1.15), (FONT, 12))))?;
    }
    chart
        .draw_series(std::iter::empty::<Cross<(f64, f64), i32>>())?
        .label("cross: the plan's run at a tolerance (N it settled on, worst band)")
        .legend(|(x, y)| Cross::new((x + 8, y), 5, BLACK.stroke_width(2)));
    super::style::draw_legend(&mut chart, SeriesLabelPosition::UpperRight, 12)?;
    Ok(())
}

/// Writes `spectral.{png,svg}` at `path_for(name)`; returns the names.
pub fn write_spectral_charts(
    mut path_for: impl FnMut(&str) -> PathBuf,
    report: &SpectralSweepResults,
) -> Result<Vec<String>> {
    if report.points.is_empty() {
        return Err(Error::data(DataCause::Empty, "the spectral sweep has no runs to chart"));
    }
    let png = "spectral.png".to_string();
    write_png_chart(&path_for(&png), 1000, 650, |r| spectral_chart(r, report))?;
    let svg = "spectral.svg".to_string();
    write_svg_chart(&path_for(&svg), 1000, 650, |r| spectral_chart(r, report))?;
    Ok(vec![png, svg])
}

#[cfg(test)]
mod tests {
    use super::*;

    fn point(method: &str, s: usize, seconds: f64, error: f64, valid: bool) -> PsfSweepPoint {
        PsfSweepPoint {
            series: format!("{method} f64"),
            method: method.into(),
            precision: "f64".into(),
            padding: 1.0,
            subsample: s,
            pixel_rule: "midpoint".into(),
            pupil_pitch: 3e-6 / s as f64,
            seconds,
            error,
            violations: if valid { vec![] } else { vec!["lens_sampling".into()] },
            pareto: valid && s == 1,
        }
    }

    #[test]
    fn the_chart_files_are_written() {
        let pts = vec![
            point("matrix_dft", 1, 0.01, 1e-3, true),
            point("matrix_dft", 2, 0.02, 1e-5, true),
            point("fresnel", 1, 0.05, 1e-1, false),
            point("fresnel", 2, 0.1, 1e-4, true),
        ];
        let plan = crate::sweep::psf::PlanPoint {
            tolerance: 1e-3,
            method: "matrix_dft".into(),
            precision: "f32".into(),
            subsample: 2,
            pupil_pitch: 3e-6,
            estimated_error: 5e-4,
            seconds: 0.015,
            error: 2e-5,
            meets_tolerance: true,
            cheapest_adequate: Some("matrix_dft f64 s=2".into()),
            time_ratio: Some(0.75),
        };
        let mut report = PsfSweepResults {
            units: String::new(),
            doe_samples: 112,
            doe_pitch: 5e-6,
            aperture: 5e-4,
            f_number: 7.0,
            wavelengths: vec![635e-9],
            crop: 40,
            budget_seconds: 10.0,
            reference: crate::sweep::psf::Reference { subsamples: [7, 9], difference: 1e-9, seconds: 0.1 },
            points: pts,
            plans: vec![plan],
            silent_failures: 0,
            skipped: vec![],
        };
        let d = tempfile::tempdir().unwrap();
        let names = write_psf_charts(|n| d.path().join(n), &report).unwrap();
        for n in &names {
            let len = std::fs::metadata(d.path().join(n)).unwrap().len();
            assert!(len > 1000, "{n}: {len} bytes");
        }
        let svg = std::fs::read_to_string(d.path().join("speed_accuracy.svg")).unwrap();
        assert!(svg.contains("Pareto front") && svg.contains("fresnel f64") && svg.contains("plan at 1e-3"));
        // The stability chart's x axis labels each whole sub-sampling once.
        let svg = std::fs::read_to_string(d.path().join("stability.svg")).unwrap();
        let labels: Vec<&str> = svg
            .split("</text>")
            .filter_map(|t| t.rsplit('>').next().map(str::trim))
            .filter(|t| t.len() == 1 && t.chars().all(|c| c.is_ascii_digit()))
            .collect();
        assert_eq!(labels, ["1", "2"], "{svg}");
        // A budget that left everything out: the charts are still written, and say so.
        report.points.clear();
        report.skipped = vec![
            "matrix_dft f32 s=1 (budget: 1.0 s predicted, 0.0 s left)".into(),
            "fresnel f64 pad 3 s=5 (memory)".into(),
        ];
        write_psf_charts(|n| d.path().join(n), &report).unwrap();
        let svg = std::fs::read_to_string(d.path().join("speed_accuracy.svg")).unwrap();
        assert!(svg.contains("left out by the budget: 1\n"), "{svg}");
        assert!(svg.contains("left out for memory: 1\n") && svg.contains("silent failures: 0 "), "{svg}");
    }
}
