#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| doefab_fuzz::scan("fuzz.gsf", data));
