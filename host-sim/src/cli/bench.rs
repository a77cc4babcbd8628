//! `harmonic-sim bench` and `bench merge`: the flags of the planner sweep and its run (the
//! sweep itself is `harmonic_sim::tools::batch`).

use std::path::PathBuf;

use clap::Subcommand;
use harmonic_sim::planners::PlannerKind;
use harmonic_sim::run::sim::SimConfig;
use harmonic_sim::tools::batch;

use super::sim_args::{BodyArgs, FieldArgs, SensingArgs};

/// The flags of `bench`.
#[derive(clap::Args)]
#[command(args_conflicts_with_subcommands = true)]
pub struct BenchArgs {
    #[command(subcommand)]
    action: Option<BenchAction>,
    /// `all` (the six thesis scenarios: s1, s2, kitchen, s4, apartment-thesis, garage) or
    /// comma-separated built-in names or scenario files.
    #[arg(long, default_value = "all")]
    scenarios: String,
    /// `all` or comma-separated planner names (see `explore --planner`; `all` leaves out the
    /// `harmonic-thesis` ablation).
    #[arg(long, default_value = "all")]
    planners: String,
    /// Runs (random starts) per scenario and planner.
    #[arg(long, default_value_t = 30, value_parser = clap::value_parser!(u32).range(1..))]
    runs: u32,
    /// Seed of the first run; run k uses seed FIRST_SEED + k.
    #[arg(long, default_value_t = 1)]
    first_seed: u64,
    /// Output directory (runs.csv, curves.csv, results.md, coverage_*.png).
    #[arg(long, default_value = "results")]
    out: PathBuf,
    /// Run only shard I of N (jobs k with k mod N = I - 1), to split a sweep across machines.
    #[arg(long, value_parser = batch::parse_shard)]
    shard: Option<(usize, usize)>,
    /// Worker threads (default: one per core).
    #[arg(long, default_value_t = 0)]
    jobs: usize,
    /// Stop a run after this many scans.
    #[arg(long, default_value_t = 3000)]
    max_scans: u32,
    /// Fly every path to its end before the next scan (the paper's mode).
    #[arg(long)]
    follow_full_path: bool,
    #[command(flatten)]
    sensing: SensingArgs,
    #[command(flatten)]
    field: FieldArgs,
    #[command(flatten)]
    body: BodyArgs,
    /// Solver of the harmonic planners' field: `mg` (multigrid, default) or `flat` (the host's
    /// fast multigrid; see `explore --solver`).
    #[arg(long, default_value = "mg", value_parser = ["mg", "flat"])]
    solver: String,
    /// No per-run progress lines.
    #[arg(long)]
    quiet: bool,
    /// Where the planning runs: `host` (the host's own loop, the default) or `companion` (the
    /// core's companion object in this process, flown as the firmware is; `explore --core
    /// companion`).
    #[arg(long, default_value = "host", value_parser = ["host", "companion"])]
    core: String,
}

/// The subcommands of `bench`.
#[derive(Subcommand)]
enum BenchAction {
    /// Join the runs of several shard directories (or runs*.csv files) into one table.
    Merge(MergeArgs),
}

/// The flags of `bench merge`.
#[derive(clap::Args)]
struct MergeArgs {
    /// Shard output directories or runs*.csv files.
    #[arg(required = true)]
    inputs: Vec<PathBuf>,
    /// Where to write the joined runs.csv, curves.csv and results.md.
    #[arg(long)]
    out: PathBuf,
}

/// Run `bench` (the sweep, or its shard) or `bench merge`.
pub fn run(args: &BenchArgs) -> Result<(), String> {
    if let Some(BenchAction::Merge(m)) = &args.action {
        let rows = batch::merge(&m.inputs, &m.out)?;
        eprintln!("bench merge: {} runs into {}", rows.len(), m.out.display());
        print!("{}", batch::markdown(&rows));
        return Ok(());
    }
    let mut sim = SimConfig::default();
    args.sensing.check()?;
    args.sensing.apply(&mut sim);
    args.field.apply(&mut sim);
    args.body.apply(&mut sim);
    sim.max_scans = args.max_scans;
    sim.follow_full_path = args.follow_full_path;
    if args.solver == "flat" {
        sim.explorer.solver = harmonic_core::explore::SolverKind::Flat;
    }
    let planners = PlannerKind::parse_list(&args.planners).map_err(|e| format!("--planners: {e}"))?;
    let cfg = batch::BenchConfig {
        scenarios: batch::parse_scenarios(&args.scenarios)?,
        planners,
        runs: args.runs,
        first_seed: args.first_seed,
        shard: args.shard.unwrap_or((1, 1)),
        jobs: args.jobs,
        sim,
        companion: args.core == "companion",
    };
    let rows = batch::run(&cfg, &args.out, args.quiet)?;
    if cfg.shard.1 == 1 {
        print!("{}", batch::markdown(&rows));
    }
    eprintln!("bench: {} runs; {}", rows.len(), args.out.display());
    Ok(())
}
