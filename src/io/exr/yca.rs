//! Luminance/chroma OpenEXR images (channels `Y`, `RY`, `BY`, the chroma subsampled 2 x 2, as
//! OpenEXR's `RgbaOutputFile` writes photographs) and their RGB, reconstructed exactly as
//! OpenEXR's `RgbaInputFile` does (`ImfRgbaFile.cpp`, `ImfRgbaYca.cpp`; BSD-3-Clause,
//! Contributors to the OpenEXR Project), every intermediate rounded to half as there:
//!
//! 1. *Chroma, horizontally*: on each line holding chroma (even `y`), the missing samples (odd
//!    `x`) are interpolated by OpenEXR's 27-tap half-band filter, whose 14 non-zero taps
//!    `c = 0.002128, -0.007540, 0.019597, -0.043159, 0.087929, -0.186077, 0.627123` (and
//!    mirrored) weigh the samples at `x +- 1, 3, ..., 13`; samples beyond the edges repeat
//!    the first and the last.
//! 2. *Chroma, vertically*: on lines without chroma (odd `y`), the same taps weigh lines
//!    `y +- 1, ..., 13`; lines above the window repeat its first line, lines below it its
//!    second-to-last (the last holding chroma).
//! 3. *YCA to RGB*: `R = (RY + 1) Y`, `B = (BY + 1) Y`, `G = (Y - R w_R - B w_B) / w_G`, or
//!    `R = G = B = Y` where both chroma are 0. The luminance weights `w` are the middle row
//!    of the RGB-to-XYZ matrix of the file's chromaticities (Rec. 709 without the attribute),
//!    normalised to sum 1 (`RgbaYca::computeYw`), computed in single precision as there.
//! 4. *Saturation*: a pixel more saturated (`s = 1 - min/max`) than `1 - (1 - m)/4`, `m` the
//!    mean saturation of its four diagonal neighbours (capped at 1), is desaturated towards
//!    its largest component to that bound, its luminance kept (`RgbaYca::fixSaturation`).
//!
//! Chroma sampled other than 2 x 2 or chroma without luminance are refused (OpenEXR's reader
//! refuses the one and fills the missing luminance with 0.5); so is a data window whose origin
//! or size is not a multiple of the sampling, as OpenEXR refuses it
//! ([`super::scanline::read_channels`]).

use std::path::Path;

use half::f16;
use ndarray::Array3;

use super::chromaticities::REC709;
use super::scanline::{read_channels, Header, Plane};
use crate::error::{Error, Result};

/// Half of OpenEXR's chroma filter length `N` = 27.
const N2: i64 = 13;

/// The non-zero taps of OpenEXR's chroma reconstruction filter, at offsets -13, -11, ..., 13.
const TAPS: [f32; 14] = [
    0.002128, -0.007540, 0.019597, -0.043159, 0.087929, -0.186077, 0.627123, 0.627123, -0.186077, 0.087929,
    -0.043159, 0.019597, -0.007540, 0.002128,
];

/// Whether the file is a luminance/chroma image: chroma channels `RY` or `BY` and no `R`,
/// `G`, `B` (OpenEXR's `RgbaInputFile` then reconstructs RGB from them).
pub fn is_luminance_chroma(header: &Header) -> bool {
    let has = |n: &str| header.channel(n).is_some();
    (has("RY") || has("BY")) && !(has("R") || has("G") || has("B"))
}

/// Rounds to half, as storing a float into OpenEXR's `half` does.
fn h(x: f32) -> f32 {
    f16::from_f32(x).to_f32()
}

/// `std::max` / `std::min` of C++ (`a < b ? b : a`, `b < a ? b : a`), which OpenEXR uses.
fn cmax(a: f32, b: f32) -> f32 {
    if a < b {
        b
    } else {
        a
    }
}
fn cmin(a: f32, b: f32) -> f32 {
    if b < a {
        b
    } else {
        a
    }
}

/// The luminance weights `(w_R, w_G, w_B)` of chromaticities `c` (`RgbaYca::computeYw`, with
/// Imath's `RGBtoXYZ` in single precision).
pub fn luminance_weights(c: &[f32; 8]) -> [f32; 3] {
    let [rx, ry, gx, gy, bx, by, wx, wy] = *c;
    let y = 1.0f32;
    let x_w = wx * y / wy;
    let z_w = (1.0 - wx - wy) * y / wy;
    let d = rx * (by - gy) + bx * (gy - ry) + gx * (ry - by);
    let sr = (x_w * (by - gy) - gx * (y * (by - 1.0) + by * (x_w + z_w))
        + bx * (y * (gy - 1.0) + gy * (x_w + z_w)))
        / d;
    let sg = (x_w * (ry - by) + rx * (y * (by - 1.0) + by * (x_w + z_w))
        - bx * (y * (ry - 1.0) + ry * (x_w + z_w)))
        / d;
    let sb = (x_w * (gy - ry) - rx * (y * (gy - 1.0) + gy * (x_w + z_w))
        + gx * (y * (ry - 1.0) + ry * (x_w + z_w)))
        / d;
    let (m01, m11, m21) = (sr * ry, sg * gy, sb * by);
    let sum = m01 + m11 + m21;
    [m01 / sum, m11 / sum, m21 / sum]
}

/// The raw channels of a luminance/chroma file: `Y` at full resolution, `RY` and `BY` at their
/// sampling (a missing one reads as zeros, OpenEXR's fill value).
#[derive(Debug, Clone, PartialEq)]
pub struct LumaChroma {
    /// Luminance `Y`, one sample per pixel.
    pub y: Plane,
    /// Chroma `RY = (R - Y) / Y`, one sample per 2 x 2 pixels.
    pub ry: Plane,
    /// Chroma `BY = (B - Y) / Y`, one sample per 2 x 2 pixels.
    pub by: Plane,
    /// `[x_min, y_min, x_max, y_max]`.
    pub data_window: [i32; 4],
    /// The file's chromaticities, or Rec. 709.
    pub chromaticities: [f32; 8],
}

/// Reads the `Y`, `RY`, `BY` channels of a luminance/chroma scan-line file (see the module
/// docs for what is refused).
pub fn read_luma_chroma(path: &Path, bytes: &[u8], header: &Header) -> Result<LumaChroma> {
    let fail = |what: String| Error::unsupported(path, format!("OpenEXR luminance/chroma image: {what}"));
    let y = header.channel("Y").ok_or_else(|| {
        Error::malformed(
            path,
            "OpenEXR luminance/chroma image: has chroma (RY, BY) but no luminance channel Y",
        )
    })?;
    if (y.x_sampling, y.y_sampling) != (1, 1) {
        return Err(fail(format!(
            "channel Y is sampled {} x {}, expected 1 x 1",
            y.x_sampling, y.y_sampling
        )));
    }
    for c in header.channels.iter().filter(|c| c.name == "RY" || c.name == "BY") {
        if (c.x_sampling, c.y_sampling) != (2, 2) {
            return Err(fail(format!(
                "channel {} is sampled {} x {}, expected 2 x 2 (as OpenEXR's RgbaOutputFile writes it)",
                c.name, c.x_sampling, c.y_sampling
            )));
        }
    }
    let names: Vec<&str> = ["Y", "RY", "BY"].into_iter().filter(|n| header.channel(n).is_some()).collect();
    let mut planes = read_channels(path, bytes, header, &names)?.into_iter();
    let y = planes.next().expect("Y was asked for");
    let (rows, cols) = (header.height().div_ceil(2), header.width().div_ceil(2));
    let zeros = || Plane { rows, cols, values: vec![0.0; rows * cols] };
    let ry = if header.channel("RY").is_some() { planes.next().expect("RY asked for") } else { zeros() };
    let by = if header.channel("BY").is_some() { planes.next().expect("BY asked for") } else { zeros() };
    Ok(LumaChroma {
        y,
        ry,
        by,
        data_window: header.data_window,
        chromaticities: header.chromaticities.unwrap_or(REC709),
    })
}

/// OpenEXR's conversion of a float sample to half (`floatToHalf`: finite values beyond the
/// half range clamp to +-65504).
fn float_to_half(x: f32) -> f32 {
    if x.is_finite() {
        h(x.clamp(-65504.0, 65504.0))
    } else {
        h(x)
    }
}

/// The RGB of a luminance/chroma image, `(H, W, 3)`, in the file's primaries, every value a
/// half (see the module docs).
pub fn reconstruct_rgb(lc: &LumaChroma) -> Array3<f32> {
    let (hgt, w) = (lc.y.rows, lc.y.cols);
    let yw = luminance_weights(&lc.chromaticities);
    let luma: Vec<f32> = lc.y.values.iter().map(|&v| float_to_half(v)).collect();
    // Step 1: every chroma line (even rows) at full width.
    let horiz = |plane: &Plane| -> Vec<Vec<f32>> {
        (0..plane.rows)
            .map(|k| {
                let row: Vec<f32> = plane.values[k * plane.cols..(k + 1) * plane.cols]
                    .iter()
                    .map(|&v| float_to_half(v))
                    .collect();
                let at = |p: i64| row[(p.clamp(0, w as i64 - 1) / 2) as usize];
                (0..w as i64)
                    .map(|j| match j % 2 {
                        0 => at(j),
                        _ => h(filter((0..14).map(|t| at(j - N2 + 2 * t)))),
                    })
                    .collect()
            })
            .collect()
    };
    let (ry, by) = (horiz(&lc.ry), horiz(&lc.by));
    // OpenEXR's readYCAScanLine: the line read for `l` (rows relative to the window, whose
    // height is even), and the chroma line it carries (used only where `r` is even).
    let last = hgt as i64 - 1;
    let line = |l: i64| -> (usize, usize) {
        let r = if l < 0 {
            0
        } else if l > last {
            last - 1
        } else {
            l
        };
        (r as usize, (r / 2) as usize)
    };
    // Steps 2 and 3: the RGB of lines -1 ..= hgt (the saturation fix reads one line beyond).
    let rgb_line = |l: i64| -> Vec<[f32; 3]> {
        let (r, c) = line(l);
        let yrow = &luma[r * w..(r + 1) * w];
        let chroma: Vec<(f32, f32)> = if l.rem_euclid(2) == 0 {
            (0..w).map(|x| (ry[c][x], by[c][x])).collect()
        } else {
            let taps: Vec<usize> = (0..14).map(|t| line(l - N2 + 2 * t).1).collect();
            (0..w)
                .map(|x| {
                    let f = |p: &Vec<Vec<f32>>| h(filter(taps.iter().map(|&k| p[k][x])));
                    (f(&ry), f(&by))
                })
                .collect()
        };
        yrow.iter()
            .zip(chroma)
            .map(|(&yv, (cr, cb))| {
                if cr == 0.0 && cb == 0.0 {
                    [yv, yv, yv]
                } else {
                    let r = (cr + 1.0) * yv;
                    let b = (cb + 1.0) * yv;
                    let g = (yv - r * yw[0] - b * yw[2]) / yw[1];
                    [h(r), h(g), h(b)]
                }
            })
            .collect()
    };
    let lines: Vec<Vec<[f32; 3]>> = (-1..=hgt as i64).map(rgb_line).collect();
    // Step 4.
    let mut out = Array3::zeros((hgt, w, 3));
    for l in 0..hgt {
        let fixed = fix_saturation(&yw, &lines[l], &lines[l + 1], &lines[l + 2]);
        for (x, p) in fixed.iter().enumerate() {
            for c in 0..3 {
                out[[l, x, c]] = p[c];
            }
        }
    }
    out
}

/// The chroma filter over 14 samples, summed left to right in single precision as OpenEXR's
/// expression is.
fn filter(samples: impl Iterator<Item = f32>) -> f32 {
    let mut terms = samples.zip(TAPS).map(|(v, c)| v * c);
    let first = terms.next().expect("14 taps");
    terms.fold(first, |s, t| s + t)
}

fn saturation(p: &[f32; 3]) -> f32 {
    let max = cmax(p[0], cmax(p[1], p[2]));
    let min = cmin(p[0], cmin(p[1], p[2]));
    if max > 0.0 {
        1.0 - min / max
    } else {
        0.0
    }
}

/// `RgbaYca::fixSaturation` for line `cur` between `above` and `below`.
fn fix_saturation(yw: &[f32; 3], above: &[[f32; 3]], cur: &[[f32; 3]], below: &[[f32; 3]]) -> Vec<[f32; 3]> {
    let n = cur.len();
    let (mut a2, mut b2) = (saturation(&above[0]), saturation(&below[0]));
    let (mut a1, mut b1) = (a2, b2);
    let mut out = Vec::with_capacity(n);
    for i in 0..n {
        let (a0, b0) = (a1, b1);
        a1 = a2;
        b1 = b2;
        if i < n - 1 {
            a2 = saturation(&above[i + 1]);
            b2 = saturation(&below[i + 1]);
        }
        let s_mean = cmin(1.0, 0.25 * (a0 + a2 + b0 + b2));
        let p = cur[i];
        let s = saturation(&p);
        if s > s_mean {
            let s_max = cmin(1.0, 1.0 - (1.0 - s_mean) * 0.25);
            if s > s_max {
                out.push(desaturate(&p, s_max / s, yw));
                continue;
            }
        }
        out.push(p);
    }
    out
}

/// `RgbaYca::desaturate`: components pulled towards the largest by factor `f`, luminance kept.
fn desaturate(p: &[f32; 3], f: f32, yw: &[f32; 3]) -> [f32; 3] {
    let max = cmax(p[0], cmax(p[1], p[2]));
    let mut o = p.map(|v| h(cmax(max - (max - v) * f, 0.0)));
    let y_in = p[0] * yw[0] + p[1] * yw[1] + p[2] * yw[2];
    let y_out = o[0] * yw[0] + o[1] * yw[1] + o[2] * yw[2];
    if y_out > 0.0 {
        o = o.map(|v| h(v * (y_in / y_out)));
    }
    o
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Rec. 709's luminance weights are the familiar 0.2126, 0.7152, 0.0722.
    #[test]
    fn rec709_luminance_weights() {
        let w = luminance_weights(&REC709);
        for (a, b) in w.iter().zip([0.2126, 0.7152, 0.0722]) {
            assert!((a - b).abs() < 1e-4, "{w:?}");
        }
    }

    fn uniform(hgt: usize, w: usize, y: f32, ry: f32, by: f32) -> LumaChroma {
        let (rows, cols) = (hgt.div_ceil(2), w.div_ceil(2));
        LumaChroma {
            y: Plane { rows: hgt, cols: w, values: vec![y; hgt * w] },
            ry: Plane { rows, cols, values: vec![ry; rows * cols] },
            by: Plane { rows, cols, values: vec![by; rows * cols] },
            data_window: [0, 0, w as i32 - 1, hgt as i32 - 1],
            chromaticities: REC709,
        }
    }

    /// A uniform colour comes back as itself (the filters' taps sum to 1 within 1e-6); grey
    /// (zero chroma) exactly.
    #[test]
    fn uniform_colour_and_grey_come_back() {
        let yw = luminance_weights(&REC709);
        let rgb = [2.0f32, 1.0, 0.5];
        let y = h(rgb[0] * yw[0] + rgb[1] * yw[1] + rgb[2] * yw[2]);
        let (ry, by) = (h((rgb[0] - y) / y), h((rgb[2] - y) / y));
        for (hgt, w) in [(6, 8), (2, 2), (34, 40)] {
            let out = reconstruct_rgb(&uniform(hgt, w, y, ry, by));
            for (k, v) in out.iter().enumerate() {
                assert!((v - rgb[k % 3]).abs() <= 2e-3 * rgb[k % 3], "{hgt}x{w}: {v} vs {}", rgb[k % 3]);
            }
            let grey = reconstruct_rgb(&uniform(hgt, w, 0.75, 0.0, 0.0));
            assert!(grey.iter().all(|&v| v == 0.75));
        }
    }
}
