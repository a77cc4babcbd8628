//! Streamlines: steepest descent of φ from the vehicle to a frontier.
//!
//! The field holds ψ = 1 − φ (see [`crate::planning::solve`]), so descending φ is ascending ψ; all
//! differences are taken in ψ, where the vehicle's surroundings have full f32 precision. The
//! default planning field ([`crate::planning::field`]) stores its u (1 on frontiers, smaller elsewhere)
//! in the same buffer, and the same ascent follows it to a frontier.
//!
//! The gradient is taken by central differences at voxel centres (a neighbour outside the domain
//! mirrors the centre value — zero flux — so walls contribute no normal component) and
//! interpolated trilinearly between the in-domain centres around a point. The tracer integrates
//! the unit descent direction with classical RK4 at a fixed step (at most half a voxel) and stops
//! on entering a frontier voxel.
//!
//! A harmonic φ has no interior local minimum, so the continuous streamline always ends on a
//! frontier. The discrete one can still stall where the interpolated gradient vanishes (a
//! saddle, a plateau below f32 resolution), leave the domain at a corner, or loop inside one
//! voxel. Each of those falls back to one step of *discrete* steepest descent: to the face
//! neighbour with the lowest φ, which the discrete maximum principle guarantees is lower than
//! the current voxel unless φ is constant around it. The first step from the source voxel is
//! always discrete (max flux out of the source), because the gradient at a point source is
//! ill-defined.
//!
//! Waypoints are kept in a fixed-capacity buffer: when it fills, every other waypoint is dropped
//! and the spacing doubles, so any path fits with bounded memory.

use heapless::Vec as HVec;
use nalgebra::{Point3, Vector3};

use crate::mapping::map::{MapGeometry, VoxelIndex};
use crate::planning::domain::Label;

/// Waypoint buffer capacity.
pub const WAYPOINT_CAPACITY: usize = 128;

/// Waypoints of a streamline, map frame.
pub type Waypoints = HVec<Point3<f32>, WAYPOINT_CAPACITY>;

/// Tracer settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StreamlineParams {
    /// RK4 step in voxels; clamped to (0.05, 0.5].
    pub step_voxels: f32,
    /// Give up after this many steps.
    pub max_steps: u32,
}

impl Default for StreamlineParams {
    fn default() -> Self {
        Self {
            step_voxels: 0.5,
            max_steps: 50_000,
        }
    }
}

/// Where and how a streamline ended.
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct StreamlineEnd {
    /// The frontier voxel it entered.
    pub frontier: VoxelIndex,
    /// Its final point, map frame.
    pub end: Point3<f32>,
    /// Unit direction of travel at the end (map frame).
    pub direction: Vector3<f32>,
    /// Path length, metres.
    pub length: f32,
    /// RK4 steps taken.
    pub steps: u32,
    /// Discrete fallback steps taken.
    pub fallback_steps: u32,
}

/// Why no streamline could be traced.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum StreamlineError {
    /// The start point is not in a domain voxel.
    StartOutsideDomain,
    /// No neighbour has a lower φ (φ is flat here: unsolved or below f32 resolution).
    Stalled,
    /// The step cap was hit.
    TooLong,
    /// `labels` or `phi` is shorter than the grid.
    StorageTooSmall,
}

/// The φ field and its domain, read-only.
#[derive(Clone, Copy)]
pub struct Field<'a> {
    /// Grid geometry.
    pub geometry: &'a MapGeometry,
    /// Domain labels.
    pub labels: &'a [Label],
    /// Stored potential: ψ = 1 − φ for the seed's field, u for the screened field (both 1 on
    /// frontiers, rising towards them).
    pub phi: &'a [f32],
}

impl Field<'_> {
    fn label(&self, v: VoxelIndex) -> Label {
        self.labels
            .get(self.geometry.dims().linear(v))
            .copied()
            .unwrap_or(Label::Outside)
    }
    fn phi_at(&self, v: VoxelIndex) -> f32 {
        self.phi
            .get(self.geometry.dims().linear(v))
            .copied()
            .unwrap_or(0.0)
    }
    fn in_domain(&self, v: VoxelIndex) -> bool {
        self.label(v).in_domain()
    }
    fn voxel_of(&self, g: &Vector3<f32>) -> Option<VoxelIndex> {
        let f = |c: f32| libm::floorf(c) as i32;
        self.geometry.dims().checked(f(g.x), f(g.y), f(g.z))
    }

    /// Central-difference gradient at a domain voxel centre (grid units).
    fn centre_gradient(&self, v: VoxelIndex) -> Vector3<f32> {
        let dims = self.geometry.dims();
        let c = self.phi_at(v);
        let side = |d: [i32; 3]| match dims.offset(v, d) {
            Some(n) if self.in_domain(n) => self.phi_at(n),
            _ => c,
        };
        Vector3::new(
            0.5 * (side([1, 0, 0]) - side([-1, 0, 0])),
            0.5 * (side([0, 1, 0]) - side([0, -1, 0])),
            0.5 * (side([0, 0, 1]) - side([0, 0, -1])),
        )
    }

    /// Trilinear interpolation of the centre gradients of ψ of the in-domain voxels around `p`
    /// (grid coordinates), renormalised over those present. `None` if none is.
    pub fn gradient(&self, p: &Vector3<f32>) -> Option<Vector3<f32>> {
        let q = p - Vector3::repeat(0.5);
        let base = q.map(libm::floorf);
        let frac = q - base;
        let dims = self.geometry.dims();
        let mut sum = Vector3::zeros();
        let mut wsum = 0.0f32;
        for corner in 0..8u8 {
            let o = Vector3::new(corner & 1, (corner >> 1) & 1, (corner >> 2) & 1);
            let Some(v) = dims.checked(
                base.x as i32 + i32::from(o.x),
                base.y as i32 + i32::from(o.y),
                base.z as i32 + i32::from(o.z),
            ) else {
                continue;
            };
            if !self.in_domain(v) {
                continue;
            }
            let w = o
                .iter()
                .zip(frac.iter())
                .map(|(&o, &f)| if o == 1 { f } else { 1.0 - f })
                .product::<f32>();
            sum += self.centre_gradient(v) * w;
            wsum += w;
        }
        (wsum > 1e-6).then(|| sum / wsum)
    }

    /// Unit direction of steepest descent of φ (ascent of ψ) at `p`, if resolvable.
    fn descent(&self, p: &Vector3<f32>) -> Option<Vector3<f32>> {
        let g = self.gradient(p)?;
        let n = g.norm();
        (n.is_finite() && n > 1e-30).then(|| g / n)
    }

    /// A frontier face neighbour of `v`, the one most in line with the descent direction at `p`.
    fn frontier_neighbour(&self, v: VoxelIndex, p: &Vector3<f32>) -> Option<VoxelIndex> {
        let dims = self.geometry.dims();
        let toward = self.descent(p).unwrap_or_else(Vector3::zeros);
        let mut best: Option<(f32, VoxelIndex)> = None;
        for d in crate::mapping::map::FACE_OFFSETS {
            let Some(n) = dims.offset(v, d) else { continue };
            if self.label(n) != Label::Frontier {
                continue;
            }
            let align = toward.dot(&Vector3::new(d[0] as f32, d[1] as f32, d[2] as f32));
            if best.is_none_or(|(a, _)| align > a) {
                best = Some((align, n));
            }
        }
        best.map(|(_, n)| n)
    }

    /// The face neighbour (or for the source, any of the 26 neighbours reachable through
    /// in-domain faces) with the steepest drop of φ per unit distance, if φ drops at all.
    fn steepest_neighbour(&self, v: VoxelIndex, all_26: bool) -> Option<VoxelIndex> {
        let dims = self.geometry.dims();
        let here = self.phi_at(v);
        let mut best: Option<(f32, VoxelIndex)> = None;
        for dz in -1i32..=1 {
            for dy in -1i32..=1 {
                for dx in -1i32..=1 {
                    let manhattan = dx.abs() + dy.abs() + dz.abs();
                    if manhattan == 0 || (!all_26 && manhattan > 1) {
                        continue;
                    }
                    let Some(n) = dims.offset(v, [dx, dy, dz]) else {
                        continue;
                    };
                    if !self.in_domain(n) {
                        continue;
                    }
                    // A diagonal move must not cut a corner of a wall: every face-step
                    // component must itself land in the domain.
                    let corner_clear = [[dx, 0, 0], [0, dy, 0], [0, 0, dz]]
                        .iter()
                        .filter(|d| d.iter().any(|&c| c != 0))
                        .all(|d| dims.offset(v, *d).is_some_and(|m| self.in_domain(m)));
                    if manhattan > 1 && !corner_clear {
                        continue;
                    }
                    let drop = (self.phi_at(n) - here) / libm::sqrtf(manhattan as f32);
                    if rises(here, self.phi_at(n)) && best.is_none_or(|(d, _)| drop > d) {
                        best = Some((drop, n));
                    }
                }
            }
        }
        best.map(|(_, n)| n)
    }
}

/// Traces the streamline from `start` (map frame, inside the source voxel or any domain voxel)
/// to a frontier. Waypoints (start included, end included) go to `out`.
pub fn trace(
    field: &Field<'_>,
    start: &Point3<f32>,
    params: &StreamlineParams,
    out: &mut Waypoints,
) -> Result<StreamlineEnd, StreamlineError> {
    let n = field.geometry.dims().len();
    if field.labels.len() < n || field.phi.len() < n {
        return Err(StreamlineError::StorageTooSmall);
    }
    out.clear();
    let h = params.step_voxels.clamp(0.05, 0.5);
    let mut rec = Recorder {
        spacing: 1.0,
        since_last: 0.0,
    };
    let mut p = field.geometry.to_grid(start);
    let mut cell = field
        .voxel_of(&p)
        .filter(|v| field.in_domain(*v))
        .ok_or(StreamlineError::StartOutsideDomain)?;
    rec.push(field, out, &p, true);
    let mut end = StreamlineEnd {
        frontier: cell,
        end: *start,
        direction: Vector3::x(),
        length: 0.0,
        steps: 0,
        fallback_steps: 0,
    };
    let centre =
        |v: VoxelIndex| Vector3::new(f32::from(v.x) + 0.5, f32::from(v.y) + 0.5, f32::from(v.z) + 0.5);
    let mut steps_in_cell = 0u32;
    let cell_budget = libm::ceilf(3.0 / h) as u32;

    while field.label(cell) != Label::Frontier {
        if end.steps + end.fallback_steps >= params.max_steps {
            return Err(StreamlineError::TooLong);
        }
        let rk4 = if field.label(cell) == Label::Source || steps_in_cell > cell_budget {
            None
        } else {
            rk4_step(field, &p, h)
        };
        // A move that changes voxel must strictly descend φ (ascend ψ): then no voxel is entered
        // twice and no plateau — a dead-end pocket at constant ψ — can trap the tracer.
        let next = rk4.and_then(|q| {
            let v = field.voxel_of(&q)?;
            (field.in_domain(v) && (v == cell || rises(field.phi_at(cell), field.phi_at(v))))
                .then_some((q, v))
        });
        let (q, v) = match (field.frontier_neighbour(cell, &p), next) {
            // Next to a frontier: step into it (it is the highest ψ there is).
            (Some(f), _) => {
                end.fallback_steps += 1;
                (centre(f), f)
            }
            (None, Some(step)) => {
                end.steps += 1;
                step
            }
            (None, None) => {
                let v = field
                    .steepest_neighbour(cell, field.label(cell) == Label::Source)
                    .ok_or(StreamlineError::Stalled)?;
                end.fallback_steps += 1;
                (centre(v), v)
            }
        };
        let d = q - p;
        let len = d.norm();
        if len > 0.0 {
            end.direction = d / len;
            end.length += len;
            rec.since_last += len;
        }
        steps_in_cell = if v == cell { steps_in_cell + 1 } else { 0 };
        p = q;
        cell = v;
        rec.push(field, out, &p, false);
    }
    rec.push(field, out, &p, true);
    end.frontier = cell;
    end.end = field.geometry.from_grid(&p);
    end.length *= field.geometry.resolution();
    // Grid and map axes are parallel with one scale, so the unit direction carries over as is.
    Ok(end)
}

/// True if the segment `a → b` passes only through domain voxels (the inflated safe space);
/// `steps` counts the voxels looked at. The core's taut paths and the host's baseline planners
/// share it.
pub fn line_of_sight(
    geometry: &MapGeometry,
    labels: &[Label],
    a: &Point3<f32>,
    b: &Point3<f32>,
    steps: &mut u64,
) -> bool {
    let dims = geometry.dims();
    let mut clear = true;
    let n = crate::mapping::integrate::traverse(geometry, a, b, |v| {
        clear &= labels.get(dims.linear(v)).is_some_and(|l| l.in_domain());
        clear
    });
    *steps += u64::from(n);
    clear && n > 0
}

/// Pulls a traced path taut: from each kept waypoint, the path goes straight to the farthest
/// later waypoint it reaches in a straight line through domain voxels (greedy string pulling,
/// stopping at the first waypoint it cannot reach), and the waypoints in between are moved onto
/// that straight segment, evenly spaced. The first and last waypoints stay where they are, so a
/// path that ended on a frontier still does, and no waypoint is added or removed: the spacing
/// only shrinks, and a caller that tracks the vehicle by its nearest waypoint keeps working.
///
/// A gradient path bends wherever the field does — towards frontier mass in an open hall,
/// around the rim of a wall's zero-flux boundary — while the vehicle only has to stay in the
/// inflated safe space that the domain voxels are. Returns the voxels the line-of-sight checks
/// visited (planning work). Waypoints outside the grid or a short `labels` leave the path as
/// it is.
pub fn pull_taut(geometry: &MapGeometry, labels: &[Label], waypoints: &mut [Point3<f32>]) -> u64 {
    if labels.len() < geometry.dims().len() {
        return 0;
    }
    let mut visited = 0u64;
    let mut reaches = |a: &Point3<f32>, b: &Point3<f32>| line_of_sight(geometry, labels, a, b, &mut visited);
    let n = waypoints.len();
    let mut anchor = 0;
    while anchor + 2 < n {
        let Some(&a) = waypoints.get(anchor) else {
            break;
        };
        let mut reach = anchor + 1;
        while let Some(b) = waypoints.get(reach + 1) {
            if !reaches(&a, b) {
                break;
            }
            reach += 1;
        }
        if let Some(&b) = waypoints.get(reach) {
            let span = (reach - anchor) as f32;
            for k in anchor + 1..reach {
                if let Some(w) = waypoints.get_mut(k) {
                    *w = a + (b - a) * ((k - anchor) as f32 / span);
                }
            }
        }
        anchor = reach;
    }
    visited
}

/// How close (metres) a vehicle following a path must come to a waypoint before the next one
/// is its setpoint, on a straight stretch; where the path turns, [`advance_radius`] is less.
pub const WAYPOINT_ADVANCE_M: f32 = 0.1;
/// How far a turn's corner may be cut by streaming the next waypoint early, metres: the path
/// turns round obstacles, so the inside of a corner is where they are.
pub const CORNER_CUT_M: f32 = 0.02;
/// Least advance radius at a sharp turn, metres: a real autopilot holds a setpoint to a few
/// centimetres, and a radius below that would never be met.
pub const MIN_ADVANCE_M: f32 = 0.03;

/// How close the vehicle must come to `waypoints[i]` before the next waypoint is
/// the setpoint: [`WAYPOINT_ADVANCE_M`] where the path runs straight on, less where it turns by θ,
/// so that flying straight at the next waypoint cuts the corner by at most
/// [`CORNER_CUT_M`] (≈ radius · sin θ; a turn of more than 90° counts as sin θ = 1), and never
/// less than [`MIN_ADVANCE_M`].
pub fn advance_radius(waypoints: &[Point3<f32>], i: usize) -> f32 {
    let (Some(prev), Some(here), Some(next)) = (
        i.checked_sub(1).and_then(|j| waypoints.get(j)),
        waypoints.get(i),
        waypoints.get(i + 1),
    ) else {
        return WAYPOINT_ADVANCE_M;
    };
    let (din, dout) = (here - prev, next - here);
    let (lin, lout) = (din.norm(), dout.norm());
    if lin < 1e-6 || lout < 1e-6 {
        return WAYPOINT_ADVANCE_M;
    }
    let sin = if din.dot(&dout) < 0.0 {
        1.0
    } else {
        din.cross(&dout).norm() / (lin * lout)
    };
    if sin * WAYPOINT_ADVANCE_M <= CORNER_CUT_M {
        WAYPOINT_ADVANCE_M
    } else {
        (CORNER_CUT_M / sin).max(MIN_ADVANCE_M)
    }
}
/// True if ψ rises from `a` to `b` by more than rounding: a few ulps of `a`. A dead-end pocket
/// carries no flux, so its ψ equals its entrance's up to rounding; stepping into it on a
/// one-ulp "rise" would strand the tracer on a plateau with no way up.
#[inline]
fn rises(a: f32, b: f32) -> bool {
    b - a > 4.0 * f32::EPSILON * a.abs()
}

fn rk4_step(field: &Field<'_>, p: &Vector3<f32>, h: f32) -> Option<Vector3<f32>> {
    let k1 = field.descent(p)?;
    let k2 = field.descent(&(p + k1 * (0.5 * h)))?;
    let k3 = field.descent(&(p + k2 * (0.5 * h)))?;
    let k4 = field.descent(&(p + k3 * h))?;
    let q = p + (k1 + k2 * 2.0 + k3 * 2.0 + k4) * (h / 6.0);
    q.iter().all(|c| c.is_finite()).then_some(q)
}

/// Keeps waypoints about `spacing` voxels apart, halving the list when it fills.
struct Recorder {
    spacing: f32,
    since_last: f32,
}

impl Recorder {
    fn push(&mut self, field: &Field<'_>, out: &mut Waypoints, g: &Vector3<f32>, force: bool) {
        if !force && self.since_last < self.spacing {
            return;
        }
        self.since_last = 0.0;
        let p = field.geometry.from_grid(g);
        if out.is_full() {
            // Keep the first point and every other one after it; double the spacing.
            let mut kept = 0;
            for i in (0..out.len()).step_by(2) {
                if let Some(&w) = out.get(i) {
                    if let Some(slot) = out.get_mut(kept) {
                        *slot = w;
                    }
                    kept += 1;
                }
            }
            out.truncate(kept);
            self.spacing *= 2.0;
        }
        // Not full after halving (capacity ≥ 2).
        let _ = out.push(p);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mapping::map::Dims;
    use crate::planning::solve::{gauss_seidel, SolveParams};

    #[test]
    fn l_shaped_corridor_streamline_turns_the_corner_and_ends_on_the_frontier() {
        // 2D L: a corridor along x (y = 1..=3) then up along y at x = 10..=12.
        let dims = Dims::new(14, 14, 1).unwrap();
        let g = MapGeometry::new(dims, Point3::origin(), 0.1).unwrap();
        let mut labels = [Label::Outside; 196];
        for y in 1..=3 {
            for x in 1..=12 {
                labels[dims.linear(VoxelIndex::new(x, y, 0))] = Label::Interior;
            }
        }
        for y in 4..=12 {
            for x in 10..=12 {
                labels[dims.linear(VoxelIndex::new(x, y, 0))] = Label::Interior;
            }
        }
        for x in 10..=12 {
            labels[dims.linear(VoxelIndex::new(x, 12, 0))] = Label::Frontier;
        }
        let src = VoxelIndex::new(2, 2, 0);
        labels[dims.linear(src)] = Label::Source;
        let mut phi = [0.0f32; 196];
        let s = gauss_seidel(&dims, &labels, &mut phi, &SolveParams::default()).unwrap();
        assert!(s.converged);
        let field = Field {
            geometry: &g,
            labels: &labels,
            phi: &phi,
        };
        let mut wps = Waypoints::new();
        let end = trace(&field, &g.center(src), &StreamlineParams::default(), &mut wps).unwrap();
        assert_eq!(end.frontier.y, 12);
        assert!(
            end.direction.y > 0.9,
            "arrives heading into the unknown: {:?}",
            end.direction
        );
        for w in &wps {
            let v = g.voxel_at(w).unwrap();
            assert!(
                labels[dims.linear(v)].in_domain(),
                "waypoint {w:?} outside the domain"
            );
        }
        // Path at least the Manhattan-free distance, not absurdly longer.
        assert!(end.length > 1.4 && end.length < 2.6, "{}", end.length);

        // Pulled taut it still ends on the frontier, turns the corner inside the corridor, and
        // is no longer.
        let traced = wps.clone();
        pull_taut(&g, &labels, &mut wps);
        assert_eq!(wps.len(), traced.len());
        assert_eq!(wps.first(), traced.first());
        assert_eq!(wps.last(), traced.last());
        assert!(path_length(&wps) <= path_length(&traced) + 1e-5);
        assert_segments_in_domain(&g, &labels, &wps);
    }

    fn path_length(w: &[Point3<f32>]) -> f32 {
        w.windows(2).map(|p| (p[1] - p[0]).norm()).sum()
    }

    fn assert_segments_in_domain(g: &MapGeometry, labels: &[Label], w: &[Point3<f32>]) {
        for p in w.windows(2) {
            crate::mapping::integrate::traverse(g, &p[0], &p[1], |v| {
                assert!(
                    labels[g.dims().linear(v)].in_domain(),
                    "segment {:?} → {:?} crosses {v:?}",
                    p[0],
                    p[1]
                );
                true
            });
        }
    }

    #[test]
    fn a_path_pulled_taut_goes_straight_where_it_can_and_around_what_it_must() {
        // A 30 × 30 room with a 10 × 10 block in the middle; a staircase path from (2, 2) to
        // (27, 27) around the block's lower-right side.
        let dims = Dims::new(30, 30, 1).unwrap();
        let g = MapGeometry::new(dims, Point3::origin(), 0.1).unwrap();
        let mut labels = [Label::Interior; 900];
        for y in 10..20 {
            for x in 10..20 {
                labels[dims.linear(VoxelIndex::new(x, y, 0))] = Label::Outside;
            }
        }
        let at = |x: u16, y: u16| g.center(VoxelIndex::new(x, y, 0));
        let mut wps = Waypoints::new();
        // Right along y = 2 to x = 24, up along x = 24, then left-up to (27, 27) in steps.
        for x in 2..=24 {
            wps.push(at(x, 2)).unwrap();
        }
        for y in 3..=27 {
            wps.push(at(24 + (y - 3) / 8, y)).unwrap();
        }
        let before = wps.clone();
        pull_taut(&g, &labels, &mut wps);
        assert_eq!(wps.len(), before.len());
        assert_eq!(wps.first(), before.first());
        assert_eq!(wps.last(), before.last());
        assert_segments_in_domain(&g, &labels, &wps);
        let (l0, l1) = (path_length(&before), path_length(&wps));
        // The straight line is blocked; around the block's corner (19.5, 9.5) it is
        // |(2.5, 2.5) → (20.5, 9.5)| + |(20.5, 9.5) → (27.5, 27.5)| ≈ 3.90 m.
        assert!(l1 < l0 - 0.3, "{l0} → {l1}");
        assert!(l1 > 3.8 && l1 < 4.3, "{l1}");
        // Waypoints stay ordered along the path and no farther apart than before.
        let gap = |w: &[Point3<f32>]| w.windows(2).map(|p| (p[1] - p[0]).norm()).fold(0.0, f32::max);
        assert!(gap(&wps) <= gap(&before) + 1e-5);

        // No domain around: nothing moves.
        let mut short = Waypoints::new();
        short.push(at(1, 1)).unwrap();
        short.push(at(5, 5)).unwrap();
        let kept = short.clone();
        pull_taut(&g, &labels[..10], &mut short);
        assert_eq!(short, kept);
    }

    #[test]
    fn the_next_waypoint_is_taken_early_only_where_that_cuts_no_corner() {
        let p = |x: f32, y: f32| Point3::new(x, y, 1.0);
        // Straight on, a gentle bend, a right angle, a hairpin; the ends.
        let straight = [p(0.0, 0.0), p(0.1, 0.0), p(0.2, 0.0)];
        assert_eq!(advance_radius(&straight, 1), WAYPOINT_ADVANCE_M);
        assert_eq!(advance_radius(&straight, 0), WAYPOINT_ADVANCE_M);
        assert_eq!(advance_radius(&straight, 2), WAYPOINT_ADVANCE_M);
        let gentle = [p(0.0, 0.0), p(0.1, 0.0), p(0.2, 0.01)];
        assert_eq!(advance_radius(&gentle, 1), WAYPOINT_ADVANCE_M);
        let right = [p(0.0, 0.0), p(1.0, 0.0), p(1.0, 1.0)];
        assert!((advance_radius(&right, 1) - MIN_ADVANCE_M).abs() < 1e-6);
        let hairpin = [p(0.0, 0.0), p(1.0, 0.0), p(0.0, 0.1)];
        assert!((advance_radius(&hairpin, 1) - MIN_ADVANCE_M).abs() < 1e-6);
        // 30°: sin = 0.5, so the radius that cuts 2 cm is 4 cm.
        let thirty = [p(0.0, 0.0), p(1.0, 0.0), p(1.0 + 0.866_025_4, 0.5)];
        assert!((advance_radius(&thirty, 1) - 0.04).abs() < 1e-4);
        // Repeated points do not divide by zero.
        assert_eq!(
            advance_radius(&[p(0.0, 0.0), p(0.0, 0.0), p(1.0, 0.0)], 1),
            WAYPOINT_ADVANCE_M
        );
    }

    #[test]
    fn flat_field_stalls_instead_of_looping() {
        let dims = Dims::new(5, 1, 1).unwrap();
        let g = MapGeometry::new(dims, Point3::origin(), 1.0).unwrap();
        let mut labels = [Label::Interior; 5];
        labels[4] = Label::Frontier;
        let phi = [0.5f32; 5];
        let field = Field {
            geometry: &g,
            labels: &labels,
            phi: &phi,
        };
        let mut wps = Waypoints::new();
        let r = trace(
            &field,
            &Point3::new(0.5, 0.5, 0.5),
            &StreamlineParams::default(),
            &mut wps,
        );
        assert_eq!(r, Err(StreamlineError::Stalled));
        let r = trace(
            &field,
            &Point3::new(-1.0, 0.5, 0.5),
            &StreamlineParams::default(),
            &mut wps,
        );
        assert_eq!(r, Err(StreamlineError::StartOutsideDomain));
    }

    #[test]
    fn long_paths_fit_the_waypoint_buffer() {
        let n = 600;
        let dims = Dims::new(n, 1, 1).unwrap();
        let g = MapGeometry::new(dims, Point3::origin(), 0.1).unwrap();
        let mut labels = [Label::Interior; 600];
        labels[0] = Label::Source;
        labels[n - 1] = Label::Frontier;
        let phi: [f32; 600] = core::array::from_fn(|x| x as f32 / (n - 1) as f32);
        let field = Field {
            geometry: &g,
            labels: &labels,
            phi: &phi,
        };
        let mut wps = Waypoints::new();
        let end = trace(
            &field,
            &g.center(VoxelIndex::new(0, 0, 0)),
            &StreamlineParams::default(),
            &mut wps,
        )
        .unwrap();
        assert_eq!(usize::from(end.frontier.x), n - 1);
        assert!(wps.len() > WAYPOINT_CAPACITY / 4 && wps.len() <= WAYPOINT_CAPACITY);
        assert!((wps.last().unwrap().x - end.end.x).abs() < 1e-4);
        assert!(wps.windows(2).all(|w| w[1].x > w[0].x), "ordered along the path");
    }
}
