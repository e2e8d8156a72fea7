#![no_main]

use std::path::Path;

// TIFF design maps and scans.
libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    doefab_fuzz::design("fuzz.tiff", doefab::io::tiff::decode_tiff(Path::new("fuzz.tiff"), data));
    doefab_fuzz::scan("fuzz.tiff", data);
});
