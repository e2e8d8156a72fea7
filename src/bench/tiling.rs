//! Reconstruction's numerics (`doefab bench tiling`): the decoder's output and time against the
//! tile size and overlap, and f32 against f64.
//!
//! The capture is simulated the way fine-tuning simulates one ([`measure`]: a seeded procedural
//! scene convolved with the paper's measured PSF, exposed so that part of it clips, read noise
//! 0.02), `size x size` pixels. The reference is the same decoder in f64 (its f32 weights and
//! the capture widened exactly) in one pass over the whole image: what the network computes
//! without rounding and without tiles. Every other run is f32: untiled (the precision floor),
//! then tiled with each tile and overlap ([`infer_tiled`]). The difference is the relative L2
//! distance of the output from the reference over the whole image, and the largest absolute
//! difference.
//!
//! With an overlap of at least the receptive radius ([`RECEPTIVE_RADIUS`], 128 px; the bound
//! is 122 px) a tile's core sees all the input it sees in one pass, so tiled equals untiled up
//! to rounding; below it, pixels near tile seams lose context and the error grows as the overlap
//! shrinks. A tile and overlap whose passes would cost more than [`MAX_COST`] times one pass
//! over the image (cores small against their tiles) are skipped, and listed.

use std::path::Path;
use std::time::Instant;

use burn::tensor::FloatDType;
use plotters::coord::Shift;
use plotters::prelude::*;
use serde::{Deserialize, Serialize};

use crate::decoder::measurement::{measure, MeasurementModel};
use crate::decoder::reconstruct::{infer_tiled, RECEPTIVE_RADIUS};
use crate::decoder::scenes::procedural_scene;
use crate::decoder::unet::{UNet, SIZE_MULTIPLE};
use crate::decoder::weights::DecoderWeights;
use crate::decoder::{infer, to_tensor};
use crate::error::{Error, Result};
use crate::image::Image;
use crate::optics::convolve::Convolver;
use crate::optics::Psf;
use crate::report::{write_png_chart, write_svg_chart, FONT};
use crate::rng::Lcg;

/// Tilings whose passes cost more than this many single passes over the image are skipped.
pub const MAX_COST: f64 = 9.0;

/// What to sweep.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TilingOptions {
    /// Side of the simulated capture, pixels (a multiple of 16).
    pub size: usize,
    /// Tile sides tried (multiples of 16).
    pub tiles: Vec<usize>,
    /// Overlaps tried (multiples of 16).
    pub overlaps: Vec<usize>,
    /// Seed of the scene and the noise.
    pub seed: u64,
}

impl Default for TilingOptions {
    fn default() -> Self {
        TilingOptions {
            size: 512,
            tiles: vec![128, 256, 384],
            overlaps: vec![0, 16, 32, 64, 96, 128],
            seed: 1,
        }
    }
}

/// One reconstruction.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TilingRun {
    /// `f32` or `f64`.
    pub precision: String,
    /// Tile side and overlap, pixels (`None`: one pass over the whole image).
    pub tile: Option<usize>,
    pub overlap: Option<usize>,
    pub passes: usize,
    pub seconds: f64,
    /// Against the f64 one-pass reference: relative L2 and largest absolute difference (output
    /// units, 1 = the sensor's clipping level).
    pub relative_l2: f64,
    pub max_abs: f64,
}

/// Everything [`run`] measured.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TilingBench {
    pub units: String,
    pub decoder: String,
    pub options: TilingOptions,
    pub receptive_radius: usize,
    /// The f64 one-pass reference's time, s.
    pub reference_seconds: f64,
    pub runs: Vec<TilingRun>,
    /// `(tile, overlap)` pairs skipped as too costly (over [`MAX_COST`] passes' worth) or
    /// impossible (`tile <= 2 overlap`).
    pub skipped: Vec<[usize; 2]>,
}

/// The cost of a tiling in single passes over an image of side `n`: tiles per side squared
/// times the tile's area over the image's.
fn cost(n: usize, tile: usize, overlap: usize) -> f64 {
    if n <= tile {
        return 1.0;
    }
    let per_side = n.div_ceil(tile - 2 * overlap) as f64;
    per_side * per_side * (tile * tile) as f64 / (n * n) as f64
}

/// The `(tile, overlap)` pairs [`run`] measures, and those it skips.
pub fn plan(o: &TilingOptions) -> (Vec<[usize; 2]>, Vec<[usize; 2]>) {
    let (mut kept, mut skipped) = (Vec::new(), Vec::new());
    for &t in &o.tiles {
        for &v in &o.overlaps {
            if t > 2 * v && cost(o.size, t, v) <= MAX_COST {
                kept.push([t, v]);
            } else {
                skipped.push([t, v]);
            }
        }
    }
    (kept, skipped)
}

/// Progress steps of [`run`].
pub fn steps(o: &TilingOptions) -> usize {
    plan(o).0.len() + 2
}

/// The simulated capture (module docs).
pub fn capture(psf: &Psf, size: usize, seed: u64) -> Result<Image<f32>> {
    let (kh, kw) = psf.dim();
    let conv = Convolver::new(psf, (size + kh - 1, size + kw - 1))?;
    let scene = procedural_scene(seed, size + kh - 1, size + kw - 1);
    Ok(measure(&scene, &conv, &MeasurementModel::default(), &mut Lcg(seed))?.capture)
}

/// The network's output on `x` computed in f64: its f32 weights and `x` widened exactly.
fn infer_f64(net: &UNet, x: &Image<f32>) -> Result<Vec<f64>> {
    let mut wide = net.clone();
    wide.set_params(net.params().iter().map(|p| p.clone().cast(FloatDType::F64)).collect());
    let input = to_tensor(&[x], net.device()).cast(FloatDType::F64);
    let y = wide.forward(input)?;
    // NCHW -> (H, W, C), as the f32 path returns it.
    let [_, c, h, w] = y.dims();
    let v = y
        .into_data()
        .try_into_vec::<f64>()
        .map_err(|e| Error::Data(format!("cannot read the f64 output back: {e:?}")))?;
    Ok((0..h * w * c).map(|k| v[(k % c) * h * w + k / c]).collect())
}

fn compare(y: &Image<f32>, reference: &[f64]) -> (f64, f64) {
    let (mut d2, mut r2, mut max) = (0.0, 0.0, 0.0f64);
    for (&a, &b) in y.values.iter().zip(reference) {
        let d = a as f64 - b;
        d2 += d * d;
        r2 += b * b;
        max = max.max(d.abs());
    }
    ((d2 / r2.max(f64::MIN_POSITIVE)).sqrt(), max)
}

/// Runs the sweep (module docs) with the decoder file (or built-in name) `decoder` on the CPU, on
/// a capture simulated through the paper's measured PSF, calling `tick` before each step
/// ([`steps`] in all).
pub fn run(decoder: &Path, opts: &TilingOptions, mut tick: impl FnMut(&str)) -> Result<TilingBench> {
    if opts.size == 0 || !opts.size.is_multiple_of(SIZE_MULTIPLE) {
        return Err(Error::param("size", format!("{} px; expected a positive multiple of 16", opts.size)));
    }
    let net = &UNet::from_weights(&DecoderWeights::read(decoder)?, &crate::decoder::device(false)?);
    let (kept, skipped) = plan(opts);
    let x = capture(&Psf::paper_measured()?, opts.size, opts.seed)?;
    tick("f64 reference, one pass");
    let t = Instant::now();
    let reference = infer_f64(net, &x)?;
    let reference_seconds = t.elapsed().as_secs_f64();
    let mut runs = Vec::new();
    tick("f32, one pass");
    let t = Instant::now();
    let y = infer(net, &x)?;
    let seconds = t.elapsed().as_secs_f64();
    let (relative_l2, max_abs) = compare(&y, &reference);
    runs.push(TilingRun {
        precision: "f32".into(),
        tile: None,
        overlap: None,
        passes: 1,
        seconds,
        relative_l2,
        max_abs,
    });
    for [tile, overlap] in kept {
        tick(&format!("f32, tile {tile}, overlap {overlap}"));
        let t = Instant::now();
        let (y, passes) = infer_tiled(net, &x, tile, overlap)?;
        let seconds = t.elapsed().as_secs_f64();
        let (relative_l2, max_abs) = compare(&y, &reference);
        runs.push(TilingRun {
            precision: "f32".into(),
            tile: Some(tile),
            overlap: Some(overlap),
            passes,
            seconds,
            relative_l2,
            max_abs,
        });
    }
    Ok(TilingBench {
        units: "differences against the f64 one-pass output (1 = the sensor's clipping level); times in s; sizes in pixels"
            .into(),
        decoder: decoder.display().to_string(),
        options: opts.clone(),
        receptive_radius: RECEPTIVE_RADIUS,
        reference_seconds,
        runs,
        skipped,
    })
}

const FLOOR: f64 = 1e-8;

fn chart<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    r: &TilingBench,
) -> std::result::Result<(), String> {
    let e = |x: &dyn std::fmt::Display| x.to_string();
    root.fill(&WHITE).map_err(|x| e(&x))?;
    let title = format!(
        "Decoder reconstruction of a {0} x {0} capture: tiles against one pass, f32 against f64 (the reference)",
        r.options.size
    );
    let root = root.titled(&title, (FONT, 17)).map_err(|x| e(&x))?;
    let panels = root.split_evenly((1, 2));
    let std::ops::Range { start: ylo, end: yhi } =
        crate::report::log_span(r.runs.iter().map(|p| p.relative_l2.max(FLOOR)), 3.0, 1e-8..1.0);
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
    let mut c = ChartBuilder::on(&panels[0])
        .caption("error against overlap (one line per tile)", (FONT, 15))
        .margin(10)
        .x_label_area_size(36)
        .y_label_area_size(60)
        .build_cartesian_2d(-4.0..max_overlap + 8.0, (ylo..yhi).log_scale())
        .map_err(|x| e(&x))?;
    c.configure_mesh()
        .x_desc("overlap, px")
        .y_desc("relative L2 to the f64 one-pass output")
        .y_label_formatter(&|v| format!("{v:.0e}"))
        .label_style((FONT, 12))
        .draw()
        .map_err(|x| e(&x))?;
    let rr = r.receptive_radius as f64;
    c.draw_series(LineSeries::new([(rr, ylo), (rr, yhi)], BLACK.stroke_width(1)))
        .map_err(|x| e(&x))?
        .label(format!("receptive radius {} px", r.receptive_radius))
        .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 18, y)], BLACK));
    if let Some(p) = one_pass {
        let f = p.relative_l2.max(FLOOR);
        c.draw_series(LineSeries::new([(-4.0, f), (max_overlap + 8.0, f)], RED.stroke_width(1)))
            .map_err(|x| e(&x))?
            .label("f32 one pass")
            .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 18, y)], RED));
    }
    for (k, &tile) in tiles.iter().enumerate() {
        let colour = palette[k % palette.len()];
        let pts: Vec<(f64, f64)> = r
            .runs
            .iter()
            .filter(|p| p.tile == Some(tile))
            .map(|p| (p.overlap.unwrap_or(0) as f64, p.relative_l2.max(FLOOR)))
            .collect();
        c.draw_series(LineSeries::new(pts.clone(), colour.stroke_width(2)))
            .map_err(|x| e(&x))?
            .label(format!("tile {tile}"))
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 18, y)], colour.stroke_width(2)));
        c.draw_series(pts.iter().map(|&p| Circle::new(p, 4, colour.filled()))).map_err(|x| e(&x))?;
    }
    crate::report::draw_legend(&mut c, SeriesLabelPosition::UpperRight, 12)?;

    // Right: error against time.
    let std::ops::Range { start: tlo, end: thi } = crate::report::log_span(
        r.runs.iter().map(|p| p.seconds).chain([r.reference_seconds]),
        1.5,
        0.1..10.0,
    );
    let mut c = ChartBuilder::on(&panels[1])
        .caption("error against time (label: tile/overlap)", (FONT, 15))
        .margin(10)
        .x_label_area_size(36)
        .y_label_area_size(60)
        .build_cartesian_2d((tlo..thi).log_scale(), (ylo..yhi).log_scale())
        .map_err(|x| e(&x))?;
    c.configure_mesh()
        .x_desc("time, s (2 threads)")
        .y_desc("relative L2 to the f64 one-pass output")
        .x_label_formatter(&|v| crate::report::log_label(*v, crate::report::short))
        .y_label_formatter(&|v| format!("{v:.0e}"))
        .label_style((FONT, 12))
        .draw()
        .map_err(|x| e(&x))?;
    for p in &r.runs {
        let at = (p.seconds, p.relative_l2.max(FLOOR));
        let (colour, label) = match p.tile {
            Some(t) => {
                let k = tiles.iter().position(|&x| x == t).unwrap_or(0);
                (palette[k % palette.len()], format!("{t}/{}", p.overlap.unwrap_or(0)))
            }
            None => (RED, "f32 one pass".to_string()),
        };
        c.draw_series([Circle::new(at, 4, colour.filled())]).map_err(|x| e(&x))?;
        c.draw_series([Text::new(label, (p.seconds * 1.03, at.1), (FONT, 11))]).map_err(|x| e(&x))?;
    }
    c.draw_series([TriangleMarker::new((r.reference_seconds, ylo * 1.5), 6, BLACK.filled())])
        .map_err(|x| e(&x))?
        .label("f64 one pass (the reference)")
        .legend(|(x, y)| TriangleMarker::new((x + 8, y), 5, BLACK.filled()));
    crate::report::draw_legend(&mut c, SeriesLabelPosition::UpperRight, 12)?;
    Ok(())
}

/// Writes `tiling.{png,svg}` at `path_for(name)`: error against overlap per tile (left, the
/// receptive radius and the f32 floor drawn) and error against time (right). Returns the names.
pub fn write_chart(
    mut path_for: impl FnMut(&str) -> std::path::PathBuf,
    r: &TilingBench,
) -> Result<Vec<String>> {
    write_png_chart(&path_for("tiling.png"), 1300, 560, |root| chart(root, r))?;
    write_svg_chart(&path_for("tiling.svg"), 1300, 560, |root| chart(root, r))?;
    Ok(vec!["tiling.png".into(), "tiling.svg".into()])
}
