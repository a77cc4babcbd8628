//! The exploration loop: integrate a frame, build the domain, solve, trace, choose a goal.
//!
//! [`Explorer`] owns the map and all planning buffers (borrowed from the caller through
//! [`ExplorerStorage`]) and is the one object the firmware and the host simulator drive:
//!
//! ```text
//! integrate(depth frame, camera pose) ─┐   (any number of frames)
//! plan(vehicle position, yaw) ─────────┴─► Goal { position, yaw } + waypoints | Complete | Hold
//! ```
//!
//! Planning steps, each reported in [`Status`]:
//!
//! 1. mark the voxels the vehicle's own body fills as free (it is there, so they are);
//! 2. build the domain around the vehicle ([`crate::domain`]); no frontier in the vehicle's
//!    component means exploration is **complete**;
//! 3. solve the planning field ([`crate::field`]: by default the frontier-sourced screened
//!    field, u = 1 on frontiers, ∇²u = κ²u elsewhere; or the seed's Laplace field with the
//!    vehicle as source), warm-started from the previous solution ([`crate::solve`]);
//! 4. trace the streamline from the vehicle to a frontier ([`crate::streamline`]);
//! 5. choose the goal (the view): the *first* point of the streamline from which the frontier
//!    is in plain sight (free voxels all the way) within [`ExplorerConfig::view_range_m`] and
//!    inside the vertical field of view — often the vehicle's own position, which then only
//!    turns to look; if that view taught nothing, the point *closest to the end* that sees it
//!    beyond the minimum range; if no point of the streamline sees it (a frontier inside the
//!    minimum range, or straight above or below), a point backed off from it, level with it,
//!    that does. The goal yaw faces the frontier. The way to the goal is the streamline up to
//!    it pulled taut through the safe space ([`streamline::pull_taut`],
//!    [`ExplorerConfig::taut_path`]): straight wherever the inflated free space allows.
//!
//! **Looking around on arrival** (opt-in, [`ExplorerConfig::arrival_looks`]): once the vehicle
//! stands at its goal, the next plans turn it on the spot instead of planning on — each time to
//! the one of eight headings, 45° apart and not yet looked along there, whose view (a grid of
//! rays over the camera's field of view, from the minimum to the maximum range) meets the most
//! unexplored voxels before a surface; until a turn teaches nothing, no heading's view meets
//! any, or the turns are used up. Turning costs time, not path: it shortens paths and lengthens
//! flights (docs/RESULTS.md, "Looking around on arrival"), so it is off by default.
//!
//! Frontiers the camera cannot resolve from any reachable pose (for example unknown voxels
//! inside the minimum range under the vehicle) would make the loop revisit the same place
//! forever (or alternate between two such places). The explorer notices when the vehicle stands
//! at its last goal and either targets the same frontier again or learned nothing there (no
//! voxel observed since the previous full plan), and after [`ExplorerConfig::stall_visits`] such
//! visits in a row it *seals* the unknown voxels behind the targeted frontier (Shade's stagnant-region sealing,
//! thesis §6.6.2), so the rest of the map can be explored. Sealed voxels are counted.
//!
//! **Remnants** ([`ExplorerConfig::remnant_frontier_m2`]): once the whole domain holds only a
//! few frontier voxels, the last crumbs of unknown space cost more flight than they are worth.
//! A target then farther along its streamline than [`ExplorerConfig::remnant_reach_m`] is not
//! flown to: the unknown behind it is sealed as for a fruitless visit (counted in
//! [`ErrorCounters::remnants_sealed`]) and the field solved again, so nearer remnants are still
//! looked at and the exploration ends sooner. Not while the map holds safe free space the
//! vehicle cannot reach, nor with noisy depth ([`is_far_remnant`]): then a passage may be
//! closed by noise, and the crumbs may be the way through. Measured in docs/RESULTS.md ("Now:
//! far remnants sealed").
//!
//! Faults never panic: a plan that cannot be made returns [`PlanOutcome::Hold`] with the reason,
//! and the reason's counter in [`ErrorCounters`] goes up; the caller keeps the last safe setpoint.

use nalgebra::{Isometry3, Point3, Vector3};

use crate::camera::{DepthFrame, Intrinsics};
use crate::domain::{self, DomainError, DomainStats, Inflation, Label, Reopening};
use crate::field::{self, PlanningField};
use crate::integrate::{self, IntegrateError, IntegrationParams, IntegrationStats};
use crate::map::{LogOddsParams, MapCounts, MapError, MapGeometry, Occupancy, VoxelIndex, VoxelMap};
#[cfg(feature = "flat")]
use crate::solve::flat::Flat;
use crate::solve::local::{resolve_near, BoxSolver, Local, LocalParams, LocalScratch, WithMethod};
use crate::solve::multigrid::{CoarseValues, Method, Multigrid, MultigridStorage};
use crate::solve::{self, SolveError, SolveParams, SolveStats};
use crate::streamline::{self, Field, StreamlineEnd, StreamlineError, StreamlineParams, Waypoints};

/// Which Laplace solver plans with.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum SolverKind {
    /// Geometric multigrid: MGPCG when Krylov storage is lent, V-cycles otherwise.
    #[default]
    Multigrid,
    /// The host's flat multigrid ([`crate::solve::flat`]): MGPCG, warm from the last field, in
    /// [`ExplorerStorage::flat`] (at least [`crate::solve::flat::flat_scratch_len`] values;
    /// refused at construction without them); re-solves go to boxes around what changed as the
    /// multigrid's do, where the box scratch is lent. Only with the `flat` feature (on by
    /// default; the firmware leaves it off, which keeps the solver out of its flash).
    #[cfg(feature = "flat")]
    Flat,
    /// Lexicographic Gauss-Seidel, the seed paper's solver (reference and baseline).
    GaussSeidel,
    /// The seed thesis's own solve ([`crate::solve::thesis`]): Jacobi sweeps from φ = 0 at every
    /// plan, stopped when the largest per-voxel relative change falls below 1e-4 (or after
    /// 20 000 sweeps, counted as not converged). An ablation of the thesis's truncated field.
    /// Needs [`ExplorerStorage::jacobi`] (one entry per voxel) and the seed's field
    /// ([`PlanningField::Harmonic`]); other fields are refused at construction.
    ThesisJacobi,
}

/// Everything an explorer is configured with.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ExplorerConfig {
    /// Occupancy update parameters.
    pub log_odds: LogOddsParams,
    /// Depth integration parameters.
    pub integration: IntegrationParams,
    /// Vehicle radius (planning clearance) in metres; obstacles are inflated by it.
    pub vehicle_radius: f32,
    /// A narrower clearance (metres) for leaving a pocket ([`domain::is_pocket`]): when the
    /// vehicle's component at `vehicle_radius` holds no frontier but at this radius holds one and
    /// is at least twice as large, the plan is made at this radius instead of calling the
    /// exploration complete, and so is every plan after it that finds the vehicle inside the
    /// planning radius's inflated space, until it is out. Each plan tries `vehicle_radius`
    /// first. 0 (the default), or not below `vehicle_radius`: none.
    pub narrow_radius: f32,
    /// Which potential plans (the screened frontier-sourced field by default).
    pub field: PlanningField,
    /// Solver choice.
    pub solver: SolverKind,
    /// Solver stopping rule.
    pub solve: SolveParams,
    /// Streamline tracer settings.
    pub streamline: StreamlineParams,
    /// Fraction of the camera's half field of view a goal must keep the frontier inside.
    pub view_margin: f32,
    /// Look from a distance: the goal is the *first* point of the streamline from which the
    /// frontier lies within this range (metres), inside the vertical field of view and in
    /// plain sight through known free voxels. The vehicle stops there and turns to it instead of
    /// flying up to it. If that view taught nothing, the next goal for the frontier is the
    /// near one (the last such point). 0: always the near one.
    pub view_range_m: f32,
    /// Fruitless visits to the same frontier before the unknown behind it is sealed.
    pub stall_visits: u8,
    /// Look around on arrival ([`ArrivalLooks`]): once the vehicle stands at its goal, before
    /// it plans the next one, it turns on the spot up to this many times, each time to the
    /// heading (of eight, 45° apart, not yet looked along there) whose view holds the most
    /// unexplored voxels in plain sight, while the last turn taught something and some
    /// heading's view holds any. A turn costs no path, only time. 0 (the default): no
    /// look-around. Measured (docs/RESULTS.md, "Looking around on arrival"): 7 turns shorten
    /// the paths of the thesis's worlds by 15–23 % and multiply the flight time by 2.3–2.6;
    /// closest frontier given the same turns gains as much.
    pub arrival_looks: u8,
    /// Doorways must not close under noise ([`Reopening`]): occupied voxels with a log-odds
    /// below this (log-odds units) are doubtful. Before the exploration ends for want of a
    /// reachable frontier, a frontier cut off by doubtful voxels alone is reopened: the doubtful
    /// voxels where the way to it leaves the safe space are forgotten, so the planner looks at
    /// them again. 0 (or less): off. Default 1.0: a voxel hit once, or hit twice and missed
    /// twice, is doubtful; one hit more and it is not.
    pub doubtful_log_odds: f32,
    /// Keep flying to the current goal, without re-solving, while its frontier voxel is still a
    /// frontier and the rest of its path is still free of (inflated) obstacles. Without this a
    /// receding-horizon caller can oscillate between two frontiers whose pull swaps as the
    /// source moves.
    pub commit_to_goal: bool,
    /// Fly to the goal along the streamline pulled taut ([`streamline::pull_taut`]): the goal
    /// is still chosen on the streamline itself (which arrives along the frontier's normal, so
    /// the look is head-on), but the way there is straight wherever the inflated safe space
    /// allows. False flies the streamline's own curve (an ablation).
    pub taut_path: bool,
    /// A frame whose camera is farther than this (metres) from the previous integrated frame's
    /// is refused ([`IntegrateError::PoseJump`], counted in [`ErrorCounters::pose_jumps`]): a
    /// pose that jumps would write the frame's walls into the wrong place. If
    /// [`FRAMES_TO_ACCEPT_JUMP`] frames in a row agree with each other on the new place (the
    /// estimator relocalised), the new place is taken. Not finite or ≤ 0: no check.
    pub max_frame_jump_m: f32,
    /// A frame taken while the vehicle yawed faster than this (rad/s, either way) is refused by
    /// [`Explorer::integrate_timed`] ([`IntegrateError::TurningTooFast`], counted in
    /// [`ErrorCounters::turning_frames`]): between two pose samples a turning camera's heading
    /// is only as good as the interpolation, and a degree of heading error moves a wall 9 cm at
    /// 5 m. Default 30°/s (0.52 rad/s): a look-around or goal turn runs at 90°/s, so frames are
    /// taken once it has finished. Not finite or ≤ 0: no check.
    pub max_frame_yaw_rate: f32,
    /// A frame whose newest pose sample is older than the frame by more than this (ms) is
    /// refused by [`Explorer::integrate_timed`] ([`IntegrateError::StalePose`], counted in
    /// [`ErrorCounters::stale_pose_frames`]): its pose would be a guess. Default 150 ms: three
    /// periods of a 20 Hz pose stream, or one of a 10 Hz stream plus 50 ms of latency. 0: no
    /// check.
    pub max_frame_pose_lag_ms: u32,
    /// Remnants: while the vehicle's component holds at most this much frontier (square metres'
    /// worth of frontier voxels: their count × the voxel size²), and the map no more safe free
    /// space outside that component than as many voxels, a target whose streamline is longer
    /// than [`ExplorerConfig::remnant_reach_m`] is sealed instead of flown to
    /// ([`is_far_remnant`]; never with noisy depth). Default 0.5 m² (50 voxels of 0.1 m): over 30 starts on each thesis
    /// world and on worlds the tuning never saw it shortens the mean path by 3–16 % and lowers
    /// free coverage by at most 0.04 points (docs/RESULTS.md, "Now: far remnants sealed"). 0: off.
    pub remnant_frontier_m2: f32,
    /// Remnants: how far along its streamline (metres) a remnant target may be and still be
    /// flown to (see [`ExplorerConfig::remnant_frontier_m2`]). Default 3 m.
    pub remnant_reach_m: f32,
}

/// How a frame's camera pose relates in time to the frame, for [`Explorer::integrate_timed`].
/// The caller measures it from the pose stream (see
/// [`PoseHistory`](crate::mavlink::PoseHistory)).
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct FrameTiming {
    /// The vehicle's yaw rate when the frame was taken, rad/s (either sign), measured from the
    /// pose samples' timestamps; `None` if unknown (a single sample), which is not refused.
    pub yaw_rate: Option<f32>,
    /// How much older than the frame the newest pose sample was when the frame was taken, ms
    /// (0 when the pose was interpolated between samples around the frame's instant).
    pub pose_lag_ms: u32,
}

/// Domain builds (each with a solve and a trace) one plan may make at most: each pass before
/// the last either returns or seals (or clears, or reopens) something and tries again.
pub const PLAN_PASSES: usize = 8;

/// True if a target `length` metres along its streamline is a far remnant
/// ([`ExplorerConfig::remnant_frontier_m2`]): the domain described by `stats` holds no more
/// frontier than the remnant area, the target lies beyond [`ExplorerConfig::remnant_reach_m`],
/// and the map holds no more safe free space outside the vehicle's component
/// ([`DomainStats::excluded`]) than that many voxels. Safe space the vehicle cannot reach means
/// a passage it has seen through is closed, by noise (docs/RESULTS.md: the thesis apartment's
/// 0.9 m hall, with a stereo camera) or by a gap: the crumbs of frontier on this side may be
/// that passage, and looking at them from near may open it, so they are not sealed. Always
/// false when the rule is off (area ≤ 0 or not finite), and with noisy depth
/// ([`IntegrationParams::depth_noise_per_m`] > 0, the stereo sensor model): there a crumb may be
/// a passage the noise narrowed without any safe space beyond it seen yet, and once sealed the
/// end's [`Reopening`] cannot open it (measured: the thesis apartment's hall under σ = 1 px,
/// `tests/tests/evaluation.rs`, `a_hall_closed_by_doubtful_voxels_is_reopened_before_the_end`).
pub fn is_far_remnant(
    config: &ExplorerConfig,
    geometry: &MapGeometry,
    stats: &DomainStats,
    length: f32,
) -> bool {
    let area = config.remnant_frontier_m2;
    if !(area > 0.0 && area.is_finite()) {
        return false;
    }
    // Noisy depth (the stereo sensor model): a crumb may be a passage that false occupied
    // voxels narrowed, and the end's reopening (`Reopening`) cannot open it once it is sealed.
    if config.integration.depth_noise_per_m > 0.0 {
        return false;
    }
    let voxels = area / (geometry.resolution() * geometry.resolution());
    stats.frontier as f32 <= voxels && stats.excluded as f32 <= voxels && length > config.remnant_reach_m
}

/// [`Explorer::plan_home`] reports the vehicle home within this distance of it, metres.
pub const HOME_REACHED_M: f32 = 0.15;

/// Refused frames in a row, each within [`ExplorerConfig::max_frame_jump_m`] of the one before,
/// after which a jumped camera pose is accepted as the new reference.
pub const FRAMES_TO_ACCEPT_JUMP: u8 = 3;

impl Default for ExplorerConfig {
    fn default() -> Self {
        Self {
            log_odds: LogOddsParams::default(),
            integration: IntegrationParams::default(),
            vehicle_radius: 0.2,
            narrow_radius: 0.0,
            field: PlanningField::default(),
            solver: SolverKind::default(),
            solve: SolveParams::default(),
            streamline: StreamlineParams::default(),
            view_margin: 0.8,
            view_range_m: 1.5,
            stall_visits: 2,
            arrival_looks: 0,
            doubtful_log_odds: 1.0,
            commit_to_goal: true,
            taut_path: true,
            max_frame_jump_m: 2.0,
            max_frame_yaw_rate: 30.0 * core::f32::consts::PI / 180.0,
            max_frame_pose_lag_ms: 150,
            remnant_frontier_m2: 0.5,
            remnant_reach_m: 3.0,
        }
    }
}

/// Buffers an explorer works in, each with at least one entry per voxel except `touched`
/// ([`map::touched_words`](crate::map::touched_words): one bit per voxel) and `queue` (any
/// length ≥ 1; a few thousand entries keep the flood fill to one pass). The multigrid buffers
/// are sized by [`crate::solve::multigrid::scratch_size`]; they may be empty when the solver is
/// Gauss-Seidel or the thesis's Jacobi, and `krylov` may be empty to run plain V-cycles in less
/// memory. `jacobi` may be empty unless the solver is [`SolverKind::ThesisJacobi`].
///
/// [`ExplorerStorage::bytes`] adds it up: 1.125 bytes of map, 1 byte of labels and 4 bytes of ψ
/// per voxel, plus the multigrid levels (about 1.3 bytes per voxel with `f32` coarse values,
/// 0.7 with bfloat16, and 0.6 of coarse face conductances) and the queue — 64 × 64 × 32
/// voxels with V-cycles, bfloat16 coarse levels and a 2048-entry queue need 956.6 KiB
/// (1029.7 KiB with `f32` ones).
pub struct ExplorerStorage<'a> {
    /// Map log-odds.
    pub log_odds: &'a mut [i8],
    /// Map "updated this frame" bits.
    pub touched: &'a mut [u32],
    /// Domain labels.
    pub labels: &'a mut [Label],
    /// Potential φ.
    pub phi: &'a mut [f32],
    /// Flood-fill queue.
    pub queue: &'a mut [u32],
    /// Multigrid coarse-level values, `f32` or bfloat16 (half the memory; see
    /// [`CoarseValues`]).
    pub coarse_values: CoarseValues<'a>,
    /// Multigrid coarse-level labels.
    pub coarse_labels: &'a mut [Label],
    /// Multigrid coarse-level face conductances.
    pub coarse_faces: &'a mut [[u8; 4]],
    /// MGPCG vectors (optional).
    pub krylov: &'a mut [f32],
    /// The fine cells' neighbour masks (optional, one byte per voxel; see
    /// [`MultigridStorage::masks`]): faster sweeps for 1 byte per voxel.
    pub masks: &'a mut [u8],
    /// The map's per-voxel surface estimate for noisy depth (optional, two words per voxel; see
    /// [`crate::integrate`]); empty, noisy frames are decided by the per-frame vote alone.
    pub surface: &'a mut [[i32; 2]],
    /// The other sweep of the thesis's Jacobi solve ([`SolverKind::ThesisJacobi`] only: one
    /// entry per voxel then; otherwise it may be empty).
    pub jacobi: &'a mut [f32],
    /// Labels of the box a local re-solve cuts out ([`crate::solve::local`]; optional, like
    /// `krylov`): with this and `local_psi` lent ([`crate::solve::local::box_scratch_len`] of
    /// the grid each, or less: a box never exceeds what is lent), a re-solve of
    /// the screened field after a scan works in boxes around what changed. Empty: every solve
    /// sweeps the whole grid.
    pub local_labels: &'a mut [Label],
    /// Values of that box (as many as `local_labels`).
    pub local_psi: &'a mut [f32],
    /// The flat solver's storage (`SolverKind::Flat` only, with the `flat` feature; otherwise
    /// it may be empty and is not used).
    pub flat: &'a mut [f32],
}

impl ExplorerStorage<'_> {
    /// Bytes of all the buffers together.
    pub fn bytes(&self) -> usize {
        use core::mem::size_of_val;
        size_of_val(self.log_odds)
            + size_of_val(self.touched)
            + size_of_val(self.labels)
            + size_of_val(self.phi)
            + size_of_val(self.queue)
            + self.coarse_values.bytes()
            + size_of_val(self.coarse_labels)
            + size_of_val(self.coarse_faces)
            + size_of_val(self.krylov)
            + size_of_val(self.masks)
            + size_of_val(self.surface)
            + size_of_val(self.jacobi)
            + size_of_val(self.local_labels)
            + size_of_val(self.local_psi)
            + size_of_val(self.flat)
    }
}

/// Why an explorer could not be built.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum ConfigError {
    /// Map geometry or storage problem.
    Map(MapError),
    /// Vehicle radius unusable at this resolution.
    Domain(DomainError),
    /// A planning buffer is shorter than the grid.
    StorageTooSmall,
    /// The multigrid scratch is too small for the grid.
    Solver(SolveError),
}

/// Why a plan was not made or a frame not integrated. Each has a counter in [`ErrorCounters`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Fault {
    /// Vehicle position not finite.
    BadPose,
    /// Vehicle outside the map grid.
    VehicleOutsideGrid,
    /// Vehicle voxel occupied or unknown, and no free voxel to escape to.
    VehicleNotFree,
    /// The streamline could not be traced.
    Streamline(StreamlineError),
    /// The solver refused to run.
    Solver(SolveError),
    /// A frame could not be integrated.
    Integrate(IntegrateError),
    /// Not planning on the operator's word: paused, aborted or waiting for start
    /// ([`crate::operator`]). The caller, not the explorer, decides this hold.
    Operator,
    /// Returning home ([`Explorer::plan_home`]): home is not in the vehicle's safe space
    /// (outside the grid, unknown, or cut off by what the map holds now).
    HomeUnreachable,
}

/// Counts of every fault and notable event since start.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[cfg_attr(feature = "serde", derive(serde::Serialize))]
pub struct ErrorCounters {
    /// Frames rejected for a bad camera pose or range settings.
    pub frames_rejected: u32,
    /// Plans refused for a non-finite vehicle position.
    pub bad_pose: u32,
    /// Plans refused because the vehicle was outside the grid.
    pub vehicle_outside_grid: u32,
    /// Plans refused because the vehicle voxel was not free and nothing free was near.
    pub vehicle_not_free: u32,
    /// Plans that had to steer the vehicle out of inflated space first.
    pub escapes: u32,
    /// Streamlines that stalled or ran too long, leaving the vehicle holding.
    pub streamline_failures: u32,
    /// Solves that hit the iteration cap before the tolerance.
    pub solver_not_converged: u32,
    /// Times unknown voxels were sealed as unobservable.
    pub seals: u32,
    /// Frames refused because their camera pose jumped (also in `frames_rejected`).
    pub pose_jumps: u32,
    /// Plans that found the vehicle walled in by unobservable unknown voxels around its body
    /// and marked twice the vehicle radius around it free instead of reporting complete.
    pub clearances: u32,
    /// Streamlines that stalled on a plateau of φ (below f32 resolution, far from the vehicle)
    /// after leaving the vehicle's voxel: the vehicle flew the traced part instead of holding.
    pub plateaus: u32,
    /// Frames refused because the vehicle turned faster than
    /// [`ExplorerConfig::max_frame_yaw_rate`] when they were taken (also in `frames_rejected`).
    pub turning_frames: u32,
    /// Frames refused because the pose stream was older than the frame by more than
    /// [`ExplorerConfig::max_frame_pose_lag_ms`] (also in `frames_rejected`).
    pub stale_pose_frames: u32,
    /// Screened-field streamlines that stalled (u unresolved far from every frontier) and
    /// were traced again on a field with half the κ.
    pub screening_retries: u32,
    /// Times the exploration would have ended while a frontier was cut off by doubtful
    /// occupied voxels alone, and the doubtful voxels in the way were forgotten to be looked
    /// at again instead ([`Reopening`]).
    pub reopenings: u32,
    /// Plans made at [`ExplorerConfig::narrow_radius`]: the vehicle stood in a pocket
    /// ([`domain::is_pocket`]) or, after such a plan, inside the planning radius's inflated
    /// space.
    pub pocket_plans: u32,
    /// Targets sealed instead of flown to because they were far remnants
    /// ([`ExplorerConfig::remnant_frontier_m2`]); not counted in `seals`.
    pub remnants_sealed: u32,
}

/// How exploration stands.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Termination {
    /// Still frontiers to visit.
    #[default]
    Running,
    /// The vehicle's component of free space has no frontier left.
    Complete,
}

/// A place to fly to and the direction to look in when there.
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Goal {
    /// Goal position, map frame.
    pub position: Point3<f32>,
    /// Goal yaw about map z, radians (0 = +x).
    pub yaw: f32,
    /// The frontier voxel the streamline ended in (for an escape, the escape voxel; for a
    /// streamline that stalled on a plateau, the voxel it stalled in).
    pub frontier: VoxelIndex,
    /// True if the goal is an escape from inflated space rather than a streamline.
    pub escape: bool,
}

/// Result of [`Explorer::plan`].
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum PlanOutcome {
    /// Fly to the goal through [`Explorer::waypoints`].
    Goal(Goal),
    /// Nothing reachable is left to explore.
    Complete,
    /// No plan: hold the last safe setpoint.
    Hold(Fault),
}

/// A monotonic tick source for per-phase timing (a board timer, a cycle counter, or the host
/// clock). Ticks are opaque units; the caller knows their rate.
pub trait Clock {
    /// Current tick count.
    fn ticks(&mut self) -> u64;
}

/// A clock that always reads 0, for callers that do not time phases.
#[derive(Debug, Clone, Copy, Default)]
pub struct NoClock;

impl Clock for NoClock {
    fn ticks(&mut self) -> u64 {
        0
    }
}

/// Ticks spent in each planning phase of the last plan.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct PhaseTicks {
    /// Domain and boundary conditions (including re-builds after sealing).
    pub domain: u64,
    /// Laplace solve.
    pub solve: u64,
    /// Streamline and goal choice.
    pub streamline: u64,
}

/// Everything the explorer reports.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Status {
    /// Voxel counts after the last plan.
    pub map: MapCounts,
    /// Domain of the last plan.
    pub domain: DomainStats,
    /// Solver statistics of the last plan.
    pub solve: SolveStats,
    /// Last streamline, if one was traced.
    pub streamline: Option<StreamlineEnd>,
    /// Last frame's integration statistics.
    pub integration: IntegrationStats,
    /// Frames integrated.
    pub frames: u32,
    /// Plans made (any outcome).
    pub plans: u32,
    /// Plans that kept the committed goal instead of re-solving.
    pub plans_kept: u32,
    /// Plans that turned the vehicle on the spot to look around on arrival
    /// ([`ExplorerConfig::arrival_looks`]) instead of re-solving.
    pub arrival_looks: u32,
    /// Total voxel updates by integration ("integration ops").
    pub integration_ops: u64,
    /// Total solver cell updates ("planning ops").
    pub planning_ops: u64,
    /// Solves of the field: every screening a plan tries, whole or in boxes.
    pub solves: u32,
    /// Solves done in boxes around what a scan changed ([`crate::solve::local`]).
    pub local_solves: u32,
    /// Local re-solves that gave the grid back to a whole-grid solve (the change reached too
    /// far).
    pub local_given_up: u32,
    /// Exploration state.
    pub termination: Termination,
    /// At a [`Termination::Complete`] end: the map's frontier voxels (observed free, next to
    /// unexplored space, [`VoxelMap::is_frontier`]) that the vehicle cannot reach — in a gap
    /// too narrow for its radius, in another component, or behind one. "Complete" means no
    /// *reachable* frontier is left; these are what was seen but left. 0 while running.
    pub unreachable_frontier: u32,
    /// Time per phase of the last plan, in the caller's clock ticks.
    pub phase_ticks: PhaseTicks,
    /// Fault counters.
    pub errors: ErrorCounters,
}

impl Status {
    /// Records what a full plan left: the map's voxel counts, the exploration state, and at a
    /// complete end the frontier voxels out of reach ([`Status::unreachable_frontier`], one
    /// pass over the grid, only then). Every planner on the core's map calls it after planning.
    pub fn record_plan(&mut self, outcome: &PlanOutcome, map: &VoxelMap<'_>) {
        self.map = map.counts();
        match outcome {
            PlanOutcome::Complete => {
                self.termination = Termination::Complete;
                self.unreachable_frontier = map.frontier_voxels();
            }
            PlanOutcome::Goal(_) => {
                self.termination = Termination::Running;
                self.unreachable_frontier = 0;
            }
            PlanOutcome::Hold(_) => {}
        }
    }
}

/// Checks a frame's [`FrameTiming`] against `config`'s limits
/// ([`ExplorerConfig::max_frame_yaw_rate`], [`ExplorerConfig::max_frame_pose_lag_ms`]); a
/// refusal is counted in `errors` (and in [`ErrorCounters::frames_rejected`]). Planners other
/// than [`Explorer`] share it.
pub fn check_frame_timing(
    config: &ExplorerConfig,
    timing: &FrameTiming,
    errors: &mut ErrorCounters,
) -> Result<(), IntegrateError> {
    let max_rate = config.max_frame_yaw_rate;
    let turning = max_rate.is_finite()
        && max_rate > 0.0
        // A rate that is not finite is no measurement: refused too.
        && timing.yaw_rate.is_some_and(|r| r.is_nan() || r.abs() > max_rate);
    let stale = config.max_frame_pose_lag_ms > 0 && timing.pose_lag_ms > config.max_frame_pose_lag_ms;
    let error = if stale {
        errors.stale_pose_frames = errors.stale_pose_frames.saturating_add(1);
        IntegrateError::StalePose
    } else if turning {
        errors.turning_frames = errors.turning_frames.saturating_add(1);
        IntegrateError::TurningTooFast
    } else {
        return Ok(());
    };
    errors.frames_rejected = errors.frames_rejected.saturating_add(1);
    Err(error)
}

/// A re-solve in boxes around what changed ([`resolve_near`]) with the explorer's box scratch,
/// counted in its status.
struct Boxes<'b> {
    local: LocalParams,
    scratch: LocalScratch<'b>,
    status: &'b mut Status,
}

impl Boxes<'_> {
    fn solve(
        self,
        solver: &mut impl BoxSolver,
        labels: &[Label],
        phi: &mut [f32],
        params: &SolveParams,
    ) -> Result<SolveStats, SolveError> {
        let solved = resolve_near(solver, labels, phi, params, &self.local, self.scratch);
        match &solved {
            Ok(Local::Solved(_)) => self.status.local_solves += 1,
            Ok(Local::Whole(_)) => self.status.local_given_up += 1,
            Err(_) => {}
        }
        solved.map(|how| how.stats())
    }
}

/// The exploration core.
pub struct Explorer<'a> {
    config: ExplorerConfig,
    map: VoxelMap<'a>,
    inflation: Inflation,
    labels: &'a mut [Label],
    phi: &'a mut [f32],
    queue: &'a mut [u32],
    multigrid: Option<Multigrid<'a>>,
    /// The flat solver ([`SolverKind::Flat`] only).
    #[cfg(feature = "flat")]
    flat: Option<Flat<'a>>,
    /// The thesis's Jacobi scratch (empty unless [`SolverKind::ThesisJacobi`]).
    jacobi: &'a mut [f32],
    /// The box scratch of local re-solves (empty: none).
    local_labels: &'a mut [Label],
    /// Its values.
    local_psi: &'a mut [f32],
    /// The screening of the field `phi` holds, if a solve left one there: a re-solve with
    /// the same screening may work locally.
    solved_screening: Option<f32>,
    waypoints: Waypoints,
    intrinsics: Option<Intrinsics>,
    last_goal: Option<Goal>,
    /// Camera position of the last integrated frame.
    last_frame_origin: Option<Point3<f32>>,
    /// A jumped camera position being refused, and how many frames in a row agreed on it.
    jump_candidate: Option<(Point3<f32>, u8)>,
    fruitless_visits: u8,
    /// Unexplored voxels at the previous full plan, to tell visits that taught nothing.
    unexplored_at_last_plan: Option<u32>,
    /// The screened field's current κ, 1/voxel (lowered while frontiers are far).
    kappa_voxel: f32,
    /// The last goal looks at its frontier from afar ([`ExplorerConfig::view_range_m`]).
    goal_from_afar: bool,
    /// The next goal choice takes the near point (a view from afar taught nothing).
    go_near: bool,
    /// Where the vehicle was at the last plan.
    last_plan_position: Option<Point3<f32>>,
    /// The look-around on arrival.
    looks: ArrivalLooks,
    /// The doubtful voxels forgotten so far ([`ExplorerConfig::doubtful_log_odds`]).
    reopening: Reopening,
    status: Status,
}

impl<'a> Explorer<'a> {
    /// Builds an explorer over `geometry` in `storage`; the map starts all unknown.
    pub fn new(
        geometry: MapGeometry,
        config: ExplorerConfig,
        storage: ExplorerStorage<'a>,
    ) -> Result<Self, ConfigError> {
        let n = geometry.dims().len();
        let ExplorerStorage {
            log_odds,
            touched,
            labels,
            phi,
            queue,
            coarse_values,
            coarse_labels,
            coarse_faces,
            krylov,
            masks,
            surface,
            jacobi,
            local_labels,
            local_psi,
            flat,
        } = storage;
        if labels.len() < n || phi.len() < n || queue.is_empty() {
            return Err(ConfigError::StorageTooSmall);
        }
        let multigrid = match config.solver {
            SolverKind::Multigrid => Some(
                Multigrid::new(
                    geometry.dims(),
                    MultigridStorage {
                        values: coarse_values,
                        labels: coarse_labels,
                        faces: coarse_faces,
                        krylov,
                        masks,
                    },
                )
                .map_err(ConfigError::Solver)?,
            ),
            SolverKind::GaussSeidel => None,
            #[cfg(feature = "flat")]
            SolverKind::Flat => None,
            SolverKind::ThesisJacobi => {
                if jacobi.len() < n {
                    return Err(ConfigError::StorageTooSmall);
                }
                if config.field != PlanningField::Harmonic {
                    // The thesis solves Laplace's equation only.
                    return Err(ConfigError::Solver(SolveError::BadScreening));
                }
                None
            }
        };
        let jacobi = match config.solver {
            SolverKind::ThesisJacobi => jacobi.get_mut(..n).unwrap_or_default(),
            _ => &mut [],
        };
        #[cfg(feature = "flat")]
        let flat = match config.solver {
            SolverKind::Flat => Some(Flat::new(geometry.dims(), flat).map_err(ConfigError::Solver)?),
            _ => None,
        };
        #[cfg(not(feature = "flat"))]
        let _ = flat;
        let map = VoxelMap::new(geometry, config.log_odds, log_odds, touched)
            .map_err(ConfigError::Map)?
            .with_surface(surface);
        let inflation = Inflation::new(config.vehicle_radius, config.narrow_radius, geometry.resolution())
            .map_err(ConfigError::Domain)?;
        let (Some(labels), Some(phi)) = (labels.get_mut(..n), phi.get_mut(..n)) else {
            return Err(ConfigError::StorageTooSmall);
        };
        labels.fill(Label::Outside);
        phi.fill(0.0);
        Ok(Self {
            config,
            map,
            inflation,
            labels,
            phi,
            queue,
            multigrid,
            #[cfg(feature = "flat")]
            flat,
            jacobi,
            local_labels,
            local_psi,
            solved_screening: None,
            waypoints: Waypoints::new(),
            intrinsics: None,
            last_goal: None,
            last_frame_origin: None,
            jump_candidate: None,
            fruitless_visits: 0,
            unexplored_at_last_plan: None,
            goal_from_afar: false,
            go_near: false,
            last_plan_position: None,
            looks: ArrivalLooks::default(),
            reopening: Reopening::default(),
            kappa_voxel: match config.field {
                PlanningField::Screened(p) => p.kappa_voxel(geometry.resolution()),
                PlanningField::Harmonic => 0.0,
            },
            status: Status::default(),
        })
    }

    /// The configuration.
    pub fn config(&self) -> &ExplorerConfig {
        &self.config
    }
    /// The map.
    pub fn map(&self) -> &VoxelMap<'a> {
        &self.map
    }
    /// Domain labels of the last plan.
    pub fn labels(&self) -> &[Label] {
        self.labels
    }
    /// The stored potential ψ = 1 − φ of the last plan (see [`crate::solve`]).
    pub fn psi(&self) -> &[f32] {
        self.phi
    }
    /// Waypoints from the vehicle to the last goal (map frame).
    pub fn waypoints(&self) -> &[Point3<f32>] {
        &self.waypoints
    }
    /// Current status and counters.
    pub fn status(&self) -> &Status {
        &self.status
    }

    /// Integrates one depth frame taken from `camera_pose` (camera → map). Without a
    /// [`FrameTiming`] the turn-rate and pose-lag checks cannot run; a caller that knows when
    /// its poses were sampled uses [`Explorer::integrate_timed`].
    pub fn integrate(
        &mut self,
        frame: &DepthFrame<'_>,
        camera_pose: &Isometry3<f32>,
    ) -> Result<IntegrationStats, Fault> {
        self.integrate_pose(frame, camera_pose)
    }

    /// [`integrate`](Self::integrate), first refusing (and counting) a frame taken while the
    /// vehicle turned faster than [`ExplorerConfig::max_frame_yaw_rate`] or whose pose stream
    /// lagged it by more than [`ExplorerConfig::max_frame_pose_lag_ms`].
    pub fn integrate_timed(
        &mut self,
        frame: &DepthFrame<'_>,
        camera_pose: &Isometry3<f32>,
        timing: &FrameTiming,
    ) -> Result<IntegrationStats, Fault> {
        check_frame_timing(&self.config, timing, &mut self.status.errors).map_err(Fault::Integrate)?;
        self.integrate_pose(frame, camera_pose)
    }

    fn integrate_pose(
        &mut self,
        frame: &DepthFrame<'_>,
        camera_pose: &Isometry3<f32>,
    ) -> Result<IntegrationStats, Fault> {
        let origin = Point3::from(camera_pose.translation.vector);
        if self.pose_jumped(&origin) {
            self.status.errors.frames_rejected += 1;
            self.status.errors.pose_jumps += 1;
            return Err(Fault::Integrate(IntegrateError::PoseJump));
        }
        // The flood-fill queue is idle between plans: it holds the noisy-depth vote.
        match integrate::integrate_with_scratch(
            &mut self.map,
            frame,
            camera_pose,
            &self.config.integration,
            self.queue,
        ) {
            Ok(stats) => {
                self.last_frame_origin = Some(origin);
                self.jump_candidate = None;
                self.intrinsics = Some(*frame.intrinsics());
                self.status.frames += 1;
                self.status.integration = stats;
                self.status.integration_ops += u64::from(stats.voxel_updates);
                Ok(stats)
            }
            Err(e) => {
                self.status.errors.frames_rejected += 1;
                Err(Fault::Integrate(e))
            }
        }
    }

    /// True if a frame taken from `origin` must be refused as a pose jump (see
    /// [`ExplorerConfig::max_frame_jump_m`]); tracks the run of agreeing refused frames.
    fn pose_jumped(&mut self, origin: &Point3<f32>) -> bool {
        let max = self.config.max_frame_jump_m;
        let Some(last) = self.last_frame_origin else {
            return false;
        };
        // A non-finite origin is refused by integration itself (BadPose).
        if !(max.is_finite() && max > 0.0 && origin.coords.iter().all(|c| c.is_finite())) {
            return false;
        }
        if (origin - last).norm() <= max {
            return false;
        }
        let agreeing = match self.jump_candidate {
            Some((p, n)) if (origin - p).norm() <= max => n.saturating_add(1),
            _ => 1,
        };
        if agreeing > FRAMES_TO_ACCEPT_JUMP {
            // The new place has persisted: take it (integrate() sets the reference).
            self.jump_candidate = None;
            return false;
        }
        self.jump_candidate = Some((*origin, agreeing));
        true
    }

    /// Plans from the vehicle at `position` (map frame) with heading `yaw`.
    pub fn plan(&mut self, position: &Point3<f32>, yaw: f32) -> PlanOutcome {
        self.plan_timed(position, yaw, &mut NoClock)
    }

    /// [`plan`](Self::plan), recording the ticks of each phase in [`Status::phase_ticks`].
    pub fn plan_timed(&mut self, position: &Point3<f32>, yaw: f32, clock: &mut impl Clock) -> PlanOutcome {
        self.status.plans += 1;
        self.status.phase_ticks = PhaseTicks::default();
        // A kept goal moves the vehicle; one that did not since the last plan is dropped, so a
        // controller that cannot follow it (or a path that ends where the vehicle is) never
        // freezes the loop.
        let moved = self
            .last_plan_position
            .replace(*position)
            .is_none_or(|last| (last - position).norm() > 0.01 * self.map.geometry().resolution());
        if self.config.commit_to_goal && moved {
            if let Some(goal) = self.last_goal.filter(|g| !g.escape) {
                let t0 = clock.ticks();
                let kept = self.keep_goal(position, &goal);
                self.status.phase_ticks.streamline += clock.ticks().saturating_sub(t0);
                if kept {
                    self.status.plans_kept += 1;
                    return PlanOutcome::Goal(goal);
                }
            }
        }
        if let Some(turn) = self.arrival_look(position, yaw, clock) {
            self.status.arrival_looks += 1;
            return PlanOutcome::Goal(turn);
        }
        self.waypoints.clear();
        let outcome = self.plan_inner(position, yaw, clock);
        self.status.record_plan(&outcome, &self.map);
        match outcome {
            PlanOutcome::Goal(g) => self.last_goal = Some(g),
            PlanOutcome::Hold(_) => self.last_goal = None,
            PlanOutcome::Complete => {}
        }
        outcome
    }

    /// The next turn of the look-around on arrival, if one is due ([`ArrivalLooks::next`]):
    /// a goal that keeps the vehicle where it is (one waypoint, its position) and turns it. It
    /// is not a plan: the last goal, the fruitless-visit bookkeeping and the field stay as they
    /// were.
    fn arrival_look(&mut self, position: &Point3<f32>, yaw: f32, clock: &mut impl Clock) -> Option<Goal> {
        let t0 = clock.ticks();
        let turn = self.looks.next(
            &self.map,
            &self.config,
            self.intrinsics.as_ref(),
            self.last_goal,
            position,
            yaw,
        );
        self.status.phase_ticks.streamline += clock.ticks().saturating_sub(t0);
        let turn = turn?;
        self.waypoints.clear();
        let _ = self.waypoints.push(*position);
        Some(turn)
    }

    /// True (and the waypoints trimmed to start at the vehicle) if the committed goal still
    /// stands: its frontier is still a frontier, the vehicle is on its path short of the goal,
    /// and every voxel the rest of the path crosses is free and clear of inflated obstacles.
    fn keep_goal(&mut self, position: &Point3<f32>, goal: &Goal) -> bool {
        let geometry = *self.map.geometry();
        let res = geometry.resolution();
        let still_open = domain::any_near(
            &self.map,
            goal.frontier,
            domain::frontier_reach(self.inflation.stencil()),
            |i| self.map.is_unexplored(i),
        );
        if !still_open || (goal.position - position).norm() <= 1.5 * res {
            return false;
        }
        let Some((k, d)) = self
            .waypoints
            .iter()
            .enumerate()
            .map(|(k, w)| (k, (w - position).norm()))
            .min_by(|a, b| a.1.total_cmp(&b.1))
        else {
            return false;
        };
        if d > 2.0 * res {
            return false;
        }
        // Check the remaining path from the vehicle on.
        let rest_of_path = self.waypoints.iter().skip(k).copied();
        if domain::first_unsafe_along(&self.map, self.inflation.stencil(), position, rest_of_path).is_some() {
            return false;
        }
        // Drop the waypoints already passed; start from where the vehicle is. A sparse path
        // (a step-back goal is one straight segment) may leave only the vehicle: the goal
        // itself is then the rest of the way.
        let mut rest: Waypoints = core::iter::once(*position)
            .chain(self.waypoints.iter().skip(k + 1).copied())
            .collect();
        if rest.len() == 1 {
            let _ = rest.push(goal.position);
        }
        self.waypoints = rest;
        true
    }

    fn plan_inner(&mut self, position: &Point3<f32>, yaw: f32, clock: &mut impl Clock) -> PlanOutcome {
        let errors = &mut self.status.errors;
        if !(position.coords.iter().all(|c| c.is_finite()) && yaw.is_finite()) {
            errors.bad_pose += 1;
            return PlanOutcome::Hold(Fault::BadPose);
        }
        let geometry = *self.map.geometry();
        let Some(vehicle) = geometry.voxel_at(position) else {
            errors.vehicle_outside_grid += 1;
            return PlanOutcome::Hold(Fault::VehicleOutsideGrid);
        };
        // Every plan tries the planning radius first; one that found a pocket left it narrowed.
        let was_narrow = self.inflation.widen();
        domain::mark_body(&mut self.map, self.inflation.stencil(), position);
        let counts = self.map.counts();
        let unexplored = counts.unknown - counts.sealed;
        let learned_nothing = self.unexplored_at_last_plan == Some(unexplored);
        self.unexplored_at_last_plan = Some(unexplored);
        let last_from_afar = core::mem::take(&mut self.goal_from_afar);

        // Each pass either returns or seals something and tries again; sealing is bounded by the
        // number of unknown voxels, the pass count keeps one call's work bounded too.
        for pass in 0..PLAN_PASSES {
            let t0 = clock.ticks();
            let built = self.build_domain(vehicle);
            let t1 = clock.ticks();
            self.status.phase_ticks.domain += t1.saturating_sub(t0);
            let stats = match built {
                Ok(s) => s,
                // On the way out of a pocket: the narrower radius still plans.
                Err(DomainError::VehicleInInflatedSpace) if was_narrow && self.inflation.narrow() => {
                    self.status.errors.pocket_plans += 1;
                    continue;
                }
                // Inflated space, or a voxel the map holds occupied (noise, pose error): the
                // vehicle is there, so it steers to the nearest safe free voxel, if any.
                Err(DomainError::VehicleInInflatedSpace | DomainError::VehicleNotFree) => {
                    return self.escape(vehicle, yaw)
                }
                Err(_) => {
                    self.status.errors.vehicle_not_free += 1;
                    return PlanOutcome::Hold(Fault::VehicleNotFree);
                }
            };
            self.status.domain = stats;
            if stats.frontier == 0 {
                if domain::clear_if_walled_in(&mut self.map, &stats, position, self.config.vehicle_radius) {
                    self.status.errors.clearances += 1;
                    continue;
                }
                let below = Reopening::threshold(self.config.doubtful_log_odds);
                if below > 0 && !self.reopening.is_full() {
                    if self.reopen_doubtful(vehicle, position, below, false, clock)
                        || self.reopen_doubtful(vehicle, position, below, true, clock)
                    {
                        self.status.errors.reopenings += 1;
                        continue;
                    }
                    // The doubting builds overwrote the labels: the caller reads the ordinary
                    // domain of the end (ψ is the last doubting solve's).
                    let t0 = clock.ticks();
                    let _ = self.build_domain(vehicle);
                    self.status.phase_ticks.domain += clock.ticks().saturating_sub(t0);
                }
                if self.in_pocket(vehicle, &stats, clock) {
                    self.status.errors.pocket_plans += 1;
                    continue;
                }
                self.status.streamline = None;
                return PlanOutcome::Complete;
            }
            let t2 = match self.solve_counted(vehicle, t1, clock) {
                Ok(t2) => t2,
                Err(fault) => return PlanOutcome::Hold(fault),
            };
            let field = Field {
                geometry: &geometry,
                labels: self.labels,
                phi: self.phi,
            };
            let end = match streamline::trace(&field, position, &self.config.streamline, &mut self.waypoints)
            {
                Ok(end) => end,
                Err(e) => {
                    self.status.streamline = None;
                    // Far from the vehicle φ can fall below what f32 resolves (a big hall):
                    // the streamline stalls on a plateau after a stretch of good descent.
                    // That stretch still leads towards the frontiers; fly it and plan again
                    // from its end, where the new source makes the field steep again.
                    if e == StreamlineError::Stalled {
                        // The screened field has no interior maximum; a stall means the solve
                        // did not resolve u this far from the frontiers. A smaller κ raises u
                        // at the vehicle: solve again with half of it.
                        if self.lower_screening() {
                            self.status.errors.screening_retries += 1;
                            continue;
                        }
                        if let Some(goal) = self.plateau_goal(vehicle, yaw) {
                            self.status.errors.plateaus += 1;
                            self.status.phase_ticks.streamline += clock.ticks().saturating_sub(t2);
                            return PlanOutcome::Goal(goal);
                        }
                    }
                    self.status.errors.streamline_failures += 1;
                    return PlanOutcome::Hold(Fault::Streamline(e));
                }
            };
            self.status.streamline = Some(end);
            // The last pass flies to whatever it found, so a plan never ends on seals alone.
            if pass + 1 < PLAN_PASSES && is_far_remnant(&self.config, &geometry, &stats, end.length) {
                domain::seal_around(
                    &mut self.map,
                    end.frontier,
                    domain::frontier_reach(self.inflation.stencil()),
                );
                self.status.errors.remnants_sealed += 1;
                self.status.phase_ticks.streamline += clock.ticks().saturating_sub(t2);
                continue;
            }
            let revisit = self.is_fruitless_revisit(end.frontier, position, learned_nothing);
            // A look from afar that taught nothing is not yet fruitless: go near first, and
            // stay near while the frontier keeps calling.
            let retry_near = revisit && last_from_afar;
            self.go_near = revisit && (last_from_afar || self.go_near);
            let goal = self.choose_goal(&end, yaw);
            if self.config.taut_path {
                // The streamline chose where to look from (it arrives along the frontier's
                // normal); the flight there need not follow its curve.
                self.status.planning_ops +=
                    streamline::pull_taut(&geometry, self.labels, &mut self.waypoints);
            }
            self.status.phase_ticks.streamline += clock.ticks().saturating_sub(t2);
            if retry_near {
                // Not fruitless yet, and not a fresh start either.
            } else if revisit {
                self.fruitless_visits = self.fruitless_visits.saturating_add(1);
                if self.fruitless_visits >= self.config.stall_visits {
                    self.fruitless_visits = 0;
                    domain::seal_around(
                        &mut self.map,
                        end.frontier,
                        domain::frontier_reach(self.inflation.stencil()),
                    );
                    self.status.errors.seals += 1;
                    continue;
                }
            } else {
                self.fruitless_visits = 0;
            }
            return PlanOutcome::Goal(goal);
        }
        self.status.errors.streamline_failures += 1;
        PlanOutcome::Hold(Fault::Streamline(StreamlineError::Stalled))
    }

    /// Before an exploration ends ([`ExplorerConfig::doubtful_log_odds`], [`Reopening`]): builds
    /// the domain with doubtful voxels taken for free space, follows the field's streamline
    /// from the vehicle towards a frontier there, and forgets the doubtful voxels around the
    /// first voxel of it the ordinary domain holds unsafe. True if any were forgotten: the
    /// caller builds the ordinary domain again, which now has a frontier where they were.
    /// `lenient` keeps the frontiers [`Doubt::lenient`](domain::Doubt::lenient) keeps; the
    /// caller asks it after the strict doubt found nothing; `below` is the stored threshold
    /// ([`Reopening::threshold`]). Leaves the labels and ψ of the doubting domain when it returns
    /// false (the caller builds the ordinary one again).
    fn reopen_doubtful(
        &mut self,
        vehicle: VoxelIndex,
        position: &Point3<f32>,
        below: i8,
        lenient: bool,
        clock: &mut impl Clock,
    ) -> bool {
        let t0 = clock.ticks();
        let doubt = self.reopening.doubt(below);
        let doubt = if lenient { doubt.lenient() } else { doubt };
        let stencil = self.inflation.stencil();
        let built = domain::build_doubting(&self.map, stencil, vehicle, self.labels, self.queue, &doubt);
        let t1 = clock.ticks();
        self.status.phase_ticks.domain += t1.saturating_sub(t0);
        if !built.is_ok_and(|s| s.frontier > 0) {
            return false;
        }
        let Ok(t2) = self.solve_counted(vehicle, t1, clock) else {
            return false;
        };
        let geometry = *self.map.geometry();
        let field = Field {
            geometry: &geometry,
            labels: self.labels,
            phi: self.phi,
        };
        let traced = streamline::trace(&field, position, &self.config.streamline, &mut self.waypoints);
        let gate = traced.ok().and_then(|_| {
            let path = self.waypoints.iter().copied();
            domain::first_unsafe_along(&self.map, self.inflation.stencil(), position, path)
        });
        self.waypoints.clear();
        self.status.phase_ticks.streamline += clock.ticks().saturating_sub(t2);
        gate.is_some_and(|g| {
            self.reopening
                .forget_around(&mut self.map, self.inflation.stencil(), g, below)
                > 0
        })
    }

    /// Solves the planning field over the domain just built (see [`crate::field`]). For the
    /// screened field the vehicle's voxel joins the interior, and while `u` at the vehicle falls
    /// below [`ScreenedParams::min_vehicle_value`](field::ScreenedParams::min_vehicle_value)
    /// (the nearest frontier is far) κ is lowered and the field solved again; once `u` there is
    /// large again κ returns towards its configured value for the next plan. Planning ops of
    /// every solve are counted; the stats returned add up the iterations.
    fn solve_field(&mut self, vehicle: VoxelIndex) -> Result<SolveStats, SolveError> {
        let dims = self.map.geometry().dims();
        let PlanningField::Screened(params) = self.config.field else {
            return self.solve_once(0.0, self.config.solve.tolerance);
        };
        field::release_source(self.labels);
        let full = params.kappa_voxel(self.map.geometry().resolution());
        let at_vehicle = dims.linear(vehicle);
        let mut total: Option<SolveStats> = None;
        for _ in 0..field::MAX_SCREENING_SOLVES {
            let kappa = self.kappa_voxel.clamp(field::MIN_KAPPA_VOXEL, full);
            let mut stats = self.solve_once(kappa * kappa, params.tolerance)?;
            if let Some(t) = total {
                stats.iterations += t.iterations;
                stats.cell_updates += t.cell_updates;
            }
            total = Some(stats);
            let u = self.phi.get(at_vehicle).copied().unwrap_or(0.0);
            if u >= params.min_vehicle_value || kappa <= field::MIN_KAPPA_VOXEL {
                // Near frontiers again: let κ recover for the next plan.
                if u >= params.raise_above {
                    self.kappa_voxel = (2.0 * kappa).min(full);
                }
                break;
            }
            self.kappa_voxel = params.lowered_kappa(kappa, u);
        }
        total.ok_or(SolveError::StorageTooSmall)
    }

    /// [`Explorer::solve_field`] from tick `t1`, its stats, work and time recorded in the
    /// status; the tick it ended at.
    fn solve_counted(&mut self, vehicle: VoxelIndex, t1: u64, clock: &mut impl Clock) -> Result<u64, Fault> {
        let solved = self.solve_field(vehicle);
        let t2 = clock.ticks();
        self.status.phase_ticks.solve += t2.saturating_sub(t1);
        let s = solved.map_err(Fault::Solver)?;
        self.status.solve = s;
        self.status.planning_ops += s.cell_updates;
        if !s.converged {
            self.status.errors.solver_not_converged += 1;
        }
        Ok(t2)
    }

    /// Halves the screened field's κ if it can go lower; false for the seed's field.
    fn lower_screening(&mut self) -> bool {
        match self.config.field {
            PlanningField::Screened(_) if self.kappa_voxel > field::MIN_KAPPA_VOXEL => {
                self.kappa_voxel = (0.5 * self.kappa_voxel).max(field::MIN_KAPPA_VOXEL);
                true
            }
            _ => false,
        }
    }

    /// One solve of the current domain with `screening` (κ²h², 0 for Laplace) to `tolerance`
    /// (the thesis's Jacobi stops by its own rule instead, [`solve::thesis`]).
    fn solve_once(&mut self, screening: f32, tolerance: f32) -> Result<SolveStats, SolveError> {
        let params = SolveParams {
            screening,
            tolerance,
            ..self.config.solve
        };
        let dims = self.map.geometry().dims();
        self.status.solves += 1;
        let same_field = self.solved_screening == Some(screening);
        self.solved_screening = None;
        // A re-solve of the same screened field may work in boxes around what changed.
        let local_ok = same_field && params.warm_start && screening > 0.0 && !self.local_labels.is_empty();
        let (labels, phi) = (&*self.labels, &mut *self.phi);
        let boxes = Boxes {
            local: LocalParams::for_screening(screening, tolerance),
            scratch: LocalScratch {
                labels: &mut *self.local_labels,
                psi: &mut *self.local_psi,
            },
            status: &mut self.status,
        };
        let solved = match (self.multigrid.as_mut(), self.config.solver) {
            (Some(mg), _) if local_ok => boxes.solve(&mut WithMethod(mg, Method::Auto), labels, phi, &params),
            (Some(mg), _) => mg.solve(labels, phi, &params, Method::Auto),
            #[cfg(feature = "flat")]
            (None, SolverKind::Flat) => match self.flat.as_mut() {
                Some(flat) if local_ok => boxes.solve(flat, labels, phi, &params),
                Some(flat) => flat.solve(labels, phi, &params),
                None => Err(SolveError::ScratchTooSmall),
            },
            (None, SolverKind::ThesisJacobi) => solve::thesis::solve(
                &dims,
                labels,
                phi,
                self.jacobi,
                &solve::thesis::ThesisParams::default(),
            ),
            (None, _) => solve::gauss_seidel(&dims, labels, phi, &params),
        };
        if solved.is_ok() {
            self.solved_screening = Some(screening);
        }
        solved
    }

    /// The goal for a traced streamline: the waypoint nearest the end that sees the frontier.
    /// Trims the waypoints to end at the goal.
    fn choose_goal(&mut self, end: &StreamlineEnd, yaw: f32) -> Goal {
        let target = end.end;
        let min_range = self.config.integration.min_range + self.map.geometry().resolution();
        let tan_v = self
            .intrinsics
            .map(|i| libm::tanf(i.half_fov().1 * self.config.view_margin))
            .unwrap_or(0.0);
        let sees = |p: &Point3<f32>| {
            let d = target - p;
            let horizontal = libm::sqrtf(d.x * d.x + d.y * d.y);
            d.norm() >= min_range && d.z.abs() <= horizontal * tan_v
        };
        let geometry = *self.map.geometry();
        let from_afar = self.config.view_range_m > 0.0 && !self.go_near;
        let in_sight = |p: &Point3<f32>| {
            if (target - p).norm() > self.config.view_range_m || !sees(p) {
                return false;
            }
            let dims = geometry.dims();
            let mut clear = true;
            integrate::traverse(&geometry, p, &target, |v| {
                clear &= self.map.is_free(dims.linear(v));
                clear
            });
            clear
        };
        let afar = if from_afar {
            self.waypoints.iter().position(in_sight)
        } else {
            None
        };
        self.goal_from_afar = afar.is_some();
        let chosen = afar.or_else(|| self.waypoints.iter().rposition(sees));
        let (position, look) = match chosen {
            Some(k) => {
                self.waypoints.truncate(k + 1);
                let p = self.waypoints.get(k).copied().unwrap_or(end.end);
                (p, target - p)
            }
            None => match self.step_back(&target, &sees) {
                // Too near to see (inside the minimum range, or straight above or below):
                // back off to where the camera sees it.
                Some(p) => {
                    let start = self.waypoints.first().copied().unwrap_or(p);
                    self.waypoints.clear();
                    let _ = self.waypoints.push(start);
                    let _ = self.waypoints.push(p);
                    (p, target - p)
                }
                None => (end.end, end.direction),
            },
        };
        Goal {
            position,
            yaw: heading(&look, yaw),
            frontier: end.frontier,
            escape: false,
        }
    }

    /// A viewpoint for a frontier `target` that no point of the streamline sees: the nearest to
    /// the vehicle of a ring of points around the target (level with it, 0.1 m past the
    /// minimum range and farther) that is a domain voxel, reached from the vehicle in a straight
    /// line through domain voxels, and sees the target through free voxels.
    fn step_back(&self, target: &Point3<f32>, sees: &impl Fn(&Point3<f32>) -> bool) -> Option<Point3<f32>> {
        let geometry = *self.map.geometry();
        let dims = geometry.dims();
        let start = *self.waypoints.first()?;
        let min_range = self.config.integration.min_range + geometry.resolution();
        let in_domain = |p: &Point3<f32>| {
            geometry
                .voxel_at(p)
                .is_some_and(|v| self.labels.get(dims.linear(v)).is_some_and(|l| l.in_domain()))
        };
        let mut best: Option<(f32, Point3<f32>)> = None;
        for r in [min_range + 0.1, min_range + 0.3, min_range + 0.6] {
            for k in 0..8 {
                let a = k as f32 * core::f32::consts::FRAC_PI_4;
                let p = target + Vector3::new(r * libm::cosf(a), r * libm::sinf(a), 0.0);
                let d = (p - start).norm();
                if best.is_some_and(|(b, _)| d >= b) || !sees(&p) || !in_domain(&p) {
                    continue;
                }
                let mut ok = true;
                integrate::traverse(&geometry, &start, &p, |v| {
                    ok &= self.labels.get(dims.linear(v)).is_some_and(|l| l.in_domain());
                    ok
                });
                integrate::traverse(&geometry, &p, target, |v| {
                    ok &= self.map.is_free(dims.linear(v));
                    ok
                });
                if ok {
                    best = Some((d, p));
                }
            }
            if best.is_some() {
                break;
            }
        }
        best.map(|(_, p)| p)
    }

    /// The vehicle stands at its last goal and either targets the same frontier again or its
    /// visit taught nothing (no voxel observed since the last full plan) — the signature of a
    /// frontier the camera cannot resolve, including loops between two such goals.
    fn is_fruitless_revisit(
        &self,
        frontier: VoxelIndex,
        position: &Point3<f32>,
        learned_nothing: bool,
    ) -> bool {
        let res = self.map.geometry().resolution();
        self.last_goal.is_some_and(|last| {
            !last.escape
                && (last.position - position).norm() <= 1.5 * res
                && (learned_nothing || last.frontier.distance_sq(&frontier) <= 2)
        })
    }

    /// The goal for a streamline that stalled on a plateau: the last traced waypoint, if the
    /// trace got at least a voxel away from the vehicle's voxel. Every waypoint lies in a
    /// domain voxel, so the goal is known free and clear of inflated space.
    fn plateau_goal(&self, vehicle: VoxelIndex, yaw: f32) -> Option<Goal> {
        let geometry = self.map.geometry();
        let (&last, before) = self.waypoints.split_last()?;
        let stalled_in = geometry.voxel_at(&last)?;
        let start = before.first()?;
        if stalled_in == vehicle || (last - start).norm() < geometry.resolution() {
            return None;
        }
        let direction = before.last().map_or(last - start, |p| last - p);
        Some(Goal {
            position: last,
            yaw: heading(&direction, yaw),
            frontier: stalled_in,
            escape: false,
        })
    }

    /// Plans the way back to `home` through known free space: the planning field of
    /// [`ExplorerConfig::field`] solved over the vehicle's safe space with the home voxel as its
    /// only target instead of the frontiers (every frontier voxel joins the interior), so its
    /// streamline ends at home by the same argument that makes exploring streamlines end on a
    /// frontier; the way is pulled taut as for exploring. The goal is home, the yaw kept.
    ///
    /// `Complete` once the vehicle is within [`HOME_REACHED_M`] of home;
    /// [`Fault::HomeUnreachable`] if home is not in the vehicle's safe space (it holds: the
    /// next scans may open the way); the faults of [`Explorer::plan`] otherwise.
    pub fn plan_home(
        &mut self,
        position: &Point3<f32>,
        yaw: f32,
        home: &Point3<f32>,
        clock: &mut impl Clock,
    ) -> PlanOutcome {
        self.status.phase_ticks = PhaseTicks::default();
        self.waypoints.clear();
        self.last_goal = None;
        let outcome = self.plan_home_inner(position, yaw, home, clock);
        self.status.record_plan(&outcome, &self.map);
        outcome
    }

    fn plan_home_inner(
        &mut self,
        position: &Point3<f32>,
        yaw: f32,
        home: &Point3<f32>,
        clock: &mut impl Clock,
    ) -> PlanOutcome {
        let geometry = *self.map.geometry();
        let (vehicle, home_voxel) = match locate_home(&geometry, position, yaw, home, &mut self.status.errors)
        {
            Ok(Some(voxels)) => voxels,
            Ok(None) => return PlanOutcome::Complete,
            Err(fault) => return PlanOutcome::Hold(fault),
        };
        let was_narrow = self.inflation.widen();
        domain::mark_body(&mut self.map, self.inflation.stencil(), position);
        let dims = geometry.dims();
        let at_home = dims.linear(home_voxel);
        let t0 = clock.ticks();
        let (built, narrowed) = domain::build_towards(
            &self.map,
            &mut self.inflation,
            vehicle,
            at_home,
            was_narrow,
            self.labels,
            self.queue,
        );
        let t1 = clock.ticks();
        self.status.phase_ticks.domain += t1.saturating_sub(t0);
        self.status.errors.pocket_plans += u32::from(narrowed);
        match built {
            Ok(stats) => self.status.domain = stats,
            Err(DomainError::VehicleInInflatedSpace | DomainError::VehicleNotFree) => {
                return self.escape(vehicle, yaw)
            }
            Err(_) => {
                self.status.errors.vehicle_not_free += 1;
                return PlanOutcome::Hold(Fault::VehicleNotFree);
            }
        }
        if !self.labels.get(at_home).is_some_and(|l| l.in_domain()) {
            return PlanOutcome::Hold(Fault::HomeUnreachable);
        }
        if at_home == dims.linear(vehicle) {
            // In home's voxel already: the rest of the way is inside one safe voxel.
            let _ = self.waypoints.push(*position);
            let _ = self.waypoints.push(*home);
            return PlanOutcome::Goal(Goal {
                position: *home,
                yaw,
                frontier: home_voxel,
                escape: false,
            });
        }
        for label in self.labels.iter_mut().filter(|l| **l == Label::Frontier) {
            *label = Label::Interior;
        }
        if let Some(label) = self.labels.get_mut(at_home) {
            *label = Label::Frontier;
        }
        // As in `plan_inner`: a streamline that stalls where the solve did not resolve the
        // field retries on a less screened one.
        for _ in 0..8 {
            let t1 = clock.ticks();
            let t2 = match self.solve_counted(vehicle, t1, clock) {
                Ok(t2) => t2,
                Err(fault) => return PlanOutcome::Hold(fault),
            };
            let field = Field {
                geometry: &geometry,
                labels: self.labels,
                phi: self.phi,
            };
            self.waypoints.clear();
            match streamline::trace(&field, position, &self.config.streamline, &mut self.waypoints) {
                Ok(end) => {
                    self.status.streamline = Some(end);
                    if self.config.taut_path {
                        self.status.planning_ops +=
                            streamline::pull_taut(&geometry, self.labels, &mut self.waypoints);
                    }
                    self.status.phase_ticks.streamline += clock.ticks().saturating_sub(t2);
                    let goal = self.waypoints.last().copied().unwrap_or(end.end);
                    return PlanOutcome::Goal(Goal {
                        position: goal,
                        yaw,
                        frontier: home_voxel,
                        escape: false,
                    });
                }
                Err(StreamlineError::Stalled) if self.lower_screening() => {
                    self.status.errors.screening_retries += 1;
                }
                Err(e) => {
                    self.status.streamline = None;
                    self.status.errors.streamline_failures += 1;
                    return PlanOutcome::Hold(Fault::Streamline(e));
                }
            }
        }
        self.status.errors.streamline_failures += 1;
        PlanOutcome::Hold(Fault::Streamline(StreamlineError::Stalled))
    }

    /// Whether the vehicle, whose component at the planning radius (`wide`) holds no frontier,
    /// stands in a [pocket](domain::is_pocket). If so the narrower radius stays in use for the
    /// plan; if not, the labels are the planning radius's domain again, as the caller expects.
    fn in_pocket(&mut self, vehicle: VoxelIndex, wide: &DomainStats, clock: &mut impl Clock) -> bool {
        let t0 = clock.ticks();
        let pocket = domain::narrow_in_pocket(
            &self.map,
            &mut self.inflation,
            vehicle,
            wide,
            self.labels,
            self.queue,
        );
        self.status.phase_ticks.domain += clock.ticks().saturating_sub(t0);
        pocket
    }

    /// The vehicle's domain at the radius in use, built into the labels.
    fn build_domain(&mut self, vehicle: VoxelIndex) -> Result<DomainStats, DomainError> {
        let stencil = self.inflation.stencil();
        domain::build(&self.map, stencil, vehicle, self.labels, self.queue)
    }

    /// Goal back into the domain for a vehicle that a new observation left inside inflated space.
    fn escape(&mut self, vehicle: VoxelIndex, yaw: f32) -> PlanOutcome {
        self.status.errors.escapes += 1;
        let stencil = self.inflation.stencil();
        let target = domain::escape_target(&self.map, stencil, vehicle, self.labels, self.queue, 4096);
        // The escape search overwrote the labels; they describe no domain now.
        self.labels.fill(Label::Outside);
        match target {
            Some(v) => {
                let p = self.map.geometry().center(v);
                let _ = self.waypoints.push(p);
                PlanOutcome::Goal(Goal {
                    position: p,
                    yaw,
                    frontier: v,
                    escape: true,
                })
            }
            None => {
                self.status.errors.vehicle_not_free += 1;
                PlanOutcome::Hold(Fault::VehicleNotFree)
            }
        }
    }
}

/// The first checks of a plan home, shared by every planner: the voxels of the vehicle and of
/// home, or `Ok(None)` when the vehicle is within [`HOME_REACHED_M`] of home. A non-finite
/// pose is [`Fault::BadPose`], a vehicle outside the grid [`Fault::VehicleOutsideGrid`]
/// (both counted in `errors`), a home outside it [`Fault::HomeUnreachable`].
pub fn locate_home(
    geometry: &crate::map::MapGeometry,
    position: &Point3<f32>,
    yaw: f32,
    home: &Point3<f32>,
    errors: &mut ErrorCounters,
) -> Result<Option<(VoxelIndex, VoxelIndex)>, Fault> {
    let finite = |p: &Point3<f32>| p.coords.iter().all(|c| c.is_finite());
    if !(finite(position) && finite(home) && yaw.is_finite()) {
        errors.bad_pose += 1;
        return Err(Fault::BadPose);
    }
    if (position - home).norm() <= HOME_REACHED_M {
        return Ok(None);
    }
    let Some(vehicle) = geometry.voxel_at(position) else {
        errors.vehicle_outside_grid += 1;
        return Err(Fault::VehicleOutsideGrid);
    };
    let home_voxel = geometry.voxel_at(home).ok_or(Fault::HomeUnreachable)?;
    Ok(Some((vehicle, home_voxel)))
}

/// Yaw that looks along `d`, or `fallback` when `d` is (nearly) vertical.
fn heading(d: &Vector3<f32>, fallback: f32) -> f32 {
    if d.x.abs() + d.y.abs() > 1e-3 * d.norm().max(1e-6) {
        libm::atan2f(d.y, d.x)
    } else {
        fallback
    }
}

/// The look-around on arrival ([`ExplorerConfig::arrival_looks`]), for any planner on the
/// core's map: [`Explorer`] runs it, and the host's baseline planners can run it too (an
/// ablation). It remembers, for the goal last arrived at, the headings already looked along
/// there, the turns made and the unexplored voxels left at the last turn.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct ArrivalLooks {
    state: Option<(Goal, u8, u8, u32)>,
}

impl ArrivalLooks {
    /// The next turn on the spot, if one is due: the vehicle (at `position`, facing `yaw`)
    /// stands at `arrived` (its last goal, not an escape; within 1.5 voxels), has turned fewer
    /// than `config.arrival_looks` times there, its last turn there (if any) taught something
    /// (the map's unexplored voxels, unknown and not sealed, fell since), and some heading of
    /// eight, 45° apart, not yet looked along there (the one it faces counts as looked along)
    /// sees an unexplored voxel the camera can resolve ([`unexplored_in_view`], within the
    /// integration's range). The turn faces the heading that sees the most; it keeps the
    /// vehicle where it is and names `arrived`'s frontier. `None` without intrinsics (no frame
    /// yet). Costs one pass over the map's voxels and up to seven views of rays.
    pub fn next(
        &mut self,
        map: &VoxelMap<'_>,
        config: &ExplorerConfig,
        intrinsics: Option<&Intrinsics>,
        arrived: Option<Goal>,
        position: &Point3<f32>,
        yaw: f32,
    ) -> Option<Goal> {
        let max_turns = config.arrival_looks;
        let (min_range, range) = (config.integration.min_range, config.integration.max_range);
        let res = map.geometry().resolution();
        let goal = arrived.filter(|g| !g.escape)?;
        if max_turns == 0 || (goal.position - position).norm() > 1.5 * res {
            return None;
        }
        // The same arrival while the goal is the same; a new goal is a new arrival.
        let (mut looked, mut turns, before) = match self.state.filter(|(g, ..)| *g == goal) {
            Some((_, looked, turns, before)) => (looked, turns, Some(before)),
            None => (0, 0, None),
        };
        if turns >= max_turns {
            return None;
        }
        let counts = map.counts();
        let unexplored = counts.unknown.saturating_sub(counts.sealed);
        looked |= 1 << octant(yaw);
        // A turn that taught nothing ends the look-around: the views left would not either.
        let taught_nothing = turns > 0 && before.is_some_and(|b| unexplored >= b);
        let best = match intrinsics {
            Some(intrinsics) if !taught_nothing => (0..8u8)
                .filter(|k| looked & (1 << k) == 0)
                .map(|k| {
                    let view =
                        unexplored_in_view(map, position, octant_yaw(k), intrinsics, (min_range, range));
                    (view, k)
                })
                .filter(|(n, _)| *n > 0)
                .fold(None, |best: Option<(u32, u8)>, (n, k)| match best {
                    Some((b, _)) if b >= n => best,
                    _ => Some((n, k)),
                }),
            _ => None,
        };
        if taught_nothing {
            turns = max_turns;
        }
        if let Some((_, k)) = best {
            looked |= 1 << k;
            turns += 1;
        }
        self.state = Some((goal, looked, turns, unexplored));
        let (_, k) = best?;
        Some(Goal {
            position: *position,
            yaw: octant_yaw(k),
            frontier: goal.frontier,
            escape: false,
        })
    }
}

/// How many of `LOOK_RAYS`² rays spread evenly over the field of view of a level camera with
/// `intrinsics` at `position`, looking along `heading`, meet an unexplored voxel (unknown, not
/// sealed) between `min_range` and `range` (the camera resolves nothing nearer) before an
/// occupied one.
pub fn unexplored_in_view(
    map: &VoxelMap<'_>,
    position: &Point3<f32>,
    heading: f32,
    intrinsics: &Intrinsics,
    (min_range, range): (f32, f32),
) -> u32 {
    let geometry = *map.geometry();
    let dims = geometry.dims();
    let (half_h, half_v) = intrinsics.half_fov();
    let mut seen = 0;
    for i in 0..LOOK_RAYS {
        let el = (2.0 * (i as f32 + 0.5) / LOOK_RAYS as f32 - 1.0) * half_v;
        let (ce, se) = (libm::cosf(el), libm::sinf(el));
        for j in 0..LOOK_RAYS {
            let az = heading + (2.0 * (j as f32 + 0.5) / LOOK_RAYS as f32 - 1.0) * half_h;
            let d = Vector3::new(libm::cosf(az) * ce, libm::sinf(az) * ce, se);
            let mut found = false;
            integrate::traverse(&geometry, position, &(position + d * range), |v| {
                let i = dims.linear(v);
                if map.occupancy(i) == Occupancy::Occupied {
                    return false;
                }
                found = map.is_unexplored(i) && (geometry.center(v) - position).norm() >= min_range;
                !found
            });
            seen += u32::from(found);
        }
    }
    seen
}

/// Rays per side of the grid [`unexplored_in_view`] casts over the field of view.
const LOOK_RAYS: usize = 24;

/// The octant (0–7, of 45° each, centred on `k`·45°) a yaw falls in; 0 for a non-finite yaw.
fn octant(yaw: f32) -> u8 {
    // A float-to-int cast saturates (NaN gives 0); rem_euclid then lies in 0..8.
    let k = libm::roundf(yaw / core::f32::consts::FRAC_PI_4) as i32;
    k.rem_euclid(8) as u8
}

/// The yaw of octant `k` (0–7), in (−π, π].
fn octant_yaw(k: u8) -> f32 {
    let k = if k > 4 { i16::from(k) - 8 } else { i16::from(k) };
    f32::from(k) * core::f32::consts::FRAC_PI_4
}

/// Camera pose of a forward-looking camera on a vehicle at `position` with heading `yaw`:
/// body x forward, y left, z up; camera z = body x, camera x = −body y, camera y = −body z.
pub fn forward_camera_pose(position: &Point3<f32>, yaw: f32) -> Isometry3<f32> {
    let body_from_camera = nalgebra::Matrix3::new(0.0, 0.0, 1.0, -1.0, 0.0, 0.0, 0.0, -1.0, 0.0);
    let r_cam = nalgebra::UnitQuaternion::from_matrix(&body_from_camera);
    let r_yaw = nalgebra::UnitQuaternion::from_axis_angle(&Vector3::z_axis(), yaw);
    Isometry3::from_parts(nalgebra::Translation3::from(position.coords), r_yaw * r_cam)
}

#[cfg(test)]
#[path = "explore_tests.rs"]
mod tests;
