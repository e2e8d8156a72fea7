#![no_main]

// Zygo Mx .datx (HDF5).
libfuzzer_sys::fuzz_target!(|data: &[u8]| doefab_fuzz::scan("fuzz.datx", data));
