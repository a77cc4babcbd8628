//! The seed thesis's own solve, reproduced as written (Shade 2011, §6.4.1, §6.6.1.2, §6.6.2.4,
//! Eq 6.29): an ablation that shows what the thesis's *truncated* field plans like, not a
//! solver to plan with.
//!
//! - **Field and convention.** The thesis's φ: vehicle φ = +1, frontiers φ = −1, zero flux at
//!   walls. It is the core's field in another scale: the stored ψ = 1 − φ_core (source 0,
//!   frontiers 1, see [`crate::planning::solve`]) is `ψ = (1 − φ) / 2`. The sweeps run on the thesis's φ
//!   itself, in the buffers, so that the stopping rule sees the values (and the f32 rounding)
//!   the thesis's code would; the result is converted to ψ at the end.
//! - **Discretisation.** Each interior voxel becomes the mean of its in-domain face neighbours,
//!   walls omitted (zero flux): the core's discretisation exactly (Eq 6.27 with the Neumann
//!   mirror rule of Eq 6.28).
//! - **Iteration.** Jacobi: every value of sweep `i` is computed from the values of sweep `i − 1`
//!   (the GPU code of §6.6.1.2), with the caller's scratch buffer holding the other sweep.
//! - **Start.** φ = 0 in every interior voxel (ψ = 0.5), at every solve: a cold start, whatever
//!   the buffer held (§6.6.2.4).
//! - **Stop.** When the largest per-voxel relative change `|(φⁱ − φⁱ⁻¹) / φⁱ⁻¹|` over the
//!   interior falls below [`RELATIVE_CHANGE`] = 1e-4 (Eq 6.29 and the text; the caption of
//!   Fig 6.12 says 1e-5).
//!
//! **The rule is ill-posed; what this module does about it** (each case documented, nothing
//! else changed):
//!
//! 1. *Division by zero.* The change is computed as the thesis's float code would compute it,
//!    `|(φⁱ − φⁱ⁻¹) / φⁱ⁻¹|` in IEEE arithmetic, and the maximum kept with a `>` comparison. A
//!    voxel that stays at 0 gives 0/0 = NaN, which no comparison picks: it is left out. A voxel
//!    that leaves 0 gives +∞: the solve cannot stop while the sweeps' wavefront (Jacobi moves
//!    information one voxel per sweep) is still reaching voxels, the first sweep included.
//! 2. *Nothing to measure.* If every interior voxel stayed at 0 the maximum is that of an empty
//!    set, taken as 0: the sweep changed nothing, a fixed point, and the solve stops, converged
//!    (for example, the only interior voxel lies halfway between the vehicle and a frontier, φ = 0
//!    for ever). With no interior voxel at all it stops before the first sweep.
//! 3. *No convergence.* Where φ crosses 0 inside the domain the relative change of the voxels
//!    near the crossing is large for as long as they move, and a voxel that ends at a value a
//!    few ulps from 0 can flip for ever. The solve therefore stops after
//!    [`ThesisParams::max_sweeps`] (default [`MAX_SWEEPS`] = 20 000) and reports
//!    `converged = false`.
//!
//! *Why not simply skip every voxel with φⁱ⁻¹ = 0* (the first reading of case 1, measured and
//! dropped): Jacobi from φ = 0 on the voxel grid, a bipartite graph, moves values in a
//! checkerboard, so on sweep 2 a voxel whose neighbours were all still 0 repeats its sweep-1
//! value, relative change 0. When the only frontier left is a voxel or two, every voxel with a
//! nonzero φ is such a voxel: the skipping rule stopped at sweep 2 with φ = 0 everywhere but
//! around the vehicle and the frontier, the streamline stalled on that plateau, and garage seed 1
//! flew 930 m to the 3000-scan limit (60 m flown when the last frontier voxel was left). The
//! IEEE reading holds the solve open until the wavefront has crossed the domain.
//!
//! The result is whatever the rule leaves: not a converged harmonic field. [`SolveStats`] reports
//! the sweeps, the cell updates, and the relative residual of ψ before and after (the core's
//! measure, for comparison with the other solvers); `converged` only where that residual meets
//! [`ThesisParams::tolerance`] too.

use super::{
    clamp_to_bounds, dirichlet_norm2, for_each_row, residual_with, row_residuals, Active, Screen, SolveError,
    SolveStats, Stop, PSI_FRONTIER, PSI_SOURCE,
};
use crate::mapping::map::Dims;
use crate::planning::domain::Label;

/// The thesis's stopping threshold on the largest per-voxel relative change (Eq 6.29).
pub const RELATIVE_CHANGE: f32 = 1e-4;
/// The sweep cap after which the thesis's solve reports not converged.
pub const MAX_SWEEPS: u32 = 20_000;

/// The thesis's φ at the vehicle.
pub const PHI_SOURCE: f32 = 1.0;
/// The thesis's φ at frontiers.
pub const PHI_FRONTIER: f32 = -1.0;
/// The thesis's starting φ in the interior.
pub const PHI_START: f32 = 0.0;

/// When the thesis's solve stops.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ThesisParams {
    /// Stop when the largest per-voxel relative change of φ falls below this.
    pub relative_change: f32,
    /// Stop after this many sweeps regardless (not converged).
    pub max_sweeps: u32,
    /// The relative residual [`SolveStats::converged`] asks for as well: the rule stops the
    /// solve, but a field it truncated is converged only if it also meets this (the core's
    /// default, 1e-6).
    pub tolerance: f32,
}

impl Default for ThesisParams {
    fn default() -> Self {
        Self {
            relative_change: RELATIVE_CHANGE,
            max_sweeps: MAX_SWEEPS,
            tolerance: 1e-6,
        }
    }
}

/// The thesis's φ for the core's stored ψ.
#[inline(always)]
fn phi_of(psi: f32) -> f32 {
    1.0 - 2.0 * psi
}

/// The core's stored ψ for the thesis's φ.
#[inline(always)]
fn psi_of(phi: f32) -> f32 {
    0.5 - 0.5 * phi
}

/// The start of every solve, as ψ: Dirichlet values, interior at the thesis's φ = 0 (ψ = 0.5),
/// 0 outside the domain.
fn start_psi(labels: &[Label], psi: &mut [f32]) {
    for (l, p) in labels.iter().zip(psi.iter_mut()) {
        *p = match l {
            Label::Frontier => PSI_FRONTIER,
            Label::Source => PSI_SOURCE,
            Label::Interior => psi_of(PHI_START),
            _ => 0.0,
        };
    }
}

/// What one Jacobi sweep did.
struct Sweep {
    /// Largest relative change (IEEE: +∞ for a voxel that left 0, NaN for one that stayed at 0
    /// and so never the maximum), 0 if every voxel stayed at 0.
    max_change: f32,
    /// Interior cell updates.
    updates: u64,
}

/// One Jacobi sweep: every interior value of `to` becomes the mean of its in-domain neighbours
/// in `from` (the previous sweep). Values outside the interior are left as they are; both
/// buffers hold the same Dirichlet values.
fn sweep(dims: &Dims, active: &Active, labels: &[Label], from: &[f32], to: &mut [f32]) -> Sweep {
    let nx = dims.nx();
    let screen = Screen::NONE;
    let mut s = Sweep {
        max_change: 0.0,
        updates: 0,
    };
    for_each_row(dims, active, &screen, labels, from, |st, row| {
        let Some(out) = to.get_mut(st.start..st.start + nx) else {
            return;
        };
        let (mut max, mut updates) = (0.0f32, 0u64);
        row_residuals(st, row, None, |x, r, n| {
            if n == 0 {
                return;
            }
            let (Some(&prev), Some(o)) = (row.get(x), out.get_mut(x)) else {
                return;
            };
            // r = Σ (φ_j − φ_x): prev + r / n is the neighbours' mean.
            let next = prev + r * screen.inv(n);
            *o = next;
            updates += 1;
            // Eq 6.29 in IEEE arithmetic: ∞ if prev = 0 ≠ next, NaN (never > max) if both 0.
            let change = ((next - prev) / prev).abs();
            if change > max {
                max = change;
            }
        });
        if max > s.max_change {
            s.max_change = max;
        }
        s.updates += updates;
    });
    s
}

/// The sweeps on the thesis's φ, from the start values already in `phi` (same length as
/// `scratch` and `labels`), until the rule, a fixed point or the cap; the last sweep's φ is left
/// in `phi`. Returns the sweeps, the cell updates and whether the rule (or a fixed point)
/// stopped it.
fn sweep_phi(
    dims: &Dims,
    active: &Active,
    labels: &[Label],
    phi: &mut [f32],
    scratch: &mut [f32],
    params: &ThesisParams,
) -> (u32, u64, bool) {
    scratch.copy_from_slice(phi);
    let (mut sweeps, mut updates) = (0u32, 0u64);
    let mut converged = !labels.contains(&Label::Interior);
    while !converged && sweeps < params.max_sweeps {
        // Odd sweeps read `phi` and write `scratch`, even sweeps the other way round.
        let s = if sweeps.is_multiple_of(2) {
            sweep(dims, active, labels, phi, scratch)
        } else {
            sweep(dims, active, labels, scratch, phi)
        };
        sweeps += 1;
        updates += s.updates;
        converged = s.max_change < params.relative_change;
    }
    // The last sweep wrote `scratch` if the count is odd.
    if !sweeps.is_multiple_of(2) {
        phi.copy_from_slice(scratch);
    }
    (sweeps, updates, converged)
}

/// Solves the seed's field the thesis's way (see the module doc) into `psi` (the core's stored
/// ψ, as [`gauss_seidel`](super::gauss_seidel) leaves it), with `scratch` (at least one entry
/// per voxel) holding the other sweep. `converged` is true only if the relative-change rule (or
/// a fixed point) stopped it *and* the field meets [`ThesisParams::tolerance`]; `stop` says
/// which rule ended it ([`Stop::Rule`], or [`Stop::Cap`] at the sweep cap).
///
/// Laplace only: the thesis solves no screened problem.
pub fn solve(
    dims: &Dims,
    labels: &[Label],
    psi: &mut [f32],
    scratch: &mut [f32],
    params: &ThesisParams,
) -> Result<SolveStats, SolveError> {
    let n = dims.len();
    let (Some(labels), Some(psi), Some(scratch)) = (labels.get(..n), psi.get_mut(..n), scratch.get_mut(..n))
    else {
        return Err(SolveError::StorageTooSmall);
    };
    if !(params.relative_change.is_finite() && params.relative_change > 0.0) {
        return Err(SolveError::BadTolerance);
    }
    start_psi(labels, psi);
    let active = Active::of(dims, labels);
    let b2 = dirichlet_norm2(dims, labels);
    let initial = residual_with(dims, &active, &Screen::NONE, (labels, &[]), psi, b2);
    let mut stats = SolveStats {
        initial_residual: initial.relative,
        ..Default::default()
    };
    // Sweep on the thesis's φ, then store it as ψ.
    for p in psi.iter_mut() {
        *p = phi_of(*p);
    }
    let (sweeps, updates, converged) = sweep_phi(dims, &active, labels, psi, scratch, params);
    for p in psi.iter_mut() {
        *p = psi_of(*p);
    }
    stats.iterations = sweeps;
    stats.cell_updates = updates;
    let _ = clamp_to_bounds(labels, psi);
    let end = residual_with(dims, &active, &Screen::NONE, (labels, &[]), psi, b2);
    stats.residual = end.relative;
    stats.floor = end.floor;
    // The rule stopping the sweeps is not a converged field: converged only where the residual
    // meets the tolerance too (no error target: the thesis estimates no error).
    stats.converged = converged && end.relative <= params.tolerance;
    stats.stop = match (stats.converged, converged) {
        (true, _) => Stop::Met,
        (false, true) => Stop::Rule,
        (false, false) => Stop::Cap,
    };
    Ok(stats)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::planning::solve::{gauss_seidel, SolveParams};

    extern crate std;
    use std::vec;
    use std::vec::Vec;

    /// A closed box of `nx × ny × nz` interior voxels: the vehicle near one corner, a patch of
    /// frontier voxels on the far face (a doorway onto unknown space).
    fn boxed(nx: usize, ny: usize, nz: usize) -> (Dims, Vec<Label>, usize) {
        let dims = Dims::new(nx, ny, nz).unwrap();
        let mut labels = vec![Label::Interior; dims.len()];
        let at = |x: usize, y: usize, z: usize| x + nx * (y + ny * z);
        let source = at(1, 1, 1);
        labels[source] = Label::Source;
        for z in 0..nz / 2 {
            for y in ny / 3..ny - 1 {
                labels[at(nx - 1, y, z)] = Label::Frontier;
            }
        }
        (dims, labels, source)
    }

    /// Largest relative change of the thesis's φ between two sweeps over the interior, in
    /// IEEE arithmetic (∞ for a voxel that left 0; a voxel that stayed at 0 is never the max).
    fn max_relative_change(labels: &[Label], before: &[f32], after: &[f32]) -> f32 {
        let mut m = 0.0f32;
        for ((l, &a), &b) in labels.iter().zip(before).zip(after) {
            let c = ((b - a) / a).abs();
            if *l == Label::Interior && c > m {
                m = c;
            }
        }
        m
    }

    #[test]
    fn stops_by_its_rule_and_orders_like_the_exact_field() {
        let (dims, labels, source) = boxed(12, 9, 6);
        let n = dims.len();
        let mut psi = vec![0.3f32; n]; // Whatever the buffer held: the solve starts cold.
        let mut scratch = vec![0.0f32; n];
        let params = ThesisParams::default();
        let s = solve(&dims, &labels, &mut psi, &mut scratch, &params).unwrap();
        // Stopped by its rule, but the field it left does not meet the core's tolerance.
        assert!(!s.converged && s.stop == Stop::Rule, "{s:?}");
        assert!(s.iterations > 2 && s.iterations < params.max_sweeps, "{s:?}");
        // The rule, checked from outside on the thesis's φ: the last sweep changed φ by less
        // than 1e-4 relative, the one before did not.
        let k = s.iterations;
        let phi_after = |sweeps: u32| {
            let mut p: Vec<f32> = vec![0.0; n];
            start_psi(&labels, &mut p);
            p.iter_mut().for_each(|v| *v = phi_of(*v));
            let mut sc = vec![0.0f32; n];
            let capped = ThesisParams {
                max_sweeps: sweeps,
                ..params
            };
            let active = Active::of(&dims, &labels);
            let (done, _, _) = sweep_phi(&dims, &active, &labels, &mut p, &mut sc, &capped);
            assert_eq!(done, sweeps);
            p
        };
        let (f0, f1, f2) = (phi_after(k - 2), phi_after(k - 1), phi_after(k));
        assert!(max_relative_change(&labels, &f1, &f2) < params.relative_change);
        assert!(max_relative_change(&labels, &f0, &f1) >= params.relative_change);
        for (i, (&p, &f)) in psi.iter().zip(&f2).enumerate() {
            if labels[i].in_domain() {
                assert_eq!(p, psi_of(f), "voxel {i}");
            }
        }
        // Truncated, not converged: the core's residual is still well above its 1e-6.
        assert!(s.residual > 1e-6 && s.residual < s.initial_residual, "{s:?}");

        // Orders like the exact solve: vehicle lowest ψ (highest φ), frontiers highest ψ, and
        // every interior voxel strictly between its neighbours' extremes (no interior extremum).
        let mut exact = vec![0.0f32; n];
        let e = gauss_seidel(
            &dims,
            &labels,
            &mut exact,
            &SolveParams {
                warm_start: false,
                ..SolveParams::default()
            },
        )
        .unwrap();
        assert!(e.converged);
        for field in [&psi, &exact] {
            assert_eq!(field[source], PSI_SOURCE);
            for (i, l) in labels.iter().enumerate() {
                match l {
                    Label::Frontier => assert_eq!(field[i], PSI_FRONTIER),
                    Label::Interior => {
                        assert!(
                            field[i] > PSI_SOURCE && field[i] < PSI_FRONTIER,
                            "voxel {i}: {}",
                            field[i]
                        );
                        let (lo, hi) = neighbour_range(&dims, &labels, field, i);
                        assert!(
                            lo < field[i] && field[i] < hi,
                            "voxel {i}: {} not in ({lo}, {hi})",
                            field[i]
                        );
                    }
                    _ => {}
                }
            }
        }
    }

    /// Smallest and largest ψ among the in-domain face neighbours of voxel `i`.
    fn neighbour_range(dims: &Dims, labels: &[Label], psi: &[f32], i: usize) -> (f32, f32) {
        let mut r = (f32::INFINITY, f32::NEG_INFINITY);
        dims.for_each_face_neighbour(dims.voxel(i), |j| {
            if labels[j].in_domain() {
                r = (r.0.min(psi[j]), r.1.max(psi[j]));
            }
        });
        r
    }

    #[test]
    fn a_lone_frontier_voxel_does_not_stop_it_at_sweep_two() {
        // The checkerboard case: after sweep 1 only the voxels beside the vehicle and beside the
        // one frontier voxel are nonzero, none of them neighbours, so sweep 2 changes none of
        // them. Voxels leaving 0 (relative change ∞) must hold the solve open until the
        // wavefront has crossed the box.
        let (nx, ny, nz) = (10, 8, 5);
        let dims = Dims::new(nx, ny, nz).unwrap();
        let mut labels = vec![Label::Interior; dims.len()];
        labels[1 + nx * (1 + ny)] = Label::Source;
        labels[8 + nx * (6 + ny * 3)] = Label::Frontier;
        let (mut psi, mut scratch) = (vec![0.0f32; dims.len()], vec![0.0f32; dims.len()]);
        let s = solve(&dims, &labels, &mut psi, &mut scratch, &ThesisParams::default()).unwrap();
        assert!(s.iterations > (nx + ny + nz) as u32, "{s:?}");
        for (l, p) in labels.iter().zip(&psi) {
            if *l == Label::Interior {
                assert!(*p != psi_of(PHI_START), "a voxel the sweeps never reached");
            }
        }
    }

    #[test]
    fn ill_posed_cases_are_handled() {
        // One interior voxel halfway between vehicle and frontier: φ = 0 for ever, never
        // counted; the first sweep changes nothing, a fixed point.
        let dims = Dims::new(3, 1, 1).unwrap();
        let labels = [Label::Source, Label::Interior, Label::Frontier];
        let (mut psi, mut scratch) = ([0.0f32; 3], [0.0f32; 3]);
        let s = solve(&dims, &labels, &mut psi, &mut scratch, &ThesisParams::default()).unwrap();
        assert!(s.converged && s.iterations == 1 && s.stop == Stop::Met, "{s:?}");
        assert_eq!(psi, [0.0, 0.5, 1.0]);
        // The cap: reported, not converged.
        let (dims, labels, _) = boxed(12, 9, 6);
        let (mut psi, mut scratch) = (vec![0.0f32; dims.len()], vec![0.0f32; dims.len()]);
        let capped = ThesisParams {
            max_sweeps: 5,
            ..ThesisParams::default()
        };
        let s = solve(&dims, &labels, &mut psi, &mut scratch, &capped).unwrap();
        assert!(!s.converged && s.iterations == 5 && s.stop == Stop::Cap, "{s:?}");
        // Short buffers and a bad threshold are refused.
        let mut short = vec![0.0f32; dims.len() - 1];
        assert_eq!(
            solve(&dims, &labels, &mut psi, &mut short, &capped),
            Err(SolveError::StorageTooSmall)
        );
        let bad = ThesisParams {
            relative_change: 0.0,
            ..capped
        };
        assert_eq!(
            solve(&dims, &labels, &mut psi, &mut scratch, &bad),
            Err(SolveError::BadTolerance)
        );
    }
}
