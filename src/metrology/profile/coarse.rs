//! The coarse search of a profile's shift along and offset across the line: detrended
//! correlation with the design, the second peak that makes a shift ambiguous (step 1 of the
//! [module docs](super)).

use super::model::{Blurred, Ctx};

/// Pearson correlation of two equally long series, each with its least-squares line in `u`
/// removed.
fn detrended_correlation(u: &[f64], a: &[f64], b: &[f64]) -> f64 {
    let n = u.len() as f64;
    if n < 3.0 {
        return f64::NAN;
    }
    let detrend = |y: &[f64]| -> Vec<f64> {
        let (mu, my) = (u.iter().sum::<f64>() / n, y.iter().sum::<f64>() / n);
        let (mut suu, mut suy) = (0.0, 0.0);
        for (x, v) in u.iter().zip(y) {
            suu += (x - mu) * (x - mu);
            suy += (x - mu) * (v - my);
        }
        let t = if suu > 0.0 { suy / suu } else { 0.0 };
        u.iter().zip(y).map(|(x, v)| v - my - t * (x - mu)).collect()
    };
    let (da, db) = (detrend(a), detrend(b));
    let (mut sab, mut saa, mut sbb) = (0.0, 0.0, 0.0);
    for (x, y) in da.iter().zip(&db) {
        sab += x * y;
        saa += x * x;
        sbb += y * y;
    }
    if saa > 0.0 && sbb > 0.0 {
        sab / (saa * sbb).sqrt()
    } else {
        f64::NAN
    }
}

/// The best match of the coarse search (module docs, step 1), in steps of `ds`.
pub(super) struct CoarseMatch {
    /// The largest `|r|`, at `along` steps along and `across` steps across; the sign of `r`.
    pub(super) peak: f64,
    pub(super) along: i64,
    pub(super) across: i64,
    pub(super) sign: f64,
    /// `|r|` along the line (shifts `-ns..=ns`) at the winning offset.
    pub(super) row: Vec<f64>,
    /// No shift and offset gave a correlation: the design is flat along the line.
    pub(super) design_flat: bool,
}

/// The coarse search: the detrended correlation ([`detrended_correlation`]) of the profile
/// (at most 4000 points, by a stride) with the sharp design along the line, for shifts
/// `is ds` (`|is| <= ns`) and offsets `iv ds` (`|iv| <= nv`, the smallest offsets first: a tie
/// goes to them); positions where less than half the points fall on the design score 0.
pub(super) fn coarse_search(ctx: &Ctx, sharp: &Blurred, ds: f64, ns: i64, nv: i64) -> CoarseMatch {
    let cstride = ctx.pts.len().div_ceil(4000).max(1);
    let cpts: Vec<(f64, f64)> = ctx.pts.iter().step_by(cstride).copied().collect();
    let mut vs: Vec<i64> = (-nv..=nv).collect();
    vs.sort_by_key(|v| v.abs());
    let mut best = (f64::NEG_INFINITY, 0i64, 0i64, 0.0f64);
    let mut rows: Vec<(i64, Vec<f64>)> = Vec::new();
    let mut design_flat = true;
    for &iv in &vs {
        let mut row = Vec::with_capacity((2 * ns + 1) as usize);
        for is in -ns..=ns {
            let (s, v) = (is as f64 * ds, iv as f64 * ds);
            let mut u = Vec::with_capacity(cpts.len());
            let (mut za, mut hb) = (Vec::with_capacity(cpts.len()), Vec::with_capacity(cpts.len()));
            for &(pu, z) in &cpts {
                if let Some((h, _, _)) = sharp.at(ctx.pos(pu, s, v)) {
                    u.push(pu);
                    za.push(z);
                    hb.push(h);
                }
            }
            let r = if u.len() * 2 >= cpts.len() { detrended_correlation(&u, &za, &hb) } else { f64::NAN };
            if r.is_finite() {
                design_flat = false;
            }
            let score = if r.is_finite() { r.abs() } else { 0.0 };
            if score > best.0 * (1.0 + 1e-9) {
                best = (score, is, iv, r.signum());
            }
            row.push(score);
        }
        rows.push((iv, row));
    }
    let (peak, along, across, sign) = best;
    let row = rows.iter().find(|(v, _)| *v == across).map(|r| r.1.clone()).unwrap_or_default();
    CoarseMatch { peak, along, across, sign, row, design_flat }
}

/// The correlation of the measured and the model heights of the fit table, each with its
/// least-squares line in the position removed ([`detrended_correlation`]).
pub(super) fn fit_correlation(fit: &[[f64; 3]]) -> f64 {
    let u: Vec<f64> = fit.iter().map(|f| f[0]).collect();
    let zz: Vec<f64> = fit.iter().map(|f| f[1]).collect();
    let mm: Vec<f64> = fit.iter().map(|f| f[2]).collect();
    detrended_correlation(&u, &zz, &mm)
}

/// The second-highest local maximum of `row` outside the main lobe around `k0` (where the
/// score first falls below half the peak on each side); 0 when there is none.
pub(super) fn second_peak(row: &[f64], k0: usize) -> f64 {
    let half = 0.5 * row[k0];
    let mut lo = k0;
    while lo > 0 && row[lo - 1] >= half && row[lo - 1] <= row[lo] {
        lo -= 1;
    }
    let mut hi = k0;
    while hi + 1 < row.len() && row[hi + 1] >= half && row[hi + 1] <= row[hi] {
        hi += 1;
    }
    let mut best = 0.0f64;
    for k in 0..row.len() {
        if (lo..=hi).contains(&k) {
            continue;
        }
        let left = k == 0 || row[k - 1] <= row[k];
        let right = k + 1 == row.len() || row[k + 1] <= row[k];
        // A maximum at the search's edge counts: the correlation may rise beyond it.
        if left && right {
            best = best.max(row[k]);
        }
    }
    best
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::metrology::profile::compare::fit_points;
    use crate::metrology::profile::line::LineSpec;
    use crate::metrology::profile::simulate::tests::staircase;
    use crate::metrology::profile::simulate::{simulate_profile, SimulateProfile};
    use crate::metrology::profile::steps::DesignIndex;

    /// A noise-free complemented profile of the sharp design, 3 steps along the line from its
    /// nominal start: the coarse search finds the shift and the sign, correlating by 1.
    #[test]
    fn the_coarse_search_finds_a_known_shift_and_sign() {
        let d = staircase();
        let ds = 1e-6;
        let sp = SimulateProfile {
            line: LineSpec::Angle { angle: 0.0 },
            length: 300e-6,
            step: 0.5e-6,
            x_origin: 0.0,
            along_shift: 3.0 * ds,
            across_offset: 0.0,
            depth_scale: -1.0,
            offset: 0.0,
            tilt: 0.0,
            blur: 0.0,
            noise: 0.0,
            seed: 1,
        };
        let prof = simulate_profile(&d, &sp).unwrap();
        let pts = fit_points(&prof, 20_000).unwrap();
        let (start, dir) = sp.line.frame(prof.length());
        let (crop, crop_centre) =
            DesignIndex::new(&d).crop_around_line(start, dir, [-10e-6, 310e-6, -4e-6, 4e-6], 10e-6).unwrap();
        let u_mean = pts.iter().map(|p| p.0).sum::<f64>() / pts.len() as f64;
        let ctx = Ctx { crop: &crop, crop_centre, pts: &pts, u_mean, start, dir, nrm: [-dir[1], dir[0]] };
        let m = coarse_search(&ctx, &ctx.blurred(0.0).unwrap(), ds, 10, 2);
        assert_eq!((m.along, m.sign, m.row.len(), m.design_flat), (3, -1.0, 21, false));
        assert!(m.peak > 0.999 && m.row[13] == m.peak, "{}", m.peak);
    }
}
