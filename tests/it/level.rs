//! Facet and substrate levelling on the reference surfaces written by third-party programs
//! (profilometry/README.md): S1 and S3 are a plane `50 nm + 2 nm * j - 1 nm * i` under flat
//! terraces, so both methods must recover that plane exactly, where the least-squares plane of
//! S3 is pulled by its spikes and missing block (Gwyddion: a = 328.636652 nm, bx = 2.12211906,
//! by = -1.14303079 nm/px).

use std::path::PathBuf;

use doefab::io::scan::{read_scan, ScanOptions};
use doefab::metrology::height_params;
use doefab::metrology::{level, LevelMethod, Plane};

fn local(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("profilometry").join(name)
}

fn assert_construction_plane(p: &Plane, offset: bool, what: &str) {
    let ok = (p.bx - 2e-9).abs() < 1e-6 * 2e-9
        && (p.by + 1e-9).abs() < 1e-6 * 1e-9
        && (!offset || (p.a - 50e-9).abs() < 1e-6 * 50e-9);
    assert!(ok, "{what}: {p:?}");
}

#[test]
fn facet_and_substrate_recover_the_reference_tilt() {
    for name in ["s1_tilt_pedestal.x3pio.x3p", "s3_spikes_missing_nan.x3pio.x3p"] {
        let g = read_scan(&local(name), &ScanOptions::default()).unwrap().grid;
        let (_, facet) = level(&g, LevelMethod::Facet).unwrap();
        assert_construction_plane(&facet.plane, false, &format!("{name} facet"));
        let (_, sub) = level(&g, LevelMethod::Substrate { aperture: None }).unwrap();
        assert_construction_plane(&sub.plane, true, &format!("{name} lowest level"));
        // The substrate is everything outside the 100 x 100 pedestal that is measured and not a
        // spike: 30000 points in S1; S3 loses the 800-point block and three spikes.
        let expected = if name.starts_with("s1") { 30000 } else { 30000 - 800 - 3 };
        assert_eq!(sub.fitted_points, expected, "{name}");
        let low = sub.lowest_level.unwrap();
        assert!((low.next_level - 1e-6).abs() < 0.02e-6 && low.spread < 1e-12, "{name}: {low:?}");
        // Outside a 150 um aperture only the substrate is left (the pedestal's corners are at
        // 70.7 um from the centre), spikes included in S3: exact for S1 only.
        let (_, out) = level(&g, LevelMethod::Substrate { aperture: Some(150e-6) }).unwrap();
        if name.starts_with("s1") {
            assert_construction_plane(&out.plane, true, "s1 outside the aperture");
        }
    }
}

#[test]
fn substrate_levelled_s1_has_gwyddions_plane_levelled_statistics() {
    // S1 is centrosymmetric, so its least-squares plane differs from the substrate plane by an
    // offset only, which the mean reference of the statistics removes: the levelled statistics
    // must equal Gwyddion's "S1 after least-squares plane" row.
    let g = read_scan(&local("s1_tilt_pedestal.x3pio.x3p"), &ScanOptions::default()).unwrap().grid;
    for method in [LevelMethod::Facet, LevelMethod::Substrate { aperture: None }] {
        let (flat, _) = level(&g, method).unwrap();
        let h = height_params(&flat).unwrap();
        let got = [h.sa * 1e9, h.sq * 1e9, h.sp * 1e9, h.sv * 1e9, h.sz * 1e9, h.ssk, h.sku];
        let want = [405.000, 476.550102, 1230.0, 270.0, 1500.0, 1.30622884, 3.00879390];
        for (g, w) in got.iter().zip(want) {
            assert!((g - w).abs() <= 1e-6 * w, "{method:?}: {got:?} vs {want:?}");
        }
    }
}

#[test]
fn scan_info_levels_on_request() {
    let exe = env!("CARGO_BIN_EXE_doefab");
    let file = local("s3_spikes_missing_nan.x3pio.x3p");
    let run = |args: &[&str]| std::process::Command::new(exe).args(args).arg(&file).output().unwrap();
    let out = run(&["--json", "scan-info", "--level", "substrate"]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let l = &v["levelling"];
    assert_eq!(l["fitted_points"], 30000 - 803);
    assert!((l["plane"]["a"].as_f64().unwrap() - 50e-9).abs() < 1e-6 * 50e-9, "{l}");
    let out = run(&["scan-info", "--level", "facet"]);
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success() && text.contains("facet levelling") && text.contains("bx = 2.000 nm"),
        "{text}"
    );
    let out = run(&["scan-info", "--level", "substrate", "--aperture", "150um"]);
    assert!(String::from_utf8_lossy(&out.stdout).contains("outside a 150 um aperture"));
    let out = run(&["scan-info", "--aperture", "1mm"]);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("--level substrate"));
    let out = run(&["scan-info", "--level", "substrate", "--aperture", "1mm"]);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("covers the whole"));
}
