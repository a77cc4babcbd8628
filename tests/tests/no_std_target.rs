//! The core is `no_std` and allocation-free: it must build for the reference MCU target.
//! (Building it is the proof: the target has no `std`, and the core links no `alloc`.)

use std::process::Command;

const TARGET: &str = "thumbv7em-none-eabihf";

#[test]
fn core_builds_for_cortex_m4f() {
    let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
    let installed = Command::new("rustup")
        .args(["target", "list", "--installed"])
        .output();
    let have_target = installed
        .as_ref()
        .is_ok_and(|o| String::from_utf8_lossy(&o.stdout).contains(TARGET));
    if !have_target {
        eprintln!("installing the {TARGET} target with rustup (one-time)");
        let ok = Command::new("rustup")
            .args(["target", "add", TARGET])
            .status()
            .is_ok_and(|s| s.success());
        assert!(
            ok,
            "the {TARGET} target is missing and `rustup target add {TARGET}` failed"
        );
    }
    // A separate target directory: the outer `cargo test` may still hold the workspace's lock.
    let target_dir = concat!(env!("CARGO_MANIFEST_DIR"), "/../target/no-std-check");
    let out = Command::new(cargo)
        .args([
            "build",
            "-p",
            "harmonic-core",
            "--release",
            "--target",
            TARGET,
            "--target-dir",
            target_dir,
        ])
        .output()
        .expect("run cargo");
    assert!(
        out.status.success(),
        "cross build failed:\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
}
