//! Speed against accuracy of the PSF methods on a design at its own geometry (`doefab bench
//! psf`): by default the paper's DOE in the paper's camera (5 mm aperture on 1306^2 samples of
//! 4.29 um, F/7, RGB, a 320^2 crop), or any height map and system file `psf` takes.
//!
//! Each method (matrix DFT in f64 and f32, two-step Fresnel, angular spectrum) runs at `s` =
//! 1, 2, ... sub-samples per pixel and axis (Gauss-Legendre nodes for the matrix DFT; the
//! transfer-function methods sample the pupil and the sensor uniformly at `pitch / s`, the
//! midpoint rule, so `s` is also their pupil grid; each of them at three paddings of its FFT
//! window, 1.25, its own and 3 times the pupil's side), forced past its validity guard so that the
//! error where it refuses is seen; the guard's verdict is recorded with each run. A time budget
//! sets how far each series goes (see [`SweepOptions::budget`]).
//!
//! The error is the worst channel's relative L2 against a reference that is itself checked: the
//! matrix DFT in f64 with Gauss-Legendre pixels at `s_max + 2` and `s_max + 4` sub-samples; the
//! second is the reference, and the difference of the two (reported) bounds how far it is from
//! converged, since Gauss-Legendre converges faster than geometrically on the band-limited
//! intensity. Times are the fastest of up to three wall-clock runs after a warm-up run of the
//! same configuration.
//!
//! The automatic plan ([`crate::optics::plan`]) is placed on the same chart for each tolerance: its
//! run's time and error, whether it meets the tolerance, and its time over that of the cheapest
//! valid run of the sweep that meets it.

use std::time::Instant;

use ndarray::Array2;
use serde::{Deserialize, Serialize};

use crate::error::Result;
use crate::grid::{Grid, Unit};
use crate::material::Material;
use crate::optics::plan::MAX_SIDE;
use crate::optics::propagate::{asm, check, fresnel};
use crate::optics::system::{OpticalSystem, PixelRule};
use crate::optics::{simulate, Method, Options, Precision, Psf};

/// Samples across the small scene's DOE grid.
pub const N: usize = 112;
/// Pitch of the small scene's DOE grid, metres.
pub const PITCH: f64 = 5e-6;

/// The series run, in order: method, precision and, for the FFT methods, the padding (FFT
/// window over the pupil's side; `None` the method's own: 1.5 for the Fresnel method, 2 for the
/// angular spectrum), below and above the method's own.
const CONFIGS: [(Method, Precision, Option<f64>); 8] = [
    (Method::MatrixDft, Precision::F32, None),
    (Method::MatrixDft, Precision::F64, None),
    (Method::Fresnel, Precision::F64, Some(1.25)),
    (Method::Fresnel, Precision::F64, None),
    (Method::Fresnel, Precision::F64, Some(3.0)),
    (Method::AngularSpectrum, Precision::F64, Some(1.25)),
    (Method::AngularSpectrum, Precision::F64, None),
    (Method::AngularSpectrum, Precision::F64, Some(3.0)),
];

/// A series' name: method and precision, and the FFT methods' nominal padding.
fn series_name(method: Method, precision: Precision, padding: Option<f64>) -> String {
    match padding.or(method.default_padding()) {
        Some(p) => format!("{method} {} pad {p}", precision.name()),
        None => format!("{method} {}", precision.name()),
    }
}

/// Timed runs per configuration at most (the fastest counts), after one warm-up run; fewer
/// once a configuration has taken this many seconds.
const REPEATS: usize = 3;
const REPEAT_SECONDS: f64 = 2.0;

/// Seconds of the budget kept for the charts and the JSON (measured: 0.6 s on the paper's
/// design on two cores shared with other builds).
pub const WRITE_SECONDS: f64 = 2.0;

/// The wall time `timed` takes for a configuration whose one run takes `t` seconds: the
/// warm-up and the first timed run, then more while the time spent stays within
/// `REPEAT_SECONDS` (2 s), up to `REPEATS` (3) timed runs.
pub fn timed_wall(t: f64) -> f64 {
    let mut runs = 2;
    while runs < 1 + REPEATS && runs as f64 * t <= REPEAT_SECONDS {
        runs += 1;
    }
    runs as f64 * t
}

/// The cost model the budget is kept with: a run's work in the plan's units (real
/// multiply-adds, [`crate::optics::plan::matrix_dft_cost`] and [`crate::optics::plan::fft_cost`], half for the
/// matrix DFT in f32) over a rate in work per second per method, taken from that method's last
/// run. Before a method has run, its rate is the reference's for the matrix DFT and, for the
/// FFT methods, that of one 2-D FFT of the method's window timed on the spot, a third of it
/// (the FFTs are a third of the FFT methods' time or more: transfer functions, lens phase and
/// pupil field make the rest; measured 0.25-0.5 on the paper's design).
#[derive(Debug, Clone, Default)]
pub struct Costs {
    rates: Vec<(Method, f64)>,
}

impl Costs {
    /// The work of one run of `method` in `precision` on `sys` (all its wavelengths).
    pub fn work(method: Method, precision: Precision, sys: &OpticalSystem, doe: &Grid) -> f64 {
        let wavelengths = sys.wavelengths.len() as f64;
        let one = match method {
            Method::MatrixDft => {
                let half = if precision == Precision::F32 { 0.5 } else { 1.0 };
                half * crate::optics::plan::matrix_dft_cost(
                    crate::optics::propagate::matrix_dft::pupil_grid(sys, doe).0,
                    sys.samples(),
                )
            }
            Method::Fresnel => crate::optics::plan::fft_cost(fresnel::grid(sys).2),
            _ => crate::optics::plan::fft_cost(asm::grid(sys).2),
        };
        one * wavelengths
    }

    /// Records that `work` of `method` took `seconds`.
    pub fn observe(&mut self, method: Method, work: f64, seconds: f64) {
        let rate = work / seconds.max(1e-9);
        match self.rates.iter_mut().find(|r| r.0 == method) {
            Some(r) => r.1 = rate,
            None => self.rates.push((method, rate)),
        }
    }

    /// The predicted seconds of one run of `method` in `precision` on `sys`.
    pub fn seconds(&mut self, method: Method, precision: Precision, sys: &OpticalSystem, doe: &Grid) -> f64 {
        let work = Costs::work(method, precision, sys, doe);
        let rate = match self.rates.iter().find(|r| r.0 == method) {
            Some(r) => r.1,
            None if method == Method::MatrixDft => return f64::INFINITY,
            None => {
                let w = if method == Method::Fresnel { fresnel::grid(sys).2 } else { asm::grid(sys).2 };
                let rate = fft_rate(w) / 3.0;
                self.rates.push((method, rate));
                rate
            }
        };
        work / rate
    }
}

/// Work per second of one forward 2-D FFT of `w x w` complex samples (a quarter of
/// [`crate::optics::plan::fft_cost`]), timed once.
fn fft_rate(w: usize) -> f64 {
    let plan = crate::fft::Plan2d::new(w);
    let mut field = Array2::<rustfft::num_complex::Complex64>::zeros((w, w));
    let t = Instant::now();
    plan.transform(&mut field, false);
    0.25 * crate::optics::plan::fft_cost(w) / t.elapsed().as_secs_f64().max(1e-9)
}

/// What [`run_sweep`] sweeps and how long it may take.
#[derive(Debug, Clone, PartialEq)]
pub struct SweepOptions {
    /// Wall-clock seconds for the whole run, the charts and the JSON included. The reference
    /// runs first, whatever the budget (every error is measured against it); then each plan and
    /// each configuration of the sweep runs only where its predicted time ([`Costs`]) ends within
    /// the budget, less [`WRITE_SECONDS`] for the files: the plans from the whole, the sweep
    /// from equal shares of what the plans leave to its eight series (a series stops at the
    /// first sub-sampling that would end past its share, or whose FFT window exceeds
    /// [`MAX_SIDE`], memory). What is left out is listed in [`PsfSweepResults::skipped`] with why.
    pub budget: f64,
    /// The largest sub-sampling of the sweep (the reference runs at two more and four more).
    pub max_subsample: usize,
    /// Tolerances at which the automatic plan is placed.
    pub tolerances: Vec<f64>,
}

impl Default for SweepOptions {
    fn default() -> SweepOptions {
        SweepOptions { budget: 300.0, max_subsample: 5, tolerances: vec![1e-2, 1e-3, 1e-4] }
    }
}

/// The reference and how far it is from converged.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Reference {
    /// Gauss-Legendre sub-samples of the two runs; the second is the reference.
    pub subsamples: [usize; 2],
    /// Worst channel's relative L2 between the two runs.
    pub difference: f64,
    /// Wall-clock seconds of the reference run (the second), run once.
    pub seconds: f64,
}

/// The automatic plan at one tolerance, run and scored like the sweep.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PlanPoint {
    /// The tolerance the plan is made for: the largest relative L2 error it may give.
    pub tolerance: f64,
    /// The method the plan picked (`matrix_dft`, `fresnel`, `angular_spectrum`, ...).
    pub method: String,
    /// The precision the plan picked (`f32` or `f64`).
    pub precision: String,
    /// Sub-samples per pixel and axis the plan picked.
    pub subsample: usize,
    /// Pupil sample pitch of the plan's system, metres: the matrix DFT's; a transfer-function
    /// method samples at `sensor_pitch / subsample` instead.
    pub pupil_pitch: f64,
    /// The plan's own error estimate.
    pub estimated_error: f64,
    /// Seconds of the plan's run: the fastest of the timed runs.
    pub seconds: f64,
    /// Worst channel's relative L2 against the reference.
    pub error: f64,
    /// `error <= tolerance`.
    pub meets_tolerance: bool,
    /// The fastest valid run of the sweep whose error is within the tolerance, if any.
    pub cheapest_adequate: Option<String>,
    /// `seconds` over that run's.
    pub time_ratio: Option<f64>,
}

/// Everything one `bench psf` run measured.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PsfSweepResults {
    /// Units of the numbers below.
    pub units: String,
    /// DOE samples per side (rows).
    pub doe_samples: usize,
    /// The DOE's pitch along x, metres.
    pub doe_pitch: f64,
    /// The aperture diameter `D`, metres.
    pub aperture: f64,
    /// The working F-number `F# = g / D`.
    pub f_number: f64,
    /// The wavelengths, metres.
    pub wavelengths: Vec<f64>,
    /// Sensor window, pixels per side.
    pub crop: usize,
    /// `BenchOptions::budget`: the wall-clock budget of the whole run, seconds.
    pub budget_seconds: f64,
    /// The reference and how far it is from converged.
    pub reference: Reference,
    /// Every run of the sweep, series by series, sub-sampling by sub-sampling (skipped ones left
    /// out).
    pub points: Vec<PsfSweepPoint>,
    /// One per tolerance whose plan ran, in the order given.
    pub plans: Vec<PlanPoint>,
    /// Plans that miss their tolerance: the plan runs only what its guards accept, so each is a
    /// silent failure.
    pub silent_failures: usize,
    /// Configurations the budget left out.
    pub skipped: Vec<String>,
}

/// One timed run.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PsfSweepPoint {
    /// Method, precision and (FFT methods) padding, as the charts name it.
    pub series: String,
    /// The method (`matrix_dft`, `fresnel`, `angular_spectrum`).
    pub method: String,
    /// The precision (`f32` or `f64`).
    pub precision: String,
    /// FFT window side over the pupil samples' side as run (the nominal padding rounded up to
    /// a fast FFT size; 1 for the matrix DFT, which has none).
    pub padding: f64,
    /// Sub-samples per pixel and axis.
    pub subsample: usize,
    /// Their quadrature rule (`gauss_legendre`, or `midpoint` for the FFT methods, whose
    /// sensor grid is uniform).
    pub pixel_rule: String,
    /// Pupil sample pitch the method used, metres.
    pub pupil_pitch: f64,
    /// Seconds of the run: the fastest of the timed runs after a warm-up.
    pub seconds: f64,
    /// Worst channel's relative L2 against the converged reference.
    pub error: f64,
    /// The validity conditions its guard refuses on, with the wavelength (empty: valid).
    pub violations: Vec<String>,
    /// On the Pareto front of (seconds, error) among the valid runs.
    pub pareto: bool,
}

/// A small scene for quick runs and tests: F/7 at 635 and 450 nm (0.5 mm aperture,
/// g = d_s = 3.5 mm, 3 um pixels, a 40 x 40 crop), for the DOE of [`doe`].
pub fn scene() -> OpticalSystem {
    OpticalSystem {
        aperture: 0.5e-3,
        doe_to_lens: 1e-3,
        focal_length: 3.5e-3,
        lens_to_sensor: 3.5e-3,
        sensor_pitch: 3e-6,
        crop: 40,
        pupil_pitch: PITCH,
        pupil_window: N as f64 * PITCH,
        wavelengths: vec![635e-9, 450e-9],
        ..Default::default()
    }
}

/// The bench DOE: phase `3 (cos(2 pi x / 60 um) + cos(2 pi y / 85 um))` radians at 550 nm in
/// PDMS, as heights.
pub fn doe() -> Result<Grid> {
    let tau = 2.0 * std::f64::consts::PI;
    heights(|x, y| 3.0 * ((tau * x / 60e-6).cos() + (tau * y / 85e-6).cos()))
}

/// The heights on the bench scene's `N x N` grid (centred, pitch `PITCH`) of a DOE whose phase
/// at 550 nm in PDMS is `phase(x, y)` radians: `h = phase / (2 pi (n - 1) / lambda)`.
pub fn heights(phase: impl Fn(f64, f64) -> f64) -> Result<Grid> {
    let l = 550e-9;
    let k = 2.0 * std::f64::consts::PI / l * (Material::pdms().index(l)? - 1.0);
    let c = (N as f64 - 1.0) * 0.5;
    let v = Array2::from_shape_fn((N, N), |(i, j)| phase((j as f64 - c) * PITCH, (i as f64 - c) * PITCH) / k);
    Grid::new(v, [PITCH; 2], Unit::Metre)
}

/// The indices of the points not dominated by another (one at most as slow and at most as
/// wrong, and better in one of the two), in increasing time.
pub fn pareto_front(points: &[(f64, f64)]) -> Vec<usize> {
    let mut front: Vec<usize> = (0..points.len())
        .filter(|&i| {
            let (t, e) = points[i];
            !points.iter().any(|&(u, f)| u <= t && f <= e && (u < t || f < e))
        })
        .collect();
    front.sort_by(|&a, &b| points[a].0.total_cmp(&points[b].0));
    front
}

/// How many times [`run_sweep`] calls its `tick` (for a progress bar): the reference, each
/// plan, each configuration of the sweep (run or skipped).
pub fn steps(opts: &SweepOptions) -> usize {
    1 + opts.tolerances.len() + CONFIGS.len() * opts.max_subsample
}

/// The fastest of up to [`REPEATS`] timed runs of `f` after a warm-up run, and its result.
fn timed<T>(mut f: impl FnMut() -> Result<T>) -> Result<(T, f64)> {
    let run = |f: &mut dyn FnMut() -> Result<T>| -> Result<(T, f64)> {
        let t = Instant::now();
        let out = f()?;
        Ok((out, t.elapsed().as_secs_f64()))
    };
    let (_, warm) = run(&mut f)?;
    let (out, mut best) = run(&mut f)?;
    let mut spent = warm + best;
    for _ in 1..REPEATS {
        if spent > REPEAT_SECONDS {
            break;
        }
        let t = run(&mut f)?.1;
        spent += t;
        best = best.min(t);
    }
    Ok((out, best))
}

/// Worst channel's relative L2 of `psf` against `reference`.
fn worst_error(psf: &Psf, reference: &[Array2<f64>]) -> f64 {
    psf.channels
        .iter()
        .zip(reference)
        .map(|(c, r)| crate::optics::psf::relative_l2(c.grid.values(), r))
        .fold(0.0, f64::max)
}

/// The matrix DFT in f64 with Gauss-Legendre pixels at `s` sub-samples.
fn gauss_legendre_run(system: &OpticalSystem, doe: &Grid, s: usize) -> Result<Psf> {
    let sys = OpticalSystem { subsample: s, pixel_rule: PixelRule::GaussLegendre, ..system.clone() };
    simulate(&sys, doe, Method::MatrixDft, &Options::default())
}

/// Runs the sweep on `doe` in `system` (see the module docs), calling `tick` with a
/// description before each step ([`steps`] in all).
pub fn run_sweep(
    system: &OpticalSystem,
    doe: &Grid,
    opts: &SweepOptions,
    mut tick: impl FnMut(&str),
) -> Result<PsfSweepResults> {
    if opts.max_subsample == 0 || opts.budget.is_nan() || opts.budget <= 0.0 {
        return Err(crate::error::Error::param(
            "bench",
            format!("max_subsample {} and budget {} s must be positive", opts.max_subsample, opts.budget),
        ));
    }
    let start = Instant::now();
    let [sa, sb] = [opts.max_subsample + 2, opts.max_subsample + 4];
    tick(&format!("reference: matrix DFT f64, Gauss-Legendre s = {sa} and {sb}"));
    let first = gauss_legendre_run(system, doe, sa)?;
    let t = Instant::now();
    let second = gauss_legendre_run(system, doe, sb)?;
    let reference_seconds = t.elapsed().as_secs_f64();
    let reference: Vec<Array2<f64>> = second.channels.iter().map(|c| c.grid.values().clone()).collect();
    let reference_check = Reference {
        subsamples: [sa, sb],
        difference: worst_error(&first, &reference),
        seconds: reference_seconds,
    };

    let mut costs = Costs::default();
    let reference_system =
        OpticalSystem { subsample: sb, pixel_rule: PixelRule::GaussLegendre, ..system.clone() };
    costs.observe(
        Method::MatrixDft,
        Costs::work(Method::MatrixDft, Precision::F64, &reference_system, doe),
        reference_seconds,
    );
    // The files' share of the budget.
    let end = opts.budget - WRITE_SECONDS;
    let fits = |predicted: f64, by: f64| {
        let left = by - start.elapsed().as_secs_f64();
        (predicted <= left)
            .then_some(())
            .ok_or(format!("budget: {predicted:.1} s predicted, {:.1} s left", left.max(0.0)))
    };

    let mut plans = Vec::new();
    let mut skipped = Vec::new();
    for &tolerance in &opts.tolerances {
        tick(&format!("automatic plan at tolerance {tolerance:e}"));
        let p = crate::optics::plan::plan(system, doe, &[], tolerance)?;
        let predicted = timed_wall(costs.seconds(p.method, p.precision, &p.system, doe));
        if let Err(why) = fits(predicted, end) {
            skipped.push(format!("plan at {tolerance:e} ({why})"));
            continue;
        }
        let ((psf, _), seconds) = timed(|| crate::optics::plan::run(&p, doe, &[]))?;
        costs.observe(p.method, Costs::work(p.method, p.precision, &p.system, doe), seconds);
        let error = worst_error(&psf, &reference);
        plans.push(PlanPoint {
            tolerance,
            method: p.method.name().into(),
            precision: p.precision.name().into(),
            subsample: p.system.subsample,
            pupil_pitch: p.system.pupil_pitch,
            estimated_error: p.estimate.total,
            seconds,
            error,
            meets_tolerance: error <= tolerance,
            cheapest_adequate: None,
            time_ratio: None,
        });
    }

    let share = (end - start.elapsed().as_secs_f64()).max(0.0) / CONFIGS.len() as f64;
    let mut points = Vec::new();
    for (k, (method, precision, padding)) in CONFIGS.into_iter().enumerate() {
        let series_end = end - share * (CONFIGS.len() - 1 - k) as f64;
        for s in 1..=opts.max_subsample {
            // The FFT methods sample the sensor on their uniform grid: the midpoint rule.
            let (pixel_rule, rule) = if method == Method::MatrixDft {
                (PixelRule::GaussLegendre, "gauss_legendre")
            } else {
                (PixelRule::Midpoint, "midpoint")
            };
            let sys = OpticalSystem { subsample: s, pixel_rule, padding, ..system.clone() };
            let window = match method {
                Method::Fresnel => fresnel::grid(&sys),
                Method::AngularSpectrum => asm::grid(&sys),
                _ => (1, 0.0, 1),
            };
            let pad = window.2 as f64 / window.0 as f64;
            let series = series_name(method, precision, padding);
            let name = format!("{series} s={s}");
            // A run left out leaves the finer ones of its series out too: their windows and
            // their predicted times are larger, the time left no longer.
            let why = if window.2 > MAX_SIDE {
                Some("memory".to_string())
            } else {
                fits(timed_wall(costs.seconds(method, precision, &sys, doe)), series_end).err()
            };
            if let Some(why) = why {
                tick(&format!("{name}: skipped ({why})"));
                skipped.push(format!("{name} ({why})"));
                continue;
            }
            tick(&name);
            let violations: Vec<String> = check(method, &sys, doe)?
                .iter()
                .map(|v| format!("{} at {:.0} nm", v.condition, v.wavelength * 1e9))
                .collect();
            let run_opts = Options { allow_invalid: true, precision };
            let (psf, seconds) = timed(|| simulate(&sys, doe, method, &run_opts))?;
            costs.observe(method, Costs::work(method, precision, &sys, doe), seconds);
            let pupil_pitch = if method == Method::MatrixDft { sys.pupil_pitch } else { sys.sample_pitch() };
            points.push(PsfSweepPoint {
                series,
                method: method.name().into(),
                precision: precision.name().into(),
                padding: pad,
                subsample: s,
                pixel_rule: rule.into(),
                pupil_pitch,
                seconds,
                error: worst_error(&psf, &reference),
                violations,
                pareto: false,
            });
        }
    }
    let valid: Vec<usize> = (0..points.len()).filter(|&i| points[i].violations.is_empty()).collect();
    let pairs: Vec<(f64, f64)> = valid.iter().map(|&i| (points[i].seconds, points[i].error)).collect();
    for k in pareto_front(&pairs) {
        points[valid[k]].pareto = true;
    }
    for plan in &mut plans {
        let cheapest = valid
            .iter()
            .map(|&i| &points[i])
            .filter(|p| p.error <= plan.tolerance)
            .min_by(|a, b| a.seconds.total_cmp(&b.seconds));
        if let Some(c) = cheapest {
            plan.cheapest_adequate = Some(format!("{} s={}", c.series, c.subsample));
            plan.time_ratio = Some(plan.seconds / c.seconds);
        }
    }
    Ok(PsfSweepResults {
        units: "lengths in m, times in s, errors as relative L2 (worst channel)".into(),
        doe_samples: doe.values().nrows(),
        doe_pitch: doe.pitch()[0],
        aperture: system.aperture,
        f_number: system.f_number(),
        wavelengths: system.wavelengths.clone(),
        crop: system.crop,
        budget_seconds: opts.budget,
        reference: reference_check,
        points,
        silent_failures: plans.iter().filter(|p| !p.meets_tolerance).count(),
        plans,
        skipped,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_pareto_front_of_a_hand_made_set() {
        // (time, error): 0 and 3 are each best in one respect, 1 trades between them, 2 is
        // dominated by 1, 4 ties 3 in time but is worse, 5 equals 1 (neither dominates).
        let pts = [(1.0, 1e-2), (2.0, 1e-4), (3.0, 1e-3), (5.0, 1e-8), (5.0, 1e-6), (2.0, 1e-4)];
        assert_eq!(pareto_front(&pts), vec![0, 1, 5, 3]);
        assert!(pareto_front(&[]).is_empty());
    }
}
