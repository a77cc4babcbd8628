//! The world stage: the ground truth a run explores, and where the vehicle starts.
//!
//! [`scenario`] reads a scenario file (TOML, or one of the built-ins) and validates it into a
//! [`scenario::Scenario`]: a [`World`], the voxel size to map it with and the start pose. A
//! [`World`] (this module) is a bounded region of free space with solid axis-aligned boxes
//! ([`aabb`]) and triangle meshes ([`mesh`]: OBJ and STL, ray cast through a BVH, voxelised on
//! the scenario grid) in it. [`aabb`] is the shared geometry under both the world and the
//! meshes, so that neither needs the other for it: `world → mesh → aabb`, `world → aabb`.
//!
//! In: scenario files and the mesh files they name. Out: a [`scenario::Scenario`] whose
//! [`World`] the sensors render depth from ([`World::raycast`]), the run checks the vehicle
//! against ([`World::sphere_collides`]) and the metrics build the ground-truth voxel grid from
//! ([`World::cell_occupied`]). Everything is in the map frame: right-handed, z up, metres.
//! This stage depends on no other (only a slow, ignored test of [`scenario`] renders from the
//! start with the sensors' camera).

pub mod aabb;
pub mod mesh;
pub mod scenario;

use nalgebra::{Point3, Vector3};

pub use aabb::Aabb;

/// A world: free space inside `bounds`, minus the solid `boxes`.
#[derive(Debug, Clone, PartialEq)]
pub struct World {
    /// Human-readable name (the scenario name).
    pub name: String,
    /// Region the vehicle must stay inside; the map covers exactly this box.
    pub bounds: Aabb,
    /// Solid obstacles: walls, slabs, furniture. They may touch or overlap.
    pub boxes: Vec<Aabb>,
    /// Per box: a surface without texture, on which stereo matching finds no depth. Empty
    /// means none is.
    pub textureless: Vec<bool>,
    /// Triangle-mesh obstacles (OBJ, STL), ray cast exactly and voxelised on the scenario grid.
    pub meshes: Vec<std::sync::Arc<mesh::MeshObject>>,
}

/// Where a ray first meets a surface.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Hit {
    /// Distance along the (unit) ray, metres.
    pub t: f32,
    /// The surface has no texture (stereo finds no depth on it).
    pub textureless: bool,
}

/// Where a ray first meets a surface, which surface it is and which way it faces: what a
/// camera that renders intensities needs ([`crate::sensors::stereo`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SurfaceHit {
    /// Distance along the (unit) ray, metres.
    pub t: f32,
    /// The surface has no texture.
    pub textureless: bool,
    /// Which obstacle: the box index, or the number of boxes plus the mesh index.
    pub surface: usize,
    /// Unit normal facing the ray's origin (for a ray starting inside a box: against the ray).
    pub normal: Vector3<f32>,
}

impl World {
    /// A world with the given name, bounds and obstacles (all textured).
    pub fn new(name: impl Into<String>, bounds: Aabb, boxes: Vec<Aabb>) -> Self {
        Self {
            name: name.into(),
            bounds,
            boxes,
            textureless: Vec::new(),
            meshes: Vec::new(),
        }
    }

    /// Distance along the unit direction `dir` from `origin` to the first box surface it hits,
    /// or `None` if nothing is hit within `max_dist`. A ray starting inside a box hits at 0.
    pub fn raycast(&self, origin: &Point3<f32>, dir: &Vector3<f32>, max_dist: f32) -> Option<f32> {
        self.raycast_hit(origin, dir, max_dist).map(|h| h.t)
    }

    /// [`World::raycast`], also telling whether the surface hit is textureless.
    pub fn raycast_hit(&self, origin: &Point3<f32>, dir: &Vector3<f32>, max_dist: f32) -> Option<Hit> {
        let inv_dir = dir.map(|c| 1.0 / c);
        let mut best: Option<Hit> = None;
        let mut t_max = max_dist;
        for (i, b) in self.boxes.iter().enumerate() {
            if let Some(t) = b.ray_entry(origin, dir, &inv_dir, t_max) {
                best = Some(Hit {
                    t,
                    textureless: self.textureless.get(i).copied().unwrap_or(false),
                });
                t_max = t;
                if t == 0.0 {
                    break;
                }
            }
        }
        for m in &self.meshes {
            if let Some(t) = m.bvh.raycast(&m.mesh, origin, dir, t_max) {
                best = Some(Hit {
                    t,
                    textureless: m.textureless,
                });
                t_max = t;
            }
        }
        best
    }

    /// [`World::raycast_hit`], also telling which surface was hit and its normal.
    pub fn raycast_surface(
        &self,
        origin: &Point3<f32>,
        dir: &Vector3<f32>,
        max_dist: f32,
    ) -> Option<SurfaceHit> {
        let inv_dir = dir.map(|c| 1.0 / c);
        let mut best: Option<(f32, usize, Option<usize>)> = None;
        let mut t_max = max_dist;
        for (i, b) in self.boxes.iter().enumerate() {
            if let Some(t) = b.ray_entry(origin, dir, &inv_dir, t_max) {
                best = Some((t, i, None));
                t_max = t;
                if t == 0.0 {
                    break;
                }
            }
        }
        for (k, m) in self.meshes.iter().enumerate() {
            if let Some((t, tri)) = m.bvh.raycast_triangle(&m.mesh, origin, dir, t_max) {
                best = Some((t, self.boxes.len() + k, Some(tri)));
                t_max = t;
            }
        }
        let (t, surface, triangle) = best?;
        let (textureless, normal) = match triangle {
            Some(tri) => {
                let m = &self.meshes[surface - self.boxes.len()];
                (m.textureless, m.mesh.triangle_normal(tri))
            }
            None => (
                self.textureless.get(surface).copied().unwrap_or(false),
                box_normal(&self.boxes[surface], &(origin + dir * t), dir, t),
            ),
        };
        // Face the viewer whatever the winding.
        let normal = if normal.dot(dir) > 0.0 { -normal } else { normal };
        Some(SurfaceHit {
            t,
            textureless,
            surface,
            normal,
        })
    }

    /// Index of the first mesh closer than `radius` to `center` or enclosing it, if any.
    pub fn first_mesh_within(&self, center: &Point3<f32>, radius: f32) -> Option<usize> {
        self.meshes
            .iter()
            .position(|m| m.solid_at(center) || m.bvh.within(&m.mesh, center, radius))
    }

    /// True if the sphere intersects any box or mesh or is not entirely inside `bounds`.
    pub fn sphere_collides(&self, center: &Point3<f32>, radius: f32) -> bool {
        self.first_box_within(center, radius).is_some()
            || !self.sphere_inside_bounds(center, radius)
            || self.first_mesh_within(center, radius).is_some()
    }

    /// Distance from `p` to the nearest surface — box, mesh or the bounds' walls — or `cap`
    /// if nothing is nearer (0 inside an obstacle or outside the bounds). Meshes are measured
    /// by bisection on [`World::first_mesh_within`] to 1 mm, so the cap bounds the work.
    pub fn clearance(&self, p: &Point3<f32>, cap: f32) -> f32 {
        let to_bounds = (0..3)
            .map(|i| (p[i] - self.bounds.min[i]).min(self.bounds.max[i] - p[i]))
            .fold(f32::INFINITY, f32::min);
        let mut d = self.distance_to_nearest_box(p).min(to_bounds).min(cap).max(0.0);
        if !self.meshes.is_empty() && d > 0.0 && self.first_mesh_within(p, d).is_some() {
            let (mut lo, mut hi) = (0.0f32, d);
            while hi - lo > 1e-3 {
                let mid = 0.5 * (lo + hi);
                if self.first_mesh_within(p, mid).is_some() {
                    hi = mid;
                } else {
                    lo = mid;
                }
            }
            d = lo;
        }
        d
    }

    /// True if the sphere lies entirely inside `bounds` (touching counts as inside).
    pub fn sphere_inside_bounds(&self, center: &Point3<f32>, radius: f32) -> bool {
        (0..3).all(|i| center[i] - radius >= self.bounds.min[i] && center[i] + radius <= self.bounds.max[i])
    }

    /// Index of the first box closer than `radius` to `center`, if any.
    pub fn first_box_within(&self, center: &Point3<f32>, radius: f32) -> Option<usize> {
        let r2 = radius * radius;
        self.boxes
            .iter()
            .position(|b| b.distance_squared_to_point(center) < r2)
    }

    /// Distance from `p` to the nearest box (`f32::INFINITY` in a world without boxes).
    pub fn distance_to_nearest_box(&self, p: &Point3<f32>) -> f32 {
        self.boxes
            .iter()
            .map(|b| b.distance_squared_to_point(p))
            .fold(f32::INFINITY, f32::min)
            .sqrt()
    }

    /// True if the open cell `(min, max)` intersects the interior of any box by more than
    /// [`World::CELL_EPSILON`]: a box that only touches a face of the cell does not occupy it.
    /// A mesh occupies the cell if its voxelisation (on the scenario grid, which the cell is
    /// expected to be part of) marks the voxel at the cell's centre solid.
    pub fn cell_occupied(&self, min: &Point3<f32>, max: &Point3<f32>) -> bool {
        self.boxes
            .iter()
            .any(|b| b.overlaps_interior(min, max, Self::CELL_EPSILON))
            || (!self.meshes.is_empty() && {
                let c = nalgebra::center(min, max);
                self.meshes.iter().any(|m| m.solid_at(&c))
            })
    }

    /// Tolerance of [`World::cell_occupied`], metres: absorbs the rounding of grid-aligned
    /// coordinates such as 0.1 m, which f32 cannot represent exactly.
    pub const CELL_EPSILON: f32 = aabb::CELL_EPSILON;
}

/// Outward normal of the face of `b` that the point `p` (on its surface) lies on; `t == 0`
/// (the ray starts inside): against the ray.
fn box_normal(b: &Aabb, p: &Point3<f32>, dir: &Vector3<f32>, t: f32) -> Vector3<f32> {
    if t == 0.0 {
        return -dir;
    }
    let mut best = (f32::INFINITY, Vector3::zeros());
    for i in 0..3 {
        for (face, sign) in [(b.min[i], -1.0), (b.max[i], 1.0)] {
            let gap = (p[i] - face).abs();
            if gap < best.0 {
                let mut n = Vector3::zeros();
                n[i] = sign;
                best = (gap, n);
            }
        }
    }
    best.1
}

#[cfg(test)]
mod tests {
    use super::*;

    fn room() -> World {
        // A 4 × 4 × 3 room with a 0.2 m wall at x ∈ [3, 3.2] and a cube on the floor.
        World::new(
            "test",
            Aabb::from_arrays([0.0, 0.0, 0.0], [4.0, 4.0, 3.0]),
            vec![
                Aabb::from_arrays([3.0, 0.0, 0.0], [3.2, 4.0, 3.0]),
                Aabb::from_arrays([1.0, 2.0, 0.0], [1.5, 2.5, 0.5]),
            ],
        )
    }

    #[test]
    fn raycast_hits_nearest_box() {
        let w = room();
        let o = Point3::new(1.0, 1.0, 1.0);
        let t = w.raycast(&o, &Vector3::x(), 60.0).unwrap();
        assert!((t - 2.0).abs() < 1e-6, "{t}");
        // Looking down at the cube from above hits its top face.
        let o = Point3::new(1.25, 2.25, 2.0);
        let t = w.raycast(&o, &-Vector3::z(), 60.0).unwrap();
        assert!((t - 1.5).abs() < 1e-6, "{t}");
    }

    #[test]
    fn raycast_misses_beyond_max_dist_and_behind() {
        let w = room();
        let o = Point3::new(1.0, 1.0, 1.0);
        assert_eq!(w.raycast(&o, &Vector3::x(), 1.5), None);
        assert_eq!(w.raycast(&o, &-Vector3::x(), 60.0), None);
        assert_eq!(w.raycast(&o, &Vector3::z(), 60.0), None);
    }

    #[test]
    fn raycast_oblique() {
        let w = room();
        let o = Point3::new(1.0, 1.0, 1.0);
        let dir = Vector3::new(1.0, 1.0, 0.0).normalize();
        let t = w.raycast(&o, &dir, 60.0).unwrap();
        assert!((t - 2.0 * std::f32::consts::SQRT_2).abs() < 1e-5, "{t}");
    }

    #[test]
    fn sphere_collides_with_boxes_and_bounds() {
        let w = room();
        assert!(!w.sphere_collides(&Point3::new(2.0, 1.0, 1.0), 0.5));
        assert!(w.sphere_collides(&Point3::new(2.7, 1.0, 1.0), 0.5));
        assert!(w.sphere_collides(&Point3::new(0.2, 1.0, 1.0), 0.5));
        assert!(w.sphere_collides(&Point3::new(1.25, 2.25, 0.8), 0.5));
        assert_eq!(w.first_box_within(&Point3::new(2.7, 1.0, 1.0), 0.5), Some(0));
    }

    #[test]
    fn clearance_is_the_distance_to_the_nearest_surface() {
        let w = room();
        // Boxes and bounds as in `sphere_collides_with_boxes_and_bounds`.
        for p in [
            Point3::new(2.0, 1.0, 1.0),
            Point3::new(1.25, 2.25, 0.8),
            Point3::new(0.2, 1.0, 1.0),
        ] {
            let d = w.clearance(&p, 10.0);
            assert!(!w.sphere_collides(&p, d - 1e-3), "{p}: {d}");
            assert!(w.sphere_collides(&p, d + 1e-3), "{p}: {d}");
        }
        assert_eq!(w.clearance(&Point3::new(2.0, 1.0, 1.0), 0.05), 0.05);
    }

    #[test]
    fn cell_occupied_ignores_touching_faces() {
        let w = room();
        let r = 0.1f32;
        // The cell just left of the wall touches its face: free.
        let min = Point3::new(29.0 * r, 10.0 * r, 10.0 * r);
        assert!(!w.cell_occupied(&min, &(min + Vector3::repeat(r))));
        // The first cell inside the wall: occupied.
        let min = Point3::new(30.0 * r, 10.0 * r, 10.0 * r);
        assert!(w.cell_occupied(&min, &(min + Vector3::repeat(r))));
        // The cell on top of the cube touches its top face only: free.
        let min = Point3::new(10.0 * r, 20.0 * r, 5.0 * r);
        assert!(!w.cell_occupied(&min, &(min + Vector3::repeat(r))));
    }

    #[test]
    fn box_distance() {
        let a = Aabb::from_arrays([0.0; 3], [1.0; 3]);
        let b = Aabb::from_arrays([2.0, 0.0, 0.0], [3.0, 1.0, 1.0]);
        let c = Aabb::from_arrays([1.0, 1.0, 0.0], [2.0, 2.0, 1.0]);
        assert!((a.distance_to(&b) - 1.0).abs() < 1e-6);
        assert_eq!(a.distance_to(&c), 0.0);
        assert!((a.distance_to_point(&Point3::new(2.0, 2.0, 0.5)) - std::f32::consts::SQRT_2).abs() < 1e-6);
    }
}
