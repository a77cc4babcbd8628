//! The companion computer: the one object that runs the exploration loop on any board.
//!
//! A [`Companion`] owns everything between two byte streams and a clock:
//!
//! - **Depth link in.** Bytes go into a [`DepthReceiver`]; every complete depth frame with its
//!   camera pose is integrated at once, then the [`Explorer`] plans from the vehicle pose the
//!   MAVLink bridge holds. Lost rows are asked for again over the link's return channel
//!   (resend requests, at most [`CompanionConfig::arq_rounds`] per image); back over the same
//!   channel go the map (two bits per voxel, [`downlink`]) and a [`PlanReport`], the camera
//!   side's "frame N done".
//! - **MAVLink.** Bytes go into a [`MavlinkDecoder`] and on to the [`Bridge`]
//!   (LOCAL_POSITION_NED + ATTITUDE, or ODOMETRY → vehicle pose; a ground station's
//!   COMMAND_LONG → the [operator](crate::links::operator) state). A TIMESYNC request from the
//!   autopilot is a *flight tick*: the companion advances its [`Follower`] along the plan's
//!   waypoints, streams what the bridge has due (setpoint, heartbeat, STATUSTEXT, COMMAND_ACK)
//!   and answers the TIMESYNC last, so the autopilot side knows that everything sent before
//!   the request has been acted on. With a signing key every frame it sends is signed and only
//!   frames the key signed are acted on ([`LinkSigning`]).
//!
//! The operator decides what a plan is: explore ([`Explorer::plan_timed`]), go home
//! ([`Explorer::plan_home`], to where the first plan was made), or hold. After a complete
//! exploration the companion flies home if [`CompanionConfig::return_home_after_complete`].
//!
//! **The grid.** A board is built with a capacity, not a grid: before the mission,
//! [`GeometryWait`] reads the grid's dimensions, origin and resolution off the depth link and
//! answers them (taken, or refused with what the grid needs and what the board has); the board
//! carves its storage for a grid that fits and builds the companion around it. A repeat of the
//! grid (the answer was lost) is answered again by the companion.
//!
//! The firmware (`harmonic-fw`) is a board around this object: UARTs, a timer, statics. The host
//! simulator runs the same object in-process over pipes, or plays the world around it on QEMU.
//!
//! **Time.** The companion keeps time by the autopilot's clock: the `time_boot_ms` of its pose
//! messages and the timestamp of its TIMESYNC requests. Setpoint periods and pose staleness are
//! then measured in the flight stack's time, which under processor-in-the-loop simulation is
//! the simulator's: however many instructions a plan takes, no simulated time passes during it
//! (lockstep). A flight build that must stream setpoints during a long plan would run the
//! bridge from a timer interrupt on the board clock instead.

mod follower;
mod geometry;
mod io;
mod mission;
mod signing;

pub use follower::{travel_heading, Follower};
pub use geometry::{GeometryWait, Waited};
pub use io::IoError;
pub use mission::{After, Mission, Planning, Step};
pub use signing::LinkSigning;

use core::fmt::Write as _;

use embedded_io::{Read, ReadReady, Write};
use nalgebra::Point3;

use crate::clock::Clock;
use crate::links::downlink::{
    self, GeometryAnswer, PlanReport, ReportOutcome, Resource, Shortfall, MAP_SLICE_VOXELS,
};
use crate::links::link::{
    max_encoded_len, DepthReceiver, LinkEncoder, LinkError, LinkEvent, Message as LinkMessage, Pose,
    ResendRequest, HEADER_LEN, MAX_RESEND_RANGES, RESEND_REQUEST_HEADER_LEN,
};
use crate::links::mavlink::common::TIMESYNC_DATA;
use crate::links::mavlink::{
    encode_v2, Bridge, BridgeConfig, MavHeader, MavMessage, MavlinkDecoder, StatusText,
    AUTOPILOT_COMPONENT_ID, DEFAULT_SYSTEM_ID, MAX_FRAME_LEN, ONBOARD_COMPUTER_COMPONENT_ID,
};
use crate::links::signing::{SecretKey, VerifierCounters};
use crate::mapping::map::MapGeometry;
use crate::planning::explore::{
    ConfigError, Explorer, Fault, Goal, HarmonicField, PlanOutcome, TargetChoice,
};

/// Payload bytes (header and body) of the largest resend request.
const RESEND_REQUEST_MAX_LEN: usize = HEADER_LEN + RESEND_REQUEST_HEADER_LEN + 4 * MAX_RESEND_RANGES;

/// How a companion behaves.
#[derive(Debug, Clone)]
pub struct CompanionConfig {
    /// The MAVLink bridge: ids, periods, pose timeout.
    pub bridge: BridgeConfig,
    /// Resend requests per depth image at most; then the image is taken with the rows that
    /// came (as `harmonic-sim --link-arq-rounds` defaults to).
    pub arq_rounds: u8,
    /// After a complete exploration, fly home (as `harmonic-sim explore` does by default);
    /// false holds where the exploration ended.
    pub return_home_after_complete: bool,
    /// Rate of the [`Clock`] passed to [`Companion::poll`], ticks per second (reported in each
    /// [`PlanReport`]).
    pub tick_hz: u32,
    /// MAVLink 2 signing key shared with the autopilot: with one, every frame sent is signed
    /// and only frames the key signed are acted on; without one, neither.
    pub signing_key: Option<SecretKey>,
    /// Scans at evenly spaced headings, turning on the spot, before the first plan (0 or 1:
    /// plan after the first scan). Without it a start whose first view leaves the vehicle's
    /// surroundings unobserved can end the exploration at once, the vehicle's voxel being the
    /// whole safe space. Default 0; the simulator's runs use 4.
    pub look_around: u32,
}

impl Default for CompanionConfig {
    fn default() -> Self {
        Self {
            bridge: BridgeConfig::default(),
            arq_rounds: 4,
            return_home_after_complete: true,
            tick_hz: 1,
            signing_key: None,
            look_around: 0,
        }
    }
}

/// What a pass of the loop is doing (for a watchdog's stall report).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
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

/// The companion computer: explorer, depth-link receiver, MAVLink bridge, follower, operator
/// and signing, and the glue between them (see the [module documentation](self)).
/// `LINK_BYTES` is the depth-link decoder's frame buffer, `STREAMS` the signing streams
/// (system, component, link) its verifier tells apart, `T` the explorer's target choice (the
/// harmonic field unless a board flies another planner).
pub struct Companion<'a, const LINK_BYTES: usize, const STREAMS: usize, T: TargetChoice = HarmonicField<'a>> {
    explorer: &'a mut Explorer<'a, T>,
    receiver: DepthReceiver<'a, LINK_BYTES>,
    mavlink: MavlinkDecoder,
    bridge: Bridge,
    follower: Follower,
    config: CompanionConfig,
    now_ms: u64,
    mav_sequence: u8,
    downlink_sequence: u16,
    /// Look-around, exploration, the way home: where a return home goes is the position of the
    /// first plan.
    mission: Mission,
    /// MAVLink signing, with [`CompanionConfig::signing_key`].
    signing: Option<LinkSigning<STREAMS>>,
    /// Encodes resend requests for the depth link's return channel.
    return_encoder: LinkEncoder,
    /// The frame the last resend requests were for, and how many were sent.
    arq: Option<(u32, u8)>,
    /// Resend requests sent.
    resend_requests: u32,
    /// An image that arrived without its pose, waiting for it.
    awaiting_pose: Option<u32>,
    /// The vehicle pose a board handed over directly ([`Companion::hand_pose`]), if any.
    handed_pose: Option<(Point3<f32>, f32)>,
    /// What the last plan (or look-around turn) decided.
    last_plan: Option<PlanOutcome>,
}

impl<'a, const LINK_BYTES: usize, const STREAMS: usize, T: TargetChoice>
    Companion<'a, LINK_BYTES, STREAMS, T>
{
    /// A companion around `explorer`, receiving depth images of up to `depth.len()` pixels.
    pub fn new(
        explorer: &'a mut Explorer<'a, T>,
        depth: &'a mut [u16],
        config: CompanionConfig,
    ) -> Result<Self, ConfigError> {
        let mut bridge = Bridge::new(config.bridge).map_err(|_| ConfigError::StorageTooSmall)?;
        // Sent with the first flight tick (the queue is empty: this cannot be refused).
        let _ = bridge.exploration_started();
        let mission = Mission::new(config.look_around, config.return_home_after_complete);
        Ok(Self {
            explorer,
            receiver: DepthReceiver::new(depth),
            mavlink: MavlinkDecoder::new(),
            bridge,
            follower: Follower::default(),
            signing: config.signing_key.clone().map(LinkSigning::new),
            config,
            now_ms: 0,
            mav_sequence: 0,
            downlink_sequence: 0,
            mission,
            return_encoder: LinkEncoder::new(),
            arq: None,
            resend_requests: 0,
            awaiting_pose: None,
            handed_pose: None,
            last_plan: None,
        })
    }

    /// Hands the companion the vehicle's pose (map frame position and yaw) directly, for a
    /// board whose flight stack is in the same process and needs no MAVLink for it (the
    /// simulator's ideal autopilot). From now on plans are made from the pose handed over last,
    /// not from the bridge's.
    pub fn hand_pose(&mut self, position: Point3<f32>, yaw: f32) {
        self.handed_pose = Some((position, yaw));
    }

    /// What the last plan decided (a look-around turn is a goal that keeps the position), if
    /// one was made; its way is [`Companion::follower`]'s.
    pub fn last_plan(&self) -> Option<&PlanOutcome> {
        self.last_plan.as_ref()
    }

    /// The follower, which holds the way of the last goal.
    pub fn follower(&self) -> &Follower {
        &self.follower
    }

    /// The explorer.
    pub fn explorer(&self) -> &Explorer<'a, T> {
        self.explorer
    }

    /// The MAVLink bridge.
    pub fn bridge(&self) -> &Bridge {
        &self.bridge
    }

    /// The autopilot time the companion has reached, ms.
    pub fn now_ms(&self) -> u64 {
        self.now_ms
    }

    /// What MAVLink signing accepted and refused (`None` without a key).
    pub fn signing_counters(&self) -> Option<VerifierCounters> {
        self.signing.as_ref().map(|s| *s.counters())
    }

    /// One pass: takes what both streams have ready and acts on it. `phase` is told what the
    /// pass is doing (a watchdog's stall report). Returns what happened worth logging.
    // One copy, not inlined into a board's loop: inlined into the firmware's `main` it cost
    // 2.6 KiB of flash more.
    #[inline(never)]
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
        let mut taken = Taken {
            delivered: None,
            without_pose: None,
            pose: None,
            heartbeat: false,
            geometry: None,
            event: ticked,
        };
        let Self {
            receiver, explorer, ..
        } = self;
        receiver.feed(buf.get(..n).unwrap_or(&[]), |e| {
            taken.take(e, explorer, clock, &mut phase)
        });
        if let Some(geometry) = taken.geometry {
            self.answer_geometry(&geometry, link)?;
        }
        self.place_awaited(&mut taken, clock, &mut phase);
        if taken.delivered.is_none() && (taken.heartbeat || taken.without_pose.is_some()) {
            self.ask_or_give_up(&mut taken, link, clock, &mut phase)?;
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

    /// A grid repeated after the mission started (the camera side did not hear the answer):
    /// taken again if it is the mission's, refused otherwise.
    fn answer_geometry<L: Write>(&mut self, geometry: &MapGeometry, link: &mut L) -> Result<(), IoError> {
        let voxels = geometry::voxels(geometry);
        let answer = if geometry == self.explorer.observed_map().geometry() {
            GeometryAnswer::Taken { voxels }
        } else {
            GeometryAnswer::Refused(Shortfall {
                what: Resource::GridInUse,
                needed: voxels,
                capacity: 0,
            })
        };
        let seq = self.downlink_sequence;
        self.downlink_sequence = seq.wrapping_add(1);
        geometry::send_answer(seq, &answer, link)
    }

    /// An image that came without its pose waits for it in the receiver's buffer; once the
    /// pose comes it is integrated.
    fn place_awaited<C: Clock>(&mut self, taken: &mut Taken, clock: &mut C, phase: &mut impl FnMut(Phase)) {
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
    }

    /// The camera side has sent what it had (its Heartbeat follows each image), or an image
    /// lacks its pose: asks for what is missing, or, once asked often enough, takes what came.
    fn ask_or_give_up<L: Write, C: Clock>(
        &mut self,
        taken: &mut Taken,
        link: &mut L,
        clock: &mut C,
        phase: &mut impl FnMut(Phase),
    ) -> Result<(), IoError> {
        let Some(frame_id) = self.receiver.frame_in_progress().or(self.awaiting_pose) else {
            return Ok(());
        };
        let rounds = match self.arq {
            Some((id, r)) if id == frame_id => r,
            _ => 0,
        };
        match self.receiver.resend_request(frame_id, true) {
            Some(request) if rounds < self.config.arq_rounds => {
                self.arq = Some((frame_id, rounds + 1));
                self.resend_requests = self.resend_requests.saturating_add(1);
                self.send_link(&LinkMessage::ResendRequest(request), link)?;
            }
            _ if self.awaiting_pose == Some(frame_id) => {
                // No pose came: the image cannot be placed. Planned from, not integrated, so
                // the camera side still hears "frame N done".
                self.awaiting_pose = None;
                taken.event = Some(Event::FrameWithoutPose(frame_id));
                taken.delivered = Some((frame_id, 0));
            }
            _ => {
                let Self {
                    receiver, explorer, ..
                } = self;
                receiver.finish_frame(|e| taken.take(e, explorer, clock, phase));
                if let Some(frame_id) = taken.without_pose.filter(|_| taken.delivered.is_none()) {
                    taken.event = Some(Event::FrameWithoutPose(frame_id));
                    taken.delivered = Some((frame_id, 0));
                }
            }
        }
        Ok(())
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
                        *now_ms = (*now_ms)
                            .max(u64::try_from(d.ts1.checked_div(1_000_000).unwrap_or(0)).unwrap_or(0));
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
        let (position, yaw) = match (self.handed_pose, self.bridge.pose(self.now_ms)) {
            (Some(pose), _) => pose,
            (None, Ok(p)) => (p.position, p.yaw),
            (None, Err(_)) => (Point3::new(f32::NAN, f32::NAN, f32::NAN), 0.0),
        };
        let kept_before = self.explorer.status().plans_kept;
        // The operator decides: explore, go home, or hold (paused, aborted, waiting).
        let state = self.bridge.operator_state();
        let (outcome, home) = match self.mission.step(self.explorer, state, position, yaw, clock) {
            Step::Look(turn) => return self.look_around(frame_id, integrate_ticks, turn, yaw, mav),
            Step::Held(_) => (PlanOutcome::Hold(Fault::Operator), false),
            Step::Plan { outcome, home } => (outcome, home),
        };
        let kept = self.explorer.status().plans_kept > kept_before;
        match self.mission.after(&outcome, home) {
            After::Home => self.bridge.arrived_home(),
            After::Returning => {
                // Explored ("exploration complete" goes out), then home by the same way the
                // operator's return-to-launch takes: the next frame plans it.
                steer(&mut self.bridge, &outcome);
                self.bridge.return_home();
            }
            After::Continue | After::Done => steer(&mut self.bridge, &outcome),
        }
        match &outcome {
            PlanOutcome::Goal(goal) => self.follower.follow(self.explorer.waypoints(), goal),
            _ => self.follower.stop(),
        }
        self.last_plan = Some(outcome);
        self.flight_tick(mav)?;
        Ok(self.report(frame_id, &outcome, kept, integrate_ticks, (position, yaw)))
    }

    /// One turn of the look-around before the first plan ([`CompanionConfig::look_around`]):
    /// the vehicle stays where it is and turns to the mission's next heading.
    fn look_around<M: Write>(
        &mut self,
        frame_id: u32,
        integrate_ticks: u64,
        turn: Goal,
        yaw: f32,
        mav: &mut M,
    ) -> Result<PlanReport, IoError> {
        let position = turn.position;
        let outcome = PlanOutcome::Goal(turn);
        steer(&mut self.bridge, &outcome);
        self.follower.follow(&[position], &turn);
        self.last_plan = Some(outcome);
        self.flight_tick(mav)?;
        let mut report = self.report(frame_id, &outcome, false, integrate_ticks, (position, yaw));
        report.outcome = ReportOutcome::Look;
        Ok(report)
    }

    /// The report of a plan (or turn) made from `pose` after integrating for `integrate_ticks`:
    /// `outcome` as the explorer returned it, `kept` if it kept its committed goal, the
    /// explorer's status after the plan. (Here, not in the downlink: the wire format knows
    /// the report, not the planner.)
    fn report(
        &self,
        frame_id: u32,
        outcome: &PlanOutcome,
        kept: bool,
        integrate_ticks: u64,
        (position, yaw): (Point3<f32>, f32),
    ) -> PlanReport {
        let status = self.explorer.status();
        PlanReport {
            frame_id,
            outcome: match outcome {
                PlanOutcome::Goal(g) if g.escape => ReportOutcome::Escape,
                PlanOutcome::Goal(_) if kept => ReportOutcome::Kept,
                PlanOutcome::Goal(_) => ReportOutcome::Goal,
                PlanOutcome::Complete => ReportOutcome::Complete,
                PlanOutcome::Hold(f) => ReportOutcome::Hold(*f),
            },
            position: position.coords.into(),
            yaw,
            frames: status.frames,
            plans: status.plans,
            plans_kept: status.plans_kept,
            frontier: status.domain.frontier,
            interior: status.domain.interior,
            solver_iterations: status.solve.iterations,
            solver_residual: status.solve.residual,
            solver_updates: status.solve.cell_updates,
            streamline_length: status.streamline.map(|s| s.length).unwrap_or(0.0),
            tick_hz: self.config.tick_hz,
            integrate_ticks,
            domain_ticks: status.phase_ticks.domain,
            solve_ticks: status.phase_ticks.solve,
            streamline_ticks: status.phase_ticks.streamline,
            integration_ops: status.integration_ops,
            planning_ops: status.planning_ops,
            sealed: status.map.sealed,
            errors: status.errors,
            link: self.receiver.counters(),
            unreachable_frontier: status.unreachable_frontier,
            operator: None,
            signing: VerifierCounters::default(),
            resend_requests: 0,
            goal: match outcome {
                PlanOutcome::Goal(g) => Some((g.position.coords.into(), g.yaw)),
                _ => None,
            },
        }
        .with_resend_requests(self.resend_requests)
        .with_operator(self.bridge.operator_state())
        .with_signing(self.signing_counters())
    }

    /// The map, then the report, back over the link.
    fn send_downlink<L: Write>(&mut self, report: &PlanReport, link: &mut L) -> Result<(), IoError> {
        let mut out = [0u8; downlink::max_frame_len(6 + (MAP_SLICE_VOXELS >> 2))];
        let map = self.explorer.observed_map();
        let voxels = map.geometry().dims().len();
        let mut first = 0;
        while first < voxels {
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
    /// A grid geometry came (a repeat: the mission's grid is fixed).
    geometry: Option<MapGeometry>,
    /// What to log.
    event: Option<Event>,
}

impl Taken {
    fn take<C: Clock, T: TargetChoice>(
        &mut self,
        e: LinkEvent<'_>,
        explorer: &mut Explorer<'_, T>,
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
            LinkEvent::Geometry(g) => self.geometry = Some(g),
            LinkEvent::Error(e) => self.event = Some(Event::LinkError(e)),
            _ => {}
        }
    }
}

/// Acts on a plan through the MAVLink bridge: a goal is streamed (a goal the bridge refuses,
/// not finite or on a stale pose, holds); completion holds and announces itself once (NOTICE);
/// a fault holds and is announced when it differs from the previous one (WARNING); the
/// operator's hold was announced when the operator asked for it.
pub fn steer(bridge: &mut Bridge, outcome: &PlanOutcome) {
    match outcome {
        PlanOutcome::Goal(goal) => {
            if bridge.set_target(goal.position, goal.yaw).is_err() {
                bridge.hold();
            }
        }
        PlanOutcome::Complete => bridge.complete(),
        PlanOutcome::Hold(Fault::Operator) => bridge.hold(),
        PlanOutcome::Hold(fault) => {
            let mut text = StatusText::new();
            let _ = write!(text, "hold: {fault:?}");
            bridge.hold_because(text);
        }
    }
}

/// Writes one MAVLink 2 frame, signed if `signing` is set.
fn write_frame<M: Write, const STREAMS: usize>(
    mav: &mut M,
    signing: Option<&mut LinkSigning<STREAMS>>,
    now_ms: u64,
    header: &MavHeader,
    message: &MavMessage,
) -> Result<(), IoError> {
    let mut frame = [0u8; MAX_FRAME_LEN];
    let mut n = encode_v2(header, message, &mut frame).map_err(|_| IoError::Mavlink)?;
    if let Some(s) = signing {
        n = s.sign(&mut frame, n, now_ms);
    }
    mav.write_all(frame.get(..n).unwrap_or(&[]))
        .map_err(|_| IoError::Mavlink)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::links::mavlink::common::{MavSeverity, LOCAL_POSITION_NED_DATA};
    use crate::links::mavlink::SetpointKind;
    use crate::mapping::map::VoxelIndex;
    use crate::planning::explore::Goal;

    #[test]
    fn plans_steer_the_bridge_and_faults_are_announced_once() {
        let mut bridge = Bridge::new(BridgeConfig::default()).unwrap();
        let header = MavHeader {
            system_id: 1,
            component_id: 1,
            sequence: 0,
        };
        let position = MavMessage::LOCAL_POSITION_NED(LOCAL_POSITION_NED_DATA {
            x: 2.0,
            y: 1.0,
            z: -3.0,
            ..LOCAL_POSITION_NED_DATA::DEFAULT
        });
        let attitude = MavMessage::ATTITUDE(crate::links::mavlink::common::ATTITUDE_DATA::DEFAULT);
        bridge.handle(0, &header, &position).unwrap();
        bridge.handle(0, &header, &attitude).unwrap();
        let goal = Goal {
            position: Point3::new(4.0, 4.0, 1.0),
            yaw: 0.0,
            frontier: VoxelIndex::new(0, 0, 0),
            escape: false,
        };
        steer(&mut bridge, &PlanOutcome::Goal(goal));
        assert_eq!(bridge.setpoint().unwrap().kind, SetpointKind::Goal);
        for _ in 0..3 {
            steer(&mut bridge, &PlanOutcome::Hold(Fault::VehicleOutsideGrid));
        }
        steer(&mut bridge, &PlanOutcome::Hold(Fault::BadPose));
        steer(&mut bridge, &PlanOutcome::Hold(Fault::Operator));
        let setpoint = bridge.setpoint().unwrap();
        assert_eq!(setpoint.kind, SetpointKind::Hold);
        // Holds where the vehicle is: NED (2, 1, −3) → map (1, 2, 3).
        assert_eq!(setpoint.position, Point3::new(1.0, 2.0, 3.0));
        steer(&mut bridge, &PlanOutcome::Complete);
        steer(&mut bridge, &PlanOutcome::Complete);
        let mut texts: heapless::Vec<(MavSeverity, StatusText), 8> = heapless::Vec::new();
        bridge.poll(0, |_, m| {
            if let MavMessage::STATUSTEXT(d) = m {
                let text = core::str::from_utf8(d.text.as_ref())
                    .unwrap()
                    .trim_end_matches('\0');
                let _ = texts.push((d.severity, StatusText::from_str_truncated(text)));
            }
        });
        let texts: heapless::Vec<(MavSeverity, &str), 8> =
            texts.iter().map(|(s, t)| (*s, t.as_str())).collect();
        assert_eq!(
            texts.as_slice(),
            [
                (MavSeverity::MAV_SEVERITY_WARNING, "hold: VehicleOutsideGrid"),
                (MavSeverity::MAV_SEVERITY_WARNING, "hold: BadPose"),
                (MavSeverity::MAV_SEVERITY_NOTICE, "exploration complete"),
            ]
        );
    }

    extern crate std;

    use std::collections::VecDeque;
    use std::vec;
    use std::vec::Vec;

    use crate::links::link::{LinkEncoder, Message, Pose};
    use crate::mapping::camera::{DepthFrame, Intrinsics};
    use crate::mapping::map::{Dims, MapGeometry};
    use crate::planning::domain::Label;
    use crate::planning::explore::{forward_camera_pose, ExplorerConfig, ExplorerStorage};
    use crate::planning::solve::multigrid;

    /// One side of an in-memory UART.
    #[derive(Default)]
    struct Wire {
        to_companion: VecDeque<u8>,
        from_companion: Vec<u8>,
    }

    impl embedded_io::ErrorType for Wire {
        type Error = core::convert::Infallible;
    }

    impl embedded_io::Read for Wire {
        fn read(&mut self, buf: &mut [u8]) -> Result<usize, Self::Error> {
            let n = buf.len().min(self.to_companion.len());
            for (slot, b) in buf.iter_mut().zip(self.to_companion.drain(..n)) {
                *slot = b;
            }
            Ok(n)
        }
    }

    impl embedded_io::ReadReady for Wire {
        fn read_ready(&mut self) -> Result<bool, Self::Error> {
            Ok(!self.to_companion.is_empty())
        }
    }

    impl embedded_io::Write for Wire {
        fn write(&mut self, buf: &[u8]) -> Result<usize, Self::Error> {
            self.from_companion.extend_from_slice(buf);
            Ok(buf.len())
        }
        fn flush(&mut self) -> Result<(), Self::Error> {
            Ok(())
        }
    }

    /// A companion whose pose is handed over (no MAVLink) turns on the spot between its first
    /// scans, as many times as the look-around asks less one, then plans; the turns plan
    /// nothing and keep the vehicle where it is.
    #[test]
    fn the_look_around_turns_between_the_first_scans_then_plans() {
        let dims = Dims::new(40, 40, 20).unwrap();
        let geometry = MapGeometry::new(dims, Point3::origin(), 0.1).unwrap();
        let n = dims.len();
        let need = multigrid::scratch_size(&dims);
        let (mut log_odds, mut touched) = (
            vec![0i8; n],
            vec![0u32; crate::mapping::map::touched_words(&dims)],
        );
        let (mut labels, mut phi, mut queue) = (vec![Label::Outside; n], vec![0.0f32; n], vec![0u32; 4096]);
        let mut values = vec![0.0f32; need.values];
        let mut coarse_labels = vec![Label::Outside; need.labels];
        let storage = ExplorerStorage {
            log_odds: &mut log_odds,
            touched: &mut touched,
            labels: &mut labels,
            phi: &mut phi,
            queue: &mut queue,
            coarse_values: values.as_mut_slice().into(),
            coarse_labels: &mut coarse_labels,
            coarse_faces: &mut [],
            krylov: &mut [],
            masks: &mut [],
            surface: &mut [],
            jacobi: &mut [],
            local_labels: &mut [],
            local_psi: &mut [],
            flat: &mut [],
            fine_log_odds: &mut [],
            fine_touched: &mut [],
        };
        let mut explorer = Explorer::new(geometry, ExplorerConfig::default(), storage).unwrap();
        let mut depth_buffer = vec![0u16; 40 * 30];
        let config = CompanionConfig {
            look_around: 4,
            ..CompanionConfig::default()
        };
        let mut companion: Companion<'_, 2048, 4> =
            Companion::new(&mut explorer, &mut depth_buffer, config).unwrap();
        let (position, yaw) = (Point3::new(2.0, 2.0, 1.0), 0.3);
        companion.hand_pose(position, yaw);

        let intrinsics = Intrinsics::new(30.0, 30.0, 20.0, 15.0, 40, 30).unwrap();
        let depth = vec![1500u16; 40 * 30];
        let frame = DepthFrame::new(intrinsics, &depth).unwrap();
        let (mut link, mut mav) = (Wire::default(), Wire::default());
        let mut encoder = LinkEncoder::new();
        let mut scratch = vec![0u8; 4096];
        let mut outcomes = Vec::new();
        for frame_id in 1..=4u32 {
            let pose = Pose::from_isometry(frame_id, &forward_camera_pose(&position, yaw)).unwrap();
            let k = encoder.encode(&Message::Pose(pose), &mut scratch).unwrap();
            link.to_companion.extend(&scratch[..k]);
            encoder
                .encode_depth_frame(frame_id, &frame, 10, &mut scratch, |bytes| {
                    link.to_companion.extend(bytes)
                })
                .unwrap();
            let mut planned = None;
            while !link.to_companion.is_empty() {
                if let Some(Event::Planned(r)) = companion
                    .poll(&mut link, &mut mav, &mut crate::clock::NoClock, |_| {})
                    .unwrap()
                {
                    planned = Some(r);
                }
            }
            let report = planned.expect("every frame is planned from (or turned on)");
            outcomes.push((report.outcome, *companion.last_plan().unwrap()));
        }
        for (k, (outcome, plan)) in outcomes.iter().take(3).enumerate() {
            assert_eq!(*outcome, ReportOutcome::Look, "scan {}", k + 1);
            let PlanOutcome::Goal(turn) = plan else {
                panic!("{plan:?}")
            };
            assert_eq!(turn.position, position, "a turn keeps the vehicle where it is");
            assert!((turn.yaw - (yaw + core::f32::consts::FRAC_PI_2)).abs() < 1e-6);
        }
        assert_ne!(outcomes[3].0, ReportOutcome::Look, "the fourth scan plans");
        assert_eq!(
            companion.explorer().status().plans,
            1,
            "the turns planned nothing"
        );
        assert_eq!(
            companion.explorer().status().frames,
            4,
            "every scan was integrated"
        );
    }

    /// The geometry answers on a return channel, decoded.
    fn answers(wire: &Wire) -> Vec<GeometryAnswer> {
        let mut decoder = downlink::DownlinkDecoder::<64>::new();
        wire.from_companion
            .iter()
            .filter_map(|&b| match decoder.push(b) {
                Some(Ok(downlink::Downlink::Geometry(a))) => Some(a),
                _ => None,
            })
            .collect()
    }

    /// Before a mission, a grid over capacity is answered with both numbers and the wait goes
    /// on; a grid that fits is taken, and the bytes after it stay for the companion.
    #[test]
    fn the_wait_refuses_a_grid_over_capacity_takes_one_that_fits_and_leaves_what_follows() {
        let grid = |nx| MapGeometry::new(Dims::new(nx, 10, 10).unwrap(), Point3::origin(), 0.1).unwrap();
        let capacity = 1000u32;
        let fits = |g: &MapGeometry| {
            let needed = g.dims().len() as u32;
            if needed <= capacity {
                Ok(())
            } else {
                Err(Shortfall {
                    what: Resource::Voxels,
                    needed,
                    capacity,
                })
            }
        };
        let mut encoder = LinkEncoder::new();
        let mut scratch = [0u8; 128];
        let mut link = Wire::default();
        let mut put = |link: &mut Wire, m: &Message<'_>| {
            let k = encoder.encode(m, &mut scratch).unwrap();
            link.to_companion.extend(&scratch[..k]);
        };
        let heartbeat = Message::Heartbeat(crate::links::link::Heartbeat {
            uptime_ms: 0,
            frames_sent: 0,
            frames_skipped: 0,
            sensor_errors: 0,
        });
        // Noise first, then a grid of 2000 voxels.
        link.to_companion.extend([7u8, 1, 2, 0]);
        put(&mut link, &heartbeat);
        put(&mut link, &Message::Geometry(grid(20)));
        let mut wait = GeometryWait::new();
        let too_big = Shortfall {
            what: Resource::Voxels,
            needed: 2000,
            capacity,
        };
        assert_eq!(wait.poll(&mut link, fits), Ok(Waited::Refused(grid(20), too_big)));
        assert_eq!(wait.poll(&mut link, fits), Ok(Waited::Nothing));
        assert_eq!(wait.refused(), 1);
        assert_eq!(answers(&link), [GeometryAnswer::Refused(too_big)]);
        // A grid of 1000 voxels, and the mission's first bytes right behind it.
        put(&mut link, &Message::Geometry(grid(10)));
        put(&mut link, &heartbeat);
        let behind = link.to_companion.len();
        assert_eq!(wait.poll(&mut link, fits), Ok(Waited::Taken(grid(10))));
        assert!(behind > 0 && link.to_companion.len() < behind);
        let k = encoder.encode(&heartbeat, &mut scratch).unwrap();
        assert_eq!(link.to_companion.len(), k, "the heartbeat after the grid is left");
        assert_eq!(
            answers(&link),
            [
                GeometryAnswer::Refused(too_big),
                GeometryAnswer::Taken { voxels: 1000 }
            ]
        );
        let text = std::format!("{too_big}");
        assert!(text.contains("2000") && text.contains("1000"), "{text}");
    }
}
