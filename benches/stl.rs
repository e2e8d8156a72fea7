//! Terrace STL of the built-in design at 1 um pitch, 16 levels (about 5600 x 5600 pixels):
//! time, triangle counts and peak memory. Run with `cargo bench --bench stl`.
//! Optional argument: pixel pitch in micrometres (default 1). `--check` also verifies that the
//! mesh is a closed manifold; `--keep PATH` keeps the STL; `--heightfield` also meshes the
//! unwrapped continuous design (1306 x 1306 at 4.29 um) as a heightfield within 2 nm.

use std::time::Instant;

use doefab::design::{paper_example, ExampleParams};
use doefab::fabrication::quantize::{quantize, QuantizeMethod};
use doefab::fabrication::stl::{heightfield_mesh, terrace_mesh, write_stl, StlUnit};
use doefab::fabrication::wrap::{wrap, WrapSpec};
use doefab::Interpolation;

const LEVELS: usize = 16;

/// Peak resident set size of this process, bytes (Linux `VmHWM`).
fn peak_rss() -> Option<u64> {
    let s = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = s.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kb: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb * 1024)
}

fn main() {
    let pitch_um: f64 = std::env::args()
        .skip(1)
        .find(|a| a.parse::<f64>().is_ok())
        .and_then(|a| a.parse().ok())
        .unwrap_or(1.0);
    if std::env::args().any(|a| a == "--heightfield") {
        let design = paper_example(&ExampleParams::default()).expect("design");
        let t0 = Instant::now();
        let mesh = heightfield_mesh(&design, 0.5e-3, 2e-9).expect("heightfield");
        let dt = t0.elapsed().as_secs_f64();
        println!(
            "heightfield {:?}: {dt:.2} s, {} triangles (naive {}), max error {:.3} nm",
            design.dim(),
            mesh.triangles().len(),
            mesh.naive_triangles(),
            mesh.max_height_error() * 1e9
        );
        if std::env::args().any(|a| a == "--check") {
            println!("heightfield closed manifold: {:?}", mesh.check_closed().map(|_| "yes"));
        }
    }
    let design = paper_example(&ExampleParams::default()).expect("design");
    let (wrapped, w) = wrap(&design, &WrapSpec::default()).expect("wrap");
    let q = quantize(&wrapped, w.period, LEVELS, QuantizeMethod::Round).expect("quantize");
    let map = q
        .heights()
        .expect("heights")
        .resample([pitch_um * 1e-6; 2], Interpolation::Nearest)
        .expect("resample");
    drop((design, wrapped, q));
    let (nr, nc) = map.dim();
    let rss_before = peak_rss();
    // Reset the high-water mark (Linux: writing 5 to clear_refs), so that the peak below is the
    // meshing stage's (with the map held), not the design preparation's.
    let reset = std::fs::write("/proc/self/clear_refs", "5").is_ok();
    let args: Vec<String> = std::env::args().collect();
    let dir = tempfile::tempdir().expect("temp dir");
    let path = match args.iter().position(|a| a == "--keep") {
        Some(k) => std::path::PathBuf::from(&args[k + 1]),
        None => dir.path().join("bench.stl"),
    };
    let t0 = Instant::now();
    let mesh = terrace_mesh(&map, 0.5e-3).expect("mesh");
    let t_mesh = t0.elapsed().as_secs_f64();
    let report = write_stl(&mesh, StlUnit::Millimetre, &path).expect("write");
    let t_all = t0.elapsed().as_secs_f64();
    let bytes = std::fs::metadata(&path).map(|m| m.len()).unwrap_or(0);
    println!("map: {nr} x {nc} pixels, 16 levels, pitch {pitch_um} um");
    println!("mesh: {t_mesh:.2} s, mesh + write: {t_all:.2} s");
    println!(
        "triangles: {} (naive {}, ratio {:.4}), vertices {}, chamfers {}, file {:.1} MB",
        report.triangles,
        report.naive_triangles,
        report.triangle_ratio,
        report.vertices,
        report.chamfers,
        bytes as f64 / 1e6
    );
    if let (Some(b), Some(p)) = (rss_before, peak_rss()) {
        let what = if reset { "during meshing and writing" } else { "whole run" };
        println!(
            "peak RSS {what}: {:.0} MiB (peak while preparing the map: {:.0} MiB)",
            p as f64 / 1048576.0,
            b as f64 / 1048576.0
        );
    }
    // Exact pixel volume: sum over pixels of (h - h_min + t) * pixel area.
    let (lo, _) = map.min_max().expect("samples");
    let want = map.values().iter().map(|h| h - lo + 0.5e-3).sum::<f64>() * map.pitch()[0] * map.pitch()[1];
    println!(
        "volume: mesh {:.9e} m^3, pixel sum {want:.9e} m^3, relative difference {:.1e}",
        report.volume,
        (report.volume - want) / want
    );
    if args.iter().any(|a| a == "--check") {
        match mesh.check_closed() {
            Ok(()) => println!("closed manifold: yes, volume {:.6e} m^3", report.volume),
            Err(e) => println!("closed manifold: NO ({e})"),
        }
    }
}
