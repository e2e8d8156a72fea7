//! The fabrication loop closed in simulation: a known process makes the part from the plain
//! target, its simulated scan is compared with the design, the next mask is pre-compensated
//! from that comparison alone, and the part made from it through the same process is scanned
//! and compared again. The truth (the process) is never shown to the correction.

use doefab::design::{paper_example, ExampleParams, PAPER_PITCH};
use doefab::fabrication::chain::{ChainParams, LoadedDesign};
use doefab::fabrication::precompensate::Response;
use doefab::fabrication::quantize::QuantizeMethod;
use doefab::fabrication::wrap::WrapSpec;
use doefab::fabrication::ReplicaMode;
use doefab::metrology::compare::{CompareOptions, Comparison, LevelSpec};
use doefab::metrology::register::Pose;
use doefab::metrology::simulate::SimulateParams;
use doefab::optics::output::system_for;
use doefab::optics::{Method, Options};
use doefab::pipeline::compare::psf_comparison;
use doefab::pipeline::precompensate::{simulate_loop, Corrections, LoopResult};

const N: usize = 320;

fn design() -> LoadedDesign {
    let p = ExampleParams { samples: N, aperture: 0.9 * N as f64 * PAPER_PITCH, ..Default::default() };
    LoadedDesign { heights: paper_example(&p).unwrap(), name: "paper-320".into(), sha256: "test".into() }
}

fn chain() -> ChainParams {
    ChainParams {
        wavelength: 530e-9,
        material: "pdms".into(),
        order: 1,
        level_count: 8,
        quantization: QuantizeMethod::Round,
        replica_mode: ReplicaMode::Design,
        min_feature: 0.0,
        fill: false,
    }
}

fn period() -> f64 {
    chain().wrap_spec().unwrap().period().unwrap()
}

fn compare_opts() -> CompareOptions {
    CompareOptions {
        aperture: Some(0.85 * N as f64 * PAPER_PITCH),
        levels: Some(LevelSpec { count: 8, step: period() / 8.0 }),
        optics: WrapSpec::default(),
        ..Default::default()
    }
}

/// A scan as a profilometer takes it: a small pose error, 5 nm of noise, 3% missing.
fn process(p: SimulateParams) -> SimulateParams {
    SimulateParams {
        pose: Pose { mirror: false, rotation: 0.1f64.to_radians(), scale: 1.0, shift: [1.3e-6, -0.8e-6] },
        noise: 5e-9,
        missing: 0.03,
        ..p
    }
}

/// A resist that bows: made = c + 0.35 c (P - c) / P over the period, from 9 points.
fn bowed() -> Response {
    let p = period();
    let c: Vec<f64> = (0..=8).map(|k| k as f64 * p / 8.0).collect();
    let m = c.iter().map(|c| c + 0.35 * c * (p - c) / p).collect();
    Response::new(c, m).unwrap()
}

fn psf_l2(target: &doefab::Grid, c: &Comparison) -> Vec<f64> {
    let mut system = system_for(target);
    system.aperture = c.aperture;
    let opts = Options { allow_invalid: true, ..Default::default() };
    psf_comparison(target, &c.surface, &system, Method::MatrixDft, &opts)
        .unwrap()
        .channels
        .iter()
        .map(|ch| ch.relative_l2)
        .collect()
}

/// The loop on one process, with the design-order efficiency per channel (Swanson at the fitted
/// depth scale) and the PSF's relative L2 against the design's, before and after.
struct Outcome {
    r: LoopResult,
    gain: f64,
    efficiency_closer: bool,
    psf_before: Vec<f64>,
    psf_after: Vec<f64>,
}

fn run(p: SimulateParams) -> Outcome {
    let r = simulate_loop(&design(), &chain(), &process(p), &compare_opts(), &Corrections::default(), None)
        .unwrap();
    let gain = r.before.rms_error / r.after.rms_error;
    let efficiency_closer = r
        .before
        .efficiency
        .iter()
        .zip(&r.after.efficiency)
        .all(|(b, a)| (a.fabricated - a.design).abs() < (b.fabricated - b.design).abs());
    let target = &r.written.target;
    let (psf_before, psf_after) = (psf_l2(target, &r.before), psf_l2(target, &r.after));
    Outcome { r, gain, efficiency_closer, psf_before, psf_after }
}

/// Measured: RMS 98.8 -> 19.8 nm (x4.98), depth scale 0.850 -> 0.991, PSF rel L2 0.20/0.23/0.28
/// -> 0.019/0.020/0.021.
#[test]
fn a_part_15_percent_too_shallow_comes_out_at_depth() {
    let o = run(SimulateParams { depth_scale: 0.85, ..Default::default() });
    assert!(o.gain >= 2.0, "{} -> {}", o.r.before.rms_error, o.r.after.rms_error);
    assert!((o.r.after.model.depth_scale - 1.0).abs() < 0.02, "{:?}", o.r.after.model);
    assert!(o.efficiency_closer, "{:?} -> {:?}", o.r.before.efficiency, o.r.after.efficiency);
    assert!(
        o.psf_after.iter().zip(&o.psf_before).all(|(a, b)| a * 4.0 < *b),
        "{:?} -> {:?}",
        o.psf_before,
        o.psf_after
    );
}

/// Measured: RMS 80.9 -> 19.7 nm (x4.10), PSF rel L2 0.050/0.055/0.062 -> 0.034/0.042/0.051.
#[test]
fn a_bowed_level_response_is_straightened() {
    let o = run(SimulateParams { response: Some(bowed()), ..Default::default() });
    assert!(o.gain >= 2.0, "{} -> {}", o.r.before.rms_error, o.r.after.rms_error);
    assert!(o.efficiency_closer, "{:?} -> {:?}", o.r.before.efficiency, o.r.after.efficiency);
    assert!(
        o.psf_after.iter().zip(&o.psf_before).all(|(a, b)| a < b),
        "{:?} -> {:?}",
        o.psf_before,
        o.psf_after
    );
}

/// A blur of 2 pitches: the deconvolution brings the PSF about 2x closer to the design's
/// (relative L2 0.141/0.168/0.192 -> 0.076/0.083/0.073) but the height RMS only 1.12x
/// (79.7 -> 71.3 nm): at a phase wrap the commands cannot undo a full-period step, and they
/// stay where the response was measured (below the 2x goal; see the README's chart of the gain
/// against blur width). A blur of one pitch is not deconvolved (the warning says so) and
/// nothing gets worse.
#[test]
fn a_blur_is_deconvolved_as_far_as_the_bounds_allow() {
    let o = run(SimulateParams { blur: 2.0 * PAPER_PITCH, ..Default::default() });
    assert!(o.r.written.result.deblur.is_some());
    assert!(o.gain > 1.08, "{} -> {}", o.r.before.rms_error, o.r.after.rms_error);
    assert!(
        o.psf_after.iter().zip(&o.psf_before).all(|(a, b)| a * 1.7 < *b),
        "{:?} -> {:?}",
        o.psf_before,
        o.psf_after
    );
    let o = run(SimulateParams { blur: PAPER_PITCH, ..Default::default() });
    assert!(o.r.written.result.deblur.is_none(), "{:?}", o.r.written.warnings);
    assert!(o.r.written.warnings.iter().any(|w| w.contains("at or below")), "{:?}", o.r.written.warnings);
    assert!(o.gain > 0.98, "{} -> {}", o.r.before.rms_error, o.r.after.rms_error);
}
