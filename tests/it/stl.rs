//! Binary STL checked by an independent reader: trimesh loads each file (merging vertices by
//! position, as any slicer does) and reports whether it is watertight, consistently wound and a
//! positive volume, with its volume, bounds and face count; the header is read byte for byte.
//! Volumes are compared with the analytic value in the file's unit.

use crate::common;

use doefab::rng::Lcg;
use std::path::{Path, PathBuf};

use doefab::fabrication::stl::{
    heightfield_mesh, level_heights, surface_stl, terrace_mesh, write_stl, StlOptions, StlUnit,
    SurfaceChoice, SurfaceKind, CHAMFER_FRACTION,
};
use doefab::{DataCause, Error, Grid, Unit};
use ndarray::Array2;

const CHECK: &str = r#"
import json, sys
import trimesh
for path in sys.argv[1:]:
    with open(path, 'rb') as f:
        header = f.read(80)
    m = trimesh.load(path, force='mesh')
    lo, hi = m.bounds
    print(json.dumps({
        'path': path,
        'header': header.decode('ascii', 'replace'),
        'watertight': bool(m.is_watertight),
        'winding': bool(m.is_winding_consistent),
        'volume_ok': bool(m.is_volume),
        'volume': float(m.volume),
        'faces': int(len(m.faces)),
        'euler': int(m.euler_number),
        'lo': [float(x) for x in lo],
        'hi': [float(x) for x in hi],
    }))
"#;

struct Case {
    name: &'static str,
    path: PathBuf,
    unit: StlUnit,
    triangles: u64,
    /// Expected volume and tolerance, in the file's unit cubed.
    volume: f64,
    tol: f64,
    /// Expected bounding box size in the file's unit.
    size: [f64; 3],
}

fn metre_grid(v: Array2<f64>, pitch: [f64; 2]) -> Grid {
    Grid::new(v, pitch, Unit::Metre).unwrap()
}

/// Writes a terrace STL and states what an exact mesh must measure: volume = sum over pixels of
/// (h - h_min + t) * pixel area (chamfers move at most d^2/2 * area * height range each, f32
/// rounding a relative 1e-6), size = extent x (height range + t).
fn terrace_case(name: &'static str, dir: &Path, g: &Grid, t: f64, unit: StlUnit) -> Case {
    let mesh = terrace_mesh(g, t).unwrap();
    let path = dir.join(format!("{name}.stl"));
    let r = write_stl(&mesh, unit, &path).unwrap();
    assert_eq!(r.surface, SurfaceKind::Terraces);
    assert_eq!(r.max_height_error, 0.0);
    let (lo, hi) = g.min_max().unwrap();
    let [px, py] = g.pitch();
    let u = unit.metres();
    let volume = g.values().iter().map(|h| h - lo + t).sum::<f64>() * px * py / u.powi(3);
    let chamfer = r.chamfers as f64 * 0.5 * CHAMFER_FRACTION.powi(2) * px * py * (hi - lo) / u.powi(3);
    let ext = g.extent();
    Case {
        name,
        path,
        unit,
        triangles: r.triangles,
        volume,
        tol: chamfer + 1e-6 * volume,
        size: [ext[0] / u, ext[1] / u, (hi - lo + t) / u],
    }
}

/// A second independent reader: `stl_io` merges vertices by position; every directed edge
/// must then meet its reverse exactly once (closed, consistently wound).
fn check_with_stl_io(c: &Case) {
    let mut f = std::fs::File::open(&c.path).unwrap();
    let mesh = stl_io::read_stl(&mut f).unwrap();
    assert_eq!(mesh.faces.len() as u64, c.triangles, "{}: stl_io reads another face count", c.name);
    let mut open = std::collections::HashMap::new();
    for face in &mesh.faces {
        for k in 0..3 {
            let (u, v) = (face.vertices[k], face.vertices[(k + 1) % 3]);
            if open.remove(&(v, u)).is_none() {
                assert!(open.insert((u, v), ()).is_none(), "{}: edge {u}->{v} used twice", c.name);
            }
        }
    }
    assert!(open.is_empty(), "{}: {} edges without a partner", c.name, open.len());
}

fn check(cases: &[Case]) {
    cases.iter().for_each(check_with_stl_io);
    let args: Vec<&str> = cases.iter().map(|c| c.path.to_str().unwrap()).collect();
    let out = common::run_python(CHECK, &args);
    let lines: Vec<serde_json::Value> = out.lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    assert_eq!(lines.len(), cases.len(), "{out}");
    for (c, r) in cases.iter().zip(&lines) {
        let n = c.name;
        assert_eq!(r["watertight"], true, "{n}: not watertight: {r}");
        assert_eq!(r["winding"], true, "{n}: winding not consistent: {r}");
        assert_eq!(r["volume_ok"], true, "{n}: not a volume: {r}");
        // A closed genus-0 surface: V - E + F = 2.
        assert_eq!(r["euler"], 2, "{n}: {r}");
        assert_eq!(r["faces"].as_u64().unwrap(), c.triangles, "{n}: trimesh dropped faces: {r}");
        let header = r["header"].as_str().unwrap();
        assert!(!header.starts_with("solid"), "{n}: {header}");
        assert!(header.starts_with(&format!("doefab STL units={} ", c.unit.symbol())), "{n}: {header}");
        let vol = r["volume"].as_f64().unwrap();
        assert!((vol - c.volume).abs() <= c.tol, "{n}: volume {vol} vs {} (tol {})", c.volume, c.tol);
        // No vertical exaggeration: the z extent is the height range plus the base.
        for k in 0..3 {
            let size = r["hi"][k].as_f64().unwrap() - r["lo"][k].as_f64().unwrap();
            assert!((size - c.size[k]).abs() <= 1e-5 * c.size[k], "{n}: axis {k}: {size} vs {}", c.size[k]);
        }
    }
}

#[test]
fn terrace_stls_are_closed_solids_with_the_pixel_volume() {
    let dir = common::tempdir();
    let d = dir.path();
    let mut cases = Vec::new();

    // A few levels on a small grid: a raised block with a step, a strip at the edge.
    let v = Array2::from_shape_fn((6, 8), |(i, j)| {
        if (2..5).contains(&i) && (1..6).contains(&j) {
            if j > 3 {
                0.3e-6
            } else {
                0.2e-6
            }
        } else if j == 7 {
            0.1e-6
        } else {
            0.0
        }
    });
    cases.push(terrace_case("few_levels", d, &metre_grid(v, [2e-6, 3e-6]), 1e-6, StlUnit::Millimetre));

    // Random 16-level map, through the level-map conversion (period 1.2 um).
    let mut rng = Lcg(2024);
    let lv = Array2::from_shape_fn((40, 36), |_| (rng.uniform() * 16.0).floor());
    let lv = Grid::new(lv, [1e-6, 1e-6], Unit::Level).unwrap();
    let g = level_heights(&lv, 16, 1.2e-6).unwrap();
    cases.push(terrace_case("random16", d, &g, 2e-6, StlUnit::Micrometre));

    // Checkerboard: every inner corner is a saddle.
    let v = Array2::from_shape_fn((10, 10), |(i, j)| ((i + j) % 2) as f64 * 0.25e-6);
    cases.push(terrace_case("checkerboard", d, &metre_grid(v, [1e-6, 1e-6]), 0.5e-6, StlUnit::Micrometre));

    // Error-diffused (Floyd-Steinberg) ramp to 3 levels: diagonal contacts everywhere.
    let (n, m) = (30, 34);
    let mut f = Array2::from_shape_fn((n, m), |(i, j)| 2.0 * (i + j) as f64 / (n + m - 2) as f64);
    let mut q = Array2::zeros((n, m));
    for i in 0..n {
        for j in 0..m {
            let l = f[[i, j]].round().clamp(0.0, 2.0);
            let e = f[[i, j]] - l;
            q[[i, j]] = l * 0.1e-6;
            for (di, dj, w) in [(0isize, 1isize, 7.0), (1, -1, 3.0), (1, 0, 5.0), (1, 1, 1.0)] {
                let (a, b) = (i as isize + di, j as isize + dj);
                if a < n as isize && b >= 0 && b < m as isize {
                    f[[a as usize, b as usize]] += e * w / 16.0;
                }
            }
        }
    }
    cases.push(terrace_case("dither", d, &metre_grid(q, [1e-6, 1e-6]), 1e-6, StlUnit::Micrometre));

    // A single pixel, and a flat map: boxes.
    let one = metre_grid(Array2::from_elem((1, 1), 0.7e-6), [5e-6, 4e-6]);
    cases.push(terrace_case("single_pixel", d, &one, 1e-6, StlUnit::Micrometre));
    let flat = metre_grid(Array2::from_elem((12, 9), 0.0), [10e-6, 10e-6]);
    cases.push(terrace_case("flat", d, &flat, 0.2e-3, StlUnit::Millimetre));

    check(&cases);
}

#[test]
fn heightfield_stl_is_a_closed_solid_within_the_error_bound() {
    let dir = common::tempdir();
    let (n, m) = (48, 40);
    let (px, py) = (1e-6, 1.25e-6);
    // A paraboloid: h = 1 um * (1 - r^2 / R^2) with r in pixels.
    let v = Array2::from_shape_fn((n, m), |(i, j)| {
        let (x, y) = (j as f64 - 17.3, i as f64 - 25.1);
        1e-6 * (1.0 - (x * x + y * y) / 3000.0)
    });
    let g = metre_grid(v, [px, py]);
    let tol = 1e-9;
    let t = 1e-6;
    let opts = StlOptions {
        unit: StlUnit::Micrometre,
        base_thickness: t,
        max_error: tol,
        surface: SurfaceChoice::Auto,
    };
    let path = dir.path().join("paraboloid.stl");
    let r = surface_stl(&g, &opts, &path).unwrap();
    assert_eq!(r.surface, SurfaceKind::Heightfield);
    assert!(r.max_height_error <= tol && r.max_height_error > 0.0, "{}", r.max_height_error);
    assert!(r.triangles < r.naive_triangles, "{} vs {}", r.triangles, r.naive_triangles);
    // Volume over the pixel-centre footprint: the trapezoid rule of the samples (the
    // bilinear surface through them), within (error bound + curvature term) * area.
    let (lo, hi) = g.min_max().unwrap();
    let mut sum = 0.0;
    for i in 0..n {
        for j in 0..m {
            let wi = if i == 0 || i == n - 1 { 0.5 } else { 1.0 };
            let wj = if j == 0 || j == m - 1 { 0.5 } else { 1.0 };
            sum += wi * wj * (g.values()[[i, j]] - lo + t);
        }
    }
    let area = (m - 1) as f64 * px * (n - 1) as f64 * py;
    let u3 = 1e-18;
    // |h''| = 2 um / 3000 per pixel^2; linear interpolation errs by at most |h''| / 8 per cell.
    let curvature = 2e-6 / 3000.0 / 8.0;
    let case = Case {
        name: "paraboloid",
        path,
        unit: StlUnit::Micrometre,
        triangles: r.triangles,
        volume: sum * px * py / u3,
        tol: (tol + curvature) * area / u3 + 1e-6 * sum * px * py / u3,
        size: [(m - 1) as f64, (n - 1) as f64 * 1.25, (hi - lo + t) * 1e6],
    };
    check(&[case]);
    // The same map as terraces (every value distinct) is exact but far larger.
    let exact = terrace_mesh(&g, t).unwrap();
    assert!(exact.triangles().len() as u64 > 3 * r.triangles);
    assert!(heightfield_mesh(&g, t, 1e-12).unwrap().triangles().len() as u64 > r.triangles);
}

#[test]
fn invalid_inputs_write_nothing() {
    let dir = common::tempdir();
    let path = dir.path().join("bad.stl");
    let opts = StlOptions::default();
    let mut v = Array2::from_elem((5, 5), 0.1e-6);
    v[[3, 1]] = f64::NAN;
    let e = surface_stl(&metre_grid(v.clone(), [1e-6; 2]), &opts, &path).unwrap_err();
    assert!(matches!(e, Error::Data { cause: DataCause::NotFinite, .. }), "{e:?}");
    let masked = Grid::from_values_nan_invalid(v, [1e-6; 2], Unit::Metre).unwrap();
    let e = surface_stl(&masked, &opts, &path).unwrap_err();
    assert!(matches!(e, Error::Data { cause: DataCause::NotFinite, .. }), "{e:?}");
    assert!(e.to_string().contains("row 3, column 1"), "{e}");
    let ok = metre_grid(Array2::from_elem((5, 5), 0.1e-6), [1e-6; 2]);
    let neg = StlOptions { base_thickness: -1e-6, ..opts };
    let e = surface_stl(&ok, &neg, &path).unwrap_err();
    assert!(matches!(e, Error::Parameter { ref name, .. } if name == "base_thickness"), "{e:?}");
    assert!(!path.exists());
}
