//! `doefab compare` through its files: a simulated scan of the built-in design compared with
//! it, the part in the design frame read back and handed to `doefab psf`, and the refusals.

use crate::common;

use crate::common::doefab;

use std::path::Path;

use doefab::design::{PAPER_APERTURE, PAPER_PITCH};
use doefab::fabrication::recipe_run::{load_design, DesignSource};
use doefab::io::heightmap::{read_heightmap, ReadOptions};

fn simulate(out: &Path, extra: &[&str]) {
    let mut args = vec!["simulate-scan", "-o", out.to_str().unwrap(), "--quiet"];
    args.extend_from_slice(extra);
    let o = doefab(&args);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
}

#[test]
fn compare_recovers_a_simulated_cast_and_its_surface_feeds_psf() {
    let dir = common::tempdir();
    let scan = dir.path().join("scan.x3p");
    simulate(
        &scan,
        &[
            "built-in:paper",
            "--blur",
            "2um",
            "--depth-scale",
            "0.95",
            "--offset",
            "150nm",
            "--noise",
            "20nm",
            "--tilt",
            "1e-4,-2e-5",
            "--rotate",
            "0.3deg",
            "--shift",
            "3.2um,-1.7um",
            "--mirror",
            "--complement",
            "--missing",
            "10%",
            "--seed",
            "7",
        ],
    );
    let out = dir.path().join("cmp");
    let o = doefab(&[
        "compare",
        scan.to_str().unwrap(),
        "--design",
        "built-in:paper",
        "-o",
        out.to_str().unwrap(),
        "--psf-method",
        "none",
        "--json",
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let j: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let on_disk: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("compare.json")).unwrap()).unwrap();
    assert_eq!(j, on_disk);
    let f = |p: &str| j.pointer(p).and_then(|v| v.as_f64()).unwrap_or_else(|| panic!("{p} in {j}"));
    // The accuracy goals.
    assert!(((f("/registration/pose/shift/0") - 3.2e-6) / PAPER_PITCH).abs() <= 0.02, "{j}");
    assert!(((f("/registration/pose/shift/1") + 1.7e-6) / PAPER_PITCH).abs() <= 0.02, "{j}");
    assert!((f("/registration/pose/rotation").to_degrees() - 0.3).abs() <= 0.01, "{j}");
    assert!((f("/registration/depth_scale") / 0.95 - 1.0).abs() <= 0.005, "{j}");
    assert!((f("/model/depth_scale") / 0.95 - 1.0).abs() <= 0.005, "{j}");
    assert!((f("/model/blur") - 2e-6).abs() <= 0.1e-6, "{j}");
    assert!((f("/model/rms_residual") / 20e-9 - 1.0).abs() < 0.05, "{j}");
    assert_eq!(f("/aperture"), PAPER_APERTURE);
    // The difference is -0.05 h plus noise plus the blur's rounding: tens of nm.
    assert!((20e-9..80e-9).contains(&f("/rms_error")), "{j}");
    for name in ["design.png", "scan.png", "difference.png", "profiles.png", "histogram.png", "surface.json"]
    {
        assert!(out.join(name).metadata().unwrap().len() > 1000, "{name}");
    }
    // The part in the design frame: 0.95 times the blurred design, plus noise, on the design grid.
    let surface = read_heightmap(&out.join("surface.exr"), &ReadOptions::default()).unwrap();
    let design = load_design(&DesignSource::BuiltIn("paper".into())).unwrap().heights;
    assert_eq!((surface.dim(), surface.pitch()), (design.dim(), design.pitch()));
    let blurred = doefab::grid::blur::gaussian_blur(&design, 2e-6).unwrap();
    let (mut n, mut s2) = (0.0, 0.0);
    for i in (400..900).step_by(7) {
        for j in (400..900).step_by(7) {
            let e = surface.values()[[i, j]] - 0.95 * blurred.values()[[i, j]];
            n += 1.0;
            s2 += e * e;
        }
    }
    let rms = (s2 / n).sqrt();
    assert!(rms < 25e-9, "surface vs 0.95 x blurred design: {rms} m RMS");
    // `doefab psf` takes it.
    let psf = dir.path().join("psf");
    let o = doefab(&[
        "psf",
        out.join("surface.exr").to_str().unwrap(),
        "-o",
        psf.to_str().unwrap(),
        "--allow-invalid",
        "--quiet",
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(psf.join("psf.json").exists());
}

/// Runs `compare SCAN --design built-in:paper` expecting exit status `code`; checks that no
/// output folder was left and returns the error text.
fn compare_refused(scan: &Path, code: i32) -> String {
    let out = scan.with_file_name("cmp");
    let o = doefab(&[
        "compare",
        scan.to_str().unwrap(),
        "--design",
        "built-in:paper",
        "-o",
        out.to_str().unwrap(),
    ]);
    let err = String::from_utf8_lossy(&o.stderr).into_owned();
    assert_eq!(o.status.code(), Some(code), "{err}");
    assert!(!out.exists());
    err
}

#[test]
fn a_scan_of_another_part_exits_with_status_3() {
    // Smooth random bumps (white noise blurred by 3 samples), 5.6 mm across.
    let dir = common::tempdir();
    let scan = dir.path().join("other.x3p");
    let mut rng = doefab::rng::Lcg(11);
    let v = ndarray::Array2::from_shape_fn((1306, 1306), |_| 0.3e-6 * rng.normal());
    let g = doefab::Grid::new(v, [PAPER_PITCH; 2], doefab::Unit::Metre).unwrap();
    let g = doefab::grid::blur::gaussian_blur(&g, 3.0 * PAPER_PITCH).unwrap();
    doefab::metrology::write_scan(&scan, &g).unwrap();
    let err = compare_refused(&scan, 3);
    assert!(err.contains("registration refused") && err.contains("does not match"), "{err}");
}

#[test]
fn a_scan_smaller_than_the_aperture_is_refused() {
    let dir = common::tempdir();
    let scan = dir.path().join("small.x3p");
    simulate(&scan, &["built-in:paper", "--size", "800"]);
    let err = compare_refused(&scan, 2);
    assert!(err.contains("3.432 x 3.432 mm") && err.contains("smaller than the 5.000 mm aperture"), "{err}");
}

#[test]
fn a_part_that_matches_only_at_the_aperture_edge_exits_with_status_3() {
    // The built-in Fresnel lens fills the same 5 mm aperture as the built-in design. The
    // registration itself refuses it: the design it places correlates 0.67 with the scan, whose
    // 5 nm of noise would allow 0.995 (before that test, `compare` refused it later, for the
    // correlation inside the aperture).
    let dir = common::tempdir();
    let scan = dir.path().join("fresnel.gsf");
    simulate(&scan, &["built-in:fresnel", "--noise", "5nm"]);
    let err = compare_refused(&scan, 3);
    assert!(err.contains("registration refused") && err.contains("not trusted"), "{err}");
    assert!(err.contains("another design"), "{err}");
}
