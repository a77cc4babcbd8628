//! cargo-fuzz target; the harness (input format and oracle) is in `fuzz/harness/mavlink.rs`.
#![no_main]

#[path = "../harness/input.rs"]
mod input;
#[path = "../harness/mavlink.rs"]
mod harness;

libfuzzer_sys::fuzz_target!(|data: &[u8]| harness::run(data));
