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
