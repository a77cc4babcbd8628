//! Solver benchmarks: the numbers in BENCHMARKS.md come from here (`harmonic-sim bench-solve`).
//!
//! The problem is a building-like grid: outer walls, floor and ceiling, a 4 × 4 plan of rooms
//! separated by one-voxel walls with door openings, the vehicle (source) in the first room and a
//! 10 × 10 patch of frontier voxels against the far wall of the last room. A *warm* re-solve
//! models the next planning step after one scan: the vehicle has moved 1 m (10 voxels) and the
//! frontier patch has shifted by three voxels; the solve starts from the previous solution.
//! For the screened field, whose vehicle is an ordinary voxel, a *scan* re-solve models a
//! smaller change: the scan resolved one edge row of the frontier patch (ten of its voxels
//! become interior, the wall behind them seen) and nothing else moved.

use std::time::Instant;

use harmonic_core::domain::Label;
use harmonic_core::map::{Dims, VoxelIndex};
use harmonic_core::solve::flat::{flat_scratch_len, Flat};
use harmonic_core::solve::local::{resolve_near, BoxSolver, Local, LocalParams, LocalScratch, WithMethod};
use harmonic_core::solve::multigrid::{Method, Multigrid};
use harmonic_core::solve::{gauss_seidel, Fork, SolveError, SolveParams, SolveStats};
use serde::Serialize;

use crate::planners::MultigridScratch;

/// A labelled Laplace problem.
pub struct Problem {
    /// Grid size.
    pub dims: Dims,
    /// Domain labels.
    pub labels: Vec<Label>,
}

impl Problem {
    /// Interior unknowns.
    pub fn unknowns(&self) -> usize {
        self.labels.iter().filter(|l| **l == Label::Interior).count()
    }
    /// Frontier voxels.
    pub fn frontier(&self) -> usize {
        self.labels.iter().filter(|l| **l == Label::Frontier).count()
    }
}

/// Rooms with doors on an `nx × ny × nz` grid; `step` moves the source and the frontier patch as
/// one scan would (0 = the cold problem).
pub fn rooms_with_doors(dims: Dims, step: usize) -> Problem {
    let (nx, ny, nz) = (dims.nx(), dims.ny(), dims.nz());
    let room_x = nx / 4;
    let room_y = ny / 4;
    let door = (room_y / 3).max(2);
    let door_height = (nz * 2 / 3).max(2);
    let mut labels = vec![Label::Outside; dims.len()];
    for (i, l) in labels.iter_mut().enumerate() {
        let v = dims.voxel(i);
        let (x, y, z) = (usize::from(v.x), usize::from(v.y), usize::from(v.z));
        let boundary = x == 0 || y == 0 || z == 0 || x == nx - 1 || y == ny - 1 || z == nz - 1;
        // Interior walls on x = k·room_x and y = k·room_y with a door in the middle of each wall
        // segment.
        let wall_x = x % room_x == 0 && {
            let mid = (y / room_y) * room_y + room_y / 2;
            !(y.abs_diff(mid) < door / 2 + 1 && z < door_height)
        };
        let wall_y = y % room_y == 0 && {
            let mid = (x / room_x) * room_x + room_x / 2;
            !(x.abs_diff(mid) < door / 2 + 1 && z < door_height)
        };
        if !(boundary || wall_x || wall_y) {
            *l = Label::Interior;
        }
    }
    // Frontier: a 10 × 10 patch on the far wall of the last room.
    let shift = 3 * step;
    let y0 = ny.saturating_sub(room_y / 2 + 5) + shift.min((room_y / 2).saturating_sub(6));
    let z0 = (nz / 2).saturating_sub(5);
    for y in y0..y0 + 10 {
        for z in z0..z0 + 10 {
            if let Some(v) = dims.checked((nx - 2) as i32, y as i32, z as i32) {
                labels[dims.linear(v)] = Label::Frontier;
            }
        }
    }
    let source = VoxelIndex::new(
        (room_x / 2 + 10 * step) as u16,
        (room_y / 2) as u16,
        (nz / 2) as u16,
    );
    labels[dims.linear(source)] = Label::Source;
    Problem { dims, labels }
}

/// [`rooms_with_doors`] at `step` 0 after a scan that resolved the frontier patch's lowest row
/// (z): its ten voxels become interior. The rest of the problem is unchanged.
pub fn rooms_after_a_scan(dims: Dims) -> Problem {
    let mut p = rooms_with_doors(dims, 0);
    let lowest = p
        .labels
        .iter()
        .enumerate()
        .filter(|(_, l)| **l == Label::Frontier)
        .map(|(i, _)| dims.voxel(i).z)
        .min();
    for (i, l) in p.labels.iter_mut().enumerate() {
        if *l == Label::Frontier && Some(dims.voxel(i).z) == lowest {
            *l = Label::Interior;
        }
    }
    p
}

/// One benchmark measurement.
#[derive(Debug, Clone, Serialize)]
pub struct SolveRow {
    /// Grid size, e.g. "64x64x32".
    pub grid: String,
    /// Interior unknowns.
    pub unknowns: usize,
    /// Frontier voxels.
    pub frontier: usize,
    /// "mg (pcg)", "mg (v-cycle)" or "gs".
    pub solver: String,
    /// "cold", "zero", "warm" or (screened field, multigrid) "scan" and "scan (local)".
    pub start: String,
    /// Cycles, CG iterations or sweeps.
    pub iterations: u32,
    /// Final relative residual.
    pub residual: f32,
    /// Converged to the tolerance.
    pub converged: bool,
    /// Median wall time, ms.
    pub ms: f64,
    /// Cell updates.
    pub cell_updates: u64,
    /// The solve's estimate of its largest error ([`SolveStats::error_estimate`]).
    pub error_estimate: Option<f32>,
    /// The `scan (local)` row's boxes ([`resolve_near`]); `None` on every other row.
    pub local: Option<LocalBoxes>,
}

/// The boxes a local re-solve took.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct LocalBoxes {
    /// Boxes solved.
    pub boxes: u8,
    /// Cells of the last.
    pub last_cells: usize,
    /// True if it gave up and the whole grid was solved instead.
    pub whole: bool,
}

impl LocalBoxes {
    /// What `how` took, on a grid of `cells`.
    fn of(how: &Local, cells: usize) -> Self {
        match how {
            Local::Solved(s) => LocalBoxes {
                boxes: s.boxes,
                last_cells: s.box_cells,
                whole: false,
            },
            Local::Whole(_) => LocalBoxes {
                boxes: 0,
                last_cells: cells,
                whole: true,
            },
        }
    }
}

/// `solver`'s re-solve of `labels` in boxes around the change ([`resolve_near`], warm from
/// `psi`, the explorer's box settings), and what it took.
pub(crate) fn in_boxes(
    solver: &mut impl BoxSolver,
    labels: &[Label],
    psi: &mut [f32],
    params: &SolveParams,
    (box_labels, box_psi): (&mut [Label], &mut [f32]),
) -> Result<(SolveStats, LocalBoxes), SolveError> {
    let local = LocalParams::for_screening(params.screening, params.tolerance);
    let scratch = LocalScratch {
        labels: box_labels,
        psi: box_psi,
    };
    let how = resolve_near(solver, labels, psi, params, &local, scratch)?;
    Ok((how.stats(), LocalBoxes::of(&how, solver.grid().len())))
}

/// [`in_boxes`] on the bench's own problems, which are valid.
fn bench_in_boxes(
    solver: &mut impl BoxSolver,
    labels: &[Label],
    psi: &mut [f32],
    params: &SolveParams,
    scratch: (&mut [Label], &mut [f32]),
) -> (SolveStats, Option<LocalBoxes>) {
    let (stats, boxes) = in_boxes(solver, labels, psi, params, scratch).expect("valid problem");
    (stats, Some(boxes))
}

fn median(v: Vec<f64>) -> f64 {
    super::quantile(v, 0.5).expect("each row is timed at least once")
}

/// Which solver a row measures.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum BenchSolver {
    /// Multigrid with the given method.
    Multigrid(Method),
    /// MGPCG with flat loops ([`harmonic_core::solve::flat`]).
    Flat,
    /// The reference Gauss-Seidel.
    GaussSeidel,
}

impl BenchSolver {
    fn name(self) -> &'static str {
        match self {
            BenchSolver::Multigrid(Method::VCycle) => "mg (v-cycle)",
            BenchSolver::Multigrid(_) => "mg (pcg)",
            BenchSolver::Flat => "flat (pcg)",
            BenchSolver::GaussSeidel => "gs",
        }
    }
}

/// Measures a cold solve and a warm re-solve of the rooms problem on `dims`, `repeat` times each
/// (median reported). `start` is `cold` (multigrid: full multigrid from the labels; Gauss-Seidel:
/// ψ = 0) and `warm` (from the previous solution after one scan); multigrid adds `zero`, a cold
/// solve from ψ = 0 without full multigrid, to show what each start is worth.
///
/// `screening` 0 solves the seed's Laplace problem; above 0 (κ²h²) the explorer's default
/// field: the frontier-sourced screened field, the vehicle an ordinary interior voxel, and then
/// `scan` too: the cold solution re-solved after a scan that resolved one row of the frontier
/// ([`rooms_after_a_scan`]), and for multigrid `scan (local)`: the same re-solve confined to
/// boxes around the scan ([`resolve_near`], the whole grid solved instead if it gives up; its
/// time includes its residual passes over the whole grid).
pub fn measure(
    dims: Dims,
    solver: BenchSolver,
    tolerance: f32,
    repeat: usize,
    screening: f32,
    fork: Option<&dyn Fork>,
) -> Vec<SolveRow> {
    let (mut cold, mut warm, mut scan) = (
        rooms_with_doors(dims, 0),
        rooms_with_doors(dims, 1),
        rooms_after_a_scan(dims),
    );
    let screened = screening > 0.0;
    if screened {
        harmonic_core::field::release_source(&mut cold.labels);
        harmonic_core::field::release_source(&mut warm.labels);
        harmonic_core::field::release_source(&mut scan.labels);
    }
    let mut scratch = MultigridScratch::new(&dims);
    // The box of `scan (local)`: the most a box may take, as the explorer lends.
    let cells = harmonic_core::solve::local::box_scratch_len(dims.len());
    let (mut box_labels, mut box_psi) = (vec![Label::Outside; cells], vec![0.0f32; cells]);
    let mut psi = vec![0.0f32; dims.len()];
    // The flat solver's storage is zeroed on its first solve: a planner lends it once.
    let mut flat_values = match solver {
        BenchSolver::Flat => vec![0.0f32; flat_scratch_len(&dims)],
        _ => Vec::new(),
    };
    let mut flat = match solver {
        BenchSolver::Flat => {
            Some(Flat::new(dims, &mut flat_values).expect("scratch sized by flat_scratch_len"))
        }
        _ => None,
    };
    if let Some(f) = flat.as_mut() {
        f.set_fork(fork);
    }
    // One solve; `boxes` re-solves in boxes around the change (multigrid, warm) and reports them.
    let mut run = |labels: &[Label], psi: &mut [f32], warm_start: bool, fmg: bool, boxes: bool| {
        let params = SolveParams {
            tolerance,
            max_iterations: 1_000_000,
            warm_start,
            screening,
            max_error: f32::INFINITY,
        };
        match solver {
            BenchSolver::Multigrid(method) => {
                let mut mg = Multigrid::new(dims, scratch.storage()).expect("scratch sized by scratch_size");
                mg.set_full_multigrid(fmg);
                mg.set_fork(fork);
                if !boxes {
                    return (
                        mg.solve(labels, psi, &params, method).expect("valid problem"),
                        None,
                    );
                }
                bench_in_boxes(
                    &mut WithMethod(&mut mg, method),
                    labels,
                    psi,
                    &params,
                    (&mut box_labels, &mut box_psi),
                )
            }
            BenchSolver::Flat => {
                let _ = fmg;
                let flat = flat.as_mut().expect("made above for the flat solver");
                if !boxes {
                    return (flat.solve(labels, psi, &params).expect("valid problem"), None);
                }
                bench_in_boxes(flat, labels, psi, &params, (&mut box_labels, &mut box_psi))
            }
            BenchSolver::GaussSeidel => (
                gauss_seidel(&dims, labels, psi, &params).expect("valid problem"),
                None,
            ),
        }
    };
    let grid = format!("{}x{}x{}", dims.nx(), dims.ny(), dims.nz());
    let row = |p: &Problem, start: &str, stats: SolveStats, ms: f64| SolveRow {
        grid: grid.clone(),
        unknowns: p.unknowns(),
        frontier: p.frontier(),
        solver: solver.name().into(),
        start: start.into(),
        iterations: stats.iterations,
        residual: stats.residual,
        converged: stats.converged,
        ms,
        cell_updates: stats.cell_updates,
        error_estimate: stats.error_estimate,
        local: None,
    };
    let is_mg = matches!(solver, BenchSolver::Multigrid(_));
    let boxes = is_mg || solver == BenchSolver::Flat;
    let (mut local_times, mut local_stats) = (Vec::new(), (SolveStats::default(), None));
    let (mut cold_times, mut zero_times, mut warm_times, mut scan_times) =
        (Vec::new(), Vec::new(), Vec::new(), Vec::new());
    let (mut cold_stats, mut zero_stats, mut warm_stats, mut scan_stats) = (
        SolveStats::default(),
        SolveStats::default(),
        SolveStats::default(),
        SolveStats::default(),
    );
    for _ in 0..repeat.max(1) {
        if is_mg {
            psi.fill(0.0);
            let t = Instant::now();
            zero_stats = run(&cold.labels, &mut psi, false, false, false).0;
            zero_times.push(t.elapsed().as_secs_f64() * 1e3);
        }
        psi.fill(0.0);
        let t = Instant::now();
        cold_stats = run(&cold.labels, &mut psi, false, true, false).0;
        cold_times.push(t.elapsed().as_secs_f64() * 1e3);
        if screened {
            let mut after = psi.clone();
            let t = Instant::now();
            scan_stats = run(&scan.labels, &mut after, true, true, false).0;
            scan_times.push(t.elapsed().as_secs_f64() * 1e3);
            if boxes {
                let mut after = psi.clone();
                let t = Instant::now();
                local_stats = run(&scan.labels, &mut after, true, true, true);
                local_times.push(t.elapsed().as_secs_f64() * 1e3);
            }
        }
        let t = Instant::now();
        warm_stats = run(&warm.labels, &mut psi, true, true, false).0;
        warm_times.push(t.elapsed().as_secs_f64() * 1e3);
    }
    let mut rows = vec![row(&cold, "cold", cold_stats, median(cold_times))];
    if is_mg {
        rows.push(row(&cold, "zero", zero_stats, median(zero_times)));
    }
    rows.push(row(&warm, "warm", warm_stats, median(warm_times)));
    if screened {
        rows.push(row(&scan, "scan", scan_stats, median(scan_times)));
        if !local_times.is_empty() {
            let mut local = row(&scan, "scan (local)", local_stats.0, median(local_times));
            local.local = local_stats.1;
            rows.push(local);
        }
    }
    rows
}

/// How far a scan's change to the screened field reaches: the cells whose `u` moved by more
/// than `threshold` between the cold problem's solution and the solution after a scan
/// ([`rooms_after_a_scan`]), both solved to a relative residual of 1e-7.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ScanReach {
    /// The change that counts.
    pub threshold: f32,
    /// Interior cells whose `u` moved by more.
    pub cells: usize,
    /// Interior cells of the problem after the scan.
    pub interior: usize,
    /// The smallest box holding them: low and high corners (voxel indices), `None` if none.
    pub bounds: Option<([u16; 3], [u16; 3])>,
}

impl ScanReach {
    /// Cells of the grid inside [`ScanReach::bounds`].
    pub fn box_cells(&self) -> usize {
        self.bounds.map_or(0, |(lo, hi)| {
            (0..3).map(|k| usize::from(hi[k] - lo[k]) + 1).product()
        })
    }
}

/// [`ScanReach`] for each of `thresholds`, on the rooms problem on `dims` with the screened
/// field's shift `screening` (κ²h²): what a re-solve after a scan has to change, and so what a
/// re-solve confined to a box around the scan could leave alone.
pub fn scan_reach(dims: Dims, screening: f32, thresholds: &[f32]) -> Vec<ScanReach> {
    let (mut cold, mut scan) = (rooms_with_doors(dims, 0), rooms_after_a_scan(dims));
    harmonic_core::field::release_source(&mut cold.labels);
    harmonic_core::field::release_source(&mut scan.labels);
    let mut scratch = MultigridScratch::new(&dims);
    let mut solve = |labels: &[Label], u: &mut [f32], warm_start: bool| {
        let params = SolveParams {
            tolerance: 1e-7,
            max_iterations: 1000,
            warm_start,
            screening,
            max_error: f32::INFINITY,
        };
        let mut mg = Multigrid::new(dims, scratch.storage()).expect("scratch sized by scratch_size");
        mg.solve(labels, u, &params, Method::Pcg).expect("valid problem");
    };
    let mut before = vec![0.0f32; dims.len()];
    solve(&cold.labels, &mut before, false);
    let mut after = before.clone();
    solve(&scan.labels, &mut after, true);
    let interior: Vec<usize> = (0..dims.len())
        .filter(|&i| scan.labels[i] == Label::Interior)
        .collect();
    thresholds
        .iter()
        .map(|&threshold| {
            let mut bounds: Option<([u16; 3], [u16; 3])> = None;
            let mut cells = 0;
            for &i in interior
                .iter()
                .filter(|&&i| (after[i] - before[i]).abs() > threshold)
            {
                cells += 1;
                let v = dims.voxel(i);
                let c = [v.x, v.y, v.z];
                let (lo, hi) = bounds.get_or_insert((c, c));
                for k in 0..3 {
                    lo[k] = lo[k].min(c[k]);
                    hi[k] = hi[k].max(c[k]);
                }
            }
            ScanReach {
                threshold,
                cells,
                interior: interior.len(),
                bounds,
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rooms_problem_has_the_advertised_shape() {
        let p = rooms_with_doors(Dims::new(64, 64, 32).unwrap(), 0);
        assert!((90_000..130_000).contains(&p.unknowns()), "{}", p.unknowns());
        assert_eq!(p.frontier(), 100);
        assert_eq!(p.labels.iter().filter(|l| **l == Label::Source).count(), 1);
        let q = rooms_with_doors(Dims::new(64, 64, 32).unwrap(), 1);
        assert_ne!(p.labels, q.labels, "a scan changes the problem");
    }

    #[test]
    fn a_scan_changes_the_screened_field_only_near_what_it_saw() {
        // The frontier patch sits on the far wall (x = 62) of the last room; the scan resolved
        // one row of it. The field's change decays with the distance from that row and at each
        // door on the way, so the change that matters stays in the rooms near it.
        let dims = Dims::new(64, 64, 32).unwrap();
        let reach = scan_reach(dims, 0.09, &[1e-2, 1e-5, 1e-9]);
        let (near, solve, all) = (reach[0], reach[1], reach[2]);
        assert!(
            near.cells > 0 && near.cells < solve.cells && solve.cells < all.cells,
            "{reach:?}"
        );
        // A tenth of the cells or so move by more than the explorer's solve resolves (~1e-5).
        assert!(solve.cells * 4 < solve.interior, "{reach:?}");
        let (lo, hi) = solve.bounds.unwrap();
        assert!(hi[0] >= 60 && lo[0] > 20 && lo[1] > 20, "{reach:?}");
        assert!(solve.box_cells() * 3 < dims.len(), "{reach:?}");
    }

    #[test]
    fn a_scan_resolves_one_row_of_the_frontier_patch() {
        let dims = Dims::new(64, 64, 32).unwrap();
        let (p, q) = (rooms_with_doors(dims, 0), rooms_after_a_scan(dims));
        assert_eq!(q.frontier(), 90);
        assert_eq!(q.unknowns(), p.unknowns() + 10);
        let changed = p.labels.iter().zip(&q.labels).filter(|(a, b)| a != b).count();
        assert_eq!(changed, 10);
    }

    #[test]
    fn a_screened_re_solve_after_a_scan_starts_from_the_last_solution_and_converges() {
        let dims = Dims::new(32, 32, 16).unwrap();
        let rows = measure(dims, BenchSolver::Multigrid(Method::Pcg), 1e-5, 1, 0.09, None);
        let get = |start: &str| rows.iter().find(|r| r.start == start).unwrap();
        let (zero, scan) = (get("zero"), get("scan"));
        assert!(zero.converged && scan.converged, "{rows:?}");
        assert!(scan.iterations < zero.iterations, "{rows:?}");
        // Laplace's problem has no scan row (its vehicle moves with every scan).
        let laplace = measure(dims, BenchSolver::Multigrid(Method::Pcg), 1e-6, 1, 0.0, None);
        assert!(laplace.iter().all(|r| r.start != "scan"), "{laplace:?}");
    }

    /// The benchmark's scan re-solved in boxes: the whole grid meets the tolerance, with a
    /// fraction of the whole-grid re-solve's work, in boxes well short of the grid.
    #[test]
    fn the_scan_re_solved_in_boxes_meets_the_tolerance_for_less_work() {
        let dims = Dims::new(64, 64, 32).unwrap();
        for method in [Method::Pcg, Method::VCycle] {
            let rows = measure(dims, BenchSolver::Multigrid(method), 1e-5, 1, 0.09, None);
            let get = |start: &str| rows.iter().find(|r| r.start == start).unwrap();
            let (whole, local) = (get("scan"), get("scan (local)"));
            let boxes = local.local.unwrap();
            assert!(!boxes.whole && boxes.boxes >= 1, "{rows:?}");
            assert!(local.converged && local.residual <= 1e-5, "{rows:?}");
            assert!(boxes.last_cells < dims.len() / 2, "{rows:?}");
            assert!(2 * local.cell_updates < whole.cell_updates, "{rows:?}");
        }
    }

    #[test]
    fn warm_and_full_multigrid_starts_beat_a_zero_start() {
        let dims = Dims::new(32, 32, 16).unwrap();
        for method in [Method::Pcg, Method::VCycle] {
            // 1e-5, the explorer's tolerance: at 1e-6 this grid's Laplace solve stops at its
            // f32 rounding floor (about 1.03e-6), which is honestly not converged.
            let rows = measure(dims, BenchSolver::Multigrid(method), 1e-5, 1, 0.0, None);
            let get = |start: &str| rows.iter().find(|r| r.start == start).unwrap();
            let (cold, zero, warm) = (get("cold"), get("zero"), get("warm"));
            assert!(cold.converged && zero.converged && warm.converged, "{rows:?}");
            assert!(warm.iterations < zero.iterations, "{method:?}: {rows:?}");
            assert!(cold.iterations < zero.iterations, "{method:?}: {rows:?}");
        }
    }
}
