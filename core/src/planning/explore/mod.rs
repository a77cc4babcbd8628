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
//! 2. build the domain around the vehicle ([`crate::planning::domain`]); no frontier in the vehicle's
//!    component means exploration is **complete**;
//! 3. solve the planning field ([`crate::planning::field`]: by default the frontier-sourced screened
//!    field, u = 1 on frontiers, ∇²u = κ²u elsewhere; or the seed's Laplace field with the
//!    vehicle as source), warm-started from the previous solution ([`crate::planning::solve`]);
//! 4. trace the streamline from the vehicle to a frontier ([`crate::planning::streamline`]);
//! 5. choose the goal (the view): the *first* point of the streamline from which the frontier
//!    is in plain sight (free voxels all the way) within [`ExplorerConfig::view_range_m`] and
//!    inside the vertical field of view — often the vehicle's own position, which then only
//!    turns to look; if that view taught nothing, the point *closest to the end* that sees it
//!    beyond the minimum range; if no point of the streamline sees it (a frontier inside the
//!    minimum range, or straight above or below), a point backed off from it, level with it,
//!    that does. The goal yaw faces the frontier. The way to the goal is the streamline up to
//!    it pulled taut through the safe space ([`streamline::pull_taut`](crate::planning::streamline::pull_taut),
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
//! vehicle cannot reach, nor with noisy depth: then a passage may be
//! closed by noise, and the crumbs may be the way through. Measured in docs/RESULTS.md ("Now:
//! far remnants sealed").
//!
//! Faults never panic: a plan that cannot be made returns [`PlanOutcome::Hold`] with the reason,
//! and the reason's counter in [`ErrorCounters`] goes up; the caller keeps the last safe setpoint.

mod config;
pub mod harmonic;
mod looks;
mod status;
pub mod target;

use config::{check_frame_timing, is_far_remnant};
pub use config::{
    ExplorerConfig, ExplorerStorage, FrameTiming, SolverKind, FRAMES_TO_ACCEPT_JUMP, HOME_REACHED_M,
    PLAN_PASSES,
};
pub use harmonic::{FieldStorage, HarmonicField};
pub use looks::unexplored_in_view;
use looks::ArrivalLooks;
pub use status::{ConfigError, ErrorCounters, Fault, Goal, PhaseTicks, PlanOutcome, Status, Termination};

use crate::clock::{Clock, NoClock};
pub use target::{Chosen, Context, TargetChoice, Watch};

use core::mem::MaybeUninit;

use nalgebra::{Isometry3, Point3, Vector3};

use crate::mapping::camera::{DepthFrame, Intrinsics};
use crate::mapping::integrate::{self, IntegrateError, IntegrationStats};
use crate::mapping::map::{MapGeometry, VoxelIndex, VoxelMap};
use crate::planning::domain::{self, DomainError, DomainStats, Inflation, Label, Reopening};
use crate::planning::streamline::{StreamlineError, Waypoints};

/// A watch of one voxel.
fn watch_of(v: VoxelIndex) -> Watch {
    let mut watch = Watch::new();
    let _ = watch.push(v);
    watch
}

/// The exploration core: the loop every planner shares, around a [`TargetChoice`] (by default
/// the harmonic planner's field, [`HarmonicField`]).
pub struct Explorer<'a, T = HarmonicField<'a>> {
    config: ExplorerConfig,
    /// The map planned on: the map itself, or with [`ExplorerConfig::plan_coarsening`] the
    /// coarser grid pooled from `observed`.
    map: VoxelMap<'a>,
    /// With [`ExplorerConfig::plan_coarsening`] above 1: the map frames are integrated into,
    /// at the mission grid's resolution.
    observed: Option<VoxelMap<'a>>,
    inflation: Inflation,
    labels: &'a mut [Label],
    queue: &'a mut [u32],
    targets: T,
    waypoints: Waypoints,
    intrinsics: Option<Intrinsics>,
    last_goal: Option<Goal>,
    /// The voxels that keep the last goal open ([`Chosen::Way`]).
    last_watch: Watch,
    /// Camera position of the last integrated frame.
    last_frame_origin: Option<Point3<f32>>,
    /// A jumped camera position being refused, and how many frames in a row agreed on it.
    jump_candidate: Option<(Point3<f32>, u8)>,
    fruitless_visits: u8,
    /// Unexplored voxels at the previous full plan, to tell visits that taught nothing.
    unexplored_at_last_plan: Option<u32>,
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
    /// Builds the harmonic planner's explorer over `geometry` in `storage` (the field is
    /// solved in its solver buffers, [`HarmonicField`]); the map starts all unknown.
    pub fn new(
        geometry: MapGeometry,
        config: ExplorerConfig,
        storage: ExplorerStorage<'a>,
    ) -> Result<Self, ConfigError> {
        let plan = planning_geometry(&geometry, &config)?;
        let n = plan.dims().len();
        if storage.labels.len() < n || storage.phi.len() < n || storage.queue.is_empty() {
            return Err(ConfigError::StorageTooSmall);
        }
        let (map, field) = split(storage);
        let targets = HarmonicField::new(&plan, &config, field)?;
        Self::build(geometry, config, map, targets)
    }

    /// [`Explorer::new`], built in `slot` (a `static` on a board): the explorer is never a value
    /// on the stack, which at boot has a few KiB to spare.
    pub fn new_in(
        slot: &'a mut MaybeUninit<Self>,
        geometry: MapGeometry,
        config: ExplorerConfig,
        storage: ExplorerStorage<'a>,
    ) -> Result<&'a mut Self, ConfigError> {
        let plan = planning_geometry(&geometry, &config)?;
        let n = plan.dims().len();
        if storage.labels.len() < n || storage.phi.len() < n || storage.queue.is_empty() {
            return Err(ConfigError::StorageTooSmall);
        }
        let (map, field) = split(storage);
        let targets = HarmonicField::new(&plan, &config, field)?;
        let parts = Parts::new(geometry, &config, map)?;
        Ok(slot.write(parts.explorer(config, targets)))
    }

    /// The stored potential ψ = 1 − φ of the last plan (see [`crate::planning::solve`]).
    pub fn psi(&self) -> &[f32] {
        self.targets.psi()
    }
}

/// The grid an explorer of the mission grid `geometry` plans on: the grid itself, or
/// [`ExplorerConfig::plan_coarsening`] times coarser.
fn planning_geometry(geometry: &MapGeometry, config: &ExplorerConfig) -> Result<MapGeometry, ConfigError> {
    match config.plan_coarsening {
        0 | 1 => Ok(*geometry),
        f => geometry.coarsened(usize::from(f)).map_err(ConfigError::Map),
    }
}

/// The buffers of the map and the domain (the part of [`ExplorerStorage`] every planner uses).
struct MapStorage<'a> {
    log_odds: &'a mut [i8],
    touched: &'a mut [u32],
    labels: &'a mut [Label],
    queue: &'a mut [u32],
    surface: &'a mut [[i32; 2]],
    fine_log_odds: &'a mut [i8],
    fine_touched: &'a mut [u32],
}

/// What an explorer is built from, checked: the maps over their buffers, the inflation, the
/// labels and the queue.
struct Parts<'a> {
    map: VoxelMap<'a>,
    observed: Option<VoxelMap<'a>>,
    inflation: Inflation,
    labels: &'a mut [Label],
    queue: &'a mut [u32],
}

impl<'a> Parts<'a> {
    fn new(
        geometry: MapGeometry,
        config: &ExplorerConfig,
        storage: MapStorage<'a>,
    ) -> Result<Self, ConfigError> {
        let plan = planning_geometry(&geometry, config)?;
        let n = plan.dims().len();
        let MapStorage {
            log_odds,
            touched,
            labels,
            queue,
            surface,
            fine_log_odds,
            fine_touched,
        } = storage;
        if labels.len() < n || queue.is_empty() {
            return Err(ConfigError::StorageTooSmall);
        }
        let map = VoxelMap::new(plan, config.log_odds, log_odds, touched).map_err(ConfigError::Map)?;
        let (map, observed) = if plan == geometry {
            (map.with_surface(surface), None)
        } else {
            let fine = VoxelMap::new(geometry, config.log_odds, fine_log_odds, fine_touched)
                .map_err(|_| ConfigError::StorageTooSmall)?
                .with_surface(surface);
            (map, Some(fine))
        };
        let inflation = Inflation::new(config.vehicle_radius, config.narrow_radius, plan.resolution())
            .map_err(ConfigError::Domain)?;
        let labels = labels.get_mut(..n).ok_or(ConfigError::StorageTooSmall)?;
        labels.fill(Label::Outside);
        Ok(Self {
            map,
            observed,
            inflation,
            labels,
            queue,
        })
    }

    /// The explorer of these parts, choosing targets with `targets`. Inlined, so that a caller
    /// that writes it into a slot builds it there.
    #[inline(always)]
    fn explorer<T>(self, config: ExplorerConfig, targets: T) -> Explorer<'a, T> {
        Explorer {
            config,
            map: self.map,
            observed: self.observed,
            inflation: self.inflation,
            labels: self.labels,
            queue: self.queue,
            targets,
            waypoints: Waypoints::new(),
            intrinsics: None,
            last_goal: None,
            last_watch: Watch::new(),
            last_frame_origin: None,
            jump_candidate: None,
            fruitless_visits: 0,
            unexplored_at_last_plan: None,
            goal_from_afar: false,
            go_near: false,
            last_plan_position: None,
            looks: ArrivalLooks::default(),
            reopening: Reopening::default(),
            status: Status::default(),
        }
    }
}

/// `storage` as the map's buffers and the harmonic field's.
fn split(storage: ExplorerStorage<'_>) -> (MapStorage<'_>, FieldStorage<'_>) {
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
        fine_log_odds,
        fine_touched,
    } = storage;
    let map = MapStorage {
        log_odds,
        touched,
        labels,
        queue,
        surface,
        fine_log_odds,
        fine_touched,
    };
    let field = FieldStorage {
        phi,
        coarse_values,
        coarse_labels,
        coarse_faces,
        krylov,
        masks,
        jacobi,
        local_labels,
        local_psi,
        flat,
    };
    (map, field)
}

impl<'a, T: TargetChoice> Explorer<'a, T> {
    /// Builds an explorer whose targets `targets` chooses, over `geometry`, in `storage`'s map,
    /// label and queue buffers (and its surface estimate, if lent; the solver buffers are not
    /// used: a choice brings its own); the map starts all unknown.
    pub fn with_targets(
        geometry: MapGeometry,
        config: ExplorerConfig,
        storage: ExplorerStorage<'a>,
        targets: T,
    ) -> Result<Self, ConfigError> {
        Self::build(geometry, config, split(storage).0, targets)
    }

    fn build(
        geometry: MapGeometry,
        config: ExplorerConfig,
        storage: MapStorage<'a>,
        targets: T,
    ) -> Result<Self, ConfigError> {
        let parts = Parts::new(geometry, &config, storage)?;
        Ok(parts.explorer(config, targets))
    }

    /// [`Explorer::with_targets`], built in `slot` (a `static` on a board): the explorer is
    /// never a value on the stack, which at boot has a few KiB to spare.
    pub fn with_targets_in(
        slot: &'a mut MaybeUninit<Self>,
        geometry: MapGeometry,
        config: ExplorerConfig,
        storage: ExplorerStorage<'a>,
        targets: T,
    ) -> Result<&'a mut Self, ConfigError> {
        let parts = Parts::new(geometry, &config, split(storage).0)?;
        Ok(slot.write(parts.explorer(config, targets)))
    }

    /// The map, to write what is known before the first plan (a prior map, a test's): the next
    /// plan reads it as it is.
    pub fn map_mut(&mut self) -> &mut VoxelMap<'a> {
        &mut self.map
    }

    /// The target choice.
    pub fn targets(&self) -> &T {
        &self.targets
    }

    /// The configuration.
    pub fn config(&self) -> &ExplorerConfig {
        &self.config
    }
    /// The map planned on (with [`ExplorerConfig::plan_coarsening`], the coarser grid pooled
    /// from [`Explorer::observed_map`]).
    pub fn map(&self) -> &VoxelMap<'a> {
        &self.map
    }
    /// The map frames are integrated into, over the mission grid: [`Explorer::map`] itself
    /// unless the explorer plans on a coarser grid.
    pub fn observed_map(&self) -> &VoxelMap<'a> {
        self.observed.as_ref().unwrap_or(&self.map)
    }
    /// Domain labels of the last plan.
    pub fn labels(&self) -> &[Label] {
        self.labels
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
        let target = self.observed.as_mut().unwrap_or(&mut self.map);
        match integrate::integrate_with_scratch(
            target,
            frame,
            camera_pose,
            &self.config.integration,
            self.queue,
        ) {
            Ok(stats) => {
                if let Some(fine) = &self.observed {
                    self.map.pool_from(fine, usize::from(self.config.plan_coarsening));
                }
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
        self.status.plan_iterations = 0;
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
        let reach = domain::frontier_reach(self.inflation.stencil());
        let still_open = self
            .last_watch
            .iter()
            .any(|w| domain::any_near(&self.map, *w, reach, |i| self.map.is_unexplored(i)));
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
        // Learning is counted on the map frames go into: a view that observed voxels taught
        // something even when the cells pooled from them are still unknown.
        let unexplored = match &self.observed {
            Some(fine) => fine.counts().unknown,
            None => {
                let counts = self.map.counts();
                counts.unknown - counts.sealed
            }
        };
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
            let (targets, cx, way) = self.parts(vehicle);
            let chosen = targets.choose(cx, position, yaw, way, clock);
            let t3 = clock.ticks();
            let (end, watch) = match chosen {
                Chosen::Way { end, watch } => (end, watch),
                Chosen::Again => continue,
                Chosen::Goal(goal) => {
                    self.last_watch = watch_of(goal.frontier);
                    return PlanOutcome::Goal(goal);
                }
                Chosen::Hold(fault) => return PlanOutcome::Hold(fault),
            };
            self.status.streamline = Some(end);
            // The last pass flies to whatever it found, so a plan never ends on seals alone.
            if pass + 1 < PLAN_PASSES && is_far_remnant(&self.config, &geometry, &stats, end.length) {
                self.seal_watched(&watch);
                self.status.errors.remnants_sealed += 1;
                self.status.phase_ticks.streamline += clock.ticks().saturating_sub(t3);
                continue;
            }
            let revisit = self.is_fruitless_revisit(end.frontier, position, learned_nothing);
            // A look from afar that taught nothing is not yet fruitless: go near first, and
            // stay near while the frontier keeps calling.
            let retry_near = revisit && last_from_afar;
            self.go_near = revisit && (last_from_afar || self.go_near);
            let near = self.go_near;
            let (targets, cx, way) = self.parts(vehicle);
            let (goal, from_afar) = targets.goal(cx, &end, way, yaw, near);
            self.goal_from_afar = from_afar;
            self.status.phase_ticks.streamline += clock.ticks().saturating_sub(t3);
            if retry_near {
                // Not fruitless yet, and not a fresh start either.
            } else if revisit {
                self.fruitless_visits = self.fruitless_visits.saturating_add(1);
                if self.fruitless_visits >= self.config.stall_visits {
                    self.fruitless_visits = 0;
                    self.seal_watched(&watch);
                    self.status.errors.seals += 1;
                    continue;
                }
            } else {
                self.fruitless_visits = 0;
            }
            self.last_watch = watch;
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
        self.status.phase_ticks.domain += clock.ticks().saturating_sub(t0);
        if !built.is_ok_and(|s| s.frontier > 0) {
            return false;
        }
        let (targets, cx, way) = self.parts(vehicle);
        let found = targets.way_to_frontier(cx, position, way, clock);
        let gate = found
            .then(|| {
                let path = self.waypoints.iter().copied();
                domain::first_unsafe_along(&self.map, self.inflation.stencil(), position, path)
            })
            .flatten();
        self.waypoints.clear();
        gate.is_some_and(|g| {
            self.reopening
                .forget_around(&mut self.map, self.inflation.stencil(), g, below)
                > 0
        })
    }

    /// The target choice, lent the domain just built around `vehicle`, and the waypoints.
    fn parts(&mut self, vehicle: VoxelIndex) -> (&mut T, Context<'_, 'a>, &mut Waypoints) {
        let cx = Context {
            map: &self.map,
            labels: self.labels,
            vehicle,
            stencil: self.inflation.stencil(),
            config: &self.config,
            intrinsics: self.intrinsics,
            status: &mut self.status,
        };
        (&mut self.targets, cx, &mut self.waypoints)
    }

    /// Seals the unknown voxels behind each voxel of `watch` (a target whose visits keep teaching
    /// nothing, or a far remnant).
    fn seal_watched(&mut self, watch: &Watch) {
        let reach = domain::frontier_reach(self.inflation.stencil());
        for w in watch {
            domain::seal_around(&mut self.map, *w, reach);
        }
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

    /// Plans the way back to `home` through known free space: the safe space is built towards
    /// home, and the target choice finds the way there ([`TargetChoice::way_home`]; the
    /// harmonic field makes home its only target, so its streamline ends there). The goal is
    /// home, the yaw kept.
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
        self.status.plan_iterations = 0;
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
        // The vehicle stood at home, so the space its body filled there is free, however the
        // map has it now (on a coarser planning grid a cell there holding voxels the camera never
        // saw, inside its minimum range at the start, pools back to unknown).
        domain::mark_body(&mut self.map, self.inflation.stencil(), home);
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
        let (targets, cx, way) = self.parts(vehicle);
        targets.way_home(cx, position, yaw, home, home_voxel, way, clock)
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
    geometry: &crate::mapping::map::MapGeometry,
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

/// Camera pose of a forward-looking camera on a vehicle at `position` with heading `yaw`:
/// body x forward, y left, z up; camera z = body x, camera x = −body y, camera y = −body z.
pub fn forward_camera_pose(position: &Point3<f32>, yaw: f32) -> Isometry3<f32> {
    let body_from_camera = nalgebra::Matrix3::new(0.0, 0.0, 1.0, -1.0, 0.0, 0.0, 0.0, -1.0, 0.0);
    let r_cam = nalgebra::UnitQuaternion::from_matrix(&body_from_camera);
    let r_yaw = nalgebra::UnitQuaternion::from_axis_angle(&Vector3::z_axis(), yaw);
    Isometry3::from_parts(nalgebra::Translation3::from(position.coords), r_yaw * r_cam)
}

#[cfg(test)]
mod tests;
