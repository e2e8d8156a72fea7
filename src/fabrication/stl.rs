//! Binary STL of a DOE surface (a master, or a cast of it): a closed, manifold, consistently
//! oriented solid made of the top surface, vertical side walls and a flat base of configurable
//! thickness. No vertical exaggeration: x, y and z share one scale.
//!
//! Two ways to mesh the top surface:
//!
//! * **Terraces** ([`terrace_mesh`]), for quantized maps: every pixel is a flat square at its
//!   height, so the part is a stack of terraces. Each terrace is meshed exactly: the boundary
//!   between pixels of different height is traced along pixel edges and merged into straight
//!   runs, the top is a constrained Delaunay triangulation of the run end points (each triangle
//!   lies inside one terrace), and vertical walls join neighbouring terraces. The mesh encloses
//!   exactly the volume `sum over pixels (h - h_min + t) * pitch_x * pitch_y` (up to the
//!   chamfers described in [`terrace_mesh`]). See `stl/terrace.rs`.
//! * **Heightfield** ([`heightfield_mesh`]), for continuous maps: a triangulated irregular
//!   network (TIN) interpolating the pixel-centre samples, simplified by greedy insertion
//!   (Garland & Heckbert 1995, "Fast polygonal approximation of terrains and height fields",
//!   CMU-CS-95-181) until every pixel centre lies within a user-given height error of the
//!   surface. See `stl/heightfield.rs`.
//!
//! Frame: pixel (i, j) covers `x in [x_j - p_x/2, x_j + p_x/2]`, `y` likewise; the STL axes are
//! `X = x`, `Y = -y` (rows go downward, so the part looks like the image seen from above) and
//! `Z = height`. The base is the plane `Z = h_min - t`. Coordinates are written as `f32` in the
//! chosen unit (millimetres by default, micrometres on request); the unit is stated in the
//! 80-byte header (`doefab STL units=mm ...`; it never starts with `solid`, so no reader
//! mistakes the file for ASCII STL).
//!
//! File layout (binary STL): 80-byte header, `u32` triangle count, then per triangle the unit
//! normal and three vertices (12 `f32`, little endian) and a zero `u16` attribute.

mod heightfield;
mod mesh;
mod terrace;

use std::path::Path;

use serde::{Deserialize, Serialize};

use crate::error::{Allowed, DataCause, Error, Resource, Result};
use crate::grid::{Grid, Unit};
use crate::io::atomic::write_atomic;

pub use mesh::{Mesh, SurfaceKind};
pub use terrace::CHAMFER_FRACTION;

/// Length unit of the STL coordinates.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum StlUnit {
    /// Millimetres (what slicers and CAD tools assume for a unitless STL).
    #[default]
    Millimetre,
    /// Micrometres.
    Micrometre,
}

impl StlUnit {
    /// Size of one unit in metres.
    pub fn metres(self) -> f64 {
        match self {
            StlUnit::Millimetre => 1e-3,
            StlUnit::Micrometre => 1e-6,
        }
    }
    /// The symbol written into the header: `mm` or `um`.
    pub fn symbol(self) -> &'static str {
        match self {
            StlUnit::Millimetre => "mm",
            StlUnit::Micrometre => "um",
        }
    }
    /// Parses `mm` or `um` (also `µm`, `micron`).
    pub fn parse(name: &str) -> Result<StlUnit> {
        match name.trim() {
            "mm" | "millimetre" | "millimeter" => Ok(StlUnit::Millimetre),
            "um" | "µm" | "μm" | "micron" | "micrometre" | "micrometer" => Ok(StlUnit::Micrometre),
            other => Err(Error::param("STL unit", format!("'{other}' is not supported (use mm or um)"))),
        }
    }
}

/// Which mesher [`surface_mesh`] uses.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum SurfaceChoice {
    /// Terraces when the map holds at most [`AUTO_TERRACE_MAX_HEIGHTS`] distinct heights,
    /// otherwise a heightfield.
    #[default]
    Auto,
    /// Exact flat terraces with vertical walls ([`terrace_mesh`]), whatever the map.
    Terraces,
    /// Error-bounded TIN through the pixel centres ([`heightfield_mesh`]), for a map of at
    /// least 2 x 2 samples.
    Heightfield,
}

/// [`SurfaceChoice::Auto`] meshes maps with at most this many distinct heights as terraces
/// (quantized maps have at most 256 levels; continuous maps have far more distinct values).
pub const AUTO_TERRACE_MAX_HEIGHTS: usize = 256;

/// Options for [`surface_stl`].
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct StlOptions {
    /// Unit of the coordinates in the file.
    pub unit: StlUnit,
    /// Thickness of the solid base below the lowest point of the surface, metres (> 0).
    pub base_thickness: f64,
    /// Largest allowed height error of the simplified heightfield at any pixel centre, metres
    /// (> 0; used for continuous maps only, terraces are exact).
    pub max_error: f64,
    /// Which mesher to use.
    pub surface: SurfaceChoice,
}

impl Default for StlOptions {
    fn default() -> Self {
        StlOptions {
            unit: StlUnit::Millimetre,
            base_thickness: 0.5e-3,
            max_error: 2e-9,
            surface: SurfaceChoice::Auto,
        }
    }
}

/// What [`write_stl`] wrote (serialised into the commands' JSON).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct StlStats {
    /// Unit of the coordinates in the file.
    pub unit: StlUnit,
    /// The 80-byte header text (trailing padding removed).
    pub header: String,
    /// How the top surface was meshed.
    pub surface: SurfaceKind,
    /// Triangles in the file: top surface, side walls and base of the closed solid.
    pub triangles: u64,
    /// Distinct vertices of the mesh (the file repeats them per triangle).
    pub vertices: u64,
    /// Triangles of the naive top mesh: two per pixel for terraces, two per cell between four
    /// pixel centres for a heightfield.
    pub naive_triangles: u64,
    /// `triangles / naive_triangles`.
    pub triangle_ratio: f64,
    /// Largest |surface - sample| over all pixels, metres.
    pub max_height_error: f64,
    /// Largest horizontal deviation of an outline from the pixel edges, metres.
    pub max_lateral_deviation: f64,
    /// Saddle corners resolved by a chamfer.
    pub chamfers: u64,
    /// Base thickness below the lowest surface point, metres.
    pub base_thickness: f64,
    /// Enclosed volume, m^3 (divergence theorem on the f64 mesh).
    pub volume: f64,
    /// Bounding box size `[x, y, z]`, metres; `z` = height range + base thickness.
    pub size: [f64; 3],
}

/// Checks what every mesher needs: heights in metres, every sample valid and finite, and a
/// positive finite base thickness. Returns `(h_min, h_max)`.
fn check_input(heights: &Grid, base_thickness: f64) -> Result<(f64, f64)> {
    match heights.unit() {
        Unit::Metre => {}
        Unit::Level => {
            return Err(Error::param(
                "heights",
                "the grid holds level indices; convert them to heights first \
                 (fabrication::stl::level_heights)",
            ))
        }
        u => {
            return Err(Error::param(
                "heights",
                format!("an STL needs heights in metres, the grid holds '{}'", u.symbol()),
            ))
        }
    }
    if let Some(mask) = heights.mask() {
        let bad = mask.iter().filter(|&&v| !v).count();
        if let Some(((i, j), _)) = mask.indexed_iter().find(|(_, &v)| !v) {
            return Err(Error::data(
                DataCause::NotFinite,
                format!(
                    "{bad} height samples are invalid (masked), the first at row {i}, column {j}: \
                 an STL needs a height everywhere (fill or crop the map first)"
                ),
            ));
        }
    }
    if let Some((count, (i, j))) = heights.non_finite() {
        return Err(Error::data(
            DataCause::NotFinite,
            format!(
                "{count} height samples are not finite (NaN or infinite), the first at row {i}, column {j}"
            ),
        ));
    }
    if !(base_thickness.is_finite() && base_thickness > 0.0) {
        return Err(Error::param_in(
            "base_thickness",
            Allowed::positive(),
            format!("must be finite and positive (a closed solid needs a base), got {base_thickness} m"),
        ));
    }
    heights.min_max().ok_or_else(|| Error::data(DataCause::Empty, "the height map holds no sample"))
}

/// Meshes a quantized height map (metres) exactly as terraces; see the module docs and
/// `stl/terrace.rs` for the algorithm.
///
/// Saddle corners (both pixels of one diagonal lower than both of the other, e.g. a
/// checkerboard) would make four walls share one vertical edge, which no manifold allows. They
/// are resolved by a tiny chamfer: the corner of the top-right pixel is cut by a 45-degree
/// segment whose legs are [`CHAMFER_FRACTION`] of the pitch and the cut triangle joins the
/// bottom-right pixel's terrace. The reported `max_lateral_deviation` is the distance from the
/// cut corner to that segment; each chamfer changes the volume by
/// `CHAMFER_FRACTION^2 / 2 * p_x * p_y * |h_BR - h_TR|`.
pub fn terrace_mesh(heights: &Grid, base_thickness: f64) -> Result<Mesh> {
    let (lo, _) = check_input(heights, base_thickness)?;
    terrace::mesh(heights, lo - base_thickness, base_thickness)
}

/// Meshes a continuous height map (metres) as a TIN through the pixel centres, simplified by
/// greedy insertion until every pixel centre lies within `max_error` (metres) of the surface;
/// the achieved maximum error is measured over all pixel centres and reported. The outline runs
/// through the outermost pixel centres (the footprint is one pitch smaller than the map's in x
/// and y). Needs at least 2 x 2 samples.
pub fn heightfield_mesh(heights: &Grid, base_thickness: f64, max_error: f64) -> Result<Mesh> {
    let (lo, _) = check_input(heights, base_thickness)?;
    if !(max_error.is_finite() && max_error > 0.0) {
        return Err(Error::param_in(
            "max_error",
            Allowed::positive(),
            format!("must be finite and positive, got {max_error} m"),
        ));
    }
    let (nr, nc) = heights.dim();
    if nr < 2 || nc < 2 {
        return Err(Error::data(
            DataCause::TooFew,
            format!("a heightfield mesh needs at least 2 x 2 samples, got {nr} x {nc} (use terraces)"),
        ));
    }
    heightfield::mesh(heights, lo - base_thickness, base_thickness, max_error)
}

/// Number of distinct heights, counting up to `limit + 1`.
fn distinct_heights(heights: &Grid, limit: usize) -> usize {
    let mut seen = std::collections::HashSet::new();
    let mut last = None;
    for &v in heights.values() {
        let bits = if v == 0.0 { 0 } else { v.to_bits() };
        if last == Some(bits) {
            continue;
        }
        last = Some(bits);
        seen.insert(bits);
        if seen.len() > limit {
            break;
        }
    }
    seen.len()
}

/// Meshes with the mesher `opts.surface` selects.
pub fn surface_mesh(heights: &Grid, opts: &StlOptions) -> Result<Mesh> {
    let terraces = match opts.surface {
        SurfaceChoice::Terraces => true,
        SurfaceChoice::Heightfield => false,
        SurfaceChoice::Auto => {
            let (nr, nc) = heights.dim();
            nr < 2
                || nc < 2
                || distinct_heights(heights, AUTO_TERRACE_MAX_HEIGHTS) <= AUTO_TERRACE_MAX_HEIGHTS
        }
    };
    if terraces {
        terrace_mesh(heights, opts.base_thickness)
    } else {
        heightfield_mesh(heights, opts.base_thickness, opts.max_error)
    }
}

/// Meshes `heights` and writes the binary STL to `path`.
pub fn surface_stl(heights: &Grid, opts: &StlOptions, path: &Path) -> Result<StlStats> {
    let mesh = surface_mesh(heights, opts)?;
    write_stl(&mesh, opts.unit, path)
}

/// Converts a level map (integers 0..N-1, [`Unit::Level`]) into heights `level * period / N`
/// (metres), the quantization convention of the fabrication stage.
pub fn level_heights(levels: &Grid, level_count: usize, period: f64) -> Result<Grid> {
    if level_count == 0 {
        return Err(Error::param_in("level_count", Allowed::at_least(1.0), "must be at least 1"));
    }
    if !(period.is_finite() && period > 0.0) {
        return Err(Error::param_in(
            "period",
            Allowed::positive(),
            format!("must be finite and positive, got {period} m"),
        ));
    }
    let n = level_count as f64;
    for ((i, j), &v) in levels.values().indexed_iter() {
        if levels.is_valid(i, j) && !(v.fract() == 0.0 && v >= 0.0 && v < n) {
            return Err(Error::data(
                DataCause::OutOfRange,
                format!(
                    "level map: sample at row {i}, column {j} is {v}, not an integer in 0..{level_count}"
                ),
            ));
        }
    }
    levels.map_values(levels.values().mapv(|l| l * period / n), Unit::Metre)
}

/// Formats a length in `unit` with 4 significant digits, in plain decimal notation.
fn header_number(metres: f64, unit: StlUnit) -> String {
    let v = metres / unit.metres();
    if v == 0.0 || !v.is_finite() {
        return "0".into();
    }
    let decimals = (3 - v.abs().log10().floor() as i32).clamp(0, 12) as usize;
    let s = format!("{v:.decimals$}");
    let s = if s.contains('.') { s.trim_end_matches('0').trim_end_matches('.') } else { &s };
    s.to_string()
}

/// The 80-byte header, padded with spaces: `doefab STL units=<mm|um> [part=<design|master>]
/// base=<t> mesh=<kind>
/// max_err=<e> lat=<d>` (lengths in the file's unit: base thickness, largest height error,
/// largest lateral deviation of an outline).
fn header(mesh: &Mesh, unit: StlUnit, part: Option<&str>) -> [u8; 80] {
    let mut text = format!("doefab STL units={}", unit.symbol());
    for field in [
        part.map(|p| format!("part={p}")).unwrap_or_default(),
        format!("base={}", header_number(mesh.base_thickness, unit)),
        format!("mesh={}", mesh.kind.name()),
        format!("max_err={}", header_number(mesh.max_height_error, unit)),
        format!("lat={}", header_number(mesh.max_lateral_deviation, unit)),
    ] {
        // A field that does not fit whole is left out rather than cut.
        if !field.is_empty() && text.len() + 1 + field.len() <= 80 {
            text.push(' ');
            text.push_str(&field);
        }
    }
    let mut h = [b' '; 80];
    let n = text.len().min(80);
    h[..n].copy_from_slice(&text.as_bytes()[..n]);
    h
}

/// Writes `mesh` as binary STL in `unit` (atomically) and reports what was written.
/// Vertices are rounded to `f32` once, so shared vertices stay bit-identical; normals are
/// computed from the rounded vertices.
pub fn write_stl(mesh: &Mesh, unit: StlUnit, path: &Path) -> Result<StlStats> {
    write_stl_part(mesh, unit, None, path)
}

/// [`write_stl`] with the part named in the header (`part=master` or `part=design`).
pub fn write_stl_part(mesh: &Mesh, unit: StlUnit, part: Option<&str>, path: &Path) -> Result<StlStats> {
    let count = u32::try_from(mesh.triangles.len()).map_err(|_| {
        let what =
            format!("{} triangles do not fit a binary STL (at most {})", mesh.triangles.len(), u32::MAX);
        Error::limit(Resource::Triangles, mesh.triangles.len() as f64, f64::from(u32::MAX), what)
    })?;
    let scale = 1.0 / unit.metres();
    let verts: Vec<[f32; 3]> = mesh
        .vertices
        .iter()
        .map(|v| [(v[0] * scale) as f32, (v[1] * scale) as f32, (v[2] * scale) as f32])
        .collect();
    let head = header(mesh, unit, part);
    write_atomic(path, |w| {
        let io = |e| Error::io(path, e);
        w.write_all(&head).map_err(io)?;
        w.write_all(&count.to_le_bytes()).map_err(io)?;
        let mut buf = Vec::with_capacity(50 * 4096);
        for chunk in mesh.triangles.chunks(4096) {
            buf.clear();
            for t in chunk {
                let [a, b, c] = t.map(|k| verts[k as usize]);
                let n = unit_normal(a, b, c);
                for v in [n, a, b, c] {
                    for x in v {
                        buf.extend_from_slice(&x.to_le_bytes());
                    }
                }
                buf.extend_from_slice(&[0, 0]);
            }
            w.write_all(&buf).map_err(io)?;
        }
        Ok(())
    })?;
    let (lo, hi) = mesh.bounds();
    let text = String::from_utf8_lossy(&head).trim_end().to_string();
    Ok(StlStats {
        unit,
        header: text,
        surface: mesh.kind,
        triangles: count as u64,
        vertices: mesh.vertices.len() as u64,
        naive_triangles: mesh.naive_triangles,
        triangle_ratio: count as f64 / mesh.naive_triangles.max(1) as f64,
        max_height_error: mesh.max_height_error,
        max_lateral_deviation: mesh.max_lateral_deviation,
        chamfers: mesh.chamfers,
        base_thickness: mesh.base_thickness,
        volume: mesh.volume(),
        size: [hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]],
    })
}

/// Unit normal of triangle (a, b, c) by the right-hand rule, zero for a degenerate one.
fn unit_normal(a: [f32; 3], b: [f32; 3], c: [f32; 3]) -> [f32; 3] {
    let u = [(b[0] - a[0]) as f64, (b[1] - a[1]) as f64, (b[2] - a[2]) as f64];
    let v = [(c[0] - a[0]) as f64, (c[1] - a[1]) as f64, (c[2] - a[2]) as f64];
    let n = [u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0]];
    let len = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
    if len > 0.0 {
        n.map(|x| (x / len) as f32)
    } else {
        [0.0; 3]
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Lcg;
    use ndarray::Array2;

    fn grid(v: Array2<f64>, pitch: [f64; 2]) -> Grid {
        Grid::new(v, pitch, Unit::Metre).unwrap()
    }

    /// sum over pixels of (h - h_min + t) * p_x * p_y.
    fn pixel_volume(g: &Grid, t: f64) -> f64 {
        let (lo, _) = g.min_max().unwrap();
        g.values().iter().map(|h| h - lo + t).sum::<f64>() * g.pitch()[0] * g.pitch()[1]
    }

    /// Height of the upward-facing surface above (x, y) in the STL frame, from every
    /// upward triangle whose projection contains the point (all of them must agree).
    fn top_heights_at(mesh: &Mesh, x: f64, y: f64) -> Vec<f64> {
        let v = mesh.vertices();
        let mut out = Vec::new();
        for t in mesh.triangles() {
            let [a, b, c] = t.map(|k| v[k as usize]);
            let det = (b[0] - a[0]) * (c[1] - a[1]) - (c[0] - a[0]) * (b[1] - a[1]);
            if det <= 0.0 {
                continue; // wall, base or face looking down
            }
            let l1 = ((x - a[0]) * (c[1] - a[1]) - (c[0] - a[0]) * (y - a[1])) / det;
            let l2 = ((b[0] - a[0]) * (y - a[1]) - (x - a[0]) * (b[1] - a[1])) / det;
            let l0 = 1.0 - l1 - l2;
            let eps = -1e-9;
            if l0 >= eps && l1 >= eps && l2 >= eps {
                out.push(l0 * a[2] + l1 * b[2] + l2 * c[2]);
            }
        }
        out
    }

    /// Closed, oriented, right volume, top surface at every pixel centre at the pixel height,
    /// z range = height range + base, no degenerate triangle.
    fn check_terraces(g: &Grid, t: f64) -> Mesh {
        let m = terrace_mesh(g, t).unwrap();
        m.check_closed().unwrap();
        let (lo, hi) = g.min_max().unwrap();
        let (pxx, pyy) = (g.pitch()[0], g.pitch()[1]);
        let d = CHAMFER_FRACTION;
        let slack = m.chamfers() as f64 * 0.5 * d * d * pxx * pyy * (hi - lo);
        let want = pixel_volume(g, t);
        let got = m.volume();
        assert!((got - want).abs() <= slack + 1e-12 * want, "volume {got} vs {want} (slack {slack})");
        let (bl, bh) = m.bounds();
        assert!((bh[2] - hi).abs() <= 1e-15 * hi.abs().max(1.0) && (bl[2] - (lo - t)).abs() < 1e-15);
        let ext = g.extent();
        assert!(((bh[0] - bl[0]) - ext[0]).abs() < 1e-12 && ((bh[1] - bl[1]) - ext[1]).abs() < 1e-12);
        let v = m.vertices();
        for tr in m.triangles() {
            let [a, b, c] = tr.map(|k| v[k as usize]);
            let u = [b[0] - a[0], b[1] - a[1], b[2] - a[2]];
            let w = [c[0] - a[0], c[1] - a[1], c[2] - a[2]];
            let n = [u[1] * w[2] - u[2] * w[1], u[2] * w[0] - u[0] * w[2], u[0] * w[1] - u[1] * w[0]];
            assert!(n.iter().map(|x| x * x).sum::<f64>() > 0.0, "degenerate triangle {tr:?}");
        }
        let (nr, nc) = g.dim();
        for i in 0..nr {
            for j in 0..nc {
                let (x, y) = (g.x(j), -g.y(i));
                let hs = top_heights_at(&m, x, y);
                assert!(!hs.is_empty(), "pixel ({i}, {j}) has no top");
                let want = g.values()[[i, j]];
                assert!(hs.iter().all(|h| (h - want).abs() < 1e-18), "pixel ({i}, {j}): {hs:?} vs {want}");
            }
        }
        m
    }

    fn levels(n: usize, m: usize, count: u32, seed: u64) -> Array2<f64> {
        let mut r = Lcg(seed);
        Array2::from_shape_fn((n, m), |_| (r.uniform() * count as f64).floor() * 0.1e-6)
    }

    #[test]
    fn single_pixel_and_flat_map_are_boxes() {
        let m = check_terraces(&grid(Array2::from_elem((1, 1), 2e-6), [3e-6, 5e-6]), 1e-6);
        assert_eq!(m.triangles().len(), 2 + 8 + 4);
        let m = check_terraces(&grid(Array2::from_elem((7, 9), 0.0), [1e-6, 1e-6]), 4e-6);
        assert_eq!(m.triangles().len(), 2 + 8 + 4);
        assert_eq!(m.chamfers(), 0);
        assert_eq!(m.max_lateral_deviation(), 0.0);
    }

    #[test]
    fn a_few_levels_on_a_small_grid() {
        let v = Array2::from_shape_fn((6, 8), |(i, j)| {
            if (2..5).contains(&i) && (1..6).contains(&j) {
                if j > 3 {
                    3e-7
                } else {
                    2e-7
                }
            } else if j == 7 {
                1e-7
            } else {
                0.0
            }
        });
        let m = check_terraces(&grid(v, [1e-6, 2e-6]), 1e-6);
        assert_eq!(m.chamfers(), 0);
        assert_eq!(m.kind(), SurfaceKind::Terraces);
    }

    #[test]
    fn random_maps_with_saddles_are_closed() {
        for (seed, count) in [(1, 16), (2, 2), (3, 3), (4, 4)] {
            let v = levels(23, 31, count, seed);
            let m = check_terraces(&grid(v, [1e-6, 1e-6]), 2e-6);
            assert!(m.chamfers() > 0, "seed {seed}: random maps have saddles");
        }
    }

    #[test]
    fn checkerboards_of_two_and_three_levels() {
        let v = Array2::from_shape_fn((8, 8), |(i, j)| ((i + j) % 2) as f64 * 1e-7);
        let m = check_terraces(&grid(v, [1e-6, 1e-6]), 1e-6);
        assert_eq!(m.chamfers(), 49);
        let lat = m.max_lateral_deviation();
        assert!((lat - CHAMFER_FRACTION * 1e-6 / 2f64.sqrt()).abs() < 1e-20);
        // TL = BR high, TR and BL two different lower levels (and the mirror images).
        let v = Array2::from_shape_fn((9, 7), |(i, j)| match ((i + j) % 2, i % 2) {
            (0, _) => 3e-7,
            (1, 0) => 1e-7,
            _ => 2e-7,
        });
        check_terraces(&grid(v.clone(), [1e-6, 1e-6]), 1e-6);
        check_terraces(&grid(v.mapv(|h| 4e-7 - h), [1e-6, 1e-6]), 1e-6);
        let mut w = v.clone();
        w.invert_axis(ndarray::Axis(1));
        check_terraces(&grid(w.as_standard_layout().to_owned(), [1e-6, 1e-6]), 1e-6);
    }

    #[test]
    fn floyd_steinberg_dither_is_closed() {
        // Error diffusion of a smooth ramp to 2 and 4 levels: many diagonal contacts.
        for count in [2.0, 4.0] {
            let (n, m) = (24, 30);
            let mut f = Array2::from_shape_fn((n, m), |(i, j)| {
                (count - 1.0) * (0.5 + 0.45 * ((i as f64 * 0.3).sin() * (j as f64 * 0.21).cos()))
            });
            let mut out = Array2::zeros((n, m));
            for i in 0..n {
                for j in 0..m {
                    let q = f[[i, j]].round().clamp(0.0, count - 1.0);
                    let e = f[[i, j]] - q;
                    out[[i, j]] = q * 5e-8;
                    if j + 1 < m {
                        f[[i, j + 1]] += e * 7.0 / 16.0;
                    }
                    if i + 1 < n {
                        if j > 0 {
                            f[[i + 1, j - 1]] += e * 3.0 / 16.0;
                        }
                        f[[i + 1, j]] += e * 5.0 / 16.0;
                        if j + 1 < m {
                            f[[i + 1, j + 1]] += e / 16.0;
                        }
                    }
                }
            }
            let m = check_terraces(&grid(out, [2e-6, 1e-6]), 3e-6);
            assert!(m.chamfers() > 0);
        }
    }

    #[test]
    fn negative_heights_and_offset_origin() {
        let v = levels(10, 12, 5, 9).mapv(|h| h - 3e-7);
        let g = grid(v, [1e-6, 1e-6]).with_origin([1e-3, -2e-3]);
        check_terraces(&g, 1e-6);
    }

    #[test]
    fn terraces_of_a_smooth_map_need_few_triangles() {
        // Concentric terraces (a quantized paraboloid) on 80 x 80 design pixels, each made of
        // 4 x 4 fabrication pixels (as after resampling a design to a finer writing grid).
        let v = Array2::from_shape_fn((320, 320), |(i, j)| {
            let r2 = ((i / 4) as f64 - 39.5).powi(2) + ((j / 4) as f64 - 39.5).powi(2);
            (r2 / 200.0).floor().min(15.0) * 1e-7
        });
        let m = terrace_mesh(&grid(v, [1e-6, 1e-6]), 1e-6).unwrap();
        m.check_closed().unwrap();
        assert!((m.triangles().len() as f64) < 0.05 * m.naive_triangles() as f64, "{}", m.triangles().len());
    }

    fn paraboloid(n: usize, m: usize) -> Grid {
        let v = Array2::from_shape_fn((n, m), |(i, j)| {
            let (x, y) = (j as f64 - 0.4 * m as f64, i as f64 - 0.55 * n as f64);
            1e-6 * (1.0 - (x * x + y * y) / (n * n + m * m) as f64)
        });
        grid(v, [1e-6, 1.5e-6])
    }

    #[test]
    fn heightfield_honours_the_error_bound() {
        let g = paraboloid(41, 53);
        let tol = 2e-9;
        let m = heightfield_mesh(&g, 1e-6, tol).unwrap();
        m.check_closed().unwrap();
        assert_eq!(m.kind(), SurfaceKind::Heightfield);
        let reported = m.max_height_error();
        assert!(reported <= tol && reported > 0.0);
        // Measure the error independently at every pixel centre.
        let mut measured = 0.0f64;
        for i in 0..41 {
            for j in 0..53 {
                let hs = top_heights_at(&m, g.x(j), -g.y(i));
                assert!(!hs.is_empty());
                for h in hs {
                    measured = measured.max((h - g.values()[[i, j]]).abs());
                }
            }
        }
        assert!((measured - reported).abs() < 1e-15, "{measured} vs {reported}");
        assert!(m.triangles().len() < m.naive_triangles() as usize / 2);
        // Volume: trapezoid rule over the pixel-centre footprint, within the error bound.
        let (lo, _) = g.min_max().unwrap();
        let mut vol = 0.0;
        for i in 0..41 {
            for j in 0..53 {
                let w = if i == 0 || i == 40 { 0.5 } else { 1.0 } * if j == 0 || j == 52 { 0.5 } else { 1.0 };
                vol += w * (g.values()[[i, j]] - lo + 1e-6);
            }
        }
        let area = 40.0 * 52.0 * 1e-6 * 1.5e-6;
        vol *= 1e-6 * 1.5e-6;
        // The paraboloid's curvature adds at most |h''| p^2 / 8 per cell between samples.
        let curv = 2e-6 / (41.0 * 41.0 + 53.0 * 53.0) / 8.0;
        assert!((m.volume() - vol).abs() <= (tol + curv) * area, "{} vs {vol}", m.volume());
        // A tighter tolerance needs more triangles; a huge one just the two corner triangles.
        let fine = heightfield_mesh(&g, 1e-6, 1e-10).unwrap();
        assert!(fine.triangles().len() > m.triangles().len());
        let coarse = heightfield_mesh(&g, 1e-6, 1.0).unwrap();
        coarse.check_closed().unwrap();
        assert!(coarse.triangles().len() <= 6 + 6 * 3, "{}", coarse.triangles().len());
    }

    #[test]
    fn bad_inputs_are_refused() {
        let mut v = Array2::from_elem((4, 4), 1e-7);
        v[[1, 2]] = f64::NAN;
        let e = terrace_mesh(&grid(v.clone(), [1e-6, 1e-6]), 1e-6).unwrap_err();
        assert!(
            matches!(e, Error::Data { cause: DataCause::NotFinite, .. })
                && e.to_string().contains("row 1, column 2"),
            "{e:?}"
        );
        let masked = Grid::from_values_nan_invalid(v, [1e-6, 1e-6], Unit::Metre).unwrap();
        let e = terrace_mesh(&masked, 1e-6).unwrap_err();
        assert!(
            matches!(e, Error::Data { cause: DataCause::NotFinite, .. })
                && e.to_string().contains("row 1, column 2"),
            "{e:?}"
        );
        assert!(heightfield_mesh(&masked, 1e-6, 1e-9).is_err());
        let ok = grid(Array2::from_elem((4, 4), 1e-7), [1e-6, 1e-6]);
        for t in [-1e-6, 0.0, f64::NAN, f64::INFINITY] {
            let e = terrace_mesh(&ok, t).unwrap_err();
            assert!(matches!(e, Error::Parameter { ref name, .. } if name == "base_thickness"), "{e:?}");
        }
        let e = heightfield_mesh(&ok, 1e-6, 0.0).unwrap_err();
        assert!(matches!(e, Error::Parameter { ref name, .. } if name == "max_error"), "{e:?}");
        let row = grid(Array2::from_elem((1, 5), 0.0), [1e-6, 1e-6]);
        let e = heightfield_mesh(&row, 1e-6, 1e-9).unwrap_err();
        assert!(matches!(e, Error::Data { cause: DataCause::TooFew, .. }), "{e:?}");
        let lv = Grid::new(Array2::from_elem((2, 2), 1.0), [1e-6, 1e-6], Unit::Level).unwrap();
        let e = terrace_mesh(&lv, 1e-6).unwrap_err();
        assert!(
            matches!(e, Error::Parameter { ref name, .. } if name == "heights")
                && e.to_string().contains("level_heights"),
            "{e:?}"
        );
    }

    #[test]
    fn level_maps_convert_with_the_quantization_convention() {
        let lv =
            Grid::new(Array2::from_shape_fn((2, 3), |(i, j)| (i * 3 + j) as f64), [1e-6; 2], Unit::Level)
                .unwrap();
        let h = level_heights(&lv, 8, 1.6e-6).unwrap();
        assert_eq!(h.unit(), Unit::Metre);
        assert!((h.values()[[1, 2]] - 5.0 * 0.2e-6).abs() < 1e-20);
        assert!(level_heights(&lv, 4, 1e-6).is_err());
        let half = lv.map_values(lv.values().mapv(|v| v + 0.5), Unit::Level).unwrap();
        assert!(level_heights(&half, 8, 1e-6).is_err());
    }

    #[test]
    fn auto_choice_and_file_layout() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("a.stl");
        let g = grid(levels(5, 6, 4, 7), [1e-6, 1e-6]);
        let opts = StlOptions { base_thickness: 1e-6, ..Default::default() };
        let r = surface_stl(&g, &opts, &path).unwrap();
        assert_eq!(r.surface, SurfaceKind::Terraces);
        let bytes = std::fs::read(&path).unwrap();
        assert_eq!(bytes.len() as u64, 84 + 50 * r.triangles);
        assert!(bytes.starts_with(b"doefab STL units=mm base=0.001 mesh=terraces"), "{}", r.header);
        assert_eq!(u32::from_le_bytes(bytes[80..84].try_into().unwrap()) as u64, r.triangles);
        // Deterministic output.
        let path2 = dir.path().join("b.stl");
        surface_stl(&g, &opts, &path2).unwrap();
        assert_eq!(bytes, std::fs::read(&path2).unwrap());
        let um = surface_stl(&g, &StlOptions { unit: StlUnit::Micrometre, ..opts }, &path2).unwrap();
        assert!(um.header.starts_with("doefab STL units=um base=1 "), "{}", um.header);
        let r = surface_stl(&paraboloid(24, 30), &opts, &path).unwrap();
        assert_eq!(r.surface, SurfaceKind::Heightfield);
        assert!(r.max_height_error <= opts.max_error);
    }

    #[test]
    fn thousands_of_small_random_maps_are_closed_manifolds() {
        // Every 2x2 .. 7x7 configuration family with 3 to 6 levels, including corners with
        // four different levels in every order.
        let mut rng = Lcg(77);
        for count in 3..7u32 {
            for n in 2..8 {
                for m in 2..8 {
                    for _ in 0..40 {
                        let v =
                            Array2::from_shape_fn((n, m), |_| (rng.uniform() * count as f64).floor() * 1e-7);
                        let g = grid(v, [1e-6, 1e-6]);
                        let mesh = terrace_mesh(&g, 1e-6).unwrap();
                        if let Err(e) = mesh.check_closed() {
                            panic!("{:?}: {e}", g.values());
                        }
                        let (lo, hi) = g.min_max().unwrap();
                        let slack = mesh.chamfers() as f64 * CHAMFER_FRACTION.powi(2) * 0.5e-12 * (hi - lo);
                        assert!((mesh.volume() - pixel_volume(&g, 1e-6)).abs() <= slack + 1e-30);
                    }
                }
            }
        }
    }

    #[test]
    fn the_closedness_check_finds_defects() {
        let g = grid(levels(6, 7, 4, 5), [1e-6, 1e-6]);
        let good = terrace_mesh(&g, 1e-6).unwrap();
        good.check_closed().unwrap();
        let mut hole = good.clone();
        hole.triangles.pop();
        assert!(hole.check_closed().is_err());
        let mut flipped = good.clone();
        flipped.triangles[3].swap(0, 1);
        assert!(flipped.check_closed().is_err());
        // Two tetrahedra sharing one vertex: closed edges, pinched vertex.
        let tet = |o: u32| [[o, o + 2, o + 1], [o, o + 1, o + 3], [o + 1, o + 2, o + 3], [o, o + 3, o + 2]];
        let mut tris: Vec<[u32; 3]> = tet(0).to_vec();
        tris.extend(tet(3));
        let pinched = Mesh { vertices: vec![[0.0; 3]; 7], triangles: tris, ..good };
        assert!(pinched.check_closed().unwrap_err().contains("pinched"));
    }

    #[test]
    fn header_numbers_and_length() {
        assert_eq!(header_number(0.5e-3, StlUnit::Millimetre), "0.5");
        assert_eq!(header_number(1.104854e-8, StlUnit::Millimetre), "0.00001105");
        assert_eq!(header_number(1234.6e-6, StlUnit::Micrometre), "1235");
        assert_eq!(header_number(0.0, StlUnit::Micrometre), "0");
        // A long case still fits in 80 bytes without cutting a field.
        let g = grid(Array2::from_elem((2, 2), 0.0), [1e-6, 1e-6]);
        let mut m = terrace_mesh(&g, 12.3456e-3).unwrap();
        m.kind = SurfaceKind::Heightfield;
        m.max_height_error = 1.234e-9;
        m.max_lateral_deviation = 1.234e-5;
        let h = String::from_utf8(header(&m, StlUnit::Millimetre, None).to_vec()).unwrap();
        assert!(h.trim_end().ends_with("lat=0.01234"), "{h}");
        let h = String::from_utf8(header(&m, StlUnit::Millimetre, Some("master")).to_vec()).unwrap();
        assert!(h.starts_with("doefab STL units=mm part=master base=12.35 mesh=heightfield"), "{h}");
    }
}
