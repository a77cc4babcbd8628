//! Late in an exploration the frontier is a small patch far away behind doors, and the walls
//! are long: the kind of world on which the solver issue found a solve reporting `converged`
//! while φ was 1.8e-4 off. Rooms, doors and furniture (64 × 64 × 32 voxels, three layouts,
//! 82–87k unknowns; and 96 × 96 × 48, two layouts, 186–204k; 110 frontier voxels each) solved
//! by the core's multigrid in f32 and compared with an f64 conjugate-gradient solve of the same
//! discrete system.

mod common;

use harmonic_core::domain::Label;
use harmonic_core::map::{Dims, VoxelIndex};
use harmonic_core::solve::multigrid::{scratch_size, Method, Multigrid, MultigridStorage};
use harmonic_core::solve::{Bf16, SolveParams, SolveStats, Stop};

/// The grid of the firmware and of the solver benchmark.
const SMALL: [usize; 3] = [64, 64, 32];
/// A larger house.
const LARGE: [usize; 3] = [96, 96, 48];

/// Rooms `room` voxels across, off each other through doors, boxes for furniture, a frontier
/// window in the far room. `variant` moves the doors and furniture.
fn rooms_of([nx, ny, nz]: [usize; 3], variant: usize, room: usize) -> (Dims, Vec<Label>, VoxelIndex) {
    let dims = Dims::new(nx, ny, nz).unwrap();
    let mut labels = vec![Label::Outside; dims.len()];
    let walls: Vec<usize> = (1..).map(|k| k * room).take_while(|w| *w < nx - 2).collect();
    let ceiling = 26;
    for (i, l) in labels.iter_mut().enumerate() {
        let v = dims.voxel(i);
        let (x, y, z) = (usize::from(v.x), usize::from(v.y), usize::from(v.z));
        let shell = x == 0 || y == 0 || z == 0 || x == nx - 1 || y == ny - 1 || z >= ceiling;
        let mut wall = walls.contains(&x) || walls.contains(&y);
        // Doors: 3 wide, 9 high, placed per room side by the variant.
        let door = |along: usize, across: usize| {
            let room_i = across / (room + 1);
            let centre = 2 + (room_i * 7 + variant * 5) % (room - 6);
            (centre..centre + 3).contains(&(along % room)) && (1..=9).contains(&z)
        };
        if walls.contains(&x) && door(y, x) || walls.contains(&y) && door(x, y) {
            wall = false;
        }
        // Furniture: a table (slab on the floor's side) and a cabinet per room.
        let (rx, ry) = (x % room, y % room);
        let table = (4..14).contains(&rx) && (5..11).contains(&ry) && (7..9).contains(&z);
        let legs = [4usize, 13].contains(&rx) && [5usize, 10].contains(&ry) && z < 7;
        let cabinet = (15 + variant % 3..19 + variant % 3).contains(&rx) && (2..6).contains(&ry) && z < 18;
        if !(shell || wall || table || legs || cabinet) {
            *l = Label::Interior;
        }
    }
    // The frontier: a window in the far room's outer wall, 10 × 11 voxels.
    for y in (ny as u16 - 14)..(ny as u16 - 4) {
        for z in 8..19 {
            labels[dims.linear(VoxelIndex::new((nx - 1) as u16, y, z))] = Label::Frontier;
        }
    }
    let source = VoxelIndex::new(10, 12, 12);
    labels[dims.linear(source)] = Label::Source;
    // As the domain build does: only the source's component (through interior voxels) takes
    // part; a room that furniture or a missing door cuts off is outside.
    common::keep_component(&dims, &mut labels, dims.linear(source));
    (dims, labels, source)
}

/// The discrete system in f64 by conjugate gradients to a relative residual of 1e-13.
fn exact(dims: &Dims, labels: &[Label]) -> Vec<f64> {
    common::exact_solution(dims, labels, 0.0)
}

fn solve(dims: Dims, labels: &[Label], method: Method, max_iterations: u32) -> (Vec<f32>, SolveStats) {
    solve_with(
        dims,
        labels,
        Setup::Host(method),
        max_iterations,
        0.0,
        f32::INFINITY,
    )
}

/// How the solver is set up.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Setup {
    /// The host's: `f32` coarse levels with face conductances, MGPCG storage lent.
    Host(Method),
    /// The firmware's: plain V-cycles, bfloat16 coarse levels, no face conductances, no
    /// Krylov vectors (`firmware/src/app.rs`).
    Firmware,
    /// The firmware's operator with `f32` coarse levels: what the bfloat16 storage changes.
    FirmwareF32,
}

fn solve_with(
    dims: Dims,
    labels: &[Label],
    setup: Setup,
    max_iterations: u32,
    screening: f32,
    max_error: f32,
) -> (Vec<f32>, SolveStats) {
    let s = scratch_size(&dims);
    let host = matches!(setup, Setup::Host(_));
    let (mut values, mut halves, mut clabels, mut faces, mut krylov, mut masks) = (
        vec![0.0f32; if setup == Setup::Firmware { 0 } else { s.values }],
        vec![Bf16::ZERO; if setup == Setup::Firmware { s.values } else { 0 }],
        vec![Label::Outside; s.labels],
        vec![[0u8; 4]; if host { s.faces } else { 0 }],
        vec![0.0f32; if host { s.krylov } else { 0 }],
        vec![0u8; if host { s.masks } else { 0 }],
    );
    let storage = MultigridStorage {
        values: if setup == Setup::Firmware {
            halves.as_mut_slice().into()
        } else {
            values.as_mut_slice().into()
        },
        labels: &mut clabels,
        faces: &mut faces,
        krylov: &mut krylov,
        masks: &mut masks,
    };
    let method = match setup {
        Setup::Host(m) => m,
        _ => Method::VCycle,
    };
    let mut mg = Multigrid::new(dims, storage).unwrap();
    let mut psi = vec![0.0f32; dims.len()];
    let params = SolveParams {
        tolerance: 1e-6,
        max_iterations,
        warm_start: false,
        screening,
        max_error,
    };
    let stats = mg.solve(labels, &mut psi, &params, method).unwrap();
    (psi, stats)
}

fn max_error(psi: &[f32], exact: &[f64]) -> f64 {
    psi.iter()
        .zip(exact)
        .map(|(&p, &e)| (f64::from(p) - e).abs())
        .fold(0.0, f64::max)
}

/// The layouts: rooms 21, 16 and 13 voxels across, each with its own doors and furniture.
const LAYOUTS: [(usize, usize); 3] = [(0, 21), (1, 16), (2, 13)];

/// Whether a solve stopped by its own rule (the tolerance, or the f32 rounding floor where that
/// lies above it), not at a cap, and reported `converged` exactly when its residual met the
/// tolerance of 1e-6 (on these rooms Laplace's floor is about 4e-6: the solves stop there and
/// are honestly not converged).
fn stopped_by_its_rule(stats: &SolveStats) -> bool {
    matches!(stats.stop, Stop::Met | Stop::Floor) && stats.converged == (stats.residual <= 1e-6)
}

/// Solves each layout of `size` with both of the core's multigrid solvers and checks that
/// each stops by its own rule, reports `converged` honestly and lies within `bound` of the f64
/// solution everywhere.
fn assert_converged_within(size: [usize; 3], layouts: &[(usize, usize)], bound: f64) {
    for &(variant, room) in layouts {
        let (dims, labels, _) = rooms_of(size, variant, room);
        let frontier = labels.iter().filter(|l| **l == Label::Frontier).count();
        assert!(
            frontier <= 120,
            "{frontier} frontier voxels: not a late-exploration problem"
        );
        let ex = exact(&dims, &labels);
        for method in [Method::Pcg, Method::VCycle] {
            let (psi, stats) = solve(dims, &labels, method, 1_000_000);
            let err = max_error(&psi, &ex);
            assert!(
                stopped_by_its_rule(&stats),
                "{size:?}, rooms {room}, {method:?}: {stats:?}"
            );
            assert!(
                err <= bound,
                "{size:?}, rooms {room}, {method:?}: max error {err:.3e}, {stats:?}"
            );
        }
    }
}

/// Both of the core's multigrid solvers — MGPCG (the host's) and plain V-cycles (the
/// firmware's) — stop by their own rule (at the rounding floor, about 4e-6 here, above the
/// tolerance of 1e-6: not converged) and are then within 2e-5 of the f64 solution everywhere
/// (the solver issue's bar is 1e-4). V-cycles that stopped at the f32 rounding floor were
/// 5.6e-5 to 8.6e-5 off on these layouts (1.1e-4 on an earlier door layout) before they learned
/// to go on while the residual falls.
#[test]
fn converged_solves_match_the_f64_solution_on_rooms_with_a_small_far_frontier() {
    assert_converged_within(SMALL, &LAYOUTS, 2e-5);
}

/// The same on a 96 × 96 × 48 house (186–204k unknowns) to the solver issue's bar of 1e-4:
/// measured 2.8e-5 and 3.3e-5 (MGPCG), 5.0e-5 and 4.1e-5 (V-cycles, 421 and 185 cycles).
#[test]
fn converged_solves_match_the_f64_solution_in_a_larger_house() {
    assert_converged_within(LARGE, &[(3, 31), (2, 13)], 1e-4);
}

/// A solve stopped by its iteration cap before its own rule says "done" reports
/// `converged: false`, even where the residual already lies below the rounding floor.
#[test]
fn a_solve_stopped_at_the_cap_is_not_converged() {
    let (dims, labels, _) = rooms_of(SMALL, 0, 21);
    let ex = exact(&dims, &labels);
    for (method, cap) in [(Method::VCycle, 5), (Method::VCycle, 150), (Method::Pcg, 5)] {
        let (psi, stats) = solve(dims, &labels, method, cap);
        assert_eq!(stats.iterations, cap, "{method:?}: {stats:?}");
        assert!(
            !stats.converged,
            "{method:?} at cap {cap}: {stats:?}, error {:.3e}",
            max_error(&psi, &ex)
        );
    }
}

/// Calls `f(room, dims, labels, s, exact)` for each 64 × 64 × 32 layout and field: Laplace's
/// equation, and the screened field (the vehicle an ordinary voxel) with s = κ²h² = 1e-4 and
/// 0.09; `exact` is the f64 solution.
fn for_each_field(mut f: impl FnMut(usize, Dims, &[Label], f32, &[f64])) {
    for &(variant, room) in &LAYOUTS {
        let (dims, laplace, _) = rooms_of(SMALL, variant, room);
        let mut screened = laplace.clone();
        for l in screened.iter_mut().filter(|l| **l == Label::Source) {
            *l = Label::Interior;
        }
        for (labels, s) in [(&laplace, 0.0f32), (&screened, 1e-4), (&screened, 0.09)] {
            let ex = common::exact_solution(&dims, labels, f64::from(s));
            f(room, dims, labels, s, &ex);
        }
    }
}

/// The error estimate a solve reports ([`SolveStats::error_estimate`]) against the true error,
/// on the three 64 × 64 × 32 layouts, for Laplace's equation and two screened fields (κ as the
/// explorer lowers it late in an exploration, s = κ²h² = 1e-4, and the default 0.33 m decay
/// length at 0.1 m voxels, s = 0.09), for the host's two multigrid solvers and the firmware's
/// (V-cycles, label-only coarse operator, bfloat16 coarse levels), each stopped after 6, 20
/// and 80 steps and at its own stop. A user relies on it not being optimistic on such late
/// problems: it is never below the true error here (a bound for the screened field, a measured
/// safe estimate for Laplace's; the estimate before issue 60 was as low as 0.7× the true error
/// here and 0.15× on the rooms). It is cautious by design: up to some thousands of
/// times the true error where the screening is weak (s = 1e-4) or the solve sits at the f32
/// floor, so only a sanity ceiling (10⁴ times the true error or 1e-2) is checked.
#[test]
fn the_error_estimate_bounds_the_true_error() {
    for_each_field(|room, dims, labels, s, ex| {
        for setup in [
            Setup::Host(Method::VCycle),
            Setup::Host(Method::Pcg),
            Setup::Firmware,
        ] {
            for cap in [6u32, 20, 80, 1_000_000] {
                let (psi, st) = solve_with(dims, labels, setup, cap, s, f32::INFINITY);
                let err = max_error(&psi, ex);
                let est = f64::from(st.error_estimate.expect("estimated"));
                let case = format!("rooms {room}, s {s}, {setup:?}, cap {cap}: error {err:.3e}, {st:?}");
                assert!(est >= err, "optimistic: {case}");
                assert!(est <= 1e4 * err.max(1e-6), "useless: {case}");
                if st.iterations < cap {
                    break;
                }
            }
        }
    });
}

/// With an error target (`SolveParams::max_error`) a solve goes on until its estimate meets
/// it, and `converged` says whether both the tolerance and the target were met: on the layout
/// where the residual rule alone left plain V-cycles 8.5e-6 off (and an earlier rule 1.1e-4
/// off), with a tolerance above the rounding floor (5e-6) and a target of 1e-4, a converged
/// solve's estimate meets the target and bounds its true error. A target the cap does not let
/// it reach is reported as not converged.
#[test]
fn an_error_target_is_met_or_reported_missed() {
    let (dims, labels, _) = rooms_of(SMALL, 0, 21);
    let ex = exact(&dims, &labels);
    for method in [Method::VCycle, Method::Pcg] {
        let (psi, st) = solve_to(dims, &labels, method, 5_000, 5e-6, 1e-4);
        let err = max_error(&psi, &ex);
        println!("{method:?}: error {err:.3e}, {st:?}");
        let met = st.residual <= 5e-6 && st.error_estimate.is_some_and(|e| e <= 1e-4);
        assert_eq!(st.converged, met, "{method:?}: {st:?}");
        if let Some(e) = st.error_estimate {
            assert!(err <= f64::from(e), "{method:?}: error {err:.3e}, {st:?}");
        }
        let (_, capped) = solve_to(dims, &labels, method, 8, 5e-6, 1e-6);
        assert!(
            !capped.converged && capped.stop == Stop::Cap,
            "{method:?} at 8 steps: {capped:?}"
        );
    }
}

/// [`solve_with`] on the host's storage with a tolerance of `tolerance`.
fn solve_to(
    dims: Dims,
    labels: &[Label],
    method: Method,
    max_iterations: u32,
    tolerance: f32,
    max_error: f32,
) -> (Vec<f32>, SolveStats) {
    let s = scratch_size(&dims);
    let (mut values, mut clabels, mut faces, mut krylov, mut masks) = (
        vec![0.0f32; s.values],
        vec![Label::Outside; s.labels],
        vec![[0u8; 4]; s.faces],
        vec![0.0f32; s.krylov],
        vec![0u8; s.masks],
    );
    let mut mg = Multigrid::new(
        dims,
        MultigridStorage {
            values: values.as_mut_slice().into(),
            labels: &mut clabels,
            faces: &mut faces,
            krylov: &mut krylov,
            masks: &mut masks,
        },
    )
    .unwrap();
    let mut psi = vec![0.0f32; dims.len()];
    let params = SolveParams {
        tolerance,
        max_iterations,
        warm_start: false,
        screening: 0.0,
        max_error,
    };
    let stats = mg.solve(labels, &mut psi, &params, method).unwrap();
    (psi, stats)
}

/// The firmware's solver — plain V-cycles on the label-only coarse operator, with its coarse
/// levels stored as bfloat16 to fit the MCU's RAM — converges like the same solver with `f32`
/// coarse levels: on each layout and field (Laplace, screened with s = 1e-4 and 0.09) it stops
/// by its own rule within 10 % of the cycles and within 2e-5 of the f64 solution (measured: 16
/// to 347 cycles, against 16 to 356 in `f32`; errors 5.3e-7 to 1.7e-5, against 5.3e-7 to
/// 1.3e-5). Coarse levels only carry corrections recomputed every cycle from the `f32` fine
/// residual, so their rounding cannot accumulate.
#[test]
fn bfloat16_coarse_levels_converge_like_f32_ones() {
    for_each_field(|room, dims, labels, s, ex| {
        let (_, full) = solve_with(dims, labels, Setup::FirmwareF32, 100_000, s, f32::INFINITY);
        let (psi, half) = solve_with(dims, labels, Setup::Firmware, 100_000, s, f32::INFINITY);
        let err = max_error(&psi, ex);
        let case = format!("rooms {room}, s {s}: error {err:.3e}, bf16 {half:?}, f32 {full:?}");
        assert!(stopped_by_its_rule(&half) && stopped_by_its_rule(&full), "{case}");
        assert!(
            f64::from(half.iterations) <= 1.1 * f64::from(full.iterations) + 2.0,
            "{case}"
        );
        assert!(err <= 2e-5, "{case}");
    });
}

/// The host's flat solver ([`harmonic_core::solve::flat`]) on the same rooms: converged at
/// 1e-6, within 5e-5 of the f64 solution for Laplace's equation, which it solves to its f32
/// rounding floor (the bar is 1e-4), and within 2e-5 for the screened field.
#[cfg(feature = "flat")]
#[test]
fn the_flat_solver_matches_the_f64_solution_on_rooms_with_a_small_far_frontier() {
    use harmonic_core::solve::flat::{flat_scratch_len, Flat};
    for &(variant, room) in &LAYOUTS {
        let (dims, labels, _) = rooms_of(SMALL, variant, room);
        let mut released = labels.clone();
        harmonic_core::field::release_source(&mut released);
        let mut values = vec![0.0f32; flat_scratch_len(&dims)];
        let mut flat = Flat::new(dims, &mut values).unwrap();
        for (labels, screening, bound) in [(&labels, 0.0f32, 5e-5), (&released, 0.0918, 2e-5)] {
            let ex = common::exact_solution(&dims, labels, f64::from(screening));
            let mut psi = vec![0.0f32; dims.len()];
            let params = SolveParams {
                tolerance: 1e-6,
                max_iterations: 1_000,
                warm_start: false,
                screening,
                max_error: f32::INFINITY,
            };
            let stats = flat.solve(labels, &mut psi, &params).unwrap();
            let err = max_error(&psi, &ex);
            assert!(
                stopped_by_its_rule(&stats),
                "rooms {room}, s = {screening}: {stats:?}"
            );
            eprintln!(
                "rooms {room}, s = {screening}: max error {err:.3e}, {} iterations",
                stats.iterations
            );
            assert!(
                err <= bound,
                "rooms {room}, s = {screening}: max error {err:.3e}, {stats:?}"
            );
        }
    }
}
