//! Batch runs: every planner on every scenario from the same random starts, in parallel, with
//! one CSV row per run and the thesis-style tables (Shade 2011, §6.5).
//!
//! ```text
//! harmonic-sim bench --scenarios all --planners all --runs 30 --out results/
//! ```
//!
//! Run `k` (seed `first_seed + k`) starts every planner at the same random pose
//! ([`Scenario::with_random_start`]) with the same sensor-noise stream, so the comparison is
//! paired. Jobs run on a rayon pool; `--shard I/N` keeps every N-th job (the I-th of each N) so a
//! sweep can be split across machines, and `bench merge` joins the shards' CSVs into one table.
//!
//! Outputs in the output directory: `runs.csv` (or `runs-shard-I-of-N.csv`), one row per run
//! ([`RunRow`]); `curves.csv`, coverage against distance flown for every run; `solves.csv`,
//! the solver's work per run ([`SolveSummary`]); `results.md`, one
//! table per scenario ([`markdown`]); `coverage_<scenario>.png`, the coverage curves of every
//! planner ([`crate::tools::figures::coverage_curves`]).

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Mutex;
use std::time::Instant;

use rayon::prelude::*;

use crate::planners::PlannerKind;
use crate::run::sim::{self, Report, SimConfig};
use crate::world::scenario::{Scenario, THESIS_SCENARIOS};

/// One run's results: a row of `runs.csv`.
#[derive(Debug, Clone, PartialEq)]
pub struct RunRow {
    /// Scenario name.
    pub scenario: String,
    /// Planner name.
    pub planner: String,
    /// Seed of the start pose and the sensor noise.
    pub seed: u64,
    /// `complete`, `scan_limit` or `stuck:FAULT`.
    pub termination: String,
    /// Path flown, metres.
    pub path_length_m: f64,
    /// Depth frames integrated.
    pub scans: u32,
    /// Free coverage at termination, 0–1.
    pub coverage_free: f64,
    /// Surface coverage at termination, 0–1.
    pub coverage_surface: f64,
    /// Reachable free voxels observed at all (free or not) at termination, 0–1.
    pub coverage_observed: f64,
    /// Collisions of the body with the true world.
    pub collisions: u32,
    /// Voxel updates by integration.
    pub integration_ops: u64,
    /// The planner's elementary operations (see [`crate::planners`]).
    pub planning_ops: u64,
    /// Planning time per scan (domain + solve or search + goal), ms.
    pub planning_ms_per_step: f64,
    /// Map accuracy against the noise-free map of the same run, 0–1, when measured.
    pub map_accuracy: Option<f64>,
    /// Wall-clock time of the run, s.
    pub wall_time_s: f64,
    /// Start position, map frame.
    pub start: [f32; 3],
    /// Start yaw, degrees.
    pub start_yaw_deg: f32,
    /// Closest the body's centre came to a surface, metres (`None` in rows written before it
    /// was recorded).
    pub min_clearance_m: Option<f64>,
    /// Simulated flight time of the exploration, s: flying, turning and waiting for frames
    /// (`None` in rows written before it was recorded).
    pub flight_time_s: Option<f64>,
}

/// The CSV header of `runs.csv`.
pub const CSV_HEADER: &str = "scenario,planner,seed,termination,path_length_m,scans,coverage_free,coverage_surface,coverage_observed,collisions,integration_ops,planning_ops,planning_ms_per_step,map_accuracy,wall_time_s,start_x,start_y,start_z,start_yaw_deg,min_clearance_m,flight_time_s";

fn clean(s: &str) -> String {
    s.replace([',', '\n', '"'], ";")
}

impl RunRow {
    /// The row for a finished run.
    pub fn from_report(report: &Report, scenario: &Scenario, seed: u64) -> Self {
        let planning_ms: f64 = report
            .steps
            .iter()
            .map(|s| s.domain_ms + s.solve_ms + s.streamline_ms)
            .sum();
        Self {
            scenario: report.scenario.clone(),
            planner: report.planner.clone(),
            seed,
            termination: report.termination.clone(),
            path_length_m: report.path_length_m,
            scans: report.scans,
            coverage_free: report.coverage_free,
            coverage_surface: report.coverage_surface,
            coverage_observed: report.coverage_observed,
            collisions: report.collisions,
            integration_ops: report.integration_ops,
            planning_ops: report.planning_ops,
            planning_ms_per_step: planning_ms / f64::from(report.scans.max(1)),
            map_accuracy: report.map_accuracy.as_ref().map(|a| a.all_voxels),
            wall_time_s: report.wall_time_s,
            start: scenario.start_position.coords.into(),
            start_yaw_deg: scenario.start_yaw.to_degrees(),
            min_clearance_m: Some(f64::from(report.min_clearance_m)),
            flight_time_s: Some(report.exploration_time_s()),
        }
    }

    /// The row as a CSV line (no newline).
    pub fn to_csv(&self) -> String {
        format!(
            "{},{},{},{},{:.3},{},{:.6},{:.6},{:.6},{},{},{},{:.4},{},{:.3},{:.2},{:.2},{:.2},{:.1},{},{}",
            clean(&self.scenario),
            clean(&self.planner),
            self.seed,
            clean(&self.termination),
            self.path_length_m,
            self.scans,
            self.coverage_free,
            self.coverage_surface,
            self.coverage_observed,
            self.collisions,
            self.integration_ops,
            self.planning_ops,
            self.planning_ms_per_step,
            self.map_accuracy.map(|a| format!("{a:.6}")).unwrap_or_default(),
            self.wall_time_s,
            self.start[0],
            self.start[1],
            self.start[2],
            self.start_yaw_deg,
            self.min_clearance_m
                .map(|c| format!("{c:.4}"))
                .unwrap_or_default(),
            self.flight_time_s.map(|t| format!("{t:.2}")).unwrap_or_default(),
        )
    }

    /// Parses a CSV line written by [`RunRow::to_csv`] (columns by the header's names).
    pub fn from_csv(header: &[&str], line: &str) -> Result<Self, String> {
        let fields: Vec<&str> = line.split(',').collect();
        if fields.len() != header.len() {
            return Err(format!(
                "{} fields, the header has {}",
                fields.len(),
                header.len()
            ));
        }
        let get = |name: &str| -> Result<&str, String> {
            header
                .iter()
                .position(|h| *h == name)
                .map(|k| fields[k])
                .ok_or_else(|| format!("no column `{name}`"))
        };
        fn num<T: std::str::FromStr>(name: &str, s: &str) -> Result<T, String> {
            s.trim()
                .parse()
                .map_err(|_| format!("column `{name}`: bad number `{s}`"))
        }
        // Columns added later: rows written before them have none.
        let optional = |name: &str| -> Result<Option<f64>, String> {
            match get(name).map(str::trim) {
                Ok("") | Err(_) => Ok(None),
                Ok(v) => num(name, v).map(Some),
            }
        };
        let accuracy = get("map_accuracy")?;
        Ok(Self {
            scenario: get("scenario")?.to_string(),
            planner: get("planner")?.to_string(),
            seed: num("seed", get("seed")?)?,
            termination: get("termination")?.to_string(),
            path_length_m: num("path_length_m", get("path_length_m")?)?,
            scans: num("scans", get("scans")?)?,
            coverage_free: num("coverage_free", get("coverage_free")?)?,
            coverage_surface: num("coverage_surface", get("coverage_surface")?)?,
            coverage_observed: num("coverage_observed", get("coverage_observed")?)?,
            collisions: num("collisions", get("collisions")?)?,
            integration_ops: num("integration_ops", get("integration_ops")?)?,
            planning_ops: num("planning_ops", get("planning_ops")?)?,
            planning_ms_per_step: num("planning_ms_per_step", get("planning_ms_per_step")?)?,
            map_accuracy: if accuracy.trim().is_empty() {
                None
            } else {
                Some(num("map_accuracy", accuracy)?)
            },
            wall_time_s: num("wall_time_s", get("wall_time_s")?)?,
            start: [
                num("start_x", get("start_x")?)?,
                num("start_y", get("start_y")?)?,
                num("start_z", get("start_z")?)?,
            ],
            start_yaw_deg: num("start_yaw_deg", get("start_yaw_deg")?)?,
            min_clearance_m: optional("min_clearance_m")?,
            flight_time_s: optional("flight_time_s")?,
        })
    }
}

/// Coverage against distance flown over one run (defined beside the figure that draws it, so
/// that `figures` needs nothing from here).
pub use crate::tools::figures::Curve;

/// The solver's work over one run: the steps that solved a new plan (outcome `goal`).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct SolveSummary {
    /// Steps that solved a new plan.
    pub solves: u32,
    /// Mean solver iterations (sweeps or cycles) of those steps' last solve.
    pub iterations_mean: f64,
    /// Fewest of them.
    pub iterations_min: u32,
    /// Most of them.
    pub iterations_max: u32,
    /// Solves that stopped at the iteration cap over the run (the core's counter).
    pub not_converged: u32,
    /// Mean solve time of those steps, ms.
    pub solve_ms_mean: f64,
}

/// The header of `solves.csv`.
pub const SOLVES_HEADER: &str =
    "scenario,planner,seed,solves,iterations_mean,iterations_min,iterations_max,not_converged,solve_ms_mean";

impl SolveSummary {
    /// The summary of a finished run.
    pub fn of(report: &Report) -> Self {
        let solved: Vec<_> = report.steps.iter().filter(|s| s.outcome == "goal").collect();
        let n = solved.len();
        let mean = |f: &dyn Fn(&crate::run::sim::StepRecord) -> f64| {
            solved.iter().map(|s| f(s)).sum::<f64>() / n.max(1) as f64
        };
        Self {
            solves: n as u32,
            iterations_mean: mean(&|s| f64::from(s.solver_iterations)),
            iterations_min: solved.iter().map(|s| s.solver_iterations).min().unwrap_or(0),
            iterations_max: solved.iter().map(|s| s.solver_iterations).max().unwrap_or(0),
            not_converged: report.errors.solver_not_converged,
            solve_ms_mean: mean(&|s| s.solve_ms),
        }
    }
}

/// A batch of runs.
#[derive(Debug, Clone)]
pub struct BenchConfig {
    /// Scenario names or paths.
    pub scenarios: Vec<String>,
    /// Planners.
    pub planners: Vec<PlannerKind>,
    /// Runs per scenario and planner.
    pub runs: u32,
    /// Seed of the first run.
    pub first_seed: u64,
    /// This shard `(I, N)`, 1-based: jobs `k` with `k % N == I − 1`.
    pub shard: (usize, usize),
    /// Worker threads (0: one per core).
    pub jobs: usize,
    /// Settings shared by every run (noise, limits, …); planner and seed are set per run.
    pub sim: SimConfig,
    /// Fly each run around the core's companion object in this process
    /// ([`crate::run::pil::run_companion`], `explore --core companion`) instead of the host's
    /// own loop.
    pub companion: bool,
}

/// One job of a batch.
#[derive(Debug, Clone)]
pub struct Job {
    /// Scenario name or path.
    pub scenario: String,
    /// Planner.
    pub planner: PlannerKind,
    /// Seed.
    pub seed: u64,
}

/// Expands `all` (the six thesis scenarios) or a comma-separated list.
pub fn parse_scenarios(s: &str) -> Result<Vec<String>, String> {
    if s.trim() == "all" {
        return Ok(THESIS_SCENARIOS.iter().map(|s| s.to_string()).collect());
    }
    let mut out: Vec<String> = Vec::new();
    for part in s.split(',').map(str::trim).filter(|p| !p.is_empty()) {
        Scenario::by_name_or_path(part).map_err(|e| e.to_string())?;
        if !out.iter().any(|o| o == part) {
            out.push(part.to_string());
        }
    }
    if out.is_empty() {
        return Err("no scenario given".into());
    }
    Ok(out)
}

/// Parses `I/N` with `1 ≤ I ≤ N`.
pub fn parse_shard(s: &str) -> Result<(usize, usize), String> {
    let bad = || format!("expected a shard I/N with 1 <= I <= N, got `{s}`");
    let (i, n) = s.split_once('/').ok_or_else(bad)?;
    let (i, n): (usize, usize) = (
        i.trim().parse().map_err(|_| bad())?,
        n.trim().parse().map_err(|_| bad())?,
    );
    if i == 0 || i > n {
        return Err(bad());
    }
    Ok((i, n))
}

impl BenchConfig {
    /// The jobs of this shard, scenario-major, then seed, then planner (so the planners of
    /// one start finish close together).
    pub fn jobs(&self) -> Vec<Job> {
        let mut all = Vec::new();
        for scenario in &self.scenarios {
            for k in 0..u64::from(self.runs) {
                for planner in &self.planners {
                    all.push(Job {
                        scenario: scenario.clone(),
                        planner: *planner,
                        seed: self.first_seed + k,
                    });
                }
            }
        }
        let (i, n) = self.shard;
        all.into_iter()
            .enumerate()
            .filter(|(k, _)| k % n == i - 1)
            .map(|(_, j)| j)
            .collect()
    }

    /// Name of this shard's CSV file.
    pub fn csv_name(&self) -> String {
        match self.shard {
            (_, 1) => "runs.csv".into(),
            (i, n) => format!("runs-shard-{i}-of-{n}.csv"),
        }
    }
}

/// Runs one job.
pub fn run_job(
    job: &Job,
    base: &SimConfig,
    companion: bool,
) -> Result<(RunRow, Curve, SolveSummary), String> {
    let scenario = Scenario::by_name_or_path(&job.scenario)
        .map_err(|e| e.to_string())?
        .with_random_start(job.seed);
    let mut cfg = base.clone();
    cfg.planner = job.planner;
    cfg.seed = job.seed;
    let report = if companion {
        crate::run::pil::run_companion(&scenario, &cfg, |_| {})
    } else {
        sim::run(&scenario, &cfg, |_| {})
    }
    .map_err(|e| e.to_string())?;
    let row = RunRow::from_report(&report, &scenario, job.seed);
    let curve = Curve {
        scenario: report.scenario.clone(),
        planner: report.planner.clone(),
        seed: job.seed,
        points: report
            .steps
            .iter()
            .map(|s| (s.path_length_m, s.coverage_free))
            .collect(),
    };
    Ok((row, curve, SolveSummary::of(&report)))
}

/// Runs a batch, writing the CSVs and the tables into `out` as runs finish; progress on stderr.
pub fn run(cfg: &BenchConfig, out: &Path, quiet: bool) -> Result<Vec<RunRow>, String> {
    std::fs::create_dir_all(out).map_err(|e| format!("{}: {e}", out.display()))?;
    let jobs = cfg.jobs();
    let total = jobs.len();
    let csv_path = out.join(cfg.csv_name());
    let curves_path = out.join(cfg.csv_name().replace("runs", "curves"));
    let solves_path = out.join(cfg.csv_name().replace("runs", "solves"));
    let create = |p: &Path| std::fs::File::create(p).map_err(|e| format!("{}: {e}", p.display()));
    let files = Mutex::new((create(&csv_path)?, create(&curves_path)?, create(&solves_path)?));
    {
        use std::io::Write;
        let mut f = files.lock().map_err(|_| "lock")?;
        writeln!(f.0, "{CSV_HEADER}").map_err(|e| e.to_string())?;
        writeln!(f.1, "scenario,planner,seed,path_length_m,coverage_free").map_err(|e| e.to_string())?;
        writeln!(f.2, "{SOLVES_HEADER}").map_err(|e| e.to_string())?;
    }
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(cfg.jobs)
        .build()
        .map_err(|e| e.to_string())?;
    let done = AtomicUsize::new(0);
    let cpu = Mutex::new(0.0f64);
    let start = Instant::now();
    if !quiet {
        eprintln!(
            "bench: {total} runs ({} scenarios × {} planners × {} seeds{}) on {} threads",
            cfg.scenarios.len(),
            cfg.planners.len(),
            cfg.runs,
            if cfg.shard.1 > 1 {
                format!(", shard {}/{}", cfg.shard.0, cfg.shard.1)
            } else {
                String::new()
            },
            pool.current_num_threads()
        );
    }
    let results: Vec<Result<RunRow, String>> = pool.install(|| {
        jobs.par_iter()
            .map(|job| {
                let (row, curve, solves) = run_job(job, &cfg.sim, cfg.companion)
                    .map_err(|e| format!("{} {} seed {}: {e}", job.scenario, job.planner, job.seed))?;
                use std::io::Write;
                {
                    let mut f = files.lock().map_err(|_| "lock")?;
                    writeln!(f.0, "{}", row.to_csv()).map_err(|e| e.to_string())?;
                    for (d, c) in &curve.points {
                        writeln!(f.1, "{},{},{},{d:.3},{c:.5}", clean(&curve.scenario), curve.planner, curve.seed)
                            .map_err(|e| e.to_string())?;
                    }
                    writeln!(
                        f.2,
                        "{},{},{},{},{:.1},{},{},{},{:.3}",
                        clean(&row.scenario),
                        row.planner,
                        row.seed,
                        solves.solves,
                        solves.iterations_mean,
                        solves.iterations_min,
                        solves.iterations_max,
                        solves.not_converged,
                        solves.solve_ms_mean
                    )
                    .map_err(|e| e.to_string())?;
                }
                let k = done.fetch_add(1, Ordering::SeqCst) + 1;
                let cpu_s = {
                    let mut c = cpu.lock().map_err(|_| "lock")?;
                    *c += row.wall_time_s;
                    *c
                };
                if !quiet {
                    let elapsed = start.elapsed().as_secs_f64();
                    let eta = elapsed / k as f64 * (total - k) as f64;
                    eprintln!(
                        "[{k}/{total}] {} {} seed {}: {} {:.1} m, {} scans, {:.1}% free, {:.1} s  (cpu {:.0} s, eta {:.0} s)",
                        row.scenario,
                        row.planner,
                        row.seed,
                        row.termination,
                        row.path_length_m,
                        row.scans,
                        100.0 * row.coverage_free,
                        row.wall_time_s,
                        cpu_s,
                        eta
                    );
                }
                Ok(row)
            })
            .collect()
    });
    let mut rows = Vec::new();
    for r in results {
        rows.push(r?);
    }
    rows.sort_by(|a, b| {
        (&a.scenario, planner_rank(&a.planner), a.seed).cmp(&(&b.scenario, planner_rank(&b.planner), b.seed))
    });
    // Rewrite sorted, so the file does not depend on the order runs finished in.
    write_csv(&csv_path, &rows)?;
    if cfg.shard.1 == 1 {
        let md = markdown(&rows);
        let md_path = out.join("results.md");
        std::fs::write(&md_path, md).map_err(|e| format!("{}: {e}", md_path.display()))?;
        write_curve_figures(&curves_path, out)?;
    }
    Ok(rows)
}

/// `coverage_<scenario>.png` for every scenario of a curves file.
fn write_curve_figures(curves_path: &Path, out: &Path) -> Result<(), String> {
    let curves = read_curves(curves_path)?;
    let mut scenarios: Vec<&str> = curves.iter().map(|c| c.scenario.as_str()).collect();
    scenarios.sort_unstable();
    scenarios.dedup();
    for s in scenarios {
        crate::tools::figures::coverage_curves(&curves, s, &out.join(format!("coverage_{s}.png")))?;
    }
    Ok(())
}

fn planner_rank(name: &str) -> usize {
    PlannerKind::ALL
        .iter()
        .position(|k| k.name() == name)
        .unwrap_or(usize::MAX)
}

/// Writes rows to a CSV file with the header.
pub fn write_csv(path: &Path, rows: &[RunRow]) -> Result<(), String> {
    let mut text = String::from(CSV_HEADER);
    text.push('\n');
    for r in rows {
        text.push_str(&r.to_csv());
        text.push('\n');
    }
    std::fs::write(path, text).map_err(|e| format!("{}: {e}", path.display()))
}

/// Reads the rows of a `runs*.csv` file.
pub fn read_csv(path: &Path) -> Result<Vec<RunRow>, String> {
    let text = std::fs::read_to_string(path).map_err(|e| format!("{}: {e}", path.display()))?;
    let mut lines = text.lines();
    let header: Vec<&str> = lines
        .next()
        .ok_or_else(|| format!("{}: empty file", path.display()))?
        .split(',')
        .collect();
    lines
        .enumerate()
        .filter(|(_, l)| !l.trim().is_empty())
        .map(|(k, l)| RunRow::from_csv(&header, l).map_err(|e| format!("{}:{}: {e}", path.display(), k + 2)))
        .collect()
}

/// Reads the curves of a `curves*.csv` file.
pub fn read_curves(path: &Path) -> Result<Vec<Curve>, String> {
    let text = std::fs::read_to_string(path).map_err(|e| format!("{}: {e}", path.display()))?;
    let mut map: BTreeMap<(String, String, u64), Vec<(f64, f64)>> = BTreeMap::new();
    for (k, line) in text.lines().enumerate().skip(1) {
        let f: Vec<&str> = line.split(',').collect();
        let bad = || format!("{}:{}: bad curve row", path.display(), k + 1);
        if f.len() != 5 {
            return Err(bad());
        }
        let seed = f[2].parse().map_err(|_| bad())?;
        let d = f[3].parse().map_err(|_| bad())?;
        let c = f[4].parse().map_err(|_| bad())?;
        map.entry((f[0].to_string(), f[1].to_string(), seed))
            .or_default()
            .push((d, c));
    }
    Ok(map
        .into_iter()
        .map(|((scenario, planner, seed), points)| Curve {
            scenario,
            planner,
            seed,
            points,
        })
        .collect())
}

/// Joins the runs (and curves) of several shard directories or CSV files into `out`
/// (`runs.csv`, `curves.csv`, `results.md`). A run present twice is an error.
pub fn merge(inputs: &[PathBuf], out: &Path) -> Result<Vec<RunRow>, String> {
    let mut rows: Vec<RunRow> = Vec::new();
    let mut curves_text = String::from("scenario,planner,seed,path_length_m,coverage_free\n");
    let mut files = Vec::new();
    for input in inputs {
        if input.is_dir() {
            let mut found: Vec<PathBuf> = std::fs::read_dir(input)
                .map_err(|e| format!("{}: {e}", input.display()))?
                .filter_map(|e| e.ok().map(|e| e.path()))
                .filter(|p| {
                    p.file_name()
                        .and_then(|n| n.to_str())
                        .is_some_and(|n| n.starts_with("runs") && n.ends_with(".csv"))
                })
                .collect();
            found.sort();
            if found.is_empty() {
                return Err(format!("{}: no runs*.csv in this directory", input.display()));
            }
            files.extend(found);
        } else {
            files.push(input.clone());
        }
    }
    for f in &files {
        rows.extend(read_csv(f)?);
        let name = f.file_name().and_then(|n| n.to_str()).unwrap_or("");
        let curves = f.with_file_name(name.replacen("runs", "curves", 1));
        if curves.exists() && curves != *f {
            let text = std::fs::read_to_string(&curves).map_err(|e| format!("{}: {e}", curves.display()))?;
            for line in text.lines().skip(1) {
                curves_text.push_str(line);
                curves_text.push('\n');
            }
        }
    }
    rows.sort_by(|a, b| {
        (&a.scenario, planner_rank(&a.planner), a.seed).cmp(&(&b.scenario, planner_rank(&b.planner), b.seed))
    });
    for w in rows.windows(2) {
        if (&w[0].scenario, &w[0].planner, w[0].seed) == (&w[1].scenario, &w[1].planner, w[1].seed) {
            return Err(format!(
                "run {} {} seed {} appears twice (overlapping shards?)",
                w[0].scenario, w[0].planner, w[0].seed
            ));
        }
    }
    std::fs::create_dir_all(out).map_err(|e| format!("{}: {e}", out.display()))?;
    write_csv(&out.join("runs.csv"), &rows)?;
    std::fs::write(out.join("curves.csv"), curves_text).map_err(|e| format!("{}: {e}", out.display()))?;
    std::fs::write(out.join("results.md"), markdown(&rows)).map_err(|e| format!("{}: {e}", out.display()))?;
    write_curve_figures(&out.join("curves.csv"), out)?;
    Ok(rows)
}

/// Mean and sample standard deviation.
pub fn mean_std(values: &[f64]) -> (f64, f64) {
    let n = values.len() as f64;
    if values.is_empty() {
        return (f64::NAN, f64::NAN);
    }
    let mean = values.iter().sum::<f64>() / n;
    let var = if values.len() > 1 {
        values.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (n - 1.0)
    } else {
        0.0
    };
    (mean, var.sqrt())
}

/// The thesis's mean ± std path length (m) for a scenario and planner (Shade 2011, §6.5;
/// "potential" for both harmonic planners).
pub fn thesis_path(scenario: &str, planner: &str) -> Option<(f64, f64)> {
    let col = match planner {
        "random-frontier" => 0,
        "closest-frontier" => 1,
        "info-gain" => 2,
        "weighted-info-gain" => 3,
        "harmonic" | "harmonic-gs" | "harmonic-thesis" => 4,
        _ => return None,
    };
    let table: [(&str, [(f64, f64); 5]); 6] = [
        (
            "s1",
            [
                (22.34, 4.1),
                (9.78, 1.72),
                (12.99, 3.66),
                (11.07, 2.8),
                (9.3, 2.39),
            ],
        ),
        (
            "s2",
            [
                (87.02, 24.86),
                (22.98, 6.08),
                (56.9, 14.56),
                (37.02, 7.13),
                (21.43, 3.96),
            ],
        ),
        (
            "kitchen",
            [
                (36.44, 10.8),
                (16.99, 3.37),
                (20.29, 7.88),
                (18.98, 4.83),
                (15.29, 4.36),
            ],
        ),
        (
            "s4",
            [
                (257.75, 98.31),
                (57.7, 18.5),
                (108.99, 31.85),
                (65.04, 24.18),
                (50.79, 11.96),
            ],
        ),
        (
            "apartment-thesis",
            [
                (71.45, 18.9),
                (34.0, 7.97),
                (40.84, 10.55),
                (38.23, 7.16),
                (30.06, 6.06),
            ],
        ),
        (
            "garage",
            [
                (37.16, 12.46),
                (23.5, 6.65),
                (25.79, 7.67),
                (24.88, 10.09),
                (21.98, 6.53),
            ],
        ),
    ];
    table.iter().find(|(s, _)| *s == scenario).map(|(_, v)| v[col])
}

/// Per-scenario aggregate of one planner.
#[derive(Debug, Clone)]
pub struct Summary {
    /// Planner name.
    pub planner: String,
    /// Runs.
    pub runs: usize,
    /// Runs that ended `complete`.
    pub complete: usize,
    /// Path length mean, std (m).
    pub path: (f64, f64),
    /// Scans mean, std.
    pub scans: (f64, f64),
    /// Simulated flight time mean, std (s); `None` if a row has none (written before it was
    /// recorded).
    pub flight_time: Option<(f64, f64)>,
    /// Free coverage at termination, mean (0–1).
    pub coverage: f64,
    /// Integration ops, mean.
    pub integration_ops: f64,
    /// Planning ops, mean.
    pub planning_ops: f64,
    /// Planning time per step, mean (ms).
    pub planning_ms: f64,
    /// Map accuracy, mean (0–1), where measured.
    pub accuracy: Option<f64>,
    /// Collisions, total.
    pub collisions: u32,
}

/// Aggregates the rows of one scenario per planner, in table order.
pub fn summarize(rows: &[RunRow], scenario: &str) -> Vec<Summary> {
    let mut planners: Vec<&str> = rows
        .iter()
        .filter(|r| r.scenario == scenario)
        .map(|r| r.planner.as_str())
        .collect();
    planners.sort_by_key(|p| planner_rank(p));
    planners.dedup();
    planners
        .into_iter()
        .map(|p| {
            let rs: Vec<&RunRow> = rows
                .iter()
                .filter(|r| r.scenario == scenario && r.planner == p)
                .collect();
            let col = |f: &dyn Fn(&RunRow) -> f64| rs.iter().map(|r| f(r)).collect::<Vec<f64>>();
            let accuracies: Vec<f64> = rs.iter().filter_map(|r| r.map_accuracy).collect();
            Summary {
                planner: p.to_string(),
                runs: rs.len(),
                complete: rs.iter().filter(|r| r.termination == "complete").count(),
                path: mean_std(&col(&|r| r.path_length_m)),
                scans: mean_std(&col(&|r| f64::from(r.scans))),
                flight_time: rs
                    .iter()
                    .map(|r| r.flight_time_s)
                    .collect::<Option<Vec<f64>>>()
                    .filter(|t| !t.is_empty())
                    .map(|t| mean_std(&t)),
                coverage: mean_std(&col(&|r| r.coverage_free)).0,
                integration_ops: mean_std(&col(&|r| r.integration_ops as f64)).0,
                planning_ops: mean_std(&col(&|r| r.planning_ops as f64)).0,
                planning_ms: mean_std(&col(&|r| r.planning_ms_per_step)).0,
                accuracy: (!accuracies.is_empty()).then(|| mean_std(&accuracies).0),
                collisions: rs.iter().map(|r| r.collisions).sum(),
            }
        })
        .collect()
}

fn sci(x: f64) -> String {
    if x >= 1e5 {
        format!("{x:.2e}")
    } else {
        format!("{x:.0}")
    }
}

/// One markdown table per scenario: mean ± std path length, scans, flight time, coverage and
/// map accuracy at termination, completed runs, integration and planning ops, planning time per
/// step, the ratios of each planner's mean path and mean flight time to closest frontier's, and
/// the thesis's path length.
pub fn markdown(rows: &[RunRow]) -> String {
    let mut scenarios: Vec<&str> = rows.iter().map(|r| r.scenario.as_str()).collect();
    scenarios.sort_by_key(|s| {
        (
            THESIS_SCENARIOS.iter().position(|t| t == s).unwrap_or(usize::MAX),
            s.to_string(),
        )
    });
    scenarios.dedup();
    let mut md = String::new();
    for scenario in scenarios {
        let summaries = summarize(rows, scenario);
        let closest = summaries.iter().find(|s| s.planner == "closest-frontier");
        let closest_time = closest.and_then(|s| s.flight_time).map(|t| t.0);
        let closest = closest.map(|s| s.path.0);
        let with_accuracy = summaries.iter().any(|s| s.accuracy.is_some());
        let _ = writeln!(md, "### {scenario}\n");
        let _ = writeln!(
            md,
            "| planner | runs | complete | path (m) | ÷ closest | thesis path (m) | scans | flight time (s) | ÷ closest | coverage{} | collisions | integration ops | planning ops | planning ms/step |",
            if with_accuracy { " | map accuracy" } else { "" }
        );
        let _ = writeln!(
            md,
            "|---|---|---|---|---|---|---|---|---|---|---|---|---|---{}|",
            if with_accuracy { "|---" } else { "" }
        );
        for s in &summaries {
            let ratio = closest.map_or("–".to_string(), |c| format!("{:.2}", s.path.0 / c));
            let thesis = thesis_path(scenario, &s.planner)
                .map_or("–".to_string(), |(m, sd)| format!("{m:.1} ± {sd:.1}"));
            let (time, time_ratio) = match (s.flight_time, closest_time) {
                (Some((m, sd)), Some(c)) => (format!("{m:.0} ± {sd:.0}"), format!("{:.2}", m / c)),
                (Some((m, sd)), None) => (format!("{m:.0} ± {sd:.0}"), "–".to_string()),
                (None, _) => ("–".to_string(), "–".to_string()),
            };
            let accuracy = match (with_accuracy, s.accuracy) {
                (true, Some(a)) => format!(" | {:.1} %", 100.0 * a),
                (true, None) => " | –".to_string(),
                _ => String::new(),
            };
            let _ = writeln!(
                md,
                "| {} | {} | {} | {:.1} ± {:.1} | {} | {} | {:.0} ± {:.0} | {} | {} | {:.1} %{} | {} | {} | {} | {:.1} |",
                s.planner,
                s.runs,
                s.complete,
                s.path.0,
                s.path.1,
                ratio,
                thesis,
                s.scans.0,
                s.scans.1,
                time,
                time_ratio,
                100.0 * s.coverage,
                accuracy,
                s.collisions,
                sci(s.integration_ops),
                sci(s.planning_ops),
                s.planning_ms,
            );
        }
        md.push('\n');
    }
    md
}

#[cfg(test)]
mod tests {
    use super::*;

    fn row(planner: &str, seed: u64, path: f64) -> RunRow {
        RunRow {
            scenario: "s1".into(),
            planner: planner.into(),
            seed,
            termination: "complete".into(),
            path_length_m: path,
            scans: 10,
            coverage_free: 0.99,
            coverage_surface: 0.98,
            coverage_observed: 0.995,
            collisions: 0,
            integration_ops: 1000,
            planning_ops: 2_000_000,
            planning_ms_per_step: 1.5,
            map_accuracy: None,
            wall_time_s: 1.0,
            start: [1.0, 2.0, 1.0],
            start_yaw_deg: 45.0,
            min_clearance_m: Some(0.2125),
            flight_time_s: Some(412.5),
        }
    }

    #[test]
    fn csv_round_trips() {
        let mut r = row("harmonic", 3, 12.5);
        r.termination = "stuck:Streamline(Stalled)".into();
        r.map_accuracy = Some(0.97);
        let header: Vec<&str> = CSV_HEADER.split(',').collect();
        let back = RunRow::from_csv(&header, &r.to_csv()).unwrap();
        assert_eq!(back, r);
        assert!(RunRow::from_csv(&header, "a,b").is_err());
        // Rows from before the flight-time column, and from before the clearance column,
        // still read, without them.
        let line = r.to_csv();
        let without_time = line.rsplit_once(',').unwrap().0;
        let old = RunRow::from_csv(&header[..header.len() - 1], without_time).unwrap();
        assert_eq!(old.flight_time_s, None);
        assert_eq!(old.min_clearance_m, r.min_clearance_m);
        let older = RunRow::from_csv(
            &header[..header.len() - 2],
            without_time.rsplit_once(',').unwrap().0,
        )
        .unwrap();
        assert_eq!(older.min_clearance_m, None);
        assert_eq!(older.path_length_m, r.path_length_m);
    }

    #[test]
    fn shards_partition_the_jobs() {
        let mut cfg = BenchConfig {
            scenarios: vec!["s1".into(), "garage".into()],
            planners: PlannerKind::ALL.to_vec(),
            runs: 5,
            first_seed: 1,
            shard: (1, 1),
            jobs: 1,
            sim: SimConfig::default(),
            companion: false,
        };
        let all = cfg.jobs();
        assert_eq!(all.len(), 2 * PlannerKind::ALL.len() * 5);
        let mut seen = 0;
        for i in 1..=3 {
            cfg.shard = (i, 3);
            seen += cfg.jobs().len();
        }
        assert_eq!(seen, all.len());
        assert_eq!(parse_shard("2/3"), Ok((2, 3)));
        assert!(parse_shard("0/3").is_err() && parse_shard("4/3").is_err() && parse_shard("x").is_err());
    }

    #[test]
    fn table_has_means_ratio_and_thesis_numbers() {
        let rows = vec![
            row("closest-frontier", 1, 10.0),
            row("closest-frontier", 2, 12.0),
            row("harmonic", 1, 9.0),
            row("harmonic", 2, 13.0),
        ];
        let md = markdown(&rows);
        assert!(md.contains("### s1"), "{md}");
        assert!(
            md.contains("| closest-frontier | 2 | 2 | 11.0 ± 1.4 | 1.00 | 9.8 ± 1.7 |"),
            "{md}"
        );
        assert!(
            md.contains("| harmonic | 2 | 2 | 11.0 ± 2.8 | 1.00 | 9.3 ± 2.4 |"),
            "{md}"
        );
        assert!(md.contains("2.00e6"), "{md}");
        // Flight time and its ratio to closest frontier's, after the scans.
        assert!(md.contains("| 10 ± 0 | 412 ± 0 | 1.00 |"), "{md}");
        // Rows written before flight time was recorded show none.
        let mut old = rows.clone();
        old[2].flight_time_s = None;
        let md = markdown(&old);
        assert!(
            md.contains(
                "| closest-frontier | 2 | 2 | 11.0 ± 1.4 | 1.00 | 9.8 ± 1.7 | 10 ± 0 | 412 ± 0 | 1.00 |"
            ),
            "{md}"
        );
        assert!(
            md.contains("| harmonic | 2 | 2 | 11.0 ± 2.8 | 1.00 | 9.3 ± 2.4 | 10 ± 0 | – | – |"),
            "{md}"
        );
    }

    #[test]
    fn merge_joins_shards_and_rejects_duplicates() {
        let dir = std::env::temp_dir().join(format!("hs-merge-{}", std::process::id()));
        let (a, b, out) = (dir.join("a"), dir.join("b"), dir.join("out"));
        std::fs::create_dir_all(&a).unwrap();
        std::fs::create_dir_all(&b).unwrap();
        write_csv(&a.join("runs-shard-1-of-2.csv"), &[row("harmonic", 1, 9.0)]).unwrap();
        write_csv(&b.join("runs-shard-2-of-2.csv"), &[row("harmonic", 2, 11.0)]).unwrap();
        let rows = merge(&[a.clone(), b.clone()], &out).unwrap();
        assert_eq!(rows.len(), 2);
        assert_eq!(read_csv(&out.join("runs.csv")).unwrap(), rows);
        assert!(std::fs::read_to_string(out.join("results.md"))
            .unwrap()
            .contains("10.0 ± 1.4"));
        write_csv(&b.join("runs-shard-2-of-2.csv"), &[row("harmonic", 1, 9.0)]).unwrap();
        assert!(merge(&[a, b], &out).unwrap_err().contains("appears twice"));
        let _ = std::fs::remove_dir_all(dir);
    }
}
