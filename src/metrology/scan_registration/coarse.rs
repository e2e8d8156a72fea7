//! The coarse search of a registration (module docs, step 2): the FFT cross-correlation of
//! the binned design and scan over rotations and mirror states, the second peak that makes a
//! shift ambiguous, and the upsampled peak's sub-sample position.

use rayon::prelude::*;
use rustfft::num_complex::{Complex32, Complex64};

use crate::error::{Condition, Error, Refusal, Result};
use crate::fft::{fast_len, Plan2d};

use super::binning::Img;
use super::options::RegisterOptions;
use super::pose::Pose;

/// Design samples per side of the coarse search (the coarse pitch is a power-of-two multiple
/// of the design's pitch chosen to stay at or below this).
pub(super) const COARSE_SIDE: usize = 192;

/// Peak of a correlation map (signed, normalised).
#[derive(Debug, Clone, Copy)]
struct Peak {
    value: f64,
}

pub(super) struct Coarse {
    pub(super) pose: Pose,
    pub(super) peak_ratio: f64,
    pub(super) rotation_contrast: f64,
    pub(super) mirror_ratio: f64,
}

/// Step 2 and the measures of step 3 of the module docs.
pub(super) fn coarse_search(d: &Img, s: &Img, opts: &RegisterOptions) -> Result<Coarse> {
    let (tr, tc) = (d.rows, d.cols);
    let nr = fast_len(s.rows + tr);
    let nc = fast_len(s.cols + tc);
    let fft = Plan2d::<f64>::rect(nr, nc);
    let mut work = fft.workspace();
    let mut sh = vec![Complex64::default(); nr * nc];
    for i in 0..s.rows {
        for j in 0..s.cols {
            sh[i * nc + j] = Complex64::new(s.v[i * s.cols + j], 0.0);
        }
    }
    fft.transform_with(&mut sh, false, &mut work);
    let s_norm = s.v.iter().map(|v| v * v).sum::<f64>().sqrt();
    if s_norm.is_nan() || s_norm <= 0.0 {
        return Err(Error::validity(
            Condition::Registration(Refusal::Featureless),
            "the scan is featureless at the coarse scale",
        ));
    }
    let radius = 0.5 * tr.min(tc) as f64;
    let step = (1.0 / radius).min(0.5f64.to_radians());
    let n_ang = (opts.max_rotation.max(0.0) / step).ceil() as isize;
    let angles: Vec<f64> = (-n_ang..=n_ang).map(|k| k as f64 * step).collect();
    let mirrors: &[bool] = if opts.try_mirror { &[false, true] } else { &[false] };
    let (ct_i, ct_j) = d.centre();
    let template = |theta: f64, mirror: bool| -> (Vec<f64>, f64) {
        // Pose::scan_to_design with rotation theta, unit scale and no shift, written out so
        // that the sine and cosine are taken once.
        let (sn, cs) = theta.sin_cos();
        let mx = if mirror { -1.0 } else { 1.0 };
        let mut t = vec![0.0; tr * tc];
        for i in 0..tr {
            let y = (i as f64 - ct_i) * d.pitch[1];
            for j in 0..tc {
                let x = (j as f64 - ct_j) * d.pitch[0];
                t[i * tc + j] = d.bilinear([mx * (cs * x + sn * y), -sn * x + cs * y]);
            }
        }
        let n = t.iter().map(|v| v * v).sum::<f64>().sqrt();
        (t, n)
    };
    let lag = |k: usize, len: usize, n: usize| if k >= len { k as isize - n as isize } else { k as isize };
    let scale = 1.0 / (nr * nc) as f64;
    // For each angle (in parallel, each with its own transform buffers) and mirror state: the
    // best |c| / (|S| |T|). Every angle is computed alone, so threads do not change the result.
    // The sweep in single precision (it only ranks peaks; the winner's map is redone in f64).
    let fft32 = Plan2d::<f32>::rect(nr, nc);
    let sh32: Vec<Complex32> = sh.iter().map(|c| Complex32::new(c.re as f32, c.im as f32)).collect();
    let per_angle: Vec<Vec<Peak>> = angles
        .par_iter()
        .map_init(
            || (fft32.workspace(), vec![Complex32::default(); nr * nc]),
            |(work, buf), &theta| {
                let ts: Vec<(Vec<f64>, f64)> = mirrors.iter().map(|&m| template(theta, m)).collect();
                buf.iter_mut().for_each(|c| *c = Complex32::default());
                for i in 0..tr {
                    for j in 0..tc {
                        let re = ts[0].0[i * tc + j];
                        let im = ts.get(1).map_or(0.0, |t| t.0[i * tc + j]);
                        buf[i * nc + j] = Complex32::new(re as f32, im as f32);
                    }
                }
                fft32.transform_with(buf, false, work);
                for (b, sv) in buf.iter_mut().zip(&sh32) {
                    *b = sv * b.conj();
                }
                fft32.transform_with(buf, true, work);
                ts.iter()
                    .enumerate()
                    .map(|(m, t)| {
                        let norm = scale / (s_norm * t.1.max(1e-300));
                        let mut best = Peak { value: 0.0 };
                        for c in buf.iter() {
                            // Real part: plain template; minus imaginary part: mirrored template.
                            let v = f64::from(if m == 0 { c.re } else { -c.im }) * norm;
                            if v.abs() > best.value.abs() {
                                best = Peak { value: v };
                            }
                        }
                        best
                    })
                    .collect()
            },
        )
        .collect();
    // peaks[m][a]: mirror state m, angle a.
    let peaks: Vec<Vec<Peak>> =
        (0..mirrors.len()).map(|m| per_angle.iter().map(|ps| ps[m]).collect()).collect();
    let mut buf = vec![Complex64::default(); nr * nc];
    let (mut bm, mut ba) = (0, 0);
    for (m, ps) in peaks.iter().enumerate() {
        for (a, p) in ps.iter().enumerate() {
            if p.value.abs() > peaks[bm][ba].value.abs() {
                (bm, ba) = (m, a);
            }
        }
    }
    let best = peaks[bm][ba];
    if best.value.is_nan() || best.value == 0.0 {
        return Err(Error::validity(
            Condition::Registration(Refusal::NoMatch),
            "no correlation between scan and design at any placement",
        ));
    }
    let mirror = mirrors[bm];
    let mirror_ratio = if mirrors.len() > 1 {
        peaks[1 - bm].iter().map(|p| p.value.abs()).fold(0.0, f64::max) / best.value.abs()
    } else {
        0.0
    };
    let amin = peaks[bm].iter().map(|p| p.value.abs()).fold(f64::INFINITY, f64::min);
    let rotation_contrast = 1.0 - amin / best.value.abs();
    // Parabolic refinement of the angle.
    let mut theta = angles[ba];
    if ba > 0 && ba + 1 < angles.len() {
        let (y0, y1, y2) = (peaks[bm][ba - 1].value.abs(), best.value.abs(), peaks[bm][ba + 1].value.abs());
        let den = y0 - 2.0 * y1 + y2;
        if den < 0.0 {
            theta += step * (0.5 * (y0 - y2) / den).clamp(-0.5, 0.5);
        }
    }
    // The winner's map once more, real template only: second peak and upsampled refinement.
    let (t, tn) = template(theta, mirror);
    buf.iter_mut().for_each(|c| *c = Complex64::default());
    for i in 0..tr {
        for j in 0..tc {
            buf[i * nc + j] = Complex64::new(t[i * tc + j], 0.0);
        }
    }
    fft.transform_with(&mut buf, false, &mut work);
    for (b, sv) in buf.iter_mut().zip(&sh) {
        *b = sv * b.conj();
    }
    let spectrum = buf.clone();
    fft.transform_with(&mut buf, true, &mut work);
    let sign = best.value.signum();
    let map: Vec<f64> = buf.iter().map(|c| sign * c.re * scale / (s_norm * tn)).collect();
    let (k0, peak) =
        map.iter().enumerate().fold((0, f64::NEG_INFINITY), |b, (k, &v)| if v > b.1 { (k, v) } else { b });
    let peak_ratio = second_peak(&map, nr, nc, k0) / peak;
    let at = (lag(k0 / nc, s.rows, nr), lag(k0 % nc, s.cols, nc));
    let (dy, dx) = upsampled_peak(&spectrum, nr, nc, at, 10, sign);
    let (cs_i, cs_j) = s.centre();
    let shift = [(dx - cs_j + ct_j) * s.pitch[0], (dy - cs_i + ct_i) * s.pitch[1]];
    Ok(Coarse {
        pose: Pose { mirror, rotation: theta, scale: 1.0, shift },
        peak_ratio,
        rotation_contrast,
        mirror_ratio,
    })
}

/// The largest local maximum of `map` outside the main lobe around `k0` (the connected region,
/// along rows and columns, where the map stays above half the peak), relative to 0.
fn second_peak(map: &[f64], nr: usize, nc: usize, k0: usize) -> f64 {
    let (i0, j0) = ((k0 / nc) as isize, (k0 % nc) as isize);
    let peak = map[k0];
    let at = |i: isize, j: isize| {
        map[(i.rem_euclid(nr as isize) as usize) * nc + j.rem_euclid(nc as isize) as usize]
    };
    let mut r = 1isize;
    for (di, dj) in [(0, 1), (0, -1), (1, 0), (-1, 0)] {
        let mut k = 1;
        while k < (nr.max(nc) as isize) / 2 && at(i0 + di * k, j0 + dj * k) > 0.5 * peak {
            k += 1;
        }
        r = r.max(k);
    }
    let mut second = 0.0f64;
    for i in 0..nr as isize {
        for j in 0..nc as isize {
            let (di, dj) = ((i - i0).rem_euclid(nr as isize), (j - j0).rem_euclid(nc as isize));
            let (di, dj) = (di.min(nr as isize - di), dj.min(nc as isize - dj));
            if di.max(dj) <= r {
                continue;
            }
            let v = at(i, j);
            if v > second
                && v >= at(i - 1, j)
                && v >= at(i + 1, j)
                && v >= at(i, j - 1)
                && v >= at(i, j + 1)
                && v >= at(i - 1, j - 1)
                && v >= at(i + 1, j + 1)
                && v >= at(i - 1, j + 1)
                && v >= at(i + 1, j - 1)
            {
                second = v;
            }
        }
    }
    second
}

/// Guizar-Sicairos et al. (2008): the cross-correlation `sum_k P[k] e^{2 pi i k x / N} / N` on a
/// 1.5-pixel window around the integer peak `at`, sampled every `1/up` pixel by two matrix
/// products; returns the (row, column) lag of its largest value (times `sign`).
fn upsampled_peak(
    p: &[Complex64],
    nr: usize,
    nc: usize,
    at: (isize, isize),
    up: usize,
    sign: f64,
) -> (f64, f64) {
    let w = (1.5 * up as f64).ceil() as usize + 1;
    let off = |a: usize| (a as f64 - (w as f64 - 1.0) * 0.5) / up as f64;
    let freq = |k: usize, n: usize| if k > n / 2 { k as f64 - n as f64 } else { k as f64 };
    let kern = |n: usize, centre: isize| -> Vec<Complex64> {
        // kern[a * n + k] = exp(2 pi i f_k (centre + off_a) / n)
        let mut e = vec![Complex64::default(); w * n];
        for a in 0..w {
            let x = centre as f64 + off(a);
            for k in 0..n {
                let ph = 2.0 * std::f64::consts::PI * freq(k, n) * x / n as f64;
                e[a * n + k] = Complex64::new(ph.cos(), ph.sin());
            }
        }
        e
    };
    let ec = kern(nc, at.1);
    let er = kern(nr, at.0);
    // a[k_r][b] = sum_kc p[k_r][k_c] ec[b][k_c]
    let mut a = vec![Complex64::default(); nr * w];
    for kr in 0..nr {
        let row = &p[kr * nc..(kr + 1) * nc];
        for b in 0..w {
            let e = &ec[b * nc..(b + 1) * nc];
            a[kr * w + b] = row.iter().zip(e).map(|(x, y)| x * y).sum();
        }
    }
    let mut best = (f64::NEG_INFINITY, 0.0, 0.0);
    for ai in 0..w {
        let e = &er[ai * nr..(ai + 1) * nr];
        for b in 0..w {
            let v: Complex64 = (0..nr).map(|kr| e[kr] * a[kr * w + b]).sum();
            let v = sign * v.re;
            if v > best.0 {
                best = (v, at.0 as f64 + off(ai), at.1 as f64 + off(b));
            }
        }
    }
    (best.1, best.2)
}
