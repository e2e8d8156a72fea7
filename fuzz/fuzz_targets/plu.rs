#![no_main]

// Sensofar PLu.
libfuzzer_sys::fuzz_target!(|data: &[u8]| doefab_fuzz::scan("fuzz.plu", data));
