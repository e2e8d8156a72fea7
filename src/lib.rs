//! doefab carries a learned diffractive optical element (DOE) from its optimized height map
//! to a fabricated part (Metzler et al., "Deep Optics for Single-shot High-dynamic-range
//! Imaging", CVPR 2020).
//!
//! Module map, in the order data flows:
//!
//! * [`grid`]: the shared physical data model, a sampled grid with pitch, origin, unit and
//!   validity mask; resampling, crop, pad, mirror, rotate; filling of non-measured samples.
//! * [`image`]: multi-channel images (`(H, W, C)`, linear), the data model of calibration and
//!   the decoder; their tone-mapped pictures.
//! * [`units`]: "550nm", "4.29 um" <-> metres at the edges.
//! * [`material`]: refractive index n(lambda) of the DOE materials.
//! * [`design`]: the built-in example designs (grating-like DOE, Fresnel lens).
//! * [`io`]: file formats and atomic writing.
//! * [`fabrication`]: wrap -> quantize -> grayscale masks, multi-level GDSII mask set, STL;
//!   the surface to command so that a measured process makes the design (pre-compensation).
//! * [`metrology`]: profilometer scans (read by [`io::scan`]): levelling, outliers,
//!   ISO 25178 height parameters.
//! * [`optics`]: the optical system and the DOE's PSF by several propagation methods.
//! * [`calibration`]: exposure brackets -> HDR merge (Debevec-Malik) -> measured PSF
//!   (`calibrate-psf`); PSNR of reconstructions against references, affine registration.
//! * [`decoder`]: the paper's U-Net decoder: weights, measurement model, reconstruction of
//!   captures, fine-tuning for a fabricated part's PSF.
//! * [`sweep`]: the sweeps behind `doefab bench ...`, one module each: speed against accuracy,
//!   and the failure maps of the methods that can fail, calling the stages' public functions
//!   (no stage uses them).
//! * [`charts`]: every chart, one file per family, with their shared style (fonts, axes, legends;
//!   the only drawing code); above the stages and the sweeps, whose results they draw.
//! * [`pipeline`]: the commands that take more than one library call (merge, calibrate-psf,
//!   psf, psf-compare, compare, precompensate, finetune, the sweeps with their files and
//!   charts), from typed options to typed results.
//! * [`demo`]: every stage on the built-in design (`doefab demo`), no input needed.
//! * [`rng`]: the seeded generator behind every stochastic step.
//! * [`linalg`]: dense linear solves (nalgebra LU) for the least-squares fits.
//! * [`fft`]: planned 1-D and 2-D FFTs (square or rectangular, `f64` or `f32`), the one plan
//!   layer below the optics and the metrology.
//! * [`tabulated`]: two-column tables with units and their monotone (PCHIP) interpolation.
//! * [`rounding`]: exact inlined `round` and `floor` for the per-sample passes.
//! * [`error`]: the library's error type, with typed causes callers match.
//!
//! Names of typed results, one meaning each:
//!
//! * `*Outcome`: what a command did, its typed result (what it prints with `--json` and writes
//!   as its JSON file), e.g. [`fabrication::recipe_run::FabOutcome`], [`demo::DemoOutcome`].
//! * `*SweepResults`: what a sweep measured, e.g. [`sweep::psf::PsfSweepResults`].
//! * `*Stats`: the numbers one step records about its run or its input (a frame, a PSF
//!   channel, a wrap), carried inside an outcome, e.g. [`calibration::hdr_merge::MergeStats`].
//! * Other results are named for what they are ([`metrology::scan_compare::LevelHeights`],
//!   [`sweep::decoder::FinetuneRun`]).
//!
//! "Report" means only the HTML page of [`pipeline::report`] (`doefab report`). "Bench" means
//! only the timings of `benches/` (`cargo bench`, against peer tools) and the command
//! `doefab bench ...`, whose sweeps are [`sweep`]'s and [`pipeline::sweep`]'s.
//!
//! A file name used in several folders names one concept at several layers, the folder saying
//! which: `fabrication/precompensate.rs` is the physics and `pipeline/precompensate.rs` the
//! command that runs it (likewise `psf`, `psf_compare`, `finetune`); `cli/X.rs`, `charts/X.rs`
//! and `sweep/X.rs` are stage or sweep X's commands, charts and measurements;
//! `grid/profile.rs`, `io/profile.rs` and `metrology/profile/` are the stylus profile's data
//! model, reader and comparison. No file is named for being shared: what several modules of a
//! folder use is named for what it is (`optics/propagate/method.rs`, `cli/options.rs`).

#![warn(missing_docs)]

pub mod calibration;
#[cfg(feature = "charts")]
pub mod charts;
#[cfg(feature = "decoder")]
pub mod decoder;
#[cfg(all(feature = "charts", feature = "decoder"))]
pub mod demo;
pub mod design;
pub mod error;
pub mod fabrication;
pub mod fft;
pub mod grid;
pub mod image;
pub mod io;
pub mod linalg;
pub mod material;
pub mod metrology;
pub mod optics;
pub mod pipeline;
pub mod rng;
pub mod rounding;
pub mod sweep;
pub mod tabulated;
pub mod units;

pub use error::{Allowed, Condition, DataCause, Error, FormatCause, OptionsCause, Refusal, Resource, Result};
pub use grid::{Grid, Interpolation, Unit};

/// The README, whose Rust blocks (its "Library use" example) run as doc tests.
#[cfg(doctest)]
#[doc = include_str!("../README.md")]
pub struct ReadmeDoctests;
