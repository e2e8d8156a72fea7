//! Grayscale lithography masks: the quantized map on the writer's address grid, mapped from
//! target depth to gray level through the resist contrast curve, with a frame, alignment
//! crosses and a label outside the optical aperture.
//!
//! Mapping (per level `l` of `N`, step `s = P / N`):
//! * positive resist: developed depth `d = (N - 1 - l) s` (the top level is not exposed);
//! * negative resist: remaining thickness `t = l s`.
//!
//! The dose for that depth comes from the inverted contrast curve, and
//! `gray = round(dose * full_scale)` with `full_scale = 2^bits - 1`: gray 0 is no exposure,
//! full scale is the writer's full dose. The frame is gray 0 and crosses and label are full
//! scale. Each design sample is a flat cell, so resampling to the writer grid takes the
//! nearest sample (no interpolation across phase wraps).

use ndarray::{s, Array2};
use serde::{Deserialize, Serialize};

use crate::error::{DataCause, Error, Resource, Result};
use crate::fabrication::contrast::ContrastCurve;
use crate::fabrication::marks::{label_cells, Canvas};
use crate::fabrication::Provenance;
use crate::grid::{row_blocks, Grid, Interpolation, Unit};

/// Resist polarity.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[cfg_attr(feature = "cli", derive(clap::ValueEnum))]
#[serde(rename_all = "snake_case")]
pub enum Polarity {
    /// Exposed resist dissolves: depth grows with dose.
    #[default]
    Positive,
    /// Exposed resist stays: remaining thickness grows with dose.
    Negative,
}

/// Options of the grayscale mask.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct MaskOptions {
    /// Writer address grid, metres.
    pub writer_pitch: f64,
    /// 8 or 16.
    pub bits: u8,
    /// Resist polarity: which of depth or remaining thickness the dose makes.
    pub polarity: Polarity,
    /// Mirror the pattern left-right on the mask (for writing through the substrate).
    pub mirror: bool,
    /// Width of the frame around the pattern, metres.
    pub border: f64,
    /// Draw alignment crosses in the frame's corners.
    pub marks: bool,
    /// Text drawn in the frame below the pattern (empty for none).
    pub label: String,
    /// Refuse outputs above this many pixels unless `force`.
    pub max_pixels: usize,
    /// Write a mask above `max_pixels` anyway.
    pub force: bool,
}

impl Default for MaskOptions {
    fn default() -> Self {
        MaskOptions {
            writer_pitch: 1e-6,
            bits: 16,
            polarity: Polarity::Positive,
            mirror: false,
            border: 500e-6,
            marks: true,
            label: String::new(),
            max_pixels: 200_000_000,
            force: false,
        }
    }
}

/// One level's row of the mapping table.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct LevelDose {
    /// Level index, 0..N-1.
    pub level: usize,
    /// Target surface height of the level, metres.
    pub height_m: f64,
    /// What the contrast curve must deliver: developed depth (positive) or remaining
    /// thickness (negative), metres.
    pub curve_depth_m: f64,
    /// Relative dose, 0..=1.
    pub dose: f64,
    /// Gray value written for the level, counts: `round(dose * full_scale)`.
    pub gray: u32,
}

/// Most rows of a sidecar's level table: a 16-bit mask's 65,536 levels would make a file of
/// 11 MB that states one rule.
pub const MAX_LISTED_LEVELS: usize = 257;

/// The rows of `table` a sidecar lists (see [`MaskMeta::levels_listed`]).
fn listed(table: Vec<LevelDose>) -> Vec<LevelDose> {
    let n = table.len();
    if n <= MAX_LISTED_LEVELS {
        return table;
    }
    let m = MAX_LISTED_LEVELS - 1;
    (0..=m).map(|k| table[k * (n - 1) / m].clone()).collect()
}

fn listed_rule(n: usize) -> String {
    if n <= MAX_LISTED_LEVELS {
        format!("all {n} levels")
    } else {
        format!(
            "{MAX_LISTED_LEVELS} of {n} levels, level k (n - 1) / {} for k = 0..={}; every level maps the same way: \
             its height to the curve's depth by the polarity, to a dose through the inverted contrast curve, \
             gray = round(dose * full_scale)",
            MAX_LISTED_LEVELS - 1,
            MAX_LISTED_LEVELS - 1
        )
    }
}

/// The sidecar metadata of a grayscale mask (written as JSON next to the image).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct MaskMeta {
    /// What the file is: `grayscale_lithography_mask`.
    pub kind: String,
    /// The unit of each kind of value in the sidecar (`length`, `pitch`, `height`: `m`; `dose`:
    /// relative to full scale; `gray`: counts).
    pub units: std::collections::BTreeMap<String, String>,
    /// `[x, y]` writer pitch, metres.
    pub pitch_m: [f64; 2],
    /// `[width, height]` of the image, pixels.
    pub size_px: [usize; 2],
    /// Top-left pixel of the pattern inside the frame, `[x, y]`.
    pub pattern_offset_px: [usize; 2],
    /// `[width, height]` of the pattern, pixels.
    pub pattern_size_px: [usize; 2],
    /// Bits per pixel of the image, 8 or 16.
    pub bits: u8,
    /// Largest gray value, `2^bits - 1` counts (full writer dose).
    pub full_scale: u32,
    /// What gray 0 means, in words (no exposure).
    pub gray_0: String,
    /// What gray `full_scale` means, in words (full writer dose).
    pub gray_full_scale: String,
    /// Resist polarity.
    pub polarity: Polarity,
    /// What the contrast curve's depth is under this polarity, in words (developed depth, or
    /// remaining thickness).
    pub curve_meaning: String,
    /// The pattern is mirrored left-right (for writing through the substrate).
    pub mirrored: bool,
    /// Number of levels `N` of the level map.
    pub level_count: usize,
    /// Depth of one full period (p * h_2pi), metres.
    pub period_m: f64,
    /// Which levels `levels` lists: every level up to [`MAX_LISTED_LEVELS`]; above, evenly
    /// spaced ones including the first and the last, each row exact.
    #[serde(default)]
    pub levels_listed: String,
    /// Level -> height -> curve depth -> dose -> gray, one row per listed level.
    pub levels: Vec<LevelDose>,
    /// The contrast curve's file (or `built-in:NAME`).
    pub contrast_curve: String,
    /// Cross centres, pixels `[x, y]`.
    pub marks_px: Vec<[f64; 2]>,
    /// Text drawn in the frame below the pattern (empty for none).
    pub label: String,
    /// Where the mask came from: design, wavelength, material, period, levels.
    pub provenance: Provenance,
    /// What `doefab precompensate` corrected, from which scan, and what it predicts (absent in
    /// a plain `fab` mask).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub precompensation: Option<serde_json::Value>,
}

/// A rendered grayscale mask.
#[derive(Debug, Clone)]
pub struct GrayscaleMask {
    /// Gray levels, row 0 at the top.
    pub gray: Array2<u16>,
    /// The sidecar metadata written next to the image.
    pub meta: MaskMeta,
}

/// Renders the mask of a level map (`Unit::Level`, values `0..level_count`), level `l` at the
/// height `l period / level_count`.
pub fn render(
    levels: &Grid,
    level_count: usize,
    period: f64,
    curve: &ContrastCurve,
    opts: &MaskOptions,
    provenance: &Provenance,
) -> Result<GrayscaleMask> {
    let step = period / level_count as f64;
    let heights: Vec<f64> = (0..level_count).map(|l| l as f64 * step).collect();
    render_levels(levels, &heights, period, curve, opts, provenance)
}

/// Renders the mask of a level map whose level `l` is written at the height `heights[l]`
/// (metres, increasing): the positive resist develops `max(heights) - heights[l]`, the negative
/// keeps `heights[l]`. [`render`] is the case `heights[l] = l period / N`; pre-compensation
/// ([`crate::fabrication::precompensate`]) gives corrected tables.
pub fn render_levels(
    levels: &Grid,
    heights: &[f64],
    period: f64,
    curve: &ContrastCurve,
    opts: &MaskOptions,
    provenance: &Provenance,
) -> Result<GrayscaleMask> {
    let level_count = heights.len();
    if level_count < 2 || !heights.iter().all(|h| h.is_finite()) || heights.windows(2).any(|w| w[1] <= w[0]) {
        return Err(Error::param("levels", "the level heights must be finite and increase strictly"));
    }
    if levels.unit() != Unit::Level {
        return Err(Error::param("levels", "expected a quantized level map"));
    }
    if opts.bits != 8 && opts.bits != 16 {
        return Err(Error::param("bits", format!("must be 8 or 16, got {}", opts.bits)));
    }
    let full_scale: u32 = (1u32 << opts.bits) - 1;
    if level_count > full_scale as usize + 1 {
        return Err(Error::param(
            "level_count",
            format!("{level_count} levels do not fit an {}-bit mask", opts.bits),
        ));
    }
    if levels.mask().is_some() {
        return Err(Error::data(
            DataCause::NotFinite,
            "the level map has non-measured samples: fill them before writing a mask",
        ));
    }
    // Size check before any large allocation.
    let layout = Layout::new(levels.extent(), opts);
    let Layout { w, h, pw, ph, b } = layout;
    if w.saturating_mul(h) > opts.max_pixels && !opts.force {
        let what = format!(
            "the mask would be {w} x {h} = {:.0} Mpx at a {:.3} um writer grid, above the limit of {:.0} Mpx; \
             set `force` to write it anyway",
            (w * h) as f64 / 1e6,
            opts.writer_pitch * 1e6,
            opts.max_pixels as f64 / 1e6
        );
        return Err(Error::limit(Resource::Samples, (w * h) as f64, opts.max_pixels as f64, what));
    }
    let table = dose_table(heights, curve, opts.polarity, full_scale)?;
    let gray_of: Vec<u16> = table.iter().map(|t| t.gray as u16).collect();
    let mut gray = paint_pattern(levels, opts, &layout, &gray_of)?;
    let mut marks_px = Vec::new();
    if b > 0 && (opts.marks || !opts.label.is_empty()) {
        let mut canvas = Canvas::new(w, h)?;
        let bf = b as f32;
        if opts.marks {
            let arm = (0.8 * bf).min((200e-6 / opts.writer_pitch) as f32).max(3.0);
            let width = (arm / 10.0).max(1.0);
            let (wf, hf) = (w as f32, h as f32);
            for (cx, cy) in [
                (0.5 * bf, 0.5 * bf),
                (wf - 0.5 * bf, 0.5 * bf),
                (0.5 * bf, hf - 0.5 * bf),
                (wf - 0.5 * bf, hf - 0.5 * bf),
            ] {
                canvas.cross(cx, cy, arm, width);
                marks_px.push([cx as f64, cy as f64]);
            }
        }
        if !opts.label.is_empty() {
            // Between the lower crosses, vertically centred in the bottom frame.
            let cells = label_cells(&opts.label) as f32;
            let cell = (0.4 * bf / 7.0)
                .min((w as f32 - 2.0 * bf) / cells.max(1.0))
                .min((100e-6 / opts.writer_pitch) as f32 / 7.0);
            if cell >= 1.0 {
                canvas.text(bf, h as f32 - 0.5 * bf - 3.5 * cell, cell.floor(), &opts.label)?;
            } else {
                return Err(Error::param("label", "the frame is too narrow for the label: widen `border`"));
            }
        }
        // Only the frame can be covered: rows above and below the pattern, and the columns
        // left and right of it.
        let canvas = &canvas;
        row_blocks::map_blocks_mut(&mut gray, |r0, mut block| {
            for (k, mut out) in block.rows_mut().into_iter().enumerate() {
                let i = r0 + k;
                let frame_row = i < b || i >= b + ph;
                // The whole row in the frame, else its parts left and right of the pattern.
                let cols = if frame_row { [0..w, 0..0] } else { [0..b, b + pw..w] };
                for j in cols.into_iter().flatten() {
                    if canvas.covered(j, i) {
                        out[j] = full_scale as u16;
                    }
                }
            }
        });
    }
    let units = [
        ("length", "m"),
        ("pitch", "m"),
        ("height", "m"),
        ("dose", "relative to the writer's full-scale dose"),
        ("gray", "counts"),
    ]
    .into_iter()
    .map(|(k, v)| (k.to_string(), v.to_string()))
    .collect();
    let meta = MaskMeta {
        kind: "grayscale_lithography_mask".into(),
        units,
        pitch_m: [opts.writer_pitch; 2],
        size_px: [w, h],
        pattern_offset_px: [b, b],
        pattern_size_px: [pw, ph],
        bits: opts.bits,
        full_scale,
        gray_0: "no exposure (relative dose 0)".into(),
        gray_full_scale: "full writer dose (relative dose 1)".into(),
        polarity: opts.polarity,
        curve_meaning: match opts.polarity {
            Polarity::Positive => "developed depth below the resist top".into(),
            Polarity::Negative => "remaining resist thickness".into(),
        },
        mirrored: opts.mirror,
        level_count,
        period_m: period,
        levels_listed: listed_rule(level_count),
        levels: listed(table),
        contrast_curve: curve.source.display().to_string(),
        marks_px,
        label: opts.label.clone(),
        provenance: provenance.clone(),
        precompensation: None,
    };
    Ok(GrayscaleMask { gray, meta })
}

/// The mask's layout on the writer grid, pixels: the pattern `pw x ph` inside a frame of `b`
/// on every side, `w x h` in all.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Layout {
    w: usize,
    h: usize,
    pw: usize,
    ph: usize,
    b: usize,
}

impl Layout {
    /// The layout of a design of extent `ext` (metres, `[x, y]`) on the writer grid of `opts`.
    fn new(ext: [f64; 2], opts: &MaskOptions) -> Layout {
        let pw = (ext[0] / opts.writer_pitch).round() as usize;
        let ph = (ext[1] / opts.writer_pitch).round() as usize;
        let b = (opts.border / opts.writer_pitch).round() as usize;
        Layout { w: pw + 2 * b, h: ph + 2 * b, pw, ph, b }
    }
}

/// The level -> gray table (module docs): level `l` at `heights[l]` needs the curve's depth
/// `max(heights) - heights[l]` (positive resist) or `heights[l]` (negative), the dose for it
/// from the inverted contrast curve and `gray = round(dose full_scale)`. Computed once per
/// level, in parallel; the first failing level in order is the one reported.
fn dose_table(
    heights: &[f64],
    curve: &ContrastCurve,
    polarity: Polarity,
    full_scale: u32,
) -> Result<Vec<LevelDose>> {
    use rayon::prelude::*;
    let top = heights[heights.len() - 1];
    let rows: Vec<Result<LevelDose>> = (0..heights.len())
        .into_par_iter()
        .map(|l| {
            let target = match polarity {
                Polarity::Positive => top - heights[l],
                Polarity::Negative => heights[l],
            };
            let dose = curve.dose_for(target)?;
            Ok(LevelDose {
                level: l,
                height_m: heights[l],
                curve_depth_m: target,
                dose,
                gray: (dose * full_scale as f64).round() as u32,
            })
        })
        .collect();
    rows.into_iter().collect()
}

/// The mask with the pattern painted: the level map on the writer grid (as it is when already
/// there, else by nearest resampling; mirrored when `opts.mirror`), each level's gray
/// `gray_of[l]` inside the frame, the frame 0. Row blocks in parallel; the first level out of
/// range in row-major order is the one reported.
fn paint_pattern(levels: &Grid, opts: &MaskOptions, layout: &Layout, gray_of: &[u16]) -> Result<Array2<u16>> {
    let Layout { w, h, pw, ph, b } = *layout;
    // A design already on the writer grid is taken as it is.
    let same =
        levels.dim() == (ph, pw) && levels.pitch().iter().all(|p| (p - opts.writer_pitch).abs() <= 1e-12 * p);
    let resampled;
    let on_writer = if same {
        levels
    } else {
        resampled = levels.resample_to(ph, pw, [opts.writer_pitch; 2], Interpolation::Nearest)?;
        &resampled
    };
    let mirrored;
    let on_writer = if opts.mirror {
        mirrored = on_writer.mirror(true, false);
        &mirrored
    } else {
        on_writer
    };
    let mut gray = Array2::<u16>::zeros((h, w));
    // The pattern, row blocks in parallel; the first level out of range in row-major order is
    // the one reported.
    let src = on_writer.values();
    let bad = row_blocks::map_blocks_mut(&mut gray, |r0, mut block| {
        for (k, mut out) in block.rows_mut().into_iter().enumerate() {
            let Some(i) = (r0 + k).checked_sub(b).filter(|&i| i < ph) else { continue };
            for (j, (o, &l)) in out.slice_mut(s![b..b + pw]).iter_mut().zip(src.row(i)).enumerate() {
                match gray_of.get(l as usize) {
                    Some(&g) => *o = g,
                    None => return Some((l as usize, i, j)),
                }
            }
        }
        None
    });
    if let Some((l, i, j)) = bad.into_iter().flatten().next() {
        let level_count = gray_of.len();
        return Err(Error::data(
            DataCause::OutOfRange,
            format!("level {l} at row {i}, column {j} is outside 0..{level_count}"),
        ));
    }
    Ok(gray)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::path::Path;

    fn linear_curve(max_depth: f64) -> ContrastCurve {
        ContrastCurve::new(vec![0.0, 1.0], vec![0.0, max_depth], Path::new("linear.csv")).unwrap()
    }

    fn levels(n: usize) -> Grid {
        let v = Array2::from_shape_fn((10, 12), |(i, j)| ((i + j) % n) as f64);
        Grid::new(v, [4e-6, 4e-6], Unit::Level).unwrap()
    }

    #[test]
    fn linear_curve_maps_levels_to_proportional_gray() {
        let period = 1.2e-6;
        let n = 4;
        let opts = MaskOptions { writer_pitch: 2e-6, border: 0.0, marks: false, ..Default::default() };
        let m = render(&levels(n), n, period, &linear_curve(period), &opts, &Provenance::default()).unwrap();
        assert_eq!(m.gray.dim(), (20, 24));
        // Positive resist: level l -> depth (N-1-l) s -> dose (N-1-l)/N.
        for l in 0..n {
            let expect = ((n - 1 - l) as f64 / n as f64 * 65535.0).round() as u16;
            assert_eq!(m.meta.levels[l].gray as u16, expect);
        }
        // Pixel (0,0) is level 0 on a 2x finer grid: rows 0-1, cols 0-1.
        assert_eq!(m.gray[[1, 1]], m.meta.levels[0].gray as u16);
        assert_eq!(m.gray[[0, 2]], m.meta.levels[1].gray as u16);
        let neg = MaskOptions { polarity: Polarity::Negative, ..opts };
        let m = render(&levels(n), n, period, &linear_curve(period), &neg, &Provenance::default()).unwrap();
        assert_eq!(m.meta.levels[3].gray, (0.75f64 * 65535.0).round() as u32);
        assert_eq!(m.meta.levels[0].gray, 0);
    }

    #[test]
    fn marks_and_label_stay_outside_the_pattern() {
        let period = 1.2e-6;
        let base = MaskOptions { writer_pitch: 1e-6, border: 30e-6, marks: false, ..Default::default() };
        let plain =
            render(&levels(4), 4, period, &linear_curve(period), &base, &Provenance::default()).unwrap();
        let deco = MaskOptions { marks: true, label: "DOE 1".into(), ..base };
        let m = render(&levels(4), 4, period, &linear_curve(period), &deco, &Provenance::default()).unwrap();
        let [bx, by] = m.meta.pattern_offset_px;
        let [pw, ph] = m.meta.pattern_size_px;
        for i in 0..m.gray.dim().0 {
            for j in 0..m.gray.dim().1 {
                let inside = i >= by && i < by + ph && j >= bx && j < bx + pw;
                if inside {
                    assert_eq!(m.gray[[i, j]], plain.gray[[i, j]]);
                }
            }
        }
        assert_eq!(m.meta.marks_px.len(), 4);
        let [cx, cy] = m.meta.marks_px[0];
        assert_eq!(m.gray[[cy as usize, cx as usize]], 65535);
        let marked = m.gray.iter().filter(|&&g| g == 65535).count();
        let plain_marked = plain.gray.iter().filter(|&&g| g == 65535).count();
        assert!(marked > plain_marked + 4 * 20);
    }

    #[test]
    fn refuses_what_it_cannot_write() {
        let period = 1.2e-6;
        // The curve does not reach the deepest level.
        let e = render(
            &levels(4),
            4,
            period,
            &linear_curve(0.5e-6),
            &MaskOptions::default(),
            &Provenance::default(),
        )
        .unwrap_err();
        assert!(matches!(e, Error::Data { cause: DataCause::OutOfRange, .. }), "{e:?}");
        // Size limit, then force.
        let big = MaskOptions { writer_pitch: 0.01e-6, max_pixels: 1_000_000, ..Default::default() };
        let e =
            render(&levels(4), 4, period, &linear_curve(period), &big, &Provenance::default()).unwrap_err();
        assert!(matches!(e, Error::Limit { resource: Resource::Samples, limit: 1e6, .. }), "{e:?}");
        let bad = MaskOptions { bits: 12, ..Default::default() };
        assert!(render(&levels(4), 4, period, &linear_curve(period), &bad, &Provenance::default()).is_err());
        let narrow = MaskOptions { border: 2e-6, label: "TOO LONG A LABEL".into(), ..Default::default() };
        assert!(
            render(&levels(4), 4, period, &linear_curve(period), &narrow, &Provenance::default()).is_err()
        );
    }

    /// Through a linear curve (depth = dose x 1.2 um) level `l` takes the dose
    /// `(h_max - h_l) / 1.2 um` (positive resist) or `h_l / 1.2 um` (negative) and the gray
    /// `round(dose 255)`; a height beyond the curve is refused.
    #[test]
    fn the_dose_table_inverts_the_contrast_curve() {
        let heights = [0.0, 0.25e-6, 0.5e-6, 0.9e-6];
        for polarity in [Polarity::Positive, Polarity::Negative] {
            let t = dose_table(&heights, &linear_curve(1.2e-6), polarity, 255).unwrap();
            for (l, row) in t.iter().enumerate() {
                let depth = if polarity == Polarity::Positive { 0.9e-6 - heights[l] } else { heights[l] };
                let dose = depth / 1.2e-6;
                assert!((row.dose - dose).abs() < 1e-12, "{polarity:?} {row:?}");
                assert_eq!((row.level, row.gray), (l, (dose * 255.0).round() as u32), "{polarity:?}");
            }
        }
        assert!(dose_table(&[0.0, 2e-6], &linear_curve(1.2e-6), Polarity::Negative, 255).is_err());
        let layout = Layout::new(
            [40e-6, 48e-6],
            &MaskOptions { writer_pitch: 2e-6, border: 10e-6, ..Default::default() },
        );
        assert_eq!(layout, Layout { w: 30, h: 34, pw: 20, ph: 24, b: 5 });
    }
}
