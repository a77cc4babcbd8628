//! Exploration planners: the core's harmonic [`Explorer`] and the baselines of the seed thesis
//! (Shade 2011, §6.5), behind one [`Planner`] interface so that the simulator flies all of them
//! through the same map, camera, vehicle and run loop.
//!
//! | name | what it does |
//! |---|---|
//! | `harmonic` | the core's explorer with its default field (frontier-sourced, screened; [`harmonic_core::field`]) on multigrid |
//! | `harmonic-laplace` | the core's explorer with the seed's field (vehicle φ = 1, frontiers φ = 0, Laplace) on multigrid |
//! | `harmonic-gs` | the seed's field with the seed paper's Gauss-Seidel solver |
//! | `harmonic-thesis` | the seed's field solved the thesis's way: Jacobi from φ = 0 at every plan, stopped at a relative change below 1e-4 ([`harmonic_core::solve::thesis`]); an ablation, not in [`PlannerKind::ALL`] |
//! | `closest-frontier` | A* to the frontier with the shortest path (Yamauchi 1997) |
//! | `random-frontier` | A* to a frontier drawn uniformly at random |
//! | `info-gain` | the candidate pose that sees the most frontier voxels (Thrun's binary gain) |
//! | `weighted-info-gain` | the candidate maximising g·exp(−λL), λ = 0.2 (González-Baños & Latombe) |
//!
//! Every planner is the core's [`Explorer`] with a different target choice
//! ([`harmonic_core::explore::target`]): the harmonic planners its own field
//! ([`HarmonicField`]), the baselines ([`baseline`], on the host: they use `std`) a search.
//! So all of them integrate into the same map, plan over the same inflated safe space (the
//! labels of [`harmonic_core::domain::build`]: the vehicle's component of free space eroded by
//! the vehicle radius; its frontier voxels are the harmonic planner's sinks), and share the
//! explorer's termination, escape, goal keeping, sealing, look-around, frame checks and way
//! home: only the choice of target and the way to it differ.
//!
//! "Planning ops" ([`Status::planning_ops`]) count each planner's elementary voxel operations:
//! solver cell updates for the harmonic planners; search-node expansions plus voxels stepped by
//! line-of-sight and visibility ray casts for the baselines.
//!
//! In: the depth frames the run hands over (after the depth link) with their poses, and the
//! vehicle's pose at each planning step; the buffers every planner borrows ([`HostStorage`]).
//! Out: the map, the plan (waypoints, goal, or the reason there is none) and the planning
//! statistics, through [`Planner`]. The run picks the planner ([`PlannerKind`]) and flies the
//! plan; nothing here depends on another stage of the simulator.

pub mod baseline;
mod kind;
pub mod search;
mod storage;

pub use kind::PlannerKind;
pub use storage::{HostClock, HostStorage, MultigridScratch};

use baseline::Baseline;

use harmonic_core::camera::DepthFrame;
use harmonic_core::companion::Planning;
use harmonic_core::domain::Label;
use harmonic_core::explore::{
    Explorer, Fault, FrameTiming, HarmonicField, PlanOutcome, SolverKind, Status, TargetChoice,
};
use harmonic_core::field::PlanningField;
use harmonic_core::map::VoxelMap;
use nalgebra::{Isometry3, Point3};

/// What the run loop asks of a planner: integrate frames, plan ([`Planning`]: exploration and
/// the way home, as the companion's mission asks), and report.
///
/// Phase times in [`Status::phase_ticks`] are nanoseconds of a [`HostClock`]: for the harmonic
/// planners domain / solve / streamline; for the baselines domain / search (A*, Dijkstra and
/// the gain evaluation) / goal choice.
pub trait Planner: Planning<HostClock> {
    /// The planner's kind.
    fn kind(&self) -> PlannerKind;
    /// Integrates one depth frame taken from `camera_pose` (camera → map); with `timing`, the
    /// core first refuses a frame taken while turning too fast or on a lagging pose
    /// ([`ExplorerConfig::max_frame_yaw_rate`](harmonic_core::explore::ExplorerConfig::max_frame_yaw_rate), `max_frame_pose_lag_ms`). The fault if the core rejected it
    /// (counted in the status).
    fn integrate(
        &mut self,
        frame: &DepthFrame<'_>,
        camera_pose: &Isometry3<f32>,
        timing: Option<&FrameTiming>,
    ) -> Result<(), Fault>;
    /// Waypoints from the vehicle to the last goal, map frame.
    fn waypoints(&self) -> &[Point3<f32>];
    /// The occupancy map over the mission grid (the one frames are integrated into).
    fn map(&self) -> &VoxelMap<'_>;
    /// Status and counters (the core's [`Status`], filled the same way by every planner).
    fn status(&self) -> &Status;
    /// Domain labels of the last full plan.
    fn labels(&self) -> &[Label];
    /// The stored potential ψ = 1 − φ of the last plan (harmonic planners only).
    fn potential(&self) -> Option<&[f32]> {
        None
    }
}

/// The core's explorer, with one planner's target choice, as a [`Planner`].
pub struct CorePlanner<'a, T> {
    explorer: Explorer<'a, T>,
    kind: PlannerKind,
}

/// The core's explorer with its own (harmonic) target choice.
pub type HarmonicPlanner<'a> = CorePlanner<'a, HarmonicField<'a>>;

impl<'a> HarmonicPlanner<'a> {
    /// Wraps an explorer; its kind is read off its field and solver.
    pub fn new(explorer: Explorer<'a>) -> Self {
        let config = explorer.config();
        let kind = match (config.field, config.solver) {
            (PlanningField::Harmonic, SolverKind::GaussSeidel) => PlannerKind::HarmonicGs,
            (PlanningField::Harmonic, SolverKind::Multigrid | SolverKind::Flat) => {
                PlannerKind::HarmonicLaplace
            }
            (PlanningField::Harmonic, SolverKind::ThesisJacobi) => PlannerKind::HarmonicThesis,
            (PlanningField::Screened(_), _) => PlannerKind::Harmonic,
        };
        Self { explorer, kind }
    }
}

impl<'a> CorePlanner<'a, Baseline> {
    /// Wraps an explorer whose targets a baseline chooses.
    pub fn baseline(explorer: Explorer<'a, Baseline>) -> Self {
        let kind = explorer.targets().kind();
        Self { explorer, kind }
    }
}

/// Exploration and the way home, as the companion's mission asks for them: the explorer's
/// ([`Explorer::plan_timed`], [`Explorer::plan_home`]). Phase times in nanoseconds of the
/// [`HostClock`].
impl<T: TargetChoice> Planning<HostClock> for CorePlanner<'_, T> {
    fn explore(&mut self, position: &Point3<f32>, yaw: f32, clock: &mut HostClock) -> PlanOutcome {
        self.explorer.explore(position, yaw, clock)
    }
    fn go_home(
        &mut self,
        position: &Point3<f32>,
        yaw: f32,
        home: &Point3<f32>,
        clock: &mut HostClock,
    ) -> PlanOutcome {
        self.explorer.go_home(position, yaw, home, clock)
    }
}

impl<T: TargetChoice> Planner for CorePlanner<'_, T> {
    fn kind(&self) -> PlannerKind {
        self.kind
    }
    fn integrate(
        &mut self,
        frame: &DepthFrame<'_>,
        camera_pose: &Isometry3<f32>,
        timing: Option<&FrameTiming>,
    ) -> Result<(), Fault> {
        match timing {
            Some(timing) => self.explorer.integrate_timed(frame, camera_pose, timing),
            None => self.explorer.integrate(frame, camera_pose),
        }
        .map(|_| ())
    }
    fn waypoints(&self) -> &[Point3<f32>] {
        self.explorer.waypoints()
    }
    fn map(&self) -> &VoxelMap<'_> {
        self.explorer.observed_map()
    }
    fn status(&self) -> &Status {
        self.explorer.status()
    }
    fn labels(&self) -> &[Label] {
        self.explorer.labels()
    }
    fn potential(&self) -> Option<&[f32]> {
        self.explorer.targets().potential()
    }
}
