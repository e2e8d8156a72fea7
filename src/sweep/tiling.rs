//! Reconstruction's numerics (`doefab bench tiling`): the decoder's output and time against the
//! tile size and overlap, and f32 against f64.
//!
//! The capture is simulated the way fine-tuning simulates one (`measure`: a seeded procedural
//! scene convolved with the paper's measured PSF, exposed so that part of it clips, read noise
//! 0.02), `size x size` pixels. The reference is the same decoder in f64 (its f32 weights and
//! the capture widened exactly) in one pass over the whole image: what the network computes
//! without rounding and without tiles. Every other run is f32: untiled (the precision floor),
//! then tiled with each tile and overlap ([`infer_tiled`]). The difference is the relative L2
//! distance of the output from the reference over the whole image, and the largest absolute
//! difference.
//!
//! With an overlap of at least the receptive radius (`RECEPTIVE_RADIUS`, 128 px; the bound
//! is 122 px) a tile's core sees all the input it sees in one pass, so tiled equals untiled up
//! to rounding; below it, pixels near tile seams lose context and the error grows as the overlap
//! shrinks. A tile and overlap whose passes would cost more than [`MAX_COST`] times one pass
//! over the image (cores small against their tiles) are skipped, and listed.

use std::path::Path;
use std::time::Instant;

use burn::tensor::FloatDType;
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
    /// Tile side, pixels (`None`: one pass over the whole image).
    pub tile: Option<usize>,
    /// Overlap, pixels: the context a tile adds on each side of its core (core side `tile - 2
    /// overlap`); `None`: one pass over the whole image.
    pub overlap: Option<usize>,
    /// Network passes run: the tiles, or 1 untiled.
    pub passes: usize,
    /// Wall-clock seconds of the reconstruction.
    pub seconds: f64,
    /// Relative L2 distance from the f64 one-pass reference over the whole image,
    /// `||y - y_ref|| / ||y_ref||`.
    pub relative_l2: f64,
    /// The largest absolute difference from the f64 one-pass reference, output units (1 = the
    /// sensor's clipping level).
    pub max_abs: f64,
}

/// Everything [`run`] measured.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TilingSweep {
    /// What the numbers are in: differences against the f64 one-pass output (1 = the sensor's
    /// clipping level), times in seconds, sizes in pixels.
    pub units: String,
    /// The decoder: its file's path or `built-in:NAME`, as given.
    pub decoder: String,
    /// The sweep's settings.
    pub options: TilingOptions,
    /// `RECEPTIVE_RADIUS`: the bound of the U-Net's receptive-field radius, pixels.
    pub receptive_radius: usize,
    /// The f64 one-pass reference's time, s.
    pub reference_seconds: f64,
    /// Every f32 reconstruction: untiled first, then each `(tile, overlap)` pair measured.
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
        .map_err(|e| Error::internal(format!("cannot read the f64 output back: {e:?}")))?;
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
pub fn run(decoder: &Path, opts: &TilingOptions, mut tick: impl FnMut(&str)) -> Result<TilingSweep> {
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
    Ok(TilingSweep {
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
