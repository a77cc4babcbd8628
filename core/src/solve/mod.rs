//! Laplace solvers over the domain built by [`crate::domain`].
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
//! [`multigrid`] is the production solver: O(cells) per solve.

use crate::domain::Label;
use crate::map::Dims;

pub mod multigrid;

/// When a solve stops.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SolveParams {
    /// Stop when the relative residual is at or below this.
    pub tolerance: f32,
    /// Stop after this many sweeps (Gauss-Seidel) or cycles (multigrid) regardless.
    pub max_iterations: u32,
    /// Start from the φ already in the buffer (interior voxels) instead of 0.
    pub warm_start: bool,
}

impl Default for SolveParams {
    fn default() -> Self {
        Self {
            tolerance: 1e-6,
            max_iterations: 20_000,
            warm_start: true,
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
    /// True if the tolerance — or, where the tolerance lies below it, the f32 floor — was
    /// reached.
    pub converged: bool,
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
}

/// Value of the stored potential ψ = 1 − φ at the source.
pub const PSI_SOURCE: f32 = 0.0;
/// Value of the stored potential ψ = 1 − φ at frontiers.
pub const PSI_FRONTIER: f32 = 1.0;

/// Sets Dirichlet values of ψ, zeroes it outside the domain and, unless warm-starting, in the
/// interior. Non-finite or out-of-range warm-start values are reset to 0.
pub fn prepare(labels: &[Label], psi: &mut [f32], warm_start: bool) {
    for (l, p) in labels.iter().zip(psi.iter_mut()) {
        *p = match l {
            Label::Frontier => PSI_FRONTIER,
            Label::Interior if warm_start && (0.0..=1.0).contains(p) => *p,
            _ => 0.0,
        };
    }
}

/// Clamps interior ψ into [0, 1], the range the maximum principle guarantees: rounding can
/// leave a value a few ulps outside it, and equal values at the top would give the streamline a
/// plateau to wander on.
pub(crate) fn clamp_to_bounds(labels: &[Label], psi: &mut [f32]) {
    for (l, p) in labels.iter().zip(psi.iter_mut()) {
        if *l == Label::Interior {
            *p = p.clamp(PSI_SOURCE, PSI_FRONTIER);
        }
    }
}

/// Calls `f` with the linear index of each face neighbour of voxel `i` at `(x, y, z)` that lies
/// inside the grid. The solvers' hot loops already know the coordinates, so this avoids
/// recomputing them from `i`.
#[inline]
pub(crate) fn each_face_neighbour(
    dims: &Dims,
    i: usize,
    x: usize,
    y: usize,
    z: usize,
    mut f: impl FnMut(usize),
) {
    let (nx, nxy) = (dims.nx(), dims.nx() * dims.ny());
    if x > 0 {
        f(i - 1);
    }
    if x + 1 < dims.nx() {
        f(i + 1);
    }
    if y > 0 {
        f(i - nx);
    }
    if y + 1 < dims.ny() {
        f(i + nx);
    }
    if z > 0 {
        f(i - nxy);
    }
    if z + 1 < dims.nz() {
        f(i + nxy);
    }
}

/// Net flux into voxel `i` at `(x, y, z)`, `Σ (φ_j − φ_i)` over in-domain face neighbours `j`, and
/// their count. Summing differences, rather than `Σ φ_j − count·φ_i`, avoids the cancellation
/// that would otherwise put an f32 rounding floor of ~1e-6 under the relative residual.
#[inline]
pub(crate) fn neighbour_flux(
    dims: &Dims,
    labels: &[Label],
    phi: &[f32],
    i: usize,
    x: usize,
    y: usize,
    z: usize,
) -> (f32, u32) {
    let centre = phi.get(i).copied().unwrap_or(0.0);
    let mut flux = 0.0f32;
    let mut count = 0u32;
    each_face_neighbour(dims, i, x, y, z, |j| {
        if let (Some(l), Some(p)) = (labels.get(j), phi.get(j)) {
            if l.in_domain() {
                flux += *p - centre;
                count += 1;
            }
        }
    });
    (flux, count)
}

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
}

impl Residual {
    /// True if the residual meets `tolerance`, or the floor where that lies above it.
    pub fn meets(&self, tolerance: f32) -> bool {
        self.relative <= tolerance.max(self.floor)
    }
}

/// Relative residual of the current ψ (see [`Residual`]).
pub fn relative_residual(dims: &Dims, labels: &[Label], psi: &[f32]) -> f32 {
    residual(dims, labels, psi).relative
}

/// Residual and rounding floor of the current ψ.
pub fn residual(dims: &Dims, labels: &[Label], psi: &[f32]) -> Residual {
    let (r2, b2, e2) = residual_norms(dims, labels, psi);
    if b2 == 0.0 {
        Residual {
            relative: 0.0,
            floor: 0.0,
        }
    } else {
        Residual {
            relative: libm::sqrt(r2 / b2) as f32,
            floor: libm::sqrt(e2 / b2) as f32,
        }
    }
}

/// The five neighbouring rows of one x-row of a grid buffer, `None` at the grid edge.
pub(crate) struct Rows<'r, T> {
    pub(crate) y_minus: Option<&'r [T]>,
    pub(crate) y_plus: Option<&'r [T]>,
    pub(crate) z_minus: Option<&'r [T]>,
    pub(crate) z_plus: Option<&'r [T]>,
}

impl<'r, T> Rows<'r, T> {
    /// Rows around the row starting at `start` = index of (0, y, z), from the parts of the
    /// buffer before it and after it (the row itself excluded).
    pub(crate) fn around(dims: &Dims, y: usize, z: usize, before: &'r [T], after: &'r [T]) -> Self {
        let (nx, ny, nz) = (dims.nx(), dims.ny(), dims.nz());
        let nxy = nx * ny;
        let start = before.len();
        Rows {
            y_minus: if y > 0 {
                before.get(start - nx..start)
            } else {
                None
            },
            z_minus: if z > 0 {
                before.get(start - nxy..start - nxy + nx)
            } else {
                None
            },
            y_plus: if y + 1 < ny { after.get(..nx) } else { None },
            z_plus: if z + 1 < nz {
                after.get(nxy - nx..nxy)
            } else {
                None
            },
        }
    }
}

/// Net flux `Σ (x_j − c)` into cell `x` of a row from its in-domain face neighbours, and their
/// count (the row-sliced form of `solve::neighbour_flux`).
#[inline]
pub(crate) fn row_flux(
    l_row: &[Label],
    row: &[f32],
    ls: &Rows<'_, Label>,
    xs: &Rows<'_, f32>,
    x: usize,
    c: f32,
) -> (f32, u32) {
    let (mut flux, mut count) = (0.0f32, 0u32);
    let mut add = |l: Option<&Label>, p: Option<&f32>| {
        if let (Some(l), Some(p)) = (l, p) {
            if l.in_domain() {
                flux += *p - c;
                count += 1;
            }
        }
    };
    if x > 0 {
        add(l_row.get(x - 1), row.get(x - 1));
    }
    add(l_row.get(x + 1), row.get(x + 1));
    for (l, p) in [
        (ls.y_minus, xs.y_minus),
        (ls.y_plus, xs.y_plus),
        (ls.z_minus, xs.z_minus),
        (ls.z_plus, xs.z_plus),
    ] {
        if let (Some(l), Some(p)) = (l, p) {
            add(l.get(x), p.get(x));
        }
    }
    (flux, count)
}

/// One x-row of a grid buffer with its labels and the five neighbouring rows.
pub(crate) struct RowView<'r> {
    /// Row coordinates.
    pub(crate) y: usize,
    /// Row coordinates.
    pub(crate) z: usize,
    /// Linear index of the row's first cell.
    pub(crate) start: usize,
    /// The row's labels.
    pub(crate) labels: &'r [Label],
    /// The row's values.
    pub(crate) values: &'r [f32],
    label_rows: Rows<'r, Label>,
    value_rows: Rows<'r, f32>,
}

impl RowView<'_> {
    /// Net flux into cell `x` of the row and the number of in-domain neighbours.
    #[inline]
    pub(crate) fn flux(&self, x: usize) -> (f32, u32) {
        let c = self.values.get(x).copied().unwrap_or(0.0);
        row_flux(self.labels, self.values, &self.label_rows, &self.value_rows, x, c)
    }
    /// Calls `f(label, value)` for each face neighbour of cell `x` inside the grid.
    #[inline]
    pub(crate) fn each_neighbour(&self, x: usize, mut f: impl FnMut(&Label, f32)) {
        let mut visit = |l: Option<&Label>, p: Option<&f32>| {
            if let (Some(l), Some(p)) = (l, p) {
                f(l, *p);
            }
        };
        if x > 0 {
            visit(self.labels.get(x - 1), self.values.get(x - 1));
        }
        visit(self.labels.get(x + 1), self.values.get(x + 1));
        let (ls, xs) = (&self.label_rows, &self.value_rows);
        for (l, p) in [
            (ls.y_minus, xs.y_minus),
            (ls.y_plus, xs.y_plus),
            (ls.z_minus, xs.z_minus),
            (ls.z_plus, xs.z_plus),
        ] {
            if let (Some(l), Some(p)) = (l, p) {
                visit(l.get(x), p.get(x));
            }
        }
    }
}

/// Calls `f` with a [`RowView`] of every x-row of `values` (read-only).
pub(crate) fn for_each_row(dims: &Dims, labels: &[Label], values: &[f32], mut f: impl FnMut(&RowView<'_>)) {
    let (nx, ny) = (dims.nx(), dims.ny());
    for z in 0..dims.nz() {
        for y in 0..ny {
            let start = nx * (y + ny * z);
            let (Some(x_before), Some(row), Some(x_after)) = (
                values.get(..start),
                values.get(start..start + nx),
                values.get(start + nx..),
            ) else {
                continue;
            };
            let (Some(l_before), Some(l_row), Some(l_after)) = (
                labels.get(..start),
                labels.get(start..start + nx),
                labels.get(start + nx..),
            ) else {
                continue;
            };
            f(&RowView {
                y,
                z,
                start,
                labels: l_row,
                values: row,
                label_rows: Rows::around(dims, y, z, l_before, l_after),
                value_rows: Rows::around(dims, y, z, x_before, x_after),
            });
        }
    }
}

/// Squared norms of the residual, of the right-hand side `b` (the Dirichlet contributions) and
/// of the rounding estimate `e`, row by row.
fn residual_norms(dims: &Dims, labels: &[Label], psi: &[f32]) -> (f64, f64, f64) {
    let (mut r2, mut b2, mut e2) = (0.0f64, 0.0f64, 0.0f64);
    for_each_row(dims, labels, psi, |row| {
        let (mut row_r, mut row_b, mut row_e) = (0.0f32, 0.0f32, 0.0f32);
        for (x, l) in row.labels.iter().enumerate() {
            if *l != Label::Interior {
                continue;
            }
            let c = row.values.get(x).copied().unwrap_or(0.0);
            let (r, count) = row.flux(x);
            row_r += r * r;
            // b: Dirichlet neighbour values; e: rounding estimate from the squares.
            let (mut b, mut spread) = (0.0f32, (count as f32 * c) * (count as f32 * c));
            row.each_neighbour(x, |l, p| {
                match l {
                    Label::Frontier => b += PSI_FRONTIER,
                    Label::Source => b += PSI_SOURCE,
                    _ => {}
                }
                if l.in_domain() {
                    spread += p * p;
                }
            });
            row_b += b * b;
            row_e += f32::EPSILON * f32::EPSILON * spread / 12.0;
        }
        r2 += f64::from(row_r);
        b2 += f64::from(row_b);
        e2 += f64::from(row_e);
    });
    (r2, b2, e2)
}

/// Validates a solve's inputs, trims the buffers to the grid and sets the Dirichlet values
/// ([`prepare`]): the common start of every solver.
pub(crate) fn checked_problem<'l, 'p>(
    dims: &Dims,
    labels: &'l [Label],
    psi: &'p mut [f32],
    params: &SolveParams,
) -> Result<(&'l [Label], &'p mut [f32]), SolveError> {
    let n = dims.len();
    let (Some(labels), Some(psi)) = (labels.get(..n), psi.get_mut(..n)) else {
        return Err(SolveError::StorageTooSmall);
    };
    if !(params.tolerance.is_finite() && params.tolerance > 0.0) {
        return Err(SolveError::BadTolerance);
    }
    prepare(labels, psi, params.warm_start);
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
    let (labels, phi) = checked_problem(dims, labels, phi, params)?;
    const CHECK_EVERY: u32 = 4;
    let mut res = residual(dims, labels, phi);
    let mut stats = SolveStats {
        initial_residual: res.relative,
        ..Default::default()
    };
    let nx = dims.nx();
    while !res.meets(params.tolerance) && stats.iterations < params.max_iterations {
        for z in 0..dims.nz() {
            for y in 0..dims.ny() {
                let base = nx * (y + dims.ny() * z);
                for x in 0..nx {
                    let i = base + x;
                    if labels.get(i) != Some(&Label::Interior) {
                        continue;
                    }
                    let (flux, count) = neighbour_flux(dims, labels, phi, i, x, y, z);
                    if count > 0 {
                        if let Some(p) = phi.get_mut(i) {
                            *p += flux / count as f32;
                        }
                        stats.cell_updates += 1;
                    }
                }
            }
        }
        stats.iterations += 1;
        if stats.iterations.is_multiple_of(CHECK_EVERY) || stats.iterations == params.max_iterations {
            res = residual(dims, labels, phi);
        }
    }
    clamp_to_bounds(labels, phi);
    stats.residual = res.relative;
    stats.floor = res.floor;
    stats.converged = res.meets(params.tolerance);
    Ok(stats)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A one-voxel corridor of `N` voxels: source at x = 0, frontier at x = N − 1.
    fn corridor<const N: usize>() -> (Dims, [Label; N]) {
        let mut labels = [Label::Interior; N];
        labels[0] = Label::Source;
        labels[N - 1] = Label::Frontier;
        (Dims::new(N, 1, 1).unwrap(), labels)
    }

    #[test]
    fn corridor_gives_a_linear_potential() {
        let (dims, labels) = corridor::<12>();
        let mut phi = [0.0f32; 12];
        let params = SolveParams {
            tolerance: 1e-6,
            max_iterations: 100_000,
            warm_start: false,
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
    fn cycle_cap_is_reported() {
        let (dims, labels) = corridor::<40>();
        let mut phi = [0.0f32; 40];
        let params = SolveParams {
            tolerance: 1e-6,
            max_iterations: 3,
            warm_start: false,
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
