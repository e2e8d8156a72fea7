#![no_main]

// Gwyddion native .gwy.
libfuzzer_sys::fuzz_target!(|data: &[u8]| doefab_fuzz::scan("fuzz.gwy", data));
