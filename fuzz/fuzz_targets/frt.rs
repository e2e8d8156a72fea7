#![no_main]

// FRT MicroProf .frt.
libfuzzer_sys::fuzz_target!(|data: &[u8]| doefab_fuzz::scan("fuzz.frt", data));
