//! Speed of the grayscale path on the paper's DOE at a 1 um writer grid (5600 x 5600 pattern,
//! 31 Mpx): wrap + quantize + 16-bit PNG, as the chain runs it (wrap and quantize on the
//! 1306 x 1306 design grid, then resample the levels to the writer grid) and, as reference in
//! the same process, the literal order (resample the heights first, wrap and quantize all
//! 31 Mpx). Prints seconds, the ratio, and the peak resident memory.
//!
//! Run with `cargo bench --bench fab`.

use std::path::Path;
use std::time::Instant;

use doefab::design::{paper_example, ExampleParams};
use doefab::fabrication::contrast::ContrastCurve;
use doefab::fabrication::mask::{render, MaskOptions};
use doefab::fabrication::quantize::{quantize, QuantizeMethod};
use doefab::fabrication::wrap::{wrap, WrapSpec};
use doefab::fabrication::Provenance;
use doefab::io::heightmap::Metadata;
use doefab::io::png::write_png_u16;
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
    Ok(())
}
