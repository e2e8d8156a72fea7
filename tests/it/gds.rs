//! The GDSII mask set read back by an independent reader (KLayout's Python module): the
//! levels decoded from the layers equal the level map pixel for pixel, polygons respect the
//! vertex limit (by default 4094, which KLayout reads without a warning), have no holes and do not overlap, and the alignment crosses are the
//! same on every layer.

use crate::common;

use doefab::rng::Lcg;
use std::collections::BTreeMap;

use doefab::fabrication::gds::{
    layer_masks, write_layer_previews, write_mask_set, MaskSetOptions, MaskSetStats, MAX_BOUNDARY_VERTICES,
    SIGNED_LENGTH_MAX_VERTICES,
};
use doefab::{DataCause, Error, Grid, Unit};
use ndarray::Array2;

/// Reads the GDSII file with KLayout and reports, per layer: shape count, most points in a
/// shape, holes, whether the shapes overlap, the crosses outside the design box (count,
/// bounding-box centres, areas, equality with layer 1) and the bit at every pixel centre.
const CHECKER: &str = r#"
import sys
import klayout.db as db

path = sys.argv[1]
rows, cols, x0, ytop, px, py = map(int, sys.argv[2:8])
ly = db.Layout()
ly.read(path)
print("dbu", repr(ly.dbu))
tops = ly.top_cells()
print("top", len(tops), tops[0].name)
top = tops[0]
design = db.Region(db.Box(x0, ytop - rows * py, x0 + cols * px, ytop))
probes = db.Region()
for i in range(rows):
    cy = ytop - (2 * i + 1) * py // 2
    for j in range(cols):
        cx = x0 + (2 * j + 1) * px // 2
        probes.insert(db.Box(cx - 1, cy - 1, cx + 1, cy + 1))
first_crosses = None
for li in sorted(ly.layer_indexes(), key=lambda l: ly.get_info(l).layer):
    info = ly.get_info(li)
    shapes = list(top.shapes(li).each())
    polys = [s.polygon for s in shapes]
    maxpts = max(p.num_points() for p in polys)
    holes = sum(p.holes() for p in polys)
    raw_area = sum(p.area() for p in polys)
    region = db.Region(top.shapes(li))
    region.merge()
    overlap_free = int(raw_area == region.area())
    pattern = region & design
    crosses = region - design
    if first_crosses is None:
        first_crosses = crosses
    same = int((crosses ^ first_crosses).is_empty())
    centres = sorted((p.bbox().center().x, p.bbox().center().y) for p in crosses.each())
    areas = sorted(set(p.area() for p in crosses.each()))
    bits = bytearray(b"0" * (rows * cols))
    for p in (probes & pattern).each():
        c = p.bbox().center()
        j = (c.x - x0) // px
        i = (ytop - c.y) // py
        bits[i * cols + j] = ord("1")
    print("layer", info.layer, info.datatype, len(shapes), maxpts, holes, overlap_free,
          crosses.count(), same, " ".join("%d,%d" % c for c in centres),
          " ".join(str(a) for a in areas))
    print("bits", info.layer, bits.decode())
"#;

/// What the checker reported for one layer.
#[derive(Debug)]
struct LayerCheck {
    datatype: u32,
    shapes: usize,
    max_points: usize,
    holes: usize,
    overlap_free: bool,
    crosses: usize,
    crosses_as_layer_1: bool,
    cross_centres: Vec<[i64; 2]>,
    cross_areas: Vec<i64>,
    bits: Vec<bool>,
}

fn nm(metres: f64) -> i64 {
    (metres * 1e9).round() as i64
}

/// Runs the KLayout checker on `path`; returns the layers by layer number and the reader's
/// warnings.
fn klayout_check(
    path: &std::path::Path,
    rows: usize,
    cols: usize,
    rep: &MaskSetStats,
) -> (BTreeMap<u32, LayerCheck>, Vec<String>) {
    let e = rep.design_extent;
    let args: Vec<String> = vec![
        path.display().to_string(),
        rows.to_string(),
        cols.to_string(),
        nm(e[0]).to_string(),
        nm(e[3]).to_string(),
        nm(rep.pitch[0]).to_string(),
        nm(rep.pitch[1]).to_string(),
    ];
    let args: Vec<&str> = args.iter().map(String::as_str).collect();
    let out = common::run_python(CHECKER, &args);
    let mut layers = BTreeMap::new();
    let mut bits = BTreeMap::new();
    let mut warnings = Vec::new();
    for line in out.lines() {
        if line.starts_with("Warning:") {
            warnings.push(line.to_string());
            continue;
        }
        let f: Vec<&str> = line.split(' ').collect();
        match f[0] {
            "dbu" => assert_eq!(f[1], "0.001", "database unit in user units"),
            "top" => assert_eq!(&f[1..], &["1", "DOEFAB"]),
            "layer" => {
                let n = |k: usize| f[k].parse::<usize>().unwrap();
                let centres = f[9..13]
                    .iter()
                    .map(|c| {
                        let (x, y) = c.split_once(',').unwrap();
                        [x.parse().unwrap(), y.parse().unwrap()]
                    })
                    .collect();
                layers.insert(
                    n(1) as u32,
                    LayerCheck {
                        datatype: n(2) as u32,
                        shapes: n(3),
                        max_points: n(4),
                        holes: n(5),
                        overlap_free: n(6) == 1,
                        crosses: n(7),
                        crosses_as_layer_1: n(8) == 1,
                        cross_centres: centres,
                        cross_areas: f[13..].iter().map(|a| a.parse().unwrap()).collect(),
                        bits: Vec::new(),
                    },
                );
            }
            "bits" => {
                bits.insert(
                    f[1].parse::<u32>().unwrap(),
                    f[2].bytes().map(|b| b == b'1').collect::<Vec<_>>(),
                );
            }
            _ => panic!("unexpected checker output: {line}\nin:\n{out}"),
        }
    }
    for (k, b) in bits {
        assert_eq!(b.len(), rows * cols);
        layers.get_mut(&k).unwrap().bits = b;
    }
    (layers, warnings)
}

/// Checks every layer of a written mask set against the level map, through KLayout; returns
/// the reader's warnings.
fn check_against_klayout(
    levels: &Grid,
    n_levels: usize,
    rep: &MaskSetStats,
    path: &std::path::Path,
) -> Vec<String> {
    let (rows, cols) = levels.dim();
    let (layers, warnings) = klayout_check(path, rows, cols, rep);
    let m = n_levels.trailing_zeros() as usize;
    assert_eq!(layers.keys().copied().collect::<Vec<_>>(), (1..=m as u32).collect::<Vec<_>>());
    let mut expected_centres: Vec<[i64; 2]> =
        rep.cross_centres.iter().map(|c| [nm(c[0]), nm(c[1])]).collect();
    expected_centres.sort();
    let (arm, width) = (nm(rep.cross_arm), nm(rep.cross_width));
    for (k, l) in &layers {
        assert_eq!(l.datatype, 0);
        assert!(l.max_points <= MAX_BOUNDARY_VERTICES, "layer {k}: {} points", l.max_points);
        assert_eq!(l.holes, 0, "layer {k}");
        assert!(l.overlap_free, "layer {k}: shapes overlap");
        assert_eq!(l.crosses, 4, "layer {k}");
        assert!(l.crosses_as_layer_1, "layer {k}: crosses differ from layer 1");
        assert_eq!(l.cross_centres, expected_centres, "layer {k}");
        assert_eq!(l.cross_areas, vec![2 * arm * width - width * width], "layer {k}");
        let mask = &rep.masks[*k as usize - 1];
        assert_eq!(l.shapes, mask.polygons + 4, "layer {k}");
        assert!((mask.etch_depth - rep.period / 2f64.powi(*k as i32)).abs() < 1e-18);
    }
    // Levels decoded from the layers: level = sum_k bit_k 2^(M - k).
    for ((i, j), &v) in levels.values().indexed_iter() {
        let decoded: usize =
            layers.values().enumerate().map(|(k, l)| (l.bits[i * cols + j] as usize) << (m - 1 - k)).sum();
        assert_eq!(decoded, v as usize, "pixel ({i}, {j})");
    }
    warnings
}

#[test]
fn eight_level_map_decodes_exactly_through_klayout() {
    let (rows, cols) = (201, 299);
    let mut g = Lcg(2024);
    let values = Array2::from_shape_fn((rows, cols), |(i, j)| {
        let smooth =
            3.5 + 2.4 * (i as f64 / 13.0).sin() + 1.5 * (j as f64 / 17.0 + 0.3 * i as f64 / 29.0).cos();
        let noise = if g.uniform() < 0.15 { (g.uniform() * 5.0).floor() - 2.0 } else { 0.0 };
        (smooth + noise).round().clamp(0.0, 7.0)
    });
    let levels = Grid::new(values, [1.5e-6, 1.5e-6], Unit::Level).unwrap();
    let dir = common::tempdir();
    let path = dir.path().join("mask.gds");
    let period = 1218.7e-9;
    let opts = MaskSetOptions::default();
    let rep = write_mask_set(&levels, 8, period, &opts, &path).unwrap();
    assert_eq!(rep.level_count, 8);
    assert_eq!(rep.masks.len(), 3);
    // The map uses every level; its polygons are small enough (< 4094 vertices) that KLayout
    // reads the file without any warning.
    for l in 0..8 {
        assert!(levels.values().iter().any(|&v| v == l as f64), "level {l} unused");
    }
    let warnings = check_against_klayout(&levels, 8, &rep, &path);
    assert!(warnings.is_empty(), "{warnings:?}");
    // Same input, same bytes.
    let again = dir.path().join("again.gds");
    write_mask_set(&levels, 8, period, &opts, &again).unwrap();
    assert_eq!(std::fs::read(&path).unwrap(), std::fs::read(&again).unwrap());

    // The previews: one 8-bit PNG per layer, white where the mask is open, with the crosses.
    let pngs = write_layer_previews(&levels, 8, &opts, dir.path(), "mask").unwrap();
    assert_eq!(pngs.len(), 3);
    let masks = layer_masks(&levels, 8).unwrap();
    // Padding: (100 + 200) um / 1.5 um + 2 = 202 pixels per side.
    let pad = 202;
    for (png, mask) in pngs.iter().zip(&masks) {
        assert!(png.file_name().unwrap().to_str().unwrap().starts_with("mask_layer"));
        let img = image::open(png).unwrap();
        assert_eq!(img.color(), image::ColorType::L8);
        let img = img.to_luma8();
        assert_eq!(img.dimensions(), ((cols + 2 * pad) as u32, (rows + 2 * pad) as u32));
        for ((i, j), &open) in mask.indexed_iter() {
            assert_eq!(img.get_pixel((j + pad) as u32, (i + pad) as u32)[0], if open { 255 } else { 0 });
        }
        // The top-left cross centre: 100 um + 100 um left of and above the design corner.
        let c = pad - (200.0 / 1.5f64).round() as usize;
        assert_eq!(img.get_pixel(c as u32, c as u32)[0], 255);
        assert_eq!(img.get_pixel(0, 0)[0], 0);
    }
}

#[test]
fn serpentine_beyond_the_vertex_limit_is_split_and_still_exact() {
    // One 4-connected serpentine with about 10000 corners, on a 2-level map (one mask).
    let (rows, cols) = (8, 5000);
    let values = Array2::from_shape_fn((rows, cols), |(i, j)| {
        (j % 2 == 0 || (i == 0 && j % 4 == 1) || (i == rows - 1 && j % 4 == 3)) as u8 as f64
    });
    let levels = Grid::new(values, [2e-6, 2e-6], Unit::Level).unwrap();
    let dir = common::tempdir();
    let path = dir.path().join("serpentine.gds");
    // The default limit, 4094 vertices, keeps every XY record within 32 KiB: KLayout reads
    // the file without a word.
    let rep = write_mask_set(&levels, 2, 600e-9, &MaskSetOptions::default(), &path).unwrap();
    assert!(rep.vertices > MAX_BOUNDARY_VERTICES, "{} vertices", rep.vertices);
    assert!(rep.polygons >= 3, "{} polygons", rep.polygons);
    let warnings = check_against_klayout(&levels, 2, &rep, &path);
    assert!(warnings.is_empty(), "{warnings:?}");
    let (layers, _) = klayout_check(&path, rows, cols, &rep);
    assert!(layers[&1].max_points <= SIGNED_LENGTH_MAX_VERTICES, "{}", layers[&1].max_points);
    // At the format's own limit (8190) the file is still exact, and KLayout reads the long
    // records (> 32 KiB) but warns that it takes their length as unsigned.
    let opts = MaskSetOptions { max_vertices: MAX_BOUNDARY_VERTICES, ..Default::default() };
    let rep = write_mask_set(&levels, 2, 600e-9, &opts, &path).unwrap();
    let warnings = check_against_klayout(&levels, 2, &rep, &path);
    assert!(warnings.iter().any(|w| w.contains("Record length larger than 0x8000")), "{warnings:?}");
    assert!(
        warnings.iter().all(|w| w.contains("In file") || w.contains("Record length larger than 0x8000")),
        "{warnings:?}"
    );
    // A tighter limit of the caller's choosing holds too.
    let opts = MaskSetOptions { max_vertices: 100, ..Default::default() };
    let rep = write_mask_set(&levels, 2, 600e-9, &opts, &path).unwrap();
    assert!(rep.polygons >= rep.vertices / 100);
    let (layers, warnings) = klayout_check(&path, rows, cols, &rep);
    assert!(layers[&1].max_points <= 100);
    assert!(warnings.is_empty(), "{warnings:?}");
}

#[test]
fn bad_level_maps_are_refused_without_writing() {
    let dir = common::tempdir();
    let path = dir.path().join("bad.gds");
    let opts = MaskSetOptions::default();
    let ok = Array2::from_shape_fn((4, 5), |(i, j)| ((i + j) % 6) as f64);
    let six = Grid::new(ok.clone(), [1e-6, 1e-6], Unit::Level).unwrap();
    let e = write_mask_set(&six, 6, 1e-6, &opts, &path).unwrap_err();
    assert!(matches!(e, Error::Parameter { ref name, .. } if name == "level_count"), "{e:?}");
    // Level 7 at (1, 2) with 4 levels.
    let mut v = Array2::from_elem((4, 5), 3.0);
    v[[1, 2]] = 7.0;
    v[[3, 4]] = 9.0;
    let g = Grid::new(v, [1e-6, 1e-6], Unit::Level).unwrap();
    let e = write_mask_set(&g, 4, 1e-6, &opts, &path).unwrap_err();
    assert!(matches!(e, Error::Data { cause: DataCause::OutOfRange, .. }), "{e:?}");
    let e = e.to_string();
    assert!(e.contains("row 1, column 2") && e.contains('7'), "{e}");
    // Heights are not levels.
    let h = Grid::new(ok, [1e-6, 1e-6], Unit::Metre).unwrap();
    let e = write_mask_set(&h, 8, 1e-6, &opts, &path).unwrap_err();
    assert!(matches!(e, Error::Parameter { .. }), "{e:?}");
    assert!(!path.exists());
}
