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
use doefab::metrology::scan_compare::{CompareOptions, Comparison, LevelSpec};
use doefab::metrology::scan_registration::Pose;
use doefab::metrology::synthetic_scan::SimulateParams;
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

/// The loop through the command line and its files: a design file, the scan of its plain
/// grayscale master's part, `doefab precompensate --scan`, the commanded surface it wrote
/// made through the same process and scanned, `doefab compare` of both scans. `--model` with
/// the compare.json of the first scan gives the same commands.
#[test]
fn the_command_closes_the_loop_through_its_files() {
    use crate::common::{ok, tempdir};
    use doefab::fabrication::recipe::Recipe;
    use doefab::io::heightmap::Metadata;
    use doefab::metrology::synthetic_scan::{simulate_scan, write_scan};
    let dir = tempdir();
    let path = |name: &str| dir.path().join(name).to_str().unwrap().to_string();
    let d = design();
    let meta = Metadata::heights(d.heights.pitch()).with("quantity", "height");
    doefab::io::exr::write_exr(
        dir.path().join("design.exr").as_path(),
        &[("height", &d.heights.values().mapv(|v| v as f32))],
        &meta,
    )
    .unwrap();
    let recipe = Recipe::read(std::path::Path::new("built-in:laser-writer-grayscale")).unwrap();
    let params = ChainParams::of_recipe(&recipe, false);
    let loaded = doefab::fabrication::chain::load_design(&doefab::fabrication::chain::DesignSource::File(
        dir.path().join("design.exr"),
        Default::default(),
    ))
    .unwrap();
    let (target, _, _) = doefab::pipeline::compare::reference_surface(&loaded, Some(&params)).unwrap();
    let truth = process(SimulateParams { depth_scale: 0.88, ..Default::default() });
    write_scan(dir.path().join("before.x3p").as_path(), &simulate_scan(&target, &truth).unwrap()).unwrap();
    let recipe_arg = "built-in:laser-writer-grayscale";
    let out = ok(&[
        "precompensate",
        &path("design.exr"),
        "--recipe",
        recipe_arg,
        "--scan",
        &path("before.x3p"),
        "-o",
        &path("pc"),
        "--json",
    ]);
    let report: serde_json::Value = serde_json::from_str(&out).unwrap();
    for f in [
        "grayscale_mask.png",
        "grayscale_mask.tif",
        "grayscale_mask.json",
        "commanded.exr",
        "precompensate.json",
    ] {
        assert!(dir.path().join("pc").join(f).is_file(), "{f} missing");
    }
    // The sidecar names the scan by its hash, what was corrected and the prediction; its level
    // table is monotone.
    let sidecar: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.path().join("pc/grayscale_mask.json")).unwrap())
            .unwrap();
    let pc = &sidecar["precompensation"];
    assert_eq!(pc["scan_sha256"], doefab::io::file_sha256(&dir.path().join("before.x3p")).unwrap());
    assert!(pc["corrected"][0].as_str().unwrap().starts_with("per-level heights"), "{pc}");
    let levels = sidecar["levels"].as_array().unwrap();
    let h: Vec<f64> = levels.iter().map(|l| l["height_m"].as_f64().unwrap()).collect();
    let g: Vec<f64> = levels.iter().map(|l| l["gray"].as_f64().unwrap()).collect();
    assert!(h.windows(2).all(|w| w[1] > w[0]), "{h:?}");
    // Positive resist, master: the top of the master is the least exposed.
    assert!(g.windows(2).all(|w| w[1] <= w[0]), "{g:?}");
    let predicted = &report["predicted"];
    assert!(
        predicted["rms_after"].as_f64().unwrap() < 0.5 * predicted["rms_before"].as_f64().unwrap(),
        "{predicted}"
    );
    // The part of the commanded surface, through the same process.
    let commanded =
        doefab::io::heightmap::read_heightmap(&dir.path().join("pc/commanded.exr"), &Default::default())
            .unwrap();
    write_scan(dir.path().join("after.x3p").as_path(), &simulate_scan(&commanded, &truth).unwrap()).unwrap();
    let rms = |scan: &str, out: &str| -> (f64, serde_json::Value) {
        let o = ok(&[
            "compare",
            &path(scan),
            "--design",
            &path("design.exr"),
            "--recipe",
            recipe_arg,
            "--psf-method",
            "none",
            "-o",
            &path(out),
            "--json",
        ]);
        let v: serde_json::Value = serde_json::from_str(&o).unwrap();
        (v["rms_error"].as_f64().unwrap(), v)
    };
    let (before, _) = rms("before.x3p", "cmp_before");
    let (after, _) = rms("after.x3p", "cmp_after");
    assert!(after * 2.0 < before, "RMS {before} -> {after}");
    // The same correction from compare.json.
    let out = ok(&[
        "precompensate",
        &path("design.exr"),
        "--recipe",
        recipe_arg,
        "--model",
        &path("cmp_before/compare.json"),
        "-o",
        &path("pc_model"),
        "--json",
    ]);
    let from_model: serde_json::Value = serde_json::from_str(&out).unwrap();
    assert_eq!(from_model["level_commands"], report["level_commands"]);
}

/// Refusals, each naming the figure: a recipe with a binary mask set, a model from another
/// design, a poor registration, an implausible depth scale, a file that is not a compare.json.
#[test]
fn the_command_refuses_what_it_cannot_correct() {
    use crate::common::{fails, tempdir};
    use doefab::pipeline::precompensate::{process_model, Measured};
    let dir = tempdir();
    let out = dir.path().join("o");
    let refused = |recipe: &str, model: &std::path::Path| {
        fails(&[
            "precompensate",
            "--recipe",
            recipe,
            "--model",
            model.to_str().unwrap(),
            "-o",
            out.to_str().unwrap(),
        ])
    };
    let e = refused("built-in:binary-3mask-8level", std::path::Path::new("nowhere.json"));
    assert!(e.contains("binary mask set (gds)") && e.contains("etch depths"), "{e}");
    // A compare.json of the built-in design, through the library's own comparison.
    let c = run(SimulateParams { depth_scale: 0.9, ..Default::default() });
    let m = Measured {
        scan: "s.x3p".into(),
        scan_sha256: "ab".into(),
        design_sha256: "not-the-design".into(),
        interior_correlation: c.r.before.interior_correlation,
        rms_error: c.r.before.rms_error,
        model: c.r.before.model.clone(),
        levels: c.r.before.levels.clone(),
    };
    let json = dir.path().join("compare.json");
    std::fs::write(&json, serde_json::to_string(&m).unwrap()).unwrap();
    let e = refused("built-in:laser-writer-grayscale", &json);
    assert!(e.contains("compare.json") && e.contains("design_sha256 not-the-design"), "{e}");
    let mut w = vec![];
    let poor = Measured { interior_correlation: 0.62, ..m.clone() };
    let e = process_model(&poor, &Corrections::default(), &mut w).unwrap_err().to_string();
    assert!(e.contains("0.620") && e.contains("below 0.9"), "{e}");
    let mut flat = m.clone();
    flat.model.depth_scale = 0.31;
    let e = process_model(&flat, &Corrections { levels: false, ..Default::default() }, &mut w)
        .unwrap_err()
        .to_string();
    assert!(e.contains("0.310") && e.contains("0.5..1.5"), "{e}");
    std::fs::write(&json, "{\"scan\": 3}").unwrap();
    let e = refused("built-in:laser-writer-grayscale", &json);
    assert!(e.contains("compare.json") && e.contains("not a compare.json"), "{e}");
    assert!(!out.exists());
}
