//! `harmonic-sim bench-solve`: the Laplace solvers on building-like grids (the measurement is
//! `harmonic_sim::tools::bench`).

use harmonic_core::map::Dims;
use harmonic_core::solve::multigrid::Method;
use harmonic_sim::tools::bench::{self, BenchSolver};
use harmonic_sim::tools::fork::{default_threads, with_fork};
use harmonic_sim::tools::replay;

use super::parse::{parse_dims, parse_positive};

/// The flags of `bench-solve`.
#[derive(clap::Args)]
pub struct BenchSolveArgs {
    /// Grid sizes, NXxNYxNZ, comma-separated.
    #[arg(long, default_value = "64x64x32,128x128x64", value_delimiter = ',', value_parser = parse_dims)]
    sizes: Vec<Dims>,
    /// Run the Gauss-Seidel reference only on grids with at most this many voxels (its cost grows
    /// like n^(5/3); the 128×128×64 grid takes many minutes).
    #[arg(long, default_value_t = 200_000)]
    gs_max_voxels: usize,
    /// Repetitions per measurement (the median is reported).
    #[arg(long, default_value_t = 3)]
    repeat: usize,
    /// Relative-residual tolerance (the explorer solves the screened field to 1e-5).
    #[arg(long, default_value_t = 1e-6, value_parser = parse_positive)]
    tol: f32,
    /// The field: `laplace` (the seed's, vehicle φ = 1, frontiers φ = 0) or `screened` (the
    /// explorer's default: frontiers u = 1, ∇²u = κ²u with the default 0.33 m decay length at
    /// 0.1 m voxels, the vehicle an ordinary voxel).
    #[arg(long, default_value = "laplace", value_parser = ["laplace", "screened"])]
    field: String,
    /// Threads for the multigrid solver's fine-level passes: 2 splits each pass between two
    /// threads of a pool (the same bits as 1, which runs everything on one thread). Default: 2
    /// on a machine with two cores or more, else 1.
    #[arg(long, value_parser = clap::value_parser!(u8).range(1..=2))]
    threads: Option<u8>,
    /// Instead of the made-up grids: replay the problems `explore --dump-problem DIR` wrote
    /// (comma-separated directories), the first solved cold and each next warm from the one
    /// before, in boxes around what changed, as the explorer re-solves the screened field
    /// (at its full κ and tolerance; `--field` and `--tol` do not apply). Each re-solve takes
    /// the fastest of `--repeat` runs.
    #[arg(long, value_delimiter = ',')]
    replay: Vec<std::path::PathBuf>,
}

/// Run `bench-solve`: measure every solver on every grid size and print the table.
pub fn run(args: &BenchSolveArgs) -> Result<(), String> {
    if !args.replay.is_empty() {
        return run_replay(args);
    }
    let screening = if args.field == "screened" {
        let k = harmonic_core::field::ScreenedParams::default().kappa_voxel(0.1);
        k * k
    } else {
        0.0
    };
    println!("| grid | unknowns | frontier | solver | start | iterations | residual | error estimate | ms | cell updates |");
    println!("|---|---|---|---|---|---|---|---|---|---|");
    let mut mg_cold_ms = Vec::new();
    for dims in &args.sizes {
        let mut solvers = vec![
            BenchSolver::Multigrid(Method::Pcg),
            BenchSolver::Multigrid(Method::VCycle),
            BenchSolver::Flat,
        ];
        if dims.len() <= args.gs_max_voxels {
            solvers.push(BenchSolver::GaussSeidel);
        }
        let mut rows = Vec::new();
        for solver in solvers {
            eprintln!(
                "measuring {} on {}x{}x{} ...",
                solver_label(solver),
                dims.nx(),
                dims.ny(),
                dims.nz()
            );
            let measured = with_fork(args.threads.unwrap_or_else(default_threads), |fork| {
                bench::measure(*dims, solver, args.tol, args.repeat, screening, fork)
            })?;
            for row in measured {
                println!(
                    "| {} | {} | {} | {} | {} | {} | {:.1e} | {} | {:.2} | {} |",
                    row.grid,
                    row.unknowns,
                    row.frontier,
                    row.solver,
                    row.start,
                    row.iterations,
                    row.residual,
                    row.error_estimate.map_or("–".to_string(), |e| format!("{e:.1e}")),
                    row.ms,
                    row.cell_updates
                );
                rows.push(row);
            }
        }
        let find = |solver: &str, start: &str| rows.iter().find(|r| r.solver == solver && r.start == start);
        if let (Some(mg), Some(gs)) = (find("mg (pcg)", "cold"), find("gs", "cold")) {
            println!(
                "\n{}: Gauss-Seidel / MGPCG, cold: time {:.0}×, cell updates {:.0}×\n",
                mg.grid,
                gs.ms / mg.ms,
                gs.cell_updates as f64 / mg.cell_updates as f64
            );
        }
        if let Some(mg) = find("mg (pcg)", "cold") {
            mg_cold_ms.push((dims.len(), mg.ms));
        }
        for r in &rows {
            if let Some(l) = r.local {
                let share = 100.0 * l.last_cells as f64 / dims.len() as f64;
                if l.whole {
                    println!(
                        "\n{} {}: gave up on boxes, solved the whole grid",
                        r.grid, r.solver
                    );
                } else {
                    println!(
                        "\n{} {}: scan (local) took {} box(es), the last {} cells ({share:.1} % of the grid)",
                        r.grid, r.solver, l.boxes, l.last_cells
                    );
                }
            }
        }
        if screening > 0.0 {
            print_scan_reach(*dims, screening);
        }
    }
    for pair in mg_cold_ms.windows(2) {
        println!(
            "growth: {:.1}× the voxels took {:.1}× the MGPCG cold-solve time",
            pair[1].0 as f64 / pair[0].0 as f64,
            pair[1].1 / pair[0].1
        );
    }
    Ok(())
}

/// `bench-solve --replay`: each dumped exploration re-solved by the flat solver and by
/// multigrid (the explorer's default, which picks MGPCG or V-cycles itself).
fn run_replay(args: &BenchSolveArgs) -> Result<(), String> {
    println!("| problems | skipped | grid | solver | re-solves in boxes / whole | in boxes, median / p90 ms | all, median ms | cell updates | not converged |");
    println!("|---|---|---|---|---|---|---|---|---|");
    for dir in &args.replay {
        for (solver, name) in [
            (BenchSolver::Flat, "flat"),
            (BenchSolver::Multigrid(Method::Auto), "mg"),
        ] {
            eprintln!("replaying {} with {name} ...", dir.display());
            let r = with_fork(args.threads.unwrap_or_else(default_threads), |fork| {
                replay::replay(dir, solver, args.repeat, fork)
            })??;
            let boxes = r.in_boxes.iter().filter(|b| **b).count();
            let ms = |q: f64, b: Option<bool>| {
                r.quantile_ms(q, b).map_or("–".to_string(), |m| format!("{m:.2}"))
            };
            println!(
                "| {} ({}) | {} | {}x{}x{} | {name} | {boxes} / {} | {} / {} | {} | {} | {} |",
                dir.display(),
                r.problems,
                r.skipped,
                r.dims.nx(),
                r.dims.ny(),
                r.dims.nz(),
                r.in_boxes.len() - boxes,
                ms(0.5, Some(true)),
                ms(0.9, Some(true)),
                ms(0.5, None),
                r.cell_updates,
                r.not_converged
            );
        }
    }
    Ok(())
}

/// What the `scan` re-solve has to change ([`bench::scan_reach`]): the cells whose `u` moved by
/// more than each threshold, and the box around them.
fn print_scan_reach(dims: harmonic_core::map::Dims, screening: f32) {
    let grid = format!("{}x{}x{}", dims.nx(), dims.ny(), dims.nz());
    println!("\n{grid}, after the scan (both solved to 1e-7): where u moved");
    println!("| more than | interior cells | share | box (voxels) | box cells, share of the grid |");
    println!("|---|---|---|---|---|");
    for r in bench::scan_reach(dims, screening, &[1e-2, 1e-3, 1e-4, 1e-5, 1e-6, 1e-7]) {
        let bounds = r
            .bounds
            .map_or("–".to_string(), |(lo, hi)| format!("{lo:?}..={hi:?}"));
        println!(
            "| {:.0e} | {} | {:.1} % | {} | {} ({:.1} %) |",
            r.threshold,
            r.cells,
            100.0 * r.cells as f64 / r.interior.max(1) as f64,
            bounds,
            r.box_cells(),
            100.0 * r.box_cells() as f64 / dims.len() as f64
        );
    }
}

/// The solver's name in the progress lines.
fn solver_label(s: BenchSolver) -> &'static str {
    match s {
        BenchSolver::Multigrid(Method::VCycle) => "multigrid V-cycles",
        BenchSolver::Multigrid(_) => "MGPCG",
        BenchSolver::Flat => "MGPCG with flat loops",
        BenchSolver::GaussSeidel => "Gauss-Seidel",
    }
}
