//! Decoder weights as named `f32` tensors in the paper's TensorFlow layouts, read from and
//! written to safetensors files.
//!
//! The 60 tensors, their names, shapes and checkpoint order are those of
//! `deepoptics-hdr/DECODER.md` (upstream `my_medium_model`): conv weights are TF HWIO
//! `[kh, kw, in, out]`, transposed-conv weights `[kh, kw, out, in]`, biases and BatchNorm
//! vectors `[C]` (beta, gamma, moving_mean, moving_variance). The paper's two pretrained files,
//! the decoders doefab writes and other tools share this one format.
//!
//! Safetensors (huggingface/safetensors, format v1): an 8-byte little-endian header length
//! `N`, a JSON header of `N` bytes mapping each tensor name to
//! `{"dtype", "shape", "data_offsets": [begin, end]}` (offsets into the data block that
//! follows) plus an optional string-to-string `__metadata__`, then the data, row-major and
//! little-endian. The writer sorts names and metadata keys and pads the header with spaces to
//! a multiple of 8 bytes, so equal content gives equal bytes.

use std::collections::BTreeMap;
use std::path::Path;

use safetensors::{Dtype, SafeTensors};
use serde_json::{json, Map, Value};

use crate::error::{Error, Result};
use crate::io::atomic::write_bytes;

/// Channels of every hidden layer of the paper's U-Net.
pub const WIDTH: usize = 64;

/// Name and shape of each tensor, in the upstream checkpoint order (DECODER.md's table).
pub fn tensor_specs() -> Vec<(String, Vec<usize>)> {
    let c = WIDTH;
    let mut specs = Vec::with_capacity(60);
    let mut push = |name: String, shape: Vec<usize>| specs.push((name, shape));
    for level in 1..=5 {
        for conv in 1..=2 {
            let cin = if level == 1 && conv == 1 { 3 } else { c };
            push(format!("enc{level}.conv{conv}.weight"), vec![3, 3, cin, c]);
            push(format!("enc{level}.conv{conv}.bias"), vec![c]);
        }
    }
    let bn = |push: &mut dyn FnMut(String, Vec<usize>), prefix: &str, n: usize| {
        for p in ["beta", "gamma", "moving_mean", "moving_variance"] {
            push(format!("{prefix}.bn.{p}"), vec![n]);
        }
    };
    for level in 1..=5 {
        if level > 1 {
            push(format!("dec{level}.fuse.weight"), vec![1, 1, 2 * c, c]);
            push(format!("dec{level}.fuse.bias"), vec![c]);
        }
        if level < 5 {
            push(format!("dec{level}.deconv.weight"), vec![4, 4, c, c]);
            push(format!("dec{level}.deconv.bias"), vec![c]);
            bn(&mut push, &format!("dec{level}"), c);
        }
    }
    push("head.conv.weight".into(), vec![1, 1, c, 3]);
    push("head.conv.bias".into(), vec![3]);
    bn(&mut push, "head", 3);
    push("head.fuse.weight".into(), vec![1, 1, 6, 3]);
    push("head.fuse.bias".into(), vec![3]);
    specs
}

/// One tensor: its shape and row-major values.
#[derive(Debug, Clone, PartialEq)]
pub struct NamedTensor {
    /// Dimensions, TF layout (a convolution kernel is `[kh, kw, in, out]`).
    pub shape: Vec<usize>,
    /// The values, row-major; as many as the product of `shape`.
    pub values: Vec<f32>,
}

/// A decoder's 60 tensors (TF layouts, checkpoint order) and the file's metadata.
#[derive(Debug, Clone, PartialEq)]
pub struct DecoderWeights {
    /// `(name, tensor)` in the order of [`tensor_specs`].
    pub tensors: Vec<(String, NamedTensor)>,
    /// The safetensors `__metadata__` (source, PSF hash, training record, ...).
    pub metadata: BTreeMap<String, String>,
}

impl DecoderWeights {
    /// Reads a decoder file; every tensor of [`tensor_specs`] must be present as F32 with its
    /// shape, and no other tensor may be. All problems are reported at once, by name.
    pub fn read(path: &Path) -> Result<DecoderWeights> {
        let (tensors, metadata) = read_safetensors(path)?;
        Self::from_map(path, tensors, metadata)
    }

    /// Checks and orders a name-to-tensor map (see [`DecoderWeights::read`]); `path` names the
    /// source in errors.
    pub fn from_map(
        path: &Path,
        mut tensors: BTreeMap<String, NamedTensor>,
        metadata: BTreeMap<String, String>,
    ) -> Result<DecoderWeights> {
        let mut problems = Vec::new();
        let mut out = Vec::with_capacity(60);
        for (name, shape) in tensor_specs() {
            match tensors.remove(&name) {
                None => problems.push(format!("tensor '{name}' is missing (expected shape {shape:?})")),
                Some(t) if t.shape != shape => {
                    problems.push(format!("tensor '{name}' has shape {:?}, expected {shape:?}", t.shape))
                }
                Some(t) => out.push((name, t)),
            }
        }
        for name in tensors.keys() {
            problems.push(format!("tensor '{name}' is not part of the decoder"));
        }
        if !problems.is_empty() {
            return Err(Error::signature(
                path,
                format!("not a DeepOpticsHDR decoder: {}", problems.join("; ")),
            ));
        }
        Ok(DecoderWeights { tensors: out, metadata })
    }

    /// The tensor called `name`.
    pub fn get(&self, name: &str) -> Option<&NamedTensor> {
        self.tensors.iter().find(|(n, _)| n == name).map(|(_, t)| t)
    }

    /// Number of scalar parameters (630,820 for the paper's network).
    pub fn parameter_count(&self) -> usize {
        self.tensors.iter().map(|(_, t)| t.values.len()).sum()
    }

    /// Writes the decoder atomically as safetensors with its metadata (plus the layout and
    /// checkpoint order, so the file describes itself).
    pub fn write(&self, path: &Path) -> Result<()> {
        let mut meta = self.metadata.clone();
        meta.insert("layout".into(), LAYOUT.into());
        let order: Vec<&str> = self.tensors.iter().map(|(n, _)| n.as_str()).collect();
        meta.insert("order".into(), json!(order).to_string());
        let refs: Vec<(&str, &NamedTensor)> = self.tensors.iter().map(|(n, t)| (n.as_str(), t)).collect();
        write_bytes(path, &encode_safetensors(&refs, &meta))
    }
}

/// The layout description stored in every decoder file (the paper's files carry the same).
pub const LAYOUT: &str =
    "NHWC activations; conv weight [kh,kw,in,out] (TF HWIO); deconv weight [kh,kw,out,in] \
(TF conv2d_transpose); BN: beta,gamma,moving_mean,moving_variance, eps=1e-5";

/// Reads every tensor of a safetensors file (F32 only) and its metadata.
/// `built-in:NAME` reads one of the decoders compiled into the binary ([`BUILT_IN`]).
pub fn read_safetensors(path: &Path) -> Result<(BTreeMap<String, NamedTensor>, BTreeMap<String, String>)> {
    decode_safetensors(path, &decoder_bytes(path)?)
}

/// The bytes of a decoder file, or of a bundled decoder for `built-in:NAME`.
pub fn decoder_bytes(path: &Path) -> Result<std::borrow::Cow<'static, [u8]>> {
    if let Some(name) = path.to_str().and_then(|p| p.strip_prefix("built-in:")) {
        let Some((_, bytes)) = BUILT_IN.iter().find(|(n, _)| *n == name) else {
            let names: Vec<_> = BUILT_IN.iter().map(|(n, _)| format!("built-in:{n}")).collect();
            return Err(Error::signature(
                path,
                format!("no bundled decoder of that name; bundled: {}", names.join(", ")),
            ));
        };
        return Ok(std::borrow::Cow::Borrowed(bytes));
    }
    Ok(std::borrow::Cow::Owned(std::fs::read(path).map_err(|e| Error::io(path, e))?))
}

/// SHA-256 (hex) of a decoder file or bundled decoder, as recorded in outputs' metadata.
pub fn decoder_sha256(path: &Path) -> Result<String> {
    Ok(crate::io::hex_sha256(&decoder_bytes(path)?))
}

/// The bundled decoders, compiled in so that an installed binary fine-tunes and reconstructs
/// with no data beside it: the paper's two (Metzler et al. 2020, BSD-3,
/// `assets/deepoptics-hdr/LICENSE`), `paper-simulated-psf` (trained end to end with the
/// simulated PSF) and `paper-measured-psf` (fine-tuned by the paper with its measured PSF),
/// and `doefab-measured-psf`, doefab's `finetune` of the first on the paper's measured PSF
/// (`assets/doefab/`, its `training.json` beside it; derived from the paper's weights, so
/// under the same licence).
pub const BUILT_IN: &[(&str, &[u8])] = &[
    ("paper-simulated-psf", include_bytes!("../../assets/deepoptics-hdr/decoder_simulated_psf.safetensors")),
    ("paper-measured-psf", include_bytes!("../../assets/deepoptics-hdr/decoder_measured_psf.safetensors")),
    ("doefab-measured-psf", include_bytes!("../../assets/doefab/decoder_measured_psf.safetensors")),
];

/// Decodes safetensors bytes (see `read_safetensors`) with the format's reference crate
/// (`safetensors`, whose `read_metadata` checks the header, each tensor's offsets against its
/// shape and dtype, and that the tensors cover the data block exactly); `path` names the
/// source in errors.
pub fn decode_safetensors(
    path: &Path,
    bytes: &[u8],
) -> Result<(BTreeMap<String, NamedTensor>, BTreeMap<String, String>)> {
    let bad = |what: String| Error::malformed(path, format!("safetensors: {what}"));
    let (header_len, header) = SafeTensors::read_metadata(bytes).map_err(|e| bad(e.to_string()))?;
    let data = &bytes[8 + header_len..];
    let metadata: BTreeMap<String, String> =
        header.metadata().clone().unwrap_or_default().into_iter().collect();
    let mut tensors = BTreeMap::new();
    for (name, info) in header.tensors() {
        if info.dtype != Dtype::F32 {
            return Err(bad(format!("tensor '{name}' has dtype {}, expected F32", info.dtype)));
        }
        let (begin, end) = info.data_offsets;
        let values =
            data[begin..end].chunks_exact(4).map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])).collect();
        tensors.insert(name, NamedTensor { shape: info.shape.clone(), values });
    }
    Ok((tensors, metadata))
}

/// Encodes tensors and metadata as safetensors bytes (names sorted, header padded to 8 bytes).
///
/// Written here rather than by `safetensors::serialize`, which takes the metadata as a
/// `HashMap` and writes it in that map's random order: twenty writes of the same six-key
/// metadata gave twenty different files (safetensors 0.8.0; `benches/codecs`: seven keys, a
/// fresh map each write, 0 of 20 writes equal). Sorted keys keep equal content equal bytes;
/// the reference crate reads these files back in the tests. Speed (`benches/codecs`): the
/// paper's 2.5 MB decoder in 0.24 ms, the crate's `serialize` 0.21 ms. Reading goes through
/// the crate's own parser ([`decode_safetensors`], 1.03x of the crate alone).
pub fn encode_safetensors(tensors: &[(&str, &NamedTensor)], metadata: &BTreeMap<String, String>) -> Vec<u8> {
    let mut sorted: Vec<&(&str, &NamedTensor)> = tensors.iter().collect();
    sorted.sort_by_key(|(n, _)| *n);
    let mut header = Map::new();
    if !metadata.is_empty() {
        header.insert("__metadata__".into(), json!(metadata));
    }
    let mut offset = 0usize;
    for (name, t) in &sorted {
        let end = offset + 4 * t.values.len();
        header
            .insert((*name).into(), json!({"dtype": "F32", "shape": t.shape, "data_offsets": [offset, end]}));
        offset = end;
    }
    // Inserted in sorted order ("__metadata__" sorts first), so the bytes are the same whether
    // serde_json's Map keeps insertion order or sorts.
    let mut text = Value::Object(header).to_string().into_bytes();
    while !text.len().is_multiple_of(8) {
        text.push(b' ');
    }
    let mut out = Vec::with_capacity(8 + text.len() + offset);
    out.extend((text.len() as u64).to_le_bytes());
    out.extend(text);
    for (_, t) in sorted {
        let start = out.len();
        out.resize(start + 4 * t.values.len(), 0);
        for (b, v) in out[start..].chunks_exact_mut(4).zip(&t.values) {
            b.copy_from_slice(&v.to_le_bytes());
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn specs_count_the_papers_parameters() {
        let specs = tensor_specs();
        assert_eq!(specs.len(), 60);
        let total: usize = specs.iter().map(|(_, s)| s.iter().product::<usize>()).sum();
        assert_eq!(total, 630_820);
        assert_eq!(specs[20].0, "dec1.deconv.weight");
        assert_eq!(specs[26].0, "dec2.fuse.weight");
        assert_eq!(specs[52].0, "head.conv.weight");
        assert_eq!(specs[59].0, "head.fuse.bias");
    }

    #[test]
    fn encode_decode_round_trip_and_truncation() {
        let t = NamedTensor { shape: vec![2, 3], values: vec![1.0, -2.5, 3.0, 0.0, f32::MIN_POSITIVE, 7.0] };
        let meta = BTreeMap::from([("k".to_string(), "v".to_string())]);
        let bytes = encode_safetensors(&[("a", &t)], &meta);
        let (back, m) = decode_safetensors(Path::new("x"), &bytes).unwrap();
        assert_eq!(back["a"], t);
        assert_eq!(m, meta);
        let err = decode_safetensors(Path::new("x"), &bytes[..bytes.len() - 4]).unwrap_err().to_string();
        assert!(
            err.contains("x") && err.contains("safetensors") && err.contains("not fully covered"),
            "{err}"
        );
    }

    #[test]
    fn equal_content_gives_equal_bytes_with_metadata_sorted() {
        let t = NamedTensor { shape: vec![1], values: vec![0.5] };
        let meta: BTreeMap<String, String> =
            (0..6).rev().map(|i| (format!("key{i}"), format!("v{i}"))).collect();
        let first = encode_safetensors(&[("b", &t), ("a", &t)], &meta);
        for _ in 0..5 {
            assert_eq!(encode_safetensors(&[("a", &t), ("b", &t)], &meta.clone()), first);
        }
        let text = String::from_utf8_lossy(&first);
        let at = |k: &str| text.find(k).unwrap();
        assert!(at("key0") < at("key1") && at("key4") < at("key5") && at("\"a\"") < at("\"b\""), "{text}");
    }
}
