//! Speed of the scan readers and the metrology basics on a 2048 x 2048 scan (the size the
//! metrology stage is specified for): each binary format written in memory by this crate's
//! test encoders, then read (decode + unit resolution + mask), plus the ISO height parameters,
//! a least-squares plane and the 3-sigma outlier test. Prints seconds per step.
//!
//! Run with `cargo bench --bench scan`.

use std::path::Path;
use std::time::Instant;

use doefab::io::scan::{decode_scan_raw, scan_from_raw, zygo, ScanOptions};
use doefab::metrology::height_params;
use doefab::metrology::nsigma_outliers;
use doefab::metrology::{level, level_plane, LevelMethod};
use ndarray::Array2;

fn main() -> doefab::Result<()> {
    let n = 2048;
    let pitch = [2.5e-6, 2.5e-6];
    let mut v = Array2::from_shape_fn((n, n), |(i, j)| {
        let (x, y) = (j as f64 - 1024.0, i as f64 - 1024.0);
        1e-9 * (0.3 * x - 0.2 * y) + 0.6e-6 * (1.0 + ((x * x + y * y).sqrt() * 0.05).sin())
    });
    for k in 0..2000 {
        v[[(k * 37) % n, (k * 101) % n]] = f64::NAN;
    }
    let opts = ScanOptions::default();
    let phase = v.mapv(|z| {
        if z.is_nan() {
            zygo::INVALID_PHASE
        } else {
            (z / (0.5 * 632.8e-9 / 32768.0)).round() as i32
        }
    });
    let mp = zygo::MetroProFields {
        header_format: 1,
        phase_res: 1,
        wavelength: 632.8e-9,
        scale_factor: 0.5,
        obliquity: 1.0,
        camera_res: 2.5e-6,
        inverted: false,
        buckets: 0,
    };
    let files: Vec<(&str, Vec<u8>)> = vec![
        ("scan.x3p", doefab::io::scan::x3p::encode(&v, pitch)?),
        ("scan.gsf", doefab::io::scan::gsf::encode(&v, pitch)),
        ("scan.sdf", doefab::io::scan::sdf::encode_binary(&v, pitch)),
        ("scan.sur", doefab::io::scan::sur::encode(&v, 2.5, b"\xb5m", 1e-6)),
        ("scan.dat", zygo::encode(&mp, &phase)),
    ];
    println!("{n} x {n} scan, {} non-measured points", 2000);
    let mut last = None;
    for (name, bytes) in &files {
        let p = Path::new(name);
        let t = Instant::now();
        let s = scan_from_raw(p, decode_scan_raw(p, bytes, &opts)?, &opts)?;
        println!("read {name:<9} {:>6.1} MB  {:.3} s", bytes.len() as f64 / 1e6, t.elapsed().as_secs_f64());
        last = Some(s.grid);
    }
    let g = last.expect("files");
    let t = Instant::now();
    let p = height_params(&g)?;
    println!("height parameters      {:.3} s (Sq {:.1} nm)", t.elapsed().as_secs_f64(), p.sq * 1e9);
    let t = Instant::now();
    let (lev, _) = level_plane(&g, None)?;
    let plane_s = t.elapsed().as_secs_f64();
    println!("least-squares plane    {plane_s:.3} s");
    for (name, method) in [
        ("facet levelling", LevelMethod::Facet),
        ("lowest-level plane", LevelMethod::Substrate { aperture: None }),
    ] {
        let t = Instant::now();
        let r = level(&g, method);
        let s = t.elapsed().as_secs_f64();
        match r {
            Ok((_, l)) => println!(
                "{name:<22} {s:.3} s ({:.1} x the plane; {} iterations, {} points fitted)",
                s / plane_s,
                l.iterations.map_or("-".to_string(), |i| i.to_string()),
                l.fitted_points
            ),
            Err(e) => println!("{name:<22} {s:.3} s, refused: {e}"),
        }
    }
    let t = Instant::now();
    let o = nsigma_outliers(&lev, 3.0, 1, 10)?;
    println!(
        "3-sigma outliers       {:.3} s ({} found, {} passes)",
        t.elapsed().as_secs_f64(),
        o.positions.len(),
        o.iterations
    );
    Ok(())
}
