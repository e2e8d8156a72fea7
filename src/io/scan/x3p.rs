//! ISO 25178-72 XML 3D surface profile files (`.x3p`): a zip archive holding `main.xml`
//! (the ISO5436_2 document), the point data `bindata/data.bin` (or inline `<DataList>`),
//! optionally a valid-points bit array, and `md5checksum.hex` (the MD5 of `main.xml`).
//!
//! From `main.xml`: `Record1/Axes/CX`, `CY` (`AxisType` must be `I`, incremental: the pitch is
//! `Increment` metres, `Offset` the position of the first sample), `CZ` (`DataType` `I` = i16,
//! `L` = i32, `F` = f32, `D` = f64, little endian; heights `z = Offset + Increment * raw`
//! metres, Increment 1 and Offset 0 when absent), `Record3/MatrixDimension` (`SizeX` points per
//! row, `SizeY` rows, `SizeZ` = 1), `Record3/DataLink/PointDataLink` and
//! `MD5ChecksumPointData`, `ValidPointsLink` (bit k of byte k / 8, least significant first,
//! 1 = measured). NaN in float data is a non-measured point, as is a cleared valid bit.
//!
//! Checksums are checked and a mismatch is reported as a warning, never refused: x3pio writes
//! revision `ISO25178-72:2017/DAM1`, and SurfaceTopography writes the MD5 of `data.bin` into
//! `md5checksum.hex` where that of `main.xml` belongs.

use std::io::{Cursor, Read};
use std::path::Path;

use md5::{Digest, Md5};

use crate::error::{Error, Result};
use crate::io::raw_map::{RawMap, SampleKind};
use crate::io::scan::raw::{data_len, shape, ScanFormat, ScanRaw};

fn hex_md5(b: &[u8]) -> String {
    Md5::digest(b).iter().map(|x| format!("{x:02x}")).collect()
}

/// Reads one zip entry, refusing more than `limit` bytes (no zip bombs).
pub(crate) fn entry(
    path: &Path,
    zip: &mut zip::ZipArchive<Cursor<&[u8]>>,
    name: &str,
    limit: usize,
) -> Result<Option<Vec<u8>>> {
    let mut f = match zip.by_name(name) {
        Ok(f) => f,
        Err(zip::result::ZipError::FileNotFound) => return Ok(None),
        Err(e) => return Err(Error::malformed(path, format!("zip entry '{name}': {e}"))),
    };
    let at = f.data_start();
    if f.size() as usize > limit {
        return Err(Error::malformed(
            path,
            format!(
                "byte offset {at}: zip entry '{name}' holds {} bytes, at most {limit} expected",
                f.size()
            ),
        )
        .at(at));
    }
    let mut out = Vec::with_capacity(f.size() as usize);
    (&mut f).take(limit as u64 + 1).read_to_end(&mut out).map_err(|e| {
        Error::malformed(path, format!("byte offset {at}: zip entry '{name}' is corrupt: {e}")).at(at)
    })?;
    if out.len() > limit {
        return Err(Error::malformed(
            path,
            format!("byte offset {at}: zip entry '{name}' is larger than it says"),
        )
        .at(at));
    }
    Ok(Some(out))
}

/// Decodes an `.x3p` file's bytes (see the module docs).
pub fn decode(path: &Path, bytes: &[u8]) -> Result<ScanRaw> {
    let mut zip = zip::ZipArchive::new(Cursor::new(bytes)).map_err(|e| {
        Error::truncated(
            path,
            bytes.len() as u64,
            format!("byte offset {}: not a complete zip archive: {e}", bytes.len()),
        )
    })?;
    let xml_bytes = entry(path, &mut zip, "main.xml", 1 << 24)?
        .ok_or_else(|| Error::signature(path, "the archive holds no main.xml"))?;
    let xml = std::str::from_utf8(&xml_bytes).map_err(|e| {
        let at = e.valid_up_to();
        Error::malformed(path, format!("main.xml: byte offset {at}: not UTF-8")).at(at as u64)
    })?;
    let doc =
        roxmltree::Document::parse(xml).map_err(|e| Error::malformed(path, format!("main.xml: {e}")))?;
    let main = MainXml { path, doc };
    let metadata = main.metadata();
    let axes = main.axes()?;
    let Axes { nx, ny, .. } = axes;
    let nbytes = data_len(path, ny, nx, axes.size)?;
    let mut warnings = Vec::new();
    let mut raw = point_data(&main, &mut zip, &axes, nbytes, &mut warnings)?;
    mask_invalid_points(&main, &mut zip, &axes, &mut raw)?;
    match entry(path, &mut zip, "md5checksum.hex", 4096)? {
        None => warnings.push("the archive holds no md5checksum.hex".to_string()),
        Some(c) => {
            let t = String::from_utf8_lossy(&c);
            let want = t.split_whitespace().next().unwrap_or("").to_string();
            let got = hex_md5(&xml_bytes);
            if !want.eq_ignore_ascii_case(&got) {
                warnings
                    .push(format!("md5checksum.hex holds '{}', not the MD5 of main.xml ({got})", t.trim()));
            }
        }
    }
    let values = shape(path, ny, nx, raw.into_iter().map(|v| axes.zoff + axes.zinc * v).collect())?;
    let raw = RawMap {
        values,
        kind: SampleKind::Float,
        pitch: Some([axes.px, axes.py]),
        unit: Some(1.0),
        metadata,
        scale_hint: None,
    };
    let mut sr = ScanRaw::new(raw, ScanFormat::X3p);
    sr.origin = Some([axes.ox, axes.oy]);
    sr.warnings = warnings;
    Ok(sr)
}

/// `main.xml`, read by element routes from its root; `path` names the file in errors.
struct MainXml<'a, 'input> {
    path: &'a Path,
    doc: roxmltree::Document<'input>,
}

impl<'input> MainXml<'_, 'input> {
    fn find(&self, route: &[&str]) -> Option<roxmltree::Node<'_, 'input>> {
        let mut node = self.doc.root_element();
        for part in route {
            node = node.children().find(|c| c.is_element() && c.tag_name().name() == *part)?;
        }
        Some(node)
    }

    fn text(&self, route: &[&str]) -> Option<String> {
        self.find(route).and_then(|n| n.text()).map(|t| t.trim().to_string())
    }

    fn need(&self, route: &[&str]) -> Result<String> {
        self.text(route)
            .ok_or_else(|| Error::malformed(self.path, format!("main.xml lacks {}", route.join("/"))))
    }

    /// A finite number, or `default` when the element is absent.
    fn num(&self, route: &[&str], default: Option<f64>) -> Result<f64> {
        let path = self.path;
        match (self.text(route), default) {
            (Some(t), _) => t.parse::<f64>().ok().filter(|v| v.is_finite()).ok_or_else(|| {
                Error::malformed(path, format!("main.xml {} = '{t}' is not a finite number", route.join("/")))
            }),
            (None, Some(d)) => Ok(d),
            (None, None) => Err(Error::malformed(path, format!("main.xml lacks {}", route.join("/")))),
        }
    }

    /// A positive integer.
    fn count(&self, route: &[&str]) -> Result<usize> {
        let t = self.need(route)?;
        t.parse::<usize>().ok().filter(|&n| n > 0).ok_or_else(|| {
            Error::malformed(
                self.path,
                format!("main.xml {} = '{t}' is not a positive integer", route.join("/")),
            )
        })
    }

    /// The revision, feature type, date, instrument and comment, where given.
    fn metadata(&self) -> Vec<(String, String)> {
        let mut metadata = Vec::new();
        for route in [
            &["Record1", "Revision"][..],
            &["Record1", "FeatureType"],
            &["Record2", "Date"],
            &["Record2", "Instrument", "Manufacturer"],
            &["Record2", "Instrument", "Model"],
            &["Record2", "Instrument", "Version"],
            &["Record2", "Comment"],
        ] {
            if let Some(t) = self.text(route) {
                metadata.push((route.join("/"), t));
            }
        }
        metadata
    }

    /// The axes and the matrix size (module docs); anything but an incremental x and y axis
    /// and a single layer is refused.
    fn axes(&self) -> Result<Axes> {
        let path = self.path;
        for ax in ["CX", "CY"] {
            let t = self.need(&["Record1", "Axes", ax, "AxisType"])?;
            if t != "I" {
                return Err(Error::unsupported(
                    path,
                    format!("axis {ax} has AxisType '{t}': only incremental (I) x and y axes are supported"),
                ));
            }
        }
        let px = self.num(&["Record1", "Axes", "CX", "Increment"], None)?;
        let py = self.num(&["Record1", "Axes", "CY", "Increment"], None)?;
        if px <= 0.0 || py <= 0.0 {
            return Err(Error::malformed(path, format!("x/y increments {px}, {py} must be positive")));
        }
        let ox = self.num(&["Record1", "Axes", "CX", "Offset"], Some(0.0))?;
        let oy = self.num(&["Record1", "Axes", "CY", "Offset"], Some(0.0))?;
        let dt = self.need(&["Record1", "Axes", "CZ", "DataType"])?;
        let size = match dt.as_str() {
            "I" => 2,
            "L" | "F" => 4,
            "D" => 8,
            _ => return Err(Error::unsupported(path, format!("CZ DataType '{dt}' is not I, L, F or D"))),
        };
        let zinc = self.num(&["Record1", "Axes", "CZ", "Increment"], Some(1.0))?;
        let zoff = self.num(&["Record1", "Axes", "CZ", "Offset"], Some(0.0))?;
        let (nx, ny) = (
            self.count(&["Record3", "MatrixDimension", "SizeX"])?,
            self.count(&["Record3", "MatrixDimension", "SizeY"])?,
        );
        let nz = self.count(&["Record3", "MatrixDimension", "SizeZ"])?;
        if nz != 1 {
            return Err(Error::unsupported(
                path,
                format!("SizeZ = {nz}: only single-layer surfaces are supported"),
            ));
        }
        Ok(Axes { px, py, ox, oy, dt, size, zinc, zoff, nx, ny })
    }
}

/// What `main.xml` says of the axes: the pitch and the first sample's position (metres), the
/// data type and its size in bytes, the height scale and offset, points per row and rows.
struct Axes {
    px: f64,
    py: f64,
    ox: f64,
    oy: f64,
    dt: String,
    size: usize,
    zinc: f64,
    zoff: f64,
    nx: usize,
    ny: usize,
}

/// The stored values, from the linked binary entry (`nbytes` long; an MD5 mismatch is a
/// warning) or the inline `DataList` (empty: not measured).
fn point_data(
    main: &MainXml,
    zip: &mut zip::ZipArchive<Cursor<&[u8]>>,
    axes: &Axes,
    nbytes: usize,
    warnings: &mut Vec<String>,
) -> Result<Vec<f64>> {
    let (path, size, dt, nx, ny) = (main.path, axes.size, &axes.dt, axes.nx, axes.ny);
    let decode_one = |c: &[u8]| -> f64 {
        match size {
            2 => i16::from_le_bytes([c[0], c[1]]) as f64,
            4 if dt == "L" => i32::from_le_bytes([c[0], c[1], c[2], c[3]]) as f64,
            4 => f32::from_le_bytes([c[0], c[1], c[2], c[3]]) as f64,
            _ => f64::from_le_bytes([c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7]]),
        }
    };
    Ok(match main.text(&["Record3", "DataLink", "PointDataLink"]) {
        Some(link) => {
            let data = entry(path, zip, &link, nbytes)?.ok_or_else(|| {
                Error::malformed(path, format!("main.xml links '{link}', which the archive lacks"))
            })?;
            if data.len() != nbytes {
                return Err(Error::truncated(
                    path, data.len() as u64,
                    format!(
                        "{link}: truncated at byte offset {} of the entry: {nx} x {ny} points of type {dt} need {nbytes} bytes",
                        data.len()
                    ),
                ));
            }
            if let Some(want) = main.text(&["Record3", "DataLink", "MD5ChecksumPointData"]) {
                let got = hex_md5(&data);
                if !want.eq_ignore_ascii_case(&got) {
                    warnings.push(format!(
                        "{link}: MD5 {got} differs from main.xml's MD5ChecksumPointData {want}"
                    ));
                }
            }
            data.chunks_exact(size).map(decode_one).collect()
        }
        None => {
            let list = main.find(&["Record3", "DataList"]).ok_or_else(|| {
                Error::malformed(path, "main.xml has neither a PointDataLink nor a DataList")
            })?;
            let mut v = Vec::with_capacity(nx * ny);
            for d in list.children().filter(|c| c.is_element() && c.tag_name().name() == "Datum") {
                let t = d.text().map(str::trim).unwrap_or("");
                v.push(if t.is_empty() {
                    f64::NAN
                } else {
                    t.parse::<f64>()
                        .map_err(|_| Error::malformed(path, format!("DataList: '{t}' is not a number")))?
                });
            }
            if v.len() != nx * ny {
                return Err(Error::malformed(
                    path,
                    format!("DataList holds {} values, {nx} x {ny} expected", v.len()),
                ));
            }
            v
        }
    })
}

/// NaN where the linked valid-points bit array (if any) clears a point's bit.
fn mask_invalid_points(
    main: &MainXml,
    zip: &mut zip::ZipArchive<Cursor<&[u8]>>,
    axes: &Axes,
    raw: &mut [f64],
) -> Result<()> {
    let (path, nx, ny) = (main.path, axes.nx, axes.ny);
    if let Some(link) = main
        .text(&["Record3", "ValidPointsLink"])
        .or_else(|| main.text(&["Record3", "DataLink", "ValidPointsLink"]))
    {
        let need = (nx * ny).div_ceil(8);
        let bits = entry(path, zip, &link, need)?.ok_or_else(|| {
            Error::malformed(path, format!("main.xml links '{link}', which the archive lacks"))
        })?;
        if bits.len() != need {
            return Err(Error::malformed(
                path,
                format!("{link}: {} bytes, {need} expected for {nx} x {ny} bits", bits.len()),
            ));
        }
        for (k, v) in raw.iter_mut().enumerate() {
            if bits[k / 8] >> (k % 8) & 1 == 0 {
                *v = f64::NAN;
            }
        }
    }
    Ok(())
}

/// Writes an `.x3p` archive in memory (f64 data, NaN for non-measured points, correct
/// checksums, deflate), for tests and synthetic scans.
pub fn encode(values: &ndarray::Array2<f64>, pitch: [f64; 2]) -> Result<Vec<u8>> {
    use std::io::Write;
    let (ny, nx) = values.dim();
    let data: Vec<u8> = values.iter().flat_map(|v| v.to_le_bytes()).collect();
    let xml = format!(
        "<?xml version=\"1.0\" encoding=\"UTF-8\"?>\n<p:ISO5436_2 xmlns:p=\"http://www.opengps.eu/2008/ISO5436_2\">\
         <Record1><Revision>ISO5436 - 2000</Revision><FeatureType>SUR</FeatureType><Axes>\
         <CX><AxisType>I</AxisType><DataType>D</DataType><Increment>{:e}</Increment><Offset>0</Offset></CX>\
         <CY><AxisType>I</AxisType><DataType>D</DataType><Increment>{:e}</Increment><Offset>0</Offset></CY>\
         <CZ><AxisType>A</AxisType><DataType>D</DataType><Increment>1</Increment><Offset>0</Offset></CZ>\
         </Axes></Record1><Record3><MatrixDimension><SizeX>{nx}</SizeX><SizeY>{ny}</SizeY><SizeZ>1</SizeZ>\
         </MatrixDimension><DataLink><PointDataLink>bindata/data.bin</PointDataLink>\
         <MD5ChecksumPointData>{}</MD5ChecksumPointData></DataLink></Record3>\
         <Record4><ChecksumFile>md5checksum.hex</ChecksumFile></Record4></p:ISO5436_2>\n",
        pitch[0],
        pitch[1],
        hex_md5(&data)
    );
    let mut buf = Cursor::new(Vec::new());
    {
        let mut z = zip::ZipWriter::new(&mut buf);
        let opt = zip::write::SimpleFileOptions::default()
            .compression_method(zip::CompressionMethod::Deflated)
            .last_modified_time(zip::DateTime::default());
        let io = |e: std::io::Error| Error::internal(format!("x3p encoding: {e}"));
        let ze = |e: zip::result::ZipError| Error::internal(format!("x3p encoding: {e}"));
        z.start_file("main.xml", opt).map_err(ze)?;
        z.write_all(xml.as_bytes()).map_err(io)?;
        z.start_file("bindata/data.bin", opt).map_err(ze)?;
        z.write_all(&data).map_err(io)?;
        z.start_file("md5checksum.hex", opt).map_err(ze)?;
        z.write_all(format!("{} *main.xml\n", hex_md5(xml.as_bytes())).as_bytes()).map_err(io)?;
        z.finish().map_err(ze)?;
    }
    Ok(buf.into_inner())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// An archive with data of type `dt` ("I", "L" or "F"), a z increment and offset, and a
    /// valid-points bit array.
    fn integer_x3p(dt: &str, raw: &[i32], nx: usize, ny: usize, valid: &[u8]) -> Vec<u8> {
        use std::io::Write;
        let data: Vec<u8> = raw
            .iter()
            .flat_map(|&v| match dt {
                "I" => (v as i16).to_le_bytes().to_vec(),
                "F" => (v as f32).to_le_bytes().to_vec(),
                _ => v.to_le_bytes().to_vec(),
            })
            .collect();
        let xml = format!(
            "<?xml version=\"1.0\"?><p:ISO5436_2 xmlns:p=\"http://www.opengps.eu/2008/ISO5436_2\"><Record1>\
             <Axes><CX><AxisType>I</AxisType><DataType>D</DataType><Increment>2e-6</Increment></CX>\
             <CY><AxisType>I</AxisType><DataType>D</DataType><Increment>3e-6</Increment><Offset>1e-3</Offset></CY>\
             <CZ><AxisType>A</AxisType><DataType>{dt}</DataType><Increment>1e-9</Increment><Offset>5e-7</Offset></CZ>\
             </Axes></Record1><Record3><MatrixDimension><SizeX>{nx}</SizeX><SizeY>{ny}</SizeY><SizeZ>1</SizeZ>\
             </MatrixDimension><DataLink><PointDataLink>bindata/data.bin</PointDataLink></DataLink>\
             <ValidPointsLink>bindata/valid.bin</ValidPointsLink></Record3></p:ISO5436_2>"
        );
        let mut buf = Cursor::new(Vec::new());
        let mut z = zip::ZipWriter::new(&mut buf);
        let opt = zip::write::SimpleFileOptions::default();
        for (name, bytes) in [
            ("main.xml", xml.as_bytes().to_vec()),
            ("bindata/data.bin", data),
            ("bindata/valid.bin", valid.to_vec()),
            ("md5checksum.hex", format!("{} *main.xml", hex_md5(xml.as_bytes())).into_bytes()),
        ] {
            z.start_file(name, opt).unwrap();
            z.write_all(&bytes).unwrap();
        }
        z.finish().unwrap();
        buf.into_inner()
    }

    #[test]
    fn data_types_scale_and_valid_points() {
        // 3 x 4 points; point 5 (row 1, column 1) and point 11 not measured.
        let raw: Vec<i32> = (0..12).map(|k| k * 100 - 300).collect();
        let valid = [0b1101_1111u8, 0b0000_0111];
        for dt in ["I", "L", "F"] {
            let r = decode(Path::new("i.x3p"), &integer_x3p(dt, &raw, 4, 3, &valid)).unwrap();
            assert!(r.warnings.is_empty(), "{:?}", r.warnings);
            assert_eq!(r.raw.pitch, Some([2e-6, 3e-6]));
            assert_eq!(r.origin, Some([0.0, 1e-3]));
            for (k, &c) in raw.iter().enumerate() {
                let v = r.raw.values[[k / 4, k % 4]];
                if k == 5 || k == 11 {
                    assert!(v.is_nan(), "{dt} point {k}");
                } else {
                    assert!((v - (5e-7 + 1e-9 * c as f64)).abs() < 1e-20, "{dt} point {k}: {v}");
                }
            }
        }
        let e =
            decode(Path::new("i.x3p"), &integer_x3p("L", &raw, 4, 3, &valid[..1])).unwrap_err().to_string();
        assert!(e.contains("valid.bin"), "{e}");
    }

    #[test]
    fn round_trip_and_cuts_never_panic() {
        let mut v = ndarray::Array2::from_shape_fn((4, 6), |(i, j)| (i * 6 + j) as f64 * 1e-8);
        v[[2, 2]] = f64::NAN;
        let b = encode(&v, [1e-6, 3e-6]).unwrap();
        let r = decode(Path::new("t.x3p"), &b).unwrap();
        assert!(r.warnings.is_empty(), "{:?}", r.warnings);
        assert_eq!(r.raw.pitch, Some([1e-6, 3e-6]));
        assert!(r.raw.values[[2, 2]].is_nan());
        assert_eq!(r.raw.values[[3, 5]], v[[3, 5]]);
        for cut in 0..b.len() {
            let e = decode(Path::new("cut.x3p"), &b[..cut]).unwrap_err().to_string();
            assert!(e.contains("cut.x3p") && e.contains("byte offset"), "cut at {cut}: {e}");
        }
    }
}
