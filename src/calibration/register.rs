//! Affine registration of two views of one scene (the reference HDR taken without the DOE
//! and a capture or reconstruction taken with it: a few percent of scale, about a degree of
//! rotation, tens of pixels at the corners).
//!
//! Model, in pixel coordinates `(x, y) = (col, row)`: a reference point `p` appears in the
//! target at `q = A p + b`.
//!
//! 1. Both images are compared as the square root of their channel mean (compressing the
//!    dynamic range so that lamps do not dominate).
//! 2. *Tile matching*: square tiles of the reference (overlapping by half) are found in the target
//!    by normalised cross-correlation (NCC), first on images binned by 4 within
//!    `max_shift`, then at full resolution within 3 px of that, refined to sub-pixel by a
//!    parabola through the NCC peak and its neighbours in x and y. Tiles with little texture
//!    (standard deviation below 2 % of the image's), a peak NCC below 0.6, or a peak flat
//!    along x or y (second difference above -0.002: a straight edge, whose shift along itself
//!    is unknown) are dropped.
//! 3. *Least squares with outlier rejection*: `A, b` from the matched tile centres by linear
//!    least squares; tiles whose residual exceeds `max(3 sigma, 1 px)` (`sigma = 1.4826 MAD`)
//!    are rejected and the fit repeated until no tile changes (at most 10 times). Fewer than 6
//!    tiles, or a fit whose RMS residual is above 2 px, are refused.
//! 4. *Refinement*: the target is mapped back through the fit (bilinear) and steps 2-3 run
//!    again within 4 px; the parabola's sub-pixel estimate is biased towards whole pixels
//!    (up to about 0.1 px at half a pixel) and unbiased near zero shift, so the residual map
//!    composed with the first one is accurate to a few hundredths of a pixel.
//!
//! The tile matching assumes the local motion within a tile is a shift: the scale and rotation
//! must move a tile's corners by well under a pixel relative to its centre (`|A - I| T / 2 <<
//! 1` for tile size `T`), which holds for the default 48 px tiles up to about 3 % scale or 2 deg.

use ndarray::{Array2, Array3};
use serde::Serialize;

use crate::error::{Error, Result};
use crate::metrology::level::solve;

/// `q = a p + b` in pixel coordinates `(x, y) = (col, row)`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Affine {
    pub a: [[f64; 2]; 2],
    pub b: [f64; 2],
}

impl Affine {
    pub fn apply(&self, p: [f64; 2]) -> [f64; 2] {
        [
            self.a[0][0] * p[0] + self.a[0][1] * p[1] + self.b[0],
            self.a[1][0] * p[0] + self.a[1][1] * p[1] + self.b[1],
        ]
    }

    /// The inverse map, `None` when `a` is singular.
    pub fn inverse(&self) -> Option<Affine> {
        let [[a, b], [c, d]] = self.a;
        let det = a * d - b * c;
        if det.abs() < 1e-12 {
            return None;
        }
        let ai = [[d / det, -b / det], [-c / det, a / det]];
        let bi =
            [-(ai[0][0] * self.b[0] + ai[0][1] * self.b[1]), -(ai[1][0] * self.b[0] + ai[1][1] * self.b[1])];
        Some(Affine { a: ai, b: bi })
    }
}

/// Options of [`register_affine`].
#[derive(Debug, Clone, PartialEq)]
pub struct RegisterOptions {
    /// Tile side, pixels.
    pub tile: usize,
    /// Largest displacement searched, pixels.
    pub max_shift: usize,
}

impl Default for RegisterOptions {
    fn default() -> Self {
        RegisterOptions { tile: 48, max_shift: 48 }
    }
}

/// The fitted map and how well it fits.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Registration {
    pub affine: Affine,
    /// Mean scale `sqrt(det A)` and rotation (degrees, counter-clockwise in (x, y)).
    pub scale: f64,
    pub rotation_deg: f64,
    pub tiles_matched: usize,
    pub tiles_used: usize,
    /// RMS distance between the matched tile positions and the fitted map, pixels.
    pub residual_rms_px: f64,
}

/// The square root of the channel mean of an `(H, W, C)` image (negative values as 0).
pub fn luminance(img: &Array3<f64>) -> Array2<f64> {
    let (h, w, c) = img.dim();
    Array2::from_shape_fn((h, w), |(i, j)| {
        ((0..c).map(|k| img[[i, j, k]]).sum::<f64>() / c as f64).max(0.0).sqrt()
    })
}

fn bin(img: &Array2<f64>, f: usize) -> Array2<f64> {
    let (h, w) = (img.dim().0 / f, img.dim().1 / f);
    Array2::from_shape_fn((h, w), |(i, j)| {
        let mut s = 0.0;
        for a in 0..f {
            for b in 0..f {
                s += img[[i * f + a, j * f + b]];
            }
        }
        s / (f * f) as f64
    })
}

/// NCC of the `t x t` tile of `r` at `(r0, c0)` with `g` at `(r0 + dy, c0 + dx)`; `None` outside.
fn ncc(
    r: &Array2<f64>,
    g: &Array2<f64>,
    r0: usize,
    c0: usize,
    t: usize,
    dy: isize,
    dx: isize,
) -> Option<f64> {
    let (gi, gj) = (r0 as isize + dy, c0 as isize + dx);
    if gi < 0 || gj < 0 || gi as usize + t > g.dim().0 || gj as usize + t > g.dim().1 {
        return None;
    }
    let (gi, gj) = (gi as usize, gj as usize);
    let n = (t * t) as f64;
    let (mut sa, mut sb, mut saa, mut sbb, mut sab) = (0.0, 0.0, 0.0, 0.0, 0.0);
    for i in 0..t {
        for j in 0..t {
            let a = r[[r0 + i, c0 + j]];
            let b = g[[gi + i, gj + j]];
            sa += a;
            sb += b;
            saa += a * a;
            sbb += b * b;
            sab += a * b;
        }
    }
    let va = saa - sa * sa / n;
    let vb = sbb - sb * sb / n;
    (va > 0.0 && vb > 0.0).then(|| (sab - sa * sb / n) / (va * vb).sqrt())
}

/// Best offset of a tile within `radius` of `(cy, cx)`.
#[allow(clippy::too_many_arguments)]
fn search(
    r: &Array2<f64>,
    g: &Array2<f64>,
    r0: usize,
    c0: usize,
    t: usize,
    cy: isize,
    cx: isize,
    radius: isize,
) -> Option<(isize, isize, f64)> {
    let mut best: Option<(isize, isize, f64)> = None;
    for dy in cy - radius..=cy + radius {
        for dx in cx - radius..=cx + radius {
            if let Some(v) = ncc(r, g, r0, c0, t, dy, dx) {
                if best.is_none_or(|b| v > b.2) {
                    best = Some((dy, dx, v));
                }
            }
        }
    }
    best
}

fn std_dev(img: &Array2<f64>) -> f64 {
    let n = img.len() as f64;
    let m = img.sum() / n;
    (img.iter().map(|v| (v - m).powi(2)).sum::<f64>() / n).sqrt()
}

/// Finds the affine map of `reference` onto `target` (both single-channel, e.g. [`luminance`]).
pub fn register_affine(
    reference: &Array2<f64>,
    target: &Array2<f64>,
    opts: &RegisterOptions,
) -> Result<Registration> {
    let first = match_and_fit(reference, target, opts)?;
    // Refinement: the target mapped back through the first fit differs from the reference by
    // a fraction of a pixel, where the parabola's sub-pixel estimate is unbiased.
    let a0 = first.affine;
    let inv = a0.inverse().ok_or_else(|| Error::Data("the affine fit is singular".into()))?;
    let (h, w) = reference.dim();
    let (back, _) = warp(&target.clone().insert_axis(ndarray::Axis(2)), &inv, h, w)?;
    let back = back.index_axis_move(ndarray::Axis(2), 0);
    let fine = match_and_fit(reference, &back, &RegisterOptions { max_shift: 4, ..opts.clone() })?;
    // q = A0 (C p + d) + b0.
    let (c, d) = (fine.affine.a, fine.affine.b);
    let a = [
        [a0.a[0][0] * c[0][0] + a0.a[0][1] * c[1][0], a0.a[0][0] * c[0][1] + a0.a[0][1] * c[1][1]],
        [a0.a[1][0] * c[0][0] + a0.a[1][1] * c[1][0], a0.a[1][0] * c[0][1] + a0.a[1][1] * c[1][1]],
    ];
    let b =
        [a0.a[0][0] * d[0] + a0.a[0][1] * d[1] + a0.b[0], a0.a[1][0] * d[0] + a0.a[1][1] * d[1] + a0.b[1]];
    let affine = Affine { a, b };
    let det = a[0][0] * a[1][1] - a[0][1] * a[1][0];
    Ok(Registration {
        affine,
        scale: det.abs().sqrt(),
        rotation_deg: (a[1][0] - a[0][1]).atan2(a[0][0] + a[1][1]).to_degrees(),
        tiles_matched: fine.tiles_matched,
        tiles_used: fine.tiles_used,
        residual_rms_px: fine.residual_rms_px,
    })
}

/// One pass of tile matching and the robust least-squares fit.
fn match_and_fit(
    reference: &Array2<f64>,
    target: &Array2<f64>,
    opts: &RegisterOptions,
) -> Result<Registration> {
    const BIN: usize = 4;
    const MIN_CURVATURE: f64 = 2e-3;
    let t = opts.tile.max(16) / BIN * BIN;
    let (h, w) = reference.dim();
    if h < 3 * t || w < 3 * t || target.dim().0 < 3 * t || target.dim().1 < 3 * t {
        return Err(Error::param("register", format!("images of {w} x {h} are too small for {t} px tiles")));
    }
    let (rb, gb) = (bin(reference, BIN), bin(target, BIN));
    let texture = 0.02 * std_dev(reference);
    let radius = (opts.max_shift / BIN).max(1) as isize;
    let mut matches: Vec<([f64; 2], [f64; 2])> = Vec::new();
    let margin = t / 2;
    let mut r0 = margin;
    while r0 + t + margin <= h {
        let mut c0 = margin;
        while c0 + t + margin <= w {
            let tile = reference.slice(ndarray::s![r0..r0 + t, c0..c0 + t]).to_owned();
            if std_dev(&tile) > texture {
                let coarse = search(&rb, &gb, r0 / BIN, c0 / BIN, t / BIN, 0, 0, radius);
                if let Some((cy, cx, _)) = coarse {
                    let fine = search(reference, target, r0, c0, t, cy * BIN as isize, cx * BIN as isize, 3);
                    if let Some((dy, dx, v)) = fine.filter(|f| f.2 > 0.6) {
                        // Sub-pixel offset of a parabola through three samples; `None` where
                        // the peak is flat along that axis (an edge: the aperture problem).
                        let sub = |m: Option<f64>, p: Option<f64>| match (m, p) {
                            (Some(m), Some(p)) if m + p - 2.0 * v < -MIN_CURVATURE => {
                                Some(0.5 * (m - p) / (m + p - 2.0 * v))
                            }
                            _ => None,
                        };
                        let at = |y: isize, x: isize| ncc(reference, target, r0, c0, t, y, x);
                        let fy = sub(at(dy - 1, dx), at(dy + 1, dx));
                        let fx = sub(at(dy, dx - 1), at(dy, dx + 1));
                        if let (Some(fy), Some(fx)) = (fy, fx) {
                            let p = [c0 as f64 + (t as f64 - 1.0) * 0.5, r0 as f64 + (t as f64 - 1.0) * 0.5];
                            matches.push((p, [p[0] + dx as f64 + fx, p[1] + dy as f64 + fy]));
                        }
                    }
                }
            }
            c0 += t / 2;
        }
        r0 += t / 2;
    }
    let matched = matches.len();
    let mut keep = vec![true; matched];
    let mut fit = None;
    for _ in 0..10 {
        let used: Vec<&([f64; 2], [f64; 2])> =
            matches.iter().zip(&keep).filter(|(_, k)| **k).map(|(m, _)| m).collect();
        if used.len() < 6 {
            return Err(Error::Data(format!(
                "only {} of {matched} tiles matched consistently (6 needed): the images do not show the same \
                 scene, or move by more than {} px",
                used.len(),
                opts.max_shift
            )));
        }
        let affine = fit_affine(&used)?;
        let res: Vec<f64> = matches
            .iter()
            .map(|(p, q)| {
                let f = affine.apply(*p);
                ((f[0] - q[0]).powi(2) + (f[1] - q[1]).powi(2)).sqrt()
            })
            .collect();
        let mut kept: Vec<f64> = res.iter().zip(&keep).filter(|(_, k)| **k).map(|(r, _)| *r).collect();
        kept.sort_by(f64::total_cmp);
        let sigma = 1.4826 * kept[kept.len() / 2];
        let limit = (3.0 * sigma).max(1.0);
        let next: Vec<bool> = res.iter().map(|&r| r <= limit).collect();
        let rms = (kept.iter().map(|r| r * r).sum::<f64>() / kept.len() as f64).sqrt();
        fit = Some((affine, rms, kept.len()));
        if next == keep {
            break;
        }
        keep = next;
    }
    let Some((affine, rms, used)) = fit else {
        return Err(Error::Data("no tiles matched".into()));
    };
    if rms > 2.0 {
        return Err(Error::Validity(format!(
            "the affine fit leaves {rms:.2} px RMS over {used} tiles: the motion is not affine, or the \
             tiles locked onto different features (a raw capture through the DOE holds shifted copies \
             of the scene; register its reconstruction instead)"
        )));
    }
    let [[a, b], [c, d]] = affine.a;
    Ok(Registration {
        affine,
        scale: (a * d - b * c).abs().sqrt(),
        rotation_deg: (c - b).atan2(a + d).to_degrees(),
        tiles_matched: matched,
        tiles_used: used,
        residual_rms_px: rms,
    })
}

/// Least squares `q = A p + b` over point pairs.
fn fit_affine(pairs: &[&([f64; 2], [f64; 2])]) -> Result<Affine> {
    let mut ata = vec![0.0; 9];
    let mut atq = [vec![0.0; 3], vec![0.0; 3]];
    for (p, q) in pairs {
        let f = [p[0], p[1], 1.0];
        for r in 0..3 {
            for c in 0..3 {
                ata[r * 3 + c] += f[r] * f[c];
            }
            atq[0][r] += f[r] * q[0];
            atq[1][r] += f[r] * q[1];
        }
    }
    let x = solve(ata.clone(), atq[0].clone(), 3)?;
    let y = solve(ata, atq[1].clone(), 3)?;
    Ok(Affine { a: [[x[0], x[1]], [y[0], y[1]]], b: [x[2], y[2]] })
}

/// The reference resampled onto the target's pixels (`rows x cols`) through `affine`
/// (bilinear), with the mask of target pixels whose source lies inside the reference.
pub fn warp(
    reference: &Array3<f64>,
    affine: &Affine,
    rows: usize,
    cols: usize,
) -> Result<(Array3<f64>, Array2<bool>)> {
    let inv = affine.inverse().ok_or_else(|| Error::Data("the affine map is singular".into()))?;
    let (h, w, nc) = reference.dim();
    let mut out = Array3::<f64>::zeros((rows, cols, nc));
    let mut inside = Array2::from_elem((rows, cols), false);
    for i in 0..rows {
        for j in 0..cols {
            let [x, y] = inv.apply([j as f64, i as f64]);
            if x < 0.0 || y < 0.0 || x > (w - 1) as f64 || y > (h - 1) as f64 {
                continue;
            }
            let (i0, j0) = (
                (y.floor() as usize).min(h.saturating_sub(2)),
                (x.floor() as usize).min(w.saturating_sub(2)),
            );
            let (ty, tx) = (y - i0 as f64, x - j0 as f64);
            for c in 0..nc {
                let v = (1.0 - ty) * ((1.0 - tx) * reference[[i0, j0, c]] + tx * reference[[i0, j0 + 1, c]])
                    + ty * ((1.0 - tx) * reference[[i0 + 1, j0, c]] + tx * reference[[i0 + 1, j0 + 1, c]]);
                out[[i, j, c]] = v;
            }
            inside[[i, j]] = true;
        }
    }
    Ok((out, inside))
}
