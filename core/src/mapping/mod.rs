//! Map and integration: what the sensors saw, in one voxel grid.
//!
//! - [`camera`] — pinhole intrinsics and depth frames, validated once at construction.
//! - [`map`] — the voxel occupancy grid: log-odds with OctoMap defaults, an explicit
//!   never-observed state, world ↔ voxel conversion, frontier test.
//! - [`integrate`] — a depth frame into the map along each pixel's ray.
//! - [`stereo`] — depth from rectified stereo rows, for boards that receive a pair.
//!
//! Nothing here plans or talks to another machine.

pub mod camera;
pub mod integrate;
pub mod map;
pub mod stereo;
