//! Honest numerics (issue 60): what a solve reports about itself holds against an f64 solve of
//! the same discrete system, on random worlds of the kind that fooled it — long walls with
//! narrow doors and only a few frontier voxels, where the smallest eigenvalue is small, the
//! error decays slowly and a small residual says little.
//!
//! For every solver the core offers (MGPCG, plain V-cycles with the host's and with the
//! firmware's storage, the flat solver, Gauss-Seidel, and a re-solve in boxes), on both fields
//! (the seed's Laplace field and the default screened one), with random tolerances, error
//! targets and iteration caps:
//!
//! - `converged` is true exactly when the reported residual meets the tolerance and, where an
//!   error target is set, the error estimate meets it (so it is false whenever either is
//!   missed, whatever stopped the solve);
//! - the residual of the returned ψ, recomputed from outside, agrees with the report;
//! - whenever `converged` is true and an estimate is reported, the true largest error against
//!   the f64 solution is at or below it.
//!
//! Run in release or the test profile (opt-level 3): 40 cases from a fixed seed, about 15 s on
//! a loaded two-core machine. `HONEST_CASES=n` runs `n` cases instead, `HONEST_SEED=random` new
//! worlds each run (1 000 random cases on 2026-12-08 found a Laplace PCG solve at 1.6 × its
//! estimate behind a one-voxel door: the estimate is not yet a bound there); `HONEST_REPORT=1` prints the ratio of
//! true error to estimate of every solve instead of asserting the bound (how the safety factor
//! of [`SolveStats::error_estimate`] was measured: 100 cases, largest ratio of a converged
//! solve 0.58 for Laplace's equation, 0.91 for the screened field).

mod common;

use harmonic_core::domain::Label;
use harmonic_core::field::{release_source, ScreenedParams};
use harmonic_core::map::{Dims, VoxelIndex};
#[cfg(feature = "flat")]
use harmonic_core::solve::flat::{flat_scratch_len, Flat};
use harmonic_core::solve::local::{resolve_near, Local, LocalParams, LocalScratch, WithMethod};
use harmonic_core::solve::multigrid::{scratch_size, Method, Multigrid, MultigridStorage};
use harmonic_core::solve::{gauss_seidel, screened_residual, Bf16, SolveParams, SolveStats, Stop};
use proptest::prelude::*;

/// A wall across the grid: along x (at `y = at`) or along y (at `x = at`), the full height,
/// with doors `(start, width, height)`.
#[derive(Debug, Clone)]
struct Wall {
    along_x: bool,
    at: usize,
    doors: Vec<(usize, usize, usize)>,
}

/// A world: grid size, walls, the unknown window on the `x = nx − 1` shell (its `y`, `z` and
/// size) and the vehicle.
#[derive(Debug, Clone)]
struct World {
    n: [usize; 3],
    walls: Vec<Wall>,
    window: (usize, usize, usize, usize),
    vehicle: [usize; 3],
}

fn world() -> impl Strategy<Value = World> {
    (16usize..=40, 16usize..=40, 6usize..=14).prop_flat_map(|(nx, ny, nz)| {
        let door = move |len: usize| (1..len - 1, 1usize..=3, 1..nz - 1);
        let wall = move || {
            any::<bool>().prop_flat_map(move |along_x| {
                let (across, len) = if along_x { (ny, nx) } else { (nx, ny) };
                (
                    Just(along_x),
                    2..across - 2,
                    prop::collection::vec(door(len), 1..=2),
                )
                    .prop_map(|(along_x, at, doors)| Wall { along_x, at, doors })
            })
        };
        (
            Just([nx, ny, nz]),
            prop::collection::vec(wall(), 1..=4),
            (1..ny - 1, 1..nz - 1, 1usize..=3, 1usize..=3),
            (1..nx - 1, 1..ny - 1, 1..nz - 1),
        )
            .prop_map(|(n, walls, window, (x, y, z))| World {
                n,
                walls,
                window,
                vehicle: [x, y, z],
            })
    })
}

/// The Laplace problem's labels (vehicle the source) and the vehicle's index, or `None` where
/// the vehicle's component has no frontier voxel or the vehicle is one. As the domain build
/// does: free voxels next to unknown space are frontier, and only the vehicle's component
/// (through interior voxels) takes part.
fn labels_of(w: &World) -> Option<(Dims, Vec<Label>)> {
    let [nx, ny, nz] = w.n;
    let dims = Dims::new(nx, ny, nz).ok()?;
    let at = |x: usize, y: usize, z: usize| x + nx * (y + ny * z);
    // 0 free, 1 occupied, 2 unknown.
    let mut cell = vec![0u8; dims.len()];
    for z in 0..nz {
        for y in 0..ny {
            for x in 0..nx {
                if x == 0 || y == 0 || z == 0 || x == nx - 1 || y == ny - 1 || z == nz - 1 {
                    cell[at(x, y, z)] = 1;
                }
            }
        }
    }
    for wall in &w.walls {
        let len = if wall.along_x { nx } else { ny };
        for s in 0..len {
            for z in 0..nz {
                let open = wall
                    .doors
                    .iter()
                    .any(|&(d, width, height)| (d..d + width).contains(&s) && (1..=height).contains(&z));
                let i = if wall.along_x {
                    at(s, wall.at, z)
                } else {
                    at(wall.at, s, z)
                };
                if !open {
                    cell[i] = 1;
                }
            }
        }
    }
    let (wy, wz, sy, sz) = w.window;
    for y in wy..(wy + sy).min(ny - 1) {
        for z in wz..(wz + sz).min(nz - 1) {
            cell[at(nx - 1, y, z)] = 2;
        }
    }
    let [vx, vy, vz] = w.vehicle;
    let source = at(vx, vy, vz);
    cell[source] = 0;
    let mut labels = vec![Label::Outside; dims.len()];
    for (i, l) in labels.iter_mut().enumerate() {
        if cell[i] != 0 {
            continue;
        }
        let mut unknown = false;
        dims.for_each_face_neighbour(dims.voxel(i), |j| unknown |= cell[j] == 2);
        *l = if unknown { Label::Frontier } else { Label::Interior };
    }
    if labels[source] != Label::Interior {
        return None;
    }
    labels[source] = Label::Source;
    common::keep_component(&dims, &mut labels, source);
    labels.contains(&Label::Frontier).then_some((dims, labels))
}

/// How a case solves: its tolerance, error target and cap.
#[derive(Debug, Clone, Copy)]
struct Ask {
    tolerance: f32,
    max_error: f32,
    cap: u32,
}

fn ask() -> impl Strategy<Value = Ask> {
    (
        prop_oneof![Just(1e-6f32), Just(1e-5)],
        prop_oneof![Just(f32::INFINITY), Just(1e-4f32), Just(1e-5)],
        prop_oneof![1 => 2u32..=8, 3 => Just(400u32)],
    )
        .prop_map(|(tolerance, max_error, cap)| Ask {
            tolerance,
            max_error,
            cap,
        })
}

/// The solvers and storage set-ups.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Solver {
    /// MGPCG with the host's storage.
    Pcg,
    /// Plain V-cycles with the host's storage.
    VCycle,
    /// Plain V-cycles with the firmware's: bfloat16 coarse levels, no faces, masks or Krylov.
    Firmware,
    /// The host's flat solver.
    #[cfg(feature = "flat")]
    Flat,
    /// The reference Gauss-Seidel.
    GaussSeidel,
}

const SOLVERS: &[Solver] = &[
    Solver::Pcg,
    Solver::VCycle,
    Solver::Firmware,
    #[cfg(feature = "flat")]
    Solver::Flat,
    Solver::GaussSeidel,
];

/// Multigrid storage: the host's (f32 coarse levels, faces, Krylov vectors, masks) or the
/// firmware's.
struct Storage {
    values: Vec<f32>,
    halves: Vec<Bf16>,
    labels: Vec<Label>,
    faces: Vec<[u8; 4]>,
    krylov: Vec<f32>,
    masks: Vec<u8>,
}

impl Storage {
    fn new(dims: &Dims, host: bool) -> Self {
        let s = scratch_size(dims);
        Self {
            values: vec![0.0; if host { s.values } else { 0 }],
            halves: vec![Bf16::ZERO; if host { 0 } else { s.values }],
            labels: vec![Label::Outside; s.labels],
            faces: vec![[0; 4]; if host { s.faces } else { 0 }],
            krylov: vec![0.0; if host { s.krylov } else { 0 }],
            masks: vec![0; if host { s.masks } else { 0 }],
        }
    }

    fn multigrid(&mut self, dims: Dims) -> Multigrid<'_> {
        let values = if self.values.is_empty() {
            self.halves.as_mut_slice().into()
        } else {
            self.values.as_mut_slice().into()
        };
        Multigrid::new(
            dims,
            MultigridStorage {
                values,
                labels: &mut self.labels,
                faces: &mut self.faces,
                krylov: &mut self.krylov,
                masks: &mut self.masks,
            },
        )
        .expect("storage sized by scratch_size")
    }
}

fn params(a: &Ask, screening: f32) -> SolveParams {
    SolveParams {
        tolerance: a.tolerance,
        max_iterations: a.cap,
        warm_start: false,
        screening,
        max_error: a.max_error,
    }
}

/// A cold solve of `labels` by `solver`.
fn solve(solver: Solver, dims: Dims, labels: &[Label], p: &SolveParams) -> (Vec<f32>, SolveStats) {
    let mut psi = vec![0.0f32; dims.len()];
    let stats = match solver {
        Solver::Pcg | Solver::VCycle | Solver::Firmware => {
            let mut storage = Storage::new(&dims, solver != Solver::Firmware);
            let method = if solver == Solver::Pcg {
                Method::Pcg
            } else {
                Method::VCycle
            };
            storage.multigrid(dims).solve(labels, &mut psi, p, method)
        }
        #[cfg(feature = "flat")]
        Solver::Flat => {
            let mut values = vec![0.0f32; flat_scratch_len(&dims)];
            Flat::new(dims, &mut values)
                .expect("scratch sized by flat_scratch_len")
                .solve(labels, &mut psi, p)
        }
        Solver::GaussSeidel => gauss_seidel(&dims, labels, &mut psi, p),
    };
    (psi, stats.expect("valid solve inputs"))
}

fn max_error(psi: &[f32], exact: &[f64]) -> f64 {
    psi.iter()
        .zip(exact)
        .map(|(&p, &e)| (f64::from(p) - e).abs())
        .fold(0.0, f64::max)
}

/// The claims of one solve's report, checked against the f64 solution `exact`.
fn check(
    case: &str,
    (dims, labels, screening): (Dims, &[Label], f32),
    p: &SolveParams,
    psi: &[f32],
    s: &SolveStats,
    exact: &[f64],
) -> Result<(), TestCaseError> {
    let err = max_error(psi, exact);
    let case = format!("{case}: error {err:.3e}, {s:?}");
    let residual_met = s.residual <= p.tolerance;
    let error_met = p.max_error == f32::INFINITY || s.error_estimate.is_some_and(|e| e <= p.max_error);
    prop_assert_eq!(
        s.converged,
        residual_met && error_met,
        "converged misreported: {}",
        case
    );
    prop_assert_eq!(s.converged, s.stop == Stop::Met, "stop misreported: {}", case);
    // The report's residual is the returned ψ's, up to how two evaluations of it differ in
    // rounding: within the floor that rounding ψ to f32 causes (a 400-case run found a converged
    // flat solve at 4.29e-7 reported, 4.53e-7 recomputed, floor 1.76e-7).
    let again = screened_residual(&dims, labels, psi, screening).relative;
    prop_assert!(
        again <= 1.05 * s.residual + s.floor + 1e-9,
        "residual {again:.3e} recomputed: {}",
        case
    );
    if std::env::var("HONEST_REPORT").is_ok() {
        if let Some(e) = s.error_estimate {
            eprintln!(
                "RATIO {:.4} conv {} err {err:.3e} est {e:.3e} | {case}",
                err / f64::from(e),
                s.converged
            );
        }
        return Ok(());
    }
    if s.converged {
        if let Some(e) = s.error_estimate {
            prop_assert!(err <= f64::from(e), "error above its estimate: {}", case);
        }
    }
    Ok(())
}

/// Runs every solver on both fields of world `w` with `a`, and a re-solve in boxes of the
/// screened field after one frontier voxel turns out to be a wall.
fn honest(w: &World, a: &Ask) -> Result<(), TestCaseError> {
    let Some((dims, laplace)) = labels_of(w) else {
        return Err(TestCaseError::reject("no frontier in the vehicle's component"));
    };
    let mut screened = laplace.clone();
    release_source(&mut screened);
    let s = {
        let k = ScreenedParams::default().kappa_voxel(0.1);
        k * k
    };
    for (field, labels, screening) in [("laplace", &laplace, 0.0f32), ("screened", &screened, s)] {
        let exact = common::exact_solution(&dims, labels, f64::from(screening));
        let p = params(a, screening);
        for &solver in SOLVERS {
            let (psi, stats) = solve(solver, dims, labels, &p);
            let case = format!("{field}, {solver:?}, {a:?}, {:?}", w.n);
            check(&case, (dims, labels, screening), &p, &psi, &stats, &exact)?;
        }
    }
    // A re-solve in boxes: the screened field solved tightly, then one frontier voxel seen to
    // be a wall.
    let frontier: Vec<usize> = (0..dims.len())
        .filter(|&i| screened[i] == Label::Frontier)
        .collect();
    if frontier.len() >= 2 {
        let mut after = screened.clone();
        after[frontier[0]] = Label::Outside;
        let exact = common::exact_solution(&dims, &after, f64::from(s));
        let mut storage = Storage::new(&dims, true);
        let mut mg = storage.multigrid(dims);
        let mut psi = vec![0.0f32; dims.len()];
        let tight = SolveParams {
            tolerance: 1e-7,
            ..params(a, s)
        };
        mg.solve(
            &screened,
            &mut psi,
            &SolveParams {
                max_iterations: 5_000,
                max_error: f32::INFINITY,
                ..tight
            },
            Method::Pcg,
        )
        .expect("valid solve inputs");
        let p = SolveParams {
            warm_start: true,
            ..params(a, s)
        };
        let (mut bl, mut bp) = (vec![Label::Outside; dims.len()], vec![0.0f32; dims.len()]);
        let scratch = LocalScratch {
            labels: &mut bl,
            psi: &mut bp,
        };
        let local = LocalParams::for_screening(s, a.tolerance);
        let out = resolve_near(
            &mut WithMethod(&mut mg, Method::Pcg),
            &after,
            &mut psi,
            &p,
            &local,
            scratch,
        )
        .expect("valid solve inputs");
        let how = if matches!(out, Local::Solved(_)) {
            "boxes"
        } else {
            "whole"
        };
        let case = format!("local ({how}), {a:?}, {:?}", w.n);
        check(&case, (dims, &after, s), &p, &psi, &out.stats(), &exact)?;
    }
    Ok(())
}

fn cases() -> u32 {
    std::env::var("HONEST_CASES")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(40)
}

/// The seed of the random worlds: fixed (the suite's 40 cases are the same on every run), or
/// `PROPTEST_RNG_SEED=n`, or `HONEST_SEED=random` for new ones (how the counterexamples above
/// and in the notes were found).
fn seed() -> proptest::test_runner::RngSeed {
    use proptest::test_runner::RngSeed;
    match std::env::var("HONEST_SEED").as_deref() {
        Ok("random") => RngSeed::Random,
        _ => match ProptestConfig::default().rng_seed {
            RngSeed::Random => RngSeed::Fixed(0x0060_2026_1208),
            fixed => fixed,
        },
    }
}

proptest! {
    #![proptest_config(ProptestConfig {
        failure_persistence: None,
        max_global_rejects: 4 * cases(),
        rng_seed: seed(),
        ..ProptestConfig::with_cases(cases())
    })]

    /// On worlds of long walls, narrow doors and a window of a few frontier voxels, every
    /// solver's `converged` means what it says, and a converged solve's error estimate bounds
    /// its true error (against an f64 solve), for Laplace's and the screened field.
    #[test]
    fn converged_solves_bound_their_error_on_few_frontier_worlds(w in world(), a in ask()) {
        honest(&w, &a)?;
    }
}

/// The generator makes what the test is about: few frontier voxels behind long walls.
#[test]
fn the_worlds_have_few_frontier_voxels_and_walls() {
    let w = World {
        n: [30, 24, 10],
        walls: vec![
            Wall {
                along_x: false,
                at: 10,
                doors: vec![(3, 2, 4)],
            },
            Wall {
                along_x: true,
                at: 12,
                doors: vec![(20, 1, 8)],
            },
        ],
        window: (18, 4, 2, 3),
        vehicle: [3, 3, 3],
    };
    let (dims, labels) = labels_of(&w).expect("a frontier in reach");
    let frontier = labels.iter().filter(|l| **l == Label::Frontier).count();
    let interior = labels.iter().filter(|l| **l == Label::Interior).count();
    assert_eq!(frontier, 6, "the 2 × 3 window");
    assert!(interior > 1_000, "{interior}");
    assert_eq!(labels[dims.linear(VoxelIndex::new(3, 3, 3))], Label::Source);
}

/// The world a CI run's random cases found (2026-12-08): PCG capped at 7 iterations left ψ
/// outside [0, 1]; the clamp moved it, and the report gave the residual of the iterate before
/// the clamp (1.60e-2 against 1.69e-2 recomputed). Every solver now reports the returned ψ's.
#[test]
fn a_capped_solve_reports_the_residual_of_the_clamped_field() {
    let w = World {
        n: [17, 30, 8],
        walls: vec![
            Wall {
                along_x: false,
                at: 9,
                doors: vec![(2, 3, 5)],
            },
            Wall {
                along_x: false,
                at: 5,
                doors: vec![(14, 2, 1)],
            },
            Wall {
                along_x: true,
                at: 14,
                doors: vec![(15, 1, 1), (5, 2, 1)],
            },
            Wall {
                along_x: false,
                at: 14,
                doors: vec![(1, 3, 4)],
            },
        ],
        window: (3, 6, 3, 1),
        vehicle: [4, 14, 3],
    };
    let a = Ask {
        tolerance: 1e-6,
        max_error: f32::INFINITY,
        cap: 7,
    };
    honest(&w, &a).expect("honest reports");
}
