//! What the benchmarks share: the Python that runs a reference implementation in the same run.

use std::path::Path;
use std::process::Command;

/// The first Python that imports `module`, tried in order: `$DOEFAB_PYTHON`, the checkout's
/// `.venv/bin/python`, `python3`. `None` when none does (the comparison is then skipped).
pub fn python_with(module: &str) -> Option<String> {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    [
        std::env::var("DOEFAB_PYTHON").ok(),
        Some(root.join(".venv/bin/python").display().to_string()),
        Some("python3".into()),
    ]
    .into_iter()
    .flatten()
    .find(|p| {
        Command::new(p).args(["-c", &format!("import {module}")]).output().is_ok_and(|o| o.status.success())
    })
}
