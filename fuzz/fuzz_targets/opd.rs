#![no_main]

// Wyko / Bruker Vision OPD.
libfuzzer_sys::fuzz_target!(|data: &[u8]| doefab_fuzz::scan("fuzz.opd", data));
