//! Fuzz target `ros2_sqlite`: see `targets::ros2_sqlite`.
#![no_main]
#[path = "../targets.rs"]
mod targets;

libfuzzer_sys::fuzz_target!(|data: &[u8]| targets::ros2_sqlite(data));
