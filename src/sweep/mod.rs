//! The sweeps behind `doefab bench ...`: each runs the stages' public functions on known inputs
//! over a range of settings and reports speed against accuracy, or where a method fails (a
//! failure map), as typed, serialisable data (`*SweepResults`, ...). They sit above the stages
//! (no stage uses them) and below the charts ([`crate::charts`] draws their results); the
//! commands that write their files, data and charts, are [`crate::pipeline::sweep`] and
//! [`crate::pipeline::report`]. (The timings of `cargo bench` against peer tools are the
//! crate's `benches/`, not these.)
//!
//! * [`fab`]: quantization, the STL heightfield and the GDSII tracing, each against a truth
//!   computed another way (`doefab bench fab`).
//! * [`register`]: where scan registration fails (`doefab bench register`).
//! * [`psf`]: speed against accuracy of the PSF methods on a design at its geometry, with the
//!   automatic plan placed at each tolerance (`doefab bench psf`).
//! * [`stability`]: stability maps of the transfer-function methods across their guards, with
//!   the silent failures counted (`doefab bench stability`).
//! * [`spectral`]: sub-bands per colour band against error, the plan's rule scored
//!   (`doefab bench spectral`).
//! * [`calibration`]: where the measured PSF fails (`doefab bench calibration`).
//! * [`tiling`]: the decoder's output against tile, overlap and precision (`doefab bench
//!   tiling`).
//! * [`decoder`]: decoders scored on real captures against bracket-merged references, with an
//!   optional fine-tuning (`doefab bench decoder`).
//! * [`forward`]: the decoder's measurement model against the real captures (`doefab bench
//!   forward`).
//! * [`finetune_time`]: fine-tuning's validation PSNR against its time (`doefab report`).

pub mod calibration;
#[cfg(feature = "decoder")]
pub mod decoder;
pub mod fab;
#[cfg(feature = "decoder")]
pub mod finetune_time;
#[cfg(feature = "decoder")]
pub mod forward;
pub mod psf;
pub mod register;
pub mod spectral;
pub mod stability;
#[cfg(feature = "decoder")]
pub mod tiling;

/// One axis of a failure map's sweep (`bench register`, `bench calibration`): its name, unit and
/// the values tried, in that unit.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct SweepAxis {
    /// The swept quantity ("noise", "rotation", "frames", "read noise", ...): what a trial's
    /// `axis` names.
    pub name: String,
    /// The unit of `values` ("nm", "um", "deg", "count", "fraction", "% of full scale", ...).
    pub unit: String,
    /// The values tried, in `unit`, in the order swept.
    pub values: Vec<f64>,
}

impl SweepAxis {
    /// An axis named `name`, in `unit`, over `values`.
    pub fn new(name: &str, unit: &str, values: &[f64]) -> SweepAxis {
        SweepAxis { name: name.into(), unit: unit.into(), values: values.to_vec() }
    }
}
