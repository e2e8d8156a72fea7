//! Metrology of fabricated surfaces: ISO 25178 height parameters (`stats`), form removal
//! ([`level`]), outlier detection (`outliers`), registration to the design (`scan_registration`) and
//! the comparison with it (`scan_compare`); non-measured points are filled by
//! [`crate::grid::fill`].
//!
//! Everything works on a [`crate::grid::Grid`] of heights and reads valid samples only: a
//! non-measured point (an invalid sample of the grid's mask) never enters a sum, a fit or a
//! statistic. Scans are read by [`crate::io::scan::read_scan`].

pub(crate) mod info;
pub(crate) mod level;
pub(crate) mod outliers;
pub(crate) mod profile;
pub(crate) mod scan_compare;
pub(crate) mod scan_registration;
pub(crate) mod stats;
pub(crate) mod synthetic_scan;

pub use info::{scan_info, summarize, ScanInfo};
pub use level::{level, level_plane, subtract_mean, LevelMethod, Plane};
pub use outliers::{median_outliers, nsigma_outliers, without_outliers, Outliers};
pub use profile::{
    level_profile, simulate_profile, terraces, LineSpec, Profile, ProfileLevel, ProfileOptions,
    SimulateProfile, Terrace,
};
pub use scan_compare::{
    compare, compare_family, Candidate, CompareOptions, Comparison, EfficiencyLoss, FabModel, LevelHeights,
    LevelSpec, LevelStat, Member, Reference,
};
pub use scan_registration::{register, Pose, RegisterOptions, Registration};
pub use stats::{height_params, HeightParams};
pub use synthetic_scan::{
    parse_length_pair, parse_size, parse_slopes, simulate_scan, write_scan, SimulateParams,
};
