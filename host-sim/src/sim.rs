//! The closed loop: render a depth frame, hand it to the core, fly the core's plan, repeat.
//!
//! The simulator never plans for the core. Each step it
//!
//! 1. renders the depth camera at the vehicle's true pose and passes the frame and camera pose to
//!    [`Explorer::integrate`];
//! 2. asks [`Explorer::plan`] where to go;
//! 3. flies the returned waypoints with simple multirotor kinematics (speed and yaw-rate
//!    limits, fixed time step), for at most `replan_distance` metres (receding horizon) or the
//!    whole path with `follow_full_path`, turning to the goal yaw on arrival;
//! 4. checks the vehicle's body sphere against the true world at every time step and counts
//!    collisions.
//!
//! It stops when the core reports `Complete`, after three consecutive `Hold`s (the fault is the
//! termination reason), or at the scan limit.
//!
//! With [`SimConfig::mavlink`] the vehicle is not handed the waypoints. The core's
//! [`Bridge`] streams them as MAVLink setpoints (the next waypoint along the plan, advancing
//! within 0.1 m) over an in-process byte pipe to a [`FlightEmulator`]; the vehicle flies
//! towards the emulator's current setpoint, and the emulator streams the vehicle's pose back
//! over a second pipe into the bridge. The explorer plans from, and the depth frames are
//! stamped with, the pose the bridge reports — not the simulator's ground truth. The link's
//! counters end up in [`Report::mavlink`].

use std::time::Instant;

use harmonic_core::camera::{DepthFrame, Intrinsics};
use harmonic_core::domain::Label;
use harmonic_core::explore::{
    forward_camera_pose, Clock, ErrorCounters, Explorer, ExplorerConfig, ExplorerStorage, Goal, PlanOutcome,
    SolverKind,
};
use harmonic_core::link::{self, DepthReceiver, LinkCounters, LinkEncoder, LinkEvent};
use harmonic_core::map::{self, Dims, MapGeometry};
use harmonic_core::mavlink::{
    encode_v2, Bridge, BridgeConfig, BridgeCounters, DecoderCounters, MavlinkDecoder, MAX_FRAME_LEN,
};
use harmonic_core::solve::multigrid;
use nalgebra::{Isometry3, Point3};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::Serialize;

use crate::camera::DepthCamera;
use crate::flight::{FlightCounters, FlightEmulator};
use crate::metrics::{Coverage, GroundTruth};
use crate::scenario::Scenario;

/// Simulation settings.
#[derive(Debug, Clone)]
pub struct SimConfig {
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
    /// Stop after this many scans.
    pub max_scans: u32,
    /// Seed for sensor noise.
    pub seed: u64,
    /// Write each full replan's problem (`step_NNNN.npy` labels and `step_NNNN.json` with the
    /// source voxel and the command that re-solves it) into this directory.
    pub dump_problem: Option<std::path::PathBuf>,
    /// Fly over MAVLink: setpoints from the core's bridge to an emulated flight stack, the
    /// pose back from it (see the [module documentation](self)). Default false.
    pub mavlink: bool,
}

impl Default for SimConfig {
    fn default() -> Self {
        Self {
            explorer: ExplorerConfig::default(),
            camera: DepthCamera::default_thesis(),
            body_radius: 0.15,
            max_speed: 1.0,
            max_yaw_rate: 90f32.to_radians(),
            dt: 0.05,
            replan_distance: 1.0,
            follow_full_path: false,
            max_scans: 3000,
            seed: 1,
            dump_problem: None,
            mavlink: false,
        }
    }
}

/// One scan-and-plan step.
#[derive(Debug, Clone, Serialize)]
pub struct StepRecord {
    /// Step number (= scans so far).
    pub step: u32,
    /// Vehicle position at the scan, map frame.
    pub position: [f32; 3],
    /// Vehicle yaw at the scan, radians.
    pub yaw: f32,
    /// "goal" (a new plan), "kept" (the committed goal still stands; nothing was solved),
    /// "escape", "complete" or "hold:FAULT".
    pub outcome: String,
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

/// Everything a run produced; serialised as `report.json`.
#[derive(Debug, Clone, Serialize)]
pub struct Report {
    /// Scenario name.
    pub scenario: String,
    /// Planner name.
    pub planner: String,
    /// Solver name.
    pub solver: String,
    /// "complete", "scan_limit" or "stuck:FAULT".
    pub termination: String,
    /// Free-space coverage at the end.
    pub coverage_free: f64,
    /// Surface coverage at the end.
    pub coverage_surface: f64,
    /// Reachable free voxels the map holds as occupied.
    pub free_marked_occupied: usize,
    /// Path flown, metres.
    pub path_length_m: f64,
    /// Depth frames integrated.
    pub scans: u32,
    /// Collision events (body sphere entering an obstacle).
    pub collisions: u32,
    /// Where each collision began, map frame.
    pub collision_points: Vec<[f32; 3]>,
    /// Voxel updates by integration.
    pub integration_ops: u64,
    /// Solver cell updates.
    pub planning_ops: u64,
    /// Simulated flight time, s.
    pub flight_time_s: f64,
    /// Wall-clock time of the run, s.
    pub wall_time_s: f64,
    /// Grid size.
    pub grid: [usize; 3],
    /// Voxel edge, metres.
    pub resolution: f32,
    /// Reachable free voxels in the ground truth.
    pub reachable_free_voxels: usize,
    /// Unknown voxels sealed as unobservable at the end.
    pub sealed_voxels: u32,
    /// Per-phase timing.
    pub timing: Timing,
    /// Fault counters.
    pub errors: ErrorCounters,
    /// Depth-link counters (frames decoded, errors by kind).
    pub link: LinkCounters,
    /// MAVLink counters; `None` unless the run flew over MAVLink ([`SimConfig::mavlink`]).
    pub mavlink: Option<MavlinkReport>,
    /// Processor-in-the-loop details; `None` unless the firmware flew ([`crate::pil`]).
    pub pil: Option<crate::pil::PilReport>,
    /// Per-step records.
    pub steps: Vec<StepRecord>,
}

/// What went over the MAVLink link of a [`SimConfig::mavlink`] run.
#[derive(Debug, Clone, Serialize)]
pub struct MavlinkReport {
    /// The core's bridge: messages sent and received, faults, stale-pose events.
    pub bridge: BridgeCounters,
    /// The bridge's decoder of the emulator's bytes.
    pub bridge_decoder: DecoderCounters,
    /// The flight-stack emulator: setpoints taken and rejected, setpoint gaps, poses sent.
    pub emulator: FlightCounters,
    /// The emulator's decoder of the bridge's bytes.
    pub emulator_decoder: DecoderCounters,
    /// STATUSTEXTs the emulator received, in order.
    pub status_texts: Vec<String>,
}

/// Errors that stop a run before it starts.
#[derive(Debug)]
pub enum SimError {
    /// The scenario's grid does not fit the core's limits.
    Grid(String),
    /// The core refused the configuration.
    Config(String),
    /// A problem dump could not be written.
    Dump(String),
}

impl std::fmt::Display for SimError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            SimError::Grid(s) => write!(f, "grid: {s}"),
            SimError::Config(s) => write!(f, "explorer configuration: {s}"),
            SimError::Dump(s) => write!(f, "--dump-problem: {s}"),
        }
    }
}

impl std::error::Error for SimError {}

/// Host-owned buffers for one explorer.
pub struct HostStorage {
    log_odds: Vec<i8>,
    touched: Vec<u32>,
    labels: Vec<Label>,
    phi: Vec<f32>,
    queue: Vec<u32>,
    coarse_values: Vec<f32>,
    coarse_labels: Vec<Label>,
    krylov: Vec<f32>,
}

impl HostStorage {
    /// Buffers for `dims`, with MGPCG storage.
    pub fn new(dims: &Dims) -> Self {
        let n = dims.len();
        let mg = multigrid::scratch_size(dims);
        Self {
            coarse_values: vec![0.0; mg.values],
            coarse_labels: vec![Label::Outside; mg.labels],
            krylov: vec![0.0; mg.krylov],
            log_odds: vec![0; n],
            touched: vec![0; map::touched_words(dims)],
            labels: vec![Label::Outside; n],
            phi: vec![0.0; n],
            queue: vec![0; 16 * 1024],
        }
    }
    /// Lends the buffers to an explorer.
    pub fn lend(&mut self) -> ExplorerStorage<'_> {
        ExplorerStorage {
            log_odds: &mut self.log_odds,
            touched: &mut self.touched,
            labels: &mut self.labels,
            phi: &mut self.phi,
            queue: &mut self.queue,
            coarse_values: &mut self.coarse_values,
            coarse_labels: &mut self.coarse_labels,
            krylov: &mut self.krylov,
        }
    }
}

/// The map geometry a scenario is explored on.
pub fn scenario_geometry(scenario: &Scenario) -> Result<MapGeometry, SimError> {
    let [nx, ny, nz] = scenario.grid_dims();
    let dims = Dims::new(nx, ny, nz).map_err(|e| SimError::Grid(format!("{nx}×{ny}×{nz}: {e:?}")))?;
    MapGeometry::new(dims, scenario.world.bounds.min, scenario.resolution)
        .map_err(|e| SimError::Grid(format!("{e:?}")))
}

/// Nanosecond host clock for the core's phase timing.
struct HostClock(Instant);

impl Clock for HostClock {
    fn ticks(&mut self) -> u64 {
        self.0.elapsed().as_nanos() as u64
    }
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

/// What one flight leg did.
#[derive(Debug, Clone, Default)]
pub(crate) struct Leg {
    pub(crate) distance: f64,
    pub(crate) time: f64,
    pub(crate) collisions: Vec<[f32; 3]>,
}

pub(crate) fn wrap_angle(a: f32) -> f32 {
    let mut a = a % std::f32::consts::TAU;
    if a > std::f32::consts::PI {
        a -= std::f32::consts::TAU;
    } else if a < -std::f32::consts::PI {
        a += std::f32::consts::TAU;
    }
    a
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

    /// Flies along `waypoints` for at most `budget` metres, then (if the end was reached) turns
    /// to the goal yaw.
    fn fly(
        &mut self,
        waypoints: &[Point3<f32>],
        goal: &Goal,
        budget: f32,
        cfg: &SimConfig,
        world: &crate::world::World,
    ) -> Leg {
        let mut leg = Leg::default();
        let step_len = cfg.max_speed * cfg.dt;
        let yaw_step = cfg.max_yaw_rate * cfg.dt;
        let mut watch = CollisionWatch::start(world, &self.position, cfg.body_radius);
        let mut travelled = 0.0f32;
        for w in waypoints.iter() {
            loop {
                let seg = w - self.position;
                let dist = seg.norm();
                if dist < 1e-5 {
                    break;
                }
                if travelled >= budget {
                    return leg;
                }
                if let Some(h) = travel_heading(&seg) {
                    self.slew_yaw(h, yaw_step);
                }
                let s = self.step_towards(w, step_len.min(budget - travelled));
                travelled += s;
                leg.distance += f64::from(s);
                leg.time += f64::from(cfg.dt);
                watch.check(world, &self.position, cfg.body_radius, &mut leg);
            }
        }
        // Arrived: look where the planner asked.
        for _ in 0..1000 {
            if self.slew_yaw(goal.yaw, yaw_step) {
                break;
            }
            leg.time += f64::from(cfg.dt);
        }
        leg
    }
}

/// Counts collision events: the body sphere *entering* an obstacle, not every step inside it.
pub(crate) struct CollisionWatch {
    colliding: bool,
}

impl CollisionWatch {
    pub(crate) fn start(world: &crate::world::World, p: &Point3<f32>, radius: f32) -> Self {
        Self {
            colliding: world.sphere_collides(p, radius),
        }
    }
    pub(crate) fn check(&mut self, world: &crate::world::World, p: &Point3<f32>, radius: f32, leg: &mut Leg) {
        let now = world.sphere_collides(p, radius);
        if now && !self.colliding {
            leg.collisions.push(p.coords.into());
        }
        self.colliding = now;
    }
}

/// Heading of travel along `seg`, unless it is mostly vertical (then the yaw is kept).
fn travel_heading(seg: &nalgebra::Vector3<f32>) -> Option<f32> {
    let horizontal = (seg.x * seg.x + seg.y * seg.y).sqrt();
    (horizontal > 0.2 * seg.norm()).then(|| seg.y.atan2(seg.x))
}

/// The MAVLink link of a [`SimConfig::mavlink`] run: the core's bridge on the companion side,
/// the flight-stack emulator on the autopilot side, and a byte pipe each way.
struct MavlinkLink {
    bridge: Bridge,
    decoder: MavlinkDecoder,
    emulator: FlightEmulator,
    /// Companion → autopilot bytes.
    down: Vec<u8>,
    /// Autopilot → companion bytes.
    up: Vec<u8>,
}

/// How close (metres) the estimated position must come to a waypoint before the next one is
/// streamed.
const WAYPOINT_ADVANCE_M: f32 = 0.1;

impl MavlinkLink {
    fn new() -> Result<Self, SimError> {
        let bridge = Bridge::new(BridgeConfig::default())
            .map_err(|e| SimError::Config(format!("mavlink bridge: {e:?}")))?;
        Ok(Self {
            bridge,
            decoder: MavlinkDecoder::new(),
            emulator: FlightEmulator::new(),
            down: Vec::new(),
            up: Vec::new(),
        })
    }

    /// Autopilot side: the emulator reports the vehicle's true pose (when due) and the bridge
    /// takes in those bytes.
    fn report_pose(&mut self, now_ms: u64, vehicle: &Vehicle) {
        self.emulator
            .poll(now_ms, &vehicle.position, vehicle.yaw, &mut self.up);
        let bridge = &mut self.bridge;
        self.decoder.push(&self.up, |header, message| {
            let _ = bridge.handle(now_ms, header, message);
        });
        self.up.clear();
    }

    /// Companion side: the bridge emits what is due and the emulator takes in those bytes.
    fn stream(&mut self, now_ms: u64) {
        let down = &mut self.down;
        self.bridge.poll(now_ms, |header, message| {
            let mut frame = [0u8; MAX_FRAME_LEN];
            if let Ok(n) = encode_v2(header, message, &mut frame) {
                down.extend_from_slice(frame.get(..n).unwrap_or(&[]));
            }
        });
        self.emulator.receive(now_ms, &self.down);
        self.down.clear();
    }

    /// One exchange both ways at `now_ms`.
    fn tick(&mut self, now_ms: u64, vehicle: &Vehicle) {
        self.report_pose(now_ms, vehicle);
        self.stream(now_ms);
    }

    /// The bridge's pose of the vehicle (map frame).
    fn pose(&self, now_ms: u64) -> Result<(Point3<f32>, f32), SimError> {
        self.bridge
            .pose(now_ms)
            .map(|p| (p.position, p.yaw))
            .map_err(|e| SimError::Config(format!("mavlink pose at {now_ms} ms: {e:?}")))
    }

    fn report(&self) -> MavlinkReport {
        MavlinkReport {
            bridge: *self.bridge.counters(),
            bridge_decoder: *self.decoder.counters(),
            emulator: *self.emulator.counters(),
            emulator_decoder: *self.emulator.decoder_counters(),
            status_texts: self.emulator.status_texts().to_vec(),
        }
    }
}

fn to_ms(time_s: f64) -> u64 {
    (time_s * 1e3).round() as u64
}

impl Vehicle {
    /// Flies one leg over MAVLink, starting at simulated time `start_s`: streams the next
    /// waypoint along `waypoints` as the setpoint (advancing when the bridge's pose is within
    /// [`WAYPOINT_ADVANCE_M`] of it), moves towards the emulator's setpoint at most `budget`
    /// metres, and on reaching the end turns to the goal yaw.
    #[allow(clippy::too_many_arguments)]
    fn fly_mavlink(
        &mut self,
        waypoints: &[Point3<f32>],
        goal: &Goal,
        budget: f32,
        cfg: &SimConfig,
        world: &crate::world::World,
        link: &mut MavlinkLink,
        start_s: f64,
    ) -> Result<Leg, SimError> {
        let mut leg = Leg::default();
        let step_len = cfg.max_speed * cfg.dt;
        let yaw_step = cfg.max_yaw_rate * cfg.dt;
        let mut watch = CollisionWatch::start(world, &self.position, cfg.body_radius);
        let mut travelled = 0.0f32;
        let mut next = 0usize;
        // Yaw of the current setpoint: along the segment towards the waypoint, as fixed when
        // the waypoint was taken (so the setpoint does not change every tick).
        let mut heading: Option<(usize, f32)> = None;
        let mut turning = false;
        // Generous: a leg is a few metres at most in receding-horizon mode.
        let max_ticks = 200_000usize;
        for _ in 0..max_ticks {
            let now = to_ms(start_s + leg.time);
            link.report_pose(now, self);
            let (position, yaw) = link.pose(now)?;
            while next + 1 < waypoints.len()
                && waypoints
                    .get(next)
                    .is_some_and(|w| (w - position).norm() < WAYPOINT_ADVANCE_M)
            {
                next += 1;
            }
            // No waypoints: stay and turn.
            let target = waypoints.get(next).copied().unwrap_or(position);
            if next + 1 >= waypoints.len() && (target - position).norm() < 1e-3 {
                turning = true;
            }
            if !turning && travelled >= budget {
                // End of the receding horizon: stop where the vehicle is.
                let _ = link.bridge.set_target(position, yaw);
                link.stream(now);
                return Ok(leg);
            }
            let target_yaw = if turning {
                goal.yaw
            } else {
                match heading {
                    Some((i, h)) if i == next => h,
                    _ => {
                        let h = travel_heading(&(target - position)).unwrap_or(yaw);
                        heading = Some((next, h));
                        h
                    }
                }
            };
            if turning && wrap_angle(goal.yaw - yaw).abs() < 1e-3 {
                break;
            }
            let _ = link.bridge.set_target(target, target_yaw);
            link.stream(now);

            // The flight stack flies its setpoint.
            let Some(setpoint) = link.emulator.setpoint() else {
                leg.time += f64::from(cfg.dt);
                continue;
            };
            let s = self.step_towards(&setpoint.position, step_len.min(budget - travelled));
            travelled += s;
            leg.distance += f64::from(s);
            self.slew_yaw(setpoint.yaw, yaw_step);
            leg.time += f64::from(cfg.dt);
            watch.check(world, &self.position, cfg.body_radius, &mut leg);
        }
        Ok(leg)
    }
}

/// Writes the labels and source of one planning step for `harmonic-sim solve`.
fn dump_problem(
    dir: &std::path::Path,
    step: u32,
    explorer: &Explorer<'_>,
    position: &Point3<f32>,
    cfg: &SimConfig,
) -> Result<(), SimError> {
    let err = |e: std::io::Error| SimError::Dump(format!("{}: {e}", dir.display()));
    std::fs::create_dir_all(dir).map_err(err)?;
    let map = explorer.map();
    let grid = crate::problem::labels_from_map(map);
    let labels_path = dir.join(format!("step_{step:04}.npy"));
    std::fs::write(&labels_path, crate::npy::write_u8(&grid)).map_err(err)?;
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

/// Decoder capacity of the simulated receiver: room for a chunk of [`LINK_ROWS_PER_CHUNK`] rows
/// of an image up to 400 px wide.
const LINK_DECODER_BYTES: usize = 8192;
/// Rows per depth chunk (a 100 px frame then costs 20261 bytes, 0.22 s at 921600 baud).
const LINK_ROWS_PER_CHUNK: u16 = 10;

/// The depth link as the simulator runs it: the camera-side encoder writes every frame and its
/// pose into an in-process byte pipe, and the core-side [`DepthReceiver`] decodes it, exactly
/// as bytes from a UART would be. A frame reaches the explorer only if it survives the wire.
struct DepthLink<'b> {
    encoder: LinkEncoder,
    receiver: DepthReceiver<'b, LINK_DECODER_BYTES>,
    rows_per_chunk: u16,
    scratch: Vec<u8>,
    pipe: Vec<u8>,
    pose_missing: u32,
}

impl<'b> DepthLink<'b> {
    fn new(intrinsics: &Intrinsics, buffer: &'b mut [u16]) -> Self {
        let width = intrinsics.width();
        // The largest chunk height whose frame fits the decoder.
        let rows = (1..=LINK_ROWS_PER_CHUNK)
            .rev()
            .find(|&r| link::max_depth_chunk_len(width, r) <= LINK_DECODER_BYTES)
            .unwrap_or(1);
        Self {
            encoder: LinkEncoder::new(),
            receiver: DepthReceiver::new(buffer),
            rows_per_chunk: rows,
            scratch: vec![0; link::max_depth_chunk_len(width, rows).max(link::max_encoded_len(64))],
            pipe: Vec::new(),
            pose_missing: 0,
        }
    }

    /// Camera side: encodes the frame's pose and the frame into the pipe.
    fn send(&mut self, frame_id: u32, frame: &DepthFrame<'_>, pose: &Isometry3<f32>) -> Result<(), SimError> {
        let wire = |e: link::LinkError| SimError::Config(format!("depth link encoder: {e:?}"));
        let pose = link::Pose::from_isometry(frame_id, pose)
            .map_err(|e| SimError::Config(format!("camera pose: {e:?}")))?;
        let n = self
            .encoder
            .encode(&link::Message::Pose(pose), &mut self.scratch)
            .map_err(wire)?;
        self.pipe.extend_from_slice(self.scratch.get(..n).unwrap_or(&[]));
        let pipe = &mut self.pipe;
        self.encoder
            .encode_depth_frame(frame_id, frame, self.rows_per_chunk, &mut self.scratch, |bytes| {
                pipe.extend_from_slice(bytes)
            })
            .map_err(wire)?;
        Ok(())
    }

    /// Core side: decodes everything in the pipe and hands each complete frame with its pose
    /// to `integrate`.
    fn receive(&mut self, mut integrate: impl FnMut(&DepthFrame<'_>, &Isometry3<f32>)) {
        let mut pose_missing = 0;
        self.receiver.feed(&self.pipe, |event| {
            if let LinkEvent::Depth { frame, pose, .. } = event {
                match pose {
                    Some(p) => integrate(&frame, &p.isometry()),
                    None => pose_missing += 1,
                }
            }
        });
        self.pose_missing += pose_missing;
        self.pipe.clear();
    }

    fn counters(&self) -> LinkCounters {
        let mut c = self.receiver.counters();
        c.depth_frames_dropped += self.pose_missing;
        c
    }
}

/// Runs one exploration of `scenario` to termination. `progress` is called after every step.
pub fn run(
    scenario: &Scenario,
    cfg: &SimConfig,
    mut progress: impl FnMut(&StepRecord),
) -> Result<Report, SimError> {
    let wall = Instant::now();
    let geometry = scenario_geometry(scenario)?;
    let truth = GroundTruth::new(&scenario.world, &geometry, &scenario.start_position);
    let mut storage = HostStorage::new(&geometry.dims());
    let mut explorer = Explorer::new(geometry, cfg.explorer, storage.lend())
        .map_err(|e| SimError::Config(format!("{e:?}")))?;
    let mut rng = ChaCha8Rng::seed_from_u64(cfg.seed);
    let mut vehicle = Vehicle {
        position: scenario.start_position,
        yaw: scenario.start_yaw,
    };
    let mut depth = Vec::new();
    let mut link_buffer = vec![0u16; cfg.camera.intrinsics.pixel_count()];
    let mut link = DepthLink::new(&cfg.camera.intrinsics, &mut link_buffer);
    let mut clock = HostClock(Instant::now());
    let mut steps = Vec::new();
    let (mut path, mut flight_time, mut collisions) = (0.0f64, 0.0f64, Vec::new());
    let mut consecutive_holds = 0u32;
    let mut termination = String::from("scan_limit");
    let budget = if cfg.follow_full_path {
        f32::INFINITY
    } else {
        cfg.replan_distance
    };
    let mut mav = if cfg.mavlink {
        let mut link = MavlinkLink::new()?;
        let _ = link.bridge.exploration_started();
        link.tick(0, &vehicle);
        Some(link)
    } else {
        None
    };

    for step in 1..=cfg.max_scans {
        // The pose the core believes: the simulator's truth, or over MAVLink what the flight
        // stack reported.
        let (position, yaw) = match &mav {
            Some(m) => m.pose(to_ms(flight_time))?,
            None => (vehicle.position, vehicle.yaw),
        };
        // The camera sees the world from where the vehicle truly is; the frame is stamped with
        // the believed pose.
        let true_pose = forward_camera_pose(&vehicle.position, vehicle.yaw);
        cfg.camera
            .render(&scenario.world, &true_pose, &mut rng, &mut depth);
        let pose = forward_camera_pose(&position, yaw);
        // Camera side: the frame and its pose go onto the wire.
        let frame = DepthFrame::new(cfg.camera.intrinsics, &depth)
            .map_err(|e| SimError::Config(format!("camera frame: {e:?}")))?;
        link.send(step, &frame, &pose)?;
        // Core side: decode, reassemble, integrate.
        let t0 = Instant::now();
        link.receive(|frame, camera_pose| {
            let _ = explorer.integrate(frame, camera_pose);
        });
        let integrate_ms = t0.elapsed().as_secs_f64() * 1e3;

        let kept_before = explorer.status().plans_kept;
        let outcome = explorer.plan_timed(&position, yaw, &mut clock);
        let status = *explorer.status();
        let kept = status.plans_kept > kept_before;
        if let (Some(dir), false) = (&cfg.dump_problem, kept) {
            dump_problem(dir, step, &explorer, &position, cfg)?;
        }
        let coverage = truth.coverage(explorer.map());
        let label = match outcome {
            PlanOutcome::Goal(g) if g.escape => "escape".to_string(),
            PlanOutcome::Goal(_) if kept => "kept".to_string(),
            PlanOutcome::Goal(_) => "goal".to_string(),
            PlanOutcome::Complete => "complete".to_string(),
            PlanOutcome::Hold(f) => format!("hold:{f:?}"),
        };
        let record = StepRecord {
            step,
            position: position.coords.into(),
            yaw,
            outcome: label,
            frontier: status.domain.frontier,
            unknowns: status.domain.interior,
            coverage_free: coverage.free,
            integrate_ms,
            domain_ms: ms(status.phase_ticks.domain),
            solve_ms: ms(status.phase_ticks.solve),
            streamline_ms: ms(status.phase_ticks.streamline),
            solver_iterations: status.solve.iterations,
            solver_residual: status.solve.residual,
            solver_updates: status.solve.cell_updates,
            streamline_m: status.streamline.map(|s| s.length).unwrap_or(0.0),
            path_length_m: path,
        };
        progress(&record);
        steps.push(record);
        if let Some(m) = mav.as_mut() {
            m.bridge.apply(&outcome);
            if !matches!(outcome, PlanOutcome::Goal(_)) {
                // The hold setpoint and any STATUSTEXT go out now.
                m.stream(to_ms(flight_time));
            }
        }

        match outcome {
            PlanOutcome::Complete => {
                termination = "complete".into();
                break;
            }
            PlanOutcome::Hold(fault) => {
                consecutive_holds += 1;
                if consecutive_holds >= 3 {
                    termination = format!("stuck:{fault:?}");
                    break;
                }
            }
            PlanOutcome::Goal(goal) => {
                consecutive_holds = 0;
                let waypoints: Vec<Point3<f32>> = explorer.waypoints().to_vec();
                let leg = match mav.as_mut() {
                    Some(m) => vehicle.fly_mavlink(
                        &waypoints,
                        &goal,
                        budget,
                        cfg,
                        &scenario.world,
                        m,
                        flight_time,
                    )?,
                    None => vehicle.fly(&waypoints, &goal, budget, cfg, &scenario.world),
                };
                path += leg.distance;
                flight_time += leg.time;
                collisions.extend(leg.collisions);
            }
        }
    }

    let status = *explorer.status();
    let coverage: Coverage = truth.coverage(explorer.map());
    let timing = Timing {
        integrate: TimeStat::of(steps.iter().map(|s| s.integrate_ms)),
        domain: TimeStat::of(steps.iter().map(|s| s.domain_ms)),
        solve: TimeStat::of(steps.iter().map(|s| s.solve_ms)),
        streamline: TimeStat::of(steps.iter().map(|s| s.streamline_ms)),
    };
    let dims = geometry.dims();
    Ok(Report {
        scenario: scenario.world.name.clone(),
        planner: "harmonic".into(),
        solver: match cfg.explorer.solver {
            SolverKind::Multigrid => "mg".into(),
            SolverKind::GaussSeidel => "gs".into(),
        },
        termination,
        coverage_free: coverage.free,
        coverage_surface: coverage.surface,
        free_marked_occupied: coverage.free_marked_occupied,
        path_length_m: path,
        scans: status.frames,
        collisions: collisions.len() as u32,
        collision_points: collisions,
        integration_ops: status.integration_ops,
        planning_ops: status.planning_ops,
        flight_time_s: flight_time,
        wall_time_s: wall.elapsed().as_secs_f64(),
        grid: [dims.nx(), dims.ny(), dims.nz()],
        resolution: geometry.resolution(),
        reachable_free_voxels: truth.reachable_free(),
        sealed_voxels: status.map.sealed,
        timing,
        errors: status.errors,
        link: link.counters(),
        mavlink: mav.as_ref().map(MavlinkLink::report),
        pil: None,
        steps,
    })
}
