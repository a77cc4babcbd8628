//! What an explorer reports: plan outcomes, goals, faults and their counters, the status after
//! each plan, and the clock phases are timed with.

use nalgebra::Point3;

use crate::mapping::integrate::{IntegrateError, IntegrationStats};
use crate::mapping::map::{MapCounts, MapError, VoxelIndex, VoxelMap};
use crate::planning::domain::{DomainError, DomainStats};
use crate::planning::solve::{SolveError, SolveStats};
use crate::planning::streamline::{StreamlineEnd, StreamlineError};

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
    /// ([`crate::links::operator`]). The caller, not the explorer, decides this hold.
    Operator,
    /// Returning home ([`Explorer::plan_home`](super::Explorer::plan_home)): home is not in the vehicle's safe space
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
    /// [`ExplorerConfig::max_frame_yaw_rate`](super::ExplorerConfig::max_frame_yaw_rate) when they were taken (also in `frames_rejected`).
    pub turning_frames: u32,
    /// Frames refused because the pose stream was older than the frame by more than
    /// [`ExplorerConfig::max_frame_pose_lag_ms`](super::ExplorerConfig::max_frame_pose_lag_ms) (also in `frames_rejected`).
    pub stale_pose_frames: u32,
    /// Screened-field streamlines that stalled (u unresolved far from every frontier) and
    /// were traced again on a field with half the κ.
    pub screening_retries: u32,
    /// Times the exploration would have ended while a frontier was cut off by doubtful
    /// occupied voxels alone, and the doubtful voxels in the way were forgotten to be looked
    /// at again instead ([`Reopening`](crate::planning::domain::Reopening)).
    pub reopenings: u32,
    /// Plans made at [`ExplorerConfig::narrow_radius`](super::ExplorerConfig::narrow_radius): the vehicle stood in a pocket
    /// ([`domain::is_pocket`](crate::planning::domain::is_pocket)) or, after such a plan, inside the planning radius's inflated
    /// space.
    pub pocket_plans: u32,
    /// Targets sealed instead of flown to because they were far remnants
    /// ([`ExplorerConfig::remnant_frontier_m2`](super::ExplorerConfig::remnant_frontier_m2)); not counted in `seals`.
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

/// Result of [`Explorer::plan`](super::Explorer::plan).
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum PlanOutcome {
    /// Fly to the goal through [`Explorer::waypoints`](super::Explorer::waypoints).
    Goal(Goal),
    /// Nothing reachable is left to explore.
    Complete,
    /// No plan: hold the last safe setpoint.
    Hold(Fault),
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
    /// ([`ExplorerConfig::arrival_looks`](super::ExplorerConfig::arrival_looks)) instead of re-solving.
    pub arrival_looks: u32,
    /// Total voxel updates by integration ("integration ops").
    pub integration_ops: u64,
    /// Total solver cell updates ("planning ops").
    pub planning_ops: u64,
    /// Solves of the field: every screening a plan tries, whole or in boxes.
    pub solves: u32,
    /// Solves done in boxes around what a scan changed ([`crate::planning::solve::local`]).
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
    /// Solver iterations of the last plan, all its solves together: what
    /// [`SolveParams::max_iterations`](crate::planning::solve::SolveParams::max_iterations) bounds.
    pub plan_iterations: u32,
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
