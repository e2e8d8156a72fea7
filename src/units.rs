//! Physical quantities at the edges: "550nm", "4.29 um", "1.55e-6 m" <-> metres.
//!
//! Inside the library every length is in metres (SI). Strings with units are parsed only where
//! a user or a file hands them over, and formatted only where something is written for a person.

use crate::error::{Allowed, Error, Result};

/// Length units accepted at the edges, with their size in metres.
pub const LENGTH_UNITS: &[(&str, f64)] = &[
    ("pm", 1e-12),
    ("nm", 1e-9),
    ("um", 1e-6),
    ("µm", 1e-6),
    ("μm", 1e-6),
    ("micron", 1e-6),
    ("microns", 1e-6),
    ("mm", 1e-3),
    ("cm", 1e-2),
    ("m", 1.0),
];

/// The size in metres of a unit name ("nm", "um", "mm", "m", ...).
pub fn length_unit(name: &str) -> Result<f64> {
    let n = name.trim();
    LENGTH_UNITS.iter().find(|(u, _)| *u == n).map(|(_, s)| *s).ok_or_else(|| {
        Error::param_in(
            "unit",
            Allowed::one_of(&["pm", "nm", "um", "mm", "cm", "m"]),
            format!("'{name}' is not a length unit (expected one of pm, nm, um, mm, cm, m)"),
        )
    })
}

/// Parses a length such as "550nm", "4.29 um", "1.55e-6 m" or "5mm" into metres.
///
/// A bare number is refused: a length without a unit is a guess.
pub fn parse_length(text: &str) -> Result<f64> {
    let t = text.trim();
    let split = t
        .char_indices()
        .find(|&(i, c)| {
            c.is_alphabetic() && !(matches!(c, 'e' | 'E') && is_exponent(t, i)) || c == 'µ' || c == 'μ'
        })
        .map(|(i, _)| i);
    let Some(i) = split else {
        return Err(Error::param(
            "length",
            format!("'{text}' has no unit (write e.g. \"{t} um\" or \"{t} nm\")"),
        ));
    };
    let (num, unit) = t.split_at(i);
    let value: f64 = num
        .trim()
        .parse()
        .map_err(|_| Error::param("length", format!("'{text}': '{}' is not a number", num.trim())))?;
    if !value.is_finite() {
        return Err(Error::param("length", format!("'{text}' is not finite")));
    }
    Ok(value * length_unit(unit)?)
}

/// True where the 'e' at byte `i` of `t` is an exponent marker (digit before, digit or sign after).
fn is_exponent(t: &str, i: usize) -> bool {
    let before = t[..i].chars().last().is_some_and(|c| c.is_ascii_digit() || c == '.');
    let after = t[i + 1..].chars().next().is_some_and(|c| c.is_ascii_digit() || c == '-' || c == '+');
    before && after
}

/// Parses a percentage "10%" or fraction "0.1" into a fraction.
pub fn parse_fraction(text: &str) -> Result<f64> {
    let t = text.trim();
    let (num, scale) = match t.strip_suffix('%') {
        Some(n) => (n.trim(), 0.01),
        None => (t, 1.0),
    };
    let v: f64 = num
        .parse()
        .map_err(|_| Error::param("fraction", format!("'{text}' is not a number or percentage")))?;
    Ok(v * scale)
}

/// Parses an angle "0.3deg", "5 mrad", "0.01 rad" into radians.
pub fn parse_angle(text: &str) -> Result<f64> {
    let t = text.trim();
    for (suffix, scale) in [
        ("deg", std::f64::consts::PI / 180.0),
        ("°", std::f64::consts::PI / 180.0),
        ("mrad", 1e-3),
        ("urad", 1e-6),
        ("rad", 1.0),
    ] {
        if let Some(n) = t.strip_suffix(suffix) {
            let v: f64 =
                n.trim().parse().map_err(|_| Error::param("angle", format!("'{text}' is not a number")))?;
            return Ok(v * scale);
        }
    }
    Err(Error::param("angle", format!("'{text}' has no unit (expected deg, rad, mrad or urad)")))
}

/// Parses a duration "300s", "5min", "1.5 h" into seconds (a bare number is refused).
pub fn parse_duration(text: &str) -> Result<f64> {
    let t = text.trim();
    for (suffix, scale) in [("min", 60.0), ("ms", 1e-3), ("s", 1.0), ("h", 3600.0)] {
        if let Some(n) = t.strip_suffix(suffix) {
            let v: f64 = n
                .trim()
                .parse()
                .map_err(|_| Error::param("duration", format!("'{text}' is not a number")))?;
            if !(v.is_finite() && v > 0.0) {
                return Err(Error::param("duration", format!("'{text}' is not a positive time")));
            }
            return Ok(v * scale);
        }
    }
    Err(Error::param("duration", format!("'{text}' has no unit (expected s, min or h, e.g. \"5min\")")))
}

/// Formats metres with an SI prefix chosen for readability: 4.29e-6 -> "4.29 um".
pub fn format_length(metres: f64) -> String {
    let a = metres.abs();
    let (scale, unit) = if a == 0.0 {
        (1.0, "m")
    } else if a < 1e-6 {
        (1e-9, "nm")
    } else if a < 1e-3 {
        (1e-6, "um")
    } else if a < 1.0 {
        (1e-3, "mm")
    } else {
        (1.0, "m")
    };
    format!("{} {unit}", trim_float(metres / scale))
}

fn trim_float(v: f64) -> String {
    let s = format!("{v:.6}");
    let s = s.trim_end_matches('0').trim_end_matches('.');
    s.to_string()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_the_forms_users_write() {
        assert!((parse_length("550nm").unwrap() - 550e-9).abs() < 1e-21);
        assert!((parse_length("4.29 um").unwrap() - 4.29e-6).abs() < 1e-18);
        assert!((parse_length("1.55e-6 m").unwrap() - 1.55e-6).abs() < 1e-18);
        assert!((parse_length("1.55E-3mm").unwrap() - 1.55e-6).abs() < 1e-18);
        assert!((parse_length("5 mm").unwrap() - 5e-3).abs() < 1e-15);
        assert!((parse_length("2µm").unwrap() - 2e-6).abs() < 1e-18);
        assert!((parse_length("-3 nm").unwrap() + 3e-9).abs() < 1e-21);
    }

    #[test]
    fn refuses_a_bare_number_or_unknown_unit() {
        assert!(parse_length("4.29").unwrap_err().to_string().contains("no unit"));
        assert!(parse_length("4 parsec").unwrap_err().to_string().contains("not a length unit"));
        assert!(parse_length("abc um").is_err());
        assert!(parse_length("").is_err());
    }

    #[test]
    fn durations() {
        assert_eq!(parse_duration("5min").unwrap(), 300.0);
        assert_eq!(parse_duration(" 90 s").unwrap(), 90.0);
        assert_eq!(parse_duration("1.5h").unwrap(), 5400.0);
        assert_eq!(parse_duration("250ms").unwrap(), 0.25);
        for bad in ["5", "five min", "-1s", "0s", "inf s"] {
            assert!(parse_duration(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn angles_and_fractions() {
        assert!((parse_angle("180deg").unwrap() - std::f64::consts::PI).abs() < 1e-15);
        assert!((parse_angle("5 mrad").unwrap() - 5e-3).abs() < 1e-15);
        assert!((parse_fraction("10%").unwrap() - 0.1).abs() < 1e-15);
        assert!((parse_fraction("0.25").unwrap() - 0.25).abs() < 1e-15);
        assert!(parse_angle("3").is_err());
    }

    #[test]
    fn formats_with_prefix() {
        assert_eq!(format_length(4.29e-6), "4.29 um");
        assert_eq!(format_length(550e-9), "550 nm");
        assert_eq!(format_length(5.6e-3), "5.6 mm");
    }
}
