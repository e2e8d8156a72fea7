//! Spectral bands: a colour channel as a band of wavelengths weighted by the sensor's spectral
//! response, `P_c(x) = int R_c(lambda) I_lambda(x) d lambda / int R_c(lambda) d lambda` for a
//! flat (white) source, `I_lambda` the PSF at `lambda` in absolute terms (pixel share of the
//! power leaving the DOE, [`Channel::captured`] times the normalised pixel value).
//!
//! The integral is the composite midpoint rule over `N` equal sub-bands ([`Band::samples`]);
//! the response between tabulated points is the monotone PCHIP interpolant ([`crate::tabulated`]).
//! A response table is a CSV `wavelength_nm,r,g,b` (any length unit in the first column's name)
//! read by [`read_response_csv`].

use std::path::Path;

use ndarray::Array2;

use super::psf::{Channel, Psf};
use crate::error::{DataCause, Error, Result};
use crate::grid::{Grid, Unit};
use crate::tabulated::{column_unit, hermite, pchip_slopes};

/// One colour channel's band: the response `response[k]` at `wavelengths[k]` (metres,
/// increasing), zero outside `[lo, hi]` = the table's range.
#[derive(Debug, Clone, PartialEq)]
pub struct Band {
    /// Channel name (the response CSV column's header).
    pub name: String,
    /// Tabulated wavelengths, metres, increasing; at least two.
    pub wavelengths: Vec<f64>,
    /// Spectral response at each wavelength, non-negative, any scale (it cancels in the
    /// normalisation).
    pub response: Vec<f64>,
    slopes: Vec<f64>,
}

impl Band {
    /// A band from a tabulated response; at least two points, increasing wavelengths,
    /// non-negative responses, not all zero.
    pub fn new(name: &str, wavelengths: Vec<f64>, response: Vec<f64>) -> Result<Band> {
        if wavelengths.len() < 2 || wavelengths.len() != response.len() {
            return Err(Error::param(
                "band",
                format!("band '{name}' needs at least two (wavelength, response) pairs"),
            ));
        }
        if wavelengths.windows(2).any(|w| w[1] <= w[0]) {
            return Err(Error::param("band", format!("band '{name}': wavelengths must increase")));
        }
        if response.iter().any(|r| !r.is_finite() || *r < 0.0) || response.iter().all(|r| *r == 0.0) {
            return Err(Error::param(
                "band",
                format!("band '{name}': responses must be finite, non-negative and not all zero"),
            ));
        }
        let slopes = pchip_slopes(&wavelengths, &response);
        Ok(Band { name: name.into(), wavelengths, response, slopes })
    }

    /// A flat response over `[lo, hi]` (metres).
    pub fn flat(name: &str, lo: f64, hi: f64) -> Result<Band> {
        Band::new(name, vec![lo, hi], vec![1.0, 1.0])
    }

    /// `(lo, hi)`, metres.
    pub fn range(&self) -> (f64, f64) {
        (self.wavelengths[0], self.wavelengths[self.wavelengths.len() - 1])
    }

    /// The response at `wavelength` (PCHIP; 0 outside the range).
    pub fn response_at(&self, wavelength: f64) -> f64 {
        let (lo, hi) = self.range();
        if wavelength < lo || wavelength > hi {
            return 0.0;
        }
        hermite(&self.wavelengths, &self.response, &self.slopes, wavelength).max(0.0)
    }

    /// The `n` midpoints of equal sub-bands with their weights `R(lambda_k) * width`.
    pub fn samples(&self, n: usize) -> Vec<(f64, f64)> {
        let (lo, hi) = self.range();
        let w = (hi - lo) / n as f64;
        (0..n)
            .map(|k| {
                let l = lo + (k as f64 + 0.5) * w;
                (l, self.response_at(l) * w)
            })
            .collect()
    }
}

/// Reads a sensor response CSV: a header `wavelength_<unit>,<name>,<name>,...` (e.g.
/// `wavelength_nm,r,g,b`), then rows of numbers; `#` comments and blank lines skipped. One
/// [`Band`] per response column, named by its header.
pub fn read_response_csv(path: &Path) -> Result<Vec<Band>> {
    let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
    let mut lines =
        text.lines().enumerate().filter(|(_, l)| !l.trim().is_empty() && !l.trim_start().starts_with('#'));
    let Some((_, header)) = lines.next() else {
        return Err(Error::malformed(path, "empty table (expected a header 'wavelength_nm,r,g,b')"));
    };
    let cols: Vec<String> = header.split(',').map(|c| c.trim().to_ascii_lowercase()).collect();
    if cols.len() < 2 {
        return Err(Error::malformed(path, format!("header '{header}' names no response column")));
    }
    let unit = column_unit(path, &cols[0], "wavelength")?;
    let mut rows: Vec<Vec<f64>> = vec![Vec::new(); cols.len()];
    for (ln, line) in lines {
        let f: Vec<&str> = line.split(',').map(str::trim).collect();
        if f.len() != cols.len() {
            return Err(Error::malformed(
                path,
                format!("line {}: expected {} fields, got {}", ln + 1, cols.len(), f.len()),
            ));
        }
        for (c, s) in f.iter().enumerate() {
            let v = s.parse::<f64>().ok().filter(|v| v.is_finite()).ok_or_else(|| {
                Error::malformed(path, format!("line {}: {} '{s}' is not a number", ln + 1, cols[c]))
            })?;
            rows[c].push(if c == 0 { v * unit } else { v });
        }
    }
    cols[1..]
        .iter()
        .enumerate()
        .map(|(c, name)| {
            Band::new(name, rows[0].clone(), rows[c + 1].clone())
                .map_err(|e| Error::malformed(path, e.to_string()))
        })
        .collect()
}

/// Combines a PSF simulated at every band's sample wavelengths (channels in the order of
/// `samples`, band after band) into one channel per band: the weighted sum of the absolute
/// intensities, normalised to sum 1. The channel's wavelength is the band's response-weighted
/// mean wavelength, its `captured` the weighted mean of the samples'.
pub fn combine(psf: &Psf, bands: &[Band], samples: &[Vec<(f64, f64)>]) -> Result<Psf> {
    let mut channels = Vec::new();
    let mut k = 0;
    for (band, s) in bands.iter().zip(samples) {
        let (rows, cols) = psf.dim();
        let mut sum = Array2::<f64>::zeros((rows, cols));
        let (mut wsum, mut lsum, mut csum) = (0.0, 0.0, 0.0);
        for &(l, w) in s {
            let ch = psf
                .channels
                .get(k)
                .ok_or_else(|| Error::data(DataCause::Shape, "fewer PSF channels than samples"))?;
            let captured = ch.captured.unwrap_or(1.0);
            sum.scaled_add(w * captured, ch.grid.values());
            wsum += w;
            lsum += w * l;
            csum += w * captured;
            k += 1;
        }
        channels.push(Channel {
            name: band.name.clone(),
            wavelength: Some(lsum / wsum),
            grid: Grid::new(sum, psf.pitch(), Unit::Dimensionless)?,
            captured: Some(csum / wsum),
        });
    }
    let mut out = Psf::new(channels, &psf.method)?;
    out.warnings = psf.warnings.clone();
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn midpoint_samples_integrate_a_smooth_response() {
        // A linear response 1 -> 3 over 500-600 nm: integral 200 nm, mean wavelength
        // 558.33 nm; the midpoint rule integrates the linear response exactly and the
        // quadratic `lambda R` within (1/24)(1/n^2) of its second derivative.
        let b = Band::new("g", vec![500e-9, 600e-9], vec![1.0, 3.0]).unwrap();
        let total: f64 = b.samples(10).iter().map(|s| s.1).sum();
        assert!((total / 200e-9 - 1.0).abs() < 1e-12, "{total}");
        let mean: f64 = b.samples(10).iter().map(|s| s.0 * s.1).sum::<f64>() / total;
        assert!((mean - 558.3333e-9).abs() < 0.1e-9, "{mean}");
        assert_eq!(b.response_at(450e-9), 0.0);
        assert!(Band::new("x", vec![600e-9, 500e-9], vec![1.0, 1.0]).is_err());
        assert!(Band::new("x", vec![500e-9, 600e-9], vec![0.0, 0.0]).is_err());
    }
}
