//! The layout of the three crates: no module imports another around a loop, between files or
//! between top-level folders, in core, firmware or host-sim (`scripts/module_cycles.py --all`;
//! python3, standard library only).

use std::path::Path;
use std::process::Command;

#[test]
fn no_crate_has_import_cycles() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let out = Command::new("python3")
        .arg(root.join("scripts/module_cycles.py"))
        .arg("--all")
        .current_dir(&root)
        .output()
        .expect("python3 runs scripts/module_cycles.py");
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "import cycles:\n{text}{}",
        String::from_utf8_lossy(&out.stderr)
    );
    for krate in ["core:", "firmware:", "host-sim:"] {
        assert!(text.contains(krate), "{krate} not checked:\n{text}");
    }
    assert!(text.contains("no cycles"), "{text}");
}
