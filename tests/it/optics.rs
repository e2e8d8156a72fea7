//! Optics stage: analytic truths (Airy pattern, grating orders), energy conservation,
//! agreement between the propagation methods, validity guards, the shared measured PSF.

use crate::common;

use doefab::fabrication::quantize::order_efficiency;
use doefab::grid::{Grid, Unit};
use doefab::material::Material;
use doefab::optics::propagate::{self, field_power, matrix_dft};
use doefab::optics::system::OpticalSystem;
use doefab::optics::{simulate, Method, Options, Psf};
use doefab::{Condition, DataCause, Error, FormatCause};
use ndarray::Array2;

const L550: f64 = 550e-9;

/// A small F/7 system at 550 nm: 1 mm aperture, g = d_s = 7 mm, 5 um pupil pitch.
fn f7(sensor_pitch: f64, crop: usize) -> OpticalSystem {
    OpticalSystem {
        aperture: 1e-3,
        doe_to_lens: 2e-3,
        focal_length: 7e-3,
        lens_to_sensor: 7e-3,
        sensor_pitch,
        crop,
        pupil_pitch: 5e-6,
        pupil_window: 1.02e-3,
        wavelengths: vec![L550],
        ..Default::default()
    }
}

fn flat(n: usize, pitch: f64) -> Grid {
    Grid::new(Array2::zeros((n, n)), [pitch; 2], Unit::Metre).unwrap()
}

/// Heights of a grating along x: `phase(x mod period)` in radians at `wavelength` in PDMS.
fn grating(n: usize, pitch: f64, wavelength: f64, phase: impl Fn(usize) -> f64) -> Grid {
    let dn = Material::pdms().index(wavelength).unwrap() - 1.0;
    let k = 2.0 * std::f64::consts::PI / wavelength;
    Grid::new(Array2::from_shape_fn((n, n), |(_, j)| phase(j) / (k * dn)), [pitch; 2], Unit::Metre).unwrap()
}

#[test]
fn flat_doe_gives_the_airy_pattern() {
    // 0.25 um pixels, odd crop: the axis sits on a pixel centre.
    let s = f7(0.25e-6, 81);
    let doe = flat(204, 5e-6);
    let psf = simulate(&s, &doe, Method::MatrixDft, &Options::default()).unwrap();
    let g = &psf.channels[0].grid;
    let row = g.values().row(40);
    // First zero of the central row between 4 and 5.5 um, refined by a parabola through
    // the smallest sample and its neighbours.
    let (k, _) =
        (56..62).map(|j| (j, row[j])).fold((0, f64::INFINITY), |b, (j, v)| if v < b.1 { (j, v) } else { b });
    // The field is real and changes sign at the zero: signed amplitudes, the sign flipping on
    // the side of the smaller neighbour, and the root of the parabola through them.
    let (a, b, c) = (row[k - 1].sqrt(), row[k].sqrt(), row[k + 1].sqrt());
    let (a, b, c) = if a < c { (a, -b, -c) } else { (a, b, -c) };
    let (qa, qb, qc) = (0.5 * (a + c) - b, 0.5 * (c - a), b);
    let disc = (qb * qb - 4.0 * qa * qc).sqrt();
    let roots = [(-qb + disc) / (2.0 * qa), (-qb - disc) / (2.0 * qa)];
    let t = roots.into_iter().find(|t| t.abs() <= 1.0).expect("a root between the samples");
    let x0 = g.x(k) + 0.25e-6 * t;
    let airy = 1.22 * L550 * 7.0;
    assert!((airy - 4.697e-6).abs() < 2e-9);
    assert!((x0 - airy).abs() < 0.01e-6, "first zero at {x0} m, Airy {airy} m");
    // Encircled energy inside the first zero: 0.838 of the power through the aperture.
    let captured = psf.channels[0].captured.unwrap();
    let ee = psf.encircled_energy(0, [0.0, 0.0], airy) * captured;
    assert!((ee - 0.838).abs() < 3e-3, "encircled energy {ee}");
    // Peak intensity equals the analytic P A / (lambda g)^2 with A the sampled aperture area:
    // a flat DOE has Strehl 1 against the ideal lens.
    let (n, dx) = matrix_dft::pupil_grid(&s, &doe);
    let u = s.pupil_field(&doe, n, dx, L550, true).unwrap();
    let area = field_power(&u, dx);
    let peak = psf.peak(0).0 * captured * area / (0.25e-6f64).powi(2);
    let ideal = area * area / (L550 * 7e-3).powi(2);
    assert!((peak / ideal - 1.0).abs() < 1e-6, "peak {peak} vs {ideal}");
    assert_eq!(psf.strehl(&psf).unwrap(), vec![1.0]);
    assert_eq!(psf.peak(0).2, (40, 40));
}

/// Energy of each diffraction order in a box half the order spacing wide, relative to the
/// flat DOE's energy in the same box around the axis.
fn order_energies(psf: &Psf, flat: &Psf, spacing: f64, orders: &[i64]) -> Vec<(f64, [f64; 2])> {
    let g = &psf.channels[0].grid;
    let gf = &flat.channels[0].grid;
    let (ca, cf) = (psf.channels[0].captured.unwrap(), flat.channels[0].captured.unwrap());
    let box_sum = |grid: &Grid, xc: f64| {
        let (mut s, mut sx) = (0.0, 0.0);
        for ((i, j), &v) in grid.values().indexed_iter() {
            if (grid.x(j) - xc).abs() < 0.5 * spacing && grid.y(i).abs() < 0.5 * spacing {
                s += v;
                sx += v * grid.x(j);
            }
        }
        (s, sx / s)
    };
    let reference = box_sum(gf, 0.0).0 * cf;
    orders
        .iter()
        .map(|&m| {
            let (e, x) = box_sum(g, m as f64 * spacing);
            (e * ca / reference, [x, 0.0])
        })
        .collect()
}

#[test]
fn binary_and_blazed_gratings_match_scalar_theory() {
    // Period 8 samples = 40 um: orders every lambda g / L = 96.25 um.
    let (pitch, period) = (5e-6, 8usize);
    // Cells: the DOE is piecewise constant, so a grating of whole cells is the continuous one.
    let s = OpticalSystem { cells: true, ..f7(1.75e-6, 401) };
    let spacing = L550 * 7e-3 / (period as f64 * pitch);
    let flat_psf = simulate(&s, &flat(204, pitch), Method::MatrixDft, &Options::default()).unwrap();
    let binary =
        grating(204, pitch, L550, |j| if j % period < period / 2 { 0.0 } else { std::f64::consts::PI });
    let psf = simulate(&s, &binary, Method::MatrixDft, &Options::default()).unwrap();
    let orders = [-2i64, -1, 0, 1, 2];
    let e = order_energies(&psf, &flat_psf, spacing, &orders);
    for (k, &m) in orders.iter().enumerate() {
        let want = order_efficiency(2, 1.0, m);
        assert!((e[k].0 - want).abs() < 2e-3, "binary order {m}: {} vs {want}", e[k].0);
        if m.abs() == 1 {
            assert!((want - 0.4053).abs() < 1e-4);
            // Order m lands at m lambda g / L.
            assert!((e[k].1[0] - m as f64 * spacing).abs() < 0.05e-6, "order {m} at {:?}", e[k].1);
        }
    }
    // The brightest peaks are the +-1 orders, each 0.405 of the flat DOE's peak; nothing at
    // the centre.
    let strehl = psf.strehl(&flat_psf).unwrap()[0];
    assert!((strehl - 0.4053).abs() < 3e-3, "Strehl {strehl}");
    assert!(psf.channels[0].grid.values()[[200, 200]] < 1e-3 * psf.peak(0).0);

    // Four-level staircase of a blaze: order +1 carries sinc^2(1/4) = 0.811, order -3 0.090.
    let blazed = grating(204, pitch, L550, |j| 2.0 * std::f64::consts::PI * ((j % period) / 2) as f64 / 4.0);
    let psf = simulate(&s, &blazed, Method::MatrixDft, &Options::default()).unwrap();
    let orders = [-3i64, -1, 0, 1, 2];
    let e = order_energies(&psf, &flat_psf, spacing, &orders);
    for (k, &m) in orders.iter().enumerate() {
        let want = order_efficiency(4, 1.0, m);
        assert!((e[k].0 - want).abs() < 3e-3, "4-level order {m}: {} vs {want}", e[k].0);
    }
    assert!((order_efficiency(4, 1.0, 1) - 0.8106).abs() < 1e-4);
}

/// A smooth test DOE: three sinusoidal phase gratings of 1 rad with periods of 10+ samples.
fn smooth_doe(n: usize, pitch: f64, wavelength: f64) -> Grid {
    let dn = Material::pdms().index(wavelength).unwrap() - 1.0;
    let k = 2.0 * std::f64::consts::PI / wavelength;
    let c = (n as f64 - 1.0) * 0.5;
    Grid::new(
        Array2::from_shape_fn((n, n), |(i, j)| {
            let (x, y) = (j as f64 - c, i as f64 - c);
            let phase = 1.0 + (0.41 * x).sin() + (0.23 * y + 0.3).cos() + 0.8 * (0.17 * (x + y)).sin();
            phase / (k * dn)
        }),
        [pitch; 2],
        Unit::Metre,
    )
    .unwrap()
}

/// F/100 at 635 and 450 nm: 0.25 mm aperture, 10 um pixels sampled twice per pixel, the pupil at
/// 5 um in a 2.2 mm window (the transfer-function methods need a window wider than the replica
/// period lambda g / dx), slow enough that the paraxial and non-paraxial models agree.
fn f100() -> OpticalSystem {
    OpticalSystem {
        aperture: 0.25e-3,
        doe_to_lens: 1e-3,
        focal_length: 25e-3,
        lens_to_sensor: 25e-3,
        sensor_pitch: 10e-6,
        crop: 32,
        subsample: 2,
        pupil_pitch: 5e-6,
        pupil_window: 2.2e-3,
        wavelengths: vec![635e-9, 450e-9],
        ..Default::default()
    }
}

#[test]
fn methods_agree_on_a_shared_valid_configuration() {
    // Sampled at 5 um (two sub-samples per 10 um pixel), the two paraxial methods differ by
    // 1.0e-4 at 450 nm and the angular spectrum by 1.28e-4: the replica period
    // lambda d_s / dx = 2.25 mm puts the sampled pupil's aliased edge-diffraction tails near the
    // crop, and the FFT methods wrap them in their window while the matrix DFT sums the replicas.
    // Not non-paraxial terms: at 2.5 um (four sub-samples, every method on the same
    // interpolated pupil) the paraxial pair agrees to 1e-5 and the angular spectrum, the only
    // non-paraxial one, to 7.6e-5.
    let s = OpticalSystem { subsample: 4, pupil_pitch: 2.5e-6, pupil_window: 4.4e-3, ..f100() };
    let doe = smooth_doe(440, 5e-6, 530e-9);
    let psfs: Vec<Psf> = [Method::MatrixDft, Method::Fresnel, Method::AngularSpectrum]
        .into_iter()
        .map(|m| {
            assert_eq!(propagate::check(m, &s, &doe).unwrap(), vec![], "{m}");
            simulate(&s, &doe, m, &Options::default()).unwrap()
        })
        .collect();
    for (a, b) in [(1, 0), (2, 0), (2, 1)] {
        let e = psfs[a].relative_l2(&psfs[b]).unwrap();
        assert!(e[0] < 1e-4 && e[1] < 1e-4, "{} vs {}: {e:?}", psfs[a].method, psfs[b].method);
    }
    // The two paraxial methods agree far closer.
    let e = psfs[1].relative_l2(&psfs[0]).unwrap();
    assert!(e[0] < 4e-5 && e[1] < 2e-5, "{e:?}");
    // Every method puts the same share of the DOE's power into the crop.
    for p in &psfs[1..] {
        for c in 0..2 {
            let (a, b) = (p.channels[c].captured.unwrap(), psfs[0].channels[c].captured.unwrap());
            assert!((a - b).abs() < 2e-4, "{} captured {a} vs {b}", p.method);
        }
    }
    // At 5 um the 450 nm channel shows the wrapped tails.
    let coarse = OpticalSystem { subsample: 2, pupil_pitch: 5e-6, ..s };
    let m = simulate(&coarse, &doe, Method::MatrixDft, &Options::default()).unwrap();
    let f = simulate(&coarse, &doe, Method::Fresnel, &Options::default()).unwrap();
    let e = f.relative_l2(&m).unwrap();
    assert!(e[0] < 5e-5 && e[1] > 1e-4, "{e:?}");
}

#[test]
fn rayleigh_sommerfeld_ground_truth_agrees_on_a_tiny_grid() {
    // 90 x 90 pupil samples at 5 um, F/50, d_phi = 14 mm: the direct integral's kernel is sampled
    // (phase steps below pi) and the 0.9 mm lens window holds the light.
    let s = OpticalSystem {
        aperture: 0.25e-3,
        doe_to_lens: 14e-3,
        focal_length: 12.5e-3,
        lens_to_sensor: 12.5e-3,
        sensor_pitch: 5e-6,
        crop: 16,
        pupil_pitch: 5e-6,
        pupil_window: 0.45e-3,
        wavelengths: vec![635e-9],
        ..Default::default()
    };
    let doe = flat(90, 5e-6);
    assert_eq!(propagate::check(Method::RayleighSommerfeld, &s, &doe).unwrap(), vec![]);
    let rs = simulate(&s, &doe, Method::RayleighSommerfeld, &Options::default()).unwrap();
    let m1 = simulate(&s, &doe, Method::MatrixDft, &Options::default()).unwrap();
    let e = m1.relative_l2(&rs).unwrap()[0];
    assert!(e < 2.5e-3, "matrix DFT vs Rayleigh-Sommerfeld: {e}");
    // Half the distance breaks the kernel sampling and the guard says so.
    let near = OpticalSystem { doe_to_lens: 7e-3, ..s };
    let v = propagate::check(Method::RayleighSommerfeld, &near, &doe).unwrap();
    assert!(v.iter().any(|v| v.condition == "kernel_sampling"), "{v:?}");
}

#[test]
fn the_paper_setup_violates_the_lens_sampling_of_method_2_at_530_and_450_nm() {
    // The paper's own system: 4.29 um pupil sampling at F/7, 635 / 530 / 450 nm.
    let s = OpticalSystem::default();
    let doe = flat(1306, 4.29e-6);
    let v = propagate::check(Method::Fresnel, &s, &doe).unwrap();
    let got: Vec<(String, u32)> =
        v.iter().map(|v| (v.condition.clone(), (v.wavelength * 1e9).round() as u32)).collect();
    assert_eq!(got, vec![("lens_sampling".to_string(), 530), ("lens_sampling".to_string(), 450)]);
    assert!(v[0].message.contains("4.290 um exceeds lambda F# = 3.710 um"), "{}", v[0].message);
    // The single transform has no lens to sample: valid at all three.
    assert_eq!(propagate::check(Method::MatrixDft, &s, &doe).unwrap(), vec![]);
    // Both sides of the boundary dx = lambda F#: 4.29 um / 7 = 612.86 nm.
    let edge = OpticalSystem { wavelengths: vec![613e-9, 612.7e-9], ..s };
    let v = propagate::check(Method::Fresnel, &edge, &doe).unwrap();
    assert_eq!(v.len(), 1);
    assert_eq!((v[0].condition.as_str(), v[0].wavelength), ("lens_sampling", 612.7e-9));
}

#[test]
fn an_invalid_configuration_is_refused_or_runs_with_a_warning() {
    // The paper's sampling and F-number on a smaller aperture (same lens-sampling condition).
    let s = OpticalSystem {
        aperture: 0.5e-3,
        focal_length: 3.5e-3,
        lens_to_sensor: 3.5e-3,
        doe_to_lens: 1e-3,
        crop: 64,
        pupil_window: 0.6e-3,
        ..Default::default()
    };
    let doe = flat(140, 4.29e-6);
    let e = simulate(&s, &doe, Method::Fresnel, &Options::default()).unwrap_err();
    assert!(matches!(e, Error::Validity { condition: Condition::Propagation, .. }), "{e:?}");
    let e = e.to_string();
    assert!(e.contains("lens_sampling at 530.0 nm") && e.contains("lens_sampling at 450.0 nm"), "{e}");
    assert!(!e.contains("635.0 nm"), "{e}");
    let psf =
        simulate(&s, &doe, Method::Fresnel, &Options { allow_invalid: true, ..Default::default() }).unwrap();
    assert_eq!(psf.warnings.len(), 2);
    assert!(psf.warnings[0].contains("lens_sampling"));
    let valid = simulate(&s, &doe, Method::MatrixDft, &Options::default()).unwrap();
    assert!(valid.warnings.is_empty());
    for c in &psf.channels {
        assert!((c.grid.values().sum() - 1.0).abs() < 1e-12);
    }
}

#[test]
fn guards_trigger_on_both_sides_of_their_boundaries() {
    let has = |m: Method, s: &OpticalSystem, doe: &Grid, cond: &str| {
        propagate::check(m, s, doe).unwrap().iter().any(|v| v.condition == cond)
    };
    let doe = flat(204, 5e-6);
    // Matrix DFT: the sensor window against the replica period lambda g / dx = 770 um.
    assert!(!has(Method::MatrixDft, &f7(1.75e-6, 439), &doe, "output_window"));
    assert!(has(Method::MatrixDft, &f7(1.75e-6, 441), &doe, "output_window"));

    // DOE phase gradient: a tilt of 0.98 pi per sample passes, 1.02 pi fails; a wrapped tilt of
    // 0.5 pi per sample (with its 2 pi drops) passes.
    let tilt = |per_sample: f64, wrap: bool| {
        grating(204, 5e-6, L550, move |j| {
            let p = per_sample * j as f64;
            if wrap {
                p.rem_euclid(2.0 * std::f64::consts::PI)
            } else {
                p
            }
        })
    };
    let s = f7(1.75e-6, 101);
    assert!(!has(Method::MatrixDft, &s, &tilt(0.98 * std::f64::consts::PI, false), "phase_gradient"));
    assert!(has(Method::MatrixDft, &s, &tilt(1.02 * std::f64::consts::PI, false), "phase_gradient"));
    assert!(!has(Method::MatrixDft, &s, &tilt(0.5 * std::f64::consts::PI, true), "phase_gradient"));

    // Fresnel transfer function over d_phi: lambda z <= window x pitch.
    let s = OpticalSystem { wavelengths: vec![635e-9], ..f100() };
    let doe = smooth_doe(440, 5e-6, 530e-9);
    let (_, dx, w) = propagate::fresnel::grid(&s);
    let limit = w as f64 * dx * dx / 635e-9;
    let at = |z: f64| OpticalSystem { doe_to_lens: z, ..s.clone() };
    assert!(!has(Method::Fresnel, &at(0.99 * limit), &doe, "transfer_function_bandwidth"));
    assert!(has(Method::Fresnel, &at(1.01 * limit), &doe, "transfer_function_bandwidth"));

    // Fresnel approximation, out of focus: k d_phi theta^4 / 8 <= pi/2 with theta = lambda / (2 dx)
    // for a binary grating (which fills the band).
    let binary = grating(204, 5e-6, L550, |j| if j % 2 == 0 { 0.0 } else { std::f64::consts::PI });
    let theta: f64 = L550 / (2.0 * 5e-6);
    let k = 2.0 * std::f64::consts::PI / L550;
    let dz = 0.5 * std::f64::consts::PI * 8.0 / (k * theta.powi(4));
    let defocus = |z: f64| OpticalSystem { doe_to_lens: z, lens_to_sensor: 7.07e-3, ..f7(1.75e-6, 101) };
    assert!(!has(Method::MatrixDft, &defocus(0.98 * dz), &binary, "fresnel_approximation"));
    assert!(has(Method::MatrixDft, &defocus(1.02 * dz), &binary, "fresnel_approximation"));
    // In focus the d_phi step cannot change the sensor intensity: no check.
    let focus = OpticalSystem { lens_to_sensor: 7e-3, ..defocus(2.0 * dz) };
    assert!(!has(Method::MatrixDft, &focus, &binary, "fresnel_approximation"));
}

#[test]
fn in_focus_the_single_transform_does_not_depend_on_d_phi() {
    let doe = smooth_doe(204, 5e-6, L550);
    let a = simulate(
        &OpticalSystem { doe_to_lens: 2e-3, ..f7(1.75e-6, 101) },
        &doe,
        Method::MatrixDft,
        &Options::default(),
    )
    .unwrap();
    let b = simulate(
        &OpticalSystem { doe_to_lens: 30e-3, ..f7(1.75e-6, 101) },
        &doe,
        Method::MatrixDft,
        &Options::default(),
    )
    .unwrap();
    assert!(a.relative_l2(&b).unwrap()[0] < 1e-12);
    // Out of focus it does.
    let c = simulate(
        &OpticalSystem { doe_to_lens: 30e-3, lens_to_sensor: 7.02e-3, ..f7(1.75e-6, 101) },
        &doe,
        Method::MatrixDft,
        &Options::default(),
    )
    .unwrap();
    let d = simulate(
        &OpticalSystem { doe_to_lens: 2e-3, lens_to_sensor: 7.02e-3, ..f7(1.75e-6, 101) },
        &doe,
        Method::MatrixDft,
        &Options::default(),
    )
    .unwrap();
    assert!(c.relative_l2(&d).unwrap()[0] > 1e-3);
}

#[test]
fn each_propagation_step_conserves_energy() {
    use doefab::fft::{fft_freq, Plan2d};
    use rustfft::num_complex::Complex64;
    // A field with structure at every frequency.
    let n = 96;
    let dx = 4e-6;
    let u = Array2::from_shape_fn((n, n), |(i, j)| {
        Complex64::from_polar(1.0 + ((i * 7 + j * 3) % 5) as f64, (i * j) as f64 * 0.37)
    });
    let e0 = field_power(&u, dx);
    let plan = Plan2d::new(n);
    // Fresnel transfer function: unit modulus everywhere.
    let h = Array2::from_shape_fn((n, n), |(p, q)| {
        let f2 = fft_freq(p, n, dx).powi(2) + fft_freq(q, n, dx).powi(2);
        Complex64::from_polar(1.0, -std::f64::consts::PI * L550 * 3e-3 * f2)
    });
    let mut v = u.clone();
    plan.convolve(&mut v, &h);
    assert!((field_power(&v, dx) / e0 - 1.0).abs() < 1e-12);
    // Band-limited angular spectrum: unit modulus inside the band; a field inside the band
    // (a smooth Gaussian beam) keeps its energy.
    let c = (n as f64 - 1.0) * 0.5;
    let g = Array2::from_shape_fn((n, n), |(i, j)| {
        let r2 = ((i as f64 - c).powi(2) + (j as f64 - c).powi(2)) * dx * dx;
        Complex64::new((-r2 / (2.0 * (40e-6f64).powi(2))).exp(), 0.0)
    });
    let mut v = g.clone();
    plan.convolve(&mut v, &propagate::asm::transfer(L550, 2e-3, n, dx, false));
    assert!((field_power(&v, dx) / field_power(&g, dx) - 1.0).abs() < 1e-10);

    // The thin lens has unit modulus; the two-step Fresnel chain read over its whole window
    // keeps all the power.
    let s = OpticalSystem {
        aperture: 0.2e-3,
        doe_to_lens: 1e-3,
        focal_length: 5e-3,
        lens_to_sensor: 5e-3,
        sensor_pitch: 4e-6,
        crop: 90,
        pupil_pitch: 4e-6,
        pupil_window: 0.24e-3,
        wavelengths: vec![L550],
        ..Default::default()
    };
    let (_, _, w) = propagate::fresnel::grid(&s);
    assert_eq!(w, 90);
    let doe = smooth_doe(60, 4e-6, L550);
    let psf =
        simulate(&s, &doe, Method::Fresnel, &Options { allow_invalid: true, ..Default::default() }).unwrap();
    assert!((psf.channels[0].captured.unwrap() - 1.0).abs() < 1e-12);

    // The single transform over one full replica period, sampled at lambda g / (n dx), is a
    // unitary DFT.
    let s = f7(1.75e-6, 101);
    let doe = smooth_doe(204, 5e-6, L550);
    let (n, dx) = matrix_dft::pupil_grid(&s, &doe);
    let u1 = s.pupil_field(&doe, n, dx, L550, true).unwrap();
    let p = L550 * 7e-3 / (n as f64 * dx);
    let xs: Vec<f64> = (0..n).map(|q| (q as f64 - (n as f64 - 1.0) * 0.5) * p).collect();
    let i = matrix_dft::transform::<f64>(&s, &u1, dx, &xs, L550).unwrap();
    assert!((i.sum() * p * p / field_power(&u1, dx) - 1.0).abs() < 1e-10);
}

#[test]
fn the_measured_psf_loads_through_the_same_type() {
    let path = common::shared_data("deepoptics-hdr/measured_psf.npz");
    let psf = Psf::read_npz(&path, Some("psf_val"), 4.29e-6, Some(&[635e-9, 530e-9, 450e-9])).unwrap();
    assert_eq!(psf.dim(), (319, 319));
    assert_eq!(psf.to_array4().dim(), (319, 319, 1, 3));
    let names: Vec<&str> = psf.channels.iter().map(|c| c.name.as_str()).collect();
    assert_eq!(names, ["R", "G", "B"]);
    for (c, ch) in psf.channels.iter().enumerate() {
        assert!((ch.grid.values().sum() - 1.0).abs() < 1e-9);
        let (_, _, (i, j)) = psf.peak(c);
        assert!(i.abs_diff(159) <= 1 && j.abs_diff(159) <= 1, "channel {c} peak at {i}, {j}");
        // Centroid about (+1.8, -1.0) px off centre in (row, column) order: y down, x left.
        let [x, y] = psf.centroid(c);
        assert!((y / 4.29e-6 - 1.8).abs() < 1.0 && (x / 4.29e-6 + 1.0).abs() < 1.0, "centroid {x} {y}");
    }
    assert_eq!(psf.peak(2).2, (159, 160));
    // The same measures work across PSFs of one shape: it differs from itself by nothing.
    assert_eq!(psf.relative_l2(&psf).unwrap(), vec![0.0; 3]);
    // Errors name the archive and the array.
    let e = Psf::read_npz(&path, Some("nope"), 4.29e-6, None).unwrap_err();
    assert_eq!(common::format_cause(&e), (FormatCause::Malformed, None, path.as_path()), "{e}");
    assert!(e.to_string().contains("no array 'nope'"), "{e}");
}

#[test]
fn bad_input_is_refused_with_a_clear_error() {
    let s = f7(1.75e-6, 101);
    let err =
        |s: &OpticalSystem, doe: &Grid, m: Method| simulate(s, doe, m, &Options::default()).unwrap_err();
    let param = |e: &Error| match e {
        Error::Parameter { name, .. } => name.clone(),
        other => panic!("expected a refused parameter, got {other:?}"),
    };
    // Heights with NaN inside the aperture.
    let mut v = Array2::zeros((204, 204));
    v[[100, 90]] = f64::NAN;
    let nan = Grid::new(v, [5e-6; 2], Unit::Metre).unwrap();
    let e = err(&s, &nan, Method::MatrixDft);
    assert!(matches!(e, Error::Data { cause: DataCause::NotFinite, .. }), "{e:?}");
    // An aperture larger than the grid.
    assert_eq!(param(&err(&s, &flat(150, 5e-6), Method::MatrixDft)), "aperture");
    // A wavelength outside the material's range names the range.
    let ir = OpticalSystem { wavelengths: vec![900e-9], ..s.clone() };
    let e = err(&ir, &flat(204, 5e-6), Method::MatrixDft);
    assert!(matches!(e, Error::Validity { condition: Condition::Domain, .. }), "{e:?}");
    assert!(e.to_string().contains("400-700 nm"), "{e}");
    // Zero and negative distances.
    let zero = OpticalSystem { focal_length: 0.0, ..s.clone() };
    assert_eq!(param(&err(&zero, &flat(204, 5e-6), Method::MatrixDft)), "focal_length");
    let neg = OpticalSystem { object_distance: Some(-1.0), ..s.clone() };
    assert_eq!(param(&err(&neg, &flat(204, 5e-6), Method::Fresnel)), "object_distance");
    // A sensor crop larger than the propagation window.
    let wide = OpticalSystem { sensor_pitch: 5e-6, pupil_pitch: 5e-6, crop: 400, ..s.clone() };
    let e = err(&wide, &flat(204, 5e-6), Method::Fresnel);
    assert!(matches!(e, Error::Validity { condition: Condition::Propagation, .. }), "{e:?}");
    assert!(e.to_string().contains("the sensor crop needs 400 samples"), "{e}");
    // Heights that are not metres.
    let levels = Grid::new(Array2::zeros((204, 204)), [5e-6; 2], Unit::Level).unwrap();
    assert_eq!(param(&err(&s, &levels, Method::MatrixDft)), "doe");
}

#[test]
fn psf_command_writes_exr_npy_png_and_json() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("psf");
    let run = std::process::Command::new(env!("CARGO_BIN_EXE_doefab"))
        .args(["psf", "built-in:paper", "--explain", "-o"])
        .arg(&out)
        .arg("--json")
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert!(run.status.success(), "{stderr}");
    // The default plan at 1e-3: the DOE's own samples, Gauss-Legendre pixels, f32, and the
    // explanation of each choice on stderr.
    for needle in [
        "plan for tolerance 1.0e-3",
        "pupil pitch",
        "the DOE's own 4.290 um samples",
        "precision",
        "f32",
        // After the run, the rejected cheaper sub-samplings measured against the plan's.
        "measured: the cheaper pixel sub-samplings against the plan's 4 x 4 run",
        "3 x 3: ",
    ] {
        assert!(stderr.contains(needle), "{needle}: {stderr}");
    }
    let report: serde_json::Value = serde_json::from_slice(&run.stdout).unwrap();
    assert_eq!(report["method"], "matrix_dft (plan, tolerance 1e-3)");
    assert_eq!(report["plan"]["precision"], "f32");
    assert_eq!(report["plan"]["system"]["pixel_rule"], "gauss_legendre");
    assert!(report["plan"]["estimate"]["total"].as_f64().unwrap() <= 1e-3);
    let channels = report["channels"].as_array().unwrap();
    assert_eq!(channels.len(), 3);
    for c in channels {
        // The grating-like design moves light into its copies: Strehl below 1.
        let strehl = c["strehl"].as_f64().unwrap();
        assert!(strehl > 0.05 && strehl < 0.95, "{strehl}");
        assert!(c["captured"].as_f64().unwrap() > 0.5);
        // The central peak and six copies, brightest first, the first at the peak pixel.
        let peaks = c["peaks"].as_array().unwrap();
        assert_eq!(peaks.len(), 7);
        assert_eq!(peaks[0]["position"], c["peak_position"]);
        assert!(peaks.windows(2).all(|w| w[0]["value"].as_f64() >= w[1]["value"].as_f64()));
    }
    for f in ["psf.exr", "psf.npy", "psf_log.png", "psf.json"] {
        assert!(out.join(f).exists(), "{f}");
    }
    let (h, arr) = doefab::io::npy::read_npy_nd(&out.join("psf.npy")).unwrap();
    assert_eq!(h.shape, vec![320, 320, 1, 3]);
    assert_eq!(h.descr, "<f4");
    for c in 0..3 {
        let s: f64 = arr.index_axis(ndarray::Axis(3), c).sum();
        assert!((s - 1.0).abs() < 1e-4, "channel {c} sums to {s}");
    }
    let exr = doefab::io::exr::read_exr(&out.join("psf.exr"), Some("530nm")).unwrap();
    assert_eq!(exr.pitch, Some([4.29e-6, 4.29e-6]));
    assert!(exr.metadata.iter().any(|(k, v)| k == "method" && v == "matrix_dft (plan, tolerance 1e-3)"));
    assert!(exr.metadata.iter().any(|(k, v)| k == "wavelengths_m" && v == "6.35e-7,5.3e-7,4.5e-7"));
}

#[test]
fn a_finite_object_focuses_at_the_thin_lens_image_distance() {
    // Point source 0.2 m before the DOE, DOE 2 mm before the lens: the image forms at
    // 1/d_i = 1/g - 1/(z_o + d_phi). The brightest pixel is there, not 3% nearer or farther,
    // and as bright as an object at infinity in focus scaled by (g / B)^2, B = d_phi + d_i -
    // d_phi d_i / g the distance that sets the image-side aperture angle.
    let (z_o, d_phi, g) = (0.2, 2e-3, 7e-3);
    let d_i = 1.0 / (1.0 / g - 1.0 / (z_o + d_phi));
    let doe = flat(204, 5e-6);
    let peak = |ds: f64, m: Method| {
        let s = OpticalSystem {
            object_distance: if ds == g { None } else { Some(z_o) },
            lens_to_sensor: ds,
            sensor_pitch: 0.5e-6,
            crop: 41,
            subsample: 1,
            ..f7(0.5e-6, 41)
        };
        let psf = simulate(&s, &doe, m, &Options::default()).unwrap();
        psf.peak(0).0 * psf.channels[0].captured.unwrap()
    };
    let at = peak(d_i, Method::MatrixDft);
    assert!(at > 1.5 * peak(d_i * 0.97, Method::MatrixDft));
    assert!(at > 1.5 * peak(d_i * 1.03, Method::MatrixDft));
    let infinity = peak(g, Method::MatrixDft);
    let b = d_phi + d_i - d_phi * d_i / g;
    assert!((at / infinity / (g / b).powi(2) - 1.0).abs() < 2e-3, "{at} vs {infinity}");
    assert_eq!(Method::from_name("angular-spectrum").unwrap(), Method::AngularSpectrum);
    let e = Method::from_name("fft").unwrap_err();
    assert!(matches!(e, Error::Parameter { ref name, .. } if name == "method"), "{e:?}");
}

#[test]
fn the_folded_real_transform_equals_the_direct_collins_sum_in_f64_and_f32() {
    use doefab::optics::Precision;
    use rustfft::num_complex::Complex64;
    // Defocused (A != 0), cells on, an asymmetric field, odd pupil and both crop parities.
    for (n, crop) in [(41usize, 12usize), (40, 7)] {
        let s = OpticalSystem {
            lens_to_sensor: 7.3e-3,
            cells: true,
            crop,
            subsample: 1,
            sensor_pitch: 3e-6,
            ..f7(3e-6, crop)
        };
        let dx = 5e-6;
        let u1 = Array2::from_shape_fn((n, n), |(i, j)| {
            Complex64::from_polar(1.0 + 0.3 * ((i + 2 * j) % 3) as f64, 0.1 * (i * i) as f64 + 0.7 * j as f64)
        });
        let xs = s.sensor_coords();
        let got = matrix_dft::transform::<f64>(&s, &u1, dx, &xs, L550).unwrap();
        let got32 = matrix_dft::transform::<f32>(&s, &u1, dx, &xs, L550).unwrap();
        // Collins' integral summed term by term.
        let m = s.abcd();
        let lb = L550 * m.b;
        let c = (n as f64 - 1.0) * 0.5;
        let u = |j: usize| (j as f64 - c) * dx;
        let sinc = doefab::optics::system::sinc;
        let pi = std::f64::consts::PI;
        let mut want = Array2::<f64>::zeros((crop, crop));
        for ((p, q), w) in want.indexed_iter_mut() {
            let (y, x) = (xs[p], xs[q]);
            let mut acc = Complex64::new(0.0, 0.0);
            for ((i, j), v) in u1.indexed_iter() {
                let ph =
                    pi * m.a * (u(i).powi(2) + u(j).powi(2)) / lb - 2.0 * pi * (x * u(j) + y * u(i)) / lb;
                acc += v * Complex64::from_polar(1.0, ph);
            }
            *w = (acc * sinc(x * dx / lb) * sinc(y * dx / lb)).norm_sqr() * (dx * dx / lb).powi(2);
        }
        let e = doefab::optics::psf::relative_l2(&got, &want);
        assert!(e < 1e-12, "n {n} crop {crop}: f64 {e}");
        let e32 = doefab::optics::psf::relative_l2(&got32, &want);
        assert!(e32 < 1e-6 && e32 > 1e-10, "n {n} crop {crop}: f32 {e32}");
    }
    // Points not symmetric about the axis are refused.
    let s = f7(3e-6, 4);
    let u1 = Array2::from_elem((8, 8), Complex64::new(1.0, 0.0));
    let e = matrix_dft::transform::<f64>(&s, &u1, 5e-6, &[0.0, 1e-6, 2e-6], L550).unwrap_err();
    assert!(matches!(e, Error::Parameter { .. }), "{e:?}");
    assert!(e.to_string().contains("symmetric"), "{e}");
    // f32 is refused for the FFT methods rather than silently run in f64.
    let doe = flat(204, 5e-6);
    let o = Options { precision: Precision::F32, ..Default::default() };
    let e = simulate(&f7(3e-6, 8), &doe, Method::Fresnel, &o).unwrap_err();
    assert!(matches!(e, Error::Parameter { ref name, .. } if name == "precision"), "{e:?}");
}

/// The stability maps of the two-step Fresnel method, the angular spectrum and the matrix DFT
/// (`bench stability`), and of the matrix DFT on a wrapped and a quantized DOE: over pupil
/// sampling x Fresnel number and pupil sampling x wavelength,
/// no run its guard accepts is over the tolerance (1e-2; for the transfer-function methods
/// not over 1e-3 either), runs on both sides of the guard's boundary are there, and the files
/// say the same. The Fresnel run at 0.97 lambda F# (g = 2.8 mm, s = 1), 1.3e-2 off its exact
/// truth, is refused for the DOE's bandwidth added to the lens phase's: the lens phase alone
/// would pass it. The angular spectrum's truth is non-paraxial: where the guard accepts, it
/// agrees with it to 4e-4 (measured 3.7e-4 at g = 4 mm, s = 1; 2.4e-5 or less at s >= 2),
/// while a paraxial truth would differ by 3e-2.
#[test]
fn the_stability_maps_count_no_silent_failure() {
    use doefab::sweep::stability::MapOptions;
    let d = tempfile::tempdir().unwrap();
    let out = d.path().join("stab");
    let r =
        doefab::pipeline::sweep::sweep_stability(&MapOptions::default(), &out, &mut |_, _, _| {}).unwrap();
    assert_eq!(r.maps.len(), 8);
    for m in &r.maps {
        assert_eq!(m.silent_failures, 0, "{:?}", m.cells.iter().filter(|c| c.silent).collect::<Vec<_>>());
        // None at a ten times tighter tolerance either, for the transfer-function methods.
        let over = m.cells.iter().filter(|c| c.violations.is_empty() && c.error > 1e-3);
        if m.method != "matrix_dft" {
            assert_eq!(over.count(), 0, "{}", m.y_axis);
        }
        assert!(m.cells.iter().any(|c| c.violations.is_empty() && c.error <= r.tolerance), "{}", m.y_axis);
        assert!(m.cells.iter().any(|c| !c.violations.is_empty() && c.error > r.tolerance), "{}", m.y_axis);
        let name = format!("stability_{}", m.name());
        let svg = std::fs::read_to_string(out.join(format!("{name}.svg"))).unwrap();
        assert!(svg.contains("silent failures: 0") && svg.contains(&m.limit), "{name}");
        assert!(out.join(format!("{name}.png")).exists());
    }
    for m in r.maps.iter().filter(|m| m.method == "angular_spectrum") {
        assert_eq!(m.cells.len(), 28, "{}", m.y_axis);
        let worst = m.cells.iter().filter(|c| c.violations.is_empty()).map(|c| c.error).fold(0.0, f64::max);
        assert!(worst < 4e-4, "{worst}");
    }
    // On the wrapped and quantized DOEs the matrix DFT of cells at the DOE's own samples and at
    // 2 x 2 and 3 x 3 nested ones is the part's PSF (within 2.5e-3, measured 2.1e-3: the
    // aperture's edge sampled at the pupil's pitch against the truth's 0.4 um), at every
    // wavelength, the steps accepted; every coarser pupil reads across the steps and is
    // refused (measured 8.2e-3 to 0.34 off).
    for m in &r.maps[6..] {
        assert_eq!((m.method.as_str(), m.y_axis.as_str()), ("matrix_dft", "wavelength"));
        for c in &m.cells {
            if c.pupil_pitch <= doefab::sweep::stability::STEPPED_DOE_PITCH * (1.0 + 1e-9) {
                assert!(c.violations.is_empty() && c.error < 2.5e-3, "{} {c:?}", m.design);
            } else {
                assert!(c.violations.iter().any(|v| v == "step_resampling"), "{} {c:?}", m.design);
            }
        }
    }
    assert_eq!((r.maps[6].design.as_str(), r.maps[7].design.as_str()), ("wrapped", "quantized"));
    // The matrix DFT's pupils coarser than the DOE's samples with more than pi / 2 per sample
    // are refused (`pupil_resampling`), and were over the tolerance: at 550 nm, g = 3.5 mm, the
    // 6.5 um pupil (2.0 rad per sample) is 1.3e-2 off.
    let mdft = &r.maps[5];
    assert_eq!(mdft.method, "matrix_dft");
    let c = mdft
        .cells
        .iter()
        .find(|c| (c.wavelength - 550e-9).abs() < 1e-15 && (c.pupil_pitch - 6.5e-6).abs() < 1e-15);
    let c = c.unwrap();
    assert!(c.error > r.tolerance, "{c:?}");
    assert_eq!(c.violations, ["pupil_resampling"]);
    let edge =
        r.maps[0].cells.iter().find(|c| c.subsample == 1 && (c.focal_length - 2.8e-3).abs() < 1e-12).unwrap();
    assert!(edge.lens_sampling_ratio < 1.0 && edge.error > r.tolerance, "{edge:?}");
    assert_eq!(edge.violations, ["lens_sampling"]);
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("stability.json")).unwrap()).unwrap();
    assert_eq!(json["maps"][0]["silent_failures"], 0);
    assert!((json["paper"][1]["lens_sampling_ratio"].as_f64().unwrap() - 4.29 / (0.53 * 7.0)).abs() < 1e-12);
}

/// A wrapped or quantized DOE is piecewise constant per sample, as the part is made: its steps
/// are no slopes to resolve. On the stability scene's wrapped and quantized DOEs (2 um samples,
/// wrapped at 550 nm, quantized to 4 levels), at 400, 450 and 650 nm, where every step is real
/// (the quantized DOE's wraps, three quarters of a period, are 2.3 rad from 2 pi at 650 nm: no
/// multiple of 2 pi), the guard accepts the DOE's own samples, and the matrix DFT of them as
/// cells (`cells`) is within 2.5e-3 of the part's truth (its piecewise-constant surface read at
/// 5 x 5 nested point samples per DOE sample, 5e-4 from its own cells; the rest is the
/// aperture's edge, sampled at 2 um against 0.4 um), the pupil of 2 x 2 samples nested by
/// nearest interpolation within 1e-3. As point samples (the paper's model) the DOE's own
/// samples are further off by the cell envelope: 1.1e-2 at 400 nm.
/// Bilinear interpolation onto the 2 x 2 pupil puts a ramp across each step, which the part does
/// not have: refused (`step_resampling`), and over 1e-2 off. Measured in the comments.
#[test]
fn a_stepped_pupil_is_exact_for_the_part_it_is() {
    use doefab::grid::Interpolation;
    use doefab::optics::psf::relative_l2;
    use doefab::optics::system::PixelRule;
    use doefab::sweep::psf::scene;
    use doefab::sweep::stability::{stepped_doe, STEPPED_DOE_PITCH};
    let (wrapped, quantized) = stepped_doe(4).unwrap();
    let pi = std::f64::consts::PI;
    for (name, doe) in [("wrapped", &wrapped), ("quantized", &quantized)] {
        for l in [400e-9, 450e-9, 650e-9] {
            let at = |pitch: f64, interpolation: Interpolation, cells: bool| OpticalSystem {
                pupil_pitch: pitch,
                interpolation,
                cells,
                subsample: 3,
                pixel_rule: PixelRule::GaussLegendre,
                wavelengths: vec![l],
                ..scene()
            };
            let psf = |s: &OpticalSystem| {
                let forced = Options { allow_invalid: true, ..Default::default() };
                simulate(s, doe, Method::MatrixDft, &forced).unwrap().channels[0].grid.values().clone()
            };
            let truth = psf(&at(STEPPED_DOE_PITCH / 5.0, Interpolation::Nearest, false));
            let verdict = |s: &OpticalSystem| -> Vec<String> {
                propagate::check(Method::MatrixDft, s, doe)
                    .unwrap()
                    .into_iter()
                    .map(|v| v.condition)
                    .collect()
            };
            let points = at(STEPPED_DOE_PITCH, Interpolation::Bilinear, false);
            let cells = at(STEPPED_DOE_PITCH, Interpolation::Bilinear, true);
            let nested = at(STEPPED_DOE_PITCH / 2.0, Interpolation::Nearest, true);
            let ramps = at(STEPPED_DOE_PITCH / 2.0, Interpolation::Bilinear, true);
            let [e_points, e_cells, e_nested, e_ramps] =
                [&points, &cells, &nested, &ramps].map(|s| relative_l2(&psf(s), &truth));
            let envelope = relative_l2(&psf(&points), &psf(&cells));
            // The truth's own error: its point samples against its cells.
            let fine_cells = at(STEPPED_DOE_PITCH / 5.0, Interpolation::Nearest, true);
            let own_error = relative_l2(&psf(&fine_cells), &truth);
            eprintln!(
                "{name} at {:.0} nm: truth {own_error:.2e}, cells {e_cells:.2e}, nested 2 x 2 {e_nested:.2e}, \
                 points {e_points:.2e} (points against cells {envelope:.2e}), bilinear 2 x 2 {e_ramps:.2e}",
                l * 1e9
            );
            for s in [&points, &cells, &nested] {
                assert_eq!(verdict(s), Vec::<String>::new(), "{name} {l}");
            }
            assert!(verdict(&ramps).contains(&"step_resampling".to_string()), "{name} {l}");
            assert!(own_error < 5e-4 && e_cells <= 2.5e-3 && e_nested <= 1e-3, "{name} {l}");
            // The point samples' error is the envelope's, and the part's own.
            assert!(e_points <= 1.05 * (envelope + e_cells), "{name} {l}");
            assert!(e_ramps > 1e-2, "{name} {l}: {e_ramps}");
        }
    }
    // The quantized DOE's wraps at 650 nm, counted from its heights: 3/4 of a period, no
    // multiple of 2 pi.
    let k = 2.0 * pi / 650e-9 * (Material::pdms().index(650e-9).unwrap() - 1.0);
    let h = quantized.values();
    let far = h
        .windows((1, 2))
        .into_iter()
        .map(|w| k * (w[[0, 1]] - w[[0, 0]]))
        .filter(|d| d.abs() > pi && (d.abs() - 2.0 * pi).abs() > 0.5 * pi)
        .count();
    assert!(far > 100, "{far}");
}

/// A smooth surface steeper than pi per sample is undersampled: its samples alias. A tilt of
/// 0.9 pi per 5 um sample at 550 nm sends the light 0.45 replica periods (`lambda g / dx` =
/// 770 um at F/7, g = 7 mm) off the axis, where the matrix DFT puts its peak, and the guard
/// accepts it; at 1.1 pi the surface sends it 0.55 periods off (out of the crop), the samples
/// read as a tilt of -0.9 pi and the run puts the peak 0.45 periods off on the other side: the
/// guard refuses (`phase_gradient`).
#[test]
fn an_undersampled_slope_is_refused_and_its_light_lands_on_the_wrong_side() {
    let pi = std::f64::consts::PI;
    let s = OpticalSystem { sensor_pitch: 5e-6, ..f7(5e-6, 150) };
    let period = L550 * 7e-3 / 5e-6;
    for (per_sample, refused) in [(0.9 * pi, false), (1.1 * pi, true)] {
        let doe = grating(204, 5e-6, L550, move |j| per_sample * j as f64);
        let v = propagate::check(Method::MatrixDft, &s, &doe).unwrap();
        assert_eq!(v.iter().any(|v| v.condition == "phase_gradient"), refused, "{v:?}");
        let forced = Options { allow_invalid: true, ..Default::default() };
        let psf = simulate(&s, &doe, Method::MatrixDft, &forced).unwrap();
        let x = psf.peak(0).1[0];
        // Where the surface sends it: its slope per sample over 2 pi, in replica periods.
        let want = per_sample / (2.0 * pi) * period;
        let aliased = want - period;
        eprintln!(
            "tilt {:.2} pi per sample: peak at {:.1} um, the surface's {:.1} um",
            per_sample / pi,
            x * 1e6,
            want * 1e6
        );
        if refused {
            assert!((x - aliased).abs() < 5e-6 && (x - want).abs() > 0.9 * period, "{x}");
        } else {
            assert!((x - want).abs() < 5e-6, "{x} against {want}");
        }
    }
}
