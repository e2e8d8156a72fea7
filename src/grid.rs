//! The one physical data model every stage consumes and produces: a sampled 2-D grid.
//!
//! A [`Grid`] is an `ndarray` of `f64` values (row index = y, column index = x) that carries
//!
//! * its pitch in x and y, in metres (the distance between neighbouring sample centres),
//! * its origin: the (x, y) position in metres of the centre of sample (0, 0),
//! * the [`Unit`] of its values (heights in metres, phase in radians, levels, ...),
//! * a validity mask: `false` marks a non-measured sample. Invalid samples are never data;
//!   their value is kept at 0 and no statistic reads it.
//!
//! Guarantees (checked by [`Grid::new`]): both pitches are finite and positive, the shape is
//! at least 1 x 1, the mask (if any) has the shape of the values.
//!
//! Geometric operations (resample, crop, pad, mirror, rotate) and the filling of non-measured
//! samples ([`fill`]) live here so that every stage treats sampling the same way. Sample `(i, j)` sits at
//! `x = origin_x + j * pitch_x`, `y = origin_y + i * pitch_y`.
//!
//! Its 1-D counterpart, a height profile along a line (a stylus profiler's), is
//! [`profile::Profile`].

pub mod blur;
pub mod fill;
pub mod profile;
pub mod row_blocks;

use ndarray::{s, Array2};
use serde::{Deserialize, Serialize};

use crate::error::{Allowed, DataCause, Error, Result};

/// What a grid's values mean.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Unit {
    /// A height or depth in metres.
    Metre,
    /// A phase in radians.
    Radian,
    /// A quantization level index 0..N-1 (dimensionless integer).
    Level,
    /// A dimensionless quantity (intensity fractions, transmission, gray).
    Dimensionless,
}

impl Unit {
    /// The unit symbol written into output metadata.
    pub fn symbol(self) -> &'static str {
        match self {
            Unit::Metre => "m",
            Unit::Radian => "rad",
            Unit::Level => "level",
            Unit::Dimensionless => "1",
        }
    }
}

/// Interpolation kernels for [`Grid::resample`] and [`Grid::rotate`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum Interpolation {
    /// Value of the nearest source sample (keeps quantized levels exact).
    Nearest,
    /// Box average of the source samples overlapping each target cell, weighted by overlap
    /// area (the right choice when reducing resolution: it conserves the mean).
    Area,
    /// Bilinear interpolation between the four nearest samples.
    #[default]
    Bilinear,
    /// Keys cubic convolution (a = -0.5), Keys 1981, IEEE Trans. ASSP 29(6).
    Bicubic,
}

/// A sampled 2-D field with pitch, origin, unit and validity mask. See the module docs.
#[derive(Debug, Clone, PartialEq)]
pub struct Grid {
    values: Array2<f64>,
    pitch: [f64; 2],
    origin: [f64; 2],
    unit: Unit,
    valid: Option<Array2<bool>>,
}

impl Grid {
    /// A grid with every sample valid. `pitch` is `[x, y]` in metres; the origin is set so that
    /// the grid is centred on (0, 0).
    pub fn new(values: Array2<f64>, pitch: [f64; 2], unit: Unit) -> Result<Self> {
        check_pitch(pitch)?;
        let (rows, cols) = values.dim();
        if rows == 0 || cols == 0 {
            return Err(Error::data(
                DataCause::Empty,
                format!("a grid needs at least 1 x 1 samples, got {rows} x {cols}"),
            ));
        }
        let origin = [-(cols as f64 - 1.0) * 0.5 * pitch[0], -(rows as f64 - 1.0) * 0.5 * pitch[1]];
        Ok(Grid { values, pitch, origin, unit, valid: None })
    }

    /// Attaches a validity mask (`false` = not measured). Invalid samples are set to 0.
    pub fn with_mask(mut self, valid: Array2<bool>) -> Result<Self> {
        if valid.dim() != self.values.dim() {
            return Err(Error::data(
                DataCause::Shape,
                format!("validity mask is {:?} but values are {:?}", valid.dim(), self.values.dim()),
            ));
        }
        ndarray::Zip::from(&mut self.values).and(&valid).for_each(|v, &ok| {
            if !ok {
                *v = 0.0
            }
        });
        self.valid = if valid.iter().all(|&v| v) { None } else { Some(valid) };
        Ok(self)
    }

    /// Sets the position of the centre of sample (0, 0), metres.
    pub fn with_origin(mut self, origin: [f64; 2]) -> Self {
        self.origin = origin;
        self
    }

    /// Builds a grid whose non-finite values are marked invalid (how NaN-bearing files arrive).
    pub fn from_values_nan_invalid(values: Array2<f64>, pitch: [f64; 2], unit: Unit) -> Result<Self> {
        let all_finite =
            row_blocks::map_blocks(&values, |_, b| b.iter().all(|v| v.is_finite())).into_iter().all(|f| f);
        if all_finite {
            return Grid::new(values, pitch, unit);
        }
        let valid = values.mapv(f64::is_finite);
        Grid::new(values, pitch, unit)?.with_mask(valid)
    }

    /// The values with invalid samples as NaN (how NaN-bearing files store them; the inverse of
    /// [`Grid::from_values_nan_invalid`] for finite valid values).
    pub fn values_nan_invalid(&self) -> Array2<f64> {
        Array2::from_shape_fn(self.values.dim(), |(i, j)| {
            if self.is_valid(i, j) {
                self.values[[i, j]]
            } else {
                f64::NAN
            }
        })
    }

    /// The values, `(rows, cols)` = `(ny, nx)`, in [`Grid::unit`]; invalid samples hold 0.
    pub fn values(&self) -> &Array2<f64> {
        &self.values
    }
    /// Mutable access to the values; the mask stays as it is.
    pub fn values_mut(&mut self) -> &mut Array2<f64> {
        &mut self.values
    }
    /// Mutable access to the values together with the mask (for passes that change values in
    /// place and skip the invalid samples).
    pub fn values_mut_and_mask(&mut self) -> (&mut Array2<f64>, Option<&Array2<bool>>) {
        (&mut self.values, self.valid.as_ref())
    }
    /// The values, the grid consumed (invalid samples hold 0; pitch, origin and mask dropped).
    pub fn into_values(self) -> Array2<f64> {
        self.values
    }
    /// The same grid with its values now meaning `unit` (changed in place by the caller).
    pub fn into_unit(self, unit: Unit) -> Grid {
        Grid { unit, ..self }
    }
    /// `[x, y]` pitch in metres.
    pub fn pitch(&self) -> [f64; 2] {
        self.pitch
    }
    /// `[x, y]` position of the centre of sample (0, 0), metres.
    pub fn origin(&self) -> [f64; 2] {
        self.origin
    }
    /// What the values mean.
    pub fn unit(&self) -> Unit {
        self.unit
    }
    /// `(rows, cols)` = `(ny, nx)`.
    pub fn dim(&self) -> (usize, usize) {
        self.values.dim()
    }
    /// Physical extent `[x, y]` in metres, counted as samples x pitch (each sample owns a cell).
    pub fn extent(&self) -> [f64; 2] {
        let (r, c) = self.dim();
        [c as f64 * self.pitch[0], r as f64 * self.pitch[1]]
    }
    /// The validity mask, `None` when every sample is valid.
    pub fn mask(&self) -> Option<&Array2<bool>> {
        self.valid.as_ref()
    }
    /// Whether sample `(i, j)` (row, column) is measured; every sample is when there is no mask.
    pub fn is_valid(&self, i: usize, j: usize) -> bool {
        self.valid.as_ref().is_none_or(|m| m[[i, j]])
    }
    /// Number of valid samples.
    pub fn valid_count(&self) -> usize {
        match &self.valid {
            None => self.values.len(),
            Some(m) => m.iter().filter(|&&v| v).count(),
        }
    }
    /// Returns a copy with the values replaced (same geometry, mask and unit given).
    pub fn map_values(&self, values: Array2<f64>, unit: Unit) -> Result<Grid> {
        if values.dim() != self.values.dim() {
            return Err(Error::data(
                DataCause::Shape,
                format!("replacement values are {:?}, grid is {:?}", values.dim(), self.values.dim()),
            ));
        }
        Ok(Grid { values, pitch: self.pitch, origin: self.origin, unit, valid: self.valid.clone() })
    }
    /// x coordinate (metres) of column `j`.
    pub fn x(&self, j: usize) -> f64 {
        self.origin[0] + j as f64 * self.pitch[0]
    }
    /// y coordinate (metres) of row `i`.
    pub fn y(&self, i: usize) -> f64 {
        self.origin[1] + i as f64 * self.pitch[1]
    }

    /// The valid flags of rows `r0..r0 + n` (`None` when every sample is valid).
    fn mask_rows(&self, r0: usize, n: usize) -> Option<ndarray::ArrayView2<'_, bool>> {
        self.valid.as_ref().map(|m| m.slice(s![r0..r0 + n, ..]))
    }

    /// Minimum and maximum over valid samples (NaN values ignored), `None` if none is valid.
    /// Computed in parallel over row blocks ([`row_blocks`]).
    pub fn min_max(&self) -> Option<(f64, f64)> {
        self.min_max_finite().0
    }

    /// [`Grid::min_max`], and whether every valid sample is finite, from one pass
    /// ([`Grid::non_finite`] then says which are not).
    pub fn min_max_finite(&self) -> (Option<(f64, f64)>, bool) {
        let start = (f64::INFINITY, f64::NEG_INFINITY, true);
        let parts = row_blocks::map_blocks(&self.values, |r0, b| {
            let fold = |(lo, hi, finite): (f64, f64, bool), &v: &f64| {
                (lo.min(v), hi.max(v), finite && v.is_finite())
            };
            match self.mask_rows(r0, b.nrows()) {
                None => b.iter().fold(start, fold),
                Some(m) => b.iter().zip(m.iter()).filter(|(_, ok)| **ok).map(|(v, _)| v).fold(start, fold),
            }
        });
        let (lo, hi, finite) = parts.into_iter().fold(start, |a, b| (a.0.min(b.0), a.1.max(b.1), a.2 && b.2));
        ((lo <= hi).then_some((lo, hi)), finite)
    }

    /// The first non-finite valid value (row-major order), with the count of all of them:
    /// `(count, (row, col))`.
    pub fn non_finite(&self) -> Option<(usize, (usize, usize))> {
        let parts = row_blocks::map_blocks(&self.values, |r0, b| {
            let mask = self.mask_rows(r0, b.nrows());
            let bad =
                |(i, j): (usize, usize), v: f64| !v.is_finite() && mask.as_ref().is_none_or(|m| m[[i, j]]);
            if !b.iter().any(|v| !v.is_finite()) {
                return (0, None);
            }
            let mut first = None;
            let mut count = 0;
            for ((i, j), &v) in b.indexed_iter() {
                if bad((i, j), v) {
                    count += 1;
                    first.get_or_insert((r0 + i, j));
                }
            }
            (count, first)
        });
        let count: usize = parts.iter().map(|p| p.0).sum();
        parts.into_iter().find_map(|p| p.1).map(|f| (count, f))
    }

    /// Crops rows `r0..r1` and columns `c0..c1` (half-open), keeping physical positions.
    pub fn crop(&self, rows: std::ops::Range<usize>, cols: std::ops::Range<usize>) -> Result<Grid> {
        let (nr, nc) = self.dim();
        if rows.start >= rows.end || cols.start >= cols.end || rows.end > nr || cols.end > nc {
            return Err(Error::param(
                "crop",
                format!("rows {rows:?}, cols {cols:?} do not fit a {nr} x {nc} grid"),
            ));
        }
        let sl = s![rows.start..rows.end, cols.start..cols.end];
        Ok(Grid {
            values: self.values.slice(sl).to_owned(),
            pitch: self.pitch,
            origin: [self.x(cols.start), self.y(rows.start)],
            unit: self.unit,
            valid: self.valid.as_ref().map(|m| m.slice(sl).to_owned()),
        })
    }

    /// Pads by `[top, bottom, left, right]` samples with `value`; padded samples are valid
    /// (they are known: the padding value is a statement, not a missing measurement).
    pub fn pad(&self, widths: [usize; 4], value: f64) -> Grid {
        let [t, b, l, r] = widths;
        let (nr, nc) = self.dim();
        let mut values = Array2::from_elem((nr + t + b, nc + l + r), value);
        values.slice_mut(s![t..t + nr, l..l + nc]).assign(&self.values);
        let valid = self.valid.as_ref().map(|m| {
            let mut v = Array2::from_elem((nr + t + b, nc + l + r), true);
            v.slice_mut(s![t..t + nr, l..l + nc]).assign(m);
            v
        });
        Grid {
            values,
            pitch: self.pitch,
            origin: [self.origin[0] - l as f64 * self.pitch[0], self.origin[1] - t as f64 * self.pitch[1]],
            unit: self.unit,
            valid,
        }
    }

    /// Mirrors about the vertical axis (x -> -x, columns reversed) and/or the horizontal one.
    /// The physical footprint stays where it was.
    pub fn mirror(&self, flip_x: bool, flip_y: bool) -> Grid {
        self.clone().into_mirrored(flip_x, flip_y)
    }

    /// [`Grid::mirror`] in place: the samples are moved within the grid's own storage.
    pub fn into_mirrored(mut self, flip_x: bool, flip_y: bool) -> Grid {
        self.values = mirror_array(self.values, flip_x, flip_y);
        self.into_mirrored_mask(flip_x, flip_y)
    }

    /// Mirrors the validity mask alone (for a caller that has mirrored the values itself).
    pub(crate) fn into_mirrored_mask(mut self, flip_x: bool, flip_y: bool) -> Grid {
        self.valid = self.valid.map(|m| mirror_array(m, flip_x, flip_y));
        self
    }

    /// Samples the grid at fractional index `(fi, fj)` (row, column) with `method`.
    /// Returns `None` outside the grid or where an invalid sample would contribute.
    /// `Area` behaves as `Bilinear` for a single point.
    pub fn sample_index(&self, fi: f64, fj: f64, method: Interpolation) -> Option<f64> {
        let (nr, nc) = self.dim();
        let inside = |i: isize, j: isize| i >= 0 && j >= 0 && (i as usize) < nr && (j as usize) < nc;
        let get = |i: isize, j: isize| -> Option<f64> {
            let (ci, cj) = (i.clamp(0, nr as isize - 1) as usize, j.clamp(0, nc as isize - 1) as usize);
            self.is_valid(ci, cj).then(|| self.values[[ci, cj]])
        };
        // Points within half a sample of the edge are inside the grid's footprint.
        if fi < -0.5 || fj < -0.5 || fi > nr as f64 - 0.5 || fj > nc as f64 - 0.5 {
            return None;
        }
        match method {
            Interpolation::Nearest => {
                let (i, j) = (fi.round() as isize, fj.round() as isize);
                if !inside(i, j) {
                    return get(i.clamp(0, nr as isize - 1), j.clamp(0, nc as isize - 1));
                }
                get(i, j)
            }
            Interpolation::Bilinear | Interpolation::Area => {
                let (i0, j0) = (fi.floor(), fj.floor());
                let (ti, tj) = (fi - i0, fj - j0);
                let (i0, j0) = (i0 as isize, j0 as isize);
                let v00 = get(i0, j0)?;
                let v01 = get(i0, j0 + 1)?;
                let v10 = get(i0 + 1, j0)?;
                let v11 = get(i0 + 1, j0 + 1)?;
                Some((1.0 - ti) * ((1.0 - tj) * v00 + tj * v01) + ti * ((1.0 - tj) * v10 + tj * v11))
            }
            Interpolation::Bicubic => {
                let (i0, j0) = (fi.floor(), fj.floor());
                let (ti, tj) = (fi - i0, fj - j0);
                let (i0, j0) = (i0 as isize, j0 as isize);
                let wi = keys_weights(ti);
                let wj = keys_weights(tj);
                let mut acc = 0.0;
                for (a, wa) in wi.iter().enumerate() {
                    for (b, wb) in wj.iter().enumerate() {
                        acc += wa * wb * get(i0 + a as isize - 1, j0 + b as isize - 1)?;
                    }
                }
                Some(acc)
            }
        }
    }

    /// Resamples onto a new pitch covering the same physical footprint (extent), so that the
    /// output has `round(extent / new_pitch)` samples per axis. Target samples whose source
    /// neighbourhood holds an invalid sample are invalid.
    pub fn resample(&self, new_pitch: [f64; 2], method: Interpolation) -> Result<Grid> {
        check_pitch(new_pitch)?;
        let ext = self.extent();
        let nc = (ext[0] / new_pitch[0]).round().max(1.0) as usize;
        let nr = (ext[1] / new_pitch[1]).round().max(1.0) as usize;
        self.resample_to(nr, nc, new_pitch, method)
    }

    /// Resamples onto `rows x cols` samples at `pitch`, centred on the same point as `self`.
    pub fn resample_to(
        &self,
        rows: usize,
        cols: usize,
        pitch: [f64; 2],
        method: Interpolation,
    ) -> Result<Grid> {
        check_pitch(pitch)?;
        if rows == 0 || cols == 0 {
            return Err(Error::param("resample", "target shape must be at least 1 x 1"));
        }
        let (sr, sc) = self.dim();
        let centre = [
            self.x(0) + (sc as f64 - 1.0) * 0.5 * self.pitch[0],
            self.y(0) + (sr as f64 - 1.0) * 0.5 * self.pitch[1],
        ];
        let origin = [
            centre[0] - (cols as f64 - 1.0) * 0.5 * pitch[0],
            centre[1] - (rows as f64 - 1.0) * 0.5 * pitch[1],
        ];
        let mut values = Array2::<f64>::zeros((rows, cols));
        let mut valid = Array2::from_elem((rows, cols), true);
        // Fractional source index of a target coordinate.
        let fj_of = |x: f64| (x - self.origin[0]) / self.pitch[0];
        let fi_of = |y: f64| (y - self.origin[1]) / self.pitch[1];
        if method == Interpolation::Area {
            // Overlap weights per axis, separable: cell [x - p/2, x + p/2] against source cells.
            let wx = area_weights(cols, origin[0], pitch[0], sc, self.origin[0], self.pitch[0]);
            let wy = area_weights(rows, origin[1], pitch[1], sr, self.origin[1], self.pitch[1]);
            for (i, wyi) in wy.iter().enumerate() {
                for (j, wxj) in wx.iter().enumerate() {
                    let mut acc = 0.0;
                    let mut wsum = 0.0;
                    let mut ok = !wyi.is_empty() && !wxj.is_empty();
                    'cell: for &(si, a) in wyi {
                        for &(sj, b) in wxj {
                            if !self.is_valid(si, sj) {
                                ok = false;
                                break 'cell;
                            }
                            acc += a * b * self.values[[si, sj]];
                            wsum += a * b;
                        }
                    }
                    if ok && wsum > 0.0 {
                        values[[i, j]] = acc / wsum;
                    } else {
                        valid[[i, j]] = false;
                    }
                }
            }
        } else {
            for i in 0..rows {
                let fi = fi_of(origin[1] + i as f64 * pitch[1]);
                for j in 0..cols {
                    let fj = fj_of(origin[0] + j as f64 * pitch[0]);
                    match self.sample_index(fi, fj, method) {
                        Some(v) => values[[i, j]] = v,
                        None => valid[[i, j]] = false,
                    }
                }
            }
        }
        Grid::new(values, pitch, self.unit)?.with_origin(origin).with_mask(valid)
    }

    /// Rotates counter-clockwise by `angle` radians about the grid centre, keeping shape and
    /// pitch. Samples that come from outside the footprint are invalid.
    pub fn rotate(&self, angle: f64, method: Interpolation) -> Result<Grid> {
        let (nr, nc) = self.dim();
        let (ci, cj) = ((nr as f64 - 1.0) * 0.5, (nc as f64 - 1.0) * 0.5);
        let (sn, cs) = angle.sin_cos();
        let mut values = Array2::<f64>::zeros((nr, nc));
        let mut valid = Array2::from_elem((nr, nc), true);
        let (px, py) = (self.pitch[0], self.pitch[1]);
        for i in 0..nr {
            for j in 0..nc {
                // Physical offset of the target sample from the centre, rotated back.
                let x = (j as f64 - cj) * px;
                let y = (i as f64 - ci) * py;
                let xs = cs * x + sn * y;
                let ys = -sn * x + cs * y;
                match self.sample_index(ys / py + ci, xs / px + cj, method) {
                    Some(v) => values[[i, j]] = v,
                    None => valid[[i, j]] = false,
                }
            }
        }
        Grid::new(values, self.pitch, self.unit)?.with_origin(self.origin).with_mask(valid)
    }
}

/// `a` with its columns (`flip_x`) and/or rows (`flip_y`) reversed, in standard layout, moved
/// in place when `a` is already in standard layout.
fn mirror_array<T: Copy + Send + Sync>(mut a: Array2<T>, flip_x: bool, flip_y: bool) -> Array2<T> {
    if !a.is_standard_layout() {
        a = a.as_standard_layout().to_owned();
    }
    if flip_x {
        row_blocks::map_blocks_mut(&mut a, |_, mut b| {
            for mut row in b.rows_mut() {
                if let Some(r) = row.as_slice_mut() {
                    r.reverse();
                }
            }
        });
    }
    if flip_y {
        let n = a.nrows();
        for i in 0..n / 2 {
            let (mut top, mut bottom) = a.multi_slice_mut((s![i, ..], s![n - 1 - i, ..]));
            ndarray::Zip::from(&mut top).and(&mut bottom).for_each(std::mem::swap);
        }
    }
    a
}

fn check_pitch(pitch: [f64; 2]) -> Result<()> {
    if pitch.iter().all(|p| p.is_finite() && *p > 0.0) {
        Ok(())
    } else {
        Err(Error::param_in(
            "pitch",
            Allowed::positive(),
            format!("must be finite and positive, got {pitch:?} m"),
        ))
    }
}

/// Keys cubic convolution weights (a = -0.5) for samples at offsets -1, 0, 1, 2 from `t` in [0, 1).
fn keys_weights(t: f64) -> [f64; 4] {
    let k = |x: f64| {
        let x = x.abs();
        if x <= 1.0 {
            1.5 * x * x * x - 2.5 * x * x + 1.0
        } else if x < 2.0 {
            -0.5 * x * x * x + 2.5 * x * x - 4.0 * x + 2.0
        } else {
            0.0
        }
    };
    [k(t + 1.0), k(t), k(1.0 - t), k(2.0 - t)]
}

/// For each of `n` target cells centred at `o + k p` with width `p`, the source cells
/// (centred at `so + m sp`, width `sp`, `m < sn`) it overlaps and the overlap length.
fn area_weights(n: usize, o: f64, p: f64, sn: usize, so: f64, sp: f64) -> Vec<Vec<(usize, f64)>> {
    (0..n)
        .map(|k| {
            let lo = o + k as f64 * p - 0.5 * p;
            let hi = lo + p;
            let m0 = (((lo - so) / sp) + 0.5).floor().max(0.0) as usize;
            let m1 = ((((hi - so) / sp) + 0.5).ceil().max(0.0) as usize).min(sn);
            (m0..m1)
                .filter_map(|m| {
                    let slo = so + m as f64 * sp - 0.5 * sp;
                    let w = hi.min(slo + sp) - lo.max(slo);
                    (w > 1e-12 * sp).then_some((m, w))
                })
                .collect()
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use ndarray::Array2;

    fn ramp(n: usize, m: usize) -> Grid {
        let v = Array2::from_shape_fn((n, m), |(i, j)| i as f64 * 10.0 + j as f64);
        Grid::new(v, [1e-6, 1e-6], Unit::Metre).unwrap()
    }

    #[test]
    fn constructor_checks_its_guarantees() {
        assert!(Grid::new(Array2::zeros((2, 2)), [0.0, 1.0], Unit::Metre).is_err());
        assert!(Grid::new(Array2::zeros((2, 2)), [f64::NAN, 1.0], Unit::Metre).is_err());
        assert!(Grid::new(Array2::zeros((0, 2)), [1.0, 1.0], Unit::Metre).is_err());
        let g = Grid::new(Array2::zeros((2, 3)), [1.0, 2.0], Unit::Metre).unwrap();
        assert!(g.clone().with_mask(Array2::from_elem((3, 2), true)).is_err());
        assert_eq!(g.origin(), [-1.0, -1.0]);
    }

    #[test]
    fn bilinear_reproduces_a_linear_field_exactly() {
        let g = ramp(20, 30);
        let r = g.resample([0.37e-6, 0.61e-6], Interpolation::Bilinear).unwrap();
        // Away from the clamped border, a bilinear resample of a plane is that plane.
        for i in 2..r.dim().0 - 2 {
            for j in 2..r.dim().1 - 2 {
                let fi = (r.y(i) - g.origin()[1]) / 1e-6;
                let fj = (r.x(j) - g.origin()[0]) / 1e-6;
                if fi > 0.0 && fj > 0.0 && fi < 19.0 && fj < 29.0 {
                    assert!((r.values()[[i, j]] - (fi * 10.0 + fj)).abs() < 1e-9);
                }
            }
        }
    }

    #[test]
    fn bicubic_reproduces_a_quadratic_in_the_interior() {
        // Keys' kernel is third-order accurate: it reproduces quadratics exactly.
        let v = Array2::from_shape_fn((16, 16), |(i, j)| (i as f64).powi(2) + 0.5 * (j as f64).powi(2));
        let g = Grid::new(v, [1.0, 1.0], Unit::Metre).unwrap();
        let got = g.sample_index(7.3, 8.6, Interpolation::Bicubic).unwrap();
        assert!((got - (7.3f64.powi(2) + 0.5 * 8.6f64.powi(2))).abs() < 1e-9);
    }

    #[test]
    fn area_downsampling_conserves_the_mean() {
        let g = ramp(40, 40);
        let r = g.resample([4e-6, 4e-6], Interpolation::Area).unwrap();
        assert_eq!(r.dim(), (10, 10));
        let m0 = g.values().mean().unwrap();
        let m1 = r.values().mean().unwrap();
        assert!((m0 - m1).abs() < 1e-9, "{m0} vs {m1}");
        // First block: mean of rows 0..4, cols 0..4 of i*10 + j = 15 + 1.5.
        assert!((r.values()[[0, 0]] - 16.5).abs() < 1e-9);
    }

    #[test]
    fn nearest_keeps_levels_and_resampling_keeps_the_centre() {
        let g = ramp(10, 10);
        let r = g.resample([0.5e-6, 0.5e-6], Interpolation::Nearest).unwrap();
        assert_eq!(r.dim(), (20, 20));
        assert!(r.values().iter().all(|v| g.values().iter().any(|w| w == v)));
        let c0 = g.x(0) + 4.5e-6;
        let c1 = r.x(0) + 9.5 * 0.5e-6;
        assert!((c0 - c1).abs() < 1e-15);
    }

    #[test]
    fn crop_pad_mirror_keep_positions() {
        let g = ramp(6, 8);
        let c = g.crop(1..4, 2..7).unwrap();
        assert_eq!(c.dim(), (3, 5));
        assert_eq!(c.values()[[0, 0]], 12.0);
        assert!((c.x(0) - g.x(2)).abs() < 1e-18 && (c.y(0) - g.y(1)).abs() < 1e-18);
        assert!(g.crop(0..7, 0..2).is_err());
        let p = g.pad([1, 2, 3, 4], -1.0);
        assert_eq!(p.dim(), (9, 15));
        assert_eq!(p.values()[[1, 3]], 0.0);
        assert!((p.x(3) - g.x(0)).abs() < 1e-18);
        let m = g.mirror(true, false);
        assert_eq!(m.values()[[0, 0]], 7.0);
        assert_eq!(m.mirror(true, false), g);
    }

    #[test]
    fn rotation_by_quarter_turns_permutes_samples() {
        let g = ramp(5, 5);
        let r = g.rotate(std::f64::consts::FRAC_PI_2, Interpolation::Bilinear).unwrap();
        // Counter-clockwise by 90 deg in (x right, y down as rows): target (i, j) reads source
        // at offset rotated back.
        for i in 0..5 {
            for j in 0..5 {
                let (x, y) = (j as f64 - 2.0, i as f64 - 2.0);
                let (xs, ys) = (y, -x);
                let v = g.values()[[(ys + 2.0).round() as usize, (xs + 2.0).round() as usize]];
                assert!((r.values()[[i, j]] - v).abs() < 1e-9);
            }
        }
        let back = r.rotate(-std::f64::consts::FRAC_PI_2, Interpolation::Bilinear).unwrap();
        assert!(back.values().iter().zip(g.values()).all(|(a, b)| (a - b).abs() < 1e-9));
    }

    #[test]
    fn invalid_samples_propagate_and_are_never_data() {
        let mut mask = Array2::from_elem((6, 6), true);
        mask[[2, 2]] = false;
        let g = ramp(6, 6).with_mask(mask).unwrap();
        assert_eq!(g.values()[[2, 2]], 0.0);
        assert_eq!(g.valid_count(), 35);
        assert!(g.sample_index(2.3, 2.3, Interpolation::Bilinear).is_none());
        assert!(g.sample_index(4.0, 4.0, Interpolation::Bilinear).is_some());
        let nan = Array2::from_shape_fn((3, 3), |(i, _)| if i == 1 { f64::NAN } else { 1.0 });
        let g = Grid::from_values_nan_invalid(nan, [1.0, 1.0], Unit::Metre).unwrap();
        assert_eq!(g.valid_count(), 6);
        assert_eq!(g.min_max(), Some((1.0, 1.0)));
        // And back: invalid samples (here holding 0 after masking) come out as NaN.
        let back = g.values_nan_invalid();
        assert!(back.row(1).iter().all(|v| v.is_nan()));
        assert!(back.row(0).iter().chain(back.row(2).iter()).all(|&v| v == 1.0));
        let masked = ramp(6, 6).with_mask(Array2::from_shape_fn((6, 6), |(i, j)| (i, j) != (2, 2))).unwrap();
        assert!(masked.values_nan_invalid()[[2, 2]].is_nan() && masked.values_nan_invalid()[[2, 3]] == 23.0);
    }
}
