//! `harmonic-sim explore`: its flags, the run (progress line, recording, map export, figures)
//! and the summary printed at the end.

use std::io::IsTerminal;
use std::path::PathBuf;
use std::str::FromStr;

use harmonic_core::explore::SolverKind;
use harmonic_sim::io::npy;
use harmonic_sim::link::depth_link::{LinkConfig, DEFAULT_ARQ_ROUNDS, DEFAULT_BAUD};
use harmonic_sim::link::fault::{FaultConfig, DEFAULT_BURST_LEN};
use harmonic_sim::link::transport::TransportSpec;
use harmonic_sim::planners::PlannerKind;
use harmonic_sim::run::record::{MapSettings, Recorder};
use harmonic_sim::run::sim::{self, Report, SimConfig, StepRecord, StepView};
use harmonic_sim::tools::batch;
use harmonic_sim::tools::figures::{self, SliceSnapshot};
use harmonic_sim::tools::quantile;
use harmonic_sim::vehicle::autopilot::{MavlinkConfig, MavlinkSpec};
use harmonic_sim::vehicle::flight::EmulatorTiming;
use harmonic_sim::world::scenario::Scenario;
use indicatif::{ProgressBar, ProgressStyle};

use super::parse::{self, parse_baud, parse_burst, parse_positive, parse_probability, OperatorScript};
use super::sim_args::{BodyArgs, FieldArgs, SensingArgs};

/// The flags of `explore`.
#[derive(clap::Args)]
pub struct ExploreArgs {
    /// A built-in scenario name (see `harmonic-sim scenarios`) or a path to a scenario .toml file.
    #[arg(long, default_value = "apartment")]
    scenario: String,
    /// Output directory for report.json (created if missing).
    #[arg(long, default_value = "out")]
    out: PathBuf,
    #[command(flatten)]
    sensing: SensingArgs,
    #[command(flatten)]
    field: FieldArgs,
    /// Random seed for sensor noise.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Start from the random free pose this seed draws instead of the scenario's start (bench
    /// run k is `--start-seed k --seed k`).
    #[arg(long)]
    start_seed: Option<u64>,
    #[command(flatten)]
    body: BodyArgs,
    /// Distance flown between scans (receding horizon), metres.
    #[arg(long, default_value_t = 1.0, value_parser = parse_positive)]
    replan_distance: f32,
    /// Fly every streamline to its end before the next scan (the paper's mode).
    #[arg(long)]
    follow_full_path: bool,
    /// Maximum speed, m/s.
    #[arg(long, default_value_t = 1.0, value_parser = parse_positive)]
    max_speed: f32,
    /// Maximum yaw rate, degrees per second.
    #[arg(long, default_value_t = 90.0, value_parser = parse_positive)]
    max_yaw_rate: f32,
    /// Stop after this many scans.
    #[arg(long, default_value_t = 3000)]
    max_scans: u32,
    /// Scans at evenly spaced headings, turning on the spot, before the first plan (0: plan
    /// after the first scan).
    #[arg(long, default_value_t = 4)]
    look_around: u32,
    /// Stay where the exploration ends instead of flying back to the start (by default the
    /// vehicle returns home through known free space after a complete exploration; the
    /// report's path and scans are the exploration's, the way home is reported apart).
    #[arg(long)]
    no_return_home: bool,
    /// Planner: `harmonic` (the core with its default field, frontier-sourced and screened, on
    /// multigrid; the default), `harmonic-laplace` (the core with the seed's Laplace field,
    /// vehicle φ = 1 and frontiers φ = 0, on multigrid), `harmonic-gs` (the seed's field on the
    /// seed paper's Gauss-Seidel), `harmonic-thesis` (the seed's field solved as the thesis
    /// did: Jacobi from φ = 0 at every plan, stopped when the largest relative change of φ falls
    /// below 1e-4, at most 20 000 sweeps; not in `all`), or a baseline: `closest-frontier`,
    /// `random-frontier`, `info-gain`, `weighted-info-gain`.
    #[arg(long, default_value = "harmonic", value_parser = PlannerKind::from_str)]
    planner: PlannerKind,
    /// Laplace solver of the harmonic planner: `mg` (multigrid, default), `flat` (the host's
    /// fast multigrid, `harmonic_core::solve::flat`, about 22 floats per voxel; re-solves in
    /// boxes as `mg`'s; BENCHMARKS.md) or `gs` (the seed paper's Gauss-Seidel; the same as
    /// `--planner harmonic-gs`).
    #[arg(long, default_value = "mg", value_parser = ["mg", "flat", "gs"])]
    solver: String,
    /// Relative-residual tolerance of the seed's Laplace solve (`harmonic-laplace`, `harmonic-gs`); the
    /// default screened field solves to its own 1e-5 (harmonic_core::field::ScreenedParams).
    #[arg(long, default_value_t = 1e-6, value_parser = parse_positive)]
    tol: f32,
    /// Write every planning step's problem (labels .npy + source) here, for `harmonic-sim solve`.
    #[arg(long)]
    dump_problem: Option<PathBuf>,
    /// Write every voxel where the map differs from the noise-free map of the same run
    /// (false occupied, false free, unseen, seen only here) to this CSV file: its index, centre,
    /// state in both maps, log-odds and, with the stereo sensor model, the surface estimate.
    /// The voxels behind `map accuracy`; needs imperfect sensing (`--noise`, `--depth-from
    /// stereo` or `--drift`).
    #[arg(long, value_name = "FILE")]
    map_errors: Option<PathBuf>,
    /// Depth-link transport: `sim` (in-process pipe), `tcp:HOST:PORT` (connect),
    /// `tcp-listen:[HOST:]PORT` (wait for the peer) or `serial:PATH[:BAUD]`. Over TCP and serial
    /// the far end must send the bytes back (echo, loopback plug): both link ends run here.
    #[arg(long, default_value = "sim", value_parser = TransportSpec::from_str)]
    link: TransportSpec,
    /// Depth-link baud rate (10 bits per byte on the wire, in simulated time).
    #[arg(long, default_value_t = DEFAULT_BAUD, value_parser = parse_baud)]
    link_baud: u32,
    /// Link fault: bit error rate (probability per data bit).
    #[arg(long, default_value_t = 0.0, value_parser = parse_probability)]
    link_ber: f64,
    /// Link fault: probability that a whole link frame (a depth chunk, pose, ...) is lost.
    #[arg(long, default_value_t = 0.0, value_parser = parse_probability)]
    link_drop: f64,
    /// Link fault: probability that a link frame is sent twice.
    #[arg(long, default_value_t = 0.0, value_parser = parse_probability)]
    link_dup: f64,
    /// Link fault: probability that a link frame is swapped with the next one.
    #[arg(long, default_value_t = 0.0, value_parser = parse_probability)]
    link_reorder: f64,
    /// Link fault: probability that a byte is lost (receiver overrun).
    #[arg(long, default_value_t = 0.0, value_parser = parse_probability)]
    link_byte_drop: f64,
    /// Link fault: noise bursts, `RATE[:BYTES]`: a burst starts at a byte with probability
    /// RATE and replaces BYTES bytes (default 32) by random ones.
    #[arg(long, value_parser = parse_burst)]
    link_burst: Option<(f64, u32)>,
    /// Depth link: resend requests per image at most (selective retransmission over a return
    /// channel at the same baud rate and with the same faults); 0 turns it off.
    #[arg(long, default_value_t = DEFAULT_ARQ_ROUNDS)]
    link_arq_rounds: u8,
    /// Depth link: rows per depth chunk, fixed (1-10 for the 100-pixel camera). Default: the
    /// camera side adapts it to the bit error rate it infers from what is asked again.
    #[arg(long)]
    link_chunk_rows: Option<u16>,
    /// Fly over MAVLink: `emulator` (the default when no value is given: an in-process
    /// PX4-like flight stack), `udpin:HOST:PORT` or `udpout:HOST:PORT` (a real autopilot or
    /// SITL; MAVProxy's address syntax). The explorer plans from the pose the autopilot reports.
    #[arg(long, num_args = 0..=1, default_missing_value = "emulator", value_parser = MavlinkSpec::from_str)]
    mavlink: Option<MavlinkSpec>,
    /// The emulator also streams ODOMETRY (the bridge then prefers it).
    #[arg(long, requires = "mavlink")]
    odometry: bool,
    /// The emulator's pose stream rate (LOCAL_POSITION_NED + ATTITUDE), Hz; it samples the
    /// vehicle at the simulator's time step, so rates above 1 / --dt run at 1 / --dt.
    #[arg(long, default_value_t = 20.0, requires = "mavlink")]
    emulator_rate: f64,
    /// Milliseconds from the emulator sampling a pose to sending its report.
    #[arg(long, default_value_t = 0, requires = "mavlink")]
    emulator_latency_ms: u64,
    /// The emulator's time_boot_ms when the run starts (it booted this long before).
    #[arg(long, default_value_t = 0, requires = "mavlink")]
    emulator_boot_ms: u64,
    /// The emulator reports velocities and yaw rate as zero.
    #[arg(long, requires = "mavlink")]
    emulator_zero_velocities: bool,
    /// Frames taken while the vehicle yaws faster than this (deg/s, measured from the pose
    /// stream) are refused by the core; 0: no check.
    #[arg(long, default_value_t = 30.0)]
    max_frame_yaw_rate: f32,
    /// Frames whose newest pose sample is older than this (ms) are refused by the core; 0: no
    /// check.
    #[arg(long, default_value_t = 150)]
    max_frame_pose_lag_ms: u32,
    /// Record every MAVLink frame both ways in this .tlog file (QGroundControl/MAVProxy format).
    #[arg(long, requires = "mavlink")]
    tlog: Option<PathBuf>,
    /// MAVLink 2 message signing: a file holding the 32-byte secret key as 64 hex digits. The
    /// bridge signs every frame it sends and acts only on frames signed with the key (newer
    /// than the last on their stream, at most a minute old); the rest are counted in
    /// report.json (`mavlink.bridge_signing`). The emulator then requires signing too.
    #[arg(long, requires = "mavlink")]
    mavlink_key: Option<PathBuf>,
    /// Hold until a ground station sends COMMAND_LONG MAV_CMD_MISSION_START to component 191
    /// (see `--operator`); without it the exploration starts at once.
    #[arg(long, requires = "mavlink")]
    wait_for_start: bool,
    /// With the emulator: a scripted ground station sends operator commands at simulated
    /// times, `COMMAND@SECONDS,...` with COMMAND one of start, pause, resume, abort (e.g.
    /// `pause@30,resume@45`). Each is answered with a COMMAND_ACK; report.json lists them
    /// (`mavlink.operator_commands`).
    #[arg(long, requires = "mavlink", value_parser = parse::parse_operator_script)]
    operator: Option<OperatorScript>,
    /// Where the planning runs: `host` (the core in this process), `qemu` (the firmware,
    /// harmonic-fw, on an emulated Cortex-M4F: processor in the loop; see `pil` in the docs) or
    /// `in-process` (the firmware's companion, with its grid, storage and configuration, built
    /// for this machine and flown exactly as under `qemu`, without the emulator) or `companion`
    /// (the core's companion object with this run's grid, planner and settings, in this
    /// process, flown as under `qemu`: any scenario).
    #[arg(long, default_value = "host", value_parser = ["host", "qemu", "in-process", "companion"])]
    core: String,
    /// With `--core qemu`: the firmware ELF to run (default: build it with cargo).
    #[arg(long)]
    firmware: Option<PathBuf>,
    /// With `--core qemu`: the QEMU binary.
    #[arg(long, default_value = "qemu-system-arm")]
    qemu: String,
    /// Write figures into the output directory: slice.png (occupancy, φ, descent directions and
    /// the chosen path in the horizontal slice through the vehicle), top_view.png (the flown path
    /// over the final map) and coverage.png.
    #[arg(long)]
    figures: bool,
    /// The step whose plan slice.png shows (the first full plan at or after it; default: a
    /// third of the way through the run).
    #[arg(long, requires = "figures")]
    figure_step: Option<u32>,
    /// Record every integrated depth frame and its pose in DIR, TUM RGB-D style (16-bit PNG in
    /// mm, depth.txt, groundtruth.txt) for `harmonic-sim replay`.
    #[arg(long)]
    record: Option<PathBuf>,
    /// No progress bar.
    #[arg(long)]
    quiet: bool,
}

/// Run `explore`: fly the scenario, write report.json (and the map, figures, recording asked
/// for) and print the summary.
pub fn run(args: ExploreArgs) -> Result<(), String> {
    let mut scenario = Scenario::by_name_or_path(&args.scenario).map_err(|e| e.to_string())?;
    if let Some(seed) = args.start_seed {
        scenario = scenario.with_random_start(seed);
    }
    let mut cfg = SimConfig::default();
    args.sensing.check()?;
    args.sensing.apply(&mut cfg);
    args.field.apply(&mut cfg);
    cfg.seed = args.seed;
    cfg.planner = args.planner;
    args.body.apply(&mut cfg);
    cfg.explorer.solve.tolerance = args.tol;
    cfg.explorer.solver = match args.solver.as_str() {
        "gs" => SolverKind::GaussSeidel,
        "flat" => SolverKind::Flat,
        _ => SolverKind::Multigrid,
    };
    cfg.replan_distance = args.replan_distance;
    cfg.follow_full_path = args.follow_full_path;
    cfg.max_speed = args.max_speed;
    cfg.max_yaw_rate = args.max_yaw_rate.to_radians();
    cfg.max_scans = args.max_scans;
    cfg.look_around = args.look_around;
    cfg.return_home = !args.no_return_home;
    cfg.explorer.max_frame_yaw_rate = args.max_frame_yaw_rate.to_radians();
    cfg.explorer.max_frame_pose_lag_ms = args.max_frame_pose_lag_ms;
    cfg.dump_problem = args.dump_problem.clone();
    cfg.map_errors = args.map_errors.clone();
    let (burst_rate, burst_len) = args.link_burst.unwrap_or((0.0, DEFAULT_BURST_LEN));
    cfg.link = LinkConfig {
        transport: args.link.clone(),
        baud: args.link_baud,
        faults: FaultConfig {
            bit_error_rate: args.link_ber,
            byte_drop: args.link_byte_drop,
            frame_drop: args.link_drop,
            frame_duplicate: args.link_dup,
            frame_reorder: args.link_reorder,
            burst_rate,
            burst_len,
        },
        arq_rounds: args.link_arq_rounds,
        chunk_rows: args.link_chunk_rows,
    };
    if !(args.emulator_rate.is_finite() && args.emulator_rate > 0.0) {
        return Err(format!(
            "--emulator-rate {}: must be a positive number of Hz",
            args.emulator_rate
        ));
    }
    let signing_key = args
        .mavlink_key
        .as_ref()
        .map(|path| {
            let text = std::fs::read_to_string(path)
                .map_err(|e| format!("--mavlink-key {}: {e}", path.display()))?;
            harmonic_core::signing::SecretKey::from_hex(&text).map_err(|_| {
                format!(
                    "--mavlink-key {}: expected the 32-byte key as 64 hex digits",
                    path.display()
                )
            })
        })
        .transpose()?;
    cfg.mavlink = args.mavlink.clone().map(|spec| MavlinkConfig {
        spec,
        odometry: args.odometry,
        emulator: EmulatorTiming {
            pose_period_ms: ((1000.0 / args.emulator_rate).round() as u64).max(1),
            latency_ms: args.emulator_latency_ms,
            boot_ms: args.emulator_boot_ms,
            zero_velocities: args.emulator_zero_velocities,
        },
        tlog: args.tlog.clone(),
        signing_key: signing_key.clone(),
        bridge: harmonic_core::mavlink::BridgeConfig {
            wait_for_start: args.wait_for_start,
            ..harmonic_core::mavlink::BridgeConfig::default()
        },
        operator_script: args.operator.clone().map(|o| o.0).unwrap_or_default(),
    });
    if args.operator.is_some() && args.mavlink.as_ref().is_some_and(|m| m.is_remote()) {
        return Err("--operator: the scripted ground station talks to the emulator only; send commands from your ground station to a real autopilot's link".into());
    }
    std::fs::create_dir_all(&args.out).map_err(|e| format!("{}: {e}", args.out.display()))?;

    // On a terminal: a live status line. Elsewhere (CI logs, pipes): a plain line every 25 steps.
    let tty = std::io::stderr().is_terminal();
    let bar = if args.quiet || !tty {
        ProgressBar::hidden()
    } else {
        ProgressBar::new_spinner()
    };
    bar.set_style(
        ProgressStyle::with_template("{spinner} [{elapsed_precise}] {msg}")
            .unwrap_or_else(|_| ProgressStyle::default_spinner()),
    );
    let mut scans = 0u32;
    let on_step = |s: &sim::StepRecord| {
        scans += s.frames_integrated;
        // Steps whose frame was lost on the link are counted apart from scans.
        let lost = if s.step > scans {
            format!(" ({} steps)", s.step)
        } else {
            String::new()
        };
        let line = format!(
            "scans {:>4}{lost}  coverage {:>5.1}%  frontier {:>5}  path {:>6.1} m  {}",
            scans,
            s.coverage_free * 100.0,
            s.frontier,
            s.path_length_m,
            match s.outcome.as_str() {
                "kept" => "goal kept".to_string(),
                "no_frame" => "no frame".to_string(),
                _ => format!("solve {:>7.1} ms", s.solve_ms),
            }
        );
        if !args.quiet && !tty && s.step.is_multiple_of(25) {
            eprintln!("{line}");
        }
        bar.set_message(line);
        bar.tick();
    };
    let firmware = args.core != "host";
    if firmware && (args.figures || args.record.is_some()) {
        return Err("--figures and --record need --core host".into());
    }
    let geometry = sim::scenario_geometry(&scenario, cfg.grid_offset).map_err(|e| e.to_string())?;
    let mut recorder = match &args.record {
        Some(dir) => {
            let lo = cfg.explorer.log_odds;
            let settings = MapSettings {
                origin: geometry.origin().coords.into(),
                dims: [geometry.dims().nx(), geometry.dims().ny(), geometry.dims().nz()],
                resolution: geometry.resolution(),
                log_odds: [lo.hit, lo.miss, lo.min, lo.max],
                min_range: cfg.explorer.integration.min_range,
                max_range: cfg.explorer.integration.max_range,
                vehicle_radius: cfg.explorer.vehicle_radius,
            };
            Some(Recorder::create(dir, &settings)?)
        }
        None => None,
    };
    let mut snapshots: Vec<SliceSnapshot> = Vec::new();
    let mut observe_error: Option<String> = None;
    let map_npy = args.out.join("map.npy");
    let map_ply = args.out.join("map.ply");
    let mut final_map_written = false;
    let observe = |view: &StepView<'_>| {
        if let Some(r) = recorder.as_mut() {
            if let Err(e) = r.step(view) {
                observe_error.get_or_insert(e);
            }
        }
        if args.figures {
            if let Some(s) = SliceSnapshot::capture(view) {
                snapshots.push(s);
            }
        }
        if view.finished {
            let map = view.planner.map();
            let written =
                figures::write_labels(map, &map_npy).and_then(|()| figures::write_ply(map, &map_ply));
            match written {
                Ok(()) => final_map_written = true,
                Err(e) => {
                    observe_error.get_or_insert(e);
                }
            }
        }
    };
    let report = if args.core == "qemu" {
        let pil = harmonic_sim::run::pil::PilConfig {
            firmware: args.firmware.clone(),
            qemu: args.qemu.clone(),
            out: args.out.clone(),
            intruder: Vec::new(),
        };
        harmonic_sim::run::pil::run(&scenario, &cfg, &pil, on_step)
    } else if args.core == "in-process" {
        harmonic_sim::run::pil::run_in_process(&scenario, &cfg, on_step)
    } else if args.core == "companion" {
        harmonic_sim::run::pil::run_companion(&scenario, &cfg, on_step)
    } else {
        sim::run_observed(&scenario, &cfg, on_step, observe)
    }
    .map_err(|e| e.to_string())?;
    bar.finish_and_clear();
    if let Some(e) = observe_error {
        return Err(e);
    }
    if let Some(r) = recorder {
        let n = r.finish()?;
        if let Some(dir) = &args.record {
            println!("recorded {n} frames: {}", dir.display());
        }
    }
    if final_map_written {
        println!(
            "map: {} (labels), {} (occupied voxel centres)",
            map_npy.display(),
            map_ply.display()
        );
    }
    if args.figures {
        write_run_figures(&report, &snapshots, args.figure_step, &args.out)?;
    }

    let path = args.out.join("report.json");
    let json = serde_json::to_string_pretty(&report).map_err(|e| e.to_string())?;
    std::fs::write(&path, json).map_err(|e| format!("{}: {e}", path.display()))?;
    print_summary(&report);
    println!("report: {}", path.display());
    Ok(())
}

/// The slice (at `--figure-step`, else the full plan a third of the way through the run), the
/// top view and the run's coverage curve.
fn write_run_figures(
    report: &Report,
    snapshots: &[SliceSnapshot],
    step: Option<u32>,
    out: &std::path::Path,
) -> Result<(), String> {
    let target = step.unwrap_or(report.steps_taken / 3);
    let snap = snapshots
        .iter()
        .find(|s| s.step >= target)
        .or_else(|| snapshots.last());
    let mut written = Vec::new();
    if let Some(snap) = snap {
        let p = out.join("slice.png");
        figures::slice_figure(snap, &report.scenario, &p)?;
        written.push(p);
    }
    let p = out.join("top_view.png");
    // The top view draws the map from map.npy, exactly as exported.
    let grid = npy::read_u8_file(out.join("map.npy")).map_err(|e| format!("map.npy: {e}"))?;
    figures::top_view_labels(
        &grid,
        report.grid_origin,
        report.resolution,
        &report.trajectory,
        &format!(
            "{}, {}: {:.1} m flown, {:.1} % free coverage",
            report.scenario,
            report.planner,
            report.path_length_m,
            100.0 * report.coverage_free
        ),
        &p,
    )?;
    written.push(p);
    let curve = batch::Curve {
        scenario: report.scenario.clone(),
        planner: report.planner.clone(),
        seed: 0,
        points: report
            .steps
            .iter()
            .map(|s| (s.path_length_m, s.coverage_free))
            .collect(),
    };
    let p = out.join("coverage.png");
    figures::coverage_curves(&[curve], &report.scenario, &p)?;
    written.push(p);
    for p in written {
        println!("figure: {}", p.display());
    }
    Ok(())
}

/// The median solve time of the plans that solved one screening, in boxes and whole: what a
/// re-solve after a scan costs, apart from plans that tried several screenings.
fn one_screening_solves(steps: &[StepRecord]) -> String {
    if steps.iter().all(|s| s.solves.is_none()) {
        return "not counted (the firmware's downlink does not report them)".into();
    }
    let median = |in_boxes: u32| {
        let ms: Vec<f64> = steps
            .iter()
            .filter(|s| s.solves == Some(1) && s.solves_in_boxes == Some(in_boxes))
            .map(|s| s.solve_ms)
            .collect();
        let plans = ms.len();
        match quantile(ms, 0.5) {
            Some(m) => format!("{m:.2} ms ({plans} plans)"),
            None => "none".into(),
        }
    };
    format!("median {} in boxes, {} whole", median(1), median(0))
}

/// The end-of-run summary: one aligned line per quantity of the report.
fn print_summary(r: &Report) {
    let rows: [(&str, String); 20] = [
        ("scenario", r.scenario.clone()),
        ("planner", r.planner.clone()),
        ("termination", r.termination.clone()),
        ("coverage (free)", format!("{:.2} %", r.coverage_free * 100.0)),
        (
            "coverage (observed)",
            format!("{:.2} %", r.coverage_observed * 100.0),
        ),
        (
            "coverage (surface)",
            format!("{:.2} %", r.coverage_surface * 100.0),
        ),
        ("path length", format!("{:.1} m", r.path_length_m)),
        ("scans", r.scans.to_string()),
        (
            "flight time",
            format!("{:.0} s (simulated)", r.exploration_time_s()),
        ),
        (
            "return home",
            match &r.return_home {
                Some(h) => format!(
                    "{} after {:.1} m, {} scans, {:.0} s; {:.2} m from the start",
                    h.termination, h.path_length_m, h.scans, h.time_s, h.distance_to_home_m
                ),
                None => "not flown".into(),
            },
        ),
        ("collisions", r.collisions.to_string()),
        ("integration ops", r.integration_ops.to_string()),
        (
            "explorer memory",
            r.explorer_bytes.map_or_else(
                || "the firmware's arena (see `fw-budget`)".into(),
                |b| {
                    let voxels = r.grid.iter().product::<usize>().max(1);
                    format!(
                        "{:.1} MiB, {:.2} B per voxel",
                        b as f64 / 1048576.0,
                        b as f64 / voxels as f64
                    )
                },
            ),
        ),
        ("planning ops", r.planning_ops.to_string()),
        (
            "local re-solves",
            format!(
                "{} in boxes, {} gave the grid back",
                r.local_solves[0], r.local_solves[1]
            ),
        ),
        (
            "integrate / step",
            format!("{:.2} ms", r.timing.integrate.mean_ms),
        ),
        (
            "solve / step",
            format!(
                "{:.2} ms (max {:.1})",
                r.timing.solve.mean_ms, r.timing.solve.max_ms
            ),
        ),
        ("one-screening solves", one_screening_solves(&r.steps)),
        (
            "domain + streamline",
            format!("{:.2} ms", r.timing.domain.mean_ms + r.timing.streamline.mean_ms),
        ),
        ("wall time", format!("{:.1} s", r.wall_time_s)),
    ];
    let mut rows = rows.to_vec();
    if let Some(n) = r.unreachable_frontier_voxels {
        rows.insert(
            3,
            (
                "left unreachable",
                format!(
                    "{n} frontier voxels seen but out of reach (too narrow for the vehicle, behind a gap); {} unknown voxels sealed (unobservable, far remnants, or hidden behind a surface){}{}{}",
                    r.sealed_voxels,
                    match r.errors.remnants_sealed {
                        0 => String::new(),
                        k => format!(" ({k} far remnants sealed instead of flown to)"),
                    },
                    match r.errors.reopenings {
                        0 => String::new(),
                        k => format!("; {k} passages closed by doubtful voxels reopened to look again"),
                    },
                    match r.errors.pocket_plans {
                        0 => String::new(),
                        k => format!("; {k} plans made on the narrower radius to leave a pocket"),
                    }
                ),
            ),
        );
    }
    if let Some(a) = &r.map_accuracy {
        rows.push((
            "map accuracy",
            format!(
                "{:.2} % of all voxels, {:.2} % of observed ones match the noise-free map ({} false occupied, {} false free, {} unseen, {} seen only here); {} reachable free voxels held occupied",
                100.0 * a.all_voxels,
                100.0 * a.observed_voxels,
                a.false_occupied,
                a.false_free,
                a.unseen,
                a.seen_only_here,
                r.free_marked_occupied
            ),
        ));
    }
    if let Some([e, y]) = r.final_drift {
        rows.push(("final drift", format!("{e:.2} m, {:.1}°", y.to_degrees())));
    }
    if let Some(s) = &r.stereo {
        rows.push((
            "stereo depth",
            format!(
                "{} pairs of {}x{} px, baseline {} m, {} disparities, window {}: {:.1} % of pixels matched, {:.1} % of depth pixels valid; render {:.1} ms, match {:.1} ms per pair",
                s.frames,
                s.render_size[0],
                s.render_size[1],
                s.baseline_m,
                s.num_disparities,
                s.window,
                100.0 * s.mean_match_density,
                100.0 * s.mean_depth_density,
                s.mean_render_ms,
                s.mean_match_ms
            ),
        ));
    }
    let l = &r.link;
    rows.push((
        "depth link",
        format!(
            "{} at {} baud: {} frames sent, {} integrated, {} lost; {:.0} ms per frame (max {:.0})",
            l.transport,
            l.baud,
            l.depth_frames_sent,
            l.depth_frames_integrated,
            l.depth_frames_lost,
            l.transfer.mean_ms,
            l.transfer.max_ms
        ),
    ));
    let c = &l.receiver;
    rows.push((
        "link errors",
        format!(
            "crc {}, cobs {}, oversize {}, malformed {}, seq gaps {}, out-of-order {}, missing chunks {}, no pose {}",
            c.crc_errors,
            c.cobs_errors,
            c.oversize,
            c.malformed,
            c.sequence_gaps,
            c.out_of_order_chunks,
            c.missing_chunks,
            l.frames_without_pose
        ),
    ));
    if l.resend_requests_sent > 0 || l.partial_frames_integrated > 0 {
        rows.push((
            "link recovery",
            format!(
                "{} partial frames integrated ({} rows missing); {} resend requests (up to {} per frame), {} chunks resent ({:.0} kB); {:.1} rows per chunk (BER estimate {:.1e})",
                l.partial_frames_integrated,
                c.rows_missing,
                l.resend_requests_sent,
                l.arq_rounds,
                l.chunks_resent,
                l.bytes_resent as f64 / 1e3,
                l.rows_per_chunk_mean,
                l.ber_estimate
            ),
        ));
    }
    if let Some(f) = &l.injected {
        rows.push((
            "link faults",
            format!(
                "{} frames dropped, {} duplicated, {} reordered; {} bits flipped, {} bytes dropped, {} bursts",
                f.frames_dropped, f.frames_duplicated, f.frames_reordered, f.bits_flipped, f.bytes_dropped, f.bursts
            ),
        ));
    }
    if let Some(m) = &r.mavlink {
        let t = &m.traffic;
        rows.push((
            "mavlink",
            format!(
                "{}: {} messages out, {} in; setpoints {:.1} Hz, max gap {} ms",
                m.endpoint, t.messages_sent, t.messages_received, t.setpoint_rate_hz, t.max_setpoint_gap_ms
            ),
        ));
        rows.push((
            "mavlink out",
            format!(
                "{} setpoints, {} heartbeats, {} statustexts",
                m.bridge.setpoints_sent, m.bridge.heartbeats_sent, m.bridge.status_texts_sent,
            ),
        ));
        rows.push((
            "mavlink in",
            format!(
                "{} local positions, {} attitudes, {} odometries; {} rejected, {} stale events",
                m.bridge.local_positions_received,
                m.bridge.attitudes_received,
                m.bridge.odometries_received,
                m.bridge.rejected(),
                m.bridge.stale_events
            ),
        ));
        if !m.operator_commands.is_empty() {
            let answers: Vec<String> = m
                .operator_commands
                .iter()
                .map(|e| {
                    let what = e
                        .command
                        .map_or("unknown".to_string(), |c| format!("{c:?}").to_lowercase());
                    format!("{what}@{:.1}s {:?}", e.time_s, e.result).to_lowercase()
                })
                .collect();
            let state = m.operator_state.map_or("?", |s| s.name());
            rows.push(("operator", format!("{state}; {}", answers.join(", "))));
        }
        if let Some(t) = &m.tlog {
            rows.push(("tlog", format!("{} ({} records)", t.path, t.records)));
        }
    }
    println!();
    for (k, v) in rows {
        println!("  {k:<20} {v}");
    }
}
