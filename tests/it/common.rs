//! Shared helpers for the integration tests.
#![allow(dead_code)]

use std::path::{Path, PathBuf};
use std::process::Command;

use doefab::{Error, FormatCause};

/// The Python interpreter that holds the independent checkers (KLayout's `klayout`, `trimesh`,
/// `numpy`): `$DOEFAB_PYTHON`, else `.venv/bin/python` made by `tests/setup-python.sh`.
pub fn python() -> PathBuf {
    if let Ok(p) = std::env::var("DOEFAB_PYTHON") {
        return PathBuf::from(p);
    }
    let p = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join(".venv/bin/python");
    assert!(p.exists(), "{} is missing: run tests/setup-python.sh first (see README)", p.display());
    p
}

/// Runs a Python script with arguments; returns its standard output, panicking with its
/// standard error if it fails.
pub fn run_python(script: &str, args: &[&str]) -> String {
    let out = Command::new(python()).arg("-c").arg(script).args(args).output().expect("python runs");
    assert!(
        out.status.success(),
        "python failed:\n{}\n{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8_lossy(&out.stdout).into_owned()
}

/// A fresh temporary directory for one test.
pub fn tempdir() -> tempfile::TempDir {
    tempfile::tempdir().expect("temp dir")
}

/// Runs the `doefab` binary with `args`.
pub fn doefab(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_doefab")).args(args).output().expect("doefab runs")
}

/// Runs `doefab` expecting success; returns stdout.
pub fn ok(args: &[&str]) -> String {
    let out = doefab(args);
    assert!(out.status.success(), "doefab {args:?} failed:\n{}", String::from_utf8_lossy(&out.stderr));
    String::from_utf8_lossy(&out.stdout).into_owned()
}

/// Runs `doefab` expecting a non-zero exit; returns stderr.
pub fn fails(args: &[&str]) -> String {
    let out = doefab(args);
    assert!(!out.status.success(), "doefab {args:?} should have failed");
    String::from_utf8_lossy(&out.stderr).into_owned()
}

/// `<shared>/data/<rel>`, where `<shared>` is `$DOEFAB_SHARED` or the `shared` folder beside
/// the checkout. A test that needs it fails when it is missing, saying where it was expected:
/// nothing is skipped in silence.
pub fn shared_data(rel: &str) -> PathBuf {
    let root = std::env::var_os("DOEFAB_SHARED")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared"));
    let p = root.join("data").join(rel);
    assert!(
        p.exists(),
        "{} is missing: this test reads the shared data set, expected in a folder `shared` beside \
         the checkout (or where $DOEFAB_SHARED points)",
        p.display()
    );
    p
}

/// The cause, byte offset and file of an [`Error::Format`]; panics naming any other error.
pub fn format_cause(e: &Error) -> (FormatCause, Option<u64>, &Path) {
    match e {
        Error::Format { cause, offset, path, .. } => (*cause, *offset, path),
        other => panic!("expected a format error, got {other:?}"),
    }
}
