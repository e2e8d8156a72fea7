//! The Python module's own suite (`tests/python`, pytest) against this build's binary: each
//! function against its command on the same input, the typed exceptions, the GIL released.
//! The module is the one `tests/setup-python.sh` installed into `.venv` with `pip install .`.

use std::process::Command;

use crate::common::python;

#[test]
fn the_python_modules_suite_passes() {
    let root = env!("CARGO_MANIFEST_DIR");
    let out = Command::new(python())
        .args(["-m", "pytest", "-q", "-p", "no:cacheprovider", "tests/python"])
        .current_dir(root)
        .env("DOEFAB_BIN", env!("CARGO_BIN_EXE_doefab"))
        .output()
        .expect("python runs");
    let text = format!("{}\n{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    assert!(out.status.success(), "pytest failed (is the module installed? tests/setup-python.sh):\n{text}");
    // The suite ran tests, not none: pytest's summary names how many passed.
    assert!(text.contains(" passed"), "{text}");
}
