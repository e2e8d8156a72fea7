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
use doefab::optics::propagate::check;
use doefab::optics::system::OpticalSystem;
use doefab::optics::{simulate, Method, Options, Precision, Psf};
use doefab::Result;

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
    Ok(())
}
