//! The closed loop: render a depth frame, send it over the depth link, let the core integrate
//! it and plan, fly the plan, repeat.
//!
//! The simulator never plans for the core. Each step it
//!
//! 1. renders the depth camera at the vehicle's true pose at the frame's instant and sends the
//!    frame, stamped with the pose the core believes for that instant, over the depth link
//!    ([`crate::link::depth_link`]: the link's wire format at its baud rate, through the configured
//!    transport and fault injector);
//! 2. keeps time running while the frame is on the wire (about 0.22 s at 921600 baud): the
//!    vehicle hovers, and over MAVLink the bridge keeps streaming its setpoint;
//! 3. hands every image that arrived whole to [`Explorer::integrate`] and asks
//!    [`Explorer::plan`] where to go — unless nothing arrived: then nothing changed for the
//!    planner, the vehicle holds, and the next step captures again;
//! 4. flies the returned waypoints with simple multirotor kinematics (speed and yaw-rate limits,
//!    fixed time step), for at most `replan_distance` metres (receding horizon) or the whole
//!    path with `follow_full_path`, turning to the goal yaw on arrival;
//! 5. checks the vehicle's body sphere against the true world at every time step and counts
//!    collisions.
//!
//! It stops when the core reports `Complete`, after three consecutive `Hold`s on fresh data
//! (the fault is the termination reason), after [`LINK_DEAD_STEPS`] steps in a row without a
//! frame (`stuck:link`), or at the scan limit.
//!
//! With [`SimConfig::mavlink`] the vehicle is not handed the waypoints. The core's `Bridge`
//! streams them as MAVLink setpoints (the next waypoint along the plan, as the companion's
//! `Follower` takes them) to the autopilot ([`crate::vehicle::autopilot`]): the in-process
//! flight-stack emulator, which the vehicle follows, or a real autopilot over UDP, which flies
//! the vehicle itself (time is then the wall clock, and the vehicle is wherever the autopilot
//! says). The explorer plans from, and the depth frames are stamped with, the pose the bridge
//! reports — not the simulator's ground truth.
//!
//! # A frame's instant over MAVLink
//!
//! Pose reports describe the past: each carries the autopilot's `time_boot_ms` of the instant
//! it was sampled, arrives some latency later, and the next one is a stream period away. So a
//! frame is captured at an instant of the *autopilot's* clock — the newest one for which both
//! position and attitude have arrived
//! ([`PoseHistory::newest_ms`](harmonic_core::mavlink::PoseHistory::newest_ms)) — and its
//! camera pose is the pose of that instant from the bridge's history
//! ([`PoseHistory::pose_at`](harmonic_core::mavlink::PoseHistory::pose_at), interpolated by
//! `time_boot_ms` when position and attitude were not sampled together). Against a remote
//! autopilot the camera renders at that same pose: it is the only truth there is. Against the
//! emulator it renders at the simulator's true pose of that instant (the emulator's clock is
//! the simulator's plus
//! [`EmulatorTiming::boot_ms`](crate::vehicle::flight::EmulatorTiming::boot_ms)), so a stamp
//! from the wrong instant shows as a smeared map. Each frame also carries its [`FrameTiming`] —
//! the yaw rate measured from the samples' timestamps, and how long before the capture the
//! newest sample arrived — and the core refuses frames taken while turning faster than
//! [`ExplorerConfig::max_frame_yaw_rate`] or on a pose stream older than
//! [`ExplorerConfig::max_frame_pose_lag_ms`]; the vehicle holds and the next step captures
//! again.

use std::time::{Duration, Instant};

use harmonic_core::camera::DepthFrame;
use harmonic_core::explore::{
    forward_camera_pose, ErrorCounters, Explorer, ExplorerConfig, FrameTiming, Goal, HarmonicField,
    PlanOutcome, SolverKind,
};
use harmonic_core::map::{self, Dims, MapGeometry, VoxelMap};
use harmonic_core::operator::OperatorState;
use nalgebra::Point3;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::Serialize;

use crate::link::depth_link::{DepthLink, LinkConfig, LinkReport};
use crate::planners::baseline::Baseline;
use crate::planners::{CorePlanner, HarmonicPlanner, HostClock, HostStorage, Planner, PlannerKind};
use crate::run::metrics::{Contact, Coverage, GroundTruth};
use crate::sensors::camera::{DepthCamera, StereoNoise};
pub use crate::sensors::faults::SimFaults;
use crate::sensors::faults::{Drift, DriftConfig};
use crate::sensors::sensing::MapAccuracy;
use crate::sensors::stereo::{StereoDepth, StereoReport, StereoRig};
use crate::vehicle::autopilot::{MavlinkConfig, MavlinkLink, MavlinkReport};
use crate::world::scenario::Scenario;
use crate::world::World;
use harmonic_core::companion::{travel_heading, After, Follower, Mission, Step};

/// Steps in a row without a depth frame after which the run gives up (`stuck:link`).
pub const LINK_DEAD_STEPS: u32 = 100;
/// Against a remote autopilot: how long to wait for a fresh pose before giving up, s.
pub const REMOTE_POSE_TIMEOUT_S: f64 = 15.0;
/// Against a remote autopilot: a leg in which the vehicle makes no progress for this long
/// (not armed, not in offboard mode) ends, s.
pub const REMOTE_STALL_S: f64 = 20.0;

/// Simulation settings.
#[derive(Debug, Clone)]
pub struct SimConfig {
    /// Which planner flies: the core's harmonic explorer (default) or a baseline.
    /// [`PlannerKind::HarmonicLaplace`], [`PlannerKind::HarmonicGs`] and
    /// [`PlannerKind::HarmonicThesis`] override `explorer.field` with the seed's Laplace field;
    /// `HarmonicGs` also overrides `explorer.solver` with Gauss-Seidel, `HarmonicThesis` with
    /// the thesis's Jacobi solve.
    pub planner: PlannerKind,
    /// Closest and random frontier choose their goal by the core's view rule (an ablation; see
    /// [`Baseline::with_core_views`]).
    pub baseline_views: bool,
    /// Every planner's map keeps a surface estimate across frames for noisy depth (the host
    /// lends the storage, two words per voxel; see [`harmonic_core::integrate`]). Only the
    /// core's stereo sensor model uses it.
    pub surface_estimate: bool,
    /// Core configuration (vehicle radius, solver, …).
    pub explorer: ExplorerConfig,
    /// Depth camera.
    pub camera: DepthCamera,
    /// Radius of the vehicle's physical body for collision checks, metres.
    pub body_radius: f32,
    /// Maximum speed, m/s.
    pub max_speed: f32,
    /// Maximum yaw rate, rad/s.
    pub max_yaw_rate: f32,
    /// Integration time step, s.
    pub dt: f32,
    /// Distance flown before the next scan and replan, metres.
    pub replan_distance: f32,
    /// Fly every streamline to its end before scanning again (the paper's mode).
    pub follow_full_path: bool,
    /// Stop after this many steps (captures).
    pub max_scans: u32,
    /// Scans at evenly spaced headings, turning on the spot, before the first plan (0 or 1:
    /// plan after the first scan). Every planner starts the same way. Without it a start
    /// whose first view leaves the vehicle's surroundings unobserved can end the run at once:
    /// the vehicle's voxel is then the whole safe component, with no frontier, and the core
    /// reports `complete`.
    pub look_around: u32,
    /// Seed for sensor noise and link faults.
    pub seed: u64,
    /// Random-walk drift of the believed pose per keyframe (not with MAVLink).
    pub drift: Option<DriftConfig>,
    /// Write each full replan's problem (`step_NNNN.npy` labels and `step_NNNN.json` with the
    /// source voxel and the command that re-solves it) into this directory.
    pub dump_problem: Option<std::path::PathBuf>,
    /// Write the voxels where the map differs from the noise-free map of the same run here, as
    /// CSV ([`crate::sensors::sensing::write_map_errors`]). Only runs with imperfect sensing
    /// keep that map.
    pub map_errors: Option<std::path::PathBuf>,
    /// The depth link: transport, baud rate, faults.
    pub link: LinkConfig,
    /// After a complete exploration, fly back to the start through known free space
    /// ([`Explorer::plan_home`](harmonic_core::explore::Explorer::plan_home)); the report keeps
    /// the exploration's numbers and gives the way home apart ([`Report::return_home`]).
    /// Default false (benchmarks compare explorations); `explore` turns it on.
    pub return_home: bool,
    /// Fly over MAVLink (see the [module documentation](self)); `None`: the vehicle flies the
    /// waypoints directly.
    pub mavlink: Option<MavlinkConfig>,
    /// Sensor and pose faults (the depth link has its own, in [`LinkConfig::faults`]).
    pub faults: SimFaults,
    /// Where depth frames come from: the depth camera (default) or rendered stereo pairs
    /// matched by the core ([`use_stereo_depth`]).
    pub depth_source: DepthSource,
    /// How far (metres, per axis, each below the voxel size) the map's grid origin lies below
    /// the scenario's bounds; see [`scenario_geometry`]. Zero: every built-in world's surfaces lie
    /// on voxel faces.
    pub grid_offset: [f32; 3],
}

/// Where the depth frames of a run come from.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub enum DepthSource {
    /// [`SimConfig::camera`] renders depth directly (with its noise model, if any).
    #[default]
    Camera,
    /// A stereo pair is rendered at the camera's pose and matched by
    /// [`harmonic_core::stereo`] ([`crate::sensors::stereo::StereoDepth`]); the frame has the
    /// camera's intrinsics.
    Stereo(StereoRig),
}

/// Depth error (m, one voxel) at the range up to which noisy depth is used with the rules of
/// exact depth, by default.
pub const TRUSTED_DEPTH_ERROR_M: f32 = 0.1;
/// Disparity error (render pixels) of the core's matcher on rendered pairs: its sub-pixel error
/// (BENCHMARKS.md) with a margin. The stereo sensor model's `σ_d` for `--depth-from stereo`.
pub const STEREO_TRUSTED_SIGMA_PX: f32 = 0.2;

/// Planning radius (metres) of a run integrated with the stereo sensor model, unless one is
/// given. The model maps a surface at its true thickness, where "the hit wins" of exact depth
/// grows it by about a voxel; on worlds whose walls lie on voxel faces the default 0.2 m then
/// puts the 0.15 m body's planned centres exactly 0.15 m from the wall, with nothing to spare.
/// Measured (docs/RESULTS.md, "Surfaces on voxel faces"): runs with a contact fell from 10 to 3
/// of 36 (the harmonic planner's from 2 to 0), at the same coverage.
pub const STEREO_MODEL_VEHICLE_RADIUS_M: f32 = 0.25;

/// Sets how `cfg`'s explorer integrates depth whose disparity error is `sigma_px` (camera focal
/// length `fx` px, baseline `baseline_m`; 0 for exact depth). With `sensor_model`, the core's
/// stereo sensor model ([`harmonic_core::integrate`]) with that error, up to `trusted_range`
/// metres (default: the camera's maximum range). Without, the rules of exact depth up to
/// `trusted_range` (default: where the error moves the depth by [`TRUSTED_DEPTH_ERROR_M`],
/// [`crate::sensors::camera::trusted_range`]), farther returns only clearing free space up to it.
/// The sensor model also widens the planning radius to at least
/// [`STEREO_MODEL_VEHICLE_RADIUS_M`], keeping the radius it had as the way out of a pocket
/// ([`ExplorerConfig::narrow_radius`]). Noisy depth (`sigma_px` > 0) turns the sealing of far
/// remnants off ([`ExplorerConfig::remnant_frontier_m2`] = 0). A later `--remnant-area` turns it
/// back on only without the sensor model: with it the core keeps the rule off itself
/// ([`ExplorerConfig::remnant_frontier_m2`]).
pub fn integrate_noisy_depth(
    cfg: &mut SimConfig,
    sigma_px: f32,
    fx: f32,
    baseline_m: f32,
    trusted_range: Option<f32>,
    sensor_model: bool,
) {
    let range = match trusted_range {
        Some(r) => r,
        None if sensor_model => cfg.camera.max_range,
        None => crate::sensors::camera::trusted_range(sigma_px, fx, baseline_m, TRUSTED_DEPTH_ERROR_M),
    };
    cfg.explorer.integration.max_range = range
        .min(cfg.camera.max_range)
        .max(cfg.explorer.integration.min_range + 0.1);
    let model = sensor_model && sigma_px > 0.0;
    cfg.explorer.integration.depth_noise_per_m = if model { sigma_px / (fx * baseline_m) } else { 0.0 };
    if model {
        // The radius it had (exact depth's) is the way out of a pocket the wider one leaves
        // ([`harmonic_core::domain::is_pocket`]).
        cfg.explorer.narrow_radius = cfg.explorer.vehicle_radius;
        cfg.explorer.vehicle_radius = cfg.explorer.vehicle_radius.max(STEREO_MODEL_VEHICLE_RADIUS_M);
    }
    // Far remnants are sealed only on trustworthy depth: on a noisy map a crumb may be a passage
    // the noise narrowed (the core turns the rule off itself under the sensor model; with the
    // exact-depth rules up to a trusted range it cannot tell, so the caller does). Measured in
    // docs/RESULTS.md, "Now: far remnants sealed".
    if sigma_px > 0.0 {
        cfg.explorer.remnant_frontier_m2 = 0.0;
    }
}

/// With the stereo sensor model, `--noise`'s filter window ([`StereoNoise::filter_px`]) is the
/// model's footprint ([`IntegrationParams::footprint_px`](harmonic_core::integrate::IntegrationParams)),
/// as the matcher's window is for stereo depth ([`use_stereo_depth`]): the median stands in for a
/// stereo pipeline's window aggregation, so slanted surfaces are less certain, returns whose
/// slant cannot be measured are left out, and no return clears deeper than the nearest depth
/// within half the window. An unfiltered camera (a 1 px window) has none. `window_px`, if
/// given, is the window instead (`--pipeline-window`; 0: none). Measured in docs/RESULTS.md,
/// "The rules for `--noise`".
pub fn use_pipeline_window(cfg: &mut SimConfig, noise: StereoNoise, window_px: Option<f32>) {
    let median = if noise.filter_px > 1 {
        f32::from(noise.filter_px)
    } else {
        0.0
    };
    cfg.explorer.integration.footprint_px = window_px.unwrap_or(median);
}

/// Switches `cfg` to stereo depth from `rig`: depth 0 (no match) becomes unknown rather than
/// free space, and the matcher's depth is integrated as [`integrate_noisy_depth`] says, with a
/// disparity error of [`STEREO_TRUSTED_SIGMA_PX`] (without `sensor_model` and `trusted_range`:
/// up to 2.8 m for the default rig). With `sensor_model` the matcher's window is the model's
/// footprint ([`IntegrationParams::footprint_px`](harmonic_core::integrate::IntegrationParams)):
/// slanted surfaces are less certain, and returns whose slant cannot be measured are left out.
pub fn use_stereo_depth(cfg: &mut SimConfig, rig: StereoRig, trusted_range: Option<f32>, sensor_model: bool) {
    cfg.depth_source = DepthSource::Stereo(rig);
    cfg.explorer.integration.no_return = harmonic_core::integrate::NoReturn::Unknown;
    let fx = cfg.camera.intrinsics.fx() * f32::from(rig.scale.max(1));
    // The matcher's window at the depth frame's scale: the sensor model's slant term.
    cfg.explorer.integration.footprint_px = if sensor_model {
        f32::from(rig.window) / f32::from(rig.scale.max(1))
    } else {
        0.0
    };
    integrate_noisy_depth(
        cfg,
        STEREO_TRUSTED_SIGMA_PX,
        fx,
        rig.baseline_m,
        trusted_range,
        sensor_model,
    );
}

impl Default for SimConfig {
    fn default() -> Self {
        Self {
            planner: PlannerKind::Harmonic,
            baseline_views: false,
            surface_estimate: false,
            explorer: ExplorerConfig::default(),
            camera: DepthCamera::default_thesis(),
            body_radius: 0.15,
            max_speed: 1.0,
            max_yaw_rate: 90f32.to_radians(),
            dt: 0.05,
            replan_distance: 1.0,
            follow_full_path: false,
            max_scans: 3000,
            look_around: 4,
            seed: 1,
            drift: None,
            dump_problem: None,
            map_errors: None,
            link: LinkConfig::default(),
            return_home: false,
            mavlink: None,
            faults: SimFaults::default(),
            depth_source: DepthSource::Camera,
            grid_offset: [0.0; 3],
        }
    }
}

/// The flight back to the start.
#[derive(Debug, Clone, Serialize)]
pub struct ReturnHome {
    /// "home" (within 0.15 m of the start), "stuck:FAULT" (e.g. `stuck:HomeUnreachable`),
    /// "aborted" or "scan_limit".
    pub termination: String,
    /// Distance flown on the way, m.
    pub path_length_m: f64,
    /// Depth frames integrated on the way.
    pub scans: u32,
    /// Distance from the start at the end, m.
    pub distance_to_home_m: f64,
    /// Simulated time of the way home, s.
    pub time_s: f64,
}

/// One capture-and-plan step.
#[derive(Debug, Clone, Serialize)]
pub struct StepRecord {
    /// Step number (= captures so far).
    pub step: u32,
    /// Vehicle position the plan started from, map frame.
    pub position: [f32; 3],
    /// Vehicle yaw at the plan, radians.
    pub yaw: f32,
    /// "goal" (a new plan), "kept" (the committed goal still stands; nothing was solved),
    /// "escape", "complete", "hold:FAULT", or "no_frame" (no depth frame arrived whole; no
    /// plan).
    pub outcome: String,
    /// Depth frames integrated before this step's plan.
    pub frames_integrated: u32,
    /// Frontier voxels in the vehicle's component.
    pub frontier: u32,
    /// Interior unknowns solved for.
    pub unknowns: u32,
    /// Free coverage after this scan.
    pub coverage_free: f64,
    /// Integration time, ms.
    pub integrate_ms: f64,
    /// Domain build time, ms.
    pub domain_ms: f64,
    /// Solve time, ms.
    pub solve_ms: f64,
    /// Streamline and goal time, ms.
    pub streamline_ms: f64,
    /// Solves of the field this step (every screening the plan tried; 0 without a plan);
    /// `None` in processor-in-the-loop runs, whose downlink report does not count them.
    pub solves: Option<u32>,
    /// Of those, the re-solves done in boxes around what the scan changed (the others are
    /// whole-grid solves, or boxes that gave the grid back); `None` as `solves`.
    pub solves_in_boxes: Option<u32>,
    /// Solver iterations.
    pub solver_iterations: u32,
    /// Final relative residual.
    pub solver_residual: f32,
    /// Solver cell updates.
    pub solver_updates: u64,
    /// Streamline length, metres.
    pub streamline_m: f32,
    /// Path flown so far, metres.
    pub path_length_m: f64,
    /// The goal this step flies to (a new or kept plan, an escape), map frame; `None` without a
    /// goal.
    pub goal: Option<[f32; 3]>,
    /// Frontier regions sealed so far (visits that kept teaching nothing; see
    /// `harmonic_core::explore::ExplorerConfig::stall_visits`).
    pub seals: u32,
}

/// Mean and maximum of a per-step time.
#[derive(Debug, Clone, Copy, Default, Serialize)]
pub struct TimeStat {
    /// Mean, ms.
    pub mean_ms: f64,
    /// Maximum, ms.
    pub max_ms: f64,
}

impl TimeStat {
    pub(crate) fn of(values: impl Iterator<Item = f64>) -> Self {
        let (mut n, mut sum, mut max) = (0usize, 0.0f64, 0.0f64);
        for v in values {
            n += 1;
            sum += v;
            max = max.max(v);
        }
        Self {
            mean_ms: if n == 0 { 0.0 } else { sum / n as f64 },
            max_ms: max,
        }
    }
}

/// Per-phase timing over a run: means and maxima over *all* steps, including steps that kept
/// the committed goal and solved nothing (their solve time is 0; see `StepRecord::outcome`).
#[derive(Debug, Clone, Copy, Default, Serialize)]
pub struct Timing {
    /// Depth integration.
    pub integrate: TimeStat,
    /// Domain build.
    pub domain: TimeStat,
    /// Laplace solve.
    pub solve: TimeStat,
    /// Streamline and goal.
    pub streamline: TimeStat,
}

impl Timing {
    /// The means and maxima of `steps`' phase times.
    pub fn of_steps(steps: &[StepRecord]) -> Self {
        Self {
            integrate: TimeStat::of(steps.iter().map(|s| s.integrate_ms)),
            domain: TimeStat::of(steps.iter().map(|s| s.domain_ms)),
            solve: TimeStat::of(steps.iter().map(|s| s.solve_ms)),
            streamline: TimeStat::of(steps.iter().map(|s| s.streamline_ms)),
        }
    }
}

/// Instructions of one phase, over a run.
#[derive(Debug, Clone, Copy, Default, Serialize)]
pub struct InstructionStat {
    /// Mean per scan (phases that did not run count as 0).
    pub mean: f64,
    /// Largest.
    pub max: u64,
}

/// Processor-in-the-loop details of a run, in `report.json` as `pil`.
#[derive(Debug, Clone, Serialize)]
pub struct PilReport {
    /// The firmware ELF.
    pub firmware: String,
    /// The QEMU command line.
    pub qemu: String,
    /// Flight ticks exchanged (TIMESYNC round trips).
    pub ticks: u64,
    /// Downlink frames the simulator could not decode.
    pub downlink_dropped: u32,
    /// Instructions integrating one frame.
    pub integrate: InstructionStat,
    /// Instructions building the domain.
    pub domain: InstructionStat,
    /// Instructions solving.
    pub solve: InstructionStat,
    /// Instructions tracing the streamline and choosing the goal.
    pub streamline: InstructionStat,
    /// Instructions of a whole planning cycle (domain + solve + streamline) on full replans.
    pub plan_cycle: InstructionStat,
    /// Per scan: instructions of integrate, domain, solve, streamline.
    pub steps: Vec<[u64; 4]>,
}

/// Everything a run produced; serialised as `report.json`.
#[derive(Debug, Clone, Serialize)]
pub struct Report {
    /// Scenario name.
    pub scenario: String,
    /// Planner name.
    pub planner: String,
    /// Solver name.
    pub solver: String,
    /// "complete", "scan_limit", "stuck:FAULT" or "stuck:link".
    pub termination: String,
    /// Free-space coverage at the end.
    pub coverage_free: f64,
    /// Surface coverage at the end.
    pub coverage_surface: f64,
    /// Reachable free voxels the map holds as occupied.
    pub free_marked_occupied: usize,
    /// Reachable free voxels the map observed at all (free or not), fraction.
    pub coverage_observed: f64,
    /// Path flown, metres.
    pub path_length_m: f64,
    /// Depth frames integrated.
    pub scans: u32,
    /// Steps (captures), with or without a frame arriving.
    pub steps_taken: u32,
    /// The way home, if one was flown (after a complete exploration with
    /// [`SimConfig::return_home`], or on the operator's command); the other fields describe
    /// the exploration up to its completion.
    pub return_home: Option<ReturnHome>,
    /// Collision events (body sphere entering an obstacle).
    pub collisions: u32,
    /// Where each collision began, map frame.
    pub collision_points: Vec<[f32; 3]>,
    /// Closest the body's centre came to a surface over the run (the exploration and any way
    /// home), metres, at most [`CLEARANCE_CAP_M`](crate::run::metrics::CLEARANCE_CAP_M): less
    /// than the body radius is a collision.
    pub min_clearance_m: f32,
    /// Where the body's centre was at its closest, map frame.
    pub min_clearance_at: [f32; 3],
    /// Voxel updates by integration.
    pub integration_ops: u64,
    /// Solver cell updates.
    pub planning_ops: u64,
    /// Solves done in boxes around a scan's change, and those that gave the grid back to a
    /// whole-grid solve ([`harmonic_core::solve::local`]); 0 for the baselines and the firmware.
    pub local_solves: [u32; 2],
    /// Simulated time of the run, flight and waiting for the link, s (wall-clock time against
    /// a remote autopilot).
    pub flight_time_s: f64,
    /// Wall-clock time of the run, s.
    pub wall_time_s: f64,
    /// Bytes of the buffers the explorer borrows on the host (map, planning grid, solver,
    /// scratch: [`HostStorage::bytes`]); `None` when the firmware's arena holds them (its size
    /// is `fw-budget`'s).
    pub explorer_bytes: Option<usize>,
    /// Grid size.
    pub grid: [usize; 3],
    /// Voxel edge, metres.
    pub resolution: f32,
    /// Minimum corner of voxel (0, 0, 0), map frame, metres.
    pub grid_origin: [f32; 3],
    /// Reachable free voxels in the ground truth.
    pub reachable_free_voxels: usize,
    /// Unknown voxels sealed at the end: unobservable, far remnants, or (with the surface
    /// estimate) weak evidence forgotten behind a surface.
    pub sealed_voxels: u32,
    /// At a `complete` end, the map's frontier voxels the vehicle could not reach (too narrow
    /// for its radius, behind a gap): seen, but left. `None` for other ends.
    pub unreachable_frontier_voxels: Option<u32>,
    /// Per-phase timing.
    pub timing: Timing,
    /// Fault counters.
    pub errors: ErrorCounters,
    /// The depth link: frames sent, integrated and lost, the receiver's error counters,
    /// injected faults, bytes, transfer time.
    pub link: LinkReport,
    /// MAVLink: messages each way by type, setpoint rate and gaps, the bridge's and emulator's
    /// counters; `None` unless the run flew over MAVLink ([`SimConfig::mavlink`]).
    pub mavlink: Option<MavlinkReport>,
    /// Processor-in-the-loop details; `None` unless the firmware flew (the `pil` module).
    pub pil: Option<PilReport>,
    /// With imperfect sensing (noise, outliers, textureless surfaces, drift): how closely the
    /// map matches the noise-free map of the same run ([`crate::sensors::sensing`]).
    pub map_accuracy: Option<MapAccuracy>,
    /// With drift: the believed pose's position and yaw error at the end, metres and radians.
    pub final_drift: Option<[f32; 2]>,
    /// With stereo depth ([`DepthSource::Stereo`]): matcher statistics.
    pub stereo: Option<StereoReport>,
    /// The true path flown, a point every 5 cm, map frame.
    pub trajectory: Vec<[f32; 3]>,
    /// Per-step records.
    pub steps: Vec<StepRecord>,
}

impl Report {
    /// The exploration's simulated time, s: [`Report::flight_time_s`] without a way home flown
    /// after it.
    pub fn exploration_time_s(&self) -> f64 {
        self.flight_time_s - self.return_home.as_ref().map_or(0.0, |h| h.time_s)
    }
}

/// A depth frame the planner integrated, with the camera pose it was integrated at.
#[derive(Debug, Clone)]
pub struct IntegratedFrame {
    /// Depth, millimetres, row-major.
    pub depth_mm: Vec<u16>,
    /// Pinhole model.
    pub intrinsics: harmonic_core::camera::Intrinsics,
    /// Camera → map pose the planner used.
    pub camera_pose: nalgebra::Isometry3<f32>,
    /// The true camera pose (differs with drift).
    pub true_pose: nalgebra::Isometry3<f32>,
    /// Simulated time of the capture, s.
    pub time_s: f64,
}

/// What an observer of [`run_observed`] sees after every step, and once more at the end.
pub struct StepView<'a> {
    /// Step number (0 for the view after the run).
    pub step: u32,
    /// True vehicle position and yaw.
    pub vehicle: (Point3<f32>, f32),
    /// The planner (map, labels, potential, waypoints of the last plan).
    pub planner: &'a dyn Planner,
    /// The step's record (`None` after the run).
    pub record: Option<&'a StepRecord>,
    /// Frames integrated this step.
    pub frames: &'a [IntegratedFrame],
    /// The vehicle positions at which the planner planned this step (for replaying the core's
    /// body marking).
    pub planned_at: Option<Point3<f32>>,
    /// True once the run is over.
    pub finished: bool,
}

/// Errors that stop a run.
#[derive(Debug)]
pub enum SimError {
    /// The scenario's grid does not fit the core's limits.
    Grid(String),
    /// The core refused the configuration.
    Config(String),
    /// A problem dump could not be written.
    Dump(String),
    /// The map's errors could not be written, or the run keeps no noise-free map.
    MapErrors(String),
    /// The depth link could not be opened or failed.
    Link(String),
    /// The MAVLink link could not be opened or failed.
    Mavlink(String),
}

/// The error for `--map-errors PATH` failing to be written.
fn map_errors_io(path: &std::path::Path, e: std::io::Error) -> SimError {
    SimError::MapErrors(format!("{}: {e}", path.display()))
}

impl std::fmt::Display for SimError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            SimError::Grid(s) => write!(f, "grid: {s}"),
            SimError::Config(s) => write!(f, "explorer configuration: {s}"),
            SimError::Dump(s) => write!(f, "--dump-problem: {s}"),
            SimError::MapErrors(s) => write!(f, "--map-errors: {s}"),
            SimError::Link(s) => write!(f, "depth link: {s}"),
            SimError::Mavlink(s) => write!(f, "mavlink: {s}"),
        }
    }
}

impl std::error::Error for SimError {}

/// The map geometry a scenario is explored on.
///
/// `offset` (metres, each in `[0, resolution)`) moves the grid's origin that far below the
/// scenario's bounds along each axis, with one more voxel along every axis it moves, so the grid
/// still covers the bounds. The built-in worlds put every surface on a voxel face (multiples of
/// the resolution from the bounds); a real map's grid lies anywhere against the walls, and an
/// offset measures how much a result owes to that alignment (`explore --grid-offset`).
pub fn scenario_geometry(scenario: &Scenario, offset: [f32; 3]) -> Result<MapGeometry, SimError> {
    let r = scenario.resolution;
    if let Some(bad) = offset.iter().find(|o| !(o.is_finite() && **o >= 0.0 && **o < r)) {
        return Err(SimError::Config(format!(
            "grid offset {bad} m: each component must lie in [0, {r}) m, the voxel size"
        )));
    }
    let [nx, ny, nz] = scenario.grid_dims();
    let [nx, ny, nz] =
        [(nx, offset[0]), (ny, offset[1]), (nz, offset[2])].map(|(n, o)| n + usize::from(o > 0.0));
    let dims = Dims::new(nx, ny, nz).map_err(|e| SimError::Grid(format!("{nx}×{ny}×{nz}: {e:?}")))?;
    let origin = scenario.world.bounds.min - nalgebra::Vector3::from(offset);
    MapGeometry::new(dims, origin, r).map_err(|e| SimError::Grid(format!("{e:?}")))
}

fn ms(ns: u64) -> f64 {
    ns as f64 * 1e-6
}

/// The simulated multirotor.
#[derive(Debug, Clone, Copy)]
pub struct Vehicle {
    /// Position, map frame.
    pub position: Point3<f32>,
    /// Yaw about map z, radians.
    pub yaw: f32,
}

/// The simulated vehicle's yaw arithmetic: `a` wrapped to [−π, π] by `%` (an angle of exactly
/// −π stays −π, where the core's [`wrap_angle`](harmonic_core::mavlink::wrap_angle), whose
/// range is (−π, π], returns π). It moves the simulated vehicle, not the companion, and every
/// recorded run's turns were timed with it: the core's would end some turns a 50 ms step
/// sooner (measured: s1 and kitchen starts 1–10, flight times 0.05–0.1 s shorter on 6 of 20,
/// paths, scans and coverage the same).
pub(crate) fn wrap_angle(a: f32) -> f32 {
    let mut a = a % std::f32::consts::TAU;
    if a > std::f32::consts::PI {
        a -= std::f32::consts::TAU;
    } else if a < -std::f32::consts::PI {
        a += std::f32::consts::TAU;
    }
    a
}

fn to_ms(time_s: f64) -> u64 {
    (time_s * 1e3).round().max(0.0) as u64
}

impl Vehicle {
    pub(crate) fn slew_yaw(&mut self, target: f32, max_step: f32) -> bool {
        let e = wrap_angle(target - self.yaw);
        if e.abs() <= max_step {
            self.yaw = wrap_angle(target);
            true
        } else {
            self.yaw = wrap_angle(self.yaw + max_step * e.signum());
            false
        }
    }

    /// Moves straight towards `target` by at most `max_step` metres; returns the distance moved.
    pub(crate) fn step_towards(&mut self, target: &Point3<f32>, max_step: f32) -> f32 {
        let seg = target - self.position;
        let dist = seg.norm();
        if dist <= 1e-6 {
            return 0.0;
        }
        let s = max_step.max(0.0).min(dist);
        self.position += seg * (s / dist);
        s
    }
}

/// The vehicle's track over the run: distance flown, collisions and closest approach.
struct Track<'w> {
    distance: f64,
    contact: Contact<'w>,
    /// True positions, one every [`TRACK_SAMPLE_M`] of flight.
    path: Vec<[f32; 3]>,
}

/// Spacing of the recorded true path, metres.
const TRACK_SAMPLE_M: f32 = 0.05;

impl<'w> Track<'w> {
    fn start(world: &'w World, p: &Point3<f32>, radius: f32) -> Self {
        Self {
            distance: 0.0,
            contact: Contact::start(world, p, radius),
            path: vec![p.coords.into()],
        }
    }

    fn moved(&mut self, p: &Point3<f32>, distance: f32) {
        self.distance += f64::from(distance);
        if self
            .path
            .last()
            .is_none_or(|l| (Point3::from(*l) - p).norm() >= TRACK_SAMPLE_M)
        {
            self.path.push(p.coords.into());
        }
        self.contact.observe(p);
    }
}

/// Where the way home began: the exploration's numbers at that moment.
struct ReturnStart {
    distance: f64,
    frames: u32,
    taken: u32,
    t_s: f64,
    status: harmonic_core::explore::Status,
    coverage: Coverage,
    /// The exploration was complete (else the operator called the vehicle home).
    after_complete: bool,
}

/// What moves with time: the depth link, and the MAVLink link if the run flies over it.
struct Rig<'b> {
    link: DepthLink<'b>,
    mav: Option<MavlinkLink>,
    /// Time since the start of the run, s: simulated, or the wall clock against a remote
    /// autopilot.
    t_s: f64,
    dt: f64,
    /// Against a remote autopilot: the wall-clock start.
    wall: Option<Instant>,
    /// Injected pose faults.
    faults: SimFaults,
    /// With the emulator: the true vehicle at each of the last pose samples it was handed
    /// (simulated ms, vehicle), for the truth at a frame's instant.
    truth: std::collections::VecDeque<(u64, Vehicle)>,
}

/// Over MAVLink, how long a capture waits for a turning vehicle to stop, s.
const SETTLE_S: f64 = 0.5;

/// Pose samples of the true vehicle the simulator keeps (5 s at its 50 ms step).
const TRUTH_HISTORY_LEN: usize = 100;

/// The poses of one captured frame.
struct Capture {
    /// What the frame is stamped with: the pose the core believes (map frame position, yaw).
    believed: (Point3<f32>, f32),
    /// Where the camera renders from: the vehicle's true pose at the frame's instant.
    truth: (Point3<f32>, f32),
    /// The frame's timing, over MAVLink.
    timing: Option<FrameTiming>,
}

impl Rig<'_> {
    fn now_ms(&self) -> u64 {
        to_ms(self.t_s)
    }

    /// Believed minus true position: the injected pose drift by now.
    fn drift(&self) -> nalgebra::Vector3<f32> {
        self.faults.drift_at(self.t_s)
    }

    /// True while the injected pose outage silences the autopilot.
    fn pose_outage(&self) -> bool {
        self.faults.outage_at(self.t_s)
    }

    /// One time step: against a remote autopilot, sleeps until the wall clock has caught up
    /// (or jumps to it, if planning took longer); then the depth link moves its bytes.
    fn advance(&mut self) -> Result<(), SimError> {
        self.t_s += self.dt;
        if let Some(start) = self.wall {
            let target = Duration::from_secs_f64(self.t_s);
            let elapsed = start.elapsed();
            if elapsed < target {
                std::thread::sleep(target - elapsed);
            } else {
                self.t_s = elapsed.as_secs_f64();
            }
        }
        self.link.tick(self.t_s).map_err(SimError::Link)
    }

    /// Autopilot → bridge at the current time: the emulator reports the vehicle (when due),
    /// or what a remote autopilot sent is read.
    fn pull(&mut self, vehicle: &Vehicle) -> Result<(), SimError> {
        let now = self.now_ms();
        if self.pose_outage() {
            return Ok(());
        }
        let reported = vehicle.position + self.drift();
        let Some(mav) = self.mav.as_mut() else {
            return Ok(());
        };
        if !mav.is_remote() {
            // What the emulator is handed now is the truth of this instant.
            if self.truth.back().is_none_or(|(t, _)| *t < now) {
                if self.truth.len() >= TRUTH_HISTORY_LEN {
                    self.truth.pop_front();
                }
                self.truth.push_back((now, *vehicle));
            }
        }
        mav.pull(now, &reported, vehicle.yaw).map_err(SimError::Mavlink)
    }

    /// Captures a frame's poses (see the [module documentation](self)): without MAVLink the
    /// truth, and the truth plus the injected drift as the belief; over MAVLink the instant is
    /// the newest pose sample's (autopilot clock), the belief the bridge's pose of that instant
    /// and the truth the vehicle's at that instant (against a remote autopilot, the same pose,
    /// which the vehicle takes).
    fn capture(
        &mut self,
        vehicle: &mut Vehicle,
        cfg: &SimConfig,
        track: &mut Track,
    ) -> Result<Capture, SimError> {
        if self.mav.is_none() {
            return Ok(Capture {
                believed: (vehicle.position + self.drift(), vehicle.yaw),
                truth: (vehicle.position, vehicle.yaw),
                timing: None,
            });
        }
        // The newest samples, and a fresh pose at all (waits, streaming, while it is stale).
        // A vehicle still turning is given up to SETTLE_S to stop (a goal turn that just ended
        // shows in the last sample interval); the core refuses what is still turning then.
        let start = self.t_s;
        let pose = loop {
            self.pull(vehicle)?;
            let believed = self.believed_pose(vehicle, track)?;
            let Some(mav) = self.mav.as_ref() else {
                return Err(SimError::Mavlink("no MAVLink link".into()));
            };
            let history = mav.history();
            let Some(Ok(pose)) = history.newest_ms().map(|t| history.pose_at(t)) else {
                // No timestamped sample (cannot happen once the bridge has a pose): the
                // bridge's pose, untimed.
                return Ok(Capture {
                    believed,
                    truth: (vehicle.position, vehicle.yaw),
                    timing: None,
                });
            };
            let limit = cfg.explorer.max_frame_yaw_rate;
            let turning = pose.yaw_rate.is_some_and(|r| r.abs() > limit);
            if !turning || self.t_s - start >= SETTLE_S {
                break pose;
            }
            let moved = self.exchange(vehicle, 0.0, 0.0)?;
            track.moved(&vehicle.position, moved);
            self.advance()?;
        };
        let now = self.now_ms();
        let Some(mav) = self.mav.as_ref() else {
            return Err(SimError::Mavlink("no MAVLink link".into()));
        };
        let timing = FrameTiming {
            yaw_rate: pose.yaw_rate,
            pose_lag_ms: u32::try_from(now.saturating_sub(pose.arrived_ms)).unwrap_or(u32::MAX),
        };
        let believed = (pose.position, pose.yaw);
        let truth = match mav.emulator_boot_ms() {
            // The emulator's clock runs `boot_ms` ahead of simulated time.
            Some(boot_ms) => {
                let at = u64::from(pose.time_boot_ms).saturating_sub(boot_ms);
                let v = self
                    .truth
                    .iter()
                    .rev()
                    .find(|(t, _)| *t <= at)
                    .map(|(_, v)| *v)
                    .unwrap_or(*vehicle);
                (v.position, v.yaw)
            }
            None => {
                vehicle.position = pose.position;
                vehicle.yaw = pose.yaw;
                believed
            }
        };
        Ok(Capture {
            believed,
            truth,
            timing: Some(timing),
        })
    }

    /// Bridge → autopilot at the current time, then the vehicle follows the autopilot:
    /// towards the emulator's setpoint by at most `max_step` metres, or to where the remote
    /// autopilot says it is. Returns the distance moved. Without MAVLink, nothing.
    fn push_and_follow(
        &mut self,
        vehicle: &mut Vehicle,
        max_step: f32,
        yaw_step: f32,
    ) -> Result<f32, SimError> {
        let now = self.now_ms();
        let Some(mav) = self.mav.as_mut() else {
            return Ok(0.0);
        };
        mav.push(now).map_err(SimError::Mavlink)?;
        if mav.is_remote() {
            return Ok(match mav.pose(now) {
                Ok((position, yaw)) => {
                    let moved = (position - vehicle.position).norm();
                    vehicle.position = position;
                    vehicle.yaw = yaw;
                    moved
                }
                // Stale: the bridge holds; the vehicle stays where it was last seen.
                Err(_) => 0.0,
            });
        }
        let drift = self.drift();
        let Some(mav) = self.mav.as_mut() else {
            return Ok(0.0);
        };
        Ok(match mav.emulator_setpoint() {
            Some(setpoint) => {
                // The autopilot flies its (drifted) estimate onto the setpoint.
                let s = vehicle.step_towards(&(setpoint.position - drift), max_step);
                vehicle.slew_yaw(setpoint.yaw, yaw_step);
                s
            }
            None => 0.0,
        })
    }

    /// One MAVLink exchange both ways; see [`Rig::push_and_follow`].
    fn exchange(&mut self, vehicle: &mut Vehicle, max_step: f32, yaw_step: f32) -> Result<f32, SimError> {
        self.pull(vehicle)?;
        self.push_and_follow(vehicle, max_step, yaw_step)
    }

    /// The pose the core believes: the truth without MAVLink, else the bridge's. Against a
    /// remote autopilot whose pose is stale, waits (streaming) for a fresh one, at most
    /// [`REMOTE_POSE_TIMEOUT_S`].
    fn believed_pose(
        &mut self,
        vehicle: &mut Vehicle,
        track: &mut Track,
    ) -> Result<(Point3<f32>, f32), SimError> {
        let start = self.t_s;
        loop {
            let now = self.now_ms();
            let Some(mav) = self.mav.as_ref() else {
                return Ok((vehicle.position + self.drift(), vehicle.yaw));
            };
            match mav.pose(now) {
                Ok(pose) => return Ok(pose),
                // Stale (a remote autopilot, or an injected outage): hold and wait.
                Err(e) if self.t_s - start > REMOTE_POSE_TIMEOUT_S => return Err(SimError::Mavlink(e)),
                Err(_) => {
                    let moved = self.exchange(vehicle, 0.0, 0.0)?;
                    track.moved(&vehicle.position, moved);
                    self.advance()?;
                    if self.wall.is_some() {
                        crate::vehicle::autopilot::nap();
                    }
                }
            }
        }
    }

    /// Waits while the depth link is sending, the vehicle following the autopilot's setpoint
    /// (or hovering, without MAVLink); then lets an outside wire deliver its last bytes.
    fn wait_for_link(
        &mut self,
        vehicle: &mut Vehicle,
        cfg: &SimConfig,
        track: &mut Track,
    ) -> Result<(), SimError> {
        let step = cfg.max_speed * cfg.dt;
        let yaw_step = cfg.max_yaw_rate * cfg.dt;
        while self.link.sending() {
            let moved = self.exchange(vehicle, step, yaw_step)?;
            track.moved(&vehicle.position, moved);
            self.advance()?;
        }
        self.link.settle().map_err(SimError::Link)
    }

    /// Flies along `waypoints` directly (no MAVLink) for at most `budget` metres, then, if the
    /// end was reached, turns to the goal yaw.
    fn fly_direct(
        &mut self,
        vehicle: &mut Vehicle,
        waypoints: &[Point3<f32>],
        goal: &Goal,
        budget: f32,
        cfg: &SimConfig,
        track: &mut Track,
    ) -> Result<(), SimError> {
        let step_len = cfg.max_speed * cfg.dt;
        let yaw_step = cfg.max_yaw_rate * cfg.dt;
        let mut travelled = 0.0f32;
        for w in waypoints {
            loop {
                let seg = w - vehicle.position;
                if seg.norm() < 1e-5 {
                    break;
                }
                if travelled >= budget {
                    return Ok(());
                }
                if let Some(h) = travel_heading(&seg) {
                    vehicle.slew_yaw(h, yaw_step);
                }
                let s = vehicle.step_towards(w, step_len.min(budget - travelled));
                travelled += s;
                track.moved(&vehicle.position, s);
                self.advance()?;
            }
        }
        // Arrived: look where the planner asked.
        for _ in 0..1000 {
            if vehicle.slew_yaw(goal.yaw, yaw_step) {
                break;
            }
            self.advance()?;
        }
        Ok(())
    }

    /// Flies one leg over MAVLink: streams the next waypoint along `waypoints` as the setpoint
    /// (the companion's [`Follower`]: advancing when the bridge's pose is within its radius of it), lets the
    /// vehicle follow the autopilot for at most `budget` metres, and on reaching the end turns
    /// to the goal yaw. At the end of the budget the setpoint becomes the believed position.
    fn fly_mavlink(
        &mut self,
        vehicle: &mut Vehicle,
        waypoints: &[Point3<f32>],
        goal: &Goal,
        budget: f32,
        cfg: &SimConfig,
        track: &mut Track,
    ) -> Result<(), SimError> {
        let step_len = cfg.max_speed * cfg.dt;
        let yaw_step = cfg.max_yaw_rate * cfg.dt;
        let mut travelled = 0.0f32;
        // The companion's follower: the next waypoint, the heading towards it as fixed when it
        // was taken (so the setpoint does not change every tick), the goal's yaw at the end.
        let mut follower = Follower::default();
        let mut last_progress = (self.t_s, 0.0f32);
        // Generous: a leg is a few metres at most in receding-horizon mode.
        for _ in 0..200_000usize {
            self.pull(vehicle)?;
            let now = self.now_ms();
            let Some(mav) = self.mav.as_mut() else {
                return Ok(());
            };
            let (position, yaw) = match mav.pose(now) {
                Ok(pose) => pose,
                // The pose gone stale (a remote link, an injected outage): the bridge holds;
                // keep exchanging until it is back.
                Err(_) => (vehicle.position, vehicle.yaw),
            };
            if !follower.is_active() {
                // No waypoints: stay and turn.
                let here = [position];
                follower.follow(if waypoints.is_empty() { &here } else { waypoints }, goal);
            }
            let (target, target_yaw) = follower.setpoint(&position, yaw).unwrap_or((position, yaw));
            let turning = follower.is_turning();
            let stalled = self.wall.is_some() && self.t_s - last_progress.0 > REMOTE_STALL_S;
            if (!turning && travelled >= budget) || stalled {
                // End of the receding horizon: stop where the vehicle is.
                let _ = mav.bridge.set_target(position, yaw);
                return Ok(());
            }
            if turning && wrap_angle(goal.yaw - yaw).abs() < 1e-3 {
                return Ok(());
            }
            let _ = mav.bridge.set_target(target, target_yaw);
            let moved =
                self.push_and_follow(vehicle, step_len.min((budget - travelled).max(0.0)), yaw_step)?;
            travelled += moved;
            if travelled > last_progress.1 + 0.01 {
                last_progress = (self.t_s, travelled);
            }
            track.moved(&vehicle.position, moved);
            self.advance()?;
        }
        Ok(())
    }
}

/// Writes the labels and source of one planning step for `harmonic-sim solve`.
fn dump_problem(
    dir: &std::path::Path,
    step: u32,
    planner: &dyn Planner,
    position: &Point3<f32>,
    cfg: &SimConfig,
) -> Result<(), SimError> {
    let err = |e: std::io::Error| SimError::Dump(format!("{}: {e}", dir.display()));
    std::fs::create_dir_all(dir).map_err(err)?;
    let map = planner.map();
    let grid = crate::io::labels::problem_labels_from_map(map);
    let labels_path = dir.join(format!("step_{step:04}.npy"));
    std::fs::write(&labels_path, crate::io::npy::write_u8(&grid)).map_err(err)?;
    let Some(v) = map.geometry().voxel_at(position) else {
        return Ok(());
    };
    // f32 → shortest decimal → f64, so the JSON says 0.2 rather than 0.20000000298.
    let short = |v: f32| v.to_string().parse::<f64>().unwrap_or(f64::from(v));
    let meta = serde_json::json!({
        "labels": labels_path.file_name().map(|n| n.to_string_lossy().into_owned()),
        "source": [v.x, v.y, v.z],
        "radius": short(cfg.explorer.vehicle_radius),
        "resolution": short(map.geometry().resolution()),
        "command": format!(
            "harmonic-sim solve --labels {} --source {},{},{} --radius {} --resolution {}",
            labels_path.display(), v.x, v.y, v.z, cfg.explorer.vehicle_radius, map.geometry().resolution()
        ),
    });
    std::fs::write(dir.join(format!("step_{step:04}.json")), meta.to_string()).map_err(err)?;
    Ok(())
}

/// The planner `cfg` asks for, over `storage`.
/// The core's explorer for the run's planner: the harmonic field's, or a baseline's.
pub enum RunExplorer<'s> {
    /// A harmonic planner (`harmonic`, `harmonic-laplace`, `harmonic-gs`, `harmonic-thesis`).
    Harmonic(Box<Explorer<'s, HarmonicField<'s>>>),
    /// A baseline's target choice.
    Baseline(Box<Explorer<'s, Baseline>>),
}

/// The explorer `cfg` asks for over `storage` (the harmonic planners' field and solver, or a
/// baseline's choice, with the run's explorer configuration).
pub fn make_explorer<'s>(
    cfg: &SimConfig,
    geometry: MapGeometry,
    storage: &'s mut HostStorage,
) -> Result<RunExplorer<'s>, SimError> {
    let config_err = |e| SimError::Config(format!("{e:?}"));
    if cfg.explorer.plan_coarsening > 1 {
        let plan = geometry
            .coarsened(usize::from(cfg.explorer.plan_coarsening))
            .map_err(|e| SimError::Config(format!("--plan-coarsening: {e:?}")))?;
        storage.with_coarser_plan(&plan.dims());
    }
    if cfg.surface_estimate {
        storage.with_surface();
    }
    Ok(match cfg.planner {
        PlannerKind::Harmonic
        | PlannerKind::HarmonicLaplace
        | PlannerKind::HarmonicGs
        | PlannerKind::HarmonicThesis => {
            let mut explorer = cfg.explorer;
            if cfg.planner != PlannerKind::Harmonic {
                explorer.field = harmonic_core::field::PlanningField::Harmonic;
            }
            if cfg.planner == PlannerKind::HarmonicGs {
                explorer.solver = SolverKind::GaussSeidel;
            }
            if cfg.planner == PlannerKind::HarmonicThesis {
                explorer.solver = SolverKind::ThesisJacobi;
                storage.with_jacobi();
            }
            if explorer.solver == SolverKind::Flat {
                storage.with_flat();
            }
            RunExplorer::Harmonic(Box::new(
                Explorer::new(geometry, explorer, storage.lend()).map_err(config_err)?,
            ))
        }
        kind => {
            let mut targets = Baseline::new(kind, geometry.dims(), cfg.seed);
            if cfg.baseline_views {
                targets = targets.with_core_views();
            }
            RunExplorer::Baseline(Box::new(
                Explorer::with_targets(geometry, cfg.explorer, storage.lend(), targets)
                    .map_err(config_err)?,
            ))
        }
    })
}

fn make_planner<'s>(
    cfg: &SimConfig,
    geometry: MapGeometry,
    storage: &'s mut HostStorage,
) -> Result<Box<dyn Planner + 's>, SimError> {
    Ok(match make_explorer(cfg, geometry, storage)? {
        RunExplorer::Harmonic(explorer) => Box::new(HarmonicPlanner::new(*explorer)),
        RunExplorer::Baseline(explorer) => Box::new(CorePlanner::baseline(*explorer)),
    })
}

/// Runs one exploration of `scenario` to termination. `progress` is called after every step.
pub fn run(
    scenario: &Scenario,
    cfg: &SimConfig,
    progress: impl FnMut(&StepRecord),
) -> Result<Report, SimError> {
    run_observed(scenario, cfg, progress, |_| {})
}

/// [`run`], showing `observe` the planner and the frames after every step and at the end
/// (figures, recordings and map exports read the run this way).
pub fn run_observed(
    scenario: &Scenario,
    cfg: &SimConfig,
    mut progress: impl FnMut(&StepRecord),
    mut observe: impl FnMut(&StepView<'_>),
) -> Result<Report, SimError> {
    let wall = Instant::now();
    let geometry = scenario_geometry(scenario, cfg.grid_offset)?;
    let mut storage = HostStorage::new(&geometry.dims());
    let mut planner = make_planner(cfg, geometry, &mut storage)?;
    if cfg.drift.is_some() && cfg.mavlink.is_some() {
        return Err(SimError::Config("drift is simulated without MAVLink only".into()));
    }
    let sensing = Sensing::new(cfg)?;
    let measure_accuracy = !cfg.camera.is_exact() || sensing.drift.is_some() || sensing.stereo.is_some();
    let mut reference_buffers = ReferenceBuffers::new(&geometry, measure_accuracy);
    let reference = Reference::new(cfg, &geometry, &mut reference_buffers, measure_accuracy)?;
    let mut link_buffer = vec![0u16; cfg.camera.intrinsics.pixel_count()];
    let link = DepthLink::open(&cfg.link, &cfg.camera.intrinsics, &mut link_buffer, cfg.seed)
        .map_err(SimError::Link)?;
    let mut run = Run::start(scenario, cfg, planner.as_mut(), link, sensing, reference)?;
    for step in 1..=cfg.max_scans {
        if !run.step(step, &mut progress, &mut observe)? {
            break;
        }
    }
    let mut report = run.finish(wall, &mut observe)?;
    drop(planner);
    report.explorer_bytes = Some(storage.bytes());
    Ok(report)
}

/// Where the depth frames come from, and what happens to them on the way: the camera or the
/// stereo pair and their noise, the sensor faults, the believed pose's drift.
struct Sensing {
    stereo: Option<StereoDepth>,
    drift: Option<Drift>,
    /// The camera's noise (and the noise-free reference's renders).
    rng: ChaCha8Rng,
    /// Sensor dropouts and outliers.
    sensor_rng: ChaCha8Rng,
    depth: Vec<u16>,
}

impl Sensing {
    fn new(cfg: &SimConfig) -> Result<Self, SimError> {
        let stereo = match cfg.depth_source {
            DepthSource::Camera => None,
            DepthSource::Stereo(rig) => {
                Some(StereoDepth::new(rig, &cfg.camera.intrinsics).map_err(SimError::Config)?)
            }
        };
        Ok(Self {
            stereo,
            drift: cfg.drift.map(|d| Drift::new(d, cfg.seed)),
            rng: ChaCha8Rng::seed_from_u64(cfg.seed),
            sensor_rng: ChaCha8Rng::seed_from_u64(cfg.seed ^ 0x5e45_0f17),
            depth: Vec::new(),
        })
    }

    /// The depth image the sensor gives at the camera's true pose, with its faults.
    fn render(
        &mut self,
        cfg: &SimConfig,
        world: &World,
        true_pose: &nalgebra::Isometry3<f32>,
    ) -> Result<(), SimError> {
        match self.stereo.as_mut() {
            Some(stereo) => {
                stereo
                    .render_depth(world, true_pose, &mut self.rng, &mut self.depth)
                    .map_err(SimError::Config)?;
            }
            None => cfg
                .camera
                .render(world, true_pose, &mut self.rng, &mut self.depth),
        }
        cfg.faults
            .corrupt_depth(&cfg.camera, &mut self.sensor_rng, &mut self.depth);
        Ok(())
    }
}

/// The buffers of the noise-free reference map (one voxel's worth when the run keeps none).
struct ReferenceBuffers {
    log_odds: Vec<i8>,
    stamps: Vec<u32>,
}

impl ReferenceBuffers {
    fn new(geometry: &MapGeometry, kept: bool) -> Self {
        let dims = geometry.dims();
        Self {
            log_odds: vec![0i8; if kept { dims.len() } else { 1 }],
            stamps: vec![0u32; map::touched_words(&dims).max(1)],
        }
    }
}

/// The noise-free map of the same run, for the accuracy of maps made with imperfect sensing,
/// and where its differences go (`--map-errors`).
struct Reference<'b> {
    map: Option<VoxelMap<'b>>,
    camera: DepthCamera,
    integration: harmonic_core::integrate::IntegrationParams,
    stencil: harmonic_core::domain::InflationStencil,
    depth: Vec<u16>,
    errors: Option<(std::path::PathBuf, std::io::BufWriter<std::fs::File>)>,
}

impl<'b> Reference<'b> {
    fn new(
        cfg: &SimConfig,
        geometry: &MapGeometry,
        buffers: &'b mut ReferenceBuffers,
        kept: bool,
    ) -> Result<Self, SimError> {
        // Opened before the flight, so a path that cannot be written fails at once.
        let errors = match &cfg.map_errors {
            Some(_) if !kept => {
                return Err(SimError::MapErrors(
                    "it compares the map with the noise-free map of the same run, which only a run \
                     with imperfect sensing keeps: give --noise, --depth-from stereo or --drift"
                        .into(),
                ))
            }
            Some(path) => {
                let err = |e| map_errors_io(path, e);
                if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
                    std::fs::create_dir_all(dir).map_err(err)?;
                }
                let file = std::fs::File::create(path).map_err(err)?;
                Some((path.clone(), std::io::BufWriter::new(file)))
            }
            None => None,
        };
        let config_err = |e| SimError::Config(format!("{e:?}"));
        let stencil =
            harmonic_core::domain::InflationStencil::new(cfg.explorer.vehicle_radius, geometry.resolution())
                .map_err(config_err)?;
        let map = if kept {
            let map = VoxelMap::new(
                *geometry,
                cfg.explorer.log_odds,
                &mut buffers.log_odds,
                &mut buffers.stamps,
            )
            .map_err(|e| SimError::Config(format!("{e:?}")))?;
            Some(map)
        } else {
            None
        };
        Ok(Self {
            map,
            camera: DepthCamera {
                noise: None,
                outliers: 0.0,
                textureless: false,
                ..cfg.camera
            },
            integration: harmonic_core::integrate::IntegrationParams {
                max_range: cfg.camera.max_range,
                depth_noise_per_m: 0.0,
                ..cfg.explorer.integration
            },
            stencil,
            depth: Vec::new(),
            errors,
        })
    }

    /// Integrates the same view, noise-free, at the true pose.
    fn integrate(&mut self, world: &World, true_pose: &nalgebra::Isometry3<f32>, rng: &mut ChaCha8Rng) {
        let Some(map) = self.map.as_mut() else {
            return;
        };
        self.camera.render(world, true_pose, rng, &mut self.depth);
        if let Ok(frame) = DepthFrame::new(self.camera.intrinsics, &self.depth) {
            let _ = harmonic_core::integrate::integrate(map, &frame, true_pose, &self.integration);
        }
    }

    /// Marks the vehicle's body free, as the planner does at a plan.
    fn mark_body(&mut self, position: &Point3<f32>) {
        if let Some(map) = self.map.as_mut() {
            harmonic_core::domain::mark_body(map, &self.stencil, position);
        }
    }

    /// Writes where `planned` differs from the reference, if asked to.
    fn write_errors(&mut self, planned: &VoxelMap<'_>) -> Result<(), SimError> {
        let (Some((path, out)), Some(map)) = (self.errors.as_mut(), self.map.as_ref()) else {
            return Ok(());
        };
        use std::io::Write;
        crate::sensors::sensing::write_map_errors(planned, map, out)
            .and_then(|_| out.flush())
            .map_err(|e| map_errors_io(path, e))
    }
}

/// What one step decided before it flies: the plan (or none), from which pose, and why.
struct Decision {
    /// What the mission did with the fresh map; `None` without one.
    step: Option<Step>,
    position: Point3<f32>,
    yaw: f32,
    /// The status before the plan.
    before: harmonic_core::explore::Status,
}

/// One exploration in flight: the world, the planner, the links and the vehicle, and the
/// step's bookkeeping. [`Run::step`] is one capture, plan and flight.
struct Run<'a> {
    scenario: &'a Scenario,
    cfg: &'a SimConfig,
    planner: &'a mut (dyn Planner + 'a),
    truth: GroundTruth,
    rig: Rig<'a>,
    vehicle: Vehicle,
    track: Track<'a>,
    sensing: Sensing,
    reference: Reference<'a>,
    clock: HostClock,
    /// The mission's rules (look-around, exploration, the way home), the companion's; home is
    /// the start, in the frame the core plans in.
    mission: Mission,
    /// Distance flown before the next scan: the receding horizon, or the whole path.
    budget: f32,
    steps: Vec<StepRecord>,
    consecutive_holds: u32,
    steps_without_frame: u32,
    termination: String,
    taken: u32,
    return_start: Option<ReturnStart>,
    return_end: Option<String>,
    /// Each frame's timing, by frame id (= step), until it arrives.
    timings: std::collections::BTreeMap<u32, FrameTiming>,
}

impl<'a> Run<'a> {
    /// Opens the MAVLink link, puts the vehicle at the start (or where a remote autopilot says
    /// it is) and announces the start.
    fn start(
        scenario: &'a Scenario,
        cfg: &'a SimConfig,
        planner: &'a mut (dyn Planner + 'a),
        link: DepthLink<'a>,
        sensing: Sensing,
        reference: Reference<'a>,
    ) -> Result<Self, SimError> {
        let geometry = *planner.map().geometry();
        let world = &scenario.world;
        let mav = cfg
            .mavlink
            .as_ref()
            .map(MavlinkLink::open)
            .transpose()
            .map_err(SimError::Mavlink)?;
        let remote = mav.as_ref().is_some_and(MavlinkLink::is_remote);
        let mut rig = Rig {
            link,
            mav,
            t_s: 0.0,
            dt: f64::from(cfg.dt),
            wall: remote.then(Instant::now),
            faults: cfg.faults,
            truth: std::collections::VecDeque::new(),
        };
        let mut vehicle = Vehicle {
            position: scenario.start_position,
            yaw: scenario.start_yaw,
        };
        let mut track = Track::start(world, &vehicle.position, cfg.body_radius);
        rig.link.tick(0.0).map_err(SimError::Link)?;
        if let Some(m) = rig.mav.as_mut() {
            let _ = m.bridge.exploration_started();
        }
        rig.exchange(&mut vehicle, 0.0, 0.0)?;
        if remote {
            // The vehicle starts wherever the autopilot says.
            let (position, yaw) = rig.believed_pose(&mut vehicle, &mut track)?;
            vehicle.position = position;
            vehicle.yaw = yaw;
            track = Track::start(world, &vehicle.position, cfg.body_radius);
        }
        Ok(Self {
            scenario,
            cfg,
            truth: GroundTruth::new(world, &geometry, &scenario.start_position),
            planner,
            rig,
            mission: Mission::new(cfg.look_around, cfg.return_home).with_home(vehicle.position),
            vehicle,
            track,
            sensing,
            reference,
            clock: HostClock::new(),
            budget: if cfg.follow_full_path {
                f32::INFINITY
            } else {
                cfg.replan_distance
            },
            steps: Vec::new(),
            consecutive_holds: 0,
            steps_without_frame: 0,
            termination: String::from("scan_limit"),
            taken: 0,
            return_start: None,
            return_end: None,
            timings: std::collections::BTreeMap::new(),
        })
    }

    /// One step: capture a frame and send it over the depth link, integrate what arrived,
    /// plan, record, fly. False once the run is over.
    fn step(
        &mut self,
        step: u32,
        progress: &mut impl FnMut(&StepRecord),
        observe: &mut impl FnMut(&StepView<'_>),
    ) -> Result<bool, SimError> {
        // An operator's abort ends the run where the vehicle holds.
        if self
            .rig
            .mav
            .as_ref()
            .is_some_and(|m| m.bridge.operator_state() == OperatorState::Aborted)
        {
            self.termination = "aborted".into();
            return Ok(false);
        }
        if step == self.cfg.max_scans && self.return_start.is_some() {
            self.return_end = Some("scan_limit".into());
        }
        self.taken = step;
        let true_pose = self.send_frame(step)?;
        let t0 = Instant::now();
        let frames = self.integrate_arrived(&true_pose)?;
        let integrate_ms = t0.elapsed().as_secs_f64() * 1e3;
        let integrated = frames.len() as u32;
        let decision = self.decide(step, integrated)?;
        let record = self.record(step, &decision, integrated, integrate_ms)?;
        progress(&record);
        observe(&StepView {
            step,
            vehicle: (self.vehicle.position, self.vehicle.yaw),
            planner: &*self.planner,
            record: Some(&record),
            frames: &frames,
            planned_at: matches!(decision.step, Some(Step::Plan { .. })).then_some(decision.position),
            finished: false,
        });
        self.steps.push(record);
        self.act(step, decision)
    }

    /// Captures the frame's poses, renders it and sends it over the depth link, the vehicle
    /// hovering (or following the autopilot) while it is on the wire, then asks for what is
    /// missing while rounds are left. The camera's true pose.
    fn send_frame(&mut self, step: u32) -> Result<nalgebra::Isometry3<f32>, SimError> {
        // The camera sees the world from where the vehicle truly is at the frame's instant; the
        // frame is stamped with the pose the core believes for that instant.
        let capture = self.rig.capture(&mut self.vehicle, self.cfg, &mut self.track)?;
        let (position, yaw) = match &self.sensing.drift {
            Some(d) => d.believed(&capture.believed.0, capture.believed.1),
            None => capture.believed,
        };
        let true_pose = forward_camera_pose(&capture.truth.0, capture.truth.1);
        if let Some(timing) = capture.timing {
            self.timings.insert(step, timing);
        }
        self.sensing.render(self.cfg, &self.scenario.world, &true_pose)?;
        let frame = DepthFrame::new(self.cfg.camera.intrinsics, &self.sensing.depth)
            .map_err(|e| SimError::Config(format!("camera frame: {e:?}")))?;
        self.rig
            .link
            .send_image(step, &frame, &forward_camera_pose(&position, yaw))
            .map_err(SimError::Link)?;
        self.rig
            .wait_for_link(&mut self.vehicle, self.cfg, &mut self.track)?;
        // Selective retransmission: ask for what is missing while rounds are left, then take
        // the image with the rows that came.
        while self.rig.link.request_missing(step).map_err(SimError::Link)? {
            self.rig
                .wait_for_link(&mut self.vehicle, self.cfg, &mut self.track)?;
        }
        self.rig.link.finish_frame();
        Ok(true_pose)
    }

    /// Core side: integrates whatever arrived, whole or with rows missing; the frames
    /// integrated. The noise-free reference integrates the same view.
    fn integrate_arrived(
        &mut self,
        true_pose: &nalgebra::Isometry3<f32>,
    ) -> Result<Vec<IntegratedFrame>, SimError> {
        let mut frames = Vec::new();
        for arrived in self.rig.link.take_arrived() {
            let Some(frame) = arrived.frame() else {
                continue;
            };
            let timing = self.timings.remove(&arrived.frame_id);
            match self
                .planner
                .integrate(&frame, &arrived.camera_pose, timing.as_ref())
            {
                Ok(()) => {
                    self.rig.link.note_integrated(&arrived);
                    frames.push(IntegratedFrame {
                        depth_mm: frame.depth_mm().to_vec(),
                        intrinsics: *frame.intrinsics(),
                        camera_pose: arrived.camera_pose,
                        true_pose: *true_pose,
                        time_s: self.rig.t_s,
                    });
                }
                // Refused and counted by the core; over MAVLink the vehicle holds and the fault
                // goes out as a STATUSTEXT.
                Err(fault) => {
                    if let Some(m) = self.rig.mav.as_mut() {
                        harmonic_core::companion::steer(&mut m.bridge, &PlanOutcome::Hold(fault));
                    }
                }
            }
        }
        if !frames.is_empty() {
            self.reference
                .integrate(&self.scenario.world, true_pose, &mut self.sensing.rng);
        }
        Ok(frames)
    }

    /// Plans from where the vehicle is now (it may have drifted while the frame was sent) —
    /// or turns to look around, or holds on the operator's word, or has nothing new to plan
    /// from.
    fn decide(&mut self, step: u32, integrated: u32) -> Result<Decision, SimError> {
        let (position, yaw) = self.rig.believed_pose(&mut self.vehicle, &mut self.track)?;
        let (position, yaw) = match &self.sensing.drift {
            Some(d) => d.believed(&position, yaw),
            None => (position, yaw),
        };
        if integrated > 0 {
            if let Some(d) = self.sensing.drift.as_mut() {
                d.keyframe(&position);
            }
        }
        let before = *self.planner.status();
        // Without MAVLink there is no operator: exploring.
        let operator = self
            .rig
            .mav
            .as_ref()
            .map_or(OperatorState::Exploring, |m| m.bridge.operator_state());
        // The way home: after a complete exploration (`return_home`), or on the operator's word.
        if self.mission.going_home(operator) && self.return_start.is_none() {
            self.return_start = Some(ReturnStart {
                distance: self.track.distance,
                frames: before.frames,
                taken: step - 1,
                t_s: self.rig.t_s,
                status: before,
                coverage: self.truth.coverage(self.planner.map()),
                after_complete: false,
            });
        }
        let step = if integrated > 0 {
            self.steps_without_frame = 0;
            let step = self
                .mission
                .step(self.planner, operator, position, yaw, &mut self.clock);
            if matches!(step, Step::Plan { .. }) {
                self.reference.mark_body(&self.vehicle.position);
            }
            Some(step)
        } else {
            self.steps_without_frame += 1;
            None
        };
        Ok(Decision {
            step,
            position,
            yaw,
            before,
        })
    }

    /// The step's record (and, with `--dump-problem`, its problem written out).
    fn record(
        &mut self,
        step: u32,
        d: &Decision,
        integrated: u32,
        integrate_ms: f64,
    ) -> Result<StepRecord, SimError> {
        let status = *self.planner.status();
        let kept = status.plans_kept > d.before.plans_kept;
        let turned = status.arrival_looks > d.before.arrival_looks;
        let outcome = match d.step {
            Some(Step::Plan { outcome, .. }) => Some(outcome),
            _ => None,
        };
        if let (Some(dir), Some(_), false) = (&self.cfg.dump_problem, &outcome, kept || turned) {
            dump_problem(dir, step, &*self.planner, &d.position, self.cfg)?;
        }
        let label = match (d.step, outcome) {
            (Some(Step::Look(_)), _) => "look_around".to_string(),
            (Some(Step::Held(s)), _) => format!("operator:{}", s.name()),
            (_, None) => "no_frame".to_string(),
            (_, Some(PlanOutcome::Goal(g))) if g.escape => "escape".to_string(),
            (_, Some(PlanOutcome::Goal(_))) if kept => "kept".to_string(),
            (_, Some(PlanOutcome::Goal(_))) if turned => "arrival_look".to_string(),
            (_, Some(PlanOutcome::Goal(_))) => "goal".to_string(),
            (_, Some(PlanOutcome::Complete)) => "complete".to_string(),
            (_, Some(PlanOutcome::Hold(f))) => format!("hold:{f:?}"),
        };
        let planned = outcome.is_some();
        let phase_ms = |ticks: u64| if planned { ms(ticks) } else { 0.0 };
        Ok(StepRecord {
            step,
            position: d.position.coords.into(),
            yaw: d.yaw,
            outcome: label,
            frames_integrated: integrated,
            frontier: status.domain.frontier,
            unknowns: status.domain.interior,
            coverage_free: self.truth.coverage(self.planner.map()).free,
            integrate_ms,
            domain_ms: phase_ms(status.phase_ticks.domain),
            solve_ms: phase_ms(status.phase_ticks.solve),
            streamline_ms: phase_ms(status.phase_ticks.streamline),
            solves: Some(status.solves.saturating_sub(d.before.solves)),
            solves_in_boxes: Some(status.local_solves.saturating_sub(d.before.local_solves)),
            solver_iterations: status.solve.iterations,
            solver_residual: status.solve.residual,
            solver_updates: status.solve.cell_updates,
            streamline_m: status.streamline.map(|s| s.length).unwrap_or(0.0),
            path_length_m: self.track.distance,
            goal: match outcome {
                Some(PlanOutcome::Goal(g)) => Some(g.position.coords.into()),
                _ => None,
            },
            seals: status.errors.seals,
        })
    }

    /// Acts on the decision: a look-around turn, a goal flown, completion (and the way home),
    /// a hold counted. False once the run is over.
    fn act(&mut self, step: u32, d: Decision) -> Result<bool, SimError> {
        let (outcome, home) = match d.step {
            None if self.steps_without_frame >= LINK_DEAD_STEPS => {
                self.termination = "stuck:link".into();
                return Ok(false);
            }
            None | Some(Step::Held(_)) => return Ok(true),
            Some(Step::Look(turn)) => {
                // A turn on the spot: over MAVLink a setpoint where the vehicle is believed to
                // be, directly no waypoint at all; the believed frame's yaw either way.
                let (vehicle, track) = (&mut self.vehicle, &mut self.track);
                if self.rig.mav.is_some() {
                    let at = [d.position];
                    self.rig
                        .fly_mavlink(vehicle, &at, &turn, self.budget, self.cfg, track)?;
                } else {
                    self.rig
                        .fly_direct(vehicle, &[], &turn, self.budget, self.cfg, track)?;
                }
                return Ok(true);
            }
            Some(Step::Plan { outcome, home }) => (outcome, home),
        };
        let after = self.mission.after(&outcome, home);
        let now = self.rig.now_ms();
        if let Some(m) = self.rig.mav.as_mut() {
            match after {
                // Home again: a hold, announced as such (not as a complete exploration).
                After::Home => m.bridge.arrived_home(),
                _ => harmonic_core::companion::steer(&mut m.bridge, &outcome),
            }
            if !matches!(outcome, PlanOutcome::Goal(_)) {
                // The hold setpoint and any STATUSTEXT go out now.
                m.push(now).map_err(SimError::Mavlink)?;
            }
        }
        match (after, outcome) {
            (After::Home, _) => {
                self.return_end = Some("home".into());
                Ok(false)
            }
            (After::Returning, _) => {
                // Explored: the numbers so far are the exploration's; now fly home.
                let status = *self.planner.status();
                self.return_start = Some(ReturnStart {
                    distance: self.track.distance,
                    frames: status.frames,
                    taken: step,
                    t_s: self.rig.t_s,
                    status,
                    coverage: self.truth.coverage(self.planner.map()),
                    after_complete: true,
                });
                if let Some(m) = self.rig.mav.as_mut() {
                    m.bridge.return_home();
                    m.push(now).map_err(SimError::Mavlink)?;
                }
                Ok(true)
            }
            (After::Done, _) | (After::Continue, PlanOutcome::Complete) => {
                self.termination = "complete".into();
                Ok(false)
            }
            (After::Continue, PlanOutcome::Hold(fault)) => {
                self.consecutive_holds += 1;
                if self.consecutive_holds < 3 {
                    return Ok(true);
                }
                self.termination = format!("stuck:{fault:?}");
                if home {
                    self.return_end = Some(self.termination.clone());
                }
                Ok(false)
            }
            (_, PlanOutcome::Goal(goal)) => {
                self.consecutive_holds = 0;
                let waypoints = self.planner.waypoints().to_vec();
                self.fly(&waypoints, &goal)?;
                Ok(true)
            }
        }
    }

    /// Flies `waypoints` to `goal` for at most the budget: over MAVLink, or directly. With
    /// drift the vehicle flies the plan in its believed frame: in the true world it moves by the
    /// believed displacement.
    fn fly(&mut self, waypoints: &[Point3<f32>], goal: &Goal) -> Result<(), SimError> {
        let mut waypoints = waypoints.to_vec();
        let mut goal = *goal;
        if let Some(d) = &self.sensing.drift {
            for w in waypoints.iter_mut() {
                *w = d.to_true(w);
            }
            goal.position = d.to_true(&goal.position);
            goal.yaw = d.to_true_yaw(goal.yaw);
        }
        let (vehicle, track) = (&mut self.vehicle, &mut self.track);
        if self.rig.mav.is_some() {
            self.rig
                .fly_mavlink(vehicle, &waypoints, &goal, self.budget, self.cfg, track)
        } else {
            self.rig
                .fly_direct(vehicle, &waypoints, &goal, self.budget, self.cfg, track)
        }
    }

    /// The end: what is still on the wire arrives, the MAVLink log closes, `observe` sees the
    /// final map, and the report adds it all up.
    fn finish(mut self, wall: Instant, observe: &mut impl FnMut(&StepView<'_>)) -> Result<Report, SimError> {
        // What is still travelling through an outside wire arrives before the counts are taken.
        self.rig.link.settle().map_err(SimError::Link)?;
        let now = self.rig.now_ms();
        if let Some(m) = self.rig.mav.as_mut() {
            // Let the last setpoint and STATUSTEXT out, and close the log.
            m.push(now).map_err(SimError::Mavlink)?;
            m.finish().map_err(SimError::Mavlink)?;
        }
        observe(&StepView {
            step: 0,
            vehicle: (self.vehicle.position, self.vehicle.yaw),
            planner: &*self.planner,
            record: None,
            frames: &[],
            planned_at: None,
            finished: true,
        });
        self.reference.write_errors(self.planner.map())?;
        Ok(self.report(wall))
    }

    /// The report: with a way home flown, the run's numbers are the exploration's, up to where
    /// the way home began.
    fn report(self, wall: Instant) -> Report {
        let planner = &*self.planner;
        let (status, coverage, explored_path, explored_steps) = match &self.return_start {
            Some(r) => (r.status, r.coverage, r.distance, r.taken),
            None => (
                *planner.status(),
                self.truth.coverage(planner.map()),
                self.track.distance,
                self.taken,
            ),
        };
        let return_home = self.return_start.as_ref().map(|r| ReturnHome {
            termination: self
                .return_end
                .clone()
                .unwrap_or_else(|| self.termination.clone()),
            path_length_m: self.track.distance - r.distance,
            scans: planner.status().frames.saturating_sub(r.frames),
            distance_to_home_m: self
                .mission
                .home()
                .map_or(f64::NAN, |home| f64::from((self.vehicle.position - home).norm())),
            time_s: self.rig.t_s - r.t_s,
        });
        let termination = match (&self.return_start, &return_home) {
            (Some(r), _) if r.after_complete => "complete".into(),
            (Some(_), Some(back)) => back.termination.clone(),
            _ => self.termination.clone(),
        };
        let timing = Timing::of_steps(&self.steps);
        let geometry = *planner.map().geometry();
        let dims = geometry.dims();
        Report {
            scenario: self.scenario.world.name.clone(),
            planner: planner.kind().name().into(),
            solver: solver_name(planner.kind(), self.cfg.explorer.solver).into(),
            termination,
            coverage_free: coverage.free,
            coverage_surface: coverage.surface,
            free_marked_occupied: coverage.free_marked_occupied,
            coverage_observed: coverage.observed,
            path_length_m: explored_path,
            scans: status.frames,
            steps_taken: explored_steps,
            return_home,
            collisions: self.track.contact.collisions.len() as u32,
            min_clearance_m: self.track.contact.closest.0,
            min_clearance_at: self.track.contact.closest.1,
            collision_points: self.track.contact.collisions,
            integration_ops: status.integration_ops,
            planning_ops: status.planning_ops,
            local_solves: [status.local_solves, status.local_given_up],
            flight_time_s: self.rig.t_s,
            wall_time_s: wall.elapsed().as_secs_f64(),
            explorer_bytes: None,
            grid: [dims.nx(), dims.ny(), dims.nz()],
            resolution: geometry.resolution(),
            grid_origin: geometry.origin().coords.into(),
            reachable_free_voxels: self.truth.reachable_free(),
            sealed_voxels: status.map.sealed,
            unreachable_frontier_voxels: (status.termination
                == harmonic_core::explore::Termination::Complete)
                .then_some(status.unreachable_frontier),
            timing,
            errors: status.errors,
            link: self.rig.link.report(),
            mavlink: self.rig.mav.as_ref().map(MavlinkLink::report),
            pil: None,
            map_accuracy: self
                .reference
                .map
                .as_ref()
                .map(|r| crate::sensors::sensing::accuracy(planner.map(), r)),
            final_drift: self.sensing.drift.as_ref().map(|d| {
                let (e, y) = d.error_at(&self.vehicle.position);
                [e, y]
            }),
            stereo: self.sensing.stereo.as_ref().map(StereoDepth::report),
            trajectory: self.track.path,
            steps: self.steps,
        }
    }
}

/// The solver a report names for a planner.
fn solver_name(kind: PlannerKind, solver: SolverKind) -> &'static str {
    match (kind, solver) {
        (k, _) if !k.is_harmonic() => "none",
        (PlannerKind::HarmonicGs, _) | (_, SolverKind::GaussSeidel) => "gs",
        (PlannerKind::HarmonicThesis, _) | (_, SolverKind::ThesisJacobi) => "thesis-jacobi",
        (_, SolverKind::Multigrid) => "mg",
        (_, SolverKind::Flat) => "flat",
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The look-around turns the vehicle on the spot, whatever the believed pose: with a
    /// drifting estimate the turn must not fly the vehicle to where it believes it is.
    #[test]
    fn the_look_around_turns_on_the_spot_under_drift() {
        let scenario = Scenario::builtin("apartment").expect("built-in");
        let cfg = SimConfig {
            max_scans: 5,
            drift: Some(DriftConfig {
                sigma_position_m: 0.1,
                sigma_yaw_rad: 0.015,
            }),
            ..SimConfig::default()
        };
        let r = run(&scenario, &cfg, |_| {}).expect("run starts");
        let looks = r.steps.iter().filter(|s| s.outcome == "look_around").count();
        assert_eq!(looks, cfg.look_around as usize - 1, "{:?}", r.steps);
        let after = &r.steps[looks];
        assert_eq!(after.path_length_m, 0.0, "the turns moved the vehicle");
        assert!(
            r.final_drift.is_some_and(|[e, _]| e > 0.0),
            "the estimate drifted"
        );
    }

    /// A run reports each step's phase, its planner and the solver by name.
    #[test]
    fn solvers_are_named_by_planner_and_kind() {
        assert_eq!(
            solver_name(PlannerKind::ClosestFrontier, SolverKind::Multigrid),
            "none"
        );
        assert_eq!(solver_name(PlannerKind::HarmonicGs, SolverKind::Multigrid), "gs");
        assert_eq!(
            solver_name(PlannerKind::HarmonicThesis, SolverKind::Multigrid),
            "thesis-jacobi"
        );
        assert_eq!(solver_name(PlannerKind::Harmonic, SolverKind::Multigrid), "mg");
        assert_eq!(solver_name(PlannerKind::Harmonic, SolverKind::Flat), "flat");
    }
}
