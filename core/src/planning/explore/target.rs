//! Target choice: the one part of a plan that differs between planners.
//!
//! The [`Explorer`](super::Explorer) runs the loop every planner shares: it integrates frames
//! (and refuses the ones whose pose jumped, came too late or turned too fast), marks the
//! vehicle's body free, builds the safe space, decides when the exploration is complete (after
//! clearing a vehicle walled in by unobservable voxels, reopening doorways closed by doubtful
//! voxels, and leaving pockets), escapes from inflated space, keeps a committed goal, turns to
//! look around on arrival, seals far remnants and frontiers that visits keep failing to
//! resolve, and plans the way home. Inside that loop a [`TargetChoice`] answers three
//! questions over the domain the explorer built:
//!
//! - [`TargetChoice::choose`]: which frontier to go to and the way there (the harmonic field's
//!   streamline, [`super::HarmonicField`]; a closest-frontier search; an information-gain
//!   pose);
//! - [`TargetChoice::goal`]: where on that way to stop and which way to look (by default the
//!   core's view rule, [`view_rule`]);
//! - [`TargetChoice::way_home`]: the way to one voxel, home.
//!
//! A choice may keep state across plans (a warm-started field, a random generator); it may
//! relabel the domain it is lent (the harmonic field makes home the only target), and it counts
//! its own work and faults in the [`Status`] it is lent.

use nalgebra::{Point3, Vector3};

use crate::mapping::camera::Intrinsics;
use crate::mapping::integrate;
use crate::mapping::map::{VoxelIndex, VoxelMap};
use crate::planning::domain::{InflationStencil, Label};
use crate::planning::streamline::{self, StreamlineEnd, Waypoints};

use super::config::ExplorerConfig;
use super::status::{Fault, Goal, PlanOutcome, Status};
use crate::clock::Clock;

/// Most voxels a target is watched by ([`Chosen::Way`]).
pub const WATCH_CAPACITY: usize = 16;

/// The voxels whose being open keeps a committed goal (see [`Chosen::Way`]).
pub type Watch = heapless::Vec<VoxelIndex, WATCH_CAPACITY>;

/// What the explorer lends a target choice for one decision: the map, the domain it just built
/// around the vehicle, and where to count.
pub struct Context<'c, 'a> {
    /// The map.
    pub map: &'c VoxelMap<'a>,
    /// The domain's labels, one per voxel of the map.
    pub labels: &'c mut [Label],
    /// The vehicle's voxel (in the domain).
    pub vehicle: VoxelIndex,
    /// The inflation in use (the planning radius, or the narrower one out of a pocket).
    pub stencil: &'c InflationStencil,
    /// The explorer's configuration.
    pub config: &'c ExplorerConfig,
    /// The camera of the last integrated frame, if any.
    pub intrinsics: Option<Intrinsics>,
    /// Counters, statistics and phase ticks of the plan being made.
    pub status: &'c mut Status,
}

/// What a target choice made of the domain.
#[derive(Debug, Clone, PartialEq)]
pub enum Chosen {
    /// A target: fly the way written into the waypoints (from the vehicle; [`TargetChoice::goal`]
    /// then says where on it to stop). `end` describes the way: its frontier voxel, end point,
    /// direction there and length. A committed goal is kept while any voxel of `watch` is
    /// still next to unexplored space, and a target whose visits keep teaching nothing is
    /// sealed around each.
    Way {
        /// The way's end.
        end: StreamlineEnd,
        /// The voxels that keep it open.
        watch: Watch,
    },
    /// Build the domain again and choose again: the choice changed how it chooses (the
    /// harmonic field lowered its screening). Counts as one of the plan's passes.
    Again,
    /// Fly to this goal as it is, outside the explorer's rules (a way that stalled short of its
    /// frontier: the vehicle flies the part traced and plans again from there).
    Goal(Goal),
    /// No target can be chosen: hold.
    Hold(Fault),
}

impl Chosen {
    /// A way watched by its frontier voxel alone.
    pub fn way(end: StreamlineEnd) -> Self {
        let mut watch = Watch::new();
        let _ = watch.push(end.frontier);
        Chosen::Way { end, watch }
    }
}

/// How a planner picks the frontier to explore next and the way there; the rest of the loop is
/// the [`Explorer`](super::Explorer)'s (see the [module documentation](self)).
pub trait TargetChoice {
    /// Chooses a target in the domain `cx` lends (it holds at least one frontier voxel) for the
    /// vehicle at `position` facing `yaw`, and writes the way there, starting at the vehicle,
    /// into `way` (empty on entry). Solve and search time goes into
    /// [`PhaseTicks::solve`](super::PhaseTicks::solve), tracing into `streamline`.
    fn choose(
        &mut self,
        cx: Context<'_, '_>,
        position: &Point3<f32>,
        yaw: f32,
        way: &mut Waypoints,
        clock: &mut impl Clock,
    ) -> Chosen;

    /// Where on `way` (as [`TargetChoice::choose`] wrote it, to `end`) to stop, and which way to
    /// look from there; `way` is trimmed to end at the goal. `near` asks for the near view (a
    /// look from afar at this target taught nothing). Returns the goal and whether it looks
    /// from afar. By default the core's [`view_rule`], then the way pulled taut
    /// ([`ExplorerConfig::taut_path`]).
    fn goal(
        &mut self,
        cx: Context<'_, '_>,
        end: &StreamlineEnd,
        way: &mut Waypoints,
        yaw: f32,
        near: bool,
    ) -> (Goal, bool) {
        let (goal, from_afar) = view_rule(&cx, end, way, yaw, near);
        if cx.config.taut_path {
            // The streamline chose where to look from (it arrives along the frontier's
            // normal); the flight there need not follow its curve.
            cx.status.planning_ops += streamline::pull_taut(cx.map.geometry(), cx.labels, way);
        }
        (goal, from_afar)
    }

    /// The way this choice would take to a frontier of the domain `cx` lends, written into
    /// `way`; false if it finds none. The explorer asks it before an exploration ends, on a
    /// domain that takes doubtful voxels for free space, to find the doorway they close.
    fn way_to_frontier(
        &mut self,
        cx: Context<'_, '_>,
        position: &Point3<f32>,
        way: &mut Waypoints,
        clock: &mut impl Clock,
    ) -> bool;

    /// The way home: from the vehicle at `position` to `home`, whose voxel `home_voxel` is in
    /// the domain `cx` lends (not the vehicle's), written into `way`; the goal (home, yaw kept)
    /// or why there is none.
    #[allow(clippy::too_many_arguments)]
    fn way_home(
        &mut self,
        cx: Context<'_, '_>,
        position: &Point3<f32>,
        yaw: f32,
        home: &Point3<f32>,
        home_voxel: VoxelIndex,
        way: &mut Waypoints,
        clock: &mut impl Clock,
    ) -> PlanOutcome;

    /// The potential of the last choice, one value per voxel, if the choice has one (figures
    /// draw it).
    fn potential(&self) -> Option<&[f32]> {
        None
    }
}

/// The core's view rule: the goal for a way `way` that ends at `end` (a dense way, as a
/// streamline is: points half a voxel apart) is the *first* point of it from which the frontier
/// is in plain sight (free voxels all the way) within [`ExplorerConfig::view_range_m`] and
/// inside the vertical field of view, unless `near`; else, and if no point sees it so, the
/// point *closest to the end* that sees it beyond the minimum range; if no point sees it at all
/// (a frontier inside the minimum range, or straight above or below), a point backed off from
/// it, level with it, that does ([`step_back`]). The goal yaw faces the frontier; on a planning
/// grid coarser than the map, the goal sees and faces the unexplored space the frontier cell
/// borders instead ([`unexplored_beyond`]), which can lie two cells past it. Trims `way`
/// to end at the goal; returns the goal and whether it looks from afar.
pub fn view_rule(
    cx: &Context<'_, '_>,
    end: &StreamlineEnd,
    way: &mut Waypoints,
    yaw: f32,
    near: bool,
) -> (Goal, bool) {
    let target = end.end;
    let geometry = *cx.map.geometry();
    let config = cx.config;
    let min_range = config.integration.min_range + geometry.resolution();
    let tan_v = cx
        .intrinsics
        .map(|i| libm::tanf(i.half_fov().1 * config.view_margin))
        .unwrap_or(0.0);
    // On a planning grid coarser than the map the unexplored space lies up to two cells past
    // the frontier cell, often off to one side of it (a door seen along a hall) or below it
    // (the floor beside a table): the goal must see and face that, not the cell.
    let aim = if config.plan_coarsening > 1 {
        unexplored_beyond(cx, end.frontier).unwrap_or(target)
    } else {
        target
    };
    let sees = |p: &Point3<f32>| {
        let d = aim - p;
        let horizontal = libm::sqrtf(d.x * d.x + d.y * d.y);
        d.norm() >= min_range && d.z.abs() <= horizontal * tan_v
    };
    let from_afar = config.view_range_m > 0.0 && !near;
    let in_sight = |p: &Point3<f32>| {
        if (target - p).norm() > config.view_range_m || !sees(p) {
            return false;
        }
        let dims = geometry.dims();
        let mut clear = true;
        integrate::traverse(&geometry, p, &target, |v| {
            clear &= cx.map.is_free(dims.linear(v));
            clear
        });
        clear
    };
    let afar = if from_afar {
        way.iter().position(in_sight)
    } else {
        None
    };
    let chosen = afar.or_else(|| way.iter().rposition(sees));
    let (position, look) = match chosen {
        Some(k) => {
            way.truncate(k + 1);
            let p = way.get(k).copied().unwrap_or(end.end);
            (p, aim - p)
        }
        None => match step_back(cx, way, &target, &sees) {
            // Too near to see (inside the minimum range, or straight above or below): back
            // off to where the camera sees it.
            Some(p) => {
                let start = way.first().copied().unwrap_or(p);
                way.clear();
                let _ = way.push(start);
                let _ = way.push(p);
                (p, aim - p)
            }
            None => (end.end, end.direction),
        },
    };
    let goal = Goal {
        position,
        yaw: heading(&look, yaw),
        frontier: end.frontier,
        escape: false,
    };
    (goal, afar.is_some())
}

/// The centre of the unexplored voxels that make `frontier` one: those within
/// [`frontier_reach`](crate::planning::domain::frontier_reach) of it (Chebyshev) that a straight
/// line from its centre reaches through no occupied, uncertain or sealed voxel. `None` if
/// there are none.
pub fn unexplored_beyond(cx: &Context<'_, '_>, frontier: VoxelIndex) -> Option<Point3<f32>> {
    let geometry = *cx.map.geometry();
    let dims = geometry.dims();
    let reach = crate::planning::domain::frontier_reach(cx.stencil);
    let from = geometry.center(frontier);
    let (mut sum, mut count) = (Vector3::zeros(), 0u32);
    for dz in -reach..=reach {
        for dy in -reach..=reach {
            for dx in -reach..=reach {
                let Some(u) = dims.offset(frontier, [dx, dy, dz]) else {
                    continue;
                };
                if !cx.map.is_unexplored(dims.linear(u)) {
                    continue;
                }
                let to = geometry.center(u);
                let mut open = true;
                integrate::traverse(&geometry, &from, &to, |v| {
                    let i = dims.linear(v);
                    open &= cx.map.is_free(i) || cx.map.is_unexplored(i);
                    open
                });
                if open {
                    sum += to.coords;
                    count += 1;
                }
            }
        }
    }
    (count > 0).then(|| Point3::from(sum / count as f32))
}

/// A viewpoint for a frontier `target` that no point of `way` sees: the nearest to the vehicle
/// (the way's first point) of a ring of points around the target (level with it, 0.1 m past
/// the minimum range and farther) that is a domain voxel, reached from the vehicle in a
/// straight line through domain voxels, and sees the target through free voxels.
pub fn step_back(
    cx: &Context<'_, '_>,
    way: &Waypoints,
    target: &Point3<f32>,
    sees: &impl Fn(&Point3<f32>) -> bool,
) -> Option<Point3<f32>> {
    let geometry = *cx.map.geometry();
    let dims = geometry.dims();
    let start = *way.first()?;
    let min_range = cx.config.integration.min_range + geometry.resolution();
    let in_domain = |v: VoxelIndex| cx.labels.get(dims.linear(v)).is_some_and(|l| l.in_domain());
    let mut best: Option<(f32, Point3<f32>)> = None;
    for r in [min_range + 0.1, min_range + 0.3, min_range + 0.6] {
        for k in 0..8 {
            let a = k as f32 * core::f32::consts::FRAC_PI_4;
            let p = target + nalgebra::Vector3::new(r * libm::cosf(a), r * libm::sinf(a), 0.0);
            let d = (p - start).norm();
            if best.is_some_and(|(b, _)| d >= b) || !sees(&p) || !geometry.voxel_at(&p).is_some_and(in_domain)
            {
                continue;
            }
            let mut ok = true;
            integrate::traverse(&geometry, &start, &p, |v| {
                ok &= in_domain(v);
                ok
            });
            integrate::traverse(&geometry, &p, target, |v| {
                ok &= cx.map.is_free(dims.linear(v));
                ok
            });
            if ok {
                best = Some((d, p));
            }
        }
        if best.is_some() {
            break;
        }
    }
    best.map(|(_, p)| p)
}

/// Yaw that looks along `d`, or `fallback` when `d` is (nearly) vertical.
pub(crate) fn heading(d: &Vector3<f32>, fallback: f32) -> f32 {
    if d.x.abs() + d.y.abs() > 1e-3 * d.norm().max(1e-6) {
        libm::atan2f(d.y, d.x)
    } else {
        fallback
    }
}
