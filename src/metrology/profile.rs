//! Stylus profiles: a 1-D height profile along a line across the part (Dektak, Alpha-Step,
//! P-series; read by [`crate::io::profile`]), levelled, and compared with the design along the
//! line the user names.
//!
//! # Profile
//! Positions `x_k` along the line (metres, strictly increasing), heights `z_k` (metres) and a
//! validity flag per point (a non-measured point never enters a sum or a fit). `u_k = x_k - x_0`
//! is the distance from the profile's first point.
//!
//! # Levelling ([`level_profile`])
//! * `line`: the least-squares line `z = o + t u` over all valid points, subtracted.
//! * `substrate`: the line through the lowest level only. With `r` the residuals of the current
//!   line, `R = max r - min r` over the first line's residuals, and `s_n` the noise estimated
//!   from the point-to-point differences (`1.4826 MAD(dz) / sqrt 2`, insensitive to steps and
//!   to the tilt), the band is `w_i = max(R / 2^(i+1), 5 s_n)`; the points with
//!   `r <= q_02 + w_i` (`q_02` the 2 % quantile of `r`, robust to low spikes) are refitted, for
//!   `i = 0..8`. Halving the band each time lets a tilt that first mixes the substrate with the
//!   level above be removed before the band closes on the substrate. The comparison with a
//!   design fits its own offset and tilt (`compare-profile` runs it on the profile as read),
//!   so the levelling changes only the levelled profile reported and plotted, and the
//!   design-free terraces.
//!
//! # The design along the line ([`LineSpec`])
//! Two points `p0 -> p1` (metres from the design's centre, x along columns, y along rows), or an
//! angle `theta` (counter-clockwise from +x in the design's (x, y) frame) through the centre,
//! the profile then centred on the centre. With `d` the unit direction and `n = (-d_y, d_x)`
//! its normal, profile point `k` sees the design at
//! `P_k = p0 + (u_k + s) d + v n`: `s` is the shift along the line, `v` the offset across it.
//!
//! # Model and fit ([`compare_profile`])
//! `z_k = a (G_sigma * h)(P_k) + b + c (u_k - u_mean) + noise`: the design `h` blurred by a 2-D
//! Gaussian of standard deviation `sigma` (the process's lateral blur, as `compare` fits it on a
//! map), read by Keys cubic convolution with its gradient ([`Sampler`]); `|a|` is the depth
//! scale, `a < 0` a complemented part (a cast), `b` the height offset at the profile's middle,
//! `c` the remaining tilt (dimensionless).
//! 1. *Coarse search.* For shifts `s` in `[-S, S]` and offsets `v` in `[-V, V]` (steps of half
//!    the design pitch), the Pearson correlation between the profile and the design along the
//!    line, both with their least-squares line removed (the 1-D cross-correlation); the largest
//!    `|r|` wins, its sign gives the sign of `a`. Along the winning offset's row, a second local
//!    maximum outside the main lobe reaching `max_peak_ratio` of the peak means the shift is
//!    ambiguous (a periodic design along the line): refused, narrow the search. A peak below
//!    `min_correlation` (and a fitted model correlating by less) is refused as not matching; a
//!    fitted model below [`TRUSTED_FRACTION`] of the correlation the profile's own noise allows
//!    is refused as not trusted ([`check_trust`], the rule of every registration).
//! 2. *Refinement.* For each `sigma`, Gauss-Newton with Levenberg-Marquardt damping on
//!    `(s, v, a, b, c)` (Jacobian `a grad H . d`, `a grad H . n`, `H`, `1`, `u - u_mean`);
//!    `sigma` minimises the residual sum of squares `SSE(sigma)` by golden-section search on
//!    `[0, 3 max(pitch)]` (the design blurred on a crop around the line for each `sigma`).
//! 3. *Uncertainty.* `s^2 = SSE / (n - p)`, covariance `s^2 (J^T J)^-1` over the free
//!    parameters, `sigma` included with its Jacobian column by central differences; where
//!    `sigma` is too small for that column to be determined (the blur's effect grows as
//!    `sigma^2`), the others' errors are taken at fixed `sigma` and the blur's from the
//!    profile likelihood, `sqrt(2 s^2 / SSE''(sigma))`. A blur whose standard error exceeds a
//!    quarter of it is reported as not resolved.
//! 4. *Across-line offset.* Where the design hardly varies across the line
//!    (`||J_v|| < 0.02 ||J_s||`), `v` is unobservable: it is held at the coarse value (0 unless
//!    the coarse search found better) and a warning says so; otherwise its standard error is
//!    reported (and a warning raised when it exceeds the design's pitch).
//!
//! # Per-level step heights
//! Where the reference is multi-level (at most [`MAX_LEVELS`] distinct heights: a design
//! quantized by a recipe, or a level map), each point at its registered position `P_k` belongs
//! to the terrace interior of level `l` when every design sample within
//! `r = 2 sigma + 1.5 max(pitch)` of `P_k` is on level `l` (the blur and the interpolation's
//! reach leave the point at the level's height). Its measured height is
//! `y_k = sign(a) (z_k - b - c (u_k - u_mean))`. With `m_l`, `s_l`, `n_l` the mean, spread and
//! count of level `l`'s interior heights, and `l0` the lowest level on the line,
//! the step height is `H_l = m_l - m_l0 +- sqrt(s_l^2 / n_l + s_l0^2 / n_l0)` and its depth scale
//! `H_l / (h_l - h_l0)` against the design's. Fewer than two levels with interior points on the
//! line is refused.
//!
//! # Terraces without a design ([`terraces`])
//! Runs of at least `max(5, N / 200)` consecutive points whose neighbour differences stay below
//! `max(5 s_n, 1e-3 (max z - min z))` are terraces; terrace means closer than
//! `max(10 s_n, 2 % of the range)` are one level. Each level's height (the mean of its points)
//! is given above the lowest level's, with its standard error.

use serde::Serialize;

use crate::error::{Error, Refusal, Result};
use crate::grid::blur::gaussian_blur;
use crate::grid::profile::median;
pub use crate::grid::profile::Profile;
use crate::grid::{Grid, Unit};
use crate::metrology::scan_registration::{check_trust, noise_ceiling, Sampler, TRUSTED_FRACTION};

/// Most distinct design heights for which the reference counts as multi-level.
pub const MAX_LEVELS: usize = 256;

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
        return Err(Error::Data(format!("a line needs at least 2 points, {n} selected")));
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
        return Err(Error::Data("the points selected for the line all lie at one position".into()));
    }
    let t = suz / suu;
    Ok((mz - t * mu, t, n as usize))
}

/// Levels a profile (see the module docs): the levelled profile and the line removed.
pub fn level_profile(p: &Profile, method: ProfileLevel) -> Result<(Profile, Levelling)> {
    let pts = p.points();
    if pts.len() < 2 {
        return Err(Error::Data(format!("the profile has {} measured points: nothing to level", pts.len())));
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
                Error::Data(format!("substrate levelling: the lowest band holds too few points ({e})"))
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
    /// Mean height above the lowest level's, metres, and its standard error.
    pub height: f64,
    pub height_sigma: f64,
    /// Spread of the level's points about their mean, metres.
    pub std: f64,
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
        return Err(Error::Data("the profile is flat: no terraces".into()));
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
        let lv = levels.last_mut().ok_or_else(|| Error::Data("no level".into()))?;
        lv.0.extend(r.iter().map(|&k| p.z()[k]));
        lv.1 += 1;
        last = m;
    }
    if levels.len() < 2 {
        return Err(Error::Data(format!(
            "the profile shows {} terrace level(s): a step height needs at least 2",
            levels.len()
        )));
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

/// The line on the design, as the user gives it.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum LineSpec {
    /// From `start` to `end`, metres from the design's centre; the profile's first point at `start`.
    Points { start: [f64; 2], end: [f64; 2] },
    /// Through the design's centre at `angle` radians (counter-clockwise from +x), the profile
    /// centred on the centre.
    Angle { angle: f64 },
}

impl LineSpec {
    /// Parses "x0,y0,x1,y1": each a length ("-1mm", "20 um"), or bare numbers with the last
    /// one's unit ("-1,0,1,0.5mm"); a bare 0 needs no unit.
    pub fn parse_points(text: &str) -> Result<LineSpec> {
        let cells: Vec<&str> = text.split(',').map(str::trim).collect();
        if cells.len() != 4 {
            return Err(Error::param("line", format!("'{text}': expected x0,y0,x1,y1 (four lengths)")));
        }
        let bare = |c: &str| c.parse::<f64>().ok();
        let last_unit = crate::units::parse_length(cells[3]).ok().and_then(|v| {
            bare(cells[3].trim_end_matches(|ch: char| ch.is_alphabetic() || ch == 'µ' || ch == 'μ').trim())
                .filter(|b| *b != 0.0)
                .map(|b| v / b)
        });
        let mut v = [0.0; 4];
        for (k, c) in cells.iter().enumerate() {
            v[k] = match (crate::units::parse_length(c), bare(c)) {
                (Ok(m), _) => m,
                (Err(_), Some(0.0)) => 0.0,
                (Err(_), Some(b)) => match last_unit {
                    Some(u) if cells.iter().filter(|c| bare(c).is_none()).count() == 1 => b * u,
                    _ => {
                        return Err(Error::param(
                            "line",
                            format!("'{text}': '{c}' has no unit (write e.g. \"{c}um\")"),
                        ))
                    }
                },
                (Err(e), None) => return Err(e),
            };
        }
        let s = LineSpec::Points { start: [v[0], v[1]], end: [v[2], v[3]] };
        s.check()?;
        Ok(s)
    }

    fn check(&self) -> Result<()> {
        match *self {
            LineSpec::Points { start, end } => {
                if start.iter().chain(&end).any(|v| !v.is_finite()) {
                    return Err(Error::param("line", "its points must be finite"));
                }
                if start == end {
                    return Err(Error::param("line", "its two points are the same: no direction"));
                }
            }
            LineSpec::Angle { angle } if !angle.is_finite() => {
                return Err(Error::param("angle", "must be finite"));
            }
            LineSpec::Angle { .. } => {}
        }
        Ok(())
    }

    /// The design position of the profile's first point and the unit direction, for a profile
    /// of `length` metres.
    pub fn frame(&self, length: f64) -> ([f64; 2], [f64; 2]) {
        match *self {
            LineSpec::Points { start, end } => {
                let d = [end[0] - start[0], end[1] - start[1]];
                let l = d[0].hypot(d[1]);
                (start, [d[0] / l, d[1] / l])
            }
            LineSpec::Angle { angle } => {
                let d = [angle.cos(), angle.sin()];
                ([-0.5 * length * d[0], -0.5 * length * d[1]], d)
            }
        }
    }
}

/// Options of [`compare_profile`].
#[derive(Debug, Clone, Serialize)]
pub struct ProfileOptions {
    /// Half-range of the coarse search along the line, metres: how well the profile's start is
    /// known on the part.
    pub along_search: f64,
    /// Half-range of the coarse search across the line, metres.
    pub across_search: f64,
    /// Refuse when a second correlation peak along the line reaches this fraction of the first.
    pub max_peak_ratio: f64,
    /// Refuse below this correlation between the profile and the design, at the coarse match
    /// and for the fitted model (a line has few independent features: a quasi-periodic design
    /// correlates by 0.5-0.6 with a profile along another direction).
    pub min_correlation: f64,
    /// Refuse below this fraction of the correlation the profile's own noise allows (the trust
    /// rule of every registration, [`check_trust`]).
    pub min_correlation_ratio: f64,
    /// Most profile points in the fit (a stride thins the rest).
    pub max_points: usize,
}

impl Default for ProfileOptions {
    fn default() -> Self {
        ProfileOptions {
            along_search: 50e-6,
            across_search: 10e-6,
            max_peak_ratio: 0.9,
            min_correlation: 0.8,
            min_correlation_ratio: TRUSTED_FRACTION,
            max_points: 20_000,
        }
    }
}

/// One design level's step on the line (see the module docs).
#[derive(Debug, Clone, Serialize)]
pub struct LevelStep {
    /// Index of the level among the design's distinct heights (0 = lowest).
    pub level: usize,
    /// The design's height of the level above the lowest level on the line, metres.
    pub design_step: f64,
    /// Terrace-interior points on the line.
    pub points: usize,
    /// Mean and spread of their measured heights `y_k`, metres.
    pub mean: f64,
    pub std: f64,
    /// `H_l = m_l - m_l0` and its standard error, metres (`None` for the reference level).
    pub step_height: Option<f64>,
    pub step_height_sigma: Option<f64>,
    /// `H_l / design_step` and its standard error.
    pub depth_scale: Option<f64>,
    pub depth_scale_sigma: Option<f64>,
}

/// The per-level step heights on the line.
#[derive(Debug, Clone, Serialize)]
pub struct LevelSteps {
    /// The design's distinct heights, metres (levels are indices into it).
    pub design_levels: Vec<f64>,
    /// The lowest level on the line, against which step heights are given.
    pub reference_level: usize,
    /// Interior radius `r`, metres.
    pub interior_radius: f64,
    /// The levels with interior points on the line, lowest first.
    pub levels: Vec<LevelStep>,
}

/// The comparison of a profile with its design along a line; lengths and heights in metres,
/// angles in radians, each `*_sigma` a standard error (1 sigma).
#[derive(Debug, Clone, Serialize)]
pub struct ProfileComparison {
    pub line: LineSpec,
    /// Design position of the profile's first point and the line's unit direction (before
    /// registration), metres.
    pub line_start: [f64; 2],
    pub line_direction: [f64; 2],
    /// Shift along the line `s` (the profile's first point lies at `line_start + s d + v n`).
    pub along_shift: f64,
    pub along_shift_sigma: f64,
    /// Offset across the line `v` (towards `n = (-d_y, d_x)`).
    pub across_offset: f64,
    pub across_offset_sigma: f64,
    /// The across-line offset was unobservable and held at the coarse value.
    pub across_fixed: bool,
    /// `|a|`, and `a < 0`.
    pub depth_scale: f64,
    pub depth_scale_sigma: f64,
    pub complement: bool,
    /// `b`: height at the profile's middle of the design's zero, metres.
    pub offset: f64,
    pub offset_sigma: f64,
    /// `c`, dimensionless.
    pub tilt: f64,
    pub tilt_sigma: f64,
    /// Gaussian lateral blur `sigma`, metres, its standard error, whether it is resolved and
    /// the upper end of its search.
    pub blur: f64,
    pub blur_sigma: f64,
    pub blur_resolved: bool,
    pub blur_search_max: f64,
    /// RMS of the residual, metres; points in the fit.
    pub rms_residual: f64,
    pub points: usize,
    /// Correlation of the profile and the fitted model, and the highest its noise allows
    /// ([`noise_ceiling`]); second to first coarse peak.
    pub correlation: f64,
    pub noise_ceiling: f64,
    pub peak_ratio: f64,
    pub levels: Option<LevelSteps>,
    pub warnings: Vec<String>,
    /// Profile position (metres, as in the file), measured and model heights at each fitted
    /// point (for plots and `profile_fit.csv`).
    #[serde(skip)]
    pub fit: Vec<[f64; 3]>,
}

/// The design blurred on a crop around the line, and where the crop's centre lies.
struct Blurred {
    sampler: Sampler<'static>,
    centre: [f64; 2],
    pitch: [f64; 2],
}

impl Blurred {
    /// `(H, dH/dx, dH/dy)` at design position `p` (metres from the design's centre).
    fn at(&self, p: [f64; 2]) -> Option<(f64, f64, f64)> {
        let (fi, fj) = self.sampler.index_of([p[0] - self.centre[0], p[1] - self.centre[1]]);
        self.sampler.eval(fi, fj).map(|(h, di, dj)| (h, dj / self.pitch[0], di / self.pitch[1]))
    }
}

/// Fit context: the crop of the design, the points and the line frame.
struct Ctx<'a> {
    crop: &'a Grid,
    crop_centre: [f64; 2],
    pts: &'a [(f64, f64)],
    u_mean: f64,
    start: [f64; 2],
    dir: [f64; 2],
    nrm: [f64; 2],
}

impl Ctx<'_> {
    fn pos(&self, u: f64, s: f64, v: f64) -> [f64; 2] {
        [
            self.start[0] + (u + s) * self.dir[0] + v * self.nrm[0],
            self.start[1] + (u + s) * self.dir[1] + v * self.nrm[1],
        ]
    }
    fn blurred(&self, sigma: f64) -> Result<Blurred> {
        let g = gaussian_blur(self.crop, sigma)?;
        Ok(Blurred { sampler: Sampler::new_owned(&g), centre: self.crop_centre, pitch: self.crop.pitch() })
    }
}

/// Normal equations of the 5 parameters `(s, v, a, b, c)` at `p`.
struct Normal {
    jtj: [[f64; 5]; 5],
    jtr: [f64; 5],
    sse: f64,
    n: usize,
    /// Squared norms of the `s` and `v` columns.
    col2: [f64; 2],
}

fn normal(ctx: &Ctx, b: &Blurred, p: &[f64; 5]) -> Normal {
    let mut nm = Normal { jtj: [[0.0; 5]; 5], jtr: [0.0; 5], sse: 0.0, n: 0, col2: [0.0; 2] };
    for &(u, z) in ctx.pts {
        let Some((h, hx, hy)) = b.at(ctx.pos(u, p[0], p[1])) else { continue };
        let du = u - ctx.u_mean;
        let r = z - (p[2] * h + p[3] + p[4] * du);
        let j = [
            p[2] * (hx * ctx.dir[0] + hy * ctx.dir[1]),
            p[2] * (hx * ctx.nrm[0] + hy * ctx.nrm[1]),
            h,
            1.0,
            du,
        ];
        for a in 0..5 {
            nm.jtr[a] += j[a] * r;
            for c in 0..5 {
                nm.jtj[a][c] += j[a] * j[c];
            }
        }
        nm.col2[0] += j[0] * j[0];
        nm.col2[1] += j[1] * j[1];
        nm.sse += r * r;
        nm.n += 1;
    }
    nm
}

/// Solves `(A + lambda diag A) x = r` over the `free` indices (scaled to unit diagonal).
fn damped_solve(a: &[[f64; 5]; 5], r: &[f64; 5], lambda: f64, free: &[usize]) -> Option<[f64; 5]> {
    let m = free.len();
    let d: Vec<f64> = free.iter().map(|&i| a[i][i].sqrt()).collect();
    if d.iter().any(|v| !(v.is_finite() && *v > 0.0)) {
        return None;
    }
    let mut mat = vec![0.0; m * m];
    let mut rhs = vec![0.0; m];
    for (p, &i) in free.iter().enumerate() {
        rhs[p] = r[i] / d[p];
        for (q, &j) in free.iter().enumerate() {
            mat[p * m + q] = a[i][j] / (d[p] * d[q]) + if p == q { lambda } else { 0.0 };
        }
    }
    let x = crate::linalg::solve(mat, rhs, m).ok()?;
    let mut out = [0.0; 5];
    for (p, &i) in free.iter().enumerate() {
        out[i] = x[p] / d[p];
    }
    Some(out)
}

/// Levenberg-Marquardt on `(s, v, a, b, c)` at a fixed blur; returns the SSE and point count.
fn refine(ctx: &Ctx, b: &Blurred, p: &mut [f64; 5], free: &[usize]) -> (f64, usize) {
    let mut nm = normal(ctx, b, p);
    let mut lambda = 1e-3;
    for _ in 0..60 {
        let Some(step) = damped_solve(&nm.jtj, &nm.jtr, lambda, free) else { break };
        let mut q = *p;
        for i in 0..5 {
            q[i] += step[i];
        }
        let nq = normal(ctx, b, &q);
        let better = nq.n + 2 >= nm.n && nq.sse / nq.n.max(1) as f64 <= nm.sse / nm.n.max(1) as f64;
        if better {
            let gain = nm.sse - nq.sse;
            *p = q;
            nm = nq;
            lambda = (lambda * 0.1).max(1e-12);
            if gain.abs() <= 1e-12 * nm.sse.max(1e-300) {
                break;
            }
        } else {
            lambda *= 10.0;
            if lambda > 1e8 {
                break;
            }
        }
    }
    (nm.sse, nm.n)
}

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

/// Compares a profile (heights in metres) with the `design` (heights in metres) along `line`;
/// see the module docs.
///
/// Errors: a line that leaves the design, a featureless profile or design along the line, a
/// multi-level design of which the line crosses fewer than 2 levels (or whose terraces leave
/// fewer than 2 levels with interior points), and, as [`Error::Registration`], an ambiguous or
/// non-matching coarse search.
pub fn compare_profile(
    profile: &Profile,
    design: &Grid,
    line: &LineSpec,
    opts: &ProfileOptions,
) -> Result<ProfileComparison> {
    if design.unit() != Unit::Metre {
        return Err(Error::param(
            "design",
            format!("must hold heights in metres, not '{}'", design.unit().symbol()),
        ));
    }
    line.check()?;
    let mut warnings = Vec::new();
    let length = profile.length();
    let (start, dir) = line.frame(length);
    let nrm = [-dir[1], dir[0]];
    warnings.extend(line_length_warning(line, length));
    let pts = fit_points(profile, opts.max_points)?;
    let u_mean = pts.iter().map(|p| p.0).sum::<f64>() / pts.len() as f64;
    let pd = design.pitch();
    let pmax = pd[0].max(pd[1]);
    let along = opts.along_search.max(0.0);
    let across = opts.across_search.max(0.0);
    let sigma_max = 3.0 * pmax;
    let index = DesignIndex::new(design);
    // Crop of the design around the line (all shifts and offsets searched, plus the blur's reach).
    let reach = [-along, length + along, -across, across];
    let (crop, crop_centre) = index.crop_around_line(start, dir, reach, 4.0 * sigma_max + 3.0 * pmax)?;
    let ctx = Ctx { crop: &crop, crop_centre, pts: &pts, u_mean, start, dir, nrm };
    let sharp = ctx.blurred(0.0)?;
    if index.levels.is_some() {
        index.check_levels_on_line(&ctx)?;
    } else {
        warnings.push(format!(
            "the design has more than {MAX_LEVELS} distinct heights: no per-level step heights (compare with \
             the design quantized as a recipe makes it)"
        ));
    }
    let variance = profile_variance(&pts)?;
    // 1. Coarse search.
    let ds = 0.5 * pd[0].min(pd[1]);
    let ns = (along / ds).ceil() as i64;
    let coarse = coarse_search(&ctx, &sharp, ds, ns, (across / ds).ceil() as i64);
    if coarse.design_flat || coarse.peak <= 0.0 {
        return Err(Error::Data(
            "the design is flat along the line (or the line leaves the design): nothing to register".into(),
        ));
    }
    let CoarseMatch { peak, along: is0, across: iv0, sign, .. } = coarse;
    let peak_ratio = second_peak(&coarse.row, (is0 + ns) as usize) / peak;
    if peak < opts.min_correlation {
        return Err(Error::registration(
            Refusal::NoMatch,
            format!(
            "the profile does not match the design along the line: best correlation {peak:.3} (below {:.2}) \
             within +-{:.1} um along and +-{:.1} um across",
            opts.min_correlation,
            along * 1e6,
            across * 1e6
        ),
        ));
    }
    if peak_ratio > opts.max_peak_ratio {
        return Err(Error::registration(Refusal::Ambiguous, format!(
            "the shift along the line is ambiguous: a second correlation peak reaches {:.3} of the first within \
             +-{:.1} um (the design repeats along the line); narrow the search (`along_search`) or choose another line",
            peak_ratio,
            along * 1e6
        )));
    }
    let (s0, v0) = (is0 as f64 * ds, iv0 as f64 * ds);
    let p = linear_start(&ctx, &sharp, [s0, v0, sign, 0.0, 0.0]);
    // Observability of the across-line offset.
    let nm = normal(&ctx, &sharp, &p);
    let across_fixed = nm.col2[1] < 0.02 * 0.02 * nm.col2[0];
    let free: Vec<usize> = if across_fixed { vec![0, 2, 3, 4] } else { vec![0, 1, 2, 3, 4] };
    if across_fixed {
        warnings.push(format!(
            "the design hardly varies across the line here: the across-line offset is unobservable and held at \
             {:.2} um",
            v0 * 1e6
        ));
    }
    // 2. Golden-section search of SSE(sigma), the geometry refined at each blur.
    let eval = |sigma: f64, p: &mut [f64; 5]| -> Result<(f64, usize)> {
        let b = ctx.blurred(sigma)?;
        Ok(refine(&ctx, &b, p, &free))
    };
    let mut p_best = p;
    eval(0.0, &mut p_best)?;
    let (sigma, mut p) = golden_section(sigma_max, 0.01 * pmax, p_best, |s, q| Ok(eval(s, q)?.0))?;
    let (sse, n) = eval(sigma, &mut p)?;
    if n < 10 {
        return Err(Error::Data(format!("only {n} profile points fall on the design once registered")));
    }
    // 3. Uncertainty.
    let blurred = ctx.blurred(sigma)?;
    let h = 0.05 * pmax;
    let sse_at = |s: f64| -> Result<f64> {
        let mut q = p;
        Ok(eval(s, &mut q)?.0)
    };
    let np = free.len() + 1;
    let s2 = sse / (n as f64 - np as f64).max(1.0);
    let profile_blur_sigma = profile_likelihood_sigma(sse_at, sigma, h, sse, s2)?;
    // Jacobian with the blur column (central differences) where sigma allows it.
    let (errors, blur_sigma) = covariance(&ctx, &blurred, &p, &free, sigma, h, s2, profile_blur_sigma)?;
    let blur_resolved = blur_sigma < 0.25 * sigma;
    let across = (!across_fixed).then_some((p[1], errors[1]));
    warnings.extend(fit_warnings(sigma, blur_sigma, blur_resolved, sigma_max, pmax, across));
    // Fit table and correlation.
    let fit = fit_table(&ctx, &blurred, &p, profile.x()[0]);
    let correlation = fit_correlation(&fit);
    if correlation.is_nan() || correlation < opts.min_correlation {
        return Err(Error::registration(Refusal::NoMatch, format!(
            "the profile does not match the design along the line: the fitted model correlates by {correlation:.3} \
             (below {:.2}), residual {:.1} nm RMS",
            opts.min_correlation,
            (sse / n as f64).sqrt() * 1e9
        )));
    }
    let noise_ceiling = noise_ceiling(noise_estimate(profile), variance);
    check_trust("the profile's fit along the line", correlation, noise_ceiling, opts.min_correlation_ratio)?;
    // Per-level step heights.
    let levels = match &index.levels {
        None => None,
        Some(dl) => {
            let r = 2.0 * sigma + 1.5 * pmax;
            let heights = index.interior_heights(&ctx, &p, r);
            Some(step_heights(dl, &heights, r)?)
        }
    };
    Ok(ProfileComparison {
        line: *line,
        line_start: start,
        line_direction: dir,
        along_shift: p[0],
        along_shift_sigma: errors[0],
        across_offset: p[1],
        across_offset_sigma: if across_fixed { f64::NAN } else { errors[1] },
        across_fixed,
        depth_scale: p[2].abs(),
        depth_scale_sigma: errors[2],
        complement: p[2] < 0.0,
        offset: p[3],
        offset_sigma: errors[3],
        tilt: p[4],
        tilt_sigma: errors[4],
        blur: sigma,
        blur_sigma,
        blur_resolved,
        blur_search_max: sigma_max,
        rms_residual: (sse / n as f64).sqrt(),
        points: n,
        correlation,
        noise_ceiling,
        peak_ratio,
        levels,
        warnings,
        fit,
    })
}

/// The warning when a line given by two points is not as long as the profile (by more than
/// 5 %): the profile is placed from the line's first point.
fn line_length_warning(line: &LineSpec, length: f64) -> Option<String> {
    let LineSpec::Points { start: s, end: e } = line else { return None };
    let l = (e[0] - s[0]).hypot(e[1] - s[1]);
    ((l - length).abs() > 0.05 * length.max(l)).then(|| {
        format!(
            "the line is {:.1} um long but the profile {:.1} um: the profile is placed from the line's first point",
            l * 1e6,
            length * 1e6
        )
    })
}

/// The profile's measured points `(u, z)` for the fit, thinned by a stride to at most
/// `max_points`; fewer than 10 are refused.
fn fit_points(profile: &Profile, max_points: usize) -> Result<Vec<(f64, f64)>> {
    let all = profile.points();
    let stride = all.len().div_ceil(max_points.max(1)).max(1);
    let pts: Vec<(f64, f64)> = all.iter().step_by(stride).copied().collect();
    if pts.len() < 10 {
        return Err(Error::Data(format!(
            "the profile has {} measured points: too few to compare",
            pts.len()
        )));
    }
    Ok(pts)
}

/// The design's distinct heights, sorted, over its valid samples; `None` when there are more
/// than [`MAX_LEVELS`] (not a multi-level design).
fn distinct_levels(design: &Grid) -> Option<Vec<f64>> {
    let nc = design.dim().1;
    let mut v: Vec<f64> = Vec::new();
    for (k, &h) in design.values().iter().enumerate() {
        let (i, j) = (k / nc, k % nc);
        if design.is_valid(i, j) && !v.contains(&h) {
            v.push(h);
            if v.len() > MAX_LEVELS {
                break;
            }
        }
    }
    (v.len() <= MAX_LEVELS).then(|| {
        v.sort_unstable_by(f64::total_cmp);
        v
    })
}

/// The design with its sample index of a position (metres from its centre: fractional index
/// `x / pitch + (n - 1) / 2` along each axis) and its levels ([`distinct_levels`]).
struct DesignIndex<'a> {
    design: &'a Grid,
    /// `(n - 1) / 2` along x (columns) and y (rows).
    half: [f64; 2],
    levels: Option<Vec<f64>>,
}

impl<'a> DesignIndex<'a> {
    fn new(design: &'a Grid) -> Self {
        let (nr, nc) = design.dim();
        let half = [(nc as f64 - 1.0) * 0.5, (nr as f64 - 1.0) * 0.5];
        DesignIndex { design, half, levels: distinct_levels(design) }
    }

    /// The crop of the design holding the line from `start` along `dir` over `u` in
    /// `reach[0]..reach[1]` and offsets across it in `reach[2]..reach[3]`, with `margin` metres
    /// around, and the position of the crop's centre; a line outside the design is refused.
    fn crop_around_line(
        &self,
        start: [f64; 2],
        dir: [f64; 2],
        reach: [f64; 4],
        margin: f64,
    ) -> Result<(Grid, [f64; 2])> {
        let (design, half) = (self.design, self.half);
        let pd = design.pitch();
        let nrm = [-dir[1], dir[0]];
        let (nr, nc) = design.dim();
        let mut lo = [f64::INFINITY; 2];
        let mut hi = [f64::NEG_INFINITY; 2];
        for u in [reach[0], reach[1]] {
            for v in [reach[2], reach[3]] {
                let p = [start[0] + u * dir[0] + v * nrm[0], start[1] + u * dir[1] + v * nrm[1]];
                for a in 0..2 {
                    lo[a] = lo[a].min(p[a] - margin);
                    hi[a] = hi[a].max(p[a] + margin);
                }
            }
        }
        let idx = |x: f64, a: usize| x / pd[a] + half[a];
        let c0 = idx(lo[0], 0).floor().max(0.0) as usize;
        let c1 = (idx(hi[0], 0).ceil().max(0.0) as usize + 1).min(nc);
        let r0 = idx(lo[1], 1).floor().max(0.0) as usize;
        let r1 = (idx(hi[1], 1).ceil().max(0.0) as usize + 1).min(nr);
        if c0 + 4 > c1 || r0 + 4 > r1 {
            return Err(Error::Data(format!(
                "the line from ({:.1}, {:.1}) um along ({:.3}, {:.3}) lies outside the {:.1} x {:.1} um design",
                start[0] * 1e6,
                start[1] * 1e6,
                dir[0],
                dir[1],
                design.extent()[0] * 1e6,
                design.extent()[1] * 1e6
            )));
        }
        let crop = design.crop(r0..r1, c0..c1)?;
        let crop_centre =
            [((c0 + c1 - 1) as f64 * 0.5 - half[0]) * pd[0], ((r0 + r1 - 1) as f64 * 0.5 - half[1]) * pd[1]];
        Ok((crop, crop_centre))
    }

    /// The level of the design sample nearest to `p` (metres from the centre); `None` off the
    /// design, on an invalid sample, or for a design that is not multi-level.
    fn level_at(&self, p: [f64; 2]) -> Option<usize> {
        let levels = self.levels.as_ref()?;
        let (design, half, pd) = (self.design, self.half, self.design.pitch());
        let (nr, nc) = design.dim();
        let j = (p[0] / pd[0] + half[0]).round();
        let i = (p[1] / pd[1] + half[1]).round();
        if i < 0.0 || j < 0.0 || i >= nr as f64 || j >= nc as f64 || !design.is_valid(i as usize, j as usize)
        {
            return None;
        }
        let h = design.values()[[i as usize, j as usize]];
        levels.iter().position(|l| *l == h)
    }

    /// Refuses a line (at zero shift and offset) that crosses fewer than 2 of the levels.
    fn check_levels_on_line(&self, ctx: &Ctx) -> Result<()> {
        let mut seen: Vec<usize> =
            ctx.pts.iter().filter_map(|&(u, _)| self.level_at(ctx.pos(u, 0.0, 0.0))).collect();
        seen.sort_unstable();
        seen.dedup();
        if seen.len() < 2 {
            return Err(Error::Data(format!(
                "the line crosses {} level(s) of the design ({}): step heights need at least 2; choose a line \
                 across the structure",
                seen.len(),
                seen.iter().map(|l| l.to_string()).collect::<Vec<_>>().join(", ")
            )));
        }
        Ok(())
    }

    /// The level of `q` when every design sample within `r` of it is on that level (the
    /// terrace interior of the module docs), else `None`.
    fn interior(&self, q: [f64; 2], r: f64) -> Option<usize> {
        let (design, half, pd) = (self.design, self.half, self.design.pitch());
        let (nr, nc) = design.dim();
        let dl = self.levels.as_ref()?;
        let l = self.level_at(q)?;
        let (fi, fj) = (q[1] / pd[1] + half[1], q[0] / pd[0] + half[0]);
        let (ri, rj) = ((r / pd[1]).ceil() as i64, (r / pd[0]).ceil() as i64);
        for di in -ri..=ri {
            for dj in -rj..=rj {
                let (i, j) = (fi.round() as i64 + di, fj.round() as i64 + dj);
                let dx = (j as f64 - fj) * pd[0];
                let dy = (i as f64 - fi) * pd[1];
                if dx * dx + dy * dy > r * r {
                    continue;
                }
                if i < 0
                    || j < 0
                    || i >= nr as i64
                    || j >= nc as i64
                    || !design.is_valid(i as usize, j as usize)
                {
                    return None;
                }
                if design.values()[[i as usize, j as usize]] != dl[l] {
                    return None;
                }
            }
        }
        Some(l)
    }

    /// Per level, the measured heights `y_k = sign(a) (z_k - b - c (u_k - u_mean))` of the
    /// points at their registered positions (parameters `p`) inside its terraces ([`Self::interior`]).
    fn interior_heights(&self, ctx: &Ctx, p: &[f64; 5], r: f64) -> Vec<Vec<f64>> {
        let count = self.levels.as_ref().map_or(0, Vec::len);
        let sgn = p[2].signum();
        let mut heights: Vec<Vec<f64>> = vec![Vec::new(); count];
        for &(u, z) in ctx.pts {
            if let Some(l) = self.interior(ctx.pos(u, p[0], p[1]), r) {
                heights[l].push(sgn * (z - p[3] - p[4] * (u - ctx.u_mean)));
            }
        }
        heights
    }
}

/// The variance of the profile's points about their least-squares line; a profile whose
/// neighbour differences are as large as white noise's (`sqrt 2` times its RMS, here over
/// `0.8 sqrt 2`) is refused as featureless.
fn profile_variance(pts: &[(f64, f64)]) -> Result<f64> {
    let zs: Vec<f64> = pts.iter().map(|p| p.1).collect();
    let us: Vec<f64> = pts.iter().map(|p| p.0).collect();
    let (o, t, _) = fit_line(pts, |_| true)?;
    let r: Vec<f64> = us.iter().zip(&zs).map(|(u, z)| z - o - t * u).collect();
    let sd = (r.iter().map(|v| v * v).sum::<f64>() / r.len() as f64).sqrt();
    let dd: Vec<f64> = r.windows(2).map(|w| w[1] - w[0]).collect();
    let sdd = (dd.iter().map(|v| v * v).sum::<f64>() / dd.len() as f64).sqrt();
    if sd.is_nan() || sd <= 0.0 || sdd > 0.8 * std::f64::consts::SQRT_2 * sd {
        return Err(Error::Data(format!(
            "the profile is featureless: {:.3} nm RMS about its line, with neighbour differences of {:.3} nm RMS \
             (white noise has sqrt 2 times its RMS)",
            sd * 1e9,
            sdd * 1e9
        )));
    }
    Ok(sd * sd)
}

/// The best match of the coarse search (module docs, step 1), in steps of `ds`.
struct CoarseMatch {
    /// The largest `|r|`, at `along` steps along and `across` steps across; the sign of `r`.
    peak: f64,
    along: i64,
    across: i64,
    sign: f64,
    /// `|r|` along the line (shifts `-ns..=ns`) at the winning offset.
    row: Vec<f64>,
    /// No shift and offset gave a correlation: the design is flat along the line.
    design_flat: bool,
}

/// The coarse search: the detrended correlation ([`detrended_correlation`]) of the profile
/// (at most 4000 points, by a stride) with the sharp design along the line, for shifts
/// `is ds` (`|is| <= ns`) and offsets `iv ds` (`|iv| <= nv`, the smallest offsets first: a tie
/// goes to them); positions where less than half the points fall on the design score 0.
fn coarse_search(ctx: &Ctx, sharp: &Blurred, ds: f64, ns: i64, nv: i64) -> CoarseMatch {
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

/// The starting parameters: `p` (the coarse shift, offset and sign) with `a, b, c` moved to
/// their linear least-squares values on the sharp design (one undamped Gauss-Newton step over
/// them alone, exact for a model linear in them).
fn linear_start(ctx: &Ctx, sharp: &Blurred, mut p: [f64; 5]) -> [f64; 5] {
    let nm = normal(ctx, sharp, &p);
    if let Some(x) = damped_solve(&nm.jtj, &nm.jtr, 0.0, &[2, 3, 4]) {
        for i in 2..5 {
            p[i] += x[i];
        }
    }
    p
}

/// Golden-section search of `f` over `[0, hi]` to a bracket narrower than `tol`: the bracket's
/// centre and the parameters of its better end. `f(x, p)` refines the parameters `p` it is
/// given (each new point starts from its neighbour's) and returns the value to minimise.
fn golden_section(
    hi: f64,
    tol: f64,
    start: [f64; 5],
    mut f: impl FnMut(f64, &mut [f64; 5]) -> Result<f64>,
) -> Result<(f64, [f64; 5])> {
    let g = 0.5 * (5f64.sqrt() - 1.0);
    let (mut a, mut bnd) = (0.0, hi);
    let mut x1 = bnd - g * (bnd - a);
    let mut x2 = a + g * (bnd - a);
    let (mut p1, mut p2) = (start, start);
    let mut f1 = f(x1, &mut p1)?;
    let mut f2 = f(x2, &mut p2)?;
    while bnd - a > tol {
        if f1 <= f2 {
            bnd = x2;
            x2 = x1;
            f2 = f1;
            p2 = p1;
            x1 = bnd - g * (bnd - a);
            p1 = p2;
            f1 = f(x1, &mut p1)?;
        } else {
            a = x1;
            x1 = x2;
            f1 = f2;
            p1 = p2;
            x2 = a + g * (bnd - a);
            p2 = p1;
            f2 = f(x2, &mut p2)?;
        }
    }
    Ok((0.5 * (a + bnd), if f1 <= f2 { p1 } else { p2 }))
}

/// The blur's standard error from the profile likelihood, `sqrt(2 s2 / SSE''(sigma))`, with
/// `SSE''` by central differences of step `h` (forward ones where `sigma <= h`) of `sse_at`,
/// `sse` its value at `sigma`; infinite where `SSE''` is not positive.
fn profile_likelihood_sigma(
    sse_at: impl Fn(f64) -> Result<f64>,
    sigma: f64,
    h: f64,
    sse: f64,
    s2: f64,
) -> Result<f64> {
    let curv = if sigma > h {
        (sse_at(sigma + h)? - 2.0 * sse + sse_at(sigma - h)?) / (h * h)
    } else {
        (sse_at(sigma + 2.0 * h)? - 2.0 * sse_at(sigma + h)? + sse) / (h * h)
    };
    Ok(if curv > 0.0 { (2.0 * s2 / curv).sqrt() } else { f64::INFINITY })
}

/// The warnings on the fitted blur `sigma` (its standard error `blur_sigma`, whether that
/// resolves it, the search's end `sigma_max`, the design's pitch `pmax`) and, when observable,
/// on the across-line offset and its standard error.
fn fit_warnings(
    sigma: f64,
    blur_sigma: f64,
    blur_resolved: bool,
    sigma_max: f64,
    pmax: f64,
    across: Option<(f64, f64)>,
) -> Vec<String> {
    let mut warnings = Vec::new();
    if !blur_resolved {
        let err = if blur_sigma < sigma_max {
            format!("+- {:.2} um", blur_sigma * 1e6)
        } else {
            format!("with a standard error beyond the {:.2} um search range", sigma_max * 1e6)
        };
        warnings.push(format!(
            "the lateral blur is not resolved: {:.2} um {err} against the design's {:.2} um pitch",
            sigma * 1e6,
            pmax * 1e6
        ));
    }
    if sigma >= 0.98 * sigma_max {
        warnings.push(format!(
            "the fitted blur sits at the end of its search range ({:.2} um): the part is blurred more than the model \
             can follow, or does not match the design along the line",
            sigma_max * 1e6
        ));
    }
    if let Some((v, error)) = across.filter(|a| a.1 > pmax) {
        warnings.push(format!(
            "the across-line offset is poorly determined: {:.2} +- {:.2} um",
            v * 1e6,
            error * 1e6
        ));
    }
    warnings
}

/// The fit table: per point on the blurred design at its registered position (parameters
/// `p`), the position as in the file (`u + x0`), the measured height and the model's.
fn fit_table(ctx: &Ctx, blurred: &Blurred, p: &[f64; 5], x0: f64) -> Vec<[f64; 3]> {
    let mut fit = Vec::with_capacity(ctx.pts.len());
    for &(u, z) in ctx.pts {
        if let Some((hh, _, _)) = blurred.at(ctx.pos(u, p[0], p[1])) {
            fit.push([u + x0, z, p[2] * hh + p[3] + p[4] * (u - ctx.u_mean)]);
        }
    }
    fit
}

/// The correlation of the measured and the model heights of the fit table, each with its
/// least-squares line in the position removed ([`detrended_correlation`]).
fn fit_correlation(fit: &[[f64; 3]]) -> f64 {
    let u: Vec<f64> = fit.iter().map(|f| f[0]).collect();
    let zz: Vec<f64> = fit.iter().map(|f| f[1]).collect();
    let mm: Vec<f64> = fit.iter().map(|f| f[2]).collect();
    detrended_correlation(&u, &zz, &mm)
}

/// The step heights of the module docs from each level's interior heights `heights[l]`
/// (`dl` the design's levels, `r` the interior radius): levels with at least 3 points, steps
/// against the lowest of them; fewer than two such levels are refused.
fn step_heights(dl: &[f64], heights: &[Vec<f64>], r: f64) -> Result<LevelSteps> {
    let mut acc: Vec<(f64, f64, usize)> = vec![(0.0, 0.0, 0); dl.len()];
    for (l, hs) in heights.iter().enumerate() {
        if !hs.is_empty() {
            let m = hs.iter().sum::<f64>() / hs.len() as f64;
            let sd =
                (hs.iter().map(|v| (v - m).powi(2)).sum::<f64>() / (hs.len() as f64 - 1.0).max(1.0)).sqrt();
            acc[l] = (m, sd, hs.len());
        }
    }
    let present: Vec<usize> = (0..dl.len()).filter(|&l| acc[l].2 >= 3).collect();
    if present.len() < 2 {
        return Err(Error::Data(format!(
            "the line holds terrace interiors (points {:.1} um or more from any other level) of {} level(s): \
             step heights need at least 2",
            r * 1e6,
            present.len()
        )));
    }
    let l0 = present[0];
    let (m0, sd0, n0) = acc[l0];
    let se0 = sd0 * sd0 / n0 as f64;
    let steps = present
        .iter()
        .map(|&l| {
            let (m, sd, n) = acc[l];
            let design_step = dl[l] - dl[l0];
            let (sh, shs, ds, dss) = if l == l0 {
                (None, None, None, None)
            } else {
                let hgt = m - m0;
                let se = (sd * sd / n as f64 + se0).sqrt();
                (Some(hgt), Some(se), Some(hgt / design_step), Some(se / design_step.abs()))
            };
            LevelStep {
                level: l,
                design_step,
                points: n,
                mean: m,
                std: sd,
                step_height: sh,
                step_height_sigma: shs,
                depth_scale: ds,
                depth_scale_sigma: dss,
            }
        })
        .collect();
    Ok(LevelSteps { design_levels: dl.to_vec(), reference_level: l0, interior_radius: r, levels: steps })
}

/// The second-highest local maximum of `row` outside the main lobe around `k0` (where the
/// score first falls below half the peak on each side); 0 when there is none.
fn second_peak(row: &[f64], k0: usize) -> f64 {
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

/// Standard errors of `(s, v, a, b, c)` and of the blur: `s2 (J^T J)^-1` with the blur's
/// column by central differences; at fixed blur (and the blur's from the profile likelihood)
/// where that column is not determined.
#[allow(clippy::too_many_arguments)]
fn covariance(
    ctx: &Ctx,
    b: &Blurred,
    p: &[f64; 5],
    free: &[usize],
    sigma: f64,
    h: f64,
    s2: f64,
    profile_blur_sigma: f64,
) -> Result<([f64; 5], f64)> {
    let with_blur = sigma > 2.0 * h;
    let (bp, bm) =
        if with_blur { (Some(ctx.blurred(sigma + h)?), Some(ctx.blurred(sigma - h)?)) } else { (None, None) };
    let m = free.len() + usize::from(with_blur);
    let mut jtj = vec![0.0; m * m];
    for &(u, _) in ctx.pts {
        let q = ctx.pos(u, p[0], p[1]);
        let Some((hh, hx, hy)) = b.at(q) else { continue };
        let full = [
            p[2] * (hx * ctx.dir[0] + hy * ctx.dir[1]),
            p[2] * (hx * ctx.nrm[0] + hy * ctx.nrm[1]),
            hh,
            1.0,
            u - ctx.u_mean,
        ];
        let mut j: Vec<f64> = free.iter().map(|&i| full[i]).collect();
        if let (Some(bp), Some(bm)) = (&bp, &bm) {
            match (bp.at(q), bm.at(q)) {
                (Some(a), Some(c)) => j.push(p[2] * (a.0 - c.0) / (2.0 * h)),
                _ => continue,
            }
        }
        for x in 0..m {
            for y in 0..m {
                jtj[x * m + y] += j[x] * j[y];
            }
        }
    }
    // Inverse by columns, on the matrix scaled to unit diagonal.
    let d: Vec<f64> = (0..m).map(|k| jtj[k * m + k].sqrt()).collect();
    if d.iter().any(|v| !(v.is_finite() && *v > 0.0)) {
        return Err(Error::Data("the fit is singular: a parameter has no effect on the profile".into()));
    }
    let scaled: Vec<f64> = (0..m * m).map(|k| jtj[k] / (d[k / m] * d[k % m])).collect();
    let mut diag = vec![0.0; m];
    let mut singular = false;
    for k in 0..m {
        let mut e = vec![0.0; m];
        e[k] = 1.0;
        match crate::linalg::solve(scaled.clone(), e, m) {
            Ok(x) => diag[k] = x[k] / (d[k] * d[k]),
            Err(_) => singular = true,
        }
    }
    if singular && with_blur {
        // The blur's column is degenerate with the others: errors at fixed blur.
        let (e, _) = covariance(ctx, b, p, free, 0.0, h, s2, profile_blur_sigma)?;
        return Ok((e, profile_blur_sigma));
    }
    if singular {
        return Err(Error::Data(
            "the fit is singular: the parameters are not determined by the profile".into(),
        ));
    }
    let mut errors = [0.0; 5];
    for (k, &i) in free.iter().enumerate() {
        errors[i] = (s2 * diag[k]).sqrt();
    }
    let blur_sigma = if with_blur { (s2 * diag[m - 1]).sqrt() } else { profile_blur_sigma };
    Ok((errors, blur_sigma))
}

/// What [`simulate_profile`] makes: a profile of the design along a line with a known model.
#[derive(Debug, Clone, Serialize)]
pub struct SimulateProfile {
    pub line: LineSpec,
    /// Profile length and sampling step, metres.
    pub length: f64,
    pub step: f64,
    /// First position written (the instrument's own origin), metres.
    pub x_origin: f64,
    pub along_shift: f64,
    pub across_offset: f64,
    /// Signed depth scale `a` (negative: complement), offset `b` at the profile's middle, tilt `c`.
    pub depth_scale: f64,
    pub offset: f64,
    pub tilt: f64,
    /// Gaussian lateral blur, metres.
    pub blur: f64,
    /// White Gaussian noise, metres.
    pub noise: f64,
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
mod tests {
    use ndarray::Array2;

    use super::*;

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

    fn sim(design: &Grid, a: f64, s: f64, v: f64, seed: u64) -> (SimulateProfile, Profile) {
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

    #[test]
    fn a_simulated_staircase_profile_is_recovered() {
        let d = staircase();
        let (sp, prof) = sim(&d, 0.9, 3.3e-6, 4.1e-6, 3);
        let c = compare_profile(&prof, &d, &sp.line, &ProfileOptions::default()).unwrap();
        let within = |name: &str, got: f64, want: f64, sig: f64, tol: f64| {
            assert!(
                (got - want).abs() <= 4.0 * sig && (got - want).abs() <= tol,
                "{name}: {got} vs {want} (sigma {sig}, tol {tol}); {c:#?}"
            );
        };
        within("along", c.along_shift, 3.3e-6, c.along_shift_sigma, 0.1e-6);
        within("across", c.across_offset, 4.1e-6, c.across_offset_sigma, 0.3e-6);
        within("depth", c.depth_scale, 0.9, c.depth_scale_sigma, 0.009);
        within("blur", c.blur, 2e-6, c.blur_sigma, 0.2e-6);
        within("tilt", c.tilt, 2e-4, c.tilt_sigma, 1e-5);
        within("offset", c.offset, 40e-9, c.offset_sigma, 2e-9);
        assert!(!c.complement && !c.across_fixed);
        eprintln!(
            "staircase: along {:.4} +- {:.4} um, across {:.4} +- {:.4} um, depth {:.5} +- {:.5}, blur {:.4} +- {:.4} um, \
             tilt {:.3e} +- {:.1e}, offset {:.3} +- {:.3} nm, rms {:.3} nm",
            c.along_shift * 1e6, c.along_shift_sigma * 1e6, c.across_offset * 1e6, c.across_offset_sigma * 1e6,
            c.depth_scale, c.depth_scale_sigma, c.blur * 1e6, c.blur_sigma * 1e6, c.tilt, c.tilt_sigma,
            c.offset * 1e9, c.offset_sigma * 1e9, c.rms_residual * 1e9
        );
        for s in &c.levels.as_ref().unwrap().levels {
            eprintln!(
                "  level {} ({} pts): step {:?} +- {:?}, ratio {:?} +- {:?}",
                s.level, s.points, s.step_height, s.step_height_sigma, s.depth_scale, s.depth_scale_sigma
            );
        }
        let l = c.levels.as_ref().unwrap();
        assert_eq!(l.levels.len(), 4, "{l:#?}");
        for s in &l.levels[1..] {
            let ds = s.depth_scale.unwrap();
            assert!(
                (ds - 0.9).abs() < 0.01 && (ds - 0.9).abs() < 5.0 * s.depth_scale_sigma.unwrap(),
                "{s:?}"
            );
        }
        assert!((c.rms_residual - 5e-9).abs() < 0.5e-9, "{}", c.rms_residual);
    }

    #[test]
    fn the_complement_is_detected_and_one_level_lines_refused() {
        let d = staircase();
        let (sp, prof) = sim(&d, -0.9, -2.0e-6, 1.0e-6, 5);
        let c = compare_profile(&prof, &d, &sp.line, &ProfileOptions::default()).unwrap();
        assert!(c.complement && (c.depth_scale - 0.9).abs() < 0.01, "{c:#?}");
        let l = c.levels.as_ref().unwrap();
        assert!(l.levels[1..].iter().all(|s| (s.depth_scale.unwrap() - 0.9).abs() < 0.01), "{l:#?}");
        // A line along y inside one terrace column crosses one level only.
        let line = LineSpec::Points { start: [-21e-6, -100e-6], end: [-21e-6, 100e-6] };
        let flat = Grid::new(
            Array2::from_shape_fn((300, 300), |(_, j)| if j < 150 { 0.0 } else { 1e-7 }),
            [2e-6; 2],
            Unit::Metre,
        )
        .unwrap();
        let sp1 = SimulateProfile { line, length: 200e-6, ..sp.clone() };
        let p1 = simulate_profile(&flat, &sp1).unwrap();
        let e = compare_profile(&p1, &flat, &line, &ProfileOptions::default()).unwrap_err().to_string();
        assert!(e.contains("crosses 1 level"), "{e}");
    }

    /// A part with one level made 180 nm too high (above the next) correlates below 0.95 with
    /// the design along the line: above the absolute floor of 0.8, below 95% of what its 5 nm
    /// of noise allow: not trusted, the rule of every registration ([`check_trust`]).
    #[test]
    fn a_profile_fitting_worse_than_its_noise_allows_is_not_trusted() {
        let d = staircase();
        let wrong = d.values().mapv(|h| if (h - 200e-9).abs() < 1e-12 { 380e-9 } else { h });
        let wrong = d.map_values(wrong, Unit::Metre).unwrap();
        let (sp, prof) = sim(&wrong, 0.9, 3.3e-6, 4.1e-6, 3);
        let e = compare_profile(&prof, &d, &sp.line, &ProfileOptions::default()).unwrap_err();
        assert!(
            matches!(e, Error::Registration { refusal: Refusal::NotTrusted, .. })
                && e.to_string().contains("not trusted"),
            "{e}"
        );
        let lenient = ProfileOptions { min_correlation_ratio: 0.0, ..Default::default() };
        let c = compare_profile(&prof, &d, &sp.line, &lenient).unwrap();
        assert!(c.correlation > 0.8 && c.correlation < 0.95 * c.noise_ceiling, "{c:#?}");
        // The right design passes the same rule.
        let (sp, prof) = sim(&d, 0.9, 3.3e-6, 4.1e-6, 3);
        let c = compare_profile(&prof, &d, &sp.line, &ProfileOptions::default()).unwrap();
        assert!(c.correlation > 0.99 && c.noise_ceiling > 0.99, "{c:#?}");
    }

    #[test]
    fn a_shift_searched_over_a_period_is_ambiguous() {
        // The staircase repeats every 160 um along the line: a +-200 um search sees it twice.
        let d = staircase();
        let (sp, prof) = sim(&d, 0.9, 3.3e-6, 0.0, 7);
        let opts = ProfileOptions { along_search: 200e-6, ..Default::default() };
        let e = compare_profile(&prof, &d, &sp.line, &opts).unwrap_err();
        assert!(
            matches!(e, Error::Registration { refusal: Refusal::Ambiguous, .. })
                && e.to_string().contains("ambiguous"),
            "{e}"
        );
    }

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

    #[test]
    fn line_text_and_featureless_profiles() {
        let close = |text: &str, want: [f64; 4]| {
            let LineSpec::Points { start, end } = LineSpec::parse_points(text).unwrap() else { panic!() };
            let got = [start[0], start[1], end[0], end[1]];
            assert!(got.iter().zip(&want).all(|(g, w)| (g - w).abs() < 1e-15), "{text}: {got:?}");
        };
        close("-1mm, 0, 1mm, 20um", [-1e-3, 0.0, 1e-3, 20e-6]);
        close("-100,0,100,5um", [-100e-6, 0.0, 100e-6, 5e-6]);
        assert!(LineSpec::parse_points("1,2,3").is_err());
        assert!(LineSpec::parse_points("0,0,0,0").is_err());
        let d = staircase();
        let mut rng = crate::rng::Lcg(1);
        let x: Vec<f64> = (0..800).map(|k| k as f64 * 0.5e-6).collect();
        let z: Vec<f64> = (0..800).map(|_| 5e-9 * rng.normal()).collect();
        let p = Profile::new(x, z, None).unwrap();
        let e = compare_profile(&p, &d, &LineSpec::Angle { angle: 0.0 }, &ProfileOptions::default())
            .unwrap_err()
            .to_string();
        assert!(e.contains("featureless"), "{e}");
    }

    #[test]
    fn distinct_levels_are_sorted_and_capped() {
        assert_eq!(distinct_levels(&staircase()), Some(vec![0.0, 100e-9, 200e-9, 300e-9]));
        let ramp = |n: usize| {
            Grid::new(Array2::from_shape_fn((1, n), |(_, j)| (n - j) as f64 * 1e-9), [1e-6; 2], Unit::Metre)
                .unwrap()
        };
        let levels = distinct_levels(&ramp(MAX_LEVELS)).unwrap();
        assert_eq!(
            (levels.len(), levels[0], levels[MAX_LEVELS - 1]),
            (MAX_LEVELS, 1e-9, MAX_LEVELS as f64 * 1e-9)
        );
        assert_eq!(distinct_levels(&ramp(MAX_LEVELS + 1)), None);
    }

    /// `H_l = m_l - m_l0 +- sqrt(s_l^2 / n_l + s_l0^2 / n_l0)` on heights whose means and
    /// spreads are known: level 0 (1.0 +- 0.2, 3 points), level 1 too few points, level 2
    /// (3.0, spread sqrt(0.02 / 3), 4 points).
    #[test]
    fn step_heights_follow_the_module_docs() {
        let dl = [0.0, 0.5, 1.0];
        let heights = vec![vec![1.0, 1.2, 0.8], vec![2.0, 2.0], vec![3.0, 3.1, 2.9, 3.0]];
        let s = step_heights(&dl, &heights, 1e-6).unwrap();
        assert_eq!((s.reference_level, s.levels.len(), s.levels[1].level), (0, 2, 2));
        let close = |a: f64, b: f64| (a - b).abs() < 1e-12;
        let (l0, l2) = (&s.levels[0], &s.levels[1]);
        assert!(close(l0.mean, 1.0) && close(l0.std, 0.2) && l0.step_height.is_none(), "{l0:?}");
        let se = (0.04 / 3.0 + 0.02 / 3.0 / 4.0f64).sqrt();
        assert!(close(l2.step_height.unwrap(), 2.0) && close(l2.step_height_sigma.unwrap(), se), "{l2:?}");
        assert!(close(l2.depth_scale.unwrap(), 2.0) && close(l2.depth_scale_sigma.unwrap(), se), "{l2:?}");
        let e = step_heights(&dl, &heights[..2], 1e-6).unwrap_err().to_string();
        assert!(e.contains("of 1 level(s)"), "{e}");
    }

    #[test]
    fn golden_section_finds_a_parabola_minimum_and_keeps_its_parameters() {
        let (x, p) = golden_section(1.0, 1e-7, [0.0; 5], |x, p| {
            p[0] = x;
            Ok((x - 0.37).powi(2))
        })
        .unwrap();
        assert!((x - 0.37).abs() < 1e-7 && (p[0] - x).abs() < 1e-7, "{x} {p:?}");
        // A minimum at the end of the range.
        let (x, _) = golden_section(2.0, 1e-6, [0.0; 5], |x, _| Ok(-x)).unwrap();
        assert!((x - 2.0).abs() < 1e-6, "{x}");
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
        assert!(profile_variance(&noise).unwrap_err().to_string().contains("featureless"));
    }

    #[test]
    fn the_crop_holds_every_searched_position_of_the_line() {
        let d = staircase();
        let index = DesignIndex::new(&d);
        let (start, dir) = LineSpec::Angle { angle: 0.4 }.frame(300e-6);
        let reach = [-20e-6, 320e-6, -10e-6, 10e-6];
        let (crop, centre) = index.crop_around_line(start, dir, reach, 5e-6).unwrap();
        let half = [0.5 * crop.extent()[0], 0.5 * crop.extent()[1]];
        for u in [reach[0], reach[1]] {
            for v in [reach[2], reach[3]] {
                let p = [start[0] + u * dir[0] - v * dir[1], start[1] + u * dir[1] + v * dir[0]];
                for a in 0..2 {
                    assert!(
                        (p[a] - centre[a]).abs() + 5e-6 <= half[a],
                        "{p:?} outside {centre:?} +- {half:?}"
                    );
                }
            }
        }
        let far = index.crop_around_line([1e-3, 1e-3], [1.0, 0.0], reach, 5e-6).unwrap_err().to_string();
        assert!(far.contains("lies outside"), "{far}");
        assert!(line_length_warning(&LineSpec::Angle { angle: 0.0 }, 1e-4).is_none());
        let line = LineSpec::Points { start: [0.0, 0.0], end: [100e-6, 0.0] };
        assert!(line_length_warning(&line, 104e-6).is_none() && line_length_warning(&line, 200e-6).is_some());
    }

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

    /// On `SSE(x) = c (x - x0)^2 + m`, `SSE'' = 2 c` on either difference, so the error is
    /// `sqrt(s2 / c)`; a flat or concave SSE gives an infinite error.
    #[test]
    fn the_profile_likelihood_error_of_a_parabolic_sse() {
        let (c, x0, m, s2) = (4.0e12, 1.1e-6, 3e-15, 2e-17);
        let sse = |x: f64| -> Result<f64> { Ok(c * (x - x0).powi(2) + m) };
        for sigma in [2e-6, 0.05e-6] {
            let got = profile_likelihood_sigma(sse, sigma, 0.1e-6, sse(sigma).unwrap(), s2).unwrap();
            assert!((got / (s2 / c).sqrt() - 1.0).abs() < 1e-6, "{sigma}: {got}");
        }
        let flat = |_: f64| -> Result<f64> { Ok(m) };
        assert_eq!(profile_likelihood_sigma(flat, 2e-6, 0.1e-6, m, s2).unwrap(), f64::INFINITY);
    }
}
