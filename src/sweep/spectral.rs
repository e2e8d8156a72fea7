//! Spectral sampling against accuracy (`doefab bench spectral`): a colour channel is a band of
//! wavelengths weighted by the sensor's response ([`crate::optics::spectrum`]), integrated by the
//! midpoint rule over `N` sub-bands; how many does a design need, and does the plan's estimate
//! ([`crate::optics::plan::spectral_error`]) pick enough?
//!
//! **Runs.** The design in its system, by the method the plan picks for it (at 1e-2, without
//! bands), in f64, with one sample per pixel: the pixel integration is the same in every run of
//! a band, so it cancels from the differences measured here. Each band is simulated at the
//! midpoints of `N_ref = 3^k` sub-bands; the midpoints of `N = 3^j` sub-bands (`j < k`) are
//! among them (the middle third of each sub-band), so `N = 1, 3, 9, ...` are all read from the
//! same runs.
//!
//! **Reference.** `N_ref` sub-bands. The midpoint rule converges as `N^-2` on a smooth
//! integrand, so the reference is `1 / 9` as far from the integral as `N_ref / 3`; the
//! difference between the two (reported) bounds the reference's own error by 1/8 of itself.
//!
//! **The plan.** For each band the pilot runs at its edges and centre give the estimate
//! `e(N) = ||D2|| / (6 N^2 ||f_mean||)` of the plan ([`crate::optics::plan::spectral_error`]); its rule
//! takes the smallest `N` with `e(N) <= tolerance` (the whole tolerance: in the plan the
//! spectral term gets what the pixel and precision terms leave, never more), rounded up to a
//! multiple of 3, and the plan's run ([`crate::optics::plan::run`]) checks that `N` against its own
//! middle thirds and triples it until they agree. Each tolerance's plan is run and scored: the
//! estimate alone and the `N` the run settled on are both reported, and a run whose measured
//! error is over the tolerance is a silent failure.
//!
//! The error is the relative L2 of the band's PSF (normalised to sum 1) against the
//! reference's.

use serde::{Deserialize, Serialize};

use crate::error::{Allowed, Error, Result};
use crate::grid::Grid;
use crate::optics::plan::{plan, run, spectral_count, spectral_error, Estimate, Plan};
use crate::optics::propagate::{simulate, Options, Precision};
use crate::optics::psf::{relative_l2, Channel, Psf};
use crate::optics::spectrum::{combine, Band};
use crate::optics::system::{OpticalSystem, PixelRule};

/// What `bench spectral` sweeps.
#[derive(Debug, Clone, PartialEq)]
pub struct SpectralOptions {
    /// The colour channels (default [`paper_bands`]).
    pub bands: Vec<Band>,
    /// `k` of the reference's `3^k` sub-bands (at least 2).
    pub reference_power: u32,
    /// Tolerances at which the plan's rule is placed.
    pub tolerances: Vec<f64>,
}

impl SpectralOptions {
    /// The paper's channels as bands ([`paper_bands`]), 243 sub-bands for the reference, the
    /// rule placed at 1e-2, 1e-3 and 1e-4.
    pub fn paper() -> Result<SpectralOptions> {
        Ok(SpectralOptions { bands: paper_bands()?, reference_power: 5, tolerances: vec![1e-2, 1e-3, 1e-4] })
    }

    /// Refuses options the bench cannot run: no band, a reference outside 3^2..3^6 sub-bands.
    fn check(&self) -> Result<()> {
        if self.bands.is_empty() {
            return Err(Error::param("bands", "bench spectral needs at least one band"));
        }
        if !(2..=6).contains(&self.reference_power) {
            return Err(Error::param_in(
                "reference_power",
                Allowed::between(2.0, 6.0),
                "the reference takes 3^2 to 3^6 sub-bands",
            ));
        }
        Ok(())
    }
}

/// The paper's three channels (635, 530, 450 nm) as bands: Gaussian responses of 80 nm full
/// width at half maximum about those wavelengths, tabulated every 10 nm over 400-700 nm (the
/// range of PDMS's dispersion formula). An illustration of a colour sensor's channels, not a
/// measured response: a measured one is given as a CSV (`--response`).
pub fn paper_bands() -> Result<Vec<Band>> {
    let sigma = 80e-9 / (2.0 * (2.0 * 2f64.ln()).sqrt());
    let grid: Vec<f64> = (0..=30).map(|k| 400e-9 + k as f64 * 10e-9).collect();
    [("r", 635e-9), ("g", 530e-9), ("b", 450e-9)]
        .into_iter()
        .map(|(name, centre)| {
            let r = grid.iter().map(|l| (-0.5 * ((l - centre) / sigma).powi(2)).exp()).collect();
            Band::new(name, grid.clone(), r)
        })
        .collect()
}

/// One band at one `N`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SpectralPoint {
    /// The band's name ("r", "g", "b", ...).
    pub band: String,
    /// Sub-bands (spectral samples).
    pub samples: usize,
    /// Relative L2 against the reference.
    pub error: f64,
    /// The plan's estimate of the error against the exact integral.
    pub estimate: f64,
    /// Seconds of the `N` monochromatic runs (each timed once).
    pub seconds: f64,
}

/// The plan at one tolerance, run and scored.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SpectralPlanPoint {
    /// The tolerance the plan is run at: the largest relative L2 error it may give.
    pub tolerance: f64,
    /// The `N` the pilot's estimate asks for (the largest over the bands, as the plan takes
    /// it); `None` where it refuses (more than [`crate::optics::plan::MAX_SPECTRAL`] sub-bands).
    pub rule_samples: Option<usize>,
    /// The `N` the run settled on after checking itself against its middle thirds.
    pub samples: Option<usize>,
    /// Worst band's measured error of the run's PSF.
    pub error: Option<f64>,
    /// `error <= tolerance` (false where refused).
    pub meets_tolerance: bool,
    /// Why the plan or its run refused, if it did.
    pub refused: Option<String>,
    /// Why a run was not scored: it took more sub-bands than the reference has.
    pub not_scored: Option<String>,
    /// The smallest `N` of the sweep whose every band is within the tolerance, if any.
    pub smallest_adequate: Option<usize>,
    /// Seconds of the run.
    pub seconds: Option<f64>,
}

/// Everything one `bench spectral` run measured.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SpectralSweepResults {
    /// What the numbers are in: lengths in metres, times in seconds, errors relative L2.
    pub units: String,
    /// The propagation method the plan picks for the design (at 1e-2, without bands), used by
    /// every run.
    pub method: String,
    /// The DOE's samples along x (columns).
    pub doe_samples: usize,
    /// The DOE's pitch along x, metres.
    pub doe_pitch: f64,
    /// Sensor window, pixels per side.
    pub crop: usize,
    /// Each band's name and wavelength range `(name, low, high)`, metres.
    pub bands: Vec<(String, f64, f64)>,
    /// `N_ref = 3^reference_power`: the reference's sub-bands per band.
    pub reference_samples: usize,
    /// Worst band's relative L2 between the reference and `N_ref / 3` sub-bands.
    pub reference_difference: f64,
    /// One point per band and `N = 1, 3, ..., N_ref / 3`, sorted by band name, then `N`.
    pub points: Vec<SpectralPoint>,
    /// One per tolerance, in the order given.
    pub plans: Vec<SpectralPlanPoint>,
    /// Tolerances whose plan, as run, measured over the tolerance (a refusal or an unscored run
    /// is not one).
    pub silent_failures: usize,
    /// Seconds of one monochromatic run (mean).
    pub seconds_per_wavelength: f64,
}

/// How many times [`run_spectral`] calls its `tick`: one per monochromatic run of the sweep and
/// the pilots, and one per tolerance's plan run.
pub fn steps(opts: &SpectralOptions) -> usize {
    opts.bands.len() * (3usize.pow(opts.reference_power) + 2) + opts.tolerances.len()
}

/// Runs the sweep (module docs) on `doe` in `system`.
pub fn run_spectral(
    system: &OpticalSystem,
    doe: &Grid,
    opts: &SpectralOptions,
    mut tick: impl FnMut(&str),
) -> Result<SpectralSweepResults> {
    opts.check()?;
    let spatial = plan(system, doe, &[], 1e-2)?;
    let method = spatial.method;
    let base = OpticalSystem { subsample: 1, pixel_rule: PixelRule::GaussLegendre, ..spatial.system.clone() };
    let run_options = Options { allow_invalid: false, precision: Precision::F64 };
    let n_ref = 3usize.pow(opts.reference_power);
    let mut run_seconds = Vec::new();
    // One monochromatic run: the channel in absolute terms (its `captured` kept).
    let mut one = |wavelength: f64| -> Result<(Channel, f64)> {
        let t = std::time::Instant::now();
        let s = OpticalSystem { wavelengths: vec![wavelength], ..base.clone() };
        let psf = simulate(&s, doe, method, &run_options)?;
        let seconds = t.elapsed().as_secs_f64();
        run_seconds.push(seconds);
        let channel =
            psf.channels.into_iter().next().ok_or_else(|| Error::internal("a run gave no channel"))?;
        Ok((channel, seconds))
    };
    let band_psf =
        |band: &Band, channels: &[Channel], samples: &[(f64, f64)]| -> Result<ndarray::Array2<f64>> {
            let psf = Psf::new(channels.to_vec(), method.name())?;
            let combined = combine(&psf, std::slice::from_ref(band), &[samples.to_vec()])?;
            Ok(combined.channels[0].grid.values().clone())
        };

    let mut points = Vec::new();
    let mut reference_difference: f64 = 0.0;
    let mut per_band = Vec::new();
    for band in &opts.bands {
        let fine = band.samples(n_ref);
        let mut runs = Vec::with_capacity(n_ref);
        for (k, &(l, _)) in fine.iter().enumerate() {
            tick(&format!("band {} sample {}/{n_ref}", band.name, k + 1));
            runs.push(one(l)?);
        }
        let channels: Vec<Channel> = runs.iter().map(|r| r.0.clone()).collect();
        let reference = band_psf(band, &channels, &fine)?;
        // The pilot: edges and centre, the centre being the middle run.
        let (lo, hi) = band.range();
        tick(&format!("band {} pilot", band.name));
        let low = one(lo)?.0;
        tick(&format!("band {} pilot", band.name));
        let high = one(hi)?.0;
        let weighted =
            |c: &Channel, l: f64| c.grid.values() * (c.captured.unwrap_or(1.0) * band.response_at(l));
        let pilot =
            [weighted(&low, lo), weighted(&channels[n_ref / 2], 0.5 * (lo + hi)), weighted(&high, hi)];
        // N = 3^j read from the reference's runs: sample k of N is run k (n_ref / N) + (n_ref / N - 1) / 2.
        for j in 0..opts.reference_power {
            let n = 3usize.pow(j);
            let stride = n_ref / n;
            let picked: Vec<Channel> =
                (0..n).map(|k| channels[k * stride + (stride - 1) / 2].clone()).collect();
            let psf = band_psf(band, &picked, &band.samples(n))?;
            let error = relative_l2(&psf, &reference);
            if 3 * n == n_ref {
                reference_difference = reference_difference.max(error);
            }
            let seconds = (0..n).map(|k| runs[k * stride + (stride - 1) / 2].1).sum();
            let estimate = spectral_error([&pilot[0], &pilot[1], &pilot[2]], n);
            points.push(SpectralPoint { band: band.name.clone(), samples: n, error, estimate, seconds });
        }
        per_band.push((band, reference, pilot));
    }

    // The plan at each tolerance: its rule's N (rounded up to a multiple of 3), then its run,
    // which checks and refines N itself.
    let mut plans = Vec::new();
    for &tol in &opts.tolerances {
        tick(&format!("the plan at {tol:.0e}"));
        let pilots = per_band.iter().map(|(b, _, f)| (b.name.as_str(), [&f[0], &f[1], &f[2]]));
        let (rule, refused) = match spectral_count(pilots, tol) {
            Ok(count) => (Some(count), None),
            Err(Error::Validity { what, .. }) => (None, Some(what)),
            Err(e) => return Err(e),
        };
        let mut point = SpectralPlanPoint {
            tolerance: tol,
            rule_samples: rule.as_ref().map(|c| c.needed),
            samples: None,
            error: None,
            meets_tolerance: false,
            refused,
            not_scored: None,
            smallest_adequate: None,
            seconds: None,
        };
        if let Some(count) = rule {
            let n = count.start();
            let planned = Plan {
                tolerance: tol,
                precision: Precision::F64,
                system: OpticalSystem {
                    wavelengths: opts.bands.iter().flat_map(|b| b.samples(n)).map(|s| s.0).collect(),
                    ..base.clone()
                },
                spectral_samples: n,
                estimate: Estimate { pixel_integration: 0.0, precision: 0.0, spectral: 0.0, total: 0.0 },
                choices: Vec::new(),
                ..spatial.clone()
            };
            let t = std::time::Instant::now();
            match run(&planned, doe, &opts.bands) {
                Ok((psf, ran)) => {
                    point.seconds = Some(t.elapsed().as_secs_f64());
                    let mut worst: f64 = 0.0;
                    for (c, (_, reference, _)) in psf.channels.iter().zip(&per_band) {
                        worst = worst.max(relative_l2(c.grid.values(), reference));
                    }
                    point.samples = Some(ran.spectral_samples);
                    if ran.spectral_samples <= n_ref {
                        point.error = Some(worst);
                        point.meets_tolerance = worst <= tol;
                    } else {
                        point.not_scored = Some(format!(
                            "the run took {} sub-bands, more than the reference's {n_ref}: raise the reference",
                            ran.spectral_samples
                        ));
                    }
                }
                Err(Error::Validity { what, .. }) => point.refused = Some(what),
                Err(e) => return Err(e),
            }
        }
        plans.push(point);
    }
    points.sort_by(|a, b| a.band.cmp(&b.band).then(a.samples.cmp(&b.samples)));
    for p in &mut plans {
        let mut counts: Vec<usize> = points.iter().map(|q| q.samples).collect();
        counts.sort_unstable();
        counts.dedup();
        p.smallest_adequate = counts.into_iter().find(|&n| {
            let at: Vec<&SpectralPoint> = points.iter().filter(|q| q.samples == n).collect();
            at.len() == opts.bands.len() && at.iter().all(|q| q.error <= p.tolerance)
        });
    }
    let silent_failures = plans.iter().filter(|p| p.error.is_some() && !p.meets_tolerance).count();
    let seconds_per_wavelength = run_seconds.iter().sum::<f64>() / run_seconds.len().max(1) as f64;
    Ok(SpectralSweepResults {
        units: "lengths in m, times in s, errors relative L2".into(),
        method: method.name().into(),
        doe_samples: doe.dim().1,
        doe_pitch: doe.pitch()[0],
        crop: base.crop,
        bands: opts.bands.iter().map(|b| (b.name.clone(), b.range().0, b.range().1)).collect(),
        reference_samples: n_ref,
        reference_difference,
        points,
        plans,
        silent_failures,
        seconds_per_wavelength,
    })
}
