#![no_main]
libfuzzer_sys::fuzz_target!(|data: &[u8]| terrain_fuzz::heights_decode(data));
