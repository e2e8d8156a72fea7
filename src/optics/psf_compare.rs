//! Comparing two PSFs (design vs as-fabricated vs measured): each one's summary numbers and
//! the relative L2 difference after centroid alignment.
//!
//! The PSFs are read by [`Psf::read`].
//!
//! Comparing ([`compare`]): both PSFs must share channel count and pitch. Windows of
//! different sizes are cropped to the common centred size (`(n - m) / 2` samples off the
//! start of each axis) and renormalised to sum 1 there; the report says so. The second PSF is
//! then moved onto the first one's centroid by a Fourier shift (shift theorem,
//! `F{b(x - s)}(f) = exp(-2 pi i f s) F{b}(f)`, applied per axis; the real part is kept, which
//! splits an even length's Nyquist term symmetrically), and
//! `L2 = ||b_shifted - a|| / ||a||` over the common window.
//!
//! Where the shift is inexact: it is the band-limited, periodic interpolation of the samples.
//! Energy that the shift carries across the window's edge wraps around to the other side,
//! and content near the sampling limit (an undersampled PSF) is interpolated as if it were
//! band-limited. Both are measured and reported as warnings: the fraction of the channel's
//! energy within `ceil(max |s|) + 1` pixels of the edge, and (for a shift with a fractional
//! part) the relative L2 norm of the channel's content above 0.4 cycles per pixel on either
//! axis ([`BAND_EDGE`]). A PSF sampled coarser than its Nyquist pitch `lambda F# / 2` (the
//! paper's 4.29 um pixels at F/7) carries a large share there: its sub-pixel alignment is not
//! defined by the samples, and the warning says so.

use ndarray::Array2;
use rustfft::num_complex::Complex64;
use serde::{Deserialize, Serialize};

use super::psf::{ChannelSummary, Peak, Psf};
use super::psf_files::PEAKS;
use super::system::OpticalSystem;
use crate::error::{DataCause, Error, Result};
use crate::fft::Plan1d;

/// Frequency (cycles per pixel) above which a channel's content counts as near the sampling
/// limit, where the Fourier shift's band-limited interpolation is unreliable.
pub const BAND_EDGE: f64 = 0.4;

/// Level above which edge energy or band-edge content is reported as a warning.
pub const WARN_LEVEL: f64 = 1e-3;

/// Shifts (pixels) below this count as none.
const SHIFT_EPS: f64 = 1e-9;

/// Relative difference of pitches treated as equal.
use super::psf::PITCH_TOLERANCE;

/// How the two PSFs are read and measured.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct CompareOptions {
    /// Pixel pitch (metres) for a file that does not state one; a file that does must agree.
    pub pitch: Option<f64>,
    /// The array to read from a `.npz` archive holding several.
    pub key: Option<String>,
    /// Radius (metres) of the encircled energy and of the peak search; default
    /// `1.22 lambda F#` at the paper's F# when the channel's wavelength is known, else two
    /// pixels.
    pub radius: Option<f64>,
}

/// Numbers of one channel of one PSF, over its own whole window.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ChannelNumbers {
    /// Name, wavelength, centroid, peak and captured power (flattened into this object).
    #[serde(flatten)]
    pub summary: ChannelSummary,
    /// Fraction of the channel (0..1) within the radius of its peak.
    pub encircled_energy: f64,
    /// The central peak and its shifted copies (at least the radius apart).
    pub peaks: Vec<Peak>,
}

/// One channel of the comparison.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ChannelComparison {
    /// The channel's name, `"A/B"` when the two PSFs name it differently.
    pub name: String,
    /// Radius of the encircled energy and the peak search, metres.
    pub radius: f64,
    /// Numbers of A's channel, over A's whole window.
    pub a: ChannelNumbers,
    /// Numbers of B's channel, over B's whole window.
    pub b: ChannelNumbers,
    /// Centroid of B minus centroid of A over the common window, `[x, y]` metres: the shift
    /// removed before the aligned L2.
    pub centroid_offset: [f64; 2],
    /// `||b - a|| / ||a||` over the common window, without alignment.
    pub relative_l2: f64,
    /// The same after moving B onto A's centroid.
    pub relative_l2_aligned: f64,
    /// Fraction of B's energy within `ceil(max |shift|) + 1` pixels of the window edge (wraps
    /// around in the circular shift; 0 when there is no shift).
    pub edge_energy: f64,
    /// Relative L2 norm of B's content above [`BAND_EDGE`] cycles per pixel (a warning when the
    /// shift has a fractional part, which interpolates it).
    pub band_edge: f64,
}

/// What `doefab psf-compare` reports.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Comparison {
    /// Name of the reference PSF A (its file path in `doefab psf-compare`).
    pub a: String,
    /// Name of the PSF B compared against it and moved onto its centroid.
    pub b: String,
    /// Pixel pitch `[x, y]`, metres.
    pub pitch: [f64; 2],
    /// `(rows, cols)` of A, pixels.
    pub dim_a: (usize, usize),
    /// `(rows, cols)` of B, pixels.
    pub dim_b: (usize, usize),
    /// `(rows, cols)` of the common centred window compared, pixels.
    pub dim_common: (usize, usize),
    /// How the windows were matched (a sentence; "same size" when they were).
    pub window: String,
    /// How the compared channels are normalised: "each channel sums to 1 over the common
    /// window".
    pub normalisation: String,
    /// One per channel, in channel order.
    pub channels: Vec<ChannelComparison>,
    /// Edge energy above [`WARN_LEVEL`] that wraps in the shift, and band-edge content above
    /// it under a sub-pixel shift, one sentence each.
    pub warnings: Vec<String>,
}

/// The numbers of channel `c` of `psf` with search/encircled radius `radius`.
fn numbers(psf: &Psf, c: usize, radius: f64) -> ChannelNumbers {
    let summary = psf.summary().swap_remove(c);
    ChannelNumbers {
        encircled_energy: psf.encircled_energy(c, summary.peak_position, radius),
        peaks: psf.peaks(c, PEAKS, radius),
        summary,
    }
}

/// Centred crop of every channel to `(rows, cols)`, renormalised.
fn crop_centred(psf: &Psf, (rows, cols): (usize, usize)) -> Result<Psf> {
    let (h, w) = psf.dim();
    let (r0, c0) = ((h - rows) / 2, (w - cols) / 2);
    let channels = psf
        .channels
        .iter()
        .map(|c| Ok(super::psf::Channel { grid: c.grid.crop(r0..r0 + rows, c0..c0 + cols)?, ..c.clone() }))
        .collect::<Result<Vec<_>>>()?;
    Psf::new(channels, &psf.method)
}

/// Centroid of channel `c` in fractional `[column, row]` indices.
fn centroid_index(psf: &Psf, c: usize) -> [f64; 2] {
    let g = &psf.channels[c].grid;
    let [x, y] = psf.centroid(c);
    [(x - g.x(0)) / g.pitch()[0], (y - g.y(0)) / g.pitch()[1]]
}

/// Compares `b` against `a` (see the module docs); `a_name`/`b_name` label them.
pub fn compare(a: &Psf, b: &Psf, a_name: &str, b_name: &str, opts: &CompareOptions) -> Result<Comparison> {
    if a.channels.len() != b.channels.len() {
        return Err(Error::data(
            DataCause::Shape,
            format!(
                "{a_name} has {} channels ({}), {b_name} has {} ({}): a comparison needs the same count",
                a.channels.len(),
                names(a),
                b.channels.len(),
                names(b)
            ),
        ));
    }
    let (pa, pb) = (a.pitch(), b.pitch());
    if (0..2).any(|k| ((pa[k] - pb[k]) / pa[k]).abs() > PITCH_TOLERANCE) {
        return Err(Error::data(
            DataCause::Shape,
            format!(
                "{a_name} has pitch [{:e}, {:e}] m, {b_name} [{:e}, {:e}] m: resample one first",
                pa[0], pa[1], pb[0], pb[1]
            ),
        ));
    }
    let (da, db) = (a.dim(), b.dim());
    let common = (da.0.min(db.0), da.1.min(db.1));
    let window = if da == db {
        "same size".to_string()
    } else {
        format!(
            "both cropped to the common centred {} x {} window ({a_name} {} x {}, {b_name} {} x {}) \
             and renormalised there",
            common.0, common.1, da.0, da.1, db.0, db.1
        )
    };
    let (ca, cb) = (crop_centred(a, common)?, crop_centred(b, common)?);
    let f_number = OpticalSystem::default().f_number();
    let mut warnings = Vec::new();
    let mut channels = Vec::new();
    for c in 0..a.channels.len() {
        let wavelength = a.channels[c].wavelength.or(b.channels[c].wavelength);
        let radius = opts.radius.unwrap_or_else(|| wavelength.map_or(2.0 * pa[0], |l| 1.22 * l * f_number));
        let (ia, ib) = (centroid_index(&ca, c), centroid_index(&cb, c));
        let shift = [ia[0] - ib[0], ia[1] - ib[1]];
        let (va, vb) = (ca.channels[c].grid.values(), cb.channels[c].grid.values());
        let moved = fourier_shift(vb, shift);
        // A whole-pixel shift is an exact circular shift (no interpolation); no shift, no wrap.
        let fractional = shift.iter().any(|s| (s - s.round()).abs() > SHIFT_EPS);
        let moved_at_all = shift.iter().any(|s| s.abs() > SHIFT_EPS);
        let margin = if moved_at_all { shift[0].abs().max(shift[1].abs()).ceil() as usize + 1 } else { 0 };
        let edge_energy = edge_energy(vb, margin);
        let band_edge = band_edge(vb);
        let name = if a.channels[c].name == b.channels[c].name {
            a.channels[c].name.clone()
        } else {
            format!("{}/{}", a.channels[c].name, b.channels[c].name)
        };
        if edge_energy > WARN_LEVEL {
            warnings.push(format!(
                "channel {name}: {edge_energy:.1e} of {b_name}'s energy lies within {margin} pixels of the \
                 window edge and wraps around in the shift of ({:.2}, {:.2}) pixels",
                shift[0], shift[1]
            ));
        }
        if fractional && band_edge > WARN_LEVEL {
            warnings.push(format!(
                "channel {name}: {b_name} holds {band_edge:.1e} (relative L2) above {BAND_EDGE} cycles per \
                 pixel; the sub-pixel shift interpolates it as band-limited, so the aligned L2 is \
                 uncertain at about that level"
            ));
        }
        channels.push(ChannelComparison {
            radius,
            a: numbers(a, c, radius),
            b: numbers(b, c, radius),
            centroid_offset: [-shift[0] * pa[0], -shift[1] * pa[1]],
            relative_l2: super::psf::relative_l2(vb, va),
            relative_l2_aligned: super::psf::relative_l2(&moved, va),
            edge_energy,
            band_edge,
            name,
        });
    }
    Ok(Comparison {
        a: a_name.into(),
        b: b_name.into(),
        pitch: pa,
        dim_a: da,
        dim_b: db,
        dim_common: common,
        window,
        normalisation: "each channel sums to 1 over the common window".into(),
        channels,
        warnings,
    })
}

fn names(psf: &Psf) -> String {
    psf.channels.iter().map(|c| c.name.as_str()).collect::<Vec<_>>().join(", ")
}

/// Frequency of FFT bin `k` of `n`, cycles per sample.
fn bin_frequency(k: usize, n: usize) -> f64 {
    if 2 * k < n {
        k as f64 / n as f64
    } else {
        k as f64 / n as f64 - 1.0
    }
}

/// The 2-D spectrum of `v` (unnormalised forward DFT, rows then columns).
fn spectrum(v: &Array2<f64>) -> Array2<Complex64> {
    let mut s = v.mapv(|x| Complex64::new(x, 0.0));
    transform_axes(&mut s, false, |_, _| Complex64::new(1.0, 0.0));
    s
}

/// Transforms every row then every column of `s`, multiplying each 1-D spectrum bin `k` of an
/// axis of length `n` by `factor(axis, k)` (axis 0 = along rows, i.e. x), forward or inverse.
fn transform_axes(s: &mut Array2<Complex64>, inverse: bool, factor: impl Fn(usize, usize) -> Complex64) {
    for axis in 0..2 {
        let mut lanes: Vec<_> = if axis == 0 {
            s.rows_mut().into_iter().collect()
        } else {
            s.columns_mut().into_iter().collect()
        };
        let n = lanes[0].len();
        let plan = Plan1d::new(n);
        let mut buf = vec![Complex64::new(0.0, 0.0); n];
        for lane in lanes.iter_mut() {
            buf.iter_mut().zip(lane.iter()).for_each(|(b, &x)| *b = x);
            plan.process(&mut buf, false);
            for (k, b) in buf.iter_mut().enumerate() {
                *b *= factor(axis, k);
            }
            if inverse {
                plan.process(&mut buf, true);
                buf.iter_mut().for_each(|b| *b /= n as f64);
            }
            lane.iter_mut().zip(&buf).for_each(|(x, &b)| *x = b);
        }
    }
}

/// `v` moved by `shift` = `[x, y]` samples (`out(x) = v(x - shift)`) by the shift theorem on
/// the periodic, band-limited interpolation of the samples; the real part.
pub fn fourier_shift(v: &Array2<f64>, shift: [f64; 2]) -> Array2<f64> {
    let (h, w) = v.dim();
    let mut s = v.mapv(|x| Complex64::new(x, 0.0));
    transform_axes(&mut s, true, |axis, k| {
        let (n, d) = if axis == 0 { (w, shift[0]) } else { (h, shift[1]) };
        Complex64::from_polar(1.0, -2.0 * std::f64::consts::PI * bin_frequency(k, n) * d)
    });
    s.mapv(|z| z.re)
}

/// Sum of `v` within `margin` samples of the window's edge (of a window summing to 1).
fn edge_energy(v: &Array2<f64>, margin: usize) -> f64 {
    let (h, w) = v.dim();
    v.indexed_iter()
        .filter(|((i, j), _)| *i < margin || *j < margin || *i + margin >= h || *j + margin >= w)
        .map(|(_, x)| x)
        .sum()
}

/// Relative L2 norm of the content of `v` above [`BAND_EDGE`] cycles per sample on either axis
/// (Parseval: the ratio of spectral power sums equals that of the image norms).
fn band_edge(v: &Array2<f64>) -> f64 {
    let (h, w) = v.dim();
    let s = spectrum(v);
    let (mut high, mut all) = (0.0, 0.0);
    for ((i, j), z) in s.indexed_iter() {
        let p = z.norm_sqr();
        all += p;
        if bin_frequency(i, h).abs() > BAND_EDGE || bin_frequency(j, w).abs() > BAND_EDGE {
            high += p;
        }
    }
    (high / all).sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::grid::{Grid, Unit};
    use crate::optics::psf::Channel;

    const PITCH: f64 = 4.29e-6;

    /// A sampled Gaussian of width `sigma` pixels centred `centre` = `[x, y]` pixels from the
    /// window centre, as a one-channel PSF.
    fn gaussian(n: usize, sigma: f64, centre: [f64; 2]) -> Psf {
        let c = (n as f64 - 1.0) / 2.0;
        let v = Array2::from_shape_fn((n, n), |(i, j)| {
            let (x, y) = (j as f64 - c - centre[0], i as f64 - c - centre[1]);
            (-(x * x + y * y) / (2.0 * sigma * sigma)).exp()
        });
        let grid = Grid::new(v, [PITCH, PITCH], Unit::Dimensionless).unwrap();
        Psf::new(vec![Channel { name: "G".into(), wavelength: Some(530e-9), grid, captured: None }], "test")
            .unwrap()
    }

    #[test]
    fn a_sub_pixel_shift_is_found_and_removed() {
        let (a, b) = (gaussian(64, 3.0, [0.0, 0.0]), gaussian(64, 3.0, [0.3, -0.45]));
        let opts = CompareOptions { radius: Some(10.0 * PITCH), ..Default::default() };
        let r = compare(&a, &b, "a", "b", &opts).unwrap();
        let c = &r.channels[0];
        assert!((c.centroid_offset[0] / PITCH - 0.3).abs() < 1e-9, "{:?}", c.centroid_offset);
        assert!((c.centroid_offset[1] / PITCH + 0.45).abs() < 1e-9, "{:?}", c.centroid_offset);
        assert!(c.relative_l2 > 0.1, "unaligned {}", c.relative_l2);
        assert!(c.relative_l2_aligned < 1e-9, "aligned {}", c.relative_l2_aligned);
        assert!(r.warnings.is_empty(), "{:?}", r.warnings);
        assert_eq!(r.window, "same size");
        // Encircled energy of a Gaussian within r: 1 - exp(-r^2 / 2 sigma^2) = 0.9961 at 10 px
        // (the pixel-centre rule misjudges the rim by about 2e-3).
        let expected = 1.0 - (-100.0f64 / 18.0).exp();
        assert!((c.a.encircled_energy - expected).abs() < 5e-3, "{}", c.a.encircled_energy);
        assert!((c.b.encircled_energy - expected).abs() < 5e-3, "{}", c.b.encircled_energy);
    }

    #[test]
    fn an_undersampled_psf_is_flagged_and_aligns_worse() {
        let (a, b) = (gaussian(64, 0.5, [0.0, 0.0]), gaussian(64, 0.5, [0.3, -0.45]));
        let r = compare(&a, &b, "a", "b", &CompareOptions::default()).unwrap();
        let c = &r.channels[0];
        assert!(c.band_edge > WARN_LEVEL && c.relative_l2_aligned > 1e-3, "{c:?}");
        assert!(r.warnings.iter().any(|w| w.contains("band-limited")), "{:?}", r.warnings);
    }

    #[test]
    fn energy_at_the_edge_is_flagged() {
        let (a, b) = (gaussian(64, 3.0, [0.0, 0.0]), gaussian(64, 3.0, [27.0, 0.0]));
        let r = compare(&a, &b, "a", "b", &CompareOptions::default()).unwrap();
        assert!(r.channels[0].edge_energy > WARN_LEVEL);
        assert!(r.warnings.iter().any(|w| w.contains("wraps around")), "{:?}", r.warnings);
    }

    #[test]
    fn different_windows_are_cropped_to_the_common_centre() {
        // 64 vs 63 samples: the common window is the first 63 of the 64, whose centre is half a
        // pixel before the 64-window's centre, which the centroid offset shows.
        let (a, b) = (gaussian(64, 3.0, [0.0, 0.0]), gaussian(63, 3.0, [0.0, 0.0]));
        let r = compare(&a, &b, "a", "b", &CompareOptions::default()).unwrap();
        assert_eq!(r.dim_common, (63, 63));
        assert!(r.window.contains("cropped"));
        let c = &r.channels[0];
        assert!((c.centroid_offset[0] / PITCH + 0.5).abs() < 1e-6, "{:?}", c.centroid_offset);
        assert!(c.relative_l2_aligned < 1e-6, "{}", c.relative_l2_aligned);
    }

    #[test]
    fn mismatched_inputs_are_refused() {
        let a = gaussian(32, 3.0, [0.0, 0.0]);
        let mut two = a.clone();
        two.channels.push(two.channels[0].clone());
        let e = compare(&a, &two, "x.npy", "y.npy", &CompareOptions::default()).unwrap_err();
        assert!(matches!(e, Error::Data { cause: DataCause::Shape, .. }), "{e:?}");
        let e = e.to_string();
        assert!(e.contains("x.npy has 1 channels") && e.contains("y.npy has 2"), "{e}");
        let g = Grid::new(a.channels[0].grid.values().clone(), [2e-6, 2e-6], Unit::Dimensionless).unwrap();
        let other = Psf::new(vec![Channel { grid: g, ..a.channels[0].clone() }], "test").unwrap();
        let e = compare(&a, &other, "x", "y", &CompareOptions::default()).unwrap_err();
        assert!(
            matches!(e, Error::Data { cause: DataCause::Shape, .. }) && e.to_string().contains("pitch"),
            "{e:?}"
        );
    }
}
