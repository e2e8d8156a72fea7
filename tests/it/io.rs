//! Height-map readers and writers against files written by independent programs (numpy,
//! hand-rolled Python writers for PNG, TIFF and OpenEXR, Gwyddion), round trips of every
//! format, and bad input: cut files, wrong magic, wrong shapes, missing pitch or unit,
//! implausible units, ragged text.

use crate::common;

use std::path::{Path, PathBuf};

use doefab::io::heightmap::{read_heightmap, read_raw, ReadOptions};

use doefab::io::raw_map::{Metadata, SampleKind};
use doefab::io::{csv, exr, npy, png, tiff};
use doefab::{Error, FormatCause};
use ndarray::{Array2, Array4};

const H: usize = 5;
const W: usize = 7;

/// The fixture formula, evaluated with the same floating-point operations as in the Python
/// scripts below so that values compare exactly.
fn f(i: usize, j: usize) -> f64 {
    (((i * 7 + j * 3) % 11) as f64 - 5.0) * 1.25e-7 + i as f64 * 1e-9
}

fn expected() -> Array2<f64> {
    Array2::from_shape_fn((H, W), |(i, j)| f(i, j))
}

const PY_FORMULA: &str = r#"
import sys, os, struct, zlib
import numpy as np
H, W = 5, 7
def f(i, j):
    return ((i * 7 + j * 3) % 11 - 5) * 1.25e-7 + i * 1e-9
a = np.array([[f(i, j) for j in range(W)] for i in range(H)], dtype=np.float64)
d = sys.argv[1]
"#;

fn opts(pitch: f64, unit: f64) -> ReadOptions {
    ReadOptions { pitch: Some([pitch, pitch]), unit: Some(unit), ..Default::default() }
}

fn err(r: doefab::Result<doefab::Grid>) -> Error {
    match r {
        Ok(g) => panic!("expected an error, got a {:?} grid", g.dim()),
        Err(e) => e,
    }
}

/// The name of the parameter `e` refuses; panics naming any other error.
fn refused(e: &Error) -> &str {
    match e {
        Error::Parameter { name, .. } => name,
        other => panic!("expected a refused parameter, got {other:?}"),
    }
}

// ---------------------------------------------------------------------------------------------
// NPY

#[test]
fn npy_files_written_by_numpy_read_exactly() {
    let dir = common::tempdir();
    let d = dir.path();
    let script = format!(
        "{PY_FORMULA}
np.save(os.path.join(d, 'c_f64.npy'), a)
np.save(os.path.join(d, 'f_f64.npy'), np.asfortranarray(a))
np.save(os.path.join(d, 'c_f32.npy'), a.astype(np.float32))
np.save(os.path.join(d, 'f_f32.npy'), np.asfortranarray(a.astype(np.float32)))
np.save(os.path.join(d, 'be_f64.npy'), a.astype('>f8'))
np.save(os.path.join(d, 'be_f32.npy'), np.asfortranarray(a.astype('>f4')))
np.save(os.path.join(d, 'hw1.npy'), a[:, :, None])
np.save(os.path.join(d, 'u2.npy'), (np.arange(H * W).reshape(H, W) * 997 % 65536).astype('<u2'))
np.save(os.path.join(d, 'u1.npy'), (np.arange(H * W).reshape(H, W) % 16).astype(np.uint8))
np.save(os.path.join(d, 'i2.npy'), (np.arange(H * W).reshape(H, W) - 17).astype('<i2'))
np.save(os.path.join(d, 'cube.npy'), np.zeros((2, 3, 4)))
with open(os.path.join(d, 'v2.npy'), 'wb') as fh:
    np.lib.format.write_array(fh, a, version=(2, 0))
with open(os.path.join(d, 'v3.npy'), 'wb') as fh:
    np.lib.format.write_array(fh, np.asfortranarray(a), version=(3, 0))
n = a.copy(); n[1, 2] = np.nan; n[3, 4] = np.inf
np.save(os.path.join(d, 'nan.npy'), n)
print(np.load(os.path.join(d, 'be_f32.npy')).dtype.str, np.load(os.path.join(d, 'f_f64.npy')).flags['F_CONTIGUOUS'])
"
    );
    let out = common::run_python(&script, &[d.to_str().unwrap()]);
    assert_eq!(out.trim(), ">f4 True", "the fixtures are what they claim to be");
    let want = expected();
    let want32 = want.mapv(|v| v as f32 as f64);
    for (name, w) in [
        ("c_f64", &want),
        ("f_f64", &want),
        ("be_f64", &want),
        ("v2", &want),
        ("v3", &want),
        ("hw1", &want),
        ("c_f32", &want32),
        ("f_f32", &want32),
        ("be_f32", &want32),
    ] {
        let got = npy::read_npy_2d(&d.join(format!("{name}.npy"))).unwrap();
        assert_eq!(&got, w, "{name}");
    }
    let u2 = npy::read_npy_2d(&d.join("u2.npy")).unwrap();
    assert_eq!(u2, Array2::from_shape_fn((H, W), |(i, j)| ((i * W + j) * 997 % 65536) as f64));
    let u1 = npy::read_npy_2d(&d.join("u1.npy")).unwrap();
    assert_eq!(u1, Array2::from_shape_fn((H, W), |(i, j)| ((i * W + j) % 16) as f64));
    let i2 = npy::read_npy_2d(&d.join("i2.npy")).unwrap();
    assert_eq!(i2, Array2::from_shape_fn((H, W), |(i, j)| (i * W + j) as f64 - 17.0));

    // A 3-D array is refused with its shape named.
    let e = npy::read_npy_2d(&d.join("cube.npy")).unwrap_err();
    assert_eq!(common::format_cause(&e), (FormatCause::Unsupported, None, d.join("cube.npy").as_path()));
    assert!(e.to_string().contains("(2, 3, 4)"), "{e}");

    // Through the entry point: NPY carries neither pitch nor unit.
    let p = d.join("c_f64.npy");
    let e = err(read_heightmap(&p, &ReadOptions::default()));
    assert_eq!(refused(&e), "pitch", "{e}");
    let e = err(read_heightmap(&p, &ReadOptions { pitch: Some([1e-6; 2]), ..Default::default() }));
    assert_eq!(refused(&e), "unit", "{e}");
    let g = read_heightmap(&p, &opts(4.29e-6, 1.0)).unwrap();
    assert_eq!(g.values(), &want);
    assert_eq!(g.pitch(), [4.29e-6, 4.29e-6]);
    assert_eq!(g.unit(), doefab::Unit::Metre);

    // NaN and inf stay in the map as invalid samples.
    let g = read_heightmap(&d.join("nan.npy"), &opts(1e-6, 1.0)).unwrap();
    assert_eq!(g.valid_count(), H * W - 2);
    assert!(!g.is_valid(1, 2) && !g.is_valid(3, 4) && g.is_valid(0, 0));

    // Values ~1e-7 stated in um are ~1e-13 m: refused, metres suggested.
    let e = err(read_heightmap(&p, &opts(1e-6, 1e-6)));
    assert_eq!(refused(&e), "unit", "{e}");
    assert!(e.to_string().contains("the values look like metres already: did you mean `unit` m?"), "{e}");
    // A level map in nm is plausible.
    let g = read_heightmap(&d.join("u1.npy"), &opts(1e-6, 100e-9)).unwrap();
    assert!((g.values()[[H - 1, W - 1]] - ((H * W - 1) % 16) as f64 * 100e-9).abs() < 1e-20);
}

#[test]
fn npy_written_here_is_byte_identical_to_numpy_and_loads_there() {
    let dir = common::tempdir();
    let d = dir.path();
    let a = expected();
    npy::write_npy_f64(&d.join("ours_f64.npy"), &a).unwrap();
    npy::write_npy_f32(&d.join("ours_f32.npy"), &a.mapv(|v| v as f32)).unwrap();
    let psf = Array4::from_shape_fn((4, 6, 1, 3), |(i, j, _, c)| (i * 100 + j * 10 + c) as f32 * 0.5);
    npy::write_npy_f32_4d(&d.join("ours_psf.npy"), &psf).unwrap();
    let script = format!(
        "{PY_FORMULA}
np.save(os.path.join(d, 'np_f64.npy'), a)
np.save(os.path.join(d, 'np_f32.npy'), a.astype(np.float32))
psf = np.array([[[[(i * 100 + j * 10 + c) * 0.5 for c in range(3)]] for j in range(6)] for i in range(4)], dtype=np.float32)
np.save(os.path.join(d, 'np_psf.npy'), psf)
assert np.array_equal(np.load(os.path.join(d, 'ours_f64.npy')), a)
assert np.array_equal(np.load(os.path.join(d, 'ours_f32.npy')), a.astype(np.float32))
p = np.load(os.path.join(d, 'ours_psf.npy'))
assert p.shape == (4, 6, 1, 3) and p.dtype == np.float32 and np.array_equal(p, psf)
print('ok')
"
    );
    assert_eq!(common::run_python(&script, &[d.to_str().unwrap()]).trim(), "ok");
    for (ours, theirs) in [("ours_f64", "np_f64"), ("ours_f32", "np_f32"), ("ours_psf", "np_psf")] {
        let x = std::fs::read(d.join(format!("{ours}.npy"))).unwrap();
        let y = std::fs::read(d.join(format!("{theirs}.npy"))).unwrap();
        assert_eq!(x, y, "{ours} differs from numpy.save's bytes");
    }
}

// ---------------------------------------------------------------------------------------------
// OpenEXR

/// An uncompressed scan-line OpenEXR writer in plain Python (independent of the `exr` crate).
const PY_EXR: &str = r#"
def attr(name, typ, payload):
    return name.encode() + b'\0' + typ.encode() + b'\0' + struct.pack('<i', len(payload)) + payload
def exr(path, channels, extra):
    # channels: list of (name, pixel_type, 2-D array); pixel_type 1 = half, 2 = float
    channels = sorted(channels, key=lambda c: c[0])
    h, w = channels[0][2].shape
    chl = b''.join(n.encode() + b'\0' + struct.pack('<iB3xii', t, 0, 1, 1) for n, t, _ in channels) + b'\0'
    hdr = attr('channels', 'chlist', chl)
    hdr += attr('compression', 'compression', b'\0')
    hdr += attr('dataWindow', 'box2i', struct.pack('<4i', 0, 0, w - 1, h - 1))
    hdr += attr('displayWindow', 'box2i', struct.pack('<4i', 0, 0, w - 1, h - 1))
    hdr += attr('lineOrder', 'lineOrder', b'\0')
    hdr += attr('pixelAspectRatio', 'float', struct.pack('<f', 1.0))
    hdr += attr('screenWindowCenter', 'v2f', struct.pack('<2f', 0.0, 0.0))
    hdr += attr('screenWindowWidth', 'float', struct.pack('<f', 1.0))
    for name, typ, payload in extra:
        hdr += attr(name, typ, payload)
    head = b'\x76\x2f\x31\x01' + struct.pack('<i', 2) + hdr + b'\0'
    lines = []
    for y in range(h):
        data = b''
        for n, t, arr in channels:
            data += arr[y].astype('<f2' if t == 1 else '<f4').tobytes()
        lines.append(struct.pack('<ii', y, len(data)) + data)
    pos = len(head) + 8 * h
    table = b''
    for l in lines:
        table += struct.pack('<Q', pos)
        pos += len(l)
    open(path, 'wb').write(head + table + b''.join(lines))
"#;

#[test]
fn exr_written_by_an_independent_writer_reads_with_its_attributes() {
    let dir = common::tempdir();
    let d = dir.path();
    let script = format!(
        "{PY_FORMULA}{PY_EXR}
s = a * 1e6  # micrometres
exr(os.path.join(d, 'f32.exr'), [('Z', 2, s)],
    [('pitch_x', 'double', struct.pack('<d', 4.29e-6)), ('pitch_y', 'double', struct.pack('<d', 2.5e-6)),
     ('unit', 'string', b'um'), ('comment', 'string', b'from python')])
exr(os.path.join(d, 'f16.exr'), [('height', 1, s)], [('pitch', 'float', struct.pack('<f', 1e-6))])
exr(os.path.join(d, 'bare.exr'), [('Y', 2, s)], [])
exr(os.path.join(d, 'two.exr'), [('Z', 2, s), ('mask', 2, s * 0 + 1)], [])
print('ok')
"
    );
    assert_eq!(common::run_python(&script, &[d.to_str().unwrap()]).trim(), "ok");
    let s = expected().mapv(|v| v * 1e6);
    let s32 = s.mapv(|v| v as f32 as f64);

    let r = exr::read_exr(&d.join("f32.exr"), None).unwrap();
    assert_eq!(r.values, s32);
    assert_eq!(r.pitch, Some([4.29e-6, 2.5e-6]));
    assert_eq!(r.unit, Some(1e-6));
    assert!(r.metadata.contains(&("comment".into(), "from python".into())));
    let g = read_heightmap(&d.join("f32.exr"), &ReadOptions::default()).unwrap();
    assert_eq!(g.pitch(), [4.29e-6, 2.5e-6]);
    for (x, y) in g.values().iter().zip(s32.iter()) {
        assert!((x - y * 1e-6).abs() <= 1e-12 * y.abs().max(1.0) * 1e-6);
    }
    // Options that agree are accepted; a different one is refused with both values.
    assert!(
        read_heightmap(&d.join("f32.exr"), &ReadOptions { unit: Some(1e-6), ..Default::default() }).is_ok()
    );
    let e = err(read_heightmap(
        &d.join("f32.exr"),
        &ReadOptions { pitch: Some([1e-6; 2]), ..Default::default() },
    ));
    assert_eq!(refused(&e), "pitch", "{e}");
    let e = e.to_string();
    assert!(e.contains("4.29 um x 2.5 um") && e.contains("1 um x 1 um"), "{e}");

    // Half floats, a single f32 `pitch` attribute, no unit.
    let r = exr::read_exr(&d.join("f16.exr"), None).unwrap();
    let s16 = s.mapv(|v| ::exr::prelude::f16::from_f64(v).to_f64());
    assert_eq!(r.values, s16);
    assert_eq!(r.pitch, Some([1e-6f32 as f64; 2]));
    assert_eq!(r.unit, None);
    let e = err(read_heightmap(&d.join("f16.exr"), &ReadOptions::default()));
    assert_eq!(refused(&e), "unit", "{e}");

    // No attributes: pitch None, so the caller must give `pitch`.
    let r = exr::read_exr(&d.join("bare.exr"), None).unwrap();
    assert_eq!((r.pitch, r.unit), (None, None));
    let e = err(read_heightmap(&d.join("bare.exr"), &ReadOptions::default()));
    assert_eq!(refused(&e), "pitch", "{e}");

    // Two channels need a choice.
    let e = err(read_heightmap(&d.join("two.exr"), &opts(1e-6, 1e-6)));
    assert_eq!(refused(&e), "channel", "{e}");
    assert!(e.to_string().contains("2 channels (Z, mask)"), "{e}");
    let o = ReadOptions { channel: Some("Z".into()), ..opts(1e-6, 1e-6) };
    assert_eq!(read_heightmap(&d.join("two.exr"), &o).unwrap().dim(), (H, W));
}

#[test]
fn exr_round_trip_and_deterministic_bytes() {
    let dir = common::tempdir();
    let d = dir.path();
    let a = expected().mapv(|v| v as f32);
    let meta = Metadata::heights([4.29e-6, 4.29e-6]).with("source", "unit test").with("levels", "8");
    let p1 = d.join("a.exr");
    let p2 = d.join("b.exr");
    exr::write_exr(&p1, &[("Z", &a)], &meta).unwrap();
    exr::write_exr(&p2, &[("Z", &a)], &meta).unwrap();
    assert_eq!(std::fs::read(&p1).unwrap(), std::fs::read(&p2).unwrap());
    let g = read_heightmap(&p1, &ReadOptions::default()).unwrap();
    assert_eq!(g.values(), &a.mapv(|v| v as f64));
    assert_eq!(g.pitch(), [4.29e-6, 4.29e-6]);
    // The same map without pitch metadata must be given a pitch.
    exr::write_exr(&p2, &[("Z", &a)], &Metadata { unit: Some("m".into()), ..Default::default() }).unwrap();
    assert_eq!(exr::read_exr(&p2, None).unwrap().pitch, None);
    assert_eq!(refused(&err(read_heightmap(&p2, &ReadOptions::default()))), "pitch");
}

// ---------------------------------------------------------------------------------------------
// TIFF

/// A baseline TIFF writer in plain Python: one uncompressed strip, either byte order.
const PY_TIFF: &str = r#"
def tiff(path, arr, bits, fmt, order):
    e = '<' if order == 'II' else '>'
    h, w = arr.shape
    data = arr.astype(e + {(32, 3): 'f4', (16, 1): 'u2', (8, 1): 'u1', (64, 3): 'f8'}[(bits, fmt)]).tobytes()
    tags = [(256, 4, w), (257, 4, h), (258, 3, bits), (259, 3, 1), (262, 3, 1), (273, 4, 0),
            (277, 3, 1), (278, 4, h), (279, 4, len(data)), (339, 3, fmt)]
    n = len(tags)
    data_at = 8 + 2 + 12 * n + 4
    ifd = struct.pack(e + 'H', n)
    for tag, typ, val in tags:
        if tag == 273:
            val = data_at
        if typ == 3:
            ifd += struct.pack(e + 'HHIH2x', tag, typ, 1, val)
        else:
            ifd += struct.pack(e + 'HHII', tag, typ, 1, val)
    ifd += struct.pack(e + 'I', 0)
    head = order.encode() + struct.pack(e + 'HI', 42, 8)
    open(path, 'wb').write(head + ifd + data)
"#;

#[test]
fn tiff_written_by_an_independent_writer_reads_exactly() {
    let dir = common::tempdir();
    let d = dir.path();
    let script = format!(
        "{PY_FORMULA}{PY_TIFF}
tiff(os.path.join(d, 'le.tif'), a, 32, 3, 'II')
tiff(os.path.join(d, 'be.tif'), a, 32, 3, 'MM')
tiff(os.path.join(d, 'f64.tif'), a, 64, 3, 'MM')
c = (np.arange(H * W).reshape(H, W) * 1877) % 65536
tiff(os.path.join(d, 'c16.tif'), c, 16, 1, 'MM')
tiff(os.path.join(d, 'c8.tif'), c % 256, 8, 1, 'II')
print('ok')
"
    );
    assert_eq!(common::run_python(&script, &[d.to_str().unwrap()]).trim(), "ok");
    let want32 = expected().mapv(|v| v as f32 as f64);
    for name in ["le.tif", "be.tif"] {
        let r = tiff::read_tiff(&d.join(name)).unwrap();
        assert_eq!(r.kind, SampleKind::Float);
        assert_eq!(r.values, want32, "{name}");
        assert_eq!((r.pitch, r.unit), (None, None));
    }
    assert_eq!(tiff::read_tiff(&d.join("f64.tif")).unwrap().values, expected());
    let g = read_heightmap(&d.join("be.tif"), &opts(2e-6, 1.0)).unwrap();
    assert_eq!(g.values(), &want32);
    let e = err(read_heightmap(&d.join("le.tif"), &ReadOptions::default()));
    assert_eq!(refused(&e), "pitch", "{e}");

    // 8/16-bit counts are refused without an explicit scale, read with one.
    let counts = Array2::from_shape_fn((H, W), |(i, j)| ((i * W + j) * 1877 % 65536) as f64);
    let r = tiff::read_tiff(&d.join("c16.tif")).unwrap();
    assert_eq!((r.kind, &r.values), (SampleKind::Counts { bits: 16 }, &counts));
    let e = err(read_heightmap(
        &d.join("c16.tif"),
        &ReadOptions { pitch: Some([1e-6; 2]), ..Default::default() },
    ));
    assert_eq!(refused(&e), "z_scale", "{e}");
    let e = err(read_heightmap(&d.join("c16.tif"), &opts(1e-6, 1e-9)));
    assert_eq!(refused(&e), "unit", "{e}");
    let o = ReadOptions {
        pitch: Some([1e-6; 2]),
        z_scale: Some(1e-11),
        z_offset: Some(-2e-7),
        ..Default::default()
    };
    let g = read_heightmap(&d.join("c16.tif"), &o).unwrap();
    assert_eq!(g.values(), &counts.mapv(|c| c * 1e-11 - 2e-7));
    let r = tiff::read_tiff(&d.join("c8.tif")).unwrap();
    assert_eq!((r.kind, &r.values), (SampleKind::Counts { bits: 8 }, &counts.mapv(|c| c % 256.0)));
}

#[test]
fn tiff_round_trips_and_loads_in_python() {
    let dir = common::tempdir();
    let d = dir.path();
    let a = expected().mapv(|v| v as f32);
    let p = d.join("h.tif");
    tiff::write_tiff_f32(&p, &a, &Metadata::heights([3e-6, 3e-6]).with("design", "t")).unwrap();
    let g = read_heightmap(&p, &ReadOptions::default()).unwrap();
    assert_eq!(g.values(), &a.mapv(f64::from));
    assert_eq!(g.pitch(), [3e-6, 3e-6]);
    let m16 = Array2::from_shape_fn((H, W), |(i, j)| (i * 10000 + j * 3) as u16);
    tiff::write_tiff_u16(&d.join("m16.tif"), &m16, &Metadata::default()).unwrap();
    let m8 = Array2::from_shape_fn((H, W), |(i, j)| (i * 50 + j) as u8);
    tiff::write_tiff_u8(&d.join("m8.tif"), &m8, &Metadata::default()).unwrap();
    let o = ReadOptions { pitch: Some([1e-6; 2]), z_scale: Some(1e-10), ..Default::default() };
    assert_eq!(read_heightmap(&d.join("m16.tif"), &o).unwrap().values(), &m16.mapv(|v| v as f64 * 1e-10));
    let o = ReadOptions { z_scale: Some(1e-8), ..o };
    assert_eq!(read_heightmap(&d.join("m8.tif"), &o).unwrap().values(), &m8.mapv(|v| v as f64 * 1e-8));
    tiff::write_tiff_f32(&d.join("h2.tif"), &a, &Metadata::heights([3e-6, 3e-6]).with("design", "t"))
        .unwrap();
    assert_eq!(std::fs::read(&p).unwrap(), std::fs::read(d.join("h2.tif")).unwrap());
}

// ---------------------------------------------------------------------------------------------
// PNG

/// A 16-bit grayscale PNG writer in plain Python (zlib + struct).
const PY_PNG: &str = r#"
def chunk(t, data):
    return struct.pack('>I', len(data)) + t + data + struct.pack('>I', zlib.crc32(t + data) & 0xffffffff)
def png16(path, counts, texts):
    h, w = counts.shape
    raw = b''.join(b'\0' + counts[y].astype('>u2').tobytes() for y in range(h))
    out = b'\x89PNG\r\n\x1a\n' + chunk(b'IHDR', struct.pack('>IIBBBBB', w, h, 16, 0, 0, 0, 0))
    for k, v in texts:
        out += chunk(b'tEXt', k.encode('latin-1') + b'\0' + v.encode('latin-1'))
    out += chunk(b'IDAT', zlib.compress(raw, 9)) + chunk(b'IEND', b'')
    open(path, 'wb').write(out)
"#;

#[test]
fn png_written_by_an_independent_writer_needs_an_explicit_scale() {
    let dir = common::tempdir();
    let d = dir.path();
    let script = format!(
        "{PY_FORMULA}{PY_PNG}
c = (np.arange(H * W).reshape(H, W) * 1877) % 65536
png16(os.path.join(d, 'c.png'), c, [('pitch_x', '2e-6'), ('pitch_y', '3 um'), ('Title', 'py')])
png16(os.path.join(d, 'bare.png'), c, [])
print('ok')
"
    );
    assert_eq!(common::run_python(&script, &[d.to_str().unwrap()]).trim(), "ok");
    let counts = Array2::from_shape_fn((H, W), |(i, j)| ((i * W + j) * 1877 % 65536) as f64);
    let r = png::read_png(&d.join("c.png")).unwrap();
    assert_eq!(r.kind, SampleKind::Counts { bits: 16 });
    assert_eq!(r.values, counts);
    assert_eq!(r.pitch, Some([2e-6, 3e-6]));
    let e = err(read_heightmap(&d.join("c.png"), &ReadOptions::default()));
    assert_eq!(refused(&e), "z_scale", "{e}");
    let o = ReadOptions { z_scale: Some(2e-11), z_offset: Some(1e-7), ..Default::default() };
    let g = read_heightmap(&d.join("c.png"), &o).unwrap();
    assert_eq!(g.values(), &counts.mapv(|c| c * 2e-11 + 1e-7));
    assert_eq!(g.pitch(), [2e-6, 3e-6]);
    let e = err(read_heightmap(&d.join("bare.png"), &o));
    assert_eq!(refused(&e), "pitch", "{e}");
    // A scale given in nm by mistake: 0.5 "m" per count is implausible, suggestion in nm or um.
    let o = ReadOptions { z_scale: Some(0.5), pitch: Some([1e-6; 2]), ..Default::default() };
    let e = err(read_heightmap(&d.join("bare.png"), &o));
    assert_eq!(refused(&e), "z_scale", "{e}");
    assert!(e.to_string().contains("per count, pass `z_scale`"), "{e}");
}

#[test]
fn png_round_trips_with_text_chunks_and_deterministic_bytes() {
    let dir = common::tempdir();
    let d = dir.path();
    let m16 = Array2::from_shape_fn((H, W), |(i, j)| (i * 13000 + j * 7) as u16);
    let meta = Metadata::heights([4.29e-6, 4.29e-6]).with("z_scale", "1e-10").with("levels", "16");
    png::write_png_u16(&d.join("a.png"), &m16, &meta).unwrap();
    png::write_png_u16(&d.join("b.png"), &m16, &meta).unwrap();
    assert_eq!(std::fs::read(d.join("a.png")).unwrap(), std::fs::read(d.join("b.png")).unwrap());
    let r = png::read_png(&d.join("a.png")).unwrap();
    assert_eq!(r.values, m16.mapv(f64::from));
    assert!(r.metadata.contains(&("levels".into(), "16".into())));
    let e = err(read_heightmap(&d.join("a.png"), &ReadOptions::default()));
    assert_eq!(refused(&e), "z_scale", "{e}");
    assert!(e.to_string().contains("its text says z_scale = 1e-10"), "{e}");
    let g = read_heightmap(&d.join("a.png"), &ReadOptions { z_scale: Some(1e-10), ..Default::default() })
        .unwrap();
    assert_eq!(g.pitch(), [4.29e-6, 4.29e-6]);
    let m8 = Array2::from_shape_fn((H, W), |(i, j)| (i * 50 + j) as u8);
    png::write_png_u8(&d.join("c.png"), &m8, &Metadata::default()).unwrap();
    let r = png::read_png(&d.join("c.png")).unwrap();
    assert_eq!((r.kind, r.values), (SampleKind::Counts { bits: 8 }, m8.mapv(f64::from)));
    // Python's zlib decodes the written file to the same counts (independent decoder).
    let script = r#"
import sys, struct, zlib
b = open(sys.argv[1], 'rb').read()
pos, idat, texts = 8, b'', {}
while pos < len(b):
    n, = struct.unpack('>I', b[pos:pos + 4]); t = b[pos + 4:pos + 8]; data = b[pos + 8:pos + 8 + n]
    assert zlib.crc32(t + data) & 0xffffffff == struct.unpack('>I', b[pos + 8 + n:pos + 12 + n])[0]
    if t == b'IHDR': w, h, depth, ctype = struct.unpack('>IIBB', data[:10])
    if t == b'IDAT': idat += data
    if t == b'tEXt': k, v = data.split(b'\0', 1); texts[k.decode()] = v.decode('latin-1')
    pos += 12 + n
raw = zlib.decompress(idat); stride = 1 + 2 * w; prev = bytearray(2 * w); out = []
for y in range(h):
    f, line = raw[y * stride], bytearray(raw[y * stride + 1:(y + 1) * stride])
    for x in range(2 * w):
        a = line[x - 2] if x >= 2 else 0; up = prev[x]; c = prev[x - 2] if x >= 2 else 0
        if f == 1: line[x] = (line[x] + a) & 255
        elif f == 2: line[x] = (line[x] + up) & 255
        elif f == 3: line[x] = (line[x] + (a + up) // 2) & 255
        elif f == 4:
            p = a + up - c; pa, pb, pc = abs(p - a), abs(p - up), abs(p - c)
            line[x] = (line[x] + (a if pa <= pb and pa <= pc else up if pb <= pc else c)) & 255
    out.append([struct.unpack('>H', bytes(line[2 * x:2 * x + 2]))[0] for x in range(w)]); prev = line
print(depth, ctype, texts['pitch_x'], texts['unit'], sum(sum(r) for r in out), out[4][6])
"#;
    let out = common::run_python(script, &[d.join("a.png").to_str().unwrap()]);
    let sum: u64 = m16.iter().map(|&v| v as u64).sum();
    assert_eq!(out.trim(), format!("16 0 4.29e-6 m {sum} {}", m16[[4, 6]]));
}

// ---------------------------------------------------------------------------------------------
// Text matrices

#[test]
fn csv_round_trip_and_bad_text() {
    let dir = common::tempdir();
    let d = dir.path();
    let a = expected();
    let p = d.join("m.csv");
    csv::write_csv(&p, &a, &Metadata::heights([1e-6, 1e-6]).with("source", "t")).unwrap();
    let g = read_heightmap(&p, &ReadOptions::default()).unwrap();
    assert_eq!(g.values(), &a);
    assert_eq!(g.pitch(), [1e-6, 1e-6]);
    let bare = d.join("bare.txt");
    std::fs::write(&bare, "# heights in nm\n1 2 3\n4 5 6\n").unwrap();
    let e = err(read_heightmap(&bare, &ReadOptions { pitch: Some([1e-6; 2]), ..Default::default() }));
    assert_eq!(refused(&e), "unit", "{e}");
    let g = read_heightmap(&bare, &opts(1e-6, 1e-9)).unwrap();
    assert!((g.values()[[1, 2]] - 6e-9).abs() < 1e-24);
    let ragged = d.join("ragged.csv");
    std::fs::write(&ragged, "1,2,3\n4,5,6\n7,8\n").unwrap();
    let e = err(read_heightmap(&ragged, &opts(1e-6, 1e-9)));
    assert_eq!(common::format_cause(&e), (FormatCause::Malformed, None, ragged.as_path()), "{e}");
    let e = e.to_string();
    assert!(e.contains("line 3 has 2 columns but line 1") && e.contains("has 3"), "{e}");
    let word = d.join("word.asc");
    std::fs::write(&word, "1;2\n3;abc\n").unwrap();
    let e = err(read_heightmap(&word, &opts(1e-6, 1e-9)));
    assert_eq!(common::format_cause(&e), (FormatCause::Malformed, None, word.as_path()), "{e}");
    assert!(e.to_string().contains("line 2, column 2: 'abc' is not a number"), "{e}");
}

// ---------------------------------------------------------------------------------------------
// Bad input: cut files and wrong magic, for every binary format

#[test]
fn cut_files_and_wrong_magic_are_errors_naming_the_file() {
    let dir = common::tempdir();
    let d = dir.path();
    let a = expected();
    let a32 = a.mapv(|v| v as f32);
    let c16 = a.mapv(|v| ((v + 1e-6) * 1e10) as u16);
    let meta = Metadata::heights([1e-6, 1e-6]);
    let full = |name: &str| d.join(name);
    npy::write_npy_f64(&full("ok.npy"), &a).unwrap();
    exr::write_exr(&full("ok.exr"), &[("Z", &a32)], &meta).unwrap();
    tiff::write_tiff_f32(&full("ok.tif"), &a32, &meta).unwrap();
    png::write_png_u16(&full("ok.png"), &c16, &meta).unwrap();
    let o = ReadOptions { pitch: Some([1e-6; 2]), ..Default::default() };
    for name in ["ok.npy", "ok.exr", "ok.tif", "ok.png"] {
        let bytes = std::fs::read(full(name)).unwrap();
        let ext = name.rsplit('.').next().unwrap();
        let n = bytes.len();
        let mut cuts: Vec<usize> =
            vec![0, 1, 4, 8, 12, 40, n / 4, n / 3, n / 2, 2 * n / 3, n - 16, n - 5, n - 1];
        cuts.retain(|&c| c < n);
        for cut in cuts {
            let p = full(&format!("cut{cut}.{ext}"));
            std::fs::write(&p, &bytes[..cut]).unwrap();
            let options = if ext == "png" {
                ReadOptions { z_scale: Some(1e-10), ..o.clone() }
            } else if ext == "npy" {
                ReadOptions { unit: Some(1.0), ..o.clone() }
            } else {
                ReadOptions::default()
            };
            let e = err(read_heightmap(&p, &options));
            assert_eq!(common::format_cause(&e).2, p, "{name} cut at {cut} of {n}: {e}");
        }
        // The uncut file reads.
        let options = match ext {
            "png" => ReadOptions { z_scale: Some(1e-10), ..Default::default() },
            "npy" => ReadOptions { unit: Some(1.0), ..o.clone() },
            _ => ReadOptions::default(),
        };
        read_heightmap(&full(name), &options).unwrap();
        // Wrong magic: the same bytes with the first one changed.
        let mut bad = bytes.clone();
        bad[0] ^= 0x55;
        let p = full(&format!("magic.{ext}"));
        std::fs::write(&p, &bad).unwrap();
        let e = err(read_heightmap(&p, &options));
        assert_eq!(common::format_cause(&e), (FormatCause::Signature, None, p.as_path()), "{e}");
    }
    // A file that does not exist is an I/O error naming it.
    let e = err(read_heightmap(&full("missing.npy"), &ReadOptions::default()));
    assert!(matches!(e, Error::Io { ref path, .. } if *path == full("missing.npy")), "{e:?}");
}

#[test]
fn failed_writes_leave_nothing_on_disk() {
    let dir = common::tempdir();
    let d = dir.path();
    let empty32 = Array2::<f32>::zeros((0, 3));
    let meta = Metadata::default();
    assert!(exr::write_exr(&d.join("a.exr"), &[("Z", &empty32)], &meta).is_err());
    assert!(tiff::write_tiff_f32(&d.join("a.tif"), &empty32, &meta).is_err());
    assert!(png::write_png_u16(&d.join("a.png"), &Array2::zeros((3, 0)), &meta).is_err());
    let reserved = Metadata::default().with("pitch_x", "1");
    assert!(csv::write_csv(&d.join("a.csv"), &Array2::zeros((2, 2)), &reserved).is_err());
    assert!(png::write_png_u8(&d.join("b.png"), &Array2::zeros((2, 2)), &reserved).is_err());
    let left: Vec<_> = std::fs::read_dir(d).unwrap().map(|e| e.unwrap().file_name()).collect();
    assert!(left.is_empty(), "left behind: {left:?}");
}

// ---------------------------------------------------------------------------------------------
// Files written by Gwyddion 2.62 (the shared reference surfaces)

/// The reference file `name`: the copy in `profilometry/`; when the shared data set sits beside
/// the checkout, the copy must be identical to it.
fn reference(name: &str) -> PathBuf {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let local = root.join("profilometry").join(name);
    let shared = root.join("../shared/data/surfaces/gwyddion").join(name);
    if shared.exists() {
        assert_eq!(std::fs::read(&local).unwrap(), std::fs::read(&shared).unwrap(), "{name} copy differs");
    }
    local
}

/// Surface S1 of the shared data set, metres.
fn s1(i: usize, j: usize) -> f64 {
    let mut z = 50e-9 + 2e-9 * j as f64 - 1e-9 * i as f64;
    if (50..150).contains(&i) && (50..150).contains(&j) {
        z += 1.0e-6;
    }
    if (80..120).contains(&i) && (80..120).contains(&j) {
        z += 0.5e-6;
    }
    z
}

#[test]
fn gwyddion_matrix_reproduces_the_surface() {
    let p = reference("s1_tilt_pedestal.matrix.txt");
    // Pitch from the header (Width 200 um over 200 columns), unit from "Value units: m".
    let g = read_heightmap(&p, &ReadOptions::default()).unwrap();
    assert_eq!(g.dim(), (200, 200));
    assert!((g.pitch()[0] - 1e-6).abs() < 1e-15 && (g.pitch()[1] - 1e-6).abs() < 1e-15);
    let mut worst = 0.0f64;
    for ((i, j), &v) in g.values().indexed_iter() {
        let want = s1(i, j);
        // %g keeps 6 significant digits: relative error at most 5e-6.
        assert!((v - want).abs() <= 5e-6 * want.abs() + 1e-15, "({i}, {j}): {v} vs {want}");
        worst = worst.max((v - want).abs());
    }
    assert!(worst > 0.0, "%g rounding should show somewhere");
}

#[test]
fn gwyddion_png_reads_with_an_explicit_scale() {
    let p = reference("s1_tilt_pedestal.grey16.png");
    let r = read_raw(&p, None).unwrap();
    assert_eq!((r.values.dim(), r.kind), ((200, 200), SampleKind::Counts { bits: 16 }));
    // Pitch from Gwy::XReal / Gwy::YReal (200 um over 200 samples).
    let pitch = r.pitch.unwrap();
    assert!((pitch[0] - 1e-6).abs() < 1e-15 && (pitch[1] - 1e-6).abs() < 1e-15);
    // Refused without a scale; the error quotes what Gwyddion's text keys suggest.
    let e = err(read_heightmap(&p, &ReadOptions::default()));
    assert_eq!(refused(&e), "z_scale", "{e}");
    let e = e.to_string();
    assert!(e.contains("ZMin = -1.49") && e.contains("ZMax = 1.708e-6"), "{e}");
    // With the scale the file declares (counts 0..65535 span ZMin..ZMax) the heights reproduce
    // S1 within one count.
    let (zmin, zmax) = (-149e-9, 1708e-9);
    let step = (zmax - zmin) / 65535.0;
    let o = ReadOptions { z_scale: Some(step), z_offset: Some(zmin), ..Default::default() };
    let g = read_heightmap(&p, &o).unwrap();
    assert_eq!(g.min_max(), Some((zmin, zmin + 65535.0 * step)));
    for ((i, j), &v) in g.values().indexed_iter() {
        assert!((v - s1(i, j)).abs() <= step, "({i}, {j}): {v} vs {}", s1(i, j));
    }
    // Gwyddion's quantizer is count = min(floor(65536 (z - ZMin) / (ZMax - ZMin)), 65535): with
    // the bin width range / 65536 and bin centres, the heights are within half a bin.
    let bin = (zmax - zmin) / 65536.0;
    let o = ReadOptions { z_scale: Some(bin), z_offset: Some(zmin + 0.5 * bin), ..Default::default() };
    let g = read_heightmap(&p, &o).unwrap();
    for ((i, j), &v) in g.values().indexed_iter() {
        assert!((v - s1(i, j)).abs() <= 0.5 * bin * (1.0 + 1e-9), "({i}, {j}): {v} vs {}", s1(i, j));
    }
}

#[test]
fn gwyddion_tiff_without_scale_is_refused_and_reads_with_one() {
    let p = reference("s1_tilt_pedestal.grey16.tiff");
    let r = read_raw(&p, None).unwrap();
    assert_eq!(
        (r.values.dim(), r.kind, r.pitch, r.unit),
        ((200, 200), SampleKind::Counts { bits: 16 }, None, None)
    );
    // Never guessed: no scale, no pitch.
    let e = err(read_heightmap(&p, &ReadOptions { pitch: Some([1e-6; 2]), ..Default::default() }));
    assert_eq!(refused(&e), "z_scale", "{e}");
    let e = err(read_heightmap(&p, &ReadOptions { z_scale: Some(1e-11), ..Default::default() }));
    assert_eq!(refused(&e), "pitch", "{e}");
    // The counts are those of the PNG export.
    let png_counts = read_raw(&reference("s1_tilt_pedestal.grey16.png"), None).unwrap().values;
    assert_eq!(r.values, png_counts);
    let (zmin, zmax) = (-149e-9, 1708e-9);
    let step = (zmax - zmin) / 65535.0;
    let o = ReadOptions {
        pitch: Some([1e-6; 2]),
        z_scale: Some(step),
        z_offset: Some(zmin),
        ..Default::default()
    };
    let g = read_heightmap(&p, &o).unwrap();
    for ((i, j), &v) in g.values().indexed_iter() {
        assert!((v - s1(i, j)).abs() <= step, "({i}, {j}): {v} vs {}", s1(i, j));
    }
}

/// A JSON or TOML file that does not parse is a malformed file, at the byte where the parser
/// stopped (serde_json) or at the start of the line it names (toml).
#[test]
fn json_and_toml_files_that_do_not_parse_state_where() {
    let dir = tempfile::tempdir().unwrap();
    // A compare.json cut inside its second line: serde_json stops where the text ends.
    let json = dir.path().join("compare.json");
    let text = "{\n  \"scan\": \"s.x3p\",\n  \"scan_sha256\": \"ab";
    std::fs::write(&json, text).unwrap();
    let e = doefab::pipeline::precompensate::Measured::read(&json).unwrap_err();
    match &e {
        doefab::Error::Format { cause: doefab::FormatCause::Malformed, offset: Some(at), path, .. } => {
            assert!(path == &json && *at == text.len() as u64, "{e:?}")
        }
        other => panic!("expected a malformed JSON file with its offset, got {other:?}"),
    }
    // A byte serde_json cannot take: the offset is that byte's.
    let text = "{\"scan\": x}";
    std::fs::write(&json, text).unwrap();
    let e = doefab::pipeline::precompensate::Measured::read(&json).unwrap_err();
    assert!(matches!(e, doefab::Error::Format { offset: Some(9), .. }) && &text[9..10] == "x", "{e:?}");
    // A system TOML whose second line is not `key = value`: the offset is that line's start.
    let toml = dir.path().join("system.toml");
    let text = "aperture = \"5 mm\"\nfocal_length 35mm\n";
    std::fs::write(&toml, text).unwrap();
    let base = doefab::optics::system::OpticalSystem::default();
    let e = doefab::optics::system::OpticalSystem::read_toml(&toml, &base).unwrap_err();
    match &e {
        doefab::Error::Format { cause: doefab::FormatCause::Malformed, offset: Some(at), .. } => {
            let line2 = text.find('\n').unwrap() as u64 + 1;
            assert!((line2..text.len() as u64).contains(at), "{e:?}")
        }
        other => panic!("expected a malformed TOML file with its offset, got {other:?}"),
    }
}
