//! The downlink: what the core reports back over the depth link's return channel.
//!
//! The depth link ([`crate::links::link`]) carries frames from the camera side to the core. On a UART
//! the other direction is free, and the core uses it to tell the camera side (and whoever
//! listens there: a ground station, the processor-in-the-loop simulator) what it did with each
//! frame:
//!
//! - [`PlanReport`] — after a depth frame was integrated and planned from: the frame id (the
//!   camera side's "frame N done"), the plan's outcome and goal, its statistics, the ticks each
//!   phase took and every fault counter, the link's included.
//! - a map slice — the occupancy state of a run of voxels, two bits each
//!   ([`encode_map_slice`]); a whole 64 × 64 × 32 map is 32 KiB in 1 KiB slices.
//! - a [`GeometryAnswer`] — before a mission, to the grid the camera side sent (a depth-link
//!   Geometry message): taken, or refused with what it needs and what the board has.
//!
//! Downlink frames use the link's framing exactly (a `0x00` delimiter, COBS of header, body and
//! CRC-32, a `0x00` delimiter; the 4-byte header of version, type and sequence number), with
//! message types of their own that have the high bit set, so a depth-link decoder that is fed
//! them drops them as an unknown type. The core's resend requests and acknowledgements (link
//! messages) share the return channel: a [`DownlinkDecoder`] passes those over as
//! [`Downlink::Link`], neither decoded nor counted as dropped.
//!
//! ```text
//! 0x81 PlanReport, 316 bytes (all little-endian)      0x82 MapSlice, 6 + ⌈count / 4⌉ bytes
//!   0  u32 frame_id   of the frame just planned from     0  u32 first   voxel index
//!   4  u8  outcome    0 goal 1 kept 2 escape             4  u16 count   1 ..= MAP_SLICE_VOXELS
//!                     3 complete 4 hold 5 look           6  u8[]  two bits per voxel, voxel
//!   5  u8  fault      0 none, else Fault (below)              first + k in bits 2(k % 4) of
//!   6  u8  detail     the fault's inner error                 byte k / 4: 0 unknown 1 free
//!   7  u8  operator   0 not reported, else 1 + the            2 occupied 3 uncertain
//!                     operator state's custom_mode
//!   8  f32 x, y, z, yaw   where the plan started (map frame)
//!  24  u32 frames, plans, plans_kept
//!  36  u32 frontier, interior             of the last domain
//!  44  u32 solver iterations, f32 residual, u64 cell updates   of the last solve
//!  60  f32 streamline length, metres (0 without one)
//!  64  u32 tick_hz    ticks per second of the fields below
//!  68  u64 ticks of integrate, domain, solve, streamline+goal
//! 100  u64 integration_ops, planning_ops  (totals)
//! 116  u32 sealed voxels
//! 120  u32 × 14 ErrorCounters, in declaration order
//! 176  u64 bytes, u32 × 15  LinkCounters, in declaration order
//! 244  u32 unreachable frontier voxels   at a complete end, else 0
//! 248  u32 × 7 VerifierCounters of MAVLink signing, in declaration order (0 without)
//! 276  u32 depth frames partial, u32 rows missing   (LinkCounters' last two)
//! 284  u32 resend requests sent on the return channel
//! 288  u32 reopenings (ErrorCounters, added after the others)
//! 292  u32 remnants_sealed (ErrorCounters, added after the others)
//! 296  u32 pocket_plans (ErrorCounters, added after the others)
//! 300  f32 x, y, z, yaw   the goal flown to (map frame); NaN without one
//!
//! 0x83 GeometryAnswer, 9 bytes
//!   0  u8  verdict   0 taken, 1 too many voxels, 2 too many multigrid cells,
//!                    3 a mission on another grid is under way, 4 too many planning cells
//!   1  u32 needed    the grid's voxels (verdicts 0, 1, 3), multigrid cells (2) or
//!                    planning cells (4)
//!   5  u32 capacity  what the board has room for (0 for verdict 3)
//! ```
//!
//! Fault codes: 1 BadPose, 2 VehicleOutsideGrid, 3 VehicleNotFree, 4 Streamline (detail:
//! 0 StartOutsideDomain, 1 Stalled, 2 TooLong, 3 StorageTooSmall), 5 Solver (detail:
//! 0 StorageTooSmall, 1 BadTolerance, 2 ScratchTooSmall, 3 Diverged, 4 BadScreening),
//! 6 Integrate (detail: 0 BadPose, 1 BadRange, 2 PoseJump, 3 TurningTooFast, 4 StalePose).

use crate::links::link::{cobs_decode_in_place, crc32, write_frame, LinkCounters, LinkError, Malformed};
use crate::links::link::{CRC_LEN, DELIMITER, HEADER_LEN, PROTOCOL_VERSION};
use crate::links::operator::OperatorState;
use crate::links::signing::VerifierCounters;
use crate::mapping::integrate::IntegrateError;
use crate::mapping::map::{Occupancy, VoxelMap};
use crate::planning::explore::{ErrorCounters, Fault};
use crate::planning::solve::SolveError;
use crate::planning::streamline::StreamlineError;

/// Message type of a [`PlanReport`].
pub const PLAN_REPORT: u8 = 0x81;
/// Message type of a map slice.
pub const MAP_SLICE: u8 = 0x82;
/// Message type of a [`GeometryAnswer`].
pub const GEOMETRY_ANSWER: u8 = 0x83;
/// Body bytes of a [`GeometryAnswer`].
pub const GEOMETRY_ANSWER_LEN: usize = 9;
/// Body bytes of a [`PlanReport`].
pub const PLAN_REPORT_LEN: usize = 316;
/// Most voxels in one map slice (1 KiB of states).
pub const MAP_SLICE_VOXELS: usize = 4096;
/// Header bytes of a map slice body before the states.
const MAP_SLICE_HEADER: usize = 6;

/// Encoded bytes of a downlink frame with a body of `body_len` bytes, at most (both
/// delimiters included).
pub const fn max_frame_len(body_len: usize) -> usize {
    crate::links::link::max_encoded_len(HEADER_LEN + body_len)
}

/// Why a downlink frame was dropped.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum DownlinkError {
    /// Framing, CRC, version, type or length, as on the depth link.
    Link(LinkError),
    /// A report with an outcome or fault code this version does not know (or a geometry answer
    /// with a verdict it does not know).
    BadOutcome,
}

impl From<LinkError> for DownlinkError {
    fn from(e: LinkError) -> Self {
        Self::Link(e)
    }
}

/// What a grid needs more of than a board has.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Resource {
    /// Voxels of the map (and the field over it).
    Voxels,
    /// Cells of the multigrid's coarse levels.
    CoarseCells,
    /// Cells of the grid the board plans on (coarser than the map).
    PlanningCells,
    /// A mission on another grid is under way (`needed` is the new grid's voxels, `capacity`
    /// 0): a board maps one grid per mission.
    GridInUse,
}

/// Why a board refused a grid: it needs `needed` of `what` and the board has `capacity`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Shortfall {
    /// What runs short.
    pub what: Resource,
    /// What the grid needs.
    pub needed: u32,
    /// What the board has room for.
    pub capacity: u32,
}

impl core::fmt::Display for Shortfall {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match self.what {
            Resource::Voxels => write!(
                f,
                "the grid has {} voxels and the board has room for {}",
                self.needed, self.capacity
            ),
            Resource::CoarseCells => write!(
                f,
                "the grid's multigrid needs {} coarse cells and the board has room for {}",
                self.needed, self.capacity
            ),
            Resource::PlanningCells => write!(
                f,
                "the grid needs {} planning cells and the board has room for {}",
                self.needed, self.capacity
            ),
            Resource::GridInUse => write!(
                f,
                "a mission on another grid is under way (this one has {} voxels)",
                self.needed
            ),
        }
    }
}

/// The core's answer to the grid the camera side sent before a mission.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum GeometryAnswer {
    /// The mission maps this grid of `voxels` voxels.
    Taken {
        /// The grid's voxels.
        voxels: u32,
    },
    /// The board cannot map this grid.
    Refused(Shortfall),
}

impl GeometryAnswer {
    fn write_body(&self) -> [u8; GEOMETRY_ANSWER_LEN] {
        let (verdict, needed, capacity) = match *self {
            GeometryAnswer::Taken { voxels } => (0u8, voxels, 0),
            GeometryAnswer::Refused(s) => {
                let verdict = match s.what {
                    Resource::Voxels => 1,
                    Resource::CoarseCells => 2,
                    Resource::GridInUse => 3,
                    Resource::PlanningCells => 4,
                };
                (verdict, s.needed, s.capacity)
            }
        };
        let mut body = [0u8; GEOMETRY_ANSWER_LEN];
        body[0] = verdict;
        body[1..5].copy_from_slice(&needed.to_le_bytes());
        body[5..].copy_from_slice(&capacity.to_le_bytes());
        body
    }

    fn read_body(body: &[u8]) -> Result<Self, DownlinkError> {
        let Ok(&[verdict, n0, n1, n2, n3, c0, c1, c2, c3]) = <&[u8; GEOMETRY_ANSWER_LEN]>::try_from(body)
        else {
            return Err(LinkError::Malformed(Malformed::BodyLength).into());
        };
        let needed = u32::from_le_bytes([n0, n1, n2, n3]);
        let capacity = u32::from_le_bytes([c0, c1, c2, c3]);
        let what = match verdict {
            0 => return Ok(GeometryAnswer::Taken { voxels: needed }),
            1 => Resource::Voxels,
            2 => Resource::CoarseCells,
            3 => Resource::GridInUse,
            4 => Resource::PlanningCells,
            _ => return Err(DownlinkError::BadOutcome),
        };
        Ok(GeometryAnswer::Refused(Shortfall {
            what,
            needed,
            capacity,
        }))
    }
}

/// Encodes `answer` with sequence number `seq` as one frame into `out`; returns its length.
/// [`max_frame_len`]`(`[`GEOMETRY_ANSWER_LEN`]`)` bytes always suffice.
pub fn encode_geometry_answer(seq: u16, answer: &GeometryAnswer, out: &mut [u8]) -> Result<usize, LinkError> {
    encode(seq, GEOMETRY_ANSWER, &[&answer.write_body()], out)
}

/// What the core did with one frame's plan, as it travels.
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum ReportOutcome {
    /// A new goal.
    Goal,
    /// The committed goal still stands; nothing was solved.
    Kept,
    /// A goal back out of inflated space.
    Escape,
    /// Nothing reachable is left.
    Complete,
    /// No plan: holding.
    Hold(Fault),
    /// A turn on the spot before the first plan (the companion's look-around): no plan.
    Look,
}

/// The core's report after planning from one depth frame. See the [module table](self).
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct PlanReport {
    /// Id of the depth frame planned from.
    pub frame_id: u32,
    /// The plan's outcome.
    pub outcome: ReportOutcome,
    /// Vehicle position the plan started from, map frame.
    pub position: [f32; 3],
    /// Vehicle yaw the plan started from.
    pub yaw: f32,
    /// Frames integrated so far.
    pub frames: u32,
    /// Plans made so far.
    pub plans: u32,
    /// Plans that kept the committed goal.
    pub plans_kept: u32,
    /// Frontier voxels of the last domain.
    pub frontier: u32,
    /// Interior unknowns of the last domain.
    pub interior: u32,
    /// Iterations of the last solve.
    pub solver_iterations: u32,
    /// Final relative residual of the last solve.
    pub solver_residual: f32,
    /// Cell updates of the last solve.
    pub solver_updates: u64,
    /// Length of the last streamline, metres (0 without one).
    pub streamline_length: f32,
    /// Ticks per second of the tick fields.
    pub tick_hz: u32,
    /// Ticks integrating the frame.
    pub integrate_ticks: u64,
    /// Ticks building the domain.
    pub domain_ticks: u64,
    /// Ticks solving.
    pub solve_ticks: u64,
    /// Ticks tracing the streamline and choosing the goal.
    pub streamline_ticks: u64,
    /// Voxel updates by integration so far.
    pub integration_ops: u64,
    /// Solver cell updates so far.
    pub planning_ops: u64,
    /// Unknown voxels sealed.
    pub sealed: u32,
    /// The explorer's fault counters.
    pub errors: ErrorCounters,
    /// The depth link's counters on the core's side.
    pub link: LinkCounters,
    /// At a complete end, frontier voxels seen but out of the vehicle's reach
    /// (the explorer status's `unreachable_frontier`); 0 otherwise.
    pub unreachable_frontier: u32,
    /// The operator state after the plan (`None` if the reporter has no operator: only the
    /// explorer, without a MAVLink bridge).
    pub operator: Option<OperatorState>,
    /// What the reporter's MAVLink signing accepted and refused (all 0 without signing).
    pub signing: VerifierCounters,
    /// Resend requests the reporter sent back over the depth link (0 if it sends none).
    pub resend_requests: u32,
    /// The goal flown to (map-frame position and yaw) when the outcome is a goal (a new one,
    /// a kept one or an escape); `None` otherwise.
    pub goal: Option<([f32; 3], f32)>,
}

impl PlanReport {
    /// The report with what MAVLink signing accepted and refused (`None`: no signing).
    pub fn with_signing(mut self, counters: Option<VerifierCounters>) -> Self {
        self.signing = counters.unwrap_or_default();
        self
    }

    /// The report with the count of resend requests sent so far.
    pub fn with_resend_requests(mut self, count: u32) -> Self {
        self.resend_requests = count;
        self
    }

    /// The report with the operator state after the plan.
    pub fn with_operator(mut self, state: OperatorState) -> Self {
        self.operator = Some(state);
        self
    }

    fn write_body(&self, out: &mut [u8; PLAN_REPORT_LEN]) {
        let mut w = Writer { out, at: 0 };
        w.u32(self.frame_id);
        let (outcome, fault, detail) = outcome_code(&self.outcome);
        let operator = self.operator.map_or(0, |s| 1 + s.custom_mode() as u8);
        w.bytes(&[outcome, fault, detail, operator]);
        for v in self.position {
            w.f32(v);
        }
        w.f32(self.yaw);
        for v in [
            self.frames,
            self.plans,
            self.plans_kept,
            self.frontier,
            self.interior,
        ] {
            w.u32(v);
        }
        w.u32(self.solver_iterations);
        w.f32(self.solver_residual);
        w.u64(self.solver_updates);
        w.f32(self.streamline_length);
        w.u32(self.tick_hz);
        for v in [
            self.integrate_ticks,
            self.domain_ticks,
            self.solve_ticks,
            self.streamline_ticks,
            self.integration_ops,
            self.planning_ops,
        ] {
            w.u64(v);
        }
        w.u32(self.sealed);
        let e = &self.errors;
        for v in [
            e.frames_rejected,
            e.bad_pose,
            e.vehicle_outside_grid,
            e.vehicle_not_free,
            e.escapes,
            e.streamline_failures,
            e.solver_not_converged,
            e.seals,
            e.pose_jumps,
            e.clearances,
            e.plateaus,
            e.turning_frames,
            e.stale_pose_frames,
            e.screening_retries,
        ] {
            w.u32(v);
        }
        let l = &self.link;
        w.u64(l.bytes);
        for v in [
            l.frames_ok,
            l.crc_errors,
            l.cobs_errors,
            l.oversize,
            l.bad_version,
            l.unknown_type,
            l.malformed,
            l.sequence_gaps,
            l.out_of_order_chunks,
            l.missing_chunks,
            l.frame_too_large,
            l.no_intrinsics,
            l.intrinsics_mismatch,
            l.depth_frames_complete,
            l.depth_frames_dropped,
        ] {
            w.u32(v);
        }
        w.u32(self.unreachable_frontier);
        let c = &self.signing;
        for v in [
            c.accepted,
            c.unsigned,
            c.malformed,
            c.bad_signature,
            c.replayed,
            c.stale,
            c.too_many_streams,
        ] {
            w.u32(v);
        }
        w.u32(l.depth_frames_partial);
        w.u32(l.rows_missing);
        w.u32(self.resend_requests);
        w.u32(self.errors.reopenings);
        w.u32(self.errors.remnants_sealed);
        w.u32(self.errors.pocket_plans);
        let (goal, goal_yaw) = self.goal.unwrap_or(([f32::NAN; 3], f32::NAN));
        for v in goal {
            w.f32(v);
        }
        w.f32(goal_yaw);
    }

    fn read_body(body: &[u8]) -> Result<Self, DownlinkError> {
        let body: &[u8; PLAN_REPORT_LEN] = body
            .try_into()
            .map_err(|_| DownlinkError::Link(LinkError::Malformed(Malformed::BodyLength)))?;
        let mut r = Reader { body, at: 0 };
        let frame_id = r.u32();
        let [outcome, fault, detail, operator] = r.bytes4();
        let operator = match operator {
            0 => None,
            k => Some(OperatorState::from_custom_mode(u32::from(k) - 1).ok_or(DownlinkError::BadOutcome)?),
        };
        let outcome = outcome_from_code(outcome, fault, detail).ok_or(DownlinkError::BadOutcome)?;
        let position = [r.f32(), r.f32(), r.f32()];
        let yaw = r.f32();
        let (frames, plans, plans_kept, frontier, interior) = (r.u32(), r.u32(), r.u32(), r.u32(), r.u32());
        let (solver_iterations, solver_residual, solver_updates) = (r.u32(), r.f32(), r.u64());
        let streamline_length = r.f32();
        let tick_hz = r.u32();
        let (integrate_ticks, domain_ticks, solve_ticks, streamline_ticks) =
            (r.u64(), r.u64(), r.u64(), r.u64());
        let (integration_ops, planning_ops) = (r.u64(), r.u64());
        let sealed = r.u32();
        let errors = ErrorCounters {
            frames_rejected: r.u32(),
            bad_pose: r.u32(),
            vehicle_outside_grid: r.u32(),
            vehicle_not_free: r.u32(),
            escapes: r.u32(),
            streamline_failures: r.u32(),
            solver_not_converged: r.u32(),
            seals: r.u32(),
            pose_jumps: r.u32(),
            clearances: r.u32(),
            plateaus: r.u32(),
            turning_frames: r.u32(),
            stale_pose_frames: r.u32(),
            screening_retries: r.u32(),
            // Sent last (offsets 288, 292 and 296), after the fields added before them.
            reopenings: 0,
            remnants_sealed: 0,
            pocket_plans: 0,
        };
        // Counters the link may add later arrive as 0 from a core that does not send them.
        #[allow(clippy::needless_update)]
        let link = LinkCounters {
            bytes: r.u64(),
            frames_ok: r.u32(),
            crc_errors: r.u32(),
            cobs_errors: r.u32(),
            oversize: r.u32(),
            bad_version: r.u32(),
            unknown_type: r.u32(),
            malformed: r.u32(),
            sequence_gaps: r.u32(),
            out_of_order_chunks: r.u32(),
            missing_chunks: r.u32(),
            frame_too_large: r.u32(),
            no_intrinsics: r.u32(),
            intrinsics_mismatch: r.u32(),
            depth_frames_complete: r.u32(),
            depth_frames_dropped: r.u32(),
            ..LinkCounters::default()
        };
        let unreachable_frontier = r.u32();
        let signing = VerifierCounters {
            accepted: r.u32(),
            unsigned: r.u32(),
            malformed: r.u32(),
            bad_signature: r.u32(),
            replayed: r.u32(),
            stale: r.u32(),
            too_many_streams: r.u32(),
        };
        let link = LinkCounters {
            depth_frames_partial: r.u32(),
            rows_missing: r.u32(),
            ..link
        };
        let resend_requests = r.u32();
        let errors = ErrorCounters {
            reopenings: r.u32(),
            remnants_sealed: r.u32(),
            pocket_plans: r.u32(),
            ..errors
        };
        let goal = [r.f32(), r.f32(), r.f32()];
        let goal_yaw = r.f32();
        let goal = (goal.iter().all(|v| v.is_finite()) && goal_yaw.is_finite()).then_some((goal, goal_yaw));
        Ok(Self {
            frame_id,
            outcome,
            position,
            yaw,
            frames,
            plans,
            plans_kept,
            frontier,
            interior,
            solver_iterations,
            solver_residual,
            solver_updates,
            streamline_length,
            tick_hz,
            integrate_ticks,
            domain_ticks,
            solve_ticks,
            streamline_ticks,
            integration_ops,
            planning_ops,
            sealed,
            errors,
            link,
            unreachable_frontier,
            operator,
            signing,
            resend_requests,
            goal,
        })
    }
}

fn outcome_code(o: &ReportOutcome) -> (u8, u8, u8) {
    match o {
        ReportOutcome::Goal => (0, 0, 0),
        ReportOutcome::Kept => (1, 0, 0),
        ReportOutcome::Escape => (2, 0, 0),
        ReportOutcome::Complete => (3, 0, 0),
        ReportOutcome::Look => (5, 0, 0),
        ReportOutcome::Hold(f) => {
            let (fault, detail) = match f {
                Fault::BadPose => (1, 0),
                Fault::VehicleOutsideGrid => (2, 0),
                Fault::VehicleNotFree => (3, 0),
                Fault::Streamline(e) => (
                    4,
                    match e {
                        StreamlineError::StartOutsideDomain => 0,
                        StreamlineError::Stalled => 1,
                        StreamlineError::TooLong => 2,
                        StreamlineError::StorageTooSmall => 3,
                    },
                ),
                Fault::Solver(e) => (
                    5,
                    match e {
                        SolveError::StorageTooSmall => 0,
                        SolveError::BadTolerance => 1,
                        SolveError::ScratchTooSmall => 2,
                        SolveError::Diverged => 3,
                        SolveError::BadScreening => 4,
                    },
                ),
                Fault::Integrate(e) => (
                    6,
                    match e {
                        IntegrateError::BadPose => 0,
                        IntegrateError::BadRange => 1,
                        IntegrateError::PoseJump => 2,
                        IntegrateError::TurningTooFast => 3,
                        IntegrateError::StalePose => 4,
                    },
                ),
                Fault::Operator => (7, 0),
                Fault::HomeUnreachable => (7, 1),
            };
            (4, fault, detail)
        }
    }
}

fn outcome_from_code(outcome: u8, fault: u8, detail: u8) -> Option<ReportOutcome> {
    Some(match outcome {
        0 => ReportOutcome::Goal,
        1 => ReportOutcome::Kept,
        2 => ReportOutcome::Escape,
        3 => ReportOutcome::Complete,
        5 => ReportOutcome::Look,
        4 => ReportOutcome::Hold(match (fault, detail) {
            (1, 0) => Fault::BadPose,
            (2, 0) => Fault::VehicleOutsideGrid,
            (3, 0) => Fault::VehicleNotFree,
            (4, 0) => Fault::Streamline(StreamlineError::StartOutsideDomain),
            (4, 1) => Fault::Streamline(StreamlineError::Stalled),
            (4, 2) => Fault::Streamline(StreamlineError::TooLong),
            (4, 3) => Fault::Streamline(StreamlineError::StorageTooSmall),
            (5, 0) => Fault::Solver(SolveError::StorageTooSmall),
            (5, 1) => Fault::Solver(SolveError::BadTolerance),
            (5, 2) => Fault::Solver(SolveError::ScratchTooSmall),
            (5, 3) => Fault::Solver(SolveError::Diverged),
            (5, 4) => Fault::Solver(SolveError::BadScreening),
            (6, 0) => Fault::Integrate(IntegrateError::BadPose),
            (6, 1) => Fault::Integrate(IntegrateError::BadRange),
            (6, 2) => Fault::Integrate(IntegrateError::PoseJump),
            (6, 3) => Fault::Integrate(IntegrateError::TurningTooFast),
            (6, 4) => Fault::Integrate(IntegrateError::StalePose),
            (7, 0) => Fault::Operator,
            (7, 1) => Fault::HomeUnreachable,
            _ => return None,
        }),
        _ => return None,
    })
}

struct Writer<'o> {
    out: &'o mut [u8; PLAN_REPORT_LEN],
    at: usize,
}

impl Writer<'_> {
    fn bytes(&mut self, b: &[u8]) {
        // The layout is fixed and sums to PLAN_REPORT_LEN, so this never runs past the end.
        if let Some(slot) = self.out.get_mut(self.at..self.at + b.len()) {
            slot.copy_from_slice(b);
        }
        self.at += b.len();
    }
    fn u32(&mut self, v: u32) {
        self.bytes(&v.to_le_bytes());
    }
    fn u64(&mut self, v: u64) {
        self.bytes(&v.to_le_bytes());
    }
    fn f32(&mut self, v: f32) {
        self.bytes(&v.to_le_bytes());
    }
}

struct Reader<'b> {
    body: &'b [u8; PLAN_REPORT_LEN],
    at: usize,
}

impl Reader<'_> {
    fn take<const K: usize>(&mut self) -> [u8; K] {
        let mut b = [0u8; K];
        if let Some(src) = self.body.get(self.at..self.at + K) {
            b.copy_from_slice(src);
        }
        self.at += K;
        b
    }
    fn bytes4(&mut self) -> [u8; 4] {
        self.take::<4>()
    }
    fn u32(&mut self) -> u32 {
        u32::from_le_bytes(self.take())
    }
    fn u64(&mut self) -> u64 {
        u64::from_le_bytes(self.take())
    }
    fn f32(&mut self) -> f32 {
        f32::from_le_bytes(self.take())
    }
}

/// Encodes `report` with sequence number `seq` as one frame into `out`; returns its length.
/// [`max_frame_len`]`(`[`PLAN_REPORT_LEN`]`)` bytes always suffice.
pub fn encode_report(seq: u16, report: &PlanReport, out: &mut [u8]) -> Result<usize, LinkError> {
    let mut body = [0u8; PLAN_REPORT_LEN];
    report.write_body(&mut body);
    encode(seq, PLAN_REPORT, &[&body], out)
}

/// The two-bit code of an occupancy state in a map slice.
pub fn occupancy_code(o: Occupancy) -> u8 {
    match o {
        Occupancy::Unknown => 0,
        Occupancy::Free => 1,
        Occupancy::Occupied => 2,
        Occupancy::Uncertain => 3,
    }
}

/// The occupancy state of a two-bit map-slice code (only the low two bits count).
pub fn occupancy_of_code(code: u8) -> Occupancy {
    match code & 3 {
        0 => Occupancy::Unknown,
        1 => Occupancy::Free,
        2 => Occupancy::Occupied,
        _ => Occupancy::Uncertain,
    }
}

/// Encodes the states of voxels `first .. first + count` of `map` (clipped to the grid and to
/// [`MAP_SLICE_VOXELS`]) as one map-slice frame into `out`; returns the frame's length and the
/// number of voxels it holds (0 past the end of the grid: nothing is written).
/// [`max_frame_len`]`(6 + MAP_SLICE_VOXELS / 4)` bytes always suffice.
pub fn encode_map_slice(
    seq: u16,
    map: &VoxelMap<'_>,
    first: usize,
    count: usize,
    out: &mut [u8],
) -> Result<(usize, usize), LinkError> {
    let n = map.dims().len();
    let count = count.min(MAP_SLICE_VOXELS).min(n.saturating_sub(first));
    if count == 0 {
        return Ok((0, 0));
    }
    // Four two-bit states per byte: byte k >> 2, bit offset 2 · (k & 3).
    let mut states = [0u8; MAP_SLICE_VOXELS >> 2];
    for k in 0..count {
        if let Some(b) = states.get_mut(k >> 2) {
            *b |= occupancy_code(map.occupancy(first + k)) << (2 * (k & 3));
        }
    }
    let first32 = u32::try_from(first).map_err(|_| LinkError::BufferTooSmall)?;
    let mut header = [0u8; MAP_SLICE_HEADER];
    header[..4].copy_from_slice(&first32.to_le_bytes());
    // count ≤ MAP_SLICE_VOXELS < 2¹⁶.
    header[4..].copy_from_slice(&(count as u16).to_le_bytes());
    let states = states.get(..count.div_ceil(4)).unwrap_or(&[]);
    let len = encode(seq, MAP_SLICE, &[&header, states], out)?;
    Ok((len, count))
}

fn encode(seq: u16, kind: u8, parts: &[&[u8]], out: &mut [u8]) -> Result<usize, LinkError> {
    write_frame(out, |w| {
        let [s0, s1] = seq.to_le_bytes();
        w.payload(&[PROTOCOL_VERSION, kind, s0, s1])?;
        parts.iter().try_for_each(|part| w.payload(part))
    })
}

/// A decoded downlink message; a map slice borrows the decoder's buffer. (A report is held by
/// value: decoded messages are handled at once, never stored in bulk.)
#[derive(Debug, Clone, Copy, PartialEq)]
#[allow(clippy::large_enum_variant)]
pub enum Downlink<'a> {
    /// A plan report.
    Report(PlanReport),
    /// States of voxels `first .. first + count`, two bits each (see [`occupancy_of_code`]).
    MapSlice {
        /// First voxel index.
        first: u32,
        /// Voxels in the slice.
        count: u16,
        /// `⌈count / 4⌉` bytes of states.
        states: &'a [u8],
    },
    /// The core's answer to a grid geometry.
    Geometry(GeometryAnswer),
    /// An intact frame of one of the depth link's own message types (high bit clear): the
    /// core's resend requests and acknowledgements travel the same return channel. Not damage;
    /// a [`crate::links::link::FrameDecoder`] fed the same bytes reads it.
    Link {
        /// Its message type ([`crate::links::link::MessageType`]'s code).
        kind: u8,
    },
}

impl Downlink<'_> {
    /// The state of the `k`-th voxel of a map slice (`None` past its end or for a report).
    pub fn slice_state(&self, k: usize) -> Option<Occupancy> {
        match self {
            Downlink::MapSlice { count, states, .. } if k < usize::from(*count) => {
                states.get(k >> 2).map(|b| occupancy_of_code(b >> (2 * (k & 3))))
            }
            _ => None,
        }
    }
}

/// Streaming decoder of downlink frames with a buffer of `N` bytes (see [`max_frame_len`]):
/// bytes in, checked messages out; damaged frames are dropped, never a panic.
#[derive(Debug, Clone)]
pub struct DownlinkDecoder<const N: usize> {
    buf: [u8; N],
    len: usize,
    overflow: bool,
    dropped: u32,
}

impl<const N: usize> Default for DownlinkDecoder<N> {
    fn default() -> Self {
        Self::new()
    }
}

impl<const N: usize> DownlinkDecoder<N> {
    /// An empty decoder.
    pub const fn new() -> Self {
        Self {
            buf: [0; N],
            len: 0,
            overflow: false,
            dropped: 0,
        }
    }

    /// Frames dropped so far (damaged, oversize, unknown type or malformed).
    pub fn dropped(&self) -> u32 {
        self.dropped
    }

    /// Takes one byte; at the end of a frame returns its message or why it was dropped.
    pub fn push(&mut self, byte: u8) -> Option<Result<Downlink<'_>, DownlinkError>> {
        if byte != DELIMITER {
            match self.buf.get_mut(self.len) {
                Some(slot) if !self.overflow => {
                    *slot = byte;
                    self.len += 1;
                }
                _ => self.overflow = true,
            }
            return None;
        }
        let len = core::mem::take(&mut self.len);
        if core::mem::take(&mut self.overflow) {
            self.dropped = self.dropped.saturating_add(1);
            return Some(Err(LinkError::Oversize.into()));
        }
        if len == 0 {
            return None;
        }
        let result = match self.buf.get_mut(..len) {
            Some(frame) => parse(frame),
            None => Err(LinkError::Oversize.into()),
        };
        if result.is_err() {
            self.dropped = self.dropped.saturating_add(1);
        }
        Some(result)
    }
}

fn parse(frame: &mut [u8]) -> Result<Downlink<'_>, DownlinkError> {
    let n = cobs_decode_in_place(frame)?;
    let frame: &[u8] = frame.get(..n).ok_or(LinkError::Cobs)?;
    let truncated = LinkError::Malformed(Malformed::Truncated);
    let (payload, crc) = frame.split_last_chunk::<CRC_LEN>().ok_or(truncated)?;
    if crc32(payload) != u32::from_le_bytes(*crc) {
        return Err(LinkError::Crc.into());
    }
    let (&[version, kind, _, _], body) = payload.split_first_chunk::<HEADER_LEN>().ok_or(truncated)?;
    if version != PROTOCOL_VERSION {
        return Err(LinkError::BadVersion(version).into());
    }
    match kind {
        PLAN_REPORT => PlanReport::read_body(body).map(Downlink::Report),
        GEOMETRY_ANSWER => GeometryAnswer::read_body(body).map(Downlink::Geometry),
        MAP_SLICE => {
            let (header, states) = body.split_first_chunk::<MAP_SLICE_HEADER>().ok_or(truncated)?;
            let first = u32::from_le_bytes([header[0], header[1], header[2], header[3]]);
            let count = u16::from_le_bytes([header[4], header[5]]);
            if count == 0
                || usize::from(count) > MAP_SLICE_VOXELS
                || states.len() != usize::from(count).div_ceil(4)
            {
                return Err(LinkError::Malformed(Malformed::BodyLength).into());
            }
            Ok(Downlink::MapSlice { first, count, states })
        }
        link if link & 0x80 == 0 => Ok(Downlink::Link { kind: link }),
        other => Err(LinkError::UnknownType(other).into()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mapping::map::{Dims, LogOddsParams, MapGeometry};
    use nalgebra::Point3;

    fn decode_all<const N: usize>(
        dec: &mut DownlinkDecoder<N>,
        bytes: &[u8],
        mut f: impl FnMut(Downlink<'_>),
    ) {
        for &b in bytes {
            if let Some(Ok(m)) = dec.push(b) {
                f(m);
            }
        }
    }

    /// A report of frame `frame_id` with `link`'s counters and every other field 0.
    fn sample(frame_id: u32, tick_hz: u32, link: LinkCounters) -> PlanReport {
        PlanReport {
            frame_id,
            outcome: ReportOutcome::Complete,
            position: [0.0; 3],
            yaw: 0.0,
            frames: 0,
            plans: 0,
            plans_kept: 0,
            frontier: 0,
            interior: 0,
            solver_iterations: 0,
            solver_residual: 0.0,
            solver_updates: 0,
            streamline_length: 0.0,
            tick_hz,
            integrate_ticks: 0,
            domain_ticks: 0,
            solve_ticks: 0,
            streamline_ticks: 0,
            integration_ops: 0,
            planning_ops: 0,
            sealed: 0,
            errors: ErrorCounters::default(),
            link,
            unreachable_frontier: 0,
            operator: None,
            signing: VerifierCounters::default(),
            resend_requests: 0,
            goal: None,
        }
    }

    #[test]
    fn report_round_trips_with_every_outcome() {
        let link = LinkCounters {
            bytes: 1 << 40,
            depth_frames_complete: 7,
            depth_frames_partial: 5,
            rows_missing: 33,
            ..LinkCounters::default()
        };
        let outcomes = [
            ReportOutcome::Goal,
            ReportOutcome::Kept,
            ReportOutcome::Escape,
            ReportOutcome::Complete,
            ReportOutcome::Look,
            ReportOutcome::Hold(Fault::Streamline(StreamlineError::TooLong)),
            ReportOutcome::Hold(Fault::Solver(SolveError::BadTolerance)),
            ReportOutcome::Hold(Fault::Integrate(IntegrateError::BadRange)),
            ReportOutcome::Hold(Fault::VehicleNotFree),
        ];
        for (k, outcome) in outcomes.into_iter().enumerate() {
            let mut report = sample(9, 25_000_000, link);
            report.position = [1.0, 2.0, 3.0];
            report.yaw = 0.5;
            report.integrate_ticks = 123;
            report.outcome = outcome;
            report.solver_updates = u64::MAX - k as u64;
            report.errors.seals = 3;
            // The counters added after the others travel at their own offsets.
            report.errors.reopenings = 7 + k as u32;
            report.errors.remnants_sealed = 11 + k as u32;
            report.errors.pocket_plans = 13 + k as u32;
            report.unreachable_frontier = 241 + k as u32;
            // Every operator state travels, and "not reported" too.
            report.operator = crate::links::operator::OperatorState::from_custom_mode(k as u32);
            report.signing.accepted = 1000 + k as u32;
            report.signing.too_many_streams = k as u32;
            report.resend_requests = 40 + k as u32;
            let mut out = [0u8; max_frame_len(PLAN_REPORT_LEN)];
            let n = encode_report(k as u16, &report, &mut out).unwrap();
            let mut dec = DownlinkDecoder::<512>::new();
            let mut got = None;
            decode_all(&mut dec, &out[..n], |m| {
                if let Downlink::Report(r) = m {
                    got = Some(r);
                }
            });
            assert_eq!(got, Some(report));
        }
    }

    #[test]
    fn geometry_answers_round_trip_and_an_unknown_verdict_is_dropped() {
        let answers = [
            GeometryAnswer::Taken { voxels: 120_000 },
            GeometryAnswer::Refused(Shortfall {
                what: Resource::Voxels,
                needed: 240_000,
                capacity: 131_072,
            }),
            GeometryAnswer::Refused(Shortfall {
                what: Resource::CoarseCells,
                needed: 25_000,
                capacity: 21_845,
            }),
            GeometryAnswer::Refused(Shortfall {
                what: Resource::GridInUse,
                needed: 6000,
                capacity: 0,
            }),
        ];
        for (k, answer) in answers.iter().enumerate() {
            let mut out = [0u8; max_frame_len(GEOMETRY_ANSWER_LEN)];
            let n = encode_geometry_answer(k as u16, answer, &mut out).unwrap();
            let mut dec = DownlinkDecoder::<64>::new();
            let mut got = None;
            decode_all(&mut dec, &out[..n], |m| {
                if let Downlink::Geometry(a) = m {
                    got = Some(a);
                }
            });
            assert_eq!(got.as_ref(), Some(answer));
        }
        let mut body = GeometryAnswer::Taken { voxels: 1 }.write_body();
        body[0] = 9;
        assert_eq!(GeometryAnswer::read_body(&body), Err(DownlinkError::BadOutcome));
        assert!(GeometryAnswer::read_body(&body[..8]).is_err());
    }

    #[test]
    fn map_slices_carry_every_state() {
        let g = MapGeometry::new(Dims::new(5, 3, 2).unwrap(), Point3::origin(), 0.1).unwrap();
        let (mut lo, mut st) = ([0i8; 30], [0u32; 1]);
        let params = LogOddsParams {
            hit: 0.5,
            miss: -0.5,
            ..LogOddsParams::default()
        };
        let mut map = VoxelMap::new(g, params, &mut lo, &mut st).unwrap();
        map.apply_miss(1);
        map.apply_hit(2);
        map.apply_hit(29);
        map.apply_hit(3);
        map.begin_frame();
        map.apply_miss(3);
        let mut out = [0u8; max_frame_len(6 + MAP_SLICE_VOXELS / 4)];
        let (n, count) = encode_map_slice(4, &map, 1, 100, &mut out).unwrap();
        assert_eq!(count, 29);
        let mut dec = DownlinkDecoder::<2048>::new();
        let mut states = [Occupancy::Unknown; 30];
        decode_all(&mut dec, &out[..n], |m| {
            if let Downlink::MapSlice { first, count, .. } = m {
                for k in 0..usize::from(count) {
                    states[first as usize + k] = m.slice_state(k).unwrap();
                }
            }
        });
        for (i, s) in states.iter().enumerate().skip(1) {
            assert_eq!(*s, map.occupancy(i), "voxel {i}");
        }
        assert_eq!(states[3], Occupancy::Uncertain);
        assert_eq!(encode_map_slice(5, &map, 30, 10, &mut out).unwrap(), (0, 0));
    }

    #[test]
    fn damage_is_dropped_and_link_frames_passed_over() {
        let report = sample(1, 1, LinkCounters::default());
        let mut out = [0u8; max_frame_len(PLAN_REPORT_LEN)];
        let n = encode_report(0, &report, &mut out).unwrap();
        let mut damaged = out;
        damaged[40] ^= 0x10;
        let mut heartbeat = [0u8; 64];
        let hb = crate::links::link::encode_frame(
            0,
            &crate::links::link::Message::Heartbeat(crate::links::link::Heartbeat::default()),
            &mut heartbeat,
        )
        .unwrap();
        let mut dec = DownlinkDecoder::<{ max_frame_len(PLAN_REPORT_LEN) }>::new();
        let mut results = heapless::Vec::<Result<u8, DownlinkError>, 4>::new();
        for bytes in [&damaged[..n], &heartbeat[..hb], &out[..n]] {
            for &b in bytes {
                if let Some(r) = dec.push(b) {
                    let kind = r.map(|m| match m {
                        Downlink::Report(_) => 0x81,
                        Downlink::MapSlice { .. } => 0x82,
                        Downlink::Geometry(_) => 0x83,
                        Downlink::Link { kind } => kind,
                    });
                    results.push(kind).unwrap();
                }
            }
        }
        assert_eq!(
            results.as_slice(),
            [Err(DownlinkError::Link(LinkError::Crc)), Ok(0x04), Ok(0x81)],
            "damage dropped, the link's Heartbeat passed over, the report read"
        );
        assert_eq!(dec.dropped(), 1);
    }
}
