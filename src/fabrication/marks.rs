//! Alignment crosses and text labels drawn with tiny-skia into a coverage mask, for the
//! frame around the optical aperture of masks and previews.
//!
//! Text uses a built-in 5 x 7 pixel font (the classic HD44780 character-ROM shapes), drawn as
//! filled squares, so labels need no font file and render identically everywhere.

use tiny_skia::{FillRule, Mask, PathBuilder, Rect, Transform};

use crate::error::{DataCause, Error, Resource, Result};

/// Rows of a 5 x 7 glyph, top to bottom; bit 4 is the leftmost column.
fn glyph(c: char) -> Option<[u8; 7]> {
    Some(match c.to_ascii_uppercase() {
        '0' => [0x0E, 0x11, 0x13, 0x15, 0x19, 0x11, 0x0E],
        '1' => [0x04, 0x0C, 0x04, 0x04, 0x04, 0x04, 0x0E],
        '2' => [0x0E, 0x11, 0x01, 0x02, 0x04, 0x08, 0x1F],
        '3' => [0x1F, 0x02, 0x04, 0x02, 0x01, 0x11, 0x0E],
        '4' => [0x02, 0x06, 0x0A, 0x12, 0x1F, 0x02, 0x02],
        '5' => [0x1F, 0x10, 0x1E, 0x01, 0x01, 0x11, 0x0E],
        '6' => [0x06, 0x08, 0x10, 0x1E, 0x11, 0x11, 0x0E],
        '7' => [0x1F, 0x01, 0x02, 0x04, 0x08, 0x08, 0x08],
        '8' => [0x0E, 0x11, 0x11, 0x0E, 0x11, 0x11, 0x0E],
        '9' => [0x0E, 0x11, 0x11, 0x0F, 0x01, 0x02, 0x0C],
        'A' => [0x0E, 0x11, 0x11, 0x11, 0x1F, 0x11, 0x11],
        'B' => [0x1E, 0x11, 0x11, 0x1E, 0x11, 0x11, 0x1E],
        'C' => [0x0E, 0x11, 0x10, 0x10, 0x10, 0x11, 0x0E],
        'D' => [0x1C, 0x12, 0x11, 0x11, 0x11, 0x12, 0x1C],
        'E' => [0x1F, 0x10, 0x10, 0x1E, 0x10, 0x10, 0x1F],
        'F' => [0x1F, 0x10, 0x10, 0x1E, 0x10, 0x10, 0x10],
        'G' => [0x0E, 0x11, 0x10, 0x17, 0x11, 0x11, 0x0F],
        'H' => [0x11, 0x11, 0x11, 0x1F, 0x11, 0x11, 0x11],
        'I' => [0x0E, 0x04, 0x04, 0x04, 0x04, 0x04, 0x0E],
        'J' => [0x07, 0x02, 0x02, 0x02, 0x02, 0x12, 0x0C],
        'K' => [0x11, 0x12, 0x14, 0x18, 0x14, 0x12, 0x11],
        'L' => [0x10, 0x10, 0x10, 0x10, 0x10, 0x10, 0x1F],
        'M' => [0x11, 0x1B, 0x15, 0x15, 0x11, 0x11, 0x11],
        'N' => [0x11, 0x11, 0x19, 0x15, 0x13, 0x11, 0x11],
        'O' => [0x0E, 0x11, 0x11, 0x11, 0x11, 0x11, 0x0E],
        'P' => [0x1E, 0x11, 0x11, 0x1E, 0x10, 0x10, 0x10],
        'Q' => [0x0E, 0x11, 0x11, 0x11, 0x15, 0x12, 0x0D],
        'R' => [0x1E, 0x11, 0x11, 0x1E, 0x14, 0x12, 0x11],
        'S' => [0x0F, 0x10, 0x10, 0x0E, 0x01, 0x01, 0x1E],
        'T' => [0x1F, 0x04, 0x04, 0x04, 0x04, 0x04, 0x04],
        'U' => [0x11, 0x11, 0x11, 0x11, 0x11, 0x11, 0x0E],
        'V' => [0x11, 0x11, 0x11, 0x11, 0x11, 0x0A, 0x04],
        'W' => [0x11, 0x11, 0x11, 0x15, 0x15, 0x15, 0x0A],
        'X' => [0x11, 0x11, 0x0A, 0x04, 0x0A, 0x11, 0x11],
        'Y' => [0x11, 0x11, 0x11, 0x0A, 0x04, 0x04, 0x04],
        'Z' => [0x1F, 0x01, 0x02, 0x04, 0x08, 0x10, 0x1F],
        ' ' => [0; 7],
        '.' => [0, 0, 0, 0, 0, 0x0C, 0x0C],
        ',' => [0, 0, 0, 0, 0x0C, 0x04, 0x08],
        '-' => [0, 0, 0, 0x1F, 0, 0, 0],
        '_' => [0, 0, 0, 0, 0, 0, 0x1F],
        ':' => [0, 0x0C, 0x0C, 0, 0x0C, 0x0C, 0],
        '/' => [0, 0x01, 0x02, 0x04, 0x08, 0x10, 0],
        '=' => [0, 0, 0x1F, 0, 0x1F, 0, 0],
        '+' => [0, 0x04, 0x04, 0x1F, 0x04, 0x04, 0],
        '(' => [0x02, 0x04, 0x08, 0x08, 0x08, 0x04, 0x02],
        ')' => [0x08, 0x04, 0x02, 0x02, 0x02, 0x04, 0x08],
        '#' => [0x0A, 0x0A, 0x1F, 0x0A, 0x1F, 0x0A, 0x0A],
        _ => return None,
    })
}

/// Checks that every character of `text` has a glyph.
pub fn check_label(text: &str) -> Result<()> {
    let bad: String = text.chars().filter(|c| glyph(*c).is_none()).collect();
    if bad.is_empty() {
        Ok(())
    } else {
        Err(Error::param(
            "label",
            format!("characters {bad:?} are not in the label font (A-Z, 0-9, space, .,-_:/=+()#)"),
        ))
    }
}

/// Width in font cells of `text` (6 cells per character including spacing, minus the last gap).
pub fn label_cells(text: &str) -> usize {
    (text.chars().count() * 6).saturating_sub(1)
}

/// A coverage canvas in pixel units.
pub struct Canvas {
    mask: Mask,
}

impl Canvas {
    /// An empty canvas of `width` x `height` pixels; refused where it cannot be allocated.
    pub fn new(width: usize, height: usize) -> Result<Canvas> {
        let fail = || {
            let what = format!("cannot allocate a {width} x {height} drawing canvas");
            match width.max(height) {
                side if width.min(height) > 0 => {
                    Error::limit(Resource::Samples, side as f64, f64::from(u32::MAX), what)
                }
                _ => Error::data(DataCause::Empty, what),
            }
        };
        let (w, h) = (u32::try_from(width).map_err(|_| fail())?, u32::try_from(height).map_err(|_| fail())?);
        let mask = Mask::new(w, h).ok_or_else(fail)?;
        Ok(Canvas { mask })
    }

    /// Fills the union of axis-aligned rectangles `(x, y, w, h)` in pixels.
    fn fill_rects(&mut self, rects: &[(f32, f32, f32, f32)]) {
        let mut pb = PathBuilder::new();
        for &(x, y, w, h) in rects {
            if let Some(r) = Rect::from_xywh(x, y, w, h) {
                pb.push_rect(r);
            }
        }
        if let Some(path) = pb.finish() {
            self.mask.fill_path(&path, FillRule::Winding, false, Transform::identity());
        }
    }

    /// An alignment cross centred at `(cx, cy)` with arm length `arm` (tip to tip) and
    /// line width `width`, pixels.
    pub fn cross(&mut self, cx: f32, cy: f32, arm: f32, width: f32) {
        self.fill_rects(&[
            (cx - arm / 2.0, cy - width / 2.0, arm, width),
            (cx - width / 2.0, cy - arm / 2.0, width, arm),
        ]);
    }

    /// Text with its top-left corner at `(x, y)` and one font cell = `cell` pixels.
    pub fn text(&mut self, x: f32, y: f32, cell: f32, text: &str) -> Result<()> {
        check_label(text)?;
        let mut rects = Vec::new();
        for (k, c) in text.chars().enumerate() {
            let g = glyph(c).unwrap_or([0; 7]);
            let x0 = x + (k * 6) as f32 * cell;
            for (row, bits) in g.iter().enumerate() {
                for col in 0..5 {
                    if bits & (0x10 >> col) != 0 {
                        rects.push((x0 + col as f32 * cell, y + row as f32 * cell, cell, cell));
                    }
                }
            }
        }
        self.fill_rects(&rects);
        Ok(())
    }

    /// True where a pixel is covered by at least half.
    pub fn covered(&self, x: usize, y: usize) -> bool {
        self.mask.data()[y * self.mask.width() as usize + x] >= 128
    }

    /// Width, pixels.
    pub fn width(&self) -> usize {
        self.mask.width() as usize
    }
    /// Height, pixels.
    pub fn height(&self) -> usize {
        self.mask.height() as usize
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cross_covers_its_arms_exactly() {
        let mut c = Canvas::new(50, 50).unwrap();
        c.cross(25.0, 25.0, 21.0, 3.0);
        let count =
            (0..50).flat_map(|y| (0..50).map(move |x| (x, y))).filter(|&(x, y)| c.covered(x, y)).count();
        // Two 21 x 3 bars overlapping in a 3 x 3 square.
        assert_eq!(count, 2 * 21 * 3 - 9);
        assert!(c.covered(25, 15) && c.covered(15, 25) && !c.covered(15, 15));
    }

    #[test]
    fn text_draws_the_glyph_bits() {
        let mut c = Canvas::new(20, 10).unwrap();
        c.text(1.0, 1.0, 1.0, "T1").unwrap();
        // 'T': full top row, then the centre column.
        assert!((1..6).all(|x| c.covered(x, 1)));
        assert!(c.covered(3, 5) && !c.covered(1, 5));
        assert!(c.text(0.0, 0.0, 1.0, "ü").is_err());
        assert_eq!(label_cells("AB"), 11);
    }
}
