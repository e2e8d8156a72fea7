//! The fabrication stage: height map -> phase wrapping -> quantization -> grayscale
//! lithography masks, multi-level binary GDSII mask set, STL.
//!
//! * [`wrap`]: phase wrapping modulo p 2 pi and the replica (master) inversion;
//! * [`quantize`]: N-level quantization, predicted efficiencies, zone-period check;
//! * [`contrast`]: resist contrast curves, monotone and invertible;
//! * [`mask`]: grayscale lithography masks with frame, crosses and label ([`marks`]);
//! * [`gds`]: the multi-level binary mask set as GDSII, polygons from [`trace`];
//! * [`stl`]: watertight STL of the surface, exact terraces or an error-bounded height field;
//! * [`recipe`]: process recipes ([`built_in`]: those of `masks/`, compiled in); [`recipe_run`]: the
//!   whole chain behind `doefab fab`.

pub mod built_in;
pub mod contrast;
pub mod gds;
pub mod marks;
pub mod mask;
pub mod precompensate;
pub mod quantize;
pub mod recipe;
pub mod recipe_run;
pub mod stl;
pub mod trace;
pub mod wrap;

use serde::{Deserialize, Serialize};

/// Whether outputs describe the design itself or the master whose PDMS cast is the design.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[cfg_attr(feature = "cli", derive(clap::ValueEnum))]
#[serde(rename_all = "snake_case")]
pub enum ReplicaMode {
    /// Outputs are the design surface as given.
    #[default]
    Design,
    /// Outputs are the master: complemented and mirrored, so that its cast equals the design.
    Master,
}

impl ReplicaMode {
    /// The part the outputs show, as written into an STL header.
    pub fn part_name(self) -> &'static str {
        match self {
            ReplicaMode::Design => "design",
            ReplicaMode::Master => "master",
        }
    }
}

/// Where an output came from; written into every output's metadata.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq, Default)]
pub struct Provenance {
    /// The design file, or `built-in:<name>`.
    pub design: String,
    /// SHA-256 of the design file's bytes (or of the built-in design's parameters).
    pub design_sha256: String,
    /// Whether the outputs show the design itself or the master that casts it.
    pub replica_mode: ReplicaMode,
    /// Design wavelength, metres.
    pub wavelength_m: f64,
    /// Name of the DOE material (`pdms`, ...).
    pub material: String,
    /// Multi-order factor p.
    pub order: u32,
    /// Wrap period p * h_2pi, metres.
    pub period_m: f64,
    /// Number of height levels the period is quantized to.
    pub level_count: usize,
    /// The quantization method, by its Rust name (`Round`, `FloydSteinberg`).
    pub quantization: String,
    /// Version of doefab that wrote the output.
    pub doefab_version: String,
}
