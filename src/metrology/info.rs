//! What `doefab scan-info` reports: a scan's geometry, validity, warnings and ISO 25178 height
//! parameters, raw and after levelling (least-squares plane unless another method is asked for).

use std::fmt::Write as _;
use std::path::Path;

use serde::Serialize;

use crate::error::Result;
use crate::io::scan::{read_scan, Scan, ScanFormat, ScanOptions};
use crate::metrology::level::{level, LevelMethod, Levelling};
use crate::metrology::stats::{height_params, HeightParams};
use crate::units::format_length;

/// A summary of one scan.
#[derive(Debug, Clone, Serialize)]
pub struct ScanInfo {
    /// The scan file.
    pub file: String,
    /// The file format it was read as.
    pub format: ScanFormat,
    /// `[columns, rows]`.
    pub size: [usize; 2],
    /// `[x, y]` pitch, metres.
    pub pitch: [f64; 2],
    /// `[x, y]` position of sample (0, 0), metres.
    pub origin: [f64; 2],
    /// Unit of the heights (always "m").
    pub z_unit: String,
    /// Measured (valid) samples.
    pub valid: usize,
    /// `valid` over all samples, 0..1.
    pub valid_fraction: f64,
    /// Problems of the read that did not stop it (checksum mismatch, odd header values).
    pub warnings: Vec<String>,
    /// Height parameters of the scan as read (reference: the mean).
    pub raw: HeightParams,
    /// The levelling applied: method, plane removed (per pixel) and what it was fitted on.
    pub levelling: Levelling,
    /// Height parameters after subtracting that plane.
    pub levelled: HeightParams,
    /// The file's own key/values.
    pub metadata: Vec<(String, String)>,
}

/// Summarises a scan already read from `path`, levelled by `method`.
pub fn summarize(path: &Path, scan: &Scan, method: LevelMethod) -> Result<ScanInfo> {
    let g = &scan.grid;
    let (rows, cols) = g.dim();
    let raw = height_params(g)?;
    let (lev, levelling) = level(g, method)?;
    let levelled = height_params(&lev)?;
    Ok(ScanInfo {
        file: path.display().to_string(),
        format: scan.format,
        size: [cols, rows],
        pitch: g.pitch(),
        origin: g.origin(),
        z_unit: g.unit().symbol().to_string(),
        valid: g.valid_count(),
        valid_fraction: g.valid_count() as f64 / (rows * cols) as f64,
        warnings: scan.warnings.clone(),
        raw,
        levelling,
        levelled,
        metadata: scan.metadata.clone(),
    })
}

/// Reads and summarises a scan.
pub fn scan_info(path: &Path, opts: &ScanOptions, method: LevelMethod) -> Result<ScanInfo> {
    let scan = read_scan(path, opts)?;
    summarize(path, &scan, method)
}

impl ScanInfo {
    /// The human-readable report (several lines, ending with a newline); the warnings are not
    /// part of it (the command line prints them on standard error).
    pub fn summary(&self) -> String {
        let mut s = String::new();
        let nm = |v: f64| format!("{:.3} nm", v * 1e9);
        let _ = writeln!(s, "{} ({})", self.file, self.format.name());
        let _ = writeln!(
            s,
            "  size {} x {} samples, pitch {} x {}, extent {} x {}",
            self.size[0],
            self.size[1],
            format_length(self.pitch[0]),
            format_length(self.pitch[1]),
            format_length(self.pitch[0] * self.size[0] as f64),
            format_length(self.pitch[1] * self.size[1] as f64)
        );
        let _ = writeln!(
            s,
            "  heights in {}, valid {} of {} ({:.2}%)",
            self.z_unit,
            self.valid,
            self.size[0] * self.size[1],
            100.0 * self.valid_fraction
        );
        let l = &self.levelling;
        let how = match l.method {
            LevelMethod::Plane => "least-squares plane".to_string(),
            LevelMethod::Facet => format!("facet levelling, {} iterations", l.iterations.unwrap_or(0)),
            LevelMethod::Substrate { aperture: Some(d) } => {
                format!("substrate outside a {} aperture, {} points", format_length(d), l.fitted_points)
            }
            LevelMethod::Substrate { aperture: None } => format!("lowest level, {} points", l.fitted_points),
        };
        let _ = writeln!(
            s,
            "  plane ({how}): a = {}, bx = {} / px, by = {} / px",
            nm(l.plane.a),
            nm(l.plane.bx),
            nm(l.plane.by)
        );
        if let Some(low) = l.lowest_level {
            let _ =
                writeln!(s, "  substrate spread {}, next level at {}", nm(low.spread), nm(low.next_level));
        }
        let _ = writeln!(s, "  {:<10} {:>14} {:>14}", "", "raw", "levelled");
        let rows: [(&str, f64, f64, bool); 7] = [
            ("Sa", self.raw.sa, self.levelled.sa, true),
            ("Sq", self.raw.sq, self.levelled.sq, true),
            ("Sp", self.raw.sp, self.levelled.sp, true),
            ("Sv", self.raw.sv, self.levelled.sv, true),
            ("Sz", self.raw.sz, self.levelled.sz, true),
            ("Ssk", self.raw.ssk, self.levelled.ssk, false),
            ("Sku", self.raw.sku, self.levelled.sku, false),
        ];
        for (name, a, b, len) in rows {
            if len {
                let _ = writeln!(s, "  {name:<10} {:>14} {:>14}", nm(a), nm(b));
            } else {
                let _ = writeln!(s, "  {name:<10} {a:>14.6} {b:>14.6}");
            }
        }
        let opt = |v: Option<f64>, f: &dyn Fn(f64) -> String| v.map_or("-".to_string(), f);
        let _ = writeln!(
            s,
            "  {:<10} {:>14} {:>14}",
            "Sdq",
            opt(self.raw.sdq, &|v| format!("{v:.6}")),
            opt(self.levelled.sdq, &|v| format!("{v:.6}"))
        );
        let _ = writeln!(
            s,
            "  {:<10} {:>14} {:>14}",
            "Sdr",
            opt(self.raw.sdr, &|v| format!("{:.6}%", v * 100.0)),
            opt(self.levelled.sdr, &|v| format!("{:.6}%", v * 100.0))
        );
        s
    }
}
