#![no_main]

// Keyence .vk4.
libfuzzer_sys::fuzz_target!(|data: &[u8]| doefab_fuzz::scan("fuzz.vk4", data));
