//! Re-solves confined to a box around what changed.
//!
//! The screened field ([`crate::field`]) does not depend on where the vehicle is, and its
//! Green's function falls as `e^{−κr}`: a scan that resolves part of a frontier changes `u`
//! only near it (BENCHMARKS.md, "How far a scan reaches"). A whole-grid warm start still pays
//! for every cell, every cycle. [`resolve_near`] instead
//!
//! 1. computes the residual of the new problem at the old solution and the box around the
//!    cells where it is large ([`LocalParams::threshold`]), widened by
//!    [`LocalParams::margin`] voxels on every side;
//! 2. cuts that box out into lent scratch, its rim (the box's outer layer, where it is not
//!    the grid's border) made Dirichlet cells that hold the values outside, and solves it with
//!    the caller's [`Multigrid`], laid out again for the box in the same storage;
//! 3. writes the box's interior back and checks the *whole grid's* residual against the same
//!    tolerance a whole-grid solve stops at: a solution this accepts meets the rule a global
//!    solve's does. Where the check fails (the change reached the rim) each rim face that
//!    still carries the change moves out by the distance `e^{−κr}` needs to bring it down to
//!    its share, and the box is solved again, up to [`LocalParams::max_boxes`] boxes or
//!    [`LocalParams::max_share`] of the grid; beyond that (or if a box solve fails) it solves
//!    the whole grid itself, warm from what the boxes left (never worse than the start), and
//!    returns [`Local::Whole`].
//!
//! Laplace's equation (no screening) changes everywhere when anything does, so it always
//! goes to the whole grid.

#[cfg(feature = "flat")]
use super::flat::Flat;
use super::multigrid::{Method, Multigrid};
use super::{
    error_estimate, error_met, for_each_row, rounding2, rounding_row, row_residuals, Active, Contraction,
    Dirichlet, Residual, Screen, SolveError, SolveParams, SolveStats,
};
use crate::domain::Label;
use crate::map::Dims;

/// Storage for the box: a label and a value per cell of the largest box to solve (the grid's
/// size fits any).
pub struct LocalScratch<'a> {
    /// The box's labels.
    pub labels: &'a mut [Label],
    /// The box's values.
    pub psi: &'a mut [f32],
}

/// How far a local re-solve reaches.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LocalParams {
    /// Cells whose residual exceeds this share of the whole grid's allowed residual
    /// (`tolerance · ‖b‖`) must lie in the box.
    pub threshold: f32,
    /// Voxels added on every side of those cells: how far the change is let spread.
    pub margin: usize,
    /// Boxes tried before the whole grid is solved instead.
    pub max_boxes: u8,
    /// Largest box worth solving on its own, as a share of the grid's cells.
    pub max_share: f32,
}

impl LocalParams {
    /// Settings for the screened field with screening `s = κ²h²` solved to `tolerance`. The
    /// change a scan makes falls as `e^{−κr}` (κ = √s per voxel) from where it acted, so
    /// the margin is the distance over which it falls by the square root of the tolerance
    /// (the box grows by as much again if the check finds it was not enough).
    pub fn for_screening(screening: f32, tolerance: f32) -> Self {
        let kappa = libm::sqrtf(screening.max(0.0));
        let fall = -0.5 * libm::logf(tolerance.clamp(1e-12, 0.5));
        let margin = if kappa > 0.0 {
            libm::ceilf(fall / kappa).clamp(2.0, 64.0) as usize
        } else {
            64
        };
        Self {
            threshold: 0.01,
            margin,
            max_boxes: 3,
            max_share: 0.5,
        }
    }
}

/// How a local re-solve solved.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Local {
    /// In boxes; the whole grid meets the tolerance.
    Solved(LocalStats),
    /// The boxes gave the grid back: a whole-grid solve from what they left. Its stats, with
    /// the work the boxes spent (box solves and residual passes) added to its cell updates.
    Whole(SolveStats),
}

impl Local {
    /// The stats of the solve, whichever way it went.
    pub fn stats(&self) -> SolveStats {
        match self {
            Local::Solved(s) => s.stats,
            Local::Whole(s) => *s,
        }
    }
}

/// A local re-solve's statistics.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct LocalStats {
    /// Iterations and cell updates summed over the boxes (the residual passes included);
    /// residual, floor, convergence and error estimate those of the whole grid.
    pub stats: SolveStats,
    /// Boxes solved (0: the old solution already met the tolerance).
    pub boxes: u8,
    /// Cells of the last box.
    pub box_cells: usize,
}

/// A box of cells, `lo` inclusive, `hi` exclusive.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Cells {
    lo: [usize; 3],
    hi: [usize; 3],
}

/// `[f(a₀, b₀), f(a₁, b₁), f(a₂, b₂)]`.
fn zip3(a: [usize; 3], b: [usize; 3], f: impl Fn(usize, usize) -> usize) -> [usize; 3] {
    let ([a0, a1, a2], [b0, b1, b2]) = (a, b);
    [f(a0, b0), f(a1, b1), f(a2, b2)]
}

/// The grid's extent along x, y, z.
fn axes(dims: &Dims) -> [usize; 3] {
    [dims.nx(), dims.ny(), dims.nz()]
}

impl Cells {
    fn point(p: [usize; 3]) -> Self {
        Self {
            lo: p,
            hi: p.map(|c| c + 1),
        }
    }

    fn union(self, o: Self) -> Self {
        Self {
            lo: zip3(self.lo, o.lo, usize::min),
            hi: zip3(self.hi, o.hi, usize::max),
        }
    }

    /// Widened by `m` on every side, within `dims`.
    fn widened(self, m: usize, dims: &Dims) -> Self {
        self.grown([m; 6], dims)
    }

    fn contains(&self, p: [usize; 3]) -> bool {
        p.iter()
            .zip(self.lo.iter().zip(&self.hi))
            .all(|(c, (lo, hi))| lo <= c && c < hi)
    }

    /// The rim faces (bits −x, +x, −y, +y, −z, +z) `p` lies on: the box's outer layer where
    /// the grid of `n` cells goes on beyond it.
    fn rim_faces(&self, p: [usize; 3], n: &[usize; 3]) -> u8 {
        if !self.contains(p) {
            return 0;
        }
        let mut f = 0;
        let axes = p.iter().zip(&self.lo).zip(&self.hi).zip(n);
        for (a, (((&c, &lo), &hi), &n)) in axes.enumerate() {
            if c == lo && c > 0 {
                f |= 1 << (2 * a);
            }
            if c + 1 == hi && c + 1 < n {
                f |= 1 << (2 * a + 1);
            }
        }
        f
    }

    /// Each face moved out by `by` (−x, +x, −y, +y, −z, +z), within `dims`.
    fn grown(self, by: [usize; 6], dims: &Dims) -> Self {
        let [mx, px, my, py, mz, pz] = by;
        Self {
            lo: zip3(self.lo, [mx, my, mz], usize::saturating_sub),
            hi: zip3(
                zip3(self.hi, [px, py, pz], usize::saturating_add),
                axes(dims),
                usize::min,
            ),
        }
    }

    fn extent(&self) -> [usize; 3] {
        zip3(self.hi, self.lo, usize::saturating_sub)
    }

    fn len(&self) -> usize {
        self.extent().iter().product()
    }
}

/// What a residual pass over a region of the grid found.
#[derive(Debug, Clone, Copy, Default)]
struct Scan {
    /// Sum of the squared residuals of the region's interior rows.
    r2: f64,
    /// Sum of their rows' rounding terms ([`rounding_row`]).
    e2: f64,
    /// Largest residual above the threshold, and at or below it.
    max: [f32; 2],
    /// The box around the cells outside `within` whose residual exceeds the threshold (inside
    /// it, the rim is measured by face and the rest is the box solve's concern).
    large: Option<Cells>,
    /// Largest residual on each rim face of `within` (−x, +x, −y, +y, −z, +z): how far the
    /// change still is from fading where the box held the values fixed.
    rim: [f32; 6],
    /// Cells on `within`'s rim.
    rim_cells: usize,
}

/// The residual of the cells of `region`, those beyond `within` whose residual exceeds `tau`,
/// and the residual on `within`'s rim.
fn scan(
    dims: &Dims,
    screen: &Screen,
    (labels, psi): (&[Label], &[f32]),
    region: &Cells,
    tau: f32,
    within: Option<&Cells>,
) -> Scan {
    let mut out = Scan::default();
    let n = axes(dims);
    let active = Active::bounded(dims, region.lo, region.hi);
    let xs = active.xs();
    for_each_row(dims, &active, screen, labels, psi, |st, row| {
        let (mut row_r, mut row_e) = (0.0f32, 0.0f32);
        row_residuals(st, row, None, |x, r, k| {
            if !xs.contains(&x) {
                // The grid's edge cells, which every row visits.
                return;
            }
            row_r += r * r;
            row_e += rounding2(k, row.get(x).copied().unwrap_or(0.0));
            let p = [x, st.y, st.z];
            let faces = within.map_or(0u8, |b| b.rim_faces(p, &n));
            if faces != 0 {
                out.rim_cells += 1;
                for (f, m) in out.rim.iter_mut().enumerate() {
                    if faces & (1 << f) != 0 {
                        *m = m.max(r.abs());
                    }
                }
            }
            let large = r.abs() > tau;
            let [above, below] = &mut out.max;
            if large {
                *above = above.max(r.abs());
            } else {
                *below = below.max(r.abs());
            }
            if large && !within.is_some_and(|b| b.contains(p)) {
                let p = Cells::point(p);
                out.large = Some(out.large.map_or(p, |b| b.union(p)));
            }
        });
        out.r2 += f64::from(row_r);
        out.e2 += rounding_row(row_e);
    });
    out
}

/// Calls `f(grid index, box index, on the rim)` for every cell of `cells`, row by row.
fn for_each_cell(dims: &Dims, cells: &Cells, mut f: impl FnMut(usize, usize, bool)) {
    let ([x0, y0, z0], [x1, y1, z1]) = (cells.lo, cells.hi);
    let [nx, ny, nz] = axes(dims);
    // A face of the box is a rim where the grid goes on beyond it.
    let rim = |c: usize, lo: usize, hi: usize, n: usize| (c == lo && c > 0) || (c + 1 == hi && c + 1 < n);
    let mut j = 0;
    for z in z0..z1 {
        for y in y0..y1 {
            let start = nx * (y + ny * z);
            let row_rim = rim(y, y0, y1, ny) || rim(z, z0, z1, nz);
            for x in x0..x1 {
                f(start + x, j, row_rim || rim(x, x0, x1, nx));
                j += 1;
            }
        }
    }
}

/// A solver that can solve boxes cut out of its grid in its own storage: the multigrid
/// ([`WithMethod`]) or the host's flat solver ([`Flat`]).
pub trait BoxSolver {
    /// The grid the solver is laid out for.
    fn grid(&self) -> Dims;
    /// Lays the solver out for a grid of `fine` (no larger along any axis than the one its
    /// storage was made for).
    fn lay_out(&mut self, fine: Dims) -> Result<(), SolveError>;
    /// Solves a box whose Dirichlet cells hold the values in `psi` (warm).
    fn solve_box(
        &mut self,
        labels: &[Label],
        psi: &mut [f32],
        params: &SolveParams,
    ) -> Result<SolveStats, SolveError>;
    /// Solves the whole grid (standard Dirichlet values).
    fn solve_whole(
        &mut self,
        labels: &[Label],
        psi: &mut [f32],
        params: &SolveParams,
    ) -> Result<SolveStats, SolveError>;
}

/// The multigrid with the method its solves use.
pub struct WithMethod<'m, 'a>(pub &'m mut Multigrid<'a>, pub Method);

impl BoxSolver for WithMethod<'_, '_> {
    fn grid(&self) -> Dims {
        self.0.fine_dims()
    }
    fn lay_out(&mut self, fine: Dims) -> Result<(), SolveError> {
        self.0.relayout(fine)
    }
    fn solve_box(
        &mut self,
        labels: &[Label],
        psi: &mut [f32],
        params: &SolveParams,
    ) -> Result<SolveStats, SolveError> {
        self.0.solve_with(labels, psi, params, self.1, Dirichlet::Given)
    }
    fn solve_whole(
        &mut self,
        labels: &[Label],
        psi: &mut [f32],
        params: &SolveParams,
    ) -> Result<SolveStats, SolveError> {
        self.0.solve(labels, psi, params, self.1)
    }
}

#[cfg(feature = "flat")]
impl BoxSolver for Flat<'_> {
    fn grid(&self) -> Dims {
        self.fine_dims()
    }
    fn lay_out(&mut self, fine: Dims) -> Result<(), SolveError> {
        self.relayout(fine)
    }
    fn solve_box(
        &mut self,
        labels: &[Label],
        psi: &mut [f32],
        params: &SolveParams,
    ) -> Result<SolveStats, SolveError> {
        self.solve_with(labels, psi, params, Dirichlet::Given)
    }
    fn solve_whole(
        &mut self,
        labels: &[Label],
        psi: &mut [f32],
        params: &SolveParams,
    ) -> Result<SolveStats, SolveError> {
        self.solve(labels, psi, params)
    }
}

/// Re-solves the problem `labels` in `psi` (holding the last solution, the warm start) with
/// `solver` (laid out for the whole grid, which it is again on return) in boxes around what
/// changed, or over the whole grid where the boxes give up; see the [module
/// documentation](self). `params` are the whole-grid solve's (`warm_start` is implied); the box
/// scratch must hold [`LocalParams::max_share`] of the grid's cells.
pub fn resolve_near(
    solver: &mut impl BoxSolver,
    labels: &[Label],
    psi: &mut [f32],
    params: &SolveParams,
    local: &LocalParams,
    scratch: LocalScratch<'_>,
) -> Result<Local, SolveError> {
    let warm = SolveParams {
        warm_start: true,
        ..*params
    };
    let mut work = 0u64;
    // A box solve that fails (never seen) writes nothing back, so `psi` is still a warm start
    // for the whole grid, whose solve reports any error of its own.
    if let Ok(Some(s)) = in_boxes(solver, labels, psi, &warm, local, scratch, &mut work) {
        return Ok(Local::Solved(s));
    }
    let mut s = solver.solve_whole(labels, psi, &warm)?;
    s.cell_updates += work;
    Ok(Local::Whole(s))
}

/// The boxes of [`resolve_near`]: the stats if they met the tolerance, `None` where they gave
/// up; `work` counts the cell updates spent either way.
fn in_boxes(
    solver: &mut impl BoxSolver,
    labels: &[Label],
    psi: &mut [f32],
    params: &SolveParams,
    local: &LocalParams,
    scratch: LocalScratch<'_>,
    work: &mut u64,
) -> Result<Option<LocalStats>, SolveError> {
    let dims = solver.grid();
    let n = dims.len();
    let (labels, psi) = super::checked_problem(&dims, labels, psi, params, Dirichlet::Standard)?;
    let screen = Screen::new(params.screening);
    let b2 = super::dirichlet_norm2(&dims, labels);
    if screen.shift <= 0.0 || b2 == 0.0 {
        return Ok(None);
    }
    let allowed = params.tolerance * libm::sqrt(b2) as f32;
    let tau = local.threshold * allowed;
    let kappa = libm::sqrtf(screen.shift);
    let grid = Cells {
        lo: [0; 3],
        hi: axes(&dims),
    };
    let first = scan(&dims, &screen, (labels, psi), &grid, tau, None);
    *work += n as u64;
    // The whole grid's sums, kept up to date from the region each box solve can change (the
    // box and the cells beside it): every other cell keeps its residual, which the first
    // pass found at or below `max_still` unless it lies in the first box.
    let (mut r2, mut e2) = (first.r2, first.e2);
    let [_, max_still] = first.max;
    let mut res = Residual::from_sums(r2, e2, first.max[0].max(max_still), b2);
    let done = |res: &Residual| {
        let estimate = error_estimate(&Contraction::default(), res, &screen);
        res.meets(params.tolerance) && error_met(estimate, params.max_error)
    };
    let mut out = LocalStats {
        stats: SolveStats {
            initial_residual: res.relative,
            ..SolveStats::default()
        },
        ..LocalStats::default()
    };
    let capacity = scratch.labels.len().min(scratch.psi.len());
    let limit = ((local.max_share.clamp(0.0, 1.0) * n as f32) as usize).min(capacity);
    let mut next = first.large.map(|c| c.widened(local.margin, &dims));
    let mut solved: Option<Cells> = None;
    while !done(&res) {
        let Some(cells) = next.filter(|c| Some(*c) != solved) else {
            // Residual spread thin everywhere (a changed κ), or a box that cannot grow.
            return Ok(None);
        };
        if out.boxes >= local.max_boxes || cells.len() > limit {
            return Ok(None);
        }
        let [ex, ey, ez] = cells.extent();
        let Ok(box_dims) = Dims::new(ex, ey, ez) else {
            return Ok(None);
        };
        let (Some(bl), Some(bp)) = (
            scratch.labels.get_mut(..cells.len()),
            scratch.psi.get_mut(..cells.len()),
        ) else {
            return Ok(None);
        };
        let region = cells.widened(1, &dims);
        let before = scan(&dims, &screen, (labels, psi), &region, tau, None);
        for_each_cell(&dims, &cells, |i, j, rim| {
            let l = labels.get(i).copied().unwrap_or(Label::Outside);
            if let (Some(bl), Some(bp)) = (bl.get_mut(j), bp.get_mut(j)) {
                // The rim holds the values outside the box fixed.
                *bl = if rim && l == Label::Interior {
                    Label::Frontier
                } else {
                    l
                };
                *bp = psi.get(i).copied().unwrap_or(0.0);
            }
        });
        let b2_box = super::dirichlet_norm2_given(&box_dims, bl, bp);
        let box_params = SolveParams {
            // Leave half the whole grid's allowed residual to the rest of it.
            tolerance: if b2_box > 0.0 {
                0.5 * allowed / libm::sqrt(b2_box) as f32
            } else {
                params.tolerance
            },
            max_error: f32::INFINITY,
            ..*params
        };
        solver.lay_out(box_dims)?;
        let result = solver.solve_box(bl, bp, &box_params);
        solver.lay_out(dims)?;
        let s = result?;
        out.boxes += 1;
        out.box_cells = cells.len();
        out.stats.iterations += s.iterations;
        *work += s.cell_updates;
        for_each_cell(&dims, &cells, |i, j, rim| {
            if !rim && labels.get(i) == Some(&Label::Interior) {
                if let (Some(p), Some(v)) = (psi.get_mut(i), bp.get(j)) {
                    *p = *v;
                }
            }
        });
        let after = scan(&dims, &screen, (labels, psi), &region, tau, Some(&cells));
        *work += 2 * region.len() as u64;
        r2 += after.r2 - before.r2;
        e2 += after.e2 - before.e2;
        // Rounding can leave the sums a hair below zero; a NaN passes, and fails the check.
        let kept = |sum: f64| if sum < 0.0 { 0.0 } else { sum };
        let max = after.max[0].max(after.max[1]).max(max_still);
        res = Residual::from_sums(kept(r2), kept(e2), max, b2);
        // Where the rim still carries the change, move that face out by the distance over
        // which e^{−κr} brings it down to its share of the allowed residual.
        let per_cell = 0.5 * allowed / libm::sqrtf(after.rim_cells.max(1) as f32);
        let by = after.rim.map(|r| {
            if r > per_cell && kappa > 0.0 {
                (libm::ceilf(libm::logf(r / per_cell) / kappa) as usize).max(2)
            } else {
                0
            }
        });
        let grown = cells.grown(by, &dims);
        next = Some(
            after
                .large
                .map_or(grown, |l| grown.union(l.widened(local.margin, &dims))),
        );
        solved = Some(cells);
    }
    out.stats.cell_updates = *work;
    out.stats.residual = res.relative;
    out.stats.floor = res.floor;
    out.stats.error_estimate = error_estimate(&Contraction::default(), &res, &screen);
    out.stats.converged = true;
    Ok(Some(out))
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
    use crate::solve::multigrid::tests::Scratch as Storage;
    use crate::solve::screened_residual;
    use std::vec;
    use std::vec::Vec;

    /// Five rooms in a row joined by doors, a frontier patch on the far wall of the last; the
    /// scan (`scanned`) resolved the patch's lowest row.
    fn rooms(scanned: bool) -> (Dims, Vec<Label>) {
        let dims = Dims::new(120, 24, 16).unwrap();
        let mut labels = vec![Label::Interior; dims.len()];
        for (i, l) in labels.iter_mut().enumerate() {
            let v = dims.voxel(i);
            let (x, y, z) = (usize::from(v.x), usize::from(v.y), usize::from(v.z));
            let border = x == 0 || y == 0 || z == 0 || x == 119 || y == 23 || z == 15;
            let door = (10..13).contains(&y) && z < 10;
            if border || (x % 24 == 0 && !door) {
                *l = Label::Outside;
            }
            let lowest = if scanned { 5 } else { 4 };
            if x == 119 && (8..16).contains(&y) && (lowest..12).contains(&z) {
                *l = Label::Frontier;
            }
        }
        (dims, labels)
    }

    const SCREENING: f32 = 0.09;

    fn params(tolerance: f32, warm_start: bool, screening: f32) -> SolveParams {
        SolveParams {
            tolerance,
            warm_start,
            screening,
            ..SolveParams::default()
        }
    }

    /// The old problem solved cold to 1e-5 (as the explorer does), and the box scratch.
    fn solved_before(screening: f32) -> (Dims, Vec<f32>, Storage) {
        let (dims, before) = rooms(false);
        let mut storage = Storage::new(&dims, true);
        let mut psi = vec![0.0; dims.len()];
        let s = storage
            .multigrid(dims)
            .solve(&before, &mut psi, &params(1e-5, false, screening), Method::Auto)
            .unwrap();
        assert!(s.converged);
        (dims, psi, storage)
    }

    fn resolve(
        storage: &mut Storage,
        dims: Dims,
        labels: &[Label],
        psi: &mut [f32],
        screening: f32,
    ) -> Local {
        resolve_lending(storage, dims, labels, psi, screening, dims.len()).unwrap()
    }

    /// [`resolve_near`] with a box scratch of `cells` labels and values.
    fn resolve_lending(
        storage: &mut Storage,
        dims: Dims,
        labels: &[Label],
        psi: &mut [f32],
        screening: f32,
        cells: usize,
    ) -> Result<Local, SolveError> {
        let (mut bl, mut bp) = (vec![Label::Outside; cells], vec![0.0; cells]);
        let scratch = LocalScratch {
            labels: &mut bl,
            psi: &mut bp,
        };
        let local = LocalParams::for_screening(screening, 1e-5);
        let mut mg = storage.multigrid(dims);
        let out = resolve_near(
            &mut WithMethod(&mut mg, Method::Auto),
            labels,
            psi,
            &params(1e-5, true, screening),
            &local,
            scratch,
        );
        assert_eq!(
            mg.fine_dims(),
            dims,
            "the multigrid is laid out for the grid again"
        );
        out
    }

    /// How far a field is from `after` solved tightly (to 1e-8, warm from `old`).
    fn off_the_tight_solve(
        storage: &mut Storage,
        dims: Dims,
        after: &[Label],
        old: &[f32],
    ) -> impl Fn(&[f32]) -> f32 {
        let mut exact = old.to_vec();
        storage
            .multigrid(dims)
            .solve(after, &mut exact, &params(1e-8, true, SCREENING), Method::Auto)
            .unwrap();
        move |v: &[f32]| {
            v.iter()
                .zip(&exact)
                .map(|(a, b)| (a - b).abs())
                .fold(0.0f32, f32::max)
        }
    }

    /// The property the explorer relies on: a re-solve confined to boxes around the scan
    /// leaves the whole grid at the tolerance a whole-grid solve stops at, as close to the exact
    /// field as that solve, for a fraction of its work.
    #[test]
    fn a_scan_is_re_solved_in_a_box_to_the_whole_grids_tolerance() {
        let (dims, old, mut storage) = solved_before(SCREENING);
        let (_, after) = rooms(true);
        let mut local = old.clone();
        let Local::Solved(s) = resolve(&mut storage, dims, &after, &mut local, SCREENING) else {
            panic!("a scan at the far wall is re-solved locally");
        };
        assert!(s.boxes >= 1 && s.stats.converged, "{s:?}");
        assert!(s.box_cells < dims.len() / 2, "{s:?}");
        let checked = screened_residual(&dims, &after, &local, SCREENING);
        assert!(checked.relative <= 1e-5, "{checked:?}");
        // Kept up to date from the boxes' regions, the same residual as a whole-grid pass.
        assert!(
            (checked.relative - s.stats.residual).abs() <= 1e-3 * checked.relative,
            "{checked:?} {s:?}"
        );
        assert!(
            checked.max <= s.stats.error_estimate.unwrap() * SCREENING * 1.001,
            "{checked:?} {s:?}"
        );
        // The whole grid re-solved from the same start, and solved tightly.
        let mut whole = old.clone();
        let w = storage
            .multigrid(dims)
            .solve(&after, &mut whole, &params(1e-5, true, SCREENING), Method::Auto)
            .unwrap();
        let worst = off_the_tight_solve(&mut storage, dims, &after, &old);
        assert!(
            worst(&local) <= 2e-5,
            "local {} whole {}",
            worst(&local),
            worst(&whole)
        );
        assert!(
            s.stats.cell_updates < w.cell_updates,
            "{} against {}",
            s.stats.cell_updates,
            w.cell_updates
        );
        // The scan did change the field.
        assert!(worst(&old) > 1e-2);
    }

    #[test]
    fn a_solved_problem_needs_no_box() {
        let (dims, mut psi, mut storage) = solved_before(SCREENING);
        let (_, before) = rooms(false);
        let kept = psi.clone();
        let Local::Solved(s) = resolve(&mut storage, dims, &before, &mut psi, SCREENING) else {
            panic!("nothing changed");
        };
        assert_eq!((s.boxes, s.stats.iterations), (0, 0));
        assert_eq!(psi, kept);
    }

    /// Laplace's field changes everywhere when anything does, and so does the screened field
    /// whose κ changed: both are solved over the whole grid, to its tolerance.
    #[test]
    fn laplace_and_a_changed_screening_are_left_to_the_whole_grid() {
        let (_, after) = rooms(true);
        for (solved, resolved) in [(0.0, 0.0), (SCREENING, 0.25 * SCREENING)] {
            let (dims, mut psi, mut storage) = solved_before(solved);
            let out = resolve(&mut storage, dims, &after, &mut psi, resolved);
            assert!(
                matches!(out, Local::Whole(s) if s.converged),
                "{solved} → {resolved}: {out:?}"
            );
        }
    }

    #[test]
    fn a_box_scratch_too_small_leaves_the_whole_grid() {
        let (dims, mut psi, mut storage) = solved_before(SCREENING);
        let (_, after) = rooms(true);
        let out = resolve_lending(&mut storage, dims, &after, &mut psi, SCREENING, 100);
        assert!(matches!(out, Ok(Local::Whole(s)) if s.converged), "{out:?}");
        let checked = screened_residual(&dims, &after, &psi, SCREENING);
        assert!(checked.relative <= 1e-5, "{checked:?}");
    }

    /// The host's flat solver in the same boxes: the whole grid at its tolerance, as close to
    /// the exact field as the multigrid's boxes, for less work than its own whole-grid
    /// re-solve; laid out for the whole grid again afterwards, whose next solve is unchanged.
    #[cfg(feature = "flat")]
    #[test]
    fn the_flat_solver_re_solves_a_scan_in_boxes() {
        use crate::solve::flat::{flat_scratch_len, Flat};
        let (dims, old, mut storage) = solved_before(SCREENING);
        let (_, after) = rooms(true);
        let mut values = vec![0.0f32; flat_scratch_len(&dims)];
        let mut flat = Flat::new(dims, &mut values).unwrap();
        let (mut bl, mut bp) = (vec![Label::Outside; dims.len()], vec![0.0; dims.len()]);
        let mut local = old.clone();
        let out = resolve_near(
            &mut flat,
            &after,
            &mut local,
            &params(1e-5, true, SCREENING),
            &LocalParams::for_screening(SCREENING, 1e-5),
            LocalScratch {
                labels: &mut bl,
                psi: &mut bp,
            },
        );
        let Ok(Local::Solved(s)) = out else {
            panic!("a scan at the far wall is re-solved locally: {out:?}");
        };
        assert_eq!(flat.fine_dims(), dims);
        assert!(
            s.boxes >= 1 && s.stats.converged && s.box_cells < dims.len() / 2,
            "{s:?}"
        );
        let checked = screened_residual(&dims, &after, &local, SCREENING);
        assert!(checked.relative <= 1e-5, "{checked:?}");
        let mut whole = old.clone();
        let w = flat
            .solve(&after, &mut whole, &params(1e-5, true, SCREENING))
            .unwrap();
        let worst = off_the_tight_solve(&mut storage, dims, &after, &old);
        assert!(
            worst(&local) <= 2e-5 && worst(&whole) <= 2e-5,
            "local {} whole {}",
            worst(&local),
            worst(&whole)
        );
        assert!(
            s.stats.cell_updates < w.cell_updates,
            "{} against {}",
            s.stats.cell_updates,
            w.cell_updates
        );
    }
}
