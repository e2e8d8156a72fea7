//! Procedural HDR scenes, so that fine-tuning and tests run with no data set.
//!
//! A scene is linear radiance `(H, W, 3)` in `[1e-5, 64]`, the range the paper clips its
//! training targets to, built from layers drawn with a seeded generator ([`crate::rng::Lcg`]):
//!
//! * textured surfaces: overlapping rectangles (walls, tables, objects) of an albedo drawn
//!   log-uniformly from 0.01 to 0.6 and a random tint, lit by an exponential gradient (up to
//!   12x across the frame), modulated by three octaves of value noise (bilinear-smoothstep
//!   interpolation of a random lattice);
//! * windows: rectangles of sky radiance 1.5-6 with dark mullions;
//! * emitters: lamps as discs of radiance 16-64 with an inverse-square glow;
//! * filaments: thin zig-zag wires of radiance 20-64 (light-bulb filaments);
//! * specular highlights: small Gaussian spots of radiance 1.5-8.
//!
//! Most pixels are diffuse surfaces between about 0.01 and 1 and the light sources sit one to
//! six stops above, so that scaling a scene to saturate 1-2 % of its pixels (the paper's
//! exposure rule) leaves detail in the saturated parts. The same seed and size give the same
//! values on every platform.
//!
//! Fine-tuning draws its scenes from a [`SceneSource`]; [`GeneratedScenes`] makes one of a
//! generator such as [`procedural_scene`].

use ndarray::{Array2, Array3};

use crate::error::{DataCause, Error, Result};
use crate::image::Image;
use crate::rng::Lcg;

/// A seeded procedural HDR scene, `height x width` RGB, linear radiance in `[1e-5, 64]`.
pub fn procedural_scene(seed: u64, height: usize, width: usize) -> Image<f32> {
    let mut rng = Lcg(seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ 0x5DEE_CE66_D1CE_5EED);
    let (h, w) = (height, width);
    let mut img = Array3::<f64>::zeros((h, w, 3));
    if h == 0 || w == 0 {
        return Image::new(img).to_f32();
    }
    let size = h.min(w) as f64;
    let mut uni = |a: f64, b: f64| a + (b - a) * rng.uniform();

    // Surfaces: a background, then rectangles painted over it.
    let texture = value_noise(&mut Lcg(seed ^ 0xA5A5), h, w, (size / 6.0).max(4.0));
    let rects = 3 + (uni(0.0, 4.0) as usize);
    for k in 0..=rects {
        let (r0, c0, r1, c1) = if k == 0 {
            (0.0, 0.0, h as f64, w as f64)
        } else {
            let (rh, rw) = (uni(0.15, 0.6) * h as f64, uni(0.15, 0.6) * w as f64);
            let (r0, c0) = (uni(0.0, h as f64 - rh), uni(0.0, w as f64 - rw));
            (r0, c0, r0 + rh, c0 + rw)
        };
        let albedo = uni(0.01f64.ln(), 0.6f64.ln()).exp();
        let tint = [uni(0.6, 1.0), uni(0.6, 1.0), uni(0.6, 1.0)];
        let (gy, gx) = (uni(-2.5, 2.5), uni(-2.5, 2.5));
        let contrast = uni(0.3, 0.9);
        for i in (r0 as usize)..(r1 as usize).min(h) {
            for j in (c0 as usize)..(c1 as usize).min(w) {
                let light = (gy * (i as f64 / h as f64 - 0.5) + gx * (j as f64 / w as f64 - 0.5)).exp();
                let t = 1.0 - contrast + contrast * 2.0 * texture[[i, j]];
                for (c, tc) in tint.iter().enumerate() {
                    img[[i, j, c]] = albedo * tc * light * t;
                }
            }
        }
    }

    // Windows with mullions.
    for _ in 0..(uni(0.0, 2.5) as usize) {
        let (wh, ww) = (uni(0.1, 0.3) * h as f64, uni(0.1, 0.3) * w as f64);
        let (r0, c0) = (uni(0.0, h as f64 - wh), uni(0.0, w as f64 - ww));
        let sky = uni(1.5, 6.0);
        let bar = (size / 80.0).max(1.0);
        for i in (r0 as usize)..((r0 + wh) as usize).min(h) {
            for j in (c0 as usize)..((c0 + ww) as usize).min(w) {
                let (di, dj) = (i as f64 - r0 - wh / 2.0, j as f64 - c0 - ww / 2.0);
                let mullion = di.abs() < bar || dj.abs() < bar;
                let v = if mullion { 0.02 } else { sky * (1.0 - 0.3 * (i as f64 - r0) / wh) };
                img[[i, j, 0]] = 0.8 * v;
                img[[i, j, 1]] = 0.9 * v;
                img[[i, j, 2]] = v;
            }
        }
    }

    // Lamps: discs with an inverse-square glow.
    for _ in 0..(1 + uni(0.0, 3.0) as usize) {
        let (ci, cj) = (uni(0.0, h as f64), uni(0.0, w as f64));
        let radius = uni(0.005, 0.03) * size + 1.0;
        let peak = uni(16.0, 64.0);
        let warm = [1.0, uni(0.7, 0.95), uni(0.4, 0.8)];
        let reach = (radius * 8.0) as isize;
        for i in (ci as isize - reach).max(0)..(ci as isize + reach).min(h as isize) {
            for j in (cj as isize - reach).max(0)..(cj as isize + reach).min(w as isize) {
                let r = ((i as f64 - ci).powi(2) + (j as f64 - cj).powi(2)).sqrt();
                let v = if r <= radius { peak } else { 0.3 * peak * (radius / r).powi(2) };
                for c in 0..3 {
                    img[[i as usize, j as usize, c]] += v * warm[c];
                }
            }
        }
    }

    // Filaments: zig-zag wires one pixel wide.
    for _ in 0..(uni(0.0, 2.5) as usize) {
        let (mut y, mut x) = (uni(0.1, 0.9) * h as f64, uni(0.1, 0.9) * w as f64);
        let peak = uni(20.0, 64.0);
        let seg = uni(0.01, 0.03) * size + 1.0;
        let dir = uni(0.0, std::f64::consts::TAU);
        for s in 0..(6 + uni(0.0, 8.0) as usize) {
            let a = dir + if s % 2 == 0 { 1.0 } else { -1.0 };
            let (dy, dx) = (a.sin(), a.cos());
            for step in 0..=(seg.ceil() as usize) {
                let (yy, xx) = (y + dy * step as f64, x + dx * step as f64);
                if yy >= 0.0 && xx >= 0.0 && (yy as usize) < h && (xx as usize) < w {
                    for (c, tint) in [1.0, 0.85, 0.6].iter().enumerate() {
                        img[[yy as usize, xx as usize, c]] = peak * tint;
                    }
                }
            }
            y += dy * seg;
            x += dx * seg;
        }
    }

    // Specular highlights.
    for _ in 0..(3 + uni(0.0, 8.0) as usize) {
        let (ci, cj) = (uni(0.0, h as f64), uni(0.0, w as f64));
        let sigma = uni(0.5, 3.0);
        let peak = uni(1.5, 8.0);
        let reach = (4.0 * sigma).ceil() as isize;
        for i in (ci as isize - reach).max(0)..(ci as isize + reach).min(h as isize) {
            for j in (cj as isize - reach).max(0)..(cj as isize + reach).min(w as isize) {
                let r2 = (i as f64 - ci).powi(2) + (j as f64 - cj).powi(2);
                let v = peak * (-r2 / (2.0 * sigma * sigma)).exp();
                for c in 0..3 {
                    img[[i as usize, j as usize, c]] += v;
                }
            }
        }
    }
    Image::new(img.mapv(|v| v.clamp(1e-5, 64.0))).to_f32()
}

/// Three octaves of value noise in `[0, 1]` with the coarsest lattice cell `cell` pixels.
fn value_noise(rng: &mut Lcg, h: usize, w: usize, cell: f64) -> Array2<f64> {
    let mut out = Array2::<f64>::zeros((h, w));
    let mut amp_sum = 0.0;
    for octave in 0..3 {
        let c = cell / f64::from(1 << octave);
        let amp = 0.5f64.powi(octave);
        let (lr, lc) = ((h as f64 / c).ceil() as usize + 2, (w as f64 / c).ceil() as usize + 2);
        let lattice = Array2::from_shape_fn((lr, lc), |_| rng.uniform());
        let smooth = |t: f64| t * t * (3.0 - 2.0 * t);
        for ((i, j), o) in out.indexed_iter_mut() {
            let (fy, fx) = (i as f64 / c, j as f64 / c);
            let (y0, x0) = (fy.floor() as usize, fx.floor() as usize);
            let (ty, tx) = (smooth(fy.fract()), smooth(fx.fract()));
            let top = lattice[[y0, x0]] * (1.0 - tx) + lattice[[y0, x0 + 1]] * tx;
            let bottom = lattice[[y0 + 1, x0]] * (1.0 - tx) + lattice[[y0 + 1, x0 + 1]] * tx;
            *o += amp * (top * (1.0 - ty) + bottom * ty);
        }
        amp_sum += amp;
    }
    out / amp_sum
}

/// Where training scenes come from: linear HDR RGB images, drawn with `rng`.
pub trait SceneSource: Sync {
    /// A short description for the decoder's metadata.
    fn describe(&self) -> String;
    /// One scene of exactly `rows x cols`.
    fn scene(&self, rng: &mut Lcg, rows: usize, cols: usize) -> Result<Image<f32>>;
}

/// Scenes from a generator `f(seed, rows, cols)` (such as a procedural scene generator), each
/// with a seed drawn from the run's generator.
pub struct GeneratedScenes<F> {
    /// What the scenes are: [`SceneSource::describe`] (the decoder's metadata) and errors give it.
    pub name: &'static str,
    /// The generator: `f(seed, rows, cols)` gives one linear HDR RGB scene of `rows x cols`; a
    /// non-finite or negative value in it is refused.
    pub generate: F,
}

impl<F> SceneSource for GeneratedScenes<F>
where
    F: Fn(u64, usize, usize) -> Image<f32> + Sync,
{
    fn describe(&self) -> String {
        self.name.to_string()
    }

    fn scene(&self, rng: &mut Lcg, rows: usize, cols: usize) -> Result<Image<f32>> {
        let seed = (rng.uniform() * (1u64 << 53) as f64) as u64;
        let scene = (self.generate)(seed, rows, cols);
        if let Some(v) = scene.values.iter().find(|v| !v.is_finite() || **v < 0.0) {
            let cause = if v.is_finite() { DataCause::OutOfRange } else { DataCause::NotFinite };
            return Err(Error::data(cause, format!("{} (seed {seed}) made the value {v}", self.name)));
        }
        Ok(scene)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The scale that saturates `fraction` of the samples (the paper's exposure rule).
    fn exposure_for(scene: &Image<f32>, fraction: f64) -> f64 {
        let mut v: Vec<f32> = scene.values.iter().copied().collect();
        v.sort_by(f32::total_cmp);
        1.0 / v[((1.0 - fraction) * v.len() as f64) as usize] as f64
    }

    #[test]
    fn deterministic_per_seed_and_in_range() {
        let a = procedural_scene(7, 96, 128);
        assert_eq!(a.dim(), (96, 128, 3));
        assert_eq!(a, procedural_scene(7, 96, 128));
        assert_ne!(a, procedural_scene(8, 96, 128));
        assert!(a.values.iter().all(|&v| (1e-5..=64.0).contains(&v)));
        assert_eq!(procedural_scene(1, 0, 5).dim(), (0, 5, 3));
    }

    #[test]
    fn the_papers_exposure_rule_leaves_hdr_detail_in_the_saturated_pixels() {
        for seed in 0..8 {
            let s = procedural_scene(seed, 160, 160);
            let k = exposure_for(&s, 0.015);
            let s = s.values;
            let n = s.len() as f64;
            let saturated = s.iter().filter(|&&v| v as f64 * k > 1.0).count() as f64 / n;
            assert!((0.01..=0.02).contains(&saturated), "seed {seed}: {saturated}");
            // Above the clip the scene spans at least three more stops ...
            let max = s.iter().fold(0.0f32, |m, &v| m.max(v)) as f64 * k;
            assert!(max >= 8.0, "seed {seed}: max {max}");
            // ... and below it the diffuse surfaces spread over a decade or more.
            let mut v: Vec<f64> = s.iter().map(|&x| x as f64 * k).collect();
            v.sort_by(f64::total_cmp);
            assert!(v[v.len() / 100] < 0.1 * v[v.len() * 9 / 10], "seed {seed}");
        }
    }
}
