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
//! 3. *Robust fit*: RANSAC (Fischler and Bolles 1981) over triples of matched tile centres
//!    finds the affine map that most tiles follow within 1.5 px; least squares on those
//!    inliers, re-selected until they do not change, gives `A, b`. Fewer than 6 inliers, or
//!    fewer than two thirds of the matched tiles, are refused: the motion is then not one
//!    affine map (parallax between objects at different depths: [`register_local`] follows
//!    it), or the tiles locked onto different features.
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

use crate::error::{Condition, DataCause, Error, Result};
use crate::image::Image;
use crate::linalg::solve;
use crate::rng::Lcg;
use rayon::prelude::*;

/// `q = a p + b` in pixel coordinates `(x, y) = (col, row)`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Affine {
    /// The linear part, row-major: `q_x = a[0][0] p_x + a[0][1] p_y + b[0]`.
    pub a: [[f64; 2]; 2],
    /// The translation `[x, y]`, pixels.
    pub b: [f64; 2],
}

impl Affine {
    /// The image `a p + b` of the point `p` (`[x, y]`, pixels).
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

/// Options of [`register_affine`] and [`register_local`].
#[derive(Debug, Clone, PartialEq)]
pub struct RegisterOptions {
    /// Tile side, pixels.
    pub tile: usize,
    /// Largest displacement searched, pixels.
    pub max_shift: usize,
    /// Which motion model [`super::evaluate::prepare`] fits.
    pub model: Model,
    /// Smallest fraction of the image a local field must cover; below it [`register_local`]
    /// refuses (too little texture to follow the motion).
    pub min_coverage: f64,
}

/// The motion model of a registration.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Model {
    /// One affine map ([`register_affine`]).
    Affine,
    /// A smooth displacement field ([`register_local`]).
    Local,
}

impl Default for RegisterOptions {
    fn default() -> Self {
        RegisterOptions { tile: 48, max_shift: 48, model: Model::Affine, min_coverage: 0.25 }
    }
}

/// The fitted map and how well it fits.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Registration {
    /// The map of the reference onto the target, `q = A p + b`, pixels.
    pub affine: Affine,
    /// Mean scale `sqrt(|det A|)`, target over reference.
    pub scale: f64,
    /// Rotation, degrees, counter-clockwise in `(x, y)`: `atan2(A10 - A01, A00 + A11)`.
    pub rotation_deg: f64,
    /// Tiles matched in the refinement pass (enough texture, a clear NCC peak).
    pub tiles_matched: usize,
    /// Of those, the tiles the fitted map follows within 1.5 px (the inliers it was fitted on).
    pub tiles_used: usize,
    /// RMS distance between the matched tile positions and the fitted map, pixels.
    pub residual_rms_px: f64,
}

/// The square root of the channel mean of an image (negative values as 0).
pub fn luminance(img: &Image) -> Array2<f64> {
    img.channel_mean().mapv(|v| v.max(0.0).sqrt())
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

/// The `t x t` tile of `r` at `(r0, c0)`, to be found in `g`.
struct Tile<'a> {
    r: &'a Array2<f64>,
    g: &'a Array2<f64>,
    r0: usize,
    c0: usize,
    t: usize,
}

impl Tile<'_> {
    /// NCC of the tile with `g` at `(r0 + dy, c0 + dx)`; `None` outside `g`.
    fn ncc(&self, dy: isize, dx: isize) -> Option<f64> {
        let (r, g, r0, c0, t) = (self.r, self.g, self.r0, self.c0, self.t);
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

    /// Best whole-pixel offset within `radius` of `(cy, cx)`, with its NCC.
    fn search(&self, cy: isize, cx: isize, radius: isize) -> Option<(isize, isize, f64)> {
        let mut best: Option<(isize, isize, f64)> = None;
        for dy in cy - radius..=cy + radius {
            for dx in cx - radius..=cx + radius {
                if let Some(v) = self.ncc(dy, dx) {
                    if best.is_none_or(|b| v > b.2) {
                        best = Some((dy, dx, v));
                    }
                }
            }
        }
        best
    }

    /// [`Tile::search`] refined to sub-pixel by a parabola through the NCC peak and its
    /// neighbours along each axis; `None` where the peak NCC is below 0.6 or flat along an axis
    /// (second difference above -0.002: an edge, whose shift along itself is unknown).
    fn refine(&self, cy: isize, cx: isize, radius: isize) -> Option<(f64, f64)> {
        const MIN_CURVATURE: f64 = 2e-3;
        let (dy, dx, v) = self.search(cy, cx, radius).filter(|f| f.2 > 0.6)?;
        let sub = |m: Option<f64>, p: Option<f64>| match (m, p) {
            (Some(m), Some(p)) if m + p - 2.0 * v < -MIN_CURVATURE => Some(0.5 * (m - p) / (m + p - 2.0 * v)),
            _ => None,
        };
        let fy = sub(self.ncc(dy - 1, dx), self.ncc(dy + 1, dx))?;
        let fx = sub(self.ncc(dy, dx - 1), self.ncc(dy, dx + 1))?;
        Some((dy as f64 + fy, dx as f64 + fx))
    }
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
    let inv = a0.inverse().ok_or_else(|| Error::data(DataCause::Singular, "the affine fit is singular"))?;
    let (h, w) = reference.dim();
    let (back, _) = warp(&Image::new(target.clone().insert_axis(ndarray::Axis(2))), &inv, h, w)?;
    let back = back.values.index_axis_move(ndarray::Axis(2), 0);
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

/// Matched tile centres `(p, q)`: square tiles of `reference` (overlapping by half) found in
/// `target` by NCC, coarse on 4x binned images within `max_shift`, then at full resolution
/// within 3 px, refined to sub-pixel by a parabola (tiles with little texture, a weak or flat
/// peak are dropped; see the module docs).
fn match_tiles(reference: &Array2<f64>, target: &Array2<f64>, opts: &RegisterOptions) -> Result<Vec<Match>> {
    const BIN: usize = 4;
    let t = opts.tile.max(16) / BIN * BIN;
    let (h, w) = reference.dim();
    if h < 3 * t || w < 3 * t || target.dim().0 < 3 * t || target.dim().1 < 3 * t {
        return Err(Error::param("register", format!("images of {w} x {h} are too small for {t} px tiles")));
    }
    let (rb, gb) = (bin(reference, BIN), bin(target, BIN));
    let texture = 0.02 * std_dev(reference);
    let radius = (opts.max_shift / BIN).max(1) as isize;
    let margin = t / 2;
    let corners: Vec<(usize, usize)> = (0..)
        .map(|k| margin + k * t / 2)
        .take_while(|r0| r0 + t + margin <= h)
        .flat_map(|r0| {
            (0..).map(move |k| (r0, margin + k * t / 2)).take_while(|(_, c0)| c0 + t + margin <= w)
        })
        .collect();
    Ok(corners
        .par_iter()
        .filter_map(|&(r0, c0)| {
            let tile = reference.slice(ndarray::s![r0..r0 + t, c0..c0 + t]).to_owned();
            if std_dev(&tile) <= texture {
                return None;
            }
            let coarse = Tile { r: &rb, g: &gb, r0: r0 / BIN, c0: c0 / BIN, t: t / BIN };
            let (cy, cx, _) = coarse.search(0, 0, radius)?;
            let fine = Tile { r: reference, g: target, r0, c0, t };
            let (dy, dx) = fine.refine(cy * BIN as isize, cx * BIN as isize, 3)?;
            let p = [c0 as f64 + (t as f64 - 1.0) * 0.5, r0 as f64 + (t as f64 - 1.0) * 0.5];
            Some((p, [p[0] + dx, p[1] + dy]))
        })
        .collect())
}

/// A matched pair of tile centres, reference `p` and target `q`, pixels `(x, y)`.
type Match = ([f64; 2], [f64; 2]);

/// One pass of tile matching and the robust fit.
fn match_and_fit(
    reference: &Array2<f64>,
    target: &Array2<f64>,
    opts: &RegisterOptions,
) -> Result<Registration> {
    let matches = match_tiles(reference, target, opts)?;
    let (affine, rms, used) = robust_affine(&matches, opts.max_shift)?;
    if 3 * used < 2 * matches.len() {
        return Err(Error::validity(Condition::Model, format!(
            "one affine map fits only {used} of {} matched tiles within 1.5 px (two thirds needed): the motion is not \
             affine (parallax between objects at different depths), or the tiles locked onto different \
             features (a raw capture through the DOE holds shifted copies of the scene; register its \
             reconstruction instead); a local registration follows such motion",
            matches.len()
        )));
    }
    let [[a, b], [c, d]] = affine.a;
    Ok(Registration {
        affine,
        scale: (a * d - b * c).abs().sqrt(),
        rotation_deg: (c - b).atan2(a + d).to_degrees(),
        tiles_matched: matches.len(),
        tiles_used: used,
        residual_rms_px: rms,
    })
}

/// The affine map best supported by `matches`: RANSAC over triples of tiles (500 draws of a
/// seeded generator, inliers within 1.5 px; Fischler and Bolles 1981), then least squares on
/// the inliers, selecting the inliers of that fit and refitting until they do not change (at
/// most 10 times). Returns the map, the RMS
/// residual over the tiles used and their number; fewer than 6 consistent tiles are refused.
fn robust_affine(matches: &[Match], max_shift: usize) -> Result<(Affine, f64, usize)> {
    const DRAWS: usize = 500;
    const INLIER_PX: f64 = 1.5;
    let matched = matches.len();
    let too_few = |n: usize| {
        let what = format!(
            "only {n} of {matched} tiles matched consistently (6 needed): the images do not show the same \
             scene, or move by more than {max_shift} px"
        );
        Error::data(DataCause::TooFew, what)
    };
    if matched < 6 {
        return Err(too_few(matched));
    }
    let residuals = |a: &Affine| -> Vec<f64> {
        matches
            .iter()
            .map(|(p, q)| {
                let f = a.apply(*p);
                ((f[0] - q[0]).powi(2) + (f[1] - q[1]).powi(2)).sqrt()
            })
            .collect()
    };
    let mut rng = Lcg(0x5eed_a551);
    let mut keep = vec![true; matched];
    let mut best = 0;
    for _ in 0..DRAWS {
        let pick: Vec<&Match> = (0..3).map(|_| &matches[(rng.uniform() * matched as f64) as usize]).collect();
        let Ok(a) = fit_affine(&pick) else { continue };
        let inside: Vec<bool> = residuals(&a).iter().map(|r| *r <= INLIER_PX).collect();
        let n = inside.iter().filter(|v| **v).count();
        if n > best {
            best = n;
            keep = inside;
        }
    }
    let mut fit = None;
    for _ in 0..10 {
        let used: Vec<&Match> = matches.iter().zip(&keep).filter(|(_, k)| **k).map(|(m, _)| m).collect();
        if used.len() < 6 {
            return Err(too_few(used.len()));
        }
        let affine = fit_affine(&used)?;
        let res = residuals(&affine);
        let kept: Vec<f64> = res.iter().zip(&keep).filter(|(_, k)| **k).map(|(r, _)| *r).collect();
        let next: Vec<bool> = res.iter().map(|&r| r <= INLIER_PX).collect();
        let rms = (kept.iter().map(|r| r * r).sum::<f64>() / kept.len() as f64).sqrt();
        fit = Some((affine, rms, kept.len()));
        if next == keep {
            break;
        }
        keep = next;
    }
    fit.ok_or_else(|| Error::data(DataCause::TooFew, "no tiles matched"))
}

/// Least squares `q = A p + b` over point pairs.
fn fit_affine(pairs: &[&Match]) -> Result<Affine> {
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
pub fn warp(reference: &Image, affine: &Affine, rows: usize, cols: usize) -> Result<(Image, Array2<bool>)> {
    let reference = &reference.values;
    let inv =
        affine.inverse().ok_or_else(|| Error::data(DataCause::Singular, "the affine map is singular"))?;
    let nc = reference.dim().2;
    let mut out = Array3::<f64>::zeros((rows, cols, nc));
    let mut inside = Array2::from_elem((rows, cols), false);
    for i in 0..rows {
        for j in 0..cols {
            let [x, y] = inv.apply([j as f64, i as f64]);
            if let Some(v) = bilinear(reference, y, x) {
                for (c, v) in v.into_iter().enumerate() {
                    out[[i, j, c]] = v;
                }
                inside[[i, j]] = true;
            }
        }
    }
    Ok((Image::new(out), inside))
}

/// Bilinear sample of every channel at `(y, x)`, `None` outside the image.
fn bilinear(img: &Array3<f64>, y: f64, x: f64) -> Option<Vec<f64>> {
    let (h, w, nc) = img.dim();
    if !(x >= 0.0 && y >= 0.0 && x <= (w - 1) as f64 && y <= (h - 1) as f64) {
        return None;
    }
    let (i0, j0) =
        ((y.floor() as usize).min(h.saturating_sub(2)), (x.floor() as usize).min(w.saturating_sub(2)));
    let (ty, tx) = (y - i0 as f64, x - j0 as f64);
    Some(
        (0..nc)
            .map(|c| {
                (1.0 - ty) * ((1.0 - tx) * img[[i0, j0, c]] + tx * img[[i0, j0 + 1, c]])
                    + ty * ((1.0 - tx) * img[[i0 + 1, j0, c]] + tx * img[[i0 + 1, j0 + 1, c]])
            })
            .collect(),
    )
}

/// A displacement field from local tile matching: where a target pixel's scene point lies in
/// the reference, for motion that no single affine map follows (parallax between objects at
/// different depths when the camera's centre of projection moves).
///
/// Method: the tiles of the *target* on the regular grid of [`register_affine`]'s step 2
/// (nodes `T/2` apart) are matched into the reference, each giving a displacement `u = p - q`,
/// and the dominant affine map over them is found as in [`register_affine`]. A match is kept
/// when at least 3 other matches lie within 2 nodes and its departure from that map is within
/// 3 px of theirs (component-wise median; repeated until nothing changes). The field at each node is the
/// affine map plus the Gaussian-weighted mean departure of the kept matches (sigma 1 node,
/// truncated at 2 nodes): nodes whose
/// weight is below `exp(-1/2)` (no kept match within about a node) are uncovered.
///
/// *Extension*: a tile without a kept match has too little texture to be matched, and there a
/// displacement error changes the image little. An uncovered node with kept matches within
/// 3 nodes takes their Gaussian-weighted mean departure (sigma 1.5 nodes, weight at least
/// `exp(-2)`), and is covered when the reference moved by it agrees with the target over the
/// node's tile — RMS of `target - a reference` (`a` the least-squares scale over the matched
/// nodes' tiles) — at least as well as at 90 % of the nodes with kept matches. The test is
/// relative to the scene's own matched tiles, so it holds whatever the scene's noise and
/// texture. Pixels between uncovered nodes are left out; pixels interpolate the field
/// bilinearly between nodes.
/// The residual is the leave-one-out error: each kept match against the field made without it.
/// Depth edges are smoothed over about a tile; the residual says how far that matters.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct LocalRegistration {
    /// Distance between neighbouring nodes of the field, pixels (half the tile side).
    pub node_spacing_px: usize,
    /// Nodes covered by the extension (no kept match within a node) rather than by matches.
    pub extended_nodes: usize,
    /// Of those, the nodes placed by guided matching: the tile matched again near the
    /// displacement its neighbours interpolate (a tile the measurement model fits poorly).
    pub guided_nodes: usize,
    /// Nodes of the field, rows times columns.
    pub nodes: usize,
    /// Tiles matched in the second pass (enough texture, a clear NCC peak).
    pub tiles_matched: usize,
    /// Of those, the matches kept by the neighbours' consensus.
    pub tiles_used: usize,
    /// Leave-one-out RMS error of the field at the kept matches, pixels.
    pub residual_rms_px: f64,
    /// Fraction of the image's pixels the field covers.
    pub covered_fraction: f64,
    /// Range of the field's displacements over covered nodes, pixels: `[[min x, min y], [max x, max y]]`.
    pub displacement_range_px: [[f64; 2]; 2],
    /// The dominant affine map, target to reference, that the departures are measured from.
    pub affine: Affine,
    #[serde(skip)]
    field: Array3<f64>,
    #[serde(skip)]
    covered: Array2<bool>,
    #[serde(skip)]
    origin: f64,
    /// The first pass's dominant map `A0` (see [`register_local`]).
    pub prewarp: Affine,
}

/// Fits a [`LocalRegistration`] of `reference` onto `target` (same size, single-channel).
///
/// Two passes: the first matches the target's tiles into the reference and fits their dominant
/// affine map `A0` (target to reference); the reference resampled through `A0` then differs from
/// the target by the parallax alone, and the second pass builds the field on it, so that a few
/// per cent of scale or degrees of rotation, which deform a tile by pixels across its width, do
/// not cost matches (tile matching assumes each tile moves by a shift). A target pixel `q` lies
/// in the reference at `A0 (q + d(q))`, `d` the second pass's field.
pub fn register_local(
    reference: &Array2<f64>,
    target: &Array2<f64>,
    opts: &RegisterOptions,
) -> Result<LocalRegistration> {
    if reference.dim() != target.dim() {
        return Err(Error::data(
            DataCause::Shape,
            format!(
                "the reference is {:?} and the target {:?}: local registration needs one size",
                reference.dim(),
                target.dim()
            ),
        ));
    }
    let (prewarp, _, _) = robust_affine(&match_tiles(target, reference, opts)?, opts.max_shift)?;
    let to_target = prewarp
        .inverse()
        .ok_or_else(|| Error::data(DataCause::Singular, "the dominant affine map is singular"))?;
    let (h, w) = target.dim();
    let (moved, _) = warp(&Image::new(reference.clone().insert_axis(ndarray::Axis(2))), &to_target, h, w)?;
    let mut reg = field_pass(&moved.values.index_axis_move(ndarray::Axis(2), 0), target, opts)?;
    reg.prewarp = prewarp;
    let [p, a] = [prewarp, reg.affine];
    // The dominant map of the whole registration: q -> A0 (A1 q + b1) + b0.
    reg.affine = Affine {
        a: [
            [p.a[0][0] * a.a[0][0] + p.a[0][1] * a.a[1][0], p.a[0][0] * a.a[0][1] + p.a[0][1] * a.a[1][1]],
            [p.a[1][0] * a.a[0][0] + p.a[1][1] * a.a[1][0], p.a[1][0] * a.a[0][1] + p.a[1][1] * a.a[1][1]],
        ],
        b: {
            let q = p.apply(a.b);
            [q[0], q[1]]
        },
    };
    let (mut lo, mut hi) = ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]);
    for i in 0..h {
        for j in 0..w {
            if let Some(d) = reg.at(i, j) {
                for k in 0..2 {
                    lo[k] = lo[k].min(d[k]);
                    hi[k] = hi[k].max(d[k]);
                }
            }
        }
    }
    reg.displacement_range_px = [lo, hi];
    Ok(reg)
}

/// One pass of [`register_local`]: the field of `reference` onto `target` (the struct docs).
fn field_pass(
    reference: &Array2<f64>,
    target: &Array2<f64>,
    opts: &RegisterOptions,
) -> Result<LocalRegistration> {
    let matches = match_tiles(target, reference, opts)?;
    let (h, w) = target.dim();
    let nodes = Nodes::new(opts.tile, h, w);
    // The consensus test runs on the departures from the dominant affine map, so that a few
    // per cent of scale (pixels per node) does not read as disagreement between neighbours.
    let (affine, _, _) = robust_affine(&matches, opts.max_shift)?;
    let mut u: Array2<Option<[f64; 2]>> = Array2::from_elem((nodes.ny, nodes.nx), None);
    for (q, p) in &matches {
        let b = affine_shift(&affine, *q);
        u[nodes.node(*q)] = Some([p[0] - q[0] - b[0], p[1] - q[1] - b[1]]);
    }
    let u = consensus(u);
    let used = u.iter().filter(|v| v.is_some()).count();
    if used < 6 {
        return Err(Error::data(
            DataCause::TooFew,
            format!(
                "only {used} of {} matched tiles agree with their neighbours (6 needed): the images do not \
             show the same scene, or move by more than {} px",
                matches.len(),
                opts.max_shift
            ),
        ));
    }
    let mut nf = bilateral_field(&u, &nodes, &affine);
    let (extended, guided_nodes) = extend_field(&mut nf, &u, &nodes, &affine, (reference, target));
    let NodeField { field, covered, lo, hi, loo } = nf;
    let mut reg = LocalRegistration {
        node_spacing_px: nodes.step,
        extended_nodes: extended,
        guided_nodes,
        nodes: nodes.ny * nodes.nx,
        tiles_matched: matches.len(),
        tiles_used: used,
        residual_rms_px: (loo / used as f64).sqrt(),
        covered_fraction: 0.0,
        displacement_range_px: [lo, hi],
        affine,
        prewarp: Affine { a: [[1.0, 0.0], [0.0, 1.0]], b: [0.0, 0.0] },
        field,
        covered,
        origin: nodes.origin,
    };
    let inside =
        (0..h).flat_map(|i| (0..w).map(move |j| (i, j))).filter(|&(i, j)| reg.at(i, j).is_some()).count();
    reg.covered_fraction = inside as f64 / (h * w) as f64;
    if reg.covered_fraction < opts.min_coverage {
        return Err(Error::validity(Condition::Coverage, format!(
            "the field covers only {:.1} % of the image ({:.0} % needed): too little texture to follow the motion",
            100.0 * reg.covered_fraction,
            100.0 * opts.min_coverage
        )));
    }
    Ok(reg)
}

/// The nodes of a field pass: tiles of `t` px every `step = t / 2` px (as [`match_tiles`] lays
/// them), node `(i, j)` at the centre of tile `(i, j)`, pixel `origin + (j, i) step`.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Nodes {
    t: usize,
    step: usize,
    origin: f64,
    ny: usize,
    nx: usize,
}

impl Nodes {
    /// The nodes of tiles of about `tile` px (at least 16, a multiple of 4) in an `h x w` image.
    fn new(tile: usize, h: usize, w: usize) -> Nodes {
        let t = tile.max(16) / 4 * 4;
        let step = t / 2;
        let origin = (t / 2) as f64 + (t as f64 - 1.0) * 0.5;
        let (ny, nx) = ((h - 2 * (t / 2) - t) / step + 1, (w - 2 * (t / 2) - t) / step + 1);
        Nodes { t, step, origin, ny, nx }
    }

    /// The node `(i, j)` nearest to pixel position `p = (x, y)`.
    fn node(&self, p: [f64; 2]) -> (usize, usize) {
        let step = self.step as f64;
        (((p[1] - self.origin) / step).round() as usize, ((p[0] - self.origin) / step).round() as usize)
    }

    /// The pixel position `(x, y)` of node `(i, j)`.
    fn position(&self, i: usize, j: usize) -> [f64; 2] {
        [self.origin + (j * self.step) as f64, self.origin + (i * self.step) as f64]
    }
}

/// The displacement `A q + b - q` of `affine` at pixel position `q`.
fn affine_shift(affine: &Affine, q: [f64; 2]) -> [f64; 2] {
    let p = affine.apply(q);
    [p[0] - q[0], p[1] - q[1]]
}

/// The consensus of the matches' departures `u` (per node, from the dominant map): a match
/// is kept when the median of its neighbours (within 2 nodes, at least 3 of them) agrees with
/// it within 3 px, or when at least [`SURFACE_SUPPORT`] of them do; repeated until nothing
/// changes (at most 10 times).
fn consensus(mut u: Array2<Option<[f64; 2]>>) -> Array2<Option<[f64; 2]>> {
    let (ny, nx) = u.dim();
    let neighbours = |u: &Array2<Option<[f64; 2]>>, i: usize, j: usize| -> Vec<[f64; 2]> {
        let mut v = Vec::new();
        for a in i.saturating_sub(2)..(i + 3).min(ny) {
            for b in j.saturating_sub(2)..(j + 3).min(nx) {
                if (a, b) != (i, j) {
                    v.extend(u[[a, b]]);
                }
            }
        }
        v
    };
    // A match is kept when its neighbours' median agrees with it, or when at least
    // `SURFACE_SUPPORT` of them do: an object nearer or farther than its surroundings (a lamp
    // before a wall) moves by its own parallax and forms such a cluster of mutual agreement,
    // while a lone match locked onto a wrong feature has none.
    for _ in 0..10 {
        let next = Array2::from_shape_fn((ny, nx), |(i, j)| {
            let d = u[[i, j]]?;
            let n = neighbours(&u, i, j);
            if n.len() < 3 {
                return None;
            }
            let med = |k: usize| {
                let mut c: Vec<f64> = n.iter().map(|v| v[k]).collect();
                c.sort_by(f64::total_cmp);
                c[c.len() / 2]
            };
            let agree = n.iter().filter(|v| (d[0] - v[0]).hypot(d[1] - v[1]) <= 3.0).count();
            ((d[0] - med(0)).hypot(d[1] - med(1)) <= 3.0 || agree >= SURFACE_SUPPORT).then_some(d)
        });
        if next == u {
            break;
        }
        u = next;
    }
    u
}

/// The displacement field on the nodes while it is built.
struct NodeField {
    /// Displacement `(x, y)` per node, pixels, and whether the node is covered.
    field: Array3<f64>,
    covered: Array2<bool>,
    /// Range of the covered nodes' displacements.
    lo: [f64; 2],
    hi: [f64; 2],
    /// Sum of the squared leave-one-out errors at the kept matches.
    loo: f64,
}

/// The field from the kept departures `u`: at each node the Gaussian-weighted mean (sigma 1
/// node, within 2 nodes) of the kept departures that agree with the node's own (within 3 px;
/// all where it has none: a bilateral weight, Tomasi and Manduchi 1998) plus the dominant
/// map's displacement; a node is covered when the weight reaches `exp(-1/2)`. Each kept match
/// adds its squared error against the mean made without it.
fn bilateral_field(u: &Array2<Option<[f64; 2]>>, nodes: &Nodes, affine: &Affine) -> NodeField {
    let (ny, nx) = (nodes.ny, nodes.nx);
    // Gaussian-weighted sums over kept matches within 2 nodes: (weight, sum x, sum y). At a
    // node with a kept match of its own, only the matches that agree with it (within 3 px)
    // count, so that the field does not average across a depth edge (an edge-preserving,
    // bilateral weight; Tomasi and Manduchi 1998).
    let sums = |i: usize, j: usize| {
        let mut s = [0.0; 3];
        let own = u[[i, j]];
        for a in i.saturating_sub(2)..(i + 3).min(ny) {
            for b in j.saturating_sub(2)..(j + 3).min(nx) {
                if let Some(d) =
                    u[[a, b]].filter(|d| own.is_none_or(|o| (o[0] - d[0]).hypot(o[1] - d[1]) <= 3.0))
                {
                    let r2 = (a as f64 - i as f64).powi(2) + (b as f64 - j as f64).powi(2);
                    let g = (-0.5 * r2).exp();
                    s[0] += g;
                    s[1] += g * d[0];
                    s[2] += g * d[1];
                }
            }
        }
        s
    };
    let min_weight = (-0.5f64).exp();
    let mut field = Array3::<f64>::zeros((ny, nx, 2));
    let mut covered = Array2::from_elem((ny, nx), false);
    let (mut loo, mut lo, mut hi) = (0.0, [f64::INFINITY; 2], [f64::NEG_INFINITY; 2]);
    for i in 0..ny {
        for j in 0..nx {
            let s = sums(i, j);
            if s[0] >= min_weight {
                covered[[i, j]] = true;
                let b = affine_shift(affine, nodes.position(i, j));
                for k in 0..2 {
                    field[[i, j, k]] = s[k + 1] / s[0] + b[k];
                    lo[k] = lo[k].min(field[[i, j, k]]);
                    hi[k] = hi[k].max(field[[i, j, k]]);
                }
            }
            if let Some(d) = u[[i, j]] {
                // Without this match (its own weight is 1); an isolated match counts its
                // distance to the field's zero, which the 3-neighbour rule rules out anyway.
                let rest = s[0] - 1.0;
                let f = if rest > 0.0 { [(s[1] - d[0]) / rest, (s[2] - d[1]) / rest] } else { [0.0; 2] };
                loo += (f[0] - d[0]).powi(2) + (f[1] - d[1]).powi(2);
            }
        }
    }
    NodeField { field, covered, lo, hi, loo }
}

/// The extension (see the struct docs): uncovered nodes with kept matches within 3 nodes take
/// their Gaussian-weighted mean departure (sigma 1.5 nodes) when the reference, moved by it,
/// agrees with the target over the node's tile as well as at 90 % of the matched nodes, else
/// the displacement [`guided`] matching finds near it. Returns the nodes extended and, of
/// those, the guided ones.
fn extend_field(
    nf: &mut NodeField,
    u: &Array2<Option<[f64; 2]>>,
    nodes: &Nodes,
    affine: &Affine,
    (reference, target): (&Array2<f64>, &Array2<f64>),
) -> (usize, usize) {
    let Nodes { t, step, ny, nx, .. } = *nodes;
    let ref3 = reference.clone().insert_axis(ndarray::Axis(2));
    let tile_pairs = |i: usize, j: usize, d: [f64; 2]| -> Vec<(f64, f64)> {
        let (r0, c0) = (t / 2 + i * step, t / 2 + j * step);
        let mut v = Vec::with_capacity(t * t);
        for a in r0..r0 + t {
            for b in c0..c0 + t {
                if let Some(x) = bilinear(&ref3, a as f64 + d[1], b as f64 + d[0]) {
                    v.push((target[[a, b]], x[0]));
                }
            }
        }
        v
    };
    let node_d = |f: &Array3<f64>, i: usize, j: usize| [f[[i, j, 0]], f[[i, j, 1]]];
    let kept: Vec<(usize, usize)> =
        (0..ny).flat_map(|i| (0..nx).map(move |j| (i, j))).filter(|&(i, j)| u[[i, j]].is_some()).collect();
    let (mut stt, mut srr) = (0.0, 0.0);
    for &(i, j) in &kept {
        for (tv, rv) in tile_pairs(i, j, node_d(&nf.field, i, j)) {
            stt += tv * rv;
            srr += rv * rv;
        }
    }
    let scale = if srr > 0.0 { stt / srr } else { 1.0 };
    let disagreement = |i: usize, j: usize, d: [f64; 2]| -> Option<f64> {
        let v = tile_pairs(i, j, d);
        (v.len() * 2 >= t * t).then(|| {
            (v.iter().map(|(tv, rv)| (tv - scale * rv).powi(2)).sum::<f64>() / v.len() as f64).sqrt()
        })
    };
    let mut matched_disagreement: Vec<f64> =
        kept.iter().filter_map(|&(i, j)| disagreement(i, j, node_d(&nf.field, i, j))).collect();
    matched_disagreement.sort_by(f64::total_cmp);
    let (mut extended, mut guided_nodes) = (0, 0);
    let Some(&limit) = matched_disagreement.get(matched_disagreement.len() * 9 / 10) else {
        return (extended, guided_nodes);
    };
    let wide = |i: usize, j: usize| {
        let mut s = [0.0; 3];
        for a in i.saturating_sub(3)..(i + 4).min(ny) {
            for b in j.saturating_sub(3)..(j + 4).min(nx) {
                if let Some(d) = u[[a, b]] {
                    let r2 = (a as f64 - i as f64).powi(2) + (b as f64 - j as f64).powi(2);
                    let g = (-r2 / (2.0 * 1.5 * 1.5)).exp();
                    s[0] += g;
                    s[1] += g * d[0];
                    s[2] += g * d[1];
                }
            }
        }
        s
    };
    // Each node's decision reads only the kept matches and the images: decided in parallel,
    // applied in node order.
    let candidates: Vec<(usize, usize)> = (0..ny)
        .flat_map(|i| (0..nx).map(move |j| (i, j)))
        .filter(|&(i, j)| !nf.covered[[i, j]] && wide(i, j)[0] >= (-2.0f64).exp())
        .collect();
    let placed: Vec<Option<([f64; 2], bool)>> = candidates
        .par_iter()
        .map(|&(i, j)| {
            let s = wide(i, j);
            let b = affine_shift(affine, nodes.position(i, j));
            let d = [s[1] / s[0] + b[0], s[2] / s[0] + b[1]];
            if disagreement(i, j, d)? <= limit {
                return Some((d, false));
            }
            let e = guided(&|e: [f64; 2]| disagreement(i, j, [d[0] + e[0], d[1] + e[1]]))?;
            Some(([d[0] + e[0], d[1] + e[1]], true))
        })
        .collect();
    for (&(i, j), placed) in candidates.iter().zip(placed) {
        let Some((d, by_guide)) = placed else { continue };
        nf.covered[[i, j]] = true;
        extended += 1;
        guided_nodes += usize::from(by_guide);
        for (k, &dk) in d.iter().enumerate() {
            nf.field[[i, j, k]] = dk;
            nf.lo[k] = nf.lo[k].min(dk);
            nf.hi[k] = nf.hi[k].max(dk);
        }
    }
    (extended, guided_nodes)
}

/// Guided matching of a tile the measurement model fits poorly (a saturated lamp whose flare
/// the measured PSF does not hold; the tile failed the NCC floor or its neighbours' consensus)
/// around the displacement its neighbours interpolate: the whole-pixel offset within
/// [`GUIDED_RADIUS`] px that minimises the tile's disagreement `at(offset)`, refined by a
/// parabola along each axis. `None` when the minimum lies on the window's edge (the tile's
/// motion is not near its neighbours') or is flat along an axis (nothing pins it there).
fn guided(at: &dyn Fn([f64; 2]) -> Option<f64>) -> Option<[f64; 2]> {
    let r = GUIDED_RADIUS;
    let mut best: Option<(i32, i32, f64)> = None;
    for dy in -r..=r {
        for dx in -r..=r {
            let v = at([dx as f64, dy as f64])?;
            if best.is_none_or(|b| v < b.2) {
                best = Some((dy, dx, v));
            }
        }
    }
    let (dy, dx, v) = best?;
    if dy.abs() == r || dx.abs() == r {
        return None;
    }
    let value = |y: i32, x: i32| at([x as f64, y as f64]);
    // A minimum: the second difference is positive, and at least 1 % of the value per px^2.
    let sub = |m: f64, p: f64| {
        let c = m + p - 2.0 * v;
        (c > 0.01 * v).then(|| 0.5 * (m - p) / c)
    };
    let fy = sub(value(dy - 1, dx)?, value(dy + 1, dx)?)?;
    let fx = sub(value(dy, dx - 1)?, value(dy, dx + 1)?)?;
    Some([dx as f64 + fx, dy as f64 + fy])
}

/// Agreeing neighbours (within 3 px, within 2 nodes) that keep a match its neighbours' median
/// does not: an object at its own depth (see [`register_local`]'s consensus).
const SURFACE_SUPPORT: usize = 3;

/// How far (whole pixels, each axis) [`guided`] matching searches around the interpolated
/// displacement.
const GUIDED_RADIUS: i32 = 8;

impl LocalRegistration {
    /// The field's displacement at target pixel `(row, col)`, `None` where it is not covered.
    pub fn at(&self, row: usize, col: usize) -> Option<[f64; 2]> {
        let (ny, nx) = self.covered.dim();
        let s = self.node_spacing_px as f64;
        let f = |x: f64, n: usize| ((x - self.origin) / s).clamp(0.0, (n - 1) as f64);
        let (fy, fx) = (f(row as f64, ny), f(col as f64, nx));
        let (i0, j0) = ((fy as usize).min(ny.saturating_sub(2)), (fx as usize).min(nx.saturating_sub(2)));
        let (i1, j1) = ((i0 + 1).min(ny - 1), (j0 + 1).min(nx - 1));
        if !(self.covered[[i0, j0]]
            && self.covered[[i0, j1]]
            && self.covered[[i1, j0]]
            && self.covered[[i1, j1]])
        {
            return None;
        }
        let (ty, tx) = (fy - i0 as f64, fx - j0 as f64);
        let v = |k: usize| {
            (1.0 - ty) * ((1.0 - tx) * self.field[[i0, j0, k]] + tx * self.field[[i0, j1, k]])
                + ty * ((1.0 - tx) * self.field[[i1, j0, k]] + tx * self.field[[i1, j1, k]])
        };
        let (x, y) = (col as f64, row as f64);
        let p = self.prewarp.apply([x + v(0), y + v(1)]);
        Some([p[0] - x, p[1] - y])
    }

    /// The reference resampled onto the target's pixels through the field (bilinear), with the
    /// mask of pixels the field covers and whose source lies inside the reference.
    pub fn warp(&self, reference: &Image) -> (Image, Array2<bool>) {
        let reference = &reference.values;
        let (h, w, nc) = reference.dim();
        let mut out = Array3::<f64>::zeros((h, w, nc));
        let mut inside = Array2::from_elem((h, w), false);
        for i in 0..h {
            for j in 0..w {
                let Some(d) = self.at(i, j) else { continue };
                let (x, y) = (j as f64 + d[0], i as f64 + d[1]);
                if let Some(v) = bilinear(reference, y, x) {
                    for (c, v) in v.into_iter().enumerate().take(nc) {
                        out[[i, j, c]] = v;
                    }
                    inside[[i, j]] = true;
                }
            }
        }
        (Image::new(out), inside)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A lone departure among agreeing neighbours is dropped; a 3 x 3 cluster moving by its
    /// own parallax (each of its nodes has at least 3 agreeing neighbours) is kept.
    #[test]
    fn the_consensus_drops_a_lone_match_and_keeps_a_cluster() {
        let mut u = Array2::from_elem((9, 9), Some([0.5, -0.2]));
        u[[6, 2]] = Some([10.0, 0.0]);
        for i in 1..4 {
            for j in 4..7 {
                u[[i, j]] = Some([8.0, 3.0]);
            }
        }
        let kept = consensus(u.clone());
        let mut want = u;
        want[[6, 2]] = None;
        assert_eq!(kept, want);
    }

    /// Equal departures give a field of those departures plus the dominant map's shift at each
    /// node, covering every node, with no leave-one-out error.
    #[test]
    fn equal_departures_make_a_flat_field() {
        let nodes = Nodes::new(48, 240, 288);
        assert_eq!((nodes.ny, nodes.nx, nodes.step, nodes.position(1, 2)), (7, 9, 24, [95.5, 71.5]));
        assert_eq!(nodes.node([95.5 + 11.0, 71.5 - 11.0]), (1, 2));
        let affine = Affine { a: [[1.01, 0.0], [0.0, 1.0]], b: [2.0, -3.0] };
        let u = Array2::from_elem((nodes.ny, nodes.nx), Some([1.5, -0.5]));
        let nf = bilateral_field(&u, &nodes, &affine);
        assert!(nf.covered.iter().all(|&c| c) && nf.loo < 1e-20, "{}", nf.loo);
        for i in 0..nodes.ny {
            for j in 0..nodes.nx {
                let x = nodes.position(i, j)[0];
                let want = [1.5 + 0.01 * x + 2.0, -0.5 - 3.0];
                for (k, w) in want.iter().enumerate() {
                    assert!((nf.field[[i, j, k]] - w).abs() < 1e-12, "({i}, {j}): {:?}", nf.field);
                }
            }
        }
    }
}
