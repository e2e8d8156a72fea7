//! The fine-tuning curve: training loss per step (log scale, left) and validation PSNR at each
//! evaluation (right axis), as a PNG.

use std::path::Path;

use plotters::prelude::*;

use crate::decoder::finetune::HistoryEntry;
use crate::error::{Error, Result};
use crate::report::{write_png_chart, FONT};

/// Draws the training curve of `history` into `path` (PNG, 900 x 500).
pub fn write_training_chart(path: &Path, history: &[HistoryEntry]) -> Result<()> {
    let losses: Vec<(f64, f64)> = history
        .iter()
        .filter_map(|h| h.loss.filter(|l| l.is_finite() && *l > 0.0).map(|l| (h.step as f64, l)))
        .collect();
    let psnr: Vec<(f64, f64)> =
        history.iter().filter_map(|h| h.val_psnr.map(|p| (h.step as f64, p))).collect();
    if losses.is_empty() && psnr.is_empty() {
        return Err(Error::Data("no training steps to chart".into()));
    }
    let last = history.iter().map(|h| h.step).max().unwrap_or(1).max(1) as f64;
    let (lo, hi) =
        losses.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &(_, l)| (a.min(l), b.max(l)));
    let (lo, hi) = if lo.is_finite() { (lo / 1.2, hi * 1.2) } else { (1e-3, 1.0) };
    let (plo, phi) =
        psnr.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &(_, p)| (a.min(p), b.max(p)));
    let (plo, phi) = if plo.is_finite() { (plo - 0.5, phi + 0.5) } else { (0.0, 1.0) };
    write_png_chart(path, 900, 500, |root| {
        let e = |e: &dyn std::fmt::Display| e.to_string();
        let mut chart = ChartBuilder::on(root)
            .caption("Decoder fine-tuning", (FONT, 22))
            .margin(12)
            .x_label_area_size(40)
            .y_label_area_size(70)
            .right_y_label_area_size(70)
            .build_cartesian_2d(0.0..last, (lo..hi).log_scale())
            .map_err(|x| e(&x))?
            .set_secondary_coord(0.0..last, plo..phi);
        chart
            .configure_mesh()
            .x_desc("step")
            .y_desc("training loss (sqrt domain)")
            .label_style((FONT, 13))
            .draw()
            .map_err(|x| e(&x))?;
        chart
            .configure_secondary_axes()
            .y_desc("validation PSNR, dB")
            .label_style((FONT, 13))
            .draw()
            .map_err(|x| e(&x))?;
        chart
            .draw_series(LineSeries::new(losses.iter().copied(), &BLUE))
            .map_err(|x| e(&x))?
            .label("training loss")
            .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 18, y)], BLUE));
        chart
            .draw_secondary_series(LineSeries::new(psnr.iter().copied(), RED.stroke_width(2)))
            .map_err(|x| e(&x))?
            .label("validation PSNR")
            .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 18, y)], RED));
        chart
            .draw_secondary_series(psnr.iter().map(|&p| Circle::new(p, 3, RED.filled())))
            .map_err(|x| e(&x))?;
        crate::report::draw_legend(&mut chart, SeriesLabelPosition::MiddleRight, 13)?;
        Ok(())
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn chart_draws_loss_and_psnr() {
        let history: Vec<HistoryEntry> = (0..=20)
            .map(|s| HistoryEntry {
                step: s,
                loss: (s > 0).then(|| 0.1 / (s as f64).sqrt()),
                val_loss: (s % 5 == 0).then_some(0.05),
                val_psnr: (s % 5 == 0).then_some(20.0 + s as f64 / 5.0),
            })
            .collect();
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("curve.png");
        write_training_chart(&path, &history).unwrap();
        let img = image::open(&path).unwrap().to_rgb8();
        let blue = img.pixels().filter(|p| p[2] > 200 && p[0] < 60 && p[1] < 60).count();
        let red = img.pixels().filter(|p| p[0] > 200 && p[1] < 60 && p[2] < 60).count();
        assert!(blue > 100 && red > 100, "blue {blue} red {red}");
        assert!(write_training_chart(&path, &[]).is_err());
    }
}
