//! A 1-D height profile along a line (a stylus profiler's measurement): positions (metres,
//! strictly increasing), heights (metres) and a validity flag per point; a non-measured point
//! never enters a sum or a fit. Read by [`crate::io::profile`], levelled and compared with a
//! design by `metrology::profile`.

use crate::error::{DataCause, Error, Result};

/// A 1-D height profile; see the module docs.
#[derive(Debug, Clone, PartialEq)]
pub struct Profile {
    x: Vec<f64>,
    z: Vec<f64>,
    valid: Vec<bool>,
}

impl Profile {
    /// Positions `x` (metres, finite, strictly increasing), heights `z` (metres) and validity
    /// (`None`: every finite height valid; non-finite heights are always invalid).
    pub fn new(x: Vec<f64>, z: Vec<f64>, valid: Option<Vec<bool>>) -> Result<Profile> {
        if x.len() != z.len() || valid.as_ref().is_some_and(|v| v.len() != x.len()) {
            return Err(Error::data(
                DataCause::Shape,
                format!(
                    "a profile needs as many heights as positions: {} positions, {} heights",
                    x.len(),
                    z.len()
                ),
            ));
        }
        if x.len() < 2 {
            return Err(Error::data(
                DataCause::TooFew,
                format!("a profile needs at least 2 points, got {}", x.len()),
            ));
        }
        if let Some(k) = x.iter().position(|v| !v.is_finite()) {
            return Err(Error::data(DataCause::NotFinite, format!("position {k} is not finite")));
        }
        if let Some(k) = (1..x.len()).find(|&k| x[k] <= x[k - 1]) {
            return Err(Error::data(
                DataCause::OutOfRange,
                format!(
                    "positions must be strictly increasing: point {k} at {:e} m follows {:e} m",
                    x[k],
                    x[k - 1]
                ),
            ));
        }
        let valid: Vec<bool> = match valid {
            Some(v) => v.iter().zip(&z).map(|(ok, h)| *ok && h.is_finite()).collect(),
            None => z.iter().map(|h| h.is_finite()).collect(),
        };
        let z = z.iter().zip(&valid).map(|(h, ok)| if *ok { *h } else { 0.0 }).collect();
        Ok(Profile { x, z, valid })
    }

    /// Positions, metres.
    pub fn x(&self) -> &[f64] {
        &self.x
    }
    /// Heights, metres (0 at invalid points).
    pub fn z(&self) -> &[f64] {
        &self.z
    }
    /// Validity per point (`false`: not measured).
    pub fn valid(&self) -> &[bool] {
        &self.valid
    }
    /// Whether point `k` is measured.
    pub fn is_valid(&self, k: usize) -> bool {
        self.valid[k]
    }
    /// Number of points, valid or not.
    pub fn len(&self) -> usize {
        self.x.len()
    }
    /// Whether the profile has no points (never, as built: [`Profile::new`] needs 2).
    pub fn is_empty(&self) -> bool {
        self.x.is_empty()
    }
    /// Number of valid points.
    pub fn valid_count(&self) -> usize {
        self.valid.iter().filter(|v| **v).count()
    }
    /// `x_last - x_first`, metres.
    pub fn length(&self) -> f64 {
        self.x[self.x.len() - 1] - self.x[0]
    }
    /// The sampling step: the median spacing of the positions, metres.
    pub fn step(&self) -> f64 {
        let mut d: Vec<f64> = self.x.windows(2).map(|w| w[1] - w[0]).collect();
        median(&mut d)
    }
    /// The same positions and validity with other heights (invalid points keep their 0).
    pub(crate) fn with_z(&self, z: Vec<f64>) -> Profile {
        let z = z.iter().zip(&self.valid).map(|(h, ok)| if *ok { *h } else { 0.0 }).collect();
        Profile { x: self.x.clone(), z, valid: self.valid.clone() }
    }
    /// `(u_k, z_k)` of the valid points, `u` from the first point.
    pub fn points(&self) -> Vec<(f64, f64)> {
        (0..self.len()).filter(|&k| self.valid[k]).map(|k| (self.x[k] - self.x[0], self.z[k])).collect()
    }
}

/// The median of `v` (sorted in place); NaN when empty.
pub fn median(v: &mut [f64]) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_unstable_by(f64::total_cmp);
    let n = v.len();
    if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    }
}
