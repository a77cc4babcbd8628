//! File formats several stages share, with no simulator types in them: NumPy `.npy` arrays
//! ([`npy`]: `uint8` label grids, `float32` fields and images), and the map as a label grid
//! ([`labels`]).
//!
//! In: bytes (or a path) from the outside world, and the core's map. Out: plain arrays
//! ([`npy::Array3`], image buffers) and the bytes to write back. Nothing here depends on
//! another module of the crate outside `io`;
//! the planning-problem grids, disparity images and map exports that use it (`solve`,
//! `explore --dump-problem`, `stereo`, `replay`) build on it from their own stages. Formats that
//! belong to one stage stay with that stage: PFM and PNG with the stereo camera
//! ([`crate::sensors::stereo`]), `.tlog` with the vehicle's MAVLink ([`crate::vehicle::tlog`]),
//! PLY with the figures ([`crate::tools::figures`]), TUM RGB-D with the recorder
//! ([`crate::run::record`]).

pub mod labels;
pub mod npy;
