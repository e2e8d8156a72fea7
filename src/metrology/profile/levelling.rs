//! Levelling a stylus profile ([`level_profile`]: the line through all points, or the
//! substrate's line), the noise of its point-to-point differences, the variance about its line,
//! and the terraces found without a design ([`terraces`]); the equations in the
//! [module docs](super).

use serde::Serialize;

use crate::error::{DataCause, Error, Result};
use crate::grid::profile::median;
use crate::grid::profile::Profile;

/// Noise of a profile from its point-to-point differences: `1.4826 MAD(dz) / sqrt 2` over
/// consecutive valid points (steps and a tilt do not enter).
pub fn noise_estimate(p: &Profile) -> f64 {
    let mut d: Vec<f64> =
        (1..p.len()).filter(|&k| p.valid()[k] && p.valid()[k - 1]).map(|k| p.z()[k] - p.z()[k - 1]).collect();
    if d.is_empty() {
        return 0.0;
    }
    let m = median(&mut d.clone());
    let mut dev: Vec<f64> = d.iter_mut().map(|v| (*v - m).abs()).collect();
    1.4826 * median(&mut dev) / std::f64::consts::SQRT_2
}

/// How to level a profile.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum ProfileLevel {
    /// Least-squares line over every valid point.
    Line,
    /// Least-squares line through the lowest level (the substrate) only.
    Substrate,
}

/// The line a profile was levelled by: `z = offset + slope u`, `u` from the first point.
#[derive(Debug, Clone, Serialize)]
pub struct Levelling {
    /// The levelling method used.
    pub method: ProfileLevel,
    /// Metres at the profile's first point.
    pub offset: f64,
    /// Dimensionless (metres per metre).
    pub slope: f64,
    /// Points the line was fitted on.
    pub points: usize,
    /// RMS of those points about the line, metres.
    pub rms: f64,
}

/// Least-squares line `z = o + t u` through the `(u, z)` points selected by `sel`.
fn fit_line(pts: &[(f64, f64)], sel: impl Fn(usize) -> bool) -> Result<(f64, f64, usize)> {
    let (mut n, mut su, mut sz) = (0.0, 0.0, 0.0);
    for (k, &(u, z)) in pts.iter().enumerate() {
        if sel(k) {
            n += 1.0;
            su += u;
            sz += z;
        }
    }
    if n < 2.0 {
        return Err(Error::data(DataCause::TooFew, format!("a line needs at least 2 points, {n} selected")));
    }
    let (mu, mz) = (su / n, sz / n);
    let (mut suu, mut suz) = (0.0, 0.0);
    for (k, &(u, z)) in pts.iter().enumerate() {
        if sel(k) {
            suu += (u - mu) * (u - mu);
            suz += (u - mu) * (z - mz);
        }
    }
    if suu <= 0.0 {
        return Err(Error::data(
            DataCause::Singular,
            "the points selected for the line all lie at one position",
        ));
    }
    let t = suz / suu;
    Ok((mz - t * mu, t, n as usize))
}

/// Levels a profile (see the module docs): the levelled profile and the line removed.
pub fn level_profile(p: &Profile, method: ProfileLevel) -> Result<(Profile, Levelling)> {
    let pts = p.points();
    if pts.len() < 2 {
        return Err(Error::data(
            DataCause::TooFew,
            format!("the profile has {} measured points: nothing to level", pts.len()),
        ));
    }
    let (mut o, mut t, mut n) = fit_line(&pts, |_| true)?;
    let mut sel: Vec<bool> = vec![true; pts.len()];
    if method == ProfileLevel::Substrate {
        let resid = |o: f64, t: f64| -> Vec<f64> { pts.iter().map(|(u, z)| z - o - t * u).collect() };
        let r0 = resid(o, t);
        let range = r0.iter().cloned().fold(f64::NEG_INFINITY, f64::max)
            - r0.iter().cloned().fold(f64::INFINITY, f64::min);
        let sn = noise_estimate(p);
        for i in 0..9 {
            let r = resid(o, t);
            let mut sorted = r.clone();
            sorted.sort_unstable_by(f64::total_cmp);
            let q = sorted[((sorted.len() - 1) as f64 * 0.02).round() as usize];
            let band = (range / 2f64.powi(i + 1)).max(5.0 * sn);
            sel = r.iter().map(|v| *v <= q + band).collect();
            (o, t, n) = fit_line(&pts, |k| sel[k]).map_err(|e| {
                Error::data(
                    DataCause::TooFew,
                    format!("substrate levelling: the lowest band holds too few points ({e})"),
                )
            })?;
        }
    }
    let ss: f64 = pts.iter().zip(&sel).filter(|(_, s)| **s).map(|((u, z), _)| (z - o - t * u).powi(2)).sum();
    let x0 = p.x()[0];
    let z =
        (0..p.len()).map(|k| if p.valid()[k] { p.z()[k] - o - t * (p.x()[k] - x0) } else { 0.0 }).collect();
    Ok((p.with_z(z), Levelling { method, offset: o, slope: t, points: n, rms: (ss / n as f64).sqrt() }))
}

/// One level found by [`terraces`].
#[derive(Debug, Clone, Serialize)]
pub struct Terrace {
    /// Mean height above the lowest level's, metres.
    pub height: f64,
    /// Standard error of `height`, `sqrt(s^2 / n + s_0^2 / n_0)`, metres; 0 for the lowest
    /// level.
    pub height_sigma: f64,
    /// Spread of the level's points about their mean (sample standard deviation), metres.
    pub std: f64,
    /// Profile points on the level's terraces.
    pub points: usize,
    /// Separate terraces (runs) on this level.
    pub runs: usize,
}

/// The levels of a (levelled) profile without a design; see the module docs. Lowest first.
pub fn terraces(p: &Profile) -> Result<Vec<Terrace>> {
    let sn = noise_estimate(p);
    let zs: Vec<f64> = (0..p.len()).filter(|&k| p.valid()[k]).map(|k| p.z()[k]).collect();
    let range = zs.iter().cloned().fold(f64::NEG_INFINITY, f64::max)
        - zs.iter().cloned().fold(f64::INFINITY, f64::min);
    if range.is_nan() || range <= 0.0 {
        return Err(Error::data(DataCause::Featureless, "the profile is flat: no terraces"));
    }
    let flat = (5.0 * sn).max(1e-3 * range);
    let min_run = (p.len() / 200).max(5);
    // Runs of consecutive valid points with small neighbour differences.
    let mut runs: Vec<Vec<usize>> = Vec::new();
    let mut cur: Vec<usize> = Vec::new();
    for k in 0..p.len() {
        let joins =
            p.valid()[k] && cur.last().is_some_and(|&j| j + 1 == k && (p.z()[k] - p.z()[j]).abs() <= flat);
        if joins {
            cur.push(k);
        } else {
            if cur.len() >= min_run {
                runs.push(std::mem::take(&mut cur));
            }
            cur.clear();
            if p.valid()[k] {
                cur.push(k);
            }
        }
    }
    if cur.len() >= min_run {
        runs.push(cur);
    }
    let mut means: Vec<(f64, Vec<usize>)> =
        runs.into_iter().map(|r| (r.iter().map(|&k| p.z()[k]).sum::<f64>() / r.len() as f64, r)).collect();
    means.sort_by(|a, b| a.0.total_cmp(&b.0));
    let merge = (10.0 * sn).max(0.02 * range);
    let mut levels: Vec<(Vec<f64>, usize)> = Vec::new();
    let mut last = f64::NEG_INFINITY;
    for (m, r) in means {
        if levels.is_empty() || m - last > merge {
            levels.push((Vec::new(), 0));
        }
        let lv = levels.last_mut().ok_or_else(|| Error::internal("no level"))?;
        lv.0.extend(r.iter().map(|&k| p.z()[k]));
        lv.1 += 1;
        last = m;
    }
    if levels.len() < 2 {
        return Err(Error::data(
            DataCause::TooFew,
            format!("the profile shows {} terrace level(s): a step height needs at least 2", levels.len()),
        ));
    }
    let stats: Vec<(f64, f64, usize, usize)> = levels
        .iter()
        .map(|(v, runs)| {
            let n = v.len() as f64;
            let m = v.iter().sum::<f64>() / n;
            let s = (v.iter().map(|z| (z - m).powi(2)).sum::<f64>() / (n - 1.0).max(1.0)).sqrt();
            (m, s, v.len(), *runs)
        })
        .collect();
    let (m0, s0, n0, _) = stats[0];
    Ok(stats
        .iter()
        .map(|&(m, s, n, runs)| Terrace {
            height: m - m0,
            height_sigma: if (m, n) == (m0, n0) {
                0.0
            } else {
                (s * s / n as f64 + s0 * s0 / n0 as f64).sqrt()
            },
            std: s,
            points: n,
            runs,
        })
        .collect())
}

/// The variance of the profile's points about their least-squares line; a profile whose
/// neighbour differences are as large as white noise's (`sqrt 2` times its RMS, here over
/// `0.8 sqrt 2`) is refused as featureless.
pub(super) fn profile_variance(pts: &[(f64, f64)]) -> Result<f64> {
    let zs: Vec<f64> = pts.iter().map(|p| p.1).collect();
    let us: Vec<f64> = pts.iter().map(|p| p.0).collect();
    let (o, t, _) = fit_line(pts, |_| true)?;
    let r: Vec<f64> = us.iter().zip(&zs).map(|(u, z)| z - o - t * u).collect();
    let sd = (r.iter().map(|v| v * v).sum::<f64>() / r.len() as f64).sqrt();
    let dd: Vec<f64> = r.windows(2).map(|w| w[1] - w[0]).collect();
    let sdd = (dd.iter().map(|v| v * v).sum::<f64>() / dd.len() as f64).sqrt();
    if sd.is_nan() || sd <= 0.0 || sdd > 0.8 * std::f64::consts::SQRT_2 * sd {
        return Err(Error::data(DataCause::Featureless, format!(
            "the profile is featureless: {:.3} nm RMS about its line, with neighbour differences of {:.3} nm RMS \
             (white noise has sqrt 2 times its RMS)",
            sd * 1e9,
            sdd * 1e9
        )));
    }
    Ok(sd * sd)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn levelling_and_terraces() {
        // Steps of 1.0 and 0.5 um on a base, tilted 2e-3, sampled at 1 um.
        let x: Vec<f64> = (0..200).map(|k| k as f64 * 1e-6).collect();
        let z: Vec<f64> = (0..200)
            .map(|k| {
                let step = if (50..150).contains(&k) { 1e-6 } else { 0.0 }
                    + if (80..120).contains(&k) { 0.5e-6 } else { 0.0 };
                5e-8 + 2e-3 * k as f64 * 1e-6 + step
            })
            .collect();
        let p = Profile::new(x, z, None).unwrap();
        let (lev, l) = level_profile(&p, ProfileLevel::Substrate).unwrap();
        assert!((l.slope - 2e-3).abs() < 1e-12 && l.points == 100, "{l:?}");
        let t = terraces(&lev).unwrap();
        assert_eq!(t.len(), 3);
        assert!((t[1].height - 1e-6).abs() < 1e-12 && (t[2].height - 1.5e-6).abs() < 1e-12, "{t:?}");
        let (_, l) = level_profile(&p, ProfileLevel::Line).unwrap();
        assert!((l.slope - 2e-3).abs() < 1e-12 && l.points == 200, "{l:?}");
        let flat = Profile::new(vec![0.0, 1e-6, 2e-6], vec![0.0; 3], None).unwrap();
        assert!(terraces(&flat).is_err());
    }

    /// A ripple `c cos(2 pi m (k - (N - 1) / 2) / N)`, even about the profile's middle, on a
    /// tilted line: its least-squares line is the tilted line, so the variance is `c^2 / 2`.
    #[test]
    fn profile_variance_is_the_ripple_about_its_line() {
        let (n, c) = (400usize, 30e-9);
        let pts: Vec<(f64, f64)> = (0..n)
            .map(|k| {
                let u = k as f64 * 1e-6;
                let t = 2.0 * std::f64::consts::PI * 5.0 * (k as f64 - (n as f64 - 1.0) * 0.5) / n as f64;
                (u, 1e-7 + 3e-4 * u + c * t.cos())
            })
            .collect();
        let v = profile_variance(&pts).unwrap();
        assert!((v / (0.5 * c * c) - 1.0).abs() < 1e-9, "{v}");
        let mut rng = crate::rng::Lcg(2);
        let noise: Vec<(f64, f64)> = (0..n).map(|k| (k as f64 * 1e-6, c * rng.normal())).collect();
        let e = profile_variance(&noise).unwrap_err();
        assert!(matches!(e, Error::Data { cause: DataCause::Featureless, .. }), "{e:?}");
    }
}
