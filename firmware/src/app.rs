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
use harmonic_core::link::{DepthReceiver, LinkError, LinkEvent};
use harmonic_core::map::{Dims, MapError, MapGeometry};
use harmonic_core::mavlink::common::TIMESYNC_DATA;
use harmonic_core::mavlink::{
    write_v2, Bridge, BridgeConfig, MavHeader, MavMessage, MavlinkDecoder, AUTOPILOT_COMPONENT_ID,
    DEFAULT_SYSTEM_ID, ONBOARD_COMPUTER_COMPONENT_ID,
};
use harmonic_core::operator::OperatorState;
use harmonic_core::solve::Bf16;
use harmonic_core::streamline::Waypoints;
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
/// within [`Follower::ADVANCE_M`] of, with the heading of travel towards it, and at the last
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
    /// How close (metres) the vehicle must come to a waypoint before the next is streamed.
    pub const ADVANCE_M: f32 = 0.1;

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
                .is_some_and(|w| (w - position).norm() < Self::ADVANCE_M)
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
            // The thesis's Jacobi solve is a host-side ablation.
            jacobi: &mut [],
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
        })
    }

    /// The explorer.
    pub fn explorer(&self) -> &Explorer<'a> {
        self.explorer
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
        let mut integrated = None;
        let mut event = ticked;
        receiver.feed(buf.get(..n).unwrap_or(&[]), |e| match e {
            LinkEvent::Depth {
                frame_id,
                frame,
                pose: Some(pose),
                ..
            } => {
                phase(Phase::Integrate);
                let t0 = clock.ticks();
                // A rejected frame is counted by the explorer and reported like any other.
                let _ = explorer.integrate(&frame, &pose.isometry());
                integrated = Some((frame_id, clock.ticks().saturating_sub(t0)));
            }
            LinkEvent::Depth { frame_id, .. } => event = Some(Event::FrameWithoutPose(frame_id)),
            LinkEvent::Error(e) => event = Some(Event::LinkError(e)),
            _ => {}
        });
        if let Some((frame_id, integrate_ticks)) = integrated {
            phase(Phase::Plan);
            let report = self.plan(frame_id, integrate_ticks, mav, clock)?;
            phase(Phase::Report);
            self.send_downlink(&report, link)?;
            event = Some(Event::Planned(report));
        }
        Ok(event)
    }

    /// MAVLink bytes from the autopilot; true if they ended a flight tick.
    fn on_mavlink<M: Write>(&mut self, bytes: &[u8], mav: &mut M) -> Result<bool, IoError> {
        let Self {
            mavlink,
            bridge,
            now_ms,
            ..
        } = self;
        let mut timesync = None;
        mavlink.push(bytes, |header, message| {
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
        self.bridge
            .poll_write(self.now_ms, mav)
            .map(|_| ())
            .map_err(|_| IoError::Mavlink)
    }

    fn send_mavlink<M: Write>(&mut self, message: &MavMessage, mav: &mut M) -> Result<(), IoError> {
        let header = MavHeader {
            system_id: u32::from(DEFAULT_SYSTEM_ID),
            component_id: ONBOARD_COMPUTER_COMPONENT_ID,
            sequence: self.mav_sequence,
        };
        self.mav_sequence = self.mav_sequence.wrapping_add(1);
        write_v2(mav, &header, message)
            .map(|_| ())
            .map_err(|_| IoError::Mavlink)
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
        ))
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
