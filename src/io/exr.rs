//! OpenEXR height maps (through the `exr` crate).
//!
//! Reading: a single-layer file with one float channel (f16 or f32; any name, "Z", "Y" or
//! "height" being the usual ones). A file with several channels is read only with an explicit
//! channel choice. Pitch and value unit come from header attributes when present; our names:
//!
//! * `pitch_x`, `pitch_y`: sample pitch in metres (f64 or f32 attribute), or a single `pitch`
//!   for both axes;
//! * `unit`: text, the unit of the stored values ("m", "um", "nm", ...).
//!
//! A file without them yields no pitch / no unit, and the caller must ask for `--pitch` /
//! `--unit`.
//!
//! Writing: f32 channels, ZIP (16 scan lines) compression, increasing line order, our
//! attributes (`pitch_x`, `pitch_y` as f64, `unit` and free text as text attributes). The `exr`
//! crate keeps custom attributes in a `HashMap` and writes them in its random iteration order;
//! the header attributes are therefore re-ordered by name after encoding, which keeps every
//! byte offset valid (the header's length does not change) and makes the output deterministic.
//! No timestamp is written.

pub mod chromaticities;
mod chunk;
mod piz;
pub mod scanline;
pub mod yca;

use std::io::Cursor;
use std::path::Path;

use exr::prelude::*;
use ndarray::Array2;

use crate::error::{Error, Result};
use crate::io::atomic::write_bytes;
use crate::io::raw_map::{unit_from_text, Metadata, RawMap, SampleKind};

/// Reads an OpenEXR height map; `channel` picks a channel by name (required when the file has
/// several).
pub fn read_exr(path: &Path, channel: Option<&str>) -> Result<RawMap> {
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    decode_exr(path, &bytes, channel)
}

/// The layer headers of an OpenEXR file, after checking its magic number and its custom
/// channel-list attributes (in file order: the `exr` crate checks custom attributes in its
/// `HashMap`'s random order, so a file with two bad ones would give a different error from run
/// to run). The decoder is third-party code fed with user bytes: a panic in it becomes an error.
fn read_headers(path: &Path, bytes: &[u8]) -> Result<exr::meta::Headers> {
    if bytes.len() < 4 || bytes[..4] != [0x76, 0x2f, 0x31, 0x01] {
        return Err(Error::signature(path, "not an OpenEXR file: bad magic (expected 76 2f 31 01)"));
    }
    scanline::check_custom_channel_lists(path, bytes)?;
    Ok(std::panic::catch_unwind(|| exr::meta::MetaData::read_from_buffered(Cursor::new(bytes), false))
        .map_err(|_| Error::malformed(path, "OpenEXR: the header decoder failed on malformed data"))?
        .map_err(|e| Error::malformed(path, format!("OpenEXR: {e}")))?
        .headers)
}

/// The channel names of every layer of an OpenEXR file, in header order (the format stores
/// them sorted by name), from its header alone.
pub fn exr_channel_names(path: &Path, bytes: &[u8]) -> Result<Vec<String>> {
    let headers = read_headers(path, bytes)?;
    Ok(headers.iter().flat_map(|h| h.channels.list.iter().map(|c| c.name.to_string())).collect())
}

/// Decodes the bytes of an OpenEXR file (see [`read_exr`]); `path` names it in errors.
pub fn decode_exr(path: &Path, bytes: &[u8], channel: Option<&str>) -> Result<RawMap> {
    let mut maps = decode_exr_channels(path, bytes, channel.as_slice())?;
    Ok(maps.swap_remove(0))
}

/// Decodes the named channels of an OpenEXR file in one pass, in the order asked (none named:
/// the file's only channel), each with the file's pitch, unit and attributes.
pub fn decode_exr_channels(path: &Path, bytes: &[u8], channels: &[&str]) -> Result<Vec<RawMap>> {
    let headers = read_headers(path, bytes)?;
    check_data_windows(path, &headers, bytes.len())?;
    let decoded = std::panic::catch_unwind(|| {
        read()
            .no_deep_data()
            .largest_resolution_level()
            .all_channels()
            .all_layers()
            .all_attributes()
            .pedantic()
            .non_parallel()
            .from_buffered(Cursor::new(bytes))
    });
    let image = match decoded {
        Ok(Ok(img)) => img,
        Ok(Err(e)) => return Err(Error::malformed(path, format!("OpenEXR: {e}"))),
        Err(_) => return Err(Error::malformed(path, "OpenEXR: the decoder failed on malformed data")),
    };
    let layers = &image.layer_data;
    if layers.len() != 1 {
        return Err(Error::unsupported(
            path,
            format!("holds {} layers; a height map has exactly one", layers.len()),
        ));
    }
    let layer = &layers[0];
    let names: Vec<String> = layer.channel_data.list.iter().map(|c| c.name.to_string()).collect();
    let indices: Vec<usize> = match channels {
        [] if names.len() == 1 => vec![0],
        [] => {
            return Err(Error::param(
                "channel",
                format!(
                    "{} has {} channels ({}): choose one with `channel`",
                    path.display(),
                    names.len(),
                    names.join(", ")
                ),
            ))
        }
        wanted => wanted
            .iter()
            .map(|want| {
                names.iter().position(|n| n == want).ok_or_else(|| {
                    Error::param(
                        "channel",
                        format!(
                            "{} has no channel '{want}' (channels: {})",
                            path.display(),
                            names.join(", ")
                        ),
                    )
                })
            })
            .collect::<Result<_>>()?,
    };
    let (w, h) = (layer.size.0, layer.size.1);
    if w == 0 || h == 0 {
        return Err(Error::malformed(path, "the image is empty"));
    }
    let mut planes = Vec::with_capacity(indices.len());
    for index in indices {
        let samples: Vec<f64> = match &layer.channel_data.list[index].sample_data {
            FlatSamples::F32(v) => v.iter().map(|&x| x as f64).collect(),
            FlatSamples::F16(v) => v.iter().map(|x| x.to_f64()).collect(),
            FlatSamples::U32(_) => {
                return Err(Error::unsupported(
                    path,
                    format!(
                        "channel '{}' holds u32 integers; a height map needs an f16 or f32 channel",
                        names[index]
                    ),
                ))
            }
        };
        planes.push(Array2::from_shape_vec((h, w), samples).map_err(|e| {
            Error::malformed(path, format!("channel '{}' does not fill {w} x {h}: {e}", names[index]))
        })?);
    }

    let Attributes { pitch, unit, metadata } = attributes(path, &layer.attributes, &image.attributes)?;
    Ok(planes
        .into_iter()
        .map(|values| RawMap {
            values,
            kind: SampleKind::Float,
            pitch,
            unit,
            metadata: metadata.clone(),
            scale_hint: None,
        })
        .collect())
}

/// Refuses a data window the file cannot hold (see the comment), `len` the file's bytes.
fn check_data_windows(path: &Path, headers: &[exr::meta::header::Header], len: usize) -> Result<()> {
    // The decoder reserves every layer's samples from the header's data window: refuse a window
    // the file cannot hold. Deflate compresses at most 1032:1 (RFC 1951); the lossy DWA codecs
    // keep at least one coefficient per 8 x 8 block on top of it, hence 1032 x 64.
    for h in headers {
        let (w, hgt) = (h.layer_size.width(), h.layer_size.height());
        let raw = w.saturating_mul(hgt).saturating_mul(h.channels.bytes_per_pixel);
        if w.saturating_mul(hgt) > 1 << 28 || raw / (1032 * 64) > len {
            return Err(Error::malformed(
                path,
                format!(
                    "OpenEXR: the data window is {w} x {hgt} pixels of {} bytes, more than a {}-byte \
                     file can hold (and above the 2^28-sample limit for a height map)",
                    h.channels.bytes_per_pixel, len
                ),
            ));
        }
    }
    Ok(())
}

/// Pitch, value unit and every attribute as text, from a layer's attributes and the image's.
struct Attributes {
    pitch: Option<[f64; 2]>,
    unit: Option<f64>,
    metadata: Vec<(String, String)>,
}

/// Our attributes (module docs) of a layer, else of the whole image: `pitch_x` and `pitch_y`
/// (or `pitch`), metres, and `unit`; one of `pitch_x` and `pitch_y` alone, or an attribute of
/// the wrong kind, is refused.
fn attributes(path: &Path, layer: &LayerAttributes, image: &ImageAttributes) -> Result<Attributes> {
    // Attributes of the layer first, then those of the whole image; each list sorted by name.
    let mut attrs: Vec<(String, &AttributeValue)> = Vec::new();
    for other in [&layer.other, &image.other] {
        let mut list: Vec<_> = other.iter().map(|(k, v)| (k.to_string(), v)).collect();
        list.sort_by(|a, b| a.0.cmp(&b.0));
        for (k, v) in list {
            if !attrs.iter().any(|(o, _)| *o == k) {
                attrs.push((k, v));
            }
        }
    }
    let get = |name: &str| attrs.iter().find(|(k, _)| k == name).map(|(_, v)| *v);
    let length = |name: &str| -> Result<Option<f64>> {
        let v = match get(name) {
            None => return Ok(None),
            Some(AttributeValue::F64(v)) => *v,
            Some(AttributeValue::F32(v)) => *v as f64,
            Some(AttributeValue::Text(t)) => unit_from_text(path, name, &t.to_string())?,
            Some(other) => {
                return Err(Error::malformed(
                    path,
                    format!(
                        "attribute '{name}' is a {:?}, expected an f64 or f32 in metres",
                        other.kind_name()
                    ),
                ))
            }
        };
        if v.is_finite() && v > 0.0 {
            Ok(Some(v))
        } else {
            Err(Error::malformed(path, format!("attribute '{name}' = {v} is not a positive length")))
        }
    };
    let pitch = match (length("pitch_x")?, length("pitch_y")?, length("pitch")?) {
        (Some(x), Some(y), _) => Some([x, y]),
        (Some(_), None, _) | (None, Some(_), _) => {
            return Err(Error::malformed(path, "has only one of the attributes 'pitch_x' and 'pitch_y'"))
        }
        (None, None, p) => p.map(|p| [p, p]),
    };
    let unit = match get("unit") {
        None => None,
        Some(AttributeValue::Text(t)) => Some(unit_from_text(path, "unit", &t.to_string())?),
        Some(_) => return Err(Error::malformed(path, "attribute 'unit' is not text")),
    };
    let metadata = attrs
        .iter()
        .map(|(k, v)| {
            let text = match v {
                AttributeValue::Text(t) => t.to_string(),
                AttributeValue::F64(x) => format!("{x:e}"),
                AttributeValue::F32(x) => format!("{x:e}"),
                AttributeValue::I32(x) => x.to_string(),
                other => format!("{other:?}"),
            };
            (k.clone(), text)
        })
        .collect::<Vec<_>>();
    Ok(Attributes { pitch, unit, metadata })
}

/// Writes f32 channels (all of one shape, row 0 at the top) with our attributes (pitch, unit,
/// free text), atomically and deterministically. Channel names must be unique; attribute and
/// channel names and texts must be Latin-1.
pub fn write_exr(path: &Path, channels: &[(&str, &Array2<f32>)], meta: &Metadata) -> Result<()> {
    let bytes = encode_exr(path, channels, meta)?;
    write_bytes(path, &bytes)
}

/// Encodes an OpenEXR file in memory (see [`write_exr`]).
pub fn encode_exr(path: &Path, channels: &[(&str, &Array2<f32>)], meta: &Metadata) -> Result<Vec<u8>> {
    let Some((_, first)) = channels.first() else {
        return Err(Error::param("channels", "an OpenEXR file needs at least one channel"));
    };
    let (h, w) = first.dim();
    if h == 0 || w == 0 {
        return Err(Error::param("channels", "an OpenEXR image needs at least 1 x 1 pixels"));
    }
    // Names must be non-empty; every text must be Latin-1, all OpenEXR can store.
    let text = |s: &str, what: &str| {
        Text::new_or_none(s).filter(|t| !(t.as_slice().is_empty() && what != "metadata value")).ok_or_else(
            || Error::param(what, format!("'{s}' is empty or not Latin-1 text, which OpenEXR cannot store")),
        )
    };
    let mut list: SmallVec<[AnyChannel<FlatSamples>; 4]> = SmallVec::new();
    for (k, (name, data)) in channels.iter().enumerate() {
        if data.dim() != (h, w) {
            return Err(Error::param(
                "channels",
                format!("channel '{name}' is {:?}, channel '{}' is {:?}", data.dim(), channels[0].0, (h, w)),
            ));
        }
        if channels[..k].iter().any(|(n, _)| n == name) {
            return Err(Error::param("channels", format!("channel name '{name}' is repeated")));
        }
        let samples: Vec<f32> = data.iter().copied().collect();
        list.push(AnyChannel::new(text(name, "channel name")?, FlatSamples::F32(samples)));
    }
    let mut attributes = LayerAttributes::default();
    // Checks reserved and repeated keys; the pitch goes in as f64 attributes, the rest as text.
    for (k, v) in meta.key_values(path)? {
        let value = match (k.as_str(), meta.pitch) {
            ("pitch_x", Some([px, _])) => AttributeValue::F64(px),
            ("pitch_y", Some([_, py])) => AttributeValue::F64(py),
            _ => AttributeValue::Text(text(&v, "metadata value")?),
        };
        attributes.other.insert(text(&k, "metadata key")?, value);
    }
    let encoding = Encoding {
        compression: Compression::ZIP16,
        blocks: Blocks::ScanLines,
        line_order: LineOrder::Increasing,
    };
    let layer = Layer::new((w, h), attributes, encoding, AnyChannels::sort(list));
    let image = Image::from_layer(layer);
    let mut buf = Vec::new();
    image
        .write()
        .non_parallel()
        .to_buffered(Cursor::new(&mut buf))
        .map_err(|e| Error::encoding(path, format!("OpenEXR encoding failed: {e}")))?;
    sort_header_attributes(&mut buf).map_err(|what| Error::encoding(path, what))?;
    Ok(buf)
}

/// Re-orders the attributes of a single-part OpenEXR header by name, in place. Each attribute
/// is `name\0 type\0 size:i32 value[size]`; the list ends with a zero byte. Moving whole
/// attributes keeps the header length, so the offset table that follows stays valid.
fn sort_header_attributes(buf: &mut [u8]) -> std::result::Result<(), String> {
    const MULTIPART: u32 = 0x1000;
    let flags =
        u32::from_le_bytes(buf.get(4..8).ok_or("no version field")?.try_into().map_err(|_| "version")?);
    if flags & MULTIPART != 0 {
        return Err("multi-part header cannot be re-ordered".into());
    }
    let start = 8;
    let mut pos = start;
    let mut attrs: Vec<(Vec<u8>, std::ops::Range<usize>)> = Vec::new();
    let cstr = |p: usize| -> std::result::Result<usize, String> {
        buf[p..].iter().position(|&b| b == 0).map(|n| p + n).ok_or_else(|| "unterminated header".to_string())
    };
    loop {
        if *buf.get(pos).ok_or("header runs past the end")? == 0 {
            break;
        }
        let name_end = cstr(pos)?;
        let type_end = cstr(name_end + 1)?;
        let size_at = type_end + 1;
        let size = i32::from_le_bytes(
            buf.get(size_at..size_at + 4).ok_or("attribute size cut off")?.try_into().map_err(|_| "size")?,
        );
        let end = size_at + 4 + usize::try_from(size).map_err(|_| "negative attribute size")?;
        if end > buf.len() {
            return Err("attribute runs past the end".into());
        }
        attrs.push((buf[pos..name_end].to_vec(), pos..end));
        pos = end;
    }
    let mut sorted = attrs.clone();
    sorted.sort_by(|a, b| a.0.cmp(&b.0));
    let region: Vec<u8> = sorted.iter().flat_map(|(_, r)| buf[r.clone()].to_vec()).collect();
    buf[start..pos].copy_from_slice(&region);
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ramp(h: usize, w: usize) -> Array2<f32> {
        Array2::from_shape_fn((h, w), |(i, j)| (i as f32 * 0.25 + j as f32 * 0.03125) * 1e-6)
    }

    #[test]
    fn round_trip_with_pitch_unit_and_text() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("h.exr");
        let a = ramp(7, 11);
        let meta = Metadata::heights([4.29e-6, 2.5e-6]).with("source", "design v1").with("material", "PDMS");
        write_exr(&p, &[("Z", &a)], &meta).unwrap();
        let r = read_exr(&p, None).unwrap();
        assert_eq!(r.values, a.mapv(|v| v as f64));
        assert_eq!(r.pitch, Some([4.29e-6, 2.5e-6]));
        assert_eq!(r.unit, Some(1.0));
        assert!(r.metadata.contains(&("source".into(), "design v1".into())));
        assert!(r.metadata.contains(&("material".into(), "PDMS".into())));
    }

    #[test]
    fn output_is_deterministic_despite_hash_map_attributes() {
        let a = ramp(5, 6);
        let mut meta = Metadata::heights([1e-6, 1e-6]);
        for k in 0..8 {
            meta = meta.with(format!("key{k}"), format!("value {k}"));
        }
        let first = encode_exr(Path::new("x.exr"), &[("Z", &a)], &meta).unwrap();
        for _ in 0..10 {
            assert_eq!(encode_exr(Path::new("x.exr"), &[("Z", &a)], &meta).unwrap(), first);
        }
        // And the re-ordered header still decodes.
        let r = decode_exr(Path::new("x.exr"), &first, None).unwrap();
        assert_eq!(r.metadata.iter().filter(|(k, _)| k.starts_with("key")).count(), 8);
    }

    #[test]
    fn no_pitch_attribute_means_none_and_multichannel_needs_a_choice() {
        let a = ramp(3, 4);
        let b = a.mapv(|v| -v);
        let bytes = encode_exr(Path::new("m.exr"), &[("Z", &a), ("mask", &b)], &Metadata::default()).unwrap();
        let e = decode_exr(Path::new("m.exr"), &bytes, None).unwrap_err().to_string();
        assert!(
            e.contains("2 channels") && e.contains("Z") && e.contains("mask") && e.contains("with `channel`"),
            "{e}"
        );
        let r = decode_exr(Path::new("m.exr"), &bytes, Some("mask")).unwrap();
        assert_eq!(r.values, b.mapv(|v| v as f64));
        assert_eq!((r.pitch, r.unit), (None, None));
        assert!(decode_exr(Path::new("m.exr"), &bytes, Some("Y"))
            .unwrap_err()
            .to_string()
            .contains("no channel 'Y'"));
    }

    #[test]
    fn several_channels_in_one_pass_in_the_order_asked() {
        let a = ramp(3, 4);
        let b = a.mapv(|v| -v);
        let bytes = encode_exr(Path::new("m.exr"), &[("Z", &a), ("mask", &b)], &Metadata::default()).unwrap();
        let maps = decode_exr_channels(Path::new("m.exr"), &bytes, &["mask", "Z"]).unwrap();
        assert_eq!(maps.len(), 2);
        assert_eq!(maps[0].values, b.mapv(|v| v as f64));
        assert_eq!(maps[1].values, a.mapv(|v| v as f64));
        let e = decode_exr_channels(Path::new("m.exr"), &bytes, &["Z", "B"]).unwrap_err().to_string();
        assert!(e.contains("no channel 'B'"), "{e}");
    }

    #[test]
    fn refuses_bad_channels_and_cut_files() {
        let a = ramp(3, 4);
        let b = ramp(4, 3);
        assert!(encode_exr(Path::new("x.exr"), &[("Z", &a), ("W", &b)], &Metadata::default()).is_err());
        assert!(encode_exr(Path::new("x.exr"), &[("Z", &a), ("Z", &a)], &Metadata::default()).is_err());
        assert!(encode_exr(Path::new("x.exr"), &[("Zµ€", &a)], &Metadata::default()).is_err());
        assert!(encode_exr(Path::new("x.exr"), &[], &Metadata::default()).is_err());
        let bytes = encode_exr(Path::new("x.exr"), &[("Z", &a)], &Metadata::heights([1e-6; 2])).unwrap();
        for cut in (0..bytes.len()).step_by(7) {
            let e = decode_exr(Path::new("cut.exr"), &bytes[..cut], None);
            assert!(e.unwrap_err().to_string().contains("cut.exr"), "cut at {cut}");
        }
    }
}

#[cfg(test)]
mod corpus_tests {
    use super::*;

    /// Two fuzz inputs whose custom channel lists are both bad: the `exr` crate's checks, in
    /// its `HashMap`'s order, gave one of two messages from run to run; the file-order check
    /// gives one, the same at every read.
    #[test]
    fn bad_custom_channel_lists_give_one_error() {
        let corpus = Path::new(env!("CARGO_MANIFEST_DIR")).join("fuzz/corpus/exr");
        for (name, expected) in [
            (
                "6913a4497bc6be663188c2888b725f9d09ffef72",
                "OpenEXR: channel 'Z' has sampling 65536 x 0, expected >= 1",
            ),
            ("a76f9780315846c69755c736e5240d6729501910", "OpenEXR: attribute 'ps' is an empty channel list"),
        ] {
            let bytes = std::fs::read(corpus.join(name)).unwrap();
            for _ in 0..50 {
                for channel in [None, Some("Z")] {
                    let e = decode_exr(Path::new("f.exr"), &bytes, channel).unwrap_err();
                    assert!(matches!(e, Error::Format { cause: crate::FormatCause::Malformed, .. }), "{e:?}");
                    assert_eq!(e.to_string(), format!("f.exr: {expected}"));
                }
            }
        }
    }
}
