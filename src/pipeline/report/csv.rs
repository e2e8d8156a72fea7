//! The report's data files as CSV: one row per run of the PSF sweep (`bench_psf.csv`) and of
//! the stability maps (`stability.csv`), lengths in metres, times in seconds.

use std::fmt::Write;

use crate::sweep::psf as psf_sweep;
use crate::sweep::stability::StabilitySweepResults;

/// One row per run of the PSF sweep.
pub(super) fn psf_csv(r: &psf_sweep::PsfSweepResults) -> String {
    let mut s = String::from(
        "method,precision,padding,subsample,pupil_pitch_m,seconds,relative_l2,guard_refuses,pareto\n",
    );
    for p in &r.points {
        let _ = writeln!(
            s,
            "{},{},{},{},{:e},{:e},{:e},{},{}",
            p.method,
            p.precision,
            p.padding,
            p.subsample,
            p.pupil_pitch,
            p.seconds,
            p.error,
            p.violations.join(";"),
            p.pareto
        );
    }
    s
}

/// One row per run of the stability maps.
pub(super) fn stability_csv(r: &StabilitySweepResults) -> String {
    let mut s = String::from(
        "map,method,subsample,pupil_pitch_m,wavelength_m,focal_length_m,lens_sampling_ratio,fresnel_number,relative_l2,guard_refuses,silent\n",
    );
    for m in &r.maps {
        for c in &m.cells {
            let _ = writeln!(
                s,
                "{},{},{},{:e},{:e},{:e},{:e},{:e},{:e},{},{}",
                m.name(),
                m.method,
                c.subsample,
                c.pupil_pitch,
                c.wavelength,
                c.focal_length,
                c.lens_sampling_ratio,
                c.fresnel_number,
                c.error,
                c.violations.join(";"),
                c.silent
            );
        }
    }
    s
}
