//! Where each colour channel of a camera clips, from where its samples pile up.
//!
//! A sensor's raw values clip at one level, but a camera's RGB output need not clip every
//! channel at full scale: white balance and the colour matrix scale the raw channels before
//! they are written, so a channel whose gain is below the others' tops out below full scale.
//! The paper's captures (Canon Rebel T5, 8-bit) clip green at 231 of 255 (0.906) in every
//! frame, red and blue at 255. A value of 0.906 in green is then *saturated*, not a radiance:
//! a merge that weights it, a scorer that counts it unsaturated, or a decoder trained on
//! captures that clip every channel at 1 all read it as light that was measured.
//!
//! Detection: for each channel, the histogram of the samples' counts (`value x full scale`,
//! rounded); a count `v` in the upper half of the range is a *pile-up* when at least
//! [`MIN_SAMPLES`] samples (and 1e-4 of the channel's) sit at exactly `v` and at least
//! [`PILE_UP_RATIO`] times as many as the mean over the occupied counts within 3 % of full scale
//! around it (its neighbourhood, `v` left out). The channel's clipping level is its lowest
//! pile-up (as a fraction of full scale), or 1 when it has none. Measuring the mean over
//! *occupied* counts keeps a sensor of fewer bits than its file (12-bit data in a 16-bit PNG,
//! every 16th count used) from reading as a row of pile-ups.
//!
//! Where it fails: a scene with a large flat area at one bright value (a white wall exposed at
//! exactly 0.8) shows a pile-up that is not clipping; a channel that clips on too few samples
//! (under [`MIN_SAMPLES`]) is not detected. The level is reported, so a caller can check it
//! against other frames of the same camera (the paper's 23 frames all agree on 231).

use crate::image::Image;

/// Fewest samples at one count for a pile-up.
pub const MIN_SAMPLES: usize = 20;

/// How many times the neighbourhood's mean count a pile-up holds.
pub const PILE_UP_RATIO: f64 = 8.0;

/// The clipping level of each channel of `images` (all of one camera, values in `[0, 1]` of
/// `full_scale` counts), as a fraction of full scale: 1 where the channel has no pile-up below
/// or at full scale (see the module docs).
pub fn channel_clipping(images: &[&Image], full_scale: f64) -> Vec<f64> {
    let Some(first) = images.first() else { return Vec::new() };
    let top = full_scale.round() as usize;
    (0..first.channels())
        .map(|c| {
            let mut counts = vec![0usize; top + 1];
            let mut n = 0usize;
            for img in images {
                for v in img.values.index_axis(ndarray::Axis(2), c) {
                    let k = (v * full_scale).round().clamp(0.0, full_scale) as usize;
                    counts[k] += 1;
                    n += 1;
                }
            }
            let window = ((0.03 * full_scale).round() as usize).max(2);
            let floor = MIN_SAMPLES.max((1e-4 * n as f64).ceil() as usize);
            (top / 2..=top)
                .find(|&v| {
                    if counts[v] < floor {
                        return false;
                    }
                    let around: Vec<usize> = (v.saturating_sub(window)..=(v + window).min(top))
                        .filter(|&k| k != v && counts[k] > 0)
                        .map(|k| counts[k])
                        .collect();
                    let mean = if around.is_empty() {
                        0.0
                    } else {
                        around.iter().sum::<usize>() as f64 / around.len() as f64
                    };
                    counts[v] as f64 >= PILE_UP_RATIO * mean
                })
                .map_or(1.0, |v| v as f64 / full_scale)
        })
        .collect()
}

/// The full-scale count of an image of counts divided by it: 255 or 65535 when every value is
/// a whole number of such steps (an 8- or 16-bit capture), `None` otherwise (a float image).
pub fn full_scale_of(image: &Image) -> Option<f64> {
    [255.0, 65535.0].into_iter().find(|fs: &f64| {
        image.iter().all(|&v| {
            let k = v * fs;
            (k - k.round()).abs() < 1e-6
        })
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Lcg;
    use ndarray::Array3;

    /// An 8-bit capture of a smooth ramp whose green is scaled by `g_gain` and clipped at
    /// `g_clip` counts, red and blue at 255.
    fn ramp(g_gain: f64, g_clip: f64, seed: u64) -> Image {
        let mut rng = Lcg(seed);
        Image::new(Array3::from_shape_fn((120, 160, 3), |(i, j, c)| {
            let x = 1.4 * (i * 160 + j) as f64 / (120.0 * 160.0) + 0.02 * rng.normal();
            let counts = match c {
                1 => (255.0 * x * g_gain).min(g_clip),
                _ => 255.0 * x,
            };
            counts.round().clamp(0.0, 255.0) / 255.0
        }))
    }

    #[test]
    fn finds_a_channel_clipping_below_full_scale() {
        let img = ramp(1.1, 231.0, 1);
        assert_eq!(full_scale_of(&img), Some(255.0));
        assert_eq!(full_scale_of(&Image::new(img.values.mapv(|v| v * 0.999))), None);
        let levels = channel_clipping(&[&img], 255.0);
        assert_eq!(levels, vec![1.0, 231.0 / 255.0, 1.0]);
    }

    #[test]
    fn no_pile_up_no_clipping_and_a_scene_that_never_clips_reads_full_scale() {
        // Values up to 0.8 of full scale only: nothing piles up.
        let mut rng = Lcg(2);
        let img = Image::new(Array3::from_shape_fn((120, 160, 3), |(i, j, _)| {
            let x = 0.8 * (i * 160 + j) as f64 / (120.0 * 160.0) + 0.01 * rng.normal();
            (255.0 * x).round().clamp(0.0, 255.0) / 255.0
        }));
        assert_eq!(channel_clipping(&[&img], 255.0), vec![1.0; 3]);
    }

    #[test]
    fn twelve_bits_in_a_sixteen_bit_file_are_not_read_as_pile_ups() {
        // Every 16th count used; values up to 1.1 of the 12-bit range.
        let counts = |seed: u64| {
            let mut rng = Lcg(seed);
            Array3::from_shape_fn((100, 100, 1), move |_| (rng.uniform() * 1.1 * 4095.0).round())
        };
        let sixteen = |c: f64| c * 16.0 / 65535.0;
        // Up to 0.9 of the range: none clipped.
        let img = Image::new(counts(3).mapv(|c| sixteen((c * 0.9 / 1.1).round())));
        assert_eq!(channel_clipping(&[&img], 65535.0), vec![1.0]);
        // Clipped at 4000 of 4095: piles up there.
        let clipped = Image::new(counts(4).mapv(|c| sixteen(c.min(4000.0))));
        let level = channel_clipping(&[&clipped], 65535.0)[0];
        assert!((level - 64000.0 / 65535.0).abs() < 1e-12, "{level}");
    }
}
