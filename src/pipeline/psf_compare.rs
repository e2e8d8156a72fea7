//! `doefab psf-compare`: two PSF files read and compared channel by channel, the comparison
//! optionally saved as JSON.

use std::path::{Path, PathBuf};

use crate::error::Result;
use crate::io::atomic;
use crate::optics::psf::Psf;
use crate::optics::psf_compare::{compare, CompareOptions, Comparison};

/// The two PSFs and how to read and measure them.
#[derive(Debug, Clone)]
pub struct PsfCompareOptions {
    /// The reference PSF file.
    pub a: PathBuf,
    /// The PSF file compared against it (moved onto its centroid).
    pub b: PathBuf,
    /// Pitch, array key and encircled-energy radius.
    pub compare: CompareOptions,
    /// Where to save the comparison as JSON.
    pub output: Option<PathBuf>,
}

/// Reads both PSFs, compares them (named by their paths) and saves the comparison where asked;
/// the comparison carries the warnings.
pub fn psf_compare(opts: &PsfCompareOptions) -> Result<Comparison> {
    let name = |p: &Path| p.display().to_string();
    let (key, pitch) = (opts.compare.key.as_deref(), opts.compare.pitch);
    let pa = Psf::read(&opts.a, key, pitch)?;
    let pb = Psf::read(&opts.b, key, pitch)?;
    let r = compare(&pa, &pb, &name(&opts.a), &name(&opts.b), &opts.compare)?;
    if let Some(out) = &opts.output {
        atomic::write_json(out, &r)?;
    }
    Ok(r)
}
