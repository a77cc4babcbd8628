//! Shortest paths over the planning domain: Dijkstra and A* on the voxel grid, 26-connected
//! with true Euclidean step costs (1, √2, √3 voxels) and no corner cutting, and line-of-sight
//! shortcutting of the voxel path (string pulling) so that paths are not needlessly jagged.
//!
//! Passable voxels are those [`Label::in_domain`] marks: the vehicle's component of safe space
//! as [`harmonic_core::domain::build`] labels it, frontier voxels included.

use std::cmp::Ordering;
use std::collections::BinaryHeap;

use harmonic_core::domain::Label;
use harmonic_core::map::{Dims, MapGeometry};
use nalgebra::Point3;

/// One of the 26 moves: offset, cost in voxels, and the voxels it sweeps past (which must be
/// passable too, so that a diagonal never cuts the corner of a wall).
#[derive(Debug, Clone)]
struct Move {
    offset: [i32; 3],
    cost: f32,
    sweeps: Vec<[i32; 3]>,
}

fn moves() -> Vec<Move> {
    let mut out = Vec::with_capacity(26);
    for dz in -1i32..=1 {
        for dy in -1i32..=1 {
            for dx in -1i32..=1 {
                let d = [dx, dy, dz];
                let nonzero = d.iter().filter(|&&c| c != 0).count();
                if nonzero == 0 {
                    continue;
                }
                // Every proper, non-empty sub-step of the move (the other corners of its cube).
                let mut sweeps = Vec::new();
                for mask in 1u8..7 {
                    let s = [0, 1, 2].map(|a| if mask & (1 << a) != 0 { d[a] } else { 0 });
                    if s != [0, 0, 0] && s != d && !sweeps.contains(&s) {
                        sweeps.push(s);
                    }
                }
                out.push(Move {
                    offset: d,
                    cost: (nonzero as f32).sqrt(),
                    sweeps,
                });
            }
        }
    }
    out
}

#[derive(Debug, Clone, Copy, PartialEq)]
struct Open {
    f: f32,
    i: u32,
}
impl Eq for Open {}
impl Ord for Open {
    fn cmp(&self, other: &Self) -> Ordering {
        // Min-heap on f; ties broken by index for determinism.
        other.f.total_cmp(&self.f).then_with(|| other.i.cmp(&self.i))
    }
}
impl PartialOrd for Open {
    fn partial_cmp(&self, other: &Self) -> Option<Ordering> {
        Some(self.cmp(other))
    }
}

/// Reusable search state over one grid.
pub struct Search {
    dims: Dims,
    moves: Vec<Move>,
    dist: Vec<f32>,
    parent: Vec<u32>,
    heap: BinaryHeap<Open>,
    source: usize,
    /// Nodes expanded (popped and settled) since construction.
    pub expansions: u64,
}

const NO_PARENT: u32 = u32::MAX;

impl Search {
    /// Search state for grids of `dims`.
    pub fn new(dims: Dims) -> Self {
        Self {
            dims,
            moves: moves(),
            dist: vec![f32::INFINITY; dims.len()],
            parent: vec![NO_PARENT; dims.len()],
            heap: BinaryHeap::new(),
            source: 0,
            expansions: 0,
        }
    }

    fn reset(&mut self, source: usize) {
        self.dist.fill(f32::INFINITY);
        self.parent.fill(NO_PARENT);
        self.heap.clear();
        self.source = source;
        if let Some(d) = self.dist.get_mut(source) {
            *d = 0.0;
        }
    }

    fn passable(labels: &[Label], i: usize) -> bool {
        labels.get(i).is_some_and(|l| l.in_domain())
    }

    /// Best-first search from `source` with heuristic `h` (voxels; 0 for Dijkstra). Returns the
    /// first popped voxel for which `stop` holds, or `None` once everything reachable is
    /// settled. Distances of settled voxels are exact (h must be consistent).
    fn run(
        &mut self,
        labels: &[Label],
        source: usize,
        h: impl Fn(usize) -> f32,
        mut stop: impl FnMut(usize) -> bool,
    ) -> Option<usize> {
        self.reset(source);
        if !Self::passable(labels, source) {
            return None;
        }
        self.heap.push(Open {
            f: h(source),
            i: source as u32,
        });
        while let Some(Open { f, i }) = self.heap.pop() {
            let i = i as usize;
            let g = self.dist[i];
            // A stale entry: the voxel was settled with a smaller f already.
            if f > g + h(i) + 1e-4 {
                continue;
            }
            self.expansions += 1;
            if stop(i) {
                return Some(i);
            }
            let v = self.dims.voxel(i);
            for m in &self.moves {
                let Some(n) = self.dims.offset(v, m.offset) else {
                    continue;
                };
                let ni = self.dims.linear(n);
                if !Self::passable(labels, ni) {
                    continue;
                }
                let ng = g + m.cost;
                if ng >= self.dist[ni] {
                    continue;
                }
                let clear = m.sweeps.iter().all(|s| {
                    self.dims
                        .offset(v, *s)
                        .is_some_and(|c| Self::passable(labels, self.dims.linear(c)))
                });
                if !clear {
                    continue;
                }
                self.dist[ni] = ng;
                self.parent[ni] = i as u32;
                self.heap.push(Open {
                    f: ng + h(ni),
                    i: ni as u32,
                });
            }
        }
        None
    }

    /// Dijkstra from `source` until a voxel satisfying `stop` is settled: it is the one with the
    /// shortest path among all that satisfy `stop`. `None` if none is reachable.
    pub fn nearest(
        &mut self,
        labels: &[Label],
        source: usize,
        stop: impl FnMut(usize) -> bool,
    ) -> Option<usize> {
        self.run(labels, source, |_| 0.0, stop)
    }

    /// Dijkstra from `source` over everything reachable; afterwards [`Search::distance`] holds
    /// the shortest-path length to every voxel.
    pub fn flood(&mut self, labels: &[Label], source: usize) {
        self.run(labels, source, |_| 0.0, |_| false);
    }

    /// A* from `source` to `goal` with the Euclidean heuristic (admissible and consistent for
    /// these step costs). Returns the path length in voxels.
    pub fn astar(&mut self, labels: &[Label], source: usize, goal: usize) -> Option<f32> {
        let dims = self.dims;
        let gv = dims.voxel(goal);
        let h = move |i: usize| {
            let v = dims.voxel(i);
            (v.distance_sq(&gv) as f32).sqrt()
        };
        self.run(labels, source, h, |i| i == goal)?;
        Some(self.dist[goal])
    }

    /// Shortest-path length (voxels) found to `i` by the last search, if reached.
    pub fn distance(&self, i: usize) -> Option<f32> {
        self.dist.get(i).copied().filter(|d| d.is_finite())
    }

    /// Voxels from the last search's source to `target`, both included (empty if unreached).
    pub fn path(&self, target: usize) -> Vec<usize> {
        if self.distance(target).is_none() {
            return Vec::new();
        }
        let mut out = vec![target];
        let mut i = target;
        while i != self.source {
            let p = self.parent[i];
            if p == NO_PARENT {
                return Vec::new();
            }
            i = p as usize;
            out.push(i);
        }
        out.reverse();
        out
    }
}

pub use harmonic_core::streamline::line_of_sight;

/// Waypoints for a voxel path: starts at `start` (the vehicle, inside the path's first voxel),
/// ends at the centre of its last voxel, and keeps only the corners that line of sight through
/// passable voxels cannot cut (greedy string pulling). `steps` counts line-of-sight voxels.
pub fn smooth(
    geometry: &MapGeometry,
    labels: &[Label],
    start: &Point3<f32>,
    path: &[usize],
    steps: &mut u64,
) -> Vec<Point3<f32>> {
    let dims = geometry.dims();
    let centre = |i: usize| geometry.center(dims.voxel(i));
    let mut out = vec![*start];
    if path.len() <= 1 {
        if let Some(&last) = path.last() {
            out.push(centre(last));
        }
        return out;
    }
    let mut anchor = *start;
    let mut k = 1;
    while k < path.len() {
        // Extend from the anchor as far along the path as it can see.
        let mut reach = k;
        while reach + 1 < path.len()
            && line_of_sight(geometry, labels, &anchor, &centre(path[reach + 1]), steps)
        {
            reach += 1;
        }
        if reach + 1 == path.len() {
            out.push(centre(path[reach]));
            break;
        }
        // `reach` is the last visible voxel: a corner the path must turn at.
        let corner = centre(path[reach]);
        out.push(corner);
        anchor = corner;
        k = reach + 1;
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use harmonic_core::map::VoxelIndex;

    fn grid(nx: usize, ny: usize, blocked: &[(usize, usize)]) -> (Dims, Vec<Label>) {
        let dims = Dims::new(nx, ny, 1).unwrap();
        let mut labels = vec![Label::Interior; dims.len()];
        for &(x, y) in blocked {
            labels[dims.linear(VoxelIndex::new(x as u16, y as u16, 0))] = Label::Outside;
        }
        (dims, labels)
    }

    #[test]
    fn moves_are_26_with_euclidean_costs() {
        let m = moves();
        assert_eq!(m.len(), 26);
        assert_eq!(m.iter().filter(|m| m.cost == 1.0).count(), 6);
        assert_eq!(
            m.iter().filter(|m| (m.cost - 2f32.sqrt()).abs() < 1e-6).count(),
            12
        );
        let corner = m.iter().find(|m| m.offset == [1, 1, 1]).unwrap();
        assert_eq!(corner.sweeps.len(), 6);
    }

    #[test]
    fn astar_goes_around_a_wall_without_cutting_corners() {
        // A wall at x = 2 from y = 0 to y = 3 in a 5 × 5 room.
        let (dims, labels) = grid(5, 5, &[(2, 0), (2, 1), (2, 2), (2, 3)]);
        let i = |x: u16, y: u16| dims.linear(VoxelIndex::new(x, y, 0));
        let mut s = Search::new(dims);
        let d = s.astar(&labels, i(0, 0), i(4, 0)).unwrap();
        let path = s.path(i(4, 0));
        assert_eq!(path.first(), Some(&i(0, 0)));
        assert_eq!(path.last(), Some(&i(4, 0)));
        // No step from x = 1 to x = 3 diagonally past the wall's end at (2, 3).
        for w in path.windows(2) {
            let (a, b) = (dims.voxel(w[0]), dims.voxel(w[1]));
            assert!(labels[w[1]].in_domain());
            assert!(a.distance_sq(&b) <= 2);
        }
        // Dijkstra agrees with A*.
        let mut s2 = Search::new(dims);
        s2.flood(&labels, i(0, 0));
        assert!((s2.distance(i(4, 0)).unwrap() - d).abs() < 1e-5);
        // Up to (1,3), diagonal through the gap at y = 4, down to (3,3)...: 4 + 2√2 + 3 + ... ≥ 10.
        assert!(d > 9.0, "{d}");
    }

    #[test]
    fn smoothing_keeps_the_path_in_the_domain() {
        let (dims, labels) = grid(9, 9, &[(4, 0), (4, 1), (4, 2), (4, 3), (4, 4), (4, 5)]);
        let g = MapGeometry::new(dims, Point3::origin(), 0.1).unwrap();
        let i = |x: u16, y: u16| dims.linear(VoxelIndex::new(x, y, 0));
        let mut s = Search::new(dims);
        s.astar(&labels, i(1, 1), i(7, 1)).unwrap();
        let path = s.path(i(7, 1));
        let start = g.center(dims.voxel(i(1, 1)));
        let mut steps = 0;
        let pts = smooth(&g, &labels, &start, &path, &mut steps);
        assert!(pts.len() >= 3 && pts.len() < path.len(), "{pts:?}");
        for w in pts.windows(2) {
            assert!(line_of_sight(&g, &labels, &w[0], &w[1], &mut steps));
        }
        assert!(steps > 0);
    }
}
