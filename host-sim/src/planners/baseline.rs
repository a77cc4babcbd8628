//! The seed thesis's baselines (Shade 2011, §6.5): frontier and information-gain planners that
//! choose a target, then fly an A* path to it.
//!
//! Each is a [`TargetChoice`] inside the core's [`Explorer`](harmonic_core::explore::Explorer),
//! so every planner integrates with the same integrator into the same map, plans over the same
//! inflated safe space and the same frontier voxels (free voxels next to unexplored space,
//! eroded by the vehicle radius) the harmonic planner uses as sinks, and shares the explorer's
//! loop: the vehicle's body marked free, completion when no reachable frontier is left (after
//! clearing, reopening doubtful doorways and leaving pockets), escape from inflated space, a
//! committed goal kept while its target is open and its path safe, the look-around on arrival,
//! far remnants and fruitless targets sealed (thesis §6.6.2), frame checks, the way home. Only
//! the choice of target, the way to it and where on it to look from differ:
//!
//! - **closest frontier** (Yamauchi 1997): Dijkstra from the vehicle; the first frontier voxel
//!   settled has the shortest path of all. The goal is the last point of the path from which
//!   the camera, turned to the unknown behind the frontier, sees it beyond the minimum range and
//!   inside the vertical field of view (the thesis's rule; [`Baseline::with_core_views`] takes
//!   the core's view rule first).
//! - **random frontier**: a frontier voxel drawn uniformly, A* to it, goal as above.
//! - **information gain** (Thrun's binary gain): candidate poses are drawn from the safe space,
//!   as many as 5 % of the free voxels; a candidate's gain is the number of frontier voxels of
//!   the map (free, next to unexplored) it sees — in range, inside the field of view for the best
//!   yaw, with a free line of sight through the current map. The candidate with the largest gain
//!   wins. Visibility is estimated on a random sample of at most
//!   [`GainParams::frontier_samples`] frontier voxels per plan and scaled to the full count.
//! - **weighted information gain** (González-Baños & Latombe 2002): the candidate maximising
//!   g·exp(−λL), L its shortest-path length in metres, λ = 0.2.
//!
//! If no candidate sees any frontier voxel, the gain planners fall back to the closest frontier.
//! The way to a target is the A* voxel path with line-of-sight shortcuts ([`smooth`]); the way
//! home is A* too.

use harmonic_core::clock::Clock;
use harmonic_core::domain::Label;
use harmonic_core::explore::target::{Context, TargetChoice, Watch, WATCH_CAPACITY};
use harmonic_core::explore::{Chosen, Fault, Goal, PlanOutcome};
use harmonic_core::integrate::traverse;
use harmonic_core::map::{VoxelIndex, VoxelMap};
use harmonic_core::streamline::{StreamlineEnd, StreamlineError, Waypoints};
use nalgebra::{Point3, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::kind::PlannerKind;
use super::search::{smooth, Search};

/// Information-gain settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GainParams {
    /// Candidate poses per plan as a fraction of the map's free voxels (thesis: 5 %).
    pub candidate_fraction: f32,
    /// Path-length weight λ of weighted information gain, 1/m (thesis: 0.2).
    pub lambda: f32,
    /// Frontier voxels whose visibility is tested per plan (a uniform sample when there are
    /// more; gains are scaled to the full count).
    pub frontier_samples: usize,
}

impl Default for GainParams {
    fn default() -> Self {
        Self {
            candidate_fraction: 0.05,
            lambda: 0.2,
            frontier_samples: 64,
        }
    }
}

/// What a baseline decided to fly to.
#[derive(Debug, Clone)]
struct Target {
    /// Voxel the path ends in.
    voxel: usize,
    /// How to face at the end.
    look: Look,
    /// Voxels whose being open keeps the goal (a frontier voxel, or the frontier voxels a
    /// candidate pose sees), and around which a fruitless target is sealed.
    watch: Watch,
    /// The frontier the goal is for (fruitless-revisit test, goal report).
    frontier: VoxelIndex,
}

#[derive(Debug, Clone, Copy)]
enum Look {
    /// Stop where this point is seen, facing it.
    At(Point3<f32>),
    /// Fly to the path's end and face this yaw.
    Yaw(f32),
}

/// A baseline planner's target choice (see the [module documentation](self)).
pub struct Baseline {
    kind: PlannerKind,
    gain: GainParams,
    search: Search,
    rng: ChaCha8Rng,
    /// Frontier goals follow the core's view rule first (see [`Baseline::with_core_views`]).
    core_views: bool,
    /// How the last target chosen is looked at, until its goal is chosen.
    look: Look,
}

impl Baseline {
    /// A baseline of `kind` (not a harmonic kind) for a grid of `dims`. `seed` drives its
    /// random choices.
    pub fn new(kind: PlannerKind, dims: harmonic_core::map::Dims, seed: u64) -> Self {
        Self {
            kind,
            gain: GainParams::default(),
            search: Search::new(dims),
            // Decorrelated from the sensor-noise stream drawn from the same seed.
            rng: ChaCha8Rng::seed_from_u64(seed ^ 0x5eed_ba5e_1100_0001),
            core_views: false,
            look: Look::Yaw(0.0),
        }
    }

    /// Lets frontier targets (closest and random frontier) choose their goal by the core's view
    /// rule instead of the thesis's: the first point of the path from which the frontier voxel
    /// is in plain sight within [`ExplorerConfig::view_range_m`](harmonic_core::explore::ExplorerConfig::view_range_m)
    /// (near again after a look that taught nothing). An ablation: it asks whether the harmonic
    /// planner's gain over closest frontier comes from its field or from this rule.
    pub fn with_core_views(mut self) -> Self {
        self.core_views = true;
        self
    }

    /// The planner this is.
    pub fn kind(&self) -> PlannerKind {
        self.kind
    }

    /// Information-gain settings in use.
    pub fn gain_params(&self) -> &GainParams {
        &self.gain
    }

    /// Dijkstra to the first frontier voxel settled.
    fn closest_frontier(&mut self, cx: &Context<'_, '_>, vehicle_i: usize) -> Option<Target> {
        let labels = &*cx.labels;
        let f = self
            .search
            .nearest(labels, vehicle_i, |i| labels[i] == Label::Frontier)?;
        Some(frontier_target(cx, f))
    }

    /// A* to a frontier voxel drawn uniformly at random.
    fn random_frontier(&mut self, cx: &Context<'_, '_>, vehicle_i: usize) -> Option<Target> {
        let frontier: Vec<usize> = (0..cx.labels.len())
            .filter(|&i| cx.labels[i] == Label::Frontier)
            .collect();
        if frontier.is_empty() {
            return None;
        }
        let f = frontier[self.rng.random_range(0..frontier.len())];
        self.search.astar(cx.labels, vehicle_i, f)?;
        Some(frontier_target(cx, f))
    }

    /// Candidate poses from the safe space, scored by the frontier voxels they see.
    fn information_gain(
        &mut self,
        cx: &Context<'_, '_>,
        vehicle_i: usize,
        free: u32,
        weighted: bool,
        steps: &mut u64,
    ) -> Option<Target> {
        self.search.flood(cx.labels, vehicle_i);
        let dims = cx.map.dims();
        let geometry = *cx.map.geometry();
        let res = geometry.resolution();
        let domain: Vec<usize> = (0..cx.labels.len())
            .filter(|&i| cx.labels[i].in_domain())
            .collect();
        let wanted =
            ((free as f32 * self.gain.candidate_fraction).ceil() as usize).clamp(1, domain.len().max(1));
        let mut candidates: Vec<usize> = if wanted >= domain.len() {
            domain.clone()
        } else {
            rand::seq::index::sample(&mut self.rng, domain.len(), wanted)
                .into_iter()
                .map(|k| domain[k])
                .collect()
        };
        candidates.sort_unstable();
        *steps += dims.len() as u64; // the frontier scan below
        let frontier: Vec<VoxelIndex> = (0..dims.len())
            .map(|i| dims.voxel(i))
            .filter(|&v| cx.map.is_frontier(v))
            .collect();
        if frontier.is_empty() {
            return self.closest_frontier(cx, vehicle_i);
        }
        let sample: Vec<VoxelIndex> = if frontier.len() > self.gain.frontier_samples {
            rand::seq::index::sample(&mut self.rng, frontier.len(), self.gain.frontier_samples)
                .into_iter()
                .map(|k| frontier[k])
                .collect()
        } else {
            frontier.clone()
        };
        let scale = frontier.len() as f32 / sample.len() as f32;
        let view = view_of(cx);
        let mut scored: Vec<(f32, usize)> = candidates
            .iter()
            .filter_map(|&c| self.search.distance(c).map(|l| (l * res, c)))
            .collect();
        if weighted {
            // Nearest first: no candidate at path length L can score more than
            // (all frontier voxels)·exp(−λL), so the search stops once that bound is beaten.
            scored.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        }
        let mut best: Option<(f32, f32, usize, Visible)> = None;
        for &(l, c) in &scored {
            if weighted {
                let bound = frontier.len() as f32 * (-self.gain.lambda * l).exp();
                if best.as_ref().is_some_and(|(s, _, _, _)| bound <= *s) {
                    break;
                }
            }
            let seen = visible_frontier(cx.map, &geometry.center(dims.voxel(c)), &sample, &view, steps);
            if seen.count == 0 {
                continue;
            }
            let g = seen.count as f32 * scale;
            let score = if weighted {
                g * (-self.gain.lambda * l).exp()
            } else {
                g
            };
            let better = match &best {
                None => true,
                Some((s, bl, _, _)) => score > *s || (score == *s && l < *bl),
            };
            if better {
                best = Some((score, l, c, seen));
            }
        }
        let Some((_, _, c, seen)) = best else {
            return self.closest_frontier(cx, vehicle_i);
        };
        // The path search above was a full flood: `path(c)` reads it.
        let cv = dims.voxel(c);
        let centre = geometry.center(cv);
        let nearest = seen
            .voxels
            .iter()
            .min_by(|a, b| {
                (geometry.center(**a) - centre)
                    .norm_squared()
                    .total_cmp(&(geometry.center(**b) - centre).norm_squared())
            })
            .copied()
            .unwrap_or(cv);
        let watch = seen.voxels.iter().copied().take(WATCH_CAPACITY).collect();
        Some(Target {
            voxel: c,
            look: Look::Yaw(seen.yaw),
            watch,
            frontier: nearest,
        })
    }

    /// The thesis's rule for a frontier target: the last point of the way, walking back from
    /// its end in half-voxel steps, from which the camera sees `p` (the unknown behind the
    /// frontier) beyond the minimum range and inside the vertical field of view; with
    /// [`Baseline::with_core_views`] first the core's rule ([`first_in_sight`]) unless `near`.
    /// Trims the way to end at the goal; the goal position, the point to face, and whether it
    /// looks from afar.
    fn frontier_goal(
        &self,
        cx: &Context<'_, '_>,
        frontier: VoxelIndex,
        p: Point3<f32>,
        way: &mut Waypoints,
        near: bool,
    ) -> (Point3<f32>, Point3<f32>, bool) {
        let end = way.last().copied().unwrap_or_else(Point3::origin);
        let view = view_of(cx);
        let sees = |q: &Point3<f32>| {
            let d = p - q;
            let horizontal = (d.x * d.x + d.y * d.y).sqrt();
            d.norm() >= view.min_range && d.z.abs() <= horizontal * view.tan_half_v
        };
        let step = 0.5 * cx.map.geometry().resolution();
        let mut chosen = None;
        if self.core_views && !near {
            chosen = first_in_sight(cx, way, frontier, step);
        }
        let from_afar = chosen.is_some();
        // Walk back from the end of the polyline in half-voxel steps.
        'walk: for k in (1..way.len()).rev() {
            if chosen.is_some() {
                break;
            }
            let (a, b) = (way[k - 1], way[k]);
            let len = (b - a).norm();
            let n = (len / step).ceil().max(1.0) as usize;
            for s in (0..=n).rev() {
                let q = a + (b - a) * (s as f32 / n as f32);
                if sees(&q) {
                    chosen = Some((k, q));
                    break 'walk;
                }
            }
        }
        match chosen {
            Some((k, q)) => {
                way.truncate(k);
                let _ = way.push(q);
                (q, p, from_afar)
            }
            None => (end, p, from_afar),
        }
    }
}

impl TargetChoice for Baseline {
    fn choose(
        &mut self,
        cx: Context<'_, '_>,
        position: &Point3<f32>,
        _yaw: f32,
        way: &mut Waypoints,
        clock: &mut impl Clock,
    ) -> Chosen {
        let t1 = clock.ticks();
        let geometry = *cx.map.geometry();
        let vehicle_i = geometry.dims().linear(cx.vehicle);
        let expansions0 = self.search.expansions;
        let mut steps = 0u64;
        let free = cx.map.counts().free;
        let target = match self.kind {
            PlannerKind::RandomFrontier => self.random_frontier(&cx, vehicle_i),
            PlannerKind::InfoGain => self.information_gain(&cx, vehicle_i, free, false, &mut steps),
            PlannerKind::WeightedInfoGain => self.information_gain(&cx, vehicle_i, free, true, &mut steps),
            _ => self.closest_frontier(&cx, vehicle_i),
        };
        let status = &mut *cx.status;
        status.phase_ticks.solve += clock.ticks().saturating_sub(t1);
        let Some(target) = target else {
            status.planning_ops += self.search.expansions - expansions0 + steps;
            status.errors.streamline_failures += 1;
            return Chosen::Hold(Fault::Streamline(StreamlineError::Stalled));
        };
        let path = self.search.path(target.voxel);
        let smoothed = smooth(&geometry, cx.labels, position, &path, &mut steps);
        status.planning_ops += self.search.expansions - expansions0 + steps;
        if !densify(&smoothed, geometry.resolution(), way) {
            status.errors.streamline_failures += 1;
            return Chosen::Hold(Fault::Streamline(StreamlineError::StorageTooSmall));
        }
        self.look = target.look;
        let last = smoothed.last().copied().unwrap_or(*position);
        let before = smoothed.iter().rev().nth(1).copied().unwrap_or(*position);
        let end = StreamlineEnd {
            frontier: target.frontier,
            end: last,
            direction: (last - before).try_normalize(1e-6).unwrap_or(Vector3::x()),
            length: polyline_length(&smoothed),
            steps: path.len() as u32,
            fallback_steps: 0,
        };
        Chosen::Way {
            end,
            watch: target.watch,
        }
    }

    fn goal(
        &mut self,
        cx: Context<'_, '_>,
        end: &StreamlineEnd,
        way: &mut Waypoints,
        yaw: f32,
        near: bool,
    ) -> (Goal, bool) {
        let (position, yaw, from_afar) = match self.look {
            Look::Yaw(y) => (way.last().copied().unwrap_or(end.end), y, false),
            Look::At(p) => {
                let (position, p, from_afar) = self.frontier_goal(&cx, end.frontier, p, way, near);
                let look = p - position;
                let yaw = if look.x.abs() + look.y.abs() > 1e-3 * look.norm().max(1e-6) {
                    look.y.atan2(look.x)
                } else {
                    yaw
                };
                (position, yaw, from_afar)
            }
        };
        let goal = Goal {
            position,
            yaw,
            frontier: end.frontier,
            escape: false,
        };
        (goal, from_afar)
    }

    /// The shortest way to the nearest frontier, with line-of-sight shortcuts.
    fn way_to_frontier(
        &mut self,
        cx: Context<'_, '_>,
        position: &Point3<f32>,
        way: &mut Waypoints,
        _clock: &mut impl Clock,
    ) -> bool {
        let geometry = *cx.map.geometry();
        let labels = &*cx.labels;
        let Some(f) = self
            .search
            .nearest(labels, geometry.dims().linear(cx.vehicle), |i| {
                labels[i] == Label::Frontier
            })
        else {
            return false;
        };
        let mut steps = 0;
        let path = smooth(&geometry, labels, position, &self.search.path(f), &mut steps);
        cx.status.planning_ops += steps;
        fill(way, &path)
    }

    /// A* through the safe space to `home`, smoothed as the exploring paths are.
    fn way_home(
        &mut self,
        cx: Context<'_, '_>,
        position: &Point3<f32>,
        yaw: f32,
        home: &Point3<f32>,
        home_voxel: VoxelIndex,
        way: &mut Waypoints,
        clock: &mut impl Clock,
    ) -> PlanOutcome {
        let t1 = clock.ticks();
        let geometry = *cx.map.geometry();
        let dims = geometry.dims();
        let (from, to) = (dims.linear(cx.vehicle), dims.linear(home_voxel));
        let expansions0 = self.search.expansions;
        let found = self.search.astar(cx.labels, from, to);
        let mut steps = 0u64;
        let mut filled = true;
        if found.is_some() {
            let path = self.search.path(to);
            filled = fill(way, &smooth(&geometry, cx.labels, position, &path, &mut steps));
        }
        cx.status.planning_ops += self.search.expansions - expansions0 + steps;
        cx.status.phase_ticks.solve += clock.ticks().saturating_sub(t1);
        if found.is_none() {
            return PlanOutcome::Hold(Fault::HomeUnreachable);
        }
        if !filled {
            cx.status.errors.streamline_failures += 1;
            return PlanOutcome::Hold(Fault::Streamline(StreamlineError::StorageTooSmall));
        }
        if way.last().is_none_or(|w| (w - home).norm() > 1e-3) && way.push(*home).is_err() {
            cx.status.errors.streamline_failures += 1;
            return PlanOutcome::Hold(Fault::Streamline(StreamlineError::StorageTooSmall));
        }
        PlanOutcome::Goal(Goal {
            position: *home,
            yaw,
            frontier: home_voxel,
            escape: false,
        })
    }
}

/// `way` holds `points` as a way as dense as a streamline is: every corner of the polyline kept,
/// and points between them at most a voxel (`resolution`) apart, or farther where the way is
/// too long for the waypoints' capacity. The explorer tracks a vehicle along a committed way by
/// its nearest waypoint, as along a streamline; on a sparse polyline it would lose it between
/// corners and drop the goal. False (and `way` cut short) if the corners alone do not fit.
fn densify(points: &[Point3<f32>], resolution: f32, way: &mut Waypoints) -> bool {
    way.clear();
    let capacity = way.capacity();
    if points.len() > capacity {
        return false;
    }
    let Some(&first) = points.first() else {
        return true;
    };
    let room = (capacity - points.len()).max(1);
    let spacing = resolution.max(polyline_length(points) / room as f32);
    let _ = way.push(first);
    for w in points.windows(2) {
        let n = ((w[1] - w[0]).norm() / spacing).ceil().max(1.0) as usize;
        for k in 1..=n {
            if way.push(w[0] + (w[1] - w[0]) * (k as f32 / n as f32)).is_err() {
                return false;
            }
        }
    }
    true
}

/// `way` holds `points`; false (and `way` cut short) if they do not fit.
fn fill(way: &mut Waypoints, points: &[Point3<f32>]) -> bool {
    way.clear();
    points.iter().all(|p| way.push(*p).is_ok())
}

/// A frontier voxel `f` as a target: looked at where the unknown behind it is.
fn frontier_target(cx: &Context<'_, '_>, f: usize) -> Target {
    let fv = cx.map.dims().voxel(f);
    let mut watch = Watch::new();
    let _ = watch.push(fv);
    Target {
        voxel: f,
        look: Look::At(unknown_behind(cx, fv)),
        watch,
        frontier: fv,
    }
}

/// The centroid of the unexplored voxels that make `f` a frontier (what the camera should look
/// at); the frontier's centre if there are none.
fn unknown_behind(cx: &Context<'_, '_>, f: VoxelIndex) -> Point3<f32> {
    let dims = cx.map.dims();
    let g = cx.map.geometry();
    let reach = harmonic_core::domain::frontier_reach(cx.stencil);
    let (mut sum, mut n) = (Vector3::zeros(), 0u32);
    for dz in -reach..=reach {
        for dy in -reach..=reach {
            for dx in -reach..=reach {
                if let Some(v) = dims.offset(f, [dx, dy, dz]) {
                    if cx.map.is_unexplored(dims.linear(v)) {
                        sum += g.center(v).coords;
                        n += 1;
                    }
                }
            }
        }
    }
    if n == 0 {
        g.center(f)
    } else {
        Point3::from(sum / n as f32)
    }
}

/// The camera's view for the explorer's configuration and the last frame's intrinsics.
fn view_of(cx: &Context<'_, '_>) -> View {
    let (h, v) = cx
        .intrinsics
        .map(|i| i.half_fov())
        .unwrap_or((37.5f32.to_radians(), 37.5f32.to_radians()));
    View {
        half_h: h * cx.config.view_margin,
        tan_half_v: (v * cx.config.view_margin).tan(),
        min_range: cx.config.integration.min_range + cx.map.geometry().resolution(),
        max_range: cx.config.integration.max_range,
    }
}

/// The core's view rule on a sparse way: the first point, walking from the vehicle in steps of
/// `step` metres, from which `frontier` lies within the view range, inside the vertical field
/// of view, in plain sight through free voxels. `(segment end index, point)`.
fn first_in_sight(
    cx: &Context<'_, '_>,
    way: &Waypoints,
    frontier: VoxelIndex,
    step: f32,
) -> Option<(usize, Point3<f32>)> {
    let view = view_of(cx);
    let g = *cx.map.geometry();
    let f = g.center(frontier);
    let in_sight = |q: &Point3<f32>| {
        let d = f - q;
        let horizontal = (d.x * d.x + d.y * d.y).sqrt();
        if d.norm() > cx.config.view_range_m || d.z.abs() > horizontal * view.tan_half_v {
            return false;
        }
        let mut clear = true;
        traverse(&g, q, &f, |v| {
            clear &= cx.map.is_free(g.dims().linear(v));
            clear
        });
        clear
    };
    for k in 1..way.len() {
        let (a, b) = (way[k - 1], way[k]);
        let n = ((b - a).norm() / step).ceil().max(1.0) as usize;
        for s in 0..=n {
            let q = a + (b - a) * (s as f32 / n as f32);
            if in_sight(&q) {
                return Some((k, q));
            }
        }
    }
    None
}

fn polyline_length(points: &[Point3<f32>]) -> f32 {
    points.windows(2).map(|w| (w[1] - w[0]).norm()).sum()
}

/// The camera's view for visibility tests.
#[derive(Debug, Clone, Copy)]
struct View {
    /// Half the horizontal field of view kept for targets, radians.
    half_h: f32,
    /// Tangent of half the vertical field of view kept for targets.
    tan_half_v: f32,
    /// Closest useful range, metres.
    min_range: f32,
    /// Farthest range, metres.
    max_range: f32,
}

/// Frontier voxels seen from a pose with its best yaw.
#[derive(Debug, Clone, Default)]
struct Visible {
    count: usize,
    yaw: f32,
    voxels: Vec<VoxelIndex>,
}

/// Which of `frontier` a camera at `p` sees for the best yaw: in range, inside the vertical
/// field of view, with every voxel of the line of sight free, and inside the horizontal field of
/// view of the yaw that sees the most of them.
fn visible_frontier(
    map: &VoxelMap<'_>,
    p: &Point3<f32>,
    frontier: &[VoxelIndex],
    view: &View,
    steps: &mut u64,
) -> Visible {
    let geometry = *map.geometry();
    let dims = geometry.dims();
    let mut seen: Vec<(f32, VoxelIndex)> = Vec::new();
    for &f in frontier {
        let q = geometry.center(f);
        let d = q - p;
        let dist = d.norm();
        if dist < view.min_range || dist > view.max_range {
            continue;
        }
        let horizontal = (d.x * d.x + d.y * d.y).sqrt();
        if d.z.abs() > horizontal * view.tan_half_v {
            continue;
        }
        let fi = dims.linear(f);
        let mut clear = true;
        let n = traverse(&geometry, p, &q, |v| {
            let i = dims.linear(v);
            clear &= i == fi || map.is_free(i);
            clear && i != fi
        });
        *steps += u64::from(n);
        if clear {
            seen.push((d.y.atan2(d.x), f));
        }
    }
    if seen.is_empty() {
        return Visible::default();
    }
    seen.sort_by(|a, b| a.0.total_cmp(&b.0));
    // Sliding window of width 2·half_h over the circle of azimuths.
    let n = seen.len();
    let width = 2.0 * view.half_h;
    let az = |k: usize| {
        if k < n {
            seen[k].0
        } else {
            seen[k - n].0 + std::f32::consts::TAU
        }
    };
    let (mut best, mut best_start, mut j) = (0usize, 0usize, 0usize);
    for i in 0..n {
        if j < i {
            j = i;
        }
        while j + 1 < i + n && az(j + 1) - az(i) <= width {
            j += 1;
        }
        if j - i + 1 > best {
            best = j - i + 1;
            best_start = i;
        }
    }
    let first = az(best_start);
    let last = az(best_start + best - 1);
    let yaw = 0.5 * (first + last);
    let voxels = (best_start..best_start + best).map(|k| seen[k % n].1).collect();
    Visible {
        count: best,
        yaw: (yaw + std::f32::consts::PI).rem_euclid(std::f32::consts::TAU) - std::f32::consts::PI,
        voxels,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::planners::storage::HostClock;
    use harmonic_core::explore::{Explorer, ExplorerConfig, Status};
    use harmonic_core::map::{Dims, LogOddsParams, MapGeometry};

    #[test]
    fn visibility_picks_the_yaw_that_sees_most_and_walls_block() {
        // 40 × 40 × 5 voxels of 0.1 m, all free; a row of frontier-like targets to the east
        // (three) and one to the west; an occupied voxel hides one of the eastern ones.
        let g = MapGeometry::new(Dims::new(40, 40, 5).unwrap(), Point3::origin(), 0.1).unwrap();
        let n = g.dims().len();
        let (mut lo, mut st) = (
            vec![0i8; n],
            vec![0u32; harmonic_core::map::touched_words(&g.dims())],
        );
        let mut map = VoxelMap::new(g, LogOddsParams::default(), &mut lo, &mut st).unwrap();
        for i in 0..n {
            map.apply_miss(i);
        }
        let v = |x: u16, y: u16| VoxelIndex::new(x, y, 2);
        map.begin_frame();
        map.apply_hit(g.dims().linear(v(30, 25)));
        let targets = [v(35, 20), v(35, 21), v(35, 25), v(5, 20)];
        let view = View {
            half_h: 0.5,
            tan_half_v: 0.7,
            min_range: 0.4,
            max_range: 10.0,
        };
        let p = g.center(v(20, 20));
        let mut steps = 0;
        let seen = visible_frontier(&map, &p, &targets, &view, &mut steps);
        // (35,25) is behind the hit at (30,25)... only if on the line; it is not: the line from
        // (20,20) to (35,25) passes (30, 23.3). Both eastern rows are seen, the west one is not in
        // the same window.
        assert_eq!(seen.count, 3, "{seen:?}");
        assert!(seen.yaw.abs() < 0.5, "{}", seen.yaw);
        assert!(steps > 0);
        // Put a wall across the line of sight to the two at y = 20/21.
        map.begin_frame();
        for y in 18..24 {
            map.apply_hit(g.dims().linear(v(28, y)));
        }
        let seen = visible_frontier(&map, &p, &targets, &view, &mut steps);
        assert_eq!(seen.count, 1, "{seen:?}");
    }

    #[test]
    fn a_way_is_made_as_dense_as_a_streamline_keeping_its_corners() {
        let corners = [
            Point3::new(0.0, 0.0, 1.0),
            Point3::new(2.0, 0.0, 1.0),
            Point3::new(2.0, 1.5, 1.0),
        ];
        let mut way = Waypoints::new();
        assert!(densify(&corners, 0.1, &mut way));
        assert_eq!(way.len(), 1 + 20 + 15);
        for c in corners {
            assert!(way.iter().any(|w| (w - c).norm() < 1e-6), "corner {c} kept");
        }
        assert!(way.windows(2).all(|w| (w[1] - w[0]).norm() <= 0.1 + 1e-5));
        assert!((polyline_length(&way) - 3.5).abs() < 1e-4, "the same way");
        // A way longer than the capacity holds at a voxel's spacing gets wider spacing, and
        // still every corner.
        let long = [
            corners[0],
            Point3::new(30.0, 0.0, 1.0),
            Point3::new(30.0, 20.0, 1.0),
        ];
        assert!(densify(&long, 0.1, &mut way));
        assert!(way.len() <= way.capacity());
        assert!(way.iter().any(|w| (w - long[1]).norm() < 1e-6));
        assert_eq!(way.last(), Some(&long[2]));
    }

    /// Closest frontier from one end of a 6 × 1 × 1 m hall seen free but for a pocket of
    /// 2 × 2 × 2 unknown voxels at voxel x = `pocket_x`, with the explorer's rule for far
    /// remnants on or off.
    fn closest_frontier_to_a_pocket(pocket_x: u16, remnants: bool) -> (PlanOutcome, Status) {
        let dims = Dims::new(60, 10, 10).unwrap();
        let g = MapGeometry::new(dims, Point3::origin(), 0.1).unwrap();
        let mut storage = crate::planners::storage::HostStorage::new(&dims);
        let mut config = ExplorerConfig {
            vehicle_radius: 0.05,
            ..Default::default()
        };
        if !remnants {
            config.remnant_frontier_m2 = 0.0;
        }
        let targets = Baseline::new(PlannerKind::ClosestFrontier, dims, 1);
        let mut planner = Explorer::with_targets(g, config, storage.lend(), targets).unwrap();
        for i in 0..dims.len() {
            let v = dims.voxel(i);
            let in_pocket =
                (pocket_x..pocket_x + 2).contains(&v.x) && (4..6).contains(&v.y) && (4..6).contains(&v.z);
            if !in_pocket {
                planner.map_mut().apply_miss(i);
            }
        }
        let outcome = planner.plan_timed(&Point3::new(0.25, 0.5, 0.5), 0.0, &mut HostClock::new());
        (outcome, *planner.status())
    }

    #[test]
    fn closest_frontier_seals_a_far_remnant_as_the_harmonic_planner_does() {
        // The thesis's closest frontier flies to the last crumb however far it is.
        let (outcome, status) = closest_frontier_to_a_pocket(50, false);
        assert!(matches!(outcome, PlanOutcome::Goal(_)), "{outcome:?}");
        assert_eq!(status.errors.remnants_sealed, 0);
        // Inside the explorer's loop it seals it, as the harmonic planner does, and is done.
        let (outcome, status) = closest_frontier_to_a_pocket(50, true);
        assert_eq!(outcome, PlanOutcome::Complete, "{status:?}");
        assert_eq!(status.errors.remnants_sealed, 1);
        // A near crumb is still looked at.
        let (outcome, status) = closest_frontier_to_a_pocket(10, true);
        assert!(matches!(outcome, PlanOutcome::Goal(_)), "{outcome:?}");
        assert_eq!(status.errors.remnants_sealed, 0);
    }

    /// Shortest 26-connected path lengths (voxels) from `source` over in-domain voxels, by
    /// plain Bellman-Ford relaxation: an implementation independent of [`Search`].
    fn brute_force_distances(dims: Dims, labels: &[Label], source: usize) -> Vec<f32> {
        let mut dist = vec![f32::INFINITY; dims.len()];
        dist[source] = 0.0;
        let ok = |v: Option<VoxelIndex>| v.is_some_and(|v| labels[dims.linear(v)].in_domain());
        loop {
            let mut changed = false;
            for i in 0..dims.len() {
                if !dist[i].is_finite() {
                    continue;
                }
                let v = dims.voxel(i);
                for dz in -1..=1i32 {
                    for dy in -1..=1i32 {
                        for dx in -1..=1i32 {
                            let d = [dx, dy, dz];
                            if d == [0, 0, 0] || !ok(dims.offset(v, d)) {
                                continue;
                            }
                            // No corner cutting: every sub-step of the move must be passable.
                            let sub_ok = (1u8..7).all(|m| {
                                let s = [0, 1, 2].map(|a| if m & (1 << a) != 0 { d[a] } else { 0 });
                                s == [0, 0, 0] || ok(dims.offset(v, s))
                            });
                            if !sub_ok {
                                continue;
                            }
                            let n = dims.linear(dims.offset(v, d).unwrap());
                            let c = dist[i] + ((dx * dx + dy * dy + dz * dz) as f32).sqrt();
                            if c + 1e-5 < dist[n] {
                                dist[n] = c;
                                changed = true;
                            }
                        }
                    }
                }
            }
            if !changed {
                return dist;
            }
        }
    }

    proptest::proptest! {
        #![proptest_config(proptest::prelude::ProptestConfig::with_cases(48))]
        /// Closest frontier never picks a frontier farther (by shortest safe path) than another.
        #[test]
        fn closest_frontier_never_picks_a_farther_frontier(
            cells in proptest::collection::vec(0u8..10, 10 * 10 * 4),
            vx in 1u16..9, vy in 1u16..9,
        ) {
            let dims = Dims::new(10, 10, 4).unwrap();
            let g = MapGeometry::new(dims, Point3::origin(), 0.1).unwrap();
            let n = dims.len();
            let mut storage = crate::planners::storage::HostStorage::new(&dims);
            let config = ExplorerConfig { vehicle_radius: 0.0, ..Default::default() };
            let targets = Baseline::new(PlannerKind::ClosestFrontier, dims, 1);
            let mut planner = Explorer::with_targets(g, config, storage.lend(), targets).unwrap();
            // 0..=5 free, 6..=7 occupied, 8..=9 unknown.
            for (i, &c) in cells.iter().enumerate() {
                match c {
                    0..=5 => planner.map_mut().apply_miss(i),
                    6..=7 => planner.map_mut().apply_hit(i),
                    _ => false,
                };
            }
            let vehicle = VoxelIndex::new(vx, vy, 1);
            let vi = dims.linear(vehicle);
            for _ in 0..3 {
                planner.map_mut().begin_frame();
                planner.map_mut().apply_miss(vi);
            }
            let position = g.center(vehicle);
            let outcome = planner.plan_timed(&position, 0.0, &mut HostClock::new());
            let labels = planner.labels().to_vec();
            let frontiers: Vec<usize> = (0..n).filter(|&i| labels[i] == Label::Frontier).collect();
            match outcome {
                PlanOutcome::Goal(goal) => {
                    let dist = brute_force_distances(dims, &labels, vi);
                    let chosen = dist[dims.linear(goal.frontier)];
                    proptest::prop_assert!(labels[dims.linear(goal.frontier)] == Label::Frontier);
                    for &f in &frontiers {
                        proptest::prop_assert!(
                            chosen <= dist[f] + 1e-4,
                            "chose {:?} at {} but {:?} is at {}", goal.frontier, chosen, dims.voxel(f), dist[f]
                        );
                    }
                }
                PlanOutcome::Complete => proptest::prop_assert!(frontiers.is_empty()),
                PlanOutcome::Hold(f) => proptest::prop_assert!(false, "hold {:?}", f),
            }
        }
    }
}
