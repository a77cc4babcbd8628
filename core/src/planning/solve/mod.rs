//! Laplace solvers over the domain built by [`crate::planning::domain`].
//!
//! Discretisation: cell-centred finite volumes on the voxel grid. For an interior voxel `i`,
//! `Σ_{j ∈ N(i)} (φ_j − φ_i) = 0`, where `N(i)` are its face neighbours that are in the domain
//! (interior, frontier or source). A face to a non-domain voxel is omitted: zero flux, the
//! Neumann condition at walls. Frontier voxels hold φ = 0 and the source φ = 1 (Dirichlet).
//! The resulting matrix is symmetric positive definite on each component that touches a
//! Dirichlet voxel, and every interior φ is the mean of its in-domain neighbours — hence the
//! discrete maximum principle: no interior local extremum.
//!
//! **Stored potential.** The buffer holds ψ = 1 − φ: the source at ψ = 0 and frontiers at
//! ψ = 1. Both describe the same field, but f32 spacing near 0 is far finer than near 1, and the
//! cells that set the rounding floor of the residual are those around the vehicle, where φ is
//! close to 1. Measured on the two-room test domain of [`multigrid`]: Gauss-Seidel stalls at a
//! relative residual of 1.5e-6 storing φ and 4.8e-7 storing ψ — below the default 1e-6 only in
//! the second form. Residuals are summed as fluxes `Σ (ψ_j − ψ_i)` for the same reason.
//!
//! Convergence is judged on the relative residual `‖b − Aφ‖₂ / ‖b‖₂`, never on the change between
//! iterations (the seed paper's relative-change rule divides by zero at φ = 0 and stops early).
//! Row sums are accumulated in `f32` and the grid total in `f64`, which keeps the norm accurate
//! without double-precision work in the inner loop.
//!
//! [`gauss_seidel`] is the seed paper's solver, kept as the reference: correct, not fast.
//! [`multigrid`] is the production solver: O(cells) per solve. [`thesis`] is the seed thesis's
//! own solve as written (Jacobi from φ = 0, stopped by its relative-change rule), kept as an
//! ablation of what its truncated field plans like.

use core::cell::Cell;

use crate::mapping::map::Dims;
use crate::planning::domain::Label;

#[cfg(feature = "flat")]
pub mod flat;
pub mod local;
pub mod multigrid;
pub mod thesis;

/// Runs two independent halves of a solve's work, at the same time where the platform can.
///
/// [`multigrid::Multigrid::set_fork`] lends one: each pass over the fine level (red-black half
/// sweeps, residuals, the restriction to the first coarse level, the interpolation from it, the
/// conjugate-gradient updates) is then cut into two slabs of z-planes handed to
/// [`Fork::join`]. A half sweep leaves the two planes where its slabs meet to the caller's
/// thread afterwards (each reads the other); the restriction visits those two planes in both
/// halves, each adding only into its own coarse planes. Every cell gets the same arithmetic in
/// the same order as without a fork (a half sweep's cells depend only on the other colour; the
/// sums into a coarse cell keep their order), so a solve gives the same bits, iterations and
/// cell updates with or without one. Coarse levels and the norms and dot products stay on the
/// caller's thread. `no_std` has no threads: the host lends a fork on its thread pool, the
/// firmware none.
pub trait Fork: Sync {
    /// Runs `a` and `b`, each exactly once, and returns when both have finished.
    fn join(&self, a: &mut (dyn FnMut() + Send), b: &mut (dyn FnMut() + Send));
}

/// A [`Fork`] that runs both halves on the caller's thread, one after the other: the split
/// code path without threads (tests use it to check that the split changes no bit).
#[derive(Debug, Clone, Copy, Default)]
pub struct Sequential;

impl Fork for Sequential {
    fn join(&self, a: &mut (dyn FnMut() + Send), b: &mut (dyn FnMut() + Send)) {
        a();
        b();
    }
}

/// Fewest cells (active planes × plane size) worth splitting between two threads: below this
/// a join costs more than half the work saves.
pub(crate) const MIN_SPLIT_CELLS: usize = 8192;

/// The plane where a [`Fork`] splits the active planes `zs` of a grid whose planes hold
/// `plane` cells, if there are enough of them (and at least four planes: each half must keep
/// one plane away from the two done afterwards).
#[inline]
pub(crate) fn split_plane(zs: &core::ops::Range<usize>, plane: usize) -> Option<usize> {
    (zs.len() >= 4 && zs.len() * plane >= MIN_SPLIT_CELLS).then_some(zs.start + (zs.len() >> 1))
}

/// When a solve stops.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SolveParams {
    /// Stop when the relative residual is at or below this.
    pub tolerance: f32,
    /// Stop after this many sweeps (Gauss-Seidel) or cycles (multigrid) regardless.
    pub max_iterations: u32,
    /// Start from the φ already in the buffer (interior voxels) instead of 0.
    pub warm_start: bool,
    /// Screening `κ²h²` (κ in 1/m, h the voxel size): each interior row gains `−κ²h²·ψᵢ`,
    /// which turns Laplace's equation into the screened one `∇²u = κ²u`. 0 (the default) is
    /// the seed's Laplace problem; see [`crate::planning::field`] for the frontier-sourced field that
    /// uses it. Negative or non-finite values are refused ([`SolveError::BadScreening`]).
    pub screening: f32,
    /// Also stop only once [`SolveStats::error_estimate`] is at or below this (the largest
    /// error of ψ it bounds or estimates, in ψ's units). Infinite (the default) stops on the
    /// residual alone; a finite value makes `converged` mean "residual *and* error met", and a
    /// solve that cannot estimate its error (no updates to measure, Laplace's equation) goes on
    /// to the cap and reports not converged.
    pub max_error: f32,
}

impl Default for SolveParams {
    fn default() -> Self {
        Self {
            tolerance: 1e-6,
            max_iterations: 20_000,
            warm_start: true,
            screening: 0.0,
            max_error: f32::INFINITY,
        }
    }
}

/// What a solve did.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct SolveStats {
    /// Sweeps or cycles performed.
    pub iterations: u32,
    /// Relative residual at the start.
    pub initial_residual: f32,
    /// Relative residual at the end.
    pub residual: f32,
    /// Interior cell updates performed (the work measure "planning ops").
    pub cell_updates: u64,
    /// Relative residual the rounding of the current f32 solution alone can produce: below
    /// this, nothing better is representable (see [`Residual`]).
    pub floor: f32,
    /// True only if the solve met what it was asked for: the relative residual at or below
    /// [`SolveParams::tolerance`] *and*, where [`SolveParams::max_error`] is finite, the
    /// [error estimate](Self::error_estimate) at or below it. A solve may stop for other
    /// reasons ([`Self::stop`]): at the f32 rounding floor where that lies above the
    /// tolerance (Laplace's equation on a late map with few frontier voxels: a floor of 4e-6
    /// against a tolerance of 1e-6), after its conjugate-gradient restarts, or at
    /// [`SolveParams::max_iterations`]; it then reports `false`, whatever else it reached.
    pub converged: bool,
    /// Why the solve stopped.
    pub stop: Stop,
    /// Largest error `max |ψ − ψ*|` against the exact solution ψ* of the same discrete
    /// system, as an upper bound (screened field) or a measured safe estimate of one (Laplace's
    /// equation), or `None` where the solve has nothing to estimate it from.
    ///
    /// **Screened field** (`s = κ²h² > 0`): `‖r‖∞ / s + ε`, a bound. Each interior row's
    /// diagonal exceeds the sum of its off-diagonals by at least `s`, so `‖A⁻¹‖∞ ≤ 1/s` and
    /// `‖ψ − ψ*‖∞ ≤ ‖r‖∞ / s` for the residual `r` of the ψ returned; ε covers the final clamp
    /// into [0, 1] and the rounding of the residual's sums. Measured 1.1–78× the true error
    /// on few-frontier worlds (`core/tests/honest_solves.rs`). It is weak where κ was lowered
    /// far (s = 2.5e-5: 4e4 × ‖r‖∞), and a contraction estimate is not used in its place there:
    /// it was measured up to 10× below the true error of plain V-cycles.
    ///
    /// **Laplace's equation**: no cheap bound exists. `‖A⁻¹‖∞` grows with the domain's
    /// volume over its few frontier voxels (the smallest eigenvalue is tiny behind long walls),
    /// and the residual of an f32 solve is rounding noise at the end, so `‖A⁻¹‖∞ · ‖r‖∞` is
    /// orders of magnitude too large. The estimate is read from how fast the solve's steps
    /// shrank: a converging iteration shrinks its error by about ρ per step, so the error left
    /// is about `ρ / (1 − ρ)` times the last step's largest change. ρ is the *largest* ratio of
    /// successive largest changes over the last eight steps (for conjugate gradients, whose
    /// changes do not fall steadily, the largest two-step contraction of their residuals within
    /// the current restart pass): the error left is made of the slowest mode, and a ratio read
    /// from the last one or two steps was often a faster one's (the estimate was as low as 0.08× the true error: 1.2e-6
    /// reported, 1.5e-5 true, flat solver; 0.15× in the rooms). That is then multiplied
    /// by a safety factor of 8 (`ESTIMATE_SAFETY`): the windowed estimate alone was still
    /// down to 0.18× the true error (MGPCG) on random worlds of long walls, narrow doors and a
    /// window of at most nine frontier voxels; with the factor the largest ratio of true error
    /// to estimate measured over 100 such worlds, every solver, was 0.58 (median 0.04:
    /// the estimate is cautious by design). Once the changes stop shrinking (ρ ≥ 1: the
    /// rounding floor) the estimate is the last one made while they shrank plus every change
    /// since. Steps measured: the coarse-grid correction of each V-cycle (doubled: the smoothing
    /// around it does about half the change), each MGPCG update, each Gauss-Seidel sweep. The
    /// thesis's Jacobi solve reports `None`.
    pub error_estimate: Option<f32>,
}

/// Why a solve stopped ([`SolveStats::stop`]). Only [`Stop::Met`] goes with
/// [`SolveStats::converged`].
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Stop {
    /// The tolerance and the error target (if one was set) were met: converged.
    #[default]
    Met,
    /// The residual reached the f32 rounding floor ([`Residual::floor`]), which lies above the
    /// tolerance, and (plain V-cycles) stopped falling; the error target, if one was set, was
    /// met. Iterating further only stirs rounding noise, so the solve stops, but the tolerance
    /// was not met: not converged.
    Floor,
    /// Multigrid-preconditioned conjugate gradients used all their restarts
    /// ([`multigrid::MAX_RESTARTS`] passes from the true residual) without meeting the
    /// tolerance or the error target: not converged.
    Restarts,
    /// [`SolveParams::max_iterations`] reached first: not converged.
    Cap,
    /// The solver's own rule stopped it, which is not the residual tolerance (the thesis's
    /// relative-change rule, [`thesis`]); converged only if the residual met the tolerance too.
    Rule,
}

impl Stop {
    /// Why a solve that ended at `res` with the error estimate `estimate`, and did not reach its
    /// iteration cap, stopped: [`Stop::Met`] where the tolerance and the error target are met,
    /// else [`Stop::Floor`] where the residual meets the floor that lies above the tolerance and
    /// the error target is met, else `otherwise`.
    pub(crate) fn of(res: &Residual, params: &SolveParams, estimate: Option<f32>, otherwise: Stop) -> Stop {
        let error_ok = error_met(estimate, params.max_error);
        if res.relative <= params.tolerance && error_ok {
            Stop::Met
        } else if res.meets(params.tolerance) && error_ok {
            Stop::Floor
        } else {
            otherwise
        }
    }
}

/// Whether a solve that ended at `res` with the error estimate `estimate` met `params`: the
/// relative residual at or below the tolerance (not the rounding floor) and the estimate at or
/// below the error target, if one was set. The one rule every solver reports
/// [`SolveStats::converged`] by.
pub(crate) fn converged(res: &Residual, params: &SolveParams, estimate: Option<f32>) -> bool {
    res.relative <= params.tolerance && error_met(estimate, params.max_error)
}

/// A box solve's outcome ([`local::BoxSolver::solve_box`]): its stats, and the residual of its
/// interior rows at the end, which [`local::resolve_near`] adds to the whole grid's sums in place
/// of a pass of its own over them.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Solved {
    /// What the solve did.
    pub stats: SolveStats,
    /// The true residual of the solution it returned (before the clamp into [0, 1], which
    /// moves a value by an ulp at most).
    pub residual: Residual,
    /// Its `‖b‖²`.
    pub b2: f64,
}

impl Solved {
    /// The sum of the squared residuals of the interior rows.
    pub fn r2(&self) -> f64 {
        let r = f64::from(self.residual.relative);
        r * r * self.b2
    }

    /// The sum of the rows' rounding terms (`rounding_row`).
    pub fn e2(&self) -> f64 {
        let f = f64::from(self.residual.floor);
        f * f * self.b2
    }
}

/// Steps whose contraction [`Contraction`] looks back over: the largest of their ratios is the
/// ρ it takes.
const RATIO_WINDOW: usize = 8;

/// What [`Contraction`] multiplies its `ρ / (1 − ρ)` estimate by: the margin between the error
/// left after the steps it watched and the error a contraction read from them predicts, as
/// measured against f64 solves (see [`SolveStats::error_estimate`]).
const ESTIMATE_SAFETY: f32 = 8.0;

/// Largest changes of successive solver steps, for [`SolveStats::error_estimate`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Contraction {
    /// Largest change of the last step.
    last: f32,
    /// Largest change of the step before.
    before: f32,
    /// The ratios of each step's largest change to the one before, newest first (the last
    /// [`RATIO_WINDOW`]).
    ratios: [f32; RATIO_WINDOW],
    /// The contractions read from the residuals over two steps, newest first, where the solver
    /// reports residuals.
    residual_ratios: [f32; RATIO_WINDOW],
    /// Steps recorded.
    steps: u32,
    /// Residuals after the last three steps (newest first), where the solver reports them.
    residuals: [f32; 3],
    /// How many of `residuals` are set.
    residual_steps: u32,
    /// Multiplies the estimate: the share of a step's change the recorded change misses.
    scale: f32,
    /// Whether the steps report residuals (conjugate gradients): the contraction is then read
    /// from them only.
    by_residuals: bool,
    /// The least estimate so far carried forward: an earlier step's estimate plus every
    /// change made since (the error cannot have grown by more), or `None` before the first.
    carried: Option<f32>,
}

impl Default for Contraction {
    /// An estimator whose recorded changes are each step's whole change.
    fn default() -> Self {
        Self::scaled(1.0)
    }
}

/// `window` with `v` pushed in front (the oldest entry drops out).
fn push_front(window: &mut [f32; RATIO_WINDOW], v: f32) {
    window.copy_within(0..RATIO_WINDOW - 1, 1);
    window[0] = v;
}

impl Contraction {
    /// An estimator whose recorded changes are about `1/scale` of the true change of a step
    /// (a V-cycle's coarse correction: the smoothing sweeps around it move values too).
    pub(crate) fn scaled(scale: f32) -> Self {
        Self {
            last: 0.0,
            before: 0.0,
            ratios: [0.0; RATIO_WINDOW],
            residual_ratios: [0.0; RATIO_WINDOW],
            steps: 0,
            residuals: [0.0; 3],
            residual_steps: 0,
            scale,
            by_residuals: false,
            carried: None,
        }
    }

    /// Starts a new conjugate-gradient pass (a restart from the true residual): its residuals
    /// are not comparable with the last pass's recursive ones, so the contraction is read
    /// afresh, from this pass's steps only. The estimate carried so far is kept.
    pub(crate) fn restart(&mut self) {
        self.residuals = [0.0; 3];
        self.residual_steps = 0;
        self.residual_ratios = [0.0; RATIO_WINDOW];
    }

    /// Records a step whose largest change was `change` and whose residual after it was
    /// `residual`. Conjugate gradients minimise an energy norm, so their largest changes do
    /// not fall steadily; their contraction is read from the residuals instead (over two
    /// steps) and the last change is the larger of the last two.
    pub(crate) fn push_with_residual(&mut self, change: f32, residual: f32) {
        self.by_residuals = true;
        self.residuals = [residual, self.residuals[0], self.residuals[1]];
        self.residual_steps = self.residual_steps.saturating_add(1);
        if self.residual_steps >= 3 {
            let [r0, _, r2] = self.residuals;
            let rho = if r2 > 0.0 {
                libm::sqrtf(r0 / r2)
            } else {
                f32::INFINITY
            };
            push_front(&mut self.residual_ratios, rho);
        }
        self.push(change);
    }

    /// Records a step whose largest change of any value was `change`.
    pub(crate) fn push(&mut self, change: f32) {
        self.record(change);
        let now = self.current();
        self.carried = match (self.carried.map(|c| c + self.scale * self.last), now) {
            (Some(c), Some(e)) => Some(c.min(e)),
            (c, e) => e.or(c),
        };
    }

    fn record(&mut self, change: f32) {
        let change = if change.is_finite() {
            change.abs()
        } else {
            f32::INFINITY
        };
        self.before = self.last;
        if self.steps > 0 {
            let ratio = if self.last > 0.0 {
                change / self.last
            } else if change > 0.0 {
                f32::INFINITY
            } else {
                0.0
            };
            push_front(&mut self.ratios, ratio);
        }
        self.last = change;
        self.steps = self.steps.saturating_add(1);
    }

    /// The error estimate: the least of this step's contraction estimate ([`Self::current`])
    /// and every earlier step's plus the changes made since (by the triangle inequality the
    /// error cannot have grown by more). Once a solve reaches the rounding floor its last
    /// changes stop shrinking and the contraction reads ρ ≥ 1; the error it had when they still
    /// shrank, plus the noise since, is then the better figure.
    pub(crate) fn estimate(&self) -> Option<f32> {
        self.carried
    }

    /// `ρ / (1 − ρ)` times the last change, times [`ESTIMATE_SAFETY`], ρ the largest ratio of
    /// the last [`RATIO_WINDOW`] steps (the slowest contraction seen lately: a ratio read
    /// from one or two steps is often one a faster mode set, and the slow mode then left is
    /// what the error is made of); `None` before three steps (two ratios) were recorded, +∞
    /// when the steps stopped shrinking.
    fn current(&self) -> Option<f32> {
        if self.steps < 3 {
            return None;
        }
        let largest = |w: &[f32; RATIO_WINDOW], n: u32| {
            w.iter()
                .take((n as usize).min(RATIO_WINDOW))
                .fold(0.0f32, |m, r| if r.is_nan() { f32::INFINITY } else { m.max(*r) })
        };
        let (rho, last) = if self.by_residuals {
            if self.residual_steps < 3 {
                // Too early in this pass to read its contraction.
                return None;
            }
            (
                largest(&self.residual_ratios, self.residual_steps - 2),
                self.last.max(self.before),
            )
        } else {
            (largest(&self.ratios, self.steps - 1), self.last)
        };
        Some(if rho.is_finite() && rho < 1.0 {
            ESTIMATE_SAFETY * self.scale * rho / (1.0 - rho) * last
        } else if last == 0.0 {
            0.0
        } else {
            f32::INFINITY
        })
    }
}

/// The error estimate of a solve that recorded `steps` and ended at `res` with `screen`
/// ([`SolveStats::error_estimate`]): for the screened field (`s > 0`) the bound
/// `‖r‖∞ / s + ε`, for Laplace's equation the contraction estimate of `steps`.
pub(crate) fn error_estimate(steps: &Contraction, res: &Residual, screen: &Screen) -> Option<f32> {
    if screen.shift > 0.0 {
        // Every interior row's diagonal exceeds the sum of its off-diagonals by at least s, so
        // ‖A⁻¹‖∞ ≤ 1/s and ‖ψ − ψ*‖∞ ≤ ‖r‖∞ / s for the exact residual r of the stored ψ. The
        // residual is summed from differences of neighbouring values (exact or nearly so in
        // f32); ε covers the clamp into [0, 1] after it and what rounding is left.
        return Some(res.max / screen.shift + f32::EPSILON);
    }
    steps.estimate()
}

/// Whether a solve may stop on its error estimate: always when no error target was set.
pub(crate) fn error_met(estimate: Option<f32>, max_error: f32) -> bool {
    max_error == f32::INFINITY || estimate.is_some_and(|e| e <= max_error)
}

/// Why a solve could not run.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum SolveError {
    /// `labels` or `phi` is shorter than the grid.
    StorageTooSmall,
    /// Tolerance not finite and positive.
    BadTolerance,
    /// The multigrid scratch storage does not fit the grid.
    ScratchTooSmall,
    /// Plain V-cycles diverged (residual grew a thousandfold or became non-finite); φ was reset.
    Diverged,
    /// Screening negative or not finite.
    BadScreening,
}

/// Value of the stored potential ψ = 1 − φ at the source.
pub const PSI_SOURCE: f32 = 0.0;
/// Value of the stored potential ψ = 1 − φ at frontiers.
pub const PSI_FRONTIER: f32 = 1.0;

/// Sets Dirichlet values of ψ, zeroes it outside the domain and, unless warm-starting, in the
/// interior. Non-finite or out-of-range warm-start values are reset to 0.
pub fn prepare(labels: &[Label], psi: &mut [f32], warm_start: bool) {
    // Selects, not a match: the loop vectorises.
    for (l, p) in labels.iter().zip(psi.iter_mut()) {
        let kept = warm_start && *l == Label::Interior && (0.0..=1.0).contains(p);
        let v = if kept { *p } else { 0.0 };
        *p = if *l == Label::Frontier { PSI_FRONTIER } else { v };
    }
}

/// Where a solve takes its Dirichlet values from.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) enum Dirichlet {
    /// Frontiers ψ = 1, the source ψ = 0 ([`prepare`]).
    Standard,
    /// As the buffer holds them (in [0, 1]; anything else takes the standard value): a box cut
    /// out of a larger grid, whose rim holds the values outside it ([`local`]). The solve
    /// stops at the residual norm `‖r‖ ≤ residual` (not a tolerance relative to `‖b‖`, which
    /// only the solve computes), or at `params.tolerance` where `‖b‖` is 0.
    Given {
        /// The residual norm to reach.
        residual: f32,
    },
}

impl Dirichlet {
    /// `params` as a solve with these Dirichlet values runs them: given values start warm
    /// (full multigrid solves for the standard ones only).
    pub(crate) fn params(self, params: &SolveParams) -> SolveParams {
        SolveParams {
            warm_start: params.warm_start || matches!(self, Dirichlet::Given { .. }),
            ..*params
        }
    }

    /// `params` with the tolerance a given residual norm sets, once the solve knows its `‖b‖²`
    /// (`b2`): unchanged for the standard values.
    pub(crate) fn tolerance(self, params: &SolveParams, b2: f64) -> SolveParams {
        match self {
            Dirichlet::Given { residual } if b2 > 0.0 => SolveParams {
                tolerance: residual / libm::sqrt(b2) as f32,
                ..*params
            },
            _ => *params,
        }
    }
}

/// [`prepare`] for a warm start whose Dirichlet cells keep the values in the buffer where they
/// lie in [0, 1] (others take the standard ones).
pub(crate) fn prepare_given(labels: &[Label], psi: &mut [f32]) {
    for (l, p) in labels.iter().zip(psi.iter_mut()) {
        let kept = (0.0..=1.0).contains(p);
        *p = match l {
            Label::Frontier | Label::Source | Label::Interior if kept => *p,
            Label::Frontier => PSI_FRONTIER,
            _ => 0.0,
        };
    }
}

/// Clamps interior ψ into [0, 1], the range the maximum principle guarantees: rounding can
/// leave a value a few ulps outside it, and equal values at the top would give the streamline a
/// plateau to wander on. A solve stopped early (by its cap) can leave values well outside; the
/// clamp only brings them closer to the solution, which lies inside. Returns the largest change,
/// so that a solve whose clamp moved ψ by more than [`CLAMP_SLACK`] reports the residual of
/// the ψ it returns, not of the iterate before the clamp.
pub(crate) fn clamp_to_bounds(labels: &[Label], psi: &mut [f32]) -> f32 {
    let mut moved = 0.0f32;
    for (l, p) in labels.iter().zip(psi.iter_mut()) {
        if *l == Label::Interior {
            let c = p.clamp(PSI_SOURCE, PSI_FRONTIER);
            moved = moved.max((c - *p).abs());
            *p = c;
        }
    }
    moved
}

/// The largest clamp ([`clamp_to_bounds`]) that leaves a solve's residual as it was measured: a
/// few ulps of 1, the rounding a converged solve leaves at the bounds.
pub(crate) const CLAMP_SLACK: f32 = 4.0 * f32::EPSILON;

/// Residual of the current solution and the floor f32 rounding puts under it.
///
/// `relative` is `‖b − Aψ‖ / ‖b‖` (0 when `b = 0`: ψ = 0 solves it). `floor` is `‖e‖ / ‖b‖`
/// with `eᵢ = ε·√((Σⱼ ψⱼ² + deg_i²·ψᵢ²) / 12)`: the RMS residual that rounding each ψ to f32
/// (an error uniform within half a unit in the last place) causes on its own. How close to 1e-6 that floor comes depends on the geometry — how
/// many voxels sit at large ψ — so a solve stops at the tolerance or at the floor, whichever is
/// higher: iterating below the floor only stirs rounding noise.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Residual {
    /// Relative residual.
    pub relative: f32,
    /// Relative rounding floor.
    pub floor: f32,
    /// Largest residual of any interior row, `max |bᵢ − (Aψ)ᵢ|` (not relative).
    pub max: f32,
}

impl Residual {
    /// The residual from the sums over interior rows of the squared residuals `r2` and of the
    /// rows' rounding terms `e2` ([`rounding_row`]), the largest residual `max` and `‖b‖² = b2`.
    pub(crate) fn from_sums(r2: f64, e2: f64, max: f32, b2: f64) -> Self {
        if b2 == 0.0 {
            return Self {
                relative: 0.0,
                floor: 0.0,
                max,
            };
        }
        Self {
            relative: libm::sqrt(r2 / b2) as f32,
            floor: libm::sqrt(e2 / b2) as f32,
            max,
        }
    }

    /// True if the residual meets `tolerance`, or the floor where that lies above it.
    pub fn meets(&self, tolerance: f32) -> bool {
        self.relative <= tolerance.max(self.floor)
    }
}

/// Relative residual of the current ψ (see [`Residual`]) for Laplace's equation.
pub fn relative_residual(dims: &Dims, labels: &[Label], psi: &[f32]) -> f32 {
    residual(dims, labels, psi).relative
}

/// Residual and rounding floor of the current ψ for Laplace's equation.
pub fn residual(dims: &Dims, labels: &[Label], psi: &[f32]) -> Residual {
    screened_residual(dims, labels, psi, 0.0)
}

/// Residual and rounding floor of the current ψ for the screened equation with
/// [`SolveParams::screening`] `screening`.
pub fn screened_residual(dims: &Dims, labels: &[Label], psi: &[f32], screening: f32) -> Residual {
    residual_with(
        dims,
        &Active::all(dims),
        &Screen::new(screening),
        (labels, &[]),
        psi,
        dirichlet_norm2(dims, labels),
    )
}

/// The screening term of a level: the diagonal shift `s` and the reciprocal diagonals
/// `1 / (n + s)` for each in-domain neighbour count `n`, so the smoothers keep a table lookup.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Screen {
    pub(crate) shift: f32,
    inv: [f32; 8],
}

impl Screen {
    /// No screening: Laplace's equation.
    pub(crate) const NONE: Screen = Screen {
        shift: 0.0,
        inv: INV_COUNT,
    };

    /// The screening `shift` (≥ 0; anything else is treated as 0).
    pub(crate) fn new(shift: f32) -> Self {
        if !(shift.is_finite() && shift > 0.0) {
            return Self::NONE;
        }
        let mut inv = [0.0f32; 8];
        for (n, v) in inv.iter_mut().enumerate().take(7) {
            *v = 1.0 / (n as f32 + shift);
        }
        Screen { shift, inv }
    }

    /// The same screening on a level `depth` halvings coarser: the mass term scales with the
    /// cell volume and the rediscretised face term with the cell size, so `s` grows by 4 per
    /// level.
    pub(crate) fn coarser(&self, depth: usize) -> Self {
        if self.shift == 0.0 {
            return Self::NONE;
        }
        let scale = libm::powf(4.0, depth as f32);
        Self::new(self.shift * scale)
    }

    /// The residual `b + flux − s·c` of a cell of value `c` whose neighbours' net flux into it
    /// is `flux`: every residual path (labels, open runs, masks) computes it here, so they give
    /// the same bits.
    #[inline(always)]
    pub(crate) fn residual(&self, c: f32, flux: f32, b: f32) -> f32 {
        b + flux - self.shift * c
    }

    /// A Gauss-Seidel update of a cell of value `c`: `c + (flux − s·c + b) · inv`, `inv` being
    /// [`Screen::inv`] of its neighbour count. Every sweep path (labels, open runs, masks)
    /// updates here, so they give the same bits.
    #[inline(always)]
    pub(crate) fn relaxed(&self, c: f32, flux: f32, b: f32, inv: f32) -> f32 {
        c + (flux - self.shift * c + b) * inv
    }

    /// `1 / (n + s)` (0 for an isolated cell of the Laplace problem).
    #[inline(always)]
    pub(crate) fn inv(&self, n: u32) -> f32 {
        self.inv.get(n as usize & 7).copied().unwrap_or(0.0)
    }
}

/// `‖b‖²`: the squared norm of the Dirichlet contributions to the interior rows (each frontier
/// neighbour adds ψ = 1; the source adds 0). It depends on the labels only, so a solver
/// computes it once per solve.
pub(crate) fn dirichlet_norm2(dims: &Dims, labels: &[Label]) -> f64 {
    dirichlet_norm2_with(dims, labels, |i| {
        if labels.get(i) == Some(&Label::Frontier) {
            PSI_FRONTIER
        } else {
            0.0
        }
    })
}

/// `‖b‖²` for the Dirichlet values `psi` holds ([`Dirichlet::Given`]).
pub(crate) fn dirichlet_norm2_given(dims: &Dims, labels: &[Label], psi: &[f32]) -> f64 {
    dirichlet_norm2_with(dims, labels, |i| match labels.get(i) {
        Some(Label::Frontier | Label::Source) => psi.get(i).copied().unwrap_or(0.0),
        _ => 0.0,
    })
}

/// `‖b‖²` with `value(i)` the Dirichlet contribution of voxel `i` (0 for any other).
///
/// `bᵢ = Σ_{f∼i} v_f` over an interior cell's Dirichlet neighbours, and expanding one factor
/// of `Σᵢ bᵢ²` gives `Σ_f v_f Σ_{i∼f} bᵢ` (over the interior neighbours `i` of each Dirichlet
/// cell `f`): a walk from the few Dirichlet cells instead of six neighbour tests at every
/// interior cell. With the standard values (0 and 1) every term is a small integer, so the
/// sum is exact either way.
fn dirichlet_norm2_with(dims: &Dims, labels: &[Label], value: impl Fn(usize) -> f32) -> f64 {
    let (nx, ny, nz) = (dims.nx(), dims.ny(), dims.nz());
    // `bᵢ` of cell `i` (0 unless it is interior).
    let b_at = |i: usize| {
        let mut b = 0.0f32;
        if labels.get(i) == Some(&Label::Interior) {
            dims.for_each_face_neighbour(dims.voxel(i), |j| b += value(j));
        }
        b
    };
    let mut total = 0.0f64;
    for z in 0..nz {
        for y in 0..ny {
            let start = nx * (y + ny * z);
            let row = labels.get(start..start + nx).unwrap_or(&[]);
            // Most rows have no Dirichlet cell: a test of the whole row (branch-free, so it
            // vectorises) skips them.
            let dirichlet = |l: &Label| (*l as u8).wrapping_sub(Label::Frontier as u8) < 2;
            if !row.iter().fold(false, |any, l| any | dirichlet(l)) {
                continue;
            }
            for (x, l) in row.iter().enumerate() {
                if !dirichlet(l) {
                    continue;
                }
                let v = value(start + x);
                if v == 0.0 {
                    continue;
                }
                let mut sum = 0.0f32;
                dims.for_each_face_neighbour_of([x, y, z], |i| sum += b_at(i));
                total += f64::from(v) * f64::from(sum);
            }
        }
    }
    total
}

/// [`residual`] with `‖b‖²` given. The rounding floor uses `Σⱼ ψⱼ² ≈ deg_i·ψᵢ²`, which keeps it
/// in the same branch-free pass as the residual.
pub(crate) fn residual_with(
    dims: &Dims,
    active: &Active,
    screen: &Screen,
    (labels, masks): (&[Label], &[u8]),
    psi: &[f32],
    b2: f64,
) -> Residual {
    if masks.len() >= dims.len() {
        residual_rows::<true>(dims, active, screen, (labels, masks), psi, b2)
    } else {
        residual_rows::<false>(dims, active, screen, (labels, &[]), psi, b2)
    }
}

/// [`residual_with`], with the [neighbour masks](neighbour_mask) (`MASKS`) or the labels: one
/// instance each, so the firmware's (labels) is the code it always was.
fn residual_rows<const MASKS: bool>(
    dims: &Dims,
    active: &Active,
    screen: &Screen,
    (labels, masks): (&[Label], &[u8]),
    psi: &[f32],
    b2: f64,
) -> Residual {
    let (mut r2, mut e2, mut max) = (0.0f64, 0.0f64, 0.0f32);
    for_each_row(dims, active, screen, labels, psi, |st, row| {
        let (mut row_r, mut row_e) = (0.0f32, 0.0f32);
        let each = |x: usize, r: f32, n: u32| {
            row_r += r * r;
            row_e += rounding2(n, row.at(x));
            if r.abs() > max {
                max = r.abs();
            }
        };
        if MASKS {
            row_residuals_masked(st, row, None, st.masks_in(masks), each);
        } else {
            row_residuals(st, row, None, each);
        }
        r2 += f64::from(row_r);
        e2 += rounding_row(row_e);
    });
    Residual::from_sums(r2, e2, max, b2)
}

/// Visits every cell of the box of half-width `radius` around each of `pins` (clipped to a
/// grid of `n` cells per axis) forward, then backward: a symmetric Gauss-Seidel sweep when
/// `update` relaxes the cell it is given. Both multigrid solvers smooth around a point source
/// with it.
pub(crate) fn symmetric_box_sweep(
    pins: &[[usize; 3]],
    n: [usize; 3],
    radius: usize,
    mut update: impl FnMut(usize, usize, usize),
) {
    for &[px, py, pz] in pins {
        let span = |p: usize, n: usize| p.saturating_sub(radius)..(p + radius + 1).min(n);
        let (xs, ys, zs) = (span(px, n[0]), span(py, n[1]), span(pz, n[2]));
        for z in zs.clone() {
            for y in ys.clone() {
                for x in xs.clone() {
                    update(x, y, z);
                }
            }
        }
        for z in zs.clone().rev() {
            for y in ys.clone().rev() {
                for x in xs.clone().rev() {
                    update(x, y, z);
                }
            }
        }
    }
}

/// A cell's share of the rounding floor ([`Residual`]) before the factor `ε²/12`: a cell of
/// value `c` with `n` in-domain neighbours, `Σⱼ ψⱼ² + n²·ψᵢ² ≈ (n + n²)·c²`.
#[inline(always)]
pub(crate) fn rounding2(n: u32, c: f32) -> f32 {
    let n = n as f32;
    (n + n * n) * c * c
}

/// A row's sum of [`rounding2`] terms, times `ε²/12`: its share of the squared floor.
#[inline(always)]
pub(crate) fn rounding_row(row_e: f32) -> f64 {
    f64::from(row_e) * f64::from(f32::EPSILON * f32::EPSILON) / 12.0
}

/// A bfloat16 number: the upper half of an `f32` (sign, the full 8-bit exponent, 7 bits of
/// mantissa), rounded to nearest even. Multigrid coarse levels can be stored in it
/// ([`multigrid::CoarseValues::Bf16`]) to halve their memory: they only carry corrections,
/// which a V-cycle recomputes from the fine residual every cycle, so their ~0.4 % relative
/// rounding limits a cycle's reduction to about that and no further (the fine level, whose
/// residual decides convergence, stays `f32`). Unlike IEEE half precision it keeps `f32`'s
/// range: late residuals of 1e-7 and below do not underflow.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
#[repr(transparent)]
pub struct Bf16(pub u16);

impl Bf16 {
    /// Zero.
    pub const ZERO: Bf16 = Bf16(0);

    /// `v` rounded to the nearest bfloat16 (ties to even). NaN stays NaN.
    #[inline(always)]
    pub fn from_f32(v: f32) -> Self {
        let bits = v.to_bits();
        if v.is_nan() {
            return Bf16((bits >> 16) as u16 | 0x40);
        }
        let round = 0x7FFF + ((bits >> 16) & 1);
        Bf16((bits.wrapping_add(round) >> 16) as u16)
    }

    /// The exact `f32` of this value.
    #[inline(always)]
    pub fn to_f32(self) -> f32 {
        f32::from_bits(u32::from(self.0) << 16)
    }
}

/// How the solvers store a value: `f32` everywhere, or [`Bf16`] on multigrid coarse levels.
/// Arithmetic is always `f32`.
pub(crate) trait Stored: Copy + Default + Send + Sync + 'static {
    /// True for `f32`, the fine level's storage: only there can [neighbour
    /// masks](neighbour_mask) be lent, so other formats need no code for them.
    const FINE: bool = false;
    /// The value as `f32`.
    fn load(self) -> f32;
    /// `v` in this format.
    fn store(v: f32) -> Self;
}

impl Stored for f32 {
    const FINE: bool = true;
    #[inline(always)]
    fn load(self) -> f32 {
        self
    }
    #[inline(always)]
    fn store(v: f32) -> Self {
        v
    }
}

impl Stored for Bf16 {
    #[inline(always)]
    fn load(self) -> f32 {
        self.to_f32()
    }
    #[inline(always)]
    fn store(v: f32) -> Self {
        Bf16::from_f32(v)
    }
}

/// Read access to one x-row of values, either plain or in place (`Cell`), so the same stencil
/// code serves residuals and the in-place smoother. Out-of-range reads give 0.
pub(crate) trait RowValues {
    /// Value at `x`, 0 past either end.
    fn at(&self, x: usize) -> f32;
}

impl<T: Stored> RowValues for [T] {
    #[inline(always)]
    fn at(&self, x: usize) -> f32 {
        self.get(x).map_or(0.0, |v| v.load())
    }
}

impl<T: Stored> RowValues for [Cell<T>] {
    #[inline(always)]
    fn at(&self, x: usize) -> f32 {
        self.get(x).map_or(0.0, |c| c.get().load())
    }
}

/// The 7-point stencil around one x-row: the row's labels and the labels and values of its
/// four neighbouring rows (y − 1, y + 1, z − 1, z + 1), empty at the grid edge.
///
/// The hot loops read neighbours with `get` on these slices: an absent row or a position past
/// the row's end simply reads as "outside the domain", so edges need no separate code path, and
/// the in-domain test becomes a 0/1 weight instead of a branch per face.
pub(crate) struct Stencil<'r, T = f32> {
    /// The level's screening.
    pub(crate) screen: Screen,
    /// Row coordinates.
    pub(crate) y: usize,
    /// Row coordinates.
    pub(crate) z: usize,
    /// Linear index of the row's first cell.
    pub(crate) start: usize,
    /// The row's labels.
    pub(crate) labels: &'r [Label],
    /// The cells `x0..x1` of the row that can hold interior cells (the active box's width).
    pub(crate) x0: usize,
    /// End of that range (exclusive).
    pub(crate) x1: usize,
    nl: [&'r [Label]; 4],
    nv: [&'r [T]; 4],
}

/// 1 / n for the neighbour counts a cell can have (0 for none: no update).
const INV_COUNT: [f32; 8] = [0.0, 1.0, 0.5, 1.0 / 3.0, 0.25, 0.2, 1.0 / 6.0, 0.0];

#[inline(always)]
fn in_domain(l: Option<&Label>) -> bool {
    l.is_some_and(|l| l.in_domain())
}

impl<'r, T: Stored> Stencil<'r, T> {
    /// The stencil of row `(y, z)`, whose values are `before = values[..start]` and
    /// `after = values[start + nx..]` around it.
    pub(crate) fn new(
        dims: &Dims,
        screen: &Screen,
        y: usize,
        z: usize,
        labels: &'r [Label],
        before: &'r [T],
        after: &'r [T],
    ) -> Self {
        Self::new_in::<false>(dims, screen, y, z, 0, labels, before, after)
    }

    /// [`Stencil::new`] over a slab of values that starts at linear index `base` of the grid:
    /// `before` and `after` are the slab's values around the row, `labels` the whole grid's.
    /// A neighbour row outside the slab reads as outside the domain, so the caller keeps every
    /// row it passes at least one plane inside the slab (or at the grid's edge). `SHIFTED`
    /// false ignores `base` (0): the code of an unsplit pass.
    #[allow(clippy::too_many_arguments)]
    #[inline(always)]
    pub(crate) fn new_in<const SHIFTED: bool>(
        dims: &Dims,
        screen: &Screen,
        y: usize,
        z: usize,
        base: usize,
        labels: &'r [Label],
        before: &'r [T],
        after: &'r [T],
    ) -> Self {
        let (nx, ny, nz) = (dims.nx(), dims.ny(), dims.nz());
        let nxy = nx * ny;
        // Row starts within the slab (values) and within the grid (labels).
        let local = before.len();
        let start = if SHIFTED { base + local } else { local };
        let lrow =
            |from: Option<usize>| -> &'r [Label] { from.and_then(|s| labels.get(s..s + nx)).unwrap_or(&[]) };
        let below = |back: usize| -> Option<usize> { local.checked_sub(back) };
        let (ym, zm) = (below(nx).filter(|_| y > 0), below(nxy).filter(|_| z > 0));
        let (yp, zp) = (
            Some(local + nx).filter(|_| y + 1 < ny),
            Some(local + nxy).filter(|_| z + 1 < nz),
        );
        let vbefore = |s: Option<usize>| -> &'r [T] { s.and_then(|s| before.get(s..s + nx)).unwrap_or(&[]) };
        // `after` starts at local + nx.
        let vafter = |s: Option<usize>| -> &'r [T] {
            s.and_then(|s| after.get(s - local - nx..s - local))
                .unwrap_or(&[])
        };
        let global = |s: Option<usize>| if SHIFTED { s.map(|s| s + base) } else { s };
        Stencil {
            screen: *screen,
            y,
            z,
            start,
            x0: 0,
            x1: nx,
            labels: lrow(Some(start)),
            nl: [
                lrow(global(ym)),
                lrow(global(yp)),
                lrow(global(zm)),
                lrow(global(zp)),
            ],
            nv: [vbefore(ym), vafter(yp), vbefore(zm), vafter(zp)],
        }
    }

    /// Net flux `Σ (v_j − c)` into cell `x` (value `c`) of `row` from its in-domain face
    /// neighbours, and their count.
    #[inline(always)]
    pub(crate) fn flux<V: RowValues + ?Sized>(&self, row: &V, x: usize, c: f32) -> (f32, u32) {
        let (mut flux, mut n) = (0.0f32, 0u32);
        let mut add = |w: bool, v: f32| {
            n += u32::from(w);
            flux += if w { v - c } else { 0.0 };
        };
        let left = x.wrapping_sub(1);
        add(in_domain(self.labels.get(left)), row.at(left));
        add(in_domain(self.labels.get(x + 1)), row.at(x + 1));
        for (l, v) in self.nl.iter().zip(&self.nv) {
            add(in_domain(l.get(x)), v.at(x));
        }
        (flux, n)
    }
}

/// The part of a [`Stencil`] away from the grid's y and z edges: all four neighbour rows
/// exist and every slice has the row's length, so the loops over `1..nx − 1` read neighbours
/// without branches (the compiler sees the lengths and drops the bounds checks).
pub(crate) struct Inner<'r, T = f32> {
    pub(crate) l: &'r [Label],
    pub(crate) nl: [&'r [Label]; 4],
    pub(crate) nv: [&'r [T]; 4],
}

impl<'r, T: Stored> Stencil<'r, T> {
    /// This row's [neighbour masks](neighbour_mask) in `masks` (a level's, one per cell;
    /// empty if it has none).
    #[inline(always)]
    pub(crate) fn masks_in<'m>(&self, masks: &'m [u8]) -> &'m [u8] {
        masks
            .get(self.start..self.start + self.labels.len())
            .unwrap_or(&[])
    }

    /// The same stencil with its cells limited to `xs` (within the row).
    #[inline(always)]
    pub(crate) fn within(mut self, xs: core::ops::Range<usize>) -> Self {
        let nx = self.labels.len();
        self.x0 = xs.start.min(nx);
        self.x1 = xs.end.clamp(self.x0, nx);
        self
    }

    /// The branch-free view of this row, if all four neighbour rows exist.
    #[inline(always)]
    pub(crate) fn inner(&self) -> Option<Inner<'r, T>> {
        let n = self.labels.len();
        let ok = self.nl.iter().all(|l| l.len() == n) && self.nv.iter().all(|v| v.len() == n);
        ok.then_some(Inner {
            l: self.labels,
            nl: self.nl,
            nv: self.nv,
        })
    }
}

impl<'r, T: Stored> Inner<'r, T> {
    /// Every slice cut to exactly `nx` entries (the row length), or `None` if one is shorter.
    /// Cutting here, in the caller's inlined code, is what lets the compiler see the lengths.
    #[inline(always)]
    pub(crate) fn cut(&self, nx: usize) -> Option<Cut<'r, T>> {
        let [l0, l1, l2, l3] = self.nl;
        let [v0, v1, v2, v3] = self.nv;
        Some(Cut {
            l: self.l.get(..nx)?,
            nl: [l0.get(..nx)?, l1.get(..nx)?, l2.get(..nx)?, l3.get(..nx)?],
            nv: [v0.get(..nx)?, v1.get(..nx)?, v2.get(..nx)?, v3.get(..nx)?],
        })
    }
}

/// An [`Inner`] row whose slices all have the row's length.
pub(crate) struct Cut<'r, T = f32> {
    pub(crate) l: &'r [Label],
    nl: [&'r [Label]; 4],
    nv: [&'r [T]; 4],
}

impl<T: Stored> Cut<'_, T> {
    /// Net flux into cell `x` (value `c`, `0 < x < nx − 1`) of `row` and the number of
    /// in-domain neighbours; the in-domain tests are 0/1 weights, not branches.
    #[inline(always)]
    pub(crate) fn flux<V: RowValues + ?Sized>(&self, row: &V, x: usize, c: f32) -> (f32, u32) {
        let mut flux = 0.0f32;
        let mut n = 0u32;
        let mut add = |lab: Option<&Label>, v: f32| {
            let w = lab.is_some_and(|&lab| weight(lab));
            n += u32::from(w);
            flux += if w { v - c } else { 0.0 };
        };
        add(self.l.get(x.wrapping_sub(1)), row.at(x.wrapping_sub(1)));
        add(self.l.get(x + 1), row.at(x + 1));
        for (l, v) in self.nl.iter().zip(&self.nv) {
            add(l.get(x), v.at(x));
        }
        (flux, n)
    }
}

impl<T: Stored> Cut<'_, T> {
    /// Whether cells `x..x + OPEN_RUN` of the row are all interior and every face neighbour of
    /// each is in the domain: then [`Cut::open_flux`] gives their flux without a label test.
    /// Away from walls and frontiers every cell is in such runs, and the labels' tests are much
    /// of a sweep's work; the run's are made on machine words. False unless `0 < x` and
    /// `x + OPEN_RUN < nx`.
    #[inline(always)]
    pub(crate) fn open_run(&self, x: usize) -> bool {
        let (Some(left), Some(centre), Some(&right)) = (
            x.checked_sub(1).and_then(|l| self.l.get(l)),
            label_word(self.l, x),
            self.l.get(x + OPEN_RUN),
        ) else {
            return false;
        };
        if centre != ALL_INTERIOR || !weight(*left) || !weight(right) {
            return false;
        }
        // In the domain: each byte 1, 2 or 3 (no bit above the lowest two, and one of them set).
        let (mut high, mut low) = (0u32, ALL_INTERIOR);
        for row in &self.nl {
            let Some(w) = label_word(row, x) else {
                return false;
            };
            high |= w;
            low &= w | (w >> 1);
        }
        high & !(ALL_INTERIOR * 3) == 0 && low & ALL_INTERIOR == ALL_INTERIOR
    }

    /// [`Cut::flux`] of a cell of an [open run](Cut::open_run), whose six neighbours are all in
    /// the domain: the same sums in the same order, so the same value to the last bit.
    #[inline(always)]
    pub(crate) fn open_flux<V: RowValues + ?Sized>(&self, row: &V, x: usize, c: f32) -> f32 {
        let mut flux = 0.0f32;
        flux += row.at(x.wrapping_sub(1)) - c;
        flux += row.at(x + 1) - c;
        for v in &self.nv {
            flux += v.at(x) - c;
        }
        flux
    }
}

impl<T: Stored> Cut<'_, T> {
    /// [`Cut::flux`] with the in-domain tests read from the cell's [neighbour
    /// mask](neighbour_mask) `m` instead of six labels: the same sums in the same order.
    #[inline(always)]
    pub(crate) fn masked_flux<V: RowValues + ?Sized>(&self, row: &V, x: usize, c: f32, m: u8) -> (f32, u32) {
        let mut flux = 0.0f32;
        let mut add = |bit: u8, v: f32| {
            flux += if m & bit != 0 { v - c } else { 0.0 };
        };
        add(1, row.at(x.wrapping_sub(1)));
        add(2, row.at(x + 1));
        for (k, v) in self.nv.iter().enumerate() {
            add(4 << k, v.at(x));
        }
        (flux, (m & ALL_FACES).count_ones())
    }
}

/// The [neighbour mask](neighbour_mask) bit of an interior cell.
pub(crate) const MASK_INTERIOR: u8 = 1 << 6;
/// The [neighbour mask](neighbour_mask) bits of the six faces.
const ALL_FACES: u8 = MASK_INTERIOR - 1;
/// The [neighbour mask](neighbour_mask) of an interior cell whose six neighbours are all in
/// the domain.
pub(crate) const MASK_OPEN: u8 = MASK_INTERIOR | ALL_FACES;

/// A cell's neighbour mask: bits 0–5 say whether its −x, +x, −y, +y, −z, +z neighbours are in
/// the domain, bit 6 whether it is interior. A solver lent a byte per cell writes them once
/// per solve (for the rows of the active box); then each sweep reads one byte per cell instead
/// of seven labels, and a cell whose mask is [`MASK_OPEN`] takes the branch-free sum.
pub(crate) fn neighbour_mask(dims: &Dims, labels: &[Label], x: usize, y: usize, z: usize) -> u8 {
    let (nx, ny, nz) = (dims.nx(), dims.ny(), dims.nz());
    let i = x + nx * (y + ny * z);
    let at = |ok: bool, j: usize| ok && labels.get(j).is_some_and(|l| l.in_domain());
    let faces = [
        at(x > 0, i.wrapping_sub(1)),
        at(x + 1 < nx, i + 1),
        at(y > 0, i.wrapping_sub(nx)),
        at(y + 1 < ny, i + nx),
        at(z > 0, i.wrapping_sub(nx * ny)),
        at(z + 1 < nz, i + nx * ny),
    ];
    let interior = u8::from(labels.get(i) == Some(&Label::Interior)) << 6;
    faces
        .iter()
        .enumerate()
        .fold(interior, |m, (k, &f)| m | (u8::from(f) << k))
}

/// Writes the [neighbour masks](neighbour_mask) of the active box's cells into `masks` (one
/// per grid cell; nothing if it is shorter than the grid). Returns cells written.
pub(crate) fn build_masks(dims: &Dims, active: &Active, labels: &[Label], masks: &mut [u8]) -> u64 {
    let (nx, ny) = (dims.nx(), dims.ny());
    if masks.len() < dims.len() {
        return 0;
    }
    let mut written = 0u64;
    active.rows(|y, z| {
        for x in active.xs() {
            if let Some(m) = masks.get_mut(x + nx * (y + ny * z)) {
                *m = neighbour_mask(dims, labels, x, y, z);
                written += 1;
            }
        }
    });
    written
}

/// Cells an [open run](Cut::open_run) spans.
pub(crate) const OPEN_RUN: usize = 4;
/// The label word of an open run's cells: four `Interior` bytes.
const ALL_INTERIOR: u32 = 0x0101_0101;

/// The labels `x..x + OPEN_RUN` of a row as one little-endian word (`None` past the row's end).
#[inline(always)]
fn label_word(l: &[Label], x: usize) -> Option<u32> {
    let run: &[Label; OPEN_RUN] = l.get(x..x + OPEN_RUN)?.try_into().ok()?;
    Some(u32::from_le_bytes(run.map(|l| l as u8)))
}

/// 0/1 in-domain weight of a label, without a branch.
#[inline(always)]
pub(crate) fn weight(l: Label) -> bool {
    (l as u8).wrapping_sub(1) < 3
}

/// Calls `f(x, r)` with the residual `r = b + Σ (v_j − v_x)` of every interior cell `x` of a
/// read-only row (`b` = 0 where absent). Rows away from the y/z edges take a branch-free path.
#[inline(always)]
pub(crate) fn row_residuals<T: Stored, F: FnMut(usize, f32, u32)>(
    st: &Stencil<'_, T>,
    row: &[T],
    b: Option<&[T]>,
    mut f: F,
) {
    let nx = row.len();
    let bx = |x: usize| b.map_or(0.0, |b| b.at(x));
    let edge = |x: usize, f: &mut F| edge_residual(st, row, b, x, f);
    let Some(inner) = st.inner().filter(|_| nx >= 3) else {
        for x in st.x0..st.x1.min(nx) {
            edge(x, &mut f);
        }
        return;
    };
    edge(0, &mut f);
    let Some(cut) = inner.cut(nx) else {
        return;
    };
    let end = st.x1.min(nx - 1);
    let mut x = st.x0.max(1);
    while x < end {
        if x + OPEN_RUN <= end && cut.open_run(x) {
            for x in x..x + OPEN_RUN {
                let c = row.at(x);
                f(x, st.screen.residual(c, cut.open_flux(row, x, c), bx(x)), 6);
            }
            x += OPEN_RUN;
            continue;
        }
        let (Some(&lc), Some(&c)) = (cut.l.get(x), row.get(x)) else {
            break;
        };
        if lc == Label::Interior {
            let c = c.load();
            let (flux, n) = cut.flux(row, x, c);
            f(x, st.screen.residual(c, flux, bx(x)), n);
        }
        x += 1;
    }
    edge(nx - 1, &mut f);
}

/// [`row_residuals`] for a row whose [neighbour masks](neighbour_mask) `masks` (`nx` of
/// them) were lent: one byte per cell instead of seven labels, the same arithmetic. The host's
/// path; the firmware lends no masks and never runs it. Rows at the grid's y/z edges, and a
/// `masks` of the wrong length, take [`row_residuals`].
#[inline(always)]
pub(crate) fn row_residuals_masked<T: Stored, F: FnMut(usize, f32, u32)>(
    st: &Stencil<'_, T>,
    row: &[T],
    b: Option<&[T]>,
    masks: &[u8],
    mut f: F,
) {
    let nx = row.len();
    let cut = st
        .inner()
        .filter(|_| nx >= 3 && masks.len() == nx)
        .and_then(|inner| inner.cut(nx));
    let Some(cut) = cut else {
        row_residuals(st, row, b, f);
        return;
    };
    let bx = |x: usize| b.map_or(0.0, |b| b.at(x));
    edge_residual(st, row, b, 0, &mut f);
    for x in st.x0.max(1)..st.x1.min(nx - 1) {
        let (Some(&m), Some(&c)) = (masks.get(x), row.get(x)) else {
            break;
        };
        if m == MASK_OPEN {
            let c = c.load();
            f(x, st.screen.residual(c, cut.open_flux(row, x, c), bx(x)), 6);
        } else if m & MASK_INTERIOR != 0 {
            let c = c.load();
            let (flux, n) = cut.masked_flux(row, x, c, m);
            f(x, st.screen.residual(c, flux, bx(x)), n);
        }
    }
    edge_residual(st, row, b, nx - 1, &mut f);
}

/// Cells per chunk of [`row_residual_chunks`].
pub(crate) const CHUNK: usize = 8;

/// What takes [`row_residual_chunks`]' residuals.
pub(crate) trait ChunkSink {
    /// The residuals of cells `x0..x0 + CHUNK` (0 for a cell that is not interior), their
    /// in-domain neighbour counts (0 likewise) and their values. The cells before `from`
    /// were given already (a row's last chunk can overlap the one before): their residual and
    /// count are 0, and they are not to be counted again.
    fn chunk(&mut self, x0: usize, from: usize, r: &[f32; CHUNK], n: &[f32; CHUNK], c: &[f32; CHUNK]);
    /// The residual `r`, neighbour count `n` and value `c` of the interior cell `x`.
    fn single(&mut self, x: usize, r: f32, n: u32, c: f32);
}

/// [`row_residuals`] (no right-hand side) of an `f32` row in chunks of [`CHUNK`] cells that
/// the compiler vectorises, given to `sink`: [`ChunkSink::chunk`] for the chunks and
/// [`ChunkSink::single`] for each interior cell of the rest of the stencil's range (the row's
/// ends, the rows at the grid's y/z edges, and what is left after the last chunk). Each
/// residual has the same bits as [`row_residuals`]' (the same sums in the same order; a
/// neighbour outside the domain adds `0·(v − c) = 0`).
#[inline(always)]
pub(crate) fn row_residual_chunks<S: ChunkSink>(st: &Stencil<'_, f32>, row: &[f32], sink: &mut S) {
    let nx = row.len();
    let one = |sink: &mut S, x: usize| cell_residual(st, row, x, sink);
    let cut = st.inner().filter(|_| nx >= 3).and_then(|inner| inner.cut(nx));
    let Some(cut) = cut else {
        for x in st.x0..st.x1.min(nx) {
            one(sink, x);
        }
        return;
    };
    // Chunks over 1..nx − 1 within the stencil's range: every cell there has both x
    // neighbours in the row.
    let (start, end) = (st.x0.max(1), st.x1.min(nx - 1));
    if st.x0 == 0 && st.x1 > 0 {
        one(sink, 0);
    }
    let mut x = start;
    while x + CHUNK <= end {
        // A chunk without an interior cell gives nothing (its residuals and counts are 0).
        let none = cut
            .l
            .get(x..x + CHUNK)
            .is_some_and(|l| l.iter().all(|l| *l != Label::Interior));
        if none {
            x += CHUNK;
            continue;
        }
        if let Some((r, n, c)) = chunk_residuals(&cut, row, st.screen.shift, x) {
            sink.chunk(x, x, &r, &n, &c);
        }
        x += CHUNK;
    }
    // The rest as a last chunk that ends at `end`, its cells before `x` (done already) zeroed;
    // one by one where the range is shorter than a chunk.
    let last = end.checked_sub(CHUNK).filter(|&l| l >= start && x < end);
    match last.and_then(|l| Some((l, chunk_residuals(&cut, row, st.screen.shift, l)?))) {
        Some((l, (mut r, mut n, c))) => {
            for (r, n) in r.iter_mut().zip(&mut n).take(x - l) {
                (*r, *n) = (0.0, 0.0);
            }
            sink.chunk(l, x, &r, &n, &c);
        }
        None => {
            for x in x..end {
                one(sink, x);
            }
        }
    }
    if st.x1 >= nx && nx > start {
        one(sink, nx - 1);
    }
}

/// Gives `sink` the residual of cell `x` of a row if it is interior (nothing for an `x` beyond
/// the row), by the stencil's label tests: the bits [`row_residual_chunks`] gives for it.
#[inline(always)]
pub(crate) fn cell_residual<S: ChunkSink>(st: &Stencil<'_, f32>, row: &[f32], x: usize, sink: &mut S) {
    let c = row.get(x).copied().unwrap_or(0.0);
    edge_residual(st, row, None, x, &mut |x, r, n| sink.single(x, r, n, c));
}

/// The residuals, in-domain neighbour counts and values of cells `x0..x0 + CHUNK` of a row
/// (`0 < x0`, `x0 + CHUNK < nx`), branch-free; `None` if the slices are shorter.
#[inline(always)]
fn chunk_residuals(
    cut: &Cut<'_, f32>,
    row: &[f32],
    shift: f32,
    x0: usize,
) -> Option<([f32; CHUNK], [f32; CHUNK], [f32; CHUNK])> {
    let span =
        |s: &[f32], from: usize| -> Option<[f32; CHUNK]> { s.get(from..from + CHUNK)?.try_into().ok() };
    let weights = |l: &[Label], from: usize| -> Option<[f32; CHUNK]> {
        let l: &[Label; CHUNK] = l.get(from..from + CHUNK)?.try_into().ok()?;
        Some(l.map(|l| f32::from(u8::from(weight(l)))))
    };
    let c = span(row, x0)?;
    let interior: &[Label; CHUNK] = cut.l.get(x0..x0 + CHUNK)?.try_into().ok()?;
    let interior = interior.map(|l| f32::from(u8::from(l == Label::Interior)));
    // The six neighbours in the order of `Cut::flux`: −x, +x, then the four rows.
    let [l0, l1, l2, l3] = cut.nl;
    let [v0, v1, v2, v3] = cut.nv;
    let nb = [
        (weights(cut.l, x0 - 1)?, span(row, x0 - 1)?),
        (weights(cut.l, x0 + 1)?, span(row, x0 + 1)?),
        (weights(l0, x0)?, span(v0, x0)?),
        (weights(l1, x0)?, span(v1, x0)?),
        (weights(l2, x0)?, span(v2, x0)?),
        (weights(l3, x0)?, span(v3, x0)?),
    ];
    let (mut flux, mut n) = ([0.0f32; CHUNK], [0.0f32; CHUNK]);
    for (w, v) in &nb {
        for ((f, k), ((w, v), c)) in flux.iter_mut().zip(&mut n).zip(w.iter().zip(v).zip(&c)) {
            *f += *w * (*v - *c);
            *k += *w;
        }
    }
    let mut r = [0.0f32; CHUNK];
    for ((r, k), ((f, c), i)) in r.iter_mut().zip(&mut n).zip(flux.iter().zip(&c).zip(&interior)) {
        *r = *i * (*f - shift * *c);
        *k *= *i;
    }
    Some((r, n, c))
}

/// Calls `f(x, r, n)` with the residual of cell `x` if it is interior, by the stencil's label
/// tests: the row's two end cells, and every cell of the rows at the grid's y/z edges.
#[inline(always)]
fn edge_residual<T: Stored, F: FnMut(usize, f32, u32)>(
    st: &Stencil<'_, T>,
    row: &[T],
    b: Option<&[T]>,
    x: usize,
    f: &mut F,
) {
    if let (Some(Label::Interior), Some(&c)) = (st.labels.get(x), row.get(x)) {
        let c = c.load();
        let (flux, n) = st.flux(row, x, c);
        f(x, st.screen.residual(c, flux, b.map_or(0.0, |b| b.at(x))), n);
    }
}

/// The box (`x`, `y`, `z` ranges) that holds the interior cells: the only cells a sweep,
/// residual or transfer has work in. A young map's domain fills a small part of the grid, and
/// even a late one rarely spans the grid's whole width, so limiting the loops to this box saves
/// much of their cost. The loops still read neighbours outside it (Dirichlet cells).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub(crate) struct Active {
    x0: usize,
    x1: usize,
    y0: usize,
    y1: usize,
    z0: usize,
    z1: usize,
}

impl Active {
    /// Every row of the grid.
    pub(crate) fn all(dims: &Dims) -> Self {
        Self {
            x0: 0,
            x1: dims.nx(),
            y0: 0,
            y1: dims.ny(),
            z0: 0,
            z1: dims.nz(),
        }
    }

    /// The rows of `dims` with at least one interior cell in `labels` (empty if none).
    pub(crate) fn of(dims: &Dims, labels: &[Label]) -> Self {
        let (nx, ny) = (dims.nx(), dims.ny());
        let mut a = Self {
            x0: usize::MAX,
            x1: 0,
            y0: usize::MAX,
            y1: 0,
            z0: usize::MAX,
            z1: 0,
        };
        for z in 0..dims.nz() {
            for y in 0..ny {
                let start = nx * (y + ny * z);
                let row = labels.get(start..start + nx).unwrap_or(&[]);
                let Some(first) = row.iter().position(|l| *l == Label::Interior) else {
                    continue;
                };
                // Only the cells beyond the box found so far need looking at from the end.
                let last = row
                    .get(first.max(a.x1)..)
                    .and_then(|tail| tail.iter().rposition(|l| *l == Label::Interior))
                    .map_or(first, |k| first.max(a.x1) + k);
                a.x0 = a.x0.min(first);
                a.x1 = a.x1.max(last + 1);
                a.y0 = a.y0.min(y);
                a.y1 = a.y1.max(y + 1);
                a.z0 = a.z0.min(z);
                a.z1 = a.z1.max(z + 1);
            }
        }
        if a.y1 == 0 {
            Self::default()
        } else {
            a
        }
    }

    /// The box of the interior cells of `labels` and of the cells next to them, within `dims`,
    /// as its first cell and the cell past its last (`None` without an interior cell). Every
    /// cell beyond it is outside the domain: no row of the problem reads it.
    pub(crate) fn domain(dims: &Dims, labels: &[Label]) -> Option<([usize; 3], [usize; 3])> {
        let a = Self::of(dims, labels);
        if a.x0 >= a.x1 || a.y0 >= a.y1 || a.z0 >= a.z1 {
            return None;
        }
        Some((
            [a.x0, a.y0, a.z0].map(|c| c.saturating_sub(1)),
            [
                (a.x1 + 1).min(dims.nx()),
                (a.y1 + 1).min(dims.ny()),
                (a.z1 + 1).min(dims.nz()),
            ],
        ))
    }

    /// The rows of the box `lo..hi` (cells `lo[0]..hi[0]` of each), within `dims`.
    pub(crate) fn bounded(dims: &Dims, lo: [usize; 3], hi: [usize; 3]) -> Self {
        let [x1, y1, z1] = [hi[0].min(dims.nx()), hi[1].min(dims.ny()), hi[2].min(dims.nz())];
        Self {
            x0: lo[0].min(x1),
            x1,
            y0: lo[1].min(y1),
            y1,
            z0: lo[2].min(z1),
            z1,
        }
    }

    /// The active `x` range.
    pub(crate) fn xs(&self) -> core::ops::Range<usize> {
        self.x0..self.x1
    }

    /// The active `y` range.
    pub(crate) fn ys(&self) -> core::ops::Range<usize> {
        self.y0..self.y1
    }

    /// The active `z` range.
    pub(crate) fn zs(&self) -> core::ops::Range<usize> {
        self.z0..self.z1
    }

    /// The same box with its planes limited to `zs` (within the box's own).
    pub(crate) fn with_zs(mut self, zs: core::ops::Range<usize>) -> Self {
        self.z0 = zs.start.max(self.z0);
        self.z1 = zs.end.min(self.z1).max(self.z0);
        self
    }

    /// Calls `f(y, z)` for each active row, z-major.
    #[inline(always)]
    pub(crate) fn rows(&self, mut f: impl FnMut(usize, usize)) {
        for z in self.z0..self.z1 {
            for y in self.y0..self.y1 {
                f(y, z);
            }
        }
    }
}

/// `[f(a₀, b₀), f(a₁, b₁), f(a₂, b₂)]`: per-axis arithmetic on cell boxes.
pub(crate) fn zip3(a: [usize; 3], b: [usize; 3], f: impl Fn(usize, usize) -> usize) -> [usize; 3] {
    let ([a0, a1, a2], [b0, b1, b2]) = (a, b);
    [f(a0, b0), f(a1, b1), f(a2, b2)]
}

/// Calls `f(stencil, row)` for every x-row of `values` (read-only).
#[inline(always)]
pub(crate) fn for_each_row<T: Stored>(
    dims: &Dims,
    active: &Active,
    screen: &Screen,
    labels: &[Label],
    values: &[T],
    mut f: impl FnMut(&Stencil<'_, T>, &[T]),
) {
    let (nx, ny) = (dims.nx(), dims.ny());
    active.rows(|y, z| {
        let start = nx * (y + ny * z);
        if let (Some(before), Some(row), Some(after)) = (
            values.get(..start),
            values.get(start..start + nx),
            values.get(start + nx..),
        ) {
            f(
                &Stencil::new(dims, screen, y, z, labels, before, after).within(active.xs()),
                row,
            );
        }
    });
}

/// Calls `f(stencil, row)` for every x-row of `values`, with the row itself writable in place
/// (as `Cell`s, so a cell's update can read its row neighbours).
pub(crate) fn for_each_row_mut<T: Stored>(
    dims: &Dims,
    active: &Active,
    screen: &Screen,
    labels: &[Label],
    values: &mut [T],
    f: impl FnMut(&Stencil<'_, T>, &[Cell<T>]),
) {
    for_each_row_mut_in::<T, false>(dims, active, screen, labels, values, 0, f);
}

/// [`for_each_row_mut`] over a slab of values that starts at linear index `base` (see
/// [`Stencil::new_in`]); rows of `active` outside the slab are skipped. `SHIFTED` false
/// ignores `base` (0): the loop of an unsplit pass, without the offset arithmetic.
pub(crate) fn for_each_row_mut_in<T: Stored, const SHIFTED: bool>(
    dims: &Dims,
    active: &Active,
    screen: &Screen,
    labels: &[Label],
    values: &mut [T],
    base: usize,
    mut f: impl FnMut(&Stencil<'_, T>, &[Cell<T>]),
) {
    let (nx, ny) = (dims.nx(), dims.ny());
    active.rows(|y, z| {
        let linear = nx * (y + ny * z);
        let start = if SHIFTED {
            let Some(start) = linear.checked_sub(base) else {
                return;
            };
            start
        } else {
            linear
        };
        let (before, rest) = values.split_at_mut(start.min(values.len()));
        if rest.len() >= nx {
            let (row, after) = rest.split_at_mut(nx);
            let row = Cell::from_mut(row).as_slice_of_cells();
            f(
                &Stencil::new_in::<SHIFTED>(dims, screen, y, z, base, labels, before, after)
                    .within(active.xs()),
                row,
            );
        }
    });
}

/// [`for_each_row_mut`] for a pass whose rows depend only on values it does not write (a
/// red-black half sweep), cut in two by a [`Fork`] if one is given and there are enough
/// planes; `f` returns a count per row, and the total is returned. Each half gets the planes
/// that read no plane of the other; the two planes where they meet follow on this thread.
pub(crate) fn for_each_row_mut_split<T: Stored>(
    fork: Option<&dyn Fork>,
    dims: &Dims,
    active: &Active,
    screen: &Screen,
    labels: &[Label],
    values: &mut [T],
    f: &(impl Fn(&Stencil<'_, T>, &[Cell<T>]) -> u64 + Sync),
) -> u64 {
    let zs = active.zs();
    let (Some(fork), Some(m)) = (fork, split_plane(&zs, dims.nx() * dims.ny())) else {
        let mut total = 0u64;
        for_each_row_mut(dims, active, screen, labels, values, |st, row| {
            total += f(st, row)
        });
        return total;
    };
    let plane = dims.nx() * dims.ny();
    let (lo, hi) = values.split_at_mut((m * plane).min(values.len()));
    let (a, b) = (active.with_zs(zs.start..m - 1), active.with_zs(m + 1..zs.end));
    let (mut ta, mut tb) = (0u64, 0u64);
    fork.join(
        &mut || for_each_row_mut(dims, &a, screen, labels, lo, |st, row| ta += f(st, row)),
        &mut || {
            for_each_row_mut_in::<T, true>(dims, &b, screen, labels, hi, m * plane, |st, row| {
                tb += f(st, row)
            })
        },
    );
    let mut tail = 0u64;
    let meet = active.with_zs(m - 1..m + 1);
    for_each_row_mut(dims, &meet, screen, labels, values, |st, row| tail += f(st, row));
    ta + tb + tail
}

/// [`for_each_row`] for a pass that writes one output row per row of `values` (a residual):
/// `f(stencil, row, out_row)`, cut in two by a [`Fork`] if one is given. `out` is as long
/// as the grid; the rows outside `active` are left alone.
#[allow(clippy::too_many_arguments)]
pub(crate) fn for_each_row_out_split<T: Stored>(
    fork: Option<&dyn Fork>,
    dims: &Dims,
    active: &Active,
    screen: &Screen,
    labels: &[Label],
    values: &[T],
    out: &mut [f32],
    f: &(impl Fn(&Stencil<'_, T>, &[T], &mut [f32]) + Sync),
) {
    let nx = dims.nx();
    let run = |active: &Active, out: &mut [f32], base: usize| {
        for_each_row(dims, active, screen, labels, values, |st, row| {
            let Some(from) = st.start.checked_sub(base) else {
                return;
            };
            if let Some(out_row) = out.get_mut(from..from + nx) {
                f(st, row, out_row);
            }
        });
    };
    let zs = active.zs();
    let (Some(fork), Some(m)) = (fork, split_plane(&zs, nx * dims.ny())) else {
        run(active, out, 0);
        return;
    };
    let plane = nx * dims.ny();
    let (lo, hi) = out.split_at_mut((m * plane).min(out.len()));
    let (a, b) = (active.with_zs(zs.start..m), active.with_zs(m..zs.end));
    fork.join(&mut || run(&a, lo, 0), &mut || run(&b, hi, m * plane));
}

/// Validates a solve's inputs, trims the buffers to the grid and sets the Dirichlet values
/// ([`prepare`]): the common start of every solver.
pub(crate) fn checked_problem<'l, 'p>(
    dims: &Dims,
    labels: &'l [Label],
    psi: &'p mut [f32],
    params: &SolveParams,
    dirichlet: Dirichlet,
) -> Result<(&'l [Label], &'p mut [f32]), SolveError> {
    let n = dims.len();
    let (Some(labels), Some(psi)) = (labels.get(..n), psi.get_mut(..n)) else {
        return Err(SolveError::StorageTooSmall);
    };
    if !(params.tolerance.is_finite() && params.tolerance > 0.0) {
        return Err(SolveError::BadTolerance);
    }
    if !(params.screening.is_finite() && params.screening >= 0.0) {
        return Err(SolveError::BadScreening);
    }
    match dirichlet {
        Dirichlet::Standard => prepare(labels, psi, params.warm_start),
        Dirichlet::Given { .. } => prepare_given(labels, psi),
    }
    Ok((labels, psi))
}

/// Lexicographic Gauss-Seidel, in place, until the relative residual reaches the tolerance or
/// the sweep cap. The residual is evaluated every few sweeps (it costs about one sweep).
pub fn gauss_seidel(
    dims: &Dims,
    labels: &[Label],
    phi: &mut [f32],
    params: &SolveParams,
) -> Result<SolveStats, SolveError> {
    let (labels, phi) = checked_problem(dims, labels, phi, params, Dirichlet::Standard)?;
    const CHECK_EVERY: u32 = 4;
    let b2 = dirichlet_norm2(dims, labels);
    if b2 == 0.0 {
        // No interior cell touches a frontier: ψ = 0 (the source's value) is exact.
        prepare(labels, phi, false);
    }
    let active = Active::of(dims, labels);
    let screen = Screen::new(params.screening);
    let mut res = residual_with(dims, &active, &screen, (labels, &[]), phi, b2);
    let mut stats = SolveStats {
        initial_residual: res.relative,
        ..Default::default()
    };
    // Each sweep updates every cell once, so its largest update is its largest change.
    let mut steps = Contraction::default();
    let done = |res: &Residual, steps: &Contraction| {
        res.meets(params.tolerance) && error_met(error_estimate(steps, res, &screen), params.max_error)
    };
    while !done(&res, &steps) && stats.iterations < params.max_iterations {
        let mut change = 0.0f32;
        for_each_row_mut(dims, &active, &screen, labels, phi, |st, row| {
            for (x, (l, cell)) in st.labels.iter().zip(row).enumerate() {
                if *l != Label::Interior {
                    continue;
                }
                let c = cell.get();
                let (flux, count) = st.flux(row, x, c);
                if count > 0 {
                    let d = (flux - screen.shift * c) * screen.inv(count);
                    cell.set(c + d);
                    if d.abs() > change {
                        change = d.abs();
                    }
                    stats.cell_updates += 1;
                }
            }
        });
        steps.push(change);
        stats.iterations += 1;
        if stats.iterations.is_multiple_of(CHECK_EVERY) || stats.iterations == params.max_iterations {
            res = residual_with(dims, &active, &screen, (labels, &[]), phi, b2);
        }
    }
    if clamp_to_bounds(labels, phi) > CLAMP_SLACK {
        res = residual_with(dims, &active, &screen, (labels, &[]), phi, b2);
    }
    stats.residual = res.relative;
    stats.floor = res.floor;
    stats.error_estimate = error_estimate(&steps, &res, &screen);
    stats.converged = converged(&res, params, stats.error_estimate);
    stats.stop = if stats.converged {
        Stop::Met
    } else if stats.iterations < params.max_iterations {
        // The loop ends before the cap only where its rule says done: at the floor.
        Stop::Floor
    } else {
        Stop::Cap
    };
    Ok(stats)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::planning::domain::tests::xorshift;

    /// A one-voxel corridor of `N` voxels: source at x = 0, frontier at x = N − 1.
    fn corridor<const N: usize>() -> (Dims, [Label; N]) {
        let mut labels = [Label::Interior; N];
        labels[0] = Label::Source;
        labels[N - 1] = Label::Frontier;
        (Dims::new(N, 1, 1).unwrap(), labels)
    }

    #[test]
    fn the_active_box_is_the_smallest_that_holds_every_interior_cell() {
        let dims = Dims::new(10, 4, 3).unwrap();
        let mut labels = [Label::Outside; 120];
        for (x, y, z) in [(6, 1, 1), (3, 2, 1), (7, 2, 2)] {
            labels[dims.linear(crate::mapping::map::VoxelIndex::new(x, y, z))] = Label::Interior;
        }
        // Dirichlet cells outside the box are read as neighbours but never updated.
        labels[dims.linear(crate::mapping::map::VoxelIndex::new(9, 2, 2))] = Label::Frontier;
        let a = Active::of(&dims, &labels);
        assert_eq!((a.xs(), a.ys(), a.zs()), (3..8, 1..3, 1..3));
        assert_eq!(Active::of(&dims, &[Label::Outside; 120]), Active::default());
        let all = Active::all(&dims);
        assert_eq!((all.xs(), all.ys(), all.zs()), (0..10, 0..4, 0..3));
    }

    #[test]
    fn bfloat16_rounds_to_nearest_even_and_keeps_f32_range() {
        for v in [0.0f32, 1.0, -2.0, 0.5, 3.0, f32::INFINITY, f32::NEG_INFINITY] {
            assert_eq!(Bf16::from_f32(v).to_f32(), v, "{v} is exact in bf16");
        }
        // 1 + 2⁻⁸ lies halfway between 1 and 1 + 2⁻⁷: ties go to the even mantissa (1).
        assert_eq!(Bf16::from_f32(1.0 + 1.0 / 256.0).to_f32(), 1.0);
        // 1 + 3·2⁻⁸ lies halfway between 1 + 2⁻⁷ and 1 + 2⁻⁶: the even one is 1 + 2⁻⁶.
        assert_eq!(Bf16::from_f32(1.0 + 3.0 / 256.0).to_f32(), 1.0 + 1.0 / 64.0);
        assert!(Bf16::from_f32(f32::NAN).to_f32().is_nan());
        // Relative error at most half a unit in the 8th bit, across f32's range (no underflow
        // at the tiny residuals late in a solve).
        let mut v = 1.234_567e-30f32;
        while v < 1e30 {
            for x in [v, -v] {
                let back = Bf16::from_f32(x).to_f32();
                assert!(((back - x) / x).abs() <= 1.0 / 256.0, "{x} -> {back}");
            }
            v *= 3.7;
        }
    }

    #[test]
    fn corridor_gives_a_linear_potential() {
        let (dims, labels) = corridor::<12>();
        let mut phi = [0.0f32; 12];
        let params = SolveParams {
            tolerance: 1e-6,
            max_iterations: 100_000,
            warm_start: false,
            ..SolveParams::default()
        };
        let s = gauss_seidel(&dims, &labels, &mut phi, &params).unwrap();
        assert!(s.converged, "{s:?}");
        for (x, p) in phi.iter().enumerate() {
            let want = x as f32 / 11.0; // ψ = 1 − φ, φ linear from 1 to 0
            assert!((p - want).abs() < 1e-5, "x={x}: {p} vs {want}");
        }
    }

    #[test]
    fn walls_carry_no_flux() {
        // A 3-wide corridor with Dirichlet ends across the whole cross-section: φ depends on x
        // only, whatever the walls beside it (they are omitted faces, not zero-valued cells).
        let dims = Dims::new(8, 3, 1).unwrap();
        let mut labels = [Label::Interior; 24];
        for y in 0..3 {
            labels[y * 8] = Label::Source;
            labels[y * 8 + 7] = Label::Frontier;
        }
        let mut phi = [0.0f32; 24];
        let s = gauss_seidel(&dims, &labels, &mut phi, &SolveParams::default()).unwrap();
        assert!(s.converged);
        for y in 0..3 {
            for x in 0..8 {
                let want = x as f32 / 7.0;
                assert!((phi[y * 8 + x] - want).abs() < 1e-5);
            }
        }
    }

    #[test]
    fn open_runs_are_found_exactly_and_give_the_label_tests_flux_to_the_bit() {
        // Mostly interior cells with some of every other label, so that runs of all kinds occur.
        let dims = Dims::new(24, 7, 6).unwrap();
        let (nx, ny, nz) = (dims.nx(), dims.ny(), dims.nz());
        let mut next = xorshift(0x9E37_79B9_7F4A_7C15);
        let (mut open, mut closed) = (0, 0);
        for _ in 0..40 {
            let labels: [Label; 24 * 7 * 6] = core::array::from_fn(|_| match next() % 40 {
                0 => Label::Outside,
                1 => Label::Frontier,
                2 => Label::Source,
                _ => Label::Interior,
            });
            let values: [f32; 24 * 7 * 6] = core::array::from_fn(|_| (next() % 1_000_000) as f32 * 1e-6);
            let at = |x: usize, y: usize, z: usize| labels[x + nx * (y + ny * z)];
            for z in 1..nz - 1 {
                for y in 1..ny - 1 {
                    let start = nx * (y + ny * z);
                    let (before, rest) = values.split_at(start);
                    let (row, after) = rest.split_at(nx);
                    let st = Stencil::new(&dims, &Screen::NONE, y, z, &labels, before, after);
                    let cut = st.inner().and_then(|inner| inner.cut(nx)).unwrap();
                    for x in 1..nx - OPEN_RUN {
                        let want = (x..x + OPEN_RUN).all(|x| {
                            at(x, y, z) == Label::Interior
                                && [
                                    at(x - 1, y, z),
                                    at(x + 1, y, z),
                                    at(x, y - 1, z),
                                    at(x, y + 1, z),
                                    at(x, y, z - 1),
                                    at(x, y, z + 1),
                                ]
                                .iter()
                                .all(|l| l.in_domain())
                        });
                        assert_eq!(cut.open_run(x), want, "run at ({x}, {y}, {z})");
                        if !want {
                            closed += 1;
                            continue;
                        }
                        open += 1;
                        for x in x..x + OPEN_RUN {
                            let c = row[x];
                            let (flux, n) = cut.flux(row, x, c);
                            assert_eq!(n, 6);
                            assert_eq!(cut.open_flux(row, x, c).to_bits(), flux.to_bits());
                        }
                    }
                    // A run needs a cell on either side of it in the row.
                    assert!(!cut.open_run(nx - OPEN_RUN) && !cut.open_run(0));
                }
            }
        }
        assert!(open > 100 && closed > 100, "{open} open, {closed} closed runs");
    }

    /// A random grid of mostly interior cells with some of every other label, and values in
    /// [0, 1) (0 outside the domain, as `prepare` leaves them).
    fn random_grid<const N: usize>(next: &mut impl FnMut() -> u64) -> ([Label; N], [f32; N]) {
        let labels: [Label; N] = core::array::from_fn(|_| match next() % 40 {
            0 | 1 => Label::Outside,
            2 => Label::Frontier,
            3 => Label::Source,
            _ => Label::Interior,
        });
        let mut values: [f32; N] = core::array::from_fn(|_| (next() % 1_000_000) as f32 * 1e-6);
        for (v, l) in values.iter_mut().zip(&labels) {
            if !l.in_domain() {
                *v = 0.0;
            }
        }
        (labels, values)
    }

    /// What a scan relies on: the chunked residuals give every interior cell of the range once,
    /// with the bits of [`row_residuals`], for every row (edge rows too) and any x range
    /// (shorter than a chunk, a chunk and a bit, the whole row).
    #[test]
    fn chunked_residuals_give_every_interior_cell_once_with_the_same_bits() {
        struct Got {
            cells: [(f32, u32, u32); 40],
        }
        impl ChunkSink for Got {
            fn chunk(
                &mut self,
                x0: usize,
                from: usize,
                r: &[f32; CHUNK],
                n: &[f32; CHUNK],
                c: &[f32; CHUNK],
            ) {
                for (x, ((r, n), _)) in (x0..).zip(r.iter().zip(n).zip(c)) {
                    if let Some(g) = self.cells.get_mut(x).filter(|_| x >= from) {
                        *g = (*r, *n as u32, g.2 + 1);
                    }
                }
            }
            fn single(&mut self, x: usize, r: f32, n: u32, _: f32) {
                if let Some(g) = self.cells.get_mut(x) {
                    *g = (r, n, g.2 + 1);
                }
            }
        }
        let dims = Dims::new(40, 5, 4).unwrap();
        let (nx, ny, nz) = (dims.nx(), dims.ny(), dims.nz());
        let mut next = xorshift(0x2545_F491_4F6C_DD1D);
        let screen = Screen::new(0.09);
        for _ in 0..20 {
            let (labels, values) = random_grid::<{ 40 * 5 * 4 }>(&mut next);
            for xs in [0..nx, 3..9, 1..nx - 1, 5..5 + CHUNK + 3, 0..CHUNK, 17..nx] {
                for (y, z) in (0..nz).flat_map(|z| (0..ny).map(move |y| (y, z))) {
                    let start = nx * (y + ny * z);
                    let (before, rest) = values.split_at(start);
                    let (row, after) = rest.split_at(nx);
                    let st = Stencil::new(&dims, &screen, y, z, &labels, before, after).within(xs.clone());
                    let mut got = Got {
                        cells: [(0.0, 0, 0); 40],
                    };
                    row_residual_chunks(&st, row, &mut got);
                    let mut want = [(0.0f32, 0u32, 0u32); 40];
                    row_residuals(&st, row, None, |x, r, n| want[x] = (r, n, 1));
                    for x in 0..nx {
                        let (g, w) = (got.cells[x], want[x]);
                        if !xs.contains(&x) {
                            assert_eq!(g.2, 0, "({x}, {y}, {z}) is outside {xs:?}");
                            continue;
                        }
                        if labels[start + x] == Label::Interior {
                            assert_eq!(g.2, 1, "({x}, {y}, {z}) in {xs:?}: given {} times", g.2);
                            assert_eq!((g.0.to_bits(), g.1), (w.0.to_bits(), w.1), "({x}, {y}, {z})");
                        } else {
                            // In a chunk, as zeros (once); never as a cell of its own.
                            assert!(g.2 <= 1 && g.0 == 0.0 && g.1 == 0, "({x}, {y}, {z}): {g:?}");
                        }
                    }
                }
            }
        }
    }

    /// The Dirichlet norm's walk from the Dirichlet cells equals the sum over the interior
    /// cells it replaced, exactly for the standard values (small integers).
    #[test]
    fn the_dirichlet_norm_is_the_sum_over_interior_cells() {
        let dims = Dims::new(9, 7, 6).unwrap();
        let (nx, ny) = (dims.nx(), dims.ny());
        let mut next = xorshift(0x9E37_79B9_7F4A_7C15);
        for _ in 0..30 {
            let (labels, values) = random_grid::<{ 9 * 7 * 6 }>(&mut next);
            let brute = |value: &dyn Fn(usize) -> f32| {
                let mut total = 0.0f64;
                for (i, l) in labels.iter().enumerate() {
                    if *l != Label::Interior {
                        continue;
                    }
                    let (x, y, z) = (i % nx, (i / nx) % ny, i / (nx * ny));
                    let mut b = 0.0f64;
                    dims.for_each_face_neighbour_of([x, y, z], |j| b += f64::from(value(j)));
                    total += b * b;
                }
                total
            };
            let standard = |j: usize| if labels[j] == Label::Frontier { 1.0 } else { 0.0 };
            assert_eq!(dirichlet_norm2(&dims, &labels), brute(&standard));
            let given = |j: usize| match labels[j] {
                Label::Frontier | Label::Source => values[j],
                _ => 0.0,
            };
            let (walk, want) = (dirichlet_norm2_given(&dims, &labels, &values), brute(&given));
            assert!((walk - want).abs() <= 1e-6 * want.max(1.0), "{walk} {want}");
        }
    }

    #[test]
    fn cycle_cap_is_reported() {
        let (dims, labels) = corridor::<40>();
        let mut phi = [0.0f32; 40];
        let params = SolveParams {
            tolerance: 1e-6,
            max_iterations: 3,
            warm_start: false,
            ..SolveParams::default()
        };
        let s = gauss_seidel(&dims, &labels, &mut phi, &params).unwrap();
        assert_eq!(s.iterations, 3);
        assert!(!s.converged);
        assert!(s.residual > 1e-6 && s.residual < s.initial_residual);
        let bad = SolveParams {
            tolerance: f32::NAN,
            ..params
        };
        assert_eq!(
            gauss_seidel(&dims, &labels, &mut phi, &bad),
            Err(SolveError::BadTolerance)
        );
    }
}
