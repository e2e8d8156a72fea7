//! The decoder sweep's charts (`doefab bench decoder`):
//!
//! * [`write_decoder_scene_chart`]: decoder x scene, grouped bars of PSNR-L and PSNR-gamma over
//!   all scored pixels, PSNR-gamma over the saturated ones and the smallest output, one group
//!   per scored scene (labelled with its coverage), one colour per decoder; refused scenes are
//!   listed under the chart with their reason.
//! * [`write_sweep_chart`]: PSNR-gamma of the decoder being fine-tuned against its training
//!   time, against the other decoders of each scene (horizontal lines), over all scored pixels
//!   and the saturated ones, and its validation PSNR on the held-out simulated set.

use std::path::Path;

use plotters::prelude::*;

use super::style::{frame, line_key, mesh, write_png_chart, GridLines, FONT};
use crate::error::{DataCause, Error, Result};
use crate::sweep::decoder::{DecoderSweepResults, Score};

const COLORS: [RGBColor; 8] = [
    RGBColor(127, 127, 127),
    RGBColor(31, 119, 180),
    RGBColor(214, 39, 40),
    RGBColor(44, 160, 44),
    RGBColor(148, 103, 189),
    RGBColor(255, 127, 14),
    RGBColor(23, 190, 207),
    RGBColor(188, 189, 34),
];

/// One panel's quantity.
type Metric = (&'static str, &'static str, fn(&Score) -> Option<f64>);

/// Draws `report`'s decoder x scene scores into `path` (PNG, 1400 x 900).
pub fn write_decoder_scene_chart(path: &Path, report: &DecoderSweepResults) -> Result<()> {
    let scenes: Vec<(String, f64)> = report
        .scenes
        .iter()
        .filter_map(|s| s.footing.as_ref().map(|f| (s.name.clone(), f.coverage)))
        .collect();
    if scenes.is_empty() || report.scores.is_empty() {
        return Err(Error::data(DataCause::Empty, "no scored scene to chart"));
    }
    let refused: Vec<String> = report
        .scenes
        .iter()
        .filter_map(|s| s.error.as_ref().map(|e| format!("{} refused: {}", s.name, e)))
        .collect();
    let metrics: [Metric; 4] = [
        ("PSNR-L, all scored pixels", "dB", |s| Some(s.all.linear_db)),
        ("PSNR-gamma, all scored pixels", "dB", |s| Some(s.all.gamma_db)),
        ("PSNR-gamma, saturated pixels of the capture", "dB", |s| s.saturated.as_ref().map(|p| p.gamma_db)),
        ("smallest output (whole image)", "capture clipping level", |s| Some(s.min_output)),
    ];
    let nd = report.decoders.len();
    write_png_chart(path, 1400, 900, |root| {
        let footer = 18 * refused.len().min(4) as u32;
        let (main, foot) = root.split_vertically(900 - footer);
        for (k, line) in refused.iter().take(4).enumerate() {
            let text: String = line.chars().take(190).collect();
            foot.draw(&Text::new(text, (10, 18 * k as i32 + 2), (FONT, 13)))?;
        }
        for (panel, (title, unit, value)) in main.split_evenly((2, 2)).iter().zip(metrics) {
            let values: Vec<f64> = report.scores.iter().filter_map(value).collect();
            let (lo, hi) =
                values.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &v| (a.min(v), b.max(v)));
            if !lo.is_finite() {
                continue;
            }
            // Bars start from the axis floor: a little under the smallest value (dB), or 0.
            let floor = if unit == "dB" { (lo - 3.0).floor() } else { lo.min(0.0) * 1.1 };
            let top = hi + 0.1 * (hi - floor).max(1e-3);
            let mut chart = frame(panel, title, 17, 10, [30, 60])
                .build_cartesian_2d(0.0..scenes.len() as f64, floor..top)?;
            let names = scenes.clone();
            mesh(&mut chart, 12, 12, GridLines::Full)
                .disable_x_mesh()
                .x_labels(scenes.len() * 2 + 1)
                .x_label_formatter(&move |x| {
                    let k = x.floor() as usize;
                    if (x - k as f64 - 0.5).abs() < 1e-6 && k < names.len() {
                        format!("{} ({:.0} % scored)", names[k].0, 100.0 * names[k].1)
                    } else {
                        String::new()
                    }
                })
                .y_desc(unit)
                .draw()?;
            let width = 0.8 / nd as f64;
            for (d, decoder) in report.decoders.iter().enumerate() {
                let color = COLORS[d % COLORS.len()];
                let bars: Vec<Rectangle<(f64, f64)>> = scenes
                    .iter()
                    .enumerate()
                    .filter_map(|(k, (scene, _))| {
                        let s = report.scores.iter().find(|s| &s.scene == scene && &s.decoder == decoder)?;
                        let v = value(s)?;
                        let x0 = k as f64 + 0.1 + d as f64 * width;
                        Some(Rectangle::new([(x0, floor), (x0 + width * 0.9, v)], color.filled()))
                    })
                    .collect();
                let short: String = decoder.chars().take(60).collect();
                chart
                    .draw_series(bars)?
                    .label(short)
                    .legend(move |(x, y)| Rectangle::new([(x, y - 5), (x + 14, y + 5)], color.filled()));
            }
            super::style::draw_legend(&mut chart, SeriesLabelPosition::LowerRight, 11)?;
        }
        Ok(())
    })
}

/// Draws the fine-tuning curve of `report` into `path` (PNG, 1650 x 500): three panels against
/// the training time in minutes (wall clock on the machine's threads, scoring excluded), the
/// step count in the captions. The validation points' times are their steps times the run's
/// mean seconds per step.
pub fn write_sweep_chart(path: &Path, report: &DecoderSweepResults) -> Result<()> {
    let Some(run) = &report.finetune else {
        return Err(Error::data(DataCause::Empty, "no fine-tuning run to chart"));
    };
    if run.curve.is_empty() {
        return Err(Error::data(DataCause::Empty, "no fine-tuning points to chart"));
    }
    let minutes = |seconds: f64| seconds / 60.0;
    let last = run.curve.iter().map(|p| minutes(p.seconds)).fold(0.0, f64::max).max(1e-3);
    let steps = run.curve.iter().map(|p| p.step).max().unwrap_or(0);
    let threads = rayon::current_num_threads();
    let x_desc = format!("training time, minutes ({steps} steps, {threads} threads)");
    let scenes: Vec<&str> =
        report.scenes.iter().filter(|s| s.footing.is_some()).map(|s| s.name.as_str()).collect();
    let others: Vec<&String> = report.decoders.iter().filter(|d| !d.starts_with("fine-tuned here")).collect();
    // How each other decoder's line is dashed: 0 for the run's start, then 1, 2, 3 in turn.
    let mut turn = 0;
    let dash_kinds: Vec<usize> = others
        .iter()
        .map(|d| match **d == run.init {
            true => 0,
            false => {
                turn += 1;
                1 + (turn - 1) % 3
            }
        })
        .collect();
    write_png_chart(path, 1650, 500, |root| {
        let panels = root.split_evenly((1, 3));
        for (panel, saturated) in panels.iter().zip([false, true]) {
            let value = |s: &Score| {
                if saturated {
                    s.saturated.as_ref().map(|p| p.gamma_db)
                } else {
                    Some(s.all.gamma_db)
                }
            };
            let all: Vec<f64> = run
                .curve
                .iter()
                .flat_map(|p| p.scores.iter())
                .chain(report.scores.iter())
                .filter_map(value)
                .collect();
            let (lo, hi) =
                all.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &v| (a.min(v), b.max(v)));
            if !lo.is_finite() {
                continue;
            }
            let title = if saturated { "saturated pixels of the capture" } else { "all scored pixels" };
            let mut chart = frame(panel, format!("PSNR-gamma, {title}"), 18, 12, [40, 60])
                // Room under the data for the legend, so that it covers no line.
                .build_cartesian_2d(0.0..last, (lo - 0.5 - 0.6 * (hi - lo))..(hi + 0.5))?;
            mesh(&mut chart, 13, 13, GridLines::Full).x_desc(x_desc.as_str()).y_desc("dB").draw()?;
            for (k, scene) in scenes.iter().enumerate() {
                let color = COLORS[(k + 1) % COLORS.len()];
                let line: Vec<(f64, f64)> = run
                    .curve
                    .iter()
                    .filter_map(|p| value(p.scores.get(k)?).map(|v| (minutes(p.seconds), v)))
                    .collect();
                chart
                    .draw_series(LineSeries::new(line.iter().copied(), color.stroke_width(2)))?
                    .label(format!("{scene}: fine-tuned here"))
                    .legend(line_key(18, color.stroke_width(2)));
                chart.draw_series(line.iter().map(|&p| Circle::new(p, 3, color.filled())))?;
                for (decoder, &kind) in others.iter().zip(&dash_kinds) {
                    let Some(v) = report
                        .scores
                        .iter()
                        .find(|s| s.scene == *scene && &s.decoder == *decoder)
                        .and_then(value)
                    else {
                        continue;
                    };
                    // One thin line per other decoder, told apart by its dashes: the start
                    // of the run in long dashes, the others solid, then dotted, then short dashes.
                    let start = kind == 0;
                    let style = color.stroke_width(1);
                    // (dash, gap) in pixels.
                    let (dash, gap): (u32, u32) = match kind {
                        0 => (10, 5),
                        1 => (10_000, 1),
                        2 => (2, 4),
                        _ => (5, 4),
                    };
                    let short: String = decoder.chars().take(44).collect();
                    let label = format!("{scene}: {short}{}", if start { " (the start)" } else { "" });
                    chart
                        .draw_series(DashedLineSeries::new([(0.0, v), (last, v)], dash, gap, style))?
                        .label(label)
                        .legend(move |at| super::style::dashed_legend(at, style, dash, gap, 18));
                }
            }
            super::style::draw_legend(&mut chart, SeriesLabelPosition::LowerRight, 11)?;
        }
        let validation: Vec<(f64, f64)> = run
            .history
            .iter()
            .filter_map(|h| h.val_psnr.map(|v| (minutes(h.step as f64 * run.seconds_per_step), v)))
            .collect();
        if let Some(&(_, first)) = validation.first() {
            let (lo, hi) = validation
                .iter()
                .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &(_, v)| (a.min(v), b.max(v)));
            let mut chart = frame(&panels[2], "validation PSNR (held-out simulated set)", 18, 12, [40, 60])
                .build_cartesian_2d(0.0..last, (lo - 0.2)..(hi + 0.2))?;
            mesh(&mut chart, 13, 13, GridLines::Full)
                .x_desc(x_desc.as_str())
                .y_desc("dB (sqrt domain, peak 1)")
                .draw()?;
            chart
                .draw_series(LineSeries::new([(0.0, first), (last, first)], BLACK.stroke_width(1)))?
                .label("the start")
                .legend(line_key(18, BLACK));
            chart
                .draw_series(LineSeries::new(validation.iter().copied(), RED.stroke_width(2)))?
                .label("fine-tuned here")
                .legend(line_key(18, RED.stroke_width(2)));
            chart.draw_series(validation.iter().map(|&p| Circle::new(p, 3, RED.filled())))?;
            super::style::draw_legend(&mut chart, SeriesLabelPosition::LowerRight, 11)?;
        }
        Ok(())
    })
}

/// Draws `report` (`doefab bench forward`) into `path` (PNG, 1400 x 900), a column per scene:
/// above, the residual of each model (a colour each, in the order they add to one another) in
/// each brightness band; below, the halo model's residual over all unsaturated pixels against
/// the halo's fraction, a line per radius, the paper model's as a dashed line.
pub fn write_forward_chart(path: &Path, report: &crate::sweep::forward::ForwardSweepResults) -> Result<()> {
    let scenes = &report.scenes;
    if scenes.is_empty() {
        return Err(Error::data(DataCause::Empty, "no scene to chart"));
    }
    let bands = ["darks", "mid-tones", "brights", "flare ring", "all"];
    write_png_chart(path, 1400, 900, |root| {
        let columns = root.split_evenly((2, scenes.len()));
        for (k, scene) in scenes.iter().enumerate() {
            let values = |m: &crate::sweep::forward::ModelFit| {
                let r = &m.residuals;
                [r.dark, r.mid, r.bright, r.ring, r.all]
            };
            let top =
                scene.models.iter().flat_map(&values).filter(|v| v.is_finite()).fold(0.0, f64::max) * 1.15;
            let mut chart = frame(
                &columns[k],
                format!(
                    "{}: sqrt-domain residual, capture - model ({:.0} % scored)",
                    scene.name,
                    100.0 * scene.coverage
                ),
                16,
                10,
                [30, 60],
            )
            .build_cartesian_2d(0.0..bands.len() as f64, 0.0..top.max(1e-3))?;
            mesh(&mut chart, 12, 12, GridLines::Full)
                .disable_x_mesh()
                .x_labels(bands.len() * 2 + 1)
                .x_label_formatter(&|x| {
                    let b = x.floor() as usize;
                    if (x - b as f64 - 0.5).abs() < 1e-6 && b < bands.len() {
                        bands[b].to_string()
                    } else {
                        String::new()
                    }
                })
                .y_desc("RMS of sqrt(model) - sqrt(capture)")
                .draw()?;
            let width = 0.8 / scene.models.len() as f64;
            for (m, model) in scene.models.iter().enumerate() {
                let color = COLORS[m % COLORS.len()];
                let bars: Vec<Rectangle<(f64, f64)>> = values(model)
                    .iter()
                    .enumerate()
                    .filter(|(_, v)| v.is_finite())
                    .map(|(b, &v)| {
                        let x0 = b as f64 + 0.1 + m as f64 * width;
                        Rectangle::new([(x0, 0.0), (x0 + 0.9 * width, v)], color.filled())
                    })
                    .collect();
                let mut label = model.model.clone();
                if let Some(h) = &model.halo {
                    label += &format!(" (eta {}, rho {} px", h.fraction, h.radius_px);
                    label += &if model.model.contains("blur") {
                        format!(", sigma {} px)", model.blur_px)
                    } else {
                        ")".into()
                    };
                }
                chart
                    .draw_series(bars)?
                    .label(label)
                    .legend(move |(x, y)| Rectangle::new([(x, y - 5), (x + 14, y + 5)], color.filled()));
            }
            super::style::draw_legend(&mut chart, SeriesLabelPosition::UpperLeft, 11)?;

            // The halo grid.
            let grid = &scene.halo_grid;
            let finite = grid.iter().flatten().copied().filter(|v| v.is_finite());
            let paper = scene.models.first().map_or(f64::NAN, |m| m.residuals.all);
            let (lo, hi) = finite
                .chain([paper])
                .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), v| (a.min(v), b.max(v)));
            let pad = 0.1 * (hi - lo).max(1e-4);
            let fmax = report.halo_fractions.iter().copied().fold(0.0, f64::max);
            let mut chart = frame(
                &columns[scenes.len() + k],
                format!("{}: halo model, all unsaturated pixels", scene.name),
                16,
                10,
                [35, 60],
            )
            .build_cartesian_2d(0.0..fmax * 1.05, (lo - pad)..(hi + pad))?;
            mesh(&mut chart, 12, 12, GridLines::Full)
                .x_desc("halo fraction eta")
                .y_desc("RMS of sqrt(model) - sqrt(capture)")
                .draw()?;
            for (r, radius) in report.halo_radii_px.iter().enumerate() {
                let color = COLORS[(r + 1) % COLORS.len()];
                let points: Vec<(f64, f64)> = report
                    .halo_fractions
                    .iter()
                    .zip(grid)
                    .map(|(&f, row)| (f, row[r]))
                    .filter(|p| p.1.is_finite())
                    .collect();
                chart
                    .draw_series(LineSeries::new(points.clone(), color.stroke_width(2)))?
                    .label(format!("rho {radius} px"))
                    .legend(line_key(16, color.stroke_width(2)));
                chart.draw_series(points.iter().map(|&p| Circle::new(p, 3, color.filled())))?;
            }
            if paper.is_finite() {
                chart
                    .draw_series(DashedLineSeries::new(
                        [(0.0, paper), (fmax * 1.05, paper)],
                        6,
                        4,
                        BLACK.stroke_width(1),
                    ))?
                    .label("paper model")
                    .legend(line_key(16, BLACK.stroke_width(1)));
            }
            super::style::draw_legend(&mut chart, SeriesLabelPosition::UpperRight, 11)?;
        }
        Ok(())
    })
}
