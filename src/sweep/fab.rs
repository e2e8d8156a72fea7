//! Speed against accuracy of the fabrication stage's numerical methods (`doefab bench fab`),
//! each scored against a truth computed another way:
//!
//! * **Quantization** ([`quantization_sweep`]): the predicted first-order efficiency of an
//!   N-level staircase ([`order_efficiency`], Swanson 1989, at the detuning of [`detuning`])
//!   against a simulation that shares neither formula: one period of a blazed grating sampled
//!   finely, quantized by [`quantize`], its transmission `exp(i 2 pi (n(lambda) - 1) h / lambda)`
//!   at each wavelength, and the power of the design order from its DFT. The DFT sees the
//!   samples as points; the grating is piecewise constant between them, so the DFT coefficient is
//!   multiplied by the zero-order hold's transfer function, `sinc(m / M)` for order `m` of `M`
//!   samples, which makes it the exact Fourier coefficient of the staircase (the quantizer's
//!   level boundaries fall on sample boundaries). The uncorrected DFT power is reported too: it
//!   exceeds the prediction by the factor `1 / sinc^2(1 / M)` (1 + 2.0e-4 at N = 2 with 64 samples
//!   per level, M = 128).
//! * **STL heightfield** ([`stl_sweep`]): [`heightfield_mesh`] at each `max_error`: triangles,
//!   time, and the height error of the mesh measured at every sample of the height map by
//!   interpolating the top triangle that covers it ([`mesh_height_error`]), not the mesher's
//!   own estimate. Truth: the height map itself.
//! * **GDSII tracing** ([`gds_sweep`]): the multi-level mask set ([`mask_set_gds`]) at each
//!   vertex limit: polygons, vertices, file size, time; the stream is read back
//!   ([`read_boundaries`]) and the shoelace area of each layer's pattern polygons compared with
//!   the number of open pixels of its bitmap ([`layer_masks`]) times the pixel area, in whole
//!   square nanometres: the polygons cover exactly the open pixels, so the difference is 0.

use std::time::Instant;

use ndarray::Array2;
use rustfft::num_complex::Complex64;
use serde::Serialize;

use crate::error::{Allowed, Error, Resource, Result};
use crate::fabrication::gds::{
    layer_masks, mask_set_gds, MaskSetOptions, DATABASE_UNIT, MAX_BOUNDARY_VERTICES,
};
use crate::fabrication::quantize::{check_level_count, detuning, order_efficiency, quantize, QuantizeMethod};
use crate::fabrication::stl::{heightfield_mesh, Mesh, StlOptions};
use crate::fabrication::wrap::{wrap, WrapSpec};
use crate::fft::Plan1d;
use crate::grid::{Grid, Interpolation, Unit};
use crate::material::{Material, PAPER_WAVELENGTHS};

/// What the sweep sweeps.
#[derive(Debug, Clone, Serialize)]
pub struct FabSweepOptions {
    /// Design wavelength of the wrap (and of the grating's blaze), metres.
    pub wavelength: f64,
    /// Material, by name.
    pub material: String,
    /// Multi-order factor p: the design order of the grating.
    pub order: u32,
    /// Level counts of the quantization sweep (2..=256 each).
    pub level_counts: Vec<usize>,
    /// Wavelengths the quantized grating is evaluated at, metres.
    pub wavelengths: Vec<f64>,
    /// Samples per level of the simulated grating.
    pub samples_per_level: usize,
    /// Height-error bounds of the STL heightfield sweep, metres.
    pub max_errors: Vec<f64>,
    /// Base thickness of the STL solid, metres.
    pub base_thickness: f64,
    /// Writer grid (pixel pitch) of the GDSII mask set, metres (a whole number of nanometres).
    pub gds_pitch: f64,
    /// Level count of the mask set (a power of two).
    pub gds_levels: usize,
    /// Vertex limits of the GDSII sweep (4..=8190 each).
    pub vertex_limits: Vec<usize>,
    /// Timed runs per configuration; the best is reported.
    pub repeats: usize,
}

impl Default for FabSweepOptions {
    fn default() -> Self {
        FabSweepOptions {
            wavelength: 530e-9,
            material: "pdms".into(),
            order: 1,
            level_counts: vec![2, 4, 8, 16, 32, 64],
            wavelengths: PAPER_WAVELENGTHS.to_vec(),
            samples_per_level: 64,
            max_errors: [1.0, 2.0, 5.0, 10.0, 20.0, 50.0].map(|nm| nm * 1e-9).to_vec(),
            base_thickness: StlOptions::default().base_thickness,
            gds_pitch: 2e-6,
            gds_levels: 8,
            vertex_limits: vec![4, 16, 64, 200, 500, 1000, 2000, 4094, MAX_BOUNDARY_VERTICES],
            repeats: 3,
        }
    }
}

impl FabSweepOptions {
    /// Refuses empty sweeps and values out of range, before any work.
    pub fn check(&self) -> Result<()> {
        let spec = self.wrap_spec()?;
        spec.period()?;
        if self.level_counts.is_empty() || self.wavelengths.is_empty() {
            return Err(Error::param(
                "level_counts",
                "the quantization sweep needs level counts and wavelengths",
            ));
        }
        for &n in &self.level_counts {
            check_level_count(n)?;
            if n > crate::fabrication::quantize::MAX_LEVELS_8BIT {
                return Err(Error::param("level_counts", format!("{n}: at most 256 levels are simulated")));
            }
        }
        for &l in &self.wavelengths {
            spec.material.index(l)?;
        }
        if !(2..=4096).contains(&self.samples_per_level) || !self.samples_per_level.is_multiple_of(2) {
            return Err(Error::param(
                "samples_per_level",
                format!(
                    "must be even (so that level boundaries fall between samples) and within 2..=4096, got {}",
                    self.samples_per_level
                ),
            ));
        }
        if self.max_errors.is_empty() || self.max_errors.iter().any(|e| !(e.is_finite() && *e > 0.0)) {
            return Err(Error::param("max_errors", "the STL sweep needs finite, positive height errors"));
        }
        if !(self.base_thickness.is_finite() && self.base_thickness > 0.0) {
            return Err(Error::param_in(
                "base_thickness",
                Allowed::positive(),
                format!("must be positive, got {} m", self.base_thickness),
            ));
        }
        if !(self.gds_pitch.is_finite() && self.gds_pitch > 0.0) {
            return Err(Error::param_in(
                "gds_pitch",
                Allowed::positive(),
                format!("must be positive, got {} m", self.gds_pitch),
            ));
        }
        if !(2..=256).contains(&self.gds_levels) || !self.gds_levels.is_power_of_two() {
            return Err(Error::param(
                "gds_levels",
                format!("a binary mask set needs a power of two in 2..=256 levels, got {}", self.gds_levels),
            ));
        }
        if self.vertex_limits.is_empty()
            || self.vertex_limits.iter().any(|v| !(4..=MAX_BOUNDARY_VERTICES).contains(v))
        {
            return Err(Error::param(
                "vertex_limits",
                format!("the GDSII sweep needs vertex limits within 4..={MAX_BOUNDARY_VERTICES}"),
            ));
        }
        if self.repeats == 0 {
            return Err(Error::param_in(
                "repeats",
                Allowed::at_least(1.0),
                "at least one timed run per configuration",
            ));
        }
        Ok(())
    }

    fn wrap_spec(&self) -> Result<WrapSpec> {
        Ok(WrapSpec {
            wavelength: self.wavelength,
            material: Material::by_name(&self.material)?,
            order: self.order,
        })
    }
}

/// Progress steps of [`run_sweep`]: the quantization sweep, one per `max_error`, the mask
/// set's level map, one per vertex limit.
pub fn steps(opts: &FabSweepOptions) -> usize {
    2 + opts.max_errors.len() + opts.vertex_limits.len()
}

/// One level count at one wavelength.
#[derive(Debug, Clone, Serialize)]
pub struct QuantizationPoint {
    /// Level count `N` of the quantized staircase.
    pub level_count: usize,
    /// Metres.
    pub wavelength: f64,
    /// Refractive index there.
    pub index: f64,
    /// Detuning `a` ([`detuning`]).
    pub detuning: f64,
    /// Swanson's efficiency of the design order ([`order_efficiency`]).
    pub predicted: f64,
    /// The simulated grating's efficiency of the design order (DFT, hold-corrected).
    pub simulated: f64,
    /// `simulated - predicted`.
    pub difference: f64,
    /// The plain DFT power of the design order, before the hold correction.
    pub dft_power: f64,
    /// Sum of the DFT power over all orders (1 by Parseval).
    pub dft_orders_sum: f64,
}

/// The quantization sweep.
#[derive(Debug, Clone, Serialize)]
pub struct QuantizationSweep {
    /// What the prediction is scored against.
    pub truth: String,
    /// Design wavelength of the wrap (and of the grating's blaze), metres.
    pub design_wavelength: f64,
    /// Material, by name.
    pub material: String,
    /// Design order (multi-order factor `p`) of the wrap and the grating.
    pub order: u32,
    /// Wrap period `p h_2pi`, metres.
    pub period: f64,
    /// Samples per level of the simulated grating (`M = N * samples_per_level` per period).
    pub samples_per_level: usize,
    /// Largest |simulated - predicted| over the sweep.
    pub max_difference: f64,
    /// One point per level count and wavelength, level count by level count.
    pub points: Vec<QuantizationPoint>,
}

/// One `max_error` of the STL heightfield.
#[derive(Debug, Clone, Serialize)]
pub struct StlPoint {
    /// The mesher's bound, metres.
    pub max_error: f64,
    /// Triangles of the whole solid (top, walls, base), as written to the STL.
    pub triangles: usize,
    /// Triangles of the top surface.
    pub top_triangles: usize,
    /// Vertices of the whole solid.
    pub vertices: usize,
    /// Best of the timed runs of [`heightfield_mesh`], seconds.
    pub seconds: f64,
    /// The mesher's own maximum error, metres.
    pub reported_max_error: f64,
    /// Largest |mesh - height map| over every sample, measured, metres.
    pub measured_max_error: f64,
    /// RMS of (mesh - height map) over every sample, measured, metres.
    pub measured_rms_error: f64,
    /// `measured_max_error <= max_error`.
    pub within_bound: bool,
}

/// The STL heightfield sweep.
#[derive(Debug, Clone, Serialize)]
pub struct StlSweep {
    /// What the mesh's error is measured against.
    pub truth: String,
    /// Samples `[rows, columns]` of the meshed map.
    pub samples: [usize; 2],
    /// Pitch `[x, y]` of the meshed map, metres.
    pub pitch: [f64; 2],
    /// Triangles of the naive top mesh (two per cell between four samples).
    pub naive_triangles: u64,
    /// Timed runs per `max_error`; the best is reported.
    pub repeats: usize,
    /// One point per `max_error`, in the order given.
    pub points: Vec<StlPoint>,
}

/// One layer of the mask set at one vertex limit; areas in square nanometres.
#[derive(Debug, Clone, Serialize)]
pub struct GdsLayerArea {
    /// GDSII layer number `k`: mask `k` of [`layer_masks`] (bit `M - k` of the level, `M =
    /// log2 level_count`).
    pub layer: u16,
    /// Pattern polygons of the layer, read back from the stream.
    pub polygons: usize,
    /// Their vertices, summed (distinct vertices, the closing repeat not counted).
    pub vertices: usize,
    /// Sum of the pattern polygons' shoelace areas.
    pub polygon_area: i64,
    /// Open pixels of the layer's bitmap times the pixel area.
    pub bitmap_area: i64,
    /// `polygon_area - bitmap_area`.
    pub difference: i64,
}

/// One vertex limit of the GDSII mask set.
#[derive(Debug, Clone, Serialize)]
pub struct GdsPoint {
    /// The vertex limit: the most vertices of one polygon the writer may emit
    /// ([`MaskSetOptions::max_vertices`]).
    pub max_vertices: usize,
    /// Pattern polygons over all layers, read back from the stream (alignment crosses not
    /// counted).
    pub polygons: usize,
    /// Their vertices, summed (distinct vertices, the closing repeat not counted).
    pub vertices: usize,
    /// The most vertices of one polygon, read back.
    pub largest_polygon: usize,
    /// File size, bytes.
    pub bytes: usize,
    /// Best of the timed runs of [`mask_set_gds`] (tracing and encoding in memory), seconds.
    pub seconds: f64,
    /// Whether the counts read back equal the writer's report.
    pub report_agrees: bool,
    /// One entry per mask layer, layer 1 first.
    pub layers: Vec<GdsLayerArea>,
}

/// The GDSII sweep.
#[derive(Debug, Clone, Serialize)]
pub struct GdsSweep {
    /// What the polygons' areas are compared with.
    pub truth: String,
    /// Level count of the mask set.
    pub level_count: usize,
    /// Writer grid (pixel pitch) of the mask set, metres.
    pub pitch: f64,
    /// The level map's samples `[rows, columns]` at the writer grid.
    pub samples: [usize; 2],
    /// Timed runs per vertex limit; the best is reported.
    pub repeats: usize,
    /// Largest |polygon area - bitmap area| over every layer and limit, nm^2.
    pub max_area_difference: i64,
    /// One point per vertex limit, in the order given.
    pub points: Vec<GdsPoint>,
}

/// The whole sweep. Deterministic but for the `seconds` fields.
#[derive(Debug, Clone, Serialize)]
pub struct FabSweepResults {
    /// What the numbers are in: lengths and heights in metres, times in seconds, file sizes in
    /// bytes, GDSII areas in square nanometres.
    pub units: String,
    /// The design: `built-in:NAME` or its file's path.
    pub design: String,
    /// The design's samples `[rows, columns]`.
    pub design_samples: [usize; 2],
    /// The design's pitch `[x, y]`, metres.
    pub design_pitch: [f64; 2],
    /// The quantization sweep: predicted against simulated efficiency.
    pub quantization: QuantizationSweep,
    /// The STL heightfield sweep: triangles and time against the measured height error.
    pub stl: StlSweep,
    /// The GDSII sweep: polygons, file size and time against the vertex limit, areas checked.
    pub gds: GdsSweep,
}

/// Runs the three sweeps on a design (heights in metres, unwrapped); `progress` is called with
/// a message before each step ([`steps`] of them).
pub fn run_sweep(
    heights: &Grid,
    design: &str,
    opts: &FabSweepOptions,
    mut progress: impl FnMut(&str),
) -> Result<FabSweepResults> {
    opts.check()?;
    progress("quantization: simulated gratings");
    let quantization = quantization_sweep(opts)?;
    let stl = stl_sweep(heights, opts, &mut progress)?;
    let gds = gds_sweep(heights, opts, &mut progress)?;
    let (r, c) = heights.dim();
    Ok(FabSweepResults {
        units: "lengths and heights in metres, times in seconds, file sizes in bytes, GDSII areas in square \
                nanometres"
            .into(),
        design: design.into(),
        design_samples: [r, c],
        design_pitch: heights.pitch(),
        quantization,
        stl,
        gds,
    })
}

/// `sin(pi x) / (pi x)`.
fn sinc(x: f64) -> f64 {
    if x == 0.0 {
        1.0
    } else {
        (std::f64::consts::PI * x).sin() / (std::f64::consts::PI * x)
    }
}

/// The simulated grating of one level count at one wavelength: `(hold-corrected power of the
/// design order, plain DFT power of it, DFT power summed over all orders)`.
///
/// One period of the blaze `h(x) = x * period`, `x in [0, 1)`, is sampled at the centres of
/// `M = N * samples_per_level` cells and quantized by [`quantize`] (rounding); each cell then
/// holds one level, and the level boundaries `(l + 1/2) / N` fall on cell boundaries
/// (`samples_per_level` even, as [`FabSweepOptions::check`] requires). The transmission of a cell is
/// `exp(i 2 pi (n(lambda) - 1) h / lambda)`; `c_m = DFT_m / M` is the DFT's order `m`, and
/// `c_m sinc(m / M)` (times a phase) is the Fourier coefficient of the piecewise-constant
/// transmission.
pub fn simulate_grating(
    level_count: usize,
    samples_per_level: usize,
    period: f64,
    material: &Material,
    wavelength: f64,
    order: u32,
) -> Result<(f64, f64, f64)> {
    let m = level_count * samples_per_level;
    let blaze = Array2::from_shape_fn((1, m), |(_, k)| (k as f64 + 0.5) / m as f64 * period);
    let blaze = Grid::new(blaze, [period / m as f64; 2], Unit::Metre)?;
    let q = quantize(&blaze, period, level_count, QuantizeMethod::Round)?;
    let phase_per_metre = 2.0 * std::f64::consts::PI * (material.index(wavelength)? - 1.0) / wavelength;
    let heights = q.heights()?;
    let mut field: Vec<Complex64> =
        heights.values().iter().map(|&h| Complex64::from_polar(1.0, phase_per_metre * h)).collect();
    Plan1d::new(m).process(&mut field, false);
    let norm = (m as f64).powi(2);
    let total = field.iter().map(|c| c.norm_sqr()).sum::<f64>() / norm;
    let k = order as usize % m;
    let dft = field[k].norm_sqr() / norm;
    Ok((dft * sinc(order as f64 / m as f64).powi(2), dft, total))
}

/// Predicted against simulated efficiency of the design order for every level count and
/// wavelength of `opts` (see the module docs).
pub fn quantization_sweep(opts: &FabSweepOptions) -> Result<QuantizationSweep> {
    let spec = opts.wrap_spec()?;
    let period = spec.period()?;
    let n0 = spec.index()?;
    let mut points = Vec::new();
    for &n in &opts.level_counts {
        for &l in &opts.wavelengths {
            let index = spec.material.index(l)?;
            let a = detuning(opts.order, opts.wavelength, n0, l, index);
            let predicted = order_efficiency(n, a, opts.order as i64);
            let (simulated, dft_power, dft_orders_sum) =
                simulate_grating(n, opts.samples_per_level, period, &spec.material, l, opts.order)?;
            points.push(QuantizationPoint {
                level_count: n,
                wavelength: l,
                index,
                detuning: a,
                predicted,
                simulated,
                difference: simulated - predicted,
                dft_power,
                dft_orders_sum,
            });
        }
    }
    Ok(QuantizationSweep {
        truth: format!(
            "one period of a blazed grating, {} samples per level, quantized by rounding; power of order {} of \
             its transmission's DFT times the zero-order hold's sinc^2(m / M)",
            opts.samples_per_level, opts.order
        ),
        design_wavelength: opts.wavelength,
        material: spec.material.name.clone(),
        order: opts.order,
        period,
        samples_per_level: opts.samples_per_level,
        max_difference: points.iter().map(|p| p.difference.abs()).fold(0.0, f64::max),
        points,
    })
}

/// The measured height error of a heightfield mesh against its height map.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MeshError {
    /// Largest |mesh - sample| over every sample (and every top triangle covering it), metres.
    pub max: f64,
    /// RMS over the samples, metres.
    pub rms: f64,
}

/// Measures a heightfield mesh against its height map: at every sample, the height of each
/// upward-facing triangle whose projection covers the sample centre (barycentric interpolation
/// of its three vertices, in the sample grid's index coordinates, with a 1e-9 sample tolerance
/// so that samples on shared edges count in both triangles). Refuses a mesh that leaves a
/// sample uncovered.
pub fn mesh_height_error(mesh: &Mesh, heights: &Grid) -> Result<MeshError> {
    const EPS: f64 = 1e-9;
    let (nr, nc) = heights.dim();
    let [px, py] = heights.pitch();
    let (x0, y0) = (heights.x(0), heights.y(0));
    let h = heights.values();
    let v = mesh.vertices();
    // STL frame (X, Y) = (x, -y) -> (column, row).
    let index = |p: [f64; 3]| [(p[0] - x0) / px, (-p[1] - y0) / py];
    let mut error = Array2::<f64>::from_elem((nr, nc), f64::NAN);
    let mut max = 0.0f64;
    for t in mesh.triangles() {
        let [a, b, c] = t.map(|k| v[k as usize]);
        let up = (b[0] - a[0]) * (c[1] - a[1]) - (c[0] - a[0]) * (b[1] - a[1]);
        if up <= 0.0 {
            continue; // a wall (vertical) or the base (looking down)
        }
        let [pa, pb, pc] = [a, b, c].map(index);
        let det = (pb[0] - pa[0]) * (pc[1] - pa[1]) - (pc[0] - pa[0]) * (pb[1] - pa[1]);
        let lo = |k: usize| pa[k].min(pb[k]).min(pc[k]);
        let hi = |k: usize| pa[k].max(pb[k]).max(pc[k]);
        let j0 = (lo(0) - EPS).ceil().max(0.0) as usize;
        let j1 = ((hi(0) + EPS).floor().max(0.0) as usize).min(nc - 1);
        let i0 = (lo(1) - EPS).ceil().max(0.0) as usize;
        let i1 = ((hi(1) + EPS).floor().max(0.0) as usize).min(nr - 1);
        for i in i0..=i1 {
            let y = i as f64;
            for j in j0..=j1 {
                let x = j as f64;
                let l1 = ((x - pa[0]) * (pc[1] - pa[1]) - (pc[0] - pa[0]) * (y - pa[1])) / det;
                let l2 = ((pb[0] - pa[0]) * (y - pa[1]) - (x - pa[0]) * (pb[1] - pa[1])) / det;
                let l0 = 1.0 - l1 - l2;
                if l0 >= -EPS && l1 >= -EPS && l2 >= -EPS {
                    let e = l0 * a[2] + l1 * b[2] + l2 * c[2] - h[[i, j]];
                    max = max.max(e.abs());
                    if error[[i, j]].is_nan() {
                        error[[i, j]] = e;
                    }
                }
            }
        }
    }
    let uncovered = error.iter().filter(|e| e.is_nan()).count();
    if uncovered > 0 {
        return Err(Error::internal(format!("{uncovered} samples lie under no top triangle of the mesh")));
    }
    let rms = (error.iter().map(|e| e * e).sum::<f64>() / error.len() as f64).sqrt();
    Ok(MeshError { max, rms })
}

/// Runs `f` `repeats` times; the best time and the last result.
fn best_of<T>(repeats: usize, mut f: impl FnMut() -> Result<T>) -> Result<(f64, T)> {
    let mut best = f64::INFINITY;
    let mut out = None;
    for _ in 0..repeats.max(1) {
        let t = Instant::now();
        let r = f()?;
        best = best.min(t.elapsed().as_secs_f64());
        out = Some(r);
    }
    match out {
        Some(r) => Ok((best, r)),
        None => Err(Error::param("repeats", "at least one run")),
    }
}

/// The heightfield mesh of `heights` (unwrapped, metres) at every `max_error` of `opts`:
/// triangles, time and the measured error ([`mesh_height_error`]).
pub fn stl_sweep(
    heights: &Grid,
    opts: &FabSweepOptions,
    progress: &mut impl FnMut(&str),
) -> Result<StlSweep> {
    let (nr, nc) = heights.dim();
    let mut points = Vec::new();
    for &max_error in &opts.max_errors {
        progress(&format!("STL heightfield within {:.0} nm", max_error * 1e9));
        let (seconds, mesh) =
            best_of(opts.repeats, || heightfield_mesh(heights, opts.base_thickness, max_error))?;
        let measured = mesh_height_error(&mesh, heights)?;
        let top_triangles = top_triangle_count(&mesh);
        points.push(StlPoint {
            max_error,
            triangles: mesh.triangles().len(),
            top_triangles,
            vertices: mesh.vertices().len(),
            seconds,
            reported_max_error: mesh.max_height_error(),
            measured_max_error: measured.max,
            measured_rms_error: measured.rms,
            within_bound: measured.max <= max_error,
        });
    }
    Ok(StlSweep {
        truth: "the height map at each of its samples, against the mesh's top triangle over it (barycentric)"
            .into(),
        samples: [nr, nc],
        pitch: heights.pitch(),
        naive_triangles: 2 * (nr.saturating_sub(1) * nc.saturating_sub(1)) as u64,
        repeats: opts.repeats,
        points,
    })
}

fn top_triangle_count(mesh: &Mesh) -> usize {
    let v = mesh.vertices();
    mesh.triangles()
        .iter()
        .filter(|t| {
            let [a, b, c] = t.map(|k| v[k as usize]);
            (b[0] - a[0]) * (c[1] - a[1]) - (c[0] - a[0]) * (b[1] - a[1]) > 0.0
        })
        .count()
}

/// One BOUNDARY of a GDSII stream: its layer and its distinct vertices (the closing repeat
/// of the first point dropped), database units.
#[derive(Debug, Clone, PartialEq)]
pub struct Boundary {
    /// GDSII layer number.
    pub layer: u16,
    /// The distinct vertices `[x, y]`, database units (1 nm), in the stream's order.
    pub points: Vec<[i32; 2]>,
}

/// Reads every BOUNDARY of a GDSII stream (records: big-endian `u16` length, record type,
/// data type, data); other elements are skipped.
pub fn read_boundaries(bytes: &[u8]) -> Result<Vec<Boundary>> {
    let bad = |what: String| Error::internal(format!("GDSII stream: {what}"));
    let mut out = Vec::new();
    let mut layer = None;
    let mut points: Option<Vec<[i32; 2]>> = None;
    let mut at = 0;
    while at + 4 <= bytes.len() {
        let len = u16::from_be_bytes([bytes[at], bytes[at + 1]]) as usize;
        let kind = u16::from_be_bytes([bytes[at + 2], bytes[at + 3]]);
        if len < 4 || at + len > bytes.len() {
            return Err(bad(format!("record at byte {at} has length {len}")));
        }
        let data = &bytes[at + 4..at + len];
        match kind {
            0x0800 => {
                layer = None;
                points = None;
            }
            0x0D02 if data.len() >= 2 => layer = Some(u16::from_be_bytes([data[0], data[1]])),
            0x1003 => {
                let mut p: Vec<[i32; 2]> = data
                    .chunks_exact(8)
                    .map(|c| {
                        [
                            i32::from_be_bytes([c[0], c[1], c[2], c[3]]),
                            i32::from_be_bytes([c[4], c[5], c[6], c[7]]),
                        ]
                    })
                    .collect();
                if p.len() < 4 || p.first() != p.last() {
                    return Err(bad(format!("the XY record at byte {at} is not a closed boundary")));
                }
                p.pop();
                points = Some(p);
            }
            0x1100 => {
                if let (Some(layer), Some(points)) = (layer.take(), points.take()) {
                    out.push(Boundary { layer, points });
                }
            }
            0x0400 => return Ok(out),
            _ => {}
        }
        at += len;
    }
    Err(bad("no ENDLIB record".into()))
}

/// Twice the signed area of a closed polygon (shoelace), exact.
fn twice_area(p: &[[i32; 2]]) -> i128 {
    (0..p.len())
        .map(|k| {
            let (a, b) = (p[k], p[(k + 1) % p.len()]);
            a[0] as i128 * b[1] as i128 - b[0] as i128 * a[1] as i128
        })
        .sum()
}

/// The multi-level mask set of `heights` (wrapped, quantized to `opts.gds_levels` by rounding,
/// resampled to `opts.gds_pitch` by nearest neighbour) at every vertex limit of `opts`.
pub fn gds_sweep(
    heights: &Grid,
    opts: &FabSweepOptions,
    progress: &mut impl FnMut(&str),
) -> Result<GdsSweep> {
    progress(&format!("GDSII: {}-level map at {:.2} um", opts.gds_levels, opts.gds_pitch * 1e6));
    let spec = opts.wrap_spec()?;
    let (wrapped, w) = wrap(heights, &spec)?;
    let levels = quantize(&wrapped, w.period, opts.gds_levels, QuantizeMethod::Round)?
        .levels
        .resample([opts.gds_pitch; 2], Interpolation::Nearest)?;
    drop(wrapped);
    let pixel = {
        let [px, py] = levels.pitch().map(|p| (p / DATABASE_UNIT).round() as i128);
        px * py
    };
    let bitmap: Vec<i128> = layer_masks(&levels, opts.gds_levels)?
        .iter()
        .map(|m| m.iter().filter(|&&o| o).count() as i128 * pixel)
        .collect();
    let mut points = Vec::new();
    for &max_vertices in &opts.vertex_limits {
        progress(&format!("GDSII mask set, at most {max_vertices} vertices a polygon"));
        let set = MaskSetOptions { max_vertices, ..MaskSetOptions::default() };
        let (seconds, (bytes, report)) =
            best_of(opts.repeats, || mask_set_gds(&levels, opts.gds_levels, w.period, &set))?;
        let e = report.design_extent.map(|v| (v / DATABASE_UNIT).round() as i64);
        let inside = |b: &Boundary| {
            b.points.iter().all(|p| {
                let (x, y) = (p[0] as i64, p[1] as i64);
                e[0] <= x && x <= e[2] && e[1] <= y && y <= e[3]
            })
        };
        let boundaries = read_boundaries(&bytes)?;
        let mut layers = Vec::new();
        for (k, &want) in bitmap.iter().enumerate() {
            let layer = k as u16 + 1;
            let own: Vec<&Boundary> = boundaries.iter().filter(|b| b.layer == layer && inside(b)).collect();
            let area: i128 = own.iter().map(|b| twice_area(&b.points)).sum::<i128>() / 2;
            let to_i64 = |v: i128| {
                let what = || format!("area {v} nm^2 out of range");
                i64::try_from(v)
                    .map_err(|_| Error::limit(Resource::Area, (v as f64).abs(), i64::MAX as f64, what()))
            };
            layers.push(GdsLayerArea {
                layer,
                polygons: own.len(),
                vertices: own.iter().map(|b| b.points.len()).sum(),
                polygon_area: to_i64(area)?,
                bitmap_area: to_i64(want)?,
                difference: to_i64(area - want)?,
            });
        }
        let polygons = layers.iter().map(|l| l.polygons).sum();
        let vertices = layers.iter().map(|l| l.vertices).sum();
        let report_agrees = polygons == report.polygons
            && vertices == report.vertices
            && report
                .masks
                .iter()
                .zip(&layers)
                .all(|(m, l)| m.polygons == l.polygons && m.vertices == l.vertices);
        points.push(GdsPoint {
            max_vertices,
            polygons,
            vertices,
            largest_polygon: boundaries
                .iter()
                .filter(|b| inside(b))
                .map(|b| b.points.len())
                .max()
                .unwrap_or(0),
            bytes: bytes.len(),
            seconds,
            report_agrees,
            layers,
        });
    }
    let (r, c) = levels.dim();
    Ok(GdsSweep {
        truth:
            "each layer's bitmap (open pixels x pixel area), against the shoelace area of its polygons read \
                back from the stream"
                .into(),
        level_count: opts.gds_levels,
        pitch: levels.pitch()[0],
        samples: [r, c],
        repeats: opts.repeats,
        max_area_difference: points
            .iter()
            .flat_map(|p| p.layers.iter().map(|l| l.difference.abs()))
            .max()
            .unwrap_or(0),
        points,
    })
}

impl QuantizationSweep {
    /// One row per level count and wavelength.
    pub fn csv(&self) -> String {
        let mut s = String::from(
            "level_count,wavelength_nm,index,detuning,predicted,simulated,difference,dft_power,dft_orders_sum\n",
        );
        for p in &self.points {
            s += &format!(
                "{},{},{},{},{},{},{:e},{},{}\n",
                p.level_count,
                p.wavelength * 1e9,
                p.index,
                p.detuning,
                p.predicted,
                p.simulated,
                p.difference,
                p.dft_power,
                p.dft_orders_sum
            );
        }
        s
    }
}

impl StlSweep {
    /// One row per `max_error`.
    pub fn csv(&self) -> String {
        let mut s = String::from(
            "max_error_nm,triangles,top_triangles,vertices,seconds,reported_max_error_nm,measured_max_error_nm,\
             measured_rms_error_nm,within_bound\n",
        );
        for p in &self.points {
            s += &format!(
                "{},{},{},{},{},{},{},{},{}\n",
                p.max_error * 1e9,
                p.triangles,
                p.top_triangles,
                p.vertices,
                p.seconds,
                p.reported_max_error * 1e9,
                p.measured_max_error * 1e9,
                p.measured_rms_error * 1e9,
                p.within_bound
            );
        }
        s
    }
}

impl GdsSweep {
    /// One row per vertex limit and layer.
    pub fn csv(&self) -> String {
        let mut s = String::from(
            "max_vertices,bytes,seconds,largest_polygon,layer,polygons,vertices,polygon_area_nm2,bitmap_area_nm2,\
             area_difference_nm2\n",
        );
        for p in &self.points {
            for l in &p.layers {
                s += &format!(
                    "{},{},{},{},{},{},{},{},{},{}\n",
                    p.max_vertices,
                    p.bytes,
                    p.seconds,
                    p.largest_polygon,
                    l.layer,
                    l.polygons,
                    l.vertices,
                    l.polygon_area,
                    l.bitmap_area,
                    l.difference
                );
            }
        }
        s
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn simulated_quantization_equals_swanson() {
        let opts = FabSweepOptions::default();
        let q = quantization_sweep(&opts).unwrap();
        assert_eq!(q.points.len(), 18);
        for p in &q.points {
            assert!(
                p.difference.abs() <= 1e-6,
                "N = {} at {:.0} nm: simulated {} vs predicted {}",
                p.level_count,
                p.wavelength * 1e9,
                p.simulated,
                p.predicted
            );
            assert!((p.dft_orders_sum - 1.0).abs() < 1e-12, "Parseval: {}", p.dft_orders_sum);
            // The plain DFT (point samples) exceeds the staircase's power by 1 / sinc^2(1 / M).
            let m = (p.level_count * opts.samples_per_level) as f64;
            assert!((p.dft_power * sinc(1.0 / m).powi(2) / p.predicted - 1.0).abs() < 1e-9);
        }
        // At the design wavelength: sinc^2(1/N), 0.405 at N = 2.
        let green = q.points.iter().find(|p| p.level_count == 2 && p.wavelength == 530e-9).unwrap();
        assert!((green.simulated - (2.0 / std::f64::consts::PI).powi(2)).abs() < 1e-9);
        assert!(green.dft_power / green.predicted - 1.0 > 1.9e-4, "{}", green.dft_power / green.predicted);
    }

    fn surface(n: usize, m: usize) -> Grid {
        let v = Array2::from_shape_fn((n, m), |(i, j)| {
            let (x, y) = (j as f64 / m as f64, i as f64 / n as f64);
            4e-7 * (1.0 + (7.0 * x).sin() * (5.0 * y + 0.3).cos()) + 2e-7 * x * y
        });
        Grid::new(v, [3e-6, 2e-6], Unit::Metre).unwrap()
    }

    #[test]
    fn measured_stl_error_is_within_each_bound() {
        let g = surface(37, 45);
        let opts =
            FabSweepOptions { max_errors: vec![0.5e-9, 2e-9, 10e-9], repeats: 1, ..Default::default() };
        let s = stl_sweep(&g, &opts, &mut |_| {}).unwrap();
        assert_eq!(s.points.len(), 3);
        for p in &s.points {
            assert!(p.within_bound && p.measured_max_error <= p.max_error, "{p:?}");
            assert!(p.measured_rms_error <= p.measured_max_error && p.measured_max_error > 0.0);
            // The mesher's own estimate and the independent measure agree.
            assert!((p.reported_max_error - p.measured_max_error).abs() < 1e-15, "{p:?}");
        }
        assert!(s.points[0].triangles > s.points[2].triangles);
        // A mesh of another map is caught.
        let mesh = heightfield_mesh(&g, 1e-6, 1e-9).unwrap();
        let shifted = g.map_values(g.values().mapv(|h| h + 3e-9), Unit::Metre).unwrap();
        let e = mesh_height_error(&mesh, &shifted).unwrap();
        assert!((e.max - 3e-9).abs() < 1.1e-9 && e.max > 2e-9, "{e:?}");
        // Every sample is covered: a smaller map leaves none out, a larger one does.
        let big = surface(40, 45);
        assert!(mesh_height_error(&mesh, &big).is_err());
    }

    #[test]
    fn gds_polygon_areas_equal_the_bitmaps() {
        let g = surface(60, 70);
        let opts = FabSweepOptions {
            gds_pitch: 1e-6,
            vertex_limits: vec![4, 12, 8190],
            repeats: 1,
            ..Default::default()
        };
        let s = gds_sweep(&g, &opts, &mut |_| {}).unwrap();
        assert_eq!(s.samples, [120, 210]);
        assert_eq!(s.max_area_difference, 0);
        for p in &s.points {
            assert!(p.report_agrees, "{p:?}");
            assert!(p.largest_polygon <= p.max_vertices);
            assert_eq!(p.layers.len(), 3);
            for l in &p.layers {
                assert_eq!(l.difference, 0);
                assert!(l.bitmap_area > 0);
            }
        }
        // A vertex limit of 4 cuts everything into rectangles: more polygons, a bigger file.
        assert!(s.points[0].polygons > s.points[2].polygons && s.points[0].bytes > s.points[2].bytes);
        assert_eq!(s.points[0].largest_polygon, 4);
    }

    #[test]
    fn bad_options_are_refused() {
        let d = FabSweepOptions::default();
        assert!(d.check().is_ok());
        for bad in [
            FabSweepOptions { level_counts: vec![], ..d.clone() },
            FabSweepOptions { level_counts: vec![1], ..d.clone() },
            FabSweepOptions { max_errors: vec![0.0], ..d.clone() },
            FabSweepOptions { vertex_limits: vec![3], ..d.clone() },
            FabSweepOptions { gds_levels: 6, ..d.clone() },
            FabSweepOptions { repeats: 0, ..d.clone() },
            FabSweepOptions { samples_per_level: 63, ..d.clone() },
            FabSweepOptions { material: "glass?".into(), ..d.clone() },
            FabSweepOptions { wavelengths: vec![5e-6], ..d.clone() },
        ] {
            assert!(bad.check().is_err(), "{bad:?}");
        }
    }
}
