//! The automatic plan on a suite of scenes: on each, the plan's PSF lies within the tolerance
//! of a converged reference computed another way: the midpoint rule over each pixel at 16 and
//! 32 sub-samples per axis, Richardson-extrapolated (`(4 I_32 - I_16) / 3`, the rule's error
//! being even in the spacing), in f64, and for a band Gauss-Legendre nodes in wavelength,
//! where the plan uses Gauss-Legendre pixel nodes, f32 where it estimates it suffices and the
//! midpoint rule in wavelength. (The propagation itself is checked against the Fresnel,
//! angular-spectrum and Rayleigh-Sommerfeld methods in `tests/optics.rs`.)

use doefab::design::{paper_example, ExampleParams};
use doefab::grid::{Grid, Unit};
use doefab::optics::plan::{plan, run};
use doefab::optics::spectrum::{combine, Band};
use doefab::optics::system::{gauss_legendre, OpticalSystem, PixelRule};
use doefab::optics::{simulate, Method, Options, Precision, Psf};
use doefab::rng::Lcg;
use ndarray::Array2;

const TOL: f64 = 1e-3;

// The bench's small F/7 scene: 0.5 mm aperture, g = 3.5 mm, 3 um pixels, 40 x 40 crop, the DOE
// at 5 um, 635 and 450 nm.
use doefab::sweep::psf::{scene, N, PITCH};

fn heights(phase: impl Fn(f64, f64) -> f64) -> Grid {
    doefab::sweep::psf::heights(phase).unwrap()
}

/// The midpoint rule at 16 and 32 sub-samples, Richardson-extrapolated, f64; with bands, each
/// band integrated at 24 Gauss-Legendre wavelengths.
fn reference(system: &OpticalSystem, doe: &Grid, bands: &[Band]) -> Vec<Array2<f64>> {
    let samples: Vec<Vec<(f64, f64)>> = bands
        .iter()
        .map(|b| {
            let (lo, hi) = b.range();
            let (t, w) = gauss_legendre(24);
            t.iter()
                .zip(&w)
                .map(|(t, w)| {
                    let l = 0.5 * (lo + hi) + 0.5 * (hi - lo) * t;
                    (l, 0.5 * (hi - lo) * w * b.response_at(l))
                })
                .collect()
        })
        .collect();
    let at = |s: usize| -> Psf {
        let wavelengths = if bands.is_empty() {
            system.wavelengths.clone()
        } else {
            samples.iter().flatten().map(|s| s.0).collect()
        };
        let sys =
            OpticalSystem { subsample: s, pixel_rule: PixelRule::Midpoint, wavelengths, ..system.clone() };
        let psf = simulate(&sys, doe, Method::MatrixDft, &Options::default()).unwrap();
        if bands.is_empty() {
            psf
        } else {
            combine(&psf, bands, &samples).unwrap()
        }
    };
    let (coarse, fine) = (at(16), at(32));
    coarse
        .channels
        .iter()
        .zip(&fine.channels)
        .map(|(c, f)| (f.grid.values() * 4.0 - c.grid.values()) / 3.0)
        .collect()
}

/// Plans, runs and compares with the reference; returns the plan's description.
fn check(name: &str, system: &OpticalSystem, doe: &Grid, bands: &[Band]) -> doefab::optics::plan::Plan {
    let p = plan(system, doe, bands, TOL).unwrap();
    assert!(p.estimate.total <= TOL, "{name}: estimate {:?}", p.estimate);
    let (psf, p) = run(&p, doe, bands).unwrap();
    let want = reference(system, doe, bands);
    for (c, w) in psf.channels.iter().zip(&want) {
        let e = doefab::optics::psf::relative_l2(c.grid.values(), w);
        eprintln!("{name} {}: error {e:.2e}, estimate {:.2e}\n{}", c.name, p.estimate.total, p.explain());
        assert!(e <= TOL, "{name} {}: error {e:.2e} over the tolerance\n{}", c.name, p.explain());
    }
    p
}

#[test]
fn flat_doe_and_fresnel_lens() {
    let s = scene();
    let p = check("flat", &s, &heights(|_, _| 0.0), &[]);
    // The DOE's own samples, Gauss-Legendre pixels, f32 products.
    assert_eq!((p.method, p.precision, p.system.pupil_pitch), (Method::MatrixDft, Precision::F32, PITCH));
    assert_eq!(p.system.pixel_rule, PixelRule::GaussLegendre);
    assert!(p.system.subsample >= 2, "{}", p.explain());
    // A wrapped diffractive lens of 40 mm focal length at 550 nm.
    let two_pi = 2.0 * std::f64::consts::PI;
    let lens =
        heights(|x, y| (-(x * x + y * y) * std::f64::consts::PI / (550e-9 * 40e-3)).rem_euclid(two_pi));
    check("fresnel lens", &s, &lens, &[]);
}

/// The built-in example design scaled to the bench scene: 0.5 mm aperture, 100 um grating.
fn built_in_doe() -> Grid {
    paper_example(&ExampleParams {
        samples: N,
        pitch: PITCH,
        aperture: 0.5e-3,
        grating_period: 20.0 * PITCH,
        ..Default::default()
    })
    .unwrap()
}

#[test]
fn built_in_doe_and_random_smooth_phase() {
    let s = scene();
    check("built-in", &s, &built_in_doe(), &[]);
    // Twelve random plane-wave phase ripples of periods 60-300 um and 0.5 rad each.
    let mut rng = Lcg(7);
    let waves: Vec<[f64; 4]> = (0..12)
        .map(|_| {
            let period = 60e-6 + 240e-6 * rng.uniform();
            let angle = 2.0 * std::f64::consts::PI * rng.uniform();
            [angle.cos() / period, angle.sin() / period, 2.0 * std::f64::consts::PI * rng.uniform(), 0.5]
        })
        .collect();
    let smooth = heights(|x, y| {
        waves
            .iter()
            .map(|w| w[3] * (2.0 * std::f64::consts::PI * (w[0] * x + w[1] * y) + w[2]).sin())
            .sum::<f64>()
            + 6.0
    });
    check("random smooth", &s, &smooth, &[]);
}

#[test]
fn defocused_sensor_and_finite_object() {
    let doe = built_in_doe();
    let defocus = OpticalSystem { lens_to_sensor: 3.5e-3 * 1.01, ..scene() };
    check("defocused", &defocus, &doe, &[]);
    // A point 100 mm in front of the DOE, the sensor at its thin-lens image distance.
    let z = 100e-3;
    let image = 1.0 / (1.0 / 3.5e-3 - 1.0 / (z + 1e-3));
    let near = OpticalSystem { object_distance: Some(z), lens_to_sensor: image, ..scene() };
    check("finite object", &near, &doe, &[]);
}

#[test]
fn a_wide_spectral_band() {
    let doe = built_in_doe();
    // 480-620 nm with a response rising towards the red.
    let band = Band::new("G", vec![480e-9, 550e-9, 620e-9], vec![0.3, 0.8, 1.0]).unwrap();
    let p = check("wide band", &scene(), &doe, &[band]);
    assert!(p.spectral_samples > 1, "{}", p.explain());
}

/// The five designs of the plan's suite, on the bench scene's grid: the built-in (paper-like)
/// DOE, a wrapped diffractive lens, a binary grating, a random phase, and a simulated scan of the
/// built-in DOE as a profilometer returns it (5 um blur, 4 % shallow, 10 nm noise).
fn five_designs() -> Vec<(&'static str, Grid)> {
    use doefab::metrology::{simulate_scan, SimulateParams};
    let tau = 2.0 * std::f64::consts::PI;
    let lens = heights(|x, y| (-(x * x + y * y) * std::f64::consts::PI / (550e-9 * 40e-3)).rem_euclid(tau));
    // 0 / 0.8 pi at 550 nm (under pi at 450 nm too, so the pupil's steps are resolved), 40 um
    // period, along x.
    let grating =
        heights(|x, _| if (x / 40e-6).rem_euclid(1.0) < 0.5 { 0.0 } else { 0.8 * std::f64::consts::PI });
    // Random phase: 40 plane waves of random direction, phase and period 25-80 um, 0.25 rad each.
    let mut rng = Lcg(11);
    let waves: Vec<[f64; 3]> = (0..40)
        .map(|_| {
            let period = 25e-6 + 55e-6 * rng.uniform();
            let angle = tau * rng.uniform();
            [angle.cos() / period, angle.sin() / period, tau * rng.uniform()]
        })
        .collect();
    let random = heights(|x, y| {
        waves.iter().map(|w| 0.25 * (tau * (w[0] * x + w[1] * y) + w[2]).sin()).sum::<f64>() + 8.0
    });
    let scan = simulate_scan(
        &built_in_doe(),
        &SimulateParams { blur: 5e-6, depth_scale: 0.96, noise: 10e-9, seed: 3, ..Default::default() },
    )
    .unwrap();
    vec![
        ("built-in", built_in_doe()),
        ("fresnel lens", lens),
        ("binary grating", grating),
        ("random phase", random),
        ("scan", scan),
    ]
}

/// Model no more than a scene needs, and never less: on the five designs at three tolerances
/// the plan's PSF is within the tolerance of the reference (computed once per design, another
/// way: the midpoint rule Richardson-extrapolated), every channel. Measured: matrix DFT f32 at
/// the DOE's pitch on all five; at 1e-2 three Gauss-Legendre sub-samples (errors 3e-5 to
/// 9e-4), at 1e-3 and 1e-4 four (5e-7 to 2.3e-5).
#[test]
fn the_plan_meets_three_tolerances_on_five_designs() {
    let s = scene();
    for (name, doe) in five_designs() {
        let want = reference(&s, &doe, &[]);
        for tol in [1e-2, 1e-3, 1e-4] {
            let p = plan(&s, &doe, &[], tol).unwrap();
            let (psf, _) = run(&p, &doe, &[]).unwrap();
            for (c, w) in psf.channels.iter().zip(&want) {
                let e = doefab::optics::psf::relative_l2(c.grid.values(), w);
                eprintln!(
                    "{name} at {tol:.0e} {}: error {e:.2e} ({} {} s={} pupil {:.2} um)",
                    c.name,
                    p.method,
                    p.precision.name(),
                    p.system.subsample,
                    p.system.pupil_pitch * 1e6
                );
                assert!(e <= tol, "{name} {} at {tol:e}: error {e:.2e}\n{}", c.name, p.explain());
            }
        }
    }
}

#[test]
fn the_plan_refuses_what_it_cannot_meet_and_names_why() {
    let s = scene();
    let doe = heights(|_, _| 0.0);
    for bad in [0.0, -1e-3, 1.5, f64::NAN] {
        let e = plan(&s, &doe, &[], bad).unwrap_err();
        match &e {
            doefab::Error::Parameter { name, allowed: Some(range), .. } => {
                assert!(name == "tolerance" && !range.contains(bad) && range.contains(TOL), "{e}")
            }
            other => panic!("expected a refused tolerance with its range, got {other:?}"),
        }
    }
    // A band reaching outside PDMS's dispersion formula names the range.
    let uv = Band::flat("UV", 350e-9, 450e-9).unwrap();
    let e = plan(&s, &doe, &[uv], TOL).unwrap_err();
    assert!(matches!(e, doefab::Error::Parameter { ref name, .. } if name == "band"), "{e:?}");
    let e = e.to_string();
    assert!(e.contains("band 'UV'") && e.contains("400-700 nm"), "{e}");
    // A crop wider than the replica period lambda B / dx of any pupil sampling the plan
    // considers (DOE pitch / 8 still leaves 2.0 mm at 450 nm over a 3 mm crop), with the FFT
    // method's grid over its size limit: refused with both reasons.
    let wide = OpticalSystem { crop: 1000, ..s.clone() };
    let e = plan(&wide, &doe, &[], TOL).unwrap_err();
    assert!(matches!(e, doefab::Error::Validity { condition: doefab::Condition::Propagation, .. }), "{e:?}");
    let e = e.to_string();
    assert!(
        e.contains("no method is valid") && e.contains("matrix_dft") && e.contains("angular_spectrum"),
        "{e}"
    );
    // One pupil refinement lifts the replica period over the crop: the plan interpolates the
    // DOE at half its pitch and says why.
    let c = (0.55e-3 / 3e-6) as usize; // 183 pixels = 0.55 mm > lambda B / dx = 0.315 mm at 450 nm
    let p = plan(&OpticalSystem { crop: c, ..s }, &doe, &[], TOL).unwrap();
    assert_eq!((p.method, p.system.pupil_pitch), (Method::MatrixDft, PITCH / 2.0), "{}", p.explain());
    assert!(p.explain().contains("output_window"), "{}", p.explain());
}

/// A stepped DOE whose crop needs a finer pupil than its samples (the wrapped lens of the suite
/// with a 0.55 mm crop, over the replica period `lambda B / dx` = 0.315 mm of its 5 um samples
/// at 450 nm): bilinear interpolation would put a ramp across each step (refused), so the plan
/// reads it by nearest interpolation, 2 x 2 pupil samples nested in each DOE sample, and says
/// so. Its pupil is the part's piecewise-constant surface: the run equals, to rounding, the same
/// run on the DOE with each sample repeated 2 x 2 at 2.5 um, taken as it is.
#[test]
fn the_plan_refines_a_stepped_doe_by_nearest_interpolation() {
    use doefab::grid::Interpolation;
    let tau = 2.0 * std::f64::consts::PI;
    let lens = heights(|x, y| (-(x * x + y * y) * std::f64::consts::PI / (550e-9 * 40e-3)).rem_euclid(tau));
    let s = OpticalSystem { crop: (0.55e-3 / 3e-6) as usize, ..scene() };
    let p = plan(&s, &lens, &[], TOL).unwrap();
    assert_eq!(
        (p.method, p.system.pupil_pitch, p.system.interpolation),
        (Method::MatrixDft, PITCH / 2.0, Interpolation::Nearest),
        "{}",
        p.explain()
    );
    assert!(p.explain().contains("nearest, the DOE's steps kept"), "{}", p.explain());
    let bilinear = OpticalSystem { interpolation: Interpolation::Bilinear, ..p.system.clone() };
    let v = doefab::optics::propagate::check(Method::MatrixDft, &bilinear, &lens).unwrap();
    assert!(v.iter().any(|v| v.condition == "step_resampling"), "{v:?}");
    let (psf, _) = run(&p, &lens, &[]).unwrap();
    let repeated = Grid::new(
        Array2::from_shape_fn((2 * N, 2 * N), |(i, j)| lens.values()[[i / 2, j / 2]]),
        [PITCH / 2.0; 2],
        Unit::Metre,
    )
    .unwrap();
    let own = OpticalSystem { interpolation: Interpolation::Bilinear, ..p.system.clone() };
    let o = Options { precision: p.precision, ..Default::default() };
    let want = simulate(&own, &repeated, Method::MatrixDft, &o).unwrap();
    for (c, w) in psf.channels.iter().zip(&want.channels) {
        let e = doefab::optics::psf::relative_l2(c.grid.values(), w.grid.values());
        assert!(e < 1e-12, "{}: {e:e}", c.name);
    }
}

#[test]
fn a_sensor_response_csv_gives_one_band_per_column() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("response.csv");
    std::fs::write(
        &path,
        "# camera\nwavelength_nm,r,g,b\n450,0.0,0.1,1.0\n550,0.1,1.0,0.2\n650,1.0,0.1,0.0\n",
    )
    .unwrap();
    let bands = doefab::optics::spectrum::read_response_csv(&path).unwrap();
    let names: Vec<&str> = bands.iter().map(|b| b.name.as_str()).collect();
    assert_eq!(names, ["r", "g", "b"]);
    let (lo, hi) = bands[1].range();
    assert!((lo - 450e-9).abs() < 1e-18 && (hi - 650e-9).abs() < 1e-18);
    assert!((bands[1].response_at(550e-9) - 1.0).abs() < 1e-12);
    for (text, needle) in [
        ("wavelength,r\n450,1\n550,1\n", "names no unit"),
        ("wavelength_nm,r\n450,1\n550\n", "line 3: expected 2 fields, got 1"),
        ("wavelength_nm,r\n450,1\n550,x\n", "line 3: r 'x' is not a number"),
        ("wavelength_nm,r\n550,1\n450,1\n", "wavelengths must increase"),
    ] {
        std::fs::write(&path, text).unwrap();
        let e = doefab::optics::spectrum::read_response_csv(&path).unwrap_err();
        let (cause, _, file) = crate::common::format_cause(&e);
        assert_eq!((cause, file), (doefab::FormatCause::Malformed, path.as_path()), "{text}: {e}");
        assert!(e.to_string().contains(needle), "{text}: {e}");
    }
}

/// A system TOML in `dir`: the aperture, the focal length (sensor in focus), a 33^2 crop of
/// 3 um pixels.
fn system_file(dir: &std::path::Path, aperture: &str, focal_length: &str) -> std::path::PathBuf {
    let sys = dir.join("system.toml");
    let text = format!(
        "aperture = \"{aperture}\"\nfocal_length = \"{focal_length}\"\nlens_to_sensor = \"{focal_length}\"\n\
         crop = 33\nsensor_pitch = \"3 um\"\n"
    );
    std::fs::write(&sys, text).unwrap();
    sys
}

#[test]
fn psf_command_with_a_system_file_and_a_sensor_response() {
    let dir = tempfile::tempdir().unwrap();
    let sys = system_file(dir.path(), "1 mm", "7 mm");
    let csv = dir.path().join("sensor.csv");
    std::fs::write(&csv, "wavelength_nm,g,b\n430,0,1\n480,0.2,0.6\n530,1,0.1\n580,0.2,0\n").unwrap();
    let out = dir.path().join("psf");
    let run = std::process::Command::new(env!("CARGO_BIN_EXE_doefab"))
        .args(["psf", "built-in:paper", "--json", "--system"])
        .arg(&sys)
        .arg("--response")
        .arg(&csv)
        .arg("-o")
        .arg(&out)
        .output()
        .unwrap();
    assert!(run.status.success(), "{}", String::from_utf8_lossy(&run.stderr));
    let r: serde_json::Value = serde_json::from_slice(&run.stdout).unwrap();
    assert_eq!(r["system"]["aperture"], 1e-3);
    let names: Vec<&str> =
        r["channels"].as_array().unwrap().iter().map(|c| c["name"].as_str().unwrap()).collect();
    assert_eq!(names, ["g", "b"]);
    // Each band is simulated at its spectral samples: 430-580 nm, twice the samples per band.
    let n = r["plan"]["spectral_samples"].as_u64().unwrap() as usize;
    assert!(n > 1 && r["plan"]["system"]["wavelengths"].as_array().unwrap().len() == 2 * n, "{r}");
    let (h, _) = doefab::io::npy::read_npy_nd(&out.join("psf.npy")).unwrap();
    assert_eq!(h.shape, vec![33, 33, 1, 2]);
    // A bad system file names itself and the field, and writes nothing.
    std::fs::write(&sys, "aperture = \"1\"\n").unwrap();
    let out2 = dir.path().join("psf2");
    let run = std::process::Command::new(env!("CARGO_BIN_EXE_doefab"))
        .args(["psf", "--system"])
        .arg(&sys)
        .arg("-o")
        .arg(&out2)
        .output()
        .unwrap();
    let e = String::from_utf8_lossy(&run.stderr);
    assert!(!run.status.success() && e.contains("system.toml") && e.contains("aperture"), "{e}");
    assert!(!out2.exists());
}

#[test]
fn peaks_find_the_central_spot_and_its_copies_with_their_energies() {
    // Three Gaussian spots of energies 0.5, 0.3, 0.2 (sigma 1.5 pixels) on a 41 x 41 grid.
    let pitch = 2e-6;
    let spots = [(20.0, 20.0, 0.5), (20.0, 32.0, 0.3), (8.0, 10.0, 0.2)];
    let norm = 1.0 / (2.0 * std::f64::consts::PI * 1.5f64.powi(2));
    let v = Array2::from_shape_fn((41, 41), |(i, j)| {
        spots
            .iter()
            .map(|&(r, c, e)| {
                e * norm * (-((i as f64 - r).powi(2) + (j as f64 - c).powi(2)) / (2.0 * 1.5f64.powi(2))).exp()
            })
            .sum::<f64>()
    });
    let ch = doefab::optics::Channel {
        name: "G".into(),
        wavelength: None,
        grid: Grid::new(v, [pitch; 2], Unit::Dimensionless).unwrap(),
        captured: None,
    };
    let psf = Psf::new(vec![ch], "test").unwrap();
    let p = psf.peaks(0, 7, 6.0 * pitch);
    assert_eq!(p.len(), 3);
    for (peak, &(r, c, e)) in p.iter().zip(&spots) {
        assert!((peak.position[0] - (c - 20.0) * pitch).abs() < 1e-12, "{peak:?}");
        assert!((peak.position[1] - (r - 20.0) * pitch).abs() < 1e-12, "{peak:?}");
        // Within 6 pixels = 4 sigma: 1 - exp(-8) of the spot's energy.
        assert!((peak.energy - e * (1.0 - (-8.0f64).exp())).abs() < 2e-3, "{peak:?} vs {e}");
    }
}

// ---------------------------------------------------------------------------------------------
// `bench psf`: its reference, the plan on its chart, the budget

use doefab::sweep::psf::{run_sweep, SweepOptions};

/// The bench's reference (Gauss-Legendre pixels at `s_max + 4`) agrees with the independent
/// one above (midpoint rule, Richardson-extrapolated) to 1e-6, and its own convergence check
/// says so; the plan meets every tolerance against it, the Fresnel method's guard refuses the
/// fine grids where its error stalls, and the FFT methods run at three paddings.
#[test]
fn bench_psf_reference_is_converged_and_the_plan_meets_its_tolerances() {
    let (system, doe) = (scene(), doefab::sweep::psf::doe().unwrap());
    let opts = SweepOptions { budget: 600.0, max_subsample: 4, tolerances: vec![1e-2, 1e-3, 1e-4] };
    let mut ticks = 0;
    let r = run_sweep(&system, &doe, &opts, |_| ticks += 1).unwrap();
    assert_eq!(ticks, doefab::sweep::psf::steps(&opts));
    assert_eq!(r.reference.subsamples, [6, 8]);
    assert!(r.reference.difference < 1e-6, "{:?}", r.reference);
    // Against the independent reference: run the bench's reference configuration here.
    let gl = OpticalSystem { subsample: 8, pixel_rule: PixelRule::GaussLegendre, ..system.clone() };
    let ours = simulate(&gl, &doe, Method::MatrixDft, &Options::default()).unwrap();
    for (c, want) in ours.channels.iter().zip(reference(&system, &doe, &[])) {
        let e = doefab::optics::psf::relative_l2(c.grid.values(), &want);
        assert!(e < 1e-6, "{}: {e:e}", c.name);
    }
    assert_eq!(r.points.len(), 8 * 4, "{:?}", r.skipped);
    assert!(r.skipped.is_empty());
    // The FFT methods at three paddings each (1.25, their own, 3): the window as run is the
    // nominal one rounded up to a fast FFT size. On this scene the error does not depend on it
    // (within 1 %: it is the pixel rule's and the pupil's); only the guard's window
    // conditions and the time do.
    for method in ["fresnel", "angular_spectrum"] {
        let own = if method == "fresnel" { 1.5 } else { 2.0 };
        for s in 1..=4 {
            let at: Vec<_> = r.points.iter().filter(|p| p.method == method && p.subsample == s).collect();
            assert_eq!(at.len(), 3, "{method} s={s}");
            for (p, nominal) in at.iter().zip([1.25, own, 3.0]) {
                assert!(p.padding >= nominal - 0.01 && p.padding < nominal * 1.1, "{p:?}");
                assert!(p.series.ends_with(&format!("pad {nominal}")), "{p:?}");
                assert!((p.error / at[1].error - 1.0).abs() < 0.01, "{p:?} against {:?}", at[1]);
            }
            if s >= 2 {
                assert!(at[0].violations.iter().any(|v| v.starts_with("output_window")), "{:?}", at[0]);
            }
        }
    }
    for p in &r.plans {
        assert!(p.meets_tolerance, "{p:?}");
        assert!(p.error <= p.tolerance && p.cheapest_adequate.is_some(), "{p:?}");
    }
    assert!(r.points.iter().any(|p| p.pareto));
    let fresnel_fine = r.points.iter().find(|p| p.method == "fresnel" && p.subsample == 4).unwrap();
    assert!(!fresnel_fine.violations.is_empty() && fresnel_fine.error > 1e-2, "{fresnel_fine:?}");
}

/// A budget the reference alone spends leaves the plans and the whole sweep out, each named
/// with its predicted time and the time left; the charts and the JSON are still written. With
/// a budget that holds them, every run was predicted to fit.
#[test]
fn bench_psf_budget_leaves_configurations_out_by_name() {
    let (system, doe) = (scene(), doefab::sweep::psf::doe().unwrap());
    let opts = SweepOptions { budget: 1e-9, max_subsample: 2, tolerances: vec![1e-3] };
    let r = run_sweep(&system, &doe, &opts, |_| {}).unwrap();
    assert!(r.points.is_empty() && r.plans.is_empty());
    assert_eq!(r.skipped.len(), 17, "{:?}", r.skipped);
    for name in
        ["plan at 1e-3 (budget: ", "matrix_dft f32 s=1 (budget: ", "angular_spectrum f64 pad 3 s=2 (budget: "]
    {
        assert!(
            r.skipped.iter().any(|s| s.starts_with(name) && s.ends_with(" s left)")),
            "{name}: {:?}",
            r.skipped
        );
    }
    let d = tempfile::tempdir().unwrap();
    doefab::charts::optics::write_psf_charts(|n| d.path().join(n), &r).unwrap();
    let svg = std::fs::read_to_string(d.path().join("speed_accuracy.svg")).unwrap();
    assert!(svg.contains("left out by the budget: 17"));
    let bad = SweepOptions { budget: 10.0, max_subsample: 0, tolerances: vec![] };
    assert!(run_sweep(&system, &doe, &bad, |_| {}).is_err());
}

/// `bench psf` on a design with a system file: the charts and the JSON, the plan on them; a
/// budget without a unit is refused, naming the option, and nothing is written.
#[test]
fn bench_psf_command_charts_a_design_in_its_system() {
    let dir = tempfile::tempdir().unwrap();
    let sys = system_file(dir.path(), "0.5 mm", "3.5 mm");
    // The small scene's DOE (112^2 at 5 um) as a file in micrometres.
    let doe = dir.path().join("doe.npy");
    let heights = doefab::sweep::psf::doe().unwrap().values().mapv(|h| h * 1e6);
    doefab::io::npy::write_npy_f64(&doe, &heights).unwrap();
    let out = dir.path().join("bench");
    let path = |p: &std::path::Path| p.to_str().unwrap().to_string();
    let (sys, doe, out_arg) = (path(&sys), path(&doe), path(&out));
    let stdout = crate::common::ok(&[
        "bench",
        "psf",
        &doe,
        "--json",
        "--budget",
        "2min",
        "--max-subsample",
        "2",
        "--pitch",
        "5um",
        "--unit",
        "um",
        "--tolerances",
        "1e-2",
        "--system",
        &sys,
        "-o",
        &out_arg,
    ]);
    let r: serde_json::Value = serde_json::from_str(&stdout).unwrap();
    assert_eq!((r["aperture"].as_f64(), r["doe_samples"].as_u64()), (Some(0.5e-3), Some(112)));
    assert_eq!(r["reference"]["subsamples"], serde_json::json!([4, 6]));
    assert_eq!(r["plans"][0]["tolerance"], 1e-2);
    assert_eq!(r["plans"][0]["meets_tolerance"], true);
    let on_disk: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("bench_psf.json")).unwrap()).unwrap();
    assert_eq!(on_disk["plans"], r["plans"]);
    for f in ["speed_accuracy.png", "speed_accuracy.svg", "stability.png", "stability.svg"] {
        assert!(out.join(f).is_file(), "{f}");
    }
    let out2 = dir.path().join("bench2");
    let err = crate::common::fails(&["bench", "psf", "--budget", "5", "-o", &path(&out2)]);
    assert!(err.contains("--budget") && err.contains("no unit"), "{err}");
    assert!(!out2.exists());
}

/// The case of the issue on the bench scene: a wrapped design (the small scene's DOE wrapped at
/// 530 nm as `wrap` does, mirrored and scaled by 0.9, written as .npy in micrometres). Its
/// steps at 635 nm are 0.9 of a period, many of them (with the slope beside them) more than
/// pi/2 from 2 pi, which the guard once took for an undersampled slope, refusing `bench psf`'s
/// reference. Now `bench psf` runs: the matrix DFT on the DOE's own samples is accepted, every
/// plan meets its tolerance (no silent failure); and `psf` plans on the DOE's own samples
/// without a warning (it once refined the pupil by bilinear interpolation, a ramp across each
/// step that the part does not have).
#[test]
fn bench_psf_runs_on_a_wrapped_user_design() {
    use doefab::fabrication::wrap::{wrap, WrapSpec};
    let dir = tempfile::tempdir().unwrap();
    let sys = system_file(dir.path(), "0.5 mm", "3.5 mm");
    let (wrapped, _) = wrap(&doefab::sweep::psf::doe().unwrap(), &WrapSpec::default()).unwrap();
    let heights = wrapped.values().slice(ndarray::s![.., ..;-1]).mapv(|h| 0.9 * h * 1e6);
    let pi = std::f64::consts::PI;
    let k = 2.0 * pi / 635e-9 * (doefab::material::Material::pdms().index(635e-9).unwrap() - 1.0) * 1e-6;
    let off = heights
        .windows((1, 2))
        .into_iter()
        .map(|w| k * (w[[0, 1]] - w[[0, 0]]))
        .filter(|d| d.abs() > pi && (d.abs() - 2.0 * pi).abs() > 0.5 * pi)
        .count();
    assert!(off > 50, "{off}");
    let doe = dir.path().join("wrapped.npy");
    doefab::io::npy::write_npy_f64(&doe, &heights).unwrap();
    let path = |p: &std::path::Path| p.to_str().unwrap().to_string();
    let (out, psf_out) = (dir.path().join("bench"), dir.path().join("psf"));
    let (sys, doe, out_arg) = (path(&sys), path(&doe), path(&out));
    let on = ["--pitch", "5um", "--unit", "um", "--system", &sys];
    let mut args = vec!["bench", "psf", &doe, "--json", "--budget", "2min", "--max-subsample", "2"];
    args.extend(["--tolerances", "1e-2,1e-3", "-o", &out_arg]);
    args.extend(on);
    let r: serde_json::Value = serde_json::from_str(&crate::common::ok(&args)).unwrap();
    assert_eq!(r["silent_failures"], 0, "{r}");
    for p in r["plans"].as_array().unwrap() {
        assert_eq!(p["meets_tolerance"], true, "{p}");
        assert!((p["pupil_pitch"].as_f64().unwrap() - 5e-6).abs() < 1e-15, "{p}");
    }
    let own = r["points"].as_array().unwrap().iter().find(|p| p["method"] == "matrix_dft").unwrap();
    assert_eq!(own["violations"], serde_json::json!([]), "{own}");
    let svg = std::fs::read_to_string(out.join("speed_accuracy.svg")).unwrap();
    assert!(svg.contains("silent failures: 0"));
    let mut args = vec!["psf", &doe, "--json", "-o"];
    let psf_arg = path(&psf_out);
    args.push(&psf_arg);
    args.extend(on);
    let p: serde_json::Value = serde_json::from_str(&crate::common::ok(&args)).unwrap();
    assert_eq!(p["warnings"], serde_json::json!([]), "{p}");
    let pitch = p["plan"]["system"]["pupil_pitch"].as_f64().unwrap();
    assert!((pitch - 5e-6).abs() < 1e-15, "{}", p["plan"]);
}

/// `bench spectral` on the bench scene with the paper's channels as 80 nm bands: the reference
/// (243 sub-bands) is converged far below the tolerances, the midpoint rule's error falls at
/// least as `N^-2` once its sub-bands resolve the band (9 -> 27: a ninth or less), and every
/// plan the bench runs meets its tolerance (no silent failure), its run having checked the
/// estimate's `N` against its own middle thirds. Measured: at 1e-2 the estimate asks 10, the
/// run settles on 36 (error 1.4e-4; 9 would do), at 1e-3 it asks 29 and settles on 90
/// (2.0e-5; 27 would do); at 1e-4 the estimate refuses (more than 64 sub-bands for 'g').
#[test]
fn spectral_sampling_sweep_meets_the_rule_and_converges() {
    use doefab::sweep::spectral::{run_spectral, steps, SpectralOptions};
    let opts = SpectralOptions::paper().unwrap();
    let mut ticks = 0;
    let r = run_spectral(&scene(), &built_in_doe(), &opts, |_| ticks += 1).unwrap();
    assert_eq!(ticks, steps(&opts));
    for p in &r.points {
        eprintln!("{} N={} error {:.2e} estimate {:.2e}", p.band, p.samples, p.error, p.estimate);
    }
    for p in &r.plans {
        eprintln!(
            "plan at {:.0e}: asks {:?}, settles on {:?}, error {:?} ({:?})",
            p.tolerance, p.rule_samples, p.samples, p.error, p.refused
        );
    }
    assert_eq!(r.silent_failures, 0);
    assert!(r.reference_difference < 1e-4, "{}", r.reference_difference);
    for band in ["r", "g", "b"] {
        let at = |n: usize| r.points.iter().find(|p| p.band == band && p.samples == n).unwrap().error;
        let ratio = at(9) / at(27);
        assert!(ratio > 6.0, "band {band}: N=9 / N=27 error ratio {ratio}");
    }
    for p in r.plans.iter().filter(|p| p.tolerance >= 1e-3) {
        let (n, adequate) = (p.samples.unwrap(), p.smallest_adequate.unwrap());
        assert!(p.meets_tolerance && n <= 4 * adequate, "{p:?}");
    }
}

/// A plan run that takes more sub-bands than the reference has is not scored against it (it
/// would be measured against a coarser integral than its own), and is not counted as a silent
/// failure: at 1e-3 the rule asks for 29 sub-bands, the reference has 9.
#[test]
fn spectral_plan_runs_finer_than_the_reference_are_not_scored() {
    use doefab::sweep::spectral::{run_spectral, SpectralOptions};
    let opts =
        SpectralOptions { reference_power: 2, tolerances: vec![1e-3], ..SpectralOptions::paper().unwrap() };
    let r = run_spectral(&scene(), &built_in_doe(), &opts, |_| {}).unwrap();
    let p = &r.plans[0];
    assert!(p.samples.unwrap() > 9 && p.error.is_none() && !p.meets_tolerance, "{p:?}");
    assert!(p.not_scored.as_deref().is_some_and(|w| w.contains("more than the reference's 9")), "{p:?}");
    assert_eq!(r.silent_failures, 0);
}

/// `psf --explain` measures the cheaper pixel sub-samplings the plan rejected: on the built-in
/// design at 1e-2 and 1e-3, each figure is that run's error against the independent reference
/// to within the plan's own error there, and the verdict line follows the figures.
#[test]
fn the_rejected_cheaper_points_are_measured_against_an_independent_reference() {
    use doefab::optics::plan::measure_cheaper;
    use doefab::optics::psf::relative_l2;
    let s = scene();
    let doe = built_in_doe();
    let want = reference(&s, &doe, &[]);
    let worst = |psf: &Psf| {
        psf.channels.iter().zip(&want).map(|(c, w)| relative_l2(c.grid.values(), w)).fold(0.0, f64::max)
    };
    for tol in [1e-2, 1e-3] {
        let p = plan(&s, &doe, &[], tol).unwrap();
        let (own, _) = run(&p, &doe, &[]).unwrap();
        let own_error = worst(&own);
        assert!(own_error <= tol, "{own_error}");
        let m = measure_cheaper(&p, &doe, &[]).unwrap();
        assert_eq!(m.runs.len(), p.system.subsample.min(4) - 1, "{}", p.explain());
        for r in &m.runs {
            let sys = OpticalSystem { subsample: r.subsample, ..p.system.clone() };
            let forced = Options { allow_invalid: true, precision: p.precision };
            let truth = worst(&simulate(&sys, &doe, p.method, &forced).unwrap());
            eprintln!(
                "{tol:.0e}: {s} x {s}: measured {:.2e}, against the reference {truth:.2e}",
                r.error,
                s = r.subsample
            );
            assert!((r.error - truth).abs() <= own_error + 1e-9, "{tol}: {r:?} vs {truth} (own {own_error})");
        }
        let text = m.explain();
        let adequate = m.runs.iter().any(|r| r.valid && r.error + m.chosen_estimate <= tol);
        assert_eq!(text.contains("would have met the tolerance"), adequate, "{text}");
        assert_eq!(text.contains("every cheaper sub-sampling misses"), !adequate, "{text}");
    }
}

/// `run_reporting` says what it simulates: first the plan's wavelengths, then each tripling of
/// the sub-bands with the check that asked for it, up to the count the run settles on. On the
/// paper's 80 nm bands at 1e-2 the pilot's count is short (the spectral bench above), so the run
/// triples at least once.
#[test]
fn the_spectral_check_reports_each_tripling() {
    use doefab::optics::plan::run_reporting;
    use doefab::sweep::spectral::paper_bands;
    let (doe, bands) = (built_in_doe(), paper_bands().unwrap());
    let p = plan(&scene(), &doe, &bands, 1e-2).unwrap();
    let mut said = Vec::new();
    let (_, ran) = run_reporting(&p, &doe, &bands, &mut |m| said.push(m.to_string())).unwrap();
    assert!(said[0].starts_with("PSF by"), "{said:?}");
    let mut n = p.spectral_samples;
    for m in &said[1..] {
        assert!(m.starts_with(&format!("spectral check: {n} sub-bands")), "{m}");
        n *= 3;
        assert!(m.ends_with(&format!("simulating {n} per band")), "{m}");
    }
    assert!(said.len() >= 2, "no tripling: {said:?}");
    assert_eq!(n, ran.spectral_samples, "{said:?}");
}
