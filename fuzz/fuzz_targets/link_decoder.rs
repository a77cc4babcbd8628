//! cargo-fuzz target; the harness (input format and oracle) is in `fuzz/harness/link.rs`.
#![no_main]

#[path = "../harness/link.rs"]
mod harness;
#[path = "../harness/input.rs"]
mod input;

libfuzzer_sys::fuzz_target!(|data: &[u8]| harness::run(data));
