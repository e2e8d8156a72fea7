//! PSNR of a reconstruction against a reference HDR image (`doefab evaluate`).
//!
//! The paper reports PSNR "computed in the linear domain (L) and in the gamma-corrected
//! domain" (Table 1) without printing the formula; its loss uses `gamma = 1/2`. Here, over a
//! set `S` of samples (pixel and channel):
//!
//! * linear: `PSNR_L = 10 log10(P^2 / mean_S (y - x)^2)`, with `P` the reference's maximum
//!   over `S`;
//! * gamma: `PSNR_gamma = 10 log10(P / mean_S (sqrt(y+) - sqrt(x+))^2)`, the same on square
//!   roots (peak `sqrt(P)`, negative values as 0, as the loss's `max(y_hat, 0)`).
//!
//! Both are reported over all pixels and over the pixels saturated in the LDR capture (any
//! channel at or above the saturation level). With `register`, the reference is first mapped
//! onto the reconstruction by an affine fit or, where objects at different depths move
//! differently (parallax), a local displacement field ([`super::register`]); pixels the map
//! does not cover are left out. Both images must be in the same units (the merge's radiance at the capture's
//! exposure: value 1 = full scale).

use std::path::Path;

use ndarray::{Array2, Array3};
use serde::Serialize;

use super::register::{
    luminance, register_affine, register_local, warp, LocalRegistration, Model, RegisterOptions, Registration,
};
use crate::error::{Error, Result};
use crate::io::exr::read_exr;

/// PSNR figures over one set of samples.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Psnr {
    pub linear_db: f64,
    pub gamma_db: f64,
    /// The peak `P` used and the pixels evaluated.
    pub peak: f64,
    pub pixels: usize,
}

/// What `doefab evaluate` reports.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Evaluation {
    pub all: Psnr,
    /// Over the pixels saturated in the capture (when one was given and any are).
    pub saturated: Option<Psnr>,
    pub saturated_pixels: Option<usize>,
    pub registration: Option<Registration>,
    pub local_registration: Option<LocalRegistration>,
    /// Pixels left out because the registered reference does not cover them.
    pub excluded_pixels: usize,
}

/// PSNR of `recon` against `reference` over the pixels where `mask` is true (all when `None`).
pub fn psnr(reference: &Array3<f64>, recon: &Array3<f64>, mask: Option<&Array2<bool>>) -> Result<Psnr> {
    if reference.dim() != recon.dim() {
        return Err(Error::Data(format!(
            "the reference is {:?} and the reconstruction {:?} (rows, cols, channels)",
            reference.dim(),
            recon.dim()
        )));
    }
    let (h, w, nc) = reference.dim();
    let (mut peak, mut sl, mut sg, mut n, mut pixels) = (0.0f64, 0.0, 0.0, 0usize, 0usize);
    for i in 0..h {
        for j in 0..w {
            if mask.is_some_and(|m| !m[[i, j]]) {
                continue;
            }
            pixels += 1;
            for c in 0..nc {
                let (x, y) = (reference[[i, j, c]], recon[[i, j, c]]);
                peak = peak.max(x);
                sl += (y - x).powi(2);
                sg += (y.max(0.0).sqrt() - x.max(0.0).sqrt()).powi(2);
                n += 1;
            }
        }
    }
    if n == 0 || peak <= 0.0 {
        return Err(Error::Data("no samples with a positive reference to evaluate".into()));
    }
    let (ml, mg) = (sl / n as f64, sg / n as f64);
    Ok(Psnr {
        linear_db: 10.0 * (peak * peak / ml).log10(),
        gamma_db: 10.0 * (peak / mg).log10(),
        peak,
        pixels,
    })
}

/// Reads an RGB (or single-channel) OpenEXR image as `(H, W, C)`.
pub fn read_rgb_exr(path: &Path) -> Result<Array3<f64>> {
    let planes = match read_exr(path, Some("R")) {
        Ok(r) => vec![r.values, read_exr(path, Some("G"))?.values, read_exr(path, Some("B"))?.values],
        Err(Error::Parameter { .. }) => vec![
            read_exr(path, None)
                .map_err(|e| {
                    Error::format(path, format!("expected channels R, G, B or a single channel: {e}"))
                })?
                .values,
        ],
        Err(e) => return Err(e),
    };
    let (h, w) = planes[0].dim();
    Ok(Array3::from_shape_fn((h, w, planes.len()), |(i, j, c)| planes[c][[i, j]]))
}

/// Evaluates `recon` against `reference`; `ldr` (values in [0, 1]) marks saturated pixels at
/// `saturation`; `register` maps the reference onto the reconstruction first.
pub fn evaluate(
    reference: &Array3<f64>,
    recon: &Array3<f64>,
    ldr: Option<&Array3<f64>>,
    saturation: f64,
    register: Option<&RegisterOptions>,
) -> Result<Evaluation> {
    let (h, w, _) = recon.dim();
    if let Some(l) = ldr {
        if (l.dim().0, l.dim().1) != (h, w) {
            return Err(Error::Data(format!(
                "the capture is {} x {} and the reconstruction {w} x {h}",
                l.dim().1,
                l.dim().0
            )));
        }
    }
    let (reference, cover, registration, local_registration) = match register {
        Some(opts) if opts.model == Model::Affine => {
            let reg = register_affine(&luminance(reference), &luminance(recon), opts)?;
            let (warped, inside) = warp(reference, &reg.affine, h, w)?;
            (warped, Some(inside), Some(reg), None)
        }
        Some(opts) => {
            let reg = register_local(&luminance(reference), &luminance(recon), opts)?;
            let (warped, inside) = reg.warp(reference);
            (warped, Some(inside), None, Some(reg))
        }
        None => (reference.clone(), None, None, None),
    };
    let excluded = cover.as_ref().map_or(0, |m| m.iter().filter(|v| !**v).count());
    let all = psnr(&reference, recon, cover.as_ref())?;
    let (saturated, saturated_pixels) = match ldr {
        Some(l) => {
            let mask = Array2::from_shape_fn((h, w), |(i, j)| {
                (0..l.dim().2).any(|c| l[[i, j, c]] >= saturation) && cover.as_ref().is_none_or(|m| m[[i, j]])
            });
            let count = mask.iter().filter(|v| **v).count();
            let p = if count > 0 { Some(psnr(&reference, recon, Some(&mask))?) } else { None };
            (p, Some(count))
        }
        None => (None, None),
    };
    Ok(Evaluation {
        all,
        saturated,
        saturated_pixels,
        registration,
        local_registration,
        excluded_pixels: excluded,
    })
}
