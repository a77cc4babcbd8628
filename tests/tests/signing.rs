//! MAVLink 2 signing end to end against the in-process flight emulator (`--mavlink-key`): a
//! signed run flies exactly as an unsigned one, and neither side refuses a frame. Kept out of
//! `links.rs`, whose UDP tests run on the wall clock and must not share the CPU with these runs.

use harmonic_core::signing::SecretKey;
use harmonic_sim::autopilot::MavlinkConfig;
use harmonic_sim::scenario::Scenario;
use harmonic_sim::sim::{self, Report, SimConfig};

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
