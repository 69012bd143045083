//! Fuzz target `params_yaml`: see `targets::params_yaml`.
#![no_main]
#[path = "../targets.rs"]
mod targets;

libfuzzer_sys::fuzz_target!(|data: &[u8]| targets::params_yaml(data));
