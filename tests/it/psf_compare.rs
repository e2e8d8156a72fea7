//! `doefab psf-compare` end to end: the files `doefab psf` writes read back through both
//! formats, the paper's measured PSF against a simulated one, bad input.

use crate::common;

use crate::common::{fails, ok};

use std::path::{Path, PathBuf};

use ndarray::Array4;

/// The paper's 320 x 320 RGB PSF of the built-in design (matrix DFT, point pixels).
fn simulated(dir: &Path) -> PathBuf {
    let out = dir.join("psf");
    ok(&["psf", "--method", "matrix_dft", "-o", out.to_str().unwrap(), "-q"]);
    out
}

fn json(text: &str) -> serde_json::Value {
    serde_json::from_str(text).expect("JSON output")
}

#[test]
fn the_npy_and_exr_of_one_run_compare_equal() {
    let d = common::tempdir();
    let psf = simulated(d.path());
    let (npy, exr) = (psf.join("psf.npy"), psf.join("psf.exr"));
    let report = d.path().join("cmp.json");
    let stdout = ok(&[
        "psf-compare",
        npy.to_str().unwrap(),
        exr.to_str().unwrap(),
        "-o",
        report.to_str().unwrap(),
        "--json",
    ]);
    let r = json(&stdout);
    assert_eq!(r, json(&std::fs::read_to_string(&report).unwrap()), "-o writes what --json prints");
    assert_eq!(r["window"], "same size");
    assert!((r["pitch"][0].as_f64().unwrap() - 4.29e-6).abs() < 1e-15, "pitch from the metadata");
    let summary = json(&std::fs::read_to_string(psf.join("psf.json")).unwrap());
    let channels = r["channels"].as_array().unwrap();
    assert_eq!(channels.len(), 3);
    for (c, ch) in channels.iter().enumerate() {
        // Names and wavelengths come from the JSON beside the .npy and from the EXR header,
        // in the writer's order.
        let want = &summary["channels"][c];
        assert_eq!(ch["name"], want["name"]);
        assert_eq!(ch["b"]["wavelength"], want["wavelength"]);
        // Both carry the same f32 numbers: nothing to shift, nothing differs, and the
        // numbers match those `psf` reported.
        assert_eq!(ch["relative_l2"].as_f64().unwrap(), 0.0);
        assert!(ch["relative_l2_aligned"].as_f64().unwrap() < 1e-12);
        assert_eq!(ch["centroid_offset"], serde_json::json!([0.0, 0.0]));
        assert_eq!(ch["a"]["peak_position"], want["peak_position"]);
        assert!((ch["a"]["peak"].as_f64().unwrap() / want["peak"].as_f64().unwrap() - 1.0).abs() < 1e-6);
        assert_eq!(ch["a"]["peaks"].as_array().unwrap().len(), want["peaks"].as_array().unwrap().len());
        let ee = want["encircled_energy_airy"].as_f64().unwrap();
        assert!((ch["a"]["encircled_energy"].as_f64().unwrap() - ee).abs() < 1e-6);
    }
}

#[test]
fn the_measured_psf_compares_against_a_simulated_one() {
    let measured = common::shared_data("deepoptics-hdr/measured_psf.npz");
    let d = common::tempdir();
    let npy = simulated(d.path()).join("psf.npy");
    let (a, b) = (npy.to_str().unwrap(), measured.to_str().unwrap());
    let r = json(&ok(&["psf-compare", a, b, "--pitch", "4.29 um", "--key", "psf_val", "--json"]));
    assert_eq!(r["dim_a"], serde_json::json!([320, 320]));
    assert_eq!(r["dim_b"], serde_json::json!([319, 319]));
    assert_eq!(r["dim_common"], serde_json::json!([319, 319]));
    assert!(r["window"].as_str().unwrap().contains("cropped to the common centred 319 x 319"));
    for ch in r["channels"].as_array().unwrap() {
        let (l2, aligned) =
            (ch["relative_l2"].as_f64().unwrap(), ch["relative_l2_aligned"].as_f64().unwrap());
        assert!(l2.is_finite() && aligned.is_finite() && aligned > 0.0, "{ch}");
        assert!(ch["b"]["encircled_energy"].as_f64().unwrap() > 0.0);
    }
    // The measured PSF is sampled coarser than its Nyquist pitch: the sub-pixel shift says so.
    assert!(r["warnings"].as_array().unwrap().iter().any(|w| w.as_str().unwrap().contains("band-limited")));
    // The archive states no pitch.
    let e = fails(&["psf-compare", a, b, "--key", "psf_val"]);
    assert!(e.contains("measured_psf.npz") && e.contains("give `pitch`"), "{e}");
    // A pitch that contradicts the file's metadata is refused.
    let e = fails(&["psf-compare", a, b, "--key", "psf_val", "--pitch", "5um"]);
    assert!(e.contains("psf.npy") && e.contains("`pitch` is"), "{e}");
}

#[test]
fn bad_input_is_refused_with_the_reason() {
    let d = common::tempdir();
    let psf = simulated(d.path());
    let npy = psf.join("psf.npy");
    // A one-channel PSF (no JSON beside it: its pitch is given) against the RGB one.
    let mono = d.path().join("mono.npy");
    let v = Array4::from_shape_fn((320, 320, 1, 1), |(i, j, _, _)| {
        (-((i as f32 - 160.0).powi(2) + (j as f32 - 160.0).powi(2)) / 8.0).exp()
    });
    doefab::io::npy::write_npy_f32_4d(&mono, &v).unwrap();
    let e = fails(&["psf-compare", npy.to_str().unwrap(), mono.to_str().unwrap(), "--pitch", "4.29um"]);
    assert!(e.contains("has 3 channels") && e.contains("has 1") && e.contains("mono.npy"), "{e}");
    let e = fails(&["psf-compare", npy.to_str().unwrap(), mono.to_str().unwrap()]);
    assert!(e.contains("mono.npy") && e.contains("give `pitch`"), "{e}");
    // A summary beside the .npy without the pitch field.
    std::fs::write(d.path().join("mono.json"), "{\"channels\": [{\"name\": \"G\"}]}").unwrap();
    let e = fails(&["psf-compare", mono.to_str().unwrap(), mono.to_str().unwrap()]);
    assert!(e.contains("mono.json") && e.contains("system.sensor_pitch"), "{e}");
    // An unknown format.
    let e = fails(&["psf-compare", npy.to_str().unwrap(), psf.join("psf_log.png").to_str().unwrap()]);
    assert!(e.contains("psf_log.png") && e.contains(".npy, .npz or .exr"), "{e}");
    // The inputs are untouched.
    assert_eq!(doefab::io::npy::read_npy_nd(&mono).unwrap().0.shape, vec![320, 320, 1, 1]);
}
