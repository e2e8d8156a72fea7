#![no_main]

// Stylus profile exports (CSV/TXT).
libfuzzer_sys::fuzz_target!(|data: &[u8]| doefab_fuzz::profile(data));
