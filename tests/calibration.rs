//! Calibration stage: HDR merge of the paper's real brackets, Debevec-Malik response recovery,
//! PSF calibration from synthetic pinhole brackets of a known PSF, PSNR and registration.

mod common;

use std::path::PathBuf;

use doefab::calibration::capture::{read_capture, read_exposures, Capture};
use doefab::calibration::hdr_merge::{merge, MergeOptions};
use doefab::calibration::response::recover_response;
use doefab::decoder::scenes::procedural_scene;
use ndarray::Array3;

/// `../shared/data/deepoptics-hdr/<rel>` beside the checkout (or under `$DOEFAB_SHARED`), if
/// present.
fn shared(rel: &str) -> Option<PathBuf> {
    let beside = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared");
    let root = std::env::var_os("DOEFAB_SHARED").map(PathBuf::from).unwrap_or(beside);
    let p = root.join("data/deepoptics-hdr").join(rel);
    if p.exists() {
        Some(p)
    } else {
        eprintln!("notice: {} is not here; skipping", p.display());
        None
    }
}

fn load(list: &doefab::calibration::capture::ExposureList) -> (Vec<Capture>, Vec<f64>) {
    let frames = list.frames.iter().map(|(p, _)| read_capture(p).unwrap()).collect();
    (frames, list.frames.iter().map(|f| f.1).collect())
}

/// Merging the paper's brackets (frames without the DOE): every frame agrees with the merge
/// (its value over its effective time) to a median relative deviation of 3 % where it sees 50k
/// or more well-exposed samples (measured: 1.0-2.0 %, the 8-bit step at z = 0.1 alone is 1.1 %),
/// and to 15 % for the shortest frames, which see only the lamps (measured up to 13 %). The
/// effective times stay within the 10-30 % drift the data's README states.
#[test]
fn real_brackets_merge_into_an_hdr_every_frame_agrees_with() {
    for scene in ["Kitchen", "Fruit"] {
        let Some(json) = shared(&format!("captures/{scene}/exposures.json")) else { return };
        let list = read_exposures(&json, false).unwrap();
        assert!(list.frames.iter().all(|(p, _)| !p.ends_with("wPSF_0_stop.png")));
        let (frames, times) = load(&list);
        let opts = MergeOptions { reference_exposure: list.reference_exposure, ..Default::default() };
        let m = merge(&frames, &times, None, None, &opts).unwrap();
        assert_eq!(m.report.saturated_everywhere.count, 0, "{scene}");
        for f in &m.report.frames {
            let median = f.agreement_median.unwrap();
            let limit = if f.agreement_samples >= 50_000 { 0.03 } else { 0.15 };
            assert!(median < limit, "{scene} {}: median deviation {median}", f.file);
            assert!((f.exposure_used / f.exposure_listed - 1.0).abs() < 0.4, "{scene} {}", f.file);
        }
        // The radiance is at the reference exposure: the reference frame's unsaturated values.
        let k = list.frames.iter().position(|f| f.1 == list.reference_exposure.unwrap()).unwrap();
        let scale = m.report.frames[k].exposure_used / times[k];
        let (mut dev, mut n) = (Vec::new(), 0);
        for (z, e) in frames[k].values.iter().zip(&m.radiance) {
            if (0.2..0.9).contains(z) {
                dev.push((z / scale - e).abs() / e);
                n += 1;
            }
        }
        dev.sort_by(f64::total_cmp);
        assert!(n > 2_000 && dev[n / 2] < 0.03, "{scene}: {}", dev[n / 2]);
    }
}

/// Debevec-Malik recovers a gamma-2.2 response from 8-bit frames of a procedural scene:
/// `g(z) - g(128) = 2.2 ln(z / 128)` within 0.015 (1.5 % in exposure) over z = 24..247 and 0.3
/// over z = 8..23, and the
/// merge through it gives back the scene's radiance (median 2 %).
#[test]
fn debevec_malik_recovers_a_known_gamma_curve() {
    let scene = procedural_scene(3, 120, 120).mapv(|v| v as f64);
    let times = [1.0 / 64.0, 1.0 / 16.0, 0.25, 1.0, 4.0];
    let frames: Vec<Capture> = times
        .iter()
        .map(|&t| Capture {
            path: PathBuf::from(format!("t{t}.png")),
            values: scene.mapv(|e| ((e * t * 0.5).min(1.0).powf(1.0 / 2.2) * 255.0).round() / 255.0),
            bits: 8,
        })
        .collect();
    let r = recover_response(&frames, &times, 0, 20.0).unwrap();
    for g in &r.log_exposure {
        let mut worst = [0.0f64; 2];
        for z in 8..248 {
            let want = 2.2 * (z as f64 / 128.0).ln();
            let e = (g[z] - g[128] - want).abs();
            worst[(z >= 24) as usize] = worst[(z >= 24) as usize].max(e);
        }
        // Measured: 0.007 above z = 24, 0.21 below (one count is over 4 % of the value there).
        assert!(worst[1] < 0.015 && worst[0] < 0.3, "{worst:?}");
    }
    let opts = MergeOptions { estimate_times: false, ..Default::default() };
    let m = merge(&frames, &times, None, Some(&r), &opts).unwrap();
    // Radiance up to one scale factor: exp(g) is fixed at z = 128 only.
    let ratios: Vec<f64> = m.radiance.iter().zip(&scene).map(|(a, b)| a / b).collect();
    let mut sorted = ratios.clone();
    sorted.sort_by(f64::total_cmp);
    let k = sorted[sorted.len() / 2];
    let mut dev: Vec<f64> = ratios.iter().map(|r| (r / k - 1.0).abs()).collect();
    dev.sort_by(f64::total_cmp);
    assert!(dev[dev.len() / 2] < 0.02, "median {}", dev[dev.len() / 2]);
    // A bracket of one exposure cannot constrain the curve.
    let one = [frames[2].clone(), frames[2].clone()];
    assert!(recover_response(&one, &[0.25, 0.25], 0, 20.0).is_err());
}

// ---------------------------------------------------------------------------------------------
// calibrate-psf on synthetic pinhole brackets

use doefab::calibration::hdr_merge::mean_dark;
use doefab::calibration::psf_extract::{calibrate_psf, Centre, PsfOptions};
use doefab::rng::Lcg;

/// A DOE-like analytic PSF, 319 x 319 x 3: a core at (159, 159), shifted copies, a wide halo.
fn analytic_psf() -> Array3<f64> {
    let copies = [(0.0, 0.0, 1.0, 1.2), (-40.0, 25.0, 0.05, 2.0), (35.0, 30.0, 0.02, 2.5), (10.0, -60.0, 0.01, 3.0)];
    Array3::from_shape_fn((319, 319, 3), |(i, j, c)| {
        let (y, x) = (i as f64 - 159.0, j as f64 - 159.0);
        let s = 1.0 + 0.15 * c as f64;
        let mut v = 1e-4 * (-(x * x + y * y) / (2.0 * 60.0f64.powi(2))).exp();
        for (dy, dx, a, sig) in copies {
            v += a * (-((x - dx).powi(2) + (y - dy).powi(2)) / (2.0 * (sig * s).powi(2))).exp();
        }
        v
    })
}

/// An 8-bit bracket of `truth` (normalised per channel) placed with its pixel (159, 159) at
/// (row0 + 159, col0 + 159) of an `h x w` capture: 11 frames one stop apart, the core
/// saturated by 2^9 in the longest, read noise 0.002, a dark level 0.03 with a fixed pattern,
/// and a stuck pixel at `hot` (not in the dark frames). Returns frames, times and 2 darks.
fn pinhole_bracket(truth: &Array3<f64>, h: usize, w: usize, at: (usize, usize), hot: (usize, usize)) -> (Vec<Capture>, Vec<f64>, Vec<Capture>) {
    let (th, tw, nc) = truth.dim();
    let mut e = Array3::<f64>::zeros((h, w, nc));
    for c in 0..nc {
        let s: f64 = truth.index_axis(ndarray::Axis(2), c).sum();
        let peak = truth.index_axis(ndarray::Axis(2), c).fold(0.0f64, |m, &v| m.max(v)) / s;
        for i in 0..th {
            for j in 0..tw {
                e[[at.0 + i, at.1 + j, c]] = truth[[i, j, c]] / s * 512.0 / peak;
            }
        }
    }
    let mut rng = Lcg(11);
    let pattern = Array3::from_shape_fn((h, w, nc), |_| 0.03 + 0.005 * rng.uniform());
    let quant = |v: f64| (v.clamp(0.0, 1.0) * 255.0).round() / 255.0;
    let times: Vec<f64> = (0..11).map(|k| 2f64.powi(-k)).collect();
    let frames = times
        .iter()
        .enumerate()
        .map(|(k, &t)| {
            let mut v = Array3::from_shape_fn((h, w, nc), |(i, j, c)| quant(pattern[[i, j, c]] + e[[i, j, c]] * t + 0.002 * rng.normal()));
            for c in 0..nc {
                v[[hot.0, hot.1, c]] = 0.4;
            }
            Capture { path: PathBuf::from(format!("frame{k}.png")), values: v, bits: 8 }
        })
        .collect();
    let darks = (0..2)
        .map(|k| Capture {
            path: PathBuf::from(format!("dark{k}.png")),
            values: Array3::from_shape_fn((h, w, nc), |(i, j, c)| quant(pattern[[i, j, c]] + 0.002 * rng.normal())),
            bits: 8,
        })
        .collect();
    (frames, times, darks)
}

fn relative_l2(a: &Array3<f64>, b: &Array3<f64>) -> f64 {
    let n: f64 = a.iter().zip(b).map(|(x, y)| (x - y).powi(2)).sum();
    (n / b.iter().map(|y| y * y).sum::<f64>()).sqrt()
}

fn normalised(t: &Array3<f64>) -> Array3<f64> {
    let mut t = t.clone();
    for c in 0..t.dim().2 {
        let s: f64 = t.index_axis(ndarray::Axis(2), c).sum();
        t.index_axis_mut(ndarray::Axis(2), c).mapv_inplace(|v| v / s);
    }
    t
}

/// The known PSF comes back from a noisy, dark-offset, saturated 8-bit bracket with a stuck
/// pixel. Relative L2 per channel: the analytic PSF below 1 % (measured 0.45-0.55 %); the
/// paper's measured PSF below 4 % (measured 1.9 / 0.5 / 3.0 % R/G/B: half of its energy lies
/// in tails near the 8-bit noise floor, where the 1-sigma floor trades lost tail for noise).
#[test]
fn a_known_psf_is_recovered_from_its_synthetic_bracket() {
    let mut truths = vec![("analytic", analytic_psf())];
    if let Some(p) = shared("measured_psf.npz") {
        let psf = doefab::optics::Psf::read_npz(&p, Some("psf_val"), 4.29e-6, None).unwrap();
        let a = psf.to_array4();
        truths.push(("measured", Array3::from_shape_fn((319, 319, 3), |(i, j, c)| a[[i, j, 0, c]] as f64)));
    }
    for (name, truth) in truths {
        let (frames, times, darks) = pinhole_bracket(&truth, 420, 400, (40, 30), (100, 260));
        let dark = mean_dark(&darks).unwrap();
        let merged = merge(&frames, &times, Some(&dark), None, &MergeOptions { estimate_times: false, ..Default::default() }).unwrap();
        let opts = PsfOptions { centre: Centre::Peak, ..Default::default() };
        let (psf, report) = calibrate_psf(&merged, &opts).unwrap();
        assert_eq!(report.peak_px, [199, 189], "{name}");
        assert!(report.hot_pixels >= 3, "{name}: {} hot pixels", report.hot_pixels);
        let got = psf.to_array4();
        let got = Array3::from_shape_fn((319, 319, 3), |(i, j, c)| got[[i, j, 0, c]] as f64);
        let want = normalised(&truth);
        for c in 0..3 {
            let e = relative_l2(
                &got.slice(ndarray::s![.., .., c..c + 1]).to_owned(),
                &want.slice(ndarray::s![.., .., c..c + 1]).to_owned(),
            );
            let limit = if name == "analytic" { 0.01 } else { 0.04 };
            assert!(e < limit, "{name} channel {c}: relative L2 {e}");
        }
        // Centroid centring puts every channel's centroid near the crop centre.
        let (psf, _) = calibrate_psf(&merged, &PsfOptions::default()).unwrap();
        let sum_centroid: Vec<f64> = (0..2).map(|k| (0..3).map(|c| psf.centroid(c)[k]).sum::<f64>() / 3.0 / 4.29e-6).collect();
        assert!(sum_centroid.iter().all(|v| v.abs() < 0.25), "{name}: centroid {sum_centroid:?} px");
    }
}
