//! Speed of the GDSII mask set: the built-in example design, wrapped and quantized to 8 levels,
//! resampled to a 5600 x 5600 map at 1 um pitch, traced and written as a GDSII file.
//!
//! Run with `cargo bench --bench gds`; prints seconds, polygons and vertices.

use std::time::Instant;

use doefab::design::{paper_example, ExampleParams};
use doefab::fabrication::gds::{write_layer_previews, write_mask_set, MaskSetOptions};
use doefab::fabrication::quantize::{quantize, QuantizeMethod};
use doefab::fabrication::wrap::{wrap, WrapSpec};
use doefab::Interpolation;

const LEVELS: usize = 8;

fn main() -> doefab::Result<()> {
    let heights = paper_example(&ExampleParams::default())?;
    let (wrapped, w) = wrap(&heights, &WrapSpec::default())?;
    let h2pi = w.period;
    let levels = quantize(&wrapped, h2pi, LEVELS, QuantizeMethod::Round)?
        .levels
        .resample([1e-6, 1e-6], Interpolation::Nearest)?;
    let (r, c) = levels.dim();
    let levels = levels.crop((r - 5600) / 2..(r - 5600) / 2 + 5600, (c - 5600) / 2..(c - 5600) / 2 + 5600)?;
    let dir = tempfile::tempdir().map_err(|e| doefab::Error::io(std::env::temp_dir(), e))?;
    let opts = MaskSetOptions::default();
    println!("map {} x {} at 1 um, {LEVELS} levels", levels.dim().0, levels.dim().1);
    for run in 0..3 {
        let t = Instant::now();
        let report = write_mask_set(&levels, LEVELS, h2pi, &opts, &dir.path().join("mask.gds"))?;
        let secs = t.elapsed().as_secs_f64();
        println!(
            "run {run}: GDSII in {secs:.2} s, {} polygons, {} vertices, {:.1} MB",
            report.polygons,
            report.vertices,
            report.bytes as f64 / 1e6
        );
        if run == 0 {
            for m in &report.masks {
                println!(
                    "  layer {}: {} polygons, {} vertices, etch {:.1} nm",
                    m.layer,
                    m.polygons,
                    m.vertices,
                    m.etch_depth * 1e9
                );
            }
        }
    }
    let t = Instant::now();
    let paths = write_layer_previews(&levels, LEVELS, &opts, dir.path(), "mask")?;
    println!("{} PNG previews in {:.2} s", paths.len(), t.elapsed().as_secs_f64());
    Ok(())
}
