//! `harmonic-sim`: explore simulated worlds with the harmonic-core planner.
//!
//! This file declares the command line (`Cli`, `Command`) and hands each subcommand to its
//! module under `cli/`, which owns the subcommand's flags and what it runs (see `cli/mod.rs`).

mod cli;

use std::process::ExitCode;

use clap::{Parser, Subcommand};

use cli::bench::BenchArgs;
use cli::bench_solve::BenchSolveArgs;
use cli::explore::ExploreArgs;
use cli::faults::FaultsArgs;
use cli::fw_budget::FwBudgetArgs;
use cli::link_echo::LinkEchoArgs;
use cli::replay::ReplayArgs;
use cli::solve::SolveArgs;
use cli::stereo::{BenchStereoArgs, StereoArgs, StereoRenderArgs};
use cli::tlog::TlogArgs;

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
    Explore(Box<ExploreArgs>),
    /// List the built-in scenarios.
    Scenarios,
    /// Benchmark the Laplace solvers on building-like grids (the numbers in BENCHMARKS.md).
    BenchSolve(BenchSolveArgs),
    /// Solve one planning problem from a .npy label grid and print a JSON line of statistics.
    Solve(SolveArgs),
    /// Summarise a MAVLink .tlog: messages per direction and type, with rates.
    Tlog(TlogArgs),
    /// Be the far end of a TCP depth link: send every byte back, as a loopback plug would.
    LinkEcho(LinkEchoArgs),
    /// The firmware's budget: RAM and flash of the image, and instructions per phase measured
    /// under QEMU with -icount shift=0 on a processor-in-the-loop run (BENCHMARKS.md).
    FwBudget(FwBudgetArgs),
    /// Run every planner on every scenario from the same random starts (parallel); write one
    /// CSV row per run and the thesis-style tables. `bench merge` joins shards.
    Bench(Box<BenchArgs>),
    /// Integrate a recorded depth sequence (ours, or TUM RGB-D style) through the core and write
    /// the map (map.npy labels, map.ply occupied voxel centres).
    Replay(ReplayArgs),
    /// The fault campaign: explore a scenario once per cell of a matrix of injected faults
    /// (link bit errors, frame loss, bursts, pose drift, sensor dropouts and outliers, a stale
    /// pose stream) over MAVLink, and print completion, collisions and error counters per cell.
    Faults(FaultsArgs),
    /// Match a rectified stereo pair (PNG, grey or RGB) with the core's block matcher and write
    /// the disparity; with --gt, print Middlebury bad-pixel rates.
    Stereo(StereoArgs),
    /// Render a textured stereo pair from a scenario, with ground truth, to try `stereo` on.
    StereoRender(StereoRenderArgs),
    /// Accuracy and speed of the core's matcher on pairs rendered from scenarios
    /// (BENCHMARKS.md); optionally writes the pairs for scripts/stereo_opencv.py.
    BenchStereo(BenchStereoArgs),
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let result = match cli.command {
        Command::Explore(args) => cli::explore::run(*args),
        Command::Scenarios => {
            cli::scenarios::run();
            Ok(())
        }
        Command::BenchSolve(args) => cli::bench_solve::run(&args),
        Command::Solve(args) => cli::solve::run(&args),
        Command::Tlog(args) => cli::tlog::run(&args),
        Command::LinkEcho(args) => cli::link_echo::run(&args),
        Command::FwBudget(args) => cli::fw_budget::run(&args),
        Command::Bench(args) => cli::bench::run(&args),
        Command::Replay(args) => cli::replay::run(&args),
        Command::Faults(args) => cli::faults::run(&args),
        Command::Stereo(args) => cli::stereo::run_match(&args),
        Command::StereoRender(args) => cli::stereo::run_render(&args),
        Command::BenchStereo(args) => cli::stereo::run_bench(&args),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::from(2)
        }
    }
}
