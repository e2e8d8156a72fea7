//! File formats: one file per format, each reader producing a [`crate::grid::Grid`] with
//! its pitch and unit resolved, each writer going through [`atomic::write_atomic`].
//! Design maps enter through [`heightmap::read_heightmap`], profilometer scans through
//! [`scan::read_scan`].

pub mod atomic;
pub mod csv;
pub mod exr;
pub mod heightmap;
pub mod npy;
pub mod png;
pub mod profile;
pub mod raw_map;
pub mod scan;
pub mod tiff;

use std::path::Path;

use sha2::{Digest, Sha256};

use crate::error::{Error, Result};

/// SHA-256 of a file's bytes, hex encoded (recorded in output metadata as the source hash).
pub fn file_sha256(path: &Path) -> Result<String> {
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    Ok(hex_sha256(&bytes))
}

/// SHA-256 of bytes, hex encoded.
pub fn hex_sha256(bytes: &[u8]) -> String {
    Sha256::digest(bytes).iter().map(|b| format!("{b:02x}")).collect()
}
