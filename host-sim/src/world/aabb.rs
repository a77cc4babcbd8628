//! The solid axis-aligned box of the ground-truth worlds, shared by [`crate::world`] (boxes)
//! and [`crate::world::mesh`] (mesh bounds and voxel tests) so that neither needs the other for it.

use nalgebra::{Point3, Vector3};

/// Tolerance of a voxel-occupancy test, metres: absorbs the rounding of grid-aligned
/// coordinates such as 0.1 m, which f32 cannot represent exactly (`World::CELL_EPSILON`).
pub const CELL_EPSILON: f32 = 1e-4;

/// A solid axis-aligned box, `min` ≤ `max` on every axis (map frame, metres).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Aabb {
    /// Corner with the smallest coordinates.
    pub min: Point3<f32>,
    /// Corner with the largest coordinates.
    pub max: Point3<f32>,
}

impl Aabb {
    /// Box spanning `min` to `max` (not checked; see [`Aabb::is_valid`]).
    pub fn new(min: Point3<f32>, max: Point3<f32>) -> Self {
        Self { min, max }
    }

    /// Box from corner coordinate arrays, as scenario files write them.
    pub fn from_arrays(min: [f32; 3], max: [f32; 3]) -> Self {
        Self::new(Point3::from(min), Point3::from(max))
    }

    /// True if every coordinate is finite and `min < max` on every axis.
    pub fn is_valid(&self) -> bool {
        (0..3).all(|i| self.min[i].is_finite() && self.max[i].is_finite() && self.min[i] < self.max[i])
    }

    /// Size along each axis.
    pub fn extent(&self) -> Vector3<f32> {
        self.max - self.min
    }

    /// Centre point.
    pub fn center(&self) -> Point3<f32> {
        nalgebra::center(&self.min, &self.max)
    }

    /// Volume, m³.
    pub fn volume(&self) -> f32 {
        let e = self.extent();
        e.x * e.y * e.z
    }

    /// True if `p` lies inside the box or on its surface.
    pub fn contains(&self, p: &Point3<f32>) -> bool {
        (0..3).all(|i| self.min[i] <= p[i] && p[i] <= self.max[i])
    }

    /// Squared Euclidean distance from `p` to the box (0 inside).
    pub fn distance_squared_to_point(&self, p: &Point3<f32>) -> f32 {
        (0..3)
            .map(|i| {
                let d = (self.min[i] - p[i]).max(p[i] - self.max[i]).max(0.0);
                d * d
            })
            .sum()
    }

    /// Euclidean distance from `p` to the box (0 inside).
    pub fn distance_to_point(&self, p: &Point3<f32>) -> f32 {
        self.distance_squared_to_point(p).sqrt()
    }

    /// Euclidean distance between two boxes (0 if they touch or overlap).
    pub fn distance_to(&self, other: &Aabb) -> f32 {
        (0..3)
            .map(|i| {
                let d = (other.min[i] - self.max[i])
                    .max(self.min[i] - other.max[i])
                    .max(0.0);
                d * d
            })
            .sum::<f32>()
            .sqrt()
    }

    /// True if the interiors of the box and the open box `(min, max)` overlap by more than
    /// `eps` on every axis; boxes that merely touch (or overlap by less than `eps`) do not.
    pub fn overlaps_interior(&self, min: &Point3<f32>, max: &Point3<f32>, eps: f32) -> bool {
        (0..3).all(|i| min[i] < self.max[i] - eps && max[i] > self.min[i] + eps)
    }

    /// Slab test: distance along the ray `origin + t * dir` at which it enters the box, if
    /// that happens for some `t` in `[0, t_max]`. `inv_dir` is the component-wise reciprocal
    /// of `dir`. A ray starting inside the box enters at `t = 0`.
    pub fn ray_entry(
        &self,
        origin: &Point3<f32>,
        dir: &Vector3<f32>,
        inv_dir: &Vector3<f32>,
        t_max: f32,
    ) -> Option<f32> {
        let mut t0 = 0.0f32;
        let mut t1 = t_max;
        for i in 0..3 {
            if dir[i] == 0.0 {
                // Parallel to this slab: inside it for all t, or never.
                if origin[i] < self.min[i] || origin[i] > self.max[i] {
                    return None;
                }
                continue;
            }
            let a = (self.min[i] - origin[i]) * inv_dir[i];
            let b = (self.max[i] - origin[i]) * inv_dir[i];
            let (near, far) = if a <= b { (a, b) } else { (b, a) };
            t0 = t0.max(near);
            t1 = t1.min(far);
            if t0 > t1 {
                return None;
            }
        }
        Some(t0)
    }
}
