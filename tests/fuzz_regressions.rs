//! Inputs the fuzz targets (`fuzz/`) found to crash, hang or allocate without bound, checked
//! here without the fuzzer: each must now be refused with an error naming the file and the
//! field, and no reader may allocate more than its input can justify. The largest single
//! allocation is measured by a counting global allocator (per thread, so parallel tests do not
//! see each other's).

use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;
use std::path::Path;

use doefab::io::scan::{decode_scan_raw, ScanOptions};
use doefab::{Error, FormatCause};

struct Counting;

thread_local! {
    static LARGEST: Cell<usize> = const { Cell::new(0) };
}

unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        let _ = LARGEST.try_with(|l| l.set(l.get().max(layout.size())));
        unsafe { System.alloc(layout) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        unsafe { System.dealloc(ptr, layout) }
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        let _ = LARGEST.try_with(|l| l.set(l.get().max(new_size)));
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

#[global_allocator]
static ALLOCATOR: Counting = Counting;

/// Decodes `bytes` as the file `name`; returns the error and the largest allocation.
fn refused(name: &str, bytes: &[u8]) -> (Error, usize) {
    LARGEST.with(|l| l.set(0));
    let r = decode_scan_raw(Path::new(name), bytes, &ScanOptions::default());
    let largest = LARGEST.with(|l| l.get());
    match r {
        Ok(raw) => panic!("{name} decoded: {:?}", raw.raw.values.dim()),
        Err(e) => (e, largest),
    }
}

/// Whether `e` is a [`FormatCause::Malformed`] fault of the file `name`.
fn malformed(e: &Error, name: &str) -> bool {
    matches!(e, Error::Format { cause: FormatCause::Malformed, path, .. } if path == Path::new(name))
}

/// A 6 x 5 ASCII SDF whose header claims `points` points per profile.
fn sdf_ascii(points_lines: &str) -> String {
    format!(
        "aISO-1.0\n{points_lines}NumProfiles = 5\nXscale = 1e-06\nYscale = 1e-06\nZscale = 1\n*\n{}*\n",
        "0 1e-09 2e-09 3e-09 4e-09 5e-09\n".repeat(5)
    )
}

/// sdf_ascii, found after 0.36 M runs: `NumPoints = 20250000` reserved 20250000 x 5 f64
/// (810 MB) before reading the 30 values the file holds; the key was also given twice (first
/// one used, the second would have fitted the data).
#[test]
fn ascii_sdf_size_claim_reserves_no_memory() {
    let (e, largest) = refused("a.sdf", sdf_ascii("NumPoints = 20250000\n").as_bytes());
    assert!(malformed(&e, "a.sdf"), "{e:?}");
    assert!(e.to_string().contains("holds 30 values"), "{e}");
    assert!(largest < 1 << 20, "largest allocation {largest} bytes for a 200-byte file");
    let (e, _) = refused("a.sdf", sdf_ascii("NumPoints = 20250000\nNumPoints = 6\n").as_bytes());
    assert!(malformed(&e, "a.sdf"), "{e:?}");
    let e = e.to_string();
    assert!(e.contains("line 3") && e.contains("'NumPoints' is given twice"), "{e}");
    // The same file with one honest NumPoints reads.
    let ok = sdf_ascii("NumPoints = 6\n");
    assert!(decode_scan_raw(Path::new("a.sdf"), ok.as_bytes(), &ScanOptions::default()).is_ok());
}

#[test]
fn gsf_header_key_given_twice_is_refused() {
    let mut f = b"Gwyddion Simple Field 1.0\nXRes = 2\nYRes = 1\nXRes = 1\n".to_vec();
    f.resize(f.len().next_multiple_of(4) + if f.len().is_multiple_of(4) { 4 } else { 0 }, 0);
    f.extend_from_slice(&[0u8; 8]);
    let (e, _) = refused("a.gsf", &f);
    assert!(malformed(&e, "a.gsf"), "{e:?}");
    assert!(e.to_string().contains("'XRes' is given twice"), "{e}");
}

/// The stored input of a fuzz finding (`tests/fuzz/`).
fn finding(name: &str) -> Vec<u8> {
    std::fs::read(Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fuzz").join(name)).unwrap()
}

/// png_pcal: Gwyddion's 2929-byte S1 PNG with the IHDR width changed to 14878664 made the PNG
/// decoder reserve its 5.95 GB output buffer before reading any image data. (Fuzz builds skip
/// PNG's chunk CRCs; the stored file has them recomputed so that this build takes the same path.)
#[test]
fn png_size_claim_beyond_deflate_is_refused_before_allocating() {
    let (e, largest) = refused("s1.png", &finding("png_pcal-ihdr-14878664x200.png"));
    assert!(malformed(&e, "s1.png") && matches!(e, Error::Format { offset: Some(16), .. }), "{e:?}");
    assert!(e.to_string().contains("14878664 x 200"), "{e}");
    assert!(largest < 1 << 20, "largest allocation {largest} bytes");
    // The unmodified file (the same IHDR but 200 x 200) still reads.
    let good = Path::new(env!("CARGO_MANIFEST_DIR")).join("profilometry/s1_tilt_pedestal.grey16.png");
    let bytes = std::fs::read(&good).unwrap();
    assert!(decode_scan_raw(&good, &bytes, &ScanOptions::default()).is_ok());
}

/// exr: a 6 x 5 seed whose dataWindow's x max became 0x500000ea made the OpenEXR decoder
/// reserve 7.4 GB of samples for a 452-byte file.
#[test]
fn exr_data_window_beyond_the_file_is_refused_before_allocating() {
    let path = Path::new("w.exr");
    LARGEST.with(|l| l.set(0));
    let e = doefab::io::exr::decode_exr(path, &finding("exr-data-window.exr"), None).unwrap_err();
    let largest = LARGEST.with(|l| l.get());
    assert!(malformed(&e, "w.exr"), "{e:?}");
    let e = e.to_string();
    assert!(e.contains("data window") && e.contains("452-byte"), "{e}");
    assert!(largest < 1 << 20, "largest allocation {largest} bytes");
}

/// gwy: a channel named `/00/data` (the fuzz target's seed with one digit added) parsed as
/// channel 0, and the reader then looked up `/0/data`, which the file does not hold, and
/// panicked. The channel is now taken by the name the file gives it.
#[test]
fn gwy_channel_number_written_with_a_leading_zero_reads() {
    let bytes = finding("gwy-channel-00.gwy");
    let r = decode_scan_raw(Path::new("c.gwy"), &bytes, &ScanOptions::default()).unwrap();
    assert!(r.raw.metadata.iter().any(|(k, v)| k == "channel" && v == "/00/data"), "{:?}", r.raw.metadata);
    assert_eq!(r.raw.values.dim(), (5, 6));
}
