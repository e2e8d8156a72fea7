//! Scan readers and surface statistics against files written by third-party programs
//! (Gwyddion 2.62, gsffile, sdfio, surfalize, x3pio, SurfaceTopography) and the reference
//! statistics those programs computed (profilometry/README.md). The copies in `profilometry/`
//! always run; the full shared set (`../shared/data/surfaces/`) is required (the test fails
//! without it).
//!
//! Tolerances: 1e-6 relative everywhere the file holds the heights to that precision. That
//! includes the `%g` text formats (ASCII SDF, text matrix, XYZ): `%g` keeps six significant
//! digits (a rounding of at most 5e-7 relative per value), and the reference surfaces' heights
//! are whole nanometres below 7 um, four to five digits, so `%g` writes them exactly. The
//! 16-bit PNG quantizes heights to one count (range / 65535 = 28 pm for S1) and each height
//! reads back within one count of the truth; a difference from the mean or from a fitted plane
//! (itself within a count) is then within three counts: Sa..Sz are held to 3 counts, Ssk and Sku
//! to 6 counts / Sq relative.

use crate::common;

use std::path::{Path, PathBuf};

use doefab::io::scan::{read_scan, ScanFormat, ScanOptions};
use doefab::metrology::level_plane;
use doefab::metrology::nsigma_outliers;
use doefab::metrology::{height_params, HeightParams};
use doefab::{Error, FormatCause, Grid};
use ndarray::Array2;

/// Reference statistics in nanometres (Sa, Sq, Sp, Sv, Sz) and dimensionless (Ssk, Sku).
#[derive(Debug, Clone, Copy)]
struct Ref {
    n: usize,
    v: [f64; 7],
}

const S1_RAW: Ref =
    Ref { n: 40000, v: [405.112375, 493.726898, 1288.5, 568.5, 1857.0, 1.08871371, 2.79533961] };
const S1_PLANE: Ref =
    Ref { n: 40000, v: [405.000, 476.550102, 1230.0, 270.0, 1500.0, 1.30622884, 3.00879390] };
const S3_RAW: Ref =
    Ref { n: 39200, v: [413.742290, 501.996377, 5808.84184, 570.158163, 6379.0, 1.18552830, 4.10879110] };
const S3_PLANE: Ref =
    Ref { n: 39200, v: [411.154049, 483.168505, 5728.96664, 302.938345, 6031.90498, 1.39870626, 4.53964131] };
const NAMES: [&str; 7] = ["Sa", "Sq", "Sp", "Sv", "Sz", "Ssk", "Sku"];

fn local(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("profilometry").join(name)
}

/// The shared reference surfaces (the test fails when they are missing).
fn shared() -> PathBuf {
    common::shared_data("surfaces")
}

/// The S1 surface, metres.
fn s1(i: usize, j: usize) -> f64 {
    let (fi, fj) = (i as f64, j as f64);
    let mut z = 50e-9 + 2e-9 * fj - 1e-9 * fi;
    if (50..150).contains(&i) && (50..150).contains(&j) {
        z += 1e-6;
    }
    if (80..120).contains(&i) && (80..120).contains(&j) {
        z += 0.5e-6;
    }
    z
}

const SPIKES: [(usize, usize); 5] = [(20, 20), (60, 120), (100, 30), (130, 90), (170, 170)];

fn in_block(i: usize, j: usize) -> bool {
    (10..30).contains(&i) && (150..190).contains(&j)
}

fn values(p: &HeightParams) -> [f64; 7] {
    [p.sa * 1e9, p.sq * 1e9, p.sp * 1e9, p.sv * 1e9, p.sz * 1e9, p.ssk, p.sku]
}

/// Tolerance per parameter: `Rel(r)` relative, or `Counts(step_nm, sq_nm)` for a quantized file.
#[derive(Clone, Copy)]
enum Tol {
    Rel(f64),
    Counts(f64),
}

fn check(label: &str, p: &HeightParams, r: &Ref, tol: Tol) {
    assert_eq!(p.n, r.n, "{label}: N");
    let got = values(p);
    for k in 0..7 {
        let (g, w) = (got[k], r.v[k]);
        let ok = match tol {
            Tol::Rel(rel) => (g - w).abs() <= rel * w.abs(),
            Tol::Counts(step) => {
                if k < 5 {
                    (g - w).abs() <= 3.0 * step
                } else {
                    (g - w).abs() <= 6.0 * step / r.v[1] * w.abs()
                }
            }
        };
        assert!(ok, "{label}: {} = {g} vs reference {w}", NAMES[k]);
    }
}

fn read(path: &Path, opts: &ScanOptions) -> doefab::io::scan::Scan {
    read_scan(path, opts).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

/// Marks Gwyddion's zero-stored non-measured block invalid.
fn mask_block(g: &Grid) -> Grid {
    let valid = Array2::from_shape_fn(g.dim(), |(i, j)| g.is_valid(i, j) && !in_block(i, j));
    g.clone().with_mask(valid).unwrap()
}

fn check_s1(label: &str, g: &Grid, tol: Tol) {
    assert_eq!(g.dim(), (200, 200), "{label}");
    let [px, py] = g.pitch();
    assert!((px - 1e-6).abs() < 1e-12 && (py - 1e-6).abs() < 1e-12, "{label}: pitch {px} {py}");
    check(&format!("{label} raw"), &height_params(g).unwrap(), &S1_RAW, tol);
    let (lev, plane) = level_plane(g, None).unwrap();
    check(&format!("{label} plane"), &height_params(&lev).unwrap(), &S1_PLANE, tol);
    check_plane(label, [plane.a, plane.bx, plane.by], [320e-9, 2e-9, -1e-9], tol);
}

fn check_s3(label: &str, g: &Grid, tol: Tol) {
    assert_eq!(g.dim(), (200, 200), "{label}");
    for i in 0..200 {
        for j in 0..200 {
            assert_eq!(g.is_valid(i, j), !in_block(i, j), "{label}: validity of ({i}, {j})");
        }
    }
    check(&format!("{label} raw"), &height_params(g).unwrap(), &S3_RAW, tol);
    let (lev, plane) = level_plane(g, None).unwrap();
    check(&format!("{label} plane"), &height_params(&lev).unwrap(), &S3_PLANE, tol);
    check_plane(label, [plane.a, plane.bx, plane.by], [328.636652e-9, 2.12211906e-9, -1.14303079e-9], tol);
    let o = nsigma_outliers(g, 3.0, 1, 10).unwrap();
    assert_eq!(o.positions, SPIKES.to_vec(), "{label}: 3-sigma outliers");
}

/// Plane coefficients: relative, or for quantized heights within 2 counts for `a` and
/// 2 counts per 100 pixels for the slopes.
fn check_plane(label: &str, got: [f64; 3], want: [f64; 3], tol: Tol) {
    for k in 0..3 {
        let ok = match tol {
            Tol::Rel(r) => (got[k] - want[k]).abs() <= r * want[k].abs(),
            Tol::Counts(step) => {
                (got[k] - want[k]).abs() <= 2.0 * step * 1e-9 / if k == 0 { 1.0 } else { 100.0 }
            }
        };
        assert!(ok, "{label}: plane {got:?} vs {want:?}");
    }
}

const REL: Tol = Tol::Rel(1e-6);

#[test]
fn x3pio_files_reproduce_the_reference_statistics() {
    let s = read(&local("s1_tilt_pedestal.x3pio.x3p"), &ScanOptions::default());
    assert_eq!(s.format, ScanFormat::X3p);
    assert!(s.warnings.is_empty(), "{:?}", s.warnings);
    assert!(s.metadata.iter().any(|(k, v)| k == "Record1/Revision" && v == "ISO25178-72:2017/DAM1"));
    for ((i, j), v) in s.grid.values().indexed_iter() {
        assert!((v - s1(i, j)).abs() < 1e-15, "({i}, {j})");
    }
    check_s1("x3pio S1", &s.grid, REL);
    let s = read(&local("s3_spikes_missing_nan.x3pio.x3p"), &ScanOptions::default());
    check_s3("x3pio S3", &s.grid, REL);
}

/// doefab's own height maps (OpenEXR with pitch and unit attributes, as `fab`, `wrap` and
/// `compare` write them) are scans too: S1 written in micrometres as f32 reproduces the
/// reference statistics, through the library and `scan-info`.
#[test]
fn doefab_exr_height_maps_are_read_as_scans() {
    let dir = common::tempdir();
    let p = dir.path().join("s1.exr");
    let v = Array2::from_shape_fn((200, 200), |(i, j)| (s1(i, j) * 1e6) as f32);
    let meta =
        doefab::io::raw_map::Metadata { pitch: Some([1e-6, 1e-6]), unit: Some("um".into()), text: vec![] };
    doefab::io::exr::write_exr(&p, &[("height", &v)], &meta).unwrap();
    let s = read(&p, &ScanOptions::default());
    assert_eq!(s.format, ScanFormat::Exr);
    check_s1("doefab EXR S1", &s.grid, REL);
    let out = common::ok(&["scan-info", p.to_str().unwrap(), "--json"]);
    let j: serde_json::Value = serde_json::from_str(&out).unwrap();
    assert_eq!((j["format"].as_str(), j["size"][0].as_u64()), (Some("exr"), Some(200)), "{j}");
    assert!((j["raw"]["sq"].as_f64().unwrap() * 1e9 / S1_RAW.v[1] - 1.0).abs() < 1e-6, "{j}");
}

#[test]
fn gsf_and_sur_copies_reproduce_the_reference_statistics() {
    let s = read(&local("s3_spikes_missing_nan.gsffile.gsf"), &ScanOptions::default());
    assert_eq!(s.format, ScanFormat::Gsf);
    check_s3("gsffile S3", &s.grid, REL);
    // Gwyddion's .sur: picometres, int32 counts, Z offset -149000 pm.
    let s = read(&local("s1_tilt_pedestal.gwyddion.sur"), &ScanOptions::default());
    assert!(s.metadata.iter().any(|(k, v)| k == "z_offset" && v.starts_with("-1.49e5")), "{:?}", s.metadata);
    for ((i, j), v) in s.grid.values().indexed_iter() {
        assert!((v - s1(i, j)).abs() < 1e-14, "({i}, {j}): {v} vs {}", s1(i, j));
    }
    check_s1("gwyddion S1 sur", &s.grid, REL);
    // surfalize's .sur: UTF-8 "µm" units, non-measured points as i32::MIN.
    let s = read(&local("s3_spikes_missing_nan.surfalize.sur"), &ScanOptions::default());
    check_s3("surfalize S3 sur", &s.grid, REL);
}

#[test]
fn png_pcal_scale_is_applied_within_one_count() {
    let s = read(&local("s1_tilt_pedestal.grey16.png"), &ScanOptions::default());
    assert_eq!(s.format, ScanFormat::Png);
    assert!(s.warnings.is_empty(), "{:?}", s.warnings);
    let step = 1857e-9 / 65535.0;
    for ((i, j), v) in s.grid.values().indexed_iter() {
        // Counts are floor(65536 (z - zmin) / range), read back as zmin + count * range / 65535.
        let d = s1(i, j) - v;
        assert!(d.abs() <= step * (1.0 + 1e-6), "({i}, {j}): {d}");
    }
    check_s1("gwyddion S1 png", &s.grid, Tol::Counts(step * 1e9));
    let s = read(&local("s3_spikes_missing.grey16.png"), &ScanOptions::default());
    let step3 = 6379e-9 / 65535.0;
    check_s3("gwyddion S3 png", &mask_block(&s.grid), Tol::Counts(step3 * 1e9));
    // The TIFF export carries no scale: refused, and the option is named.
    let tiff = local("s1_tilt_pedestal.grey16.tiff");
    let e = read_scan(&tiff, &ScanOptions::default()).unwrap_err();
    assert!(matches!(e, Error::Parameter { ref name, .. } if name == "pitch"), "{e:?}");
    let e = read_scan(&tiff, &ScanOptions { pitch: Some([1e-6; 2]), ..Default::default() }).unwrap_err();
    assert!(matches!(e, Error::Parameter { ref name, .. } if name == "z_scale"), "{e:?}");
    let o = ScanOptions {
        pitch: Some([1e-6; 2]),
        z_scale: Some(step),
        z_offset: Some(-149e-9),
        ..Default::default()
    };
    let s = read(&local("s1_tilt_pedestal.grey16.tiff"), &o);
    check_s1("gwyddion S1 tiff", &s.grid, Tol::Counts(step * 1e9));
}

#[test]
fn text_matrix_copy_reproduces_the_reference_statistics() {
    let s = read(&local("s1_tilt_pedestal.matrix.txt"), &ScanOptions::default());
    assert_eq!(s.format, ScanFormat::Matrix);
    check_s1("gwyddion S1 matrix", &s.grid, REL);
}

/// Every file of the shared set, when present.
#[test]
fn shared_reference_files_all_formats() {
    let dir = shared();
    let none = ScanOptions::default();
    let metres = ScanOptions { z_unit: Some(1.0), ..Default::default() };
    let s1_files: &[(&str, &ScanOptions)] = &[
        ("gwyddion/s1_tilt_pedestal.gsf", &none),
        ("gwyddion/s1_tilt_pedestal.sdf", &none),
        ("gwyddion/s1_tilt_pedestal.sur", &none),
        ("gwyddion/s1_tilt_pedestal.xyz", &metres),
        ("gwyddion/s1_tilt_pedestal.matrix.txt", &none),
        ("gwyddion/s1_tilt_pedestal.asc", &none),
        ("gsffile/s1_tilt_pedestal.gsf", &none),
        ("sdfio/s1_tilt_pedestal.ascii.sdf", &none),
        ("sdfio/s1_tilt_pedestal.bin.sdf", &none),
        ("surfalize/s1_tilt_pedestal.ascii.sdf", &none),
        ("surfalize/s1_tilt_pedestal.sdf", &none),
        ("surfalize/s1_tilt_pedestal.sur", &none),
        ("surfalize/s1_tilt_pedestal.x3p", &none),
        ("x3pio/s1_tilt_pedestal.x3p", &none),
        ("surfacetopography/s1_tilt_pedestal.x3p", &none),
    ];
    for (name, opts) in s1_files {
        let s = read(&dir.join(name), opts);
        check_s1(name, &s.grid, REL);
        if name.starts_with("surfacetopography") {
            assert!(
                s.warnings
                    .iter()
                    .any(|w| w.contains("md5checksum.hex") && w.contains("not the MD5 of main.xml")),
                "{name}: {:?}",
                s.warnings
            );
        }
    }
    let s3_nan = [
        "gsffile/s3_spikes_missing_nan.gsf",
        "sdfio/s3_spikes_missing_nan.ascii.sdf",
        "sdfio/s3_spikes_missing_nan.bin.sdf",
        "surfalize/s3_spikes_missing_nan.ascii.sdf",
        "surfalize/s3_spikes_missing_nan.sdf",
        "surfalize/s3_spikes_missing_nan.sur",
        "surfalize/s3_spikes_missing_nan.x3p",
        "x3pio/s3_spikes_missing_nan.x3p",
    ];
    for name in s3_nan {
        check_s3(name, &read(&dir.join(name), &none).grid, REL);
    }
    // Gwyddion's own exports store the non-measured block as 0.0: mask it, then compare.
    let s3_zero: &[(&str, &ScanOptions)] = &[
        ("gwyddion/s3_spikes_missing.gsf", &none),
        ("gwyddion/s3_spikes_missing.sdf", &none),
        ("gwyddion/s3_spikes_missing.sur", &none),
        ("gwyddion/s3_spikes_missing.xyz", &metres),
        ("gwyddion/s3_spikes_missing.matrix.txt", &none),
        ("gwyddion/s3_spikes_missing.asc", &none),
    ];
    for (name, opts) in s3_zero {
        let g = read(&dir.join(name), opts).grid;
        assert_eq!(g.valid_count(), 40000, "{name}");
        check_s3(name, &mask_block(&g), REL);
    }
    // The copies in profilometry/ are the shared files unchanged.
    for (copy, orig) in [
        ("s1_tilt_pedestal.x3pio.x3p", "x3pio/s1_tilt_pedestal.x3p"),
        ("s3_spikes_missing_nan.x3pio.x3p", "x3pio/s3_spikes_missing_nan.x3p"),
        ("s3_spikes_missing_nan.gsffile.gsf", "gsffile/s3_spikes_missing_nan.gsf"),
        ("s1_tilt_pedestal.gwyddion.sur", "gwyddion/s1_tilt_pedestal.sur"),
        ("s3_spikes_missing_nan.surfalize.sur", "surfalize/s3_spikes_missing_nan.sur"),
        ("s3_spikes_missing.grey16.png", "gwyddion/s3_spikes_missing.grey16.png"),
    ] {
        assert_eq!(std::fs::read(local(copy)).unwrap(), std::fs::read(dir.join(orig)).unwrap(), "{copy}");
    }
}

#[test]
fn scan_info_command_prints_the_statistics() {
    let exe = env!("CARGO_BIN_EXE_doefab");
    let out = std::process::Command::new(exe)
        .args(["--json", "scan-info"])
        .arg(local("s3_spikes_missing_nan.x3pio.x3p"))
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(v["size"], serde_json::json!([200, 200]));
    assert_eq!(v["valid"], 39200);
    assert!((v["valid_fraction"].as_f64().unwrap() - 0.98).abs() < 1e-12);
    let sa = v["levelled"]["sa"].as_f64().unwrap();
    assert!((sa * 1e9 - S3_PLANE.v[0]).abs() < 1e-6 * S3_PLANE.v[0], "{sa}");
    assert!((v["levelling"]["plane"]["a"].as_f64().unwrap() - 328.636652e-9).abs() < 1e-6 * 328.6e-9);
    // Human output, and a refusal that names the missing option.
    let out = std::process::Command::new(exe)
        .arg("scan-info")
        .arg(local("s1_tilt_pedestal.gwyddion.sur"))
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success() && text.contains("Sku") && text.contains("1 um x 1 um"), "{text}");
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("s.npy");
    doefab::io::npy::write_npy_f64(&p, &Array2::from_elem((3, 3), 1.0)).unwrap();
    let out = std::process::Command::new(exe).arg("scan-info").arg(&p).output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2));
    assert!(err.contains("pass `pitch`"), "{err}");
    let out = std::process::Command::new(exe)
        .args(["scan-info", "--pitch", "1um", "--z-unit", "nm"])
        .arg(&p)
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
}

#[test]
fn median_outliers_and_laplace_fill_restore_s1_from_s3() {
    use doefab::grid::fill::fill_missing;
    use doefab::metrology::{median_outliers, without_outliers};
    let s3 = read(&local("s3_spikes_missing_nan.x3pio.x3p"), &ScanOptions::default()).grid;
    // 3 x 3 median residuals: 5 um at the spikes, one step height (1 um or 0.5 um) at the
    // pedestal's corners, 0 on the tilted planes (the median of a plane's 3 x 3 window is its
    // centre). A floor of 2 um between the two finds exactly the spikes.
    let m = median_outliers(&s3, 3, 5.0, 2e-6).unwrap();
    assert_eq!(m.positions, SPIKES.to_vec());
    let n = nsigma_outliers(&s3, 3.0, 1, 10).unwrap();
    let clean = without_outliers(&s3, &n).unwrap();
    assert_eq!(clean.valid_count(), 39195);
    // S1 is piecewise planar and every hole (the block, each spike) sits inside one plane, where
    // the discrete Laplace equation holds exactly: the fill gives back S1.
    let (filled, count) = fill_missing(&clean).unwrap();
    assert_eq!(count, 805);
    for ((i, j), v) in filled.values().indexed_iter() {
        assert!((v - s1(i, j)).abs() < 1e-12, "({i}, {j}): {v} vs {}", s1(i, j));
    }
    check("S3 filled", &height_params(&filled).unwrap(), &S1_RAW, Tol::Rel(1e-6));
}

/// An 8-bit 4 x 1 PNG of counts 0, 85, 170, 255 with a `pCAL` chunk (x0, x1, p0, p1, unit "m"),
/// and a `Software` text when `software` is given.
fn pcal_png(x0: i32, x1: i32, p0: f64, p1: f64, software: Option<&str>) -> Vec<u8> {
    let mut out = Vec::new();
    let mut enc = png::Encoder::new(&mut out, 4, 1);
    enc.set_color(png::ColorType::Grayscale);
    enc.set_depth(png::BitDepth::Eight);
    if let Some(s) = software {
        enc.add_text_chunk("Software".to_string(), s.to_string()).unwrap();
    }
    let mut w = enc.write_header().unwrap();
    let mut d = b"Z\0".to_vec();
    d.extend_from_slice(&x0.to_be_bytes());
    d.extend_from_slice(&x1.to_be_bytes());
    d.extend_from_slice(&[0, 2]);
    d.extend_from_slice(format!("m\0{p0:e}\0{p1:e}").as_bytes());
    w.write_chunk(png::chunk::ChunkType(*b"pCAL"), &d).unwrap();
    w.write_image_data(&[0, 85, 170, 255]).unwrap();
    w.finish().unwrap();
    out
}

/// The PNG specification's pCAL (11.3.3.2): X = x0 + stored (x1 - x0) / (2^bits - 1), then
/// z = p0 + p1 X / (x1 - x0); x0 and x1 span the whole i32 range without overflow; a Gwyddion
/// file is read in Gwyddion's form only with the x0 = 0, x1 = 2^bits - 1 it writes.
#[test]
fn png_pcal_follows_the_specification_for_any_x0_x1() {
    let dir = common::tempdir();
    let opts = ScanOptions { pitch: Some([1e-6; 2]), allow_implausible: true, ..Default::default() };
    let heights = |x0: i32, x1: i32, p0: f64, p1: f64, software: Option<&str>| {
        let path = dir.path().join("p.png");
        std::fs::write(&path, pcal_png(x0, x1, p0, p1, software)).unwrap();
        read_scan(&path, &opts).map(|s| s.grid.values().iter().copied().collect::<Vec<f64>>())
    };
    let close = |got: &[f64], want: &[f64]| {
        got.iter().zip(want).all(|(g, w)| (g - w).abs() <= 1e-12 * w.abs().max(1e-9))
    };
    // x0 = -100, x1 = 155: X = stored - 100, z = 1e-6 + 1e-9 (stored - 100).
    let z = heights(-100, 155, 1e-6, 255e-9, None).unwrap();
    let want: Vec<f64> = [0.0, 85.0, 170.0, 255.0].iter().map(|s| 1e-6 + 1e-9 * (s - 100.0)).collect();
    assert!(close(&z, &want), "{z:?} vs {want:?}");
    // The whole i32 range (a fuzz finding: x1 - x0 overflowed i32).
    let z = heights(i32::MIN, i32::MAX, 0.0, 1e-6, None).unwrap();
    let span = f64::from(i32::MAX) - f64::from(i32::MIN);
    let want: Vec<f64> = [0.0, 85.0, 170.0, 255.0]
        .iter()
        .map(|s| 1e-6 * (f64::from(i32::MIN) + s * span / 255.0) / span)
        .collect();
    assert!(close(&z, &want), "{z:?} vs {want:?}");
    let e = heights(7, 7, 0.0, 1e-6, None).unwrap_err();
    let (cause, offset, path) = common::format_cause(&e);
    assert!(cause == FormatCause::Malformed && offset.is_some() && path.ends_with("p.png"), "{e:?}");
    assert!(e.to_string().contains("pCAL x0 = x1"), "{e}");
    // Gwyddion's form: z = p0 + p1 stored, and only with the x0, x1 Gwyddion writes.
    let z = heights(0, 255, 1e-6, 1e-9, Some("Gwyddion")).unwrap();
    let want: Vec<f64> = [0.0, 85.0, 170.0, 255.0].iter().map(|s| 1e-6 + 1e-9 * s).collect();
    assert!(close(&z, &want), "{z:?} vs {want:?}");
    let e = heights(i32::MIN, i32::MAX, 0.0, 1e-9, Some("Gwyddion")).unwrap_err();
    let (cause, offset, path) = common::format_cause(&e);
    assert!(cause == FormatCause::Malformed && offset.is_some() && path.ends_with("p.png"), "{e:?}");
    assert!(e.to_string().contains("x0 = -2147483648, x1 = 2147483647"), "{e}");
}

/// The real Wyko / Bruker Vision file of the shared set (`instruments/wyko.opd`, GPL-3.0, read
/// from there): size, x pitch, the non-measured points and the statistics after the
/// least-squares plane, against the values Gwyddion 2.62 and SurfaceTopography 1.27.1 computed
/// (`instruments/README.md`; six printed digits, so 1e-5 relative).
#[test]
fn wyko_opd_reproduces_two_programs_statistics() {
    let path = shared().join("instruments/wyko.opd");
    let s = read(&path, &ScanOptions::default());
    assert_eq!(s.format, ScanFormat::Opd);
    assert_eq!(s.grid.dim(), (480, 736));
    assert!((s.grid.pitch()[0] - 1.634e-6).abs() < 5e-10, "{:?}", s.grid.pitch());
    // y = Aspect (1.1667) x Pixel_size: SurfaceTopography's 0.9151750398154745 mm over 480 rows.
    assert!((s.grid.pitch()[1] / (0.9151750398154745e-3 / 480.0) - 1.0).abs() < 1e-9, "{:?}", s.grid.pitch());
    assert_eq!(s.grid.dim().0 * s.grid.dim().1 - s.grid.valid_count(), 809);
    let (lev, _) = level_plane(&s.grid, None).unwrap();
    let p = height_params(&lev).unwrap();
    let close = |got: f64, want: f64, tol: f64| (got - want).abs() <= tol * want.abs();
    for (name, got, want) in [("Sa", p.sa, 1.59376e-06), ("Sq", p.sq, 1.92653e-06), ("Sz", p.sz, 1.88444e-05)]
    {
        assert!(close(got, want, 1e-5), "{name}: {got} vs {want}");
    }
    assert!((p.ssk - 0.148677).abs() < 1e-5 && (p.sku - 2.50654).abs() < 1e-5, "{} {}", p.ssk, p.sku);
    assert!(s.metadata.iter().any(|(k, v)| k == "ObjectiveLabel" && v == "5 X"), "{:?}", s.metadata);
}

/// Wyko `.opd` files built from the layout (profilometry/make_opd_files.py): a later Vision
/// version's directory (heights in an i16 array named `Raw`, type-15 entries, an `Image` array
/// before it, entries whose sizes differ from their types'), the layout this reader refused and
/// surfalize stops on; and f32 wavelengths in an `OPD` array with each non-measured marker.
/// Against SurfaceTopography 1.27.1's reading of each (profilometry/README.md; 1e-6 relative)
/// and the injected surface (half a stored count).
#[test]
fn wyko_opd_layouts_reproduce_surface_topographys_reading() {
    const MISSING: [(usize, usize); 6] = [(0, 0), (3, 7), (12, 20), (12, 21), (25, 34), (17, 33)];
    // name, SurfaceTopography's pitch x, y (mm) and Sq, Sa, Sz (mm), one stored count (m).
    let files = [
        (
            "wave_pedestal.raw.layout.opd",
            [0.0006500000017695129, 0.0008125000022118911],
            [0.000356966941, 0.000270245439, 0.00164317887],
            f64::from(632.8f32) * 1e-9 / 2048.0,
        ),
        (
            "wave_pedestal.opd_f32.layout.opd",
            [0.0007999999797903001, 0.0007999999797903001],
            [0.000356966191, 0.000270244907, 0.00164316716],
            // Two f32 steps of the largest height.
            2.0 * f64::from(f32::EPSILON) * 1.7e-6,
        ),
    ];
    for (name, pitch_mm, sq_sa_sz_mm, count) in files {
        let s = read(&local(name), &ScanOptions::default());
        assert_eq!(s.format, ScanFormat::Opd);
        assert!(s.warnings.is_empty(), "{name}: {:?}", s.warnings);
        assert_eq!(s.grid.dim(), (26, 35), "{name}");
        assert_eq!(26 * 35 - s.grid.valid_count(), 6, "{name}");
        for (got, want) in s.grid.pitch().into_iter().zip(pitch_mm) {
            assert!((got / (want * 1e-3) - 1.0).abs() < 1e-12, "{name}: pitch {got} vs {want} mm");
        }
        let p = height_params(&s.grid).unwrap();
        for ((label, got), want) in [("Sq", p.sq), ("Sa", p.sa), ("Sz", p.sz)].into_iter().zip(sq_sa_sz_mm) {
            let want = want * 1e-3;
            println!(
                "{name} {label} {got:.9e} vs SurfaceTopography {want:.9e}, {:.1e} relative",
                (got - want) / want
            );
            assert!((got - want).abs() <= 1e-6 * want, "{name} {label} {got} vs {want}");
        }
        check_wave_pedestal(name, &s, 0.0, count, &MISSING);
    }
    let s = read(&local("wave_pedestal.raw.layout.opd"), &ScanOptions::default());
    let md = |k: &str| s.metadata.iter().find(|(key, _)| key == k).map(|(_, v)| v.as_str());
    assert_eq!(md("Title"), Some("later Vision layout"));
    assert_eq!(md("AdjustVSI_Gain"), Some("3"));
    assert_eq!(md("NumFrames"), Some("70000"));
    assert_eq!(md("ImageModificat~0"), Some("2"));
}

/// The real Digital Surf file of the shared set (`instruments/digitalsurf.sur`): the statistics
/// after the least-squares plane against Gwyddion's and SurfaceTopography's (1e-5 relative).
#[test]
fn digital_surf_instrument_file_reproduces_two_programs_statistics() {
    let s = read(&shared().join("instruments/digitalsurf.sur"), &ScanOptions::default());
    assert_eq!(s.grid.dim(), (512, 512));
    assert!((s.grid.pitch()[0] - 19.57e-9).abs() < 5e-12, "{:?}", s.grid.pitch());
    assert_eq!(s.grid.valid_count(), 512 * 512);
    let (lev, _) = level_plane(&s.grid, None).unwrap();
    let p = height_params(&lev).unwrap();
    let close = |got: f64, want: f64| (got - want).abs() <= 1e-5 * want.abs();
    for (name, got, want) in [("Sa", p.sa, 4.3248e-08), ("Sq", p.sq, 5.57426e-08), ("Sz", p.sz, 2.41356e-07)]
    {
        assert!(close(got, want), "{name}: {got} vs {want}");
    }
    assert!((p.ssk - 1.40475).abs() < 1e-5 && (p.sku - 3.54574).abs() < 1e-5, "{} {}", p.ssk, p.sku);
}

/// The real Sensofar file of the shared set (`instruments/sensofar.plu`, a later revision of the
/// 2000 layout with an intensity image after the heights): size, pitch and the statistics after
/// the least-squares plane against Gwyddion's and SurfaceTopography's (1e-5 relative).
#[test]
fn sensofar_plu_reproduces_two_programs_statistics() {
    let s = read(&shared().join("instruments/sensofar.plu"), &ScanOptions::default());
    assert_eq!(s.format, ScanFormat::Plu);
    assert_eq!(s.grid.dim(), (576, 768));
    assert!(s.grid.pitch().iter().all(|p| (p - 0.332e-6).abs() < 1e-12), "{:?}", s.grid.pitch());
    assert_eq!(s.grid.valid_count(), 576 * 768);
    let (lev, _) = level_plane(&s.grid, None).unwrap();
    let p = height_params(&lev).unwrap();
    let close = |got: f64, want: f64| (got - want).abs() <= 1e-5 * want.abs();
    for (name, got, want) in [("Sa", p.sa, 4.48391e-06), ("Sq", p.sq, 5.16969e-06), ("Sz", p.sz, 2.3656e-05)]
    {
        assert!(close(got, want), "{name}: {got} vs {want}");
    }
    assert!((p.ssk + 0.227113).abs() < 1e-5 && (p.sku - 1.86818).abs() < 1e-5, "{} {}", p.ssk, p.sku);
    assert!(s.metadata.iter().any(|(k, v)| k == "date" && v.starts_with("Mon Apr 19")), "{:?}", s.metadata);
}

/// Gwyddion's own `.gwy` files of the shared set: S1 as written, S1 after Gwyddion's plane
/// levelling, S3 with its mask (the one Gwyddion format that keeps the non-measured block
/// apart), and S3 after Gwyddion's Laplace fill with the mask kept: each reproduces the
/// statistics Gwyddion computed (README of the shared set), the mask exactly the block.
#[test]
fn gwyddion_native_files_reproduce_gwyddions_statistics() {
    let dir = shared().join("gwyddion");
    let none = ScanOptions::default();
    let s1 = read(&dir.join("s1_tilt_pedestal.gwy"), &none);
    assert_eq!(s1.format, ScanFormat::Gwy);
    check_s1("s1_tilt_pedestal.gwy", &s1.grid, REL);
    assert!(s1.warnings.is_empty(), "{:?}", s1.warnings);
    assert!(s1.metadata.iter().any(|(k, v)| k == "/0/data/title" && !v.is_empty()), "{:?}", s1.metadata);
    let levelled = read(&dir.join("s1_after_level.gwy"), &none);
    check("s1_after_level.gwy", &height_params(&levelled.grid).unwrap(), &S1_PLANE, REL);
    for name in ["s3_spikes_missing.gwy", "s3_after_laplace.gwy"] {
        let s = read(&dir.join(name), &none);
        check_s3(name, &s.grid, REL);
        assert!(
            s.warnings.iter().any(|w| w.contains("800 points under the channel's mask")),
            "{:?}",
            s.warnings
        );
    }
}

/// What surfalize 0.19.2 computed reading a file back (profilometry/README.md): rows, columns,
/// pitch, non-measured points, Sq, Sa, Sz (in `unit` metres).
struct Surfalize {
    dim: (usize, usize),
    pitch: [f64; 2],
    missing: usize,
    sq_sa_sz: [f64; 3],
    unit: f64,
}

/// A scan against surfalize's reading of the same file: size, pitch (exact: both compute it
/// from the same stored numbers), non-measured count (exact), Sq, Sa, Sz within 1e-4 relative
/// (surfalize's figures are printed to 9 digits).
fn check_surfalize(name: &str, s: &doefab::io::scan::Scan, want: &Surfalize) {
    check_reading(name, s, want, "surfalize");
}

/// As [`check_surfalize`], against the reading of `program`.
fn check_reading(name: &str, s: &doefab::io::scan::Scan, want: &Surfalize, program: &str) {
    assert_eq!(s.grid.dim(), want.dim, "{name}: size");
    assert_eq!(s.grid.pitch(), want.pitch, "{name}: pitch");
    assert_eq!(want.dim.0 * want.dim.1 - s.grid.valid_count(), want.missing, "{name}: non-measured points");
    let p = height_params(&s.grid).unwrap();
    for (k, (got, w)) in [p.sq, p.sa, p.sz].into_iter().zip(want.sq_sa_sz).enumerate() {
        let w = w * want.unit;
        println!(
            "{name}: {} {got:.9e} vs {program} {w:.9e}, {:.1e} relative",
            ["Sq", "Sa", "Sz"][k],
            (got - w) / w
        );
        assert!((got - w).abs() <= 1e-4 * w, "{name}: {} = {got} vs {program} {w}", ["Sq", "Sa", "Sz"][k]);
    }
}

/// Alicona `.al3d` written by surfalize (rows padded to 8 bytes, the invalid pixel value for the
/// non-measured points) and one built from the format's layout (more tags, a comment, texture
/// planes and a repeatability plane that filters three points), each against surfalize's
/// reading; the shared S1/S3 files against the reference statistics.
#[test]
fn alicona_al3d_reproduces_surfalizes_reading() {
    let none = ScanOptions::default();
    let s = read(&local("wave_pedestal.surfalize.al3d"), &none);
    assert_eq!(s.format, ScanFormat::Al3d);
    assert!(s.warnings.is_empty(), "{:?}", s.warnings);
    let want = Surfalize {
        dim: (30, 41),
        pitch: [1.5e-6, 2.0e-6],
        missing: 7,
        sq_sa_sz: [0.331273951, 0.24561185, 1.6470824],
        unit: 1e-6,
    };
    check_surfalize("wave_pedestal.surfalize.al3d", &s, &want);
    assert!(
        s.metadata.iter().any(|(k, v)| k == "InvalidPixelValue" && v.starts_with("3000000")),
        "{:?}",
        s.metadata
    );
    let s = read(&local("quality_map.layout.al3d"), &none);
    let want = Surfalize {
        dim: (9, 13),
        pitch: [2.5e-6, 2.0e-6],
        missing: 5,
        sq_sa_sz: [0.218434186, 0.184382914, 0.784082431],
        unit: 1e-6,
    };
    check_surfalize("quality_map.layout.al3d", &s, &want);
    assert!(s.warnings.iter().any(|w| w.starts_with("3 points whose repeatability")), "{:?}", s.warnings);
    assert!(s.metadata.iter().any(|(k, v)| k == "comment" && v == "Built from the AL3D layout"));
    let dir = shared().join("surfalize");
    check_s1("surfalize S1 al3d", &read(&dir.join("s1_tilt_pedestal.al3d"), &none).grid, REL);
    check_s3("surfalize S3 al3d", &read(&dir.join("s3_spikes_missing_nan.al3d"), &none).grid, REL);
}

/// TrueMap `.tmd` written by surfalize from the surface in millimetres (the format's unit; see
/// profilometry/README.md), against surfalize's reading; the shared S1 file, which surfalize
/// wrote from micrometre numbers, reads per the format as a surface a thousand times larger.
#[test]
fn truemap_tmd_reproduces_surfalizes_reading() {
    let none = ScanOptions::default();
    let s = read(&local("wave_pedestal.surfalize.tmd"), &none);
    assert_eq!(s.format, ScanFormat::Tmd);
    assert!(s.warnings.is_empty(), "{:?}", s.warnings);
    let want = Surfalize {
        dim: (29, 37),
        // surfalize's step (f32 length / count, in the file's millimetres), in metres.
        pitch: [0.0008000000002416404 * 1e-3, 0.00124999996403168 * 1e-3],
        missing: 5,
        sq_sa_sz: [0.000347417401, 0.000262105081, 0.00164708239],
        unit: 1e-3,
    };
    check_surfalize("wave_pedestal.surfalize.tmd", &s, &want);
    assert!(
        s.metadata.iter().any(|(k, v)| k == "comment" && v == "Exported by surfalize"),
        "{:?}",
        s.metadata
    );
    let s = read(&shared().join("surfalize/s1_tilt_pedestal.tmd"), &none);
    assert_eq!(s.grid.pitch(), [1e-3, 1e-3]);
    let p = height_params(&s.grid).unwrap();
    assert!((p.sq / (S1_RAW.v[1] * 1e-6) - 1.0).abs() < 1e-6, "Sq {}", p.sq);
    assert!(s.warnings.iter().any(|w| w.contains("kept: the file states its unit")), "{:?}", s.warnings);
}

/// The wave-pedestal surface of `profilometry/wave_pedestal.py`, micrometres (i = row from
/// the top of the image, j = column).
fn wave_pedestal_um(i: usize, j: usize) -> f64 {
    use std::f64::consts::PI;
    let (fi, fj) = (i as f64, j as f64);
    let mut z =
        0.05 + 0.4 * (2.0 * PI * fj / 13.0).sin() * (2.0 * PI * fi / 11.0).cos() + 0.002 * fj - 0.001 * fi;
    if (10..20).contains(&i) && (15..30).contains(&j) {
        z += 0.8;
    }
    z
}

/// Every measured point of `s` against the injected surface shifted by `shift_um`, within half a
/// count of `count` metres; the non-measured points exactly `missing`.
fn check_wave_pedestal(
    name: &str,
    s: &doefab::io::scan::Scan,
    shift_um: f64,
    count: f64,
    missing: &[(usize, usize)],
) {
    let v = s.grid.values_nan_invalid();
    for ((i, j), h) in v.indexed_iter() {
        if missing.contains(&(i, j)) {
            assert!(h.is_nan(), "{name}: ({i}, {j}) should be non-measured, reads {h}");
        } else {
            let want = (wave_pedestal_um(i, j) + shift_um) * 1e-6;
            assert!((h - want).abs() <= 0.5 * count * (1.0 + 1e-9), "{name}: ({i}, {j}) {h} vs {want}");
        }
    }
}

/// Keyence `.vk4` and `.vk6` built from the VK4 layout (profilometry/make_vk_frt_files.py),
/// against surfalize's and SurfaceTopography's readings (the same figures from both) and the
/// surface the script injected; the second height layer is skipped with a warning.
#[test]
fn keyence_vk_reproduces_surfalize_and_surfacetopography() {
    let none = ScanOptions::default();
    for name in ["wave_pedestal.layout.vk4", "wave_pedestal.layout.vk6"] {
        let s = read(&local(name), &none);
        assert_eq!(s.format, ScanFormat::Vk);
        let want = Surfalize {
            dim: (23, 31),
            // surfalize: 1.25 and 1.5999999999999999 um; SurfaceTopography: 1250000 and
            // 1600000 pm: the stored 1250000 and 1600000 pm.
            pitch: [1_250_000.0 * 1e-12, 1_600_000.0 * 1e-12],
            missing: 0,
            sq_sa_sz: [0.389009715, 0.307907414, 1.64316],
            unit: 1e-6,
        };
        check_surfalize(name, &s, &want);
        check_wave_pedestal(name, &s, 1.0, 10e-12, &[]);
        assert_eq!(s.warnings, ["height image 1 read; height image 2 skipped"], "{name}");
        let m = |k: &str| s.metadata.iter().find(|(key, _)| key == k).map(|(_, v)| v.as_str());
        assert_eq!(m("date"), Some("2023-11-07T09:41:03+01:00"), "{name}");
        assert_eq!(m("lens_magnification"), Some("50"));
        assert_eq!(m("lens_name"), Some("CF IC EPI Plan 50X"));
        assert_eq!(m("title"), Some("wave pedestal"));
        assert_eq!(m("numerical_aperture"), Some("0.95"));
        assert_eq!(m("images_not_read"), Some("colour peak image, light image 1"));
    }
}

/// Olympus LEXT `.lext` written with tifffile in the LEXT layout (profilometry/make_lext.py):
/// little-endian with the EXIF calibration factors (1.002, 0.998, 1.010), and big-endian with
/// signed 32-bit counts in strips of 5 rows, the mask as page 0 too and no EXIF block; each
/// against surfalize's reading (and the first against SurfaceTopography's), and the injected
/// surface with the INVALID page's points not measured.
#[test]
fn olympus_lext_reproduces_surfalize_and_surfacetopography() {
    let none = ScanOptions::default();
    let missing = [(3, 4), (12, 20), (22, 30), (0, 17), (7, 0)];
    let pm = 1e-12;
    // (file, calibration factors as MakerCalibrationValue x 1e-6, surfalize's Sq, Sa, Sz in um)
    for (name, cal, sq_sa_sz) in [
        (
            "wave_pedestal.tifffile.lext",
            [1_002_000.0 * 1e-6, 998_000.0 * 1e-6, 1_010_000.0 * 1e-6],
            [0.389467548, 0.307868036, 1.643169],
        ),
        ("wave_pedestal_be.tifffile.lext", [1.0; 3], [0.389468345, 0.30786835, 1.6432]),
    ] {
        let s = read(&local(name), &none);
        assert_eq!(s.format, ScanFormat::Lext);
        assert!(s.warnings.is_empty(), "{name}: {:?}", s.warnings);
        // surfalize: 2.505 and 1.2475 um (calibrated), 2.5 and 1.25 um; SurfaceTopography
        // 2.5049999999999994 and 1.2475 um: the stored 2500000 and 1250000 pm times the factors.
        let want = Surfalize {
            dim: (23, 31),
            pitch: [2_500_000.0 * cal[0] * pm, 1_250_000.0 * cal[1] * pm],
            missing: 5,
            sq_sa_sz,
            unit: 1e-6,
        };
        check_surfalize(name, &s, &want);
        check_wave_pedestal(name, &s, 1.0, 50.0 * cal[2] * pm, &missing);
        let m = |k: &str| s.metadata.iter().find(|(key, _)| key == k).map(|(_, v)| v.as_str());
        assert_eq!(m("instrument"), Some("OLYMPUS OLS4100"), "{name}");
        assert_eq!(m("date"), Some("2024-03-05T14:22:31"), "{name}");
        assert_eq!(m("software"), Some("LEXT 2.1.3.1"), "{name}");
        assert_eq!(m("invalid_page"), Some("page 3: 5 points not measured"), "{name}");
        assert_eq!(m("HeightInfo/HeightDataPerPixelZ"), Some("50"), "{name}");
        if name.contains("_be") {
            assert_eq!(m("calibration"), Some("no EXIF device settings"));
            assert_eq!(m("images_not_read"), Some("INTENSITY (page 1), COLOR (page 4)"));
            assert_eq!(m("height_page"), Some("page 2 of 5 (32-bit signed, byte order MM)"));
        } else {
            assert_eq!(m("objective"), Some("MPLAPON50XLEXT"));
            assert_eq!(m("magnification"), Some("50.0"));
            assert_eq!(
                m("calibration"),
                Some("MakerCalibrationValue x 1e-6 applied: X 1.002, Y 0.998, Z 1.01")
            );
            assert_eq!(m("images_not_read"), Some("COLOR (page 0, inferred), INTENSITY (page 1)"));
            assert_eq!(m("height_page"), Some("page 2 of 4 (16-bit unsigned, byte order II)"));
            // SurfaceTopography 1.27.1 (its heights, with the INVALID page as the mask).
            let st = Surfalize { sq_sa_sz: [0.389467548, 0.307868036, 1.643169], ..want };
            check_reading(name, &s, &st, "SurfaceTopography");
        }
    }
}

/// FRT MicroProf `.frt` built from the FRT layout (profilometry/make_vk_frt_files.py): version
/// 1.00 with the single-image block and 1.01 with the multi-image block (an intensity image
/// skipped with a warning), against SurfaceTopography's reading and the injected surface,
/// the first stored row the bottom of the image and the count 1 non-measured.
#[test]
fn frt_microprof_reproduces_surfacetopography() {
    let none = ScanOptions::default();
    let missing = [(3, 4), (12, 20), (22, 30), (0, 17)];
    // (file, SurfaceTopography's Sq; Sa and Sz by numpy on its heights, metres; count, shift)
    for (name, sq_sa_sz, count, shift) in [
        ("wave_pedestal.layout.frt", [3.8926128e-07, 3.07642757e-07, 1.643168e-06], 1e-12, 0.0),
        ("wave_pedestal_multi.layout.frt", [3.89262602e-07, 3.07643927e-07, 1.6432e-06], 5e-11, 1.0),
    ] {
        let s = read(&local(name), &none);
        assert_eq!(s.format, ScanFormat::Frt);
        // SurfaceTopography: steps 2.5e-06 and 2e-06 m, the ranges over the counts.
        let want = Surfalize {
            dim: (23, 31),
            pitch: [31.0 * 2.5e-6 / 31.0, 23.0 * 2e-6 / 23.0],
            missing: 4,
            sq_sa_sz,
            unit: 1.0,
        };
        check_reading(name, &s, &want, "SurfaceTopography");
        check_wave_pedestal(name, &s, shift, count, &missing);
        let m = |k: &str| s.metadata.iter().find(|(key, _)| key == k).map(|(_, v)| v.as_str());
        assert_eq!(m("date"), Some("2023-11-14T22:13:20Z"), "{name}");
        assert_eq!(m("parameter_set"), Some("CWL 300um"));
        assert_eq!(m("description"), Some("wave pedestal from the FRT layout"));
        if name.contains("multi") {
            assert_eq!(s.warnings, ["Topography (top sensor) 1 read; skipped: Intensity (top sensor) 1"]);
        } else {
            assert!(s.warnings.is_empty(), "{:?}", s.warnings);
        }
    }
}

/// The surface `make_datx_files.py` injects ([`wave_pedestal_um`]), `None` where the file marks
/// the point not measured.
fn datx_surface_um(i: usize, j: usize) -> Option<f64> {
    const MISSING: [(usize, usize); 6] = [(0, 0), (3, 7), (12, 20), (12, 21), (25, 34), (17, 33)];
    (!MISSING.contains(&(i, j))).then(|| wave_pedestal_um(i, j))
}

/// Zygo `.datx` written with h5py in Mx's layout: f32 nanometres in a chunked, deflated and
/// shuffled dataset, `No Data` points, an intensity channel, found through the `/MetaData`
/// link table; against SurfaceTopography 1.27.1's reading (profilometry/README.md) and the
/// injected surface. The same surface as f64 fringes in an older layout (`/Data/Surface`, no
/// link table, fixed-array converters; SurfaceTopography refuses fringes) against the surface.
#[test]
fn zygo_datx_reproduces_surface_topographys_reading() {
    let none = ScanOptions::default();
    let s = read(&local("wave_pedestal.h5py.datx"), &none);
    assert_eq!(s.format, ScanFormat::Datx);
    assert_eq!(
        s.warnings,
        ["the height map /Measurement/Surface is read; other channels skipped: /Measurement/Intensity"]
    );
    // SurfaceTopography: 35 x 26 points, pitch 650 nm x 800 nm (its 799.9999999999999 is its
    // size / count), 6 masked, Sq 356.96619 nm; Sa 270.244907 nm and Sz 1643.16705 nm from the
    // heights it returns.
    assert_eq!(s.grid.dim(), (26, 35));
    let [px, py] = s.grid.pitch();
    assert!((px / 650e-9 - 1.0).abs() < 1e-12 && (py / 800e-9 - 1.0).abs() < 1e-12, "{px} {py}");
    assert_eq!(26 * 35 - s.grid.valid_count(), 6);
    let p = height_params(&s.grid).unwrap();
    for (name, got, want) in
        [("Sq", p.sq, 356.96619e-9), ("Sa", p.sa, 270.244907e-9), ("Sz", p.sz, 1643.16705e-9)]
    {
        println!(
            "datx {name} {got:.9e} vs SurfaceTopography {want:.9e}, {:.1e} relative",
            (got - want) / want
        );
        assert!((got - want).abs() <= 1e-6 * want, "{name} {got} vs {want}");
    }
    let md = |k: &str| s.metadata.iter().find(|(key, _)| key == k).map(|(_, v)| v.as_str());
    assert_eq!(md("Data Context.Data Attributes.System Type"), Some("NexView NX2"));
    assert_eq!(md("Data Context.Data Attributes.Objective"), Some("50X Mirau"));
    assert_eq!(md("Data Context.Data Attributes.Time Stamp"), Some("2026-11-26 10:15:00"));
    assert_eq!(md("Unit"), Some("NanoMeters"));
    let fringes = read(&local("wave_pedestal_fringes.h5py.datx"), &none);
    assert!(fringes.warnings.is_empty(), "{:?}", fringes.warnings);
    assert_eq!(fringes.grid.pitch(), [650e-9, 800e-9]);
    for (g, tol) in [(&s.grid, 6e-8), (&fringes.grid, 1e-12)] {
        for ((i, j), v) in g.values().indexed_iter() {
            match datx_surface_um(i, j) {
                None => assert!(!g.is_valid(i, j), "({i}, {j}) should be non-measured"),
                Some(z) => {
                    assert!(g.is_valid(i, j), "({i}, {j})");
                    // f32 nanometres: half an f32 step of the largest height (1.7 um).
                    assert!((v - z * 1e-6).abs() <= tol * 1.7e-6, "({i}, {j}) {v} vs {z} um");
                }
            }
        }
    }
}

/// Bruker Vision64 `.opdx` built from the format's layout (make_opdx_files.py: f32 counts of
/// `DataScale` = 0.001 um, extents over (n - 1) points, NaN non-measured points, an intensity
/// channel beside the height channel), against SurfaceTopography 1.27.1's reading
/// (profilometry/README.md) and the injected surface.
#[test]
fn vision64_opdx_reproduces_surface_topographys_reading() {
    let s = read(&local("wave_pedestal.layout.opdx"), &ScanOptions::default());
    assert_eq!(s.format, ScanFormat::Opdx);
    assert_eq!(s.warnings, ["the height channel 'Height' is read; other 2-D channels skipped: Intensity"]);
    assert_eq!(s.grid.dim(), (26, 35));
    let [px, py] = s.grid.pitch();
    assert!((px / 0.65e-6 - 1.0).abs() < 1e-12 && (py / 0.8e-6 - 1.0).abs() < 1e-12, "{px} {py}");
    assert_eq!(26 * 35 - s.grid.valid_count(), 6);
    let p = height_params(&s.grid).unwrap();
    for (name, got, want) in
        [("Sq", p.sq, 0.35696619e-6), ("Sa", p.sa, 0.270244907e-6), ("Sz", p.sz, 1.64316705e-6)]
    {
        println!(
            "opdx {name} {got:.9e} vs SurfaceTopography {want:.9e}, {:.1e} relative",
            (got - want) / want
        );
        assert!((got - want).abs() <= 1e-6 * want, "{name} {got} vs {want}");
    }
    let md = |k: &str| s.metadata.iter().find(|(key, _)| key == k).map(|(_, v)| v.as_str());
    assert_eq!(md("MeasurementSettings/InstrumentName"), Some("ContourX-500"));
    assert_eq!(md("MeasurementSettings/Objective"), Some("20X"));
    assert_eq!(md("Date"), Some("11/26/2026"));
    for ((i, j), v) in s.grid.values().indexed_iter() {
        match datx_surface_um(i, j) {
            None => assert!(!s.grid.is_valid(i, j), "({i}, {j}) should be non-measured"),
            Some(z) => assert!((v - z * 1e-6).abs() <= 6e-8 * 1.7e-6, "({i}, {j}) {v} vs {z} um"),
        }
    }
}

/// Bruker Nanoscope `.spm` built from the format's layout (version 9.3 with 32-bit data and three
/// channels, version 5.31 with 16-bit data), against SurfaceTopography's reading (pySPM reads
/// the same Sq, Sa, Sz) and against the surface injected, within one stored count.
#[test]
fn nanoscope_spm_reproduces_surfacetopographys_reading() {
    let none = ScanOptions::default();
    // (file, Sq, Sa, Sz in nm, metres per count)
    for (name, sq_sa_sz, count) in [
        (
            "wave_pedestal.v9.layout.spm",
            [334.365262, 248.59571, 1647.08242],
            440.0 / 2f64.powi(32) * 43.91e-9,
        ),
        ("wave_pedestal.v5.layout.spm", [334.364555, 248.595143, 1647.08061], 440.0 / 65536.0 * 43.91e-9),
    ] {
        let s = read(&local(name), &none);
        assert_eq!(s.format, ScanFormat::Nanoscope);
        let want = Surfalize {
            dim: (29, 41),
            // Scan Size 20 x 12 um over the counts, as the reader computes it from the header.
            pitch: [20.0 * 1e-6 / 41.0, 12.0 * 1e-6 / 29.0],
            missing: 0,
            sq_sa_sz,
            unit: 1e-9,
        };
        check_surfalize(name, &s, &want);
        // The top line of the image is row 0 (the file stores the bottom line first).
        let g = s.grid.values();
        for ((i, j), v) in g.indexed_iter() {
            let truth = wave_pedestal_um(i, j) * 1e-6;
            assert!((v - truth).abs() <= 0.5 * count + 1e-15, "{name} ({i}, {j}): {v} vs {truth}");
        }
        let meta = |k: &str| s.metadata.iter().find(|(key, _)| key == k).map(|(_, v)| v.as_str());
        assert_eq!(meta("channel"), Some("Height"), "{name}");
        assert_eq!(meta("instrument"), Some("Bruker Dimension Icon"), "{name}");
        assert_eq!(meta("Ciao scan list: @Sens. Phase"), Some("V 18 \u{ba}/V"), "{name}");
    }
    let s = read(&local("wave_pedestal.v9.layout.spm"), &none);
    assert!(
        s.warnings.iter().any(|w| w.contains("read 'Height', skipped 'ZSensor', 'Phase'")),
        "{:?}",
        s.warnings
    );
    assert!(read(&local("wave_pedestal.v5.layout.spm"), &none).warnings.is_empty());
}

/// Sensofar `.plux` built from the format's layout (two layers, an intensity stack, NaN points),
/// against surfalize's and SurfaceTopography's readings and the surface injected.
#[test]
fn sensofar_plux_reproduces_two_programs_readings() {
    let name = "wave_pedestal.layout.plux";
    let s = read(&local(name), &ScanOptions::default());
    assert_eq!(s.format, ScanFormat::Plux);
    let mut want = Surfalize {
        dim: (27, 37),
        pitch: [0.65 * 1e-6, 0.9 * 1e-6],
        missing: 6,
        sq_sa_sz: [0.350323766, 0.26383993, 1.64316726],
        unit: 1e-6,
    };
    check_surfalize(name, &s, &want);
    // SurfaceTopography's figures (f64 sums; surfalize sums in f32).
    want.sq_sa_sz = [0.350323778, 0.263839931, 1.64316714];
    check_surfalize(name, &s, &want);
    for ((i, j), v) in s.grid.values().indexed_iter() {
        if s.grid.is_valid(i, j) {
            let truth = wave_pedestal_um(i, j) * 1e-6;
            assert!((v - truth).abs() <= 1e-7 * truth.abs() + 1e-15, "({i}, {j}): {v} vs {truth}");
        }
    }
    assert!(s.warnings.iter().any(|w| w.contains("skipped LAYER_1")), "{:?}", s.warnings);
    let meta = |k: &str| s.metadata.iter().find(|(key, _)| key == k).map(|(_, v)| v.as_str());
    assert_eq!(meta("instrument"), Some("Sensofar S neox"));
    assert_eq!(meta("objective"), Some("Nikon 50X EPI"));
    assert_eq!(meta("date"), Some("2025-10-16 14:15:41"));
}
