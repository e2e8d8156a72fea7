#![no_main]

// Olympus LEXT .lext (multi-page TIFF with XML).
libfuzzer_sys::fuzz_target!(|data: &[u8]| doefab_fuzz::scan("fuzz.lext", data));
