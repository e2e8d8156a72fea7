#![no_main]

// Keyence .vk6 / .vk7 (a zip holding the VK4 stream after a preview).
libfuzzer_sys::fuzz_target!(|data: &[u8]| doefab_fuzz::scan("fuzz.vk6", data));
