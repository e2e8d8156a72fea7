//! Bad input for the scan readers and analytic checks of the surface statistics: truncated and
//! corrupted files of every binary format (an error naming the file and, for the formats this
//! crate parses itself, the byte offset; never a panic), all-NaN scans, missing pitch or height
//! unit, x/y pitch mismatch, implausible heights, a MetroPro file built byte by byte.

use crate::common;

use std::path::{Path, PathBuf};

use doefab::io::scan::zygo::{self, MetroProFields, INVALID_PHASE};
use doefab::io::scan::{decode_scan_raw, read_scan, scan_from_raw, ScanOptions};
use doefab::metrology::height_params;
use doefab::{DataCause, Error, FormatCause};
use ndarray::Array2;

fn local(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("profilometry").join(name)
}

fn decode(name: &str, bytes: &[u8], opts: &ScanOptions) -> doefab::Result<doefab::io::scan::Scan> {
    let p = Path::new(name);
    scan_from_raw(p, decode_scan_raw(p, bytes, opts)?, opts)
}

/// Cuts `bytes` at several offsets (every byte of the first 600, then a spread) and checks the
/// error names the file and, when `offsets`, a byte offset.
fn check_cuts(name: &str, bytes: &[u8], offsets: bool) {
    check_cuts_below(name, bytes, 600, bytes.len(), offsets);
}

/// As [`check_cuts`] for a file whose reader needs only its first `n` bytes (padding after the
/// last row may be absent), cut at every byte of the first `every`.
fn check_cuts_below(name: &str, bytes: &[u8], every: usize, n: usize, offsets: bool) {
    let mut cuts: Vec<usize> = (0..n.min(every)).collect();
    cuts.extend((1..40).map(|k| k * n / 40));
    cuts.extend([n - 1, n - 2, n - 8]);
    for cut in cuts {
        let r = std::panic::catch_unwind(|| decode(name, &bytes[..cut], &ScanOptions::default()));
        let e = match r {
            Ok(Err(e)) => e,
            Ok(Ok(_)) => panic!("{name} cut at {cut} of {n} bytes was accepted"),
            Err(_) => panic!("{name} cut at {cut} panicked"),
        };
        let (_, offset, path) = common::format_cause(&e);
        assert_eq!(path, Path::new(name), "{name} cut at {cut}: {e:?}");
        if offsets && cut > 0 {
            assert!(offset.is_some(), "{name} cut at {cut}: {e:?}");
        }
    }
}

/// Flips bytes one at a time at a spread of positions: errors or reads, never panics.
fn check_corruption(name: &str, bytes: &[u8]) {
    let n = bytes.len();
    for k in 0..200 {
        let pos = (k * 7919) % n;
        let mut b = bytes.to_vec();
        b[pos] ^= 0x5a;
        let r = std::panic::catch_unwind(|| decode(name, &b, &ScanOptions::default()));
        match r {
            Err(_) => panic!("{name} corrupted at {pos} panicked"),
            Ok(Err(e)) => assert!(e.to_string().contains(name), "{name} corrupted at {pos}: {e}"),
            Ok(Ok(_)) => {}
        }
    }
}

fn mp_fields() -> MetroProFields {
    MetroProFields {
        header_format: 1,
        phase_res: 1,
        wavelength: 632.8e-9,
        scale_factor: 0.5,
        obliquity: 1.0,
        camera_res: 2.5e-6,
        inverted: false,
        buckets: 1,
    }
}

#[test]
fn truncated_and_corrupted_binary_files_are_errors_with_offsets() {
    for name in [
        "s1_tilt_pedestal.x3pio.x3p",
        "s3_spikes_missing_nan.gsffile.gsf",
        "s1_tilt_pedestal.gwyddion.sur",
        "s3_spikes_missing_nan.surfalize.sur",
    ] {
        let bytes = std::fs::read(local(name)).unwrap();
        let short = format!("cut-{name}");
        check_cuts(&short, &bytes, true);
        check_corruption(&short, &bytes);
    }
    let v = Array2::from_shape_fn((20, 30), |(i, j)| (i * 30 + j) as f64 * 1e-9);
    check_cuts("cut.sdf", &doefab::io::scan::sdf::encode_binary(&v, [1e-6; 2]), true);
    let phase = Array2::from_shape_fn((12, 16), |(i, j)| (i * 16 + j) as i32 * 100);
    let mp = zygo::encode(&mp_fields(), &phase);
    check_cuts("cut.dat", &mp, true);
    check_corruption("bad.dat", &mp);
    // Gwyddion's native format, from the shared set (read there, not copied).
    let gwy = std::fs::read(common::shared_data("surfaces/gwyddion/s3_spikes_missing.gwy")).unwrap();
    check_cuts("cut.gwy", &gwy, true);
    check_corruption("bad.gwy", &gwy);
    // PNG goes through the png crate: the file is named, no offset promised.
    let png = std::fs::read(local("s3_spikes_missing.grey16.png")).unwrap();
    check_cuts("cut.png", &png, false);
    check_corruption("bad.png", &png);
}

#[test]
fn metropro_file_built_byte_by_byte() {
    let mut phase = Array2::from_shape_fn((6, 8), |(i, j)| (i as i32 - 2) * 5000 + j as i32 * 300);
    phase[[1, 2]] = INVALID_PHASE;
    phase[[4, 7]] = i32::MAX;
    let f = mp_fields();
    let bytes = zygo::encode(&f, &phase);
    // Header format 1: 834-byte header, then 1 bucket of 8 x 6 u16, then the i32 phase map.
    assert_eq!(bytes.len(), 834 + 2 * 48 + 4 * 48);
    let s = decode("m.dat", &bytes, &ScanOptions::default()).unwrap();
    assert_eq!(s.grid.pitch(), [2.5e-6f32 as f64; 2]);
    assert_eq!(s.grid.valid_count(), 46);
    assert!(!s.grid.is_valid(1, 2) && !s.grid.is_valid(4, 7));
    // High phase resolution: R = 32768; heights = phase * S * O * lambda / R.
    let k = 0.5 * 1.0 * (632.8e-9f32 as f64) / 32768.0;
    for ((i, j), &p) in phase.indexed_iter() {
        if s.grid.is_valid(i, j) {
            let want = p as f64 * k;
            assert!((s.grid.values()[[i, j]] - want).abs() <= 1e-12 * want.abs().max(1e-9), "({i}, {j})");
        }
    }
    // The same counts at normal resolution (R = 4096) are 8 times higher.
    let normal = decode(
        "n.dat",
        &zygo::encode(&MetroProFields { phase_res: 0, ..f.clone() }, &phase),
        &ScanOptions::default(),
    )
    .unwrap();
    let (a, b) = (s.grid.values()[[5, 5]], normal.grid.values()[[5, 5]]);
    assert!((b / a - 8.0).abs() < 1e-12, "{a} {b}");
    // Format 3 (4096-byte header) with R = 131072 and inverted data.
    let f3 = MetroProFields { header_format: 3, phase_res: 2, inverted: true, buckets: 0, ..f.clone() };
    let s3 = decode("f3.dat", &zygo::encode(&f3, &phase), &ScanOptions::default()).unwrap();
    let want = -(phase[[5, 5]] as f64) * 0.5 * (632.8e-9f32 as f64) / 131072.0;
    assert!((s3.grid.values()[[5, 5]] - want).abs() < 1e-12 * want.abs());
    // phase_res 2 outside format 3, and unknown codes, are refused at their offset.
    let e = decode(
        "x.dat",
        &zygo::encode(&MetroProFields { phase_res: 2, ..f.clone() }, &phase),
        &ScanOptions::default(),
    )
    .unwrap_err();
    assert_eq!(common::format_cause(&e).1, Some(218), "{e:?}");
    // No lateral resolution in the file: `pitch` is required.
    let nores = zygo::encode(&MetroProFields { camera_res: 0.0, ..f }, &phase);
    let e = decode("p.dat", &nores, &ScanOptions::default()).unwrap_err();
    assert!(matches!(e, Error::Parameter { ref name, .. } if name == "pitch"), "{e:?}");
    assert!(e.to_string().contains("pass `pitch`"), "{e}");
    let s = decode("p.dat", &nores, &ScanOptions { pitch: Some([1e-6; 2]), ..Default::default() }).unwrap();
    assert_eq!(s.grid.pitch(), [1e-6; 2]);
}

#[test]
fn all_nan_scans_are_refused() {
    let v = Array2::from_elem((4, 5), f64::NAN);
    let e = decode("nan.gsf", &doefab::io::scan::gsf::encode(&v, [1e-6; 2]), &ScanOptions::default())
        .unwrap_err();
    assert!(matches!(e, Error::Data { cause: DataCause::Empty, .. }), "{e:?}");
    assert!(e.to_string().starts_with("nan.gsf: no measured point"), "{e}");
    let e =
        decode("nan.x3p", &doefab::io::scan::x3p::encode(&v, [1e-6; 2]).unwrap(), &ScanOptions::default())
            .unwrap_err();
    assert!(matches!(e, Error::Data { cause: DataCause::Empty, .. }), "{e:?}");
    let t =
        "aISO-1.0\nNumPoints = 2\nNumProfiles = 1\nXscale = 1e-6\nYscale = 1e-6\nZscale = 1\n*\nBAD BAD\n*\n";
    let e = decode("nan.sdf", t.as_bytes(), &ScanOptions::default()).unwrap_err();
    assert!(matches!(e, Error::Data { cause: DataCause::Empty, .. }), "{e:?}");
}

#[test]
fn missing_pitch_or_unit_is_refused_with_the_option_to_pass() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("scan.npy");
    let v = Array2::from_shape_fn((5, 6), |(i, j)| (i + j) as f64 * 10.0);
    doefab::io::npy::write_npy_f64(&p, &v).unwrap();
    let e = read_scan(&p, &ScanOptions::default()).unwrap_err();
    assert!(matches!(e, Error::Parameter { ref name, .. } if name == "pitch"), "{e:?}");
    assert!(e.to_string().contains("carries no pitch: pass `pitch`"), "{e}");
    let o = ScanOptions { pitch: Some([1e-6; 2]), ..Default::default() };
    let e = read_scan(&p, &o).unwrap_err();
    assert!(matches!(e, Error::Parameter { ref name, .. } if name == "z_unit"), "{e:?}");
    assert!(e.to_string().contains("no height unit: pass `z_unit`"), "{e}");
    let o = ScanOptions { pitch: Some([1e-6; 2]), z_unit: Some(1e-9), ..Default::default() };
    let s = read_scan(&p, &o).unwrap();
    assert!((s.grid.values()[[4, 5]] - 90e-9).abs() < 1e-20);
    // A point list states no unit for its columns.
    let e = decode("p.xyz", b"0 0 1\n1 0 2\n0 1 3\n1 1 4\n", &ScanOptions::default()).unwrap_err();
    assert!(matches!(e, Error::Parameter { ref name, .. } if name == "z_unit"), "{e:?}");
    // A GSF without units: the field and heights need the caller's pitch and unit.
    let head = b"Gwyddion Simple Field 1.0\nXRes = 2\nYRes = 1\n";
    let mut g = head.to_vec();
    g.extend(std::iter::repeat_n(0u8, 4 - head.len() % 4));
    g.extend_from_slice(&1.0f32.to_le_bytes());
    g.extend_from_slice(&2.0f32.to_le_bytes());
    let e = decode("u.gsf", &g, &ScanOptions::default()).unwrap_err();
    assert!(matches!(e, Error::Parameter { ref name, .. } if name == "pitch"), "{e:?}");
    let o = ScanOptions { pitch: Some([1e-6; 2]), z_unit: Some(1e-9), ..Default::default() };
    assert!(decode("u.gsf", &g, &o).is_ok());
}

#[test]
fn different_x_and_y_pitches_are_supported() {
    let (gx, gy) = (0.02, 0.01);
    let (px, py) = (1e-6, 3e-6);
    let v = Array2::from_shape_fn((12, 9), |(i, j)| gx * j as f64 * px + gy * i as f64 * py);
    for (name, bytes) in [
        ("a.gsf", doefab::io::scan::gsf::encode(&v, [px, py])),
        ("a.x3p", doefab::io::scan::x3p::encode(&v, [px, py]).unwrap()),
        ("a.sdf", doefab::io::scan::sdf::encode_binary(&v, [px, py])),
    ] {
        let s = decode(name, &bytes, &ScanOptions::default()).unwrap();
        let p = s.grid.pitch();
        assert!((p[0] - px).abs() < 1e-12 && (p[1] - py).abs() < 1e-12, "{name}: {p:?}");
        let sdq = height_params(&s.grid).unwrap().sdq.unwrap();
        let slope = (gx * gx + gy * gy).sqrt();
        assert!((sdq - slope).abs() < 1e-5 * slope, "{name}: Sdq {sdq} vs {slope}");
    }
}

/// A file's own stated unit is trusted: heights written as nanometre numbers into a file whose
/// unit is metres (a 150 m relief) read with a warning naming the unit that would fit, and
/// only a comparison with a design refuses them, naming the figure. A unit the caller states
/// (`z_unit`) is still refused when implausible.
#[test]
fn implausible_heights_of_a_stated_unit_warn_and_compare_refuses() {
    let v = Array2::from_shape_fn((4, 4), |(i, j)| (i * 4 + j) as f64 * 10.0);
    let bytes = doefab::io::scan::x3p::encode(&v, [1e-6; 2]).unwrap();
    let s = decode("nm.x3p", &bytes, &ScanOptions::default()).unwrap();
    assert!(
        s.warnings
            .iter()
            .any(|w| w.contains("implausible") && w.contains("`z_unit` nm?") && w.contains("kept")),
        "{:?}",
        s.warnings
    );
    let e = doefab::io::heightmap::check_relief(Path::new("nm.x3p"), &s.grid).unwrap_err();
    assert!(matches!(e, Error::Data { cause: DataCause::OutOfRange, .. }), "{e:?}");
    let e = e.to_string();
    assert!(e.contains("nm.x3p") && e.contains("150 m") && e.contains("beyond a DOE's relief"), "{e}");
    // Through the command: scan-info reads it, compare refuses it.
    let dir = common::tempdir();
    let path = dir.path().join("nm.x3p");
    std::fs::write(&path, &bytes).unwrap();
    let out = common::doefab(&["scan-info", path.to_str().unwrap()]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    assert!(String::from_utf8_lossy(&out.stderr).contains("implausible"));
    let e = common::fails(&[
        "compare",
        path.to_str().unwrap(),
        "--design",
        "built-in:paper",
        "-o",
        dir.path().join("c").to_str().unwrap(),
    ]);
    assert!(e.contains("beyond a DOE's relief"), "{e}");
    // A unit the caller states is checked as before.
    let xyz = "0 0 0\n1 0 100\n0 1 200\n1 1 300\n";
    let e = decode("a.xyz", xyz.as_bytes(), &ScanOptions { z_unit: Some(1.0), ..Default::default() })
        .unwrap_err();
    assert!(matches!(e, Error::Parameter { ref name, .. } if name == "z_unit"), "{e:?}");
    assert!(e.to_string().contains("implausible"), "{e}");
}

#[test]
fn x3p_checksum_mismatch_is_a_warning() {
    let v = Array2::from_shape_fn((3, 3), |(i, j)| (i + j) as f64 * 1e-8);
    let good = doefab::io::scan::x3p::encode(&v, [1e-6; 2]).unwrap();
    assert!(decode("g.x3p", &good, &ScanOptions::default()).unwrap().warnings.is_empty());
    // Rebuild the archive with a wrong point-data MD5 in main.xml.
    let mut zip = zip::ZipArchive::new(std::io::Cursor::new(&good)).unwrap();
    let mut out = std::io::Cursor::new(Vec::new());
    {
        use std::io::{Read, Write};
        let mut w = zip::ZipWriter::new(&mut out);
        for k in 0..zip.len() {
            let mut f = zip.by_index(k).unwrap();
            let name = f.name().to_string();
            let mut data = Vec::new();
            f.read_to_end(&mut data).unwrap();
            if name == "main.xml" {
                let t = String::from_utf8(data).unwrap();
                let a = t.find("<MD5ChecksumPointData>").unwrap() + 22;
                data = format!("{}{}{}", &t[..a], "0".repeat(32), &t[a + 32..]).into_bytes();
            }
            w.start_file(name, zip::write::SimpleFileOptions::default()).unwrap();
            w.write_all(&data).unwrap();
        }
        w.finish().unwrap();
    }
    let s = decode("w.x3p", out.get_ref(), &ScanOptions::default()).unwrap();
    assert!(
        s.warnings.iter().any(|w| w.contains("differs from main.xml's MD5ChecksumPointData")),
        "{:?}",
        s.warnings
    );
    assert!(s.warnings.iter().any(|w| w.contains("not the MD5 of main.xml")), "{:?}", s.warnings);
    assert_eq!(s.grid.values()[[2, 2]], 4e-8);
}

#[test]
fn gaussian_random_surface_has_iso_kurtosis_three() {
    let n = 256;
    let sigma = 20e-9;
    let mut rng = doefab::rng::Lcg(42);
    let z: Vec<f64> = (0..n * n).map(|_| rng.normal() * sigma).collect();
    let g = doefab::Grid::new(Array2::from_shape_vec((n, n), z).unwrap(), [1e-6; 2], doefab::Unit::Metre)
        .unwrap();
    let p = height_params(&g).unwrap();
    // Standard errors for N = 65536: Sku sqrt(24/N) = 0.019, Ssk sqrt(6/N) = 0.0096.
    assert!((p.sku - 3.0).abs() < 0.08, "Sku {}", p.sku);
    assert!(p.ssk.abs() < 0.04, "Ssk {}", p.ssk);
    assert!((p.sq / sigma - 1.0).abs() < 0.02, "Sq {}", p.sq);
    // Sa = sigma sqrt(2 / pi) for a Gaussian.
    assert!((p.sa / (sigma * (2.0 / std::f64::consts::PI).sqrt()) - 1.0).abs() < 0.02, "Sa {}", p.sa);
}

/// Alicona `.al3d` and TrueMap `.tmd`: cut at every byte of the header and a spread beyond (an
/// error naming the file and the byte offset, never a panic), flipped bytes (no panic), and a
/// file of another format under each extension (refused naming what was expected).
#[test]
fn al3d_and_tmd_cuts_corruption_and_other_formats() {
    // (file, header length, bytes the reader needs: the padding after the last image row,
    // 4 bytes for 41 f32 columns and 3 for 13 texture bytes, may be absent)
    for (name, header, pad) in [
        ("wave_pedestal.surfalize.al3d", 845, 4),
        ("quality_map.layout.al3d", 17 + 52 * 15 + 256, 3),
        ("wave_pedestal.surfalize.tmd", 32 + 24 + 24, 0),
    ] {
        let bytes = std::fs::read(local(name)).unwrap();
        let short = format!("cut-{name}");
        check_cuts_below(&short, &bytes, header + 8, bytes.len() - pad, true);
        if pad > 0 {
            assert!(decode(&short, &bytes[..bytes.len() - pad], &ScanOptions::default()).is_ok(), "{name}");
        }
        check_corruption(&short, &bytes);
    }
    let al3d = std::fs::read(local("wave_pedestal.surfalize.al3d")).unwrap();
    let tmd = std::fs::read(local("wave_pedestal.surfalize.tmd")).unwrap();
    let x3p = std::fs::read(local("s1_tilt_pedestal.x3pio.x3p")).unwrap();
    let err = |name: &str, b: &[u8]| {
        let e = decode(name, b, &ScanOptions::default()).unwrap_err();
        let (cause, _, path) = common::format_cause(&e);
        assert!(path == Path::new(name) && cause == FormatCause::Signature, "{e:?}");
        e.to_string()
    };
    for other in [&tmd, &x3p] {
        let e = err("wrong.al3d", other);
        assert!(e.contains("wrong.al3d") && e.contains("not an Alicona AL3D file"), "{e}");
    }
    for other in [&al3d, &x3p] {
        let e = err("wrong.tmd", other);
        assert!(e.contains("wrong.tmd") && e.contains("not a TrueMap file"), "{e}");
    }
}

/// Bruker Nanoscope `.spm` and Sensofar `.plux`: cut at every byte of the header (and a spread
/// beyond), flipped bytes, and a file of another format under each extension; an ISO 28600 text
/// `.spm` is refused naming that format.
#[test]
fn spm_and_plux_cuts_corruption_and_other_formats() {
    // (file, cut at every byte below, bytes the reader needs: the v9 file's Height image is the
    // second of three 29 x 41 x 4-byte images after an 8192-byte header)
    for (name, every, need) in [
        ("wave_pedestal.v9.layout.spm", 8192 + 8, Some(8192 + 2 * 29 * 41 * 4)),
        ("wave_pedestal.v5.layout.spm", 8192 + 8, None),
        ("wave_pedestal.layout.plux", 600, None),
    ] {
        let bytes = std::fs::read(local(name)).unwrap();
        let short = format!("cut-{name}");
        let n = need.unwrap_or(bytes.len());
        check_cuts_below(&short, &bytes, every, n, true);
        assert!(decode(&short, &bytes[..n], &ScanOptions::default()).is_ok(), "{name}");
        check_corruption(&short, &bytes);
    }
    let spm = std::fs::read(local("wave_pedestal.v5.layout.spm")).unwrap();
    let plux = std::fs::read(local("wave_pedestal.layout.plux")).unwrap();
    let x3p = std::fs::read(local("s1_tilt_pedestal.x3pio.x3p")).unwrap();
    let err = |name: &str, b: &[u8]| {
        let e = decode(name, b, &ScanOptions::default()).unwrap_err();
        let (cause, _, path) = common::format_cause(&e);
        assert!(path == Path::new(name) && cause == FormatCause::Signature, "{e:?}");
        e.to_string()
    };
    for other in [&plux, &x3p] {
        let e = err("wrong.spm", other);
        assert!(e.contains("wrong.spm") && e.contains("not a Bruker Nanoscope file"), "{e}");
    }
    for other in [&spm, &x3p] {
        let e = err("wrong.plux", other);
        assert!(e.contains("wrong.plux") && e.contains("not a Sensofar PLUx file"), "{e}");
    }
    let iso = b"ISO/TC 201 SPM data transfer format\r\ngeneral information\r\n";
    let e = err("iso.spm", iso);
    assert!(e.contains("iso.spm") && e.contains("ISO 28600") && e.contains(".x3p"), "{e}");
}

/// Zygo `.datx`: cut at every byte of the first 600 and a spread beyond (an error naming the file
/// and where it ends, never a panic), flipped bytes (no panic), an HDF5 file without a surface
/// and a file of another format (refused naming what was expected).
#[test]
fn datx_cuts_corruption_and_other_formats() {
    for name in ["wave_pedestal.h5py.datx", "wave_pedestal_fringes.h5py.datx"] {
        let bytes = std::fs::read(local(name)).unwrap();
        let short = format!("cut-{name}");
        check_cuts(&short, &bytes, true);
        check_corruption(&short, &bytes);
    }
    let err = |name: &str, b: &[u8]| {
        let e = decode(name, b, &ScanOptions::default()).unwrap_err();
        let (cause, _, path) = common::format_cause(&e);
        assert!(path == Path::new(name) && cause == FormatCause::Signature, "{e:?}");
        e.to_string()
    };
    let x3p = std::fs::read(local("s1_tilt_pedestal.x3pio.x3p")).unwrap();
    let e = err("wrong.datx", &x3p);
    assert!(e.contains("wrong.datx") && e.contains("not a Zygo .datx file: no HDF5 signature"), "{e}");
}

/// Wyko `.opd` built from the layouts (a later Vision directory with type-15 entries and a
/// 40-byte `ImageModificat~0` before the heights; f32 heights): cut at every byte of the first
/// 600 and a spread beyond, and 36 bytes short, where Gwyddion's count for that entry ends (an
/// error naming the file and the byte offset, never a panic); flipped bytes (no panic).
#[test]
fn opd_cuts_and_corruption() {
    for name in ["wave_pedestal.raw.layout.opd", "wave_pedestal.opd_f32.layout.opd"] {
        let bytes = std::fs::read(local(name)).unwrap();
        let short = format!("cut-{name}");
        check_cuts(&short, &bytes, true);
        check_corruption(&short, &bytes);
        let e = decode(&short, &bytes[..bytes.len() - 36], &ScanOptions::default()).unwrap_err();
        let (_, offset, path) = common::format_cause(&e);
        assert!(offset.is_some() && path == Path::new(&short), "{e:?}");
    }
}

/// Bruker Vision64 `.opdx`: cut at every byte of the first 600 and a spread beyond (an error
/// naming the file and the byte offset, never a panic), flipped bytes (no panic), and files of
/// other formats (refused naming what was expected).
#[test]
fn opdx_cuts_corruption_and_other_formats() {
    let bytes = std::fs::read(local("wave_pedestal.layout.opdx")).unwrap();
    check_cuts("cut.opdx", &bytes, true);
    check_corruption("cut.opdx", &bytes);
    let err = |name: &str, b: &[u8]| {
        let e = decode(name, b, &ScanOptions::default()).unwrap_err();
        let (cause, _, path) = common::format_cause(&e);
        assert!(path == Path::new(name) && cause == FormatCause::Signature, "{e:?}");
        e.to_string()
    };
    for other in ["s1_tilt_pedestal.x3pio.x3p", "wave_pedestal.h5py.datx"] {
        let e = err("wrong.opdx", &std::fs::read(local(other)).unwrap());
        assert!(e.contains("wrong.opdx") && e.contains("not a Bruker Vision64 .opdx file"), "{e}");
    }
    let e = err("wrong.datx", &bytes);
    assert!(e.contains("not a Zygo .datx file"), "{e}");
}

/// An instrument format that is known but not read is refused by `scan-info` with its name and
/// what to export, not as an unknown extension; an extension nobody uses stays unknown.
#[test]
fn known_unread_instrument_formats_are_refused_by_name() {
    let dir = common::tempdir();
    for (name, says) in
        [("part.mnt", "MountainsMap"), ("part.ols", "Olympus LEXT OLS3000"), ("part.nms", "NanoFocus")]
    {
        let p = dir.path().join(name);
        std::fs::write(&p, b"not read").unwrap();
        let o = common::doefab(&["scan-info", p.to_str().unwrap()]);
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(!o.status.success() && err.contains(says) && err.contains(".x3p"), "{name}: {err}");
        assert!(!err.contains("unknown scan format"), "{err}");
    }
    let p = dir.path().join("part.qqq");
    std::fs::write(&p, b"x").unwrap();
    let o = common::doefab(&["scan-info", p.to_str().unwrap()]);
    assert!(String::from_utf8_lossy(&o.stderr).contains("unknown scan format"));
}

/// Keyence `.vk4` / `.vk6` and FRT `.frt`: cut at every byte of the header and a spread beyond
/// (an error naming the file and the byte offset, never a panic), flipped bytes (no panic), and
/// a file of another format under each extension (refused naming what was expected).
#[test]
fn vk_and_frt_cuts_corruption_and_other_formats() {
    for (name, every) in [
        // Header, offset table and measurement conditions (84 + 336), then the images.
        ("wave_pedestal.layout.vk4", 1200),
        ("wave_pedestal.layout.vk6", 800),
        ("wave_pedestal.layout.frt", 400),
        ("wave_pedestal_multi.layout.frt", 400),
    ] {
        let bytes = std::fs::read(local(name)).unwrap();
        let short = format!("cut-{name}");
        check_cuts_below(&short, &bytes, every, bytes.len(), true);
        check_corruption(&short, &bytes);
    }
    let vk4 = std::fs::read(local("wave_pedestal.layout.vk4")).unwrap();
    let frt = std::fs::read(local("wave_pedestal.layout.frt")).unwrap();
    let tmd = std::fs::read(local("wave_pedestal.surfalize.tmd")).unwrap();
    let x3p = std::fs::read(local("s1_tilt_pedestal.x3pio.x3p")).unwrap();
    let err = |name: &str, b: &[u8]| {
        let e = decode(name, b, &ScanOptions::default()).unwrap_err();
        let (cause, _, path) = common::format_cause(&e);
        assert!(path == Path::new(name) && cause == FormatCause::Signature, "{e:?}");
        e.to_string()
    };
    for other in [&frt, &tmd, &x3p] {
        let e = err("wrong.vk4", other);
        assert!(e.contains("wrong.vk4") && e.contains("not a Keyence VK file"), "{e}");
    }
    let e = err("wrong.vk6", &x3p);
    assert!(e.contains("wrong.vk6") && e.contains("not a Keyence VK file"), "{e}");
    for other in [&vk4, &tmd, &x3p] {
        let e = err("wrong.frt", other);
        assert!(e.contains("wrong.frt") && e.contains("not an FRT MicroProf file"), "{e}");
    }
}

/// Olympus `.lext`: cut at every byte of the first pages' IFDs and a spread beyond (an error
/// naming the file and the byte offset: every page's strips must lie in the file), flipped
/// bytes (no panic), a file of another format or a plain TIFF under the extension, and a LEXT
/// file without a HEIGHT page (each refused naming what was expected).
#[test]
fn lext_cuts_corruption_and_other_formats() {
    for name in ["wave_pedestal.tifffile.lext", "wave_pedestal_be.tifffile.lext"] {
        let bytes = std::fs::read(local(name)).unwrap();
        let short = format!("cut-{name}");
        check_cuts_below(&short, &bytes, 1500, bytes.len(), true);
        check_corruption(&short, &bytes);
    }
    let lext = std::fs::read(local("wave_pedestal.tifffile.lext")).unwrap();
    let tmd = std::fs::read(local("wave_pedestal.surfalize.tmd")).unwrap();
    let x3p = std::fs::read(local("s1_tilt_pedestal.x3pio.x3p")).unwrap();
    let tiff = std::fs::read(local("s1_tilt_pedestal.grey16.tiff")).unwrap();
    let err = |name: &str, b: &[u8]| {
        let e = decode(name, b, &ScanOptions::default()).unwrap_err();
        let (cause, _, path) = common::format_cause(&e);
        assert!(path == Path::new(name) && cause == FormatCause::Signature, "{e:?}");
        e.to_string()
    };
    for other in [&tmd, &x3p] {
        let e = err("wrong.lext", other);
        assert!(e.contains("wrong.lext") && e.contains("not an Olympus LEXT file"), "{e}");
    }
    let e = err("plain.lext", &tiff);
    assert!(e.contains("plain.lext") && e.contains("no <TiffTagDescData>"), "{e}");
    let at = lext.windows(7).position(|w| w == b"HEIGHT\0").unwrap();
    let mut no_height = lext.clone();
    no_height[at..at + 6].copy_from_slice(b"HEIGHX");
    let e = decode("flat.lext", &no_height, &ScanOptions::default()).unwrap_err();
    assert_eq!(common::format_cause(&e), (FormatCause::Malformed, Some(8), Path::new("flat.lext")), "{e}");
    assert!(e.to_string().contains("no page titled HEIGHT"), "{e}");
}
