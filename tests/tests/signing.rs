//! MAVLink 2 signing end to end against the in-process flight emulator (`--mavlink-key`): a
//! signed run flies exactly as an unsigned one, neither side refuses a frame, and pymavlink
//! verifies every signature in the run's `.tlog` (`tests/peer/tlog_signatures.py`). Kept out of
//! `links.rs`, whose UDP tests run on the wall clock and must not share the CPU with these runs.

use std::process::{Command, Stdio};

use harmonic_core::signing::SecretKey;
use harmonic_sim::run::sim::{self, Report, SimConfig};
use harmonic_sim::vehicle::autopilot::MavlinkConfig;
use harmonic_sim::world::scenario::Scenario;

fn apartment() -> Scenario {
    Scenario::builtin("apartment").unwrap()
}

/// A short run against the emulator over MAVLink with signing set up by `configure`.
fn signed_emulator_run(configure: impl FnOnce(&mut MavlinkConfig)) -> Report {
    let mut mavlink = MavlinkConfig {
        signing_key: Some(SecretKey::new([0x5a; 32])),
        ..MavlinkConfig::default()
    };
    configure(&mut mavlink);
    let cfg = SimConfig {
        max_scans: 8,
        look_around: 1,
        mavlink: Some(mavlink),
        ..SimConfig::default()
    };
    sim::run(&apartment(), &cfg, |_| {}).expect("run against the emulator")
}

#[test]
fn signed_mavlink_flies_as_unsigned_and_nothing_unsigned_is_acted_on() {
    let signed = signed_emulator_run(|_| {});
    let plain = signed_emulator_run(|m| m.signing_key = None);
    // The same flight: signing changes the bytes, not what is flown.
    assert_eq!(signed.path_length_m, plain.path_length_m);
    assert!(signed.path_length_m > 0.2, "{}", signed.path_length_m);
    let mav = signed.mavlink.as_ref().unwrap();
    let (bridge, emulator) = (mav.bridge_signing.unwrap(), mav.emulator_signing.unwrap());
    assert!(
        bridge.accepted > 50 && emulator.accepted > 50,
        "{bridge:?} {emulator:?}"
    );
    for c in [bridge, emulator] {
        assert_eq!(
            (c.unsigned, c.bad_signature, c.replayed, c.stale, c.malformed),
            (0, 0, 0, 0, 0),
            "{c:?}"
        );
    }
    assert!(plain.mavlink.as_ref().unwrap().bridge_signing.is_none());
}

#[test]
fn every_frame_the_companion_logs_is_signed_and_pymavlink_verifies_it() {
    let ready = Command::new("python3")
        .args(["-c", "import pymavlink"])
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .status();
    if !ready.is_ok_and(|s| s.success()) {
        eprintln!("SKIPPED: python3 with pymavlink is needed (pip install pymavlink)");
        return;
    }
    let dir = std::env::temp_dir().join(format!("harmonic-signing-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let tlog = dir.join("run.tlog");
    let run = signed_emulator_run(|m| m.tlog = Some(tlog.clone()));
    assert!(run.path_length_m > 0.2);
    let check = |key: &str, component: &str| -> serde_json::Value {
        let script = concat!(env!("CARGO_MANIFEST_DIR"), "/peer/tlog_signatures.py");
        let out = Command::new("python3")
            .arg(script)
            .arg(&tlog)
            .args(["--key", key, "--component", component])
            .output()
            .expect("run the checker");
        assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
        serde_json::from_slice(&out.stdout).expect("JSON counts")
    };
    let key = "5a".repeat(32);
    // The companion (component 191): every frame MAVLink 2, signed, verified.
    let ours = check(&key, "191");
    let frames = ours["frames"].as_u64().unwrap();
    assert!(frames > 50, "{ours}");
    assert_eq!(ours["good_signatures"].as_u64(), Some(frames), "{ours}");
    for k in ["mavlink1", "unsigned", "bad_signatures"] {
        assert_eq!(ours[k].as_u64(), Some(0), "{k}: {ours}");
    }
    // The emulator's frames are signed with the same key; another key verifies none.
    let theirs = check(&key, "1");
    assert_eq!(theirs["good_signatures"], theirs["frames"], "{theirs}");
    let wrong = check(&"5b".repeat(32), "191");
    assert_eq!(wrong["bad_signatures"].as_u64(), Some(frames), "{wrong}");
    let _ = std::fs::remove_dir_all(&dir);
}
