//! Re-solves of a real exploration: the problems `explore --dump-problem DIR` wrote, solved in
//! order as the explorer solves them (`bench-solve --replay DIR`).
//!
//! The bench's own re-solve ([`super::bench`], `scan`) is one scan of a made-up house. Here each
//! dumped step's domain is built from its label grid and vehicle voxel as the explorer built it
//! ([`super::problem::domain_labels`]), with the screened field's source released; the first is
//! solved cold, each next one warm from the solution before it, in boxes around what changed
//! ([`resolve_near`](harmonic_core::solve::local::resolve_near), the whole grid where the boxes give up), at the field's full κ and
//! tolerance (the explorer lowers κ when a streamline stalls; those few solves are not
//! replayed). Each re-solve is timed `repeat` times from the same start; the fastest counts.

use std::path::{Path, PathBuf};
use std::time::Instant;

use harmonic_core::domain::Label;
use harmonic_core::field::{release_source, ScreenedParams};
use harmonic_core::map::Dims;
use harmonic_core::solve::flat::{flat_scratch_len, Flat};
use harmonic_core::solve::local::{box_scratch_len, WithMethod};
use harmonic_core::solve::multigrid::{Method, Multigrid};
use harmonic_core::solve::{Fork, SolveParams, SolveStats};

use super::bench::{in_boxes, BenchSolver, LocalBoxes};
use super::problem::{domain_labels, ProblemError};
use crate::io::npy;
use crate::planners::MultigridScratch;

/// One dumped step: its domain and the field's screening.
struct Step {
    labels: Vec<Label>,
    screening: f32,
}

/// The solver a replay runs, made once.
enum Solver<'a> {
    Flat(Box<Flat<'a>>),
    Multigrid(Box<Multigrid<'a>>, Method),
}

impl Solver<'_> {
    /// A cold solve (`boxes` `None`) or a re-solve in boxes; its stats, and whether it stayed
    /// in boxes.
    fn solve(
        &mut self,
        labels: &[Label],
        psi: &mut [f32],
        params: &SolveParams,
        boxes: Option<(&mut [Label], &mut [f32])>,
    ) -> Result<(SolveStats, bool), String> {
        let stayed = |(s, b): (SolveStats, LocalBoxes)| (s, !b.whole);
        let solved = match (self, boxes) {
            (Solver::Flat(flat), None) => flat.solve(labels, psi, params).map(|s| (s, false)),
            (Solver::Multigrid(mg, method), None) => {
                mg.solve(labels, psi, params, *method).map(|s| (s, false))
            }
            (Solver::Flat(flat), Some(b)) => in_boxes(&mut **flat, labels, psi, params, b).map(stayed),
            (Solver::Multigrid(mg, method), Some(b)) => {
                in_boxes(&mut WithMethod(mg, *method), labels, psi, params, b).map(stayed)
            }
        };
        solved.map_err(|e| format!("{e:?}"))
    }
}

/// What the replay of one exploration's problems measured.
#[derive(Debug, Clone)]
pub struct Replay {
    /// The grid.
    pub dims: Dims,
    /// Dumped steps with a frontier to solve for.
    pub problems: usize,
    /// Dumped steps skipped: no frontier (the end of an exploration) or no domain (the vehicle
    /// voxel not free; the explorer held or escaped there).
    pub skipped: usize,
    /// The fastest time of each re-solve (every problem after the first), ms.
    pub ms: Vec<f64>,
    /// Whether each re-solve stayed in boxes (false: the boxes gave the grid back).
    pub in_boxes: Vec<bool>,
    /// Cell updates of all re-solves.
    pub cell_updates: u64,
    /// Re-solves that stopped short of the tolerance.
    pub not_converged: usize,
}

impl Replay {
    /// The `q` quantile (0–1) of the re-solve times, in boxes (`Some(true)`), whole
    /// (`Some(false)`) or all (`None`); `None` without such a re-solve.
    pub fn quantile_ms(&self, q: f64, in_boxes: Option<bool>) -> Option<f64> {
        let ms = self
            .ms
            .iter()
            .zip(&self.in_boxes)
            .filter(|(_, b)| in_boxes.is_none_or(|want| want == **b))
            .map(|(ms, _)| *ms)
            .collect();
        super::quantile(ms, q)
    }
}

/// Reads the problems `explore --dump-problem` wrote into `dir`, in step order.
fn read_steps(dir: &Path) -> Result<(Dims, Vec<Step>, usize), String> {
    let err = |p: &Path, e: &dyn std::fmt::Display| format!("{}: {e}", p.display());
    let mut metas: Vec<PathBuf> = std::fs::read_dir(dir)
        .map_err(|e| err(dir, &e))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            let name = p.file_name().and_then(|n| n.to_str()).unwrap_or("");
            name.starts_with("step_") && name.ends_with(".json")
        })
        .collect();
    metas.sort();
    let mut dims = None;
    let mut steps = Vec::new();
    let mut skipped = 0;
    for meta_path in &metas {
        let text = std::fs::read_to_string(meta_path).map_err(|e| err(meta_path, &e))?;
        let meta: serde_json::Value = serde_json::from_str(&text).map_err(|e| err(meta_path, &e))?;
        let number = |key: &str| {
            meta[key]
                .as_f64()
                .ok_or_else(|| err(meta_path, &format!("no {key}")))
        };
        let (radius, resolution) = (number("radius")? as f32, number("resolution")? as f32);
        let source: Vec<usize> = meta["source"]
            .as_array()
            .map(|a| a.iter().filter_map(|v| v.as_u64()).map(|v| v as usize).collect())
            .unwrap_or_default();
        let [sx, sy, sz] = source[..] else {
            return Err(err(meta_path, &"no source voxel"));
        };
        let labels_path = dir.join(
            meta["labels"]
                .as_str()
                .ok_or_else(|| err(meta_path, &"no labels"))?,
        );
        let grid = npy::read_u8_file(&labels_path).map_err(|e| err(&labels_path, &e))?;
        let (d, mut labels, stats) = match domain_labels(&grid, [sx, sy, sz], radius, resolution) {
            Ok(built) => built,
            Err(ProblemError::Domain(_)) => {
                skipped += 1;
                continue;
            }
            Err(e) => return Err(err(meta_path, &e)),
        };
        if dims.is_some_and(|old: Dims| old != d) {
            return Err(err(meta_path, &"a grid of another size than the steps before"));
        }
        dims = Some(d);
        if stats.frontier == 0 {
            skipped += 1;
            continue;
        }
        release_source(&mut labels);
        let kappa = ScreenedParams::default().kappa_voxel(resolution);
        steps.push(Step {
            labels,
            screening: kappa * kappa,
        });
    }
    match dims {
        Some(d) if steps.len() >= 2 => Ok((d, steps, skipped)),
        _ => Err(format!(
            "{}: fewer than two problems with a frontier (write them with `explore --dump-problem`)",
            dir.display()
        )),
    }
}

/// Replays the problems dumped into `dir` with `solver` (multigrid or flat), each re-solve timed
/// `repeat` times.
pub fn replay(
    dir: &Path,
    solver: BenchSolver,
    repeat: usize,
    fork: Option<&dyn Fork>,
) -> Result<Replay, String> {
    let (dims, steps, skipped) = read_steps(dir)?;
    let tolerance = ScreenedParams::default().tolerance;
    let mut scratch = MultigridScratch::new(&dims);
    let mut flat_values = match solver {
        BenchSolver::Flat => vec![0.0f32; flat_scratch_len(&dims)],
        _ => Vec::new(),
    };
    // Made once, as a planner makes its solver: the flat solver zeroes its storage on its
    // first solve only.
    let mut solver = match solver {
        BenchSolver::Flat => {
            let mut flat = Flat::new(dims, &mut flat_values).map_err(|e| format!("{e:?}"))?;
            flat.set_fork(fork);
            Solver::Flat(Box::new(flat))
        }
        BenchSolver::Multigrid(method) => {
            let mut mg = Multigrid::new(dims, scratch.storage()).map_err(|e| format!("{e:?}"))?;
            mg.set_fork(fork);
            Solver::Multigrid(Box::new(mg), method)
        }
        BenchSolver::GaussSeidel => return Err("the replay solves with multigrid or flat".into()),
    };
    let cells = box_scratch_len(dims.len());
    let (mut box_labels, mut box_psi) = (vec![Label::Outside; cells], vec![0.0f32; cells]);
    let mut psi = vec![0.0f32; dims.len()];
    let mut out = Replay {
        dims,
        problems: steps.len(),
        skipped,
        ms: Vec::new(),
        in_boxes: Vec::new(),
        cell_updates: 0,
        not_converged: 0,
    };
    let params = |step: &Step, warm_start: bool| SolveParams {
        tolerance,
        max_iterations: 1_000,
        warm_start,
        screening: step.screening,
        max_error: f32::INFINITY,
    };
    let mut steps = steps.iter();
    if let Some(first) = steps.next() {
        solver.solve(&first.labels, &mut psi, &params(first, false), None)?;
    }
    for step in steps {
        let start = psi.clone();
        let mut best = f64::INFINITY;
        let mut last = None;
        for _ in 0..repeat.max(1) {
            psi.copy_from_slice(&start);
            let boxes = (box_labels.as_mut_slice(), box_psi.as_mut_slice());
            let t = Instant::now();
            let solved = solver.solve(&step.labels, &mut psi, &params(step, true), Some(boxes))?;
            best = best.min(t.elapsed().as_secs_f64() * 1e3);
            last = Some(solved);
        }
        let Some((stats, in_boxes)) = last else {
            continue;
        };
        out.ms.push(best);
        out.in_boxes.push(in_boxes);
        out.cell_updates += stats.cell_updates;
        out.not_converged += usize::from(!stats.converged);
    }
    Ok(out)
}
