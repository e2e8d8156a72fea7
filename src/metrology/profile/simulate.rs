//! A stylus profile simulated along a line across a design ([`simulate_profile`]): the model of
//! the [module docs](super) with known parameters and noise, for tests and demonstrations.

use serde::Serialize;

use crate::error::{Error, Result};
use crate::grid::blur::gaussian_blur;
use crate::grid::profile::Profile;
use crate::grid::Grid;
use crate::metrology::scan_registration::Sampler;

use super::line::LineSpec;

/// What [`simulate_profile`] makes: a profile of the design along a line with a known model.
#[derive(Debug, Clone, Serialize)]
pub struct SimulateProfile {
    /// The line on the design the profile follows.
    pub line: LineSpec,
    /// Profile length, metres (`round(length / step) + 1` points).
    pub length: f64,
    /// Sampling step along the line, metres.
    pub step: f64,
    /// First position written (the instrument's own origin), metres.
    pub x_origin: f64,
    /// Shift along the line `s`, metres: point `u` sees the design at `u + s` along the line.
    pub along_shift: f64,
    /// Offset across the line `v`, metres (towards `n = (-d_y, d_x)`).
    pub across_offset: f64,
    /// Signed depth scale `a` (negative: complement).
    pub depth_scale: f64,
    /// Height offset `b` at the profile's middle, metres.
    pub offset: f64,
    /// Tilt `c` along the line, height per length (dimensionless).
    pub tilt: f64,
    /// Gaussian lateral blur (standard deviation), metres.
    pub blur: f64,
    /// Standard deviation of the white Gaussian noise added to each height, metres.
    pub noise: f64,
    /// Seed of the noise's random number generator (one seed, one profile).
    pub seed: u64,
}

/// A stylus profile of `design` simulated with the model of the module docs:
/// `z_k = a (G_blur * h)(P_k) + b + c (u_k - length / 2) + noise`, `P_k` the line's point at
/// `u_k + s` along and `v` across. Points off the design are not measured.
pub fn simulate_profile(design: &Grid, sp: &SimulateProfile) -> Result<Profile> {
    sp.line.check()?;
    if !(sp.length > 0.0 && sp.step > 0.0 && sp.length / sp.step < 1e7) {
        return Err(Error::param("length/step", "must be positive, with fewer than 1e7 points"));
    }
    let blurred = gaussian_blur(design, sp.blur)?;
    let sampler = Sampler::new(&blurred);
    let (start, dir) = sp.line.frame(sp.length);
    let nrm = [-dir[1], dir[0]];
    let n = (sp.length / sp.step).round() as usize + 1;
    let mut rng = crate::rng::Lcg(sp.seed);
    let mut x = Vec::with_capacity(n);
    let mut z = Vec::with_capacity(n);
    let mut valid = Vec::with_capacity(n);
    for k in 0..n {
        let u = k as f64 * sp.step;
        let q = [
            start[0] + (u + sp.along_shift) * dir[0] + sp.across_offset * nrm[0],
            start[1] + (u + sp.along_shift) * dir[1] + sp.across_offset * nrm[1],
        ];
        let e = rng.normal();
        x.push(sp.x_origin + u);
        match sampler.at_position(q) {
            Some(h) => {
                z.push(sp.depth_scale * h + sp.offset + sp.tilt * (u - 0.5 * sp.length) + sp.noise * e);
                valid.push(true);
            }
            None => {
                z.push(0.0);
                valid.push(false);
            }
        }
    }
    Profile::new(x, z, Some(valid))
}

#[cfg(test)]
pub(super) mod tests {
    use ndarray::Array2;

    use super::*;
    use crate::grid::Unit;

    /// A staircase design: 4 levels of 100 nm in 40 um terraces along x, whose boundaries lean
    /// across (y) by an amount that changes along x, so that an offset across a line along x
    /// moves the edges unequally (observable, unlike a uniform lean that mimics a shift).
    pub(crate) fn staircase() -> Grid {
        let (n, p) = (300usize, 2e-6);
        let c = (n as f64 - 1.0) * 0.5;
        let v = Array2::from_shape_fn((n, n), |(i, j)| {
            let (x, y) = ((j as f64 - c) * p, (i as f64 - c) * p);
            let tau = 2.0 * std::f64::consts::PI;
            let t = x + 15e-6 * (tau * y / 120e-6).sin() * (tau * x / 170e-6).cos();
            let k = (t / 40e-6).floor().rem_euclid(4.0);
            k * 100e-9
        });
        Grid::new(v, [p, p], Unit::Metre).unwrap()
    }

    pub(crate) fn sim(design: &Grid, a: f64, s: f64, v: f64, seed: u64) -> (SimulateProfile, Profile) {
        let sp = SimulateProfile {
            line: LineSpec::Angle { angle: 0.0 },
            length: 400e-6,
            step: 0.5e-6,
            x_origin: 12e-6,
            along_shift: s,
            across_offset: v,
            depth_scale: a,
            offset: 40e-9,
            tilt: 2e-4,
            blur: 2e-6,
            noise: 5e-9,
            seed,
        };
        let p = simulate_profile(design, &sp).unwrap();
        (sp, p)
    }
}
