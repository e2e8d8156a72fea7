//! Charts of the metrology comparison: false-colour height maps with a colour bar in nm,
//! profiles through the centre (design against the part) and the height histogram with the
//! level heights marked. PNG through [`write_png_chart`]. The registration's speed against its
//! accuracy ([`registration_speed_accuracy`]).

use std::path::Path;

use plotters::prelude::*;

use super::style::{
    draw_legend, frame, line_key, mesh, write_png_chart, write_svg_chart, Drawn, GridLines, FONT,
};
use crate::error::Result;
use crate::grid::Grid;

/// Most map pixels drawn per side (larger grids are shown by nearest-sample decimation).
const MAP_SIDE: usize = 560;

/// Colour maps of [`height_map`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Palette {
    /// Perceptually ordered dark blue -> green -> yellow (viridis anchors), for heights.
    Sequential,
    /// Blue -> white -> red, symmetric about 0, for differences.
    Diverging,
}

/// Colour of `t` in [0, 1].
fn colour(p: Palette, t: f64) -> RGBColor {
    let t = if t.is_finite() { t.clamp(0.0, 1.0) } else { 0.0 };
    let anchors: &[(u8, u8, u8)] = match p {
        // Viridis at 0, 1/4, 1/2, 3/4, 1 (matplotlib's table).
        Palette::Sequential => &[(68, 1, 84), (59, 82, 139), (33, 145, 140), (94, 201, 98), (253, 231, 37)],
        Palette::Diverging => {
            &[(33, 102, 172), (146, 197, 222), (247, 247, 247), (244, 165, 130), (178, 24, 43)]
        }
    };
    let x = t * (anchors.len() - 1) as f64;
    let k = (x.floor() as usize).min(anchors.len() - 2);
    let f = x - k as f64;
    let mix = |a: u8, b: u8| (a as f64 + f * (b as f64 - a as f64)).round() as u8;
    let (a, b) = (anchors[k], anchors[k + 1]);
    RGBColor(mix(a.0, b.0), mix(a.1, b.1), mix(a.2, b.2))
}

/// Range of the valid values (nm). A diverging range is symmetric about 0 and spans the 99th
/// percentile of `|v|` (a few edge spikes would otherwise wash the map out; larger values are
/// drawn at the end colours).
fn range_nm(g: &Grid, p: Palette) -> (f64, f64) {
    let (lo, hi) = if p == Palette::Diverging {
        let mut a: Vec<f64> = g
            .values()
            .indexed_iter()
            .filter(|((i, j), _)| g.is_valid(*i, *j))
            .map(|(_, v)| v.abs() * 1e9)
            .collect();
        a.sort_by(f64::total_cmp);
        let m =
            a.get(((a.len() as f64 * 0.99) as usize).min(a.len().saturating_sub(1))).copied().unwrap_or(0.0);
        (-m, m)
    } else {
        let (lo, hi) = g.min_max().unwrap_or((0.0, 0.0));
        (lo * 1e9, hi * 1e9)
    };
    if hi > lo {
        (lo, hi)
    } else {
        (lo - 1.0, hi + 1.0)
    }
}

/// A false-colour map of `g` (heights in metres) titled `title`, with a colour bar in nm;
/// invalid (non-measured) samples are grey. Row 0 at the top.
pub fn height_map(path: &Path, g: &Grid, title: &str, palette: Palette) -> Result<()> {
    let (nr, nc) = g.dim();
    let step = nr.max(nc).div_ceil(MAP_SIDE).max(1);
    let (h, w) = (nr.div_ceil(step), nc.div_ceil(step));
    let (lo, hi) = range_nm(g, palette);
    let (width, height) = (w as u32 + 170, h as u32 + 70);
    write_png_chart(path, width, height, |root| {
        let (map_area, bar_area) = root.split_horizontally(w as u32 + 30);
        map_area.draw(&Text::new(title.to_string(), (15, 10), (FONT, 18).into_font()))?;
        let mm = [nc as f64 * g.pitch()[0] * 1e3, nr as f64 * g.pitch()[1] * 1e3];
        map_area.draw(&Text::new(
            format!("{:.2} x {:.2} mm, {} x {} samples", mm[0], mm[1], nc, nr),
            (15, h as i32 + 45),
            (FONT, 13).into_font(),
        ))?;
        for i in 0..h {
            for j in 0..w {
                let (si, sj) = (i * step, j * step);
                let c = if g.is_valid(si, sj) {
                    colour(palette, (g.values()[[si, sj]] * 1e9 - lo) / (hi - lo))
                } else {
                    RGBColor(160, 160, 160)
                };
                map_area.draw_pixel((15 + j as i32, 35 + i as i32), &c)?;
            }
        }
        let mut bar = ChartBuilder::on(&bar_area)
            .margin_top(35)
            .margin_bottom(35)
            .margin_right(10)
            .y_label_area_size(70)
            .build_cartesian_2d(0.0..1.0, lo..hi)?;
        mesh(&mut bar, 13, 14, GridLines::Full)
            .disable_x_mesh()
            .disable_y_mesh()
            .disable_x_axis()
            .y_desc("height (nm)")
            .draw()?;
        let n = 200;
        bar.draw_series((0..n).map(|k| {
            let (a, b) = (lo + (hi - lo) * k as f64 / n as f64, lo + (hi - lo) * (k + 1) as f64 / n as f64);
            Rectangle::new([(0.0, a), (1.0, b)], colour(palette, (k as f64 + 0.5) / n as f64).filled())
        }))?;
        Ok(())
    })
}

/// Runs of consecutive valid samples of a profile, as (position mm, height nm) lines.
fn runs(points: impl Iterator<Item = (f64, Option<f64>)>) -> Vec<Vec<(f64, f64)>> {
    let mut out: Vec<Vec<(f64, f64)>> = vec![Vec::new()];
    for (x, v) in points {
        match v {
            Some(z) => out.last_mut().map_or((), |r| r.push((x * 1e3, z * 1e9))),
            None if out.last().is_some_and(|r| !r.is_empty()) => out.push(Vec::new()),
            None => {}
        }
    }
    out.retain(|r| !r.is_empty());
    out
}

/// Profiles through the centre of the design grid along x (centre row) and y (centre column):
/// the design and the as-fabricated surface, heights in nm against position in mm.
pub fn profiles(path: &Path, design: &Grid, surface: &Grid) -> Result<()> {
    let (nr, nc) = design.dim();
    let (ci, cj) = (nr / 2, nc / 2);
    let p = design.pitch();
    let xs = |j: usize| (j as f64 - (nc as f64 - 1.0) * 0.5) * p[0];
    let ys = |i: usize| (i as f64 - (nr as f64 - 1.0) * 0.5) * p[1];
    let val = |g: &Grid, i: usize, j: usize| g.is_valid(i, j).then(|| g.values()[[i, j]]);
    let panels = [
        (
            "x (mm), centre row",
            runs((0..nc).map(|j| (xs(j), val(design, ci, j)))),
            runs((0..nc).map(|j| (xs(j), val(surface, ci, j)))),
            (xs(0), xs(nc - 1)),
        ),
        (
            "y (mm), centre column",
            runs((0..nr).map(|i| (ys(i), val(design, i, cj)))),
            runs((0..nr).map(|i| (ys(i), val(surface, i, cj)))),
            (ys(0), ys(nr - 1)),
        ),
    ];
    let all = [design, surface].map(|g| g.min_max().unwrap_or((0.0, 0.0)));
    let lo = all[0].0.min(all[1].0) * 1e9;
    let hi = all[0].1.max(all[1].1) * 1e9;
    let pad = 0.05 * (hi - lo).max(1.0);
    write_png_chart(path, 1000, 760, |root| {
        let areas = root.split_evenly((2, 1));
        for (area, (label, d, s, (x0, x1))) in areas.iter().zip(&panels) {
            let mut ch = ChartBuilder::on(area)
                .margin(12)
                .x_label_area_size(40)
                .y_label_area_size(70)
                .build_cartesian_2d(x0 * 1e3..x1 * 1e3, lo - pad..hi + pad)?;
            mesh(&mut ch, 13, 14, GridLines::Full).x_desc(*label).y_desc("height (nm)").draw()?;
            for (k, r) in d.iter().enumerate() {
                let s = ch.draw_series(LineSeries::new(r.iter().copied(), BLACK.stroke_width(1)))?;
                if k == 0 {
                    s.label("design").legend(line_key(18, BLACK));
                }
            }
            for (k, r) in s.iter().enumerate() {
                let s = ch.draw_series(LineSeries::new(r.iter().copied(), RED.stroke_width(1)))?;
                if k == 0 {
                    s.label("part (registered scan)").legend(line_key(18, RED));
                }
            }
            super::style::draw_legend(&mut ch, SeriesLabelPosition::MiddleRight, 13)?;
        }
        Ok(())
    })
}

/// Histogram of `heights` (metres) with the design's level heights (dark grey) and the measured
/// level means (red) marked.
pub fn height_histogram(
    path: &Path,
    heights: &[f64],
    design_levels: &[f64],
    measured_levels: &[f64],
) -> Result<()> {
    let nm: Vec<f64> = heights.iter().filter(|v| v.is_finite()).map(|v| v * 1e9).collect();
    let marks = design_levels.iter().chain(measured_levels).filter(|v| v.is_finite()).map(|v| v * 1e9);
    let (lo, hi) = nm
        .iter()
        .copied()
        .chain(marks)
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), v| (a.min(v), b.max(v)));
    let (lo, hi) = if hi > lo { (lo, hi) } else { (lo - 1.0, lo + 1.0) };
    let bins = 200usize;
    let width = (hi - lo) / bins as f64;
    let mut counts = vec![0usize; bins];
    for v in &nm {
        counts[(((v - lo) / width) as usize).min(bins - 1)] += 1;
    }
    let top = counts.iter().copied().max().unwrap_or(1).max(1) as f64 * 1.05;
    write_png_chart(path, 1000, 500, |root| {
        let mut ch = frame(root, "heights over the aperture", 18, 12, [40, 70])
            .build_cartesian_2d(lo..hi, 0.0..top)?;
        mesh(&mut ch, 13, 14, GridLines::Full)
            .disable_x_mesh()
            .disable_y_mesh()
            .x_desc("height (nm)")
            .y_desc("samples")
            .draw()?;
        ch.draw_series(counts.iter().enumerate().map(|(k, &c)| {
            let x = lo + k as f64 * width;
            Rectangle::new([(x, 0.0), (x + width, c as f64)], RGBColor(59, 82, 139).filled())
        }))?
        .label("part")
        .legend(|(x, y)| Rectangle::new([(x, y - 5), (x + 12, y + 5)], RGBColor(59, 82, 139).filled()));
        let grey = RGBColor(90, 90, 90);
        ch.draw_series(
            design_levels
                .iter()
                .map(|v| PathElement::new([(v * 1e9, 0.0), (v * 1e9, top)], grey.stroke_width(2))),
        )?
        .label("design levels")
        .legend(line_key(18, grey));
        ch.draw_series(
            measured_levels
                .iter()
                .filter(|v| v.is_finite())
                .map(|v| PathElement::new([(v * 1e9, 0.0), (v * 1e9, top)], RED.stroke_width(2))),
        )?
        .label("measured level means")
        .legend(line_key(18, RED));
        super::style::draw_legend(&mut ch, SeriesLabelPosition::MiddleRight, 13)?;
        Ok(())
    })
}

/// A stylus profile against the design model fitted to it (or, without a design, against the
/// terrace levels found): `measured` and `model` as (position m, height m) points, `levels` as
/// horizontal lines (heights in metres); SVG at `path`.
pub fn profile_chart(
    path: &Path,
    measured: &[(f64, f64)],
    model: &[(f64, f64)],
    levels: &[f64],
    title: &str,
) -> Result<()> {
    let all = measured.iter().chain(model).map(|p| p.1).chain(levels.iter().copied());
    let (lo, hi) = all.fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), v| (a.min(v), b.max(v)));
    let (x0, x1) =
        measured.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), p| (a.min(p.0), b.max(p.0)));
    let (lo, hi) = if lo.is_finite() && hi > lo { (lo * 1e9, hi * 1e9) } else { (-1.0, 1.0) };
    let (x0, x1) = if x0.is_finite() && x1 > x0 { (x0 * 1e6, x1 * 1e6) } else { (0.0, 1.0) };
    let pad = 0.05 * (hi - lo);
    let line = |pts: &[(f64, f64)]| pts.iter().map(|p| (p.0 * 1e6, p.1 * 1e9)).collect::<Vec<_>>();
    let (m, f) = (line(measured), line(model));
    write_svg_chart(path, 1000, 420, |root| {
        let mut ch = frame(root, title, 16, 12, [40, 70]).build_cartesian_2d(x0..x1, lo - pad..hi + pad)?;
        mesh(&mut ch, 13, 14, GridLines::Full)
            .x_desc("position along the profile (um)")
            .y_desc("height (nm)")
            .draw()?;
        ch.draw_series(LineSeries::new(m, RED.stroke_width(1)))?.label("profile").legend(line_key(18, RED));
        if !f.is_empty() {
            ch.draw_series(LineSeries::new(f, BLACK.stroke_width(1)))?
                .label("design, fitted")
                .legend(line_key(18, BLACK));
        }
        for (k, h) in levels.iter().enumerate() {
            let s = ch.draw_series(LineSeries::new(
                [(x0, h * 1e9), (x1, h * 1e9)],
                BLUE.mix(0.6).stroke_width(1),
            ))?;
            if k == 0 {
                s.label("levels").legend(line_key(18, BLUE));
            }
        }
        super::style::draw_legend(&mut ch, SeriesLabelPosition::UpperRight, 13)
    })
}

/// One setting of [`registration_speed_accuracy`]: its label, time (seconds), shift error and
/// formal standard error (design pixels), and whether it is the default.
pub struct SpeedAccuracyPoint {
    /// Name of the setting, written beside its point.
    pub label: String,
    /// Time per registration, seconds.
    pub seconds: f64,
    /// Length of the shift error (registered - true), design pixels.
    pub error: f64,
    /// Formal standard error of the shift (length of the per-axis pair), design pixels.
    pub sigma: f64,
    /// The setting is the default (marked "(default)" and ringed).
    pub chosen: bool,
}

/// Registration time against shift error (log-log), one labelled point per setting, the formal
/// standard error beside it and the accuracy goal `goal_px` as a line; PNG at `path` and SVG
/// beside it.
pub fn registration_speed_accuracy(path: &Path, points: &[SpeedAccuracyPoint], goal_px: f64) -> Result<()> {
    let pos = |v: f64| v.is_finite() && v > 0.0;
    let xs: Vec<f64> = points.iter().map(|p| p.seconds).filter(|&v| pos(v)).collect();
    let ys: Vec<f64> =
        points.iter().flat_map(|p| [p.error, p.sigma]).chain([goal_px]).filter(|&v| pos(v)).collect();
    let span = |v: &[f64]| {
        let (lo, hi) = v.iter().fold((f64::INFINITY, 0.0f64), |(l, h), &x| (l.min(x), h.max(x)));
        if lo.is_finite() && hi > 0.0 {
            (lo / 1.6, hi * 1.6)
        } else {
            (1e-3, 1.0)
        }
    };
    let (x, y) = (span(&xs), span(&ys));
    fn draw<DB: DrawingBackend>(
        root: &DrawingArea<DB, plotters::coord::Shift>,
        points: &[SpeedAccuracyPoint],
        goal: f64,
        x: (f64, f64),
        y: (f64, f64),
    ) -> Drawn {
        let mut ch = frame(
            root,
            "registration: time against shift error (least-squares point budget)",
            17,
            14,
            [44, 70],
        )
        .build_cartesian_2d((x.0..x.1).log_scale(), (y.0..y.1).log_scale())?;
        // Three significant digits, no float noise ("0.3", not "0.30000000000000004").
        let fmt = |v: &f64| {
            let d = (2 - v.abs().log10().floor() as i32).max(0) as usize;
            format!("{v:.d$}")
        };
        mesh(&mut ch, 13, 14, GridLines::Labels)
            .x_label_formatter(&fmt)
            .y_label_formatter(&fmt)
            .x_desc("time per registration (s)")
            .y_desc("shift error (design pixels, 4.29 um)")
            .draw()?;
        ch.draw_series(LineSeries::new([(x.0, goal), (x.1, goal)], RED.mix(0.6).stroke_width(1)))?
            .label(format!("goal {goal} px"))
            .legend(line_key(18, RED.mix(0.6)));
        let ok = |v: f64| v.is_finite() && v > 0.0;
        let measured: Vec<(f64, f64)> =
            points.iter().filter(|p| ok(p.seconds) && ok(p.error)).map(|p| (p.seconds, p.error)).collect();
        let formal: Vec<(f64, f64)> =
            points.iter().filter(|p| ok(p.seconds) && ok(p.sigma)).map(|p| (p.seconds, p.sigma)).collect();
        ch.draw_series(LineSeries::new(measured.iter().copied(), BLUE.stroke_width(2)))?
            .label("measured error")
            .legend(line_key(18, BLUE.stroke_width(2)));
        ch.draw_series(measured.iter().map(|&p| Circle::new(p, 4, BLUE.filled())))?;
        ch.draw_series(LineSeries::new(formal.iter().copied(), BLACK.mix(0.5).stroke_width(1)))?
            .label("formal standard error")
            .legend(line_key(18, BLACK.mix(0.5)));
        for p in points.iter().filter(|p| ok(p.seconds) && ok(p.error)) {
            let text = if p.chosen { format!("{} (default)", p.label) } else { p.label.clone() };
            ch.draw_series([EmptyElement::at((p.seconds, p.error)) + Text::new(text, (7, 4), (FONT, 12))])?;
            if p.chosen {
                ch.draw_series([Circle::new((p.seconds, p.error), 8, BLUE.stroke_width(2))])?;
            }
        }
        draw_legend(&mut ch, SeriesLabelPosition::UpperRight, 13)
    }
    write_png_chart(path, 900, 560, |root| draw(root, points, goal_px, x, y))?;
    write_svg_chart(&path.with_extension("svg"), 900, 560, |root| draw(root, points, goal_px, x, y))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::grid::Unit;
    use ndarray::Array2;

    /// The map's pixels follow the palette: the lowest sample is viridis' first colour, the
    /// highest its last, an invalid one grey.
    #[test]
    fn height_map_colours_follow_the_values() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("m.png");
        let v = Array2::from_shape_fn((40, 60), |(_, j)| j as f64 * 1e-9);
        let mut mask = Array2::from_elem((40, 60), true);
        mask[[20, 30]] = false;
        let g = Grid::new(v, [1e-6; 2], Unit::Metre).unwrap().with_mask(mask).unwrap();
        height_map(&path, &g, "t", Palette::Sequential).unwrap();
        let img = image::open(&path).unwrap().to_rgb8();
        assert_eq!(img.dimensions(), (230, 110));
        // Map pixel (i, j) sits at (15 + j, 35 + i).
        assert_eq!(img.get_pixel(15, 40).0, [68, 1, 84]);
        assert_eq!(img.get_pixel(15 + 59, 40).0, [253, 231, 37]);
        assert_eq!(img.get_pixel(15 + 30, 35 + 20).0, [160, 160, 160]);
        assert_eq!(colour(Palette::Diverging, 0.5), RGBColor(247, 247, 247));
    }

    /// The chart is written as PNG and SVG, names the default and the goal, and its log-axis
    /// labels carry no float noise (plotters prints 0.3 as 0.30000000000000004 unformatted).
    #[test]
    fn speed_accuracy_chart_marks_the_default_and_the_goal() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("sa.png");
        let pts: Vec<SpeedAccuracyPoint> = [(0.06, 3e-3, 8e-3), (0.09, 1e-3, 2e-3), (0.3, 1.5e-3, 1e-3)]
            .iter()
            .enumerate()
            .map(|(k, &(t, e, s))| SpeedAccuracyPoint {
                label: format!("{}k", 25 << (2 * k)),
                seconds: t,
                error: e,
                sigma: s,
                chosen: k == 1,
            })
            .collect();
        registration_speed_accuracy(&path, &pts, 0.02).unwrap();
        assert!(image::open(&path).is_ok());
        let svg = std::fs::read_to_string(path.with_extension("svg")).unwrap();
        assert!(svg.contains("100k (default)") && svg.contains("goal 0.02 px"), "{svg}");
        assert!(!svg.contains("0000000"), "float noise in the labels");
    }
}
