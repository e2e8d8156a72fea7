//! Metrology of fabricated surfaces: ISO 25178 height parameters ([`stats`]), form removal
//! ([`level`]), outlier detection ([`outliers`]), registration to the design ([`scan_registration`]) and
//! the comparison with it ([`scan_compare`]); non-measured points are filled by
//! [`crate::grid::fill`].
//!
//! Everything works on a [`crate::grid::Grid`] of heights and reads valid samples only: a
//! non-measured point (an invalid sample of the grid's mask) never enters a sum, a fit or a
//! statistic. Scans are read by [`crate::io::scan::read_scan`].

pub mod info;
pub mod level;
pub mod outliers;
pub mod profile;
pub mod scan_compare;
pub mod scan_registration;
pub mod stats;
pub mod synthetic_scan;
