//! Data flows one way, design to decoder: no stage module names a later stage, and the shared
//! modules below the stages (grid, io, image, ...) name none. Above the stages sit the
//! benchmarks (`bench`, which call the stages), then the charts (`charts`, which draw the
//! stages' results and the benchmarks' reports: `plotters` is named nowhere else), then the
//! commands (`pipeline`, `demo`), which run them and write their files. Read from the source,
//! so a new `use` that closes a cycle fails here with the file and the line.

use std::fs;
use std::path::{Path, PathBuf};

/// The stages in the order data flows through them.
const STAGES: [&str; 6] = ["design", "fabrication", "metrology", "optics", "calibration", "decoder"];
/// Modules every stage may use; they use no stage (nor the layers above the stages).
const SHARED: [&str; 10] =
    ["error", "grid", "units", "material", "table", "rng", "linalg", "io", "image", "float"];
/// The layers above the stages, lowest first: each names none above it.
const ABOVE: [&str; 4] = ["bench", "charts", "pipeline", "demo"];

/// The `.rs` files of module `name`: `src/name.rs` and everything below `src/name/`.
fn sources(name: &str) -> Vec<PathBuf> {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let mut files = vec![];
    let file = src.join(format!("{name}.rs"));
    if file.is_file() {
        files.push(file);
    }
    let mut dirs = vec![src.join(name)];
    while let Some(d) = dirs.pop() {
        let Ok(entries) = fs::read_dir(&d) else { continue };
        for e in entries.flatten() {
            let p = e.path();
            if p.is_dir() {
                dirs.push(p);
            } else if p.extension().is_some_and(|x| x == "rs") {
                files.push(p);
            }
        }
    }
    assert!(!files.is_empty(), "module {name} has no source under src/");
    files
}

/// Whether `line` names the module `crate::<module>` (not a longer name that starts so).
fn names(line: &str, module: &str) -> bool {
    let needle = format!("crate::{module}");
    line.match_indices(&needle).any(|(at, _)| {
        let next = line[at + needle.len()..].chars().next();
        !next.is_some_and(|c| c.is_alphanumeric() || c == '_')
    })
}

/// Lines of `name`'s sources that name `crate::<other>` for any of `others` (comments, where docs
/// link to the layers above, left out).
fn imports(name: &str, others: &[&str]) -> Vec<String> {
    let mut found = vec![];
    for file in sources(name) {
        let text = fs::read_to_string(&file).unwrap();
        for (i, line) in text.lines().enumerate() {
            if !line.trim_start().starts_with("//") && others.iter().any(|other| names(line, other)) {
                found.push(format!("{}:{}: {}", file.display(), i + 1, line.trim()));
            }
        }
    }
    found
}

#[test]
fn no_module_imports_a_later_one() {
    let mut wrong = vec![];
    for (k, stage) in STAGES.iter().enumerate() {
        let later: Vec<&str> = STAGES[k + 1..].iter().chain(&ABOVE).copied().collect();
        wrong.extend(imports(stage, &later));
    }
    for (k, layer) in ABOVE.iter().enumerate() {
        wrong.extend(imports(layer, &ABOVE[k + 1..]));
    }
    let above: Vec<&str> = STAGES.iter().chain(&ABOVE).copied().collect();
    for shared in SHARED {
        wrong.extend(imports(shared, &above));
    }
    assert!(wrong.is_empty(), "imports against the flow:\n{}", wrong.join("\n"));
}

/// `plotters` is named in the charts and nowhere else in the sources.
#[test]
fn only_the_charts_draw() {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let (mut drawing, mut dirs) = (vec![], vec![src.clone()]);
    while let Some(d) = dirs.pop() {
        for p in fs::read_dir(&d).unwrap().flatten().map(|e| e.path()) {
            if p.is_dir() {
                dirs.push(p);
            } else if !p.starts_with(src.join("charts"))
                && fs::read_to_string(&p).unwrap().contains("plotters")
            {
                drawing.push(p.display().to_string());
            }
        }
    }
    assert!(drawing.is_empty(), "plotters named outside src/charts: {drawing:?}");
    assert!(fs::read_to_string(src.join("charts/style.rs")).unwrap().contains("plotters"));
}

#[test]
fn the_check_sees_an_import_and_not_a_longer_name() {
    // `calibration` names `optics` (earlier: allowed) and so must be seen by the scan.
    assert!(!imports("calibration", &["optics"]).is_empty());
    assert!(names("use crate::io::atomic;", "io") && names("crate::decoder}", "decoder"));
    assert!(!names("use crate::iox::a;", "io") && !names("use crate::decoders;", "decoder"));
}
