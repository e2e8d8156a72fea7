#![no_main]

// Zygo MetroPro: `.dat` with the MetroPro magic number (else the text-matrix reader).
libfuzzer_sys::fuzz_target!(|data: &[u8]| doefab_fuzz::scan("fuzz.dat", data));
