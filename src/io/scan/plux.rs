//! Sensofar PLUx files (`.plux`, SensoSCAN / SensoVIEW 3 and later): a zip archive with an XML
//! index and one binary height member per layer.
//!
//! Layout (as Gwyddion's `sensofarx` module, SurfaceTopography's `PLUX` reader and surfalize's
//! `plux` reader read it; every number little-endian):
//!
//! | member | content |
//! |---|---|
//! | `index.xml` | UTF-8 XML (a byte-order mark allowed), root `<xml>`: `GENERAL/IMAGE_SIZE_X`, `IMAGE_SIZE_Y` (columns, rows), `GENERAL/FOV_X`, `FOV_Y` (the pitch: micrometres per pixel, despite the name), `GENERAL/DATE`; one `LAYER_N` element per layer with `FILENAME_Z`, the member holding its heights; `INFO/ITEM_k` elements with `NAME` and `VALUE` (`Device`, `Objective`, `Technique`, `Measurement Type`, `Algorithm`, `Comment`, ...) |
//! | `LAYER_0.raw` (the name `FILENAME_Z` gives) | `IMAGE_SIZE_Y` rows of `IMAGE_SIZE_X` f32 heights in micrometres, the first row first; NaN = not measured |
//! | `LAYER_0.stack.raw`, `recipe.txt`, ... | the intensity image, the recipe: not read |
//!
//! The layer read is the lowest-numbered one with a `FILENAME_Z`; other layers are skipped with
//! a warning naming them. Infinities are read as non-measured too. Every `GENERAL` element and
//! every `INFO` item is kept as metadata, plus `date`, `instrument` (the `Device`) and
//! `objective`. The older binary `.plu` is [`crate::io::scan::plu`].

use std::io::Cursor;
use std::path::Path;

use crate::error::{Error, Result};
use crate::io::raw_map::{RawMap, SampleKind};
use crate::io::scan::raw::{data_len, shape, ScanFormat, ScanRaw};
use crate::io::scan::x3p::entry;

const INDEX: &str = "index.xml";
const UM: f64 = 1e-6;

/// The first child element of `node` named `name`.
fn child<'a, 'i>(node: roxmltree::Node<'a, 'i>, name: &str) -> Option<roxmltree::Node<'a, 'i>> {
    node.children().find(|c| c.is_element() && c.tag_name().name() == name)
}

/// Decodes a `.plux` file (see the module docs).
pub fn decode(path: &Path, bytes: &[u8]) -> Result<ScanRaw> {
    if !bytes.starts_with(b"PK") {
        return Err(Error::signature(
            path,
            "byte offset 0: not a Sensofar PLUx file: it is not a zip archive (no 'PK' signature)",
        )
        .at(0));
    }
    let mut zip = zip::ZipArchive::new(Cursor::new(bytes)).map_err(|e| {
        Error::truncated(
            path,
            bytes.len() as u64,
            format!("byte offset {}: not a complete zip archive: {e}", bytes.len()),
        )
    })?;
    let xml = entry(path, &mut zip, INDEX, 1 << 24)?.ok_or_else(|| {
        Error::signature(path, "not a Sensofar PLUx file: the zip archive holds no index.xml")
    })?;
    let xml = xml.strip_prefix(b"\xef\xbb\xbf").unwrap_or(&xml);
    let xml = std::str::from_utf8(xml).map_err(|e| {
        let at = e.valid_up_to();
        Error::malformed(path, format!("index.xml: byte offset {at}: not UTF-8")).at(at as u64)
    })?;
    let doc =
        roxmltree::Document::parse(xml).map_err(|e| Error::malformed(path, format!("index.xml: {e}")))?;
    let root = doc.root_element();
    let Some(general) = child(root, "GENERAL").filter(|g| child(*g, "IMAGE_SIZE_X").is_some()) else {
        return Err(Error::signature(
            path,
            "not a Sensofar PLUx file: index.xml has no GENERAL/IMAGE_SIZE_X (an index.xml of another format)",
        ));
    };
    let text = |name: &str| child(general, name).and_then(|n| n.text()).map(|t| t.trim().to_string());
    let count = |name: &str| -> Result<usize> {
        let t =
            text(name).ok_or_else(|| Error::malformed(path, format!("index.xml lacks GENERAL/{name}")))?;
        t.parse::<usize>()
            .map_err(|_| Error::malformed(path, format!("index.xml GENERAL/{name} = '{t}' is not a count")))
    };
    let cols = count("IMAGE_SIZE_X")?;
    let rows = count("IMAGE_SIZE_Y")?;
    if rows == 0 || cols == 0 {
        return Err(Error::malformed(path, format!("index.xml: the map is empty ({cols} x {rows} points)")));
    }
    let need = data_len(path, rows, cols, 4)?;

    // Layers in index order: LAYER_0, LAYER_1, ...
    let mut layers: Vec<(u32, String)> = Vec::new();
    for n in root.children().filter(|c| c.is_element()) {
        let name = n.tag_name().name();
        let Some(index) = name.strip_prefix("LAYER_").and_then(|i| i.parse::<u32>().ok()) else { continue };
        if let Some(f) =
            child(n, "FILENAME_Z").and_then(|f| f.text()).map(str::trim).filter(|f| !f.is_empty())
        {
            layers.push((index, f.to_string()));
        }
    }
    layers.sort();
    let Some((index, member)) = layers.first().cloned() else {
        return Err(Error::malformed(
            path,
            "index.xml names no layer with a FILENAME_Z: the file holds no heights",
        ));
    };
    let data = entry(path, &mut zip, &member, need)?.ok_or_else(|| {
        Error::malformed(
            path,
            format!("index.xml names '{member}' for LAYER_{index}, but the archive has no such member"),
        )
    })?;
    if data.len() != need {
        return Err(Error::malformed(
            path,
            format!(
                "zip member '{member}': {} bytes, {need} expected for {cols} x {rows} f32 heights",
                data.len()
            ),
        ));
    }
    let values: Vec<f64> = data
        .chunks_exact(4)
        .map(|c| {
            let v = f32::from_le_bytes([c[0], c[1], c[2], c[3]]);
            if v.is_finite() {
                v as f64 * UM
            } else {
                f64::NAN
            }
        })
        .collect();
    let values = shape(path, rows, cols, values)?;

    let mut warnings = Vec::new();
    let step = |name: &str| text(name).and_then(|t| t.parse::<f64>().ok()).map(f64::abs);
    let pitch = match (step("FOV_X"), step("FOV_Y")) {
        (Some(x), Some(y)) if x.is_finite() && x > 0.0 && y.is_finite() && y > 0.0 => Some([x * UM, y * UM]),
        (x, y) => {
            warnings
                .push(format!("GENERAL/FOV_X, FOV_Y ({x:?}, {y:?} um) give no usable pitch: pass `pitch`"));
            None
        }
    };
    if layers.len() > 1 {
        let others: Vec<String> = layers[1..].iter().map(|(i, f)| format!("LAYER_{i} ('{f}')")).collect();
        warnings.push(format!(
            "the file holds {} layers: read LAYER_{index} ('{member}'), skipped {}",
            layers.len(),
            others.join(", ")
        ));
    }

    let mut metadata = vec![("layer".to_string(), format!("LAYER_{index} ({member})"))];
    if let Some(d) = text("DATE") {
        metadata.push(("date".into(), d));
    }
    let mut info = Vec::new();
    if let Some(node) = child(root, "INFO") {
        for item in node.children().filter(|c| c.is_element() && c.tag_name().name().starts_with("ITEM_")) {
            let get = |n: &str| child(item, n).and_then(|v| v.text()).map(|t| t.trim().to_string());
            if let (Some(k), Some(v)) = (get("NAME"), get("VALUE")) {
                info.push((k, v));
            }
        }
    }
    let find = |k: &str| info.iter().find(|(n, _)| n.eq_ignore_ascii_case(k)).map(|(_, v)| v.clone());
    if let Some(d) = find("Device") {
        metadata.push(("instrument".into(), format!("Sensofar {d}")));
    }
    if let Some(o) = find("Objective") {
        metadata.push(("objective".into(), o));
    }
    metadata.push(("height_unit".into(), "um (f32)".into()));
    for n in general.children().filter(|c| c.is_element()) {
        if let Some(t) = n.text().map(str::trim).filter(|t| !t.is_empty()) {
            metadata.push((format!("GENERAL/{}", n.tag_name().name()), t.to_string()));
        }
    }
    metadata.extend(info.into_iter().map(|(k, v)| (format!("INFO/{k}"), v)));
    let raw = RawMap { values, kind: SampleKind::Float, pitch, unit: Some(1.0), metadata, scale_hint: None };
    let mut sr = ScanRaw::new(raw, ScanFormat::Plux);
    sr.warnings = warnings;
    Ok(sr)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::Write;

    fn archive(index: &str, members: &[(&str, &[u8])]) -> Vec<u8> {
        let mut buf = Cursor::new(Vec::new());
        {
            let mut z = zip::ZipWriter::new(&mut buf);
            let opt =
                zip::write::SimpleFileOptions::default().compression_method(zip::CompressionMethod::Stored);
            for (name, data) in members {
                z.start_file(*name, opt).unwrap();
                z.write_all(data).unwrap();
            }
            z.start_file(INDEX, opt).unwrap();
            z.write_all(index.as_bytes()).unwrap();
            z.finish().unwrap();
        }
        buf.into_inner()
    }

    fn index(layers: &str) -> String {
        format!(
            "<xml><GENERAL><DATE>2025-03-04 10:11:12</DATE><IMAGE_SIZE_X>3</IMAGE_SIZE_X>\
             <IMAGE_SIZE_Y>2</IMAGE_SIZE_Y><FOV_X>0.5</FOV_X><FOV_Y>0.25</FOV_Y></GENERAL>{layers}\
             <INFO><ITEM_0><NAME>Device</NAME><VALUE>S neox</VALUE></ITEM_0>\
             <ITEM_1><NAME>Objective</NAME><VALUE>50X EPI</VALUE></ITEM_1></INFO></xml>"
        )
    }

    #[test]
    fn layers_units_nan_and_refusals() {
        let heights: Vec<u8> =
            [1.0f32, 2.0, f32::NAN, 4.0, 5.0, 6.0].iter().flat_map(|v| v.to_le_bytes()).collect();
        let other = vec![0u8; 24];
        let layers = "<LAYER_1><FILENAME_Z>LAYER_1.raw</FILENAME_Z></LAYER_1>\
                      <LAYER_0><FILENAME_Z>LAYER_0.raw</FILENAME_Z></LAYER_0>";
        let bytes = archive(&index(layers), &[("LAYER_0.raw", &heights), ("LAYER_1.raw", &other)]);
        let p = Path::new("t.plux");
        let r = decode(p, &bytes).unwrap();
        assert_eq!(r.raw.values.dim(), (2, 3));
        assert_eq!(r.raw.values[[1, 2]], 6e-6);
        assert!(r.raw.values[[0, 2]].is_nan());
        assert_eq!(r.raw.pitch, Some([0.5e-6, 0.25e-6]));
        assert!(r.warnings[0].contains("skipped LAYER_1"), "{:?}", r.warnings);
        assert!(r.raw.metadata.iter().any(|(k, v)| k == "objective" && v == "50X EPI"));
        assert!(r.raw.metadata.iter().any(|(k, v)| k == "instrument" && v == "Sensofar S neox"));

        let err = |b: &[u8]| decode(p, b).unwrap_err().to_string();
        assert!(err(b"\\*File list\r\n").contains("not a Sensofar PLUx file"));
        let x3p = archive("<x/>", &[("main.xml", b"<ISO5436_2/>")]);
        assert!(err(&x3p).contains("no index.xml") || err(&x3p).contains("GENERAL/IMAGE_SIZE_X"));
        let foreign = archive("<xml><a/></xml>", &[]);
        assert!(err(&foreign).contains("not a Sensofar PLUx file"));
        let missing = archive(&index(layers), &[("LAYER_1.raw", &other)]);
        assert!(err(&missing).contains("no such member"));
        let short = archive(&index(layers), &[("LAYER_0.raw", &heights[..20])]);
        assert!(err(&short).contains("24 expected"));
        let none = archive(&index(""), &[]);
        assert!(err(&none).contains("no layer"));
        for cut in (0..bytes.len()).step_by(5) {
            let e = err(&bytes[..cut]);
            assert!(e.contains("t.plux"), "{cut}: {e}");
        }
    }
}
