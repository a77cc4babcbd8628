//! Ground truth and coverage.
//!
//! The true world is voxelised at the map's resolution: a voxel is truly occupied if its open
//! cube meets the interior of a box. The *reachable free space* is the face-connected set of
//! truly free voxels containing the start. Coverage compares the explorer's map with it:
//!
//! - `coverage_free` — observed-free voxels among the reachable free voxels;
//! - `coverage_surface` — observed-occupied voxels among the truly occupied voxels that face the
//!   reachable free space (the surfaces a camera in that space could see).

use std::collections::VecDeque;

use harmonic_core::map::{MapGeometry, Occupancy, VoxelMap};
use nalgebra::{Point3, Vector3};

use crate::world::World;

/// The world voxelised on the explorer's grid.
pub struct GroundTruth {
    geometry: MapGeometry,
    /// Truly occupied voxels.
    occupied: Vec<bool>,
    /// Reachable free voxels (face-connected to the start through free voxels).
    reachable: Vec<bool>,
    /// Occupied voxels with a face neighbour in `reachable`.
    surface: Vec<bool>,
    reachable_count: usize,
    surface_count: usize,
}

/// Coverage of one map against the ground truth.
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize)]
pub struct Coverage {
    /// Fraction of reachable free voxels the map knows as free.
    pub free: f64,
    /// Fraction of the reachable space's surface voxels the map knows as occupied.
    pub surface: f64,
    /// Reachable free voxels the map holds as occupied (false obstacles).
    pub free_marked_occupied: usize,
    /// Fraction of reachable free voxels the map has observed at all (free, occupied or
    /// uncertain): how much was explored, whatever the sensor made of it.
    pub observed: f64,
}

impl GroundTruth {
    /// Voxelises `world` on `geometry` and floods the free space from `start`.
    pub fn new(world: &World, geometry: &MapGeometry, start: &Point3<f32>) -> Self {
        let dims = geometry.dims();
        let n = dims.len();
        let res = geometry.resolution();
        let occupied: Vec<bool> = (0..n)
            .map(|i| {
                let v = dims.voxel(i);
                let min =
                    geometry.origin() + Vector3::new(f32::from(v.x), f32::from(v.y), f32::from(v.z)) * res;
                let max = min + Vector3::repeat(res);
                world.cell_occupied(&min, &max)
            })
            .collect();
        let mut reachable = vec![false; n];
        if let Some(s) = geometry.voxel_at(start) {
            let si = dims.linear(s);
            if !occupied[si] {
                let mut queue = VecDeque::from([si]);
                reachable[si] = true;
                while let Some(i) = queue.pop_front() {
                    dims.for_each_face_neighbour(dims.voxel(i), |j| {
                        if !occupied[j] && !reachable[j] {
                            reachable[j] = true;
                            queue.push_back(j);
                        }
                    });
                }
            }
        }
        let surface: Vec<bool> = (0..n)
            .map(|i| {
                let mut faces = false;
                if occupied[i] {
                    dims.for_each_face_neighbour(dims.voxel(i), |j| faces |= reachable[j]);
                }
                faces
            })
            .collect();
        let reachable_count = reachable.iter().filter(|&&r| r).count();
        let surface_count = surface.iter().filter(|&&s| s).count();
        Self {
            geometry: *geometry,
            occupied,
            reachable,
            surface,
            reachable_count,
            surface_count,
        }
    }

    /// Number of reachable free voxels.
    pub fn reachable_free(&self) -> usize {
        self.reachable_count
    }
    /// Number of surface voxels facing the reachable space.
    pub fn surface_voxels(&self) -> usize {
        self.surface_count
    }
    /// The grid this truth is voxelised on.
    pub fn geometry(&self) -> &MapGeometry {
        &self.geometry
    }
    /// True if voxel `i` is truly occupied.
    pub fn is_occupied(&self, i: usize) -> bool {
        self.occupied.get(i).copied().unwrap_or(true)
    }

    /// Coverage of `map` (which must be on the same grid).
    pub fn coverage(&self, map: &VoxelMap<'_>) -> Coverage {
        self.coverage_of(|i| map.occupancy(i))
    }

    /// Coverage of a map given as the occupancy of each voxel index (on the same grid): a map
    /// that lives elsewhere, say in the firmware of a processor-in-the-loop run.
    pub fn coverage_of(&self, occupancy: impl Fn(usize) -> Occupancy) -> Coverage {
        let (mut free_seen, mut surf_seen, mut false_occ, mut observed) = (0usize, 0usize, 0usize, 0usize);
        for i in 0..self.reachable.len() {
            let occ = occupancy(i);
            if self.reachable[i] {
                if occ != Occupancy::Unknown {
                    observed += 1;
                }
                match occ {
                    Occupancy::Free => free_seen += 1,
                    Occupancy::Occupied => false_occ += 1,
                    _ => {}
                }
            }
            if self.surface[i] && occ == Occupancy::Occupied {
                surf_seen += 1;
            }
        }
        let frac = |a: usize, b: usize| if b == 0 { 1.0 } else { a as f64 / b as f64 };
        Coverage {
            free: frac(free_seen, self.reachable_count),
            surface: frac(surf_seen, self.surface_count),
            free_marked_occupied: false_occ,
            observed: frac(observed, self.reachable_count),
        }
    }
}

/// Clearances above this are not measured (a report's `min_clearance_m` is at most this), metres.
pub const CLEARANCE_CAP_M: f32 = 1.0;

/// What the true world says of a moving body, position by position: collision events (the body
/// sphere *entering* an obstacle, not every step inside it) and its closest approach. One
/// [`World::clearance`] per position answers both; only within 2 mm of touching does the
/// collision test look again with [`World::sphere_collides`], so that a mesh's clearance,
/// bisected to 1 mm, cannot decide it.
#[derive(Debug, Clone)]
pub struct Contact<'w> {
    world: &'w World,
    radius: f32,
    colliding: bool,
    /// Where each collision began, map frame.
    pub collisions: Vec<[f32; 3]>,
    /// Closest the body's centre came to a surface, metres (at most [`CLEARANCE_CAP_M`]), and
    /// where.
    pub closest: (f32, [f32; 3]),
}

impl<'w> Contact<'w> {
    /// A body of `radius` starting at `p` in `world` (already touching counts as no new
    /// collision).
    pub fn start(world: &'w World, p: &Point3<f32>, radius: f32) -> Self {
        let c = world.clearance(p, CLEARANCE_CAP_M.max(radius + TOUCH_MARGIN_M));
        Self {
            world,
            radius,
            colliding: touching(world, p, radius, c),
            collisions: Vec::new(),
            closest: (c.min(CLEARANCE_CAP_M), p.coords.into()),
        }
    }

    /// The body is now at `p`.
    pub fn observe(&mut self, p: &Point3<f32>) {
        // Nearer than the closest so far, or touching, is all that needs an exact distance.
        let c = self
            .world
            .clearance(p, self.closest.0.max(self.radius + TOUCH_MARGIN_M));
        let now = touching(self.world, p, self.radius, c);
        if now && !self.colliding {
            self.collisions.push(p.coords.into());
        }
        self.colliding = now;
        if c < self.closest.0 {
            self.closest = (c, p.coords.into());
        }
    }
}

/// Within this of the body radius, [`Contact`] decides a collision with the exact sphere test.
const TOUCH_MARGIN_M: f32 = 2e-3;

fn touching(world: &World, p: &Point3<f32>, radius: f32, clearance: f32) -> bool {
    if (clearance - radius).abs() < TOUCH_MARGIN_M {
        world.sphere_collides(p, radius)
    } else {
        clearance < radius
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::world::Aabb;
    use harmonic_core::map::{Dims, LogOddsParams};

    #[test]
    fn box_room_truth_counts() {
        // A 1×1×1 m room of 0.1 m voxels with 0.1 m walls all round: 8×8×8 free inside.
        let b = |min: [f32; 3], max: [f32; 3]| Aabb::from_arrays(min, max);
        let boxes = vec![
            b([0.0, 0.0, 0.0], [1.0, 1.0, 0.1]),
            b([0.0, 0.0, 0.9], [1.0, 1.0, 1.0]),
            b([0.0, 0.0, 0.0], [0.1, 1.0, 1.0]),
            b([0.9, 0.0, 0.0], [1.0, 1.0, 1.0]),
            b([0.0, 0.0, 0.0], [1.0, 0.1, 1.0]),
            b([0.0, 0.9, 0.0], [1.0, 1.0, 1.0]),
        ];
        let world = World::new("room", b([0.0; 3], [1.0; 3]), boxes);
        let g = MapGeometry::new(Dims::new(10, 10, 10).unwrap(), Point3::origin(), 0.1).unwrap();
        let t = GroundTruth::new(&world, &g, &Point3::new(0.5, 0.5, 0.5));
        assert_eq!(t.reachable_free(), 512);
        // Surface: the inner faces of six walls, 8×8 each, no edges (they face no free voxel).
        assert_eq!(t.surface_voxels(), 6 * 64);
        let (mut lo, mut st) = (vec![0i8; 1000], vec![0u32; 32]);
        let mut map = VoxelMap::new(g, LogOddsParams::default(), &mut lo, &mut st).unwrap();
        let c0 = t.coverage(&map);
        assert_eq!((c0.free, c0.surface), (0.0, 0.0));
        for i in 0..1000 {
            if t.reachable[i] {
                map.apply_miss(i);
            } else if t.surface[i] {
                map.apply_hit(i);
            }
        }
        let c = t.coverage(&map);
        assert_eq!(
            (c.free, c.surface, c.free_marked_occupied, c.observed),
            (1.0, 1.0, 0, 1.0)
        );
    }
}
