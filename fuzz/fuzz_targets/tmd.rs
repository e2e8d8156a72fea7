#![no_main]

// TrueMap .tmd.
libfuzzer_sys::fuzz_target!(|data: &[u8]| doefab_fuzz::scan("fuzz.tmd", data));
