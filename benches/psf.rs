//! Speed of the RGB PSF of the paper's geometry (the built-in 1306 x 1306 DOE at 4.29 um,
//! 5 mm aperture, F/7, 320 x 320 crop at 4.29 um, 635 / 530 / 450 nm) for each propagation
//! method and precision, with the relative L2 difference against the single transform in f64 at
//! the same pupil sampling (the exact value of the sampled model: the tests check it against
//! the term-by-term Collins sum to 1e-12) and the validity violations each run carried. Prints
//! one line per run; the f32 line's error is the error the fast path reaches.
//!
//! Run with `cargo bench --bench psf`.

use std::time::Instant;

use doefab::design::{paper_example, ExampleParams, PAPER_PITCH};
use doefab::optics::plan::{plan, Plan};
use doefab::optics::propagate::{check, matrix_dft};
use doefab::optics::psf::relative_l2;
use doefab::optics::system::{OpticalSystem, PixelRule};
use doefab::optics::{simulate, Method, Options, Precision, Psf};
use doefab::Result;
use ndarray::Array2;
use rustfft::num_complex::Complex64;

fn run(
    label: &str,
    s: &OpticalSystem,
    doe: &doefab::Grid,
    m: Method,
    precision: Precision,
    reference: Option<&Psf>,
) -> Result<Psf> {
    let v = check(m, s, doe)?;
    let opts = Options { allow_invalid: true, precision };
    // One warm-up run (thread pool, page faults), then the best of three.
    simulate(s, doe, m, &opts)?;
    let mut secs = f64::INFINITY;
    let mut psf = None;
    for _ in 0..3 {
        let t = Instant::now();
        psf = Some(simulate(s, doe, m, &opts)?);
        secs = secs.min(t.elapsed().as_secs_f64());
    }
    let psf = psf.expect("three runs");
    let err = reference.map(|r| psf.relative_l2(r)).transpose()?;
    let conds: Vec<String> =
        v.iter().map(|v| format!("{}@{:.0}nm", v.condition, v.wavelength * 1e9)).collect();
    println!(
        "{label:<34} {:<20} {:<4} {secs:>7.3} s  L2 vs matrix_dft f64 {}  violations [{}]",
        m.name(),
        precision.name(),
        err.map_or("-".to_string(), |e| e.iter().map(|x| format!("{x:.2e}")).collect::<Vec<_>>().join(" / ")),
        conds.join(", ")
    );
    Ok(psf)
}

fn main() -> Result<()> {
    let doe = paper_example(&ExampleParams::default())?;
    println!("threads: {}", rayon::current_num_threads());
    // The paper's sampling: pupil = pixel = 4.29 um.
    let s1 = OpticalSystem::default();
    let r1 = run("paper, 4.29 um pupil, point pixels", &s1, &doe, Method::MatrixDft, Precision::F64, None)?;
    run("paper, 4.29 um pupil, point pixels", &s1, &doe, Method::MatrixDft, Precision::F32, Some(&r1))?;
    run("paper, 4.29 um pupil, point pixels", &s1, &doe, Method::Fresnel, Precision::F64, Some(&r1))?;
    run("paper, 4.29 um pupil, point pixels", &s1, &doe, Method::AngularSpectrum, Precision::F64, Some(&r1))?;
    // Two sub-samples per pixel, the pupil at 2.145 um for every method.
    let s2 = OpticalSystem { subsample: 2, pupil_pitch: PAPER_PITCH / 2.0, ..OpticalSystem::default() };
    let r2 = run("paper, 2.145 um pupil, 2x2 pixels", &s2, &doe, Method::MatrixDft, Precision::F64, None)?;
    run("paper, 2.145 um pupil, 2x2 pixels", &s2, &doe, Method::MatrixDft, Precision::F32, Some(&r2))?;
    run("paper, 2.145 um pupil, 2x2 pixels", &s2, &doe, Method::Fresnel, Precision::F64, Some(&r2))?;
    run("paper, 2.145 um pupil, 2x2 pixels", &s2, &doe, Method::AngularSpectrum, Precision::F64, Some(&r2))?;
    // The single transform with the DOE's own 4.29 um pupil and 2x2 pixel integration.
    let s3 = OpticalSystem { subsample: 2, ..OpticalSystem::default() };
    run("paper, 4.29 um pupil, 2x2 pixels", &s3, &doe, Method::MatrixDft, Precision::F64, Some(&r2))?;

    // The plan at two tolerances against the converged pixel integral (Gauss-Legendre 8 x 8,
    // f64, estimated error 1e-9), the DOE's own samples.
    let conv =
        OpticalSystem { subsample: 8, pixel_rule: PixelRule::GaussLegendre, ..OpticalSystem::default() };
    let reference = simulate(&conv, &doe, Method::MatrixDft, &Options::default())?;
    for tol in [1e-3, 1e-4] {
        let p = plan(&OpticalSystem::default(), &doe, &[], tol)?;
        run_plan(&p, &doe)?;
        let mut secs = f64::INFINITY;
        let mut psf = None;
        for _ in 0..3 {
            let t = Instant::now();
            psf = Some(run_plan(&p, &doe)?);
            secs = secs.min(t.elapsed().as_secs_f64());
        }
        let err = psf.expect("three runs").relative_l2(&reference)?;
        println!(
            "plan tolerance {tol:.0e}: {} {} {:?} {}x{}  {secs:>7.3} s  estimate {:.1e}  L2 vs converged {}",
            p.method,
            p.precision.name(),
            p.system.pixel_rule,
            p.system.subsample,
            p.system.subsample,
            p.estimate.total,
            err.iter().map(|x| format!("{x:.2e}")).collect::<Vec<_>>().join(" / ")
        );
    }

    // Speed of the folded real products against the plain complex matrix DFT `F G F^T`
    // (ndarray's GEMM), one wavelength, point pixels, same process.
    let s = OpticalSystem::default();
    let (n, dx) = matrix_dft::pupil_grid(&s, &doe);
    let u1 = s.pupil_field(&doe, n, dx, 530e-9, true)?;
    let xs = s.sensor_coords();
    let lb = 530e-9 * s.abcd().b;
    let c = (n as f64 - 1.0) * 0.5;
    let time = |f: &dyn Fn() -> Result<ndarray::Array2<f64>>| -> Result<(f64, ndarray::Array2<f64>)> {
        f()?;
        let t = Instant::now();
        let r = f()?;
        Ok((t.elapsed().as_secs_f64(), r))
    };
    let (t_plain, plain) = time(&|| {
        let f = Array2::from_shape_fn((xs.len(), n), |(q, j)| {
            Complex64::from_polar(1.0, -2.0 * std::f64::consts::PI * xs[q] * (j as f64 - c) * dx / lb)
        });
        let u2 = f.dot(&u1.dot(&f.t()));
        Ok(u2.mapv(|v| v.norm_sqr() * (dx * dx / lb).powi(2)))
    })?;
    let (t64, r64) = time(&|| matrix_dft::transform::<f64>(&s, &u1, dx, &xs, 530e-9))?;
    let (t32, r32) = time(&|| matrix_dft::transform::<f32>(&s, &u1, dx, &xs, 530e-9))?;
    println!(
        "one wavelength: complex F G F^T {t_plain:.3} s; folded f64 {t64:.3} s ({:.1}x, L2 {:.1e}); folded f32 {t32:.3} s ({:.1}x, L2 {:.1e})",
        t_plain / t64,
        relative_l2(&r64, &plain),
        t_plain / t32,
        relative_l2(&r32, &plain)
    );
    Ok(())
}

fn run_plan(p: &Plan, doe: &doefab::Grid) -> Result<Psf> {
    doefab::optics::plan::run(p, doe, &[]).map(|(psf, _)| psf)
}
