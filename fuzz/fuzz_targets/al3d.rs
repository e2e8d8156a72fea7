#![no_main]

// Alicona .al3d.
libfuzzer_sys::fuzz_target!(|data: &[u8]| doefab_fuzz::scan("fuzz.al3d", data));
