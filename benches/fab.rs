//! Speed of the grayscale path on the paper's DOE at a 1 um writer grid (5600 x 5600 pattern,
//! 31 Mpx): wrap + quantize + 16-bit PNG, as the chain runs it (wrap and quantize on the
//! 1306 x 1306 design grid, then resample the levels to the writer grid) and, as reference in
//! the same process, the literal order (resample the heights first, wrap and quantize all
//! 31 Mpx). Prints seconds, the ratio, and the peak resident memory.
//!
//! Then the command's whole path on a design already at the writer grid (the same DOE sampled
//! at 1 um, 5603^2, written as an f64 .npy): `fab` with the grayscale recipe at 65,536 levels
//! and a 16-bit PNG only (read, hash, checks, wrap, master, quantize, mask, PNG, sidecar,
//! report), against OpenCV's wrap + quantize + imwrite of the same file timed inside
//! `benches/fab_opencv.py` in the same run, when a Python with `cv2` is found
//! (`$DOEFAB_PYTHON`, `.venv/bin/python`, `python3`; `pip install opencv-python-headless`).
//!
//! Run with `cargo bench --bench fab`.

use std::path::Path;
use std::time::Instant;

mod common;

use doefab::design::{paper_example, ExampleParams};
use doefab::fabrication::contrast::ContrastCurve;
use doefab::fabrication::mask::{render, MaskOptions};
use doefab::fabrication::quantize::{quantize, QuantizeMethod};
use doefab::fabrication::wrap::{wrap, WrapSpec};
use doefab::fabrication::Provenance;
use doefab::io::png::write_png_u16;
use doefab::io::raw_map::Metadata;
use doefab::{Grid, Interpolation, Result};

const LEVELS: usize = 65536;

fn peak_rss_mib() -> f64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| s.lines().find(|l| l.starts_with("VmHWM:")).map(|l| l.to_string()))
        .and_then(|l| l.split_whitespace().nth(1).and_then(|v| v.parse::<f64>().ok()))
        .map_or(f64::NAN, |kb| kb / 1024.0)
}

fn mask_png(levels: &Grid, period: f64, curve: &ContrastCurve, path: &Path) -> Result<()> {
    let opts = MaskOptions { writer_pitch: 1e-6, border: 0.0, marks: false, ..Default::default() };
    let m = render(levels, LEVELS, period, curve, &opts, &Provenance::default())?;
    write_png_u16(path, &m.gray, &Metadata::default())
}

fn main() -> Result<()> {
    let design = paper_example(&ExampleParams::default())?;
    let spec = WrapSpec::default();
    let curve = ContrastCurve::new(vec![0.0, 1.0], vec![0.0, 1.3e-6], Path::new("linear"))?;
    let dir = tempfile::tempdir().map_err(|e| doefab::Error::io(std::env::temp_dir(), e))?;
    let out = dir.path().join("mask.png");
    for run in 0..3 {
        let t = Instant::now();
        let (w, r) = wrap(&design, &spec)?;
        let q = quantize(&w, r.period, LEVELS, QuantizeMethod::Round)?;
        let t_q = t.elapsed().as_secs_f64();
        mask_png(&q.levels, r.period, &curve, &out)?;
        let chain = t.elapsed().as_secs_f64();

        let t = Instant::now();
        let fine = design.resample([1e-6, 1e-6], Interpolation::Nearest)?;
        let (w, r) = wrap(&fine, &spec)?;
        let q = quantize(&w, r.period, LEVELS, QuantizeMethod::Round)?;
        let t_fine_q = t.elapsed().as_secs_f64();
        mask_png(&q.levels, r.period, &curve, &out)?;
        let literal = t.elapsed().as_secs_f64();
        let size = std::fs::metadata(&out).map(|m| m.len()).unwrap_or(0);
        println!(
            "run {run}: chain order {chain:.2} s (wrap+quantize {t_q:.2} s); literal order on {} x {} px {literal:.2} s \
             (wrap+quantize {t_fine_q:.2} s); ratio literal/chain {:.2}; PNG {:.1} MB",
            q.levels.dim().1,
            q.levels.dim().0,
            literal / chain,
            size as f64 / 1e6
        );
    }
    println!("peak resident memory {:.0} MiB", peak_rss_mib());
    writer_grid(&design, dir.path())
}

/// `fab` on a design at the writer grid against OpenCV (module docs).
fn writer_grid(design: &Grid, dir: &Path) -> Result<()> {
    use doefab::fabrication::recipe::{Output, Recipe};
    use doefab::fabrication::recipe_run::{run_recipe, DesignSource, FabOptions};
    use doefab::io::heightmap::ReadOptions;
    let fine = design.resample([1e-6, 1e-6], Interpolation::Nearest)?;
    let npy = dir.join("design_1um.npy");
    doefab::io::npy::write_npy_f64(&npy, fine.values())?;
    let mut recipe = Recipe::read(Path::new("built-in:laser-writer-grayscale"))?;
    recipe.level_count = LEVELS;
    recipe.outputs = vec![Output::GrayscalePng];
    let read = ReadOptions { pitch: Some([1e-6; 2]), unit: Some(1.0), ..Default::default() };
    let source = DesignSource::File(npy.clone(), read);
    let period = WrapSpec::default().period()?;
    let root = std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR"));
    let script = root.join("benches/fab_opencv.py");
    let python = common::python_with("cv2");
    for run in 0..3 {
        let t = Instant::now();
        run_recipe(&source, &recipe, &dir.join("fab"), &FabOptions::default(), &mut |_| {})?;
        let ours = t.elapsed().as_secs_f64();
        let cv = python.as_ref().and_then(|py| {
            let out = std::process::Command::new(py)
                .arg(&script)
                .arg(&npy)
                .arg(dir.join("opencv.png"))
                .arg(format!("{period:e}"))
                .arg(LEVELS.to_string())
                .output()
                .ok()?;
            let text = String::from_utf8_lossy(&out.stdout).into_owned();
            text.trim().strip_prefix("opencv ")?.parse::<f64>().ok()
        });
        let n = fine.dim().0;
        match cv {
            Some(cv) => println!(
                "run {run}: fab on the {n} x {n} design at the writer grid {ours:.2} s; OpenCV wrap + quantize + \
                 imwrite {cv:.2} s; ratio fab / OpenCV {:.2}",
                ours / cv
            ),
            None => println!("run {run}: fab on the {n} x {n} design at the writer grid {ours:.2} s"),
        }
    }
    if python.is_none() {
        println!("notice: no Python with cv2 found; the OpenCV comparison is skipped");
    }
    Ok(())
}
