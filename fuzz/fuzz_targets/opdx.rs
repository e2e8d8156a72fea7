#![no_main]

// Bruker Vision64 .opdx.
libfuzzer_sys::fuzz_target!(|data: &[u8]| doefab_fuzz::scan("fuzz.opdx", data));
