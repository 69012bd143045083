//! Fuzz target `mcap`: see `targets::mcap`.
#![no_main]
#[path = "../targets.rs"]
mod targets;

libfuzzer_sys::fuzz_target!(|data: &[u8]| targets::mcap(data));
