#![no_main]

// Bruker Nanoscope .spm.
libfuzzer_sys::fuzz_target!(|data: &[u8]| doefab_fuzz::scan("fuzz.spm", data));
