//! OpenEXR images as the decoder's training data reads them, against the OpenEXR library
//! (Python `OpenEXR`, and `RgbaInputFile` crops in `tests/data/rgba-yca/`) and colour-science:
//! luminance/chroma files (subsampled chroma, several compressions), other primaries than
//! Rec. 709, tiled mip-maps, and every image of the shared `hdr` folder.

use std::path::{Path, PathBuf};

use doefab::calibration::{read_image, read_rgb_exr};
use doefab::io::exr::scanline::Header;
use doefab::io::exr::yca;

use crate::common;

/// The luminance/chroma photographs of the shared set.
const YCA: [&str; 3] = ["CrissyField", "MtTamNorth", "Flowers"];

fn photos() -> PathBuf {
    common::shared_data("hdr/photos-openexr")
}

/// Writes each channel's samples as Python OpenEXR reads them (little-endian) to
/// `OUT/NAME.CHANNEL.bin`; prints `NAME CHANNEL ROWS COLS DTYPE` lines.
const RAW_CHANNELS: &str = r#"
import sys, numpy as np, OpenEXR
src, out = sys.argv[1], sys.argv[2]
for name in sys.argv[3:]:
    ch = OpenEXR.File(f'{src}/{name}.exr').channels()
    for c in ('Y', 'RY', 'BY'):
        p = ch[c].pixels
        p.astype(p.dtype.newbyteorder('<')).tofile(f'{out}/{name}.{c}.bin')
        print(name, c, *p.shape, p.dtype.name)
"#;

/// Our raw `Y`, `RY`, `BY` of `dir/NAME.exr` against the OpenEXR library's, bit for bit (half
/// or float as stored); returns the decoded channels.
fn raw_channels_match(dir: &Path, names: &[&str]) -> Vec<yca::LumaChroma> {
    let t = common::tempdir();
    let mut args = vec![dir.to_str().unwrap(), t.path().to_str().unwrap()];
    args.extend(names);
    let listing = common::run_python(RAW_CHANNELS, &args);
    let mut out = Vec::new();
    for name in names {
        let path = dir.join(format!("{name}.exr"));
        let bytes = std::fs::read(&path).unwrap();
        let header = Header::parse(&path, &bytes).unwrap();
        assert!(yca::is_luminance_chroma(&header), "{name}");
        let lc = yca::read_luma_chroma(&path, &bytes, &header).unwrap();
        for (c, plane) in [("Y", &lc.y), ("RY", &lc.ry), ("BY", &lc.by)] {
            let prefix = format!("{name} {c} {} {} ", plane.rows, plane.cols);
            let line = listing
                .lines()
                .find(|l| l.starts_with(&prefix))
                .unwrap_or_else(|| panic!("{prefix} in\n{listing}"));
            let theirs = std::fs::read(t.path().join(format!("{name}.{c}.bin"))).unwrap();
            let ours: Vec<u8> = match line.rsplit(' ').next() {
                Some("float16") => plane
                    .values
                    .iter()
                    .flat_map(|&v| half::f16::from_f32(v).to_bits().to_le_bytes())
                    .collect(),
                Some("float32") => plane.values.iter().flat_map(|v| v.to_le_bytes()).collect(),
                other => panic!("{line}: {other:?}"),
            };
            assert_eq!(ours.len(), theirs.len(), "{line}");
            let differ = ours.iter().zip(&theirs).filter(|(a, b)| a != b).count();
            assert_eq!(differ, 0, "{line}: {differ} bytes differ");
        }
        out.push(lc);
    }
    out
}

/// The three luminance/chroma photographs (B44, PIZ, B44): raw channels equal to the OpenEXR
/// library's, and RGB equal to what its `RgbaInputFile` reconstructs (committed crops at the
/// corners and at the most saturated pixel), bit for bit; `read_rgb_exr` gives that RGB.
#[test]
fn luminance_chroma_photos_decode_as_the_openexr_library_does() {
    let dir = photos();
    let decoded = raw_channels_match(&dir, &YCA);
    let refs = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/data/rgba-yca");
    let mut crops = 0;
    for (name, lc) in YCA.iter().zip(&decoded) {
        let rgb = yca::reconstruct_rgb(lc);
        let via_reader = read_rgb_exr(&dir.join(format!("{name}.exr"))).unwrap();
        assert_eq!(via_reader.dim(), rgb.dim());
        assert!(via_reader.values.iter().zip(rgb.iter()).all(|(a, &b)| *a == b as f64), "{name}");
        for entry in std::fs::read_dir(&refs).unwrap() {
            let p = entry.unwrap().path();
            let file = p.file_stem().unwrap().to_string_lossy().into_owned();
            let Some(pos) = file.strip_prefix(&format!("{name}_y")) else { continue };
            let (y, x) = pos.split_once("_x").unwrap();
            let (y0, x0): (usize, usize) = (y.parse().unwrap(), x.parse().unwrap());
            let (_, crop) = doefab::io::npy::read_npy_nd(&p).unwrap();
            assert_eq!(crop.shape(), [16, 16, 3]);
            let differ =
                crop.indexed_iter().filter(|(i, v)| rgb[[y0 + i[0], x0 + i[1], i[2]]] as f64 != **v).count();
            assert_eq!(differ, 0, "{file}: {differ} of 768 values differ from RgbaInputFile's");
            crops += 1;
        }
    }
    assert_eq!(crops, 9);
}

/// Writes a smooth RGB image as Y, RY, BY (chroma point-sampled 2 x 2, as half) with Python
/// OpenEXR under each compression, two sizes (one with its data window at (-4, 2)), Y as half
/// or float; prints the files.
const WRITE_YCA: &str = r#"
import sys, numpy as np, OpenEXR
out = sys.argv[1]
yw = np.array([0.2126390059, 0.7151686788, 0.0721923154])
C = OpenEXR.Compression

def subsampled(a):
    # The binding takes a subsampled channel's samples from the start of an array shaped as
    # the image (it refuses arrays of other shapes).
    s = np.ascontiguousarray(a[::2, ::2]).astype(np.float16)
    full = np.zeros(a.shape, np.float16)
    full.ravel()[:s.size] = s.ravel()
    return full

for (h, w, x0, y0) in [(48, 62, 0, 0), (46, 66, -4, 2)]:
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    rgb = np.stack([1.0 + 0.4 * np.sin(x / 9.0 + y / 13.0),
                    0.8 + 0.3 * np.cos(x / 11.0 - y / 7.0),
                    0.5 + 0.2 * np.sin(y / 10.0) * np.cos(x / 15.0)], axis=2)
    Y = rgb @ yw
    RY = (rgb[..., 0] - Y) / Y
    BY = (rgb[..., 2] - Y) / Y
    rgb.astype('<f4').tofile(f'{out}/rgb_{h}x{w}.bin')
    window = (np.array([x0, y0], np.int32), np.array([x0 + w - 1, y0 + h - 1], np.int32))
    for comp in ['NO', 'RLE', 'ZIPS', 'ZIP', 'PIZ', 'B44', 'B44A']:
        for ytype in [np.float16, np.float32]:
            if ytype == np.float32 and comp not in ('ZIP', 'PIZ', 'B44'):
                continue
            name = f'{comp}_{np.dtype(ytype).name}_{h}x{w}'
            ch = {'Y': OpenEXR.Channel(Y.astype(ytype)),
                  'RY': OpenEXR.Channel(subsampled(RY), 2, 2, True),
                  'BY': OpenEXR.Channel(subsampled(BY), 2, 2, True)}
            hdr = {'compression': getattr(C, comp + '_COMPRESSION'), 'type': OpenEXR.scanlineimage,
                   'dataWindow': window, 'displayWindow': window}
            OpenEXR.File(hdr, ch).write(f'{out}/{name}.exr')
            print(name)
"#;

/// Luminance/chroma files written by the OpenEXR library under every compression this
/// reader decodes (NONE, RLE, ZIPS, ZIP, PIZ, B44, B44A; a window at the origin and one at
/// (-4, 2); Y half or float): raw channels equal to the library's reading of them, bit for
/// bit, and RGB equal to the smooth image they were made from within half precision (B44's
/// own loss aside; away from the edges, where the chroma filters extend the image by its edge
/// values).
#[test]
fn luminance_chroma_files_of_every_compression_round_trip() {
    let t = common::tempdir();
    let names: Vec<String> =
        common::run_python(WRITE_YCA, &[t.path().to_str().unwrap()]).lines().map(String::from).collect();
    assert_eq!(names.len(), 2 * 10, "{names:?}");
    raw_channels_match(t.path(), &names.iter().map(String::as_str).collect::<Vec<_>>());
    let mut worst = 0.0f64;
    for name in &names {
        let size = name.rsplit('_').next().unwrap();
        let (h, w) = size.split_once('x').unwrap();
        let (h, w): (usize, usize) = (h.parse().unwrap(), w.parse().unwrap());
        let truth: Vec<f32> = std::fs::read(t.path().join(format!("rgb_{size}.bin")))
            .unwrap()
            .chunks(4)
            .map(|b| f32::from_le_bytes(b.try_into().unwrap()))
            .collect();
        let img = read_rgb_exr(&t.path().join(format!("{name}.exr"))).unwrap();
        assert_eq!(img.dim(), (h, w, 3), "{name}");
        // The chroma filters reach 13 pixels: nearer the edges they extend the image by its
        // edge values (as OpenEXR does), which a smooth gradient does not follow exactly.
        let (mut inner, mut all) = (0.0f64, 0.0f64);
        for ((k, a), &b) in img.values.indexed_iter().zip(&truth) {
            let e = (a / b as f64 - 1.0).abs();
            all = all.max(e);
            if k.0 >= 14 && k.0 + 14 < h && k.1 >= 14 && k.1 + 14 < w {
                inner = inner.max(e);
            }
        }
        eprintln!("{name}: largest relative RGB error {inner:.2e} inside, {all:.2e} at the edges");
        // A few half steps (2^-11 relative): G = (Y - R w_R - B w_B) / w_G amplifies the
        // rounding of Y and of the chroma.
        // B44 is lossy: it quantises each 4 x 4 block's differences to 6 bits.
        let bound = if name.starts_with("B44") { 1.5e-2 } else { 4e-3 };
        assert!(inner < bound && all < 0.1, "{name}: {inner} {all}");
        if !name.starts_with("B44") {
            worst = worst.max(inner);
        }
    }
    eprintln!("largest relative RGB error inside, over the lossless files: {worst:.2e}");
}

/// Reads RGBA of a file with Python OpenEXR and converts it from the file's chromaticities to
/// Rec. 709 with colour-science (Bradford adaptation); writes float64 RGB to `OUT/NAME.bin`.
const COLOUR_SCIENCE: &str = r#"
import sys, warnings
warnings.simplefilter('ignore')
import numpy as np, OpenEXR, colour
src, out = sys.argv[1], sys.argv[2]
for name in sys.argv[3:]:
    f = OpenEXR.File(f'{src}/{name}.exr')
    c = f.header()['chromaticities']
    rgb = np.asarray(f.channels()['RGBA'].pixels, dtype=np.float64)[..., :3]
    cs = colour.RGB_Colourspace(name, np.reshape(c[:6], (3, 2)), np.array(c[6:]))
    conv = colour.RGB_to_RGB(rgb, cs, colour.RGB_COLOURSPACES['ITU-R BT.709'],
                             chromatic_adaptation_transform='Bradford')
    conv.astype('<f8').tofile(f'{out}/{name}.bin')
    print(name, *conv.shape, np.abs(conv - rgb).max() / np.abs(conv).max())
"#;

/// Carrots (ACES AP0 primaries, ACES white) and Tree (primaries and white of their own) come
/// out in Rec. 709 as colour-science's Bradford conversion of the library's pixels has them.
#[test]
fn other_primaries_are_converted_to_rec709_as_colour_science_does() {
    let dir = photos();
    let t = common::tempdir();
    let out = common::run_python(
        COLOUR_SCIENCE,
        &[dir.to_str().unwrap(), t.path().to_str().unwrap(), "Carrots", "Tree"],
    );
    for name in ["Carrots", "Tree"] {
        let ours = read_rgb_exr(&dir.join(format!("{name}.exr"))).unwrap();
        let (h, w, c) = ours.dim();
        let line = out.lines().find(|l| l.starts_with(&format!("{name} {h} {w} {c} "))).expect("shape");
        // The conversion moves values by a good part of their scale: not converting would fail.
        let moved: f64 = line.rsplit(' ').next().unwrap().parse().unwrap();
        assert!(moved > 0.01, "{line}");
        let theirs: Vec<f64> = std::fs::read(t.path().join(format!("{name}.bin")))
            .unwrap()
            .chunks(8)
            .map(|b| f64::from_le_bytes(b.try_into().unwrap()))
            .collect();
        let scale = theirs.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        let d = ours.values.iter().zip(&theirs).map(|(a, b)| (a - b).abs()).fold(0.0, f64::max);
        eprintln!("{name}: max |ours - colour-science| = {d:.2e} of a scale {scale:.3} (the conversion moves {moved:.3})");
        assert!(d <= 1e-12 * scale, "{name}: {d}");
    }
}

/// Prints each EXR's data-window size and whether it is tiled (`PATH H W TILED`) and writes
/// the pixels of the tiled files (level 0 as the library reads it, RGB) as float32 to
/// `OUT/STEM.bin`.
const HEADERS: &str = r#"
import sys, os, numpy as np, OpenEXR
root, out = sys.argv[1], sys.argv[2]
for d, _, files in sorted(os.walk(root)):
    for f in sorted(files):
        if not f.endswith('.exr'):
            continue
        p = os.path.join(d, f)
        x = OpenEXR.File(p)
        (x0, y0), (x1, y1) = x.header()['dataWindow']
        print(os.path.relpath(p, root), y1 - y0 + 1, x1 - x0 + 1, x.header().get('tiles') is not None)
        if x.header().get('tiles') is not None:
            ch = x.channels()
            rgb = ch['RGBA'].pixels if 'RGBA' in ch else ch['RGB'].pixels
            rgb[..., :3].astype('<f4').tofile(os.path.join(out, f[:-4] + '.bin'))
"#;

/// Every image of the shared `hdr` folder is read (43: none skipped), each at the size of its
/// data window; the five tiled files (GoldenGate, Ocean, and the mip-maps Bonita,
/// KernerEnvLatLong, StageEnvLatLong) at level 0, equal to the library's value for value.
#[test]
fn every_image_of_the_shared_hdr_folder_is_read() {
    let root = common::shared_data("hdr");
    let t = common::tempdir();
    let listing = common::run_python(HEADERS, &[root.to_str().unwrap(), t.path().to_str().unwrap()]);
    let folder = doefab::decoder::read_dir(&root).unwrap();
    assert!(folder.skipped.is_empty(), "{:?}", folder.skipped);
    assert_eq!(folder.images.len(), 43);
    let mut tiled = 0;
    for line in listing.lines() {
        let f: Vec<&str> = line.split(' ').collect();
        let img =
            folder.images.iter().find(|i| i.name == f[0]).unwrap_or_else(|| panic!("{} not read", f[0]));
        let (h, w, c) = img.pixels.dim();
        assert_eq!((h.to_string(), w.to_string(), c), (f[1].into(), f[2].into(), 3), "{line}");
        if f[3] == "True" {
            let stem = Path::new(f[0]).file_stem().unwrap().to_string_lossy().into_owned();
            let theirs: Vec<f32> = std::fs::read(t.path().join(format!("{stem}.bin")))
                .unwrap()
                .chunks(4)
                .map(|b| f32::from_le_bytes(b.try_into().unwrap()))
                .collect();
            let ours = read_image(&root.join(f[0])).unwrap();
            assert_eq!(ours.values.len(), theirs.len(), "{line}");
            assert!(ours.values.iter().zip(&theirs).all(|(a, &b)| *a == b as f64), "{line}: level 0 differs");
            tiled += 1;
        }
    }
    assert_eq!(tiled, 5, "{listing}");
    assert_eq!(listing.lines().count(), 42, "42 EXR files and one .hdr");
}
