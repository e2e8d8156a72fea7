//! The integration tests: one binary of topic modules (as ripgrep's), so the library and
//! its decoder framework are linked once. `tests/fuzz_regressions.rs` stays apart: it installs
//! a counting global allocator.

mod common;

mod calibration;
mod cli;
mod compare;
mod decoder;
mod docs;
mod exr_images;
mod gds;
mod io;
mod layering;
mod level;
mod optics;
mod optics_plan;
mod precompensate;
mod profile;
mod psf_compare;
mod python;
mod register;
mod report;
mod scan;
mod scan_bad;
mod stl;
