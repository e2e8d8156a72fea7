#![no_main]

use std::path::Path;

// NumPy .npy: the n-dimensional decoder, then the scan path (2-D maps).
libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    let _ = doefab::io::npy::decode_npy(Path::new("fuzz.npy"), data);
    doefab_fuzz::scan("fuzz.npy", data);
});
