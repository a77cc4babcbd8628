//! `stereo-render` and `stereo` as a user meets them: PNG pairs in, disparity (.npy / .pfm)
//! out, Middlebury rates printed against ground truth.

use std::path::PathBuf;
use std::process::Command;

fn sim() -> Command {
    Command::new(env!("CARGO_BIN_EXE_harmonic-sim"))
}

fn scratch_dir(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("harmonic-stereo-cli-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

fn run(cmd: &mut Command) -> String {
    let out = cmd.output().unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout).into_owned();
    assert!(
        out.status.success(),
        "{stdout}{}",
        String::from_utf8_lossy(&out.stderr)
    );
    stdout
}

#[test]
fn rendered_pair_round_trips_through_the_matcher() {
    let dir = scratch_dir("round-trip");
    let d = |f: &str| dir.join(f).display().to_string();
    run(sim().args(["stereo-render", "--scenario", "apartment", "--out", &d("")]));
    for f in [
        "left.png",
        "right.png",
        "gt.pfm",
        "gt.npy",
        "mask.png",
        "calib.txt",
    ] {
        assert!(dir.join(f).is_file(), "{f} missing");
    }
    // npy out, PFM ground truth with the non-occlusion mask.
    let text = run(sim().args([
        "stereo",
        "--left",
        &d("left.png"),
        "--right",
        &d("right.png"),
        "--gt",
        &d("gt.pfm"),
        "--mask",
        &d("mask.png"),
        "--out",
        &d("disp.npy"),
    ]));
    let rates = text
        .lines()
        .find(|l| l.starts_with("bad-1.0"))
        .unwrap_or_else(|| panic!("{text}"));
    assert!(rates.contains("bad-2.0") && rates.contains("density"), "{rates}");
    let bytes = std::fs::read(dir.join("disp.npy")).unwrap();
    let (h, w, disparity) = harmonic_sim::io::npy::read_f32_image(&bytes).unwrap();
    assert_eq!((h, w), (200, 200));
    let valid = disparity.iter().filter(|d| d.is_finite()).count();
    assert!(valid > 20_000 && valid < 40_000, "{valid}");
    assert!(disparity
        .iter()
        .all(|d| d.is_infinite() || (0.0..64.0).contains(d)));
    // PFM out, npy ground truth without a mask: the same disparities.
    let text = run(sim().args([
        "stereo",
        "--left",
        &d("left.png"),
        "--right",
        &d("right.png"),
        "--gt",
        &d("gt.npy"),
        "--out",
        &d("disp.pfm"),
    ]));
    assert!(text.contains("ground-truth pixels"), "{text}");
    let (pw, ph, pfm) = harmonic_sim::sensors::stereo::read_pfm(&dir.join("disp.pfm")).unwrap();
    assert_eq!((pw, ph), (200, 200));
    assert_eq!(pfm.len(), disparity.len());
    assert!(pfm
        .iter()
        .zip(&disparity)
        .all(|(a, b)| a == b || (a.is_infinite() && b.is_infinite())));
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn stereo_input_errors_exit_with_code_2() {
    let dir = scratch_dir("errors");
    let d = |f: &str| dir.join(f).display().to_string();
    run(sim().args(["stereo-render", "--out", &d(""), "--scale", "1"]));
    // An unknown output format, a missing file, an even window.
    for args in [
        vec!["--out", &d("disp.txt")],
        vec!["--out", &d("disp.pfm"), "--gt", &d("nope.pfm")],
        vec!["--out", &d("disp.pfm"), "--window", "8"],
    ] {
        let out = sim()
            .args(["stereo", "--left", &d("left.png"), "--right", &d("right.png")])
            .args(&args)
            .output()
            .unwrap();
        assert_eq!(out.status.code(), Some(2), "{args:?}");
        assert!(!out.stderr.is_empty());
    }
    let _ = std::fs::remove_dir_all(&dir);
}
