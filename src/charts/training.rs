//! The fine-tuning curves: training loss per step (log scale, left) and validation PSNR at
//! each evaluation (right axis), as a PNG ([`write_training_chart`]); validation PSNR against
//! training time, the report's ([`write_finetune_time_chart`]).

use std::path::{Path, PathBuf};

use plotters::coord::Shift;
use plotters::prelude::*;

use super::style::{
    frame, line_key, mesh, secondary_axes, write_png_chart, write_svg_chart, Drawn, GridLines,
};
use crate::decoder::finetune::HistoryEntry;
use crate::error::{DataCause, Error, Result};
use crate::sweep::finetune_time::TimedFinetune;

/// Draws the training curve of `history` into `path` (PNG, 900 x 500).
pub fn write_training_chart(path: &Path, history: &[HistoryEntry]) -> Result<()> {
    let losses: Vec<(f64, f64)> = history
        .iter()
        .filter_map(|h| h.loss.filter(|l| l.is_finite() && *l > 0.0).map(|l| (h.step as f64, l)))
        .collect();
    let psnr: Vec<(f64, f64)> =
        history.iter().filter_map(|h| h.val_psnr.map(|p| (h.step as f64, p))).collect();
    if losses.is_empty() && psnr.is_empty() {
        return Err(Error::data(DataCause::Empty, "no training steps to chart"));
    }
    let last = history.iter().map(|h| h.step).max().unwrap_or(1).max(1) as f64;
    let (lo, hi) =
        losses.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &(_, l)| (a.min(l), b.max(l)));
    let (lo, hi) = if lo.is_finite() { (lo / 1.2, hi * 1.2) } else { (1e-3, 1.0) };
    let (plo, phi) =
        psnr.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &(_, p)| (a.min(p), b.max(p)));
    let (plo, phi) = if plo.is_finite() { (plo - 0.5, phi + 0.5) } else { (0.0, 1.0) };
    write_png_chart(path, 900, 500, |root| {
        let mut chart = frame(root, "Decoder fine-tuning", 22, 12, [40, 70])
            .right_y_label_area_size(70)
            .build_cartesian_2d(0.0..last, (lo..hi).log_scale())?
            .set_secondary_coord(0.0..last, plo..phi);
        mesh(&mut chart, 13, 13, GridLines::Full)
            .x_desc("step")
            .y_desc("training loss (sqrt domain)")
            .draw()?;
        secondary_axes(&mut chart, 13, 13).y_desc("validation PSNR, dB").draw()?;
        chart
            .draw_series(LineSeries::new(losses.iter().copied(), &BLUE))?
            .label("training loss")
            .legend(line_key(18, BLUE));
        chart
            .draw_secondary_series(LineSeries::new(psnr.iter().copied(), RED.stroke_width(2)))?
            .label("validation PSNR")
            .legend(line_key(18, RED));
        chart.draw_secondary_series(psnr.iter().map(|&p| Circle::new(p, 3, RED.filled())))?;
        super::style::draw_legend(&mut chart, SeriesLabelPosition::MiddleRight, 13)?;
        Ok(())
    })
}

fn finetune_time_chart<DB: DrawingBackend>(root: &DrawingArea<DB, Shift>, r: &TimedFinetune) -> Drawn {
    root.fill(&WHITE)?;
    let minutes = |s: f64| s / 60.0;
    let last = r.points.iter().map(|p| minutes(p.seconds)).fold(0.0, f64::max).max(1e-3);
    let (lo, hi) = r
        .points
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), p| (a.min(p.val_psnr), b.max(p.val_psnr)));
    if !lo.is_finite() {
        return Err("no validation to chart".into());
    }
    let pad = ((hi - lo) * 0.15).max(0.1);
    let mut c = frame(
        root,
        format!(
            "Fine-tuning {} on {}: held-out validation PSNR against training time",
            r.init.split(' ').next().unwrap_or(""),
            r.training_data
        ),
        16,
        12,
        [44, 60],
    )
    .build_cartesian_2d(0.0..last * 1.05, (lo - pad)..(hi + pad))?;
    let x_desc = format!(
        "training time, minutes of wall clock on {} threads ({} steps of {} x {}^2, {:.2} s a step)",
        r.threads, r.steps, r.batch, r.crop, r.seconds_per_step
    );
    mesh(&mut c, 12, 12, GridLines::Full).x_desc(x_desc).y_desc("validation PSNR, dB").draw()?;
    let (start, best) = r.start_and_best();
    c.draw_series(LineSeries::new([(0.0, start), (last * 1.05, start)], BLACK.stroke_width(1)))?
        .label(format!("the start, {start:.2} dB"))
        .legend(line_key(18, BLACK));
    let line: Vec<(f64, f64)> = r.points.iter().map(|p| (minutes(p.seconds), p.val_psnr)).collect();
    c.draw_series(LineSeries::new(line.clone(), BLUE.stroke_width(2)))?
        .label(format!("fine-tuned, best {best:.2} dB"))
        .legend(line_key(18, BLUE.stroke_width(2)));
    c.draw_series(line.iter().map(|&p| Circle::new(p, 4, BLUE.filled())))?;
    if let Some(s) = r.half_gain_seconds() {
        let at = minutes(s);
        c.draw_series(LineSeries::new([(at, lo - pad), (at, hi + pad)], RED.stroke_width(1)))?
            .label(format!("half the gain, {s:.0} s"))
            .legend(line_key(18, RED));
    }
    super::style::draw_legend(&mut c, SeriesLabelPosition::LowerRight, 12)?;
    Ok(())
}

/// Writes `finetune_time.{png,svg}` at `path_for(name)`: validation PSNR against training
/// minutes, the start and the time of half the gain drawn. Returns the names.
pub fn write_finetune_time_chart(
    mut path_for: impl FnMut(&str) -> PathBuf,
    r: &TimedFinetune,
) -> Result<Vec<String>> {
    write_png_chart(&path_for("finetune_time.png"), 1000, 520, |root| finetune_time_chart(root, r))?;
    write_svg_chart(&path_for("finetune_time.svg"), 1000, 520, |root| finetune_time_chart(root, r))?;
    Ok(vec!["finetune_time.png".into(), "finetune_time.svg".into()])
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
                grad_norm: None,
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

    /// The time chart is written as PNG and SVG with the start, the best and the time of half
    /// the gain (the first validation half-way from the start to the best: 10.9 dB at 5 s is
    /// short of 11, 11.0 at 10 s is not) in its legend; a run without validations is refused.
    #[test]
    fn the_time_chart_names_the_start_the_best_and_half_the_gain() {
        use crate::sweep::finetune_time::TimedPoint;
        let point = |step, seconds, val_psnr| TimedPoint { step, seconds, val_psnr };
        let mut r = TimedFinetune {
            init: "built-in:paper-measured-psf (sha256 x)".into(),
            psf: "p".into(),
            training_data: "procedural scenes".into(),
            batch: 2,
            crop: 64,
            validation_views: 2,
            threads: 1,
            steps: 3,
            seconds_per_step: 5.0,
            total_seconds: 16.0,
            points: vec![
                point(0, 0.0, 10.0),
                point(1, 5.0, 10.9),
                point(2, 10.0, 11.0),
                point(3, 15.0, 12.0),
            ],
            units: "",
        };
        let dir = tempfile::tempdir().unwrap();
        let names = write_finetune_time_chart(|n| dir.path().join(n), &r).unwrap();
        assert_eq!(names, ["finetune_time.png", "finetune_time.svg"]);
        for n in &names {
            assert!(std::fs::metadata(dir.path().join(n)).unwrap().len() > 1000, "{n}");
        }
        let svg = std::fs::read_to_string(dir.path().join("finetune_time.svg")).unwrap();
        for text in ["the start, 10.00 dB", "fine-tuned, best 12.00 dB", "half the gain, 10 s"] {
            assert!(svg.contains(text), "{text}");
        }
        r.points.clear();
        assert!(write_finetune_time_chart(|n| dir.path().join(n), &r).is_err());
    }
}
