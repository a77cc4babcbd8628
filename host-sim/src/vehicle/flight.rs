//! A flight-stack emulator: the part of PX4 or ArduPilot the core's MAVLink bridge talks to.
//!
//! [`FlightEmulator`] sits at the other end of the bridge's wire. It
//!
//! - decodes the bridge's MAVLink 2 bytes with the core's [`MavlinkDecoder`];
//! - keeps the latest SET_POSITION_TARGET_LOCAL_NED as the vehicle's setpoint, converted into
//!   the map frame with [`ned_to_map`] — only setpoints in `MAV_FRAME_LOCAL_NED` whose type
//!   mask asks for position and yaw (velocity and acceleration ignored) are taken; anything
//!   else is counted in [`FlightCounters::setpoints_rejected`] and ignored, as PX4 would not
//!   fly it in offboard position mode;
//! - measures the setpoint stream: PX4 leaves offboard mode when setpoints arrive slower than
//!   2 Hz, so every gap longer than [`OFFBOARD_TIMEOUT_MS`] is counted;
//! - collects the STATUSTEXTs it receives;
//! - streams LOCAL_POSITION_NED and ATTITUDE of the simulated vehicle's true pose every
//!   [`EmulatorTiming::pose_period_ms`] of simulated time (default [`POSE_PERIOD_MS`], 20 Hz),
//!   and with [`FlightEmulator::with_odometry`] ODOMETRY as well (PX4 streams all three), as
//!   system [`DEFAULT_SYSTEM_ID`], component [`AUTOPILOT_COMPONENT_ID`] — the autopilot the
//!   bridge listens to by default — encoded with [`encode_v2`]. Velocities (and the yaw rate)
//!   are the change of the pose since the last report, as an estimator would give them, or zero
//!   ([`EmulatorTiming::zero_velocities`]); roll and pitch are level.
//!
//! Its timing follows a real autopilot's ([`EmulatorTiming`]): `time_boot_ms` counts from the
//! emulator's own boot ([`EmulatorTiming::boot_ms`] before the run started), is the instant the
//! pose was *sampled*, and a report leaves [`EmulatorTiming::latency_ms`] after that instant.
//! Yaw is NED (0 = North, clockwise positive, (−π, π]), as in the MAVLink spec. A companion
//! that stamps camera frames with "the last pose received" instead of the pose of the frame's
//! instant smears its map against it, as it would against PX4.
//!
//! The emulator does not fly: the simulator moves the vehicle towards [`FlightEmulator::setpoint`]
//! and hands the resulting pose to [`FlightEmulator::poll`].

use harmonic_core::mavlink::common::{
    MavFrame, MavModeFlag, MavState, MavType, ATTITUDE_DATA, HEARTBEAT_DATA, LOCAL_POSITION_NED_DATA,
    ODOMETRY_DATA, SET_POSITION_TARGET_LOCAL_NED_DATA,
};
use harmonic_core::mavlink::{
    encode_v2, map_to_ned, ned_to_map, DecoderCounters, MavHeader, MavMessage, MavlinkDecoder,
    PositionTargetTypemask, AUTOPILOT_COMPONENT_ID, DEFAULT_SYSTEM_ID, MAX_FRAME_LEN,
};
use harmonic_core::signing::{SecretKey, Signer, Verifier, VerifierCounters};
use nalgebra::Point3;
use serde::Serialize;

/// Milliseconds between two pose reports (LOCAL_POSITION_NED + ATTITUDE): 50 ms, 20 Hz.
pub const POSE_PERIOD_MS: u64 = 50;
/// PX4 leaves offboard mode when no setpoint arrived for this long (2 Hz).
pub const OFFBOARD_TIMEOUT_MS: u64 = 500;
/// Milliseconds between the emulator's HEARTBEATs (1 Hz).
pub const HEARTBEAT_PERIOD_MS: u64 = 1000;

/// When and how the emulator reports the pose. [`Default`]: 20 Hz, no latency, booted at the
/// start of the run, velocities reported.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct EmulatorTiming {
    /// Milliseconds between pose reports (≥ 1). The emulator samples the vehicle when it is
    /// polled, so a period shorter than the caller's time step runs at the step's rate.
    pub pose_period_ms: u64,
    /// Milliseconds from sampling a pose to sending its report (estimator and link delay).
    pub latency_ms: u64,
    /// The emulator's `time_boot_ms` at simulated time 0: the autopilot was switched on this
    /// long before the run.
    pub boot_ms: u64,
    /// Report velocities and the yaw rate as zero, as autopilots that do not fill them in do.
    pub zero_velocities: bool,
}

impl Default for EmulatorTiming {
    fn default() -> Self {
        Self {
            pose_period_ms: POSE_PERIOD_MS,
            latency_ms: 0,
            boot_ms: 0,
            zero_velocities: false,
        }
    }
}

/// Type-mask bits that must be set for a position + yaw setpoint: velocity and acceleration
/// ignored.
const MUST_IGNORE: PositionTargetTypemask = PositionTargetTypemask::POSITION_TARGET_TYPEMASK_VX_IGNORE
    .union(PositionTargetTypemask::POSITION_TARGET_TYPEMASK_VY_IGNORE)
    .union(PositionTargetTypemask::POSITION_TARGET_TYPEMASK_VZ_IGNORE)
    .union(PositionTargetTypemask::POSITION_TARGET_TYPEMASK_AX_IGNORE)
    .union(PositionTargetTypemask::POSITION_TARGET_TYPEMASK_AY_IGNORE)
    .union(PositionTargetTypemask::POSITION_TARGET_TYPEMASK_AZ_IGNORE);
/// Type-mask bits that must be clear: position and yaw are used.
const MUST_USE: PositionTargetTypemask = PositionTargetTypemask::POSITION_TARGET_TYPEMASK_X_IGNORE
    .union(PositionTargetTypemask::POSITION_TARGET_TYPEMASK_Y_IGNORE)
    .union(PositionTargetTypemask::POSITION_TARGET_TYPEMASK_Z_IGNORE)
    .union(PositionTargetTypemask::POSITION_TARGET_TYPEMASK_YAW_IGNORE);

/// A setpoint as the emulator flies it, map frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FlightSetpoint {
    /// Target position, map frame, metres.
    pub position: Point3<f32>,
    /// Target yaw about map z, radians, counter-clockwise from +x.
    pub yaw: f32,
    /// Simulated time it arrived, ms.
    pub at_ms: u64,
}

/// Counts of everything the emulator received and sent.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize)]
pub struct FlightCounters {
    /// SET_POSITION_TARGET_LOCAL_NEDs accepted as the setpoint.
    pub setpoints_received: u32,
    /// SET_POSITION_TARGET_LOCAL_NEDs ignored: another frame than `MAV_FRAME_LOCAL_NED`, a
    /// type mask that is not position + yaw, another target, or values that are not finite.
    pub setpoints_rejected: u32,
    /// Gaps longer than [`OFFBOARD_TIMEOUT_MS`] between two accepted setpoints (each would
    /// have dropped PX4 out of offboard mode).
    pub setpoint_gaps: u32,
    /// The longest gap between two accepted setpoints, ms.
    pub max_setpoint_gap_ms: u64,
    /// HEARTBEATs received from the companion.
    pub heartbeats_received: u32,
    /// STATUSTEXTs received.
    pub status_texts_received: u32,
    /// Other messages received, ignored.
    pub other_received: u32,
    /// LOCAL_POSITION_NEDs sent.
    pub local_positions_sent: u32,
    /// ATTITUDEs sent.
    pub attitudes_sent: u32,
    /// ODOMETRYs sent (only [`FlightEmulator::with_odometry`]).
    pub odometries_sent: u32,
    /// HEARTBEATs sent.
    pub heartbeats_sent: u32,
    /// Bytes sent.
    pub bytes_sent: u64,
}

/// MAVLink 2 signing of one end of a link ([`harmonic_core::signing`]): every frame it sends is
/// signed with the shared key, and a frame it receives is acted on only if the key signed it,
/// with a timestamp newer than the last on its stream.
#[derive(Debug, Clone)]
pub struct LinkSigning {
    signer: Signer,
    verifier: Verifier<16>,
    /// MAVLink signing time (10 µs since 2015-01-01 UTC) at simulated time 0.
    base: u64,
}

/// 2015-01-01 00:00 UTC, seconds since the Unix epoch: MAVLink signing's time origin.
const SIGNING_EPOCH_UNIX_S: u64 = 1_420_070_400;

impl LinkSigning {
    /// Signing with `key` on link `link_id`; timestamps count from the wall clock now.
    pub fn new(key: SecretKey, link_id: u8) -> Self {
        let now = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .unwrap_or_default();
        let since_2015_us = now
            .as_micros()
            .saturating_sub(u128::from(SIGNING_EPOCH_UNIX_S) * 1_000_000);
        Self {
            signer: Signer::new(key.clone(), link_id),
            verifier: Verifier::new(key),
            base: u64::try_from(since_2015_us / 10).unwrap_or(u64::MAX),
        }
    }

    /// Signs the unsigned frame in `frame[..len]` at simulated time `now_ms`; returns its new
    /// length (the frame unchanged if it cannot be signed).
    pub fn sign(&mut self, frame: &mut [u8], len: usize, now_ms: u64) -> usize {
        let stamp = self.base.saturating_add(now_ms.saturating_mul(100));
        self.signer.sign(frame, len, stamp).unwrap_or(len)
    }

    /// Whether a received frame may be acted on (counted either way).
    pub fn admits(&mut self, frame: &[u8]) -> bool {
        self.verifier.check(frame).is_ok()
    }

    /// What the verifier accepted and refused.
    pub fn counters(&self) -> VerifierCounters {
        *self.verifier.counters()
    }
}

/// The emulated autopilot. See the [module documentation](self).
#[derive(Debug)]
pub struct FlightEmulator {
    decoder: MavlinkDecoder,
    setpoint: Option<FlightSetpoint>,
    next_pose_ms: Option<u64>,
    next_heartbeat_ms: Option<u64>,
    sequence: u8,
    counters: FlightCounters,
    status_texts: Vec<String>,
    odometry: bool,
    /// The last reported pose (NED position, NED yaw, ms), for velocities.
    last_report: Option<([f32; 3], f32, u64)>,
    timing: EmulatorTiming,
    /// Encoded pose reports waiting out their latency: (when they leave, ms; bytes).
    in_flight: std::collections::VecDeque<(u64, Vec<u8>)>,
    /// MAVLink 2 signing: sign what it sends, act only on what the key signed.
    signing: Option<LinkSigning>,
    /// The time of the latest [`poll`](Self::poll), ms: the signing time of what it sends.
    clock_ms: u64,
}

impl Default for FlightEmulator {
    fn default() -> Self {
        Self::new()
    }
}

impl FlightEmulator {
    /// An emulator with no setpoint yet.
    pub fn new() -> Self {
        Self {
            decoder: MavlinkDecoder::new(),
            setpoint: None,
            next_pose_ms: None,
            next_heartbeat_ms: None,
            sequence: 0,
            counters: FlightCounters::default(),
            status_texts: Vec::new(),
            odometry: false,
            last_report: None,
            timing: EmulatorTiming::default(),
            in_flight: std::collections::VecDeque::new(),
            signing: None,
            clock_ms: 0,
        }
    }

    /// Reports the pose with `timing` (rate, latency, clock, velocities); a zero period is
    /// taken as 1 ms.
    pub fn with_timing(mut self, timing: EmulatorTiming) -> Self {
        self.timing = EmulatorTiming {
            pose_period_ms: timing.pose_period_ms.max(1),
            ..timing
        };
        self
    }

    /// How the pose is reported.
    pub fn timing(&self) -> &EmulatorTiming {
        &self.timing
    }

    /// Also streams ODOMETRY (position, attitude quaternion, body-frame velocities) with every
    /// pose report, as PX4 does.
    pub fn with_odometry(mut self, odometry: bool) -> Self {
        self.odometry = odometry;
        self
    }

    /// Signs every frame it sends with `key` and ignores (counts) every frame the key did not
    /// sign, as an autopilot with signing required does.
    pub fn with_signing(mut self, key: SecretKey) -> Self {
        self.signing = Some(LinkSigning::new(key, 0));
        self
    }

    /// What its signing accepted and refused (`None` without signing).
    pub fn signing_counters(&self) -> Option<VerifierCounters> {
        self.signing.as_ref().map(LinkSigning::counters)
    }

    /// The latest accepted setpoint, map frame; `None` before the first.
    pub fn setpoint(&self) -> Option<FlightSetpoint> {
        self.setpoint
    }

    /// Counts of everything received and sent.
    pub fn counters(&self) -> &FlightCounters {
        &self.counters
    }

    /// Counts of the decoder of the incoming bytes.
    pub fn decoder_counters(&self) -> &DecoderCounters {
        self.decoder.counters()
    }

    /// The STATUSTEXTs received, in order.
    pub fn status_texts(&self) -> &[String] {
        &self.status_texts
    }

    /// Takes in bytes from the companion computer that arrived at `now_ms`.
    pub fn receive(&mut self, now_ms: u64, bytes: &[u8]) {
        let mut messages = Vec::new();
        let signing = &mut self.signing;
        self.decoder.push_frames(bytes, |raw, decoded| {
            let admitted = signing.as_mut().is_none_or(|s| s.admits(raw));
            if let (true, Some((_, message))) = (admitted, decoded) {
                messages.push(message.clone());
            }
        });
        for message in messages {
            self.take(now_ms, &message);
        }
    }

    fn take(&mut self, now_ms: u64, message: &MavMessage) {
        match message {
            MavMessage::SET_POSITION_TARGET_LOCAL_NED(data) => match accepted_setpoint(data) {
                Some((position, yaw)) => {
                    if let Some(previous) = self.setpoint {
                        let gap = now_ms.saturating_sub(previous.at_ms);
                        self.counters.max_setpoint_gap_ms = self.counters.max_setpoint_gap_ms.max(gap);
                        if gap > OFFBOARD_TIMEOUT_MS {
                            self.counters.setpoint_gaps += 1;
                        }
                    }
                    self.setpoint = Some(FlightSetpoint {
                        position,
                        yaw,
                        at_ms: now_ms,
                    });
                    self.counters.setpoints_received += 1;
                }
                None => self.counters.setpoints_rejected += 1,
            },
            MavMessage::STATUSTEXT(data) => {
                self.counters.status_texts_received += 1;
                self.status_texts
                    .push(data.text.to_str().unwrap_or("<not UTF-8>").to_string());
            }
            MavMessage::HEARTBEAT(_) => self.counters.heartbeats_received += 1,
            _ => self.counters.other_received += 1,
        }
    }

    /// Appends to `out` whatever is due at `now_ms`: a HEARTBEAT every
    /// [`HEARTBEAT_PERIOD_MS`], and every [`EmulatorTiming::pose_period_ms`] a sample of the
    /// vehicle at `position` with `yaw` (map frame, level attitude) as LOCAL_POSITION_NED +
    /// ATTITUDE stamped with the sampling instant, which leave [`EmulatorTiming::latency_ms`]
    /// later (in a later call's `out`). The first call sends a HEARTBEAT and samples at once.
    pub fn poll(&mut self, now_ms: u64, position: &Point3<f32>, yaw: f32, out: &mut Vec<u8>) {
        self.clock_ms = now_ms;
        if self.next_heartbeat_ms.is_none_or(|due| now_ms >= due) {
            self.next_heartbeat_ms = Some(now_ms + HEARTBEAT_PERIOD_MS);
            let heartbeat = MavMessage::HEARTBEAT(HEARTBEAT_DATA {
                custom_mode: 0,
                mavtype: MavType::MAV_TYPE_QUADROTOR,
                base_mode: MavModeFlag::MAV_MODE_FLAG_SAFETY_ARMED
                    | MavModeFlag::MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
                system_status: MavState::MAV_STATE_ACTIVE,
                ..HEARTBEAT_DATA::DEFAULT
            });
            self.send(&heartbeat, out);
            self.counters.heartbeats_sent += 1;
        }
        if self.next_pose_ms.is_none_or(|due| now_ms >= due) {
            // Keep the grid of periods unless the caller fell behind by more than a period.
            let period = self.timing.pose_period_ms;
            self.next_pose_ms = Some(match self.next_pose_ms {
                Some(due) if now_ms - due < period => due + period,
                _ => now_ms + period,
            });
            let mut report = Vec::new();
            self.sample(now_ms, position, yaw, &mut report);
            self.in_flight
                .push_back((now_ms + self.timing.latency_ms, report));
        }
        while self.in_flight.front().is_some_and(|(at, _)| *at <= now_ms) {
            if let Some((_, bytes)) = self.in_flight.pop_front() {
                out.extend_from_slice(&bytes);
            }
        }
    }

    /// Encodes the pose reports of one sample at `now_ms` into `out`.
    fn sample(&mut self, now_ms: u64, position: &Point3<f32>, yaw: f32, out: &mut Vec<u8>) {
        let ([x, y, z], yaw_ned) = map_to_ned(*position, yaw);
        // Velocities: the change since the last report (zero for the first).
        let (velocity, yaw_rate) = match self.last_report {
            Some((p, y0, t)) if now_ms > t => {
                let dt = (now_ms - t) as f32 * 1e-3;
                let v = [(x - p[0]) / dt, (y - p[1]) / dt, (z - p[2]) / dt];
                (v, harmonic_core::mavlink::wrap_angle(yaw_ned - y0) / dt)
            }
            _ => ([0.0; 3], 0.0),
        };
        self.last_report = Some(([x, y, z], yaw_ned, now_ms));
        let (velocity, yaw_rate) = if self.timing.zero_velocities {
            ([0.0; 3], 0.0)
        } else {
            (velocity, yaw_rate)
        };
        // The autopilot's clock: since its boot, at the instant of the sample.
        let boot_now_ms = now_ms + self.timing.boot_ms;
        let time_boot_ms = boot_now_ms as u32;
        let local = MavMessage::LOCAL_POSITION_NED(LOCAL_POSITION_NED_DATA {
            time_boot_ms,
            x,
            y,
            z,
            vx: velocity[0],
            vy: velocity[1],
            vz: velocity[2],
        });
        self.send(&local, out);
        self.counters.local_positions_sent += 1;
        let attitude = MavMessage::ATTITUDE(ATTITUDE_DATA {
            time_boot_ms,
            roll: 0.0,
            pitch: 0.0,
            yaw: yaw_ned,
            rollspeed: 0.0,
            pitchspeed: 0.0,
            yawspeed: yaw_rate,
        });
        self.send(&attitude, out);
        self.counters.attitudes_sent += 1;
        if self.odometry {
            // Body FRD → NED is a pure yaw: q = (cos ψ/2, 0, 0, sin ψ/2). ODOMETRY's
            // velocities are in the child (body) frame.
            let (s, c) = (yaw_ned * 0.5).sin_cos();
            let (sy, cy) = yaw_ned.sin_cos();
            let odometry = MavMessage::ODOMETRY(ODOMETRY_DATA {
                time_usec: boot_now_ms * 1000,
                x,
                y,
                z,
                q: [c, 0.0, 0.0, s],
                vx: cy * velocity[0] + sy * velocity[1],
                vy: -sy * velocity[0] + cy * velocity[1],
                vz: velocity[2],
                yawspeed: yaw_rate,
                frame_id: MavFrame::MAV_FRAME_LOCAL_NED,
                child_frame_id: MavFrame::MAV_FRAME_BODY_FRD,
                ..ODOMETRY_DATA::DEFAULT
            });
            self.send(&odometry, out);
            self.counters.odometries_sent += 1;
        }
    }

    fn send(&mut self, message: &MavMessage, out: &mut Vec<u8>) {
        let header = MavHeader {
            system_id: u32::from(DEFAULT_SYSTEM_ID),
            component_id: AUTOPILOT_COMPONENT_ID,
            sequence: self.sequence,
        };
        self.sequence = self.sequence.wrapping_add(1);
        let mut frame = [0u8; MAX_FRAME_LEN];
        // A buffer of MAX_FRAME_LEN always holds a frame, signed or not.
        if let Ok(n) = encode_v2(&header, message, &mut frame) {
            let n = match self.signing.as_mut() {
                Some(s) => s.sign(&mut frame, n, self.clock_ms),
                None => n,
            };
            out.extend_from_slice(&frame[..n]);
            self.counters.bytes_sent += n as u64;
        }
    }
}

/// The map-frame position and yaw of a setpoint PX4 would fly in offboard position mode.
fn accepted_setpoint(data: &SET_POSITION_TARGET_LOCAL_NED_DATA) -> Option<(Point3<f32>, f32)> {
    let frame_ok = data.coordinate_frame == MavFrame::MAV_FRAME_LOCAL_NED;
    let mask_ok = data.type_mask.contains(MUST_IGNORE) && !data.type_mask.intersects(MUST_USE);
    let target_ok =
        data.target_system == DEFAULT_SYSTEM_ID && data.target_component == AUTOPILOT_COMPONENT_ID;
    let finite = [data.x, data.y, data.z, data.yaw].iter().all(|v| v.is_finite());
    (frame_ok && mask_ok && target_ok && finite).then(|| ned_to_map([data.x, data.y, data.z], data.yaw))
}

#[cfg(test)]
mod tests {
    use super::*;
    use harmonic_core::mavlink::{Bridge, BridgeConfig, PositionTargetTypemask, POSITION_YAW_TYPEMASK};

    fn encode(message: &MavMessage, sequence: u8) -> Vec<u8> {
        let header = MavHeader {
            system_id: 1,
            component_id: 191,
            sequence,
        };
        let mut frame = [0u8; MAX_FRAME_LEN];
        let n = encode_v2(&header, message, &mut frame).unwrap();
        frame[..n].to_vec()
    }

    fn bridge_bytes(bridge: &mut Bridge, now: u64) -> Vec<u8> {
        let mut bytes = Vec::new();
        bridge.poll(now, |header, message| {
            let mut frame = [0u8; MAX_FRAME_LEN];
            let n = encode_v2(header, message, &mut frame).unwrap();
            bytes.extend_from_slice(&frame[..n]);
        });
        bytes
    }

    #[test]
    fn with_signing_only_setpoints_the_key_signed_move_the_vehicle() {
        let key = SecretKey::new([9; 32]);
        let mut emulator = FlightEmulator::new().with_signing(key.clone());
        let setpoint = MavMessage::SET_POSITION_TARGET_LOCAL_NED(SET_POSITION_TARGET_LOCAL_NED_DATA {
            coordinate_frame: MavFrame::MAV_FRAME_LOCAL_NED,
            type_mask: POSITION_YAW_TYPEMASK,
            target_system: DEFAULT_SYSTEM_ID,
            target_component: AUTOPILOT_COMPONENT_ID,
            x: 1.0,
            y: 2.0,
            z: -1.0,
            ..SET_POSITION_TARGET_LOCAL_NED_DATA::DEFAULT
        });
        // Unsigned: refused, counted, the vehicle has no setpoint.
        let plain = encode(&setpoint, 0);
        emulator.receive(10, &plain);
        assert!(emulator.setpoint().is_none());
        // Signed with another key: refused.
        let mut frame = [0u8; MAX_FRAME_LEN];
        let n = plain.len();
        frame[..n].copy_from_slice(&plain);
        let n_other = LinkSigning::new(SecretKey::new([1; 32]), 0).sign(&mut frame, n, 10);
        emulator.receive(20, &frame[..n_other]);
        assert!(emulator.setpoint().is_none());
        // Signed with the key: taken. The same bytes again: a replay, not taken twice.
        let mut frame = [0u8; MAX_FRAME_LEN];
        frame[..n].copy_from_slice(&plain);
        let n_signed = LinkSigning::new(key, 0).sign(&mut frame, n, 30);
        emulator.receive(30, &frame[..n_signed]);
        let taken = emulator.setpoint().expect("a signed setpoint is taken");
        assert_eq!(taken.at_ms, 30);
        emulator.receive(40, &frame[..n_signed]);
        assert_eq!(emulator.setpoint().unwrap().at_ms, 30);
        let c = emulator.signing_counters().unwrap();
        assert_eq!(
            (c.accepted, c.unsigned, c.bad_signature, c.replayed),
            (1, 1, 1, 1)
        );
        assert_eq!(emulator.counters().setpoints_received, 1);
        // What it sends is signed: a verifier with the key accepts its HEARTBEAT.
        let mut out = Vec::new();
        emulator.poll(50, &Point3::origin(), 0.0, &mut out);
        let mut bridge_side = LinkSigning::new(SecretKey::new([9; 32]), 1);
        let mut decoder = MavlinkDecoder::new();
        let mut admitted = 0;
        decoder.push_frames(&out, |raw, _| admitted += usize::from(bridge_side.admits(raw)));
        assert!(admitted >= 1, "{admitted}");
        assert_eq!(bridge_side.counters().unsigned, 0);
    }

    #[test]
    fn setpoint_is_decoded_and_pose_round_trips_through_the_bridge() {
        let mut bridge = Bridge::new(BridgeConfig::default()).unwrap();
        let mut emulator = FlightEmulator::new();
        let target = Point3::new(1.25f32, -3.5, 1.1);
        let target_yaw = 2.0f32;
        bridge.set_target(target, target_yaw).unwrap();
        bridge.exploration_started().unwrap();
        emulator.receive(0, &bridge_bytes(&mut bridge, 0));

        let sp = emulator.setpoint().expect("setpoint accepted");
        assert!((sp.position - target).norm() < 1e-5, "{sp:?}");
        assert!((sp.yaw - target_yaw).abs() < 1e-5, "{sp:?}");
        assert_eq!(emulator.counters().setpoints_received, 1);
        assert_eq!(emulator.counters().setpoints_rejected, 0);
        assert_eq!(emulator.counters().heartbeats_received, 1);
        assert_eq!(emulator.status_texts(), ["exploration started"]);

        // Back: the vehicle's pose, as the bridge reads it.
        // Far-apart positions, each after the last went stale (the bridge refuses a jump of
        // more than 1 m between fresh positions).
        let mut decoder = MavlinkDecoder::new();
        for (now, position, yaw) in [
            (0u64, Point3::new(0.5f32, 0.25, 1.0), 0.3f32),
            (600, Point3::new(-2.0, 7.5, 2.75), -3.0),
            (1200, Point3::new(3.0, -1.0, 0.5), std::f32::consts::PI),
        ] {
            let mut bytes = Vec::new();
            emulator.poll(now, &position, yaw, &mut bytes);
            let mut messages = Vec::new();
            decoder.push(&bytes, |h, m| messages.push((*h, m.clone())));
            assert!(messages.len() >= 2);
            for (h, m) in &messages {
                bridge.handle(now, h, m).expect("accepted by the bridge");
            }
            let pose = bridge.pose(now).expect("fresh pose");
            assert!((pose.position - position).norm() < 1e-4, "{pose:?} vs {position}");
            let dyaw = harmonic_core::mavlink::wrap_angle(pose.yaw - yaw);
            assert!(dyaw.abs() < 1e-4, "yaw {} vs {yaw}", pose.yaw);
        }
        assert_eq!(bridge.counters().sequence_gaps, 0);
        assert_eq!(bridge.counters().local_positions_received, 3);
        assert_eq!(bridge.counters().attitudes_received, 3);
    }

    #[test]
    fn setpoints_in_other_frames_or_modes_are_rejected() {
        let mut emulator = FlightEmulator::new();
        let good = SET_POSITION_TARGET_LOCAL_NED_DATA {
            x: 1.0,
            y: 2.0,
            z: -1.0,
            yaw: 0.5,
            type_mask: POSITION_YAW_TYPEMASK,
            target_system: 1,
            target_component: 1,
            coordinate_frame: MavFrame::MAV_FRAME_LOCAL_NED,
            ..SET_POSITION_TARGET_LOCAL_NED_DATA::DEFAULT
        };
        let body = SET_POSITION_TARGET_LOCAL_NED_DATA {
            coordinate_frame: MavFrame::MAV_FRAME_BODY_FRD,
            ..good.clone()
        };
        let velocity = SET_POSITION_TARGET_LOCAL_NED_DATA {
            type_mask: PositionTargetTypemask::POSITION_TARGET_TYPEMASK_X_IGNORE
                | PositionTargetTypemask::POSITION_TARGET_TYPEMASK_Y_IGNORE
                | PositionTargetTypemask::POSITION_TARGET_TYPEMASK_Z_IGNORE,
            ..good.clone()
        };
        emulator.receive(0, &encode(&MavMessage::SET_POSITION_TARGET_LOCAL_NED(body), 0));
        emulator.receive(
            0,
            &encode(&MavMessage::SET_POSITION_TARGET_LOCAL_NED(velocity), 1),
        );
        assert_eq!(emulator.setpoint(), None);
        assert_eq!(emulator.counters().setpoints_rejected, 2);

        emulator.receive(
            100,
            &encode(&MavMessage::SET_POSITION_TARGET_LOCAL_NED(good.clone()), 2),
        );
        let sp = emulator.setpoint().unwrap();
        // NED (north 1, east 2, down −1) is map (x 2, y 1, z 1).
        assert!((sp.position - Point3::new(2.0, 1.0, 1.0)).norm() < 1e-6);
        assert!((sp.yaw - (std::f32::consts::FRAC_PI_2 - 0.5)).abs() < 1e-6);

        // 600 ms of silence: PX4 would have left offboard mode.
        emulator.receive(
            700,
            &encode(&MavMessage::SET_POSITION_TARGET_LOCAL_NED(good.clone()), 3),
        );
        emulator.receive(800, &encode(&MavMessage::SET_POSITION_TARGET_LOCAL_NED(good), 4));
        assert_eq!(emulator.counters().setpoint_gaps, 1);
        assert_eq!(emulator.counters().max_setpoint_gap_ms, 600);
    }

    #[test]
    fn reports_leave_late_stamped_with_the_sampling_instant_on_the_autopilots_clock() {
        let timing = EmulatorTiming {
            pose_period_ms: 100,
            latency_ms: 50,
            boot_ms: 7000,
            zero_velocities: true,
        };
        let mut emulator = FlightEmulator::new().with_timing(timing);
        let mut decoder = MavlinkDecoder::new();
        // (poll time, time_boot_ms, NED east, NED east velocity) of every LOCAL_POSITION_NED out.
        let mut out: Vec<(u64, u32, f32, f32)> = Vec::new();
        for now in (0u64..=300).step_by(25) {
            // Flying map +x (East) at 1 m/s: NED east = now / 1000.
            let mut bytes = Vec::new();
            emulator.poll(now, &Point3::new(now as f32 * 1e-3, 0.0, 1.0), 0.0, &mut bytes);
            decoder.push(&bytes, |_, m| {
                if let MavMessage::LOCAL_POSITION_NED(d) = m {
                    out.push((now, d.time_boot_ms, d.y, d.vy));
                }
            });
        }
        // Sampled at 0, 100, 200, 300 ms; each leaves 50 ms later (300's is still in flight),
        // stamped with its sampling instant on a clock that started 7 s earlier.
        let expected = [(50u64, 7000u32, 0.0f32), (150, 7100, 0.1), (250, 7200, 0.2)];
        assert_eq!(out.len(), expected.len(), "{out:?}");
        for ((now, t, east, v), (want_now, want_t, want_east)) in out.iter().zip(expected) {
            assert_eq!((*now, *t), (want_now, want_t));
            assert!((east - want_east).abs() < 1e-6 && *v == 0.0, "{out:?}");
        }
    }

    #[test]
    fn reports_carry_velocities_and_optional_odometry() {
        let mut bridge = Bridge::new(BridgeConfig::default()).unwrap();
        let mut emulator = FlightEmulator::new().with_odometry(true);
        let mut decoder = MavlinkDecoder::new();
        let mut local = Vec::new();
        let mut odometry = Vec::new();
        // Flying map +x (East) at 2 m/s, heading East.
        for (now, x) in [(0u64, 0.0f32), (50, 0.1), (100, 0.2)] {
            let mut bytes = Vec::new();
            emulator.poll(now, &Point3::new(x, 0.0, 1.0), 0.0, &mut bytes);
            decoder.push(&bytes, |h, m| {
                bridge.handle(now, h, m).unwrap();
                match m {
                    MavMessage::LOCAL_POSITION_NED(d) => local.push(d.clone()),
                    MavMessage::ODOMETRY(d) => odometry.push(d.clone()),
                    _ => {}
                }
            });
        }
        assert_eq!(emulator.counters().odometries_sent, 3);
        assert_eq!(bridge.counters().odometries_received, 3);
        // NED: East is y.
        let last = local.last().unwrap();
        assert!((last.vy - 2.0).abs() < 1e-3 && last.vx.abs() < 1e-3, "{last:?}");
        // Body FRD, heading East: all forward.
        let odo = odometry.last().unwrap();
        assert!((odo.vx - 2.0).abs() < 1e-3 && odo.vy.abs() < 1e-3, "{odo:?}");
        let pose = bridge.pose(100).unwrap();
        assert_eq!(pose.source, harmonic_core::mavlink::PoseSource::Odometry);
        assert!((pose.position - Point3::new(0.2, 0.0, 1.0)).norm() < 1e-5);
        assert!(pose.yaw.abs() < 1e-5, "{}", pose.yaw);
    }
}
