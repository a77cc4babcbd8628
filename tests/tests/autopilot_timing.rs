//! Flying against autopilots whose pose stream has a real autopilot's timing: reports that
//! describe the instant they were sampled (`time_boot_ms` from the autopilot's own boot),
//! arrive late, at 10–50 Hz, with velocities zero or true, and a vehicle that turns at its own
//! rate. The map must stay true: a depth frame's camera pose is the pose of the frame's
//! instant, not "the last pose received".
//!
//! - The in-process flight-stack emulator with that timing (simulated time, fast).
//! - `tests/peer/px4_peer.py`: an independent autopilot written on pymavlink from the MAVLink
//!   spec alone (no code of this project), over UDP on localhost, in wall-clock time. Skipped,
//!   with a message, where `python3` or pymavlink is missing; `.ci/run` installs pymavlink.

use std::io::Read;
use std::net::UdpSocket;
use std::process::{Child, Command, Stdio};
use std::sync::Mutex;

use harmonic_core::signing::SecretKey;
use harmonic_sim::run::sim::{self, Report, SimConfig};
use harmonic_sim::vehicle::autopilot::{MavlinkConfig, MavlinkSpec};
use harmonic_sim::vehicle::flight::EmulatorTiming;
use harmonic_sim::world::scenario::Scenario;

fn apartment() -> Scenario {
    Scenario::builtin("apartment").expect("built-in scenario")
}

/// At most 0.1 % of the reachable free voxels may be held occupied (the bound).
fn assert_map_true(r: &Report, what: &str) {
    let bound = r.reachable_free_voxels / 1000;
    assert!(
        r.free_marked_occupied <= bound,
        "{what}: {} free voxels marked occupied (bound {bound} of {} reachable)",
        r.free_marked_occupied,
        r.reachable_free_voxels
    );
    assert_eq!(r.collisions, 0, "{what}: collisions at {:?}", r.collision_points);
}

#[test]
fn emulator_with_latency_slow_stream_and_a_late_boot_keeps_the_map_true() {
    // 10 Hz, 50 ms late, booted 12.3 s before the run, velocities zero.
    let timing = EmulatorTiming {
        pose_period_ms: 100,
        latency_ms: 50,
        boot_ms: 12_345,
        zero_velocities: true,
    };
    let cfg = SimConfig {
        max_scans: 30,
        mavlink: Some(MavlinkConfig {
            emulator: timing,
            ..MavlinkConfig::default()
        }),
        ..SimConfig::default()
    };
    let r = sim::run(&apartment(), &cfg, |_| {}).expect("run");
    // The planner looks at near frontiers before it flies (the view rule): 30 scans from the
    // apartment's start turn the vehicle many times and move it about a metre.
    assert!(
        r.scans >= 20 && r.path_length_m > 0.5 && r.coverage_free > 0.45,
        "it explored: {} scans, {:.1} m, {:.1} % free coverage",
        r.scans,
        r.path_length_m,
        100.0 * r.coverage_free
    );
    // A few voxels can be wrong with perfect poses too (rays grazing a corner; a transient
    // the next views clear): the bound, not zero. A frame stamped with another instant's pose
    // gives thousands.
    assert_map_true(&r, "emulator, 10 Hz, 50 ms late");
    let mav = r.mavlink.as_ref().unwrap();
    assert!(mav.pose_history.samples > 100, "{:?}", mav.pose_history);
    assert_eq!(mav.pose_history.restarts, 0);
}

/// One peer run at a time: they run in wall-clock time on a shared machine.
static PEER: Mutex<()> = Mutex::new(());

/// python3 with pymavlink, or why not.
fn peer_missing() -> Option<String> {
    match Command::new("python3")
        .args(["-c", "import pymavlink"])
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .status()
    {
        Ok(s) if s.success() => None,
        Ok(_) => Some("pymavlink is not installed (pip install pymavlink)".into()),
        Err(e) => Some(format!("python3 cannot be run: {e}")),
    }
}

/// The peer process, killed if the test ends early.
struct Peer(Child);

impl Drop for Peer {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// Runs the apartment against the peer with `peer_args` for at most `max_scans` scans; the
/// report and the peer's JSON summary.
fn against_peer(peer_args: &[&str], max_scans: u32) -> (Report, serde_json::Value) {
    against_peer_signed(peer_args, max_scans, None)
}

/// [`against_peer`] with MAVLink signing on the explorer's side when `key` is given.
fn against_peer_signed(
    peer_args: &[&str],
    max_scans: u32,
    key: Option<SecretKey>,
) -> (Report, serde_json::Value) {
    let (report, summary) = peer_run(peer_args, max_scans, key);
    (report.expect("run against the peer"), summary)
}

/// [`against_peer_signed`], with the run's error (if any) handed back instead of failing.
fn peer_run(
    peer_args: &[&str],
    max_scans: u32,
    key: Option<SecretKey>,
) -> (Result<Report, sim::SimError>, serde_json::Value) {
    let _serial = PEER.lock().unwrap_or_else(|e| e.into_inner());
    let port = UdpSocket::bind("127.0.0.1:0")
        .and_then(|s| s.local_addr())
        .expect("a free port")
        .port();
    let script = concat!(env!("CARGO_MANIFEST_DIR"), "/peer/px4_peer.py");
    let mut peer = Peer(
        Command::new("python3")
            .arg(script)
            .args(["--connect", &format!("127.0.0.1:{port}"), "--idle-exit-s", "2"])
            .args(peer_args)
            .stdout(Stdio::piped())
            .spawn()
            .expect("start the peer"),
    );
    let cfg = SimConfig {
        max_scans,
        mavlink: Some(MavlinkConfig {
            spec: MavlinkSpec::UdpIn(([127, 0, 0, 1], port).into()),
            signing_key: key,
            ..MavlinkConfig::default()
        }),
        ..SimConfig::default()
    };
    let report = sim::run(&apartment(), &cfg, |_| {});
    // The peer leaves 2 s after the explorer fell silent, with its summary.
    let status = peer.0.wait().expect("peer exit");
    assert!(status.success(), "peer: {status}");
    let mut out = String::new();
    if let Some(mut stdout) = peer.0.stdout.take() {
        stdout.read_to_string(&mut out).expect("peer output");
    }
    let summary: serde_json::Value = serde_json::from_str(out.trim()).expect("peer summary JSON");
    (report, summary)
}

#[test]
fn peer_turning_on_the_spot_adds_no_false_obstacles() {
    if let Some(why) = peer_missing() {
        eprintln!("SKIPPED peer_turning_on_the_spot_adds_no_false_obstacles: {why}");
        return;
    }
    // The vehicle stands still and only turns, 90° between the four look-around scans: views
    // that give no false obstacle with perfect poses, so none at all here.
    let (r, peer) = against_peer(&["--turn-only"], 4);
    assert!(r.scans >= 3, "frames were integrated: {}", r.scans);
    assert!(peer["setpoints"].as_u64().unwrap_or(0) > 10, "{peer}");
    assert_eq!(r.free_marked_occupied, 0, "turning alone added false obstacles");
    assert_map_true(&r, "peer, turning only");
    assert_eq!(r.path_length_m, 0.0, "the vehicle stood still");
}

#[test]
fn signed_mavlink_with_pymavlink_both_ways() {
    if let Some(why) = peer_missing() {
        eprintln!("SKIPPED signed_mavlink_with_pymavlink_both_ways: {why}");
        return;
    }
    // pymavlink signs what the peer sends and drops unsigned frames; the explorer signs with
    // the same key and acts only on signed frames. Both sides must accept each other's.
    let key = [0x3c_u8; 32];
    let hex: String = key.iter().map(|b| format!("{b:02x}")).collect();
    // The peer also plays an intruder: unsigned COMMAND_LONG (land) and SET_MODE frames, which
    // must be refused and counted, and change nothing.
    let (r, peer) = against_peer_signed(
        &["--turn-only", "--key", &hex, "--inject-unsigned", "2"],
        4,
        Some(SecretKey::new(key)),
    );
    assert!(r.scans >= 3, "frames were integrated: {}", r.scans);
    // Our signatures pass pymavlink's check: setpoints arrived, none refused or bad.
    assert!(peer["setpoints"].as_u64().unwrap_or(0) > 10, "{peer}");
    assert_eq!(peer["unsigned_refused"].as_u64(), Some(0), "{peer}");
    assert_eq!(peer["bad_signatures"].as_u64(), Some(0), "{peer}");
    // pymavlink's pass ours: poses arrived and were used, nothing refused.
    let signing = r
        .mavlink
        .as_ref()
        .and_then(|m| m.bridge_signing)
        .expect("signing counters");
    assert!(signing.accepted > 20, "{signing:?}");
    let injected = peer["unsigned_injected"].as_u64().unwrap_or(0);
    assert!(injected >= 2, "{peer}");
    assert_eq!(
        (
            u64::from(signing.unsigned),
            signing.bad_signature,
            signing.replayed,
            signing.stale
        ),
        (injected, 0, 0, 0),
        "{signing:?}"
    );
    assert_map_true(&r, "peer, signed");
}

#[test]
fn a_peer_with_another_key_is_never_obeyed_and_never_believed() {
    if let Some(why) = peer_missing() {
        eprintln!("SKIPPED a_peer_with_another_key_is_never_obeyed_and_never_believed: {why}");
        return;
    }
    // The explorer signs with one key, the pymavlink peer with another: the explorer acts on
    // none of the peer's frames, so it never has a pose to plan from and stops with that error
    // instead of flying; and since udpin answers only the autopilot's admitted frames, it
    // never even answers the peer (nothing to obey). The peer hears nothing, so it leaves at
    // its time limit.
    let (run, peer) = peer_run(
        &["--key", &"11".repeat(32), "--max-s", "25"],
        4,
        Some(SecretKey::new([0x22; 32])),
    );
    let err = run.expect_err("no pose it can trust: the run must not go on");
    assert!(format!("{err:?}").contains("NoPose"), "{err:?}");
    assert_eq!(peer["setpoints"].as_u64(), Some(0), "{peer}");
    assert_eq!(peer["good_signatures"].as_u64(), Some(0), "{peer}");
    assert!(peer["poses_sent"].as_u64().unwrap_or(0) > 10, "{peer}");
}

#[test]
fn peer_flights_with_latency_and_odd_stream_rates_keep_the_map_true() {
    if let Some(why) = peer_missing() {
        eprintln!("SKIPPED peer_flights_with_latency_and_odd_stream_rates_keep_the_map_true: {why}");
        return;
    }
    for (what, args) in [
        (
            "10 Hz, 50 ms latency, velocities zero, 180°/s",
            &["--rate", "10", "--latency-ms", "50", "--yaw-rate-deg", "180"][..],
        ),
        (
            "50 Hz, velocities truthful, 45°/s",
            &["--rate", "50", "--velocities", "truthful", "--yaw-rate-deg", "45"][..],
        ),
    ] {
        let (r, peer) = against_peer(args, 14);
        assert!(
            r.scans >= 8 && r.path_length_m > 0.2,
            "{what}: it explored: {} scans, {:.1} m",
            r.scans,
            r.path_length_m
        );
        assert!(peer["poses_sent"].as_u64().unwrap_or(0) > 100, "{what}: {peer}");
        assert_map_true(&r, what);
    }
}
