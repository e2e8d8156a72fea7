//! The line across the part along which a profile meets the design ([`LineSpec`]): two points,
//! or an angle through the design's centre, and the frame (start, direction) it gives.

use serde::Serialize;

use crate::error::{Error, Result};

/// The line on the design, as the user gives it.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum LineSpec {
    /// From `start` to `end`, metres from the design's centre; the profile's first point at `start`.
    Points {
        /// `[x, y]` of the line's first point, metres from the design's centre.
        start: [f64; 2],
        /// `[x, y]` of the line's end, metres from the design's centre: it sets the direction
        /// (the profile's own length sets where the profile ends).
        end: [f64; 2],
    },
    /// Through the design's centre at `angle` radians (counter-clockwise from +x), the profile
    /// centred on the centre.
    Angle {
        /// Direction of the line, radians counter-clockwise from +x in the design's (x, y) frame.
        angle: f64,
    },
}

impl LineSpec {
    /// Parses "x0,y0,x1,y1": each a length ("-1mm", "20 um"), or bare numbers with the last
    /// one's unit ("-1,0,1,0.5mm"); a bare 0 needs no unit.
    pub fn parse_points(text: &str) -> Result<LineSpec> {
        let cells: Vec<&str> = text.split(',').map(str::trim).collect();
        if cells.len() != 4 {
            return Err(Error::param("line", format!("'{text}': expected x0,y0,x1,y1 (four lengths)")));
        }
        let bare = |c: &str| c.parse::<f64>().ok();
        let last_unit = crate::units::parse_length(cells[3]).ok().and_then(|v| {
            bare(cells[3].trim_end_matches(|ch: char| ch.is_alphabetic() || ch == 'µ' || ch == 'μ').trim())
                .filter(|b| *b != 0.0)
                .map(|b| v / b)
        });
        let mut v = [0.0; 4];
        for (k, c) in cells.iter().enumerate() {
            v[k] = match (crate::units::parse_length(c), bare(c)) {
                (Ok(m), _) => m,
                (Err(_), Some(0.0)) => 0.0,
                (Err(_), Some(b)) => match last_unit {
                    Some(u) if cells.iter().filter(|c| bare(c).is_none()).count() == 1 => b * u,
                    _ => {
                        return Err(Error::param(
                            "line",
                            format!("'{text}': '{c}' has no unit (write e.g. \"{c}um\")"),
                        ))
                    }
                },
                (Err(e), None) => return Err(e),
            };
        }
        let s = LineSpec::Points { start: [v[0], v[1]], end: [v[2], v[3]] };
        s.check()?;
        Ok(s)
    }

    pub(super) fn check(&self) -> Result<()> {
        match *self {
            LineSpec::Points { start, end } => {
                if start.iter().chain(&end).any(|v| !v.is_finite()) {
                    return Err(Error::param("line", "its points must be finite"));
                }
                if start == end {
                    return Err(Error::param("line", "its two points are the same: no direction"));
                }
            }
            LineSpec::Angle { angle } if !angle.is_finite() => {
                return Err(Error::param("angle", "must be finite"));
            }
            LineSpec::Angle { .. } => {}
        }
        Ok(())
    }

    /// The design position of the profile's first point and the unit direction, for a profile
    /// of `length` metres.
    pub fn frame(&self, length: f64) -> ([f64; 2], [f64; 2]) {
        match *self {
            LineSpec::Points { start, end } => {
                let d = [end[0] - start[0], end[1] - start[1]];
                let l = d[0].hypot(d[1]);
                (start, [d[0] / l, d[1] / l])
            }
            LineSpec::Angle { angle } => {
                let d = [angle.cos(), angle.sin()];
                ([-0.5 * length * d[0], -0.5 * length * d[1]], d)
            }
        }
    }
}

/// The warning when a line given by two points is not as long as the profile (by more than
/// 5 %): the profile is placed from the line's first point.
pub(super) fn line_length_warning(line: &LineSpec, length: f64) -> Option<String> {
    let LineSpec::Points { start: s, end: e } = line else { return None };
    let l = (e[0] - s[0]).hypot(e[1] - s[1]);
    ((l - length).abs() > 0.05 * length.max(l)).then(|| {
        format!(
            "the line is {:.1} um long but the profile {:.1} um: the profile is placed from the line's first point",
            l * 1e6,
            length * 1e6
        )
    })
}
