//! Fuzz target `image_msg`: see `targets::image_msg`.
#![no_main]
#[path = "../targets.rs"]
mod targets;

libfuzzer_sys::fuzz_target!(|data: &[u8]| targets::image_msg(data));
