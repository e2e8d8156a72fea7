//! Registration speed and accuracy at the size the metrology stage is specified for: 2048 x 2048
//! scans (2.7 um pitch, 5.5 mm across) of the built-in 1306 x 1306 design, made by the
//! synthetic scan generator with 2 um blur, 20 nm noise and 10% non-measured points.
//!
//! 1. *Shift only*, beside OpenCV: the part placed with a pure shift. doefab's `register` (which
//!    does not know that: it searches rotation, mirror and height sign and fits all eight
//!    parameters) against `cv2.phaseCorrelate` (translation only) run by
//!    `benches/register_opencv.py` in the same run on the same arrays, when a Python with `cv2`
//!    is found (`$DOEFAB_PYTHON`, `.venv/bin/python`, `python3`; `pip install
//!    opencv-python-headless`). Times are the best of 5 for both, from arrays in memory.
//! 2. *A cast*: mirrored and complemented, rotated by 0.3 deg, shifted, tilted (OpenCV's phase
//!    correlation has no answer for it): time and the recovered pose's errors, and read + level +
//!    register from an X3P file in memory.
//! 3. *Speed against accuracy*: the cast registered with the least-squares point budget
//!    (`max_points`) from 25,000 to 1.6 M: time and shift error (with its formal standard error)
//!    for each, charted in `target/tmp/bench-register/speed_accuracy.svg` (and `.png`).
//!
//! Run with `cargo bench --bench register`.

use std::path::Path;
use std::time::Instant;

mod common;

use doefab::charts::metrology::{registration_speed_accuracy, SpeedAccuracyPoint};
use doefab::design::{paper_example, ExampleParams, PAPER_PITCH};
use doefab::grid::Grid;
use doefab::io::scan::{decode_scan_raw, scan_from_raw, ScanOptions};
use doefab::metrology::level_plane;
use doefab::metrology::{register, Pose, RegisterOptions, Registration};
use doefab::metrology::{simulate_scan, SimulateParams};

const RUNS: usize = 5;

/// Best time of `runs` registrations, and the last result.
fn timed(
    design: &Grid,
    scan: &Grid,
    opts: &RegisterOptions,
    runs: usize,
) -> doefab::Result<(f64, Registration)> {
    let mut best = f64::INFINITY;
    let mut reg = None;
    for _ in 0..runs {
        let t = Instant::now();
        let r = register(design, scan, opts)?;
        best = best.min(t.elapsed().as_secs_f64());
        reg = Some(r);
    }
    Ok((best, reg.expect("at least one run")))
}

/// Shift error `[x, y]` in design pixels.
fn shift_error(found: [f64; 2], truth: [f64; 2]) -> [f64; 2] {
    [(found[0] - truth[0]) / PAPER_PITCH, (found[1] - truth[1]) / PAPER_PITCH]
}

fn main() -> doefab::Result<()> {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let dir = Path::new(env!("CARGO_TARGET_TMPDIR")).join("bench-register");
    std::fs::create_dir_all(&dir).map_err(|e| doefab::Error::io(&dir, e))?;
    let design = paper_example(&ExampleParams::default())?;
    let opts = RegisterOptions::default();
    let size = Some((2048, 2048));
    let pitch = Some([2.7e-6, 2.7e-6]);

    // 1. Shift only, beside OpenCV.
    let truth = [12.3e-6, -7.9e-6];
    let sp = SimulateParams {
        blur: 2e-6,
        noise: 20e-9,
        missing: 0.1,
        pose: Pose { shift: truth, ..Pose::default() },
        pitch,
        size,
        seed: 7,
        ..SimulateParams::default()
    };
    let scan = simulate_scan(&design, &sp)?;
    let (t_ours, r) = timed(&design, &scan, &opts, RUNS)?;
    let e = shift_error(r.pose.shift, truth);
    println!("1. shift only: 2048 x 2048 scan at 2.7 um, 2 um blur, 20 nm noise, 10% non-measured");
    println!(
        "   doefab register   {t_ours:.3} s  shift error [{:+.4}, {:+.4}] px (design pixels of 4.29 um), \
         formal sigma [{:.1e}, {:.1e}] px; rotation {:+.5} deg, scale {:.6}, mirror {}, complement {}",
        e[0],
        e[1],
        r.shift_sigma[0] / PAPER_PITCH,
        r.shift_sigma[1] / PAPER_PITCH,
        r.pose.rotation.to_degrees(),
        r.pose.scale,
        r.pose.mirror,
        r.complement,
    );
    match common::python_with("cv2") {
        Some(py) => {
            let (dn, sn) = (dir.join("design.npy"), dir.join("scan.npy"));
            doefab::io::npy::write_npy_f64(&dn, design.values())?;
            doefab::io::npy::write_npy_f64(&sn, &scan.values_nan_invalid())?;
            let out = std::process::Command::new(&py)
                .arg(root.join("benches/register_opencv.py"))
                .arg(&dn)
                .arg(format!("{PAPER_PITCH:e}"))
                .arg(&sn)
                .arg("2.7e-6")
                .arg(RUNS.to_string())
                .output()
                .map_err(|e| doefab::Error::io(Path::new(&py), e))?;
            let text = String::from_utf8_lossy(&out.stdout).into_owned();
            let f: Vec<f64> = text
                .trim()
                .strip_prefix("opencv ")
                .map(|s| s.split_whitespace().filter_map(|v| v.parse().ok()).collect())
                .unwrap_or_default();
            if let [t_cv, dx, dy] = f[..] {
                let e = shift_error([dx, dy], truth);
                println!(
                    "   cv2.phaseCorrelate {t_cv:.3} s  shift error [{:+.4}, {:+.4}] px (translation only)",
                    e[0], e[1]
                );
                println!("   time doefab / OpenCV {:.2}", t_ours / t_cv);
            } else {
                println!("   OpenCV run failed: {}{}", text, String::from_utf8_lossy(&out.stderr));
            }
        }
        None => println!("   notice: no Python with cv2 found; the OpenCV comparison is skipped"),
    }

    // 2. A cast.
    let sp = SimulateParams { pitch, size, ..SimulateParams::typical_cast() };
    let scan = simulate_scan(&design, &sp)?;
    let (t_cast, r) = timed(&design, &scan, &opts, RUNS)?;
    let e = shift_error(r.pose.shift, sp.pose.shift);
    println!("2. a cast: mirrored, complemented, rotated 0.3 deg, shifted, tilted (same blur, noise, holes)");
    println!(
        "   doefab register   {t_cast:.3} s  shift error [{:+.4}, {:+.4}] px, rotation {:+.5} deg, depth scale \
         {:+.3}%, blur {:.2} um (true 2), correlation {:.5}, {} points",
        e[0],
        e[1],
        (r.pose.rotation - sp.pose.rotation).to_degrees(),
        100.0 * (r.depth_scale / 0.95 - 1.0),
        r.blur * 1e6,
        r.correlation,
        r.points
    );
    let bytes = doefab::io::scan::x3p::encode(&scan.values_nan_invalid(), scan.pitch())?;
    let p = Path::new("scan.x3p");
    let so = ScanOptions::default();
    let mut best_all = f64::INFINITY;
    for _ in 0..3 {
        let t = Instant::now();
        let s = scan_from_raw(p, decode_scan_raw(p, &bytes, &so)?, &so)?;
        let (lev, _) = level_plane(&s.grid, None)?;
        register(&design, &lev, &opts)?;
        best_all = best_all.min(t.elapsed().as_secs_f64());
    }
    println!("   read X3P + level + register (best of 3) {best_all:.3} s");

    // 3. Speed against accuracy over the point budget.
    println!("3. speed against accuracy (the cast), least-squares point budget:");
    println!("   max_points  points   time s   shift error px (x, y)   formal sigma px   rotation error deg");
    let mut chart = vec![];
    for max_points in [25_000, 50_000, 100_000, 200_000, 400_000, 800_000, 1_600_000] {
        let o = RegisterOptions { max_points, ..RegisterOptions::default() };
        let (t, r) = timed(&design, &scan, &o, 3)?;
        let e = shift_error(r.pose.shift, sp.pose.shift);
        let sigma = r.shift_sigma[0].hypot(r.shift_sigma[1]) / PAPER_PITCH;
        let marker = if max_points == opts.max_points { "  (default)" } else { "" };
        println!(
            "   {max_points:>10}  {:>7}  {t:.3}    [{:+.4}, {:+.4}]      {sigma:.1e}          {:+.5}{marker}",
            r.points,
            e[0],
            e[1],
            (r.pose.rotation - sp.pose.rotation).to_degrees()
        );
        chart.push(SpeedAccuracyPoint {
            label: format!("{}k", max_points / 1000),
            seconds: t,
            error: e[0].hypot(e[1]),
            sigma,
            chosen: max_points == opts.max_points,
        });
    }
    let path = dir.join("speed_accuracy.png");
    registration_speed_accuracy(&path, &chart, 0.02)?;
    println!("   chart: {} (and .svg)", path.display());
    Ok(())
}
