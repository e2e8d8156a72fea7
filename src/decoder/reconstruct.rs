//! Reconstruction of an HDR image from one capture through the DOE.
//!
//! * Input: an RGB PNG or TIFF of linear sensor values, 8 or 16 bits per sample, read as
//!   `x = value / (2^bits - 1)` (the paper's `PNG / 255`; 1 = the clipping level).
//! * Border context: the network's 3x3 convolutions pad with zeros (TF 'SAME'), so at the image
//!   border it sees black cells, and near dark borders it makes large negative blobs (the
//!   paper's decoders: -684 and -293 at the right border of the shared Fruit and Kitchen frames).
//!   The capture is therefore mirrored (`x[-i] = x[i]`, no edge repeat) by
//!   [`ReconstructOptions::border`] pixels on every side, and further at the bottom and right up
//!   to multiples of 16 (the U-Net's size multiple); the output is cropped back. With 32 px the
//!   raw output within 32 px of the border of both frames stays above -0.02 for the paper's two
//!   decoders (tested); `border = 0` gives the upstream demo's output.
//! * Tiling: an image larger than the tile is cut into tiles whose cores are written and whose
//!   overlap (context on every side) is discarded. Tile and core origins are multiples of 16,
//!   so pooling cells line up with the full image's. The network's receptive field reaches at
//!   most [`RECEPTIVE_RADIUS`] pixels from an output pixel (bound below); with an overlap at
//!   least that large every core pixel sees exactly the input it sees in one pass, and tiled
//!   equals untiled up to float rounding (the gemm blocking differs with the tile size).
//! * Negative outputs: the network has no output activation. DECODER.md documents large
//!   negative blobs in near-black areas at the image border (down to -293 on the shared
//!   Kitchen frame; the border context above removes them). [`Negatives::Clamp`] (the default) applies the upstream demo's
//!   `max(y, 0)`; [`Negatives::Keep`] writes the raw output. Either way the counts of values
//!   below 0 and below -1 and the minimum are reported.
//!
//! Receptive-field bound, in full-resolution pixels from an output pixel: the encoder's 3x3
//! convs reach 2 cells per level at scales 1, 2, 4, 8, 16 (2 + 4 + 8 + 16 + 32 = 62), the four
//! poolings add at most one finer cell each (1 + 2 + 4 + 8 = 15), the four transposed convs
//! one coarser cell plus one finer cell of alignment each (24 + 12 + 6 + 3 = 45): 122 < 128.

use std::path::Path;

use ndarray::{s, Array3};
use serde::Serialize;

use crate::decoder::runtime::infer;
use crate::decoder::unet::{UNet, SIZE_MULTIPLE};
use crate::error::{DataCause, Error, Result};
use crate::image::tone::tone_map;
use crate::image::Image;

/// An upper bound of the U-Net's receptive-field radius, pixels (see the module docs),
/// rounded up to a multiple of 16.
pub const RECEPTIVE_RADIUS: usize = 128;

/// Default mirrored context around the capture, pixels (see the module docs).
pub const BORDER: usize = 32;

/// What to do with negative network outputs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Negatives {
    /// `max(y, 0)`, as the paper's demo.
    Clamp,
    /// Write the raw output.
    Keep,
}

/// Tiling and output options.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct ReconstructOptions {
    /// Largest tile side fed to the network (a multiple of 16).
    pub tile: usize,
    /// Context kept on each side of a tile's core (a multiple of 16).
    pub overlap: usize,
    /// Mirrored context added on every side of the capture before the network, pixels.
    pub border: usize,
    /// What is done with negative outputs.
    pub negatives: Negatives,
}

impl Default for ReconstructOptions {
    fn default() -> Self {
        ReconstructOptions {
            tile: 1024,
            overlap: RECEPTIVE_RADIUS,
            border: BORDER,
            negatives: Negatives::Clamp,
        }
    }
}

/// What happened during a reconstruction (in `doefab reconstruct`'s JSON).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ReconstructStats {
    /// Rows of the capture, pixels.
    pub rows: usize,
    /// Columns of the capture, pixels.
    pub cols: usize,
    /// Rows fed to the network: the border context added, then padded to a multiple of 16.
    pub padded_rows: usize,
    /// Columns fed to the network, likewise.
    pub padded_cols: usize,
    /// Network passes (1 when the image fits in one tile).
    pub tiles: usize,
    /// What was done with negative outputs.
    pub negatives: Negatives,
    /// Raw output values (over pixels and channels) below 0.
    pub values_below_zero: usize,
    /// Raw output values (over pixels and channels) below -1.
    pub values_below_minus_one: usize,
    /// The smallest raw output value, in units of the capture's clipping level.
    pub min_raw: f32,
    /// The largest output value written (after clamping, if any), in units of the capture's
    /// clipping level.
    pub max: f32,
    /// Warnings (e.g. an overlap smaller than the receptive field).
    pub warnings: Vec<String>,
}

/// Reads an RGB capture (8- or 16-bit PNG or TIFF, linear) as `count / (2^bits - 1)` in `f32`,
/// through the one capture reader, [`crate::calibration::capture::read_capture`]; the decoder
/// takes three channels.
pub fn read_capture(path: &Path) -> Result<Image<f32>> {
    let c = crate::calibration::capture::read_capture(path)?;
    let channels = c.image.channels();
    if channels != 3 {
        return Err(Error::unsupported(
            path,
            format!("has {channels} channel(s); the decoder takes RGB captures (linear sensor values)"),
        ));
    }
    // Back to the counts, exact, then divided in f32.
    let full = c.full_scale();
    Ok(Image::new(c.image.values.mapv(|v| (v * full).round() as f32 / full as f32)))
}

/// Index `i` (counted from `-border`) of a mirrored axis of length `n`: `x[-i] = x[i]` and
/// `x[n - 1 + i] = x[n - 1 - i]`, repeated with period `2 (n - 1)` for a context wider than
/// the axis.
fn mirror(i: usize, border: usize, n: usize) -> usize {
    if n == 1 {
        return 0;
    }
    let period = 2 * (n - 1);
    let r = (i + period * border.div_ceil(period) - border) % period;
    if r < n {
        r
    } else {
        period - r
    }
}

/// `x` mirrored by `border` pixels on every side and further at the bottom and right up to
/// multiples of 16.
fn pad_mirrored(x: &Array3<f32>, border: usize) -> Array3<f32> {
    let (h, w, c) = x.dim();
    let (ph, pw) =
        ((h + 2 * border).next_multiple_of(SIZE_MULTIPLE), (w + 2 * border).next_multiple_of(SIZE_MULTIPLE));
    let rows: Vec<usize> = (0..ph).map(|i| mirror(i, border, h)).collect();
    let cols: Vec<usize> = (0..pw).map(|j| mirror(j, border, w)).collect();
    Array3::from_shape_fn((ph, pw, c), |(i, j, k)| x[[rows[i], cols[j], k]])
}

/// Tile windows along one axis of length `n`: `(window_start, window_end, core_start,
/// core_end)`, cores of `tile - 2 overlap` tiling `[0, n)`, windows the cores widened by the
/// overlap and clipped to the image.
fn windows(n: usize, tile: usize, overlap: usize) -> Vec<(usize, usize, usize, usize)> {
    if n <= tile {
        return vec![(0, n, 0, n)];
    }
    let core = tile - 2 * overlap;
    (0..n)
        .step_by(core)
        .map(|c0| {
            let c1 = (c0 + core).min(n);
            (c0.saturating_sub(overlap), (c1 + overlap).min(n), c0, c1)
        })
        .collect()
}

/// The network's raw output for an image whose sides are multiples of 16, tiled when larger
/// than `tile`. Returns the output and the number of passes.
pub fn infer_tiled(net: &UNet, x: &Image<f32>, tile: usize, overlap: usize) -> Result<(Image<f32>, usize)> {
    let (h, w, _) = x.dim();
    if !tile.is_multiple_of(SIZE_MULTIPLE) || !overlap.is_multiple_of(SIZE_MULTIPLE) || tile <= 2 * overlap {
        return Err(Error::param(
            "tile",
            format!("tile {tile} and overlap {overlap} must be multiples of 16 with tile > 2 x overlap"),
        ));
    }
    let (rows, cols) = (windows(h, tile, overlap), windows(w, tile, overlap));
    if rows.len() == 1 && cols.len() == 1 {
        return Ok((infer(net, x)?, 1));
    }
    let mut out = Array3::zeros(x.dim());
    let x = &x.values;
    for &(r0, r1, cr0, cr1) in &rows {
        for &(c0, c1, cc0, cc1) in &cols {
            let y = infer(net, &Image::new(x.slice(s![r0..r1, c0..c1, ..]).to_owned()))?;
            out.slice_mut(s![cr0..cr1, cc0..cc1, ..]).assign(&y.values.slice(s![
                cr0 - r0..cr1 - r0,
                cc0 - c0..cc1 - c0,
                ..
            ]));
        }
    }
    Ok((Image::new(out), rows.len() * cols.len()))
}

/// Reconstructs the HDR image of capture `x` (RGB, 1 = clipping level).
pub fn reconstruct(
    net: &UNet,
    x: &Image<f32>,
    opts: &ReconstructOptions,
) -> Result<(Image<f32>, ReconstructStats)> {
    let (h, w, c) = x.dim();
    if c != 3 || h == 0 || w == 0 {
        return Err(Error::param("capture", format!("is {h} x {w} x {c}; an RGB image is needed")));
    }
    let mut warnings = Vec::new();
    if opts.overlap < RECEPTIVE_RADIUS {
        warnings.push(format!(
            "overlap {} px is below the receptive-field radius {RECEPTIVE_RADIUS} px: tiles larger than \
             the image are exact, smaller ones differ near their seams",
            opts.overlap
        ));
    }
    let padded = Image::new(pad_mirrored(&x.values, opts.border));
    let (ph, pw, _) = padded.dim();
    let (y, tiles) = infer_tiled(net, &padded, opts.tile, opts.overlap)?;
    let b = opts.border;
    let mut y = y.values.slice(s![b..b + h, b..b + w, ..]).to_owned();
    let values_below_zero = y.iter().filter(|&&v| v < 0.0).count();
    let values_below_minus_one = y.iter().filter(|&&v| v < -1.0).count();
    let min_raw = y.iter().copied().fold(f32::INFINITY, f32::min);
    if let Some(bad) = y.iter().find(|v| !v.is_finite()) {
        return Err(Error::data(
            DataCause::NotFinite,
            format!("the decoder produced {bad}: the weights are broken"),
        ));
    }
    if opts.negatives == Negatives::Clamp {
        y.mapv_inplace(|v| v.max(0.0));
    }
    let max = y.iter().copied().fold(f32::NEG_INFINITY, f32::max);
    let report = ReconstructStats {
        rows: h,
        cols: w,
        padded_rows: ph,
        padded_cols: pw,
        tiles,
        negatives: opts.negatives,
        values_below_zero,
        values_below_minus_one,
        min_raw,
        max,
        warnings,
    };
    Ok((Image::new(y), report))
}

/// A reconstruction written to disk (`doefab reconstruct`'s JSON).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ReconstructOutcome {
    /// The capture file.
    pub capture: String,
    /// The decoder file (or bundled decoder name).
    pub decoder: String,
    /// SHA-256 of the decoder's bytes, hex.
    pub decoder_sha256: String,
    /// The linear HDR written, OpenEXR (R, G, B; 1 = the capture's clipping level).
    pub exr: String,
    /// The tone-mapped sRGB picture written, PNG.
    pub png: String,
    /// Exposure of the picture, stops: it shows `clip(y 2^ev, 0, 1)`.
    pub ev: f64,
    /// Tiling and output options used.
    pub options: ReconstructOptions,
    /// What happened during the reconstruction (flattened into this object).
    #[serde(flatten)]
    pub stats: ReconstructStats,
}

/// Reads `capture`, reconstructs it with the decoder file `decoder` on `device`, writes the
/// linear HDR as EXR (channels R, G, B; 1 = the capture's clipping level) at `exr` and its
/// tone-mapped sRGB rendering at exposure `ev` at `png`.
pub fn reconstruct_file(
    capture: &Path,
    decoder: &Path,
    exr: &Path,
    png_path: &Path,
    ev: f64,
    opts: &ReconstructOptions,
    device: &burn::tensor::Device,
) -> Result<ReconstructOutcome> {
    let x = read_capture(capture)?;
    let weights = crate::decoder::weights::DecoderWeights::read(decoder)?;
    let net = UNet::from_weights(&weights, device);
    let (y, stats) = reconstruct(&net, &x, opts)?;
    let decoder_sha256 = crate::decoder::weights::decoder_sha256(decoder)?;
    let text = vec![
        ("quantity".to_string(), "linear HDR radiance, 1 = sensor clipping level of the capture".to_string()),
        ("source".to_string(), capture.display().to_string()),
        ("decoder_sha256".to_string(), decoder_sha256.clone()),
        ("negatives".to_string(), format!("{:?}", opts.negatives).to_lowercase()),
    ];
    let channels: Vec<ndarray::Array2<f32>> =
        (0..3).map(|c| y.values.slice(s![.., .., c]).to_owned()).collect();
    let meta = crate::io::raw_map::Metadata { pitch: None, unit: None, text };
    crate::io::exr::write_exr(exr, &[("R", &channels[0]), ("G", &channels[1]), ("B", &channels[2])], &meta)?;
    let png_meta = meta.with("tone_map", format!("sRGB of clip(y * 2^{ev}, 0, 1)"));
    crate::io::png::write_png_image_u8(png_path, &tone_map(&y, ev), &png_meta)?;
    Ok(ReconstructOutcome {
        capture: capture.display().to_string(),
        decoder: decoder.display().to_string(),
        decoder_sha256,
        exr: exr.display().to_string(),
        png: png_path.display().to_string(),
        ev,
        options: *opts,
        stats,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn mirrored_padding_reflects_without_repeating_the_edge() {
        let x = Array3::from_shape_fn((3, 5, 1), |(i, j, _)| (10 * i + j) as f32);
        let p = pad_mirrored(&x, 2);
        assert_eq!(p.dim(), (16, 16, 1));
        let row: Vec<f32> = (0..9).map(|j| p[[2, j, 0]]).collect();
        assert_eq!(row, [2.0, 1.0, 0.0, 1.0, 2.0, 3.0, 4.0, 3.0, 2.0]);
        let col: Vec<f32> = (0..16).map(|i| p[[i, 2, 0]]).collect();
        // Rows -2..14 of a 3-row axis: period 4.
        assert_eq!(
            col,
            [20.0, 10.0, 0.0, 10.0, 20.0, 10.0, 0.0, 10.0, 20.0, 10.0, 0.0, 10.0, 20.0, 10.0, 0.0, 10.0]
        );
        assert_eq!(pad_mirrored(&x, 0).slice(s![..3, ..5, ..]), x);
        let one = Array3::from_elem((1, 1, 1), 7.0f32);
        assert!(pad_mirrored(&one, 40).iter().all(|&v| v == 7.0));
    }

    #[test]
    fn windows_cover_the_axis_with_aligned_cores() {
        assert_eq!(windows(640, 1024, 128), vec![(0, 640, 0, 640)]);
        let w = windows(700, 384, 128);
        assert_eq!(w[0], (0, 256, 0, 128));
        assert_eq!(w[1], (0, 384, 128, 256));
        let last = *w.last().unwrap();
        assert_eq!(last.3, 700);
        for pair in w.windows(2) {
            assert_eq!(pair[0].3, pair[1].2, "cores abut");
        }
        assert!(w.iter().all(|&(a, b, c, _)| a.is_multiple_of(16) && c.is_multiple_of(16) && b - a <= 384));
    }
}
