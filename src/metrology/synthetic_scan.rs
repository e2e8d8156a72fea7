//! Synthetic fabricated scans of a design, for tests, benchmarks and the demo.
//!
//! A scan sample at position `x_s` (metres from the scan's centre) sees the part at design
//! position `x_d = pose.scan_to_design(x_s)` (see [`Pose`]: the part is mirrored, scaled,
//! rotated counter-clockwise and shifted on the stage), and reads
//!
//! `z(x_s) = k * h'(x_d) + offset + tilt_x x_s + tilt_y y_s + n`,
//!
//! where `h' = G_sigma * R(h)` is the design through the process's height response `R` (a
//! per-level nonlinearity, [`crate::fabrication::precompensate::Response`]; none by default),
//! blurred by a Gaussian of standard deviation `blur` (the writer's and the replication's lateral resolution, normalised over valid samples),
//! `k` the depth scale, `h'` replaced by `max(h) - h'` for a complemented (cast) part, and `n`
//! white Gaussian noise of standard deviation `noise`. The blurred design is read at `x_d` by
//! Keys cubic convolution. Samples whose `x_d` falls outside the design's footprint, and a
//! random `missing` fraction of the others, are non-measured (invalid). Every random number
//! comes from [`crate::rng::Lcg`] seeded with `seed`: the same parameters give the same scan.

use std::ops::Bound;
use std::path::Path;

use ndarray::Array2;
use serde::Serialize;

use crate::error::{Allowed, Condition, DataCause, Error, Resource, Result};
use crate::fabrication::precompensate::Response;
use crate::grid::blur::gaussian_blur;
use crate::grid::{Grid, Unit};
use crate::metrology::scan_registration::{Pose, Sampler};
use crate::rng::Lcg;

/// What goes wrong between design and scan; see the module docs.
#[derive(Debug, Clone, Serialize)]
pub struct SimulateParams {
    /// The process's height response, applied to the design's heights before the blur (a
    /// per-level nonlinearity; `None`: heights made as commanded).
    pub response: Option<Response>,
    /// Gaussian lateral blur, standard deviation in metres (0 = none).
    pub blur: f64,
    /// Depth scale `k` (1 = the design's depth).
    pub depth_scale: f64,
    /// Height added to every sample, metres.
    pub offset: f64,
    /// Slopes `[dz/dx, dz/dy]` of a plane added to the scan (dimensionless).
    pub tilt: [f64; 2],
    /// Placement of the part on the stage.
    pub pose: Pose,
    /// Height sign inverted: the scan shows `max(h) - h` (a cast of the design).
    pub complement: bool,
    /// Standard deviation of additive white Gaussian noise, metres.
    pub noise: f64,
    /// Fraction (0..1) of the measured samples dropped at random.
    pub missing: f64,
    /// Seed of the generator behind the noise and the dropped samples.
    pub seed: u64,
    /// Scan pitch `[x, y]`, metres (default: the design's).
    pub pitch: Option<[f64; 2]>,
    /// Scan size `(rows, cols)` (default: the design's extent at the scan pitch).
    pub size: Option<(usize, usize)>,
}

impl Default for SimulateParams {
    fn default() -> Self {
        SimulateParams {
            response: None,
            blur: 0.0,
            depth_scale: 1.0,
            offset: 0.0,
            tilt: [0.0, 0.0],
            pose: Pose::default(),
            complement: false,
            noise: 0.0,
            missing: 0.0,
            seed: 1,
            pitch: None,
            size: None,
        }
    }
}

impl SimulateParams {
    /// A plausible cast of a replica-moulded part as the demo and the benchmarks scan it:
    /// mirrored and complemented (a replica of the master), 5 % too shallow, 0.1 um offset,
    /// blurred by a 2 um Gaussian, tilted (1e-4, -5e-5), rotated 0.3 deg and shifted by
    /// (3.2, -1.7) um, 20 nm of noise and 10 % of samples missing; at the design's pitch.
    pub fn typical_cast() -> SimulateParams {
        SimulateParams {
            blur: 2e-6,
            depth_scale: 0.95,
            offset: 0.1e-6,
            tilt: [1e-4, -5e-5],
            pose: Pose { mirror: true, rotation: 0.3f64.to_radians(), scale: 1.0, shift: [3.2e-6, -1.7e-6] },
            complement: true,
            noise: 20e-9,
            missing: 0.1,
            ..SimulateParams::default()
        }
    }
}

/// A synthetic scan of `design` (heights in metres); see the module docs.
pub fn simulate_scan(design: &Grid, p: &SimulateParams) -> Result<Grid> {
    if design.unit() != Unit::Metre {
        return Err(Error::param("design", "a simulated scan needs a height map in metres"));
    }
    if !(p.depth_scale.is_finite() && p.offset.is_finite() && p.tilt.iter().all(|t| t.is_finite())) {
        return Err(Error::param("depth scale/offset/tilt", "must be finite"));
    }
    if !(p.noise.is_finite() && p.noise >= 0.0) {
        return Err(Error::param_in(
            "noise",
            Allowed::at_least(0.0),
            format!("must be finite and >= 0, got {} m", p.noise),
        ));
    }
    if !(0.0..1.0).contains(&p.missing) {
        return Err(Error::param_in(
            "missing",
            Allowed::within(Bound::Included(0.0), Bound::Excluded(1.0)),
            format!("must be in [0, 1), got {}", p.missing),
        ));
    }
    p.pose.check()?;
    let made = match &p.response {
        Some(r) => design.map_values(design.values().mapv(|h| r.made(h)), Unit::Metre)?,
        None => design.clone(),
    };
    let blurred = gaussian_blur(&made, p.blur)?;
    let (_, hmax) =
        design.min_max().ok_or_else(|| Error::data(DataCause::Empty, "the design has no valid sample"))?;
    let pitch = p.pitch.unwrap_or(design.pitch());
    if !pitch.iter().all(|v| v.is_finite() && *v > 0.0) {
        return Err(Error::param_in(
            "pitch",
            Allowed::positive(),
            format!("must be finite and positive, got {pitch:?} m"),
        ));
    }
    let (rows, cols) = p.size.unwrap_or_else(|| {
        let e = design.extent();
        ((e[1] / pitch[1]).round().max(1.0) as usize, (e[0] / pitch[0]).round().max(1.0) as usize)
    });
    if rows == 0 || cols == 0 || rows.saturating_mul(cols) > 1 << 28 {
        let what = format!("a {rows} x {cols} scan is empty or too large");
        return Err(match rows.saturating_mul(cols) {
            0 => Error::data(DataCause::Empty, what),
            n => Error::limit(Resource::Samples, n as f64, (1u64 << 28) as f64, what),
        });
    }
    let sampler = Sampler::new(&blurred);
    let mut rng = Lcg(p.seed);
    let mut values = Array2::<f64>::zeros((rows, cols));
    let mut valid = Array2::from_elem((rows, cols), true);
    let (ci, cj) = ((rows as f64 - 1.0) * 0.5, (cols as f64 - 1.0) * 0.5);
    for i in 0..rows {
        let y = (i as f64 - ci) * pitch[1];
        for j in 0..cols {
            let x = (j as f64 - cj) * pitch[0];
            // Draws are made for every sample so that the noise does not depend on the mask.
            let n = rng.normal();
            let drop = rng.uniform() < p.missing;
            let xd = p.pose.scan_to_design([x, y]);
            match sampler.at_position(xd) {
                Some(h) if !drop => {
                    let h = if p.complement { hmax - h } else { h };
                    values[[i, j]] =
                        p.depth_scale * h + p.offset + p.tilt[0] * x + p.tilt[1] * y + p.noise * n;
                }
                _ => valid[[i, j]] = false,
            }
        }
    }
    if !valid.iter().any(|&v| v) {
        return Err(Error::validity(
            Condition::Geometry,
            "the simulated scan does not overlap the design (check the shift, size and pitch)",
        ));
    }
    Grid::new(values, pitch, Unit::Metre)?.with_mask(valid)
}

/// Parses "X,Y" lengths (e.g. "3.2um,-1.7um") into metres; one value means X = Y.
pub fn parse_length_pair(text: &str) -> Result<[f64; 2]> {
    let v: Vec<f64> = text.split(',').map(crate::units::parse_length).collect::<Result<_>>()?;
    match v.as_slice() {
        [x] => Ok([*x, *x]),
        [x, y] => Ok([*x, *y]),
        _ => Err(Error::param("length pair", format!("'{text}': expected X or X,Y"))),
    }
}

/// Parses plane slopes "SX\[,SY\]" (dimensionless; one value is a slope along x only).
pub fn parse_slopes(text: &str) -> Result<[f64; 2]> {
    let v: Vec<f64> = text
        .split(',')
        .map(|t| {
            t.trim()
                .parse::<f64>()
                .ok()
                .filter(|v| v.is_finite())
                .ok_or_else(|| Error::param("tilt", format!("'{text}': '{t}' is not a number")))
        })
        .collect::<Result<_>>()?;
    match v.as_slice() {
        [x] => Ok([*x, 0.0]),
        [x, y] => Ok([*x, *y]),
        _ => Err(Error::param("tilt", format!("'{text}': expected SX or SX,SY"))),
    }
}

/// Parses a scan size "N" (square) or "COLSxROWS" into `(rows, cols)`.
pub fn parse_size(text: &str) -> Result<(usize, usize)> {
    let bad = || Error::param("size", format!("'{text}': expected N or COLSxROWS (e.g. 2048x1536)"));
    let n: Vec<usize> =
        text.split('x').map(|t| t.trim().parse::<usize>().map_err(|_| bad())).collect::<Result<_>>()?;
    match n.as_slice() {
        [k] if *k > 0 => Ok((*k, *k)),
        [c, r] if *c > 0 && *r > 0 => Ok((*r, *c)),
        _ => Err(bad()),
    }
}

/// Writes a scan as `.x3p` (f64, NaN for non-measured) or `.gsf` (f32), chosen by extension.
pub fn write_scan(path: &Path, scan: &Grid) -> Result<()> {
    let values = scan.values_nan_invalid();
    let ext = path.extension().and_then(|e| e.to_str()).map(|e| e.to_ascii_lowercase()).unwrap_or_default();
    let bytes = match ext.as_str() {
        "x3p" => crate::io::scan::x3p::encode(&values, scan.pitch())?,
        "gsf" => crate::io::scan::gsf::encode(&values, scan.pitch()),
        _ => {
            return Err(Error::param(
                "output",
                format!("{}: a simulated scan is written as .x3p or .gsf", path.display()),
            ))
        }
    };
    crate::io::atomic::write_bytes(path, &bytes)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn bump(n: usize) -> Grid {
        let c = (n as f64 - 1.0) * 0.5;
        let v = Array2::from_shape_fn((n, n), |(i, j)| {
            let r2 = (i as f64 - c).powi(2) + (j as f64 - c).powi(2);
            1e-6 * (-r2 / 50.0).exp()
        });
        Grid::new(v, [1e-6, 1e-6], Unit::Metre).unwrap()
    }

    #[test]
    fn command_line_values_parse() {
        assert_eq!(parse_length_pair("3um,-2um").unwrap(), [3e-6, -2e-6]);
        assert_eq!(parse_length_pair("1mm").unwrap(), [1e-3, 1e-3]);
        assert!(parse_length_pair("3,2").is_err());
        assert_eq!(parse_slopes("1e-4").unwrap(), [1e-4, 0.0]);
        assert_eq!(parse_slopes("1e-4,-2e-4").unwrap(), [1e-4, -2e-4]);
        assert!(parse_slopes("a").is_err());
        assert_eq!(parse_size("2048x1536").unwrap(), (1536, 2048));
        assert_eq!(parse_size("64").unwrap(), (64, 64));
        assert!(parse_size("0").is_err() && parse_size("3x").is_err());
    }

    #[test]
    fn blur_of_a_gaussian_adds_variances_and_keeps_volume() {
        // G(s1) * G(s2) = G(sqrt(s1^2 + s2^2)): a bump of variance 25 px^2 blurred by 3 px.
        let g = bump(81);
        let b = gaussian_blur(&g, 3e-6).unwrap();
        let peak = b.values()[[40, 40]];
        assert!((peak / 1e-6 - 25.0 / 34.0).abs() < 1e-4, "{peak}");
        let (s0, s1) = (g.values().sum(), b.values().sum());
        assert!((s0 - s1).abs() < 1e-6 * s0);
    }

    #[test]
    fn the_unmasked_blur_equals_the_normalized_convolution() {
        let g = bump(50)
            .map_values(Array2::from_shape_fn((50, 50), |(i, j)| ((i * 7 + j * 3) % 11) as f64), Unit::Metre)
            .unwrap();
        let masked = g.clone().with_mask(Array2::from_elem((50, 50), true)).unwrap();
        let (a, b) = (gaussian_blur(&g, 2.5e-6).unwrap(), gaussian_blur(&masked, 2.5e-6).unwrap());
        assert!(a.values().iter().zip(b.values()).all(|(x, y)| (x - y).abs() < 1e-12));
    }

    #[test]
    fn identity_pose_reproduces_the_design_and_noise_has_its_sigma() {
        let g = bump(64);
        let s = simulate_scan(&g, &SimulateParams::default()).unwrap();
        assert_eq!(s.dim(), (64, 64));
        assert!(s.values().iter().zip(g.values()).all(|(a, b)| (a - b).abs() < 1e-15));
        let p = SimulateParams { noise: 20e-9, missing: 0.1, seed: 7, ..Default::default() };
        let s = simulate_scan(&g, &p).unwrap();
        let (mut n, mut ss) = (0.0f64, 0.0f64);
        for ((i, j), v) in s.values().indexed_iter() {
            if s.is_valid(i, j) {
                n += 1.0;
                ss += (v - g.values()[[i, j]]).powi(2);
            }
        }
        let frac = 1.0 - n / 4096.0;
        assert!((frac - 0.1).abs() < 0.02, "{frac}");
        assert!(((ss / n).sqrt() / 20e-9 - 1.0).abs() < 0.05);
        assert_eq!(simulate_scan(&g, &p).unwrap(), s);
    }

    #[test]
    fn shift_moves_the_bump_and_complement_inverts_it() {
        let g = bump(64);
        let pose = Pose { shift: [5e-6, -3e-6], ..Default::default() };
        let p = SimulateParams { pose, complement: true, depth_scale: 0.5, ..Default::default() };
        let s = simulate_scan(&g, &p).unwrap();
        // The bump's minimum now sits 5 samples right of and 3 above the centre (31.5, 31.5).
        let (mut best, mut at) = (f64::INFINITY, (0, 0));
        for ((i, j), v) in s.values().indexed_iter() {
            if s.is_valid(i, j) && *v < best {
                best = *v;
                at = (i, j);
            }
        }
        assert!(at == (28, 36) || at == (29, 37) || at == (28, 37) || at == (29, 36), "{at:?}");
        let hmax = g.min_max().unwrap().1;
        assert!(best < 0.5 * (hmax - 0.9e-6));
        assert!(!s.is_valid(0, 0) && s.is_valid(0, 63));
    }
}
