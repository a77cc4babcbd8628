//! `harmonic-sim faults`: the fault campaign's flags and run (the matrix itself is
//! `harmonic_sim::tools::faults`).

use std::path::PathBuf;

use harmonic_sim::run::sim::SimConfig;
use harmonic_sim::world::scenario::Scenario;

/// The flags of `faults`.
#[derive(clap::Args)]
pub struct FaultsArgs {
    /// Built-in scenario name or path to a scenario TOML file.
    #[arg(long, default_value = "apartment")]
    scenario: String,
    /// Output directory for faults.json and faults.md (created if missing).
    #[arg(long, default_value = "out/faults")]
    out: PathBuf,
    /// Only the cells whose name contains one of these (comma-separated), e.g. `ber,stale`.
    #[arg(long, value_delimiter = ',')]
    cells: Vec<String>,
    /// Stop each run after this many scans.
    #[arg(long, default_value_t = 3000)]
    max_scans: u32,
    /// Random seed for sensor noise and injected faults.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Vehicle radius in metres: obstacles are inflated by this much for planning.
    #[arg(long, default_value_t = 0.2)]
    vehicle_radius: f32,
    /// Instead of the matrix: one pose-drift cell per rate, mm/s (comma-separated), to find
    /// where collisions start, e.g. `1,2,5,10`.
    #[arg(long, value_delimiter = ',', conflicts_with = "cells")]
    drift_rates: Vec<f32>,
}

/// Run `faults`: explore once per cell, print the table, write faults.json and faults.md; an
/// error if any cell collided.
pub fn run(args: &FaultsArgs) -> Result<(), String> {
    use harmonic_sim::tools::faults;
    let scenario = Scenario::by_name_or_path(&args.scenario).map_err(|e| e.to_string())?;
    let mut cfg = SimConfig {
        max_scans: args.max_scans,
        seed: args.seed,
        ..SimConfig::default()
    };
    cfg.explorer.vehicle_radius = args.vehicle_radius;
    let cells: Vec<_> = if args.drift_rates.is_empty() {
        faults::default_matrix()
            .into_iter()
            .filter(|c| args.cells.is_empty() || args.cells.iter().any(|f| c.name.contains(f.as_str())))
            .collect()
    } else {
        args.drift_rates.iter().map(|&r| faults::drift_cell(r)).collect()
    };
    if cells.is_empty() {
        return Err(format!("--cells {}: no cell matches", args.cells.join(",")));
    }
    std::fs::create_dir_all(&args.out).map_err(|e| format!("{}: {e}", args.out.display()))?;
    let total = cells.len();
    let mut done = 0;
    let results = faults::run(&scenario, &cfg, cells, |r| {
        done += 1;
        eprintln!(
            "[{done}/{total}] {}: {}, {} collisions, {}/{} frames integrated",
            r.cell.name, r.termination, r.collisions, r.frames_integrated, r.frames_sent
        );
    });
    let table = faults::table(&results);
    print!("{table}");
    let json = serde_json::to_string_pretty(&results).map_err(|e| e.to_string())?;
    for (name, text) in [("faults.json", json), ("faults.md", table)] {
        let path = args.out.join(name);
        std::fs::write(&path, text).map_err(|e| format!("{}: {e}", path.display()))?;
    }
    let collisions: u32 = results.iter().map(|r| r.collisions).sum();
    if collisions > 0 {
        return Err(format!("{collisions} collisions in the fault matrix"));
    }
    Ok(())
}
