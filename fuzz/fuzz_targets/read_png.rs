#![no_main]
libfuzzer_sys::fuzz_target!(|data: &[u8]| terrain_fuzz::read_png(data));
