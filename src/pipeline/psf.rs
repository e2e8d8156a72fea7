//! `doefab psf`: the RGB PSF of a design in the paper's camera, by the automatic plan
//! ([`crate::optics::plan`], optionally over a sensor's spectral response) or by a forced
//! method at the DOE's pitch; EXR, NPY, log-scale PNG and a JSON summary.
//!
//! In two steps, [`prepare`] then [`PsfJob::run`], so that the plan can be shown before the
//! simulation runs.

use std::path::{Path, PathBuf};

use crate::error::{Error, OptionsCause, Result};
use crate::fabrication::recipe_run::{self, DesignSource};
use crate::grid::Grid;
use crate::material::Material;
use crate::optics::plan::{self, Plan};
use crate::optics::psf::Psf;
use crate::optics::psf_files::{self, PsfOutcome};
use crate::optics::spectrum::{self, Band};
use crate::optics::system::OpticalSystem;
use crate::optics::{Method, Options};

/// The design, the optical system and how to simulate.
#[derive(Debug, Clone)]
pub struct PsfOptions {
    /// The height map (file or built-in).
    pub design: DesignSource,
    /// Force a method by name (`matrix_dft`, `fresnel`, `angular_spectrum`,
    /// `rayleigh_sommerfeld`) at the DOE's pitch; `None`: the automatic plan.
    pub method: Option<String>,
    /// Sub-samples per pixel and axis, with a forced method.
    pub subsample: usize,
    /// The plan's tolerance: relative L2 error per channel.
    pub tolerance: f64,
    /// Sensor spectral response CSV (plan only).
    pub response: Option<PathBuf>,
    /// Optical system TOML; unset fields keep the paper's values.
    pub system: Option<PathBuf>,
    /// Material of the DOE, by name.
    pub material: String,
    /// Run a forced method even where its validity conditions fail (recorded as warnings).
    pub allow_invalid: bool,
}

/// A loaded design with its optical system and the way it will be simulated.
#[derive(Debug, Clone)]
pub struct PsfJob {
    heights: Grid,
    how: How,
    /// Why the plan found no valid method, when `allow_invalid` forced one instead.
    forced_because: Option<String>,
}

#[derive(Debug, Clone)]
enum How {
    Method { system: Box<OpticalSystem>, method: Method, options: Options },
    Plan { plan: Box<Plan>, bands: Vec<Band> },
}

/// Loads the design and the optical system and, without a forced method, plans the
/// simulation. A spectral response with a forced method is refused ([`Error::Options`]).
pub fn prepare(opts: &PsfOptions) -> Result<PsfJob> {
    let loaded = recipe_run::load_design(&opts.design)?;
    let mut system = psf_files::system_for(&loaded.heights);
    system.material = Material::by_name(&opts.material)?;
    if let Some(p) = &opts.system {
        system = OpticalSystem::read_toml(p, &system)?;
    }
    let how = if let Some(method) = &opts.method {
        if opts.response.is_some() {
            let what = "`response` needs the automatic plan: leave out `method`";
            return Err(Error::options(&["response", "method"], OptionsCause::Exclusive, what));
        }
        system.subsample = opts.subsample;
        let options = Options { allow_invalid: opts.allow_invalid, ..Default::default() };
        How::Method { system: Box::new(system), method: Method::from_name(method)?, options }
    } else {
        let bands = match &opts.response {
            Some(p) => spectrum::read_response_csv(p)?,
            None => Vec::new(),
        };
        match plan::plan(&system, &loaded.heights, &bands, opts.tolerance) {
            Ok(plan) => How::Plan { plan: Box::new(plan), bands },
            // Asked to run where nothing is valid (a measured part's blurred steps are slopes
            // no pupil sampling resolves): the matrix DFT at the DOE's own samples, the plan's
            // refusal kept as a warning beside the method's violations.
            Err(Error::Validity { what: why, .. }) if opts.allow_invalid && bands.is_empty() => {
                system.subsample = opts.subsample;
                let options = Options { allow_invalid: true, ..Default::default() };
                let how = How::Method { system: Box::new(system), method: Method::MatrixDft, options };
                let forced_because =
                    Some(format!("the plan found no valid method, matrix_dft forced: {why}"));
                return Ok(PsfJob { heights: loaded.heights, how, forced_because });
            }
            Err(e) => return Err(e),
        }
    };
    Ok(PsfJob { heights: loaded.heights, how, forced_because: None })
}

impl PsfJob {
    /// The plan's choices and the condition that bounds each; `None` with a forced method.
    pub fn explain(&self) -> Option<String> {
        match &self.how {
            How::Plan { plan, .. } => Some(plan.explain()),
            How::Method { .. } => None,
        }
    }

    /// The plan's rejected cheaper pixel sub-samplings, run and measured against its own
    /// ([`plan::measure_cheaper`]); `None` with a forced method.
    pub fn measure_cheaper(&self) -> Result<Option<plan::CheaperMeasured>> {
        match &self.how {
            How::Plan { plan, bands } => Ok(Some(plan::measure_cheaper(plan, &self.heights, bands)?)),
            How::Method { .. } => Ok(None),
        }
    }

    /// Simulates and writes the outputs into the folder `output`; the report carries the
    /// warnings. Progress: one step, the planned simulation, its message saying what is being
    /// simulated (each tripling of spectral sub-bands; none with a forced method).
    pub fn run(&self, output: &Path, progress: &mut dyn FnMut(&str, u64, u64)) -> Result<PsfOutcome> {
        let (psf, mut report) = self.simulate(progress)?;
        psf_files::write_psf(&psf, &mut report, output)?;
        Ok(report)
    }

    /// [`PsfJob::run`] in memory: the PSF (each channel summing to 1, at the sensor pitch)
    /// and the report `run` would write, its `files` empty.
    pub fn simulate(&self, progress: &mut dyn FnMut(&str, u64, u64)) -> Result<(Psf, PsfOutcome)> {
        match &self.how {
            How::Method { system, method, options } => {
                let notes: Vec<String> = self.forced_because.iter().cloned().collect();
                psf_files::simulate_with_report(&self.heights, system, *method, options, &notes)
            }
            How::Plan { plan, bands } => {
                psf_files::plan_with_report(&self.heights, plan, bands, &mut |what| progress(what, 0, 1))
            }
        }
    }
}
