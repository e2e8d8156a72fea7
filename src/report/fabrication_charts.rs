//! Charts of the fabrication loop: what pre-compensation gains against the process's blur.

use std::path::Path;

use plotters::prelude::*;

use crate::error::Result;
use crate::report::{draw_legend, write_png_chart, write_svg_chart, FONT};

/// One blur width of the chart: the blur in samples, and before/after pairs of the height RMS
/// (metres) and of the PSF's relative L2 against the design's.
pub struct GainPoint {
    pub blur_samples: f64,
    pub rms: [f64; 2],
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
    ) -> std::result::Result<(), String> {
        let err = |e: DrawingAreaErrorKind<DB::ErrorType>| e.to_string();
        let mut ch = ChartBuilder::on(root)
            .caption("pre-compensation: error of the plain mask / error of the corrected one", (FONT, 17))
            .margin(14)
            .x_label_area_size(44)
            .y_label_area_size(64)
            .build_cartesian_2d(0.0..x1, 0.0..y1)
            .map_err(err)?;
        ch.configure_mesh()
            .x_desc("process blur (standard deviation, design samples)")
            .y_desc("gain (before / after)")
            .label_style((FONT, 13))
            .axis_desc_style((FONT, 14))
            .draw()
            .map_err(err)?;
        ch.draw_series(LineSeries::new([(0.0, 2.0), (x1, 2.0)], BLACK.mix(0.4).stroke_width(1)))
            .map_err(err)?
            .label("2x")
            .legend(|(x, y)| PathElement::new([(x, y), (x + 18, y)], BLACK.mix(0.4)));
        ch.draw_series(LineSeries::new([(0.0, 1.0), (x1, 1.0)], BLACK.stroke_width(1))).map_err(err)?;
        for (data, colour, label) in [(rms, BLUE, "height RMS"), (psf, RED, "PSF relative L2")] {
            ch.draw_series(LineSeries::new(data.iter().copied(), colour.stroke_width(2)))
                .map_err(err)?
                .label(label)
                .legend(move |(x, y)| PathElement::new([(x, y), (x + 18, y)], colour.stroke_width(2)));
            ch.draw_series(data.iter().map(|&p| Circle::new(p, 4, colour.filled()))).map_err(err)?;
        }
        draw_legend(&mut ch, SeriesLabelPosition::UpperLeft, 13)
    }
    write_png_chart(path, 900, 560, |root| draw(root, &rms, &psf, x1, y1))?;
    write_svg_chart(&path.with_extension("svg"), 900, 560, |root| draw(root, &rms, &psf, x1, y1))
}
