//! Fuzz harness for the MAVLink input side: [`MavlinkDecoder`] and [`Bridge::handle`],
//! [`Bridge::pose`], [`Bridge::poll`] and the goal/hold calls, with arbitrary bytes and times.
//! Shared by `fuzz/fuzz_targets/mavlink_input.rs` and `tests/tests/fuzz_harness.rs`.
//!
//! Input: a script of operations. Each takes one selector byte and its fields: raw line bytes;
//! LOCAL_POSITION_NED, ATTITUDE, ODOMETRY, HEARTBEAT or an operator's COMMAND_LONG with fuzzed
//! values and sender ids, encoded as valid MAVLink 2 frames (so the fuzzer gets past the
//! checksum) and split across two pushes; clock steps (forward, or to any u64); `poll`,
//! `pose`, `set_target`, `apply`, `return_home` and `arrived_home`. The oracle checks:
//!
//! - no panic;
//! - a pose the bridge hands out is finite, inside [`BridgeConfig::max_position_m`] and fresh;
//! - every setpoint it holds or sends is finite;
//! - every operator command addressed to the bridge is accepted or refused, and answered or
//!   counted as dropped;
//! - the decoder yields the same messages when all the bytes are pushed at once.

use harmonic_core::explore::{Fault, Goal, PlanOutcome};
use harmonic_core::map::VoxelIndex;
use harmonic_core::mavlink::common::{
    MavCmd, MavFrame, ATTITUDE_DATA, COMMAND_LONG_DATA, HEARTBEAT_DATA, LOCAL_POSITION_NED_DATA,
    ODOMETRY_DATA,
};
use harmonic_core::mavlink::{encode_v2, Bridge, BridgeConfig, MavHeader, MavMessage, MavlinkDecoder};
use nalgebra::Point3;

// The crate that includes this harness also includes `input.rs` as `crate::input`.
use crate::input::{Floats, Input};

/// Plausible floats here: multiples of 0.25 around 0.
const FLOATS: Floats = Floats {
    raw: 24,
    step: 0.25,
    offset: -32.0,
};

/// Runs the harness on one input. Panics only when the oracle finds a bug.
pub fn run(data: &[u8]) {
    let mut input = Input(data);
    let config = BridgeConfig::default();
    let mut bridge = match Bridge::new(config) {
        Ok(b) => b,
        Err(e) => panic!("default config refused: {e:?}"),
    };
    let mut decoder = MavlinkDecoder::new();
    let mut line = Vec::new();
    let mut decoded = Vec::new();
    let mut now: u64 = 0;
    let mut seq = 0u8;
    let mut scratch = [0u8; 512];

    for _ in 0..256 {
        if input.is_empty() {
            break;
        }
        let op = input.u8() % 14;
        let mut bytes = Vec::new();
        let message = match op {
            0 => {
                let n = usize::from(input.u8() % 64);
                bytes.extend((0..n).map(|_| input.u8()));
                None
            }
            1 => Some(MavMessage::LOCAL_POSITION_NED(LOCAL_POSITION_NED_DATA {
                time_boot_ms: input.u32(),
                x: input.float(FLOATS),
                y: input.float(FLOATS),
                z: input.float(FLOATS),
                ..LOCAL_POSITION_NED_DATA::DEFAULT
            })),
            2 => Some(MavMessage::ATTITUDE(ATTITUDE_DATA {
                roll: input.float(FLOATS),
                pitch: input.float(FLOATS),
                yaw: input.float(FLOATS),
                ..ATTITUDE_DATA::DEFAULT
            })),
            3 => {
                let frame_id = match input.u8() % 4 {
                    0 => MavFrame::MAV_FRAME_LOCAL_FRD,
                    _ => MavFrame::MAV_FRAME_LOCAL_NED,
                };
                let position = [input.float(FLOATS), input.float(FLOATS), input.float(FLOATS)];
                let mut q = [
                    input.float(FLOATS),
                    input.float(FLOATS),
                    input.float(FLOATS),
                    input.float(FLOATS),
                ];
                if input.u8() % 2 == 0 {
                    let n = q.iter().map(|c| c * c).sum::<f32>().sqrt();
                    q = q.map(|c| c / n);
                }
                Some(MavMessage::ODOMETRY(ODOMETRY_DATA {
                    x: position[0],
                    y: position[1],
                    z: position[2],
                    q,
                    frame_id,
                    child_frame_id: MavFrame::MAV_FRAME_BODY_FRD,
                    ..ODOMETRY_DATA::DEFAULT
                }))
            }
            4 => Some(MavMessage::HEARTBEAT(HEARTBEAT_DATA::DEFAULT)),
            5 => {
                now = now.saturating_add(u64::from(input.u16()));
                None
            }
            6 => {
                now = input.u64();
                None
            }
            7 => {
                poll(&mut bridge, now, &mut scratch);
                None
            }
            8 => {
                check_pose(&bridge, &config, now);
                None
            }
            9 => {
                let position = Point3::new(input.float(FLOATS), input.float(FLOATS), input.float(FLOATS));
                let yaw = input.float(FLOATS);
                let _ = bridge.set_target(position, yaw);
                None
            }
            10 => {
                let outcome = match input.u8() % 4 {
                    0 => PlanOutcome::Complete,
                    1 => PlanOutcome::Hold(Fault::VehicleNotFree),
                    2 => PlanOutcome::Hold(Fault::VehicleOutsideGrid),
                    _ => PlanOutcome::Goal(Goal {
                        position: Point3::new(input.float(FLOATS), input.float(FLOATS), input.float(FLOATS)),
                        yaw: input.float(FLOATS),
                        frontier: VoxelIndex::new(0, 0, 0),
                        escape: false,
                    }),
                };
                harmonic_core::companion::steer(&mut bridge, &outcome);
                None
            }
            12 => {
                let command = [
                    MavCmd::MAV_CMD_MISSION_START,
                    MavCmd::MAV_CMD_DO_PAUSE_CONTINUE,
                    MavCmd::MAV_CMD_NAV_LOITER_UNLIM,
                    MavCmd::MAV_CMD_NAV_RETURN_TO_LAUNCH,
                    MavCmd::MAV_CMD_NAV_LAND,
                ][usize::from(input.u8() % 5)];
                // Mostly to the bridge (1, 191), sometimes to any component or anyone.
                let (target_system, target_component) = match input.u8() % 4 {
                    0 => (input.u8(), input.u8()),
                    1 => (1, 0),
                    _ => (1, 191),
                };
                Some(MavMessage::COMMAND_LONG(COMMAND_LONG_DATA {
                    param1: input.float(FLOATS),
                    command,
                    target_system,
                    target_component,
                    ..COMMAND_LONG_DATA::DEFAULT
                }))
            }
            13 => {
                if input.u8() % 2 == 0 {
                    bridge.return_home();
                } else {
                    bridge.arrived_home();
                }
                None
            }
            _ => {
                bridge.hold();
                None
            }
        };
        if let Some(message) = message {
            // Mostly from the autopilot (1, 1), sometimes from anyone.
            let header = match input.u8() % 8 {
                0 => MavHeader {
                    system_id: u32::from(input.u8()),
                    component_id: input.u8(),
                    sequence: seq,
                },
                _ => MavHeader {
                    system_id: 1,
                    component_id: 1,
                    sequence: seq,
                },
            };
            seq = seq.wrapping_add(1);
            if let Ok(n) = encode_v2(&header, &message, &mut scratch) {
                bytes.extend_from_slice(&scratch[..n]);
            }
        }
        if !bytes.is_empty() {
            let cut = usize::from(input.u8()) % (bytes.len() + 1);
            line.extend_from_slice(&bytes);
            for part in [&bytes[..cut], &bytes[cut..]] {
                decoder.push(part, |header, message| {
                    decoded.push(format!("{header:?} {message:?}"));
                    let _ = bridge.handle(now, header, message);
                });
            }
        }
        if let Some(setpoint) = bridge.setpoint() {
            assert!(
                setpoint.position.coords.iter().all(|c| c.is_finite()) && setpoint.yaw.is_finite(),
                "non-finite setpoint held: {setpoint:?}"
            );
        }
    }
    poll(&mut bridge, now, &mut scratch);
    check_pose(&bridge, &config, now);
    let c = bridge.counters();
    assert_eq!(
        c.commands_received,
        c.commands_accepted + c.commands_refused,
        "a command neither accepted nor refused: {c:?}"
    );
    assert_eq!(
        c.commands_received,
        c.command_acks_sent + c.command_acks_dropped,
        "a command neither answered nor counted as dropped (all polled): {c:?}"
    );

    let mut again = MavlinkDecoder::new();
    let mut decoded_again = Vec::new();
    again.push(&line, |header, message| {
        decoded_again.push(format!("{header:?} {message:?}"))
    });
    assert_eq!(
        decoded, decoded_again,
        "the slicing changed what the decoder yields"
    );
    assert_eq!(
        decoder.counters(),
        again.counters(),
        "the slicing changed the decoder counters"
    );
}

/// Polls and checks everything sent: finite setpoints, encodable messages.
fn poll(bridge: &mut Bridge, now: u64, scratch: &mut [u8]) {
    bridge.poll(now, |header, message| {
        if let MavMessage::SET_POSITION_TARGET_LOCAL_NED(sp) = message {
            assert!(
                [sp.x, sp.y, sp.z, sp.yaw].iter().all(|c| c.is_finite()),
                "non-finite setpoint sent: {sp:?}"
            );
        }
        assert!(
            encode_v2(header, message, scratch).is_ok(),
            "outgoing message does not encode"
        );
    });
}

/// A pose handed out is finite, within the position limit and not older than the timeout.
fn check_pose(bridge: &Bridge, config: &BridgeConfig, now: u64) {
    if let Ok(pose) = bridge.pose(now) {
        let p = pose.position.coords;
        assert!(
            p.iter().all(|c| c.is_finite()) && pose.yaw.is_finite(),
            "non-finite pose: {pose:?}"
        );
        assert!(
            p.iter().all(|c| c.abs() <= config.max_position_m),
            "pose beyond the position limit: {pose:?}"
        );
        assert!(
            pose.age_ms <= u64::from(config.pose_timeout_ms),
            "stale pose handed out"
        );
        let a = pose.attitude;
        assert!(
            a.rotation.quaternion().coords.iter().all(|c| c.is_finite()),
            "non-finite attitude"
        );
    }
}
