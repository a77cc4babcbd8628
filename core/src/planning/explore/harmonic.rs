//! The harmonic planner's target choice: solve the planning field over the domain and follow
//! its streamline from the vehicle to a frontier.
//!
//! The field is [`ExplorerConfig::field`] ([`crate::planning::field`]: by default the frontier-sourced
//! screened field, u = 1 on frontiers, ∇²u = κ²u elsewhere; or the seed's Laplace field with
//! the vehicle as source), solved by [`ExplorerConfig::solver`] warm-started from the previous
//! solution ([`crate::planning::solve`]; a re-solve of the screened field works in boxes around what the
//! scans changed where box scratch is lent, [`crate::planning::solve::local`]). Its streamline
//! ([`crate::planning::streamline`]) ends on a frontier. Far from every frontier the screened field can
//! fall below what f32 resolves: a streamline that stalls there is traced again on a field
//! with half the κ; once κ is as low as it goes, the vehicle flies the part it traced.

use nalgebra::Point3;

use crate::planning::domain::Label;
use crate::planning::field::{self, PlanningField};
#[cfg(feature = "flat")]
use crate::planning::solve::flat::Flat;
use crate::planning::solve::local::{resolve_near, BoxSolver, Local, LocalParams, LocalScratch, WithMethod};
use crate::planning::solve::multigrid::{CoarseValues, Method, Multigrid, MultigridStorage};
use crate::planning::solve::{self, SolveError, SolveParams, SolveStats, Stop};
use crate::planning::streamline::{self, Field, StreamlineError, Waypoints};

use super::config::{ExplorerConfig, SolverKind};
use super::status::{ConfigError, Fault, Goal, PlanOutcome, Status};
use super::target::heading;
use super::target::{Chosen, Context, TargetChoice};
use crate::clock::Clock;
use crate::mapping::map::{MapGeometry, VoxelIndex};

/// The buffers the field is solved in (see [`ExplorerStorage`](super::ExplorerStorage), whose
/// solver buffers these are).
pub struct FieldStorage<'a> {
    /// Potential φ, one per voxel.
    pub phi: &'a mut [f32],
    /// Multigrid coarse-level values.
    pub coarse_values: CoarseValues<'a>,
    /// Multigrid coarse-level labels.
    pub coarse_labels: &'a mut [Label],
    /// Multigrid coarse-level face conductances.
    pub coarse_faces: &'a mut [[u8; 4]],
    /// MGPCG vectors (optional).
    pub krylov: &'a mut [f32],
    /// The fine cells' neighbour masks (optional).
    pub masks: &'a mut [u8],
    /// The thesis's Jacobi scratch ([`SolverKind::ThesisJacobi`] only).
    pub jacobi: &'a mut [f32],
    /// Labels of the box a local re-solve cuts out (optional).
    pub local_labels: &'a mut [Label],
    /// Values of that box.
    pub local_psi: &'a mut [f32],
    /// The flat solver's storage ([`SolverKind::Flat`] only).
    pub flat: &'a mut [f32],
}

/// The harmonic planner's target choice (see the [module documentation](self)): the planning
/// field, its solver and what it keeps between plans.
pub struct HarmonicField<'a> {
    phi: &'a mut [f32],
    multigrid: Option<Multigrid<'a>>,
    /// The flat solver ([`SolverKind::Flat`] only).
    #[cfg(feature = "flat")]
    flat: Option<Flat<'a>>,
    /// The thesis's Jacobi scratch (empty unless [`SolverKind::ThesisJacobi`]).
    jacobi: &'a mut [f32],
    /// The box scratch of local re-solves (empty: none).
    local_labels: &'a mut [Label],
    /// Its values.
    local_psi: &'a mut [f32],
    /// The screening of the field `phi` holds, if a solve left one there: a re-solve with
    /// the same screening may work locally.
    solved_screening: Option<f32>,
    /// The screened field's current κ, 1/voxel (lowered while frontiers are far).
    kappa_voxel: f32,
}

impl<'a> HarmonicField<'a> {
    /// The field of `config` over `geometry`, solved in `storage`: φ at least one entry per
    /// voxel; the multigrid buffers sized by [`crate::planning::solve::multigrid::scratch_size`] unless the
    /// solver is Gauss-Seidel or the thesis's Jacobi; `jacobi` one entry per voxel for the
    /// thesis's solve, which needs the seed's field.
    pub fn new(
        geometry: &MapGeometry,
        config: &ExplorerConfig,
        storage: FieldStorage<'a>,
    ) -> Result<Self, ConfigError> {
        let n = geometry.dims().len();
        let FieldStorage {
            phi,
            coarse_values,
            coarse_labels,
            coarse_faces,
            krylov,
            masks,
            jacobi,
            local_labels,
            local_psi,
            flat,
        } = storage;
        if phi.len() < n {
            return Err(ConfigError::StorageTooSmall);
        }
        let multigrid = match config.solver {
            SolverKind::Multigrid => Some(
                Multigrid::new(
                    geometry.dims(),
                    MultigridStorage {
                        values: coarse_values,
                        labels: coarse_labels,
                        faces: coarse_faces,
                        krylov,
                        masks,
                    },
                )
                .map_err(ConfigError::Solver)?,
            ),
            SolverKind::GaussSeidel => None,
            #[cfg(feature = "flat")]
            SolverKind::Flat => None,
            SolverKind::ThesisJacobi => {
                if jacobi.len() < n {
                    return Err(ConfigError::StorageTooSmall);
                }
                if config.field != PlanningField::Harmonic {
                    // The thesis solves Laplace's equation only.
                    return Err(ConfigError::Solver(SolveError::BadScreening));
                }
                None
            }
        };
        let jacobi = match config.solver {
            SolverKind::ThesisJacobi => jacobi.get_mut(..n).unwrap_or_default(),
            _ => &mut [],
        };
        #[cfg(feature = "flat")]
        let flat = match config.solver {
            SolverKind::Flat => Some(Flat::new(geometry.dims(), flat).map_err(ConfigError::Solver)?),
            _ => None,
        };
        #[cfg(not(feature = "flat"))]
        let _ = flat;
        let phi = phi.get_mut(..n).ok_or(ConfigError::StorageTooSmall)?;
        phi.fill(0.0);
        Ok(Self {
            phi,
            multigrid,
            #[cfg(feature = "flat")]
            flat,
            jacobi,
            local_labels,
            local_psi,
            solved_screening: None,
            kappa_voxel: match config.field {
                PlanningField::Screened(p) => p.kappa_voxel(geometry.resolution()),
                PlanningField::Harmonic => 0.0,
            },
        })
    }

    /// The stored potential ψ = 1 − φ of the last solve (see [`crate::planning::solve`]).
    pub fn psi(&self) -> &[f32] {
        self.phi
    }

    /// Solves the planning field over the domain `cx` lends (see [`crate::planning::field`]). For the
    /// screened field the vehicle's voxel joins the interior, and while `u` at the vehicle falls
    /// below [`ScreenedParams::min_vehicle_value`](field::ScreenedParams::min_vehicle_value)
    /// (the nearest frontier is far) κ is lowered and the field solved again; once `u` there is
    /// large again κ returns towards its configured value for the next plan. The stats returned
    /// add up the iterations.
    ///
    /// [`SolveParams::max_iterations`] bounds the plan's iterations, all its solves together
    /// ([`Status::plan_iterations`]), so that a board can bound a plan's time: a solve it stops
    /// short leaves κ as it is (an unconverged `u` says little), and the next plan resumes from
    /// the ψ it left (warm).
    pub(super) fn solve_field(&mut self, cx: &mut Context<'_, '_>) -> Result<SolveStats, SolveError> {
        let geometry = *cx.map.geometry();
        let PlanningField::Screened(params) = cx.config.field else {
            let stats = self.solve_once(cx, 0.0, cx.config.solve.tolerance, budget_left(cx))?;
            cx.status.plan_iterations = cx.status.plan_iterations.saturating_add(stats.iterations);
            return Ok(stats);
        };
        field::release_source(cx.labels);
        let full = params.kappa_voxel(geometry.resolution());
        let at_vehicle = geometry.dims().linear(cx.vehicle);
        let mut total: Option<SolveStats> = None;
        for _ in 0..field::MAX_SCREENING_SOLVES {
            let kappa = self.kappa_voxel.clamp(field::MIN_KAPPA_VOXEL, full);
            let mut stats = self.solve_once(cx, kappa * kappa, params.tolerance, budget_left(cx))?;
            cx.status.plan_iterations = cx.status.plan_iterations.saturating_add(stats.iterations);
            let capped = stats.stop == Stop::Cap;
            if let Some(t) = total {
                stats.iterations += t.iterations;
                stats.cell_updates += t.cell_updates;
            }
            total = Some(stats);
            if capped {
                break;
            }
            let u = self.phi.get(at_vehicle).copied().unwrap_or(0.0);
            if u >= params.min_vehicle_value || kappa <= field::MIN_KAPPA_VOXEL {
                // Near frontiers again: let κ recover for the next plan.
                if u >= params.raise_above {
                    self.kappa_voxel = (2.0 * kappa).min(full);
                }
                break;
            }
            self.kappa_voxel = params.lowered_kappa(kappa, u);
        }
        total.ok_or(SolveError::StorageTooSmall)
    }

    /// [`HarmonicField::solve_field`], its stats, work and time (from tick `t1`) recorded in
    /// the status; the tick it ended at.
    fn solve_counted(
        &mut self,
        cx: &mut Context<'_, '_>,
        t1: u64,
        clock: &mut impl Clock,
    ) -> Result<u64, Fault> {
        let solved = self.solve_field(cx);
        let t2 = clock.ticks();
        let status = &mut *cx.status;
        status.phase_ticks.solve += t2.saturating_sub(t1);
        let s = solved.map_err(Fault::Solver)?;
        status.solve = s;
        status.planning_ops += s.cell_updates;
        if !s.converged {
            status.errors.solver_not_converged += 1;
        }
        Ok(t2)
    }

    /// Halves the screened field's κ if it can go lower; false for the seed's field.
    fn lower_screening(&mut self, config: &ExplorerConfig) -> bool {
        match config.field {
            PlanningField::Screened(_) if self.kappa_voxel > field::MIN_KAPPA_VOXEL => {
                self.kappa_voxel = (0.5 * self.kappa_voxel).max(field::MIN_KAPPA_VOXEL);
                true
            }
            _ => false,
        }
    }

    /// One solve of the current domain with `screening` (κ²h², 0 for Laplace) to `tolerance`, in
    /// at most `max_iterations`
    /// (the thesis's Jacobi stops by its own rule instead, [`solve::thesis`]).
    fn solve_once(
        &mut self,
        cx: &mut Context<'_, '_>,
        screening: f32,
        tolerance: f32,
        max_iterations: u32,
    ) -> Result<SolveStats, SolveError> {
        let params = SolveParams {
            screening,
            tolerance,
            max_iterations,
            ..cx.config.solve
        };
        let dims = cx.map.geometry().dims();
        cx.status.solves += 1;
        let same_field = self.solved_screening == Some(screening);
        self.solved_screening = None;
        // A re-solve of the same screened field may work in boxes around what changed.
        let local_ok = same_field && params.warm_start && screening > 0.0 && !self.local_labels.is_empty();
        let (labels, phi) = (&*cx.labels, &mut *self.phi);
        let boxes = Boxes {
            local: LocalParams::for_screening(screening, tolerance),
            scratch: LocalScratch {
                labels: &mut *self.local_labels,
                psi: &mut *self.local_psi,
            },
            status: &mut *cx.status,
        };
        let solved = match (self.multigrid.as_mut(), cx.config.solver) {
            (Some(mg), _) if local_ok => boxes.solve(&mut WithMethod(mg, Method::Auto), labels, phi, &params),
            (Some(mg), _) => mg.solve(labels, phi, &params, Method::Auto),
            #[cfg(feature = "flat")]
            (None, SolverKind::Flat) => match self.flat.as_mut() {
                Some(flat) if local_ok => boxes.solve(flat, labels, phi, &params),
                Some(flat) => flat.solve(labels, phi, &params),
                None => Err(SolveError::ScratchTooSmall),
            },
            (None, SolverKind::ThesisJacobi) => solve::thesis::solve(
                &dims,
                labels,
                phi,
                self.jacobi,
                &solve::thesis::ThesisParams::default(),
            ),
            (None, _) => solve::gauss_seidel(&dims, labels, phi, &params),
        };
        if solved.is_ok() {
            self.solved_screening = Some(screening);
        }
        solved
    }

    /// Traces the streamline of the field just solved from `position` into `way`.
    fn trace(
        &self,
        cx: &Context<'_, '_>,
        position: &Point3<f32>,
        way: &mut Waypoints,
    ) -> Result<streamline::StreamlineEnd, StreamlineError> {
        let field = Field {
            geometry: cx.map.geometry(),
            labels: cx.labels,
            phi: self.phi,
        };
        streamline::trace(&field, position, &cx.config.streamline, way)
    }
}

impl TargetChoice for HarmonicField<'_> {
    fn choose(
        &mut self,
        mut cx: Context<'_, '_>,
        position: &Point3<f32>,
        yaw: f32,
        way: &mut Waypoints,
        clock: &mut impl Clock,
    ) -> Chosen {
        let t1 = clock.ticks();
        let t2 = match self.solve_counted(&mut cx, t1, clock) {
            Ok(t2) => t2,
            Err(fault) => return Chosen::Hold(fault),
        };
        let traced = self.trace(&cx, position, way);
        let budget = budget_left(&cx);
        let status = &mut *cx.status;
        match traced {
            Ok(end) => {
                status.streamline = Some(end);
                status.phase_ticks.streamline += clock.ticks().saturating_sub(t2);
                Chosen::way(end)
            }
            Err(e) => {
                status.streamline = None;
                // Far from the vehicle φ can fall below what f32 resolves (a big hall): the
                // streamline stalls on a plateau after a stretch of good descent. That stretch
                // still leads towards the frontiers; fly it and plan again from its end, where
                // the new source makes the field steep again.
                if e == StreamlineError::Stalled {
                    // The screened field has no interior maximum; a stall means the solve did
                    // not resolve u this far from the frontiers. A smaller κ raises u at the
                    // vehicle: solve again with half of it.
                    if budget > 0 && self.lower_screening(cx.config) {
                        status.errors.screening_retries += 1;
                        return Chosen::Again;
                    }
                    if let Some(goal) = plateau_goal(cx.map.geometry(), way, cx.vehicle, yaw) {
                        status.errors.plateaus += 1;
                        status.phase_ticks.streamline += clock.ticks().saturating_sub(t2);
                        return Chosen::Goal(goal);
                    }
                }
                status.errors.streamline_failures += 1;
                Chosen::Hold(Fault::Streamline(e))
            }
        }
    }

    fn way_to_frontier(
        &mut self,
        mut cx: Context<'_, '_>,
        position: &Point3<f32>,
        way: &mut Waypoints,
        clock: &mut impl Clock,
    ) -> bool {
        let t1 = clock.ticks();
        let Ok(t2) = self.solve_counted(&mut cx, t1, clock) else {
            return false;
        };
        let traced = self.trace(&cx, position, way);
        cx.status.phase_ticks.streamline += clock.ticks().saturating_sub(t2);
        traced.is_ok()
    }

    /// The field of [`ExplorerConfig::field`] solved over the vehicle's safe space with home as
    /// its only target instead of the frontiers (every frontier voxel joins the interior), so
    /// its streamline ends at home by the same argument that makes exploring streamlines end on
    /// a frontier; the way is pulled taut as for exploring. The goal is home, the yaw kept.
    fn way_home(
        &mut self,
        mut cx: Context<'_, '_>,
        position: &Point3<f32>,
        yaw: f32,
        _home: &Point3<f32>,
        home_voxel: VoxelIndex,
        way: &mut Waypoints,
        clock: &mut impl Clock,
    ) -> PlanOutcome {
        let geometry = *cx.map.geometry();
        for label in cx.labels.iter_mut().filter(|l| **l == Label::Frontier) {
            *label = Label::Interior;
        }
        if let Some(label) = cx.labels.get_mut(geometry.dims().linear(home_voxel)) {
            *label = Label::Frontier;
        }
        // As for exploring: a streamline that stalls where the solve did not resolve the field
        // retries on a less screened one.
        for _ in 0..8 {
            let t1 = clock.ticks();
            let t2 = match self.solve_counted(&mut cx, t1, clock) {
                Ok(t2) => t2,
                Err(fault) => return PlanOutcome::Hold(fault),
            };
            way.clear();
            match self.trace(&cx, position, way) {
                Ok(end) => {
                    cx.status.streamline = Some(end);
                    if cx.config.taut_path {
                        cx.status.planning_ops += streamline::pull_taut(&geometry, cx.labels, way);
                    }
                    cx.status.phase_ticks.streamline += clock.ticks().saturating_sub(t2);
                    let goal = way.last().copied().unwrap_or(end.end);
                    return PlanOutcome::Goal(Goal {
                        position: goal,
                        yaw,
                        frontier: home_voxel,
                        escape: false,
                    });
                }
                Err(StreamlineError::Stalled) if budget_left(&cx) > 0 && self.lower_screening(cx.config) => {
                    cx.status.errors.screening_retries += 1;
                }
                Err(e) => {
                    cx.status.streamline = None;
                    cx.status.errors.streamline_failures += 1;
                    return PlanOutcome::Hold(Fault::Streamline(e));
                }
            }
        }
        cx.status.errors.streamline_failures += 1;
        PlanOutcome::Hold(Fault::Streamline(StreamlineError::Stalled))
    }

    fn potential(&self) -> Option<&[f32]> {
        Some(self.phi)
    }
}

/// The goal for a streamline that stalled on a plateau: the last traced waypoint of `way`, if
/// the trace got at least a voxel away from the vehicle's voxel. Every waypoint lies in a domain
/// voxel, so the goal is known free and clear of inflated space.
fn plateau_goal(geometry: &MapGeometry, way: &Waypoints, vehicle: VoxelIndex, yaw: f32) -> Option<Goal> {
    let (&last, before) = way.split_last()?;
    let stalled_in = geometry.voxel_at(&last)?;
    let start = before.first()?;
    if stalled_in == vehicle || (last - start).norm() < geometry.resolution() {
        return None;
    }
    let direction = before.last().map_or(last - start, |p| last - p);
    Some(Goal {
        position: last,
        yaw: heading(&direction, yaw),
        frontier: stalled_in,
        escape: false,
    })
}

/// A re-solve in boxes around what changed ([`resolve_near`]) with the field's box scratch,
/// counted in the status.
struct Boxes<'b> {
    local: LocalParams,
    scratch: LocalScratch<'b>,
    status: &'b mut Status,
}

impl Boxes<'_> {
    fn solve(
        self,
        solver: &mut impl BoxSolver,
        labels: &[Label],
        phi: &mut [f32],
        params: &SolveParams,
    ) -> Result<SolveStats, SolveError> {
        let solved = resolve_near(solver, labels, phi, params, &self.local, self.scratch);
        match &solved {
            Ok(Local::Solved(_)) => self.status.local_solves += 1,
            Ok(Local::Whole(_)) => self.status.local_given_up += 1,
            Err(_) => {}
        }
        solved.map(|how| how.stats())
    }
}

/// The iterations the plan being made may still spend ([`SolveParams::max_iterations`] less
/// [`Status::plan_iterations`]).
fn budget_left(cx: &Context<'_, '_>) -> u32 {
    cx.config
        .solve
        .max_iterations
        .saturating_sub(cx.status.plan_iterations)
}
