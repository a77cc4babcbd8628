//! Geometric multigrid for the domain's Laplace problem, in place, over caller storage.
//!
//! **Hierarchy.** Each coarser level halves every axis (rounding up) until an axis reaches one
//! or two cells or [`MAX_LEVELS`] is hit (McAdams, Sifakis & Teran 2010). A coarse cell is
//! *interior* if any of its (up to eight) children is interior, *Dirichlet* if its in-domain
//! children are all Dirichlet, else *outside*. Coarse levels solve the error equation, whose
//! Dirichlet values are 0.
//!
//! **Coarse operator: rediscretisation with face conductances and sinks.** Each coarse level
//! uses a 7-point finite-volume operator whose face conductances come from the level below: a
//! coarse face covers four child faces between interior cells, and its conductance is their
//! mean (1 for a fine face between two interior voxels), floored at ½ where any child face is
//! open ([`FACE_ONE`], `MIN_OPEN_FACE`). Faces from interior children to Dirichlet cells become
//! the coarse cell's *sink*: a conductance to a zero correction, summed over the children and
//! halved per level (the Dirichlet cells sit inside or beside the coarse cell, closer to its
//! centre than a neighbour's centre is, so the sink is stronger than a face of the same area).
//! Per coarse cell this costs four bytes.
//!
//! Why: labelling cells alone ("interior if any child is") makes a one-voxel wall vanish on
//! every coarse level, because the coarse cells on both sides still hold free children; the
//! coarse grid then couples rooms the fine grid keeps apart. And "Dirichlet if any child is"
//! moves frontiers and the source by up to a coarse cell on every level. Measured in V(2,2)
//! cycles to 1e-6 on the 64×64×32 rooms-with-doors benchmark: labels only 109, with face
//! conductances 41; with V(3,3), full-multigrid starts, local smoothing at the source and sinks
//! (the current solver) 22, and MGPCG 10 iterations. The exact mean conductance without the ½
//! floor diverges (partial faces beside walls get too weak for the renormalised transfers), and
//! so do sinks summed without halving. Galerkin products `R·A·P` with trilinear transfers would
//! give 27-point coarse stencils: three times the memory traffic and a coefficient array per
//! coarse cell that the firmware cannot afford.
//!
//! **Transfers.** Prolongation is cell-centred trilinear interpolation (weights ¾, ¼ per axis)
//! from the non-outside coarse neighbours, renormalised where some are outside (Dirichlet
//! coarse cells count, with value 0). Restriction is the same weights transposed, scaled by ½
//! so that `R·A_h·P ≈ A_2h` for the unscaled operator. Transposed transfers plus a smoother whose
//! post-sweeps mirror its pre-sweeps make the V-cycle a symmetric operator.
//!
//! **Cycles and Krylov.** [`Multigrid::solve`] runs V(3,3) cycles in place on φ (measured on
//! the 64×64×32 benchmark in instructions per solve: V(1,1) 1.6×, V(2,2) 1.1× and V(4,4) 0.99×
//! the cost of V(3,3): the transfers cost as much as several sweeps, so more smoothing per level
//! pays). On domains with thin walls or one-voxel doors the coarse levels still couple cells
//! the fine grid keeps apart, and plain cycles slow down; if the caller lends three extra fine
//! vectors, the solve is conjugate gradients preconditioned by one V-cycle (MGPCG), which stays
//! fast there.
//!
//! **Cold starts: full multigrid.** Without a previous solution, the coarsest level solves the
//! problem itself (frontier cells at ψ = 1, the cells holding a source voxel pinned at ψ = 0),
//! each finer level interpolates it and runs one V-cycle, and the fine grid starts from the
//! interpolated field. It saves about a fifth of the iterations of a start from ψ = 0.
//!
//! **Precision.** Arithmetic is `f32` (the Cortex-M4F has no double FPU); the fine level is
//! stored in `f32`, the coarse levels in `f32` or, to halve their memory, bfloat16
//! ([`CoarseValues`]). Every
//! cycle works on the residual of the current φ, so the correction is computed relative to what
//! is already there (defect correction): rounding errors do not accumulate across cycles, and
//! the final accuracy is set by how precisely the fine residual is evaluated, not by the
//! coarse-grid arithmetic. Norms and dot products sum rows in `f32` and rows in `f64`.

use core::cell::Cell;

use heapless::Vec as HVec;

use super::{
    build_masks, error_estimate, error_met, for_each_row_mut_split, for_each_row_out_split, residual_with,
    split_plane, Active, Bf16, Contraction, Dirichlet, Fork, Residual, RowValues, Screen, SolveError,
    SolveParams, SolveStats, Solved, Stencil, Stop, Stored, MASK_INTERIOR, MASK_OPEN, OPEN_RUN,
};
use crate::mapping::map::Dims;
use crate::planning::domain::Label;

/// Most levels in a hierarchy (fine included).
pub const MAX_LEVELS: usize = 12;

/// Smoothing sweeps (red + black) before and after each coarse correction.
const PRE_SWEEPS: u32 = 3;
const POST_SWEEPS: u32 = 3;
/// Most CG restarts from the true residual (defect-correction passes) per solve.
pub const MAX_RESTARTS: u32 = 6;
/// Source voxels that pin the coarse potentials of a full-multigrid start.
pub(crate) const MAX_PINS: usize = 64;
/// A V-cycle solve whose residual grows past this multiple of its start is reported diverged.
const DIVERGED: f32 = 1e3;
/// Plain V-cycles that reach the f32 rounding floor (but not the tolerance) keep cycling until
/// the residual has not fallen by [`STALL_GAIN`] for this many cycles. At the floor the residual
/// no longer shows the error: on rooms behind doors with a small far frontier
/// (`core/tests/few_frontiers.rs`) the smooth error still falls by ~4 % per cycle there, and
/// stopping at the floor left it at up to 1.1e-4 against an f64 solve of the same system.
const STALL_CYCLES: u32 = 8;
/// Relative fall of the best residual that counts as progress for [`STALL_CYCLES`].
const STALL_GAIN: f32 = 0.01;
/// Symmetric sweeps on the coarsest level.
const COARSEST_SWEEPS: u32 = 16;
/// The error estimate of plain V-cycles measures each cycle by its coarse-grid correction, which
/// is about half of what the cycle changes: the smoothing sweeps around it do the rest. Measured
/// on the rooms of `core/tests/few_frontiers.rs`: the correction-based estimate was 0.4–0.64 of
/// the true error for the screened field and 0.3–1.2 for Laplace's before this factor.
const CORRECTION_SHARE: f32 = 2.0;

/// How a multigrid solve iterates.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Method {
    /// Use MGPCG when Krylov storage was lent, V-cycles otherwise.
    #[default]
    Auto,
    /// Plain V-cycles in place.
    VCycle,
    /// Conjugate gradients preconditioned by one V-cycle (needs Krylov storage).
    Pcg,
}

#[derive(Debug, Clone, Copy)]
struct Level {
    dims: Dims,
    /// Start of this level's `x` in the value scratch; `b` follows at `offset + len`.
    offset: usize,
    /// Start of this level's labels in the label scratch.
    label_offset: usize,
    /// Rows with interior cells, set with the labels.
    active: Active,
}

impl Level {
    /// This level's share of the labels of all coarse levels (empty if `all` is short).
    fn labels<'l>(&self, all: &'l [Label]) -> &'l [Label] {
        all.get(self.label_offset..self.label_offset + self.dims.len())
            .unwrap_or(&[])
    }
}

/// Scratch sizes a hierarchy over `fine` needs.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ScratchSize {
    /// Values for all coarse levels (unknowns and right-hand sides), `f32` or [`Bf16`]
    /// ([`CoarseValues`]).
    pub values: usize,
    /// Labels for all coarse levels.
    pub labels: usize,
    /// Face conductances for all coarse levels (one `[u8; 4]` per coarse cell).
    pub faces: usize,
    /// `f32` values for MGPCG's three extra fine vectors (optional).
    pub krylov: usize,
    /// Bytes for the fine cells' neighbour masks (optional): with them a sweep reads one byte
    /// per cell instead of seven labels.
    pub masks: usize,
}

/// The coarse levels' dimensions for a fine grid.
fn coarse_dims(fine: &Dims) -> HVec<Dims, MAX_LEVELS> {
    let mut out = HVec::new();
    let mut d = *fine;
    while out.len() + 1 < MAX_LEVELS && (d.nx() > 2 || d.ny() > 2 || d.nz() > 2) {
        let half = |n: usize| n.div_ceil(2);
        let Ok(c) = Dims::new(half(d.nx()), half(d.ny()), half(d.nz())) else {
            break;
        };
        if out.push(c).is_err() {
            break;
        }
        d = c;
    }
    out
}

/// The coarse levels over `fine`, laid out one after the other in the scratch.
fn lay_out(fine: &Dims) -> HVec<Level, MAX_LEVELS> {
    let mut levels = HVec::new();
    let (mut offset, mut label_offset) = (0, 0);
    for dims in coarse_dims(fine) {
        // coarse_dims yields at most MAX_LEVELS - 1 entries.
        let _ = levels.push(Level {
            dims,
            offset,
            label_offset,
            active: Active::all(&dims),
        });
        offset += 2 * dims.len();
        label_offset += dims.len();
    }
    levels
}

/// Scratch a [`Multigrid`] over `fine` needs.
pub fn scratch_size(fine: &Dims) -> ScratchSize {
    let cells: usize = coarse_dims(fine).iter().map(|d| d.len()).sum();
    ScratchSize {
        values: 2 * cells,
        labels: cells,
        faces: cells,
        krylov: 3 * fine.len(),
        masks: fine.len(),
    }
}

/// The coarse levels' values, in the precision the caller chose to lend.
#[derive(Debug)]
pub enum CoarseValues<'a> {
    /// Full precision (the host's).
    F32(&'a mut [f32]),
    /// bfloat16 ([`Bf16`]): half the memory (73 KiB instead of 146 KiB at 64 × 64 × 32, the
    /// firmware's choice). Coarse levels only carry corrections that each V-cycle recomputes
    /// from the `f32` fine residual, so the solve still converges to the same tolerance and
    /// error; `core/tests/few_frontiers.rs` checks both against f64 solves.
    Bf16(&'a mut [Bf16]),
}

impl CoarseValues<'_> {
    /// Entries lent.
    pub fn len(&self) -> usize {
        match self {
            CoarseValues::F32(v) => v.len(),
            CoarseValues::Bf16(v) => v.len(),
        }
    }

    /// True if nothing was lent.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Bytes lent.
    pub fn bytes(&self) -> usize {
        match self {
            CoarseValues::F32(v) => core::mem::size_of_val(*v),
            CoarseValues::Bf16(v) => core::mem::size_of_val(*v),
        }
    }
}

impl<'a> From<&'a mut [f32]> for CoarseValues<'a> {
    fn from(v: &'a mut [f32]) -> Self {
        CoarseValues::F32(v)
    }
}

impl<'a> From<&'a mut [Bf16]> for CoarseValues<'a> {
    fn from(v: &'a mut [Bf16]) -> Self {
        CoarseValues::Bf16(v)
    }
}

/// Runs `$body` with `$h` bound to a [`Hierarchy`] over the coarse values as a slice of their
/// own type: one instantiation of the generic solver code per storage type.
macro_rules! with_hierarchy {
    (@one $v:ident, $levels:expr, $labels:expr, $faces:expr, $pins:expr, |$h:ident| $body:expr) => {{
        let $h = Hierarchy {
            levels: $levels,
            values: $v,
            labels: $labels,
            faces: $faces,
            pins: $pins,
        };
        $body
    }};
    ($values:expr, $levels:expr, $labels:expr, $faces:expr, $pins:expr, |$h:ident| $body:expr) => {
        match $values {
            CoarseValues::F32(v) => with_hierarchy!(@one v, $levels, $labels, $faces, $pins, |$h| $body),
            CoarseValues::Bf16(v) => with_hierarchy!(@one v, $levels, $labels, $faces, $pins, |$h| $body),
        }
    };
}

/// Storage lent to a [`Multigrid`].
pub struct MultigridStorage<'a> {
    /// At least [`ScratchSize::values`] entries.
    pub values: CoarseValues<'a>,
    /// At least [`ScratchSize::labels`] entries.
    pub labels: &'a mut [Label],
    /// Either empty or at least [`ScratchSize::faces`] entries. Empty: coarse levels use the
    /// plain 7-point operator over their labels ("Dirichlet wins", no face conductances), which
    /// converges more slowly near thin walls but saves four bytes per coarse cell (73 KiB at
    /// 64×64×32, which the firmware's 1 MiB cannot spare).
    pub faces: &'a mut [[u8; 4]],
    /// Either empty (no MGPCG) or at least [`ScratchSize::krylov`] entries.
    pub krylov: &'a mut [f32],
    /// Either empty or at least [`ScratchSize::masks`] entries: each solve then writes every
    /// active cell's in-domain neighbours into a byte, which the fine level's sweeps and
    /// residuals read instead of seven labels (the same arithmetic, so the same bits; about 15 %
    /// off a host solve, BENCHMARKS.md). The firmware, short of 128 KiB, lends none.
    pub masks: &'a mut [u8],
}

/// A multigrid solver bound to one fine grid size.
pub struct Multigrid<'a> {
    fine: Dims,
    levels: HVec<Level, MAX_LEVELS>,
    values: CoarseValues<'a>,
    labels: &'a mut [Label],
    faces: &'a mut [[u8; 4]],
    krylov: &'a mut [f32],
    masks: &'a mut [u8],
    history: HVec<f32, 64>,
    /// Source voxels of the current problem (first [`MAX_PINS`]), for full multigrid.
    pins: HVec<[usize; 3], MAX_PINS>,
    full_multigrid: bool,
    /// Rows of the fine grid with interior cells, for the current problem.
    fine_active: Active,
    /// Screening of the current problem on the fine level.
    screen: Screen,
    /// Splits the fine level's passes between two threads ([`Multigrid::set_fork`]).
    fork: Option<&'a dyn Fork>,
}

/// The coarse levels of a solve, lent to the cycles: their layout, values (stored as `U`),
/// labels and face conductances, and the source voxels full multigrid pins.
struct Hierarchy<'h, U> {
    levels: &'h [Level],
    values: &'h mut [U],
    labels: &'h [Label],
    faces: &'h [[u8; 4]],
    pins: &'h [[usize; 3]],
}

impl<'v, T> View<'v, T> {
    /// The view of coarse level `level` (`depth` halvings below the fine grid, whose screening
    /// is `fine_screen`) over its labels, face conductances and values.
    fn coarse(
        level: &Level,
        depth: usize,
        fine_screen: &Screen,
        labels: &'v [Label],
        faces: Option<&'v [[u8; 4]]>,
        x: &'v mut [T],
        b: Option<&'v [T]>,
    ) -> Self {
        View {
            dims: level.dims,
            active: level.active,
            labels,
            masks: &[],
            faces,
            x,
            b,
            screen: fine_screen.coarser(depth),
            fork: None,
        }
    }
}

/// One level's view: its labels, unknowns and right-hand side (`None` = 0, with Dirichlet
/// values held in `x` itself — the fine level's φ), stored as `T` (`f32` on the fine level).
struct View<'v, T = f32> {
    dims: Dims,
    /// Rows with interior cells: the loops skip the others.
    active: Active,
    labels: &'v [Label],
    /// The fine level's neighbour masks if a [`MultigridStorage::masks`] was lent, else empty.
    masks: &'v [u8],
    /// Coarse levels: face conductances (see [`FACE_ONE`]); `None` on the fine level, whose
    /// faces are all 1 between in-domain cells.
    faces: Option<&'v [[u8; 4]]>,
    x: &'v mut [T],
    b: Option<&'v [T]>,
    /// This level's screening (its diagonal shift in units of a fine face).
    screen: Screen,
    /// The fine level's [`Fork`], if one was lent ([`Multigrid::set_fork`]); `None` on coarse
    /// levels, whose passes are too small to split.
    fork: Option<&'v dyn Fork>,
}

impl<'a> Multigrid<'a> {
    /// Lays out the coarse levels of `fine` in `storage`.
    pub fn new(fine: Dims, storage: MultigridStorage<'a>) -> Result<Self, SolveError> {
        let need = scratch_size(&fine);
        let faces_ok = storage.faces.is_empty() || storage.faces.len() >= need.faces;
        if storage.values.len() < need.values || storage.labels.len() < need.labels || !faces_ok {
            return Err(SolveError::ScratchTooSmall);
        }
        let krylov = if storage.krylov.len() >= need.krylov {
            storage.krylov
        } else {
            &mut []
        };
        let masks = if storage.masks.len() >= need.masks {
            storage.masks
        } else {
            &mut []
        };
        Ok(Self {
            fine,
            levels: lay_out(&fine),
            values: storage.values,
            labels: storage.labels,
            faces: storage.faces,
            krylov,
            masks,
            history: HVec::new(),
            pins: HVec::new(),
            full_multigrid: true,
            fine_active: Active::all(&fine),
            screen: Screen::NONE,
            fork: None,
        })
    }

    /// Lends a [`Fork`] that runs the fine level's passes in two halves at once (the host's
    /// thread pool); `None` (the default) runs them on the caller's thread. Either way a solve
    /// gives the same bits.
    pub fn set_fork(&mut self, fork: Option<&'a dyn Fork>) {
        self.fork = fork;
    }

    /// Whether cold solves (`warm_start == false`) start with full multigrid (the default).
    pub fn set_full_multigrid(&mut self, on: bool) {
        self.full_multigrid = on;
    }

    /// Number of levels including the fine one.
    pub fn levels(&self) -> usize {
        self.levels.len() + 1
    }
    /// True if MGPCG storage was lent.
    pub fn has_krylov(&self) -> bool {
        !self.krylov.is_empty()
    }
    /// Relative residual after each cycle or CG iteration of the last solve (first 64).
    pub fn history(&self) -> &[f32] {
        &self.history
    }

    /// Solves `L φ = 0` on the domain given by `labels` (Dirichlet values set by [`super::prepare`]),
    /// in place in `phi`, to `params.tolerance` or `params.max_iterations` cycles.
    pub fn solve(
        &mut self,
        labels: &[Label],
        phi: &mut [f32],
        params: &SolveParams,
        method: Method,
    ) -> Result<SolveStats, SolveError> {
        Ok(self
            .solve_with(labels, phi, params, method, Dirichlet::Standard)?
            .stats)
    }

    /// Lays the coarse levels out again for a fine grid of `fine`, which the storage lent to
    /// [`Multigrid::new`] must fit (any grid no larger along each axis than the one it was
    /// made for does): [`super::local`] solves boxes cut out of the grid in the same storage.
    pub(crate) fn relayout(&mut self, fine: Dims) -> Result<(), SolveError> {
        let need = scratch_size(&fine);
        let faces_ok = self.faces.is_empty() || self.faces.len() >= need.faces;
        let krylov_ok = self.krylov.is_empty() || self.krylov.len() >= need.krylov;
        let masks_ok = self.masks.is_empty() || self.masks.len() >= need.masks;
        if self.values.len() < need.values
            || self.labels.len() < need.labels
            || !faces_ok
            || !krylov_ok
            || !masks_ok
        {
            return Err(SolveError::ScratchTooSmall);
        }
        self.levels = lay_out(&fine);
        self.fine = fine;
        self.fine_active = Active::all(&fine);
        Ok(())
    }

    /// The grid the coarse levels are laid out for.
    pub(crate) fn fine_dims(&self) -> Dims {
        self.fine
    }

    /// [`Multigrid::solve`] with the Dirichlet values taken as `dirichlet` says.
    pub(crate) fn solve_with(
        &mut self,
        labels: &[Label],
        phi: &mut [f32],
        params: &SolveParams,
        method: Method,
        dirichlet: Dirichlet,
    ) -> Result<Solved, SolveError> {
        let n = self.fine.len();
        let params = &dirichlet.params(params);
        let (labels, phi) = super::checked_problem(&self.fine, labels, phi, params, dirichlet)?;
        self.history.clear();
        let mut stats = SolveStats::default();
        stats.cell_updates += self.build_labels(labels);
        self.fine_active = Active::of(&self.fine, labels);
        build_masks(&self.fine, &self.fine_active, labels, self.masks);
        self.screen = Screen::new(params.screening);
        let screen = self.screen;
        let active = self.fine_active;
        let b2 = match dirichlet {
            Dirichlet::Standard => super::dirichlet_norm2(&self.fine, labels),
            Dirichlet::Given { .. } => super::dirichlet_norm2_given(&self.fine, labels, phi),
        };
        let params = &dirichlet.tolerance(params, b2);
        if b2 == 0.0 {
            // No interior cell touches a frontier (or a Dirichlet value above 0): every
            // interior component holds only the value 0, and ψ = 0 there is the exact solution.
            zero_interior(labels, phi);
        }
        let mut res = residual_with(&self.fine, &active, &screen, (labels, self.masks), phi, b2);
        stats.initial_residual = res.relative;
        if !params.warm_start && self.full_multigrid && b2 > 0.0 {
            stats.cell_updates += self.full_multigrid(labels, phi);
            res = residual_with(&self.fine, &active, &screen, (labels, self.masks), phi, b2);
            stats.cell_updates += n as u64;
        }
        let use_pcg = match method {
            Method::Auto => self.has_krylov(),
            Method::VCycle => false,
            Method::Pcg => {
                if !self.has_krylov() {
                    return Err(SolveError::ScratchTooSmall);
                }
                true
            }
        };
        // Why the solve stopped, where not at its cap (V-cycles only: MGPCG's comes from
        // its residual and estimate at the end).
        let mut stopped = Stop::Cap;
        let mut steps = Contraction::scaled(CORRECTION_SHARE);
        let error_ok = |steps: &Contraction, res: &Residual| {
            error_met(error_estimate(steps, res, &screen), params.max_error)
        };
        if use_pcg {
            (res, steps) = self.pcg(labels, phi, params, res, b2, &mut stats);
            // Its passes stop at the tolerance (or the floor above it) with the error target
            // met, else out of restarts, unless the cap came first.
            if stats.iterations < params.max_iterations {
                let estimate = error_estimate(&steps, &res, &screen);
                stopped = Stop::of(&res, params, estimate, Stop::Restarts);
            }
        } else {
            // Aim at half the tolerance, as the CG passes do: the error left is up to the
            // condition number times the residual, and long corridors have a large one. Below
            // the rounding floor, go on while the residual still falls (see `STALL_CYCLES`).
            let mut best = res.relative;
            // A warm start already at the floor was left there by a solve that stopped by this
            // rule on nearly the same problem: accept it without cycles.
            let mut since_progress = if params.warm_start { STALL_CYCLES } else { 0 };
            loop {
                let residual_done = res.relative <= 0.5 * params.tolerance
                    || res.meets(0.5 * params.tolerance) && since_progress >= STALL_CYCLES;
                if residual_done && error_ok(&steps, &res) {
                    // At the floor, above the tolerance: the rule stops, but not converged.
                    stopped = Stop::Floor;
                    break;
                }
                if stats.iterations >= params.max_iterations {
                    break;
                }
                let fine = View {
                    dims: self.fine,
                    active,
                    labels,
                    masks: self.masks,
                    faces: None,
                    x: &mut *phi,
                    b: None,
                    screen,
                    fork: self.fork,
                };
                let (work, correction) = with_hierarchy!(
                    &mut self.values,
                    &self.levels,
                    self.labels,
                    self.faces,
                    &self.pins,
                    |h| fine_cycle(fine, h)
                );
                stats.cell_updates += work;
                steps.push(correction);
                stats.iterations += 1;
                res = residual_with(&self.fine, &active, &screen, (labels, self.masks), phi, b2);
                stats.cell_updates += n as u64;
                let _ = self.history.push(res.relative);
                if res.relative < (1.0 - STALL_GAIN) * best {
                    best = res.relative;
                    since_progress = 0;
                } else {
                    since_progress += 1;
                }
                let limit = DIVERGED * stats.initial_residual.max(params.tolerance);
                if !res.relative.is_finite() || res.relative > limit {
                    // Never observed with the face floor above, but a diverged φ must not
                    // reach the streamline: reset it and report.
                    zero_interior(labels, phi);
                    return Err(SolveError::Diverged);
                }
            }
        }
        if super::clamp_to_bounds(labels, phi) > super::CLAMP_SLACK {
            res = residual_with(&self.fine, &active, &screen, (labels, self.masks), phi, b2);
            stats.cell_updates += n as u64;
        }
        stats.residual = res.relative;
        stats.floor = res.floor;
        stats.error_estimate = error_estimate(&steps, &res, &screen);
        // Converged only where the tolerance itself (not the floor) and the error target are
        // met, whichever rule stopped the solve.
        stats.converged = super::converged(&res, params, stats.error_estimate);
        stats.stop = if stats.converged { Stop::Met } else { stopped };
        Ok(Solved {
            stats,
            residual: res,
            b2,
        })
    }

    /// Full multigrid start for a cold solve (see [`full_multigrid`]). Returns cell updates.
    fn full_multigrid(&mut self, labels: &[Label], phi: &mut [f32]) -> u64 {
        let fine = View {
            dims: self.fine,
            active: self.fine_active,
            labels,
            masks: self.masks,
            faces: None,
            x: phi,
            b: None,
            screen: self.screen,
            fork: self.fork,
        };
        with_hierarchy!(
            &mut self.values,
            &self.levels,
            self.labels,
            self.faces,
            &self.pins,
            |h| full_multigrid(fine, h)
        )
    }

    /// Coarse labels and face conductances from the fine labels. Returns cells touched.
    fn build_labels(&mut self, fine_labels: &[Label]) -> u64 {
        let mut work = 0u64;
        self.pins = source_pins(&self.fine, fine_labels);
        let mut prev_dims = self.fine;
        let mut prev_offset: Option<usize> = None;
        for level in self.levels.iter_mut() {
            let Some((done, rest)) = self.labels.split_at_mut_checked(level.label_offset) else {
                break;
            };
            // Empty when no face storage was lent: every level then takes `coarsen_labels`.
            let (faces_done, faces_rest) = self.faces.split_at_mut(level.label_offset.min(self.faces.len()));
            let (prev, prev_faces): (&[Label], Option<&[[u8; 4]]>) = match prev_offset {
                None => (fine_labels, None),
                Some(o) => (
                    done.get(o..o + prev_dims.len()).unwrap_or(&[]),
                    faces_done.get(o..o + prev_dims.len()),
                ),
            };
            let Some(coarse) = rest.get_mut(..level.dims.len()) else {
                return work;
            };
            match faces_rest.get_mut(..level.dims.len()) {
                Some(faces) => coarsen(&prev_dims, prev, prev_faces, &level.dims, coarse, faces),
                None => coarsen_labels(&prev_dims, prev, &level.dims, coarse),
            }
            level.active = Active::of(&level.dims, coarse);
            work += prev.len() as u64;
            prev_dims = level.dims;
            prev_offset = Some(level.label_offset);
        }
        work
    }

    /// MGPCG on the correction: solves `A e = r(φ)` and adds `e` to φ. Returns the true
    /// residual at the end and the steps' changes, for the error estimate.
    fn pcg(
        &mut self,
        labels: &[Label],
        phi: &mut [f32],
        params: &SolveParams,
        mut res: Residual,
        b2: f64,
        stats: &mut SolveStats,
    ) -> (Residual, Contraction) {
        let mut steps = Contraction::default();
        let Self {
            fine,
            levels,
            values,
            labels: coarse_labels,
            faces,
            krylov,
            masks,
            history,
            pins,
            fine_active,
            screen,
            fork,
            ..
        } = self;
        let fork: Option<&dyn Fork> = *fork;
        let masks: &[u8] = masks;
        let fine_active = *fine_active;
        let screen = *screen;
        let dims = *fine;
        let n = dims.len();
        let mut precondition = |r: &[f32], z: &mut [f32]| -> u64 {
            z.fill(0.0);
            let fine = View {
                dims,
                active: fine_active,
                labels,
                masks,
                faces: None,
                x: z,
                b: Some(r),
                screen,
                fork,
            };
            with_hierarchy!(values, levels, coarse_labels, faces, pins, |h| fine_cycle(
                fine, h
            )
            .0)
        };
        // `new` lends MGPCG at least 3n values or none (and then this is never called).
        let Some((r, rest)) = krylov.split_at_mut_checked(n) else {
            return (res, steps);
        };
        let Some((p, rest)) = rest.split_at_mut_checked(n) else {
            return (res, steps);
        };
        let Some(z) = rest.get_mut(..n) else {
            return (res, steps);
        };
        residual_into(fork, &dims, &fine_active, &screen, (labels, masks), phi, None, r);
        let b_norm = libm::sqrt(b2);
        if b_norm == 0.0 {
            return (res, steps);
        }
        let rel = |r: &[f32]| (libm::sqrt(dot(r, r)) / b_norm) as f32;
        // Defect correction: each pass runs CG on the true residual of the current φ, so the
        // f32 drift between CG's recursive residual and the true one cannot stall the solve.
        for pass in 0..MAX_RESTARTS {
            if pass > 0 {
                residual_into(fork, &dims, &fine_active, &screen, (labels, masks), phi, None, r);
                res = residual_with(&dims, &fine_active, &screen, (labels, masks), phi, b2);
                stats.cell_updates += 2 * n as u64;
            }
            let error_ok = error_met(error_estimate(&steps, &res, &screen), params.max_error);
            if res.meets(params.tolerance) && error_ok || stats.iterations >= params.max_iterations {
                break;
            }
            let target = params.tolerance.max(res.floor);
            steps.restart();
            stats.cell_updates += precondition(r, z);
            p.copy_from_slice(z);
            let mut rho = dot(r, z);
            let start = res.relative;
            while stats.iterations < params.max_iterations {
                // z ← A p
                apply(fork, &dims, &fine_active, &screen, (labels, masks), p, z);
                stats.cell_updates += n as u64;
                let pq = dot(p, z);
                if !(pq > 0.0 && rho.is_finite()) {
                    break;
                }
                let alpha = (rho / pq) as f32;
                let change = split_cells(
                    fork,
                    n,
                    (&mut *phi, &mut *r),
                    (&*p, &*z),
                    labels,
                    |(x, r), (p, q), l| {
                        let mut change = 0.0f32;
                        for ((((x, r), p), q), l) in x.iter_mut().zip(r).zip(p).zip(q).zip(l) {
                            if *l == Label::Interior {
                                *x += alpha * p;
                                *r -= alpha * q;
                                if (alpha * p).abs() > change {
                                    change = (alpha * p).abs();
                                }
                            }
                        }
                        change
                    },
                );
                stats.iterations += 1;
                let recursive = rel(r);
                steps.push_with_residual(change, recursive);
                let _ = history.push(recursive);
                // Stop this pass at the target, or once it has gained three orders of
                // magnitude (beyond that the recursive residual is no longer trustworthy).
                if recursive <= target * 0.5 || recursive <= start * 1e-3 {
                    break;
                }
                stats.cell_updates += precondition(r, z);
                let rho_new = dot(r, z);
                let beta = (rho_new / rho) as f32;
                rho = rho_new;
                split_cells(
                    fork,
                    n,
                    (&mut *p, &mut []),
                    (&*z, &[]),
                    labels,
                    |(p, _), (z, _), _| {
                        for (pi, zi) in p.iter_mut().zip(z) {
                            *pi = zi + beta * *pi;
                        }
                        0.0
                    },
                );
            }
        }
        // Report the true residual, not the recurrence's.
        stats.cell_updates += n as u64;
        (
            residual_with(&dims, &fine_active, &screen, (labels, masks), phi, b2),
            steps,
        )
    }
}

/// Sets ψ = 0 on the interior, keeping the Dirichlet values.
fn zero_interior(labels: &[Label], phi: &mut [f32]) {
    for (l, p) in labels.iter().zip(phi.iter_mut()) {
        if *l == Label::Interior {
            *p = 0.0;
        }
    }
}

/// Full multigrid start for a cold solve: solves the problem itself (not an error
/// equation) on the coarsest level, then on each finer level interpolates that solution
/// and improves it with one V-cycle, and finally interpolates onto the fine grid. Coarse
/// levels absorb the source into interior cells (see `coarsen`), so the coarse cells holding
/// a source voxel are pinned at ψ = 0 after every step instead. `fine` is the fine level
/// (its φ is overwritten on the interior). Returns cell updates.
fn full_multigrid<U: Stored>(mut fine: View<'_>, coarse: Hierarchy<'_, U>) -> u64 {
    let Hierarchy {
        levels,
        values,
        labels: coarse_labels,
        faces: coarse_faces,
        pins,
    } = coarse;
    let mut work = 0u64;
    let Some(coarsest) = levels.len().checked_sub(1) else {
        return 0;
    };
    for k in (0..=coarsest).rev() {
        let Some(level) = levels.get(k).copied() else {
            continue;
        };
        let n = level.dims.len();
        let lo = level.label_offset;
        let Some(clabels) = coarse_labels.get(lo..lo + n) else {
            return work;
        };
        let cfaces = coarse_faces.get(lo..lo + n);
        let (head, rest) = values.split_at_mut((level.offset + 2 * n).min(values.len()));
        let Some(mine) = head.get_mut(level.offset..) else {
            return work;
        };
        let (x, b) = mine.split_at_mut(n.min(mine.len()));
        // The problem itself: sinks lead to frontier values (the source is pinned below).
        b.fill(U::default());
        for (bi, f) in b.iter_mut().zip(cfaces.unwrap_or(&[])) {
            *bi = U::store(f32::from(f[3]) * SINK_UNIT as f32 / f32::from(FACE_ONE) * super::PSI_FRONTIER);
        }
        for (v, l) in x.iter_mut().zip(clabels) {
            *v = U::store(if *l == Label::Frontier {
                super::PSI_FRONTIER
            } else {
                0.0
            });
        }
        let rest_levels: HVec<Level, MAX_LEVELS> = levels
            .iter()
            .skip(k + 1)
            .map(|l| Level {
                offset: l.offset - (level.offset + 2 * n),
                ..*l
            })
            .collect();
        if let Some(coarser) = rest_levels.first() {
            // Interpolate the coarser solution (it sits at the start of `rest`).
            let cn = coarser.dims.len();
            let cl = coarser.labels(coarse_labels);
            let cx = rest.get(coarser.offset..coarser.offset + cn).unwrap_or(&[]);
            let mut view = View::coarse(&level, k + 1, &fine.screen, clabels, cfaces, &mut *x, None);
            let _ = interpolate_into(&mut view, &coarser.dims, cl, cx, true);
        }
        pin_sources(pins, k + 1, &level.dims, x);
        let mut view = View::coarse(&level, k + 1, &fine.screen, clabels, cfaces, &mut *x, Some(&*b));
        if rest_levels.is_empty() {
            for _ in 0..COARSEST_SWEEPS {
                work += relax(&mut view, 0) + relax(&mut view, 1);
                pin_sources(pins, k + 1, &level.dims, view.x);
            }
        } else {
            work += vcycle(view, &rest_levels, rest, coarse_labels, coarse_faces).0;
            pin_sources(pins, k + 1, &level.dims, x);
        }
    }
    // The fine grid: interpolate the first coarse level's solution onto the interior.
    if let Some(level) = levels.first() {
        let n = level.dims.len();
        let cl = level.labels(coarse_labels);
        let cx = values.get(level.offset..level.offset + n).unwrap_or(&[]);
        let _ = interpolate_into(&mut fine, &level.dims, cl, cx, true);
        work += fine.dims.len() as u64;
    }
    work
}

/// Face conductance of a fully open coarse face. A coarse face covers four faces of the level
/// below; its conductance is the mean of theirs (1 for a face between two in-domain fine
/// cells, 0 otherwise), stored as a multiple of 1/240 so that quarters stay exact.
pub const FACE_ONE: u8 = 240;

/// Least conductance of a coarse face with any open child face.
///
/// The exact mean makes faces beside walls and in corners very weak, while the renormalised
/// transfers still hand those cells their full share of the residual; the coarse correction
/// then overshoots there and plain V-cycles diverge (measured on the rooms-with-doors
/// benchmark: a floor of ¼ diverges on 32×32×16, ⅓ converges in 35 cycles on 64×64×32, ½ in 41,
/// "any open child face = fully open" in 63, the old label-only operator in 109). ½ is the
/// safe choice: walls stay closed, and partial faces are never weaker than half.
const MIN_OPEN_FACE: u8 = FACE_ONE >> 1; // ½

/// Unit of the sink conductance stored in a coarse cell's fourth face byte, in units of
/// [`FACE_ONE`]: 1/16 of an open face, so a byte holds up to ~16 open faces of sink.
const SINK_UNIT: u32 = (FACE_ONE as u32) >> 4; // 1/16

/// Labels and face conductances of one coarse level from the level below (`prev_faces` is
/// `None` for the fine level, where a face is open when both its cells are in the domain).
///
/// Labels: *Dirichlet wins* (any frontier child makes a frontier cell), else interior if any
/// child is in the domain. Faces: the conductance of the `+axis` face of coarse cell `C` is the
/// mean over the (up to four) child faces that cross it. A one-voxel wall therefore stays a
/// wall on the coarse levels (its faces are closed) instead of vanishing because each coarse
/// cell beside it still holds some free child.
fn coarsen(
    prev_dims: &Dims,
    prev: &[Label],
    prev_faces: Option<&[[u8; 4]]>,
    dims: &Dims,
    coarse: &mut [Label],
    faces: &mut [[u8; 4]],
) {
    coarse.fill(Label::Outside);
    faces.fill([0; 4]);
    let (pnx, pny, pnz) = (prev_dims.nx(), prev_dims.ny(), prev_dims.nz());
    let strides = [1, pnx, pnx * pny];
    let sizes = [pnx, pny, pnz];
    let dirichlet = |l: Label| matches!(l, Label::Frontier | Label::Source);
    // Conductance of the +axis face of cell `i` of the level below.
    let face = |i: usize, axis: usize| match prev_faces {
        None => FACE_ONE,
        Some(f) => f.get(i).and_then(|f| f.get(axis)).copied().unwrap_or(0),
    };
    for z in 0..pnz {
        for y in 0..pny {
            let start = pnx * (y + pny * z);
            let parent_row = dims.nx() * ((y >> 1) + dims.ny() * (z >> 1));
            for x in 0..pnx {
                let i = start + x;
                let label = prev.get(i).copied().unwrap_or(Label::Outside);
                if !label.in_domain() {
                    continue;
                }
                let parent = parent_row + (x >> 1);
                let Some((c, f)) = coarse.get_mut(parent).zip(faces.get_mut(parent)) else {
                    continue;
                };
                *c = match (*c, label) {
                    (_, Label::Interior) | (Label::Interior, _) => Label::Interior,
                    (Label::Outside | Label::Source, Label::Source) => Label::Source,
                    _ => Label::Frontier,
                };
                if label != Label::Interior {
                    continue;
                }
                // What this interior child inherits as a sink, and its faces.
                let mut sink = u32::from(prev_faces.and_then(|pf| pf.get(i)).map_or(0, |f| f[3])) * SINK_UNIT;
                let coords = [x, y, z];
                for (axis, ((&cc, &n), &stride)) in coords.iter().zip(&sizes).zip(&strides).enumerate() {
                    // −axis neighbour: its +axis face is ours.
                    if cc > 0 {
                        let j = i - stride;
                        if prev.get(j).is_some_and(|&l| dirichlet(l)) {
                            sink += u32::from(face(j, axis));
                        }
                    }
                    if cc + 1 < n {
                        let j = i + stride;
                        match prev.get(j).copied() {
                            Some(l) if dirichlet(l) => sink += u32::from(face(i, axis)),
                            Some(Label::Interior) if !cc.is_multiple_of(2) => {
                                // Crosses into the next parent: part of the coarse +axis face.
                                if let Some(w) = f.get_mut(axis) {
                                    *w = w.saturating_add(face(i, axis).div_ceil(4));
                                }
                            }
                            _ => {}
                        }
                    }
                }
                // A coarse face is the sum of its child faces over four; a sink only halves (see
                // the module doc).
                if let Some(s) = f.get_mut(3) {
                    let add = (sink >> 1).div_ceil(SINK_UNIT);
                    *s = u8::try_from(u32::from(*s) + add).unwrap_or(u8::MAX);
                }
            }
        }
    }
    for (f, l) in faces.iter_mut().zip(coarse.iter()) {
        if *l != Label::Interior {
            // Dirichlet and outside cells are never relaxed; their faces carry nothing.
            *f = [0; 4];
            continue;
        }
        // A partly open face keeps at least half the conductance of an open one.
        for w in f.iter_mut().take(3) {
            if *w > 0 {
                *w = (*w).max(MIN_OPEN_FACE);
            }
        }
    }
}

/// Labels of one coarse level when no face storage was lent: *Dirichlet wins* (any frontier
/// child makes a frontier cell, so the frontiers' pull reaches every level; the source is
/// absorbed into interior cells), else interior if any child is in the domain.
fn coarsen_labels(prev_dims: &Dims, prev: &[Label], dims: &Dims, coarse: &mut [Label]) {
    coarse.fill(Label::Outside);
    let (pnx, pny) = (prev_dims.nx(), prev_dims.ny());
    for z in 0..prev_dims.nz() {
        for y in 0..pny {
            let start = pnx * (y + pny * z);
            let parent_row = dims.nx() * ((y >> 1) + dims.ny() * (z >> 1));
            for (x, l) in prev.get(start..start + pnx).unwrap_or(&[]).iter().enumerate() {
                if !l.in_domain() {
                    continue;
                }
                if let Some(c) = coarse.get_mut(parent_row + (x >> 1)) {
                    *c = match (*c, *l) {
                        (_, Label::Frontier) | (Label::Frontier, _) => Label::Frontier,
                        _ => Label::Interior,
                    };
                }
            }
        }
    }
}

/// Weighted flux `Σ w (v_j − v_i)` into cell `i` of a coarse level and the weight sum, both in
/// units of [`FACE_ONE`]. The `+axis` conductance of a cell is stored with the cell, the
/// `−axis` one with its lower neighbour; conductances are 0 at the upper grid edges, so the
/// wrapped or out-of-range reads at the edges contribute nothing.
#[inline(always)]
fn weighted_flux<V: RowValues + ?Sized>(
    faces: &[[u8; 4]],
    v: &V,
    i: usize,
    nx: usize,
    nxy: usize,
) -> (f32, f32) {
    let c = v.at(i);
    let w = |j: usize, axis: usize| {
        faces
            .get(j)
            .and_then(|f| f.get(axis))
            .map_or(0.0, |&w| f32::from(w))
    };
    let (mut flux, mut sum) = (0.0f32, 0.0f32);
    for (below, axis, step) in [
        (i.wrapping_sub(1), 0, 1),
        (i.wrapping_sub(nx), 1, nx),
        (i.wrapping_sub(nxy), 2, nxy),
    ] {
        let (wl, wu) = (w(below, axis), w(i, axis));
        flux += wl * (v.at(below) - c) + wu * (v.at(i + step) - c);
        sum += wl + wu;
    }
    // The sink: conductance to Dirichlet children, whose correction is 0.
    let sink = faces.get(i).map_or(0.0, |f| f32::from(f[3])) * SINK_UNIT as f32;
    (flux - sink * c, sum + sink)
}

/// Red-black half sweep on a coarse level with face conductances.
fn relax_weighted<T: Stored>(v: &mut View<'_, T>, faces: &[[u8; 4]], colour: usize) -> u64 {
    let (nx, ny) = (v.dims.nx(), v.dims.ny());
    let nxy = nx * ny;
    let cells = Cell::from_mut(&mut *v.x).as_slice_of_cells();
    // The screening in face-conductance units.
    let shift = v.screen.shift * f32::from(FACE_ONE);
    let mut updates = 0u64;
    let xs = v.active.xs();
    for z in v.active.zs() {
        for y in v.active.ys() {
            let start = nx * (y + ny * z);
            let mut x = first_of_colour(xs.start, (colour + y + z) & 1);
            while x < xs.end.min(nx) {
                let i = start + x;
                if let (Some(Label::Interior), Some(cell)) = (v.labels.get(i), cells.get(i)) {
                    let (flux, sum) = weighted_flux(faces, cells, i, nx, nxy);
                    if sum > 0.0 {
                        let b = v.b.map_or(0.0, |b| b.at(i));
                        let c = cell.get().load();
                        cell.set(T::store(
                            c + (flux - shift * c + f32::from(FACE_ONE) * b) / (sum + shift),
                        ));
                        updates += 1;
                    }
                }
                x += 2;
            }
        }
    }
    updates
}

/// Sets ψ = 0 at the cells of a level `depth` halvings below the fine grid that hold a
/// source voxel.
fn pin_sources<T: Stored>(pins: &[[usize; 3]], depth: usize, dims: &Dims, x: &mut [T]) {
    for &[px, py, pz] in pins {
        let (cx, cy, cz) = (px >> depth, py >> depth, pz >> depth);
        if cx < dims.nx() && cy < dims.ny() && cz < dims.nz() {
            if let Some(v) = x.get_mut(cx + dims.nx() * (cy + dims.ny() * cz)) {
                *v = T::store(super::PSI_SOURCE);
            }
        }
    }
}

/// Dot product summed in f32 over chunks of 64, chunks in f64.
fn cut(v: &[f32], at: usize) -> (&[f32], &[f32]) {
    v.split_at(at.min(v.len()))
}

fn cut_mut(v: &mut [f32], at: usize) -> (&mut [f32], &mut [f32]) {
    let at = at.min(v.len());
    v.split_at_mut(at)
}

/// Runs `f` over the first `n` cells of two written and two read vectors (an empty one stays
/// empty) and their labels: whole, or in two halves through `fork`. Returns the larger of the
/// halves' results (a largest change). Every cell's arithmetic is its own, so the split changes
/// no bit.
#[allow(clippy::type_complexity)]
fn split_cells(
    fork: Option<&dyn Fork>,
    n: usize,
    (w0, w1): (&mut [f32], &mut [f32]),
    (r0, r1): (&[f32], &[f32]),
    labels: &[Label],
    f: impl Fn((&mut [f32], &mut [f32]), (&[f32], &[f32]), &[Label]) -> f32 + Sync,
) -> f32 {
    let (w0, _) = cut_mut(w0, n);
    let (w1, _) = cut_mut(w1, n);
    let (r0, _) = cut(r0, n);
    let (r1, _) = cut(r1, n);
    let (labels, _) = labels.split_at(n.min(labels.len()));
    let Some(fork) = fork.filter(|_| n >= 2 * super::MIN_SPLIT_CELLS) else {
        return f((w0, w1), (r0, r1), labels);
    };
    let m = n >> 1;
    let ((w0a, w0b), (w1a, w1b)) = (cut_mut(w0, m), cut_mut(w1, m));
    let ((r0a, r0b), (r1a, r1b)) = (cut(r0, m), cut(r1, m));
    let (la, lb) = labels.split_at(m.min(labels.len()));
    let (mut a, mut b) = (0.0f32, 0.0f32);
    fork.join(&mut || a = f((&mut *w0a, &mut *w1a), (r0a, r1a), la), &mut || {
        b = f((&mut *w0b, &mut *w1b), (r0b, r1b), lb)
    });
    if b > a {
        b
    } else {
        a
    }
}

fn dot(a: &[f32], b: &[f32]) -> f64 {
    let mut total = 0.0f64;
    for (ca, cb) in a.chunks(64).zip(b.chunks(64)) {
        let s: f32 = ca.iter().zip(cb).map(|(x, y)| x * y).sum();
        total += f64::from(s);
    }
    total
}

/// `out ← A p` on interior cells (0 elsewhere); `p` must be 0 off the interior.
fn apply(
    fork: Option<&dyn Fork>,
    dims: &Dims,
    active: &Active,
    screen: &Screen,
    cells: (&[Label], &[u8]),
    p: &[f32],
    out: &mut [f32],
) {
    residual_into(fork, dims, active, screen, cells, p, None, out);
    for o in out.iter_mut() {
        *o = -*o;
    }
}

/// `out ← b − L x` on interior cells (0 elsewhere).
#[allow(clippy::too_many_arguments)]
fn residual_into(
    fork: Option<&dyn Fork>,
    dims: &Dims,
    active: &Active,
    screen: &Screen,
    (labels, masks): (&[Label], &[u8]),
    x: &[f32],
    b: Option<&[f32]>,
    out: &mut [f32],
) {
    if masks.len() >= dims.len() {
        residual_rows_into::<true>(fork, dims, active, screen, (labels, masks), x, b, out);
    } else {
        residual_rows_into::<false>(fork, dims, active, screen, (labels, &[]), x, b, out);
    }
}

/// [`residual_into`] with the [neighbour masks](super::neighbour_mask) (`MASKS`) or the
/// labels: one instance each, so the firmware's (labels) is the code it always was.
#[allow(clippy::too_many_arguments)]
fn residual_rows_into<const MASKS: bool>(
    fork: Option<&dyn Fork>,
    dims: &Dims,
    active: &Active,
    screen: &Screen,
    (labels, masks): (&[Label], &[u8]),
    x: &[f32],
    b: Option<&[f32]>,
    out: &mut [f32],
) {
    // Rows outside the active box hold no interior cell: their residual is 0.
    out.fill(0.0);
    let each_row = |st: &Stencil<'_, f32>, row: &[f32], out_row: &mut [f32]| {
        let b_row = b.and_then(|b| b.get(st.start..st.start + row.len()));
        let each = |x: usize, r: f32, _: u32| {
            if let Some(o) = out_row.get_mut(x) {
                *o = r;
            }
        };
        if MASKS {
            super::row_residuals_masked(st, row, b_row, st.masks_in(masks), each);
        } else {
            super::row_residuals(st, row, b_row, each);
        }
    };
    for_each_row_out_split(fork, dims, active, screen, labels, x, out, &each_row);
}

/// One red-black half sweep: relaxes interior cells with `(x + y + z) % 2 == colour`, in place,
/// row by row. Rows away from the y/z edges take the branch-free path of [`relax_inner`].
fn relax<T: Stored>(v: &mut View<'_, T>, colour: usize) -> u64 {
    if let Some(faces) = v.faces {
        return relax_weighted(v, faces, colour);
    }
    if T::FINE && v.masks.len() >= v.dims.len() {
        relax_rows::<T, true>(v, colour)
    } else {
        relax_rows::<T, false>(v, colour)
    }
}

/// [`relax`] with the [neighbour masks](super::neighbour_mask) (`MASKS`) or the labels: one
/// instance each, so the firmware's (labels) is the code it always was.
fn relax_rows<T: Stored, const MASKS: bool>(v: &mut View<'_, T>, colour: usize) -> u64 {
    let b = v.b;
    let screen = v.screen;
    let masks = v.masks;
    let each_row = |st: &Stencil<'_, T>, row: &[Cell<T>]| -> u64 {
        let mut updates = 0u64;
        let nx = row.len();
        let b_row = b.and_then(|b| b.get(st.start..st.start + nx));
        let first = (colour + st.y + st.z) & 1;
        let end = st.x1.min(nx);
        let mut one = |x: usize| {
            if let (Some(Label::Interior), Some(cell)) = (st.labels.get(x), row.get(x)) {
                let c = cell.get().load();
                let (flux, n) = st.flux(row, x, c);
                let bx = b_row.map_or(0.0, |b| b.at(x));
                cell.set(T::store(screen.relaxed(c, flux, bx, screen.inv(n))));
                updates += u64::from(n > 0);
            }
        };
        match st.inner() {
            Some(inner) if nx >= 3 => {
                if first == 0 && st.x0 == 0 {
                    one(0);
                }
                if (nx - 1) & 1 == first && end == nx {
                    one(nx - 1);
                }
                let start = first_of_colour(st.x0.max(1), first);
                updates += if MASKS {
                    relax_masked(&inner, st.masks_in(masks), &screen, row, b_row, start, end)
                } else {
                    relax_inner(&inner, &screen, row, b_row, start, end)
                };
            }
            _ => {
                let mut x = first_of_colour(st.x0, first);
                while x < end {
                    one(x);
                    x += 2;
                }
            }
        }
        updates
    };
    // A half sweep's cells read only the other colour: the fork may split it (fine level).
    let fork = if T::FINE { v.fork } else { None };
    for_each_row_mut_split(fork, &v.dims, &v.active, &screen, v.labels, v.x, &each_row)
}

/// The first `x ≥ from` of the colour whose first cell is `first` (0 or 1): red-black sweeps
/// visit `first, first + 2, …`.
#[inline(always)]
fn first_of_colour(from: usize, first: usize) -> usize {
    from + ((from ^ first) & 1)
}

/// [`relax_inner`] for a row whose [neighbour masks](super::neighbour_mask) `masks` were lent
/// (the host's storage): one byte per cell instead of seven labels, the same arithmetic.
#[inline(always)]
fn relax_masked<T: Stored>(
    inner: &super::Inner<'_, T>,
    masks: &[u8],
    screen: &Screen,
    row: &[Cell<T>],
    b: Option<&[T]>,
    start: usize,
    end: usize,
) -> u64 {
    let nx = row.len();
    let (Some(cut), Some(masks)) = (inner.cut(nx), masks.get(..nx)) else {
        return relax_inner(inner, screen, row, b, start, end);
    };
    let b = b.and_then(|b| b.get(..nx));
    let bx = |x: usize| b.map_or(0.0, |b| b.at(x));
    let (mut x, end) = (start, end.min(nx - 1));
    let inv6 = screen.inv(6);
    let mut updates = 0u64;
    while x < end {
        let (Some(&m), Some(cell)) = (masks.get(x), row.get(x)) else {
            break;
        };
        if m == MASK_OPEN {
            let c = cell.get().load();
            let flux = cut.open_flux(row, x, c);
            cell.set(T::store(screen.relaxed(c, flux, bx(x), inv6)));
            updates += 1;
        } else if m & MASK_INTERIOR != 0 {
            let c = cell.get().load();
            let (flux, n) = cut.masked_flux(row, x, c, m);
            cell.set(T::store(screen.relaxed(c, flux, bx(x), screen.inv(n))));
            updates += u64::from(n > 0);
        }
        x += 2;
    }
    updates
}

/// Relaxes cells `start, start + 2, …` below `end` and `nx − 1` of a row whose four neighbour
/// rows exist. Every slice is cut to the row length first, so the neighbour reads compile
/// without bounds checks and the in-domain tests become selects.
#[inline(always)]
fn relax_inner<T: Stored>(
    inner: &super::Inner<'_, T>,
    screen: &Screen,
    row: &[Cell<T>],
    b: Option<&[T]>,
    start: usize,
    end: usize,
) -> u64 {
    let nx = row.len();
    let Some(cut) = inner.cut(nx) else {
        return 0;
    };
    let b = b.and_then(|b| b.get(..nx));
    let mut updates = 0u64;
    let mut x = start;
    let end = end.min(nx - 1);
    let bx = |x: usize| b.map_or(0.0, |b| b.at(x));
    while x < end {
        // This colour's cells of an open run skip the label tests.
        if x + OPEN_RUN <= end && cut.open_run(x) {
            let inv = screen.inv(6);
            for x in (x..x + OPEN_RUN).step_by(2) {
                if let Some(cell) = row.get(x) {
                    let c = cell.get().load();
                    let flux = cut.open_flux(row, x, c);
                    cell.set(T::store(screen.relaxed(c, flux, bx(x), inv)));
                }
            }
            updates += (OPEN_RUN >> 1) as u64;
            x += OPEN_RUN;
            continue;
        }
        let (Some(&lc), Some(cell)) = (cut.l.get(x), row.get(x)) else {
            break;
        };
        if lc == Label::Interior {
            let c = cell.get().load();
            let (flux, n) = cut.flux(row, x, c);
            cell.set(T::store(screen.relaxed(c, flux, bx(x), screen.inv(n))));
            updates += u64::from(n > 0);
        }
        x += 2;
    }
    updates
}

/// Coarse parents of fine coordinate `c` along one axis: its own parent (weight ¾) and the
/// coarse neighbour on the side `c` lies towards (¼), `None` past the grid edge.
#[inline]
fn axis_parents(c: usize, n: usize) -> [(Option<usize>, f32); 2] {
    let p = c >> 1;
    let other = if c.is_multiple_of(2) {
        p.checked_sub(1)
    } else {
        Some(p + 1).filter(|&o| o < n)
    };
    [(Some(p), 0.75), (other, 0.25)]
}

/// The coarse rows holding the parents of fine row `(y, z)`: start of coarse row `(0, cy, cz)`
/// and the weight `w_y·w_z`. Up to four; the count is returned alongside.
fn parent_rows(y: usize, z: usize, coarse: &Dims) -> ([(usize, f32); 4], usize) {
    let mut rows = [(0usize, 0.0f32); 4];
    let mut n = 0;
    for (cz, wz) in axis_parents(z, coarse.nz()) {
        for (cy, wy) in axis_parents(y, coarse.ny()) {
            if let (Some(cy), Some(cz), Some(slot)) = (cy, cz, rows.get_mut(n)) {
                *slot = (coarse.nx() * (cy + coarse.ny() * cz), wy * wz);
                n += 1;
            }
        }
    }
    (rows, n)
}

/// The coarse rows under one fine row: each row's labels, its values and the weight `w_y·w_z`;
/// unused entries are empty.
struct Parents<'c, U> {
    rows: [(&'c [Label], &'c [U], f32); 4],
}

impl<'c, U: Stored> Parents<'c, U> {
    /// The parent rows of fine row `(y, z)` in a coarse grid with `labels` and `values`.
    fn of(y: usize, z: usize, coarse: &Dims, labels: &'c [Label], values: &'c [U]) -> Self {
        let (starts, n) = parent_rows(y, z, coarse);
        let cnx = coarse.nx();
        let mut rows: [(&'c [Label], &'c [U], f32); 4] = [(&[], &[], 0.0); 4];
        for (slot, &(start, w)) in rows.iter_mut().zip(starts.iter().take(n)) {
            *slot = (
                labels.get(start..start + cnx).unwrap_or(&[]),
                values.get(start..start + cnx).unwrap_or(&[]),
                w,
            );
        }
        Parents { rows }
    }

    /// Trilinear interpolation at fine `x` of the coarse values and of the coarse
    /// "not outside" mask: `(Σ w·v, Σ w·m)`. Outside coarse cells hold 0, so the value sum
    /// needs no mask; dividing one by the other renormalises over the cells that exist.
    #[inline(always)]
    fn interpolate(&self, x: usize) -> (f32, f32) {
        let (c0, c1) = fine_to_coarse_x(x);
        let (mut num, mut den) = (0.0f32, 0.0f32);
        for &(l, v, w) in &self.rows {
            let m = |c: usize| {
                if l.get(c).is_some_and(|l| *l != Label::Outside) {
                    1.0
                } else {
                    0.0
                }
            };
            num += w * (0.75 * v.at(c0) + 0.25 * v.at(c1));
            den += w * (0.75 * m(c0) + 0.25 * m(c1));
        }
        (num, den)
    }
}

impl<U: Stored> Parents<'_, U> {
    /// Collapses the parent rows along y and z: `cv[c] = Σ w·v[c]` and `cm[c] = Σ w·m[c]`
    /// (`m` = 1 where the coarse cell is not outside). Interpolating at a fine `x` then reads
    /// two entries of each instead of eight labels and values. `cv` may be empty (mask only).
    fn collapse(&self, cv: &mut [f32], cm: &mut [f32]) {
        cv.fill(0.0);
        cm.fill(0.0);
        for &(l, v, w) in &self.rows {
            for (m, l) in cm.iter_mut().zip(l) {
                *m += if *l != Label::Outside { w } else { 0.0 };
            }
            for (c, v) in cv.iter_mut().zip(v.iter()) {
                *c += w * v.load();
            }
        }
    }
}

/// [`Parents::interpolate`] from collapsed rows.
#[inline(always)]
fn interpolate_collapsed(cv: &[f32], cm: &[f32], x: usize) -> (f32, f32) {
    let (c0, c1) = fine_to_coarse_x(x);
    (
        0.75 * cv.at(c0) + 0.25 * cv.at(c1),
        0.75 * cm.at(c0) + 0.25 * cm.at(c1),
    )
}

/// Longest coarse row the transfers collapse on the stack; longer rows take the per-cell path.
const ROW_BUF: usize = 256;

/// The two coarse parents of fine `x` along the x axis: its own (weight ¾) and the neighbour
/// on its side (¼; `usize::MAX` past the low edge, which reads as absent).
#[inline(always)]
fn fine_to_coarse_x(x: usize) -> (usize, usize) {
    let c = x >> 1;
    (
        c,
        if x.is_multiple_of(2) {
            c.wrapping_sub(1)
        } else {
            c + 1
        },
    )
}

/// `cb ← ½ Pᵀ r`: restricts the residual of `fine` (the fine level or a coarse one) to the
/// interior coarse cells with the transpose of [`prolongate`]'s renormalised weights, scaled by ½
/// so that the coarse operator matches `R A P` in open space.
// Not inlined: its stack rows must not sit in every frame of the recursive `vcycle`.
#[inline(never)]
fn restrict<T: Stored, U: Stored>(fine: &View<'_, T>, coarse: &Dims, clabels: &[Label], cb: &mut [U]) {
    if T::FINE && fine.masks.len() >= fine.dims.len() {
        restrict_rows::<T, U, true>(fine, coarse, clabels, cb);
    } else {
        restrict_rows::<T, U, false>(fine, coarse, clabels, cb);
    }
}

/// [`restrict`] with the fine level's [neighbour masks](super::neighbour_mask) (`MASKS`) or its
/// labels: one instance each, so the firmware's (labels) is the code it always was.
fn restrict_rows<T: Stored, U: Stored, const MASKS: bool>(
    fine: &View<'_, T>,
    coarse: &Dims,
    clabels: &[Label],
    cb: &mut [U],
) {
    let zs = fine.active.zs();
    let fork = if T::FINE { fine.fork } else { None };
    let czs = 0..coarse.nz();
    let (Some(fork), Some(cm), true) = (
        fork,
        split_plane(&czs, coarse.nx() * coarse.ny()),
        coarse.nx() <= ROW_BUF,
    ) else {
        restrict_planes::<T, U, MASKS>(fine, zs, coarse, clabels, cb, 0);
        return;
    };
    // Each half sums into its own coarse planes, from every fine plane with a parent there, in
    // the order of the whole pass: fine planes 2·cm − 1 and 2·cm, whose parents straddle the
    // split, are visited by both halves (each adds to its own planes only).
    let cplane = coarse.nx() * coarse.ny();
    let (lo, hi) = cb.split_at_mut((cm * cplane).min(cb.len()));
    let a = zs.start..zs.end.min(2 * cm + 1);
    let b = zs.start.max(2 * cm - 1)..zs.end;
    fork.join(
        &mut || restrict_planes::<T, U, MASKS>(fine, a.clone(), coarse, clabels, lo, 0),
        &mut || restrict_planes::<T, U, MASKS>(fine, b.clone(), coarse, clabels, hi, cm * cplane),
    );
}

/// [`restrict_rows`] from the fine planes `zs` into the coarse values `cb`, a slab starting at
/// coarse linear index `cbase`: parents outside the slab are left to the other half.
fn restrict_planes<T: Stored, U: Stored, const MASKS: bool>(
    fine: &View<'_, T>,
    zs: core::ops::Range<usize>,
    coarse: &Dims,
    clabels: &[Label],
    cb: &mut [U],
    cbase: usize,
) {
    let cnx = coarse.nx();
    let zeros: [U; 0] = [];
    let (fnx, fny) = (fine.dims.nx(), fine.dims.ny());
    let nxy = fnx * fny;
    let x_all: &[T] = fine.x;
    let (mut cm_buf, mut acc_buf) = ([0.0f32; ROW_BUF], [0.0f32; ROW_BUF]);
    let collapsed = cnx <= ROW_BUF;
    for z in zs.clone() {
        for y in fine.active.ys() {
            let start = fnx * (y + fny * z);
            // Mask only: coarse values are not read here.
            let parents = Parents::of(y, z, coarse, clabels, &zeros);
            let (starts, n) = parent_rows(y, z, coarse);
            let cm = cm_buf.get_mut(..cnx).unwrap_or(&mut []);
            let acc = acc_buf.get_mut(..cnx).unwrap_or(&mut []);
            if collapsed {
                parents.collapse(&mut [], cm);
                acc.fill(0.0);
            }
            let cm: &[f32] = cm;
            let mut scatter = |x: usize, r: f32, _n: u32| {
                let (c0, c1) = fine_to_coarse_x(x);
                if collapsed {
                    // Along x into the row accumulator; the y/z weights follow per row below.
                    let (_, den) = interpolate_collapsed(&[], cm, x);
                    if den > 0.0 {
                        let s = 0.5 * r / den;
                        if let Some(a) = acc.get_mut(c0) {
                            *a += 0.75 * s;
                        }
                        if let Some(a) = acc.get_mut(c1) {
                            *a += 0.25 * s;
                        }
                    }
                    return;
                }
                let (_, den) = parents.interpolate(x);
                if den <= 0.0 {
                    return;
                }
                let s = 0.5 * r / den;
                for (&(row_start, wyz), &(l, _, _)) in starts.iter().take(n).zip(&parents.rows) {
                    for (c, wx) in [(c0, 0.75), (c1, 0.25)] {
                        if c < cnx && l.get(c) == Some(&Label::Interior) {
                            if let Some(b) = (row_start + c).checked_sub(cbase).and_then(|i| cb.get_mut(i)) {
                                *b = U::store(b.load() + wyz * wx * s);
                            }
                        }
                    }
                }
            };
            match fine.faces {
                None => {
                    let (Some(before), Some(row), Some(after)) = (
                        x_all.get(..start),
                        x_all.get(start..start + fnx),
                        x_all.get(start + fnx..),
                    ) else {
                        return;
                    };
                    let st = super::Stencil::new(&fine.dims, &fine.screen, y, z, fine.labels, before, after)
                        .within(fine.active.xs());
                    let b_row = fine.b.and_then(|b| b.get(start..start + fnx));
                    if MASKS {
                        super::row_residuals_masked(&st, row, b_row, st.masks_in(fine.masks), scatter);
                    } else {
                        super::row_residuals(&st, row, b_row, scatter);
                    }
                }
                Some(faces) => {
                    for x in fine.active.xs() {
                        let i = start + x;
                        if fine.labels.get(i) == Some(&Label::Interior) {
                            let (flux, _) = weighted_flux(faces, x_all, i, fnx, nxy);
                            let b = fine.b.map_or(0.0, |b| b.at(i));
                            let c = x_all.at(i);
                            let screened = fine.screen.shift * c;
                            scatter(x, b + flux * (1.0 / f32::from(FACE_ONE)) - screened, 0);
                        }
                    }
                }
            }
            if collapsed {
                let acc: &[f32] = acc_buf.get(..cnx).unwrap_or(&[]);
                for (&(row_start, wyz), &(l, _, _)) in starts.iter().take(n).zip(&parents.rows) {
                    let Some(b_row) = row_start.checked_sub(cbase).and_then(|r| cb.get_mut(r..r + cnx))
                    else {
                        continue;
                    };
                    for ((b, a), l) in b_row.iter_mut().zip(acc).zip(l) {
                        if *l == Label::Interior {
                            *b = U::store(b.load() + wyz * a);
                        }
                    }
                }
            }
        }
    }
}

/// `x_f += P x_c` on interior fine cells: trilinear interpolation renormalised over the coarse
/// cells that are not outside (Dirichlet ones count with their value).
/// Returns the largest correction added to any cell.
fn prolongate<T: Stored, U: Stored>(
    fine: &mut View<'_, T>,
    coarse: &Dims,
    clabels: &[Label],
    cx: &[U],
) -> f32 {
    interpolate_into(fine, coarse, clabels, cx, false)
}

/// `x_f ← P x_c` (`set`) or `x_f += P x_c` on interior fine cells. Returns the largest
/// interpolated value's magnitude (with `set` false: the largest correction).
// Not inlined: its stack rows must not sit in every frame of the recursive `vcycle`.
#[inline(never)]
fn interpolate_into<T: Stored, U: Stored>(
    fine: &mut View<'_, T>,
    coarse: &Dims,
    clabels: &[Label],
    cx: &[U],
    set: bool,
) -> f32 {
    let zs = fine.active.zs();
    let fork = if T::FINE { fine.fork } else { None };
    let (Some(fork), Some(m)) = (fork, split_plane(&zs, fine.dims.nx() * fine.dims.ny())) else {
        return interpolate_planes(
            (&fine.dims, &fine.active, fine.labels),
            zs,
            fine.x,
            0,
            coarse,
            clabels,
            cx,
            set,
        );
    };
    // Every fine cell is written from coarse values only: the planes split anywhere.
    let plane = fine.dims.nx() * fine.dims.ny();
    let at = (&fine.dims, &fine.active, fine.labels);
    let (lo, hi) = fine.x.split_at_mut((m * plane).min(fine.x.len()));
    let (mut a, mut b) = (0.0f32, 0.0f32);
    fork.join(
        &mut || a = interpolate_planes(at, zs.start..m, lo, 0, coarse, clabels, cx, set),
        &mut || b = interpolate_planes(at, m..zs.end, hi, m * plane, coarse, clabels, cx, set),
    );
    if b > a {
        b
    } else {
        a
    }
}

/// [`interpolate_into`] over the planes `zs` of the fine level (its dimensions, active box and
/// labels), whose values there are `x` (a slab starting at linear index `base`).
#[allow(clippy::too_many_arguments)]
fn interpolate_planes<T: Stored, U: Stored>(
    (dims, active, labels): (&Dims, &Active, &[Label]),
    zs: core::ops::Range<usize>,
    x: &mut [T],
    base: usize,
    coarse: &Dims,
    clabels: &[Label],
    cx: &[U],
    set: bool,
) -> f32 {
    let mut largest = 0.0f32;
    let xs = active.xs();
    let (fnx, fny) = (dims.nx(), dims.ny());
    let cnx = coarse.nx();
    let (mut cv_buf, mut cm_buf) = ([0.0f32; ROW_BUF], [0.0f32; ROW_BUF]);
    let mut apply = |v: &mut T, add: f32| {
        // A plain comparison: `f32::max` also orders NaNs, which costs a blend per cell.
        if add.abs() > largest {
            largest = add.abs();
        }
        *v = T::store(add + if set { 0.0 } else { v.load() });
    };
    for z in zs {
        for y in active.ys() {
            // Only the active columns: interior cells lie nowhere else.
            let from = fnx * (y + fny * z) + xs.start;
            let to = from + xs.len();
            let (Some(l_row), Some(row)) = (
                labels.get(from..to),
                from.checked_sub(base).and_then(|f| x.get_mut(f..f + xs.len())),
            ) else {
                continue;
            };
            let parents = Parents::of(y, z, coarse, clabels, cx);
            let (Some(cv), Some(cm)) = (cv_buf.get_mut(..cnx), cm_buf.get_mut(..cnx)) else {
                // Longer rows than the stack buffers: interpolate cell by cell.
                for (k, (l, v)) in l_row.iter().zip(row.iter_mut()).enumerate() {
                    if *l == Label::Interior {
                        let (num, den) = parents.interpolate(xs.start + k);
                        if den > 0.0 {
                            apply(v, num / den);
                        }
                    }
                }
                continue;
            };
            parents.collapse(cv, cm);
            for (k, (l, v)) in l_row.iter().zip(row.iter_mut()).enumerate() {
                if *l == Label::Interior {
                    let (num, den) = interpolate_collapsed(cv, cm, xs.start + k);
                    if den > 0.0 {
                        apply(v, num / den);
                    }
                }
            }
        }
    }
    largest
}

/// The source voxels of `labels` (Dirichlet ψ = 0; none in the screened field), the first
/// [`MAX_PINS`]: where both multigrid solvers smooth locally.
pub(crate) fn source_pins(dims: &Dims, labels: &[Label]) -> HVec<[usize; 3], MAX_PINS> {
    let mut pins = HVec::new();
    let nx = dims.nx().max(1);
    for (r, row) in labels.chunks(nx).enumerate() {
        // Most rows have no source (the screened field has none at all): a test without an
        // early exit, which vectorises, before the cell-by-cell search.
        if !row.iter().fold(false, |any, l| any | (*l == Label::Source)) {
            continue;
        }
        for (x, l) in row.iter().enumerate() {
            if *l == Label::Source {
                let v = dims.voxel(r * nx + x);
                if pins
                    .push([usize::from(v.x), usize::from(v.y), usize::from(v.z)])
                    .is_err()
                {
                    return pins;
                }
            }
        }
    }
    pins
}

/// Half-width of the box around each source voxel that gets extra smoothing.
pub(crate) const LOCAL_RADIUS: usize = 3;

/// Symmetric Gauss-Seidel sweeps (forward, then backward) over a small box around each source
/// voxel of the fine level. A single-voxel Dirichlet source is invisible to the coarse levels
/// (they absorb it), so the error it leaves is local and sharp: ordinary cycles reduce it by
/// only about half per cycle. A few local sweeps remove it at negligible cost. Applied before
/// and after each fine-level V-cycle, which keeps the preconditioner symmetric.
fn local_smooth(v: &mut View<'_>, pins: &[[usize; 3]]) -> u64 {
    let dims = v.dims;
    let (nx, ny, nz) = (dims.nx(), dims.ny(), dims.nz());
    let mut work = 0u64;
    let mut update = |v: &mut View<'_>, x: usize, y: usize, z: usize| {
        let i = x + nx * (y + ny * z);
        if v.labels.get(i) != Some(&Label::Interior) {
            return;
        }
        let c = v.x.get(i).copied().unwrap_or(0.0);
        let (mut flux, mut n) = (0.0f32, 0u32);
        let mut add = |j: usize| {
            if v.labels.get(j).is_some_and(|l| l.in_domain()) {
                flux += v.x.get(j).copied().unwrap_or(0.0) - c;
                n += 1;
            }
        };
        dims.for_each_face_neighbour_of([x, y, z], &mut add);
        let b = v.b.map_or(0.0, |b| b.at(i));
        if let Some(xi) = v.x.get_mut(i) {
            *xi = c + (flux - v.screen.shift * c + b) * v.screen.inv(n);
        }
        work += 1;
    };
    super::symmetric_box_sweep(pins, [nx, ny, nz], LOCAL_RADIUS, |x, y, z| update(v, x, y, z));
    work
}

/// One fine-level cycle: [`local_smooth`] at the source, a V-cycle, [`local_smooth`] again.
/// Returns the cell updates and the largest coarse-grid correction (see [`vcycle`]).
fn fine_cycle<U: Stored>(mut fine: View<'_>, coarse: Hierarchy<'_, U>) -> (u64, f32) {
    let Hierarchy {
        levels,
        values,
        labels,
        faces,
        pins,
    } = coarse;
    let work = local_smooth(&mut fine, pins);
    let View {
        dims,
        active,
        labels: fl,
        masks,
        faces: ff,
        x,
        b,
        screen,
        fork,
    } = fine;
    let (cycle, correction) = vcycle(
        View {
            dims,
            active,
            labels: fl,
            masks,
            faces: ff,
            x: &mut *x,
            b,
            screen,
            fork,
        },
        levels,
        values,
        labels,
        faces,
    );
    let mut fine = View {
        dims,
        active,
        labels: fl,
        masks,
        faces: ff,
        x,
        b,
        screen,
        fork,
    };
    (work + cycle + local_smooth(&mut fine, pins), correction)
}

/// One V-cycle ([`PRE_SWEEPS`], [`POST_SWEEPS`]) on `fine` with the coarse `levels`. Returns
/// cell updates and the largest coarse-grid correction added to `fine` (+∞ where there was no
/// coarse level to correct from: the error estimate then has nothing to go on).
fn vcycle<T: Stored, U: Stored>(
    mut fine: View<'_, T>,
    levels: &[Level],
    values: &mut [U],
    labels: &[Label],
    faces: &[[u8; 4]],
) -> (u64, f32) {
    let Some((level, coarser)) = levels.split_first() else {
        // Coarsest: symmetric sweeps.
        let mut work = 0;
        for _ in 0..COARSEST_SWEEPS {
            work += relax(&mut fine, 0) + relax(&mut fine, 1);
            work += relax(&mut fine, 1) + relax(&mut fine, 0);
        }
        return (work, f32::INFINITY);
    };
    let mut work = 0u64;
    for _ in 0..PRE_SWEEPS {
        work += relax(&mut fine, 0) + relax(&mut fine, 1);
    }
    let n = level.dims.len();
    // `new` sized `values` for every level; a shortfall skips the coarse correction.
    let Some((mine, rest)) = values.split_at_mut_checked(level.offset + 2 * n) else {
        return (work, f32::INFINITY);
    };
    let Some((cx, cb)) = mine
        .get_mut(level.offset..)
        .and_then(|m| m.split_at_mut_checked(n))
    else {
        return (work, f32::INFINITY);
    };
    let clabels = level.labels(labels);
    cx.fill(U::default());
    cb.fill(U::default());
    // Restrict the residual.
    let fdims = fine.dims;
    restrict(&fine, &level.dims, clabels, cb);
    work += fdims.len() as u64;
    {
        // The coarser levels' values live after this level's block.
        let rest_levels: HVec<Level, MAX_LEVELS> = coarser
            .iter()
            .map(|l| Level {
                offset: l.offset - (level.offset + 2 * n),
                ..*l
            })
            .collect();
        let coarse = View::coarse(
            level,
            1,
            &fine.screen,
            clabels,
            faces.get(level.label_offset..level.label_offset + n),
            cx,
            Some(cb),
        );
        work += vcycle(coarse, &rest_levels, rest, labels, faces).0;
    }
    // Prolongate and correct.
    let correction = prolongate(&mut fine, &level.dims, clabels, cx);
    work += fdims.len() as u64;
    for _ in 0..POST_SWEEPS {
        work += relax(&mut fine, 1) + relax(&mut fine, 0);
    }
    (work, correction)
}

#[cfg(test)]
pub(crate) mod tests {
    extern crate std;
    use super::*;
    use crate::mapping::map::VoxelIndex;
    use crate::planning::solve::gauss_seidel;
    use std::vec;
    use std::vec::Vec;

    /// A room with an internal wall and a door, source in one half, frontier strip in the other.
    fn rooms(nx: usize, ny: usize, nz: usize) -> (Dims, Vec<Label>) {
        let dims = Dims::new(nx, ny, nz).unwrap();
        let mut labels = vec![Label::Interior; dims.len()];
        for (i, l) in labels.iter_mut().enumerate() {
            let v = dims.voxel(i);
            let (x, y) = (v.x as usize, v.y as usize);
            let door = (ny / 3..ny / 3 + 2).contains(&y);
            if x == nx / 2 && !door {
                *l = Label::Outside;
            }
            if x == nx - 1 && y > ny / 2 {
                *l = Label::Frontier;
            }
        }
        labels[dims.linear(VoxelIndex::new(2, 2, (nz / 2) as u16))] = Label::Source;
        (dims, labels)
    }

    /// Solves from ψ = 0 with `method`; returns ψ, the stats and the residual history.
    fn solve_mg(
        dims: Dims,
        labels: &[Label],
        method: Method,
        max_iterations: u32,
    ) -> (Vec<f32>, SolveStats, Vec<f32>) {
        solve_mg_with(dims, labels, method, max_iterations, 0.0, None)
    }

    /// Owned storage for a multigrid over a grid, the neighbour masks included, for tests.
    pub(crate) struct Scratch {
        values: Vec<f32>,
        labels: Vec<Label>,
        faces: Vec<[u8; 4]>,
        krylov: Vec<f32>,
        masks: Vec<u8>,
    }

    impl Scratch {
        /// Zeroed storage for `dims`, with the MGPCG vectors if `krylov`.
        pub(crate) fn new(dims: &Dims, krylov: bool) -> Self {
            let size = scratch_size(dims);
            Self {
                values: vec![0.0; size.values],
                labels: vec![Label::Outside; size.labels],
                faces: vec![[0; 4]; size.faces],
                krylov: vec![0.0; if krylov { size.krylov } else { 0 }],
                masks: vec![0; size.masks],
            }
        }

        /// A multigrid over `dims` in this storage.
        pub(crate) fn multigrid(&mut self, dims: Dims) -> Multigrid<'_> {
            let storage = MultigridStorage {
                values: self.values.as_mut_slice().into(),
                labels: &mut self.labels,
                faces: &mut self.faces,
                krylov: &mut self.krylov,
                masks: &mut self.masks,
            };
            Multigrid::new(dims, storage).unwrap()
        }
    }

    /// [`solve_mg`] with a screening and a [`Fork`].
    fn solve_mg_with(
        dims: Dims,
        labels: &[Label],
        method: Method,
        max_iterations: u32,
        screening: f32,
        fork: Option<&dyn Fork>,
    ) -> (Vec<f32>, SolveStats, Vec<f32>) {
        let mut scratch = Scratch::new(&dims, method != Method::VCycle);
        let mut mg = scratch.multigrid(dims);
        mg.set_fork(fork);
        let mut phi = vec![0.0f32; dims.len()];
        let params = SolveParams {
            tolerance: 1e-6,
            max_iterations,
            warm_start: false,
            screening,
            ..SolveParams::default()
        };
        let s = mg.solve(labels, &mut phi, &params, method).unwrap();
        let history = mg.history().to_vec();
        (phi, s, history)
    }

    /// Two threads for [`Multigrid::set_fork`]: a scoped thread per join.
    struct Threads;

    impl Fork for Threads {
        fn join(&self, a: &mut (dyn FnMut() + Send), b: &mut (dyn FnMut() + Send)) {
            std::thread::scope(|s| {
                s.spawn(b);
                a();
            });
        }
    }

    /// A grid large enough that every split path runs — the fine level's sweeps, residuals and
    /// interpolation, the first coarse level's sweeps, and the restriction into it (32 × 24 × 12
    /// coarse cells) — gives the same bits, iterations and cell updates with a fork as without.
    #[test]
    fn a_fork_splits_every_pass_without_changing_a_bit() {
        let (dims, laplace) = rooms(64, 48, 24);
        let mut screened = laplace.clone();
        crate::planning::field::release_source(&mut screened);
        for (labels, screening) in [(&laplace, 0.0), (&screened, 0.09)] {
            for method in [Method::Pcg, Method::VCycle] {
                let solve = |fork: Option<&dyn Fork>| {
                    let (psi, s, _) = solve_mg_with(dims, labels, method, 400, screening, fork);
                    (psi, s.iterations, s.cell_updates)
                };
                let (alone, its, updates) = solve(None);
                assert!(its > 1, "{method:?}: a solve of {its} iteration tests little");
                for fork in [&Threads as &dyn Fork, &super::super::Sequential] {
                    let (split, i, u) = solve(Some(fork));
                    assert_eq!((i, u), (its, updates), "{method:?}, screening {screening}");
                    let differ = split
                        .iter()
                        .zip(&alone)
                        .filter(|(a, b)| a.to_bits() != b.to_bits())
                        .count();
                    assert_eq!(
                        differ, 0,
                        "{method:?}, screening {screening}: {differ} values differ"
                    );
                }
            }
        }
    }

    #[test]
    fn vcycles_and_pcg_agree_with_gauss_seidel() {
        let (dims, labels) = rooms(24, 20, 6);
        let mut reference = vec![0.0f32; dims.len()];
        let params = SolveParams {
            tolerance: 6e-7,
            max_iterations: 400_000,
            warm_start: false,
            ..SolveParams::default()
        };
        let gs = gauss_seidel(&dims, &labels, &mut reference, &params).unwrap();
        // 6e-7 lies below the rounding floor (9e-7): Gauss-Seidel stops there, not converged.
        assert!(gs.stop == Stop::Floor && !gs.converged, "{gs:?}");
        for method in [Method::Pcg, Method::VCycle] {
            let (phi, s, _) = solve_mg(dims, &labels, method, 200);
            assert!(
                matches!(s.stop, Stop::Met | Stop::Floor) && s.converged == (s.residual <= 1e-6),
                "{method:?}: {s:?}"
            );
            // The one-voxel wall couples the rooms on coarse levels: plain cycles slow down there,
            // which is what the Krylov wrapper is for.
            let bound = if method == Method::Pcg { 40 } else { 150 };
            assert!(
                s.iterations < bound,
                "{method:?} took {} iterations",
                s.iterations
            );
            let max_diff = phi
                .iter()
                .zip(&reference)
                .map(|(a, b)| (a - b).abs())
                .fold(0.0f32, f32::max);
            assert!(max_diff <= 1e-4, "{method:?}: max |Δφ| = {max_diff}");
            let gain = if method == Method::Pcg { 20 } else { 5 };
            assert!(
                s.cell_updates * gain < gs.cell_updates,
                "{method:?} not {gain}× cheaper: {} vs {}",
                s.cell_updates,
                gs.cell_updates
            );
        }
    }

    #[test]
    fn vcycles_converge_on_an_open_box() {
        let dims = Dims::new(32, 32, 16).unwrap();
        let mut labels = vec![Label::Interior; dims.len()];
        for (i, l) in labels.iter_mut().enumerate() {
            if dims.voxel(i).x == 31 {
                *l = Label::Frontier;
            }
        }
        labels[dims.linear(VoxelIndex::new(3, 16, 8))] = Label::Source;
        let (_, _, h) = solve_mg(dims, &labels, Method::VCycle, 30);
        assert!(
            h.len() <= 30 && h[h.len() - 1] <= 1e-6,
            "V-cycles did not converge: {h:?}"
        );
    }

    #[test]
    fn without_face_storage_the_label_only_operator_still_converges() {
        // The firmware lends no face storage: coarse levels fall back to labels only.
        let (dims, labels) = rooms(24, 20, 6);
        let size = scratch_size(&dims);
        let mut values = vec![0.0f32; size.values];
        let mut clabels = vec![Label::Outside; size.labels];
        let mut mg = Multigrid::new(
            dims,
            MultigridStorage {
                values: values.as_mut_slice().into(),
                labels: &mut clabels,
                faces: &mut [],
                krylov: &mut [],
                masks: &mut [],
            },
        )
        .unwrap();
        let mut phi = vec![0.0f32; dims.len()];
        let params = SolveParams {
            tolerance: 1e-6,
            max_iterations: 300,
            warm_start: false,
            ..SolveParams::default()
        };
        let s = mg.solve(&labels, &mut phi, &params, Method::VCycle).unwrap();
        assert!(s.converged, "{s:?}");
        let (with_faces, f, _) = solve_mg(dims, &labels, Method::VCycle, 300);
        assert!(f.converged);
        let worst = phi
            .iter()
            .zip(&with_faces)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0f32, f32::max);
        assert!(worst <= 1e-4, "max |Δψ| = {worst}");
    }

    #[test]
    fn scratch_too_small_is_an_error() {
        let dims = Dims::new(16, 16, 16).unwrap();
        let size = scratch_size(&dims);
        let mut values = vec![0.0f32; size.values - 1];
        let mut labels = vec![Label::Outside; size.labels];
        let mut faces = vec![[0u8; 4]; size.faces];
        let r = Multigrid::new(
            dims,
            MultigridStorage {
                values: values.as_mut_slice().into(),
                labels: &mut labels,
                faces: &mut faces,
                krylov: &mut [],
                masks: &mut [],
            },
        );
        assert!(matches!(r, Err(SolveError::ScratchTooSmall)));
    }

    /// A multigrid laid out again for a smaller grid (a local re-solve's box) solves it to the
    /// same bits as one made for that grid, refuses a larger one without changing its layout,
    /// and solves its own grid as before once laid out for it again.
    #[test]
    fn a_relayout_for_a_smaller_grid_solves_it_like_a_fresh_multigrid() {
        let (big, big_labels) = rooms(40, 30, 20);
        let (small, small_labels) = rooms(27, 19, 13);
        let params = SolveParams {
            tolerance: 1e-6,
            warm_start: false,
            screening: 0.09,
            ..SolveParams::default()
        };
        let mut scratch = Scratch::new(&big, true);
        let mut mg = scratch.multigrid(big);
        let mut before = vec![0.0f32; big.len()];
        let first = mg.solve(&big_labels, &mut before, &params, Method::Pcg).unwrap();
        mg.relayout(small).unwrap();
        let mut relaid = vec![0.0f32; small.len()];
        let s = mg
            .solve(&small_labels, &mut relaid, &params, Method::Pcg)
            .unwrap();
        let larger = Dims::new(41, 30, 20).unwrap();
        assert!(matches!(mg.relayout(larger), Err(SolveError::ScratchTooSmall)));
        assert_eq!(mg.fine_dims(), small);
        mg.relayout(big).unwrap();
        let mut again = vec![0.0f32; big.len()];
        let second = mg.solve(&big_labels, &mut again, &params, Method::Pcg).unwrap();
        drop(mg);
        let (fresh, f, _) = solve_mg_with(small, &small_labels, Method::Pcg, 20_000, 0.09, None);
        assert_eq!((s.iterations, s.cell_updates), (f.iterations, f.cell_updates));
        assert!(relaid.iter().zip(&fresh).all(|(a, b)| a.to_bits() == b.to_bits()));
        assert_eq!(
            (first.iterations, first.cell_updates),
            (second.iterations, second.cell_updates)
        );
        assert!(before.iter().zip(&again).all(|(a, b)| a.to_bits() == b.to_bits()));
    }
}
