//! The MAVLink bridge: setpoints out to the flight stack, the vehicle pose back in.
//!
//! On a vehicle the explorer runs on an onboard computer next to the autopilot (PX4, ArduPilot)
//! and talks to it in MAVLink 2. This module is that conversation, without allocation:
//!
//! - [`map_to_ned`] and [`ned_to_map`] — the one place where the map frame (z up) meets
//!   MAVLink's `MAV_FRAME_LOCAL_NED`, for positions and yaw.
//! - [`Bridge`] — the protocol state. [`Bridge::poll`] emits whatever is due: HEARTBEAT at 1 Hz,
//!   SET_POSITION_TARGET_LOCAL_NED at 10 Hz *whether or not a new plan exists* (it repeats the
//!   current setpoint: the last goal, or a hold), and queued STATUSTEXTs. [`Bridge::handle`]
//!   consumes LOCAL_POSITION_NED, ATTITUDE and ODOMETRY from the autopilot into a
//!   [`VehiclePose`] in the map frame; [`Bridge::pose`] hands it out, or a [`PoseFault`].
//! - [`encode_v2`], [`write_v2`] and [`MavlinkDecoder`] — MAVLink 2 bytes in caller buffers or
//!   over any `embedded-io` stream, framed and checked by the `mavlink` crate, whose message
//!   types are generated from the official XML definitions (common dialect). Nothing here packs
//!   MAVLink bytes by hand.
//! - [`BridgeCounters`] and [`DecoderCounters`] — every message and fault, for the status output.
//! - [`PoseHistory`] — the last poses by the autopilot's own clock (`time_boot_ms`), for the
//!   pose at the instant a camera frame was taken ([`PoseHistory::pose_at`], interpolated
//!   between the samples that bracket it) and the yaw rate then.
//!
//! # Frames
//!
//! The map frame is right-handed with z up; the bridge reads it as ENU: map x = East,
//! y = North, z = Up. `MAV_FRAME_LOCAL_NED` is x = North, y = East, z = Down, with the same
//! origin (the flight stack's local origin is the map origin). Yaw in the map frame is
//! counter-clockwise from +x (East) about +z (Up); NED yaw is clockwise from North about +Down,
//! so `yaw_ned = π/2 − yaw_map`, wrapped to (−π, π]. The vehicle body frame of
//! [`VehiclePose::attitude`] is x forward, y left, z up (as in
//! [`forward_camera_pose`](crate::planning::explore::forward_camera_pose)); MAVLink's body frame is
//! FRD (x forward, y right, z down).
//!
//! # Faults
//!
//! Nothing here panics on input. Messages from another system or component, values that are not
//! finite or not sane (positions beyond [`BridgeConfig::max_position_m`], angles beyond 2π,
//! ODOMETRY quaternions whose norm is off by more than [`QUATERNION_NORM_TOLERANCE`], ODOMETRY in
//! another frame than `MAV_FRAME_LOCAL_NED`) are dropped and counted. A pose that stops arriving
//! for [`BridgeConfig::pose_timeout_ms`] is a fault: the bridge switches its setpoint to a hold at
//! the last known vehicle position, says so in a STATUSTEXT, refuses new goals until the pose is
//! back, and keeps streaming.

use core::f32::consts::{FRAC_1_SQRT_2, PI, TAU};
use core::fmt::{self, Write as _};

use ::mavlink::dialects::common::{
    MavAutopilot, MavCmd, MavFrame, MavModeFlag, MavResult, MavState, MavType, ATTITUDE_DATA,
    COMMAND_ACK_DATA, COMMAND_LONG_DATA, HEARTBEAT_DATA, LOCAL_POSITION_NED_DATA, ODOMETRY_DATA,
    SET_POSITION_TARGET_LOCAL_NED_DATA, STATUSTEXT_DATA,
};
use ::mavlink::{MAVLinkMessageRaw, MAVLinkV2MessageRaw};
use nalgebra::{Isometry3, Point3, Quaternion, Translation3, UnitQuaternion};

use crate::links::operator::{CommandResult, Operator, OperatorCommand, OperatorState};

pub use ::mavlink::dialects::common::{self, MavComponent, MavMessage, MavSeverity, PositionTargetTypemask};
/// The `mavlink` crate's message trait (`message_name`, `message_id`, `parse`), for hosts that
/// must not depend on the crate themselves (its `std` and `embedded` features conflict).
pub use ::mavlink::Message as MavlinkMessage;
pub use ::mavlink::{MavHeader, MavlinkVersion};

/// System id the bridge sends with by default. A companion computer shares the system id of the
/// vehicle it sits on (MAVLink's convention; PX4 and ArduPilot vehicles default to 1) and is told
/// apart by its component id.
pub const DEFAULT_SYSTEM_ID: u8 = 1;
/// Milliseconds before the same kind of pose rejection is announced again by STATUSTEXT.
pub const REJECTION_REPEAT_MS: u64 = 5000;
/// Component id the bridge sends with: `MAV_COMP_ID_ONBOARD_COMPUTER` (191), the id PX4 and
/// MAVLink routers expect of a companion computer.
pub const ONBOARD_COMPUTER_COMPONENT_ID: u8 = MavComponent::MAV_COMP_ID_ONBOARD_COMPUTER as u8;
/// Component id of the autopilot the bridge talks to by default: `MAV_COMP_ID_AUTOPILOT1` (1).
pub const AUTOPILOT_COMPONENT_ID: u8 = MavComponent::MAV_COMP_ID_AUTOPILOT1 as u8;
/// The slowest setpoint stream [`BridgeConfig`] accepts: 200 ms (5 Hz). PX4 leaves offboard
/// mode when setpoints arrive slower than 2 Hz; 5 Hz leaves room for a lost message or two.
pub const MAX_SETPOINT_PERIOD_MS: u32 = 200;
/// How far the norm of an ODOMETRY quaternion may be from 1.
pub const QUATERNION_NORM_TOLERANCE: f32 = 1e-3;
/// Bytes of the STATUSTEXT text field (no terminating NUL when full).
pub const STATUSTEXT_LEN: usize = 50;
/// STATUSTEXTs the bridge queues between two polls; more are dropped and counted.
pub const STATUS_QUEUE_LEN: usize = 8;
/// Largest MAVLink frame on the wire (v2, signed, 32-bit system id): a buffer this long holds
/// any frame [`encode_v2`] writes.
pub const MAX_FRAME_LEN: usize = ::mavlink::consts::MAX_FRAME_SIZE;

/// The type mask of every setpoint: use x, y, z and yaw; ignore velocity, acceleration and yaw
/// rate (bits 3–8 and 11: 8 + 16 + 32 + 64 + 128 + 256 + 2048 = 2552 = 0x09F8, PX4's
/// "position + yaw" setpoint).
pub const POSITION_YAW_TYPEMASK: PositionTargetTypemask =
    PositionTargetTypemask::POSITION_TARGET_TYPEMASK_VX_IGNORE
        .union(PositionTargetTypemask::POSITION_TARGET_TYPEMASK_VY_IGNORE)
        .union(PositionTargetTypemask::POSITION_TARGET_TYPEMASK_VZ_IGNORE)
        .union(PositionTargetTypemask::POSITION_TARGET_TYPEMASK_AX_IGNORE)
        .union(PositionTargetTypemask::POSITION_TARGET_TYPEMASK_AY_IGNORE)
        .union(PositionTargetTypemask::POSITION_TARGET_TYPEMASK_AZ_IGNORE)
        .union(PositionTargetTypemask::POSITION_TARGET_TYPEMASK_YAW_RATE_IGNORE);

// ---------------------------------------------------------------------------------------------
// Frames

/// `angle` wrapped to (−π, π]. Non-finite angles come back unchanged.
pub fn wrap_angle(angle: f32) -> f32 {
    // Already in range (the common case): returned exactly, without fmod's rounding.
    if !angle.is_finite() || (angle > -PI && angle <= PI) {
        return angle;
    }
    let mut shifted = libm::fmodf(angle + PI, TAU);
    if shifted <= 0.0 {
        shifted += TAU;
    }
    shifted - PI
}

/// Converts a map-frame position and yaw (ENU: x East, y North, z Up; yaw counter-clockwise
/// from East) into `MAV_FRAME_LOCAL_NED` (x North, y East, z Down; yaw clockwise from North):
/// `[north, east, down] = [y, x, −z]` and `yaw_ned = π/2 − yaw_map` wrapped to (−π, π].
///
/// The inverse is [`ned_to_map`]; both maps are their own inverse.
pub fn map_to_ned(position: Point3<f32>, yaw_map: f32) -> ([f32; 3], f32) {
    (
        [position.y, position.x, -position.z],
        wrap_angle(PI / 2.0 - yaw_map),
    )
}

/// Converts a `MAV_FRAME_LOCAL_NED` position `[north, east, down]` and yaw (clockwise from
/// North) into the map frame (x East, y North, z Up; yaw counter-clockwise from East):
/// `(x, y, z) = (east, north, −down)` and `yaw_map = π/2 − yaw_ned` wrapped to (−π, π].
///
/// The inverse of [`map_to_ned`].
pub fn ned_to_map(ned: [f32; 3], yaw_ned: f32) -> (Point3<f32>, f32) {
    let [north, east, down] = ned;
    (Point3::new(east, north, -down), wrap_angle(PI / 2.0 - yaw_ned))
}

/// Rotation taking NED vectors to map (ENU) vectors: a half turn about (North + East)/√2.
fn enu_from_ned() -> UnitQuaternion<f32> {
    UnitQuaternion::new_unchecked(Quaternion::new(0.0, FRAC_1_SQRT_2, FRAC_1_SQRT_2, 0.0))
}

/// Rotation taking body FLU vectors (x forward, y left, z up) to body FRD vectors, and back: a
/// half turn about forward.
fn frd_from_flu() -> UnitQuaternion<f32> {
    UnitQuaternion::new_unchecked(Quaternion::new(0.0, 1.0, 0.0, 0.0))
}

// ---------------------------------------------------------------------------------------------
// Configuration, setpoints, poses

/// Everything a [`Bridge`] is configured with. [`Default`] gives the values documented on each
/// field.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BridgeConfig {
    /// System id sent in every header. Default [`DEFAULT_SYSTEM_ID`] (1, the vehicle's own).
    pub system_id: u8,
    /// Component id sent in every header. Default [`ONBOARD_COMPUTER_COMPONENT_ID`] (191).
    pub component_id: u8,
    /// System id of the autopilot: setpoints are addressed to it and poses accepted only from
    /// it. Default 1.
    pub target_system: u8,
    /// Component id of the autopilot. Default [`AUTOPILOT_COMPONENT_ID`] (1).
    pub target_component: u8,
    /// Milliseconds between HEARTBEATs. Default 1000 (1 Hz, MAVLink's convention).
    pub heartbeat_period_ms: u32,
    /// Milliseconds between setpoints, 1 ..= [`MAX_SETPOINT_PERIOD_MS`]. Default 100 (10 Hz:
    /// twice the 5 Hz floor, 5 × PX4's 2 Hz offboard timeout).
    pub setpoint_period_ms: u32,
    /// A pose older than this is stale. Default 500 ms: autopilots stream LOCAL_POSITION_NED
    /// and ATTITUDE at 20–50 Hz, so 500 ms is 10–25 lost messages in a row, and a vehicle at a
    /// few m/s moves about a metre in that time.
    pub pose_timeout_ms: u32,
    /// Largest |x|, |y| or |z| (metres) of a believable position. Default 1000 m, far beyond
    /// any building, so only garbage is rejected.
    pub max_position_m: f32,
    /// Largest step (metres) a position may take from the previous one of the same message
    /// type while that one is still fresh. Default 1 m: at the 20–50 Hz autopilots stream
    /// poses, a multirotor at 5 m/s moves 0.1–0.25 m between messages, so a longer step is an
    /// estimator glitch. A jump that persists (an estimator reset) is accepted once the old
    /// position has gone stale; the bridge holds meanwhile.
    pub max_pose_jump_m: f32,
    /// Wait for the operator's start command (COMMAND_LONG `MAV_CMD_MISSION_START`) before
    /// exploring (see [`crate::links::operator`]). Default false: explore at once.
    pub wait_for_start: bool,
}

impl Default for BridgeConfig {
    fn default() -> Self {
        Self {
            system_id: DEFAULT_SYSTEM_ID,
            component_id: ONBOARD_COMPUTER_COMPONENT_ID,
            target_system: 1,
            target_component: AUTOPILOT_COMPONENT_ID,
            heartbeat_period_ms: 1000,
            setpoint_period_ms: 100,
            pose_timeout_ms: 500,
            max_position_m: 1000.0,
            max_pose_jump_m: 1.0,
            wait_for_start: false,
        }
    }
}

/// Why a [`BridgeConfig`] was refused.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum BridgeConfigError {
    /// The heartbeat period is zero.
    HeartbeatPeriod,
    /// The setpoint period is zero or longer than [`MAX_SETPOINT_PERIOD_MS`].
    SetpointPeriod,
    /// The pose timeout is zero.
    PoseTimeout,
    /// The position limit is not a positive finite number.
    MaxPosition,
    /// The pose jump limit is not a positive finite number.
    MaxPoseJump,
}

/// What a setpoint asks of the vehicle.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SetpointKind {
    /// Fly to a goal of the explorer (or a target set by the caller).
    Goal,
    /// Stay where the vehicle was last known to be.
    Hold,
}

/// The position and yaw the bridge streams, in the map frame. Finite (checked when set).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Setpoint {
    /// Target position, map frame, metres.
    pub position: Point3<f32>,
    /// Target yaw about map z, radians, counter-clockwise from +x.
    pub yaw: f32,
    /// Goal or hold.
    pub kind: SetpointKind,
}

/// Which messages a pose came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PoseSource {
    /// ODOMETRY (position and attitude quaternion in one message); preferred when fresh.
    Odometry,
    /// LOCAL_POSITION_NED for the position and ATTITUDE for the orientation.
    LocalPositionAttitude,
}

/// The vehicle pose as the flight stack reports it, converted to the map frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct VehiclePose {
    /// Vehicle position, map frame, metres.
    pub position: Point3<f32>,
    /// Heading about map z, radians in (−π, π], counter-clockwise from +x.
    pub yaw: f32,
    /// Full attitude and position: body frame (x forward, y left, z up) → map frame.
    pub attitude: Isometry3<f32>,
    /// Which messages it came from.
    pub source: PoseSource,
    /// Milliseconds since its oldest part arrived.
    pub age_ms: u64,
}

/// Why there is no pose to use.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum PoseFault {
    /// Nothing usable has arrived yet (for LOCAL_POSITION_NED + ATTITUDE: not both).
    NoPose,
    /// No update for longer than [`BridgeConfig::pose_timeout_ms`].
    Stale {
        /// Milliseconds since the freshest usable pose arrived.
        age_ms: u64,
    },
}

/// What [`Bridge::handle`] made of an accepted message.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Received {
    /// A LOCAL_POSITION_NED, stored as the vehicle position.
    LocalPosition,
    /// An ATTITUDE, stored as the vehicle orientation.
    Attitude,
    /// An ODOMETRY, stored as a whole pose.
    Odometry,
    /// The autopilot's HEARTBEAT.
    Heartbeat,
    /// Any other message from the autopilot; counted and ignored.
    Other,
    /// An operator's COMMAND_LONG addressed to this component (from any sender), answered
    /// with a COMMAND_ACK: what it asked, and the answer.
    Command(Option<OperatorCommand>, CommandResult),
    /// A COMMAND_LONG addressed to another system or component; ignored.
    CommandForOthers,
}

/// Why [`Bridge::handle`] dropped a message. Each has a counter in [`BridgeCounters`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum InputError {
    /// From another system than [`BridgeConfig::target_system`].
    ForeignSystem,
    /// From the target system but another component than [`BridgeConfig::target_component`].
    ForeignComponent,
    /// A position, angle or quaternion component is NaN or infinite.
    NotFinite,
    /// A position beyond [`BridgeConfig::max_position_m`] or an angle beyond 2π.
    OutOfRange,
    /// An ODOMETRY quaternion whose norm is not within [`QUATERNION_NORM_TOLERANCE`] of 1.
    NotUnitQuaternion,
    /// An ODOMETRY pose in another frame than `MAV_FRAME_LOCAL_NED`.
    UnsupportedFrame,
    /// A position more than [`BridgeConfig::max_pose_jump_m`] from the previous, still fresh,
    /// one.
    PoseJump,
}

/// Why [`Bridge::set_target`] kept the current setpoint. Counted in
/// [`BridgeCounters::goals_refused`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum GoalError {
    /// Position or yaw not finite.
    NotFinite,
    /// The pose is stale: the bridge holds until it is back.
    PoseFault,
}

/// The STATUSTEXT queue was full; the text was dropped and counted.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct QueueFull;

/// Counts of every message and fault of a [`Bridge`] since start.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[cfg_attr(feature = "serde", derive(serde::Serialize))]
pub struct BridgeCounters {
    /// HEARTBEATs sent.
    pub heartbeats_sent: u32,
    /// SET_POSITION_TARGET_LOCAL_NEDs sent.
    pub setpoints_sent: u32,
    /// STATUSTEXTs sent.
    pub status_texts_sent: u32,
    /// STATUSTEXTs dropped because the queue was full.
    pub status_texts_dropped: u32,
    /// Goals refused (not finite, or pose stale).
    pub goals_refused: u32,
    /// Messages a [`Bridge::poll_write`] writer failed to take.
    pub write_errors: u32,
    /// HEARTBEATs received from the autopilot.
    pub heartbeats_received: u32,
    /// LOCAL_POSITION_NEDs accepted.
    pub local_positions_received: u32,
    /// ATTITUDEs accepted.
    pub attitudes_received: u32,
    /// ODOMETRYs accepted.
    pub odometries_received: u32,
    /// Other messages from the autopilot, ignored.
    pub other_received: u32,
    /// Pose messages with values that are not finite.
    pub rejected_not_finite: u32,
    /// Pose messages with positions or angles out of range.
    pub rejected_out_of_range: u32,
    /// ODOMETRYs with a quaternion too far from unit norm.
    pub rejected_quaternion: u32,
    /// ODOMETRYs in an unsupported frame.
    pub rejected_frame: u32,
    /// Positions that jumped further than [`BridgeConfig::max_pose_jump_m`].
    pub rejected_jump: u32,
    /// Messages from other systems, ignored.
    pub foreign_system: u32,
    /// Messages from other components of the target system, ignored.
    pub foreign_component: u32,
    /// Messages from the autopilot missing by sequence number.
    pub sequence_gaps: u32,
    /// Times the pose went stale (fresh → stale transitions seen by [`Bridge::poll`]).
    pub stale_events: u32,
    /// Operator COMMAND_LONGs addressed to this component.
    pub commands_received: u32,
    /// Of those, accepted.
    pub commands_accepted: u32,
    /// Of those, denied (not in the current state) or unsupported.
    pub commands_refused: u32,
    /// COMMAND_ACKs sent.
    pub command_acks_sent: u32,
    /// COMMAND_ACKs dropped because the queue was full.
    pub command_acks_dropped: u32,
}

impl BridgeCounters {
    /// Pose messages rejected for any reason.
    pub fn rejected(&self) -> u32 {
        self.rejected_not_finite
            .saturating_add(self.rejected_out_of_range)
            .saturating_add(self.rejected_quaternion)
            .saturating_add(self.rejected_frame)
            .saturating_add(self.rejected_jump)
    }

    fn record(&mut self, error: InputError) {
        let counter = match error {
            InputError::ForeignSystem => &mut self.foreign_system,
            InputError::ForeignComponent => &mut self.foreign_component,
            InputError::NotFinite => &mut self.rejected_not_finite,
            InputError::OutOfRange => &mut self.rejected_out_of_range,
            InputError::NotUnitQuaternion => &mut self.rejected_quaternion,
            InputError::UnsupportedFrame => &mut self.rejected_frame,
            InputError::PoseJump => &mut self.rejected_jump,
        };
        bump(counter);
    }
}

fn bump(counter: &mut u32) {
    *counter = counter.saturating_add(1);
}

// ---------------------------------------------------------------------------------------------
// STATUSTEXT text

/// The 32-bit FNV-1a digest of `bytes`.
fn fnv1a(bytes: &[u8]) -> u32 {
    bytes
        .iter()
        .fold(0x811c_9dc5, |h, &b| (h ^ u32::from(b)).wrapping_mul(0x0100_0193))
}

/// A STATUSTEXT text field: at most [`STATUSTEXT_LEN`] bytes of UTF-8, cut at a character
/// boundary, NUL-padded. Formatting into it never fails; what does not fit is dropped.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct StatusText {
    bytes: [u8; STATUSTEXT_LEN],
    len: usize,
}

impl StatusText {
    /// An empty text.
    pub const fn new() -> Self {
        Self {
            bytes: [0; STATUSTEXT_LEN],
            len: 0,
        }
    }

    /// `text`, cut to the longest prefix of whole characters that fits.
    pub fn from_str_truncated(text: &str) -> Self {
        let mut field = Self::new();
        field.push_str(text);
        field
    }

    /// The text as a string slice.
    pub fn as_str(&self) -> &str {
        // Only whole characters of a `&str` are ever copied in, so this cannot fail.
        self.bytes
            .get(..self.len)
            .and_then(|b| core::str::from_utf8(b).ok())
            .unwrap_or("")
    }

    /// The field as sent: the text followed by NULs.
    pub fn field(&self) -> [u8; STATUSTEXT_LEN] {
        self.bytes
    }

    fn push_str(&mut self, text: &str) {
        for c in text.chars() {
            let mut utf8 = [0u8; 4];
            let encoded = c.encode_utf8(&mut utf8).as_bytes();
            let end = self.len + encoded.len();
            match self.bytes.get_mut(self.len..end) {
                Some(slot) => slot.copy_from_slice(encoded),
                None => return,
            }
            self.len = end;
        }
    }
}

impl Default for StatusText {
    fn default() -> Self {
        Self::new()
    }
}

impl fmt::Write for StatusText {
    fn write_str(&mut self, s: &str) -> fmt::Result {
        self.push_str(s);
        Ok(())
    }
}

#[derive(Debug, Clone, Copy)]
struct PendingText {
    severity: MavSeverity,
    text: StatusText,
}

// ---------------------------------------------------------------------------------------------
// Bridge

/// A pose in NED as received: position, body FRD → NED rotation, NED yaw.
#[derive(Debug, Clone, Copy)]
struct NedPose {
    position: [f32; 3],
    rotation: UnitQuaternion<f32>,
    yaw: f32,
}

#[derive(Debug, Clone, Copy)]
struct Stamped<T> {
    value: T,
    at_ms: u64,
}

#[derive(Debug, Clone, Copy)]
struct NedAttitude {
    rotation: UnitQuaternion<f32>,
    yaw: f32,
}

/// The bridge between the explorer and the flight stack. Owns no buffers beyond a few hundred
/// bytes of state; time is whatever monotonic millisecond clock the caller passes in.
///
/// ```text
/// set_target / hold / hold_because / complete / status_text ─────────┐
///                                                                   ├─► poll(now) ─► HEARTBEAT,
/// handle(now, header, msg) ◄── LOCAL_POSITION_NED, ATTITUDE, ODOMETRY│    SET_POSITION_TARGET_LOCAL_NED,
///           │                                                       │    STATUSTEXT
///           └──► pose(now) ─► VehiclePose (map frame) | PoseFault ──┘
/// ```
#[derive(Debug, Clone)]
pub struct Bridge {
    config: BridgeConfig,
    sequence: u8,
    next_heartbeat_ms: Option<u64>,
    next_setpoint_ms: Option<u64>,
    setpoint: Option<Setpoint>,
    setpoint_changed: bool,
    texts: heapless::Deque<PendingText, STATUS_QUEUE_LEN>,
    local_position: Option<Stamped<[f32; 3]>>,
    attitude: Option<Stamped<NedAttitude>>,
    odometry: Option<Stamped<NedPose>>,
    last_target_sequence: Option<u8>,
    pose_fault: bool,
    complete_reported: bool,
    /// A digest of the reason of the last hold announced ([`Bridge::hold_because`]): 4 bytes
    /// where the text would take 51 in the firmware's RAM.
    last_hold: Option<u32>,
    /// The last pose rejection announced by STATUSTEXT, and when.
    last_rejection: Option<(InputError, u64)>,
    operator: Operator,
    /// COMMAND_ACKs to send: the command and the result.
    acks: heapless::Deque<(MavCmd, MavResult), ACK_QUEUE_LEN>,
    counters: BridgeCounters,
}

/// COMMAND_ACKs waiting for the next [`Bridge::poll`] at most.
pub const ACK_QUEUE_LEN: usize = 4;

impl Bridge {
    /// A bridge with `config`, checked: positive periods (setpoints at least every
    /// [`MAX_SETPOINT_PERIOD_MS`]), a positive timeout and position limit.
    pub fn new(config: BridgeConfig) -> Result<Self, BridgeConfigError> {
        if config.heartbeat_period_ms == 0 {
            return Err(BridgeConfigError::HeartbeatPeriod);
        }
        if config.setpoint_period_ms == 0 || config.setpoint_period_ms > MAX_SETPOINT_PERIOD_MS {
            return Err(BridgeConfigError::SetpointPeriod);
        }
        if config.pose_timeout_ms == 0 {
            return Err(BridgeConfigError::PoseTimeout);
        }
        if !(config.max_position_m.is_finite() && config.max_position_m > 0.0) {
            return Err(BridgeConfigError::MaxPosition);
        }
        if !(config.max_pose_jump_m.is_finite() && config.max_pose_jump_m > 0.0) {
            return Err(BridgeConfigError::MaxPoseJump);
        }
        Ok(Self {
            config,
            sequence: 0,
            next_heartbeat_ms: None,
            next_setpoint_ms: None,
            setpoint: None,
            setpoint_changed: false,
            texts: heapless::Deque::new(),
            local_position: None,
            attitude: None,
            odometry: None,
            last_target_sequence: None,
            pose_fault: false,
            complete_reported: false,
            last_hold: None,
            last_rejection: None,
            operator: Operator::new(config.wait_for_start),
            acks: heapless::Deque::new(),
            counters: BridgeCounters::default(),
        })
    }

    /// The configuration.
    pub fn config(&self) -> &BridgeConfig {
        &self.config
    }

    /// Counts of everything sent, received and rejected.
    pub fn counters(&self) -> &BridgeCounters {
        &self.counters
    }

    /// The setpoint being streamed, if any. There is none until the first goal or the first
    /// pose (which starts a hold where the vehicle is): streaming a made-up position would
    /// send the vehicle there.
    pub fn setpoint(&self) -> Option<Setpoint> {
        self.setpoint
    }

    /// True while the pose is stale (as of the last [`Bridge::poll`]).
    pub fn pose_fault(&self) -> bool {
        self.pose_fault
    }

    /// Streams a setpoint at `position` with `yaw` (map frame) from now on. Refused, keeping
    /// the current setpoint, if either is not finite or while the pose is stale.
    pub fn set_target(&mut self, position: Point3<f32>, yaw: f32) -> Result<(), GoalError> {
        let error = if !(position.coords.iter().all(|c| c.is_finite()) && yaw.is_finite()) {
            Some(GoalError::NotFinite)
        } else if self.pose_fault {
            Some(GoalError::PoseFault)
        } else {
            None
        };
        if let Some(error) = error {
            bump(&mut self.counters.goals_refused);
            return Err(error);
        }
        self.complete_reported = false;
        self.last_hold = None;
        self.change_setpoint(Setpoint {
            position,
            yaw: wrap_angle(yaw),
            kind: SetpointKind::Goal,
        });
        Ok(())
    }

    /// Holds: streams the last known vehicle position and yaw (however old) from now on. Before
    /// any pose has arrived the current setpoint, if any, is kept.
    pub fn hold(&mut self) {
        if let Some(pose) = self.latest_ned_pose() {
            let (position, yaw) = ned_to_map(pose.position, pose.yaw);
            if position.coords.iter().all(|c| c.is_finite()) && yaw.is_finite() {
                self.change_setpoint(Setpoint {
                    position,
                    yaw,
                    kind: SetpointKind::Hold,
                });
                return;
            }
        }
        if let Some(setpoint) = self.setpoint.as_mut() {
            setpoint.kind = SetpointKind::Hold;
        }
    }

    /// The exploration is complete: holds, tells the operator state, and announces it once
    /// (NOTICE) until the next target.
    pub fn complete(&mut self) {
        self.hold();
        let _ = self.operator.complete();
        if !self.complete_reported {
            self.complete_reported = true;
            let _ = self.status_text(MavSeverity::MAV_SEVERITY_NOTICE, "exploration complete");
        }
    }

    /// Holds for `reason`, announced (WARNING) when it differs from the last hold's, so a
    /// planner that fails every cycle does not flood the link.
    pub fn hold_because(&mut self, reason: StatusText) {
        self.hold();
        let digest = fnv1a(reason.as_str().as_bytes());
        if self.last_hold != Some(digest) {
            self.last_hold = Some(digest);
            let _ = self.queue_text(MavSeverity::MAV_SEVERITY_WARNING, reason);
        }
    }

    /// Announces the start of exploration (INFO).
    pub fn exploration_started(&mut self) -> Result<(), QueueFull> {
        self.complete_reported = false;
        self.last_hold = None;
        self.status_text(MavSeverity::MAV_SEVERITY_INFO, "exploration started")
    }

    /// Queues a STATUSTEXT, cut to [`STATUSTEXT_LEN`] bytes at a character boundary; sent by
    /// the next [`Bridge::poll`].
    pub fn status_text(&mut self, severity: MavSeverity, text: &str) -> Result<(), QueueFull> {
        self.queue_text(severity, StatusText::from_str_truncated(text))
    }

    /// Queues an already formatted STATUSTEXT.
    pub fn queue_text(&mut self, severity: MavSeverity, text: StatusText) -> Result<(), QueueFull> {
        match self.texts.push_back(PendingText { severity, text }) {
            Ok(()) => Ok(()),
            Err(_) => {
                bump(&mut self.counters.status_texts_dropped);
                Err(QueueFull)
            }
        }
    }

    /// Emits, through `send`, every message due at `now_ms`: a HEARTBEAT every
    /// [`BridgeConfig::heartbeat_period_ms`] (the first at once), queued COMMAND_ACKs and
    /// STATUSTEXTs, and the
    /// current setpoint every [`BridgeConfig::setpoint_period_ms`] or at once when it changed.
    /// Also notices a pose going stale (hold, WARNING) or coming back (INFO). Call it at least
    /// as often as the setpoint period; a late call sends one of each, not a burst.
    pub fn poll(&mut self, now_ms: u64, mut send: impl FnMut(&MavHeader, &MavMessage)) {
        self.check_pose(now_ms);

        if self.next_heartbeat_ms.is_none_or(|due| now_ms >= due) {
            self.next_heartbeat_ms = Some(next_due(
                self.next_heartbeat_ms,
                now_ms,
                self.config.heartbeat_period_ms,
            ));
            let message = MavMessage::HEARTBEAT(self.heartbeat());
            self.emit(&message, &mut send);
            bump(&mut self.counters.heartbeats_sent);
        }

        while let Some((command, result)) = self.acks.pop_front() {
            let message = MavMessage::COMMAND_ACK(COMMAND_ACK_DATA { command, result });
            self.emit(&message, &mut send);
            bump(&mut self.counters.command_acks_sent);
        }

        while let Some(pending) = self.texts.pop_front() {
            let message = MavMessage::STATUSTEXT(STATUSTEXT_DATA {
                severity: pending.severity,
                text: pending.text.field().into(),
            });
            self.emit(&message, &mut send);
            bump(&mut self.counters.status_texts_sent);
        }

        if let Some(setpoint) = self.setpoint {
            if self.setpoint_changed || self.next_setpoint_ms.is_none_or(|due| now_ms >= due) {
                let previous = if self.setpoint_changed {
                    None
                } else {
                    self.next_setpoint_ms
                };
                self.next_setpoint_ms = Some(next_due(previous, now_ms, self.config.setpoint_period_ms));
                self.setpoint_changed = false;
                let message =
                    MavMessage::SET_POSITION_TARGET_LOCAL_NED(self.setpoint_message(&setpoint, now_ms));
                self.emit(&message, &mut send);
                bump(&mut self.counters.setpoints_sent);
            }
        }
    }

    /// [`Bridge::poll`] straight into a byte stream as MAVLink 2 frames. A message the writer
    /// does not take is counted in [`BridgeCounters::write_errors`] (and still counts as sent:
    /// the stream goes on); the first such error is returned after all due messages were tried.
    pub fn poll_write<W: embedded_io::Write>(
        &mut self,
        now_ms: u64,
        writer: &mut W,
    ) -> Result<usize, TransportError> {
        let mut written = 0usize;
        let mut first_error = None;
        let mut errors = 0u32;
        self.poll(now_ms, |header, message| {
            match write_v2(writer, header, message) {
                Ok(n) => written = written.saturating_add(n),
                Err(e) => {
                    errors = errors.saturating_add(1);
                    first_error.get_or_insert(e);
                }
            }
        });
        self.counters.write_errors = self.counters.write_errors.saturating_add(errors);
        match first_error {
            Some(e) => Err(e),
            None => Ok(written),
        }
    }

    /// Takes in one message received at `now_ms`. Only messages from the target system and
    /// component count; of those, LOCAL_POSITION_NED, ATTITUDE and ODOMETRY update the pose
    /// after their values are checked. The first pose starts a hold setpoint if none exists.
    pub fn handle(
        &mut self,
        now_ms: u64,
        header: &MavHeader,
        message: &MavMessage,
    ) -> Result<Received, InputError> {
        if let MavMessage::COMMAND_LONG(command) = message {
            return Ok(self.operator_command(command));
        }
        let result = self.accept(now_ms, header, message);
        match result {
            Ok(Received::LocalPosition) => bump(&mut self.counters.local_positions_received),
            Ok(Received::Attitude) => bump(&mut self.counters.attitudes_received),
            Ok(Received::Odometry) => bump(&mut self.counters.odometries_received),
            Ok(Received::Heartbeat) => bump(&mut self.counters.heartbeats_received),
            Ok(Received::Other) => bump(&mut self.counters.other_received),
            // Commands are taken before `accept`, from any sender.
            Ok(Received::Command(..) | Received::CommandForOthers) => {}
            Err(error) => {
                self.counters.record(error);
                self.announce_rejection(now_ms, error);
            }
        }
        if result.is_ok() && self.setpoint.is_none() && self.latest_ned_pose().is_some() {
            self.hold();
        }
        result
    }

    /// What the operator has the explorer doing ([`crate::links::operator`]): plan only while it is
    /// [`OperatorState::Exploring`]; hold otherwise.
    pub fn operator_state(&self) -> OperatorState {
        self.operator.state()
    }

    /// An operator's COMMAND_LONG: addressed to this component (or all components of this
    /// system), it is acted on, answered with a COMMAND_ACK, and a state change is announced
    /// (INFO) — a pause or abort also holds at once. From any sender: signing, where it is on,
    /// has already refused frames without the key.
    fn operator_command(&mut self, data: &COMMAND_LONG_DATA) -> Received {
        let ours = data.target_system == self.config.system_id
            && (data.target_component == self.config.component_id || data.target_component == 0);
        if !ours {
            return Received::CommandForOthers;
        }
        bump(&mut self.counters.commands_received);
        let command = match data.command {
            MavCmd::MAV_CMD_MISSION_START => Some(OperatorCommand::Start),
            MavCmd::MAV_CMD_DO_PAUSE_CONTINUE if data.param1 == 0.0 => Some(OperatorCommand::Pause),
            MavCmd::MAV_CMD_DO_PAUSE_CONTINUE if data.param1 == 1.0 => Some(OperatorCommand::Resume),
            MavCmd::MAV_CMD_NAV_LOITER_UNLIM => Some(OperatorCommand::Abort),
            MavCmd::MAV_CMD_NAV_RETURN_TO_LAUNCH => Some(OperatorCommand::ReturnHome),
            _ => None,
        };
        let (result, changed) = match command {
            Some(c) => self.operator.command(c),
            None => (CommandResult::Unsupported, None),
        };
        let mav_result = match result {
            CommandResult::Accepted => {
                bump(&mut self.counters.commands_accepted);
                MavResult::MAV_RESULT_ACCEPTED
            }
            CommandResult::Denied => {
                bump(&mut self.counters.commands_refused);
                MavResult::MAV_RESULT_DENIED
            }
            CommandResult::Unsupported => {
                bump(&mut self.counters.commands_refused);
                MavResult::MAV_RESULT_UNSUPPORTED
            }
        };
        if self.acks.push_back((data.command, mav_result)).is_err() {
            bump(&mut self.counters.command_acks_dropped);
        }
        if let Some(state) = changed {
            self.announce_operator_state(state);
        }
        Received::Command(command, result)
    }

    /// The explorer's way home ended at home: hold there, and while the operator state was
    /// returning home, enter [`OperatorState::Home`] and announce it.
    pub fn arrived_home(&mut self) {
        self.hold();
        if let Some(state) = self.operator.arrived_home() {
            self.announce_operator_state(state);
        }
    }

    /// Returns home without an operator's command (after a complete exploration, by default):
    /// as if NAV_RETURN_TO_LAUNCH had come, without an acknowledgement.
    pub fn return_home(&mut self) {
        if let (_, Some(state)) = self.operator.command(OperatorCommand::ReturnHome) {
            self.announce_operator_state(state);
        }
    }

    fn announce_operator_state(&mut self, state: OperatorState) {
        if !state.plans() {
            self.hold();
        }
        let mut text = StatusText::new();
        let _ = write!(text, "operator: {}", state.name());
        let _ = self.queue_text(MavSeverity::MAV_SEVERITY_INFO, text);
    }

    /// The latest vehicle pose in the map frame: from ODOMETRY if it is fresh, else from
    /// LOCAL_POSITION_NED and ATTITUDE if both are fresh. [`PoseFault::Stale`] if the freshest
    /// usable pose is older than [`BridgeConfig::pose_timeout_ms`], [`PoseFault::NoPose`]
    /// before there was any.
    pub fn pose(&self, now_ms: u64) -> Result<VehiclePose, PoseFault> {
        let timeout = u64::from(self.config.pose_timeout_ms);
        let mut freshest_age: Option<u64> = None;
        if let Some(odometry) = self.odometry {
            let age = now_ms.saturating_sub(odometry.at_ms);
            if age <= timeout {
                return Ok(vehicle_pose(&odometry.value, PoseSource::Odometry, age));
            }
            freshest_age = Some(age);
        }
        if let Some((pose, at_ms)) = self.local_position_attitude() {
            let age = now_ms.saturating_sub(at_ms);
            if age <= timeout {
                return Ok(vehicle_pose(&pose, PoseSource::LocalPositionAttitude, age));
            }
            freshest_age = Some(freshest_age.map_or(age, |a| a.min(age)));
        }
        match freshest_age {
            Some(age_ms) => Err(PoseFault::Stale { age_ms }),
            None => Err(PoseFault::NoPose),
        }
    }

    // --- internals ---

    fn change_setpoint(&mut self, setpoint: Setpoint) {
        if self.setpoint != Some(setpoint) {
            self.setpoint = Some(setpoint);
            self.setpoint_changed = true;
        }
    }

    fn check_pose(&mut self, now_ms: u64) {
        match self.pose(now_ms) {
            Ok(_) => {
                if self.pose_fault {
                    self.pose_fault = false;
                    let _ = self.status_text(MavSeverity::MAV_SEVERITY_INFO, "pose back");
                }
            }
            Err(PoseFault::Stale { .. }) => {
                if !self.pose_fault {
                    self.pose_fault = true;
                    bump(&mut self.counters.stale_events);
                    self.hold();
                    let _ = self.status_text(MavSeverity::MAV_SEVERITY_WARNING, "pose stale: holding");
                }
            }
            Err(PoseFault::NoPose) => {}
        }
    }

    fn emit(&mut self, message: &MavMessage, send: &mut impl FnMut(&MavHeader, &MavMessage)) {
        let header = MavHeader {
            system_id: u32::from(self.config.system_id),
            component_id: self.config.component_id,
            sequence: self.sequence,
        };
        self.sequence = self.sequence.wrapping_add(1);
        send(&header, message);
    }

    fn heartbeat(&self) -> HEARTBEAT_DATA {
        let system_status = if self.pose_fault {
            MavState::MAV_STATE_CRITICAL
        } else if self.setpoint.is_some() {
            MavState::MAV_STATE_ACTIVE
        } else {
            MavState::MAV_STATE_STANDBY
        };
        HEARTBEAT_DATA {
            // The operator state (crate::links::operator): exploring, paused, ...
            custom_mode: self.operator.state().custom_mode(),
            mavtype: MavType::MAV_TYPE_ONBOARD_CONTROLLER,
            autopilot: MavAutopilot::MAV_AUTOPILOT_INVALID,
            // The generated default is SAFETY_ARMED; an onboard computer claims no flight
            // mode, only that custom_mode means something.
            base_mode: MavModeFlag::MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
            system_status,
            ..HEARTBEAT_DATA::DEFAULT
        }
    }

    fn setpoint_message(&self, setpoint: &Setpoint, now_ms: u64) -> SET_POSITION_TARGET_LOCAL_NED_DATA {
        let ([x, y, z], yaw) = map_to_ned(setpoint.position, setpoint.yaw);
        SET_POSITION_TARGET_LOCAL_NED_DATA {
            // Milliseconds since boot; MAVLink's u32 wraps after 49 days.
            time_boot_ms: now_ms as u32,
            x,
            y,
            z,
            vx: 0.0,
            vy: 0.0,
            vz: 0.0,
            afx: 0.0,
            afy: 0.0,
            afz: 0.0,
            yaw,
            yaw_rate: 0.0,
            type_mask: POSITION_YAW_TYPEMASK,
            target_system: self.config.target_system,
            target_component: self.config.target_component,
            coordinate_frame: MavFrame::MAV_FRAME_LOCAL_NED,
        }
    }

    fn accept(
        &mut self,
        now_ms: u64,
        header: &MavHeader,
        message: &MavMessage,
    ) -> Result<Received, InputError> {
        if header.system_id != u32::from(self.config.target_system) {
            return Err(InputError::ForeignSystem);
        }
        if header.component_id != self.config.target_component {
            return Err(InputError::ForeignComponent);
        }
        if let Some(last) = self.last_target_sequence {
            let missing = header.sequence.wrapping_sub(last.wrapping_add(1));
            // A jump of more than half the range is a restart or reordering, not a loss.
            if missing < 128 {
                self.counters.sequence_gaps = self.counters.sequence_gaps.saturating_add(u32::from(missing));
            }
        }
        self.last_target_sequence = Some(header.sequence);

        match message {
            MavMessage::LOCAL_POSITION_NED(data) => {
                let position = self.check_position(data)?;
                self.check_jump(now_ms, self.local_position.map(|p| (p.value, p.at_ms)), position)?;
                self.local_position = Some(Stamped {
                    value: position,
                    at_ms: now_ms,
                });
                Ok(Received::LocalPosition)
            }
            MavMessage::ATTITUDE(data) => {
                let attitude = check_attitude(data)?;
                self.attitude = Some(Stamped {
                    value: attitude,
                    at_ms: now_ms,
                });
                Ok(Received::Attitude)
            }
            MavMessage::ODOMETRY(data) => {
                let pose = self.check_odometry(data)?;
                self.check_jump(
                    now_ms,
                    self.odometry.map(|o| (o.value.position, o.at_ms)),
                    pose.position,
                )?;
                self.odometry = Some(Stamped {
                    value: pose,
                    at_ms: now_ms,
                });
                Ok(Received::Odometry)
            }
            MavMessage::HEARTBEAT(_) => Ok(Received::Heartbeat),
            _ => Ok(Received::Other),
        }
    }

    fn check_xyz(&self, xyz: [f32; 3]) -> Result<[f32; 3], InputError> {
        if !xyz.iter().all(|c| c.is_finite()) {
            return Err(InputError::NotFinite);
        }
        if xyz.iter().any(|c| c.abs() > self.config.max_position_m) {
            return Err(InputError::OutOfRange);
        }
        Ok(xyz)
    }

    /// A WARNING STATUSTEXT for a rejected pose message: once per kind of rejection, again
    /// after [`REJECTION_REPEAT_MS`] (so a bad stream does not flood the link). Messages
    /// from other systems or components are normal on a shared bus and not announced.
    fn announce_rejection(&mut self, now_ms: u64, error: InputError) {
        if matches!(error, InputError::ForeignSystem | InputError::ForeignComponent) {
            return;
        }
        let repeat = self
            .last_rejection
            .is_none_or(|(e, at)| e != error || now_ms.saturating_sub(at) >= REJECTION_REPEAT_MS);
        if repeat {
            self.last_rejection = Some((error, now_ms));
            let mut text = StatusText::new();
            let _ = write!(text, "pose rejected: {error:?}");
            let _ = self.queue_text(MavSeverity::MAV_SEVERITY_WARNING, text);
        }
    }

    /// Refuses `position` if it is further than the jump limit from `previous` while that is
    /// still fresh.
    fn check_jump(
        &self,
        now_ms: u64,
        previous: Option<([f32; 3], u64)>,
        position: [f32; 3],
    ) -> Result<(), InputError> {
        let Some((last, at_ms)) = previous else {
            return Ok(());
        };
        if now_ms.saturating_sub(at_ms) > u64::from(self.config.pose_timeout_ms) {
            return Ok(());
        }
        let d2: f32 = last
            .iter()
            .zip(position.iter())
            .map(|(a, b)| (a - b) * (a - b))
            .sum();
        let limit = self.config.max_pose_jump_m;
        if d2 > limit * limit {
            Err(InputError::PoseJump)
        } else {
            Ok(())
        }
    }

    fn check_position(&self, data: &LOCAL_POSITION_NED_DATA) -> Result<[f32; 3], InputError> {
        self.check_xyz([data.x, data.y, data.z])
    }

    fn check_odometry(&self, data: &ODOMETRY_DATA) -> Result<NedPose, InputError> {
        let position = self.check_xyz([data.x, data.y, data.z])?;
        let [w, x, y, z] = data.q;
        if !data.q.iter().all(|c| c.is_finite()) {
            return Err(InputError::NotFinite);
        }
        let norm = libm::sqrtf(w * w + x * x + y * y + z * z);
        if (norm - 1.0).abs() > QUATERNION_NORM_TOLERANCE {
            return Err(InputError::NotUnitQuaternion);
        }
        if data.frame_id != MavFrame::MAV_FRAME_LOCAL_NED {
            return Err(InputError::UnsupportedFrame);
        }
        let rotation = UnitQuaternion::new_normalize(Quaternion::new(w, x, y, z));
        let (_, _, yaw) = rotation.euler_angles();
        Ok(NedPose {
            position,
            rotation,
            yaw: wrap_angle(yaw),
        })
    }

    fn local_position_attitude(&self) -> Option<(NedPose, u64)> {
        let (position, attitude) = (self.local_position?, self.attitude?);
        let pose = NedPose {
            position: position.value,
            rotation: attitude.value.rotation,
            yaw: attitude.value.yaw,
        };
        Some((pose, position.at_ms.min(attitude.at_ms)))
    }

    /// The most recent complete pose, however old.
    fn latest_ned_pose(&self) -> Option<NedPose> {
        match (self.odometry, self.local_position_attitude()) {
            (Some(odometry), Some((pose, at_ms))) => Some(if at_ms > odometry.at_ms {
                pose
            } else {
                odometry.value
            }),
            (Some(odometry), None) => Some(odometry.value),
            (None, Some((pose, _))) => Some(pose),
            (None, None) => None,
        }
    }
}

/// When a periodic message sent at `now_ms` is next due: one period after it was due, so the
/// average rate holds under jitter, or one period from now if the caller fell behind by more
/// than a period (no burst of catch-up messages).
fn next_due(previous_due: Option<u64>, now_ms: u64, period_ms: u32) -> u64 {
    let period = u64::from(period_ms);
    match previous_due {
        Some(due) if now_ms.saturating_sub(due) < period => due.saturating_add(period),
        _ => now_ms.saturating_add(period),
    }
}

fn check_attitude(data: &ATTITUDE_DATA) -> Result<NedAttitude, InputError> {
    let angles = [data.roll, data.pitch, data.yaw];
    if !angles.iter().all(|a| a.is_finite()) {
        return Err(InputError::NotFinite);
    }
    if angles.iter().any(|a| a.abs() > TAU) {
        return Err(InputError::OutOfRange);
    }
    Ok(NedAttitude {
        // Aerospace Z-Y-X order: R = Rz(yaw) · Ry(pitch) · Rx(roll), body FRD → NED.
        rotation: UnitQuaternion::from_euler_angles(data.roll, data.pitch, data.yaw),
        yaw: wrap_angle(data.yaw),
    })
}

fn vehicle_pose(pose: &NedPose, source: PoseSource, age_ms: u64) -> VehiclePose {
    let (position, yaw) = ned_to_map(pose.position, pose.yaw);
    // body FLU → FRD → NED → map.
    let rotation = enu_from_ned() * pose.rotation * frd_from_flu();
    VehiclePose {
        position,
        yaw,
        attitude: Isometry3::from_parts(Translation3::from(position.coords), rotation),
        source,
        age_ms,
    }
}

// ---------------------------------------------------------------------------------------------
// Poses by the autopilot's clock

/// A sample that moved the autopilot's clock back by more than this (ms) is taken as a restart
/// of the autopilot: the history starts over. A smaller step back is a reordered message.
pub const HISTORY_RESTART_MS: u32 = 1000;

/// One sample of a pose stream, stamped with the autopilot's time and the local arrival time.
#[derive(Debug, Clone, Copy)]
struct TimedSample {
    /// Position `[north, east, down]` or attitude `[roll, pitch, yaw]` (NED, FRD body).
    value: [f32; 3],
    time_boot_ms: u32,
    arrived_ms: u64,
}

/// Counts of what a [`PoseHistory`] did with the samples it was given.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[cfg_attr(feature = "serde", derive(serde::Serialize))]
pub struct PoseHistoryCounters {
    /// Samples stored.
    pub samples: u32,
    /// Samples older than the newest of their stream (reordered), dropped.
    pub out_of_order: u32,
    /// Times the autopilot's clock went back by more than [`HISTORY_RESTART_MS`] and the
    /// history started over.
    pub restarts: u32,
}

/// The vehicle pose at one instant of the autopilot's clock ([`PoseHistory::pose_at`]), map
/// frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TimedPose {
    /// Vehicle position, map frame, metres.
    pub position: Point3<f32>,
    /// Heading about map z, radians in (−π, π], counter-clockwise from +x.
    pub yaw: f32,
    /// Body frame (x forward, y left, z up) → map frame.
    pub attitude: Isometry3<f32>,
    /// The instant, autopilot milliseconds since boot (`time_boot_ms`).
    pub time_boot_ms: u32,
    /// Yaw rate about map z at that instant, rad/s (counter-clockwise positive), measured from
    /// the timestamps of the attitude samples around it; `None` from a single sample.
    pub yaw_rate: Option<f32>,
    /// Local arrival time (the caller's clock, ms) of the latest sample used.
    pub arrived_ms: u64,
}

/// Why [`PoseHistory::pose_at`] has no pose for an instant.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum PoseAtError {
    /// No position or no attitude sample yet.
    NoPose,
    /// The instant is after the newest sample of a stream: wait for it.
    NotYet {
        /// The latest instant both streams cover ([`PoseHistory::newest_ms`]).
        newest_ms: u32,
    },
    /// The instant is before the oldest sample kept.
    Forgotten,
}

/// The autopilot's recent poses, by its own clock: the last `N` position samples
/// (LOCAL_POSITION_NED, or ODOMETRY) and the last `N` attitude samples (ATTITUDE, or ODOMETRY),
/// each stamped with the message's `time_boot_ms` (ODOMETRY: `time_usec` / 1000).
///
/// [`PoseHistory::pose_at`] gives the pose at any instant the samples cover: position linearly
/// interpolated, roll, pitch and yaw each along the shorter arc, between the two samples of each
/// stream that bracket it — by the autopilot's timestamps, never by arrival times, so latency
/// and jitter on the link do not move a pose in time. A camera frame taken at a known instant
/// of the autopilot's clock gets exactly the pose of that instant (as exact as the samples and
/// straight-line motion between them). Rates are measured from the samples, not read from the
/// messages' rate fields, which autopilots may leave at zero.
///
/// It trusts its input: feed it only messages [`Bridge::handle`] accepted. `time_boot_ms` is
/// taken not to wrap (it does after 49 days).
#[derive(Debug, Clone)]
pub struct PoseHistory<const N: usize> {
    positions: heapless::Deque<TimedSample, N>,
    attitudes: heapless::Deque<TimedSample, N>,
    counters: PoseHistoryCounters,
}

impl<const N: usize> Default for PoseHistory<N> {
    fn default() -> Self {
        Self::new()
    }
}

impl<const N: usize> PoseHistory<N> {
    /// An empty history.
    pub const fn new() -> Self {
        Self {
            positions: heapless::Deque::new(),
            attitudes: heapless::Deque::new(),
            counters: PoseHistoryCounters {
                samples: 0,
                out_of_order: 0,
                restarts: 0,
            },
        }
    }

    /// What happened to the samples so far.
    pub fn counters(&self) -> &PoseHistoryCounters {
        &self.counters
    }

    /// Forgets every sample.
    pub fn clear(&mut self) {
        self.positions.clear();
        self.attitudes.clear();
    }

    /// Stores the pose samples of `message`, which arrived at `arrived_ms` (the caller's
    /// clock). Other messages are ignored. Returns true if a sample was stored.
    pub fn record(&mut self, arrived_ms: u64, message: &MavMessage) -> bool {
        match message {
            MavMessage::LOCAL_POSITION_NED(d) => {
                self.push_position(arrived_ms, d.time_boot_ms, [d.x, d.y, d.z])
            }
            MavMessage::ATTITUDE(d) => {
                self.push_attitude(arrived_ms, d.time_boot_ms, [d.roll, d.pitch, d.yaw])
            }
            MavMessage::ODOMETRY(d) => {
                let [w, x, y, z] = d.q;
                let q = UnitQuaternion::from_quaternion(Quaternion::new(w, x, y, z));
                let (roll, pitch, yaw) = q.euler_angles();
                // time_usec is since boot on PX4 and ArduPilot; ms fits u32 for 49 days.
                let t = (d.time_usec as f64 * 1e-3) as u32;
                let p = self.push_position(arrived_ms, t, [d.x, d.y, d.z]);
                let a = self.push_attitude(arrived_ms, t, [roll, pitch, yaw]);
                p || a
            }
            _ => false,
        }
    }

    fn push_position(&mut self, arrived_ms: u64, time_boot_ms: u32, value: [f32; 3]) -> bool {
        let sample = TimedSample {
            value,
            time_boot_ms,
            arrived_ms,
        };
        self.push(sample, true)
    }

    fn push_attitude(&mut self, arrived_ms: u64, time_boot_ms: u32, value: [f32; 3]) -> bool {
        let sample = TimedSample {
            value,
            time_boot_ms,
            arrived_ms,
        };
        self.push(sample, false)
    }

    fn push(&mut self, sample: TimedSample, position: bool) -> bool {
        if !sample.value.iter().all(|v| v.is_finite()) {
            return false;
        }
        let newest = if position {
            self.positions.back()
        } else {
            self.attitudes.back()
        }
        .map(|s| s.time_boot_ms);
        if let Some(newest) = newest {
            if sample.time_boot_ms < newest {
                if newest - sample.time_boot_ms > HISTORY_RESTART_MS {
                    bump(&mut self.counters.restarts);
                    self.clear();
                } else {
                    bump(&mut self.counters.out_of_order);
                    return false;
                }
            }
        }
        let stream = if position {
            &mut self.positions
        } else {
            &mut self.attitudes
        };
        // The same instant again (ODOMETRY beside LOCAL_POSITION_NED): the newer message wins.
        if stream
            .back()
            .is_some_and(|s| s.time_boot_ms == sample.time_boot_ms)
        {
            let _ = stream.pop_back();
        }
        if stream.is_full() {
            let _ = stream.pop_front();
        }
        let stored = stream.push_back(sample).is_ok();
        if stored {
            bump(&mut self.counters.samples);
        }
        stored
    }

    /// The latest instant both streams cover: the older of the newest position and the newest
    /// attitude sample's time. `None` before there is one of each.
    pub fn newest_ms(&self) -> Option<u32> {
        let p = self.positions.back()?.time_boot_ms;
        let a = self.attitudes.back()?.time_boot_ms;
        Some(p.min(a))
    }

    /// The vehicle pose at `time_boot_ms` (autopilot clock), map frame; see the
    /// [type documentation](Self).
    pub fn pose_at(&self, time_boot_ms: u32) -> Result<TimedPose, PoseAtError> {
        let newest_ms = self.newest_ms().ok_or(PoseAtError::NoPose)?;
        if time_boot_ms > newest_ms {
            return Err(PoseAtError::NotYet { newest_ms });
        }
        let (ned, p_arrived) = interpolate(&self.positions, time_boot_ms, false)?;
        let ([roll, pitch, yaw_ned], a_arrived) = interpolate(&self.attitudes, time_boot_ms, true)?;
        let (position, yaw) = ned_to_map(ned, yaw_ned);
        // body FLU → FRD → NED → map, as in the bridge.
        let rotation =
            enu_from_ned() * UnitQuaternion::from_euler_angles(roll, pitch, yaw_ned) * frd_from_flu();
        Ok(TimedPose {
            position,
            yaw,
            attitude: Isometry3::from_parts(Translation3::from(position.coords), rotation),
            time_boot_ms,
            // Map yaw turns the other way from NED yaw.
            yaw_rate: yaw_rate_ned(&self.attitudes, time_boot_ms).map(|r| -r),
            arrived_ms: p_arrived.max(a_arrived),
        })
    }
}

/// `stream` at `t`: linear between the bracketing samples (angles along the shorter arc), and
/// the arrival time of the later one.
fn interpolate<const N: usize>(
    stream: &heapless::Deque<TimedSample, N>,
    t: u32,
    angles: bool,
) -> Result<([f32; 3], u64), PoseAtError> {
    let mut previous: Option<&TimedSample> = None;
    for s in stream.iter() {
        if s.time_boot_ms == t {
            return Ok((s.value, s.arrived_ms));
        }
        if s.time_boot_ms > t {
            let Some(a) = previous else {
                return Err(PoseAtError::Forgotten);
            };
            let span = (s.time_boot_ms - a.time_boot_ms) as f32;
            let f = (t - a.time_boot_ms) as f32 / span;
            let mut out = [0.0f32; 3];
            for ((o, x0), x1) in out.iter_mut().zip(a.value.iter()).zip(s.value.iter()) {
                *o = if angles {
                    wrap_angle(x0 + f * wrap_angle(x1 - x0))
                } else {
                    x0 + f * (x1 - x0)
                };
            }
            return Ok((out, s.arrived_ms));
        }
        previous = Some(s);
    }
    // After the newest sample: pose_at checked against newest_ms first.
    Err(PoseAtError::NoPose)
}

/// NED yaw rate at `t`, rad/s: over the attitude samples bracketing it, or at a sample's own
/// instant the faster of the intervals on either side. `None` with fewer than two samples.
fn yaw_rate_ned<const N: usize>(stream: &heapless::Deque<TimedSample, N>, t: u32) -> Option<f32> {
    let mut rate: Option<f32> = None;
    let mut previous: Option<&TimedSample> = None;
    for s in stream.iter() {
        if let Some(a) = previous {
            // Intervals touching t: [a, s] with a ≤ t ≤ s.
            if a.time_boot_ms <= t && t <= s.time_boot_ms && s.time_boot_ms > a.time_boot_ms {
                let dt = (s.time_boot_ms - a.time_boot_ms) as f32 * 1e-3;
                let ([_, _, y0], [_, _, y1]) = (a.value, s.value);
                let r = wrap_angle(y1 - y0) / dt;
                if rate.is_none_or(|old| r.abs() > old.abs()) {
                    rate = Some(r);
                }
            }
        }
        previous = Some(s);
    }
    rate
}

// ---------------------------------------------------------------------------------------------
// Bytes

/// Why bytes could not be produced or written.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TransportError {
    /// The output buffer is shorter than the frame.
    BufferTooSmall {
        /// Bytes the frame needs.
        needed: usize,
    },
    /// The writer failed.
    Io,
    /// The `mavlink` crate could not encode the message.
    Encode,
}

/// Encodes `message` as one MAVLink 2 frame (unsigned) into `out`; returns its length. A
/// buffer of [`MAX_FRAME_LEN`] bytes always suffices.
pub fn encode_v2(header: &MavHeader, message: &MavMessage, out: &mut [u8]) -> Result<usize, TransportError> {
    let mut raw = MAVLinkV2MessageRaw::new();
    raw.serialize_message(*header, message);
    let frame = raw.raw_bytes();
    let slot = out
        .get_mut(..frame.len())
        .ok_or(TransportError::BufferTooSmall { needed: frame.len() })?;
    slot.copy_from_slice(frame);
    Ok(frame.len())
}

/// Writes `message` as one MAVLink 2 frame to `writer` (with the `mavlink` crate's
/// `write_v2_msg`); returns the bytes written.
pub fn write_v2<W: embedded_io::Write>(
    writer: &mut W,
    header: &MavHeader,
    message: &MavMessage,
) -> Result<usize, TransportError> {
    ::mavlink::write_v2_msg(writer, *header, message).map_err(|e| match e {
        ::mavlink::error::MessageWriteError::Io => TransportError::Io,
        _ => TransportError::Encode,
    })
}

/// Counts of what a [`MavlinkDecoder`] saw.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[cfg_attr(feature = "serde", derive(serde::Serialize))]
pub struct DecoderCounters {
    /// Bytes pushed in.
    pub bytes: u64,
    /// Bytes inside frames with a valid checksum.
    pub framed_bytes: u64,
    /// Frames with a valid checksum (MAVLink 1 or 2, common dialect).
    pub frames: u32,
    /// Frames decoded into a message.
    pub messages: u32,
    /// Frames with a valid checksum whose payload did not decode (say, an unknown enum value).
    pub parse_errors: u32,
}

impl DecoderCounters {
    /// Bytes not (yet) inside a valid frame: line noise, damaged frames and frames of messages
    /// outside the common dialect (which the `mavlink` crate skips without telling), plus at
    /// most one partial frame still waiting for its end.
    pub fn unframed_bytes(&self) -> u64 {
        self.bytes.saturating_sub(self.framed_bytes)
    }
}

/// Bytes handed to the `mavlink` crate's reader: the current slice of [`MavlinkDecoder::push`],
/// copied in windows of this many bytes.
const INPUT_WINDOW: usize = 64;

/// The reader's byte source: a window of pushed bytes. Read returns 0 (end of input) when it
/// is empty, which makes the reader stop and keep any partial frame for the next push.
#[derive(Debug)]
struct InputWindow {
    bytes: [u8; INPUT_WINDOW],
    start: usize,
    end: usize,
}

impl InputWindow {
    /// Refills the (drained) window from the front of `input`; returns the bytes taken.
    fn fill(&mut self, input: &[u8]) -> usize {
        let n = input.len().min(INPUT_WINDOW);
        // n is within both lengths: both `get`s succeed (and their checks fold away).
        if let (Some(window), Some(input)) = (self.bytes.get_mut(..n), input.get(..n)) {
            window.copy_from_slice(input);
        }
        self.start = 0;
        self.end = n;
        n
    }
}

impl embedded_io::ErrorType for InputWindow {
    type Error = core::convert::Infallible;
}

impl embedded_io::Read for InputWindow {
    fn read(&mut self, buf: &mut [u8]) -> Result<usize, Self::Error> {
        let available = self.bytes.get(self.start..self.end).unwrap_or(&[]);
        let n = available.len().min(buf.len());
        if let (Some(buf), Some(available)) = (buf.get_mut(..n), available.get(..n)) {
            buf.copy_from_slice(available);
        }
        self.start += n;
        Ok(n)
    }
}

/// Streaming MAVLink receiver: bytes in any slicing in, checked messages out. Framing, checksum
/// and resynchronisation are the `mavlink` crate's `MavlinkReader` (a fixed buffer of one
/// maximum frame, no allocation); damaged or foreign bytes are skipped and counted, never a
/// panic. Accepts MAVLink 1 and 2 frames of the common dialect.
pub struct MavlinkDecoder {
    reader: ::mavlink::MavlinkReader<InputWindow>,
    counters: DecoderCounters,
}

impl core::fmt::Debug for MavlinkDecoder {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.debug_struct("MavlinkDecoder")
            .field("counters", &self.counters)
            .finish_non_exhaustive()
    }
}

impl Default for MavlinkDecoder {
    fn default() -> Self {
        Self::new()
    }
}

impl MavlinkDecoder {
    /// A decoder with nothing buffered.
    pub const fn new() -> Self {
        Self {
            reader: ::mavlink::MavlinkReader::new(InputWindow {
                bytes: [0; INPUT_WINDOW],
                start: 0,
                end: 0,
            }),
            counters: DecoderCounters {
                bytes: 0,
                framed_bytes: 0,
                frames: 0,
                messages: 0,
                parse_errors: 0,
            },
        }
    }

    /// What the decoder has seen.
    pub fn counters(&self) -> &DecoderCounters {
        &self.counters
    }

    /// Takes in `bytes` and calls `on_message` for every message completed by them, in order.
    /// A frame cut across pushes is completed by a later push.
    pub fn push(&mut self, bytes: &[u8], mut on_message: impl FnMut(&MavHeader, &MavMessage)) {
        self.push_frames(bytes, |_, decoded| {
            if let Some((header, message)) = decoded {
                on_message(header, message);
            }
        });
    }

    /// Like [`MavlinkDecoder::push`], but hands out every frame with a valid checksum as the
    /// bytes it arrived in (for logs that must keep them exactly, such as a `.tlog`), with its
    /// message if the payload decoded (`None`: counted in [`DecoderCounters::parse_errors`]).
    pub fn push_frames(
        &mut self,
        bytes: &[u8],
        mut on_frame: impl FnMut(&[u8], Option<(&MavHeader, &MavMessage)>),
    ) {
        self.counters.bytes = self.counters.bytes.saturating_add(bytes.len() as u64);
        let mut rest = bytes;
        while !rest.is_empty() {
            let taken = self.reader.get_mut().fill(rest);
            rest = rest.get(taken..).unwrap_or(&[]);
            self.drain(&mut on_frame);
        }
    }

    /// Reads once from `source` (blocking as its `read` does) and pushes what arrived; returns
    /// the number of bytes read (0 at the end of the stream).
    pub fn read_from<R: embedded_io::Read>(
        &mut self,
        source: &mut R,
        on_message: impl FnMut(&MavHeader, &MavMessage),
    ) -> Result<usize, R::Error> {
        let mut buffer = [0u8; INPUT_WINDOW];
        let n = source.read(&mut buffer)?;
        self.push(buffer.get(..n).unwrap_or(&[]), on_message);
        Ok(n)
    }

    fn drain(&mut self, on_frame: &mut impl FnMut(&[u8], Option<(&MavHeader, &MavMessage)>)) {
        // The reader returns an error only when the window is empty (end of input).
        while let Ok(raw) = self.reader.read_any_raw_message::<MavMessage>() {
            let frame = match &raw {
                MAVLinkMessageRaw::V1(frame) => frame.raw_bytes(),
                MAVLinkMessageRaw::V2(frame) => frame.raw_bytes(),
            };
            self.counters.framed_bytes = self.counters.framed_bytes.saturating_add(frame.len() as u64);
            bump(&mut self.counters.frames);
            let header = MavHeader {
                system_id: raw.system_id(),
                component_id: raw.component_id(),
                sequence: raw.sequence(),
            };
            match MavMessage::parse(raw.version(), raw.message_id(), raw.payload()) {
                Ok(message) => {
                    bump(&mut self.counters.messages);
                    on_frame(frame, Some((&header, &message)));
                }
                Err(_) => {
                    bump(&mut self.counters.parse_errors);
                    on_frame(frame, None);
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    extern crate std;

    use super::*;
    use nalgebra::Vector3;
    use std::vec::Vec;

    const EPS: f32 = 1e-5;

    fn close(a: f32, b: f32) -> bool {
        (a - b).abs() <= EPS
    }

    fn angle_close(a: f32, b: f32) -> bool {
        wrap_angle(a - b).abs() <= 1e-4
    }

    /// Numerical Recipes' LCG, for reproducible "random" inputs without a dependency.
    struct Lcg(u64);

    impl Lcg {
        fn next_u32(&mut self) -> u32 {
            self.0 = self
                .0
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (self.0 >> 33) as u32
        }
        fn byte(&mut self) -> u8 {
            self.next_u32() as u8
        }
        fn below(&mut self, n: u32) -> u32 {
            self.next_u32() % n.max(1)
        }
        fn uniform(&mut self, lo: f32, hi: f32) -> f32 {
            lo + (hi - lo) * (self.next_u32() as f32 / (1u64 << 31) as f32)
        }
    }

    fn goal(x: f32, y: f32, z: f32, yaw: f32) -> (Point3<f32>, f32) {
        (Point3::new(x, y, z), yaw)
    }

    fn target(bridge: &mut Bridge, (position, yaw): (Point3<f32>, f32)) -> Result<(), GoalError> {
        bridge.set_target(position, yaw)
    }

    fn autopilot(sequence: u8) -> MavHeader {
        MavHeader {
            system_id: 1,
            component_id: 1,
            sequence,
        }
    }

    fn local_position(north: f32, east: f32, down: f32) -> MavMessage {
        MavMessage::LOCAL_POSITION_NED(LOCAL_POSITION_NED_DATA {
            x: north,
            y: east,
            z: down,
            ..LOCAL_POSITION_NED_DATA::DEFAULT
        })
    }

    fn attitude(roll: f32, pitch: f32, yaw: f32) -> MavMessage {
        MavMessage::ATTITUDE(ATTITUDE_DATA {
            roll,
            pitch,
            yaw,
            ..ATTITUDE_DATA::DEFAULT
        })
    }

    fn odometry(ned: [f32; 3], q_wxyz: [f32; 4]) -> MavMessage {
        MavMessage::ODOMETRY(ODOMETRY_DATA {
            x: ned[0],
            y: ned[1],
            z: ned[2],
            q: q_wxyz,
            frame_id: MavFrame::MAV_FRAME_LOCAL_NED,
            child_frame_id: MavFrame::MAV_FRAME_BODY_FRD,
            ..ODOMETRY_DATA::DEFAULT
        })
    }

    /// Sends a position and attitude from the autopilot at `now`.
    fn feed_pose(bridge: &mut Bridge, now: u64, seq: &mut u8, ned: [f32; 3], yaw_ned: f32) {
        for message in [
            local_position(ned[0], ned[1], ned[2]),
            attitude(0.0, 0.0, yaw_ned),
        ] {
            bridge.handle(now, &autopilot(*seq), &message).unwrap();
            *seq = seq.wrapping_add(1);
        }
    }

    #[derive(Default, Debug)]
    struct Sent {
        heartbeats: Vec<u64>,
        setpoints: Vec<(u64, SET_POSITION_TARGET_LOCAL_NED_DATA)>,
        texts: Vec<(MavSeverity, std::string::String)>,
        headers: Vec<MavHeader>,
    }

    fn poll_into(bridge: &mut Bridge, now: u64, sent: &mut Sent) {
        bridge.poll(now, |header, message| {
            sent.headers.push(*header);
            match message {
                MavMessage::HEARTBEAT(_) => sent.heartbeats.push(now),
                MavMessage::SET_POSITION_TARGET_LOCAL_NED(data) => sent.setpoints.push((now, data.clone())),
                MavMessage::STATUSTEXT(data) => sent.texts.push((
                    data.severity,
                    std::string::String::from(data.text.to_str().unwrap()),
                )),
                other => panic!("unexpected message {other:?}"),
            }
        });
    }

    // --- frames ---

    #[test]
    fn map_to_ned_hand_computed() {
        // Map (x East 1, y North 2, z Up 3), facing East (yaw_map 0):
        //   north = y = 2, east = x = 1, down = −z = −3; yaw_ned = π/2 − 0 = π/2 (East is 90°
        //   clockwise from North).
        let (ned, yaw) = map_to_ned(Point3::new(1.0, 2.0, 3.0), 0.0);
        assert_eq!(ned, [2.0, 1.0, -3.0]);
        assert!(close(yaw, PI / 2.0));

        // Facing +y = North (yaw_map π/2): yaw_ned = π/2 − π/2 = 0.
        assert!(close(map_to_ned(Point3::origin(), PI / 2.0).1, 0.0));
        // Facing −x = West (yaw_map π): π/2 − π = −π/2 (West is 90° anticlockwise of North).
        assert!(close(map_to_ned(Point3::origin(), PI).1, -PI / 2.0));
        // Facing −y = South (yaw_map −π/2): π/2 + π/2 = π, inside (−π, π].
        assert!(close(map_to_ned(Point3::origin(), -PI / 2.0).1, PI));
        // Facing North-West (yaw_map 3π/4): π/2 − 3π/4 = −π/4.
        assert!(close(map_to_ned(Point3::origin(), 3.0 * PI / 4.0).1, -PI / 4.0));
        // Facing South-East (yaw_map −π/4): π/2 + π/4 = 3π/4 (135° clockwise from North).
        assert!(close(map_to_ned(Point3::origin(), -PI / 4.0).1, 3.0 * PI / 4.0));
        // A yaw beyond ±π wraps: yaw_map 5π/2 ≡ π/2 → 0.
        assert!(close(map_to_ned(Point3::origin(), 5.0 * PI / 2.0).1, 0.0));
    }

    #[test]
    fn ned_to_map_hand_computed() {
        // NED (north 2, east 1, down −3) facing East (yaw_ned π/2):
        //   x = east = 1, y = north = 2, z = −down = 3; yaw_map = π/2 − π/2 = 0.
        let (p, yaw) = ned_to_map([2.0, 1.0, -3.0], PI / 2.0);
        assert_eq!(p, Point3::new(1.0, 2.0, 3.0));
        assert!(close(yaw, 0.0));
        // North (yaw_ned 0) is map +y: yaw_map π/2.
        assert!(close(ned_to_map([0.0; 3], 0.0).1, PI / 2.0));
        // South (yaw_ned π) is map −y: π/2 − π = −π/2.
        assert!(close(ned_to_map([0.0; 3], PI).1, -PI / 2.0));
    }

    #[test]
    fn wrap_angle_range() {
        assert!(close(wrap_angle(PI), PI));
        assert!(close(wrap_angle(-PI), PI));
        assert!(close(wrap_angle(0.0), 0.0));
        assert!(close(wrap_angle(3.0 * PI), PI));
        assert!(close(wrap_angle(-0.5 - 4.0 * PI), -0.5));
        assert!(wrap_angle(f32::NAN).is_nan());
    }

    #[test]
    fn frame_round_trips() {
        let mut rng = Lcg(7);
        for _ in 0..10_000 {
            let p = Point3::new(
                rng.uniform(-500.0, 500.0),
                rng.uniform(-500.0, 500.0),
                rng.uniform(-50.0, 50.0),
            );
            let yaw = rng.uniform(-20.0, 20.0);
            let (ned, yaw_ned) = map_to_ned(p, yaw);
            assert!(yaw_ned > -PI && yaw_ned <= PI);
            let (back, yaw_back) = ned_to_map(ned, yaw_ned);
            assert_eq!(back, p);
            assert!(angle_close(yaw_back, yaw), "{yaw} → {yaw_ned} → {yaw_back}");
        }
    }

    #[test]
    fn attitude_to_map_hand_computed() {
        let mut bridge = Bridge::new(BridgeConfig::default()).unwrap();
        let mut seq = 0;
        // Facing East (yaw_ned π/2), level: body forward = map +x, body left = map +y (North).
        feed_pose(&mut bridge, 0, &mut seq, [2.0, 1.0, -3.0], PI / 2.0);
        let pose = bridge.pose(0).unwrap();
        assert_eq!(pose.source, PoseSource::LocalPositionAttitude);
        assert_eq!(pose.position, Point3::new(1.0, 2.0, 3.0));
        assert!(close(pose.yaw, 0.0));
        let r = pose.attitude.rotation;
        assert!((r * Vector3::x() - Vector3::x()).norm() < EPS);
        assert!((r * Vector3::y() - Vector3::y()).norm() < EPS);
        assert!((r * Vector3::z() - Vector3::z()).norm() < EPS);
        assert!((pose.attitude.translation.vector - Vector3::new(1.0, 2.0, 3.0)).norm() < EPS);

        // Facing North, nose up by θ = 0.3 (FRD pitch > 0): forward in NED is
        // (cos θ, 0, −sin θ), in the map (0, cos θ, sin θ).
        let theta = 0.3f32;
        bridge
            .handle(1, &autopilot(seq), &attitude(0.0, theta, 0.0))
            .unwrap();
        seq += 1;
        let r = bridge.pose(1).unwrap().attitude.rotation;
        assert!((r * Vector3::x() - Vector3::new(0.0, theta.cos(), theta.sin())).norm() < EPS);

        // Facing North, right wing down by φ = 0.4 (FRD roll > 0): right in NED is
        // (0, cos φ, sin φ); left (FLU y) is its negative, in the map (−cos φ, 0, sin φ).
        let phi = 0.4f32;
        bridge
            .handle(2, &autopilot(seq), &attitude(phi, 0.0, 0.0))
            .unwrap();
        let pose = bridge.pose(2).unwrap();
        assert!(
            (pose.attitude.rotation * Vector3::y() - Vector3::new(-phi.cos(), 0.0, phi.sin())).norm() < EPS
        );
        assert!(close(pose.yaw, PI / 2.0));
    }

    #[test]
    fn odometry_takes_precedence_and_matches_attitude() {
        let mut bridge = Bridge::new(BridgeConfig::default()).unwrap();
        let mut seq = 0;
        feed_pose(&mut bridge, 0, &mut seq, [5.0, 6.0, -1.0], 0.0);
        // Yaw π/2 about down (facing East): q = (cos π/4, 0, 0, sin π/4).
        let q = [FRAC_1_SQRT_2, 0.0, 0.0, FRAC_1_SQRT_2];
        assert_eq!(
            bridge.handle(10, &autopilot(seq), &odometry([2.0, 1.0, -3.0], q)),
            Ok(Received::Odometry)
        );
        let pose = bridge.pose(10).unwrap();
        assert_eq!(pose.source, PoseSource::Odometry);
        assert_eq!(pose.position, Point3::new(1.0, 2.0, 3.0));
        assert!(close(pose.yaw, 0.0));
        assert!((pose.attitude.rotation * Vector3::x() - Vector3::x()).norm() < EPS);

        // Odometry stale, position + attitude fresh: fall back to them.
        let mut seq = seq + 1;
        feed_pose(&mut bridge, 600, &mut seq, [5.0, 6.0, -1.0], 0.0);
        let pose = bridge.pose(600).unwrap();
        assert_eq!(pose.source, PoseSource::LocalPositionAttitude);
        assert_eq!(pose.position, Point3::new(6.0, 5.0, 1.0));
    }

    #[test]
    fn pose_jumps_are_rejected_announced_and_held_until_the_old_pose_is_stale() {
        let mut bridge = Bridge::new(BridgeConfig::default()).unwrap();
        let mut seq = 0;
        let mut sent = Sent::default();
        feed_pose(&mut bridge, 0, &mut seq, [1.0, 2.0, -1.0], 0.0);
        poll_into(&mut bridge, 0, &mut sent);
        // 0.5 m in 50 ms: plausible. 3 m in the next 50 ms: a glitch.
        assert!(bridge
            .handle(50, &autopilot(seq), &local_position(1.5, 2.0, -1.0))
            .is_ok());
        seq += 1;
        assert_eq!(
            bridge.handle(100, &autopilot(seq), &local_position(4.5, 2.0, -1.0)),
            Err(InputError::PoseJump)
        );
        seq += 1;
        assert_eq!(bridge.counters().rejected_jump, 1);
        assert_eq!(bridge.pose(100).unwrap().position, Point3::new(2.0, 1.5, 1.0));
        // The same kind of rejection again at once is counted, not announced twice.
        assert_eq!(
            bridge.handle(120, &autopilot(seq), &local_position(4.5, 2.0, -1.0)),
            Err(InputError::PoseJump)
        );
        seq += 1;
        assert_eq!(bridge.counters().rejected_jump, 2);
        poll_into(&mut bridge, 120, &mut sent);
        let warnings: Vec<_> = sent
            .texts
            .iter()
            .filter(|(s, t)| *s == MavSeverity::MAV_SEVERITY_WARNING && t.contains("PoseJump"))
            .collect();
        assert_eq!(warnings.len(), 1, "{:?}", sent.texts);
        // An estimator reset that persists: once the old position is stale, the bridge holds
        // (no fresh pose) and then takes the new one.
        assert!(matches!(bridge.pose(700), Err(PoseFault::Stale { .. })));
        assert_eq!(
            bridge.handle(700, &autopilot(seq), &local_position(4.5, 2.0, -1.0)),
            Ok(Received::LocalPosition)
        );
        seq += 1;
        bridge
            .handle(700, &autopilot(seq), &attitude(0.0, 0.0, 0.0))
            .unwrap();
        assert_eq!(bridge.pose(700).unwrap().position, Point3::new(2.0, 4.5, 1.0));
        // ODOMETRY is held to the same limit.
        let q = [1.0, 0.0, 0.0, 0.0];
        seq += 1;
        assert!(bridge
            .handle(710, &autopilot(seq), &odometry([0.0, 0.0, -1.0], q))
            .is_ok());
        seq += 1;
        assert_eq!(
            bridge.handle(720, &autopilot(seq), &odometry([0.0, 0.0, -9.0], q)),
            Err(InputError::PoseJump)
        );
        assert_eq!(
            Bridge::new(BridgeConfig {
                max_pose_jump_m: 0.0,
                ..BridgeConfig::default()
            })
            .err(),
            Some(BridgeConfigError::MaxPoseJump)
        );
    }

    #[test]
    fn bad_pose_messages_are_rejected_and_counted() {
        let mut bridge = Bridge::new(BridgeConfig::default()).unwrap();
        let h = autopilot(0);
        assert_eq!(
            bridge.handle(0, &h, &local_position(f32::NAN, 0.0, 0.0)),
            Err(InputError::NotFinite)
        );
        assert_eq!(
            bridge.handle(0, &h, &local_position(0.0, 1e6, 0.0)),
            Err(InputError::OutOfRange)
        );
        assert_eq!(
            bridge.handle(0, &h, &attitude(0.0, f32::INFINITY, 0.0)),
            Err(InputError::NotFinite)
        );
        assert_eq!(
            bridge.handle(0, &h, &attitude(0.0, 0.0, 100.0)),
            Err(InputError::OutOfRange)
        );
        assert_eq!(
            bridge.handle(0, &h, &odometry([0.0; 3], [1.01, 0.0, 0.0, 0.0])),
            Err(InputError::NotUnitQuaternion)
        );
        assert_eq!(
            bridge.handle(0, &h, &odometry([0.0; 3], [0.0, 0.0, 0.0, 0.0])),
            Err(InputError::NotUnitQuaternion)
        );
        assert_eq!(
            bridge.handle(0, &h, &odometry([0.0; 3], [f32::NAN, 0.0, 0.0, 0.0])),
            Err(InputError::NotFinite)
        );
        let mut frd = odometry([0.0; 3], [1.0, 0.0, 0.0, 0.0]);
        if let MavMessage::ODOMETRY(data) = &mut frd {
            data.frame_id = MavFrame::MAV_FRAME_LOCAL_FRD;
        }
        assert_eq!(bridge.handle(0, &h, &frd), Err(InputError::UnsupportedFrame));
        // Within tolerance of unit norm: accepted and normalised.
        assert_eq!(
            bridge.handle(0, &h, &odometry([0.0; 3], [1.0005, 0.0, 0.0, 0.0])),
            Ok(Received::Odometry)
        );
        let c = bridge.counters();
        assert_eq!(
            (
                c.rejected_not_finite,
                c.rejected_out_of_range,
                c.rejected_quaternion,
                c.rejected_frame
            ),
            (3, 2, 2, 1)
        );
        assert_eq!(c.rejected(), 8);
        assert_eq!(c.odometries_received, 1);
    }

    // --- outgoing ---

    #[test]
    fn heartbeat_fields() {
        let mut bridge = Bridge::new(BridgeConfig::default()).unwrap();
        let mut seen = Vec::new();
        bridge.poll(0, |header, message| seen.push((*header, message.clone())));
        assert_eq!(seen.len(), 1);
        let (header, message) = &seen[0];
        assert_eq!(header.system_id, 1);
        assert_eq!(header.component_id, 191);
        let MavMessage::HEARTBEAT(hb) = message else {
            panic!("{message:?}")
        };
        assert_eq!(hb.mavtype, MavType::MAV_TYPE_ONBOARD_CONTROLLER);
        assert_eq!(hb.autopilot, MavAutopilot::MAV_AUTOPILOT_INVALID);
        // No flight mode claimed; custom_mode is the operator state (exploring).
        assert_eq!(hb.base_mode, MavModeFlag::MAV_MODE_FLAG_CUSTOM_MODE_ENABLED);
        assert_eq!(hb.custom_mode, OperatorState::Exploring.custom_mode());
        assert_eq!(hb.system_status, MavState::MAV_STATE_STANDBY);
        assert_eq!(hb.mavlink_version, 3);
    }

    /// A ground station's COMMAND_LONG to `target` (system, component).
    fn command(target: (u8, u8), command: MavCmd, param1: f32) -> MavMessage {
        MavMessage::COMMAND_LONG(COMMAND_LONG_DATA {
            param1,
            command,
            target_system: target.0,
            target_component: target.1,
            ..COMMAND_LONG_DATA::DEFAULT
        })
    }

    #[test]
    fn operator_commands_are_acted_on_acknowledged_and_reported() {
        let config = BridgeConfig {
            wait_for_start: true,
            ..BridgeConfig::default()
        };
        let mut bridge = Bridge::new(config).unwrap();
        let gcs = MavHeader {
            system_id: 255,
            component_id: 190,
            sequence: 0,
        };
        let us = (1, 191);
        let mut sent = Vec::new();
        let mut exchange = |bridge: &mut Bridge, t: u64, message: MavMessage| {
            let got = bridge.handle(t, &gcs, &message).unwrap();
            sent.clear();
            bridge.poll(t, |_, m| sent.push(m.clone()));
            let acks: Vec<(MavCmd, MavResult)> = sent
                .iter()
                .filter_map(|m| match m {
                    MavMessage::COMMAND_ACK(a) => Some((a.command, a.result)),
                    _ => None,
                })
                .collect();
            let mode = sent.iter().find_map(|m| match m {
                MavMessage::HEARTBEAT(h) => Some(h.custom_mode),
                _ => None,
            });
            let texts: Vec<std::string::String> = sent
                .iter()
                .filter_map(|m| match m {
                    MavMessage::STATUSTEXT(t) => Some(
                        std::string::String::from_utf8_lossy(&t.text.to_vec())
                            .trim_end_matches('\0')
                            .into(),
                    ),
                    _ => None,
                })
                .collect();
            (got, acks, mode, texts)
        };
        assert_eq!(bridge.operator_state(), OperatorState::Waiting);
        let (_, acks, mode, _) = exchange(
            &mut bridge,
            0,
            command(us, MavCmd::MAV_CMD_DO_PAUSE_CONTINUE, 1.0),
        );
        assert_eq!(
            acks,
            [(MavCmd::MAV_CMD_DO_PAUSE_CONTINUE, MavResult::MAV_RESULT_DENIED)]
        );
        assert_eq!(mode, Some(OperatorState::Waiting.custom_mode()));
        let (got, acks, _, texts) =
            exchange(&mut bridge, 10, command(us, MavCmd::MAV_CMD_MISSION_START, 0.0));
        assert_eq!(
            got,
            Received::Command(Some(OperatorCommand::Start), CommandResult::Accepted)
        );
        assert_eq!(
            acks,
            [(MavCmd::MAV_CMD_MISSION_START, MavResult::MAV_RESULT_ACCEPTED)]
        );
        assert_eq!(texts, ["operator: exploring"]);
        assert!(bridge.operator_state().plans());
        // Pause: held at once; the next HEARTBEAT says paused.
        bridge.set_target(Point3::new(1.0, 2.0, 3.0), 0.0).unwrap();
        let (_, acks, _, texts) = exchange(
            &mut bridge,
            20,
            command((1, 0), MavCmd::MAV_CMD_DO_PAUSE_CONTINUE, 0.0),
        );
        assert_eq!(
            acks,
            [(MavCmd::MAV_CMD_DO_PAUSE_CONTINUE, MavResult::MAV_RESULT_ACCEPTED)]
        );
        assert_eq!(texts, ["operator: paused"]);
        assert_eq!(bridge.setpoint().map(|s| s.kind), Some(SetpointKind::Hold));
        let (_, _, mode, _) = exchange(
            &mut bridge,
            1000,
            command(us, MavCmd::MAV_CMD_DO_PAUSE_CONTINUE, 0.0),
        );
        assert_eq!(mode, Some(OperatorState::Paused.custom_mode()));
        // Unknown commands are unsupported; commands for someone else are not answered.
        let (got, acks, _, _) = exchange(
            &mut bridge,
            1010,
            command(us, MavCmd::MAV_CMD_COMPONENT_ARM_DISARM, 0.0),
        );
        assert_eq!(got, Received::Command(None, CommandResult::Unsupported));
        assert_eq!(
            acks,
            [(
                MavCmd::MAV_CMD_COMPONENT_ARM_DISARM,
                MavResult::MAV_RESULT_UNSUPPORTED
            )]
        );
        let (got, acks, _, _) = exchange(
            &mut bridge,
            1020,
            command((1, 1), MavCmd::MAV_CMD_MISSION_START, 0.0),
        );
        assert_eq!((got, acks.len()), (Received::CommandForOthers, 0));
        let (_, acks, _, texts) = exchange(
            &mut bridge,
            1030,
            command(us, MavCmd::MAV_CMD_NAV_LOITER_UNLIM, 0.0),
        );
        assert_eq!(
            acks,
            [(MavCmd::MAV_CMD_NAV_LOITER_UNLIM, MavResult::MAV_RESULT_ACCEPTED)]
        );
        assert_eq!(texts, ["operator: aborted"]);
        let c = bridge.counters();
        assert_eq!(
            (
                c.commands_received,
                c.commands_accepted,
                c.commands_refused,
                c.command_acks_sent
            ),
            (6, 4, 2, 6)
        );
        // Completion is a state too, reported like the others.
        let mut bridge = Bridge::new(BridgeConfig::default()).unwrap();
        bridge.complete();
        assert_eq!(bridge.operator_state(), OperatorState::Complete);
    }

    #[test]
    fn setpoint_type_mask_frame_and_addressing() {
        let config = BridgeConfig {
            target_system: 7,
            target_component: 1,
            ..BridgeConfig::default()
        };
        let mut bridge = Bridge::new(config).unwrap();
        target(&mut bridge, goal(1.0, 2.0, 3.0, 0.0)).unwrap();
        let mut sent = Sent::default();
        poll_into(&mut bridge, 1234, &mut sent);
        let (_, sp) = &sent.setpoints[0];
        // 2552 = VX 8 + VY 16 + VZ 32 + AX 64 + AY 128 + AZ 256 + YAW_RATE 2048.
        assert_eq!(sp.type_mask.bits(), 2552);
        use PositionTargetTypemask as M;
        for ignored in [
            M::POSITION_TARGET_TYPEMASK_VX_IGNORE,
            M::POSITION_TARGET_TYPEMASK_VY_IGNORE,
            M::POSITION_TARGET_TYPEMASK_VZ_IGNORE,
            M::POSITION_TARGET_TYPEMASK_AX_IGNORE,
            M::POSITION_TARGET_TYPEMASK_AY_IGNORE,
            M::POSITION_TARGET_TYPEMASK_AZ_IGNORE,
            M::POSITION_TARGET_TYPEMASK_YAW_RATE_IGNORE,
        ] {
            assert!(sp.type_mask.contains(ignored));
        }
        for used in [
            M::POSITION_TARGET_TYPEMASK_X_IGNORE,
            M::POSITION_TARGET_TYPEMASK_Y_IGNORE,
            M::POSITION_TARGET_TYPEMASK_Z_IGNORE,
            M::POSITION_TARGET_TYPEMASK_YAW_IGNORE,
            M::POSITION_TARGET_TYPEMASK_FORCE_SET,
        ] {
            assert!(!sp.type_mask.intersects(used));
        }
        assert_eq!(sp.coordinate_frame, MavFrame::MAV_FRAME_LOCAL_NED);
        assert_eq!((sp.target_system, sp.target_component), (7, 1));
        // Map (1, 2, 3) yaw 0 → NED (2, 1, −3) yaw π/2, as computed by hand above.
        assert_eq!((sp.x, sp.y, sp.z), (2.0, 1.0, -3.0));
        assert!(close(sp.yaw, PI / 2.0));
        assert_eq!(sp.time_boot_ms, 1234);
    }

    /// Runs a bridge for 10 s of fake time polled every `step(i)` ms, the autopilot sending a
    /// pose every 20 ms, and a new goal every second if `new_goals`. Returns what was sent.
    fn run_ten_seconds(new_goals: bool, mut step: impl FnMut(u64) -> u64) -> Sent {
        let mut bridge = Bridge::new(BridgeConfig::default()).unwrap();
        let mut sent = Sent::default();
        let mut seq = 0u8;
        let mut now = 0u64;
        let mut next_pose = 0u64;
        let mut i = 0;
        while now <= 10_000 {
            while next_pose <= now {
                feed_pose(&mut bridge, next_pose, &mut seq, [0.0, 0.0, -1.0], 0.0);
                next_pose += 20;
            }
            if new_goals && now % 1000 < 10 {
                let k = (now / 1000) as f32;
                let _ = target(&mut bridge, goal(k, 0.5 * k, 1.0, 0.1 * k));
            }
            poll_into(&mut bridge, now, &mut sent);
            now += step(i);
            i += 1;
        }
        sent
    }

    fn assert_stream(sent: &Sent) {
        let times: Vec<u64> = sent.setpoints.iter().map(|(t, _)| *t).collect();
        // ≥ 5 Hz over 10 s, and no gap longer than the 200 ms a 5 Hz stream allows.
        assert!(times.len() >= 50, "{} setpoints", times.len());
        assert!(times[0] <= 20, "first setpoint at {}", times[0]);
        let max_gap = times.windows(2).map(|w| w[1] - w[0]).max().unwrap();
        assert!(max_gap <= 200, "gap of {max_gap} ms");
        assert!(
            sent.heartbeats.len() >= 10 && sent.heartbeats.len() <= 11,
            "{:?}",
            sent.heartbeats
        );
        // Sequence numbers +1 per message sent.
        for w in sent.headers.windows(2) {
            assert_eq!(w[1].sequence, w[0].sequence.wrapping_add(1));
        }
    }

    #[test]
    fn setpoints_stream_without_new_goals() {
        let sent = run_ten_seconds(false, |_| 10);
        assert_stream(&sent);
        // 10 Hz: one every 100 ms from t = 0 to t = 10 000.
        assert_eq!(sent.setpoints.len(), 101);
        // A hold where the vehicle is: NED (0, 0, −1), yaw 0.
        for (_, sp) in &sent.setpoints {
            assert_eq!((sp.x, sp.y, sp.z, sp.yaw), (0.0, 0.0, -1.0, 0.0));
        }
    }

    #[test]
    fn setpoints_stream_with_new_goals_and_jittery_polls() {
        let sent = run_ten_seconds(true, |_| 10);
        assert_stream(&sent);
        // Each new goal goes out at once, on top of the 10 Hz stream.
        assert!(sent.setpoints.len() >= 101);
        let last = &sent.setpoints.last().unwrap().1;
        // Goal k = 10: map (10, 5, 1) → NED (5, 10, −1).
        assert_eq!((last.x, last.y, last.z), (5.0, 10.0, -1.0));

        let mut rng = Lcg(3);
        let sent = run_ten_seconds(true, move |_| 1 + u64::from(rng.below(37)));
        assert_stream(&sent);
    }

    #[test]
    fn no_setpoint_before_goal_or_pose() {
        let mut bridge = Bridge::new(BridgeConfig::default()).unwrap();
        let mut sent = Sent::default();
        for t in (0..2000).step_by(10) {
            poll_into(&mut bridge, t, &mut sent);
        }
        assert!(sent.setpoints.is_empty());
        assert_eq!(sent.heartbeats, [0, 1000]);
    }

    #[test]
    fn status_text_truncated_at_char_boundary() {
        // 48 ASCII bytes then "é" (2 bytes, ends at 50) then "€" (3 bytes): the field holds
        // exactly 48 + 2 = 50 bytes.
        let text = std::format!("{}é€ tail", "a".repeat(48));
        let field = StatusText::from_str_truncated(&text);
        assert_eq!(field.as_str().len(), 50);
        assert!(field.as_str().ends_with('é'));
        // 49 ASCII bytes then "é": "é" does not fit in the one byte left.
        let text = std::format!("{}é", "b".repeat(49));
        assert_eq!(StatusText::from_str_truncated(&text).as_str().len(), 49);

        let mut bridge = Bridge::new(BridgeConfig::default()).unwrap();
        bridge
            .status_text(MavSeverity::MAV_SEVERITY_INFO, &"x".repeat(80))
            .unwrap();
        let mut sent = Sent::default();
        poll_into(&mut bridge, 0, &mut sent);
        assert_eq!(sent.texts, [(MavSeverity::MAV_SEVERITY_INFO, "x".repeat(50))]);

        for i in 0..STATUS_QUEUE_LEN {
            bridge
                .status_text(MavSeverity::MAV_SEVERITY_INFO, &std::format!("{i}"))
                .unwrap();
        }
        assert_eq!(
            bridge.status_text(MavSeverity::MAV_SEVERITY_INFO, "one too many"),
            Err(QueueFull)
        );
        assert_eq!(bridge.counters().status_texts_dropped, 1);
    }

    #[test]
    fn start_completion_and_hold_reasons_are_announced_once() {
        let mut bridge = Bridge::new(BridgeConfig::default()).unwrap();
        let mut seq = 0;
        feed_pose(&mut bridge, 0, &mut seq, [2.0, 1.0, -3.0], 0.0);
        bridge.exploration_started().unwrap();
        target(&mut bridge, goal(4.0, 4.0, 1.0, 0.0)).unwrap();
        assert_eq!(bridge.setpoint().unwrap().kind, SetpointKind::Goal);
        for _ in 0..3 {
            bridge.hold_because(StatusText::from_str_truncated("hold: VehicleOutsideGrid"));
        }
        bridge.hold_because(StatusText::from_str_truncated("hold: BadPose"));
        let setpoint = bridge.setpoint().unwrap();
        assert_eq!(setpoint.kind, SetpointKind::Hold);
        // Holds where the vehicle is: NED (2, 1, −3) → map (1, 2, 3).
        assert_eq!(setpoint.position, Point3::new(1.0, 2.0, 3.0));
        bridge.complete();
        bridge.complete();
        let mut sent = Sent::default();
        poll_into(&mut bridge, 0, &mut sent);
        let texts: Vec<_> = sent.texts.iter().map(|(s, t)| (*s, t.as_str())).collect();
        assert_eq!(
            texts,
            [
                (MavSeverity::MAV_SEVERITY_INFO, "exploration started"),
                (MavSeverity::MAV_SEVERITY_WARNING, "hold: VehicleOutsideGrid"),
                (MavSeverity::MAV_SEVERITY_WARNING, "hold: BadPose"),
                (MavSeverity::MAV_SEVERITY_NOTICE, "exploration complete"),
            ]
        );
        assert_eq!(
            target(&mut bridge, goal(f32::NAN, 0.0, 0.0, 0.0)),
            Err(GoalError::NotFinite)
        );
        assert_eq!(bridge.counters().goals_refused, 1);
    }

    #[test]
    fn config_is_checked() {
        let bad = |c: BridgeConfig| Bridge::new(c).err();
        let d = BridgeConfig::default();
        assert_eq!(
            bad(BridgeConfig {
                setpoint_period_ms: 201,
                ..d
            }),
            Some(BridgeConfigError::SetpointPeriod)
        );
        assert_eq!(
            bad(BridgeConfig {
                setpoint_period_ms: 0,
                ..d
            }),
            Some(BridgeConfigError::SetpointPeriod)
        );
        assert_eq!(
            bad(BridgeConfig {
                heartbeat_period_ms: 0,
                ..d
            }),
            Some(BridgeConfigError::HeartbeatPeriod)
        );
        assert_eq!(
            bad(BridgeConfig {
                pose_timeout_ms: 0,
                ..d
            }),
            Some(BridgeConfigError::PoseTimeout)
        );
        assert_eq!(
            bad(BridgeConfig {
                max_position_m: f32::NAN,
                ..d
            }),
            Some(BridgeConfigError::MaxPosition)
        );
        assert!(Bridge::new(BridgeConfig {
            setpoint_period_ms: 200,
            ..d
        })
        .is_ok());
    }

    // --- incoming ---

    #[test]
    fn stale_pose_holds_and_recovers() {
        let mut bridge = Bridge::new(BridgeConfig::default()).unwrap();
        let mut sent = Sent::default();
        assert_eq!(bridge.pose(0), Err(PoseFault::NoPose));
        let mut seq = 0;
        feed_pose(&mut bridge, 0, &mut seq, [2.0, 1.0, -3.0], PI / 2.0);
        target(&mut bridge, goal(10.0, 10.0, 2.0, 0.0)).unwrap();
        poll_into(&mut bridge, 0, &mut sent);
        assert!(bridge.pose(500).is_ok(), "500 ms old is still fresh");
        assert_eq!(bridge.pose(501), Err(PoseFault::Stale { age_ms: 501 }));

        // Polls keep going with no pose: stale at 501 ms, one event, hold at the last pose.
        for t in (10..=2000).step_by(10) {
            poll_into(&mut bridge, t, &mut sent);
        }
        assert!(bridge.pose_fault());
        assert_eq!(bridge.counters().stale_events, 1);
        let hold = bridge.setpoint().unwrap();
        assert_eq!(hold.kind, SetpointKind::Hold);
        assert_eq!(hold.position, Point3::new(1.0, 2.0, 3.0));
        let (t, sp) = sent.setpoints.last().unwrap();
        assert!(*t >= 1900);
        assert_eq!((sp.x, sp.y, sp.z), (2.0, 1.0, -3.0));
        assert!(sent
            .texts
            .iter()
            .any(|(s, t)| *s == MavSeverity::MAV_SEVERITY_WARNING && t == "pose stale: holding"));
        assert_eq!(
            target(&mut bridge, goal(0.0, 0.0, 1.0, 0.0)),
            Err(GoalError::PoseFault)
        );
        let mut hb = Vec::new();
        bridge.poll(3000, |_, m| hb.push(m.clone()));
        assert!(
            matches!(&hb[0], MavMessage::HEARTBEAT(h) if h.system_status == MavState::MAV_STATE_CRITICAL)
        );

        // A new pose: fresh again, fault cleared at the next poll, goals accepted.
        feed_pose(&mut bridge, 3010, &mut seq, [0.0, 0.0, -1.0], 0.0);
        assert_eq!(bridge.pose(3010).unwrap().position, Point3::new(0.0, 0.0, 1.0));
        poll_into(&mut bridge, 3010, &mut sent);
        assert!(!bridge.pose_fault());
        assert!(target(&mut bridge, goal(0.0, 0.0, 1.0, 0.0)).is_ok());
        assert_eq!(bridge.counters().stale_events, 1);
    }

    #[test]
    fn other_systems_and_components_are_ignored_and_counted() {
        let mut bridge = Bridge::new(BridgeConfig::default()).unwrap();
        let gcs = MavHeader {
            system_id: 255,
            component_id: 190,
            sequence: 0,
        };
        let camera = MavHeader {
            system_id: 1,
            component_id: 100,
            sequence: 0,
        };
        assert_eq!(
            bridge.handle(0, &gcs, &local_position(1.0, 2.0, 3.0)),
            Err(InputError::ForeignSystem)
        );
        assert_eq!(
            bridge.handle(0, &gcs, &attitude(0.0, 0.0, 0.0)),
            Err(InputError::ForeignSystem)
        );
        assert_eq!(
            bridge.handle(0, &camera, &attitude(0.0, 0.0, 0.0)),
            Err(InputError::ForeignComponent)
        );
        assert_eq!(bridge.pose(0), Err(PoseFault::NoPose));
        assert!(bridge.setpoint().is_none());
        let c = bridge.counters();
        assert_eq!((c.foreign_system, c.foreign_component), (2, 1));
        assert_eq!(c.local_positions_received + c.attitudes_received, 0);

        // Heartbeat and other messages from the autopilot are taken (and counted).
        let hb = MavMessage::HEARTBEAT(HEARTBEAT_DATA::default());
        assert_eq!(bridge.handle(0, &autopilot(0), &hb), Ok(Received::Heartbeat));
        let other = MavMessage::STATUSTEXT(STATUSTEXT_DATA::default());
        assert_eq!(bridge.handle(0, &autopilot(3), &other), Ok(Received::Other));
        // Sequence 0 then 3: 1 and 2 are missing.
        assert_eq!(bridge.counters().sequence_gaps, 2);
    }

    // --- bytes ---

    fn sample_messages() -> Vec<MavMessage> {
        let mut bridge = Bridge::new(BridgeConfig::default()).unwrap();
        target(&mut bridge, goal(1.0, 2.0, 3.0, 0.5)).unwrap();
        bridge
            .status_text(MavSeverity::MAV_SEVERITY_NOTICE, "exploration complete")
            .unwrap();
        let mut out = Vec::new();
        bridge.poll(100, |_, m| out.push(m.clone()));
        out.push(MavMessage::LOCAL_POSITION_NED(LOCAL_POSITION_NED_DATA {
            time_boot_ms: 42,
            x: 1.5,
            y: -2.5,
            z: -3.0,
            vx: 0.1,
            vy: 0.2,
            vz: -0.3,
        }));
        out.push(MavMessage::ATTITUDE(ATTITUDE_DATA {
            time_boot_ms: 43,
            roll: 0.1,
            pitch: -0.2,
            yaw: 3.0,
            rollspeed: 0.01,
            pitchspeed: 0.02,
            yawspeed: 0.03,
        }));
        out.push(odometry(
            [1.0, 2.0, -3.0],
            [FRAC_1_SQRT_2, 0.0, 0.0, FRAC_1_SQRT_2],
        ));
        out
    }

    fn header(sequence: u8) -> MavHeader {
        MavHeader {
            system_id: 1,
            component_id: 191,
            sequence,
        }
    }

    #[test]
    fn encode_decode_round_trip_every_message_type() {
        let messages = sample_messages();
        let names: Vec<_> = messages.iter().map(|m| m.message_name()).collect();
        assert_eq!(
            names,
            [
                "HEARTBEAT",
                "STATUSTEXT",
                "SET_POSITION_TARGET_LOCAL_NED",
                "LOCAL_POSITION_NED",
                "ATTITUDE",
                "ODOMETRY"
            ]
        );
        let mut stream = Vec::new();
        for (i, m) in messages.iter().enumerate() {
            let mut buf = [0u8; MAX_FRAME_LEN];
            let n = encode_v2(&header(i as u8), m, &mut buf).unwrap();
            assert_eq!(buf[0], 0xFD, "MAVLink 2 start marker");
            // Same bytes through the embedded-io writer.
            let mut out = [0u8; MAX_FRAME_LEN];
            let mut writer: &mut [u8] = &mut out;
            assert_eq!(write_v2(&mut writer, &header(i as u8), m), Ok(n));
            assert_eq!(out[..n], buf[..n]);
            assert!(
                matches!(encode_v2(&header(0), m, &mut buf[..n - 1]), Err(TransportError::BufferTooSmall { needed }) if needed == n)
            );
            stream.extend_from_slice(&buf[..n]);
        }
        for chunk in [1, 2, 7, 64, 65, 1000] {
            let mut decoder = MavlinkDecoder::new();
            let mut got = Vec::new();
            for piece in stream.chunks(chunk) {
                decoder.push(piece, |h, m| got.push((*h, m.clone())));
            }
            assert_eq!(got.len(), messages.len(), "chunk {chunk}");
            for (i, ((h, m), expected)) in got.iter().zip(&messages).enumerate() {
                assert_eq!(*h, header(i as u8));
                assert_eq!(m, expected, "chunk {chunk}");
            }
            let c = decoder.counters();
            assert_eq!((c.frames, c.messages, c.parse_errors), (6, 6, 0));
            assert_eq!(c.unframed_bytes(), 0);
        }
    }

    #[test]
    fn poll_write_and_read_from() {
        let mut bridge = Bridge::new(BridgeConfig::default()).unwrap();
        target(&mut bridge, goal(1.0, 2.0, 3.0, 0.0)).unwrap();
        let mut out = [0u8; 512];
        let mut writer: &mut [u8] = &mut out;
        let n = bridge.poll_write(0, &mut writer).unwrap();
        let mut source: &[u8] = &out[..n];
        let mut decoder = MavlinkDecoder::new();
        let mut names = Vec::new();
        while decoder
            .read_from(&mut source, |_, m| names.push(m.message_name()))
            .unwrap()
            > 0
        {}
        assert_eq!(names, ["HEARTBEAT", "SET_POSITION_TARGET_LOCAL_NED"]);

        // A writer that is full: counted, reported, and the stream goes on.
        let mut tiny = [0u8; 4];
        let mut writer: &mut [u8] = &mut tiny;
        assert_eq!(bridge.poll_write(1000, &mut writer), Err(TransportError::Io));
        assert_eq!(bridge.counters().write_errors, 2);
    }

    #[test]
    fn decoder_resynchronises_after_garbage() {
        let messages = sample_messages();
        let mut decoder = MavlinkDecoder::new();
        let mut got = Vec::new();
        let mut buf = [0u8; MAX_FRAME_LEN];
        // Garbage with start markers in it, a truncated frame, then a good frame.
        decoder.push(&[0x00, 0xFD, 0x05, 0xFE, 0x33, 0xFD], |_, m| got.push(m.clone()));
        let n = encode_v2(&header(0), &messages[3], &mut buf).unwrap();
        decoder.push(&buf[..n / 2], |_, m| got.push(m.clone()));
        let n = encode_v2(&header(1), &messages[4], &mut buf).unwrap();
        decoder.push(&buf[..n], |_, m| got.push(m.clone()));
        assert_eq!(got.last(), Some(&messages[4]));
        assert!(decoder.counters().unframed_bytes() > 0);
    }

    #[test]
    fn decoder_hands_out_frames_as_they_arrived() {
        let messages = sample_messages();
        let mut wire = std::vec![0x55, 0xFD, 0x01];
        let mut sent = Vec::new();
        for (i, m) in messages.iter().enumerate() {
            let mut buf = [0u8; MAX_FRAME_LEN];
            let n = encode_v2(&header(i as u8), m, &mut buf).unwrap();
            wire.extend_from_slice(&buf[..n]);
            sent.push(buf[..n].to_vec());
        }
        let mut decoder = MavlinkDecoder::new();
        let mut frames = Vec::new();
        let mut decoded = Vec::new();
        // Odd slices, so frames straddle pushes.
        for piece in wire.chunks(7) {
            decoder.push_frames(piece, |raw, message| {
                frames.push(raw.to_vec());
                decoded.push(message.map(|(h, m)| (h.sequence, m.clone())));
            });
        }
        assert_eq!(frames, sent);
        for (i, d) in decoded.iter().enumerate() {
            assert_eq!(d.as_ref(), Some(&(i as u8, messages[i].clone())));
        }
        let c = decoder.counters();
        assert_eq!(c.framed_bytes, sent.iter().map(|f| f.len() as u64).sum::<u64>());
        assert_eq!(c.unframed_bytes(), 3);
    }

    #[test]
    fn garbage_and_damaged_streams_never_panic() {
        let messages = sample_messages();
        let mut frames = Vec::new();
        for (i, m) in messages.iter().enumerate() {
            let mut buf = [0u8; MAX_FRAME_LEN];
            let n = encode_v2(&header(i as u8), m, &mut buf).unwrap();
            frames.push(buf[..n].to_vec());
        }
        let mut rng = Lcg(0xDECAF);
        let mut decoder = MavlinkDecoder::new();
        let mut bridge = Bridge::new(BridgeConfig::default()).unwrap();
        let mut now = 0u64;
        for round in 0..5000 {
            let mut input = Vec::new();
            match round % 5 {
                // Pure noise, with start markers now and then.
                0 => {
                    for _ in 0..rng.below(600) {
                        input.push(match rng.below(10) {
                            0 => 0xFD,
                            1 => 0xFE,
                            _ => rng.byte(),
                        });
                    }
                }
                // A valid frame with bytes flipped.
                1 => {
                    input = frames[rng.below(frames.len() as u32) as usize].clone();
                    for _ in 0..=rng.below(4) {
                        let at = rng.below(input.len() as u32) as usize;
                        input[at] ^= 1 << rng.below(8);
                    }
                }
                // A truncated frame.
                2 => {
                    let frame = &frames[rng.below(frames.len() as u32) as usize];
                    input.extend_from_slice(&frame[..rng.below(frame.len() as u32) as usize]);
                }
                // A frame of a known message id whose payload is random but whose checksum is
                // right, so the generated parsers see arbitrary payloads (and enum values).
                3 => {
                    let id = [0u32, 30, 32, 84, 253, 331][rng.below(6) as usize];
                    let len = rng.below(256) as usize;
                    input.extend_from_slice(&[0xFD, len as u8, 0, 0, rng.byte(), 1, 1]);
                    input.extend_from_slice(&id.to_le_bytes()[..3]);
                    for _ in 0..len {
                        input.push(rng.byte());
                    }
                    let crc = ::mavlink::calculate_crc(&input[1..], MavMessage::extra_crc(id));
                    input.extend_from_slice(&crc.to_le_bytes());
                }
                // A valid frame cut in random pieces between noise.
                _ => {
                    input.push(rng.byte());
                    input.extend_from_slice(&frames[rng.below(frames.len() as u32) as usize]);
                    input.push(rng.byte());
                }
            }
            let mut rest = &input[..];
            while !rest.is_empty() {
                let (piece, tail) = rest.split_at(1 + rng.below(rest.len() as u32) as usize);
                decoder.push(piece, |h, m| {
                    let _ = bridge.handle(now, h, m);
                });
                rest = tail;
            }
            bridge.poll(now, |_, _| {});
            now += 7;
        }
        let c = *decoder.counters();
        assert!(c.messages > 0 && c.parse_errors > 0, "{c:?}");
        assert!(c.unframed_bytes() > 0);
        assert_eq!(c.frames, c.messages + c.parse_errors);
        // Still in sync: a clean frame decodes.
        let mut got = Vec::new();
        decoder.push(&[0u8; 300], |_, _| {});
        decoder.push(&frames[0], |_, m| got.push(m.clone()));
        assert_eq!(got, [messages[0].clone()]);
        // Some of the noise passed as pose messages with wild values and was rejected.
        assert!(bridge.counters().rejected() + bridge.counters().foreign_system > 0);
    }

    fn timed_local(t: u32, ned: [f32; 3]) -> MavMessage {
        MavMessage::LOCAL_POSITION_NED(LOCAL_POSITION_NED_DATA {
            time_boot_ms: t,
            x: ned[0],
            y: ned[1],
            z: ned[2],
            ..LOCAL_POSITION_NED_DATA::DEFAULT
        })
    }

    fn timed_attitude(t: u32, yaw_ned: f32) -> MavMessage {
        MavMessage::ATTITUDE(ATTITUDE_DATA {
            time_boot_ms: t,
            yaw: yaw_ned,
            ..ATTITUDE_DATA::DEFAULT
        })
    }

    #[test]
    fn pose_history_interpolates_by_the_autopilots_clock_not_arrival() {
        let mut h = PoseHistory::<8>::new();
        assert_eq!(h.pose_at(0), Err(PoseAtError::NoPose));
        // Samples 50 ms apart by the autopilot's clock, arriving with jitter (arrival times
        // must not matter). Heading East (NED yaw π/2) turning clockwise at 90°/s, flying
        // North at 1 m/s.
        for (k, arrived) in [(0u32, 1000u64), (1, 1093), (2, 1101), (3, 1180)] {
            let t = 5000 + 50 * k;
            let s = k as f32 * 0.05;
            assert!(h.record(arrived, &timed_local(t, [s, 0.0, -1.0])));
            assert!(h.record(arrived, &timed_attitude(t, PI / 2.0 + s * PI / 2.0)));
        }
        assert_eq!(h.newest_ms(), Some(5150));
        // Halfway between the second and third samples: t = 5075 ms, 0.075 s after the first.
        let p = h.pose_at(5075).unwrap();
        assert!((p.position - Point3::new(0.0, 0.075, 1.0)).norm() < 1e-5, "{p:?}");
        // NED yaw π/2 + 0.075·π/2 → map yaw −0.075·π/2; turning clockwise in the map (−).
        assert!(angle_close(p.yaw, -0.075 * PI / 2.0), "{}", p.yaw);
        let rate = p.yaw_rate.unwrap();
        assert!((rate + PI / 2.0).abs() < 1e-3, "{rate}");
        assert_eq!((p.time_boot_ms, p.arrived_ms), (5075, 1101));
        // Exactly at a sample: that sample.
        let q = h.pose_at(5150).unwrap();
        assert!((q.position - Point3::new(0.0, 0.15, 1.0)).norm() < 1e-6);
        assert_eq!(h.pose_at(5151), Err(PoseAtError::NotYet { newest_ms: 5150 }));
        assert_eq!(h.pose_at(4999), Err(PoseAtError::Forgotten));
        // The attitude at the instant is the same as the bridge's for the same sample.
        let mut bridge = Bridge::new(BridgeConfig::default()).unwrap();
        let mut seq = 0u8;
        feed_pose(
            &mut bridge,
            1180,
            &mut seq,
            [0.15, 0.0, -1.0],
            PI / 2.0 + 0.15 * PI / 2.0,
        );
        let b = bridge.pose(1180).unwrap();
        assert!(angle_close(b.yaw, q.yaw) && (b.position - q.position).norm() < 1e-6);
        assert!((b.attitude.rotation.angle_to(&q.attitude.rotation)).abs() < 1e-5);
    }

    #[test]
    fn pose_history_pairs_streams_wraps_yaw_and_survives_restarts() {
        let mut h = PoseHistory::<4>::new();
        // Attitude ahead of position: the newest instant both cover is the position's.
        h.record(0, &timed_local(100, [0.0, 0.0, -1.0]));
        h.record(0, &timed_attitude(100, 3.0));
        h.record(0, &timed_attitude(200, -3.0));
        h.record(0, &timed_local(300, [1.0, 0.0, -1.0]));
        assert_eq!(h.newest_ms(), Some(200));
        // Yaw 3.0 → −3.0 is 0.283 rad clockwise through ±π, not 6 rad back.
        let p = h.pose_at(150).unwrap();
        let (_, yaw_ned) = map_to_ned(p.position, p.yaw);
        assert!(angle_close(yaw_ned, PI), "{yaw_ned}");
        let rate_ned = -p.yaw_rate.unwrap();
        assert!((rate_ned - (2.0 * PI - 6.0) / 0.1).abs() < 1e-2, "{rate_ned}");
        // Reordered: dropped and counted. Capacity: the oldest goes.
        assert!(!h.record(0, &timed_local(250, [0.5, 0.0, -1.0])));
        assert_eq!(h.counters().out_of_order, 1);
        for t in [1400u32, 1500, 1600, 1700] {
            h.record(0, &timed_local(t, [0.0, 0.0, -1.0]));
        }
        assert!(matches!(h.pose_at(150), Err(PoseAtError::Forgotten)));
        // The autopilot restarted: its clock went back by more than a second.
        assert!(h.record(0, &timed_local(20, [0.0, 0.0, -1.0])));
        assert_eq!(h.counters().restarts, 1);
        assert_eq!(h.newest_ms(), None);
        // Not finite: not stored. Other messages: ignored.
        assert!(!h.record(0, &timed_attitude(30, f32::NAN)));
        assert!(!h.record(0, &MavMessage::HEARTBEAT(HEARTBEAT_DATA::DEFAULT)));
        // A single attitude sample gives no rate.
        h.record(0, &timed_attitude(20, 0.0));
        assert_eq!(h.pose_at(20).unwrap().yaw_rate, None);
    }

    #[test]
    fn state_fits_a_microcontroller() {
        // The bridge (mostly its STATUSTEXT queue) and the decoder (one maximum frame) are all
        // the RAM MAVLink costs; both live in `static`s on the firmware.
        assert!(
            core::mem::size_of::<Bridge>() <= 1024,
            "{}",
            core::mem::size_of::<Bridge>()
        );
        assert!(
            core::mem::size_of::<MavlinkDecoder>() <= 512,
            "{}",
            core::mem::size_of::<MavlinkDecoder>()
        );
    }
}
