//! Recovery of a camera's response curve from an 8-bit exposure bracket (Debevec & Malik,
//! "Recovering High Dynamic Range Radiance Maps from Photographs", SIGGRAPH 1997, Sec. 2.1).
//!
//! A pixel value is `Z = f(E t)`; with `g = ln f^-1`, every sample pixel `i` seen in frame `j`
//! gives `g(Z_ij) = ln E_i + ln t_j`. The 256 values of `g` (per channel) and the `N` unknown
//! `ln E_i` minimise (eq. 3)
//!
//! `sum_ij [w(Z_ij) (g(Z_ij) - ln E_i - ln t_j)]^2 + lambda sum_z [w(z) g''(z)]^2`
//!
//! with the hat weight `w(z) = min(z, 255 - z)` and `g''(z) = g(z-1) - 2 g(z) + g(z+1)`. The
//! curve is fixed by `g(128) = ln(128/255)`, so that a linear camera gives `exp(g(z)) = z/255`
//! (the scale of linear captures). The normal equations of this sparse least-squares problem
//! (`256 + N` unknowns) are solved by LU with partial pivoting (`crate::linalg`).
//!
//! Validity: the samples must span the curve. The sample pixels are picked from the middle
//! frame at evenly spaced values, `N >= 2 * 256 / (P - 1)` of them for `P` frames (the paper
//! asks `N (P - 1) > 255`); a bracket whose weighted observations cover less than half of the
//! value range leaves `g` unconstrained there and is refused, and a recovered curve that
//! decreases anywhere inside the observed range is reported.

use std::path::Path;

use ndarray::{Array2, Array3};
use serde::Serialize;

use super::capture::Capture;
use crate::error::{Allowed, Condition, Error, Result};
use crate::image::Image;
use crate::io::csv::write_csv;
use crate::io::raw_map::Metadata;
use crate::linalg::solve;

/// The recovered `g(z) = ln f^-1(z)` per channel, 256 values each.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Response {
    /// Per channel, `g(z)` for `z = 0..=255` counts: the natural log of the exposure `E t` that
    /// gives value `z`, fixed by `g(128) = ln(128/255)`.
    pub log_exposure: Vec<Vec<f64>>,
    /// Per channel, the lowest and highest value the samples observe with non-zero weight;
    /// outside this range `g` is an extrapolation by the smoothness term alone.
    pub observed: Vec<[usize; 2]>,
    /// Sample pixels per channel.
    pub samples: usize,
    /// The smoothness weight `lambda` of eq. 3.
    pub lambda: f64,
    /// Channels whose recovered curve decreases inside the observed range, one sentence each.
    pub warnings: Vec<String>,
}

/// Hat weight of an 8-bit value.
fn w(z: usize) -> f64 {
    z.min(255 - z) as f64
}

impl Response {
    /// `exp(g(z))` for every value (rounded to its 8-bit count).
    pub fn linearize(&self, image: &Image) -> Image {
        let values = &image.values;
        Image::new(Array3::from_shape_fn(values.dim(), |(i, j, c)| {
            let z = (values[[i, j, c]] * 255.0).round().clamp(0.0, 255.0) as usize;
            self.log_exposure[c][z].exp()
        }))
    }

    /// Writes the curve as CSV ([`crate::io::csv::write_csv`]): one row per value
    /// `z = 0..=255`, columns `z` and `g(z)` per channel (R, G, B, or Y for one channel), after
    /// `# key: value` lines naming the columns and units, the observed range per channel, the
    /// sample count and lambda. Atomic.
    pub fn write_csv(&self, path: &Path) -> Result<()> {
        let nc = self.log_exposure.len();
        let names: Vec<String> = match nc {
            3 => ["R", "G", "B"].map(String::from).to_vec(),
            1 => vec!["Y".into()],
            _ => (0..nc).map(|c| format!("C{c}")).collect(),
        };
        let columns: Vec<String> = names.iter().map(|n| format!("g_{n} (ln exposure)")).collect();
        let mut meta = Metadata::default()
            .with("quantity", "camera response g(z) = ln f^-1(z) (Debevec & Malik 1997)")
            .with("columns", format!("z (8-bit value, counts), {}", columns.join(", ")))
            .with(
                "g_unit",
                "ln of the exposure E t that gives value z; exp(g) in fractions of full scale, \
                 fixed by g(128) = ln(128/255)",
            );
        for (name, [lo, hi]) in names.iter().zip(&self.observed) {
            meta = meta.with(format!("observed_{name}"), format!("{lo}..{hi} (outside: smoothness only)"));
        }
        let meta =
            meta.with("samples", format!("{}", self.samples)).with("lambda", format!("{}", self.lambda));
        let table =
            Array2::from_shape_fn(
                (256, nc + 1),
                |(z, k)| {
                    if k == 0 {
                        z as f64
                    } else {
                        self.log_exposure[k - 1][z]
                    }
                },
            );
        write_csv(path, &table, &meta)
    }

    /// Refuses frames this curve cannot linearize (not 8-bit, other channel count).
    pub fn check(&self, frames: &[Capture]) -> Result<()> {
        for f in frames {
            if f.bits != 8 || f.image.values.dim().2 != self.log_exposure.len() {
                return Err(Error::unsupported(
                    &f.path,
                    format!(
                        "is {}-bit with {} channels; the response curve is for 8-bit captures with {} channels",
                        f.bits,
                        f.image.values.dim().2,
                        self.log_exposure.len()
                    ),
                ));
            }
        }
        Ok(())
    }
}

/// Recovers the response from a bracket of 8-bit `frames` with exposure `times` (seconds);
/// `samples` pixels per channel (0: the minimum above), smoothness `lambda`.
pub fn recover_response(frames: &[Capture], times: &[f64], samples: usize, lambda: f64) -> Result<Response> {
    let p = frames.len();
    if p < 2 || times.len() != p {
        return Err(Error::param(
            "bracket",
            format!("response recovery needs 2 or more frames with times, got {p}"),
        ));
    }
    let dim = frames[0].image.values.dim();
    for f in frames {
        if f.bits != 8 {
            return Err(Error::unsupported(
                &f.path,
                format!("is {}-bit; response recovery is for 8-bit captures", f.bits),
            ));
        }
        if f.image.values.dim() != dim {
            return Err(Error::malformed(
                &f.path,
                format!("is {:?}, the first frame {dim:?}", f.image.values.dim()),
            ));
        }
    }
    let (tmin, tmax) = times.iter().fold((f64::INFINITY, 0.0f64), |a, &t| (a.0.min(t), a.1.max(t)));
    if !(tmin > 0.0 && tmax > tmin * 1.01) {
        return Err(Error::param(
            "times",
            "response recovery needs frames of different positive exposure times",
        ));
    }
    if !(lambda.is_finite() && lambda > 0.0) {
        return Err(Error::param_in(
            "lambda",
            Allowed::positive(),
            format!("must be positive, got {lambda}"),
        ));
    }
    let n = if samples == 0 { (512 / (p - 1)).clamp(50, 300) } else { samples };
    let mut order: Vec<usize> = (0..p).collect();
    order.sort_by(|&a, &b| times[a].total_cmp(&times[b]));
    let middle = &frames[order[p / 2]].image.values;
    let count = |v: f64| (v * 255.0).round().clamp(0.0, 255.0) as usize;
    let mut curves = Vec::new();
    let mut observed = Vec::new();
    let mut warnings = Vec::new();
    for c in 0..dim.2 {
        // The first pixel of every value in the middle frame, then N of them evenly spaced.
        let mut first: Vec<Option<(usize, usize)>> = vec![None; 256];
        for ((i, j, cc), &v) in middle.indexed_iter() {
            if cc == c && first[count(v)].is_none() {
                first[count(v)] = Some((i, j));
            }
        }
        let distinct: Vec<(usize, usize)> = first.into_iter().flatten().collect();
        let picks: Vec<(usize, usize)> = if distinct.len() <= n {
            distinct
        } else {
            (0..n).map(|k| distinct[k * distinct.len() / n]).collect()
        };
        let m = 256 + picks.len();
        let mut ata = vec![0.0; m * m];
        let mut atb = vec![0.0; m];
        let mut add_row = |entries: &[(usize, f64)], rhs: f64| {
            for &(a, va) in entries {
                atb[a] += va * rhs;
                for &(b, vb) in entries {
                    ata[a * m + b] += va * vb;
                }
            }
        };
        let (mut zmin, mut zmax) = (255, 0);
        for (s, &(i, j)) in picks.iter().enumerate() {
            for k in 0..p {
                let z = count(frames[k].image.values[[i, j, c]]);
                let wz = w(z);
                if wz > 0.0 {
                    zmin = zmin.min(z);
                    zmax = zmax.max(z);
                }
                add_row(&[(z, wz), (256 + s, -wz)], wz * times[k].ln());
            }
        }
        add_row(&[(128, 1.0)], (128.0f64 / 255.0).ln());
        for z in 1..255 {
            let s = lambda * w(z);
            add_row(&[(z - 1, s), (z, -2.0 * s), (z + 1, s)], 0.0);
        }
        if zmax < zmin + 128 {
            return Err(Error::validity(
                Condition::Conditioning,
                format!(
                "channel {c}: the bracket's samples span only values {zmin}..{zmax} of 0..255; the response \
                 outside is unconstrained (add shorter and longer exposures)"
            ),
            ));
        }
        let x = solve(ata, atb, m).map_err(|_| {
            Error::validity(
                Condition::Conditioning,
                format!("channel {c}: the response equations are singular"),
            )
        })?;
        let g = x[..256].to_vec();
        if let Some(z) = (zmin..zmax).find(|&z| g[z + 1] < g[z]) {
            warnings.push(format!(
                "channel {c}: the recovered response decreases at value {z}; more samples or a larger \
                 lambda may help"
            ));
        }
        curves.push(g);
        observed.push([zmin, zmax]);
    }
    Ok(Response { log_exposure: curves, observed, samples: n, lambda, warnings })
}
