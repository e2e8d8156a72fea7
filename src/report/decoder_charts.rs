//! The decoder benchmark's chart: PSNR-gamma on the real scenes along the fine-tuning, against
//! the paper's measured-PSF decoder and the capture as it is (horizontal lines), over all
//! registered pixels (left) and the saturated ones (right), as a PNG.

use std::path::Path;

use plotters::prelude::*;

use crate::decoder::bench::{BenchReport, CAPTURE, PAPER};
use crate::error::{Error, Result};
use crate::report::{write_png_chart, FONT};

/// Draws `report`'s curve into `path` (PNG, 1200 x 500).
pub fn write_bench_chart(path: &Path, report: &BenchReport) -> Result<()> {
    if report.curve.is_empty() {
        return Err(Error::Data("no fine-tuning points to chart".into()));
    }
    let last = report.curve.iter().map(|p| p.step).max().unwrap_or(0).max(1) as f64;
    let colors =
        [RGBColor(31, 119, 180), RGBColor(214, 39, 40), RGBColor(44, 160, 44), RGBColor(148, 103, 189)];
    write_png_chart(path, 1200, 500, |root| {
        let e = |e: &dyn std::fmt::Display| e.to_string();
        let panels = root.split_evenly((1, 2));
        for (panel, saturated) in panels.iter().zip([false, true]) {
            // PSNR-gamma of a score over the panel's pixel set.
            let value = |s: &crate::decoder::bench::Score| {
                if saturated {
                    s.saturated.as_ref().map(|p| p.gamma_db)
                } else {
                    Some(s.all.gamma_db)
                }
            };
            let all: Vec<f64> = report
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
            let title = if saturated { "saturated pixels of the capture" } else { "all registered pixels" };
            let mut chart = ChartBuilder::on(panel)
                .caption(format!("PSNR-gamma, {title}"), (FONT, 18))
                .margin(12)
                .x_label_area_size(40)
                .y_label_area_size(60)
                .build_cartesian_2d(0.0..last, (lo - 0.5)..(hi + 0.5))
                .map_err(|x| e(&x))?;
            chart
                .configure_mesh()
                .x_desc("fine-tuning step")
                .y_desc("dB")
                .label_style((FONT, 13))
                .draw()
                .map_err(|x| e(&x))?;
            for (k, scene) in report.scenes.iter().enumerate() {
                let color = colors[k % colors.len()];
                let line: Vec<(f64, f64)> = report
                    .curve
                    .iter()
                    .filter_map(|p| value(p.scores.get(k)?).map(|v| (p.step as f64, v)))
                    .collect();
                chart
                    .draw_series(LineSeries::new(line.iter().copied(), color.stroke_width(2)))
                    .map_err(|x| e(&x))?
                    .label(format!("{}: fine-tuned here", scene.name))
                    .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 18, y)], color.stroke_width(2)));
                chart
                    .draw_series(line.iter().map(|&p| Circle::new(p, 3, color.filled())))
                    .map_err(|x| e(&x))?;
                for (decoder, style) in
                    [(PAPER, color.stroke_width(1)), (CAPTURE, color.mix(0.4).stroke_width(1))]
                {
                    let Some(v) = report
                        .scores
                        .iter()
                        .find(|s| s.scene == scene.name && s.decoder == decoder)
                        .and_then(value)
                    else {
                        continue;
                    };
                    chart
                        .draw_series(LineSeries::new([(0.0, v), (last, v)], style))
                        .map_err(|x| e(&x))?
                        .label(format!("{}: {decoder}", scene.name))
                        .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 18, y)], style));
                }
            }
            crate::report::draw_legend(&mut chart, SeriesLabelPosition::LowerRight, 12)?;
        }
        Ok(())
    })
}
