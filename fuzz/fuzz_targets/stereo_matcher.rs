//! cargo-fuzz target; the harness (input format and oracle) is in `fuzz/harness/stereo.rs`.
#![no_main]

#[path = "../harness/stereo.rs"]
mod harness;
#[path = "../harness/input.rs"]
mod input;

libfuzzer_sys::fuzz_target!(|data: &[u8]| harness::run(data));
