//! The firmware's loop, independent of the board: two byte streams and a clock in, an
//! [`Explorer`] in the middle.
//!
//! - **Depth link (UART0).** Bytes go into a [`DepthReceiver`]; every complete depth frame with
//!   its camera pose is integrated at once, then the explorer plans from the vehicle pose the
//!   MAVLink bridge holds. The plan goes to the bridge, and back over the link's return channel
//!   go the map (two bits per voxel, [`downlink`]) and a [`PlanReport`] — the camera side's
//!   "frame N done".
//! - **MAVLink (UART1).** Bytes go into a [`MavlinkDecoder`] and on to the [`Bridge`]
//!   (LOCAL_POSITION_NED + ATTITUDE → vehicle pose). A TIMESYNC request from the autopilot is a
//!   *flight tick*: the firmware advances its [`Follower`] along the plan's waypoints, streams
//!   what the bridge has due (setpoint, heartbeat, STATUSTEXT) and answers the TIMESYNC last, so
//!   the autopilot side knows that everything sent before the request has been acted on.
//!
//! **Time.** The firmware keeps time by the autopilot's clock: the `time_boot_ms` of its pose
//! messages and the timestamp of its TIMESYNC requests. Setpoint periods and pose staleness are
//! then measured in the flight stack's time, which under processor-in-the-loop simulation is
//! the simulator's — however many instructions a plan takes, no simulated time passes during
//! it (lockstep). A flight build that must stream setpoints during a long plan would run the
//! bridge from a timer interrupt on the board clock instead.

use core::mem::MaybeUninit;

use embedded_io::{Read, ReadReady, Write};
use harmonic_core::domain::Label;
use harmonic_core::downlink::{self, PlanReport, MAP_SLICE_VOXELS};
use harmonic_core::explore::{
    Clock, ConfigError, Explorer, ExplorerConfig, ExplorerStorage, Fault, Goal, PlanOutcome,
};
use harmonic_core::link::{
    max_encoded_len, DepthReceiver, LinkEncoder, LinkError, LinkEvent, Message as LinkMessage, Pose,
    ResendRequest, HEADER_LEN, MAX_RESEND_RANGES, RESEND_REQUEST_HEADER_LEN,
};
use harmonic_core::map::{Dims, MapError, MapGeometry};
use harmonic_core::mavlink::common::TIMESYNC_DATA;
use harmonic_core::mavlink::{
    encode_v2, Bridge, BridgeConfig, MavHeader, MavMessage, MavlinkDecoder, AUTOPILOT_COMPONENT_ID,
    DEFAULT_SYSTEM_ID, MAX_FRAME_LEN, ONBOARD_COMPUTER_COMPONENT_ID,
};
use harmonic_core::operator::OperatorState;
use harmonic_core::signing::{SecretKey, Signer, Verifier, VerifierCounters};
use harmonic_core::solve::Bf16;
use harmonic_core::streamline::{advance_radius, Waypoints};
use nalgebra::Point3;

/// Voxels along x of the firmware's grid.
pub const NX: usize = 64;
/// Voxels along y.
pub const NY: usize = 64;
/// Voxels along z.
pub const NZ: usize = 32;
/// Voxels in the grid.
pub const VOXELS: usize = NX * NY * NZ;
/// Voxel edge, metres: the grid covers 6.4 × 6.4 × 3.2 m.
pub const RESOLUTION: f32 = 0.1;
/// Map-frame position of the grid's minimum corner.
pub const ORIGIN: [f32; 3] = [0.0, 0.0, 0.0];
/// Cells of the multigrid's coarse levels for the grid (32·32·16 + 16·16·8 + 8·8·4 + 4·4·2 +
/// 2·2·1); checked against `scratch_size` when the explorer is built.
pub const COARSE_CELLS: usize = 18_724;
/// Flood-fill queue entries (larger fills sweep, see `harmonic_core::domain`).
pub const QUEUE_LEN: usize = 2048;
/// Largest depth image, pixels.
pub const MAX_DEPTH_PIXELS: usize = 100 * 100;
/// Bytes of the depth link's frame decoder: one chunk of 10 rows of a 100-pixel-wide image.
pub const LINK_DECODER_BYTES: usize = 2048;
/// Link speed of both UARTs, baud (8N1).
pub const BAUD: u32 = 921_600;
/// Resend requests per depth image at most; then the image is taken with the rows that came
/// (as `harmonic-sim --link-arq-rounds` defaults to).
pub const ARQ_ROUNDS: u8 = 4;
/// Payload bytes (header and body) of the largest resend request.
const RESEND_REQUEST_MAX_LEN: usize = HEADER_LEN + RESEND_REQUEST_HEADER_LEN + 4 * MAX_RESEND_RANGES;

/// After a complete exploration the firmware flies home, as `harmonic-sim explore` does by
/// default; false holds where the exploration ended.
pub const RETURN_HOME_AFTER_COMPLETE: bool = true;
/// MAVLink 2 signing key shared with the autopilot (64 hex digits), taken from the build
/// environment: `HARMONIC_FW_MAVLINK_KEY=$(cat key.hex) cargo build -p harmonic-fw …`. With a
/// key every frame the firmware sends is signed and only frames the key signed are acted on
/// (see [`harmonic_core::signing`]); without one, neither. A key that is not 64 hex digits
/// fails the build.
pub const MAVLINK_KEY: Option<SecretKey> = match option_env!("HARMONIC_FW_MAVLINK_KEY") {
    Some(hex) => Some(built_in_key(hex)),
    None => None,
};
/// Signing streams (system, component, link) the firmware's verifier tells apart: the
/// autopilot, a ground station or two, and room to spare.
pub const SIGNING_STREAMS: usize = 8;

/// The built-in key, read at compile time for [`MAVLINK_KEY`] by the same parser as
/// `--mavlink-key` files ([`SecretKey::from_hex`]); a bad one stops the build.
#[allow(
    clippy::panic,
    reason = "evaluated only for the MAVLINK_KEY constant: the panic is a build error naming the variable"
)]
const fn built_in_key(hex: &str) -> SecretKey {
    match SecretKey::from_hex(hex) {
        Ok(key) => key,
        Err(_) => panic!("HARMONIC_FW_MAVLINK_KEY: not 64 hex digits"),
    }
}

/// MAVLink 2 signing on the firmware's side of UART1. The board has no calendar clock, so, as
/// the signing spec recommends for such systems, it signs with time taken from the newest
/// timestamp it has accepted, advanced by the autopilot time since (the signer also never
/// repeats one). Until it has accepted a signed frame its own frames carry boot-relative
/// timestamps, which an autopilot that already signs refuses as stale — the firmware speaks
/// once it has heard the autopilot.
#[derive(Debug, Clone)]
struct Signing {
    signer: Signer,
    verifier: Verifier<SIGNING_STREAMS>,
    /// (newest accepted timestamp, autopilot ms when it was accepted).
    anchor: Option<(u64, u64)>,
}

impl Signing {
    fn new(key: SecretKey) -> Self {
        Self {
            signer: Signer::new(key.clone(), 0),
            verifier: Verifier::new(key),
            anchor: None,
        }
    }

    /// The signing time (10 µs units) at autopilot time `now_ms`.
    fn now(&self, now_ms: u64) -> u64 {
        match self.anchor {
            Some((stamp, at_ms)) => stamp.saturating_add(now_ms.saturating_sub(at_ms).saturating_mul(100)),
            None => now_ms.saturating_mul(100),
        }
    }

    /// Whether a received frame may be acted on (counted either way); an accepted one moves
    /// the clock.
    fn admits(&mut self, raw: &[u8], now_ms: u64) -> bool {
        let ok = self.verifier.check(raw).is_ok();
        if ok {
            self.anchor = Some((self.verifier.newest(), now_ms));
        }
        ok
    }
}

/// Everything the explorer and the link work in; lives in one `static` on the MCU. Zeroed
/// (`.bss`): the explorer initialises what it needs.
pub struct Storage {
    log_odds: [i8; VOXELS],
    touched: [u32; VOXELS / 32],
    labels: [Label; VOXELS],
    phi: [f32; VOXELS],
    queue: [u32; QUEUE_LEN],
    /// bfloat16: 73 KiB instead of 146 KiB (see `harmonic_core::solve::multigrid::CoarseValues`).
    coarse_values: [Bf16; 2 * COARSE_CELLS],
    coarse_labels: [Label; COARSE_CELLS],
    depth: [u16; MAX_DEPTH_PIXELS],
}

impl Storage {
    /// All zeros.
    pub const fn new() -> Self {
        Self {
            log_odds: [0; VOXELS],
            touched: [0; VOXELS / 32],
            labels: [Label::Outside; VOXELS],
            phi: [0.0; VOXELS],
            queue: [0; QUEUE_LEN],
            coarse_values: [Bf16::ZERO; 2 * COARSE_CELLS],
            coarse_labels: [Label::Outside; COARSE_CELLS],
            depth: [0; MAX_DEPTH_PIXELS],
        }
    }
}

impl Default for Storage {
    fn default() -> Self {
        Self::new()
    }
}

/// The firmware's map geometry. (The constants are valid, so this is `Ok`; a port that edits
/// them gets the reason at boot instead of a panic.)
pub fn geometry() -> Result<MapGeometry, MapError> {
    MapGeometry::new(Dims::new(NX, NY, NZ)?, Point3::from(ORIGIN), RESOLUTION)
}

/// The explorer configuration: the host's defaults, with plain V-cycles (no Krylov storage
/// fits) and a cap on cycles so one plan stays bounded.
pub fn explorer_config() -> ExplorerConfig {
    let mut config = ExplorerConfig::default();
    config.solve.max_iterations = 400;
    // The `cold-start` feature measures cold solves (fw-budget): every solve from ψ = 0.
    config.solve.warm_start = !cfg!(feature = "cold-start");
    config
}

/// What the main loop is doing (for the watchdog's stall report).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(target_os = "none", derive(defmt::Format))]
pub enum Phase {
    /// Waiting for bytes.
    Idle,
    /// Integrating a depth frame.
    Integrate,
    /// Planning.
    Plan,
    /// Sending the map and the report.
    Report,
}

/// A stream failed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(target_os = "none", derive(defmt::Format))]
pub enum IoError {
    /// The depth link.
    Link,
    /// MAVLink.
    Mavlink,
}

/// What one pass of the loop did, for the log. (Returned and logged at once, never stored.)
#[derive(Debug, Clone, Copy, PartialEq)]
#[allow(clippy::large_enum_variant)]
pub enum Event {
    /// A frame was integrated and planned from.
    Planned(PlanReport),
    /// A depth frame arrived without a camera pose and was not integrated.
    FrameWithoutPose(u32),
    /// A link frame or chunk was dropped.
    LinkError(LinkError),
    /// A flight tick was answered, at this autopilot time (ms).
    FlightTick(u64),
}

/// Follows a plan's waypoints one setpoint at a time: the first waypoint the vehicle is not yet
/// within [`advance_radius`](harmonic_core::streamline::advance_radius) of (less where the path
/// turns, so corners are not cut), with the heading of travel towards it, and at the last
/// one the goal's yaw.
#[derive(Debug, Clone, Default)]
pub struct Follower {
    waypoints: Waypoints,
    next: usize,
    goal_yaw: f32,
    heading: Option<(usize, f32)>,
    turning: bool,
    active: bool,
}

impl Follower {
    /// Starts following `waypoints` to `goal`.
    pub fn follow(&mut self, waypoints: &[Point3<f32>], goal: &Goal) {
        self.waypoints.clear();
        for w in waypoints {
            if self.waypoints.push(*w).is_err() {
                break;
            }
        }
        if self.waypoints.is_empty() {
            let _ = self.waypoints.push(goal.position);
        }
        self.next = 0;
        self.goal_yaw = goal.yaw;
        self.heading = None;
        self.turning = false;
        self.active = true;
    }

    /// Stops following (the bridge holds).
    pub fn stop(&mut self) {
        self.active = false;
    }

    /// The setpoint for a vehicle at `position` with heading `yaw`, if following.
    pub fn setpoint(&mut self, position: &Point3<f32>, yaw: f32) -> Option<(Point3<f32>, f32)> {
        if !self.active {
            return None;
        }
        let len = self.waypoints.len();
        while self.next + 1 < len
            && self
                .waypoints
                .get(self.next)
                .is_some_and(|w| (w - position).norm() < advance_radius(&self.waypoints, self.next))
        {
            self.next += 1;
        }
        let target = self.waypoints.get(self.next).copied().unwrap_or(*position);
        if self.next + 1 >= len && (target - position).norm() < 1e-3 {
            self.turning = true;
        }
        let yaw = if self.turning {
            self.goal_yaw
        } else {
            match self.heading {
                Some((i, h)) if i == self.next => h,
                _ => {
                    let h = travel_heading(&(target - position)).unwrap_or(yaw);
                    self.heading = Some((self.next, h));
                    h
                }
            }
        };
        Some((target, yaw))
    }
}

/// Heading of travel along `seg`, unless it is mostly vertical.
fn travel_heading(seg: &nalgebra::Vector3<f32>) -> Option<f32> {
    let horizontal = libm::sqrtf(seg.x * seg.x + seg.y * seg.y);
    (horizontal > 0.2 * seg.norm()).then(|| libm::atan2f(seg.y, seg.x))
}

/// Builds the explorer over `storage`, in place in `slot` (a `static` on the MCU), and returns
/// it with the depth-image buffer. Its own function, so its stack frame (the explorer under
/// construction) is gone before the rest of the firmware is built.
#[inline(never)]
pub fn build_explorer<'a>(
    storage: &'a mut Storage,
    slot: &'a mut MaybeUninit<Explorer<'a>>,
) -> Result<(&'a mut Explorer<'a>, &'a mut [u16]), ConfigError> {
    let Storage {
        log_odds,
        touched,
        labels,
        phi,
        queue,
        coarse_values,
        coarse_labels,
        depth,
    } = storage;
    let explorer = Explorer::new(
        geometry().map_err(ConfigError::Map)?,
        explorer_config(),
        ExplorerStorage {
            log_odds,
            touched,
            labels,
            phi,
            queue,
            coarse_values: coarse_values.as_mut_slice().into(),
            coarse_labels,
            // No face conductances: 73 KiB the 1 MiB budget does not have (see
            // `MultigridStorage::faces`); coarse levels use the label-only operator.
            coarse_faces: &mut [],
            krylov: &mut [],
            // 128 KiB more than the budget has: sweeps test the labels instead.
            masks: &mut [],
            surface: &mut [],
            // The thesis's Jacobi solve is a host-side ablation.
            jacobi: &mut [],
            // No room for a box (half a grid's labels and values): whole-grid re-solves.
            local_labels: &mut [],
            local_psi: &mut [],
            flat: &mut [],
        },
    )?;
    Ok((slot.write(explorer), depth))
}

/// The firmware: explorer, link receiver, MAVLink bridge and the glue between them.
pub struct Firmware<'a> {
    explorer: &'a mut Explorer<'a>,
    receiver: DepthReceiver<'a, LINK_DECODER_BYTES>,
    mavlink: MavlinkDecoder,
    bridge: Bridge,
    follower: Follower,
    now_ms: u64,
    mav_sequence: u8,
    downlink_sequence: u16,
    tick_hz: u32,
    /// Where a return home goes: the position of the first plan.
    home: Option<Point3<f32>>,
    /// MAVLink signing, with [`MAVLINK_KEY`].
    signing: Option<Signing>,
    /// Encodes resend requests for the depth link's return channel.
    return_encoder: LinkEncoder,
    /// The frame the last resend requests were for, and how many were sent.
    arq: Option<(u32, u8)>,
    /// Resend requests sent.
    resend_requests: u32,
    /// An image that arrived without its pose, waiting for it.
    awaiting_pose: Option<u32>,
}

impl<'a> Firmware<'a> {
    /// Builds the firmware around `explorer` (see [`build_explorer`]) and the depth-image
    /// buffer; `tick_hz` is the rate of the clock later passed to [`Firmware::poll`].
    pub fn new(
        explorer: &'a mut Explorer<'a>,
        depth: &'a mut [u16],
        tick_hz: u32,
    ) -> Result<Self, ConfigError> {
        let mut bridge = Bridge::new(BridgeConfig::default()).map_err(|_| ConfigError::StorageTooSmall)?;
        // Sent with the first flight tick (the queue is empty: this cannot be refused).
        let _ = bridge.exploration_started();
        Ok(Self {
            explorer,
            receiver: DepthReceiver::new(depth),
            mavlink: MavlinkDecoder::new(),
            bridge,
            follower: Follower::default(),
            now_ms: 0,
            mav_sequence: 0,
            downlink_sequence: 0,
            tick_hz,
            home: None,
            signing: MAVLINK_KEY.map(Signing::new),
            return_encoder: LinkEncoder::new(),
            arq: None,
            resend_requests: 0,
            awaiting_pose: None,
        })
    }

    /// The explorer.
    pub fn explorer(&self) -> &Explorer<'a> {
        self.explorer
    }

    /// What MAVLink signing accepted and refused (`None` when built without a key).
    pub fn signing_counters(&self) -> Option<VerifierCounters> {
        self.signing.as_ref().map(|s| *s.verifier.counters())
    }

    /// One pass: takes what both streams have ready and acts on it. `phase` is told what the
    /// pass is doing (the watchdog's stall report). Returns what happened worth logging.
    pub fn poll<L, M, C>(
        &mut self,
        link: &mut L,
        mav: &mut M,
        clock: &mut C,
        mut phase: impl FnMut(Phase),
    ) -> Result<Option<Event>, IoError>
    where
        L: Read + ReadReady + Write,
        M: Read + ReadReady + Write,
        C: Clock,
    {
        let mut buf = [0u8; 256];
        let mut ticked = None;
        if mav.read_ready().map_err(|_| IoError::Mavlink)? {
            let n = mav.read(&mut buf).map_err(|_| IoError::Mavlink)?;
            if self.on_mavlink(buf.get(..n).unwrap_or(&[]), mav)? {
                ticked = Some(Event::FlightTick(self.now_ms));
            }
        }
        if !link.read_ready().map_err(|_| IoError::Link)? {
            return Ok(ticked);
        }
        let n = link.read(&mut buf).map_err(|_| IoError::Link)?;
        let Self {
            receiver, explorer, ..
        } = self;
        let mut taken = Taken {
            delivered: None,
            without_pose: None,
            pose: None,
            heartbeat: false,
            event: ticked,
        };
        receiver.feed(buf.get(..n).unwrap_or(&[]), |e| {
            taken.take(e, explorer, clock, &mut phase)
        });
        // An image that came without its pose waits for it (asked for below), kept in the
        // receiver's buffer.
        if let Some(frame_id) = taken.without_pose {
            self.awaiting_pose = Some(frame_id);
        }
        if let (Some(frame_id), Some(pose)) = (self.awaiting_pose, taken.pose) {
            if pose.frame_id() == frame_id {
                self.awaiting_pose = None;
                if let Some(frame) = self.receiver.completed_frame() {
                    phase(Phase::Integrate);
                    let t0 = clock.ticks();
                    let _ = self.explorer.integrate(&frame, &pose.isometry());
                    taken.delivered = Some((frame_id, clock.ticks().saturating_sub(t0)));
                }
            }
        }
        if taken.delivered.is_none() && (taken.heartbeat || taken.without_pose.is_some()) {
            // The camera side has sent what it had (its Heartbeat follows each image), or an
            // image lacks its pose: ask for what is missing, or, once asked often enough, take
            // what came.
            if let Some(frame_id) = self.receiver.frame_in_progress().or(self.awaiting_pose) {
                let rounds = match self.arq {
                    Some((id, r)) if id == frame_id => r,
                    _ => 0,
                };
                match self.receiver.resend_request(frame_id, true) {
                    Some(request) if rounds < ARQ_ROUNDS => {
                        self.arq = Some((frame_id, rounds + 1));
                        self.resend_requests = self.resend_requests.saturating_add(1);
                        self.send_link(&LinkMessage::ResendRequest(request), link)?;
                    }
                    _ if self.awaiting_pose == Some(frame_id) => {
                        // No pose came: the image cannot be placed. Planned from, not
                        // integrated, so the camera side still hears "frame N done".
                        self.awaiting_pose = None;
                        taken.event = Some(Event::FrameWithoutPose(frame_id));
                        taken.delivered = Some((frame_id, 0));
                    }
                    _ => {
                        let Self {
                            receiver, explorer, ..
                        } = self;
                        receiver.finish_frame(|e| taken.take(e, explorer, clock, &mut phase));
                        if let Some(frame_id) = taken.without_pose.filter(|_| taken.delivered.is_none()) {
                            taken.event = Some(Event::FrameWithoutPose(frame_id));
                            taken.delivered = Some((frame_id, 0));
                        }
                    }
                }
            }
        }
        if let Some((frame_id, _)) = taken.delivered {
            // Acknowledged at once (an empty request), before the plan: the camera side
            // knows the image is in and waits for the report however long the plan takes.
            self.send_link(&LinkMessage::ResendRequest(ResendRequest::new(frame_id)), link)?;
        }
        let mut event = taken.event;
        if let Some((frame_id, integrate_ticks)) = taken.delivered {
            phase(Phase::Plan);
            let report = self.plan(frame_id, integrate_ticks, mav, clock)?;
            phase(Phase::Report);
            self.send_downlink(&report, link)?;
            event = Some(Event::Planned(report));
        }
        Ok(event)
    }

    /// One link message on the return channel (resend requests).
    fn send_link<L: Write>(&mut self, message: &LinkMessage<'_>, link: &mut L) -> Result<(), IoError> {
        let mut out = [0u8; max_encoded_len(RESEND_REQUEST_MAX_LEN)];
        let n = self
            .return_encoder
            .encode(message, &mut out)
            .map_err(|_| IoError::Link)?;
        link.write_all(out.get(..n).unwrap_or(&[]))
            .map_err(|_| IoError::Link)?;
        link.flush().map_err(|_| IoError::Link)
    }

    /// MAVLink bytes from the autopilot (and any ground station on the same wire); true if
    /// they ended a flight tick. With signing, a frame the key did not sign is counted and
    /// dropped before anything reads it.
    fn on_mavlink<M: Write>(&mut self, bytes: &[u8], mav: &mut M) -> Result<bool, IoError> {
        let Self {
            mavlink,
            bridge,
            now_ms,
            signing,
            ..
        } = self;
        let mut timesync = None;
        mavlink.push_frames(bytes, |raw, decoded| {
            let Some((header, message)) = decoded else {
                return;
            };
            if signing.as_mut().is_some_and(|s| !s.admits(raw, *now_ms)) {
                return;
            }
            let autopilot = header.system_id == u32::from(DEFAULT_SYSTEM_ID)
                && header.component_id == AUTOPILOT_COMPONENT_ID;
            if autopilot {
                match message {
                    MavMessage::LOCAL_POSITION_NED(d) => *now_ms = (*now_ms).max(u64::from(d.time_boot_ms)),
                    MavMessage::ATTITUDE(d) => *now_ms = (*now_ms).max(u64::from(d.time_boot_ms)),
                    MavMessage::TIMESYNC(d) if d.tc1 == 0 => {
                        *now_ms = (*now_ms).max(u64::try_from(d.ts1 / 1_000_000).unwrap_or(0));
                        timesync = Some(d.ts1);
                    }
                    _ => {}
                }
            }
            let _ = bridge.handle(*now_ms, header, message);
        });
        if let Some(ts1) = timesync {
            self.flight_tick(mav)?;
            let reply = MavMessage::TIMESYNC(TIMESYNC_DATA {
                // tc1 = 0 would read as a request: at time 0 answer with 1 ns.
                tc1: i64::try_from(self.now_ms.saturating_mul(1_000_000))
                    .unwrap_or(i64::MAX)
                    .max(1),
                ts1,
            });
            self.send_mavlink(&reply, mav)?;
        }
        Ok(timesync.is_some())
    }

    /// Advances along the plan and streams what is due.
    fn flight_tick<M: Write>(&mut self, mav: &mut M) -> Result<(), IoError> {
        if let Ok(pose) = self.bridge.pose(self.now_ms) {
            if let Some((target, yaw)) = self.follower.setpoint(&pose.position, pose.yaw) {
                // Refused only while the pose is stale; the bridge then holds by itself.
                let _ = self.bridge.set_target(target, yaw);
            }
        }
        let Self {
            bridge,
            signing,
            now_ms,
            ..
        } = self;
        let mut result = Ok(());
        bridge.poll(*now_ms, |header, message| {
            if let Err(e) = write_frame(mav, signing.as_mut(), *now_ms, header, message) {
                result = Err(e);
            }
        });
        result
    }

    fn send_mavlink<M: Write>(&mut self, message: &MavMessage, mav: &mut M) -> Result<(), IoError> {
        let header = MavHeader {
            system_id: u32::from(DEFAULT_SYSTEM_ID),
            component_id: ONBOARD_COMPUTER_COMPONENT_ID,
            sequence: self.mav_sequence,
        };
        self.mav_sequence = self.mav_sequence.wrapping_add(1);
        write_frame(mav, self.signing.as_mut(), self.now_ms, &header, message)
    }

    /// Plans from the bridge's vehicle pose and hands the plan to the bridge and the follower.
    fn plan<M: Write, C: Clock>(
        &mut self,
        frame_id: u32,
        integrate_ticks: u64,
        mav: &mut M,
        clock: &mut C,
    ) -> Result<PlanReport, IoError> {
        // Without a pose the explorer refuses the plan (BadPose) and counts it.
        let (position, yaw) = match self.bridge.pose(self.now_ms) {
            Ok(p) => (p.position, p.yaw),
            Err(_) => (Point3::new(f32::NAN, f32::NAN, f32::NAN), 0.0),
        };
        let kept_before = self.explorer.status().plans_kept;
        // Home is where the first plan was made from.
        if self.home.is_none() && position.coords.iter().all(|c| c.is_finite()) {
            self.home = Some(position);
        }
        // The operator decides: explore, go home, or hold (paused, aborted, waiting).
        let state = self.bridge.operator_state();
        let outcome = match (state, self.home) {
            (OperatorState::Exploring, _) => self.explorer.plan_timed(&position, yaw, clock),
            (OperatorState::ReturningHome, Some(home)) => {
                self.explorer.plan_home(&position, yaw, &home, clock)
            }
            (OperatorState::ReturningHome, None) => PlanOutcome::Hold(Fault::HomeUnreachable),
            _ => PlanOutcome::Hold(Fault::Operator),
        };
        let kept = self.explorer.status().plans_kept > kept_before;
        match outcome {
            PlanOutcome::Complete if state == OperatorState::ReturningHome => self.bridge.arrived_home(),
            PlanOutcome::Complete if RETURN_HOME_AFTER_COMPLETE && self.home.is_some() => {
                // Explored ("exploration complete" goes out), then home by the same way the
                // operator's return-to-launch takes: the next frame plans it.
                self.bridge.apply(&outcome);
                self.bridge.return_home();
            }
            _ => self.bridge.apply(&outcome),
        }
        match &outcome {
            PlanOutcome::Goal(goal) => self.follower.follow(self.explorer.waypoints(), goal),
            _ => self.follower.stop(),
        }
        self.flight_tick(mav)?;
        Ok(PlanReport::new(
            frame_id,
            &outcome,
            kept,
            position.coords.into(),
            yaw,
            self.explorer.status(),
            integrate_ticks,
            self.tick_hz,
            self.receiver.counters(),
        )
        .with_resend_requests(self.resend_requests)
        .with_operator(self.bridge.operator_state())
        .with_signing(self.signing_counters()))
    }

    /// The map, then the report, back over the link.
    fn send_downlink<L: Write>(&mut self, report: &PlanReport, link: &mut L) -> Result<(), IoError> {
        let mut out = [0u8; downlink::max_frame_len(6 + MAP_SLICE_VOXELS / 4)];
        let map = self.explorer.map();
        let mut first = 0;
        while first < VOXELS {
            let seq = self.downlink_sequence;
            self.downlink_sequence = seq.wrapping_add(1);
            match downlink::encode_map_slice(seq, map, first, MAP_SLICE_VOXELS, &mut out) {
                Ok((n, count)) if count > 0 => {
                    link.write_all(out.get(..n).unwrap_or(&[]))
                        .map_err(|_| IoError::Link)?;
                    first += count;
                }
                _ => break,
            }
        }
        let seq = self.downlink_sequence;
        self.downlink_sequence = seq.wrapping_add(1);
        let n = downlink::encode_report(seq, report, &mut out).map_err(|_| IoError::Link)?;
        link.write_all(out.get(..n).unwrap_or(&[]))
            .map_err(|_| IoError::Link)?;
        link.flush().map_err(|_| IoError::Link)
    }
}

/// What one read of the depth link delivered.
struct Taken {
    /// The frame to plan from: its id and the ticks integrating it took (0 for a frame whose
    /// pose never came: it is not integrated, but still planned from and reported, so the
    /// camera side hears "frame N done").
    delivered: Option<(u32, u64)>,
    /// An image that came whole or finished without its pose.
    without_pose: Option<u32>,
    /// A Pose that came.
    pose: Option<Pose>,
    /// The camera side's Heartbeat came: it has sent what it had.
    heartbeat: bool,
    /// What to log.
    event: Option<Event>,
}

impl Taken {
    fn take<C: Clock>(
        &mut self,
        e: LinkEvent<'_>,
        explorer: &mut Explorer<'_>,
        clock: &mut C,
        phase: &mut impl FnMut(Phase),
    ) {
        match e {
            LinkEvent::Depth {
                frame_id,
                frame,
                pose: Some(pose),
                ..
            } => {
                phase(Phase::Integrate);
                let t0 = clock.ticks();
                // A rejected frame is counted by the explorer and reported like any other.
                // Rows that never arrived hold NOT_RECEIVED, which integration skips.
                let _ = explorer.integrate(&frame, &pose.isometry());
                self.delivered = Some((frame_id, clock.ticks().saturating_sub(t0)));
            }
            LinkEvent::Depth { frame_id, .. } => self.without_pose = Some(frame_id),
            LinkEvent::Pose(pose) => self.pose = Some(pose),
            LinkEvent::Heartbeat(_) => self.heartbeat = true,
            LinkEvent::Error(e) => self.event = Some(Event::LinkError(e)),
            _ => {}
        }
    }
}

/// Writes one MAVLink 2 frame, signed if `signing` is set.
fn write_frame<M: Write>(
    mav: &mut M,
    signing: Option<&mut Signing>,
    now_ms: u64,
    header: &MavHeader,
    message: &MavMessage,
) -> Result<(), IoError> {
    let mut frame = [0u8; MAX_FRAME_LEN];
    let mut n = encode_v2(header, message, &mut frame).map_err(|_| IoError::Mavlink)?;
    if let Some(s) = signing {
        let stamp = s.now(now_ms);
        // Only a frame the encoder did not write could be refused; it goes out as it is.
        n = s.signer.sign(&mut frame, n, stamp).unwrap_or(n);
    }
    mav.write_all(frame.get(..n).unwrap_or(&[]))
        .map_err(|_| IoError::Mavlink)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn follower_walks_the_waypoints_then_turns_to_the_goal_yaw() {
        let mut f = Follower::default();
        let goal = Goal {
            position: Point3::new(2.0, 1.0, 1.0),
            yaw: 1.0,
            frontier: harmonic_core::map::VoxelIndex::new(0, 0, 0),
            escape: false,
        };
        let wps = [
            Point3::new(0.0, 0.0, 1.0),
            Point3::new(1.0, 0.0, 1.0),
            goal.position,
        ];
        f.follow(&wps, &goal);
        let (t, yaw) = f.setpoint(&Point3::new(0.0, 0.0, 1.0), 0.3).unwrap();
        assert_eq!(t, wps[1], "the vehicle stands on the first waypoint");
        assert!(yaw.abs() < 1e-6, "heading along +x");
        let (t, yaw) = f.setpoint(&Point3::new(1.0, 0.0, 1.0), 0.0).unwrap();
        assert_eq!(t, goal.position);
        assert!(
            (yaw - core::f32::consts::FRAC_PI_4).abs() < 1e-6,
            "heading to (2, 1)"
        );
        let (t, yaw) = f.setpoint(&goal.position, yaw).unwrap();
        assert_eq!((t, yaw), (goal.position, 1.0));
        f.stop();
        assert!(f.setpoint(&goal.position, 0.0).is_none());
    }

    #[test]
    fn the_build_time_key_reads_as_hex_and_signing_time_follows_the_autopilot() {
        let key = built_in_key("  000102030405060708090a0b0c0d0e0f101112131415161718191A1B1C1D1E1F\n");
        let mut bytes = [0u8; 32];
        bytes.iter_mut().enumerate().for_each(|(i, b)| *b = i as u8);
        assert_eq!(key.as_bytes(), &bytes);
        let mut signing = Signing::new(key);
        assert_eq!(
            signing.now(1500),
            150_000,
            "boot-relative until a signed frame is accepted"
        );
        // A signed frame accepted at 2 s sets the clock; 1.5 s later it reads 150 000 more.
        signing.anchor = Some((7_000_000_000, 2000));
        assert_eq!(signing.now(3500), 7_000_150_000);
        // An unsigned frame is refused and does not move it.
        let mut frame = [0u8; MAX_FRAME_LEN];
        let header = MavHeader {
            system_id: 255,
            component_id: 190,
            sequence: 0,
        };
        let n = encode_v2(
            &header,
            &MavMessage::HEARTBEAT(harmonic_core::mavlink::common::HEARTBEAT_DATA::DEFAULT),
            &mut frame,
        )
        .unwrap();
        assert!(!signing.admits(&frame[..n], 4000));
        assert_eq!(signing.anchor, Some((7_000_000_000, 2000)));
        assert_eq!(signing.verifier.counters().unsigned, 1);
    }

    #[test]
    fn the_grid_fits_the_multigrid_scratch_and_the_budget() {
        let g = geometry().unwrap();
        let need = harmonic_core::solve::multigrid::scratch_size(&g.dims());
        assert_eq!(need.values, 2 * COARSE_CELLS);
        assert_eq!(need.labels, COARSE_CELLS);
        assert_eq!(
            harmonic_core::map::touched_words(&g.dims()),
            VOXELS / 32,
            "touched bitset"
        );
        // The whole state must leave room for the stack in 1 MiB.
        assert!(core::mem::size_of::<Storage>() < 1000 * 1024);
    }
}
