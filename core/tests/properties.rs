//! Property tests of the exploration core's public API: random maps go through the real
//! pipeline (map → domain → solve → streamline) and the invariants the planner relies on are
//! checked on every case.
//!
//! Run in release (`cargo test --release -p harmonic-core --test properties`): the properties do
//! real Laplace solves. Grids are small (2–14 voxels per axis), so each property finishes in a
//! few seconds at most on a 2-core machine.
//!
//! Properties marked `#[ignore]` are *known to fail*: each carries the minimal counterexample
//! found, and a fix in the core should make it pass again (`-- --ignored`).
//!
//! Failure persistence is off on purpose: proptest would otherwise write a
//! `properties.proptest-regressions` file next to this one. Known counterexamples are pinned as
//! explicit tests below instead.

mod common;

use std::fmt;

use harmonic_core::domain::{self, DomainError, DomainStats, InflationStencil, Label};
use harmonic_core::integrate::traverse;
use harmonic_core::map::{self, Dims, LogOddsParams, MapGeometry, VoxelIndex, VoxelMap};
#[cfg(feature = "flat")]
use harmonic_core::solve::flat::{flat_scratch_len, Flat};
use harmonic_core::solve::multigrid::{scratch_size, Method, Multigrid, MultigridStorage};
use harmonic_core::solve::{
    gauss_seidel, Fork, Sequential, SolveParams, SolveStats, Stop, PSI_FRONTIER, PSI_SOURCE,
};
use harmonic_core::streamline::{trace, Field, StreamlineError, StreamlineParams, Waypoints};
use nalgebra::{Point3, Vector3};
use proptest::prelude::*;
use proptest::sample::Index;

/// `ProptestConfig::with_cases`, without the regressions file and with room to shrink.
fn config(cases: u32) -> ProptestConfig {
    ProptestConfig {
        failure_persistence: None,
        max_shrink_iters: 8192,
        // Cases without a frontier are rejected, about one in five: leave ample room.
        max_global_rejects: 4 * cases,
        ..ProptestConfig::with_cases(cases)
    }
}

// ---------------------------------------------------------------------------------------------
// Random worlds
// ---------------------------------------------------------------------------------------------

/// What a test world says about one voxel before it becomes a [`VoxelMap`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Cell {
    Free,
    Occupied,
    Unknown,
}

/// A random world: per-voxel states and the vehicle voxel (always free).
#[derive(Clone)]
struct World {
    nx: usize,
    ny: usize,
    nz: usize,
    cells: Vec<Cell>,
    vehicle: VoxelIndex,
}

impl World {
    /// Builds a world from ASCII layers, one slice of rows per z: `.` free, `#` occupied, `V`
    /// the (free) vehicle voxel, anything else unknown. Row `y`, column `x`.
    fn from_layers(layers: &[&[&str]]) -> Self {
        let (nz, ny, nx) = (layers.len(), layers[0].len(), layers[0][0].len());
        let mut cells = vec![Cell::Unknown; nx * ny * nz];
        let mut vehicle = VoxelIndex::new(0, 0, 0);
        for (z, layer) in layers.iter().enumerate() {
            for (y, row) in layer.iter().enumerate() {
                for (x, c) in row.bytes().enumerate() {
                    cells[x + nx * (y + ny * z)] = match c {
                        b'.' => Cell::Free,
                        b'#' => Cell::Occupied,
                        b'V' => {
                            vehicle = VoxelIndex::new(x as u16, y as u16, z as u16);
                            Cell::Free
                        }
                        _ => Cell::Unknown,
                    };
                }
            }
        }
        Self {
            nx,
            ny,
            nz,
            cells,
            vehicle,
        }
    }
}

/// Prints the world in the format [`World::from_layers`] reads (`.` free, `#` occupied, `?`
/// unknown, `V` vehicle), so a shrunk counterexample can be pasted into a pinned test.
impl fmt::Debug for World {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let v = self.vehicle;
        writeln!(
            f,
            "World {}x{}x{}, vehicle ({}, {}, {}):",
            self.nx, self.ny, self.nz, v.x, v.y, v.z
        )?;
        for z in 0..self.nz {
            writeln!(f, "  z = {z}")?;
            for y in 0..self.ny {
                let row: String = (0..self.nx)
                    .map(|x| {
                        if (x, y, z) == (usize::from(v.x), usize::from(v.y), usize::from(v.z)) {
                            'V'
                        } else {
                            match self.cells[x + self.nx * (y + self.ny * z)] {
                                Cell::Free => '.',
                                Cell::Occupied => '#',
                                Cell::Unknown => '?',
                            }
                        }
                    })
                    .collect();
                writeln!(f, "    {row}")?;
            }
        }
        Ok(())
    }
}

/// One voxel: 75 % free, 10 % occupied, 15 % unknown. Shrinks towards free.
fn cell() -> impl Strategy<Value = Cell> {
    (0u8..100).prop_map(|r| match r {
        0..75 => Cell::Free,
        75..85 => Cell::Occupied,
        _ => Cell::Unknown,
    })
}

/// Independent random voxels on a grid with the given axis ranges; the vehicle voxel is free.
fn scattered_world(
    xy: std::ops::RangeInclusive<usize>,
    z: std::ops::RangeInclusive<usize>,
) -> impl Strategy<Value = World> {
    (xy.clone(), xy, z).prop_flat_map(|(nx, ny, nz)| {
        (
            proptest::collection::vec(cell(), nx * ny * nz),
            0..nx as u16,
            0..ny as u16,
            0..nz as u16,
        )
            .prop_map(move |(mut cells, x, y, z)| {
                cells[usize::from(x) + nx * (usize::from(y) + ny * usize::from(z))] = Cell::Free;
                World {
                    nx,
                    ny,
                    nz,
                    cells,
                    vehicle: VoxelIndex::new(x, y, z),
                }
            })
    })
}

/// Free space with a few random occupied and unknown boxes: rooms, walls with gaps, dead ends,
/// large interiors and long paths (the hard cases for the solvers and the tracer).
fn box_world() -> impl Strategy<Value = World> {
    box_world_in(6..=14, 1..=8, 6)
}

/// [`box_world`] on a grid with the given axis ranges and up to `most` boxes.
fn box_world_in(
    xy: std::ops::RangeInclusive<usize>,
    z: std::ops::RangeInclusive<usize>,
    most: usize,
) -> impl Strategy<Value = World> {
    (xy.clone(), xy, z).prop_flat_map(move |(nx, ny, nz)| {
        let range = |n: usize| (0..n, 0..n).prop_map(|(a, b)| (a.min(b), a.max(b)));
        let boxes = proptest::collection::vec((cell(), range(nx), range(ny), range(nz)), 1..=most);
        (boxes, 0..nx as u16, 0..ny as u16, 0..nz as u16).prop_map(move |(boxes, x, y, z)| {
            let mut cells = vec![Cell::Free; nx * ny * nz];
            for (kind, (x0, x1), (y0, y1), (z0, z1)) in boxes {
                // A "free" box would be a no-op; make it an obstacle so every box does something.
                let kind = if kind == Cell::Free { Cell::Occupied } else { kind };
                for zz in z0..=z1 {
                    for yy in y0..=y1 {
                        for xx in x0..=x1 {
                            cells[xx + nx * (yy + ny * zz)] = kind;
                        }
                    }
                }
            }
            cells[usize::from(x) + nx * (usize::from(y) + ny * usize::from(z))] = Cell::Free;
            World {
                nx,
                ny,
                nz,
                cells,
                vehicle: VoxelIndex::new(x, y, z),
            }
        })
    })
}

/// The world mix every domain property draws from: cluttered 6–12 voxel grids, box worlds up to
/// 14 voxels, and tiny 2–5 voxel grids (degenerate multigrid hierarchies, one-voxel rooms).
fn world() -> impl Strategy<Value = World> {
    prop_oneof![
        3 => scattered_world(6..=12, 1..=8),
        3 => box_world(),
        1 => scattered_world(2..=5, 1..=5),
    ]
}

/// A world turned into a domain (radius 0: every observed free voxel is safe).
#[derive(Clone)]
struct Built {
    geometry: MapGeometry,
    labels: Vec<Label>,
    stats: DomainStats,
    vehicle: VoxelIndex,
}

impl Built {
    fn dims(&self) -> Dims {
        self.geometry.dims()
    }
}

/// Grid resolution of the test maps. A power of two with the origin at 0 makes the map ↔ grid
/// conversions exact, so a waypoint on a voxel face is attributed to the voxel the tracer meant.
const RESOLUTION: f32 = 0.25;

fn build(world: &World) -> Result<Built, DomainError> {
    let dims = Dims::new(world.nx, world.ny, world.nz).expect("test dims are valid");
    let geometry = MapGeometry::new(dims, Point3::origin(), RESOLUTION).expect("valid geometry");
    let (mut lo, mut st) = (vec![0i8; dims.len()], vec![0u32; map::touched_words(&dims)]);
    let mut map = VoxelMap::new(geometry, LogOddsParams::default(), &mut lo, &mut st).expect("storage fits");
    for (i, c) in world.cells.iter().enumerate() {
        match c {
            Cell::Free => map.apply_miss(i),
            Cell::Occupied => map.apply_hit(i),
            Cell::Unknown => false,
        };
    }
    let stencil = InflationStencil::new(0.0, RESOLUTION)?;
    let mut labels = vec![Label::Outside; dims.len()];
    let mut queue = vec![0u32; dims.len()];
    let stats = domain::build(&map, &stencil, world.vehicle, &mut labels, &mut queue)?;
    Ok(Built {
        geometry,
        labels,
        stats,
        vehicle: world.vehicle,
    })
}

/// Builds the domain, rejecting (not failing) cases with a domain error or no frontier.
fn build_with_frontier(world: &World) -> Result<Built, TestCaseError> {
    let b = build(world);
    prop_assume!(b.is_ok(), "domain error {:?}", b.err());
    let b = b.unwrap();
    prop_assume!(b.stats.frontier > 0, "no frontier");
    Ok(b)
}

// ---------------------------------------------------------------------------------------------
// Solves
// ---------------------------------------------------------------------------------------------

/// Whether a solve stopped by its own rule — the tolerance, or the f32 rounding floor where
/// that lies above it — rather than at its cap, and reported `converged` exactly when its
/// residual met the tolerance (1e-6 in every property here; the floor of a small domain rarely
/// lies above it).
fn stopped_by_its_rule(s: &SolveStats) -> bool {
    matches!(s.stop, Stop::Met | Stop::Floor) && s.converged == (s.residual <= 1e-6)
}

fn solve_gs(b: &Built, tolerance: f32) -> (Vec<f32>, SolveStats) {
    let mut psi = vec![0.0f32; b.dims().len()];
    let params = SolveParams {
        tolerance,
        max_iterations: 200_000,
        warm_start: false,
        ..SolveParams::default()
    };
    let s = gauss_seidel(&b.dims(), &b.labels, &mut psi, &params).expect("valid solve inputs");
    (psi, s)
}

fn solve_mg(b: &Built, method: Method) -> (Vec<f32>, SolveStats) {
    solve_mg_to(b, method, 1e-6)
}

fn solve_mg_to(b: &Built, method: Method, tolerance: f32) -> (Vec<f32>, SolveStats) {
    solve_mg_screened(b, method, tolerance, 0.0)
}

/// [`solve_mg_to`] with [`SolveParams::screening`] `screening`.
fn solve_mg_screened(b: &Built, method: Method, tolerance: f32, screening: f32) -> (Vec<f32>, SolveStats) {
    solve_mg_lent(b, method, tolerance, screening, true, None)
}

/// [`solve_mg_screened`], lending the neighbour masks (the host's storage) or not (the
/// firmware's), and a [`Fork`] or not.
fn solve_mg_lent(
    b: &Built,
    method: Method,
    tolerance: f32,
    screening: f32,
    masks: bool,
    fork: Option<&dyn Fork>,
) -> (Vec<f32>, SolveStats) {
    let dims = b.dims();
    let size = scratch_size(&dims);
    let mut values = vec![0.0f32; size.values];
    let mut clabels = vec![Label::Outside; size.labels];
    let mut faces = vec![[0u8; 4]; size.faces];
    let mut krylov = vec![0.0f32; size.krylov];
    let mut mask_bytes = vec![0u8; if masks { size.masks } else { 0 }];
    let mut mg = Multigrid::new(
        dims,
        MultigridStorage {
            values: values.as_mut_slice().into(),
            labels: &mut clabels,
            faces: &mut faces,
            krylov: &mut krylov,
            masks: &mut mask_bytes,
        },
    )
    .expect("scratch sized by scratch_size");
    mg.set_fork(fork);
    let mut psi = vec![0.0f32; dims.len()];
    let params = SolveParams {
        tolerance,
        max_iterations: 2000,
        warm_start: false,
        screening,
        max_error: f32::INFINITY,
    };
    let s = mg
        .solve(&b.labels, &mut psi, &params, method)
        .expect("valid solve inputs");
    (psi, s)
}

/// `b` solved by the flat solver ([`harmonic_core::solve::flat`], the host's fast MGPCG) from
/// ψ = 0, with a [`Fork`] or not.
#[cfg(feature = "flat")]
fn solve_flat(b: &Built, tolerance: f32, screening: f32, fork: Option<&dyn Fork>) -> (Vec<f32>, SolveStats) {
    let dims = b.dims();
    let mut values = vec![0.0f32; flat_scratch_len(&dims)];
    let mut flat = Flat::new(dims, &mut values).expect("scratch sized by flat_scratch_len");
    flat.set_fork(fork);
    let mut psi = vec![0.0f32; dims.len()];
    let params = SolveParams {
        tolerance,
        max_iterations: 2000,
        warm_start: false,
        screening,
        max_error: f32::INFINITY,
    };
    let s = flat
        .solve(&b.labels, &mut psi, &params)
        .expect("valid solve inputs");
    (psi, s)
}

proptest! {
    #![proptest_config(config(12))]

    /// **The flat solver's threads change nothing but the speed** either: the same bits,
    /// iterations and cell updates with two threads, the split without threads, and none.
    #[cfg(feature = "flat")]
    #[test]
    fn a_fork_gives_the_flat_solver_the_same_bits(w in prop_oneof![scattered_world(20..=30, 12..=18), box_world_in(20..=32, 12..=18, 12)]) {
        let b = build_with_frontier(&w)?;
        let mut s = b.clone();
        harmonic_core::field::release_source(&mut s.labels);
        for (problem, screening) in [(&b, 0.0), (&s, SCREENING)] {
            let (alone, z) = solve_flat(problem, 1e-6, screening, None);
            for fork in [&Threads as &dyn Fork, &Sequential] {
                let (split, a) = solve_flat(problem, 1e-6, screening, Some(fork));
                prop_assert_eq!((a.iterations, a.cell_updates), (z.iterations, z.cell_updates));
                let differ = split.iter().zip(&alone).filter(|(p, q)| p.to_bits() != q.to_bits()).count();
                prop_assert_eq!(differ, 0, "screening {}: {} values differ", screening, differ);
            }
        }
    }

    /// **Two threads change nothing but the speed:** a solve lent a [`Fork`] — one that runs
    /// the halves on two threads, and [`Sequential`], the split without threads — gives every
    /// ψ to the bit of one without, with the same iterations and cell updates: MGPCG and
    /// V-cycles, Laplace's equation and the screened one, with and without the neighbour
    /// masks. The worlds are large enough (20–30 voxels across) for the fine level and the
    /// first coarse one to be split.
    #[test]
    fn a_fork_gives_the_same_bits(w in prop_oneof![scattered_world(20..=30, 12..=18), box_world_in(20..=32, 12..=18, 12)]) {
        let b = build_with_frontier(&w)?;
        let mut s = b.clone();
        harmonic_core::field::release_source(&mut s.labels);
        for (problem, screening) in [(&b, 0.0), (&s, SCREENING)] {
            for method in [Method::Pcg, Method::VCycle] {
                for masks in [true, false] {
                    let (alone, z) = solve_mg_lent(problem, method, 1e-6, screening, masks, None);
                    for fork in [&Threads as &dyn Fork, &Sequential] {
                        let (split, a) = solve_mg_lent(problem, method, 1e-6, screening, masks, Some(fork));
                        prop_assert_eq!((a.iterations, a.cell_updates), (z.iterations, z.cell_updates));
                        let differ = split.iter().zip(&alone).filter(|(p, q)| p.to_bits() != q.to_bits()).count();
                        prop_assert_eq!(differ, 0, "{:?}, screening {}, masks {}: {} values differ", method, screening, masks, differ);
                    }
                }
            }
        }
    }
}

/// A [`Fork`] on two threads of the standard library (a scoped thread per join).
struct Threads;

impl Fork for Threads {
    fn join(&self, a: &mut (dyn FnMut() + Send), b: &mut (dyn FnMut() + Send)) {
        std::thread::scope(|s| {
            s.spawn(b);
            a();
        });
    }
}

/// The exact discrete solution, independently (see [`common::exact_solution`]).
fn solve_exact(b: &Built) -> Vec<f64> {
    solve_exact_screened(b, 0.0)
}

/// [`solve_exact`] for the screened system: every interior row gains `screening · x_i`.
fn solve_exact_screened(b: &Built, screening: f64) -> Vec<f64> {
    common::exact_solution(&b.dims(), &b.labels, screening)
}

fn neighbour_range(dims: &Dims, labels: &[Label], psi: &[f32], i: usize) -> (f32, f32, u32) {
    let (mut lo, mut hi, mut count) = (f32::INFINITY, f32::NEG_INFINITY, 0);
    dims.for_each_face_neighbour(dims.voxel(i), |j| {
        if labels[j].in_domain() {
            lo = lo.min(psi[j]);
            hi = hi.max(psi[j]);
            count += 1;
        }
    });
    (lo, hi, count)
}

/// ‖b‖₂ of the ψ system (the Dirichlet contributions to each interior row), as the solvers
/// measure it: the relative residual is ‖r‖ / ‖b‖.
fn rhs_norm(b: &Built) -> f32 {
    let dims = b.dims();
    let mut b2 = 0.0f64;
    for i in 0..dims.len() {
        if b.labels[i] == Label::Interior {
            let mut row = 0.0f64;
            dims.for_each_face_neighbour(dims.voxel(i), |j| match b.labels[j] {
                Label::Frontier => row += f64::from(PSI_FRONTIER),
                Label::Source => row += f64::from(PSI_SOURCE),
                _ => {}
            });
            b2 += row * row;
        }
    }
    b2.sqrt() as f32
}

/// Checks the discrete maximum principle and the Dirichlet values on a solved ψ.
/// Interior values are checked against [0, 1] to 1e-5; strict local extrema against
/// `extremum_tol`.
fn check_maximum_principle(
    b: &Built,
    psi: &[f32],
    solver: &str,
    extremum_tol: f32,
) -> Result<(), TestCaseError> {
    const TOL: f32 = 1e-5;
    let dims = b.dims();
    for (i, (&l, &p)) in b.labels.iter().zip(psi).enumerate() {
        let v = dims.voxel(i);
        prop_assert!(p.is_finite(), "{solver}: ψ at {v:?} is {p}");
        match l {
            Label::Source => prop_assert_eq!(p, PSI_SOURCE, "{}: source ψ at {:?}", solver, v),
            Label::Frontier => prop_assert_eq!(p, PSI_FRONTIER, "{}: frontier ψ at {:?}", solver, v),
            Label::Interior => {
                prop_assert!(
                    (-TOL..=1.0 + TOL).contains(&p),
                    "{solver}: interior ψ = {p} at {v:?} outside [0, 1]"
                );
                let (lo, hi, count) = neighbour_range(&dims, &b.labels, psi, i);
                prop_assert!(
                    count > 0,
                    "{solver}: interior voxel {v:?} has no domain neighbour"
                );
                prop_assert!(
                    p <= hi + extremum_tol && p >= lo - extremum_tol,
                    "{solver}: interior ψ = {p} at {v:?}: strict extremum, neighbours in [{lo}, {hi}]"
                );
            }
            _ => {}
        }
    }
    Ok(())
}

/// A point strictly inside voxel `v`, at fractions `f` of its edge.
fn point_in(g: &MapGeometry, v: VoxelIndex, f: (f32, f32, f32)) -> Point3<f32> {
    g.from_grid(&Vector3::new(
        f32::from(v.x) + f.0,
        f32::from(v.y) + f.1,
        f32::from(v.z) + f.2,
    ))
}

/// Random positions inside a voxel, away from its faces.
fn fractions() -> impl Strategy<Value = (f32, f32, f32)> {
    (0.05f32..0.95, 0.05f32..0.95, 0.05f32..0.95)
}

/// Checks a successful trace: it ends in a frontier voxel and every waypoint lies in the domain.
fn check_trace_end(
    b: &Built,
    start: &Point3<f32>,
    end: &harmonic_core::streamline::StreamlineEnd,
    wps: &Waypoints,
) -> Result<(), TestCaseError> {
    let dims = b.dims();
    prop_assert_eq!(
        b.labels[dims.linear(end.frontier)],
        Label::Frontier,
        "trace from {:?} ended in {:?}",
        start,
        end.frontier
    );
    prop_assert!(wps.len() >= 2, "start and end are always recorded");
    for w in wps {
        let v = b.geometry.voxel_at(w);
        prop_assert!(v.is_some(), "waypoint {w:?} outside the grid");
        let l = b.labels[dims.linear(v.unwrap())];
        prop_assert!(
            l.in_domain(),
            "waypoint {w:?} (trace from {start:?}) in a {l:?} voxel"
        );
    }
    Ok(())
}

// ---------------------------------------------------------------------------------------------
// Solver properties
// ---------------------------------------------------------------------------------------------

proptest! {
    #![proptest_config(config(512))]

    /// **Discrete maximum principle, production solver.** Protects the guarantee the streamline
    /// tracer (and the whole "harmonic potentials have no local minima" argument) relies on: a
    /// solved potential lies within its Dirichlet values (ψ ∈ [0, 1]) and no interior voxel is a
    /// strict local extremum, so steepest descent always has somewhere lower to go. It also pins
    /// the documented Dirichlet values of the stored ψ = 1 − φ (source exactly 0, frontier
    /// exactly 1). Multigrid PCG at its default tolerance 1e-6; tolerance 1e-5 on both checks
    /// (MGPCG does overshoot the bounds by up to ~2.6e-6 — never Gauss-Seidel — which is within
    /// it).
    #[test]
    fn multigrid_potential_obeys_the_discrete_maximum_principle(w in world()) {
        let b = build_with_frontier(&w)?;
        let (mg, mg_stats) = solve_mg(&b, Method::Pcg);
        prop_assert!(stopped_by_its_rule(&mg_stats), "multigrid PCG did not converge: {mg_stats:?}");
        check_maximum_principle(&b, &mg, "multigrid PCG", 1e-5)?;
    }

    /// **Discrete maximum principle, reference solver, to 1e-5.** The same guarantee as above for
    /// Gauss-Seidel converged to a relative residual of 1e-6.
    ///
    /// KNOWN TO FAIL (about 1 case in 5 000): the relative-residual stop lets GS leave a local
    /// defect |r_i| up to 1e-6·‖b‖, and ‖b‖ grows with the number of frontier contacts, so at the
    /// end of a dead-end corridor — where GS lags behind the rising value at the entrance — a
    /// voxel stays a strict local *minimum* of ψ by more than 1e-5. Shrunk counterexample (6x6x4,
    /// pinned as `gauss_seidel_dead_end_is_a_local_minimum_beyond_1e_5`): ψ(0,2,0) = 0.9542219,
    /// its only domain neighbour (0,3,0) = 0.9542339 (excess 1.2e-5; the exact solution is flat
    /// there). Multigrid never exceeded 2.4e-6 over 28 000 random domains.
    /// `gauss_seidel_potential_obeys_the_maximum_principle_within_its_residual` checks the bound
    /// GS does promise.
    #[test]
    #[ignore = "known to fail: GS leaves dead-end voxels 1.2e-5 below their neighbours (see doc)"]
    fn gauss_seidel_potential_obeys_the_discrete_maximum_principle(w in world()) {
        let b = build_with_frontier(&w)?;
        let (gs, gs_stats) = solve_gs(&b, 1e-6);
        prop_assert!(stopped_by_its_rule(&gs_stats), "Gauss-Seidel did not converge: {gs_stats:?}");
        check_maximum_principle(&b, &gs, "Gauss-Seidel", 1e-5)?;
    }

    /// **Discrete maximum principle, reference solver, within its reported residual.** What
    /// Gauss-Seidel's documented stop (relative residual ≤ 1e-6) does guarantee: ψ ∈ [0, 1]
    /// (to 1e-5; GS approaches from below and never overshoots), exact Dirichlet values, and no
    /// interior extremum deeper than the local defect the reported residual allows
    /// (|ψ_i − mean of neighbours| = |r_i| / n_i ≤ ‖r‖ = residual · ‖b‖), plus 1e-5 for f32.
    /// Protects the consistency of the residual GS reports with the field it returns, which is
    /// what makes it usable as a reference at all.
    #[test]
    fn gauss_seidel_potential_obeys_the_maximum_principle_within_its_residual(w in world()) {
        let b = build_with_frontier(&w)?;
        let (gs, gs_stats) = solve_gs(&b, 1e-6);
        prop_assert!(stopped_by_its_rule(&gs_stats), "Gauss-Seidel did not converge: {gs_stats:?}");
        let allowed = 1e-5 + gs_stats.residual * rhs_norm(&b);
        check_maximum_principle(&b, &gs, "Gauss-Seidel", allowed)?;
    }

    /// **Multigrid agrees with Gauss-Seidel** (max |Δψ| ≤ 1e-4; GS to 6e-7, or ≤ 1e-6 at its
    /// f32 floor; MGPCG to 1e-6). Protects the claim that the production solver computes the
    /// same potential as the seed paper's reference solver.
    ///
    /// KNOWN TO FAIL (about 1 case in 1000), and the culprit is the *reference*: a relative
    /// residual of 6e-7 does not bound GS's error by 1e-4 on long, poorly connected domains
    /// (GS's remaining error is the smooth, slowest mode). Shrunk counterexample (6x13x1):
    ///
    /// ```text
    ///   ......
    ///   .#....
    ///   .#....
    ///   .#....
    ///   .#....
    ///   .#....
    ///   .#####
    ///   ......
    ///   V.....
    ///   ......
    ///   ??....
    ///   ......
    ///   ......
    /// ```
    ///
    /// GS converged (3364 sweeps, residual 5.96e-7) but is 1.05e-4 from the exact discrete
    /// solution; MGPCG (13 iterations, residual 3.4e-7) is within 3.4e-7 of it. So
    /// |Δψ| = 1.05e-4. See `multigrid_matches_the_exact_discrete_solution` for the check that
    /// holds, and `gauss_seidel_reference_is_not_accurate_to_1e_4` for the pinned case.
    #[test]
    #[ignore = "known to fail: the GS reference itself is 1e-4 off on long domains (see doc)"]
    fn multigrid_agrees_with_gauss_seidel(w in world()) {
        let b = build_with_frontier(&w)?;
        let (gs, gs_stats) = solve_gs(&b, 6e-7);
        if !gs_stats.converged {
            // The GS floor in f32: accept a reference that is nearly there, skip otherwise.
            prop_assume!(gs_stats.residual <= 1e-6);
        }
        let (mg, mg_stats) = solve_mg(&b, Method::Pcg);
        prop_assert!(stopped_by_its_rule(&mg_stats), "multigrid PCG did not converge: {mg_stats:?}");
        let (worst, at) = max_difference(&gs, &mg);
        prop_assert!(
            worst <= 1e-4,
            "max |Δψ| = {worst} at {:?} (GS {}, MG {}); GS {gs_stats:?}, MG {mg_stats:?}",
            b.dims().voxel(at),
            gs[at],
            mg[at]
        );
    }

    /// **Multigrid computes the exact discrete potential.** Protects the planner's dependence on
    /// the production solver (MGPCG on the host, plain V-cycles on the firmware) being *right*, not merely
    /// converged: at its default tolerance 1e-6 its ψ is within 1e-4 of the exact solution of
    /// the documented finite-volume system, computed independently in f64. (Largest error seen
    /// over 17 000 random domains: 3.4e-5; Gauss-Seidel converged to 6e-7 reached 1.8e-4.)
    #[test]
    fn multigrid_matches_the_exact_discrete_solution(w in world()) {
        let b = build_with_frontier(&w)?;
        let exact = solve_exact(&b);
        // MGPCG is the host's solver; plain V-cycles are the firmware's (no Krylov storage).
        // A residual of 1e-6 bounds the error only up to the condition number: on thin dead
        // ends V-cycles stopping near 5e-7 (or at their f32 floor) were up to 1.7e-4 off (worst
        // of ~2,000 random domains), where MGPCG, whose iterates overshoot, stays within 1e-4.
        // The firmware's V-cycles are held to 5e-4.
        for (method, tolerance, bound) in [(Method::Pcg, 1e-6, 1e-4), (Method::VCycle, 1e-6, 5e-4)] {
            let (mg, mg_stats) = solve_mg_to(&b, method, tolerance);
            prop_assert!(stopped_by_its_rule(&mg_stats), "{method:?} did not converge: {mg_stats:?}");
            let (worst, at) = exact
                .iter()
                .zip(&mg)
                .map(|(e, m)| (e - f64::from(*m)).abs())
                .enumerate()
                .fold((0.0f64, 0usize), |(w, wi), (i, d)| if d > w { (d, i) } else { (w, wi) });
            prop_assert!(
                worst <= bound,
                "{method:?}: max |ψ_mg − ψ_exact| = {worst:e} at {:?} (MG {}, exact {}); {mg_stats:?}",
                b.dims().voxel(at),
                mg[at],
                exact[at]
            );
        }
    }
}

/// The default planning field (`harmonic_core::field`): the same worlds with the vehicle
/// released from its Dirichlet value and κ = 0.3 per voxel (screening 0.09).
const SCREENING: f32 = 0.09;

/// The screened field of `w`'s domain: labels with the source released, and u by MGPCG.
fn screened(b: &Built) -> (Built, Vec<f32>, SolveStats) {
    let mut s = b.clone();
    harmonic_core::field::release_source(&mut s.labels);
    let (u, stats) = solve_mg_screened(&s, Method::Pcg, 1e-6, SCREENING);
    (s, u, stats)
}

proptest! {
    #![proptest_config(config(256))]

    /// **The screened field is what the module doc says it is:** multigrid (MGPCG and plain
    /// V-cycles, whose coarse levels carry the screening scaled by 4 per level) converges to
    /// the exact discrete solution of `(n + s)·u − Σ u_j = Σ frontier values`, computed
    /// independently in f64, within 5e-5 (the solver issue asks 1e-4). Stopped at a residual of
    /// 1e-6, V-cycles were up to 1.46e-5 off and MGPCG up to 1.02e-5 on rare small domains:
    /// held to 1e-5, this test failed in about one run in twenty (18 of 300 before 2026-12-02).
    #[test]
    fn screened_multigrid_matches_the_exact_discrete_solution(w in world()) {
        let b = build_with_frontier(&w)?;
        let mut s = b.clone();
        harmonic_core::field::release_source(&mut s.labels);
        let exact = solve_exact_screened(&s, f64::from(SCREENING));
        for method in [Method::Pcg, Method::VCycle] {
            let (u, stats) = solve_mg_screened(&s, method, 1e-6, SCREENING);
            prop_assert!(stopped_by_its_rule(&stats), "{method:?} did not converge: {stats:?}");
            let worst = exact.iter().zip(&u).map(|(e, m)| (e - f64::from(*m)).abs()).fold(0.0, f64::max);
            prop_assert!(worst <= 5e-5, "{method:?}: max |u − u_exact| = {worst:e}; {stats:?}");
        }
    }

    /// **The flat solver computes the same exact discrete potential:** converged at 1e-6, its
    /// ψ is within 1e-4 of the f64 solution (Laplace's equation, the bound the multigrid test
    /// above holds MGPCG to) and within 5e-5 for the screened field.
    #[cfg(feature = "flat")]
    #[test]
    fn the_flat_solver_matches_the_exact_discrete_solution(w in world()) {
        let b = build_with_frontier(&w)?;
        let mut s = b.clone();
        harmonic_core::field::release_source(&mut s.labels);
        for (problem, screening, bound) in [(&b, 0.0, 1e-4), (&s, SCREENING, 5e-5)] {
            let exact = solve_exact_screened(problem, f64::from(screening));
            let (u, stats) = solve_flat(problem, 1e-6, screening, None);
            prop_assert!(stopped_by_its_rule(&stats), "screening {screening}: did not converge: {stats:?}");
            let worst = exact.iter().zip(&u).map(|(e, m)| (e - f64::from(*m)).abs()).fold(0.0, f64::max);
            prop_assert!(worst <= bound, "screening {screening}: max |ψ − ψ_exact| = {worst:e}; {stats:?}");
        }
    }

    /// **The neighbour masks change nothing but the speed:** a solve lent them (the host's
    /// storage) gives every ψ to the bit of one without (the firmware's), with the same
    /// iterations and cell updates — MGPCG and V-cycles, Laplace's equation and the screened
    /// one.
    #[test]
    fn neighbour_masks_give_the_same_bits(w in world()) {
        let b = build_with_frontier(&w)?;
        let mut s = b.clone();
        harmonic_core::field::release_source(&mut s.labels);
        for (problem, screening) in [(&b, 0.0), (&s, SCREENING)] {
            for method in [Method::Pcg, Method::VCycle] {
                let (with, a) = solve_mg_lent(problem, method, 1e-6, screening, true, None);
                let (without, z) = solve_mg_lent(problem, method, 1e-6, screening, false, None);
                prop_assert_eq!((a.iterations, a.cell_updates), (z.iterations, z.cell_updates));
                let differ = with.iter().zip(&without).filter(|(p, q)| p.to_bits() != q.to_bits()).count();
                prop_assert_eq!(differ, 0, "{:?}, screening {}: {} values differ", method, screening, differ);
            }
        }
    }

    /// **No interior maximum:** every interior voxel of the screened field (where u is above
    /// the solve's accuracy) has an in-domain neighbour with a strictly larger u — the M-matrix
    /// argument of `harmonic_core::field`, checked on the solved field. This is what lets the
    /// streamline climb from anywhere to a frontier.
    #[test]
    fn screened_field_has_no_interior_maximum(w in world()) {
        let b = build_with_frontier(&w)?;
        let (s, u, stats) = screened(&b);
        prop_assert!(stopped_by_its_rule(&stats), "{stats:?}");
        let dims = s.dims();
        for i in 0..dims.len() {
            if s.labels[i] != Label::Interior || u[i] < 1e-4 {
                continue;
            }
            let (_, hi, count) = neighbour_range(&dims, &s.labels, &u, i);
            prop_assert!(count > 0);
            prop_assert!(hi > u[i], "u = {} at {:?} is a maximum (neighbours up to {hi})", u[i], dims.voxel(i));
        }
    }

    /// **Every streamline of the screened field ends on a frontier**, from the vehicle and
    /// from random points of random domain voxels — including the dead-end pockets where the
    /// seed's field is flat and its tracer rightly stalls (`every_streamline_ends_on_a_frontier`).
    #[test]
    fn screened_streamlines_from_any_domain_voxel_end_on_a_frontier(
        w in world(),
        picks in proptest::collection::vec((any::<Index>(), fractions()), 4),
    ) {
        let b = build_with_frontier(&w)?;
        let (s, u, stats) = screened(&b);
        prop_assert!(stopped_by_its_rule(&stats), "{stats:?}");
        let (dims, g) = (s.dims(), s.geometry);
        let field = Field { geometry: &g, labels: &s.labels, phi: &u };
        let domain: Vec<usize> = (0..dims.len()).filter(|&i| s.labels[i].in_domain()).collect();
        let mut starts = vec![g.center(s.vehicle)];
        for (pick, f) in &picks {
            starts.push(point_in(&g, dims.voxel(domain[pick.index(domain.len())]), *f));
        }
        for start in starts {
            let mut wps = Waypoints::new();
            match trace(&field, &start, &StreamlineParams::default(), &mut wps) {
                Ok(end) => check_trace_end(&s, &start, &end, &wps)?,
                Err(e) => prop_assert!(false, "trace from {start:?}: {e:?}"),
            }
        }
    }
}

/// Pinned counterexample of `gauss_seidel_potential_obeys_the_discrete_maximum_principle`: the
/// end of a dead-end corridor, (0,2,0), stays 1.2e-5 below its only neighbour after GS
/// converges to a relative residual of 1e-6 (the exact solution is flat there).
#[test]
#[ignore = "known to fail: pinned counterexample of the GS maximum principle to 1e-5"]
fn gauss_seidel_dead_end_is_a_local_minimum_beyond_1e_5() {
    let w = World::from_layers(&[
        &["......", "#.....", ".#....", ".#....", "#.....", "?..?.."],
        &["......", ".?...?", "#.....", ".#....", "......", "..V..."],
        &["......", "......", "......", ".#....", "...?.?", "......"],
        &["..?...", "......", ".?....", "#?....", "......", "......"],
    ]);
    let b = build(&w).unwrap();
    let (gs, s) = solve_gs(&b, 1e-6);
    assert!(s.converged, "{s:?}");
    let at = |x, y, z| gs[b.dims().linear(VoxelIndex::new(x, y, z))];
    let (end, entrance) = (at(0, 2, 0), at(0, 3, 0));
    assert!(
        entrance - end <= 1e-5,
        "ψ(0,2,0) = {end}, ψ(0,3,0) = {entrance}: local minimum by {}; {s:?}",
        entrance - end
    );
}

/// Largest |a − b| and where.
fn max_difference(a: &[f32], b: &[f32]) -> (f32, usize) {
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .enumerate()
        .fold(
            (0.0f32, 0usize),
            |(m, mi), (i, d)| if d > m { (d, i) } else { (m, mi) },
        )
}

/// Pinned counterexample of `multigrid_agrees_with_gauss_seidel`: the GS reference, converged
/// to 6e-7, is more than 1e-4 from the exact solution while multigrid is not. Passes once the
/// reference is accurate to 1e-4 (e.g. an absolute-error stop, or f64 accumulation).
#[test]
#[ignore = "known to fail: pinned counterexample of multigrid_agrees_with_gauss_seidel"]
fn gauss_seidel_reference_is_not_accurate_to_1e_4() {
    let w = World::from_layers(&[&[
        "......", ".#....", ".#....", ".#....", ".#....", ".#....", ".#####", "......", "V.....", "......",
        "??....", "......", "......",
    ]]);
    let b = build(&w).unwrap();
    let (gs, gs_stats) = solve_gs(&b, 6e-7);
    let (mg, mg_stats) = solve_mg(&b, Method::Pcg);
    assert!(gs_stats.converged && mg_stats.converged);
    let (worst, _) = max_difference(&gs, &mg);
    assert!(
        worst <= 1e-4,
        "max |Δψ| = {worst}; GS {gs_stats:?}, MG {mg_stats:?}"
    );
}

// ---------------------------------------------------------------------------------------------
// Streamline properties
// ---------------------------------------------------------------------------------------------

proptest! {
    #![proptest_config(config(512))]

    /// **Every streamline ends on a frontier** — from the vehicle (centre of the source voxel)
    /// and from random points in random interior voxels (the tracer documents "inside the
    /// source voxel or any domain voxel" as valid starts). Protects the planner's core promise:
    /// the path it hands the controller reaches a frontier voxel, the goal, through in-domain
    /// free space.
    ///
    /// KNOWN TO FAIL, also from the vehicle itself. The common cause is that an RK4 step is
    /// accepted into a voxel of *equal* ψ (`ψ(v) >= ψ(cell)`), while the discrete fallback needs
    /// a *strictly* higher one. Counterexamples:
    ///
    /// 1. From the vehicle (MGPCG field; the GS field happens to work), one layer:
    ///
    ///    ```text
    ///    .?.      frontiers (2,0) (1,1) (1,3); exactly, ψ(1,2) = ψ(0,2) = 17/18.
    ///    #..
    ///    ...      The tracer goes V → (2,3) → (1,2), which has two frontier face
    ///    #..      neighbours, then RK4 steps into the dead end (0,2) — equal ψ, accepted —
    ///    .?V      where no neighbour is strictly higher: `Err(Stalled)`, next to the goal.
    ///    ```
    ///
    ///    Any dead-end pocket behind a single articulation voxel has ψ constant (= that voxel's
    ///    value): a plateau the tracer may enter but not leave. Pinned as
    ///    `streamline_from_the_vehicle_does_not_stall_beside_a_frontier`. Rare from the vehicle
    ///    (about 1 in 5 000 tiny worlds, none seen in 27 000 of the 6–14 voxel ones).
    /// 2. From an interior voxel in a pocket whose only exit is the source (`?.V..`, start at
    ///    x = 4): ψ ≡ 0 there and no streamline exists; `Stalled`. Arguably not a bug.
    /// 3. From interior voxels nearly enclosed by frontiers: exact ψ is within 1e-8 of 1,
    ///    MGPCG puts some up to 2.6e-6 *above* 1 (GS never), so they are local maxima above
    ///    their frontier neighbours: `Stalled` beside the goal, or — when two such voxels have
    ///    equal ψ — RK4 ping-pongs between them forever (the per-voxel step budget resets on
    ///    every voxel change): `TooLong` after 50 000 steps. Pinned (4x7x6 world) as
    ///    `streamline_does_not_cycle_between_equal_psi_voxels`.
    ///
    /// About 3 % of random interior starts fail.
    #[test]
    #[ignore = "starts inside zero-flux dead ends (e.g. a 2x3x1 pocket behind the source) have constant psi and no ascending path: the tracer rightly reports Stalled. Planning only traces from the source, covered by streamline_from_the_vehicle_ends_on_a_frontier"]
    fn every_streamline_ends_on_a_frontier(
        w in world(),
        picks in proptest::collection::vec((any::<Index>(), fractions()), 3),
    ) {
        let b = build_with_frontier(&w)?;
        let (psi, s) = solve_mg(&b, Method::Pcg);
        prop_assert!(stopped_by_its_rule(&s), "multigrid PCG did not converge: {s:?}");
        let (dims, g) = (b.dims(), b.geometry);
        let field = Field { geometry: &g, labels: &b.labels, phi: &psi };
        let interior: Vec<usize> = (0..dims.len()).filter(|&i| b.labels[i] == Label::Interior).collect();
        let mut starts = vec![g.center(b.vehicle)];
        if !interior.is_empty() {
            for (pick, f) in &picks {
                starts.push(point_in(&g, dims.voxel(interior[pick.index(interior.len())]), *f));
            }
        }
        for start in starts {
            let mut wps = Waypoints::new();
            let end = trace(&field, &start, &StreamlineParams::default(), &mut wps);
            prop_assert!(end.is_ok(), "trace from {start:?} failed: {end:?}");
            check_trace_end(&b, &start, &end.unwrap(), &wps)?;
        }
    }

    /// **From the vehicle: always a frontier.** Protects what the explorer's plan step relies on
    /// (it traces from the vehicle's actual position, anywhere in the source voxel): the
    /// streamline ends in a frontier voxel and every waypoint lies in the domain. Strict ascent
    /// by more than rounding keeps the tracer out of flat dead-end pockets (4897 random worlds
    /// without a failure when first made strict).
    #[test]
    fn streamline_from_the_vehicle_ends_on_a_frontier(
        w in world(),
        in_source in proptest::collection::vec(fractions(), 3),
    ) {
        let b = build_with_frontier(&w)?;
        let (psi, s) = solve_mg(&b, Method::Pcg);
        prop_assert!(stopped_by_its_rule(&s), "multigrid PCG did not converge: {s:?}");
        let g = b.geometry;
        let field = Field { geometry: &g, labels: &b.labels, phi: &psi };
        let mut starts = vec![g.center(b.vehicle)];
        starts.extend(in_source.iter().map(|f| point_in(&g, b.vehicle, *f)));
        for start in starts {
            let mut wps = Waypoints::new();
            match trace(&field, &start, &StreamlineParams::default(), &mut wps) {
                Ok(end) => check_trace_end(&b, &start, &end, &wps)?,
                Err(e) => prop_assert!(false, "trace from the vehicle at {start:?}: {e:?}"),
            }
        }
    }

    /// **From any domain voxel: successful traces are well formed.** Protects callers that trace
    /// from arbitrary domain points (the documented contract): `trace` accepts every domain
    /// start, never panics, and whenever it returns `Ok` the path ends in a frontier voxel
    /// with every waypoint in the domain. Failures are reported as values; which ones occur
    /// (`Stalled`, and `TooLong` on MGPCG overshoot plateaus) is the known bug documented on
    /// `every_streamline_ends_on_a_frontier`.
    #[test]
    fn streamlines_from_any_domain_voxel_are_well_formed(
        w in world(),
        picks in proptest::collection::vec((any::<Index>(), fractions()), 4),
    ) {
        let b = build_with_frontier(&w)?;
        let (psi, s) = solve_mg(&b, Method::Pcg);
        prop_assert!(stopped_by_its_rule(&s), "multigrid PCG did not converge: {s:?}");
        let (dims, g) = (b.dims(), b.geometry);
        let field = Field { geometry: &g, labels: &b.labels, phi: &psi };
        let domain: Vec<usize> = (0..dims.len()).filter(|&i| b.labels[i].in_domain()).collect();
        for (pick, f) in &picks {
            let start = point_in(&g, dims.voxel(domain[pick.index(domain.len())]), *f);
            let mut wps = Waypoints::new();
            match trace(&field, &start, &StreamlineParams::default(), &mut wps) {
                Ok(end) => check_trace_end(&b, &start, &end, &wps)?,
                Err(StreamlineError::Stalled | StreamlineError::TooLong) => {}
                Err(e) => prop_assert!(false, "trace from domain point {start:?}: {e:?}"),
            }
        }
    }
}

/// Traces from `start` (grid coordinates; default: the vehicle voxel's centre) over the MGPCG
/// solution of `w`.
fn trace_mg(
    w: &World,
    start: Option<Vector3<f32>>,
) -> (Built, Result<VoxelIndex, StreamlineError>, Waypoints) {
    let b = build(w).unwrap();
    let (psi, s) = solve_mg(&b, Method::Pcg);
    assert!(s.converged, "{s:?}");
    let g = b.geometry;
    let field = Field {
        geometry: &g,
        labels: &b.labels,
        phi: &psi,
    };
    let mut wps = Waypoints::new();
    let from = start.map_or_else(|| g.center(b.vehicle), |p| g.from_grid(&p));
    let end = trace(&field, &from, &StreamlineParams::default(), &mut wps).map(|e| e.frontier);
    (b, end, wps)
}

/// Pinned counterexample 1 of `every_streamline_ends_on_a_frontier`: the streamline *from the
/// vehicle* stalls in a one-voxel dead end next to a voxel with two frontier neighbours.
#[test]
fn streamline_from_the_vehicle_does_not_stall_beside_a_frontier() {
    let w = World::from_layers(&[&[".?.", "#..", "...", "#..", ".?V"]]);
    let (b, end, wps) = trace_mg(&w, None);
    let end = end.unwrap_or_else(|e| panic!("{e:?}; waypoints {wps:?}"));
    assert_eq!(b.labels[b.dims().linear(end)], Label::Frontier);
}

/// Pinned counterexample 3 of `every_streamline_ends_on_a_frontier`: MGPCG leaves (2,2,2) and
/// (2,3,2) — which have two and five frontier face neighbours — both at ψ = 1 + 1 ulp, above
/// every frontier; from a point in (2,2,2), RK4 moves back and forth between the two until
/// `TooLong` (from the voxel centre it reports `Stalled` instead).
#[test]
fn streamline_does_not_cycle_between_equal_psi_voxels() {
    let w = World::from_layers(&[
        &["..#?", "...?", ".?.#", "....", "..?.", "....", "...."],
        &["....", "....", "....", "....", "..?.", "....", "...."],
        &["..#.", "?...", "....", "?...", "....", "....", ".?.."],
        &["..#.", "....", ".?..", "....", "..??", "....", "...."],
        &["....", ".#?.", "..??", "?..#", "....", "?...", "..V?"],
        &["....", ".#..", "....", "....", "....", "....", ".?.?"],
    ]);
    let (b, end, _) = trace_mg(&w, Some(Vector3::new(2.5464008, 2.3625088, 2.1170087)));
    let end = end.unwrap_or_else(|e| panic!("{e:?}"));
    assert_eq!(b.labels[b.dims().linear(end)], Label::Frontier);
}

// ---------------------------------------------------------------------------------------------
// Ray traversal
// ---------------------------------------------------------------------------------------------

/// A coordinate: mostly ordinary (around and beyond the grid), sometimes hostile.
fn coordinate() -> impl Strategy<Value = f32> {
    prop_oneof![
        8 => -3.0f32..6.0,
        1 => prop_oneof![
            Just(f32::NAN),
            Just(f32::INFINITY),
            Just(f32::NEG_INFINITY),
            Just(f32::MAX),
            Just(f32::MIN),
            Just(f32::MIN_POSITIVE),
            Just(-0.0f32),
            -1e30f32..1e30,
            -1e7f32..1e7,
        ],
    ]
}

fn point() -> impl Strategy<Value = Point3<f32>> {
    (coordinate(), coordinate(), coordinate()).prop_map(|(x, y, z)| Point3::new(x, y, z))
}

/// A random grid geometry: 1–20 voxels per axis, a few resolutions, an offset origin.
fn geometry() -> impl Strategy<Value = MapGeometry> {
    (
        (1usize..=20, 1usize..=20, 1usize..=20),
        prop_oneof![Just(0.05f32), Just(0.1), Just(0.25), Just(1.0), 0.01f32..2.0],
        (-2.0f32..2.0, -2.0f32..2.0, -2.0f32..2.0),
    )
        .prop_map(|((nx, ny, nz), res, (ox, oy, oz))| {
            MapGeometry::new(Dims::new(nx, ny, nz).unwrap(), Point3::new(ox, oy, oz), res).unwrap()
        })
}

/// Runs `traverse` and records the visited voxels, stopping after `stop_after` if given.
fn visited(
    g: &MapGeometry,
    a: &Point3<f32>,
    b: &Point3<f32>,
    stop_after: Option<u32>,
) -> (u32, Vec<VoxelIndex>) {
    let mut seen: Vec<VoxelIndex> = Vec::new();
    let count = traverse(g, a, b, |v| {
        seen.push(v);
        stop_after.is_none_or(|k| seen.len() < k as usize)
    });
    (count, seen)
}

proptest! {
    #![proptest_config(config(4096))]

    /// **Ray traversal is safe on any segment.** Protects depth integration, which feeds every
    /// camera ray — including rays from corrupt poses or depth, with NaN, infinite or huge
    /// coordinates — through `traverse`: it must never panic, must only ever hand out voxels
    /// inside the grid (the caller indexes map storage with them), must visit a face-connected
    /// sequence without repeats (no free voxel between two marked ones is skipped, none is
    /// updated twice), must honour an early stop and return the number of voxels it visited.
    /// When the start point is inside the grid (and the segment is not so long that its
    /// direction overflows f32), the first voxel is the start point's own.
    #[test]
    fn traverse_visits_a_face_connected_in_grid_sequence(
        g in geometry(),
        a in point(),
        b in point(),
        stop_after in prop::option::of(1u32..40),
    ) {
        let dims = g.dims();
        let (count, seen) = visited(&g, &a, &b, stop_after);
        prop_assert_eq!(count as usize, seen.len());
        if let Some(k) = stop_after {
            prop_assert!(seen.len() <= k as usize, "kept going after visit returned false");
        }
        prop_assert!(seen.len() <= dims.nx() + dims.ny() + dims.nz() + 1);
        for v in &seen {
            prop_assert!(
                usize::from(v.x) < dims.nx() && usize::from(v.y) < dims.ny() && usize::from(v.z) < dims.nz(),
                "{v:?} outside {dims:?}"
            );
        }
        for pair in seen.windows(2) {
            let (p, q) = (pair[0], pair[1]);
            let steps = [p.x.abs_diff(q.x), p.y.abs_diff(q.y), p.z.abs_diff(q.z)];
            prop_assert!(
                steps.iter().sum::<u16>() == 1,
                "{p:?} → {q:?} is not a face step (segment {a:?} → {b:?})"
            );
        }
        let mut sorted: Vec<_> = seen.iter().map(|v| dims.linear(*v)).collect();
        sorted.sort_unstable();
        sorted.dedup();
        prop_assert_eq!(sorted.len(), seen.len(), "a voxel was visited twice");
        let moderate = a.coords.iter().chain(b.coords.iter()).all(|c| c.abs() < 1e6);
        if let (true, Some(va)) = (moderate, g.voxel_at(&a)) {
            prop_assert_eq!(seen.first().copied(), Some(va), "does not start at the voxel of a");
        }
    }

    /// **Traversal ends in the voxel of `b`** when `b` is inside the grid, as `traverse`'s doc
    /// promises ("ending with the voxel of b"), and does not run past it. Protects callers
    /// that take the last visited voxel as the endpoint's (a ray's free space must stop there).
    ///
    /// KNOWN TO FAIL, at voxel faces only. Harmless for `integrate` today: it finds the endpoint
    /// with `voxel_at` and hits it separately, and stops the walk when it meets it: a walk that
    /// ends one voxel short marks nothing wrong, one that would run past is cut off (except
    /// for no-return rays, which have no endpoint: one voxel beyond max range, by rounding).
    /// Counterexamples: on a 4x4x1 grid, resolution 1, origin 0, `a = (0.25, 0, 0.5)`,
    /// `b = (0, 1, 0.5)` visits only (0,0,0) — `b` is on the face y = 1
    /// (voxel (0,1,0)) *and* on the grid edge x = 0, the x and y crossings tie at t = 1, x wins
    /// and leaves the grid (pinned as `traverse_reaches_b_on_the_grid_edge`). With random
    /// geometries, f32 rounding at faces: `b` at grid y = 14.999999 (voxel 14) visited 14 then
    /// 15; `b` exactly on an interior edge ended one diagonal step short of it.
    #[test]
    #[ignore = "known to fail: ties/rounding at voxel faces (see doc)"]
    fn traverse_ends_in_the_voxel_of_b(
        g in geometry(),
        fa in (0.0f32..1.0, 0.0f32..1.0, 0.0f32..1.0),
        fb in (0.0f32..1.0, 0.0f32..1.0, 0.0f32..1.0),
    ) {
        let d = g.dims();
        let ext = Vector3::new(d.nx() as f32, d.ny() as f32, d.nz() as f32);
        // Quantise to quarter voxels half the time: ends on faces, edges and corners.
        let place = |f: (f32, f32, f32)| {
            let q = Vector3::new(f.0, f.1, f.2).component_mul(&ext);
            g.from_grid(&if f.0 < 0.5 { q.map(|c| (c * 4.0).floor() / 4.0) } else { q })
        };
        let (a, b) = (place(fa), place(fb));
        let (_, seen) = visited(&g, &a, &b, None);
        if let Some(vb) = g.voxel_at(&b) {
            prop_assert_eq!(seen.last().copied(), Some(vb), "{:?} → {:?}: {:?}", a, b, seen);
        }
    }
}

/// Pinned counterexample of `traverse_ends_in_the_voxel_of_b`: the segment ends exactly on the
/// face y = 1 at the grid edge x = 0; the tied x crossing is taken first and leaves the grid, so
/// the voxel of `b`, (0,1,0), is never visited.
#[test]
#[ignore = "known to fail: tie at a face on the grid edge"]
fn traverse_reaches_b_on_the_grid_edge() {
    let g = MapGeometry::new(Dims::new(4, 4, 1).unwrap(), Point3::origin(), 1.0).unwrap();
    let (a, b) = (Point3::new(0.25, 0.0, 0.5), Point3::new(0.0, 1.0, 0.5));
    let (_, seen) = visited(&g, &a, &b, None);
    assert_eq!(seen.last().copied(), g.voxel_at(&b), "visited {seen:?}");
}
