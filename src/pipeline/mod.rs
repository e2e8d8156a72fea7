//! The commands that take more than one library call, each a function from typed options to a
//! typed, serialisable result: the orchestration the command line runs, usable without it.
//!
//! Progress goes through a callback `(message, done, total)`, as in [`crate::demo::run`];
//! warnings come back in the results, for the caller to show.
//!
//! * [`merge`]: an exposure bracket and its dark frames -> HDR merge (`doefab merge`), with
//!   the tone-mapped picture and the recovered response.
//! * [`calibrate_psf`]: a pinhole bracket -> the measured PSF (`doefab calibrate-psf`).
//! * [`psf`]: the simulated PSF of a design by the automatic plan or a forced method
//!   (`doefab psf`).
//! * [`psf_compare`]: two PSF files compared (`doefab psf-compare`).
//! * [`compare`]: a part's scan against its design through the fabrication chain, metrology and
//!   optics (`doefab compare`).
//! * [`compare_profile`]: a stylus profile against its design along a line, or measured by its
//!   own terraces (`doefab compare-profile`).
//! * [`finetune`]: a decoder fine-tuned for a PSF, with its training curve (`doefab
//!   finetune`).
//! * [`precompensate`]: the next mask set corrected for the process a scan of the last part
//!   measured (`doefab precompensate`), and the loop closed in simulation.
//! * [`sweep`]: the sweeps of [`crate::sweep`] run with their defaults, their data and charts
//!   written (`doefab bench ...`).
//! * [`report`]: the sweeps of a design within one time budget, gathered into one static
//!   HTML page with its charts and data (`doefab report`).

pub mod calibrate_psf;
pub mod compare;
pub mod compare_profile;
#[cfg(all(feature = "charts", feature = "decoder"))]
pub mod finetune;
pub mod merge;
pub mod precompensate;
pub mod psf;
pub mod psf_compare;
#[cfg(all(feature = "charts", feature = "decoder"))]
pub mod report;
#[cfg(all(feature = "charts", feature = "decoder"))]
pub mod sweep;
