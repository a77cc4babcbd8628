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
//! The baselines ([`baseline`]) live on the host and use `std`, but they read the same map the
//! core integrates into (the core's [`VoxelMap`] and [`integrate`](harmonic_core::integrate)),
//! plan over the same inflated safe space (the labels of [`harmonic_core::domain::build`]: the
//! vehicle's component of free space eroded by the vehicle radius; its frontier voxels are the
//! harmonic planner's sinks) and end, like the core, when that space has no frontier left.
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
pub mod search;

use std::fmt;
use std::str::FromStr;
use std::time::Instant;

use harmonic_core::camera::DepthFrame;
use harmonic_core::domain::Label;
use harmonic_core::explore::{
    Clock, Explorer, ExplorerStorage, Fault, FrameTiming, PlanOutcome, SolverKind, Status,
};
use harmonic_core::field::PlanningField;
use harmonic_core::map::{self, Dims, VoxelMap};
use harmonic_core::solve::multigrid;
use nalgebra::{Isometry3, Point3};

/// The planners the simulator can fly.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum PlannerKind {
    /// The core's explorer with its default (screened, frontier-sourced) field, multigrid.
    Harmonic,
    /// The core's explorer with the seed's Laplace field, multigrid.
    HarmonicLaplace,
    /// The core's explorer with the seed's Laplace field and the seed paper's Gauss-Seidel.
    HarmonicGs,
    /// The core's explorer with the seed's Laplace field, solved the seed thesis's way
    /// ([`SolverKind::ThesisJacobi`]). Selectable by name; not in [`PlannerKind::ALL`], so `all`
    /// and the default sweeps do not include it.
    HarmonicThesis,
    /// Closest frontier + A*.
    ClosestFrontier,
    /// Random frontier + A*.
    RandomFrontier,
    /// Information gain: most frontier voxels visible from a candidate pose.
    InfoGain,
    /// Information gain weighted by path length, g·exp(−λL).
    WeightedInfoGain,
}

impl PlannerKind {
    /// Every planner of the comparison, in the order tables list them (`all`). The
    /// thesis-faithful ablation [`PlannerKind::HarmonicThesis`] is left out: see
    /// [`PlannerKind::ABLATIONS`].
    pub const ALL: [PlannerKind; 7] = [
        PlannerKind::RandomFrontier,
        PlannerKind::ClosestFrontier,
        PlannerKind::InfoGain,
        PlannerKind::WeightedInfoGain,
        PlannerKind::HarmonicGs,
        PlannerKind::HarmonicLaplace,
        PlannerKind::Harmonic,
    ];

    /// Ablations `--planner` accepts by name but `all` leaves out.
    pub const ABLATIONS: [PlannerKind; 1] = [PlannerKind::HarmonicThesis];

    /// Every planner `--planner` accepts by name: [`PlannerKind::ALL`], then the ablations.
    pub fn named() -> impl Iterator<Item = PlannerKind> {
        Self::ALL.into_iter().chain(Self::ABLATIONS)
    }

    /// The name `--planner` takes.
    pub fn name(self) -> &'static str {
        match self {
            PlannerKind::Harmonic => "harmonic",
            PlannerKind::HarmonicLaplace => "harmonic-laplace",
            PlannerKind::HarmonicGs => "harmonic-gs",
            PlannerKind::HarmonicThesis => "harmonic-thesis",
            PlannerKind::ClosestFrontier => "closest-frontier",
            PlannerKind::RandomFrontier => "random-frontier",
            PlannerKind::InfoGain => "info-gain",
            PlannerKind::WeightedInfoGain => "weighted-info-gain",
        }
    }

    /// True for the core's explorer (any field, either solver).
    pub fn is_harmonic(self) -> bool {
        matches!(
            self,
            PlannerKind::Harmonic
                | PlannerKind::HarmonicLaplace
                | PlannerKind::HarmonicGs
                | PlannerKind::HarmonicThesis
        )
    }

    /// Parses `all` or a comma-separated list of names (duplicates removed, order kept).
    pub fn parse_list(s: &str) -> Result<Vec<PlannerKind>, String> {
        if s.trim() == "all" {
            return Ok(Self::ALL.to_vec());
        }
        let mut out = Vec::new();
        for part in s.split(',') {
            let k = part.trim().parse::<PlannerKind>()?;
            if !out.contains(&k) {
                out.push(k);
            }
        }
        Ok(out)
    }
}

impl fmt::Display for PlannerKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for PlannerKind {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        Self::named().find(|k| k.name() == s).ok_or_else(|| {
            let names: Vec<&str> = Self::named().map(|k| k.name()).collect();
            format!("unknown planner `{s}` (expected one of {})", names.join(", "))
        })
    }
}

/// Nanosecond host clock for per-phase timing (implements the core's [`Clock`]).
pub struct HostClock(Instant);

impl HostClock {
    /// A clock starting now.
    pub fn new() -> Self {
        Self(Instant::now())
    }
}

impl Default for HostClock {
    fn default() -> Self {
        Self::new()
    }
}

impl Clock for HostClock {
    fn ticks(&mut self) -> u64 {
        self.0.elapsed().as_nanos() as u64
    }
}

/// Heap storage for a [`Multigrid`](multigrid::Multigrid) on one grid
/// ([`multigrid::scratch_size`]): what an explorer lends its solver ([`HostStorage`]), and the
/// host tools' solves.
pub struct MultigridScratch {
    values: Vec<f32>,
    labels: Vec<Label>,
    faces: Vec<[u8; 4]>,
    krylov: Vec<f32>,
    masks: Vec<u8>,
}

impl MultigridScratch {
    /// Zeroed storage sized for `dims`.
    pub fn new(dims: &Dims) -> Self {
        let size = multigrid::scratch_size(dims);
        Self {
            values: vec![0.0; size.values],
            labels: vec![Label::Outside; size.labels],
            faces: vec![[0; 4]; size.faces],
            krylov: vec![0.0; size.krylov],
            masks: vec![0; size.masks],
        }
    }

    /// The storage to lend [`Multigrid::new`](multigrid::Multigrid::new).
    pub fn storage(&mut self) -> multigrid::MultigridStorage<'_> {
        multigrid::MultigridStorage {
            values: self.values.as_mut_slice().into(),
            labels: &mut self.labels,
            faces: &mut self.faces,
            krylov: &mut self.krylov,
            masks: &mut self.masks,
        }
    }
}

/// Host-owned buffers for one explorer.
pub struct HostStorage {
    dims: Dims,
    log_odds: Vec<i8>,
    touched: Vec<u32>,
    labels: Vec<Label>,
    phi: Vec<f32>,
    queue: Vec<u32>,
    solver: MultigridScratch,
    /// The map's surface estimate: empty until [`HostStorage::with_surface`].
    surface: Vec<[i32; 2]>,
    /// The thesis's Jacobi scratch: empty until [`HostStorage::with_jacobi`].
    jacobi: Vec<f32>,
    /// The box of local re-solves: three quarters of a grid, the most
    /// [`MAX_SHARE`](harmonic_core::solve::local::MAX_SHARE) lets a box take.
    local_labels: Vec<Label>,
    /// Its values.
    local_psi: Vec<f32>,
    /// The flat solver's storage: empty until [`HostStorage::with_flat`].
    flat: Vec<f32>,
}

impl HostStorage {
    /// Buffers for `dims`, with MGPCG storage, the fine level's neighbour masks and a box for
    /// local re-solves.
    pub fn new(dims: &Dims) -> Self {
        let n = dims.len();
        let box_cells = harmonic_core::solve::local::box_scratch_len(n);
        Self {
            dims: *dims,
            solver: MultigridScratch::new(dims),
            surface: Vec::new(),
            log_odds: vec![0; n],
            touched: vec![0; map::touched_words(dims)],
            labels: vec![Label::Outside; n],
            phi: vec![0.0; n],
            queue: vec![0; 16 * 1024],
            jacobi: Vec::new(),
            local_labels: vec![Label::Outside; box_cells],
            local_psi: vec![0.0; box_cells],
            flat: Vec::new(),
        }
    }
    /// Adds the storage of the flat solver ([`SolverKind::Flat`](harmonic_core::explore::SolverKind::Flat),
    /// [`harmonic_core::solve::flat::flat_scratch_len`] values); a no-op if it is there.
    pub fn with_flat(&mut self) -> &mut Self {
        self.flat
            .resize(harmonic_core::solve::flat::flat_scratch_len(&self.dims), 0.0);
        self
    }
    /// Adds the one-per-voxel scratch the thesis's Jacobi solve needs
    /// ([`SolverKind::ThesisJacobi`]); a no-op if it is there.
    pub fn with_jacobi(&mut self) -> &mut Self {
        self.jacobi.resize(self.phi.len(), 0.0);
        self
    }
    /// Adds the map's surface estimate for noisy depth (two words per voxel; see
    /// [`harmonic_core::integrate`]); a no-op if it is there.
    pub fn with_surface(&mut self) -> &mut Self {
        self.surface.resize(self.phi.len(), [0, 0]);
        self
    }
    /// Lends the buffers to an explorer.
    pub fn lend(&mut self) -> ExplorerStorage<'_> {
        let solver = self.solver.storage();
        ExplorerStorage {
            log_odds: &mut self.log_odds,
            touched: &mut self.touched,
            labels: &mut self.labels,
            phi: &mut self.phi,
            queue: &mut self.queue,
            coarse_values: solver.values,
            coarse_labels: solver.labels,
            coarse_faces: solver.faces,
            krylov: solver.krylov,
            masks: solver.masks,
            surface: &mut self.surface,
            jacobi: &mut self.jacobi,
            local_labels: &mut self.local_labels,
            local_psi: &mut self.local_psi,
            flat: &mut self.flat,
        }
    }
}

/// What the run loop asks of a planner: integrate frames, plan from a pose, and report.
///
/// Phase times in [`Status::phase_ticks`] are nanoseconds of a [`HostClock`]: for the harmonic
/// planners domain / solve / streamline; for the baselines domain / search (A*, Dijkstra and
/// the gain evaluation) / goal choice.
pub trait Planner {
    /// The planner's kind.
    fn kind(&self) -> PlannerKind;
    /// Integrates one depth frame taken from `camera_pose` (camera → map); with `timing`, the
    /// core first refuses a frame taken while turning too fast or on a lagging pose
    /// ([`harmonic_core::explore::check_frame_timing`]). The fault if the core rejected it
    /// (counted in the status).
    fn integrate(
        &mut self,
        frame: &DepthFrame<'_>,
        camera_pose: &Isometry3<f32>,
        timing: Option<&FrameTiming>,
    ) -> Result<(), Fault>;
    /// Plans from the vehicle at `position` with heading `yaw`.
    fn plan(&mut self, position: &Point3<f32>, yaw: f32, clock: &mut HostClock) -> PlanOutcome;
    /// Plans the way back to `home` through known free space: `Complete` once there (within
    /// [`harmonic_core::explore::HOME_REACHED_M`]), `Hold(HomeUnreachable)` if home is not in
    /// the vehicle's safe space. The core's planners follow their field with home as its only
    /// target ([`harmonic_core::explore::Explorer::plan_home`]); the baselines take A* there.
    fn plan_home(
        &mut self,
        position: &Point3<f32>,
        yaw: f32,
        home: &Point3<f32>,
        clock: &mut HostClock,
    ) -> PlanOutcome;
    /// Waypoints from the vehicle to the last goal, map frame.
    fn waypoints(&self) -> &[Point3<f32>];
    /// The occupancy map.
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

/// The core's explorer as a [`Planner`].
pub struct HarmonicPlanner<'a> {
    explorer: Explorer<'a>,
    kind: PlannerKind,
}

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

impl Planner for HarmonicPlanner<'_> {
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
    fn plan(&mut self, position: &Point3<f32>, yaw: f32, clock: &mut HostClock) -> PlanOutcome {
        self.explorer.plan_timed(position, yaw, clock)
    }
    fn plan_home(
        &mut self,
        position: &Point3<f32>,
        yaw: f32,
        home: &Point3<f32>,
        clock: &mut HostClock,
    ) -> PlanOutcome {
        self.explorer.plan_home(position, yaw, home, clock)
    }
    fn waypoints(&self) -> &[Point3<f32>] {
        self.explorer.waypoints()
    }
    fn map(&self) -> &VoxelMap<'_> {
        self.explorer.map()
    }
    fn status(&self) -> &Status {
        self.explorer.status()
    }
    fn labels(&self) -> &[Label] {
        self.explorer.labels()
    }
    fn potential(&self) -> Option<&[f32]> {
        Some(self.explorer.psi())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_thesis_ablation_is_named_but_not_in_all() {
        assert_eq!(
            "harmonic-thesis".parse::<PlannerKind>(),
            Ok(PlannerKind::HarmonicThesis)
        );
        assert!(!PlannerKind::ALL.contains(&PlannerKind::HarmonicThesis));
        assert!(PlannerKind::HarmonicThesis.is_harmonic());
        assert_eq!(PlannerKind::parse_list("all").unwrap(), PlannerKind::ALL.to_vec());
        for k in PlannerKind::named() {
            assert_eq!(k.name().parse::<PlannerKind>(), Ok(k));
        }
    }
}
