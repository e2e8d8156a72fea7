#![no_main]

use std::path::Path;

// OpenEXR design maps (the only channel, then one named "Z"). The reader turns a panic inside
// the third-party decoder into an error (`catch_unwind`); the default panic hook is restored so
// that such a caught panic is not reported as a crash, while one that escapes still aborts.
libfuzzer_sys::fuzz_target!(
    init: {
        let _ = std::panic::take_hook();
    },
    |data: &[u8]| {
        let path = Path::new("fuzz.exr");
        doefab_fuzz::design("fuzz.exr", doefab::io::exr::decode_exr(path, data, None));
        doefab_fuzz::design("fuzz.exr", doefab::io::exr::decode_exr(path, data, Some("Z")));
    }
);
