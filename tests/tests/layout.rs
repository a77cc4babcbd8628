//! The host simulator's layout: no module imports another around a loop, between files or
//! between its stage folders (`scripts/module_cycles.py`; python3, standard library only).

use std::path::Path;
use std::process::Command;

#[test]
fn host_sim_has_no_import_cycles() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let out = Command::new("python3")
        .arg(root.join("scripts/module_cycles.py"))
        .current_dir(&root)
        .output()
        .expect("python3 runs scripts/module_cycles.py");
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "import cycles in host-sim:\n{text}{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(text.contains("no cycles"), "{text}");
}
