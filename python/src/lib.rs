//! The native part of the Python module `doefab` (`doefab._doefab`): argument conversion
//! around the library's typed options and results, and nothing else. Every result that the
//! command line prints with `--json` crosses as that JSON text (the one serialisation), which
//! `doefab/__init__.py` turns into a dict; arrays cross as numpy arrays. Long calls release
//! the GIL; a progress callable is called back with it held.

use std::path::PathBuf;

use numpy::{PyArray2, PyArray3, PyArrayMethods, PyReadonlyArray2, PyReadonlyArray3, PyUntypedArrayMethods};
use pyo3::prelude::*;

mod errors;

use errors::{to_py, OrPy};

/// A sampled surface: heights in metres on a regular grid with its pitch, and which samples
/// were measured. Made from an array (`Grid(values, pitch)`) or read from a file
/// (`read_heightmap`, `read_scan`); a grid read from a file remembers it, so that what is made
/// of it records the file's name and SHA-256 as the command line does.
#[pyclass(module = "doefab._doefab", frozen)]
pub struct Grid {
    grid: doefab::Grid,
    file: Option<FileOrigin>,
}

/// The file a grid was read from, and how.
#[derive(Clone)]
enum FileOrigin {
    Design(PathBuf, doefab::io::heightmap::ReadOptions),
    Scan(PathBuf, doefab::io::scan::ScanOptions),
}

#[pymethods]
impl Grid {
    /// `Grid(values, pitch, valid=None, pitch_y=None)`: heights in metres ((H, W) float64),
    /// the sample pitch in metres along x (and along y when it differs), and the measured
    /// samples ((H, W) bool; NaN values are unmeasured either way).
    #[new]
    #[pyo3(signature = (values, pitch, valid=None, pitch_y=None))]
    fn new(
        values: PyReadonlyArray2<'_, f64>,
        pitch: f64,
        valid: Option<PyReadonlyArray2<'_, bool>>,
        pitch_y: Option<f64>,
    ) -> PyResult<Self> {
        let values = values.as_array().to_owned();
        let pitch = [pitch, pitch_y.unwrap_or(pitch)];
        let mut grid = doefab::Grid::from_values_nan_invalid(values, pitch, doefab::Unit::Metre).or_py()?;
        if let Some(valid) = valid {
            let mut mask = valid.as_array().to_owned();
            if let Some(nan) = grid.mask() {
                mask.zip_mut_with(nan, |m, &n| *m &= n);
            }
            grid = grid.with_mask(mask).or_py()?;
        }
        Ok(Grid { grid, file: None })
    }

    /// Heights in metres, (H, W) float64; unmeasured samples are NaN.
    #[getter]
    fn values<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray2<f64>> {
        PyArray2::from_owned_array(py, self.grid.values_nan_invalid())
    }

    /// Which samples were measured, (H, W) bool.
    #[getter]
    fn valid<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray2<bool>> {
        let (rows, cols) = self.grid.dim();
        let mask = match self.grid.mask() {
            Some(m) => m.clone(),
            None => ndarray::Array2::from_elem((rows, cols), true),
        };
        PyArray2::from_owned_array(py, mask)
    }

    /// The sample pitch along x, metres.
    #[getter]
    fn pitch(&self) -> f64 {
        self.grid.pitch()[0]
    }

    /// The sample pitch `(x, y)`, metres.
    #[getter]
    fn pitch_xy(&self) -> (f64, f64) {
        let [x, y] = self.grid.pitch();
        (x, y)
    }

    /// `(rows, columns)`.
    #[getter]
    fn shape(&self) -> (usize, usize) {
        self.grid.dim()
    }

    /// The file the grid was read from, or None for a grid made from an array.
    #[getter]
    fn path(&self) -> Option<String> {
        match &self.file {
            Some(FileOrigin::Design(p, _) | FileOrigin::Scan(p, _)) => Some(p.display().to_string()),
            None => None,
        }
    }

    fn __repr__(&self) -> String {
        let (rows, cols) = self.grid.dim();
        let [px, py] = self.grid.pitch();
        let from = self.path().map(|p| format!(", from {p}")).unwrap_or_default();
        format!("Grid({rows} x {cols}, pitch {:.4} x {:.4} um{from})", px * 1e6, py * 1e6)
    }

    /// Pickles as its values, pitch and valid samples (the file it came from is not kept).
    fn __reduce__<'py>(slf: &Bound<'py, Self>) -> PyResult<(Bound<'py, PyAny>, Bound<'py, PyAny>)> {
        let py = slf.py();
        let this = slf.get();
        let [px, pyy] = this.grid.pitch();
        let args = (this.values(py), px, this.valid(py), pyy).into_pyobject(py)?.into_any();
        Ok((py.get_type::<Grid>().into_any(), args))
    }
}

impl Grid {
    fn design_source(&self) -> doefab::fabrication::recipe_run::DesignSource {
        use doefab::fabrication::recipe_run::DesignSource;
        match &self.file {
            Some(FileOrigin::Design(p, o)) => DesignSource::File(p.clone(), o.clone()),
            _ => DesignSource::Heights(self.grid.clone()),
        }
    }

    fn scan_source(&self) -> doefab::pipeline::compare::ScanSource {
        use doefab::pipeline::compare::ScanSource;
        match &self.file {
            Some(FileOrigin::Scan(p, o)) => ScanSource::File(p.clone(), o.clone()),
            _ => ScanSource::Heights(self.grid.clone()),
        }
    }
}

/// A design given to a function: a Grid, a path, or `built-in:NAME`.
fn design_of(design: &Bound<'_, PyAny>) -> PyResult<doefab::fabrication::recipe_run::DesignSource> {
    use doefab::fabrication::recipe_run::DesignSource;
    if let Ok(g) = design.cast::<Grid>() {
        return Ok(g.get().design_source());
    }
    let text: PathBuf = design.extract()?;
    let text = text.to_string_lossy().into_owned();
    Ok(DesignSource::parse(Some(&text), Default::default()))
}

/// Runs `f` without the GIL, handing it a progress callback that calls `progress`
/// (`progress(message, done, total)`) with the GIL held, when one is given.
fn detached<T: Send>(
    py: Python<'_>,
    progress: Option<Py<PyAny>>,
    f: impl FnOnce(&mut dyn FnMut(&str, u64, u64)) -> doefab::Result<T> + Send,
) -> PyResult<T> {
    let mut failed: Option<PyErr> = None;
    let result = py.detach(|| {
        let mut report = |what: &str, done: u64, total: u64| {
            if let (Some(cb), None) = (&progress, &failed) {
                Python::attach(|py| {
                    if let Err(e) = cb.call1(py, (what, done, total)) {
                        failed = Some(e);
                    }
                });
            }
        };
        f(&mut report)
    });
    if let Some(e) = failed {
        return Err(e);
    }
    result.or_py()
}

fn to_json<T: serde::Serialize>(value: &T) -> PyResult<String> {
    serde_json::to_string(value).map_err(|e| to_py(doefab::Error::internal(e.to_string())))
}

/// `read_heightmap(path, pitch=None, unit=None, z_scale=None, z_offset=None, channel=None,
/// allow_implausible=False)`: a design height map (.npy, .exr, .tif, .png, .csv) as a Grid in
/// metres; `pitch` metres (for files that state none), `unit` metres per stored value
/// (floats), `z_scale` metres per count (integer images), `z_offset` metres.
#[pyfunction]
#[pyo3(signature = (path, pitch=None, unit=None, z_scale=None, z_offset=None, channel=None, allow_implausible=false))]
#[allow(clippy::too_many_arguments)]
fn read_heightmap(
    py: Python<'_>,
    path: PathBuf,
    pitch: Option<f64>,
    unit: Option<f64>,
    z_scale: Option<f64>,
    z_offset: Option<f64>,
    channel: Option<String>,
    allow_implausible: bool,
) -> PyResult<Grid> {
    let read = doefab::io::heightmap::ReadOptions {
        pitch: pitch.map(|p| [p, p]),
        unit,
        z_scale,
        z_offset,
        channel,
        allow_implausible,
    };
    let source = doefab::fabrication::recipe_run::DesignSource::File(path.clone(), read.clone());
    let loaded = py.detach(|| doefab::fabrication::recipe_run::load_design(&source)).or_py()?;
    Ok(Grid { grid: loaded.heights, file: Some(FileOrigin::Design(path, read)) })
}

/// `read_scan(path, pitch=None, z_unit=None, z_scale=None, z_offset=None,
/// allow_implausible=False)`: a profilometer scan (every format of `doefab scan-info`) as a
/// Grid in metres, unmeasured points invalid.
#[pyfunction]
#[pyo3(signature = (path, pitch=None, z_unit=None, z_scale=None, z_offset=None, allow_implausible=false))]
fn read_scan(
    py: Python<'_>,
    path: PathBuf,
    pitch: Option<f64>,
    z_unit: Option<f64>,
    z_scale: Option<f64>,
    z_offset: Option<f64>,
    allow_implausible: bool,
) -> PyResult<Grid> {
    let opts = doefab::io::scan::ScanOptions {
        pitch: pitch.map(|p| [p, p]),
        z_unit,
        z_scale,
        z_offset,
        allow_implausible,
    };
    let scan = py.detach(|| doefab::io::scan::read_scan(&path, &opts)).or_py()?;
    Ok(Grid { grid: scan.grid, file: Some(FileOrigin::Scan(path, opts)) })
}

/// `psf(design, tolerance, method, subsample, response, system, material, allow_invalid, out,
/// progress)`: the RGB PSF as `((H, W, 3) float64, pitch in metres, wavelengths in metres,
/// report JSON)`; with `out`, the files `doefab psf` writes too.
#[pyfunction]
#[pyo3(signature = (design, tolerance, method, subsample, response, system, material, allow_invalid, out, progress))]
#[allow(clippy::too_many_arguments, clippy::type_complexity)]
fn psf<'py>(
    py: Python<'py>,
    design: &Bound<'py, PyAny>,
    tolerance: f64,
    method: Option<String>,
    subsample: usize,
    response: Option<PathBuf>,
    system: Option<PathBuf>,
    material: String,
    allow_invalid: bool,
    out: Option<PathBuf>,
    progress: Option<Py<PyAny>>,
) -> PyResult<(Bound<'py, PyArray3<f64>>, f64, Vec<Option<f64>>, String)> {
    use doefab::pipeline::psf as pipeline;
    let opts = pipeline::PsfOptions {
        design: design_of(design)?,
        method,
        subsample,
        tolerance,
        response,
        system,
        material,
        allow_invalid,
    };
    let (psf, report) = detached(py, progress, |report| {
        let job = pipeline::prepare(&opts)?;
        let (psf, mut outcome) = job.simulate(report)?;
        if let Some(out) = &out {
            doefab::optics::psf_files::write_psf(&psf, &mut outcome, out)?;
        }
        Ok((psf, outcome))
    })?;
    let (rows, cols) = psf.dim();
    let mut values = ndarray::Array3::<f64>::zeros((rows, cols, psf.channels.len()));
    for (c, channel) in psf.channels.iter().enumerate() {
        values.index_axis_mut(ndarray::Axis(2), c).assign(channel.grid.values());
    }
    let pitch = psf.pitch()[0];
    let wavelengths = psf.channels.iter().map(|c| c.wavelength).collect();
    Ok((PyArray3::from_owned_array(py, values), pitch, wavelengths, to_json(&report)?))
}

/// `fab(design, recipe, out, levels, fill, force, intermediates, progress)`: the whole
/// fabrication chain into the folder `out`; `doefab fab --json`'s JSON.
#[pyfunction]
#[pyo3(signature = (design, recipe, out, levels, fill, force, intermediates, progress))]
#[allow(clippy::too_many_arguments)]
fn fab(
    py: Python<'_>,
    design: &Bound<'_, PyAny>,
    recipe: PathBuf,
    out: PathBuf,
    levels: Option<usize>,
    fill: bool,
    force: bool,
    intermediates: bool,
    progress: Option<Py<PyAny>>,
) -> PyResult<String> {
    use doefab::fabrication::recipe::Recipe;
    use doefab::fabrication::recipe_run::{run_recipe, step_count, FabOptions};
    let source = design_of(design)?;
    let opts = FabOptions { fill, force, intermediates };
    let outcome = detached(py, progress, |report| {
        let mut recipe = Recipe::read(&recipe)?;
        if let Some(n) = levels {
            recipe.level_count = n;
        }
        let total = step_count(&recipe) as u64;
        let mut done = 0;
        run_recipe(&source, &recipe, &out, &opts, &mut |step| {
            done += 1;
            report(step, done, total)
        })
    })?;
    to_json(&outcome)
}

/// `compare(design, scan, out, recipe, levels, wavelength, material, order, aperture,
/// psf_method, allow_invalid, progress)`: a scan against its design into the folder `out`;
/// `doefab compare --json`'s JSON.
#[pyfunction]
#[pyo3(signature = (design, scan, out, recipe, levels, wavelength, material, order, aperture, psf_method, allow_invalid, progress))]
#[allow(clippy::too_many_arguments)]
fn compare(
    py: Python<'_>,
    design: &Bound<'_, PyAny>,
    scan: &Bound<'_, PyAny>,
    out: PathBuf,
    recipe: Option<PathBuf>,
    levels: Option<usize>,
    wavelength: f64,
    material: String,
    order: u32,
    aperture: Option<f64>,
    psf_method: String,
    allow_invalid: bool,
    progress: Option<Py<PyAny>>,
) -> PyResult<String> {
    use doefab::pipeline::compare::{compare_scan, comparison_chain, ScanSource};
    let design = design_of(design)?;
    let scan = match scan.cast::<Grid>() {
        Ok(g) => g.get().scan_source(),
        Err(_) => ScanSource::File(scan.extract()?, Default::default()),
    };
    let outcome = detached(py, progress, |report| {
        let chain = comparison_chain(recipe.as_deref(), levels, wavelength, &material, order)?;
        let psf =
            (psf_method != "none").then(|| doefab::optics::Method::from_name(&psf_method)).transpose()?;
        let psf_opts = doefab::optics::Options { allow_invalid, ..Default::default() };
        let mut done = 0;
        let total = if psf.is_some() { 4 } else { 3 };
        compare_scan(&scan, &design, chain.as_ref(), aperture, psf.map(|m| (m, &psf_opts)), &out, &mut |s| {
            done += 1;
            report(s, done, total)
        })
    })?;
    to_json(&outcome)
}

/// A PSF given to `psf_compare`: a file (.npy with psf.json, .exr, .npz), or
/// `(values (H, W, C) float64, pitch in metres, wavelengths in metres or None per channel)`.
fn psf_of(
    given: &Bound<'_, PyAny>,
    key: Option<&str>,
    pitch: Option<f64>,
) -> PyResult<(doefab::optics::Psf, String)> {
    use doefab::optics::{Channel, Psf};
    if let Ok((values, at, wavelengths)) =
        given.extract::<(PyReadonlyArray3<'_, f64>, f64, Vec<Option<f64>>)>()
    {
        let values = values.as_array();
        let count = values.shape()[2];
        if wavelengths.len() != count {
            let what = format!("{} wavelengths for {count} channels", wavelengths.len());
            return Err(to_py(doefab::Error::param("wavelengths", what)));
        }
        let channels = (0..count)
            .map(|c| {
                let plane = values.index_axis(ndarray::Axis(2), c).to_owned();
                let name = match (wavelengths[c], count) {
                    (Some(l), _) => format!("{:.0}nm", l * 1e9),
                    (None, 3) => ["R", "G", "B"][c].to_string(),
                    (None, _) => format!("channel {c}"),
                };
                let grid = doefab::Grid::new(plane, [at, at], doefab::Unit::Dimensionless)?;
                Ok(Channel { name, wavelength: wavelengths[c], grid, captured: None })
            })
            .collect::<doefab::Result<Vec<_>>>()
            .or_py()?;
        return Ok((Psf { channels, method: "array".into(), warnings: Vec::new() }, "array".into()));
    }
    let path: PathBuf = given.extract()?;
    let psf = Psf::read(&path, key, pitch).or_py()?;
    Ok((psf, path.display().to_string()))
}

/// `psf_compare(a, b, pitch, key, radius, out)`: two PSFs' peaks, encircled energy, centroids
/// and difference, as `doefab psf-compare --json`; `b` is moved onto `a`'s centroid. `pitch`
/// metres (for files that state none), `radius` metres; `out` also saves the JSON.
#[pyfunction]
#[pyo3(signature = (a, b, pitch, key, radius, out))]
fn psf_compare(
    py: Python<'_>,
    a: &Bound<'_, PyAny>,
    b: &Bound<'_, PyAny>,
    pitch: Option<f64>,
    key: Option<String>,
    radius: Option<f64>,
    out: Option<PathBuf>,
) -> PyResult<String> {
    let (pa, name_a) = psf_of(a, key.as_deref(), pitch)?;
    let (pb, name_b) = psf_of(b, key.as_deref(), pitch)?;
    let opts = doefab::optics::psf_compare::CompareOptions { pitch, key, radius };
    let r = detached(py, None, |_| {
        let r = doefab::optics::psf_compare::compare(&pa, &pb, &name_a, &name_b, &opts)?;
        if let Some(out) = &out {
            doefab::io::atomic::write_json(out, &r)?;
        }
        Ok(r)
    })?;
    to_json(&r)
}

/// `reconstruct(capture, decoder, tile, overlap, border, keep_negative)` (None: the library's
/// default tiling): the linear HDR image
/// ((H, W, 3) float32, 1 = the capture's clipping level) of a capture (a path, or an (H, W, 3)
/// float32 array in units of the clipping level) through a decoder (a file or `built-in:NAME`),
/// and `doefab reconstruct`'s statistics as JSON.
#[pyfunction]
#[pyo3(signature = (capture, decoder, tile, overlap, border, keep_negative))]
fn reconstruct<'py>(
    py: Python<'py>,
    capture: &Bound<'py, PyAny>,
    decoder: PathBuf,
    tile: Option<usize>,
    overlap: Option<usize>,
    border: Option<usize>,
    keep_negative: bool,
) -> PyResult<(Bound<'py, PyArray3<f32>>, String)> {
    use doefab::decoder::{read_capture, reconstruct, Negatives, ReconstructOptions, UNet};
    let default = ReconstructOptions::default();
    let opts = ReconstructOptions {
        tile: tile.unwrap_or(default.tile),
        overlap: overlap.unwrap_or(default.overlap),
        border: border.unwrap_or(default.border),
        negatives: if keep_negative { Negatives::Keep } else { Negatives::Clamp },
    };
    let given = match capture.cast::<PyArray3<f32>>() {
        Ok(a) => {
            let a: PyReadonlyArray3<'_, f32> = a.readonly();
            if a.shape()[2] != 3 {
                let what = format!("is {:?}; an (H, W, 3) RGB array is needed", a.shape());
                return Err(to_py(doefab::Error::param("capture", what)));
            }
            Capture::Array(doefab::image::Image::new(a.as_array().to_owned()))
        }
        Err(_) => Capture::File(capture.extract()?),
    };
    let (y, stats) = detached(py, None, |_| {
        let x = match given {
            Capture::Array(x) => x,
            Capture::File(p) => read_capture(&p)?,
        };
        let weights = doefab::decoder::DecoderWeights::read(&decoder)?;
        let net = UNet::from_weights(&weights, &doefab::decoder::select_device(false)?.device);
        reconstruct(&net, &x, &opts)
    })?;
    Ok((PyArray3::from_owned_array(py, y.values), to_json(&stats)?))
}

/// A capture given to `reconstruct`.
enum Capture {
    Array(doefab::image::Image<f32>),
    File(PathBuf),
}

/// The library's version.
#[pyfunction]
fn version() -> &'static str {
    env!("CARGO_PKG_VERSION")
}

#[pymodule]
fn _doefab(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<Grid>()?;
    m.add_function(wrap_pyfunction!(read_heightmap, m)?)?;
    m.add_function(wrap_pyfunction!(read_scan, m)?)?;
    m.add_function(wrap_pyfunction!(psf, m)?)?;
    m.add_function(wrap_pyfunction!(fab, m)?)?;
    m.add_function(wrap_pyfunction!(compare, m)?)?;
    m.add_function(wrap_pyfunction!(psf_compare, m)?)?;
    m.add_function(wrap_pyfunction!(reconstruct, m)?)?;
    m.add_function(wrap_pyfunction!(version, m)?)?;
    errors::register(m)
}
