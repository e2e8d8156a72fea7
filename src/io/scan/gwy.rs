//! Gwyddion native files (`.gwy`): the first channel, with its mask of non-measured points.
//!
//! Layout (Gwyddion user guide, "Gwyddion native file format"; little-endian): the magic
//! `GWYP`, then one serialized object. An object is its type name (NUL-terminated), a u32 byte
//! size of its components, then the components; a component is its name (NUL-terminated), a
//! type character and the value:
//!
//! | type | value |
//! |---|---|
//! | `b`, `c` | one byte |
//! | `i` / `q` | i32 / i64 |
//! | `d` | f64 |
//! | `s` | NUL-terminated UTF-8 string |
//! | `o` | a nested object |
//! | `C`, `I`, `Q`, `D` | u32 count, then that many bytes / i32 / i64 / f64 |
//! | `S`, `O` | u32 count, then that many strings / objects |
//!
//! The file's object is a `GwyContainer` whose components are named by path: channel `N` is
//! the `GwyDataField` at `/N/data` (its title at `/N/data/title`), its mask the `GwyDataField`
//! at `/N/mask`. A `GwyDataField` holds `xres`, `yres` (samples), `xreal`, `yreal` (the field's
//! width and height, so the pitch is `xreal / xres`), `xoff`, `yoff` (origin, default 0),
//! `si_unit_xy`, `si_unit_z` (`GwySIUnit` objects whose `unitstr` is the unit, in base SI
//! units: "m") and `data` (`yres x xres` f64, row by row, the first row at the top).
//!
//! The lowest-numbered channel is read. Where its mask is 1 the point is read as non-measured:
//! Gwyddion's imports mark the points an instrument did not measure that way (and fill them),
//! and `.gwy` is the one format Gwyddion writes that keeps them apart; the warning says how many
//! points the mask covers, since a mask drawn for another purpose is read the same way.
//! Checked against the statistics Gwyddion itself computed for the files of the shared set.

use std::path::Path;

use crate::error::Result;
use crate::io::raw_map::{RawMap, SampleKind};
use crate::io::scan::raw::{data_len, scan_length_unit, shape, Bin, ScanFormat, ScanRaw};

/// Objects nested deeper than this are refused (a container of fields of units is 3 deep).
const MAX_DEPTH: usize = 16;

/// A component's value (arrays of numbers are kept as their byte range).
#[derive(Debug, Clone)]
enum Value {
    Int(i64),
    Double(f64),
    Text(String),
    Object(Object),
    /// `(offset of the first element, count)` of an f64 array.
    Doubles(usize, usize),
    Other,
}

/// A serialized object: its type name, components in file order, and its offset.
#[derive(Debug, Clone)]
struct Object {
    type_name: String,
    offset: usize,
    components: Vec<(String, Value)>,
}

impl Object {
    fn get(&self, name: &str) -> Option<&Value> {
        self.components.iter().find(|(n, _)| n == name).map(|(_, v)| v)
    }
}

/// The parser: a cursor over the bytes with the file's name for errors.
struct Parser<'a> {
    b: Bin<'a>,
    at: usize,
}

impl Parser<'_> {
    /// A NUL-terminated string at the cursor.
    fn cstring(&mut self, what: &str) -> Result<String> {
        let rest = self.b.bytes.get(self.at..).unwrap_or(&[]);
        let Some(len) = rest.iter().position(|&c| c == 0) else {
            return Err(self
                .b
                .bad(self.at, format!("{what} has no terminating NUL before the end of the file")));
        };
        let s = String::from_utf8_lossy(&rest[..len]).into_owned();
        self.at += len + 1;
        Ok(s)
    }

    fn u32(&mut self, what: &str) -> Result<usize> {
        let v = self.b.u32le(self.at, what)? as usize;
        self.at += 4;
        Ok(v)
    }

    /// Skips `count` elements of `size` bytes, refusing counts the file cannot hold.
    fn skip(&mut self, count: usize, size: usize, what: &str) -> Result<usize> {
        let start = self.at;
        let len =
            count.checked_mul(size).ok_or_else(|| self.b.bad(start, format!("{what}: {count} elements")))?;
        self.b.take(start, len, what)?;
        self.at += len;
        Ok(start)
    }

    fn object(&mut self, depth: usize) -> Result<Object> {
        let offset = self.at;
        if depth > MAX_DEPTH {
            return Err(self.b.bad(offset, format!("objects nested deeper than {MAX_DEPTH}")));
        }
        let type_name = self.cstring("an object's type name")?;
        let size = self.u32(&format!("the size of object {type_name}"))?;
        let end = self.at.checked_add(size).filter(|&e| e <= self.b.bytes.len()).ok_or_else(|| {
            self.b.bad(
                self.at - 4,
                format!(
                    "object {type_name} of {size} bytes runs past the end of the file ({} bytes)",
                    self.b.bytes.len()
                ),
            )
        })?;
        let mut components = Vec::new();
        while self.at < end {
            let name = self.cstring(&format!("a component name of {type_name}"))?;
            let kind =
                *self.b.take(self.at, 1, &format!("the type of component '{name}'"))?.first().unwrap_or(&0);
            self.at += 1;
            let what = format!("component '{name}' of {type_name}");
            let value = match kind {
                b'b' | b'c' => {
                    let v = self.b.take(self.at, 1, &what)?[0];
                    self.at += 1;
                    Value::Int(v as i64)
                }
                b'i' => {
                    let v = self.b.i32le(self.at, &what)?;
                    self.at += 4;
                    Value::Int(v as i64)
                }
                b'q' => {
                    let v = i64::from_le_bytes(self.b.take(self.at, 8, &what)?.try_into().unwrap_or([0; 8]));
                    self.at += 8;
                    Value::Int(v)
                }
                b'd' => {
                    let v = self.b.f64le(self.at, &what)?;
                    self.at += 8;
                    Value::Double(v)
                }
                b's' => Value::Text(self.cstring(&what)?),
                b'o' => Value::Object(self.object(depth + 1)?),
                b'C' | b'I' | b'Q' | b'D' => {
                    let count = self.u32(&what)?;
                    let size = match kind {
                        b'C' => 1,
                        b'I' => 4,
                        _ => 8,
                    };
                    let start = self.skip(count, size, &what)?;
                    if kind == b'D' {
                        Value::Doubles(start, count)
                    } else {
                        Value::Other
                    }
                }
                b'S' => {
                    for _ in 0..self.u32(&what)? {
                        self.cstring(&what)?;
                    }
                    Value::Other
                }
                b'O' => {
                    for _ in 0..self.u32(&what)? {
                        self.object(depth + 1)?;
                    }
                    Value::Other
                }
                k => {
                    return Err(self.b.bad(
                        self.at - 1,
                        format!("{what} has type '{}', not one of b c i q d s o C I Q D S O", k as char),
                    ))
                }
            };
            components.push((name, value));
        }
        if self.at != end {
            return Err(self.b.bad(
                self.at,
                format!(
                    "the components of object {type_name} end {} bytes past its stated size",
                    self.at - end
                ),
            ));
        }
        Ok(Object { type_name, offset, components })
    }
}

/// True when `head` starts as a `.gwy` file does.
pub fn has_magic(head: &[u8]) -> bool {
    head.starts_with(b"GWYP")
}

/// The unit string of a `GwySIUnit` component (`""` when absent or empty: no unit).
fn unit_of(field: &Object, name: &str) -> String {
    match field.get(name) {
        Some(Value::Object(u)) => match u.get("unitstr") {
            Some(Value::Text(t)) => t.trim().to_string(),
            _ => String::new(),
        },
        _ => String::new(),
    }
}

/// One `GwyDataField`: size, extent, corner offset, units and its values.
struct Field {
    rows: usize,
    cols: usize,
    xreal: f64,
    yreal: f64,
    origin: [f64; 2],
    unit_xy: String,
    unit_z: String,
    values: Vec<f64>,
}

fn field(b: &Bin, path_name: &str, v: &Value) -> Result<Field> {
    let Value::Object(o) = v else {
        return Err(b.bad(0, format!("'{path_name}' is not an object")));
    };
    if o.type_name != "GwyDataField" {
        return Err(
            b.unsupported(o.offset, format!("'{path_name}' is a {}, not a GwyDataField", o.type_name))
        );
    }
    let int = |n: &str| match o.get(n) {
        Some(Value::Int(v)) => Ok(*v),
        _ => Err(b.bad(o.offset, format!("'{path_name}' has no integer '{n}'"))),
    };
    let double = |n: &str, default: Option<f64>| match (o.get(n), default) {
        (Some(Value::Double(v)), _) => Ok(*v),
        (None, Some(d)) => Ok(d),
        _ => Err(b.bad(o.offset, format!("'{path_name}' has no number '{n}'"))),
    };
    let (xres, yres) = (int("xres")?, int("yres")?);
    if xres < 1 || yres < 1 {
        return Err(b.bad(o.offset, format!("'{path_name}' is {xres} x {yres} samples")));
    }
    let (cols, rows) = (xres as usize, yres as usize);
    let n = data_len(b.path, rows, cols, 8)? / 8;
    let (start, count) = match o.get("data") {
        Some(Value::Doubles(s, c)) => (*s, *c),
        _ => return Err(b.bad(o.offset, format!("'{path_name}' has no array of numbers 'data'"))),
    };
    if count != n {
        return Err(b.bad(start, format!("'{path_name}' holds {count} values for {cols} x {rows} samples")));
    }
    let values = b.bytes[start..start + 8 * n]
        .chunks_exact(8)
        .map(|c| f64::from_le_bytes(c.try_into().unwrap_or([0; 8])))
        .collect();
    Ok(Field {
        rows,
        cols,
        xreal: double("xreal", None)?,
        yreal: double("yreal", None)?,
        origin: [double("xoff", Some(0.0))?, double("yoff", Some(0.0))?],
        unit_xy: unit_of(o, "si_unit_xy"),
        unit_z: unit_of(o, "si_unit_z"),
        values,
    })
}

/// Decodes a `.gwy` file (see the module docs).
pub fn decode(path: &Path, bytes: &[u8]) -> Result<ScanRaw> {
    let b = Bin::new(path, bytes);
    b.take(0, 4, "the magic GWYP")?;
    if !has_magic(bytes) {
        return Err(b.signature(0, "not a Gwyddion native file: it does not start with GWYP"));
    }
    let top = Parser { b: Bin::new(path, bytes), at: 4 }.object(0)?;
    if top.type_name != "GwyContainer" {
        return Err(b.unsupported(4, format!("the file holds a {}, not a GwyContainer", top.type_name)));
    }
    // The lowest-numbered channel `/N/data`, by the name the file gives it (`/01/data` and
    // `/+1/data` parse as 1 too: the key is the file's own, not one rebuilt from the number).
    let (key, value) = top
        .components
        .iter()
        .filter_map(|(n, v)| Some((n.strip_prefix('/')?.strip_suffix("/data")?.parse::<u32>().ok()?, n, v)))
        .min_by_key(|(number, _, _)| *number)
        .map(|(_, n, v)| (n.clone(), v))
        .ok_or_else(|| b.bad(4, "no channel (/N/data) in the container"))?;
    let data = field(&b, &key, value)?;
    let mut metadata: Vec<(String, String)> = top
        .components
        .iter()
        .filter_map(|(n, v)| match v {
            Value::Text(t) => Some((n.clone(), t.clone())),
            _ => None,
        })
        .collect();
    metadata.push(("channel".into(), key.clone()));
    // The field's corner (not read as the grid's origin: the grid is centred as for other
    // formats without one).
    metadata.push(("xoff".into(), format!("{} {}", data.origin[0], data.unit_xy)));
    metadata.push(("yoff".into(), format!("{} {}", data.origin[1], data.unit_xy)));
    let mut warnings = Vec::new();
    let mut values = data.values;
    let mask_key = format!("{}/mask", key.trim_end_matches("/data"));
    if let Some(m) = top.get(&mask_key) {
        let mask = field(&b, &mask_key, m)?;
        if (mask.rows, mask.cols) != (data.rows, data.cols) {
            return Err(b.bad(
                4,
                format!(
                    "the mask is {} x {}, the channel {} x {}",
                    mask.cols, mask.rows, data.cols, data.rows
                ),
            ));
        }
        let mut masked = 0;
        for (v, m) in values.iter_mut().zip(&mask.values) {
            if *m > 0.5 {
                *v = f64::NAN;
                masked += 1;
            }
        }
        warnings.push(format!(
            "{masked} points under the channel's mask read as non-measured ({mask_key}; Gwyddion marks the points \
             an instrument did not measure so)"
        ));
    }
    let values = shape(path, data.rows, data.cols, values)?;
    let unit = if data.unit_z.is_empty() {
        warnings.push("the channel states no height unit: pass `z_unit`".into());
        None
    } else {
        Some(scan_length_unit(&data.unit_z).ok_or_else(|| {
            b.bad(4, format!("the channel's values are in '{}', not a length", data.unit_z))
        })?)
    };
    let pitch = match scan_length_unit(&data.unit_xy) {
        Some(u)
            if data.xreal.is_finite() && data.xreal > 0.0 && data.yreal.is_finite() && data.yreal > 0.0 =>
        {
            Some([u * data.xreal / data.cols as f64, u * data.yreal / data.rows as f64])
        }
        _ => {
            warnings.push(format!(
                "the channel's extent {} x {} '{}' gives no pitch: pass `pitch`",
                data.xreal, data.yreal, data.unit_xy
            ));
            None
        }
    };
    let raw = RawMap { values, kind: SampleKind::Float, pitch, unit, metadata, scale_hint: None };
    let mut sr = ScanRaw::new(raw, ScanFormat::Gwy);
    sr.warnings = warnings;
    Ok(sr)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A serialized object from its type name and already serialized components.
    fn object(type_name: &str, components: &[Vec<u8>]) -> Vec<u8> {
        let body: Vec<u8> = components.concat();
        let mut out = type_name.as_bytes().to_vec();
        out.push(0);
        out.extend((body.len() as u32).to_le_bytes());
        out.extend(body);
        out
    }

    fn component(name: &str, kind: u8, value: &[u8]) -> Vec<u8> {
        let mut out = name.as_bytes().to_vec();
        out.push(0);
        out.push(kind);
        out.extend(value);
        out
    }

    fn unit(u: &str) -> Vec<u8> {
        object("GwySIUnit", &[component("unitstr", b's', format!("{u}\0").as_bytes())])
    }

    fn data_field(cols: i32, rows: i32, values: &[f64], unit_z: &str) -> Vec<u8> {
        let mut data = (values.len() as u32).to_le_bytes().to_vec();
        data.extend(values.iter().flat_map(|v| v.to_le_bytes()));
        object(
            "GwyDataField",
            &[
                component("xres", b'i', &cols.to_le_bytes()),
                component("yres", b'i', &rows.to_le_bytes()),
                component("xreal", b'd', &(cols as f64 * 2e-6).to_le_bytes()),
                component("yreal", b'd', &(rows as f64 * 3e-6).to_le_bytes()),
                component("si_unit_xy", b'o', &unit("m")),
                component("si_unit_z", b'o', &unit(unit_z)),
                component("data", b'D', &data),
            ],
        )
    }

    fn file(components: &[Vec<u8>]) -> Vec<u8> {
        let mut out = b"GWYP".to_vec();
        out.extend(object("GwyContainer", components));
        out
    }

    fn read(bytes: &[u8]) -> Result<ScanRaw> {
        decode(Path::new("t.gwy"), bytes)
    }

    #[test]
    fn a_written_file_reads_back_with_its_mask_pitch_and_unit() {
        let v = [1e-9, 2e-9, 3e-9, 4e-9, 5e-9, 6e-9];
        let mask = [0.0, 1.0, 0.0, 0.0, 0.0, 1.0];
        // Channel 3 and channel 1: the lower number is read.
        let bytes = file(&[
            component("/3/data", b'o', &data_field(3, 2, &[9.0; 6], "m")),
            component("/1/data", b'o', &data_field(3, 2, &v, "m")),
            component("/1/data/title", b's', b"Height\0"),
            component("/1/mask", b'o', &data_field(3, 2, &mask, "")),
            component(
                "/1/data/log",
                b'O',
                &[&1u32.to_le_bytes()[..], &object("GwyStringList", &[])].concat(),
            ),
        ]);
        let r = read(&bytes).unwrap();
        assert_eq!(r.raw.values.dim(), (2, 3));
        assert_eq!(r.raw.pitch, Some([2e-6, 3e-6]));
        assert_eq!(r.raw.unit, Some(1.0));
        let got: Vec<f64> = r.raw.values.iter().copied().collect();
        for (k, (g, w)) in got.iter().zip(&v).enumerate() {
            assert!(if mask[k] > 0.5 { g.is_nan() } else { g == w }, "{k}: {g} vs {w}");
        }
        assert!(r.raw.metadata.iter().any(|(k, v)| k == "/1/data/title" && v == "Height"));
        assert!(
            r.warnings.iter().any(|w| w.contains("2 points under the channel's mask")),
            "{:?}",
            r.warnings
        );
    }

    #[test]
    fn malformed_files_are_refused_with_the_reason() {
        let err = |bytes: &[u8]| read(bytes).unwrap_err().to_string();
        assert!(err(b"GWYQ....").contains("does not start with GWYP"));
        let e = err(&file(&[component("/0/data/title", b's', b"x\0")]));
        assert!(e.contains("no channel"), "{e}");
        let e = err(&file(&[component("/0/data", b'o', &data_field(2, 1, &[0.0; 2], "V"))]));
        assert!(e.contains("'V', not a length"), "{e}");
        let e = err(&file(&[component("/0/data", b'o', &data_field(2, 2, &[0.0; 3], "m"))]));
        assert!(e.contains("holds 3 values for 2 x 2 samples"), "{e}");
        let e = err(&file(&[component("/0/data", b'x', b"")]));
        assert!(e.contains("has type 'x'"), "{e}");
        let e = err(&file(&[
            component("/0/data", b'o', &data_field(2, 1, &[0.0; 2], "m")),
            component("/0/mask", b'o', &data_field(1, 2, &[0.0; 2], "")),
        ]));
        assert!(e.contains("the mask is 1 x 2, the channel 2 x 1"), "{e}");
        // Objects nested past the limit, and an array longer than the file.
        let mut deep = unit("m");
        for _ in 0..=MAX_DEPTH {
            deep = object("GwyContainer", &[component("x", b'o', &deep)]);
        }
        let mut bomb = b"GWYP".to_vec();
        bomb.extend(deep);
        assert!(err(&bomb).contains("nested deeper"), "{}", err(&bomb));
        let e = err(&file(&[component("/0/data", b'D', &u32::MAX.to_le_bytes())]));
        assert!(e.contains("truncated") && e.contains("t.gwy"), "{e}");
    }
}
