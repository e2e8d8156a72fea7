//! Read and write speed of doefab's NumPy and safetensors codecs against the `ndarray-npy` and
//! `safetensors` crates, on the files doefab reads (`../shared/data/deepoptics-hdr`): the best of
//! 30 runs each, from bytes in memory (no disk time), ratios taken in this one process.
//!
//! Run: `cargo run --release --manifest-path benches/codecs/Cargo.toml [DATA_DIR]`.

use std::collections::{BTreeMap, HashMap};
use std::io::{Cursor, Read};
use std::path::{Path, PathBuf};
use std::time::Instant;

use doefab::decoder::{decode_safetensors, encode_safetensors};
use doefab::io::npy::decode_npy;
use ndarray::ArrayD;
use ndarray_npy::{NpzReader, ReadNpyExt};

/// The best of `runs` timings of `f`, in milliseconds.
fn best_ms(runs: usize, mut f: impl FnMut()) -> f64 {
    (0..runs)
        .map(|_| {
            let t = Instant::now();
            f();
            t.elapsed().as_secs_f64() * 1e3
        })
        .fold(f64::INFINITY, f64::min)
}

fn row(what: &str, ours: f64, theirs: f64) {
    println!("| {what} | {ours:.3} | {theirs:.3} | {:.2} |", ours / theirs);
}

fn main() {
    let data =
        std::env::args().nth(1).map_or_else(|| PathBuf::from("../shared/data/deepoptics-hdr"), PathBuf::from);
    let runs = 30;
    println!("| file and operation | doefab (ms) | crate (ms) | doefab / crate |");
    println!("| --- | --- | --- | --- |");

    // A 4.9 MB float32 .npy (the paper's decoder output on Kitchen, written by NumPy).
    let npy = data.join("parity/kitchen_full_output_decoder_measured_psf.npy");
    let bytes = std::fs::read(&npy).expect("the parity .npy");
    let (_, ours) = decode_npy(&npy, &bytes).expect("doefab reads it");
    let theirs = ArrayD::<f32>::read_npy(Cursor::new(&bytes)).expect("ndarray-npy reads it");
    assert_eq!(ours.shape(), theirs.shape());
    assert!(ours.iter().zip(theirs.iter()).all(|(a, b)| *a == f64::from(*b)), "the two readers differ");
    row(
        &format!(
            "read {} ({} bytes, <f4) to f64 / f32",
            npy.file_name().unwrap().to_string_lossy(),
            bytes.len()
        ),
        best_ms(runs, || drop(decode_npy(&npy, &bytes).unwrap())),
        best_ms(runs, || drop(ArrayD::<f32>::read_npy(Cursor::new(&bytes)).unwrap())),
    );

    // The measured PSF archive (.npz, deflated), the array psf_val.
    let npz = data.join("measured_psf.npz");
    let zbytes = std::fs::read(&npz).expect("measured_psf.npz");
    let ours_npz = |p: &Path| {
        let mut zip = zip::ZipArchive::new(Cursor::new(&zbytes)).unwrap();
        let mut entry = zip.by_name("psf_val.npy").unwrap();
        let mut b = Vec::new();
        entry.read_to_end(&mut b).unwrap();
        decode_npy(p, &b).unwrap().1
    };
    let theirs_npz = || {
        NpzReader::new(Cursor::new(&zbytes))
            .unwrap()
            .by_name::<ndarray::OwnedRepr<f64>, ndarray::IxDyn>("psf_val")
            .unwrap()
    };
    let (a, b) = (ours_npz(&npz), theirs_npz());
    assert!(a.iter().zip(b.iter()).all(|(x, y)| *x == *y), "the two npz readers differ");
    row(
        &format!("read measured_psf.npz psf_val {:?} ({} bytes deflated)", a.shape(), zbytes.len()),
        best_ms(runs, || drop(ours_npz(&npz))),
        best_ms(runs, || drop(theirs_npz())),
    );

    // The paper's decoder: 60 float32 tensors, 2.5 MB.
    let st = data.join("decoder_measured_psf.safetensors");
    let sbytes = std::fs::read(&st).expect("the decoder");
    let (tensors, metadata) = decode_safetensors(&st, &sbytes).expect("doefab reads it");
    let named: Vec<(&str, &doefab::decoder::NamedTensor)> =
        tensors.iter().map(|(k, v)| (k.as_str(), v)).collect();
    let raw: Vec<(String, Vec<u8>, Vec<usize>)> = tensors
        .iter()
        .map(|(k, v)| (k.clone(), v.values.iter().flat_map(|x| x.to_le_bytes()).collect(), v.shape.clone()))
        .collect();
    let views: Vec<(&str, safetensors::tensor::TensorView)> = raw
        .iter()
        .map(|(k, b, s)| {
            (k.as_str(), safetensors::tensor::TensorView::new(safetensors::Dtype::F32, s.clone(), b).unwrap())
        })
        .collect();
    let meta: HashMap<String, String> = metadata.clone().into_iter().collect();
    let ours_bytes = encode_safetensors(&named, &metadata);
    let theirs_bytes = safetensors::serialize(views.clone(), Some(meta.clone())).unwrap();
    let back = decode_safetensors(&st, &theirs_bytes).expect("doefab reads the crate's file");
    assert_eq!(back.0, tensors);
    row(
        &format!("write the paper's decoder ({} tensors, {} bytes)", tensors.len(), ours_bytes.len()),
        best_ms(runs, || drop(encode_safetensors(&named, &metadata))),
        best_ms(runs, || drop(safetensors::serialize(views.clone(), Some(meta.clone())).unwrap())),
    );
    // Reading: doefab parses with the crate's own header reader and copies the data out as f32.
    let read_ours = best_ms(runs, || drop(decode_safetensors(&st, &sbytes).unwrap()));
    let read_theirs = best_ms(runs, || {
        let t = safetensors::SafeTensors::deserialize(&sbytes).unwrap();
        let v: BTreeMap<String, Vec<f32>> = t
            .tensors()
            .into_iter()
            .map(|(k, v)| {
                (k, v.data().chunks_exact(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect())
            })
            .collect();
        drop(v)
    });
    row("read the paper's decoder to f32 tensors", read_ours, read_theirs);
    // A fresh map each time, as a caller building its metadata would (a clone keeps the hasher).
    let same: usize = (0..20)
        .map(|_| {
            let fresh: HashMap<String, String> = metadata.clone().into_iter().collect();
            safetensors::serialize(views.clone(), Some(fresh)).unwrap()
        })
        .filter(|b| *b == theirs_bytes)
        .count();
    println!(
        "\nmetadata keys: {}; safetensors::serialize gave the same bytes in {same} of 20 writes; doefab's writer: always (sorted keys)",
        meta.len()
    );
}
