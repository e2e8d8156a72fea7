#![no_main]

// Sensofar .plux (a zip archive).
libfuzzer_sys::fuzz_target!(|data: &[u8]| doefab_fuzz::scan("fuzz.plux", data));
