//! How an explorer is configured, what it works in, and the checks every frame and target
//! passes whatever the planner.

use crate::mapping::integrate::{IntegrateError, IntegrationParams};
use crate::mapping::map::{LogOddsParams, MapGeometry};
use crate::planning::domain::{DomainStats, Label};
use crate::planning::field::PlanningField;
use crate::planning::solve::multigrid::CoarseValues;
use crate::planning::solve::SolveParams;
use crate::planning::streamline::StreamlineParams;

use super::status::ErrorCounters;

/// Which Laplace solver plans with.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum SolverKind {
    /// Geometric multigrid: MGPCG when Krylov storage is lent, V-cycles otherwise.
    #[default]
    Multigrid,
    /// The host's flat multigrid ([`crate::planning::solve::flat`]): MGPCG, warm from the last field, in
    /// [`ExplorerStorage::flat`] (at least [`crate::planning::solve::flat::flat_scratch_len`] values;
    /// refused at construction without them); re-solves go to boxes around what changed as the
    /// multigrid's do, where the box scratch is lent. Only with the `flat` feature (on by
    /// default; the firmware leaves it off, which keeps the solver out of its flash).
    #[cfg(feature = "flat")]
    Flat,
    /// Lexicographic Gauss-Seidel, the seed paper's solver (reference and baseline).
    GaussSeidel,
    /// The seed thesis's own solve ([`crate::planning::solve::thesis`]): Jacobi sweeps from φ = 0 at every
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
    /// A narrower clearance (metres) for leaving a pocket ([`domain::is_pocket`](crate::planning::domain::is_pocket)): when the
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
    /// Look around on arrival (the explorer's look-around): once the vehicle stands at its goal, before
    /// it plans the next one, it turns on the spot up to this many times, each time to the
    /// heading (of eight, 45° apart, not yet looked along there) whose view holds the most
    /// unexplored voxels in plain sight, while the last turn taught something and some
    /// heading's view holds any. A turn costs no path, only time. 0 (the default): no
    /// look-around. Measured (docs/RESULTS.md, "Looking around on arrival"): 7 turns shorten
    /// the paths of the thesis's worlds by 15–23 % and multiply the flight time by 2.3–2.6;
    /// closest frontier given the same turns gains as much.
    pub arrival_looks: u8,
    /// Doorways must not close under noise ([`Reopening`](crate::planning::domain::Reopening)): occupied voxels with a log-odds
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
    /// Fly to the goal along the streamline pulled taut ([`streamline::pull_taut`](crate::planning::streamline::pull_taut)): the goal
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
    /// [`Explorer::integrate_timed`](super::Explorer::integrate_timed) ([`IntegrateError::TurningTooFast`], counted in
    /// [`ErrorCounters::turning_frames`]): between two pose samples a turning camera's heading
    /// is only as good as the interpolation, and a degree of heading error moves a wall 9 cm at
    /// 5 m. Default 30°/s (0.52 rad/s): a look-around or goal turn runs at 90°/s, so frames are
    /// taken once it has finished. Not finite or ≤ 0: no check.
    pub max_frame_yaw_rate: f32,
    /// A frame whose newest pose sample is older than the frame by more than this (ms) is
    /// refused by [`Explorer::integrate_timed`](super::Explorer::integrate_timed) ([`IntegrateError::StalePose`], counted in
    /// [`ErrorCounters::stale_pose_frames`]): its pose would be a guess. Default 150 ms: three
    /// periods of a 20 Hz pose stream, or one of a 10 Hz stream plus 50 ms of latency. 0: no
    /// check.
    pub max_frame_pose_lag_ms: u32,
    /// Remnants: while the vehicle's component holds at most this much frontier (square metres'
    /// worth of frontier voxels: their count × the voxel size²), and the map no more safe free
    /// space outside that component than as many voxels, a target whose streamline is longer
    /// than [`ExplorerConfig::remnant_reach_m`](super::ExplorerConfig::remnant_reach_m) is sealed instead of flown to
    /// (never with noisy depth). Default 0.5 m² (50 voxels of 0.1 m): over 30 starts on each thesis
    /// world and on worlds the tuning never saw it shortens the mean path by 3–16 % and lowers
    /// free coverage by at most 0.04 points (docs/RESULTS.md, "Now: far remnants sealed"). 0: off.
    pub remnant_frontier_m2: f32,
    /// Remnants: how far along its streamline (metres) a remnant target may be and still be
    /// flown to (see [`ExplorerConfig::remnant_frontier_m2`](super::ExplorerConfig::remnant_frontier_m2)). Default 3 m.
    pub remnant_reach_m: f32,
    /// Plan on a grid this many times coarser than the map (1 or 2; default 1): frames are
    /// integrated into the map at the mission grid's resolution
    /// ([`ExplorerStorage::fine_log_odds`]), and the domain, the field and the streamline work
    /// on cells of `plan_coarsening` voxels a side whose state is pooled from the map's
    /// ([`VoxelMap::pool_from`](crate::mapping::map::VoxelMap::pool_from): occupied if any voxel
    /// is, unknown if any is, free only if all are). A board that cannot hold, or solve in time,
    /// a field over every voxel of a building plans this way: 2 takes an eighth of the planning
    /// memory and work.
    pub plan_coarsening: u8,
}

/// How a frame's camera pose relates in time to the frame, for [`Explorer::integrate_timed`](super::Explorer::integrate_timed).
/// The caller measures it from the pose stream (see
/// [`PoseHistory`](crate::links::mavlink::PoseHistory)).
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
/// ([`ExplorerConfig::remnant_frontier_m2`](super::ExplorerConfig::remnant_frontier_m2)): the domain described by `stats` holds no more
/// frontier than the remnant area, the target lies beyond [`ExplorerConfig::remnant_reach_m`](super::ExplorerConfig::remnant_reach_m),
/// and the map holds no more safe free space outside the vehicle's component
/// ([`DomainStats::excluded`]) than that many voxels. Safe space the vehicle cannot reach means
/// a passage it has seen through is closed, by noise (docs/RESULTS.md: the thesis apartment's
/// 0.9 m hall, with a stereo camera) or by a gap: the crumbs of frontier on this side may be
/// that passage, and looking at them from near may open it, so they are not sealed. Always
/// false when the rule is off (area ≤ 0 or not finite), and with noisy depth
/// ([`IntegrationParams::depth_noise_per_m`] > 0, the stereo sensor model): there a crumb may be
/// a passage the noise narrowed without any safe space beyond it seen yet, and once sealed the
/// end's [`Reopening`](crate::planning::domain::Reopening) cannot open it (measured: the thesis apartment's hall under σ = 1 px,
/// `tests/tests/evaluation.rs`, `a_hall_closed_by_doubtful_voxels_is_reopened_before_the_end`).
pub(crate) fn is_far_remnant(
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

/// [`Explorer::plan_home`](super::Explorer::plan_home) reports the vehicle home within this distance of it, metres.
pub const HOME_REACHED_M: f32 = 0.15;

/// Refused frames in a row, each within [`ExplorerConfig::max_frame_jump_m`](super::ExplorerConfig::max_frame_jump_m) of the one before,
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
            plan_coarsening: 1,
        }
    }
}

/// Buffers an explorer works in, each with at least one entry per voxel except `touched`
/// ([`map::touched_words`](crate::mapping::map::touched_words): one bit per voxel) and `queue` (any
/// length ≥ 1; a few thousand entries keep the flood fill to one pass). The multigrid buffers
/// are sized by [`crate::planning::solve::multigrid::scratch_size`]; they may be empty when the solver is
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
    /// [`MultigridStorage::masks`](crate::planning::solve::multigrid::MultigridStorage::masks)): faster sweeps for 1 byte per voxel.
    pub masks: &'a mut [u8],
    /// The map's per-voxel surface estimate for noisy depth (optional, two words per voxel; see
    /// [`crate::mapping::integrate`]); empty, noisy frames are decided by the per-frame vote alone.
    pub surface: &'a mut [[i32; 2]],
    /// The other sweep of the thesis's Jacobi solve ([`SolverKind::ThesisJacobi`] only: one
    /// entry per voxel then; otherwise it may be empty).
    pub jacobi: &'a mut [f32],
    /// Labels of the box a local re-solve cuts out ([`crate::planning::solve::local`]; optional, like
    /// `krylov`): with this and `local_psi` lent ([`crate::planning::solve::local::box_scratch_len`] of
    /// the grid each, or less: a box never exceeds what is lent), a re-solve of
    /// the screened field after a scan works in boxes around what changed. Empty: every solve
    /// sweeps the whole grid.
    pub local_labels: &'a mut [Label],
    /// Values of that box (as many as `local_labels`).
    pub local_psi: &'a mut [f32],
    /// The flat solver's storage (`SolverKind::Flat` only, with the `flat` feature; otherwise
    /// it may be empty and is not used).
    pub flat: &'a mut [f32],
    /// With [`ExplorerConfig::plan_coarsening`] above 1: the log-odds of the map at the mission
    /// grid's resolution (one per voxel of the grid), which frames are integrated into; every
    /// buffer above is then sized for the coarser planning grid. Empty otherwise.
    pub fine_log_odds: &'a mut [i8],
    /// Its touched bits ([`map::touched_words`](crate::mapping::map::touched_words) of the
    /// mission grid). Empty without a fine map.
    pub fine_touched: &'a mut [u32],
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
            + size_of_val(self.fine_log_odds)
            + size_of_val(self.fine_touched)
    }
}

/// Checks a frame's [`FrameTiming`] against `config`'s limits
/// ([`ExplorerConfig::max_frame_yaw_rate`](super::ExplorerConfig::max_frame_yaw_rate), [`ExplorerConfig::max_frame_pose_lag_ms`](super::ExplorerConfig::max_frame_pose_lag_ms)); a
/// refusal is counted in `errors` (and in [`ErrorCounters::frames_rejected`]).
pub(crate) fn check_frame_timing(
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
