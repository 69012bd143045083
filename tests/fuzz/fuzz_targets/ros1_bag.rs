//! Fuzz target `ros1_bag`: see `targets::ros1_bag`.
#![no_main]
#[path = "../targets.rs"]
mod targets;

libfuzzer_sys::fuzz_target!(|data: &[u8]| targets::ros1_bag(data));
