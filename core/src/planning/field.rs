//! Which potential plans: the seed's vehicle-sourced harmonic field, or the frontier-sourced
//! screened field that is the default.
//!
//! **The seed's field** ([`PlanningField::Harmonic`]): Laplace's equation over the domain with
//! the vehicle's voxel at φ = 1 and every frontier at φ = 0. φ is the probability that a random
//! walk from a voxel reaches the vehicle before any frontier; its descent from the vehicle
//! follows the *harmonic measure* of the frontiers. That measure favours large, open frontier
//! regions over near ones, so the vehicle leaves small frontiers behind and flies back for
//! them later (docs/RESULTS.md measured 1.4–2.6× the path of closest frontier).
//!
//! **The screened field** ([`PlanningField::Screened`], the default): `u = 1` on frontier
//! voxels, zero flux through walls, and `∇²u = κ²u` everywhere else, the vehicle included (it is
//! *not* a boundary). The streamline climbs `u` from the vehicle. `u` is the expected value of
//! `e^{−κT}` over random walks started at a voxel, `T` the time they take to hit a frontier: a
//! frontier counts by how much of it there is *and* how near it is, and κ is the dial between
//! the two (κ → 0 weighs frontier mass alone; for large κ, `−ln u / κ` tends to the geodesic
//! distance to the nearest frontier, Varadhan's formula).
//!
//! **Why every streamline still ends on a frontier.** In the discrete problem each interior row
//! reads `(n_i + s)·u_i − Σ_{j ∈ N(i)} u_j = Σ_{frontier neighbours} 1` with `s = κ²h² > 0`
//! (h the voxel size, `n_i` the in-domain face neighbours). The matrix has a positive diagonal,
//! non-positive off-diagonals and strict diagonal dominance: an M-matrix. Two consequences:
//!
//! 1. `0 < u ≤ 1` wherever the domain connects to a frontier (the inverse of an M-matrix is
//!    non-negative, and the row sums bound u by the Dirichlet value 1);
//! 2. *no interior voxel is a local maximum*: `u_i = (Σ u_j) / (n_i + s) < max_j u_j` whenever
//!    `u_i > 0`, because `s > 0`. A voxel beside a wall has fewer neighbours but the same
//!    inequality — zero flux adds no term — which is the discrete form of Hopf's lemma (no
//!    maximum on a Neumann wall).
//!
//! So from any domain voxel there is a face neighbour with a strictly larger `u`, and strict
//! ascent cannot revisit a voxel: the discrete ascent (the streamline's fallback step) ends on a
//! frontier, the only voxels with no higher neighbour. In the continuous field the same follows
//! from the strong maximum principle for `∇²u − κ²u = 0` and Hopf's lemma at the walls. The seed
//! form screened the other way round (vehicle source, screening) would lose this: in one
//! dimension its solution is a `cosh`, with an interior minimum the streamline stalls in.
//!
//! **What else it buys.** The field does not depend on where the vehicle is, so a scan changes
//! the problem only near what it saw and a warm start from the last field is nearly the
//! answer. Values are stored as they are (`u`, not `1 − u`): f32's precision is relative, so
//! `u = 10⁻²⁰` still has a gradient, where the seed's field flattens below f32 resolution far
//! from the vehicle.
//!
//! **Keeping the vehicle in range.** `u` at the vehicle is about `e^{−κd}` for a frontier `d`
//! voxels away; late in an exploration the nearest frontier can be far enough for that to fall
//! below what the solve resolves. The explorer then lowers κ (see [`ScreenedParams`]) and solves
//! again, and raises it back once frontiers are near.

use crate::planning::domain::Label;

/// The planning potential.
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum PlanningField {
    /// The seed's field: Laplace's equation, vehicle φ = 1, frontiers φ = 0.
    Harmonic,
    /// The frontier-sourced screened field (the default).
    Screened(ScreenedParams),
}

impl Default for PlanningField {
    fn default() -> Self {
        PlanningField::Screened(ScreenedParams::default())
    }
}

/// Settings of the screened field.
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct ScreenedParams {
    /// The decay length `1/κ` in metres while frontiers are near: a frontier this much farther
    /// away than another weighs `1/e` as much per voxel of it.
    pub decay_length_m: f32,
    /// Smallest `u` at the vehicle the plan accepts; below it κ is lowered and the field
    /// solved again (the solve resolves values down to a few orders below its tolerance).
    pub min_vehicle_value: f32,
    /// The `u` at the vehicle a lowered κ aims for.
    pub target_vehicle_value: f32,
    /// `u` at the vehicle above which κ doubles (up to its configured value) for the next plan.
    pub raise_above: f32,
    /// Relative-residual tolerance of the screened solve. The streamline needs u's direction of
    /// ascent where u ≥ `min_vehicle_value`; 1e-5 leaves errors far below that and saves about
    /// a fifth of the solve against 1e-6 (measured on the four small thesis worlds, starts 1–3:
    /// the same mean path ratio to closest frontier, 0.76 against 0.77).
    pub tolerance: f32,
}

impl Default for ScreenedParams {
    fn default() -> Self {
        Self {
            decay_length_m: 0.33,
            // Keep the field as local as the solve resolves. A solve to a relative residual
            // of 1e-6 leaves absolute errors of about 1e-7 to 1e-6 in u (measured: a vehicle
            // voxel at u = 5e-7 came out above all its neighbours on s1), so at the default
            // 1e-5 a lowered κ aims a decade above the error (1e-4 at the vehicle) and
            // accepts down to it; a streamline that still stalls retries on half the κ.
            // Late in an exploration only scattered remnants are left, and the deeper the
            // field stays local, the more it visits them nearest first rather than by their
            // mass. Measured against 1e-3 / 1e-2 (the first setting): 1 % shorter on s2 over
            // 30 starts, the same on s4, no worse elsewhere (docs/RESULTS.md, "Remnants").
            min_vehicle_value: 1e-5,
            target_vehicle_value: 1e-4,
            raise_above: 0.1,
            tolerance: 1e-5,
        }
    }
}

/// Most solves one plan makes while it lowers κ.
pub const MAX_SCREENING_SOLVES: u8 = 4;

impl ScreenedParams {
    /// κ in 1/voxel while frontiers are near, for voxels of `resolution` metres (at least
    /// [`MIN_KAPPA_VOXEL`]).
    pub fn kappa_voxel(&self, resolution: f32) -> f32 {
        let k = resolution / self.decay_length_m;
        if k.is_finite() && k > MIN_KAPPA_VOXEL {
            k
        } else {
            MIN_KAPPA_VOXEL
        }
    }

    /// The κ (1/voxel) that brings `u` at the vehicle to [`Self::target_vehicle_value`], given
    /// that the last solve with `kappa` left `u_vehicle` there: `u ≈ e^{−κd}`, so the
    /// frontier's distance is about `d = −ln u / κ`. Never above `kappa` (the caller lowers
    /// it) nor below [`MIN_KAPPA_VOXEL`].
    pub fn lowered_kappa(&self, kappa: f32, u_vehicle: f32) -> f32 {
        let u = u_vehicle.max(f32::MIN_POSITIVE);
        let d = -libm::logf(u) / kappa.max(MIN_KAPPA_VOXEL);
        let want = -libm::logf(self.target_vehicle_value.clamp(f32::MIN_POSITIVE, 0.5));
        let k = if d > 0.0 { want / d } else { kappa };
        k.clamp(MIN_KAPPA_VOXEL, kappa.max(MIN_KAPPA_VOXEL))
    }
}

/// Least κ, in 1/voxel: below it the field is nearly constant over a 64-voxel grid.
pub const MIN_KAPPA_VOXEL: f32 = 0.005;

/// Turns the seed's labels into the screened field's: the vehicle's source voxel becomes an
/// ordinary interior voxel. Returns how many voxels changed.
pub fn release_source(labels: &mut [Label]) -> usize {
    let mut n = 0;
    for l in labels.iter_mut().filter(|l| **l == Label::Source) {
        *l = Label::Interior;
        n += 1;
    }
    n
}
