//! The process recipes and the contrast curve of `masks/`, compiled into the binary so that an
//! installed `doefab` needs no source tree beside it: `built-in:NAME` names one of them
//! wherever a recipe or curve path is taken.

use std::path::Path;

use crate::error::{Error, Result};

/// Prefix of a path that names a file bundled into the binary.
pub const BUILT_IN: &str = "built-in:";

/// The files of `masks/`, compiled in: `(file name, text)`.
pub const BUNDLED: &[(&str, &str)] = &[
    ("laser-writer-grayscale.toml", include_str!("../../masks/laser-writer-grayscale.toml")),
    ("binary-3mask-8level.toml", include_str!("../../masks/binary-3mask-8level.toml")),
    ("two-photon-stl.toml", include_str!("../../masks/two-photon-stl.toml")),
    ("positive-resist-contrast.csv", include_str!("../../masks/positive-resist-contrast.csv")),
];

/// The text of the file `path` names: a bundled file for `built-in:NAME` (`NAME` with or
/// without its extension `ext`), else the file on disk.
pub fn read_text(path: &Path, ext: &str) -> Result<String> {
    let Some(name) = path.to_str().and_then(|p| p.strip_prefix(BUILT_IN)) else {
        return std::fs::read_to_string(path).map_err(|e| Error::io(path, e));
    };
    let with_ext = if name.ends_with(ext) { name.to_string() } else { format!("{name}{ext}") };
    BUNDLED.iter().find(|(n, _)| *n == with_ext).map(|(_, t)| t.to_string()).ok_or_else(|| {
        let names: Vec<_> = BUNDLED
            .iter()
            .filter(|(n, _)| n.ends_with(ext))
            .map(|(n, _)| format!("{BUILT_IN}{}", n.trim_end_matches(ext)))
            .collect();
        Error::signature(path, format!("no bundled file of that name; bundled: {}", names.join(", ")))
    })
}
