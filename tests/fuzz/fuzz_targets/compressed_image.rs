//! Fuzz target `compressed_image`: see `targets::compressed_image`.
#![no_main]
#[path = "../targets.rs"]
mod targets;

libfuzzer_sys::fuzz_target!(|data: &[u8]| targets::compressed_image(data));
