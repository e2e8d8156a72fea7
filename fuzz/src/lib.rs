//! What every fuzz target does with its input: decode it as a file named `name` (the extension
//! picks the reader), then carry whatever decodes through the rest of `doefab scan-info` (unit
//! resolution, levelling, height parameters). Errors are the expected outcome for almost every
//! input; the targets look for panics, hangs and huge allocations.

use std::path::Path;

use doefab::io::heightmap::{heightmap_from_raw, ReadOptions};
use doefab::io::raw_map::RawMap;
use doefab::io::scan::{decode_scan_raw, scan_from_raw, ScanOptions};
use doefab::metrology::LevelMethod;

/// Options that let a file with no pitch or unit of its own through to the later stages.
fn stated() -> ScanOptions {
    ScanOptions {
        pitch: Some([1e-6, 1e-6]),
        z_unit: Some(1e-9),
        z_scale: Some(1e-9),
        z_offset: None,
        allow_implausible: true,
    }
}

/// Decodes `data` as the scan file `name` and summarises it as `scan-info` does.
pub fn scan(name: &str, data: &[u8]) {
    let path = Path::new(name);
    for opts in [ScanOptions::default(), stated()] {
        let Ok(raw) = decode_scan_raw(path, data, &opts) else { return };
        if let Ok(scan) = scan_from_raw(path, raw, &opts) {
            let _ = doefab::metrology::summarize(path, &scan, LevelMethod::Plane);
            let _ =
                doefab::metrology::summarize(path, &scan, LevelMethod::Substrate { aperture: None });
        }
    }
}

/// Resolves a design map decoded by `decode` (pitch and unit as the file states them, then as
/// a caller would state them).
pub fn design(name: &str, decoded: doefab::Result<RawMap>) {
    let path = Path::new(name);
    let Ok(raw) = decoded else { return };
    let _ = heightmap_from_raw(path, raw.clone(), &ReadOptions::default());
    let opts = ReadOptions {
        pitch: Some([1e-6; 2]),
        unit: Some(1e-9),
        z_scale: Some(1e-9),
        allow_implausible: true,
        ..Default::default()
    };
    let _ = heightmap_from_raw(path, raw, &opts);
}

/// Parses `data` as a stylus profile export and carries what parses through `compare-profile`
/// without a design (both levellings, the terraces).
pub fn profile(data: &[u8]) {
    use doefab::io::profile::{parse_profile, ProfileReadOptions};
    use doefab::metrology::{level_profile, terraces, ProfileLevel};
    let path = Path::new("fuzz.csv");
    for opts in [ProfileReadOptions::default(), ProfileReadOptions { x_unit: Some(1e-6), z_unit: Some(1e-9) }] {
        let Ok(file) = parse_profile(path, data, &opts) else { continue };
        for method in [ProfileLevel::Line, ProfileLevel::Substrate] {
            if let Ok((levelled, _)) = level_profile(&file.profile, method) {
                let _ = terraces(&levelled);
            }
        }
    }
}
