//! The chart of `doefab bench tiling`: the decoder's output against tile size and overlap, and
//! f32 against f64, as its difference from the f64 one-pass output, and their times.

use plotters::coord::Shift;
use plotters::prelude::*;

use super::style::{frame, line_key, mesh, write_png_chart, write_svg_chart, Drawn, GridLines, FONT};
use crate::error::Result;
use crate::sweep::tiling::TilingSweep;

const FLOOR: f64 = 1e-8;

fn chart<DB: DrawingBackend>(root: &DrawingArea<DB, Shift>, r: &TilingSweep) -> Drawn {
    root.fill(&WHITE)?;
    let title = format!(
        "Decoder reconstruction of a {0} x {0} capture: tiles against one pass, f32 against f64 (the reference)",
        r.options.size
    );
    let root = root.titled(&title, (FONT, 17))?;
    let panels = root.split_evenly((1, 2));
    let std::ops::Range { start: ylo, end: yhi } =
        super::style::log_span(r.runs.iter().map(|p| p.relative_l2.max(FLOOR)), 3.0, 1e-8..1.0);
    let palette = [RGBColor(0, 90, 200), RGBColor(220, 120, 0), RGBColor(0, 140, 60), RGBColor(160, 0, 160)];
    let tiles: Vec<usize> = {
        let mut t: Vec<usize> = r.runs.iter().filter_map(|p| p.tile).collect();
        t.sort_unstable();
        t.dedup();
        t
    };
    let one_pass = r.runs.iter().find(|p| p.tile.is_none());

    // Left: error against overlap, one line per tile; the receptive radius as a line.
    let max_overlap = r.options.overlaps.iter().copied().max().unwrap_or(128).max(r.receptive_radius) as f64;
    let mut c = frame(&panels[0], "error against overlap (one line per tile)", 15, 10, [36, 60])
        .build_cartesian_2d(-4.0..max_overlap + 8.0, (ylo..yhi).log_scale())?;
    mesh(&mut c, 12, 12, GridLines::Full)
        .x_desc("overlap, px")
        .y_desc("relative L2 to the f64 one-pass output")
        .y_label_formatter(&|v| format!("{v:.0e}"))
        .draw()?;
    let rr = r.receptive_radius as f64;
    c.draw_series(LineSeries::new([(rr, ylo), (rr, yhi)], BLACK.stroke_width(1)))?
        .label(format!("receptive radius {} px", r.receptive_radius))
        .legend(line_key(18, BLACK));
    if let Some(p) = one_pass {
        let f = p.relative_l2.max(FLOOR);
        c.draw_series(LineSeries::new([(-4.0, f), (max_overlap + 8.0, f)], RED.stroke_width(1)))?
            .label("f32 one pass")
            .legend(line_key(18, RED));
    }
    for (k, &tile) in tiles.iter().enumerate() {
        let colour = palette[k % palette.len()];
        let pts: Vec<(f64, f64)> = r
            .runs
            .iter()
            .filter(|p| p.tile == Some(tile))
            .map(|p| (p.overlap.unwrap_or(0) as f64, p.relative_l2.max(FLOOR)))
            .collect();
        c.draw_series(LineSeries::new(pts.clone(), colour.stroke_width(2)))?
            .label(format!("tile {tile}"))
            .legend(line_key(18, colour.stroke_width(2)));
        c.draw_series(pts.iter().map(|&p| Circle::new(p, 4, colour.filled())))?;
    }
    super::style::draw_legend(&mut c, SeriesLabelPosition::UpperRight, 12)?;

    // Right: error against time.
    let std::ops::Range { start: tlo, end: thi } =
        super::style::log_span(r.runs.iter().map(|p| p.seconds).chain([r.reference_seconds]), 1.5, 0.1..10.0);
    let mut c = frame(&panels[1], "error against time (label: tile/overlap)", 15, 10, [36, 60])
        .build_cartesian_2d((tlo..thi).log_scale(), (ylo..yhi).log_scale())?;
    mesh(&mut c, 12, 12, GridLines::Full)
        .x_desc("time, s (2 threads)")
        .y_desc("relative L2 to the f64 one-pass output")
        .x_label_formatter(&|v| super::style::log_label(*v, super::style::short))
        .y_label_formatter(&|v| format!("{v:.0e}"))
        .draw()?;
    for p in &r.runs {
        let at = (p.seconds, p.relative_l2.max(FLOOR));
        let (colour, label) = match p.tile {
            Some(t) => {
                let k = tiles.iter().position(|&x| x == t).unwrap_or(0);
                (palette[k % palette.len()], format!("{t}/{}", p.overlap.unwrap_or(0)))
            }
            None => (RED, "f32 one pass".to_string()),
        };
        c.draw_series([Circle::new(at, 4, colour.filled())])?;
        c.draw_series([Text::new(label, (p.seconds * 1.03, at.1), (FONT, 11))])?;
    }
    c.draw_series([TriangleMarker::new((r.reference_seconds, ylo * 1.5), 6, BLACK.filled())])?
        .label("f64 one pass (the reference)")
        .legend(|(x, y)| TriangleMarker::new((x + 8, y), 5, BLACK.filled()));
    super::style::draw_legend(&mut c, SeriesLabelPosition::UpperRight, 12)?;
    Ok(())
}

/// Writes `tiling.{png,svg}` at `path_for(name)`: error against overlap per tile (left, the
/// receptive radius and the f32 floor drawn) and error against time (right). Returns the names.
pub fn write_tiling_chart(
    mut path_for: impl FnMut(&str) -> std::path::PathBuf,
    r: &TilingSweep,
) -> Result<Vec<String>> {
    write_png_chart(&path_for("tiling.png"), 1300, 560, |root| chart(root, r))?;
    write_svg_chart(&path_for("tiling.svg"), 1300, 560, |root| chart(root, r))?;
    Ok(vec!["tiling.png".into(), "tiling.svg".into()])
}
