//! `harmonic-sim`: explore simulated worlds with the harmonic-core planner.

use std::io::IsTerminal;
use std::path::PathBuf;
use std::process::ExitCode;

use clap::{Parser, Subcommand};
use harmonic_core::explore::SolverKind;
use harmonic_sim::camera::StereoNoise;
use harmonic_sim::scenario::{builtin_names, Scenario};
use harmonic_sim::sim::{self, Report, SimConfig};
use indicatif::{ProgressBar, ProgressStyle};

#[derive(Parser)]
#[command(
    name = "harmonic-sim",
    version,
    about = "Harmonic-potential exploration simulator"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Fly a simulated multirotor through a world until no reachable frontier is left.
    Explore(ExploreArgs),
    /// List the built-in scenarios.
    Scenarios,
}

#[derive(clap::Args)]
struct ExploreArgs {
    /// A built-in scenario name (see `harmonic-sim scenarios`) or a path to a scenario .toml file.
    #[arg(long, default_value = "apartment")]
    scenario: String,
    /// Output directory for report.json (created if missing).
    #[arg(long, default_value = "out")]
    out: PathBuf,
    /// Sensor noise model: `stereo` (σ = 1 px disparity noise) or `stereo:SIGMA_PX`.
    #[arg(long, value_parser = parse_noise)]
    noise: Option<StereoNoise>,
    /// Random seed for sensor noise.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Vehicle radius in metres: obstacles are inflated by this much for planning.
    #[arg(long, default_value_t = 0.2, value_parser = parse_radius)]
    vehicle_radius: f32,
    /// Radius of the vehicle body for collision counting, metres.
    #[arg(long, default_value_t = 0.15, value_parser = parse_positive)]
    body_radius: f32,
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
    /// Laplace solver: `mg` (multigrid, default) or `gs` (the seed paper's Gauss-Seidel).
    #[arg(long, default_value = "mg", value_parser = ["mg", "gs"])]
    solver: String,
    /// Solver relative-residual tolerance.
    #[arg(long, default_value_t = 1e-6, value_parser = parse_positive)]
    tol: f32,
    /// No progress bar.
    #[arg(long)]
    quiet: bool,
}

fn parse_positive(s: &str) -> Result<f32, String> {
    match s.parse::<f32>() {
        Ok(v) if v.is_finite() && v > 0.0 => Ok(v),
        _ => Err(format!("expected a positive number, got `{s}`")),
    }
}

fn parse_radius(s: &str) -> Result<f32, String> {
    match s.parse::<f32>() {
        Ok(v) if v.is_finite() && (0.0..=0.6).contains(&v) => Ok(v),
        _ => Err(format!("expected a radius between 0 and 0.6 m, got `{s}`")),
    }
}

fn parse_noise(s: &str) -> Result<StereoNoise, String> {
    let (kind, sigma) = match s.split_once(':') {
        Some((k, v)) => (k, Some(v)),
        None => (s, None),
    };
    if kind != "stereo" {
        return Err(format!(
            "unknown noise model `{kind}` (expected `stereo` or `stereo:SIGMA_PX`)"
        ));
    }
    let mut noise = StereoNoise::default();
    if let Some(v) = sigma {
        noise.sigma_px = match v.parse::<f32>() {
            Ok(x) if x.is_finite() && x >= 0.0 => x,
            _ => {
                return Err(format!(
                    "bad disparity sigma `{v}` (expected a number of pixels ≥ 0)"
                ))
            }
        };
    }
    Ok(noise)
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let result = match cli.command {
        Command::Scenarios => {
            for name in builtin_names() {
                println!("{name}");
            }
            Ok(())
        }
        Command::Explore(args) => explore(args),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::from(2)
        }
    }
}

fn explore(args: ExploreArgs) -> Result<(), String> {
    let scenario = Scenario::by_name_or_path(&args.scenario).map_err(|e| e.to_string())?;
    let mut cfg = SimConfig::default();
    cfg.camera = cfg.camera.with_noise(args.noise);
    cfg.seed = args.seed;
    cfg.explorer.vehicle_radius = args.vehicle_radius;
    cfg.explorer.solve.tolerance = args.tol;
    cfg.explorer.solver = if args.solver == "gs" {
        SolverKind::GaussSeidel
    } else {
        SolverKind::Multigrid
    };
    cfg.body_radius = args.body_radius;
    cfg.replan_distance = args.replan_distance;
    cfg.follow_full_path = args.follow_full_path;
    cfg.max_speed = args.max_speed;
    cfg.max_yaw_rate = args.max_yaw_rate.to_radians();
    cfg.max_scans = args.max_scans;
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
    let report = sim::run(&scenario, &cfg, |s| {
        let line = format!(
            "scans {:>4}  coverage {:>5.1}%  frontier {:>5}  path {:>6.1} m  solve {:>7.1} ms",
            s.step,
            s.coverage_free * 100.0,
            s.frontier,
            s.path_length_m,
            s.solve_ms
        );
        if !args.quiet && !tty && s.step % 25 == 0 {
            eprintln!("{line}");
        }
        bar.set_message(line);
        bar.tick();
    })
    .map_err(|e| e.to_string())?;
    bar.finish_and_clear();

    let path = args.out.join("report.json");
    let json = serde_json::to_string_pretty(&report).map_err(|e| e.to_string())?;
    std::fs::write(&path, json).map_err(|e| format!("{}: {e}", path.display()))?;
    print_summary(&report);
    println!("report: {}", path.display());
    Ok(())
}

fn print_summary(r: &Report) {
    let rows: [(&str, String); 13] = [
        ("scenario", r.scenario.clone()),
        ("termination", r.termination.clone()),
        ("coverage (free)", format!("{:.2} %", r.coverage_free * 100.0)),
        (
            "coverage (surface)",
            format!("{:.2} %", r.coverage_surface * 100.0),
        ),
        ("path length", format!("{:.1} m", r.path_length_m)),
        ("scans", r.scans.to_string()),
        ("collisions", r.collisions.to_string()),
        ("integration ops", r.integration_ops.to_string()),
        ("planning ops", r.planning_ops.to_string()),
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
        (
            "domain + streamline",
            format!("{:.2} ms", r.timing.domain.mean_ms + r.timing.streamline.mean_ms),
        ),
        ("wall time", format!("{:.1} s", r.wall_time_s)),
    ];
    println!();
    for (k, v) in rows {
        println!("  {k:<20} {v}");
    }
}
