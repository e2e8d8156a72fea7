#![no_main]

// Binary SDF: the reader picks binary by the first byte `b`.
libfuzzer_sys::fuzz_target!(|data: &[u8]| doefab_fuzz::scan("fuzz.sdf", data));
