//! The optics stage: the paper's camera model (Metzler et al. 2020, "Modeling the Optical Point
//! Spread Function") and the PSF of a DOE in it.
//!
//! * [`system`]: the optical system (aperture, distances, lens, sensor, wavelengths, material)
//!   and the DOE's transmission on a pupil grid.
//! * [`psf`]: the PSF type (one grid per channel), its measures, the `.npz` reader.
//! * [`propagate`]: the propagation methods, one file each, with their validity checks.
//! * [`convolve`]: images convolved with a PSF (FFT, linear), `y = h * x`.
//! * [`psf_compare`]: two PSFs compared (summary numbers, L2 after centroid alignment).
//! * [`psf_files`]: the PSF written as EXR, NPY, log-scale PNG and a JSON summary.
//! * [`plan`]: the automatic plan (method, sampling, precision, spectral samples for a
//!   tolerance).
//! * [`spectrum`]: spectral bands weighted by a sensor response.

pub mod convolve;
pub mod plan;
pub mod propagate;
pub mod psf;
pub mod psf_compare;
pub mod psf_files;
pub mod spectrum;
pub mod system;

pub use propagate::{simulate, Method, Options, Precision, Violation};
pub use psf::{Channel, Psf};
pub use system::OpticalSystem;
