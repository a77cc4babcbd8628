//! A multigrid whose every pass is one flat loop over a padded plane: the host's fast solver.
//!
//! [`super::multigrid`] walks its levels row by row through labels, masks and stencil structs
//! that the firmware's memory can afford; each pass costs 3–5 ns per cell on the development
//! machine whatever its kernel (BENCHMARKS.md). This solver spends memory instead, which the host
//! has: every level stores its operator as arrays — the `+x`, `+y`, `+z` face conductances, the
//! diagonal and its reciprocal — on a grid padded by [`PAD`] cells of zeros on every side. Then
//! each pass (a smoothing sweep, a residual, `A·p`) is the same seven-point formula over a
//! whole z-plane as one contiguous loop, with no test for walls, edges or labels: a closed face
//! is a zero weight, a cell outside the domain has a zero reciprocal diagonal and stays 0. The
//! compiler vectorises those loops.
//!
//! **The discrete problem is the one [`super::multigrid`] solves** (the same rows; the tests
//! check the solutions against each other and against exact solves). Dirichlet cells are
//! folded into the right-hand side: an interior row keeps a frontier neighbour as `+1` in `b`
//! and as `1` on its diagonal, a source neighbour (ψ = 0) as `1` on its diagonal only, so the
//! unknowns are the interior cells alone and every other cell holds 0.
//!
//! **Smoother.** Chebyshev polynomial steps in the Jacobi-preconditioned operator (`Smoother`;
//! [`W_SWEEPS`] or [`V_SWEEPS`] before and after the coarse correction): a step reads the two
//! previous iterates only, so it needs no colouring and runs as one loop per plane. Pre- and
//! post-smoothing are the same polynomial, so the cycle is a symmetric preconditioner for
//! conjugate gradients (MGPCG, as [`super::multigrid`]): a V-cycle for the
//! screened field, a W-cycle (each coarse level solved twice) for Laplace's equation, whose
//! nearly singular coarse levels one visit leaves far from solved (`Cycle`).
//!
//! **Coarse levels** follow [`super::multigrid`]'s rules: a coarse cell is interior if any child
//! is, else Dirichlet if any child is, else outside; a coarse face's conductance is the mean of
//! the (up to four) child faces between interior children, at least ½ where any is open; a
//! coarse cell's *sink* (its conductance to Dirichlet cells, whose correction is 0) is half the
//! sum of its interior children's sinks; the screening grows fourfold per level. The transfers
//! are trilinear interpolation renormalised over the coarse cells that are not outside, except
//! that a fine cell takes nothing from a coarse neighbour behind a wall (`Transfer`), and half
//! its transpose for the restriction, both done one axis at a time.
//!
//! **The box of the domain.** Each solve lays its levels out for the box of the interior
//! cells and the cells next to them (`Crop`), not for the whole grid: every cell beyond it is
//! outside the domain, which the padding stands for exactly, so the discrete problem is the
//! same and a domain that fills part of the grid (early in an exploration; a box
//! [`super::local`] cuts out across a frontier into unknown space) costs only its box.
//!
//! **Cold solves** start with full multigrid: the right-hand side restricted down the levels,
//! the coarsest level smoothed to convergence, and each finer level started from the coarser
//! solution interpolated and given one cycle.
//!
//! **Memory** ([`flat_scratch_len`]): about 22 `f32` per voxel (64 × 64 × 32: 2.90 million,
//! 11.1 MiB), against about 5 bytes per voxel for [`super::multigrid`], which the firmware
//! keeps. The fine level stores no face conductances (its faces are its interior mask,
//! `Arrays::w`), and conjugate gradients keep their residual in its right-hand side and
//! `A·p` in its sweep scratch (`KRYLOV_ARRAYS`).

use heapless::Vec as HVec;

use super::multigrid::{source_pins, LOCAL_RADIUS, MAX_PINS, MAX_RESTARTS};
use super::{
    checked_problem, clamp_to_bounds, converged, error_estimate, error_met, rounding_row, zip3, Active,
    Contraction, Dirichlet, Fork, Residual, Screen, SolveError, SolveParams, SolveStats, Solved, Stop,
    CLAMP_SLACK, PSI_FRONTIER, PSI_SOURCE,
};
use crate::mapping::map::Dims;
use crate::planning::domain::Label;

/// Cells of zero padding on every side of every level.
pub const PAD: usize = 2;
/// Chebyshev smoothing steps before and after each coarse correction of a W-cycle (Laplace's
/// equation, whose nearly singular coarse levels one visit leaves far from solved).
pub const W_SWEEPS: u32 = 3;
/// The same for a V-cycle (the screened field).
pub const V_SWEEPS: u32 = 2;
/// Jacobi damping (the coarsest level's sweeps).
const OMEGA: f32 = 6.0 / 7.0;
/// The Chebyshev smoother damps the eigenvalues of `D⁻¹A` in `[CHEB_MAX / CHEB_RATIO,
/// CHEB_MAX]`. Every row's diagonal is at least the sum of its face weights, so no eigenvalue
/// exceeds 2 (Gershgorin); on a seven-point grid the modes the next coarser level cannot hold
/// (some wavenumber above π/2) have eigenvalues of at least 1/3 of that, hence the ratio 6.
/// This is the textbook interval, not a value fitted to any world: on the houses of
/// `scripts/pyamg_compare.py` ratio 4 took one or two more MGPCG steps, ratio 10 as many or one
/// more.
const CHEB_MAX: f32 = 2.0;
/// See [`CHEB_MAX`].
const CHEB_RATIO: f32 = 6.0;
/// Centre of the Chebyshev interval.
const CHEB_THETA: f32 = (CHEB_MAX + CHEB_MAX / CHEB_RATIO) / 2.0;
/// Half-width of the Chebyshev interval.
const CHEB_DELTA: f32 = (CHEB_MAX - CHEB_MAX / CHEB_RATIO) / 2.0;

/// How a level is smoothed.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
enum Smoother {
    /// Damped Jacobi, ω = [`OMEGA`]: the coarsest level, which is smoothed to a solution.
    Jacobi,
    /// Chebyshev polynomial steps in `D⁻¹A` on the interval of [`CHEB_MAX`]: each step costs a
    /// Jacobi sweep and one more array read, and damps the modes the coarse levels miss
    /// better. Damped Jacobi leaves `5/7` of the worst such mode per sweep, `0.36` after
    /// three; Chebyshev leaves `0.34` after two steps and `0.15` after three.
    Chebyshev,
}
/// Jacobi sweeps on the coarsest level.
const COARSEST_SWEEPS: u32 = 64;
/// Most levels, the fine one included.
const MAX_LEVELS: usize = 12;
/// A level is coarsened again while every axis holds more than this many cells.
const MIN_COARSE: usize = 4;
/// Least conductance of a coarse face with any open child face (see [`super::multigrid`]).
const MIN_OPEN_FACE: f32 = 0.5;
/// A conjugate-gradient pass stops once its recursive residual is this share of the target
/// (the true residual decides after it).
const STOP_SHARE: f32 = 0.9;
/// `kind` values: the [`Label`] codes outside (0), interior (1), frontier (2) and source (3);
/// the Dirichlet kinds are the last two, coarse Dirichlet cells take the frontier's.
const OUT: f32 = 0.0;
const INTERIOR: f32 = 1.0;
const FRONTIER: f32 = 2.0;

/// Per-level arrays, in this order, each [`Grid::len`] long.
const LEVEL_ARRAYS: usize = 13;
/// The fine level's: the same but the face conductances, which are its interior mask (see
/// [`Arrays::w`]).
const FINE_ARRAYS: usize = LEVEL_ARRAYS - 3;
/// Fine-level arrays for conjugate gradients: right-hand side, solution, direction. The
/// residual is the fine level's `b`, which the preconditioner solves for (so it needs no copy),
/// and `A·p` goes to the fine level's `tmp`, free between preconditioner calls.
const KRYLOV_ARRAYS: usize = 3;

/// One level's padded grid.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Grid {
    /// Cells along each axis (unpadded).
    n: [usize; 3],
    /// Stride between rows.
    sy: usize,
    /// Stride between planes.
    sz: usize,
    /// Cells in the padded grid.
    len: usize,
}

impl Grid {
    fn new(n: [usize; 3]) -> Self {
        let sy = n[0] + 2 * PAD;
        let sz = sy * (n[1] + 2 * PAD);
        Grid {
            n,
            sy,
            sz,
            len: sz * (n[2] + 2 * PAD),
        }
    }

    /// Padded index of cell `(x, y, z)`.
    #[inline(always)]
    fn at(&self, x: usize, y: usize, z: usize) -> usize {
        (x + PAD) + self.sy * (y + PAD) + self.sz * (z + PAD)
    }

    /// The flat range of plane `z`'s rows, their x padding included.
    #[inline(always)]
    fn plane(&self, z: usize) -> core::ops::Range<usize> {
        let start = self.sz * (z + PAD) + self.sy * PAD;
        start..start + self.sy * self.n[1]
    }

    /// The next coarser grid.
    fn coarser(&self) -> Self {
        Grid::new([
            self.n[0].div_ceil(2),
            self.n[1].div_ceil(2),
            self.n[2].div_ceil(2),
        ])
    }

    /// Scratch of the transfers from this (coarse) grid to `fine`: the two intermediate grids.
    fn transfer_len(&self, fine: &Grid) -> (usize, usize) {
        let (cpx, cpy) = (self.n[0] + 2 * PAD, self.n[1] + 2 * PAD);
        let fpy = fine.n[1] + 2 * PAD;
        let fpz = fine.n[2] + 2 * PAD;
        (cpx * cpy * fpz, cpx * fpy * fpz)
    }
}

/// The grids of every level for a fine grid of `fine` cells along x, y, z.
fn grids(fine: [usize; 3]) -> HVec<Grid, MAX_LEVELS> {
    let mut out = HVec::new();
    let mut g = Grid::new(fine);
    let _ = out.push(g);
    while g.n.iter().all(|&d| d > MIN_COARSE) && out.len() < MAX_LEVELS {
        g = g.coarser();
        let _ = out.push(g);
    }
    out
}

/// `f32` values [`Flat::new`] needs for a fine grid of `fine`.
pub fn flat_scratch_len(fine: &Dims) -> usize {
    let gs = grids(fine.extent());
    level_blocks(&gs).iter().sum::<usize>() + gs.first().map_or(0, |g| KRYLOV_ARRAYS * g.len)
}

/// One level's arrays, carved out of the storage.
struct Arrays<'s> {
    /// Current iterate (the correction on coarse levels).
    u: &'s mut [f32],
    /// Right-hand side.
    b: &'s mut [f32],
    /// Residual scratch.
    r: &'s mut [f32],
    /// Sweep output and interpolation scratch.
    tmp: &'s mut [f32],
    /// `1 / diag` on interior cells, 0 elsewhere.
    inv: &'s mut [f32],
    /// The diagonal on interior cells, 0 elsewhere.
    diag: &'s mut [f32],
    /// `1 / den` of the transfers with the next coarser level on interior cells, 0 elsewhere.
    invden: &'s mut [f32],
    /// `+x`, `+y`, `+z` face conductances (non-zero only between two interior cells). Empty
    /// on the fine level, where a face's conductance is 1 between two interior cells and 0
    /// elsewhere: every vector a pass reads there holds 0 outside the interior, so the plain
    /// sum of the six neighbours is the weighted one ([`stencil`]), without three arrays to
    /// store and stream.
    w: [&'s mut [f32]; 3],
    /// Cell kind ([`OUT`], [`INTERIOR`], [`FRONTIER`], [`SOURCE`]).
    kind: &'s mut [f32],
    /// The weight of each cell's other parent along x in the transfers with the next coarser
    /// level ([`Transfer`]).
    ox: &'s mut [f32],
    /// Conductance to Dirichlet cells.
    sink: &'s mut [f32],
}

impl<'s> Arrays<'s> {
    /// Splits one level's block (at least `LEVEL_ARRAYS · n`, or `FINE_ARRAYS · n` without
    /// `weighted` faces) into its arrays.
    fn carve(block: &'s mut [f32], n: usize, weighted: bool) -> Option<Self> {
        let mut rest = block;
        let mut take = || -> Option<&'s mut [f32]> {
            let (a, b) = core::mem::take(&mut rest).split_at_mut_checked(n)?;
            rest = b;
            Some(a)
        };
        Some(Arrays {
            u: take()?,
            b: take()?,
            r: take()?,
            tmp: take()?,
            inv: take()?,
            diag: take()?,
            invden: take()?,
            w: if weighted {
                [take()?, take()?, take()?]
            } else {
                [&mut [], &mut [], &mut []]
            },
            kind: take()?,
            ox: take()?,
            sink: take()?,
        })
    }

    /// The operator, with the two vectors conjugate gradients keep on the fine level: `tmp`
    /// (for `A·p`) and `b` (the residual).
    fn split(&mut self) -> (Op<'_>, &mut [f32], &mut [f32]) {
        let op = Op {
            w: [&*self.w[0], &*self.w[1], &*self.w[2]],
            diag: self.diag,
            sink: self.sink,
            kind: self.kind,
        };
        (op, &mut *self.tmp, &mut *self.b)
    }
}

/// The operator of a level, read-only.
#[derive(Clone, Copy)]
struct Op<'s> {
    w: [&'s [f32]; 3],
    diag: &'s [f32],
    sink: &'s [f32],
    kind: &'s [f32],
}

/// The fine level's conjugate-gradient vectors (the residual is the fine level's `b`).
struct Krylov<'s> {
    rhs: &'s mut [f32],
    x: &'s mut [f32],
    p: &'s mut [f32],
}

/// The part of the problem's grid the levels are laid out for: the box of its interior cells
/// and their neighbours (every cell beyond it is outside the domain, which the padding of
/// zeros stands for exactly), so a domain that fills part of the grid (early in an
/// exploration, or a box [`super::local`] cut out across a frontier into unknown space) costs
/// only its own box.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Crop {
    /// The box's first cell in the problem's grid.
    lo: [usize; 3],
    /// Its cells along x, y, z.
    n: [usize; 3],
    /// The problem grid's row and plane strides.
    sy: usize,
    sz: usize,
}

impl Crop {
    /// The whole of `dims`.
    fn all(dims: &Dims) -> Self {
        Self {
            lo: [0; 3],
            n: dims.extent(),
            sy: dims.nx(),
            sz: dims.nx() * dims.ny(),
        }
    }

    /// The box of the domain of `labels` ([`Active::domain`]), from an even cell on each
    /// axis; the whole grid where there is no interior cell.
    fn of(dims: &Dims, labels: &[Label]) -> Self {
        let Some((lo, hi)) = Active::domain(dims, labels) else {
            return Self::all(dims);
        };
        // From an even cell: the first coarse level pairs the cells as it would over the
        // whole grid.
        let lo = lo.map(|c| c & !1);
        Self {
            lo,
            n: zip3(hi, lo, usize::saturating_sub),
            ..Self::all(dims)
        }
    }

    /// Cell `p` of the problem's grid in the box's coordinates, if the box holds it.
    fn local(&self, p: [usize; 3]) -> Option<[usize; 3]> {
        let q = zip3(p, self.lo, usize::wrapping_sub);
        q.iter().zip(&self.n).all(|(c, n)| c < n).then_some(q)
    }

    /// Where row `(y, z)` of the box starts in the problem's grid.
    #[inline(always)]
    fn row_start(&self, y: usize, z: usize) -> usize {
        let [lx, ly, lz] = self.lo;
        lx + self.sy * (y + ly) + self.sz * (z + lz)
    }
}

/// The fast multigrid solver over borrowed storage ([`flat_scratch_len`] values).
pub struct Flat<'a> {
    fine: Dims,
    /// The box of `fine` the levels are laid out for (that of the last solve's domain).
    crop: Crop,
    fork: Option<&'a dyn Fork>,
    /// Whether the storage has been zeroed (its padding must hold zeros; see [`build`]).
    zeroed: bool,
    grids: HVec<Grid, MAX_LEVELS>,
    values: &'a mut [f32],
    history: HVec<f32, 64>,
}

impl core::fmt::Debug for Flat<'_> {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.debug_struct("Flat")
            .field("fine", &self.fine)
            .field("levels", &self.grids.len())
            .finish()
    }
}

impl<'a> Flat<'a> {
    /// A solver for grids of `fine`, working in `values` (at least [`flat_scratch_len`] long).
    pub fn new(fine: Dims, values: &'a mut [f32]) -> Result<Self, SolveError> {
        if values.len() < flat_scratch_len(&fine) {
            return Err(SolveError::ScratchTooSmall);
        }
        Ok(Flat {
            fine,
            crop: Crop::all(&fine),
            fork: None,
            zeroed: false,
            grids: grids(fine.extent()),
            values,
            history: HVec::new(),
        })
    }

    /// Lends a [`Fork`]: every pass over the fine level (smoothing, residuals, `A·p`, the
    /// conjugate-gradient updates) then runs as two halves of z-planes at once. Each cell's
    /// arithmetic is the same either way, so is the solution, to the bit.
    pub fn set_fork(&mut self, fork: Option<&'a dyn Fork>) {
        self.fork = fork;
    }

    /// Levels, the fine one included, of the last solve (they are laid out for the box of its
    /// domain; before any solve, for the whole grid).
    pub fn levels(&self) -> usize {
        self.grids.len()
    }

    /// Relative residual after each conjugate-gradient step of the last solve (the recurrence's,
    /// not recomputed; the first 64).
    pub fn history(&self) -> &[f32] {
        &self.history
    }

    /// Solves for ψ on the domain given by `labels` (Dirichlet values as
    /// [`super::prepare`] sets them), in place in `psi`, by MGPCG to `params.tolerance` (or the
    /// f32 rounding floor, where that lies above it: then not [`SolveStats::converged`]), out
    /// of restarts, or `params.max_iterations` steps. A cold solve (`warm_start` false) starts
    /// from full multigrid.
    pub fn solve(
        &mut self,
        labels: &[Label],
        psi: &mut [f32],
        params: &SolveParams,
    ) -> Result<SolveStats, SolveError> {
        Ok(self.solve_with(labels, psi, params, Dirichlet::Standard)?.stats)
    }

    /// Lays the levels out again for a grid of `fine`, which the storage must fit (any grid
    /// no larger along each axis than the one it was made for does): [`super::local`] solves
    /// boxes cut out of the grid in the same storage.
    pub(crate) fn relayout(&mut self, fine: Dims) -> Result<(), SolveError> {
        if self.values.len() < flat_scratch_len(&fine) {
            return Err(SolveError::ScratchTooSmall);
        }
        self.fine = fine;
        Ok(())
    }

    /// Lays the levels out for `crop` of the problem's grid, unless they are already.
    fn crop_to(&mut self, crop: Crop) {
        if crop != self.crop {
            self.crop = crop;
            self.grids = grids(crop.n);
            // The arrays move: their padding must be zeroed again.
            self.zeroed = false;
        }
    }

    /// The grid the levels are laid out for.
    pub(crate) fn fine_dims(&self) -> Dims {
        self.fine
    }

    /// [`Flat::solve`] with the Dirichlet values taken as `dirichlet` says (given ones start
    /// warm).
    pub(crate) fn solve_with(
        &mut self,
        labels: &[Label],
        psi: &mut [f32],
        params: &SolveParams,
        dirichlet: Dirichlet,
    ) -> Result<Solved, SolveError> {
        let params = &dirichlet.params(params);
        let (labels, psi) = checked_problem(&self.fine, labels, psi, params, dirichlet)?;
        self.crop_to(Crop::of(&self.fine, labels));
        let crop = self.crop;
        self.history.clear();
        let fork = self.fork;
        let mut stats = SolveStats::default();
        let screen = Screen::new(params.screening);
        let grids = self.grids.clone();
        let Some(fine) = grids.first().copied() else {
            return Err(SolveError::ScratchTooSmall);
        };
        let level_total: usize = level_blocks(&grids).iter().sum();
        let zero = !self.zeroed;
        self.zeroed = true;
        let Some((levels_store, krylov_store)) = self.values.split_at_mut_checked(level_total) else {
            return Err(SolveError::ScratchTooSmall);
        };
        if zero {
            levels_store.fill(0.0);
            if let Some(k) = krylov_store.get_mut(..KRYLOV_ARRAYS * fine.len) {
                k.fill(0.0);
            }
        }
        let Some(mut kr) = carve_krylov(krylov_store, fine.len) else {
            return Err(SolveError::ScratchTooSmall);
        };
        // Every level's operator.
        stats.cell_updates += build(&grids, &crop, levels_store, (labels, psi), screen.shift, kr.rhs)
            .ok_or(SolveError::ScratchTooSmall)?;
        let interior = interior_counts(&grids, levels_store);
        // The source cells in the box (one beyond it touches no interior cell).
        let pins: HVec<[usize; 3], MAX_PINS> = source_pins(&self.fine, labels)
            .iter()
            .filter_map(|p| crop.local(*p))
            .collect();
        let cycle = if screen.shift > 0.0 { Cycle::V } else { Cycle::W };
        let b2 = sum_sq(kr.rhs);
        let params = &dirichlet.tolerance(params, b2);
        // Every pass writes what it reads later (the padding stays zero, see `build`); only the
        // iterate needs a value here.
        if params.warm_start {
            load(&fine, &crop, labels, psi, kr.x);
        } else if b2 > 0.0 {
            stats.cell_updates += full_multigrid(fork, &grids, levels_store, kr.rhs, kr.x, &interior, cycle);
        } else {
            kr.x.fill(0.0);
        }
        let shift = screen.shift;
        let residual = |store: &mut [f32], kr: &mut Krylov<'_>| {
            level_arrays(&grids, store, 0).map_or(Residual::from_sums(0.0, 0.0, 0.0, b2), |mut a| {
                let (op, _, r) = a.split();
                true_residual(fork, &fine, op, (kr.rhs, kr.x), r, b2, shift)
            })
        };
        let mut res = residual(levels_store, &mut kr);
        stats.initial_residual = res.relative;
        stats.cell_updates += fine.len as u64;
        let mut steps = Contraction::default();
        let b_norm = libm::sqrt(b2);
        if b_norm > 0.0 {
            // Whether `res` is the true residual of the iterate as it stands.
            let mut current = true;
            for _ in 0..MAX_RESTARTS {
                if !current {
                    res = residual(levels_store, &mut kr);
                    stats.cell_updates += fine.len as u64;
                    current = true;
                }
                let error_ok = error_met(error_estimate(&steps, &res, &screen), params.max_error);
                if res.meets(params.tolerance) && error_ok || stats.iterations >= params.max_iterations {
                    break;
                }
                let target = params.tolerance.max(res.floor);
                steps.restart();
                let start = res.relative;
                current = false;
                stats.cell_updates += precondition(fork, &grids, levels_store, &interior, &pins, cycle);
                let Some(level0) = level_arrays(&grids, levels_store, 0) else {
                    break;
                };
                kr.p.copy_from_slice(level0.u);
                let mut rho = dot(level0.b, level0.u);
                while stats.iterations < params.max_iterations {
                    let Some(mut level0) = level_arrays(&grids, levels_store, 0) else {
                        break;
                    };
                    // q = A·p, in the fine level's sweep scratch.
                    let (op, q, r) = level0.split();
                    apply(fork, &fine, op, kr.p, q);
                    stats.cell_updates += fine.len as u64;
                    let (pq, max_p) = dot_max(kr.p, q);
                    if !(pq > 0.0 && rho.is_finite()) {
                        break;
                    }
                    let alpha = (rho / pq) as f32;
                    // |α·p| = |α|·|p| exactly, so the largest step is |α|·max |p|.
                    let change = alpha.abs() * max_p;
                    let r2 = step_and_norm(fork, (kr.x, r), (kr.p, q), alpha);
                    stats.iterations += 1;
                    let recursive = (libm::sqrt(r2) / b_norm) as f32;
                    steps.push_with_residual(change, recursive);
                    let _ = self.history.push(recursive);
                    if recursive <= target * STOP_SHARE || recursive <= start * 1e-3 {
                        break;
                    }
                    stats.cell_updates += precondition(fork, &grids, levels_store, &interior, &pins, cycle);
                    let Some(level0) = level_arrays(&grids, levels_store, 0) else {
                        break;
                    };
                    let rho_new = dot(level0.b, level0.u);
                    let beta = (rho_new / rho) as f32;
                    rho = rho_new;
                    let z = &*level0.u;
                    each_half(fork, kr.p, &mut [], &|p, _, at| {
                        let Some(z) = z.get(at..at + p.len()) else {
                            return;
                        };
                        for (p, z) in p.iter_mut().zip(z) {
                            *p = z + beta * *p;
                        }
                    });
                }
            }
            // Report the true residual of the ψ returned, not the recurrence's, nor the
            // iterate's before the clamp (a capped solve can overshoot the bounds).
            if clamp_to_bounds_all(kr.x) > CLAMP_SLACK {
                current = false;
            }
            if !current {
                res = residual(levels_store, &mut kr);
                stats.cell_updates += fine.len as u64;
            }
        }
        store(&fine, &crop, labels, kr.x, psi);
        let _ = clamp_to_bounds(labels, psi);
        stats.residual = res.relative;
        stats.floor = res.floor;
        stats.error_estimate = error_estimate(&steps, &res, &screen);
        // Converged only where the tolerance itself (not the floor above it) and the error
        // target are met; the passes also stop at the floor, or out of restarts.
        stats.converged = converged(&res, params, stats.error_estimate);
        stats.stop = if stats.converged {
            Stop::Met
        } else if stats.iterations >= params.max_iterations {
            Stop::Cap
        } else {
            Stop::of(&res, params, stats.error_estimate, Stop::Restarts)
        };
        Ok(Solved {
            stats,
            residual: res,
            b2,
        })
    }
}

/// Each level's block length (its arrays and the transfer scratch to the level above).
fn level_blocks(grids: &[Grid]) -> HVec<usize, MAX_LEVELS> {
    let mut out = HVec::new();
    let mut prev: Option<&Grid> = None;
    for g in grids {
        // The two intermediate grids, and a weight per cell of each.
        let extra = prev.map_or(0, |f| {
            let (a, b) = g.transfer_len(f);
            2 * (a + b)
        });
        let arrays = if prev.is_some() { LEVEL_ARRAYS } else { FINE_ARRAYS };
        let _ = out.push(arrays * g.len + extra);
        prev = Some(g);
    }
    out
}

/// Level `k`'s block of the storage.
fn level_block<'s>(grids: &[Grid], store: &'s mut [f32], k: usize) -> Option<&'s mut [f32]> {
    let blocks = level_blocks(grids);
    let start: usize = blocks.iter().take(k).sum();
    let len = *blocks.get(k)?;
    store.get_mut(start..start + len)
}

/// Level `k`'s arrays.
fn level_arrays<'s>(grids: &[Grid], store: &'s mut [f32], k: usize) -> Option<Arrays<'s>> {
    let g = grids.get(k)?;
    Arrays::carve(level_block(grids, store, k)?, g.len, k > 0)
}

/// The transfers between a level and the next coarser one, done one axis at a time through two
/// intermediate grids: `t1` (coarse x, coarse y, fine z) and `t2` (coarse x, fine y, fine z).
///
/// A fine cell takes ¾ of its own parent along each axis and up to ¼ of the other parent (the
/// coarse neighbour on its side): `oz` (on `t1`'s grid), `oy` (on `t2`'s) and the fine level's
/// [`Arrays::ox`] hold that weight, ¼ times the share of the face towards the other parent that
/// no wall closes. Geometric trilinear interpolation would give a cell beside a wall a quarter
/// of the correction of the room behind it; here it takes none, as operator-dependent
/// interpolation does. The restriction is the transpose, with the same weights.
struct Transfer<'s> {
    t1: &'s mut [f32],
    t2: &'s mut [f32],
    oz: &'s mut [f32],
    oy: &'s mut [f32],
}

/// Levels `k` and `k + 1`: the second's arrays and its transfer scratch.
fn two_levels<'s>(
    grids: &[Grid],
    store: &'s mut [f32],
    k: usize,
) -> Option<(Arrays<'s>, Arrays<'s>, Transfer<'s>)> {
    let blocks = level_blocks(grids);
    let start: usize = blocks.iter().take(k).sum();
    let (a_len, b_len) = (*blocks.get(k)?, *blocks.get(k + 1)?);
    let (f, c) = (grids.get(k)?, grids.get(k + 1)?);
    let block = store.get_mut(start..start + a_len + b_len)?;
    let (fine, coarse) = block.split_at_mut(a_len);
    let (carr, scratch) = coarse.split_at_mut_checked(LEVEL_ARRAYS * c.len)?;
    let (t1_len, t2_len) = c.transfer_len(f);
    let (t1, rest) = scratch.split_at_mut_checked(t1_len)?;
    let (t2, rest) = rest.split_at_mut_checked(t2_len)?;
    let (oz, rest) = rest.split_at_mut_checked(t1_len)?;
    let oy = rest.get_mut(..t2_len)?;
    Some((
        Arrays::carve(fine, f.len, k > 0)?,
        Arrays::carve(carr, c.len, true)?,
        Transfer { t1, t2, oz, oy },
    ))
}

fn carve_krylov(store: &mut [f32], n: usize) -> Option<Krylov<'_>> {
    let (rhs, rest) = store.split_at_mut_checked(n)?;
    let (x, rest) = rest.split_at_mut_checked(n)?;
    let p = rest.get_mut(..n)?;
    Some(Krylov { rhs, x, p })
}

/// Every level's operator from the fine labels; `rhs` gets the fine right-hand side. Returns
/// cells touched, or `None` if the storage does not fit.
///
/// The padding of every array must hold zeros: [`Flat::solve`] zeroes the whole storage before
/// its first solve, and no pass writes anything but 0 there (a padding cell has no faces, a
/// zero diagonal and zero values around it), so it stays so.
fn build(
    grids: &[Grid],
    crop: &Crop,
    store: &mut [f32],
    problem: (&[Label], &[f32]),
    shift: f32,
    rhs: &mut [f32],
) -> Option<u64> {
    let fine = grids.first()?;
    let mut work = 0u64;
    {
        let mut a = level_arrays(grids, store, 0)?;
        build_fine(fine, crop, problem, &mut a, rhs, shift)?;
        work += fine.len as u64;
    }
    for k in 0..grids.len().saturating_sub(1) {
        let (f, c) = (grids.get(k)?, grids.get(k + 1)?);
        let (fa, mut ca, mut tr) = two_levels(grids, store, k)?;
        // The fine level's faces, which it does not keep, are in its scratch (`build_fine`).
        let fw = if k == 0 {
            [&*fa.u, &*fa.tmp, &*fa.b]
        } else {
            [&*fa.w[0], &*fa.w[1], &*fa.w[2]]
        };
        coarsen(f, (fa.kind, fa.sink, fw), c, ca.kind, &mut ca.w, ca.sink);
        finish(
            c,
            ca.kind,
            &ca.w,
            ca.sink,
            ca.diag,
            ca.inv,
            Screen::new(shift).coarser(k + 1).shift,
        );
        // den: the coarse "not outside" mask interpolated onto the fine interior cells.
        for (m, k) in ca.tmp.iter_mut().zip(ca.kind.iter()) {
            *m = f32::from(*k != OUT);
        }
        fa.invden.fill(0.0);
        transfer_weights(f, fa.kind, fa.ox, c, &mut tr);
        interpolate(c, ca.tmp, f, fa.invden, fa.ox, &mut tr);
        for (d, inv) in fa.invden.iter_mut().zip(fa.inv.iter()) {
            // Divided everywhere and selected (the loop vectorises; a branch around the
            // division kept it scalar).
            let r = 1.0 / *d;
            *d = if *inv > 0.0 && *d > 0.0 { r } else { 0.0 };
        }
        work += f.len as u64;
    }
    Some(work)
}

/// The fine level's kinds and right-hand side from the labels, and its `+x`, `+y`, `+z` face
/// conductances (the interior mask's products, which it does not keep; [`Arrays::w`]) in its
/// `u`, `tmp` and `b` for [`coarsen`]: nothing reads those before writing every cell of them
/// again (full multigrid, the preconditioner and the sweeps do), and where a face is 0 the
/// padding is too.
fn build_fine(
    g: &Grid,
    crop: &Crop,
    (labels, psi): (&[Label], &[f32]),
    a: &mut Arrays<'_>,
    rhs: &mut [f32],
    shift: f32,
) -> Option<()> {
    // Kinds, and the Dirichlet values (in `r`, 0 on every other cell).
    each_row(g, crop, |row, padded| {
        let (Some(l), Some(v), Some(k), Some(d)) = (
            labels.get(row.clone()),
            psi.get(row),
            a.kind.get_mut(padded.clone()),
            a.r.get_mut(padded),
        ) else {
            return;
        };
        for ((k, d), (l, v)) in k.iter_mut().zip(d.iter_mut()).zip(l.iter().zip(v)) {
            // After the domain build only these four remain (`Label` is `repr(u8)`).
            // The code selected before its conversion: the loop vectorises.
            let code = *l as u8;
            *k = f32::from(if code <= Label::Source as u8 {
                code
            } else {
                OUT as u8
            });
            *d = if *k >= FRONTIER { *v } else { 0.0 };
        }
    });
    let dval: &[f32] = a.r;
    // Per interior cell and axis: the face to an interior neighbour (w), the Dirichlet faces
    // (sink), the values they bring (rhs) and the in-domain neighbours (the diagonal).
    let kind: &[f32] = a.kind;
    for z in 0..g.n[2] {
        let range = g.plane(z);
        let me = kind.get(range.clone())?;
        let (rhs, sink, diag) = (
            rhs.get_mut(range.clone())?,
            a.sink.get_mut(range.clone())?,
            a.diag.get_mut(range.clone())?,
        );
        rhs.fill(0.0);
        sink.fill(0.0);
        for (d, m) in diag.iter_mut().zip(me) {
            *d = if *m == INTERIOR { shift } else { 0.0 };
        }
        for (axis, stride) in [1, g.sy, g.sz].into_iter().enumerate() {
            let w = match axis {
                0 => &mut *a.u,
                1 => &mut *a.tmp,
                _ => &mut *a.b,
            }
            .get_mut(range.clone())?;
            let up = kind.get(range.start + stride..range.end + stride)?;
            let down = kind.get(range.start - stride..range.end - stride)?;
            let (vu, vd) = (
                dval.get(range.start + stride..range.end + stride)?,
                dval.get(range.start - stride..range.end - stride)?,
            );
            let cells = w
                .iter_mut()
                .zip(rhs.iter_mut())
                .zip(sink.iter_mut())
                .zip(diag.iter_mut());
            let around = me.iter().zip(up).zip(down).zip(vu.iter().zip(vd));
            for ((((w, b), s), d), (((&m, &u), &dn), (&vu, &vd))) in cells.zip(around) {
                let i = f32::from(m == INTERIOR);
                *w = i * f32::from(u == INTERIOR);
                *s += i * (f32::from(u >= FRONTIER) + f32::from(dn >= FRONTIER));
                *b += i * (vu + vd);
                *d += i * (f32::from(u != OUT) + f32::from(dn != OUT));
            }
        }
        let inv = a.inv.get_mut(range)?;
        for (iv, d) in inv.iter_mut().zip(diag.iter()) {
            // Divided everywhere and selected: the loop vectorises.
            let r = 1.0 / d;
            *iv = if *d > 0.0 { r } else { 0.0 };
        }
    }
    Some(())
}

/// Diagonal and its reciprocal of every interior cell: its faces, sink and screening.
fn finish(
    g: &Grid,
    kind: &[f32],
    w: &[&mut [f32]; 3],
    sink: &[f32],
    diag: &mut [f32],
    inv: &mut [f32],
    shift: f32,
) {
    diag.fill(0.0);
    inv.fill(0.0);
    let w = [&*w[0], &*w[1], &*w[2]];
    for z in 0..g.n[2] {
        let range = g.plane(z);
        let (Some(d), Some(iv), Some(k), Some(s)) = (
            diag.get_mut(range.clone()),
            inv.get_mut(range.clone()),
            kind.get(range.clone()),
            sink.get(range.clone()),
        ) else {
            continue;
        };
        for ((d, k), s) in d.iter_mut().zip(k).zip(s) {
            if *k == INTERIOR {
                *d = s + shift;
            }
        }
        for (axis, stride) in [1, g.sy, g.sz].into_iter().enumerate() {
            let (Some(wu), Some(wd)) = (
                w.get(axis).and_then(|w| w.get(range.clone())),
                w.get(axis)
                    .and_then(|w| w.get(range.start - stride..range.end - stride)),
            ) else {
                continue;
            };
            for ((d, u), dn) in d.iter_mut().zip(wu).zip(wd) {
                *d += u + dn;
            }
        }
        for (d, iv) in d.iter().zip(iv.iter_mut()) {
            *iv = if *d > 0.0 { 1.0 / d } else { 0.0 };
        }
    }
}

/// A coarse level's kinds, faces and sinks from the level below's (`fine`: its kinds, sinks
/// and faces).
fn coarsen(
    f: &Grid,
    fine: (&[f32], &[f32], [&[f32]; 3]),
    c: &Grid,
    kind: &mut [f32],
    w: &mut [&mut [f32]; 3],
    sink: &mut [f32],
) {
    let (fkind, fsink, fw) = fine;
    kind.fill(OUT);
    sink.fill(0.0);
    let [wx, wy, wz] = w;
    wx.fill(0.0);
    wy.fill(0.0);
    wz.fill(0.0);
    let cn = c.n[0];
    // Row by row of the coarse grid, from the (up to) four fine rows under it.
    for cz in 0..c.n[2] {
        for cy in 0..c.n[1] {
            let at = c.at(0, cy, cz);
            let (Some(ck), Some(cs), Some(cwx), Some(cwy), Some(cwz)) = (
                kind.get_mut(at..at + cn),
                sink.get_mut(at..at + cn),
                wx.get_mut(at..at + cn),
                wy.get_mut(at..at + cn),
                wz.get_mut(at..at + cn),
            ) else {
                continue;
            };
            for (dy, dz) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
                let (y, z) = (2 * cy + dy, 2 * cz + dz);
                if y >= f.n[1] || z >= f.n[2] {
                    continue;
                }
                // Two fine cells per coarse one; an odd last one pairs with the zero padding.
                let from = f.at(0, y, z);
                let to = from + 2 * cn;
                let (fk, fs, fwx, fwy, fwz) = (
                    sl(fkind, from, to),
                    sl(fsink, from, to),
                    sl(fw[0], from, to),
                    sl(fw[1], from, to),
                    sl(fw[2], from, to),
                );
                let cells = ck.iter_mut().zip(cs.iter_mut()).zip(cwx.iter_mut());
                let fine = fk
                    .chunks_exact(2)
                    .zip(fs.chunks_exact(2))
                    .zip(fwx.chunks_exact(2));
                for (((k, s), wxc), ((kp, sp), wxp)) in cells.zip(fine) {
                    if let (&[k0, k1], &[s0, s1], &[_, wx1]) = (kp, sp, wxp) {
                        // Interior wins, else Dirichlet.
                        if k0 == INTERIOR || k1 == INTERIOR {
                            *k = INTERIOR;
                        } else if (k0 >= FRONTIER || k1 >= FRONTIER) && *k != INTERIOR {
                            *k = FRONTIER;
                        }
                        // Half the interior children's sinks; the +x face from the odd child.
                        *s += 0.5 * (s0 + s1);
                        *wxc += 0.25 * wx1;
                    }
                }
                if dy == 1 {
                    for (cw, pair) in cwy.iter_mut().zip(fwy.chunks_exact(2)) {
                        if let &[a, b] = pair {
                            *cw += 0.25 * (a + b);
                        }
                    }
                }
                if dz == 1 {
                    for (cw, pair) in cwz.iter_mut().zip(fwz.chunks_exact(2)) {
                        if let &[a, b] = pair {
                            *cw += 0.25 * (a + b);
                        }
                    }
                }
            }
        }
    }
    // Faces are open only between interior children, so between interior coarse cells;
    // partly open ones are at least half open. Sinks stay on interior cells only (the
    // children's are 0 elsewhere).
    for ((((k, s), x), y), z) in kind
        .iter()
        .zip(sink.iter_mut())
        .zip(wx.iter_mut())
        .zip(wy.iter_mut())
        .zip(wz.iter_mut())
    {
        if *k != INTERIOR {
            *s = 0.0;
        }
        for w in [x, y, z] {
            if *w > 0.0 {
                *w = w.max(MIN_OPEN_FACE);
            }
        }
    }
}

/// The cells of `range` in `v` and their six face neighbours' (`[centre, −x, +x, −y, +y, −z,
/// +z]`), each as long as `range`; `None` for a range in the first plane or row (never one of
/// [`Grid::plane`]'s).
#[inline(always)]
fn faces<'v>(g: &Grid, v: &'v [f32], range: &core::ops::Range<usize>) -> Option<[&'v [f32]; 7]> {
    let (s, e) = (range.start, range.end);
    let (sy, sz) = (g.sy, g.sz);
    let (s_lo_y, s_lo_z) = (s.checked_sub(sy)?, s.checked_sub(sz)?);
    Some([
        sl(v, s, e),
        sl(v, s - 1, e - 1),
        sl(v, s + 1, e + 1),
        sl(v, s_lo_y, e - sy),
        sl(v, s + sy, e + sy),
        sl(v, s_lo_z, e - sz),
        sl(v, s + sz, e + sz),
    ])
}

/// `a[from..to]`, empty where out of range.
#[inline(always)]
fn sl(a: &[f32], from: usize, to: usize) -> &[f32] {
    a.get(from..to).unwrap_or(&[])
}

/// `out[i] = f(Σ_faces w·v, v[i], e₀[i], e₁[i], e₂[i], out[i])` for every cell `i` of `range`
/// (the seven-point sum without its centre; `out` and the extra inputs `e` cover `range`
/// alone). Without weights (the fine level, [`Arrays::w`]) the sum is the plain one, which is
/// the same number where `v` holds 0 outside the interior.
#[inline(always)]
fn stencil(
    g: &Grid,
    w: [&[f32]; 3],
    v: &[f32],
    range: core::ops::Range<usize>,
    extra: [&[f32]; 3],
    out: &mut [f32],
    f: impl FnMut(f32, f32, f32, f32, f32, f32) -> f32,
) {
    if w[0].is_empty() {
        stencil_as::<false>(g, w, v, range, extra, out, f)
    } else {
        stencil_as::<true>(g, w, v, range, extra, out, f)
    }
}

/// `f(Σ_j w_j (v_j − v_i), v_i, e₀, e₁)` on the fine level, `w_j` its face conductances (1
/// between two interior cells, else 0: [`Arrays::w`]) taken from `kind`: the net flux, whose
/// rounding near ψ = 1 is that of the differences (see [`super`]), for the true residual.
#[inline(always)]
fn fine_flux(
    g: &Grid,
    kind: &[f32],
    v: &[f32],
    range: core::ops::Range<usize>,
    extra: [&[f32]; 2],
    out: &mut [f32],
    mut f: impl FnMut(f32, f32, f32, f32) -> f32,
) {
    let m = |k: f32| f32::from(k == INTERIOR);
    let (Some([c, l, r, ym, yp, zm, zp]), Some([kc, kl, kr, kym, kyp, kzm, kzp])) =
        (faces(g, v, &range), faces(g, kind, &range))
    else {
        return;
    };
    let it = out
        .iter_mut()
        .zip(c.iter().zip(kc))
        .zip(l.iter().zip(r).zip(kl.iter().zip(kr)))
        .zip(ym.iter().zip(yp).zip(kym.iter().zip(kyp)))
        .zip(zm.iter().zip(zp).zip(kzm.iter().zip(kzp)))
        .zip(extra[0].iter().zip(extra[1]));
    for (
        ((((o, (&c, &kc)), ((&l, &r), (&kl, &kr))), ((&ym, &yp), (&kym, &kyp))), ((&zm, &zp), (&kzm, &kzp))),
        (&a, &b),
    ) in it
    {
        let wc = m(kc);
        // The weighted flux's weights: the product of the two cells' masks.
        let (wl, wr, wym, wyp, wzm, wzp) = (
            wc * m(kl),
            wc * m(kr),
            wc * m(kym),
            wc * m(kyp),
            wc * m(kzm),
            wc * m(kzp),
        );
        let flux =
            wl * (l - c) + wr * (r - c) + wym * (ym - c) + wyp * (yp - c) + wzm * (zm - c) + wzp * (zp - c);
        *o = f(flux, c, a, b);
    }
}

/// [`stencil`]; with `WEIGHTED` false the weights are not read and the sum is the plain one.
#[inline(always)]
fn stencil_as<const WEIGHTED: bool>(
    g: &Grid,
    w: [&[f32]; 3],
    v: &[f32],
    range: core::ops::Range<usize>,
    extra: [&[f32]; 3],
    out: &mut [f32],
    mut f: impl FnMut(f32, f32, f32, f32, f32, f32) -> f32,
) {
    let Some([c, l, r, ym, yp, zm, zp]) = faces(g, v, &range) else {
        return;
    };
    let extra = extra[0].iter().zip(extra[1]).zip(extra[2]);
    let around = out
        .iter_mut()
        .zip(c)
        .zip(l.iter().zip(r))
        .zip(ym.iter().zip(yp))
        .zip(zm.iter().zip(zp));
    if !WEIGHTED {
        for (((((o, &c), (&l, &r)), (&ym, &yp)), (&zm, &zp)), ((&a, &b), &d)) in around.zip(extra) {
            *o = f(l + r + ym + yp + zm + zp, c, a, b, d, *o);
        }
        return;
    }
    // A cell's face towards +axis is its own weight, towards −axis its neighbour's.
    let (Some([wr, wl, ..]), Some([wyp, _, _, wym, ..]), Some([wzp, .., wzm, _])) = (
        faces(g, w[0], &range),
        faces(g, w[1], &range),
        faces(g, w[2], &range),
    ) else {
        return;
    };
    let it = around
        .zip(wl.iter().zip(wr))
        .zip(wym.iter().zip(wyp))
        .zip(wzm.iter().zip(wzp))
        .zip(extra);
    for (
        (((((((o, &c), (&l, &r)), (&ym, &yp)), (&zm, &zp)), (&wl, &wr)), (&wym, &wyp)), (&wzm, &wzp)),
        ((&a, &b), &d),
    ) in it
    {
        let sum = wl * l + wr * r + wym * ym + wyp * yp + wzm * zm + wzp * zp;
        *o = f(sum, c, a, b, d, *o);
    }
}

/// One smoothing step of `A u = b` into `tmp`:
/// `tmp ← u + c1·(u − old) + c2·(inv·(b + Σ w u_j) − u)`, `old` being the iterate before `u`,
/// held in `tmp` (or 0 where `old_zero`). Jacobi is `c1 = 0`, `c2 = ω`. Cells outside the
/// interior have `inv = 0` and hold 0 in `u` and `old`, so they stay 0.
fn sweep(fork: Option<&dyn Fork>, g: &Grid, a: &mut Arrays<'_>, c1: f32, c2: f32, old_zero: bool) {
    let (u, b, inv) = (&*a.u, &*a.b, &*a.inv);
    let w = [&*a.w[0], &*a.w[1], &*a.w[2]];
    each_plane(fork, g, a.tmp, &|range, out| {
        let (Some(b), Some(inv)) = (b.get(range.clone()), inv.get(range.clone())) else {
            return;
        };
        let keep = 1.0 + c1 - c2;
        if old_zero || c1 == 0.0 {
            stencil(g, w, u, range, [b, inv, inv], out, |sum, c, b, inv, _, _| {
                keep * c + c2 * inv * (sum + b)
            });
        } else {
            stencil(g, w, u, range, [b, inv, inv], out, |sum, c, b, inv, _, old| {
                keep * c - c1 * old + c2 * inv * (sum + b)
            });
        }
    });
}

/// `sweeps` smoothing steps of `A u = b` from `start` ([`Smoother`]), the result in the level's
/// own `u`. Returns interior cell updates.
fn smooth(
    fork: Option<&dyn Fork>,
    g: &Grid,
    a: &mut Arrays<'_>,
    sweeps: u32,
    interior: u64,
    start: Start,
    smoother: Smoother,
) -> u64 {
    if sweeps == 0 {
        if start == Start::Zero {
            a.u.fill(0.0);
        }
        return 0;
    }
    let first = match smoother {
        Smoother::Chebyshev => 1.0 / CHEB_THETA,
        Smoother::Jacobi => OMEGA,
    };
    // Whether `a.u` is the carved `tmp`. Each step after the first trades the two, so the
    // first step's result is put where the last one lands in the carved `u` without a copy
    // (except from a given `u` with an odd count).
    let mut swapped = false;
    let mut trade = |a: &mut Arrays<'_>| {
        core::mem::swap(&mut a.u, &mut a.tmp);
        swapped = !swapped;
    };
    match start {
        Start::Zero => {
            // The first step from 0: u = c2·inv·b (the neighbour sum is 0), in place.
            if sweeps & 1 == 0 {
                trade(a);
            }
            for ((u, b), inv) in a.u.iter_mut().zip(a.b.iter()).zip(a.inv.iter()) {
                *u = first * inv * b;
            }
        }
        Start::Given | Start::Corrected => {
            if start == Start::Corrected {
                if sweeps & 1 == 1 {
                    for ((t, u), w) in a.tmp.iter_mut().zip(a.u.iter()).zip(a.invden.iter()) {
                        *t = u + *t * w;
                    }
                    trade(a);
                } else {
                    for ((u, e), w) in a.u.iter_mut().zip(a.tmp.iter()).zip(a.invden.iter()) {
                        *u += e * w;
                    }
                }
            }
            sweep(fork, g, a, 0.0, first, true);
            trade(a);
        }
    }
    let mut old_zero = start == Start::Zero;
    let sigma = CHEB_THETA / CHEB_DELTA;
    let mut rho_old = 1.0 / sigma;
    for _ in 1..sweeps {
        let (c1, c2) = match smoother {
            Smoother::Chebyshev => {
                let rho = 1.0 / (2.0 * sigma - rho_old);
                let c = (rho * rho_old, 2.0 * rho / CHEB_DELTA);
                rho_old = rho;
                c
            }
            Smoother::Jacobi => (0.0, OMEGA),
        };
        sweep(fork, g, a, c1, c2, old_zero);
        trade(a);
        old_zero = false;
    }
    if swapped {
        // `u` and `tmp` traded places: copy back into the carved `u`.
        a.tmp.copy_from_slice(a.u);
        core::mem::swap(&mut a.u, &mut a.tmp);
    }
    u64::from(sweeps) * interior
}

/// `r = (b − A u)·invden`: the residual weighted for the restriction.
fn residual_for_restriction(fork: Option<&dyn Fork>, g: &Grid, a: &mut Arrays<'_>) {
    let (u, b, d, den) = (&*a.u, &*a.b, &*a.diag, &*a.invden);
    let w = [&*a.w[0], &*a.w[1], &*a.w[2]];
    each_plane(fork, g, a.r, &|range, out| {
        let (Some(b), Some(d), Some(den)) =
            (b.get(range.clone()), d.get(range.clone()), den.get(range.clone()))
        else {
            return;
        };
        stencil(g, w, u, range, [b, d, den], out, |sum, c, b, d, den, _| {
            (b + sum - d * c) * den
        });
    });
}

/// `q = A p` on the fine level.
fn apply(fork: Option<&dyn Fork>, g: &Grid, op: Op<'_>, p: &[f32], q: &mut [f32]) {
    each_plane(fork, g, q, &|range, out| {
        let Some(d) = op.diag.get(range.clone()) else {
            return;
        };
        // Cells outside the interior (a zero diagonal) hold 0: on the fine level the plain
        // neighbour sum is not 0 beside the interior.
        stencil(g, op.w, p, range, [d, d, d], out, |sum, c, d, _, _, _| {
            if d > 0.0 {
                d * c - sum
            } else {
                0.0
            }
        });
    });
}

/// Runs `body(range, out)` for the flat range of every plane of `g`, `out` being that range
/// of `whole`; in two halves of planes at once where a fork is lent (each cell is computed the
/// same way either way).
fn each_plane(
    fork: Option<&dyn Fork>,
    g: &Grid,
    whole: &mut [f32],
    body: &(dyn Fn(core::ops::Range<usize>, &mut [f32]) + Sync),
) {
    let run = |zs: core::ops::Range<usize>, part: &mut [f32], offset: usize| {
        for z in zs {
            let range = g.plane(z);
            if let Some(out) = part.get_mut(range.start - offset..range.end - offset) {
                body(range, out);
            }
        }
    };
    let nz = g.n[2];
    match fork {
        Some(fork) if nz >= 2 => {
            let m = nz >> 1;
            let at = (g.sz * (m + PAD)).min(whole.len());
            let (lo, hi) = whole.split_at_mut(at);
            fork.join(&mut || run(0..m, lo, 0), &mut || run(m..nz, hi, at));
        }
        _ => run(0..nz, whole, 0),
    }
}

/// The work of [`each_half`] on one half: its pieces of `a` and `b` and where they start.
type HalfBody<'b> = dyn Fn(&mut [f32], &mut [f32], usize) + Sync + 'b;

/// Runs `body(a, b, start)` over `a` and `b` (the same length, or `b` empty), in two halves at
/// once where a fork is lent; `start` is where the pieces begin.
fn each_half(fork: Option<&dyn Fork>, a: &mut [f32], b: &mut [f32], body: &HalfBody<'_>) {
    match fork {
        Some(fork) => {
            let at = (a.len() >> 1) & !15;
            let (a_lo, a_hi) = a.split_at_mut(at);
            let (b_lo, b_hi) = b.split_at_mut(at.min(b.len()));
            fork.join(&mut || body(a_lo, b_lo, 0), &mut || body(a_hi, b_hi, at));
        }
        None => body(a, b, 0),
    }
}

/// The true residual `rhs − A x` of the iterate `x` into `r`, with its rounding floor.
fn true_residual(
    fork: Option<&dyn Fork>,
    g: &Grid,
    op: Op<'_>,
    (rhs, x): (&[f32], &[f32]),
    r: &mut [f32],
    b2: f64,
    shift: f32,
) -> Residual {
    each_plane(fork, g, r, &|range, out| {
        let (Some(rhs), Some(s)) = (rhs.get(range.clone()), op.sink.get(range.clone())) else {
            return;
        };
        // As fluxes: b + Σ w·(x_j − x_i) − (sink + s)·x_i.
        fine_flux(g, op.kind, x, range, [rhs, s], out, |flux, c, b, sink| {
            b + flux - (sink + shift) * c
        });
    });
    let (mut r2, mut e2, mut max) = (0.0f64, 0.0f64, 0.0f32);
    for z in 0..g.n[2] {
        let range = g.plane(z);
        let (Some(d), Some(x), Some(out)) = (
            op.diag.get(range.clone()),
            x.get(range.clone()),
            r.get(range.clone()),
        ) else {
            continue;
        };
        r2 += sum_sq(out);
        max = max.max(max_abs(out));
        // Rounding: (n + n²)·c² per cell, n its in-domain neighbours (its diagonal less the
        // screening; 0 outside the interior, where c = 0 too).
        let mut lanes = [0.0f32; 16];
        let (dc, xc) = (d.chunks_exact(16), x.chunks_exact(16));
        let (dr, xr) = (dc.remainder(), xc.remainder());
        for (d, x) in dc.zip(xc) {
            for ((l, d), c) in lanes.iter_mut().zip(d).zip(x) {
                let n = d - shift;
                *l += (n + n * n) * c * c;
            }
        }
        let mut pe2: f32 = lanes.iter().sum();
        for (d, c) in dr.iter().zip(xr) {
            let n = d - shift;
            pe2 += (n + n * n) * c * c;
        }
        e2 += rounding_row(pe2);
    }
    Residual::from_sums(r2, e2, max, b2)
}

/// `out = P v`: `v` on the coarse grid `c` interpolated onto the logical cells of the fine grid
/// `f`, one axis at a time through the [`Transfer`]'s grids, with its weights (`ox` the fine
/// level's).
fn interpolate(c: &Grid, v: &[f32], f: &Grid, out: &mut [f32], ox: &[f32], tr: &mut Transfer<'_>) {
    let (cpx, cplane) = (c.sy, c.sz);
    let fpy = f.n[1] + 2 * PAD;
    // Along z: t1 holds (coarse x, coarse y, fine z).
    for z in 0..f.n[2] {
        let (own, other) = parents(z);
        let plane = cplane * (z + PAD)..cplane * (z + PAD + 1);
        let (Some(a), Some(b), Some(w), Some(dst)) = (
            v.get(cplane * own..cplane * (own + 1)),
            v.get(cplane * other..cplane * (other + 1)),
            tr.oz.get(plane.clone()),
            tr.t1.get_mut(plane),
        ) else {
            continue;
        };
        for (((d, a), b), w) in dst.iter_mut().zip(a).zip(b).zip(w) {
            *d = 0.75 * a + w * b;
        }
    }
    // Along y: t2 holds (coarse x, fine y, fine z).
    for z in 0..f.n[2] {
        let plane = cplane * (z + PAD);
        for y in 0..f.n[1] {
            let (own, other) = parents(y);
            let at = cpx * (y + PAD) + cpx * fpy * (z + PAD);
            let (Some(a), Some(b), Some(w), Some(dst)) = (
                tr.t1.get(plane + cpx * own..plane + cpx * (own + 1)),
                tr.t1.get(plane + cpx * other..plane + cpx * (other + 1)),
                tr.oy.get(at..at + cpx),
                tr.t2.get_mut(at..at + cpx),
            ) else {
                continue;
            };
            for (((d, a), b), w) in dst.iter_mut().zip(a).zip(b).zip(w) {
                *d = 0.75 * a + w * b;
            }
        }
    }
    // Along x, into the fine rows: fine 2X takes ¾ of X and its weight of X − 1, fine 2X + 1
    // ¾ of X and its weight of X + 1.
    for z in 0..f.n[2] {
        for y in 0..f.n[1] {
            let at = cpx * (y + PAD) + cpx * fpy * (z + PAD);
            let fat = f.at(0, y, z);
            let (Some(src), Some(w), Some(dst)) = (
                tr.t2.get(at + PAD - 1..at + cpx),
                ox.get(fat..fat + f.n[0]),
                out.get_mut(fat..fat + f.n[0]),
            ) else {
                continue;
            };
            for ((pair, w), s) in dst.chunks_mut(2).zip(w.chunks(2)).zip(src.windows(3)) {
                let (lo, mid, hi) = (s.first().copied(), s.get(1).copied(), s.get(2).copied());
                let (Some(lo), Some(mid), Some(hi)) = (lo, mid, hi) else {
                    continue;
                };
                let mut cells = pair.iter_mut().zip(w);
                if let Some((e, w)) = cells.next() {
                    *e = 0.75 * mid + w * lo;
                }
                if let Some((o, w)) = cells.next() {
                    *o = 0.75 * mid + w * hi;
                }
            }
        }
    }
}

/// The [`Transfer`] weights from the kinds of the fine level `f` (`ox` its own): ¼ of the
/// share of the faces towards a cell's other parent whose two sides are both in the domain,
/// over the children the intermediate cell stands for that are in it. Only logical cells are
/// written: the padding keeps the zeros it holds (see [`build`]).
fn transfer_weights(f: &Grid, kind: &[f32], ox: &mut [f32], c: &Grid, tr: &mut Transfer<'_>) {
    // In the domain (1) or not (0): the kinds are 0 outside, 1 or more inside.
    let m = |k: &f32| k.min(1.0);
    let [nx, ny, nz] = f.n;
    let (cpx, cplane, cnx) = (c.sy, c.sz, c.n[0]);
    let fpy = ny + 2 * PAD;
    // Fine row `(y, z)` of the kinds, in padded coordinates, from x = −1 to x = 2·cnx (the
    // padding included).
    let row = |yp: usize, zp: usize| {
        let at = PAD + f.sy * yp + f.sz * zp;
        kind.get(at - 1..at + 2 * cnx + 1).unwrap_or(&[])
    };
    // The padded coordinate of the cell towards the other parent of fine coordinate `c`: below
    // for even, above for odd (the padding where that is past the edge).
    let other = |c: usize| if c & 1 == 0 { c + PAD - 1 } else { c + PAD + 1 };
    for z in 0..nz {
        let (zp, zo) = (z + PAD, other(z));
        for y in 0..ny {
            let (k, ky) = (row(y + PAD, zp), row(other(y), zp));
            // ox: fine 2X looks at 2X − 1, fine 2X + 1 at 2X + 2.
            let at = f.at(0, y, z);
            if let Some(w) = ox.get_mut(at..at + nx) {
                for (pair, k) in w.chunks_mut(2).zip(k.windows(4).step_by(2)) {
                    if let &[lo, a, b, hi] = k {
                        let mut cells = pair.iter_mut();
                        if let Some(e) = cells.next() {
                            *e = 0.25 * m(&a) * m(&lo);
                        }
                        if let Some(o) = cells.next() {
                            *o = 0.25 * m(&b) * m(&hi);
                        }
                    }
                }
            }
            // oy: over the two fine x under each coarse x (the second may be padding).
            let at = cpx * (y + PAD) + cpx * fpy * (z + PAD) + PAD;
            let (Some(w), Some(k), Some(ko)) = (tr.oy.get_mut(at..at + cnx), k.get(1..), ky.get(1..)) else {
                continue;
            };
            for ((w, k), ko) in w.iter_mut().zip(k.chunks_exact(2)).zip(ko.chunks_exact(2)) {
                if let (&[a, b], &[ao, bo]) = (k, ko) {
                    let cells = m(&a) + m(&b);
                    *w = 0.25 * (m(&a) * m(&ao) + m(&b) * m(&bo)) / cells.max(1.0);
                }
            }
        }
        // oz: over the four fine (x, y) under each coarse (x, y).
        for cy in 0..c.n[1] {
            let at = cplane * (z + PAD) + cpx * (cy + PAD) + PAD;
            let (y0, y1) = (2 * cy + PAD, 2 * cy + 1 + PAD);
            let (Some(w), Some(k0), Some(k1), Some(o0), Some(o1)) = (
                tr.oz.get_mut(at..at + cnx),
                row(y0, zp).get(1..),
                row(y1, zp).get(1..),
                row(y0, zo).get(1..),
                row(y1, zo).get(1..),
            ) else {
                continue;
            };
            let pairs = k0.chunks_exact(2).zip(k1.chunks_exact(2));
            let others = o0.chunks_exact(2).zip(o1.chunks_exact(2));
            for ((w, (k0, k1)), (o0, o1)) in w.iter_mut().zip(pairs).zip(others) {
                if let (&[a, b], &[c, d], &[ao, bo], &[co, do_]) = (k0, k1, o0, o1) {
                    let cells = m(&a) + m(&b) + m(&c) + m(&d);
                    let faces = m(&a) * m(&ao) + m(&b) * m(&bo) + m(&c) * m(&co) + m(&d) * m(&do_);
                    *w = 0.25 * faces / cells.max(1.0);
                }
            }
        }
    }
}

/// The padded indices of a fine cell's own parent and its other parent along one axis.
#[inline(always)]
fn parents(fine: usize) -> (usize, usize) {
    let own = (fine >> 1) + PAD;
    (own, if fine & 1 == 0 { own - 1 } else { own + 1 })
}

/// `cb = ½ Pᵀ rn` on the interior cells of the coarse grid `c` (0 on the others): the transpose
/// of [`interpolate`], one axis at a time.
#[allow(clippy::too_many_arguments)]
fn restrict(
    f: &Grid,
    rn: &[f32],
    ox: &[f32],
    c: &Grid,
    ckind: &[f32],
    cb: &mut [f32],
    tr: &mut Transfer<'_>,
) {
    let (cpx, cplane) = (c.sy, c.sz);
    let fpy = f.n[1] + 2 * PAD;
    // Along x: fine rows into coarse x. Coarse X gathers fine 2X and 2X + 1 (¾ each) and, with
    // their weights, 2X − 1 and 2X + 2, whose other parent it is.
    for z in 0..f.n[2] {
        for y in 0..f.n[1] {
            let fat = f.at(0, y, z);
            let at = cpx * (y + PAD) + cpx * fpy * (z + PAD);
            let (Some(src), Some(w), Some(dst)) = (
                rn.get(fat - 1..fat + f.n[0] + PAD),
                ox.get(fat - 1..fat + f.n[0] + PAD),
                tr.t2.get_mut(at + PAD..at + PAD + c.n[0]),
            ) else {
                continue;
            };
            for ((d, v), w) in dst
                .iter_mut()
                .zip(src.windows(4).step_by(2))
                .zip(w.windows(4).step_by(2))
            {
                if let (&[a, b, cc, e], &[wa, _, _, we]) = (v, w) {
                    *d = 0.75 * (b + cc) + wa * a + we * e;
                }
            }
        }
    }
    // Along y.
    for z in 0..f.n[2] {
        let base = cpx * fpy * (z + PAD);
        for cy in 0..c.n[1] {
            let row = |y: usize| base + cpx * y..base + cpx * (y + 1);
            let y0 = 2 * cy + PAD;
            let at = cplane * (z + PAD) + cpx * (cy + PAD);
            let (t2, oy) = (&*tr.t2, &*tr.oy);
            let (Some(a), Some(b), Some(m), Some(p), Some(wm), Some(wp)) = (
                t2.get(row(y0)),
                t2.get(row(y0 + 1)),
                t2.get(row(y0 - 1)),
                t2.get(row(y0 + 2)),
                oy.get(row(y0 - 1)),
                oy.get(row(y0 + 2)),
            ) else {
                continue;
            };
            let Some(dst) = tr.t1.get_mut(at..at + cpx) else {
                continue;
            };
            let sides = m.iter().zip(p).zip(wm.iter().zip(wp));
            for (((d, a), b), ((m, p), (wm, wp))) in dst.iter_mut().zip(a).zip(b).zip(sides) {
                *d = 0.75 * (a + b) + wm * m + wp * p;
            }
        }
    }
    // Along z, into the interior coarse cells.
    for cz in 0..c.n[2] {
        let z0 = 2 * cz + PAD;
        let plane = |z: usize| cplane * z..cplane * (z + 1);
        let at = cplane * (cz + PAD);
        let (t1, oz) = (&*tr.t1, &*tr.oz);
        let (Some(a), Some(b), Some(m), Some(p), Some(wm), Some(wp)) = (
            t1.get(plane(z0)),
            t1.get(plane(z0 + 1)),
            t1.get(plane(z0 - 1)),
            t1.get(plane(z0 + 2)),
            oz.get(plane(z0 - 1)),
            oz.get(plane(z0 + 2)),
        ) else {
            continue;
        };
        let (Some(k), Some(dst)) = (ckind.get(at..at + cplane), cb.get_mut(at..at + cplane)) else {
            continue;
        };
        let sides = m.iter().zip(p).zip(wm.iter().zip(wp));
        for ((((d, a), b), ((m, p), (wm, wp))), k) in dst.iter_mut().zip(a).zip(b).zip(sides).zip(k) {
            let v = 0.5 * (0.75 * (a + b) + wm * m + wp * p);
            *d = if *k == INTERIOR { v } else { 0.0 };
        }
    }
}

/// Interior cells of each level, for the work count.
fn interior_counts(grids: &[Grid], store: &mut [f32]) -> HVec<u64, MAX_LEVELS> {
    let mut out = HVec::new();
    for k in 0..grids.len() {
        let n =
            level_arrays(grids, store, k).map_or(0, |a| a.kind.iter().filter(|&&k| k == INTERIOR).count());
        let _ = out.push(n as u64);
    }
    out
}

/// One V- or W-cycle on level `k` (and below) for `A u = b` from the `u` there. Returns cell
/// updates.
///
/// `Start::Zero` stands for `u = 0` without its having been written: the first sweep from 0
/// reads only `b` (its neighbour sum is 0) and writes `u` in place, the same values as a sweep
/// of a zeroed `u`.
fn vcycle(
    fork: Option<&dyn Fork>,
    grids: &[Grid],
    store: &mut [f32],
    k: usize,
    interior: &[u64],
    start: Start,
    cycle: Cycle,
) -> u64 {
    // Only the fine level is worth splitting between threads.
    let fk = if k == 0 { fork } else { None };
    let (Some(f), count) = (grids.get(k), interior.get(k).copied().unwrap_or(0)) else {
        return 0;
    };
    let Some(c) = grids.get(k + 1) else {
        // Coarsest: smoothing alone.
        return level_arrays(grids, store, k).map_or(0, |mut a| {
            smooth(fk, f, &mut a, COARSEST_SWEEPS, count, start, Smoother::Jacobi)
        });
    };
    let mut work = 0;
    {
        let Some((mut fa, ca, mut tr)) = two_levels(grids, store, k) else {
            return work;
        };
        work += smooth(fk, f, &mut fa, cycle.sweeps(), count, start, Smoother::Chebyshev);
        residual_for_restriction(fk, f, &mut fa);
        restrict(f, fa.r, fa.ox, c, ca.kind, ca.b, &mut tr);
        work += 2 * f.len as u64;
    }
    work += vcycle(fork, grids, store, k + 1, interior, Start::Zero, cycle);
    if cycle == Cycle::W {
        work += vcycle(fork, grids, store, k + 1, interior, Start::Given, cycle);
    }
    let Some((mut fa, ca, mut tr)) = two_levels(grids, store, k) else {
        return work;
    };
    interpolate(c, ca.u, f, fa.tmp, fa.ox, &mut tr);
    work += f.len as u64;
    work + smooth(
        fk,
        f,
        &mut fa,
        cycle.sweeps(),
        count,
        Start::Corrected,
        Smoother::Chebyshev,
    )
}

/// How often a cycle solves on the next coarser level: once (a V-cycle) or twice (a W-cycle).
///
/// Laplace's equation on a map with long walls and a small frontier is nearly singular, and
/// one V-cycle leaves each coarse level's problem far from solved: on the houses of
/// `scripts/pyamg_compare.py` (64³ and 96³, 100 frontier voxels) MGPCG takes 14–21 steps with
/// V-cycles and 8 with W-cycles, both with three Chebyshev steps (with three Jacobi sweeps:
/// 18–27 and 9–11; 25–31 and 15–19 before the transfers stopped at walls, where an exactly
/// solved second level gave 16–21). The screened field's coarse levels carry a shift that
/// grows fourfold per level, and a V-cycle solves them well enough: W-cycles there took as many
/// steps or one fewer for a fifth more work.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
enum Cycle {
    V,
    W,
}

impl Cycle {
    /// Smoothing steps before and after each coarse correction.
    fn sweeps(self) -> u32 {
        match self {
            Cycle::V => V_SWEEPS,
            Cycle::W => W_SWEEPS,
        }
    }
}

/// Where a cycle starts from.
#[derive(Clone, Copy, PartialEq, Eq)]
enum Start {
    /// The level's `u` as it holds.
    Given,
    /// `u = 0`, not written yet.
    Zero,
    /// `u + tmp·invden`: the level's `u` corrected by the coarse correction interpolated
    /// into `tmp` (only where the level has a coarser one).
    Corrected,
}

/// Full multigrid for `A x = rhs` from nothing: `rhs` restricted down the levels, the coarsest
/// smoothed, each finer level started from the one below and given a cycle.
fn full_multigrid(
    fork: Option<&dyn Fork>,
    grids: &[Grid],
    store: &mut [f32],
    rhs: &[f32],
    x: &mut [f32],
    interior: &[u64],
    cycle: Cycle,
) -> u64 {
    let mut work = 0u64;
    if let Some(a) = level_arrays(grids, store, 0) {
        a.b.copy_from_slice(rhs);
    }
    for k in 0..grids.len().saturating_sub(1) {
        let (Some(f), Some(c)) = (grids.get(k), grids.get(k + 1)) else {
            break;
        };
        let Some((fa, ca, mut tr)) = two_levels(grids, store, k) else {
            break;
        };
        for ((r, b), w) in fa.r.iter_mut().zip(fa.b.iter()).zip(fa.invden.iter()) {
            *r = b * w;
        }
        restrict(f, fa.r, fa.ox, c, ca.kind, ca.b, &mut tr);
        work += f.len as u64;
    }
    let last = grids.len().saturating_sub(1);
    if let (Some(g), Some(mut a)) = (grids.get(last), level_arrays(grids, store, last)) {
        a.u.fill(0.0);
        work += smooth(
            None,
            g,
            &mut a,
            COARSEST_SWEEPS,
            interior.get(last).copied().unwrap_or(0),
            Start::Given,
            Smoother::Jacobi,
        );
    }
    for k in (0..last).rev() {
        let (Some(f), Some(c)) = (grids.get(k), grids.get(k + 1)) else {
            break;
        };
        if let Some((fa, ca, mut tr)) = two_levels(grids, store, k) {
            interpolate(c, ca.u, f, fa.tmp, fa.ox, &mut tr);
            for ((u, e), w) in fa.u.iter_mut().zip(fa.tmp.iter()).zip(fa.invden.iter()) {
                *u = e * w;
            }
        }
        work += f.len as u64 + vcycle(fork, grids, store, k, interior, Start::Given, cycle);
    }
    if let Some(a) = level_arrays(grids, store, 0) {
        x.copy_from_slice(a.u);
    }
    work
}

/// `z = M⁻¹ r`: one cycle from 0 with `r` as the fine right-hand side; `z` is left in the
/// fine level's `u`. Returns cell updates.
fn precondition(
    fork: Option<&dyn Fork>,
    grids: &[Grid],
    store: &mut [f32],
    interior: &[u64],
    pins: &[[usize; 3]],
    cycle: Cycle,
) -> u64 {
    let Some(fine) = grids.first() else {
        return 0;
    };
    let mut work = 0;
    // From 0; written first only where the smoothing at a source reads it.
    let start = if pins.is_empty() {
        Start::Zero
    } else {
        Start::Given
    };
    if start == Start::Given {
        if let Some(mut a) = level_arrays(grids, store, 0) {
            a.u.fill(0.0);
            work += local_smooth(fine, &mut a, pins);
        }
    }
    work += vcycle(fork, grids, store, 0, interior, start, cycle);
    if let Some(mut a) = level_arrays(grids, store, 0) {
        work += local_smooth(fine, &mut a, pins);
    }
    work
}

/// Symmetric Gauss-Seidel (forward, then backward) over a small box around each source voxel of
/// the fine level, before and after each V-cycle of the preconditioner, as
/// [`super::multigrid`] does: the coarse levels absorb a single-voxel Dirichlet source, so the
/// error it leaves is local and sharp, and a few local sweeps remove it. Returns cell updates.
fn local_smooth(g: &Grid, a: &mut Arrays<'_>, pins: &[[usize; 3]]) -> u64 {
    let mut work = 0u64;
    let offsets = [1, g.sy, g.sz];
    let mut update = |a: &mut Arrays<'_>, x: usize, y: usize, z: usize| {
        let i = g.at(x, y, z);
        let inv = a.inv.get(i).copied().unwrap_or(0.0);
        if inv <= 0.0 {
            return;
        }
        // The fine level: a face is open exactly where the neighbour is interior, and `u` is 0
        // on every other cell (see `Arrays::w`).
        let mut sum = a.b.get(i).copied().unwrap_or(0.0);
        for step in offsets {
            sum += a.u.get(i + step).copied().unwrap_or(0.0) + a.u.get(i - step).copied().unwrap_or(0.0);
        }
        if let Some(u) = a.u.get_mut(i) {
            *u = inv * sum;
        }
        work += 1;
    };
    super::symmetric_box_sweep(pins, g.n, LOCAL_RADIUS, |x, y, z| update(a, x, y, z));
    work
}

/// Calls `f(psi range, padded range)` for every row of the grid laid out for `crop`: where
/// a row lies in the caller's unpadded arrays of the problem's grid, and where in the padded
/// one.
fn each_row(g: &Grid, crop: &Crop, mut f: impl FnMut(core::ops::Range<usize>, core::ops::Range<usize>)) {
    let nx = g.n[0];
    for z in 0..g.n[2] {
        for y in 0..g.n[1] {
            let (from, at) = (crop.row_start(y, z), g.at(0, y, z));
            f(from..from + nx, at..at + nx);
        }
    }
}

/// The interior values of `psi` (a warm start; [`super::prepare`] has cleaned them) into the
/// padded `x`.
fn load(g: &Grid, crop: &Crop, labels: &[Label], psi: &[f32], x: &mut [f32]) {
    each_row(g, crop, |row, padded| {
        if let (Some(src), Some(l), Some(dst)) = (psi.get(row.clone()), labels.get(row), x.get_mut(padded)) {
            for ((d, s), l) in dst.iter_mut().zip(src).zip(l) {
                *d = if *l == Label::Interior { *s } else { 0.0 };
            }
        }
    });
}

/// The padded `x` back into the interior cells of `psi`.
/// Clamps the whole padded iterate into [0, 1] (its padding is 0, its Dirichlet values are 0
/// or 1, so only unknowns move); returns the largest change, as [`clamp_to_bounds`] does.
fn clamp_to_bounds_all(x: &mut [f32]) -> f32 {
    let mut moved = 0.0f32;
    for v in x.iter_mut() {
        let c = v.clamp(PSI_SOURCE, PSI_FRONTIER);
        moved = moved.max((c - *v).abs());
        *v = c;
    }
    moved
}

fn store(g: &Grid, crop: &Crop, labels: &[Label], x: &[f32], psi: &mut [f32]) {
    each_row(g, crop, |row, padded| {
        if let (Some(dst), Some(l), Some(src)) = (psi.get_mut(row.clone()), labels.get(row), x.get(padded)) {
            for ((d, s), l) in dst.iter_mut().zip(src).zip(l) {
                // A select, not a branch around the store: the loop vectorises.
                *d = if *l == Label::Interior { *s } else { *d };
            }
        }
    });
}

/// `Σ aᵢbᵢ`, summed in sixteen lanes per block of 4096 (so it vectorises) and across blocks in
/// f64 ([`dot_max`], whose running maximum costs nothing beside the memory traffic).
fn dot(a: &[f32], b: &[f32]) -> f64 {
    dot_max(a, b).0
}

/// [`dot`]`(a, b)` and [`max_abs`]`(a)` in one pass.
fn dot_max(a: &[f32], b: &[f32]) -> (f64, f32) {
    let mut total = 0.0f64;
    let mut top = [0.0f32; 16];
    let mut m = 0.0f32;
    for (a, b) in a.chunks(4096).zip(b.chunks(4096)) {
        let mut lanes = [0.0f32; 16];
        let (ac, bc) = (a.chunks_exact(16), b.chunks_exact(16));
        let (ar, br) = (ac.remainder(), bc.remainder());
        for (x, y) in ac.zip(bc) {
            for (((l, t), x), y) in lanes.iter_mut().zip(top.iter_mut()).zip(x).zip(y) {
                *l += x * y;
                let v = x.abs();
                *t = if v > *t { v } else { *t };
            }
        }
        let mut sum: f32 = lanes.iter().sum();
        for (x, y) in ar.iter().zip(br) {
            sum += x * y;
            m = if x.abs() > m { x.abs() } else { m };
        }
        total += f64::from(sum);
    }
    for t in top {
        if t > m {
            m = t;
        }
    }
    (total, m)
}

/// The conjugate-gradient step `x += α·p`, `r −= α·q`, returning `Σ rᵢ²` of the new `r`: one
/// pass, in two halves at a block boundary of [`dot`] (on two threads where a fork is lent,
/// one after the other otherwise; the same bits either way), each block summed as [`dot`]
/// sums it.
fn step_and_norm(
    fork: Option<&dyn Fork>,
    (x, r): (&mut [f32], &mut [f32]),
    (p, q): (&[f32], &[f32]),
    alpha: f32,
) -> f64 {
    let at = (x.len() >> 1) & !4095;
    let (x_lo, x_hi) = x.split_at_mut(at.min(x.len()));
    let (r_lo, r_hi) = r.split_at_mut(at.min(r.len()));
    let (p_lo, p_hi) = p.split_at(at.min(p.len()));
    let (q_lo, q_hi) = q.split_at(at.min(q.len()));
    let half = |x: &mut [f32], r: &mut [f32], p: &[f32], q: &[f32]| -> f64 {
        let mut total = 0.0f64;
        let blocks = x
            .chunks_mut(4096)
            .zip(r.chunks_mut(4096))
            .zip(p.chunks(4096).zip(q.chunks(4096)));
        for ((x, r), (p, q)) in blocks {
            let mut lanes = [0.0f32; 16];
            let (mut xc, mut rc) = (x.chunks_exact_mut(16), r.chunks_exact_mut(16));
            let (pc, qc) = (p.chunks_exact(16), q.chunks_exact(16));
            let (pr, qr) = (pc.remainder(), qc.remainder());
            for ((x, r), (p, q)) in xc.by_ref().zip(rc.by_ref()).zip(pc.zip(qc)) {
                for ((l, (x, r)), (p, q)) in lanes
                    .iter_mut()
                    .zip(x.iter_mut().zip(r.iter_mut()))
                    .zip(p.iter().zip(q))
                {
                    *x += alpha * p;
                    *r -= alpha * q;
                    *l += *r * *r;
                }
            }
            let mut sum: f32 = lanes.iter().sum();
            let rest = xc.into_remainder().iter_mut().zip(rc.into_remainder().iter_mut());
            for ((x, r), (p, q)) in rest.zip(pr.iter().zip(qr)) {
                *x += alpha * p;
                *r -= alpha * q;
                sum += *r * *r;
            }
            total += f64::from(sum);
        }
        total
    };
    let (mut lo, mut hi) = (0.0f64, 0.0f64);
    match fork {
        Some(fork) => fork.join(&mut || lo = half(x_lo, r_lo, p_lo, q_lo), &mut || {
            hi = half(x_hi, r_hi, p_hi, q_hi)
        }),
        None => {
            lo = half(x_lo, r_lo, p_lo, q_lo);
            hi = half(x_hi, r_hi, p_hi, q_hi);
        }
    }
    lo + hi
}

/// `max |aᵢ|`, in sixteen lanes.
fn max_abs(a: &[f32]) -> f32 {
    let mut lanes = [0.0f32; 16];
    let chunks = a.chunks_exact(16);
    let rest = chunks.remainder();
    for c in chunks {
        for (l, v) in lanes.iter_mut().zip(c) {
            let v = v.abs();
            *l = if v > *l { v } else { *l };
        }
    }
    let mut m = rest
        .iter()
        .fold(0.0f32, |m, v| if v.abs() > m { v.abs() } else { m });
    for l in lanes {
        if l > m {
            m = l;
        }
    }
    m
}

/// `Σ aᵢ²`.
fn sum_sq(a: &[f32]) -> f64 {
    dot(a, a)
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
    use crate::mapping::map::VoxelIndex;
    use crate::planning::solve::multigrid::tests::Scratch;
    use crate::planning::solve::multigrid::Method;
    use crate::planning::solve::Sequential;
    use std::vec;
    use std::vec::Vec;

    /// Rooms behind a wall with a door and a pillar, a frontier strip in the far room, the source
    /// in the near one. Odd sizes exercise the coarse grids' half cells.
    fn rooms(nx: usize, ny: usize, nz: usize) -> (Dims, Vec<Label>) {
        let dims = Dims::new(nx, ny, nz).unwrap();
        let mut labels = vec![Label::Interior; dims.len()];
        for (i, l) in labels.iter_mut().enumerate() {
            let v = dims.voxel(i);
            let (x, y, z) = (v.x as usize, v.y as usize, v.z as usize);
            let door = (ny / 3..ny / 3 + 2).contains(&y) && z < nz.div_ceil(2);
            let pillar = (nx / 4..nx / 4 + 2).contains(&x) && (ny / 2..ny / 2 + 2).contains(&y);
            if x == nx / 2 && !door || pillar {
                *l = Label::Outside;
            }
            if x == nx - 1 && y > ny / 2 {
                *l = Label::Frontier;
            }
        }
        labels[dims.linear(VoxelIndex::new(2, 2, (nz / 2) as u16))] = Label::Source;
        (dims, labels)
    }

    fn params(tolerance: f32, screening: f32) -> SolveParams {
        SolveParams {
            tolerance,
            max_iterations: 1_000,
            warm_start: false,
            screening,
            max_error: f32::INFINITY,
        }
    }

    /// `labels` solved by the flat solver (with `fork`) from ψ = 0.
    fn solve_flat(
        dims: Dims,
        labels: &[Label],
        p: &SolveParams,
        fork: Option<&dyn Fork>,
    ) -> (Vec<f32>, SolveStats) {
        let mut values = vec![0.0f32; flat_scratch_len(&dims)];
        let mut flat = Flat::new(dims, &mut values).unwrap();
        flat.set_fork(fork);
        let mut psi = vec![0.0f32; dims.len()];
        let s = flat.solve(labels, &mut psi, p).unwrap();
        (psi, s)
    }

    /// The same problem by [`super::super::multigrid`]'s MGPCG.
    fn solve_mg(dims: Dims, labels: &[Label], p: &SolveParams) -> Vec<f32> {
        let mut scratch = Scratch::new(&dims, true);
        let mut mg = scratch.multigrid(dims);
        let mut psi = vec![0.0f32; dims.len()];
        mg.solve(labels, &mut psi, p, Method::Pcg).unwrap();
        psi
    }

    fn max_diff(a: &[f32], b: &[f32]) -> f32 {
        a.iter().zip(b).map(|(x, y)| (x - y).abs()).fold(0.0, f32::max)
    }

    /// The flat solver and the multigrid one solve the same discrete problem: Laplace's equation
    /// and the screened field, on even and odd grids, agree to well within the tolerance's error.
    #[test]
    fn solves_the_problem_multigrid_solves() {
        for (nx, ny, nz) in [(32, 24, 16), (27, 19, 13), (9, 7, 5)] {
            let (dims, labels) = rooms(nx, ny, nz);
            let mut released = labels.clone();
            crate::planning::field::release_source(&mut released);
            for (labels, screening) in [(&labels, 0.0), (&released, 0.09)] {
                let (flat, s) = solve_flat(dims, labels, &params(1e-7, screening), None);
                // 1e-7 lies below Laplace's rounding floor here: stopped there, not converged.
                assert!(
                    matches!(s.stop, Stop::Met | Stop::Floor) && s.converged == (s.residual <= 1e-7),
                    "{nx}x{ny}x{nz}, s = {screening}: {s:?}"
                );
                let mg = solve_mg(dims, labels, &params(1e-7, screening));
                let d = max_diff(&flat, &mg);
                assert!(
                    d <= 2e-5,
                    "{nx}x{ny}x{nz}, s = {screening}: max |Δψ| = {d:e}, {s:?}"
                );
                // Dirichlet values as `prepare` sets them, outside 0.
                for (l, p) in labels.iter().zip(&flat) {
                    match l {
                        Label::Frontier => assert_eq!(*p, PSI_FRONTIER_TEST),
                        Label::Source | Label::Outside => assert_eq!(*p, 0.0),
                        _ => assert!((0.0..=1.0).contains(p)),
                    }
                }
            }
        }
    }

    const PSI_FRONTIER_TEST: f32 = crate::planning::solve::PSI_FRONTIER;

    /// A domain that fills part of the grid costs its own box: the rooms placed at two odd
    /// offsets in a grid six times their size, solved one after the other by one solver (its
    /// levels laid out again for the second box), give the rooms' own solution, with about the
    /// cell updates of a solve on a grid of the rooms' size, and leave every cell outside the
    /// domain as it was.
    #[test]
    fn a_domain_in_part_of_the_grid_is_solved_in_its_box() {
        let (small, rooms) = rooms(20, 14, 9);
        for screening in [0.0, 0.09] {
            let p = params(1e-7, screening);
            let (alone, s_alone) = solve_flat(small, &rooms, &p, None);
            let big = Dims::new(40, 30, 18).unwrap();
            let mut values = vec![0.0f32; flat_scratch_len(&big)];
            let mut flat = Flat::new(big, &mut values).unwrap();
            for offset in [(13usize, 9usize, 5usize), (3, 15, 8)] {
                let mut labels = vec![Label::Outside; big.len()];
                let at = |i: usize| {
                    let v = small.voxel(i);
                    big.linear(VoxelIndex::new(
                        v.x + offset.0 as u16,
                        v.y + offset.1 as u16,
                        v.z + offset.2 as u16,
                    ))
                };
                for (i, l) in rooms.iter().enumerate() {
                    labels[at(i)] = *l;
                }
                let mut psi = vec![0.0f32; big.len()];
                let s = flat.solve(&labels, &mut psi, &p).unwrap();
                assert!(
                    matches!(s.stop, Stop::Met | Stop::Floor) && s.converged == (s.residual <= p.tolerance),
                    "{offset:?}, s = {screening}: {s:?}"
                );
                let mut within = vec![false; big.len()];
                for (i, a) in alone.iter().enumerate() {
                    within[at(i)] = true;
                    let d = (psi[at(i)] - a).abs();
                    assert!(d <= 2e-5, "{offset:?}, s = {screening}: |Δψ| = {d:e} at {i}");
                }
                assert!(psi.iter().zip(&within).all(|(p, w)| *w || *p == 0.0));
                assert!(
                    s.cell_updates <= s_alone.cell_updates * 3 / 2,
                    "{offset:?}, s = {screening}: {} cell updates, {} on the rooms' own grid",
                    s.cell_updates,
                    s_alone.cell_updates
                );
            }
        }
    }

    /// Two threads or one: the same bits, iterations and cell updates (the fork splits every
    /// fine pass at a plane, and no cell's arithmetic depends on where).
    #[test]
    fn a_fork_gives_the_same_bits() {
        let (dims, labels) = rooms(30, 22, 14);
        for screening in [0.0, 0.09] {
            let p = params(1e-6, screening);
            let (a, sa) = solve_flat(dims, &labels, &p, None);
            let (b, sb) = solve_flat(dims, &labels, &p, Some(&Sequential));
            assert_eq!((sa.iterations, sa.cell_updates), (sb.iterations, sb.cell_updates));
            assert!(
                a.iter().zip(&b).all(|(x, y)| x.to_bits() == y.to_bits()),
                "s = {screening}"
            );
        }
    }

    /// A warm start from the solution needs no step; one from a perturbed solution comes back.
    #[test]
    fn a_warm_start_from_the_solution_is_kept() {
        let (dims, labels) = rooms(24, 20, 12);
        let (solved, _) = solve_flat(dims, &labels, &params(1e-6, 0.0), None);
        let mut values = vec![0.0f32; flat_scratch_len(&dims)];
        let mut flat = Flat::new(dims, &mut values).unwrap();
        let warm = SolveParams {
            warm_start: true,
            ..params(1e-6, 0.0)
        };
        let mut psi = solved.clone();
        let s = flat.solve(&labels, &mut psi, &warm).unwrap();
        assert!(s.converged && s.iterations == 0, "{s:?}");
        for (p, l) in psi.iter_mut().zip(&labels) {
            if *l == Label::Interior {
                *p *= 0.9;
            }
        }
        let s = flat.solve(&labels, &mut psi, &warm).unwrap();
        assert!(s.converged && s.iterations > 0, "{s:?}");
        assert!(max_diff(&psi, &solved) <= 2e-5);
    }

    /// Stopped at the cap before the tolerance: not converged, and ψ still in its bounds.
    #[test]
    fn a_solve_stopped_at_the_cap_is_not_converged() {
        let (dims, labels) = rooms(24, 20, 12);
        let p = SolveParams {
            max_iterations: 1,
            ..params(1e-9, 0.0)
        };
        let (psi, s) = solve_flat(dims, &labels, &p, None);
        assert!(!s.converged && s.iterations == 1, "{s:?}");
        assert!(psi.iter().all(|p| (0.0..=1.0).contains(p)));
    }

    /// No interior cell touches a frontier: ψ = 0 is exact, with no step taken.
    #[test]
    fn no_frontier_leaves_zero() {
        let (dims, mut labels) = rooms(16, 12, 8);
        for l in labels.iter_mut() {
            if *l == Label::Frontier {
                *l = Label::Outside;
            }
        }
        let (psi, s) = solve_flat(dims, &labels, &params(1e-6, 0.09), None);
        assert!(s.converged && s.iterations == 0, "{s:?}");
        assert!(psi.iter().all(|p| *p == 0.0));
    }

    /// Bad inputs are errors, not panics.
    #[test]
    fn bad_inputs_are_errors() {
        let (dims, labels) = rooms(16, 12, 8);
        let mut short = vec![0.0f32; flat_scratch_len(&dims) - 1];
        assert_eq!(
            Flat::new(dims, &mut short).err(),
            Some(SolveError::ScratchTooSmall)
        );
        let mut values = vec![0.0f32; flat_scratch_len(&dims)];
        let mut flat = Flat::new(dims, &mut values).unwrap();
        let mut psi = vec![0.0f32; dims.len()];
        assert_eq!(
            flat.solve(&labels[1..], &mut psi, &params(1e-6, 0.0)),
            Err(SolveError::StorageTooSmall)
        );
        assert_eq!(
            flat.solve(&labels, &mut psi, &params(0.0, 0.0)),
            Err(SolveError::BadTolerance)
        );
        assert_eq!(
            flat.solve(&labels, &mut psi, &params(1e-6, f32::NAN)),
            Err(SolveError::BadScreening)
        );
        // NaN warm-start values are cleaned by `prepare`.
        psi.fill(f32::NAN);
        let warm = SolveParams {
            warm_start: true,
            ..params(1e-6, 0.09)
        };
        let s = flat.solve(&labels, &mut psi, &warm).unwrap();
        assert!(s.converged && psi.iter().all(|p| p.is_finite()), "{s:?}");
    }
}

#[cfg(test)]
mod timing {
    extern crate std;
    use super::*;
    use std::time::Instant;
    use std::vec;

    /// Where a cold solve's time goes (development aid; `cargo test --release -p harmonic-core
    /// --lib flat::timing -- --ignored --nocapture`).
    #[test]
    #[ignore]
    fn phases() {
        let dims = Dims::new(64, 64, 32).unwrap();
        let mut labels = vec![Label::Outside; dims.len()];
        for (i, l) in labels.iter_mut().enumerate() {
            let v = dims.voxel(i);
            let (x, y, z) = (v.x as usize, v.y as usize, v.z as usize);
            let shell = x == 0 || y == 0 || z == 0 || x == 63 || y == 63 || z == 31;
            let wall =
                (x % 16 == 0 && !(6..9).contains(&(y % 16))) || (y % 16 == 0 && !(6..9).contains(&(x % 16)));
            if !shell && !wall {
                *l = if x == 62 && (50..60).contains(&y) && (10..20).contains(&z) {
                    Label::Frontier
                } else {
                    Label::Interior
                };
            }
        }
        let grids = grids(dims.extent());
        let crop = Crop::all(&dims);
        let psi: std::vec::Vec<f32> = labels
            .iter()
            .map(|l| if *l == Label::Frontier { 1.0 } else { 0.0 })
            .collect();
        let mut values = vec![0.0f32; flat_scratch_len(&dims)];
        let total: usize = level_blocks(&grids).iter().sum();
        let (store, kstore) = values.split_at_mut(total);
        let kr = carve_krylov(kstore, grids[0].len).unwrap();
        let reps = 50;
        let t = Instant::now();
        for _ in 0..reps {
            build(&grids, &crop, store, (&labels, &psi), 0.09, kr.rhs).unwrap();
        }
        let build_ms = t.elapsed().as_secs_f64() * 1e3 / reps as f64;
        let interior = interior_counts(&grids, store);
        {
            let mut a = level_arrays(&grids, store, 0).unwrap();
            let t = Instant::now();
            for _ in 0..reps {
                build_fine(&grids[0], &crop, (&labels, &psi), &mut a, kr.rhs, 0.09).unwrap();
            }
            let bf = t.elapsed().as_secs_f64() * 1e3 / reps as f64;
            std::println!("build_fine {bf:.3} ms");
        }
        {
            let (fa, mut ca, mut tr) = two_levels(&grids, store, 0).unwrap();
            let t = Instant::now();
            for _ in 0..reps {
                coarsen(
                    &grids[0],
                    (fa.kind, fa.sink, [&*fa.u, &*fa.tmp, &*fa.b]),
                    &grids[1],
                    ca.kind,
                    &mut ca.w,
                    ca.sink,
                );
            }
            let co = t.elapsed().as_secs_f64() * 1e3 / reps as f64;
            let t = Instant::now();
            for _ in 0..reps {
                finish(&grids[1], ca.kind, &ca.w, ca.sink, ca.diag, ca.inv, 0.36);
            }
            let fin = t.elapsed().as_secs_f64() * 1e3 / reps as f64;
            let t = Instant::now();
            for _ in 0..reps {
                interpolate(&grids[1], ca.tmp, &grids[0], fa.invden, fa.ox, &mut tr);
            }
            let ip = t.elapsed().as_secs_f64() * 1e3 / reps as f64;
            std::println!(
                "coarsen level 1 {co:.3} ms, finish it {fin:.3}, interpolate to the fine level {ip:.3}"
            );
        }
        let t = Instant::now();
        for _ in 0..reps {
            let _ = interior_counts(&grids, store);
        }
        let count_ms = t.elapsed().as_secs_f64() * 1e3 / reps as f64;
        let t = Instant::now();
        for _ in 0..reps {
            full_multigrid(None, &grids, store, kr.rhs, kr.x, &interior, Cycle::V);
        }
        let fmg_ms = t.elapsed().as_secs_f64() * 1e3 / reps as f64;
        // One cycle on level `k` and below, from what the level holds.
        let cycle_ms = |store: &mut [f32], k: usize, cycle: Cycle| {
            let t = Instant::now();
            for _ in 0..reps {
                vcycle(None, &grids, store, k, &interior, Start::Given, cycle);
            }
            t.elapsed().as_secs_f64() * 1e3 / reps as f64
        };
        let (v_ms, v1_ms) = (cycle_ms(store, 0, Cycle::V), cycle_ms(store, 1, Cycle::V));
        let (w_ms, w1_ms) = (cycle_ms(store, 0, Cycle::W), cycle_ms(store, 1, Cycle::W));
        let coarsest_ms = cycle_ms(store, grids.len() - 1, Cycle::W);
        let g = grids[0];
        let mut a = level_arrays(&grids, store, 0).unwrap();
        let t = Instant::now();
        for _ in 0..reps {
            smooth(None, &g, &mut a, 2, 0, Start::Given, Smoother::Chebyshev);
        }
        let sweep_ms = t.elapsed().as_secs_f64() * 1e3 / reps as f64 / 2.0;
        let t = Instant::now();
        for _ in 0..reps {
            residual_for_restriction(None, &g, &mut a);
        }
        let res_ms = t.elapsed().as_secs_f64() * 1e3 / reps as f64;
        std::println!(
            "build {build_ms:.3} ms, counts {count_ms:.3}, fmg {fmg_ms:.3}, v-cycle {v_ms:.3} (below the fine level {v1_ms:.3}), fine sweep {sweep_ms:.3}, residual {res_ms:.3}"
        );
        std::println!("w-cycle {w_ms:.3} ms (below the fine level {w1_ms:.3}; the coarsest level once {coarsest_ms:.3})");
    }
}
