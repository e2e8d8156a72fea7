#![no_main]

// 16/8-bit PNG with its pCAL height scale.
libfuzzer_sys::fuzz_target!(|data: &[u8]| doefab_fuzz::scan("fuzz.png", data));
