//! A height map as its file stores it, before any unit is applied: the stored numbers, what
//! the file states about pitch and value unit ([`RawMap`]), and the metadata writers store with
//! a map ([`Metadata`]). Every format reader returns a [`RawMap`];
//! [`crate::io::heightmap`] resolves it into a grid.

use std::path::Path;

use ndarray::Array2;

use crate::error::{Allowed, Error, Result};
use crate::units::{length_unit, parse_length};

/// Whether the stored numbers are values in some length unit or integer counts of an image.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SampleKind {
    /// Floating-point (or plain numeric) values in a length unit: scaled by the unit.
    Float,
    /// Unsigned or signed integer counts of an image format with `bits` per sample:
    /// scaled by an explicit metres-per-count factor.
    Counts {
        /// Bits per sample: 8 or 16 (PNG), 8, 16 or 32 (TIFF).
        bits: u8,
    },
}

/// What a format reader found: the stored numbers and what the file states about them.
#[derive(Debug, Clone, PartialEq)]
pub struct RawMap {
    /// The stored numbers, row 0 = first row of the file (top of an image).
    pub values: Array2<f64>,
    /// Whether the numbers are length values or integer counts.
    pub kind: SampleKind,
    /// `[x, y]` pitch in metres, when the file states it.
    pub pitch: Option<[f64; 2]>,
    /// Metres per stored value, when the file states a value unit.
    pub unit: Option<f64>,
    /// Every text key/value the file carries (attributes, text chunks, comment headers),
    /// in file order.
    pub metadata: Vec<(String, String)>,
    /// For counts images: a sentence on the scale the file's own metadata suggests (shown in
    /// the error that asks for an explicit scale; never applied).
    pub scale_hint: Option<String>,
}

/// Metadata a writer stores with a map: pitch, value unit and free text, written in this order
/// (`pitch_x`, `pitch_y`, `unit`, then `text` as given) so output is deterministic.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Metadata {
    /// `[x, y]` pitch in metres, stored as `pitch_x`, `pitch_y`.
    pub pitch: Option<[f64; 2]>,
    /// Value unit symbol (a length unit such as "m", "um", "nm"), stored as `unit`.
    pub unit: Option<String>,
    /// Further keys and values.
    pub text: Vec<(String, String)>,
}

/// Keys with a meaning to the readers; free text may not use them.
pub const RESERVED_KEYS: &[&str] = &["pitch", "pitch_x", "pitch_y", "unit"];

impl Metadata {
    /// Metadata of a height map in metres at `pitch`.
    pub fn heights(pitch: [f64; 2]) -> Self {
        Metadata { pitch: Some(pitch), unit: Some("m".into()), text: Vec::new() }
    }

    /// Adds a free-text key/value.
    pub fn with(mut self, key: impl Into<String>, value: impl Into<String>) -> Self {
        self.text.push((key.into(), value.into()));
        self
    }

    /// All key/values in write order; numbers in the shortest form that reads back exactly.
    /// `path` names the output in errors (reserved or repeated keys, bad pitch or unit).
    pub fn key_values(&self, path: &Path) -> Result<Vec<(String, String)>> {
        let mut out = Vec::new();
        if let Some([px, py]) = self.pitch {
            if !(px.is_finite() && px > 0.0 && py.is_finite() && py > 0.0) {
                return Err(Error::param_in(
                    "pitch",
                    Allowed::positive(),
                    format!("must be finite and positive, got [{px}, {py}] m"),
                ));
            }
            out.push(("pitch_x".to_string(), format!("{px:e}")));
            out.push(("pitch_y".to_string(), format!("{py:e}")));
        }
        if let Some(u) = &self.unit {
            length_unit(u)?;
            out.push(("unit".to_string(), u.clone()));
        }
        for (k, v) in &self.text {
            if RESERVED_KEYS.contains(&k.as_str()) {
                return Err(Error::param(
                    "metadata",
                    format!("{}: key '{k}' is reserved (set it through pitch/unit)", path.display()),
                ));
            }
            if out.iter().any(|(o, _)| o == k) {
                return Err(Error::param("metadata", format!("{}: key '{k}' is repeated", path.display())));
            }
            out.push((k.clone(), v.clone()));
        }
        Ok(out)
    }
}

/// Reads pitch (`pitch_x` + `pitch_y`, or `pitch`) and value unit (`unit`) from text key/values,
/// as the PNG, TIFF and CSV writers store them. A pitch is a number in metres or a length with a
/// unit ("4.29 um").
pub(crate) fn pitch_unit_from_text(
    path: &Path,
    kv: &[(String, String)],
) -> Result<(Option<[f64; 2]>, Option<f64>)> {
    let get = |key: &str| kv.iter().find(|(k, _)| k == key).map(|(_, v)| v.trim());
    let length = |key: &str, text: &str| -> Result<f64> {
        let v = match text.parse::<f64>() {
            Ok(v) => v,
            Err(_) => parse_length(text).map_err(|_| {
                Error::malformed(path, format!("metadata '{key}' = '{text}' is not a length"))
            })?,
        };
        if v.is_finite() && v > 0.0 {
            Ok(v)
        } else {
            Err(Error::malformed(path, format!("metadata '{key}' = '{text}' is not a positive length")))
        }
    };
    let pitch = match (get("pitch_x"), get("pitch_y"), get("pitch")) {
        (Some(x), Some(y), _) => Some([length("pitch_x", x)?, length("pitch_y", y)?]),
        (Some(_), None, _) | (None, Some(_), _) => {
            return Err(Error::malformed(path, "metadata has only one of 'pitch_x' and 'pitch_y'"))
        }
        (None, None, Some(p)) => {
            let p = length("pitch", p)?;
            Some([p, p])
        }
        (None, None, None) => None,
    };
    let unit = match get("unit") {
        Some(u) => Some(unit_from_text(path, "unit", u)?),
        None => None,
    };
    Ok((pitch, unit))
}

/// The size in metres of a value-unit text ("m", "um", "1e-9 m").
pub(crate) fn unit_from_text(path: &Path, key: &str, text: &str) -> Result<f64> {
    length_unit(text)
        .or_else(|_| parse_length(text))
        .ok()
        .filter(|v| v.is_finite() && *v > 0.0)
        .ok_or_else(|| Error::malformed(path, format!("metadata '{key}' = '{text}' is not a length unit")))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn metadata_key_values_in_order_and_exact() {
        let m = Metadata::heights([4.29e-6, 1.0 / 3.0 * 1e-5]).with("source", "x");
        let kv = m.key_values(Path::new("o")).unwrap();
        assert_eq!(kv[0].0, "pitch_x");
        assert_eq!(kv[0].1.parse::<f64>().unwrap(), 4.29e-6);
        assert_eq!(kv[1].1.parse::<f64>().unwrap(), 1.0 / 3.0 * 1e-5);
        assert_eq!(kv[2], ("unit".into(), "m".into()));
        assert_eq!(kv[3], ("source".into(), "x".into()));
        assert!(Metadata::default().with("unit", "m").key_values(Path::new("o")).is_err());
        let (p, u) = pitch_unit_from_text(Path::new("o"), &kv).unwrap();
        assert_eq!(p, Some([4.29e-6, 1.0 / 3.0 * 1e-5]));
        assert_eq!(u, Some(1.0));
        let kv = vec![("pitch".to_string(), "2 um".to_string()), ("unit".to_string(), "nm".to_string())];
        assert_eq!(pitch_unit_from_text(Path::new("o"), &kv).unwrap(), (Some([2e-6, 2e-6]), Some(1e-9)));
    }
}
