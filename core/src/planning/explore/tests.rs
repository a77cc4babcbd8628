//! The explorer's defined behaviour for bad input and dead ends (docs/RELIABILITY.md): each
//! case returns a fault or outcome the caller acts on (hold), with its counter.

extern crate std;

use std::vec;
use std::vec::Vec;

use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};

use super::looks::{octant, octant_yaw};
use super::target::heading;
use super::*;
use crate::mapping::camera::{DepthFrame, Intrinsics};
use crate::mapping::map::{Dims, MapGeometry};
use crate::planning::field::PlanningField;
use crate::planning::solve::multigrid;
use crate::planning::solve::SolveError;
use crate::planning::solve::Stop;

struct Buffers {
    log_odds: Vec<i8>,
    touched: Vec<u32>,
    labels: Vec<Label>,
    phi: Vec<f32>,
    queue: Vec<u32>,
    values: Vec<f32>,
    coarse_labels: Vec<Label>,
    faces: Vec<[u8; 4]>,
    krylov: Vec<f32>,
    masks: Vec<u8>,
    jacobi: Vec<f32>,
    local_labels: Vec<Label>,
    local_psi: Vec<f32>,
    flat: Vec<f32>,
    /// The map at the grid's resolution when the explorer plans on coarser cells (empty
    /// otherwise: [`Buffers::coarse_explorer`]).
    fine_log_odds: Vec<i8>,
    fine_touched: Vec<u32>,
}

impl Buffers {
    fn new(dims: &Dims) -> Self {
        let n = dims.len();
        let s = multigrid::scratch_size(dims);
        Self {
            log_odds: vec![0; n],
            touched: vec![0; crate::mapping::map::touched_words(dims)],
            labels: vec![Label::Outside; n],
            phi: vec![0.0; n],
            queue: vec![0; 4096],
            values: vec![0.0; s.values],
            coarse_labels: vec![Label::Outside; s.labels],
            faces: vec![[0; 4]; s.faces],
            krylov: vec![0.0; s.krylov],
            masks: vec![0; s.masks],
            jacobi: Vec::new(),
            local_labels: Vec::new(),
            local_psi: Vec::new(),
            flat: Vec::new(),
            fine_log_odds: Vec::new(),
            fine_touched: Vec::new(),
        }
    }
    fn explorer(&mut self, dims: Dims, config: ExplorerConfig) -> Explorer<'_> {
        self.try_explorer(dims, config).unwrap()
    }
    /// An explorer with the thesis's camera (its vertical field of view decides which points
    /// see a frontier) whose map holds the voxels `seen` picks as observed free, the rest
    /// unknown.
    fn seen_explorer(
        &mut self,
        dims: Dims,
        config: ExplorerConfig,
        seen: impl Fn(VoxelIndex) -> bool,
    ) -> Explorer<'_> {
        let mut e = self.explorer(dims, config);
        e.intrinsics = Some(Intrinsics::from_hfov(100, 100, 75f32.to_radians()).unwrap());
        e.map.begin_frame();
        for i in 0..dims.len() {
            if seen(dims.voxel(i)) {
                e.map.apply_miss(i);
            }
        }
        e
    }
    fn try_explorer(&mut self, dims: Dims, config: ExplorerConfig) -> Result<Explorer<'_>, ConfigError> {
        let geometry = MapGeometry::new(dims, Point3::origin(), 0.1).unwrap();
        Explorer::new(geometry, config, self.storage())
    }
    /// An explorer of `config` (which plans on coarser cells) on a 0.1 m grid of `dims`: this
    /// grid's map beside the planning buffers, which are sized for `dims` too.
    fn coarse_explorer(&mut self, dims: Dims, config: ExplorerConfig) -> Explorer<'_> {
        self.fine_log_odds = vec![0; dims.len()];
        self.fine_touched = vec![0; crate::mapping::map::touched_words(&dims)];
        let geometry = MapGeometry::new(dims, Point3::origin(), 0.1).unwrap();
        Explorer::new(geometry, config, self.storage()).unwrap()
    }
    /// The buffers lent to an explorer, with the map at the grid's resolution in `fine_*` (empty
    /// unless it plans on coarser cells).
    fn storage(&mut self) -> ExplorerStorage<'_> {
        ExplorerStorage {
            log_odds: &mut self.log_odds,
            touched: &mut self.touched,
            labels: &mut self.labels,
            phi: &mut self.phi,
            queue: &mut self.queue,
            coarse_values: self.values.as_mut_slice().into(),
            coarse_labels: &mut self.coarse_labels,
            coarse_faces: &mut self.faces,
            krylov: &mut self.krylov,
            masks: &mut self.masks,
            surface: &mut [],
            jacobi: &mut self.jacobi,
            local_labels: &mut self.local_labels,
            local_psi: &mut self.local_psi,
            flat: &mut self.flat,
            fine_log_odds: &mut self.fine_log_odds,
            fine_touched: &mut self.fine_touched,
        }
    }
}

fn intrinsics() -> Intrinsics {
    Intrinsics::from_hfov(48, 48, 2.6).unwrap()
}

/// A camera at `p` looking along `dir` (map frame).
fn looking(p: Point3<f32>, dir: Vector3<f32>) -> Isometry3<f32> {
    let r = UnitQuaternion::rotation_between(&Vector3::z(), &dir)
        .unwrap_or_else(|| UnitQuaternion::from_axis_angle(&Vector3::x_axis(), core::f32::consts::PI));
    Isometry3::from_parts(Translation3::from(p.coords), r)
}

/// Integrates an image of constant depth `mm` (0 = no return) seen from `pose`.
fn look(explorer: &mut Explorer<'_>, pose: &Isometry3<f32>, mm: u16) {
    let depth = vec![mm; intrinsics().pixel_count()];
    let frame = DepthFrame::new(intrinsics(), &depth).unwrap();
    explorer.integrate(&frame, pose).unwrap();
}

const AXES: [[f32; 3]; 6] = [
    [1.0, 0.0, 0.0],
    [-1.0, 0.0, 0.0],
    [0.0, 1.0, 0.0],
    [0.0, -1.0, 0.0],
    [0.0, 0.0, 1.0],
    [0.0, 0.0, -1.0],
];

#[test]
fn non_finite_vehicle_pose_holds_and_counts() {
    let dims = Dims::new(12, 12, 6).unwrap();
    let mut b = Buffers::new(&dims);
    let mut e = b.explorer(dims, ExplorerConfig::default());
    let p = Point3::new(0.6, 0.6, 0.3);
    assert_eq!(
        e.plan(&Point3::new(f32::NAN, 0.6, 0.3), 0.0),
        PlanOutcome::Hold(Fault::BadPose)
    );
    assert_eq!(e.plan(&p, f32::INFINITY), PlanOutcome::Hold(Fault::BadPose));
    assert_eq!(e.status().errors.bad_pose, 2);
}

#[test]
fn vehicle_outside_the_grid_holds_and_counts() {
    let dims = Dims::new(12, 12, 6).unwrap();
    let mut b = Buffers::new(&dims);
    let mut e = b.explorer(dims, ExplorerConfig::default());
    for p in [
        Point3::new(-0.05, 0.6, 0.3),
        Point3::new(0.6, 1.3, 0.3),
        Point3::new(0.6, 0.6, 1e9),
    ] {
        assert_eq!(e.plan(&p, 0.0), PlanOutcome::Hold(Fault::VehicleOutsideGrid));
    }
    assert_eq!(e.status().errors.vehicle_outside_grid, 3);
}

#[test]
fn frames_with_bad_camera_poses_are_refused_without_touching_the_map() {
    let dims = Dims::new(12, 12, 6).unwrap();
    let mut b = Buffers::new(&dims);
    let mut e = b.explorer(dims, ExplorerConfig::default());
    let depth = vec![500u16; intrinsics().pixel_count()];
    let frame = DepthFrame::new(intrinsics(), &depth).unwrap();
    let before = e.map().counts();
    let nan = Isometry3::from_parts(Translation3::new(f32::NAN, 0.0, 0.0), UnitQuaternion::identity());
    let skewed = Isometry3::from_parts(
        Translation3::new(0.6, 0.6, 0.3),
        UnitQuaternion::new_unchecked(nalgebra::Quaternion::new(1.2, 0.0, 0.0, 0.0)),
    );
    for pose in [nan, skewed] {
        assert_eq!(
            e.integrate(&frame, &pose),
            Err(Fault::Integrate(IntegrateError::BadPose))
        );
    }
    assert_eq!(e.status().errors.frames_rejected, 2);
    assert_eq!(e.map().counts(), before);
}

#[test]
fn camera_pose_jumps_are_refused_until_the_new_place_persists() {
    let dims = Dims::new(40, 12, 6).unwrap();
    let mut b = Buffers::new(&dims);
    let mut e = b.explorer(dims, ExplorerConfig::default());
    let depth = vec![500u16; intrinsics().pixel_count()];
    let frame = DepthFrame::new(intrinsics(), &depth).unwrap();
    let at = |x: f32| forward_camera_pose(&Point3::new(x, 0.6, 0.3), 0.0);
    assert!(e.integrate(&frame, &at(0.6)).is_ok());
    // Within the 2 m limit of the last frame: integrated.
    assert!(e.integrate(&frame, &at(1.6)).is_ok());
    let before = e.map().counts();
    // 2.4 m on: refused, counted, map untouched, three times in a row.
    for _ in 0..FRAMES_TO_ACCEPT_JUMP {
        assert_eq!(
            e.integrate(&frame, &at(4.0)),
            Err(Fault::Integrate(IntegrateError::PoseJump))
        );
    }
    assert_eq!(e.map().counts(), before);
    assert_eq!(e.status().errors.pose_jumps, u32::from(FRAMES_TO_ACCEPT_JUMP));
    assert_eq!(
        e.status().errors.frames_rejected,
        u32::from(FRAMES_TO_ACCEPT_JUMP)
    );
    // A frame back near the reference is taken at once, and resets the run.
    assert!(e.integrate(&frame, &at(1.7)).is_ok());
    assert!(e.integrate(&frame, &at(4.3)).is_err());
    // The new place persists (the estimator relocalised): taken after the run.
    for _ in 1..FRAMES_TO_ACCEPT_JUMP {
        assert!(e.integrate(&frame, &at(4.3)).is_err());
    }
    assert!(e.integrate(&frame, &at(4.3)).is_ok());
    assert!(e.integrate(&frame, &at(4.4)).is_ok());
}

#[test]
fn no_frontier_from_the_start_is_complete() {
    // A 0.6 m cube seen whole from its centre: nothing unknown is left, so nothing to explore.
    let dims = Dims::new(6, 6, 6).unwrap();
    let mut b = Buffers::new(&dims);
    let config = ExplorerConfig {
        vehicle_radius: 0.05,
        ..ExplorerConfig::default()
    };
    let mut e = b.explorer(dims, config);
    let p = Point3::new(0.3, 0.3, 0.3);
    for d in AXES {
        look(&mut e, &looking(p, Vector3::from(d)), 0);
    }
    assert_eq!(e.map().counts().unknown, 0);
    assert_eq!(e.plan(&p, 0.0), PlanOutcome::Complete);
    assert_eq!(e.status().termination, Termination::Complete);
    assert_eq!(e.status().unreachable_frontier, 0);
}

#[test]
fn a_vehicle_walled_in_by_unseen_voxels_around_its_body_is_not_complete() {
    // A vehicle on voxel corners that has only looked level (four headings from 120°, as from
    // s2's original start): the voxels just above and below its body are outside the camera's
    // view and beyond the body marking, so every neighbour of its voxel is within the radius of
    // unknown space and the safe component has no frontier. That is not a finished
    // exploration (without the rule this plan returned Complete): the explorer takes twice the
    // radius around the body as clear.
    let dims = Dims::new(30, 30, 20).unwrap();
    let mut b = Buffers::new(&dims);
    let mut e = b.explorer(dims, ExplorerConfig::default());
    let p = Point3::new(1.5, 1.5, 1.0);
    // The thesis's camera: 75° field of view, level.
    let intr = Intrinsics::from_hfov(100, 100, 75f32.to_radians()).unwrap();
    let depth = vec![5000u16; intr.pixel_count()];
    let frame = DepthFrame::new(intr, &depth).unwrap();
    for k in 0..4 {
        let yaw = 120f32.to_radians() + k as f32 * core::f32::consts::FRAC_PI_2;
        e.integrate(&frame, &forward_camera_pose(&p, yaw)).unwrap();
    }
    let outcome = e.plan(&p, 0.0);
    assert!(matches!(outcome, PlanOutcome::Goal(_)), "{outcome:?}");
    assert_eq!(e.status().errors.clearances, 1);
    assert!(e.status().domain.frontier > 0);
}

#[test]
fn every_frontier_unreachable_is_complete() {
    // A wall across a 2.0 × 0.4 × 0.4 m tube at x = 1.0 m. The vehicle's side is seen whole;
    // beyond the wall a pocket next to unknown space was seen from the far end. Its frontier
    // is in another component, unreachable: the vehicle's exploration is complete.
    let dims = Dims::new(20, 4, 4).unwrap();
    let mut b = Buffers::new(&dims);
    let config = ExplorerConfig {
        vehicle_radius: 0.05,
        ..ExplorerConfig::default()
    };
    let mut e = b.explorer(dims, config);
    let p = Point3::new(0.5, 0.2, 0.2);
    look(&mut e, &looking(p, Vector3::x()), 500);
    for d in &AXES[1..] {
        look(&mut e, &looking(p, Vector3::from(*d)), 0);
    }
    look(&mut e, &looking(Point3::new(1.95, 0.2, 0.2), Vector3::x()), 0);
    let outcome = e.plan(&p, 0.0);
    assert_eq!(outcome, PlanOutcome::Complete, "{:?}", e.status().domain);
    assert!(
        e.status().domain.excluded > 0,
        "the far pocket is excluded: {:?}",
        e.status().domain
    );
    // Seen but left: the pocket's frontier voxels are reported, not hidden in "complete".
    let unreachable = e.status().unreachable_frontier;
    assert!(unreachable > 0, "{:?}", e.status());
    assert_eq!(unreachable, e.map().frontier_voxels());
    let mut frontier = (0..dims.len())
        .map(|i| dims.voxel(i))
        .filter(|&v| e.map().is_frontier(v));
    assert!(frontier.all(|v| v.x >= 10), "all beyond the wall");
}

#[test]
fn vehicle_in_an_occupied_voxel_escapes_to_free_space() {
    // A wall seen 0.5 m ahead; then the vehicle is reported inside it (pose noise).
    let dims = Dims::new(20, 12, 6).unwrap();
    let mut b = Buffers::new(&dims);
    let mut e = b.explorer(dims, ExplorerConfig::default());
    let camera = Point3::new(0.45, 0.6, 0.3);
    look(&mut e, &looking(camera, Vector3::x()), 500);
    let inside = Point3::new(0.95, 0.6, 0.3);
    let g = *e.map().geometry();
    assert_eq!(
        e.map().occupancy(g.dims().linear(g.voxel_at(&inside).unwrap())),
        crate::mapping::map::Occupancy::Occupied
    );
    match e.plan(&inside, 0.0) {
        PlanOutcome::Goal(goal) => {
            assert!(goal.escape);
            let v = g.voxel_at(&goal.position).unwrap();
            assert!(
                e.map().is_free(g.dims().linear(v)),
                "escape goal not free: {goal:?}"
            );
        }
        other => panic!("expected an escape goal, got {other:?}"),
    }
    assert_eq!(e.status().errors.escapes, 1);
}

#[test]
fn vehicle_in_occupied_space_with_no_free_space_holds() {
    // Seen from outside the grid, a wall fills the first layer: the grid holds no free voxel.
    // The vehicle reported inside the wall has nowhere safe to go: hold, counted.
    let dims = Dims::new(8, 8, 4).unwrap();
    let mut b = Buffers::new(&dims);
    let config = ExplorerConfig {
        vehicle_radius: 0.0,
        ..ExplorerConfig::default()
    };
    let mut e = b.explorer(dims, config);
    look(&mut e, &looking(Point3::new(-0.5, 0.4, 0.2), Vector3::x()), 550);
    let c = e.map().counts();
    assert!(c.free == 0 && c.occupied > 0, "{c:?}");
    let outcome = e.plan(&Point3::new(0.05, 0.45, 0.25), 0.0);
    assert_eq!(outcome, PlanOutcome::Hold(Fault::VehicleNotFree));
    assert_eq!(e.status().errors.vehicle_not_free, 1);
}

#[test]
fn solver_cycle_cap_is_counted_and_the_goal_is_still_safe() {
    let dims = Dims::new(30, 12, 6).unwrap();
    let mut b = Buffers::new(&dims);
    let mut config = ExplorerConfig::default();
    config.solve.max_iterations = 1;
    config.solve.tolerance = 1e-12;
    let mut e = b.explorer(dims, config);
    let p = Point3::new(0.3, 0.6, 0.3);
    look(&mut e, &looking(p, Vector3::x()), 0);
    let outcome = e.plan(&p, 0.0);
    assert_eq!(e.status().errors.solver_not_converged, 1);
    assert!(!e.status().solve.converged);
    match outcome {
        PlanOutcome::Goal(goal) => {
            let g = *e.map().geometry();
            let v = g.voxel_at(&goal.position).unwrap();
            assert!(e.map().is_free(g.dims().linear(v)), "goal not free: {goal:?}");
        }
        PlanOutcome::Hold(_) => {}
        PlanOutcome::Complete => panic!("unexplored space left, yet complete"),
    }
}

#[test]
fn thesis_jacobi_plans_the_seed_field_and_needs_its_scratch() {
    let dims = Dims::new(30, 12, 6).unwrap();
    let mut b = Buffers::new(&dims);
    let config = ExplorerConfig {
        field: PlanningField::Harmonic,
        solver: SolverKind::ThesisJacobi,
        ..ExplorerConfig::default()
    };
    assert!(matches!(
        b.try_explorer(dims, config),
        Err(ConfigError::StorageTooSmall)
    ));
    b.jacobi = vec![0.0; dims.len()];
    let screened = ExplorerConfig {
        field: PlanningField::default(),
        ..config
    };
    assert!(matches!(
        b.try_explorer(dims, screened),
        Err(ConfigError::Solver(SolveError::BadScreening))
    ));
    let mut e = b.explorer(dims, config);
    let p = Point3::new(0.3, 0.6, 0.3);
    look(&mut e, &looking(p, Vector3::x()), 0);
    let outcome = e.plan(&p, 0.0);
    assert!(matches!(outcome, PlanOutcome::Goal(_)), "{outcome:?}");
    let s = e.status().solve;
    // The thesis's rule stops it with the field short of the tolerance: counted, not hidden.
    assert!(!s.converged && s.stop == Stop::Rule && s.iterations > 2, "{s:?}");
    assert_eq!(e.status().errors.solver_not_converged, 1);
}

/// A 4.0 × 2.4 × 1.2 m corridor seen free up to x = 2.5 m, unknown beyond; the vehicle at
/// x = 0.6 m plans once with `view_range_m`. Returns the goal, the frontier voxel's centre, the
/// vehicle, whether the goal was chosen from afar and whether every voxel between the goal and
/// the frontier is free.
fn plan_in_a_half_seen_corridor(view_range_m: f32) -> (Goal, Point3<f32>, Point3<f32>, bool, bool) {
    let dims = Dims::new(40, 24, 12).unwrap();
    let mut b = Buffers::new(&dims);
    let config = ExplorerConfig {
        view_range_m,
        ..ExplorerConfig::default()
    };
    let mut e = b.seen_explorer(dims, config, |v| v.x < 25);
    let p = Point3::new(0.6, 1.2, 0.6);
    let PlanOutcome::Goal(goal) = e.plan(&p, 0.0) else {
        panic!("no goal: {:?}", e.status());
    };
    let g = *e.map().geometry();
    let frontier = g.center(goal.frontier);
    let mut clear = true;
    integrate::traverse(&g, &goal.position, &frontier, |v| {
        clear &= e.map().is_free(g.dims().linear(v));
        clear
    });
    (goal, frontier, p, e.goal_from_afar, clear)
}

#[test]
fn a_frontier_in_plain_sight_is_looked_at_from_afar() {
    // From afar: the goal is the first point of the streamline that sees the frontier through
    // free voxels within the view range (1.5 m), and it faces the frontier.
    let (goal, frontier, vehicle, afar, clear) = plan_in_a_half_seen_corridor(1.5);
    assert!(afar && clear, "{goal:?}");
    let to_frontier = frontier - goal.position;
    let d = to_frontier.norm();
    assert!((1.3..=1.5).contains(&d), "{goal:?} is {d} m from {frontier}");
    let yaw_error = heading(&to_frontier, 0.0) - goal.yaw;
    assert!(libm::fabsf(libm::remainderf(yaw_error, core::f32::consts::TAU)) < 0.05);
    // The near rule (view range 0) flies on to just outside the camera's minimum range.
    let (near, near_frontier, _, near_afar, _) = plan_in_a_half_seen_corridor(0.0);
    assert!(!near_afar);
    let near_d = (near.position - near_frontier).norm();
    assert!(
        (0.4..0.6).contains(&near_d),
        "{near:?} is {near_d} m from {near_frontier}"
    );
    assert!((goal.position - vehicle).norm() + 0.5 < (near.position - vehicle).norm());
}

#[test]
fn frames_taken_while_turning_fast_or_on_a_stale_pose_are_refused_and_counted() {
    let dims = Dims::new(12, 12, 6).unwrap();
    let mut b = Buffers::new(&dims);
    let config = ExplorerConfig::default();
    let mut e = b.explorer(dims, config);
    let depth = vec![500u16; intrinsics().pixel_count()];
    let frame = DepthFrame::new(intrinsics(), &depth).unwrap();
    let pose = forward_camera_pose(&Point3::new(0.6, 0.6, 0.3), 0.0);
    let limit = config.max_frame_yaw_rate;
    let lag = config.max_frame_pose_lag_ms;
    let timing = |yaw_rate: Option<f32>, pose_lag_ms: u32| FrameTiming {
        yaw_rate,
        pose_lag_ms,
    };
    let before = e.map().counts();
    for (t, expected) in [
        // Turning faster than the limit, either way; an unmeasurable rate.
        (timing(Some(limit * 1.1), 0), IntegrateError::TurningTooFast),
        (timing(Some(-limit * 3.0), 0), IntegrateError::TurningTooFast),
        (timing(Some(f32::NAN), 0), IntegrateError::TurningTooFast),
        // The newest pose older than the frame by more than the bound.
        (timing(Some(0.0), lag + 1), IntegrateError::StalePose),
        (timing(None, 10 * lag), IntegrateError::StalePose),
    ] {
        assert_eq!(
            e.integrate_timed(&frame, &pose, &t),
            Err(Fault::Integrate(expected)),
            "{t:?}"
        );
    }
    assert_eq!(e.map().counts(), before, "refused frames leave the map alone");
    let errors = e.status().errors;
    assert_eq!(
        (
            errors.turning_frames,
            errors.stale_pose_frames,
            errors.frames_rejected
        ),
        (3, 2, 5)
    );
    // At the limits, or with no rate measured yet: integrated.
    assert!(e
        .integrate_timed(&frame, &pose, &timing(Some(limit), lag))
        .is_ok());
    assert!(e.integrate_timed(&frame, &pose, &timing(None, 0)).is_ok());
    assert_eq!(e.status().frames, 2);
    // Limits switched off: anything goes.
    let off = ExplorerConfig {
        max_frame_yaw_rate: 0.0,
        max_frame_pose_lag_ms: 0,
        ..config
    };
    let mut errors = ErrorCounters::default();
    assert_eq!(
        check_frame_timing(&off, &timing(Some(100.0), 100_000), &mut errors),
        Ok(())
    );
    assert_eq!(errors, ErrorCounters::default());
}

/// Plans once from behind a wall whose far end the vehicle must round to reach the frontier
/// (unknown space beyond x = 3 m, south of y = 1 m);
/// returns the goal, the waypoints, the labels and the vehicle's position.
fn plan_around_a_wall(taut_path: bool) -> (Goal, Vec<Point3<f32>>, Vec<Label>, Point3<f32>) {
    let dims = Dims::new(40, 30, 12).unwrap();
    let mut b = Buffers::new(&dims);
    // Flying up to the frontier (view range 0): the streamline's bend towards the frontier's
    // normal is then part of the way.
    let config = ExplorerConfig {
        taut_path,
        view_range_m: 0.0,
        ..ExplorerConfig::default()
    };
    let mut e = b.explorer(dims, config);
    e.intrinsics = Some(Intrinsics::from_hfov(100, 100, 75f32.to_radians()).unwrap());
    e.map.begin_frame();
    for i in 0..dims.len() {
        let v = dims.voxel(i);
        if (10..16).contains(&v.x) && v.y < 20 {
            e.map.apply_hit(i);
        } else if v.x < 30 || v.y >= 10 {
            e.map.apply_miss(i);
        }
    }
    let p = Point3::new(0.55, 0.55, 0.65);
    let PlanOutcome::Goal(goal) = e.plan(&p, 0.0) else {
        panic!("no goal: {:?}", e.status());
    };
    (goal, e.waypoints().to_vec(), e.labels().to_vec(), p)
}

#[test]
fn the_way_to_a_goal_is_pulled_taut_through_the_safe_space_and_keeps_the_goal() {
    let (raw_goal, raw, _, _) = plan_around_a_wall(false);
    let (goal, taut, labels, vehicle) = plan_around_a_wall(true);
    // The same view of the same frontier: the streamline chose it, the pull only straightens
    // the way there.
    assert_eq!(goal, raw_goal);
    let length = |w: &[Point3<f32>]| w.windows(2).map(|s| (s[1] - s[0]).norm()).sum::<f32>();
    assert!(
        length(&taut) < length(&raw) - 0.05,
        "taut {} m, streamline {} m",
        length(&taut),
        length(&raw)
    );
    assert!((taut[0] - vehicle).norm() < 1e-4);
    assert!((taut[taut.len() - 1] - goal.position).norm() < 1e-4);
    // The vehicle rounds the wall's end (y ≥ 2.0 m), and no segment leaves the domain (the
    // free space eroded by the vehicle's radius).
    assert!(taut.iter().any(|w| w.y > 2.0), "{taut:?}");
    let g = MapGeometry::new(Dims::new(40, 30, 12).unwrap(), Point3::origin(), 0.1).unwrap();
    for s in taut.windows(2) {
        integrate::traverse(&g, &s[0], &s[1], |v| {
            assert!(labels[g.dims().linear(v)].in_domain(), "{s:?} crosses {v:?}");
            true
        });
    }
}

/// A 4 × 4 × 1.2 m room seen free except its north strip (y ≥ 2.8 m), which is unexplored;
/// the vehicle stands at its last goal in the south, facing east. Plans once per entry of
/// `yaws` (the vehicle's yaw at each plan, as if it had turned as told) and returns the
/// outcomes. `teach`: each turn's view observes one voxel of the strip (without it, no turn
/// teaches anything).
fn arrive_beside_an_unexplored_strip(
    arrival_looks: u8,
    yaws: &[f32],
    teach: bool,
) -> (Vec<PlanOutcome>, u32, Vec<Point3<f32>>) {
    let dims = Dims::new(40, 40, 12).unwrap();
    let mut b = Buffers::new(&dims);
    let config = ExplorerConfig {
        arrival_looks,
        ..ExplorerConfig::default()
    };
    let mut e = b.seen_explorer(dims, config, |v| v.y < 28);
    let p = Point3::new(2.0, 1.0, 0.6);
    let arrived = Goal {
        position: p,
        yaw: 0.0,
        frontier: VoxelIndex::new(20, 27, 6),
        escape: false,
    };
    e.last_goal = Some(arrived);
    let mut outcomes = Vec::new();
    let mut waypoints = Vec::new();
    for (k, &yaw) in yaws.iter().enumerate() {
        outcomes.push(e.plan(&p, yaw));
        waypoints = e.waypoints().to_vec();
        if teach {
            e.map.begin_frame();
            e.map
                .apply_miss(dims.linear(VoxelIndex::new(30 + k as u16, 39, 6)));
        }
    }
    (outcomes, e.status().arrival_looks, waypoints)
}

#[test]
fn on_arrival_the_vehicle_turns_to_the_unexplored_side_before_planning_on() {
    let p = Point3::new(2.0, 1.0, 0.6);
    let (outcomes, turns, waypoints) = arrive_beside_an_unexplored_strip(1, &[0.0], true);
    let PlanOutcome::Goal(turn) = outcomes[0] else {
        panic!("{outcomes:?}");
    };
    // It stays where it is and faces north, the heading whose view holds the most unexplored
    // voxels; the goal it arrived at is not replaced.
    assert_eq!(turns, 1);
    assert_eq!(turn.position, p);
    assert_eq!(waypoints, vec![p]);
    assert!((turn.yaw - core::f32::consts::FRAC_PI_2).abs() < 1e-6, "{turn:?}");
    assert_eq!(turn.frontier, VoxelIndex::new(20, 27, 6));
    // With its one look made, the next plan is a plan: a goal towards the strip.
    let (outcomes, turns, _) =
        arrive_beside_an_unexplored_strip(1, &[0.0, core::f32::consts::FRAC_PI_2], true);
    let PlanOutcome::Goal(next) = outcomes[1] else {
        panic!("{outcomes:?}");
    };
    assert_eq!(turns, 1);
    assert_ne!(next.frontier, VoxelIndex::new(20, 27, 6), "{next:?}");
    // Without the look-around, the first plan is that plan.
    let (outcomes, turns, _) = arrive_beside_an_unexplored_strip(0, &[0.0], true);
    assert_eq!(turns, 0);
    assert!(
        matches!(outcomes[0], PlanOutcome::Goal(g) if g.position != p),
        "{outcomes:?}"
    );
}

#[test]
fn the_look_around_never_looks_twice_along_a_heading_and_stops_when_nothing_is_left_to_see() {
    // Up to seven turns allowed: the headings whose view reaches the strip (north-east, north,
    // north-west), each once, the most revealing first; the headings facing away from it see
    // only the room's seen floor and the grid's edge, so the fourth plan is a plan.
    let p = Point3::new(2.0, 1.0, 0.6);
    let turns = |teach: bool| {
        let (outcomes, _, _) = arrive_beside_an_unexplored_strip(7, &[0.0; 4], teach);
        let turned: Vec<u8> = outcomes
            .iter()
            .map_while(|o| match o {
                PlanOutcome::Goal(g) if g.position == p && g.frontier == VoxelIndex::new(20, 27, 6) => {
                    Some(octant(g.yaw))
                }
                _ => None,
            })
            .collect();
        let next = outcomes[turned.len()];
        assert!(
            matches!(next, PlanOutcome::Goal(g) if g.frontier != VoxelIndex::new(20, 27, 6)),
            "{outcomes:?}"
        );
        turned
    };
    assert_eq!(turns(true), vec![2, 1, 3]);
    // A turn whose view taught nothing ends the look-around.
    assert_eq!(turns(false), vec![2]);
}

#[test]
fn octants_round_trip_and_a_bad_yaw_is_octant_zero() {
    for k in 0..8u8 {
        assert_eq!(octant(octant_yaw(k)), k);
        assert_eq!(octant(octant_yaw(k) + 0.3), k);
        assert_eq!(octant(octant_yaw(k) + core::f32::consts::TAU), k);
        let y = octant_yaw(k);
        assert!(y > -core::f32::consts::PI && y <= core::f32::consts::PI);
    }
    assert_eq!(octant(f32::NAN), 0);
    assert_eq!(octant(f32::INFINITY), octant(f32::INFINITY));
}

/// A room (x < 12) and a hall beyond a door in the wall at x = 12, both seen free, unknown
/// space from x = 20 on; the walls seen occupied in four frames, and one voxel in the middle of
/// the door seen occupied once, as a noisy stereo return leaves it. With the 0.2 m radius
/// that voxel alone closes the door. Returns the explorer after one plan from the room.
fn plan_behind_a_doubtful_door(
    b: &mut Buffers,
    doubtful_log_odds: f32,
) -> (Explorer<'_>, PlanOutcome, usize) {
    let dims = Dims::new(24, 12, 12).unwrap();
    let config = ExplorerConfig {
        doubtful_log_odds,
        ..ExplorerConfig::default()
    };
    let mut e = b.seen_explorer(dims, config, |v| v.x < 20);
    let door = |v: VoxelIndex| (3..9).contains(&v.y) && (3..9).contains(&v.z);
    let d = dims.linear(VoxelIndex::new(12, 6, 6));
    for frame in 0..4 {
        e.map.begin_frame();
        for i in 0..dims.len() {
            let v = dims.voxel(i);
            if (v.x == 12 && !door(v)) || (i == d && frame == 0) {
                e.map.apply_hit(i);
            }
        }
    }
    let outcome = e.plan(&Point3::new(0.45, 0.65, 0.65), 0.0);
    (e, outcome, d)
}

#[test]
fn a_door_closed_by_one_doubtful_voxel_is_looked_at_again_before_the_end() {
    let mut b = Buffers::new(&Dims::new(24, 12, 12).unwrap());
    let (e, outcome, _) = plan_behind_a_doubtful_door(&mut b, 0.0);
    assert_eq!(
        outcome,
        PlanOutcome::Complete,
        "off: the closed door ends the exploration"
    );
    drop(e);

    let (mut e, outcome, d) = plan_behind_a_doubtful_door(&mut b, 1.0);
    let PlanOutcome::Goal(goal) = outcome else {
        panic!(
            "the door's doubtful voxel ended the exploration: {:?}",
            e.status()
        );
    };
    assert_eq!(e.status().errors.reopenings, 1);
    assert!(e.map().is_unexplored(d), "the doubtful voxel is forgotten");
    assert!(
        goal.position.x < 1.2,
        "the vehicle looks at it from the room: {goal:?}"
    );

    // Seen free from there: the door is open and the hall's frontier is the next goal.
    e.map.begin_frame();
    e.map.apply_miss(d);
    let PlanOutcome::Goal(next) = e.plan(&goal.position, goal.yaw) else {
        panic!("{:?}", e.status());
    };
    assert!(next.frontier.x > 12, "{next:?}");
    assert_eq!(e.status().errors.reopenings, 1);
}

#[test]
fn a_doubtful_voxel_seen_occupied_again_is_believed() {
    let mut b = Buffers::new(&Dims::new(24, 12, 12).unwrap());
    let (mut e, outcome, d) = plan_behind_a_doubtful_door(&mut b, 1.0);
    let PlanOutcome::Goal(goal) = outcome else {
        panic!("{:?}", e.status());
    };
    e.map.begin_frame();
    e.map.apply_hit(d);
    assert_eq!(e.plan(&goal.position, goal.yaw), PlanOutcome::Complete);
    assert_eq!(e.status().errors.reopenings, 1, "each voxel is doubted once");
}

/// A 3.2 × 1.6 × 1.6 m box seen free, with a wall at `wall_x` (seen occupied in four frames)
/// whose 5 × 5-voxel door a 0.3 m planning radius does not pass and the 0.2 m one does, and
/// unknown space from `unknown_from` on. Runs `f` on an explorer with the planning radius 0.3 m
/// and the narrower radius `narrow`.
fn beside_a_narrow_door<R>(
    wall_x: u16,
    unknown_from: u16,
    narrow: f32,
    f: impl FnOnce(&mut Explorer<'_>) -> R,
) -> R {
    let dims = Dims::new(32, 16, 16).unwrap();
    let mut b = Buffers::new(&dims);
    let config = ExplorerConfig {
        vehicle_radius: 0.3,
        narrow_radius: narrow,
        ..ExplorerConfig::default()
    };
    let mut e = b.seen_explorer(dims, config, |v| v.x < unknown_from && v.x != wall_x);
    let door = |v: VoxelIndex| (5..10).contains(&v.y) && (5..10).contains(&v.z);
    for _ in 0..4 {
        e.map.begin_frame();
        for i in 0..dims.len() {
            let v = dims.voxel(i);
            if v.x == wall_x && !door(v) {
                e.map.apply_hit(i);
            } else if v.x == wall_x {
                e.map.apply_miss(i);
            }
        }
    }
    f(&mut e)
}

/// The centre of voxel `(x, 8, 8)`.
fn at_x(x: u16) -> Point3<f32> {
    let centre = |k: u16| (f32::from(k) + 0.5) * 0.1;
    Point3::new(centre(x), centre(8), centre(8))
}

/// [`beside_a_narrow_door`], planning once from voxel `(vehicle_x, 8, 8)`.
fn plan_beside_a_narrow_door(
    wall_x: u16,
    unknown_from: u16,
    vehicle_x: u16,
    narrow: f32,
) -> (PlanOutcome, Status) {
    beside_a_narrow_door(wall_x, unknown_from, narrow, |e| {
        let outcome = e.plan(&at_x(vehicle_x), 0.0);
        (outcome, *e.status())
    })
}

#[test]
fn home_in_a_pocket_is_reached_on_the_narrower_radius() {
    // Home in the nook behind the narrow door (a cramped start); the vehicle beyond it.
    let home = |narrow: f32| {
        beside_a_narrow_door(8, 32, narrow, |e| {
            let outcome = e.plan_home(&at_x(20), 0.0, &at_x(4), &mut NoClock);
            (outcome, *e.status())
        })
    };
    let (outcome, status) = home(0.0);
    assert_eq!(outcome, PlanOutcome::Hold(Fault::HomeUnreachable), "{status:?}");
    let (outcome, status) = home(0.2);
    let PlanOutcome::Goal(goal) = outcome else {
        panic!("home was not reached: {outcome:?} {status:?}");
    };
    assert_eq!(status.errors.pocket_plans, 1);
    assert!(goal.position.x < 0.8, "into the nook: {goal:?}");
}

#[test]
fn a_vehicle_in_a_pocket_leaves_it_on_the_narrower_radius() {
    // A nook (x < 8) behind the narrow door, the rest of the box beyond it with a frontier.
    let (outcome, status) = plan_beside_a_narrow_door(8, 28, 4, 0.0);
    assert_eq!(
        outcome,
        PlanOutcome::Complete,
        "without a narrower radius the nook ends it"
    );
    assert_eq!(status.errors.pocket_plans, 0);

    let (outcome, status) = plan_beside_a_narrow_door(8, 28, 4, 0.2);
    let PlanOutcome::Goal(goal) = outcome else {
        panic!("the nook ended the exploration: {status:?}");
    };
    assert_eq!(status.errors.pocket_plans, 1);
    assert!(goal.position.x > 0.9, "through the door: {goal:?}");
    assert!(status.domain.frontier > 0, "{status:?}");
}

#[test]
fn a_remnant_behind_a_narrow_door_is_no_pocket() {
    // The vehicle in the explored box (x < 24); behind the door a small hall with the only
    // frontier. Both radii give the vehicle nearly the same space: the exploration ends as it
    // did without the narrower radius.
    let (outcome, status) = plan_beside_a_narrow_door(24, 28, 10, 0.2);
    assert_eq!(outcome, PlanOutcome::Complete, "{status:?}");
    assert_eq!(status.errors.pocket_plans, 0);
    assert!(
        status.domain.interior > 0 && status.domain.frontier == 0,
        "{status:?}"
    );
}

/// Plans from one end of a 6 × 1 × 1 m hall seen free except for 2 × 2 × 2-voxel pockets of
/// unknown space with their low corners at `pockets` (voxel indices), under `config`.
fn plan_to_pockets(config: ExplorerConfig, pockets: &[[u16; 3]]) -> (PlanOutcome, Status) {
    let dims = Dims::new(60, 10, 10).unwrap();
    let mut b = Buffers::new(&dims);
    let in_pocket = |v: VoxelIndex| {
        pockets.iter().any(|&[x, y, z]| {
            (x..x + 2).contains(&v.x) && (y..y + 2).contains(&v.y) && (z..z + 2).contains(&v.z)
        })
    };
    let mut e = b.seen_explorer(dims, config, |v| !in_pocket(v));
    let outcome = e.plan(&Point3::new(0.25, 0.5, 0.5), 0.0);
    (outcome, *e.status())
}

fn remnant_config(area_m2: f32) -> ExplorerConfig {
    ExplorerConfig {
        vehicle_radius: 0.05,
        remnant_frontier_m2: area_m2,
        ..ExplorerConfig::default()
    }
}

#[test]
fn a_far_remnant_is_sealed_and_a_near_one_is_flown_to() {
    // All that is left is a pocket 5 m away: not worth the flight, it is sealed and the
    // exploration ends.
    let far = [[50, 4, 4]];
    let (outcome, status) = plan_to_pockets(remnant_config(0.5), &far);
    assert_eq!(outcome, PlanOutcome::Complete, "{status:?}");
    assert_eq!(status.errors.remnants_sealed, 1);
    assert_eq!(
        status.errors.seals, 0,
        "a remnant is not counted as a fruitless visit"
    );
    // The same pocket 1 m away is looked at.
    let (outcome, status) = plan_to_pockets(remnant_config(0.5), &[[10, 4, 4]]);
    assert!(matches!(outcome, PlanOutcome::Goal(_)), "{outcome:?} {status:?}");
    assert_eq!(status.errors.remnants_sealed, 0);
    // With noisy depth (the stereo sensor model) a crumb may be a passage the noise narrowed:
    // it is flown to.
    let mut noisy = remnant_config(0.5);
    noisy.integration.depth_noise_per_m = 0.01;
    let (outcome, status) = plan_to_pockets(noisy, &far);
    assert!(matches!(outcome, PlanOutcome::Goal(_)), "{outcome:?}");
    assert_eq!(status.errors.remnants_sealed, 0);
    // With the rule off the far pocket is flown to as well.
    let (outcome, status) = plan_to_pockets(remnant_config(0.0), &far);
    assert!(matches!(outcome, PlanOutcome::Goal(_)), "{outcome:?}");
    assert_eq!(status.errors.remnants_sealed, 0);
    let length = status.streamline.map_or(0.0, |s| s.length);
    assert!(length > 4.0, "{length} m");
}

#[test]
fn a_far_target_is_flown_to_while_much_frontier_is_left() {
    // Eight far pockets hold more frontier than a remnant area of one pocket's worth: the
    // nearest is a target like any other.
    let pockets: Vec<[u16; 3]> = (0..8).map(|k| [36 + 6 * (k % 4), 1 + 6 * (k / 4), 4]).collect();
    let (_, one) = plan_to_pockets(remnant_config(0.0), &pockets[..1]);
    let one_pocket_m2 = one.domain.frontier as f32 * 0.01;
    let (outcome, status) = plan_to_pockets(remnant_config(one_pocket_m2), &pockets);
    assert!(matches!(outcome, PlanOutcome::Goal(_)), "{outcome:?}");
    assert_eq!(status.errors.remnants_sealed, 0);
    // Taken for remnants all, seven are sealed and the last pass flies to the eighth: a plan
    // never ends on seals alone.
    let (outcome, status) = plan_to_pockets(remnant_config(100.0), &pockets);
    assert!(matches!(outcome, PlanOutcome::Goal(_)), "{outcome:?} {status:?}");
    assert_eq!(status.errors.remnants_sealed, PLAN_PASSES as u32 - 1);
}

#[test]
fn a_far_remnant_is_flown_to_while_safe_space_is_out_of_reach() {
    // The hall of `plan_to_pockets` with a wall across it at x = 5.7 m and a seen, free room
    // beyond: safe space the vehicle cannot reach (a passage closed, by noise perhaps). The far
    // pocket might be the way there, so it is looked at, not sealed.
    let dims = Dims::new(60, 10, 10).unwrap();
    let mut b = Buffers::new(&dims);
    let pocket = |v: VoxelIndex| (50..52).contains(&v.x) && (4..6).contains(&v.y) && (4..6).contains(&v.z);
    let mut e = b.seen_explorer(dims, remnant_config(0.5), |v| !pocket(v) && v.x != 57);
    for i in 0..dims.len() {
        if dims.voxel(i).x == 57 {
            for _ in 0..3 {
                e.map.begin_frame();
                e.map.apply_hit(i);
            }
        }
    }
    let outcome = e.plan(&Point3::new(0.25, 0.5, 0.5), 0.0);
    let status = e.status();
    assert!(status.domain.excluded > 50, "{:?}", status.domain);
    assert!(matches!(outcome, PlanOutcome::Goal(_)), "{outcome:?} {status:?}");
    assert_eq!(status.errors.remnants_sealed, 0);
}

#[test]
fn storage_bytes_count_every_buffer() {
    use crate::planning::solve::Bf16;
    let label = core::mem::size_of::<Label>();
    let (mut lo, mut touched, mut labels, mut phi) = ([0i8; 10], [0u32; 1], [Label::default(); 3], [0f32; 2]);
    let (mut queue, mut values, mut coarse_labels) =
        ([0u32; 5], [Bf16::default(); 7], [Label::default(); 11]);
    let (mut faces, mut krylov, mut masks, mut jacobi) = ([[0u8; 4]; 13], [0f32; 17], [0u8; 19], [0f32; 23]);
    let (mut local_labels, mut local_psi) = ([Label::default(); 29], [0f32; 31]);
    let storage = ExplorerStorage {
        log_odds: &mut lo,
        touched: &mut touched,
        labels: &mut labels,
        phi: &mut phi,
        queue: &mut queue,
        coarse_values: values.as_mut_slice().into(),
        coarse_labels: &mut coarse_labels,
        coarse_faces: &mut faces,
        krylov: &mut krylov,
        masks: &mut masks,
        surface: &mut [],
        jacobi: &mut jacobi,
        local_labels: &mut local_labels,
        local_psi: &mut local_psi,
        flat: &mut [],
        fine_log_odds: &mut [],
        fine_touched: &mut [],
    };
    let want = 10 + 4 + 3 * label + 8 + 20 + 14 + 11 * label + 52 + 68 + 19 + 92 + 29 * label + 4 * 31;
    assert_eq!(storage.bytes(), want);
}

impl Explorer<'_> {
    /// Solves the planning field over the domain built last.
    fn solve_field(&mut self, vehicle: VoxelIndex) -> Result<crate::planning::solve::SolveStats, SolveError> {
        let (targets, mut cx, _) = self.parts(vehicle);
        targets.solve_field(&mut cx)
    }
}

/// A re-solve after a scan, with a box lent, works in a box around the scan and leaves the
/// field a whole-grid re-solve leaves, for less work; without the box it sweeps the grid.
#[test]
fn a_re_solve_after_a_scan_works_in_a_box_around_it() {
    let dims = Dims::new(160, 24, 12).unwrap();
    let vehicle = VoxelIndex::new(120, 12, 6);
    let mut fields = Vec::new();
    for local in [false, true] {
        let mut b = Buffers::new(&dims);
        if local {
            b.local_labels = vec![Label::Outside; dims.len() / 2];
            b.local_psi = vec![0.0; dims.len() / 2];
        }
        let mut e = b.seen_explorer(dims, ExplorerConfig::default(), |v| v.x < 130);
        e.build_domain(vehicle).unwrap();
        let first = e.solve_field(vehicle).unwrap();
        // The scan: three more planes seen beyond the frontier.
        e.map.begin_frame();
        for i in 0..dims.len() {
            if (130..133).contains(&dims.voxel(i).x) {
                e.map.apply_miss(i);
            }
        }
        e.build_domain(vehicle).unwrap();
        let s = e.solve_field(vehicle).unwrap();
        assert!(first.converged && s.converged, "{first:?} {s:?}");
        assert_eq!(
            (e.status.local_solves, e.status.local_given_up),
            (u32::from(local), 0)
        );
        fields.push((e.psi().to_vec(), s.cell_updates));
    }
    let [(whole, whole_work), (boxed, boxed_work)] = [fields[0].clone(), fields[1].clone()];
    let worst = whole
        .iter()
        .zip(&boxed)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0f32, f32::max);
    assert!(worst <= 1e-4, "{worst}");
    assert!(2 * boxed_work < whole_work, "{boxed_work} against {whole_work}");
}

/// [`SolverKind::Flat`] plans on the field the multigrid solves (to within the solve's
/// accuracy), cold and after a scan; without its storage the explorer is refused.
#[cfg(feature = "flat")]
#[test]
fn the_flat_solver_solves_the_field_multigrid_does() {
    let dims = Dims::new(96, 24, 12).unwrap();
    let vehicle = VoxelIndex::new(60, 12, 6);
    let mut fields = Vec::new();
    for solver in [SolverKind::Multigrid, SolverKind::Flat] {
        let mut b = Buffers::new(&dims);
        if solver == SolverKind::Flat {
            assert!(matches!(
                b.try_explorer(
                    dims,
                    ExplorerConfig {
                        solver,
                        ..ExplorerConfig::default()
                    }
                ),
                Err(ConfigError::Solver(
                    crate::planning::solve::SolveError::ScratchTooSmall
                ))
            ));
            b.flat = vec![0.0; crate::planning::solve::flat::flat_scratch_len(&dims)];
        }
        let config = ExplorerConfig {
            solver,
            ..ExplorerConfig::default()
        };
        let mut e = b.seen_explorer(dims, config, |v| v.x < 70);
        e.build_domain(vehicle).unwrap();
        let first = e.solve_field(vehicle).unwrap();
        e.map.begin_frame();
        for i in 0..dims.len() {
            if (70..73).contains(&dims.voxel(i).x) {
                e.map.apply_miss(i);
            }
        }
        e.build_domain(vehicle).unwrap();
        let s = e.solve_field(vehicle).unwrap();
        assert!(first.converged && s.converged, "{solver:?}: {first:?} {s:?}");
        fields.push(e.psi().to_vec());
    }
    let worst = fields[0]
        .iter()
        .zip(&fields[1])
        .map(|(a, b)| (a - b).abs())
        .fold(0.0f32, f32::max);
    assert!(worst <= 1e-4, "{worst}");
}

/// With `plan_coarsening` 2 frames go into the map at the grid's resolution and the explorer
/// plans on cells twice as large pooled from it: a goal that looks at a frontier cell, its way
/// inside the domain. Without the fine map's storage it is refused.
#[test]
fn a_coarser_planning_grid_plans_from_the_map_it_pools_and_needs_the_map_storage() {
    let dims = Dims::new(64, 12, 12).unwrap();
    let config = ExplorerConfig {
        plan_coarsening: 2,
        ..ExplorerConfig::default()
    };
    let mut b = Buffers::new(&dims);
    assert_eq!(
        b.try_explorer(dims, config).err(),
        Some(ConfigError::StorageTooSmall)
    );
    let mut e = b.coarse_explorer(dims, config);
    assert_eq!(e.observed_map().dims().extent(), [64, 12, 12]);
    assert_eq!(e.map().dims().extent(), [32, 6, 6]);
    // A 6.4 × 1.2 × 1.2 m corridor seen from its west end every way: what the rays missed is
    // unknown.
    let p = Point3::new(0.5, 0.6, 0.6);
    for d in AXES {
        look(&mut e, &looking(p, Vector3::from(d)), 0);
    }
    let fine = e.observed_map().counts();
    assert!(fine.free > 0 && fine.unknown > 0, "{fine:?}");
    let coarse = e.map().counts();
    assert!(
        coarse.free > 0 && coarse.free * 8 <= fine.free,
        "{coarse:?} from {fine:?}"
    );
    let PlanOutcome::Goal(goal) = e.plan(&p, 0.0) else {
        panic!("{:?}", e.status())
    };
    assert!(!goal.escape, "{goal:?}");
    let end = e
        .map()
        .geometry()
        .voxel_at(e.waypoints().last().unwrap())
        .unwrap();
    assert!(e.map().geometry().voxel_at(&goal.position).is_some());
    assert!(
        e.labels().contains(&Label::Frontier) && e.status().domain.frontier > 0,
        "the field has frontier cells: {goal:?} {:?}",
        e.status()
    );
    assert_ne!(
        e.labels()[e.map().dims().linear(end)],
        Label::Outside,
        "the way stays in the domain"
    );
    // The goal looks at a frontier cell of the coarser grid.
    assert_eq!(e.labels()[e.map().dims().linear(goal.frontier)], Label::Frontier);
}

/// The unexplored space a frontier cell borders, as the view rule aims at it: the centre of
/// the unexplored voxels within reach that a straight line from the frontier reaches, not
/// those behind a wall.
#[test]
fn the_unexplored_space_beyond_a_frontier_is_what_a_line_from_it_reaches() {
    let dims = Dims::new(12, 12, 6).unwrap();
    let mut b = Buffers::new(&dims);
    let mut e = b.explorer(dims, ExplorerConfig::default());
    let (open, hidden, wall) = (
        [VoxelIndex::new(7, 5, 2), VoxelIndex::new(5, 7, 2)],
        VoxelIndex::new(5, 2, 2),
        VoxelIndex::new(5, 3, 2),
    );
    e.map.begin_frame();
    for i in 0..dims.len() {
        let v = dims.voxel(i);
        if v == wall {
            e.map.apply_hit(i);
        } else if !open.contains(&v) && v != hidden {
            e.map.apply_miss(i);
        }
    }
    let g = *e.map.geometry();
    let (mut labels, mut status) = (vec![Label::Outside; dims.len()], Status::default());
    let cx = Context {
        map: &e.map,
        labels: &mut labels,
        vehicle: VoxelIndex::new(1, 1, 2),
        stencil: e.inflation.stencil(),
        config: &e.config,
        intrinsics: None,
        status: &mut status,
    };
    let frontier = VoxelIndex::new(5, 5, 2);
    let centre = super::target::unexplored_beyond(&cx, frontier).expect("two open voxels");
    let expected = Point3::from((g.center(open[0]).coords + g.center(open[1]).coords) / 2.0);
    assert!((centre - expected).norm() < 1e-5, "{centre} against {expected}");
    // Nothing unexplored in reach: none.
    assert_eq!(
        super::target::unexplored_beyond(&cx, VoxelIndex::new(10, 10, 2)),
        None
    );
}

/// On a planning grid coarser than the map a frontier cell can lie two cells from the space it
/// borders and off to one side: here the cells of a narrow hall beside a door in its wall, the
/// vehicle in the hall a little short of them. The goal faces the unexplored space through the
/// door (inside the camera's field of view, with the view rule's margin), not along the hall
/// at the frontier cell (the doorway 0.67 rad off that; the margin allows 0.52).
#[test]
fn on_a_coarser_grid_the_goal_faces_the_unexplored_space_the_frontier_borders() {
    let fine = Dims::new(48, 24, 12).unwrap();
    let config = ExplorerConfig {
        plan_coarsening: 2,
        ..ExplorerConfig::default()
    };
    let mut b = Buffers::new(&fine);
    let mut e = b.coarse_explorer(fine, config);
    let intrinsics = Intrinsics::from_hfov(100, 100, 75f32.to_radians()).unwrap();
    e.intrinsics = Some(intrinsics);
    // Planning cells: a hall y 1..=4 between a floor, a ceiling and walls; the wall y = 5 with
    // a door at x 16..=19, unexplored beyond it.
    let dims = e.map.dims();
    let door = |v: VoxelIndex| v.y >= 5 && (16..=19).contains(&v.x);
    e.map.begin_frame();
    for i in 0..dims.len() {
        let v = dims.voxel(i);
        let shell = v.z == 0 || v.z == 5 || v.x == 0 || v.x == 23 || v.y == 0;
        if door(v) || v.y > 5 {
            continue;
        }
        if shell || v.y == 5 {
            e.map.apply_hit(i);
        } else {
            e.map.apply_miss(i);
        }
    }
    let p = Point3::new(3.1, 0.7, 0.5);
    let PlanOutcome::Goal(goal) = e.plan(&p, 0.0) else {
        panic!("{:?}", e.status())
    };
    let g = *e.map.geometry();
    let f = goal.frontier;
    let centre = |vs: &mut dyn Iterator<Item = VoxelIndex>| {
        let (mut sum, mut n) = (Vector3::zeros(), 0.0f32);
        for v in vs {
            sum += g.center(v).coords;
            n += 1.0;
        }
        Point3::from(sum / n)
    };
    let doorway = centre(&mut (16..=19).flat_map(|x| (1..=4).map(move |z| VoxelIndex::new(x, 5, z))));
    let off = libm::remainderf(
        heading(&(doorway - goal.position), 0.0) - goal.yaw,
        core::f32::consts::TAU,
    );
    assert!(
        f.y < 5 && (14..=21).contains(&f.x),
        "a hall cell by the door: {goal:?}"
    );
    let half = intrinsics.half_fov().0 * config.view_margin;
    assert!(
        off.abs() <= half,
        "the doorway is {off} rad off the goal's yaw: {goal:?}"
    );
    // Facing the frontier cell would have left the doorway outside the margin.
    let towards = |q: Point3<f32>| heading(&(q - goal.position), 0.0);
    let cell_off = libm::remainderf(towards(g.center(f)) - towards(doorway), core::f32::consts::TAU);
    assert!(cell_off.abs() > half, "{cell_off}");
}

/// `solve.max_iterations` bounds a plan's solves together (the screened field solves again at
/// a lower κ while the frontier is far: here 10 m down a corridor): a board bounds a plan's
/// time with it. The plan stops short, says so, and still plans on the field as it stands.
#[test]
fn a_plans_solves_together_keep_to_its_iteration_budget() {
    let dims = Dims::new(120, 24, 12).unwrap();
    let p = Point3::new(0.3, 1.2, 0.6);
    let plan = |budget: u32| {
        let mut b = Buffers::new(&dims);
        let mut config = ExplorerConfig::default();
        config.solve.max_iterations = budget;
        let mut e = b.seen_explorer(dims, config, |v| v.x < 110);
        let outcome = e.plan(&p, 0.0);
        (outcome, *e.status())
    };
    // Unbounded, the plan solves more than once and takes more than the budget below.
    let (_, free) = plan(20_000);
    assert!(
        free.solves > 1 && free.solve.iterations > 8,
        "{:?} in {} solves",
        free.solve,
        free.solves
    );
    let (outcome, s) = plan(8);
    assert!(
        s.solve.iterations <= 8 && !s.solve.converged && s.solve.stop == Stop::Cap,
        "{:?}",
        s.solve
    );
    assert!(s.plan_iterations <= 8 && free.plan_iterations > 8, "{s:?}");
    assert_eq!(s.errors.solver_not_converged, 1);
    assert!(matches!(outcome, PlanOutcome::Goal(_)), "{outcome:?}");
}
