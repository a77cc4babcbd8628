//! Puts the board's memory map (the workspace's `memory.x`) where cortex-m-rt's `link.x` finds
//! it, and links with `link.x` and defmt's `defmt.x` — only when building for the MCU.

use std::path::PathBuf;

fn main() {
    let target = std::env::var("TARGET").unwrap_or_default();
    let memory_x = PathBuf::from(std::env::var("CARGO_MANIFEST_DIR").unwrap_or_default()).join("../memory.x");
    println!("cargo:rerun-if-changed={}", memory_x.display());
    println!("cargo:rerun-if-changed=build.rs");
    if !target.starts_with("thumbv") {
        return;
    }
    let out = PathBuf::from(std::env::var("OUT_DIR").unwrap_or_default());
    if let Err(e) = std::fs::copy(&memory_x, out.join("memory.x")) {
        panic!("cannot copy {} to OUT_DIR: {e}", memory_x.display());
    }
    println!("cargo:rustc-link-search={}", out.display());
    println!("cargo:rustc-link-arg-bins=-Tlink.x");
    println!("cargo:rustc-link-arg-bins=-Tdefmt.x");
    // examples/stereo_bench.rs is a second image for the same board.
    println!("cargo:rustc-link-arg-examples=-Tlink.x");
    println!("cargo:rustc-link-arg-examples=-Tdefmt.x");
    // Keep the stack reserve visible to the size check: see `_stack_reserve` in memory.x.
}
