#![no_main]

// ASCII SDF (aBCR/aISO header, BAD markers).
libfuzzer_sys::fuzz_target!(|data: &[u8]| doefab_fuzz::scan("fuzz.sdf", data));
