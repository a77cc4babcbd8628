//! `harmonic-sim solve`: one planning problem from a .npy label grid.

use std::path::PathBuf;

use harmonic_sim::io::npy;
use harmonic_sim::tools::problem::{self, FieldChoice, SolverChoice};

use super::parse::{parse_positive, parse_radius, parse_voxel};

/// The flags of `solve`.
#[derive(clap::Args)]
pub struct SolveArgs {
    /// uint8 .npy label grid, shape (NX, NY, NZ), C order: 0 unknown, 1 free, 2 occupied.
    #[arg(long)]
    labels: PathBuf,
    /// Source (vehicle) voxel as X,Y,Z indices.
    #[arg(long, value_parser = parse_voxel)]
    source: [usize; 3],
    /// Solver: `mg` (multigrid-preconditioned CG, the host's), `flat` (the same method with
    /// every level's operator stored as arrays and each pass a flat loop: faster, about 22
    /// floats per voxel), `vc` (plain V-cycles, the firmware's) or `gs` (Gauss-Seidel reference).
    #[arg(long, default_value = "mg", value_parser = ["mg", "flat", "vc", "gs"])]
    solver: String,
    /// Relative-residual tolerance.
    #[arg(long, default_value_t = 1e-6, value_parser = parse_positive)]
    tol: f32,
    /// Most cycles (sweeps for `gs`). A solve stopped here prints `"converged": false` and
    /// `"stop": "cap"` (and still exits 0); so does one stopped at the f32 rounding floor above
    /// `--tol` (`"stop": "floor"`).
    #[arg(long, default_value_t = 1_000_000)]
    max_cycles: u32,
    /// Error target: go on until the solve's bound on its largest error of φ (printed as
    /// `error_estimate`: a bound for the screened field, a measured safe estimate for
    /// Laplace's) is at or below this as well as the tolerance; `converged` then means both
    /// were met. Default: the residual alone decides.
    #[arg(long, value_parser = parse_positive)]
    max_error: Option<f32>,
    /// Vehicle radius in metres (obstacles and unknown space are inflated by it).
    #[arg(long, default_value_t = 0.0, value_parser = parse_radius)]
    radius: f32,
    /// Voxel edge in metres (scales the radius).
    #[arg(long, default_value_t = 0.1, value_parser = parse_positive)]
    resolution: f32,
    /// Write φ (float32 .npy, same shape, 0 outside the domain) here.
    #[arg(long)]
    out: Option<PathBuf>,
    /// Threads for the multigrid solvers (`mg`, `vc`): 2 splits the fine level's passes
    /// between two threads, with the same φ as 1. Default: 2 on a machine with two cores or
    /// more, else 1.
    #[arg(long, value_parser = clap::value_parser!(u8).range(1..=2))]
    threads: Option<u8>,
    /// The field: `laplace` (the seed's: vehicle φ = 1, frontiers φ = 0) or `screened` (the
    /// explorer's default: frontiers u = 1, ∇²u = κ²u with the default 0.33 m decay length at
    /// `--resolution`, the vehicle an ordinary voxel that only picks the component; φ is
    /// written as u). The explorer solves it to `--tol 1e-5`.
    #[arg(long, default_value = "laplace", value_parser = ["laplace", "screened"])]
    field: String,
    /// Solve the problem this many times in this process (domain build included each time)
    /// and print the fastest run's times, with the first run's in `first_ms`. The first run
    /// pays for the process's fresh memory, as a planner does once; an onboard planner
    /// solves again and again in one process, as `pyamg` does in `scripts/pyamg_compare.py`.
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..=1000))]
    repeat: u32,
}

/// Run `solve`: solve the problem, write φ if asked and print the statistics as a JSON line.
pub fn run(args: &SolveArgs) -> Result<(), String> {
    let grid = npy::read_u8_file(&args.labels).map_err(|e| format!("{}: {e}", args.labels.display()))?;
    let request = problem::SolveRequest {
        source: args.source,
        solver: match args.solver.as_str() {
            "gs" => SolverChoice::GaussSeidel,
            "vc" => SolverChoice::VCycle,
            "flat" => SolverChoice::Flat,
            _ => SolverChoice::Multigrid,
        },
        tolerance: args.tol,
        max_cycles: args.max_cycles,
        max_error: args.max_error.unwrap_or(f32::INFINITY),
        radius: args.radius,
        resolution: args.resolution,
        threads: args
            .threads
            .unwrap_or_else(harmonic_sim::tools::fork::default_threads),
        field: if args.field == "screened" {
            FieldChoice::Screened
        } else {
            FieldChoice::Laplace
        },
    };
    let solve = || problem::solve(&grid, &request).map_err(|e| format!("{}: {e}", args.labels.display()));
    let (mut phi, mut summary) = solve()?;
    let first_ms = summary.first_ms;
    for _ in 1..args.repeat {
        let (p, s) = solve()?;
        if s.setup_ms + s.solve_ms < summary.setup_ms + summary.solve_ms {
            (phi, summary) = (p, s);
        }
    }
    summary.runs = args.repeat;
    summary.first_ms = first_ms;
    if let Some(out) = &args.out {
        std::fs::write(out, npy::write_f32(&phi)).map_err(|e| format!("{}: {e}", out.display()))?;
    }
    println!("{}", serde_json::to_string(&summary).map_err(|e| e.to_string())?);
    Ok(())
}
