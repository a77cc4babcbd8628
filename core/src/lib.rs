//! # harmonic-core
//!
//! An autonomous exploration core that chooses where to go with a harmonic potential (Shade &
//! Newman, "Choosing Where To Go", ICRA 2011). `#![no_std]`, no allocation: every buffer is
//! borrowed from the caller, so the same code runs in firmware `static`s and in a host `Vec`.
//!
//! ## Data flow
//!
//! ```text
//! depth frame ──► integrate ──► map ──► domain ──► solve ──► streamline ──► goal
//!  (camera)      (ray DDA,     (log-odds, (free, eroded,  (Laplace,   (RK4 down ∇φ)  (position, yaw)
//!                 log-odds)     unknown)   φ=1 vehicle,    in place)
//!                                          φ=0 frontier)
//! ```
//!
//! - [`camera`] — pinhole intrinsics and depth frames, validated once at construction.
//! - [`map`] — the voxel occupancy grid: log-odds with OctoMap defaults, an explicit
//!   never-observed state, world ↔ voxel conversion, frontier test.
//! - [`integrate`] — Amanatides–Woo traversal of every depth ray; hits and misses, each voxel at
//!   most once per frame; no-return pixels clear free space to the maximum range (or nothing,
//!   for stereo); an opt-in stereo sensor model (depth error σ_z = z²σ_d/(f·b), a hit/miss vote
//!   per voxel per frame).
//! - [`domain`] — boundary conditions: free space eroded by the vehicle radius, the vehicle's
//!   connected component, source (φ = 1) and frontier (φ = 0) voxels; walls are zero-flux.
//! - [`field`] — which potential plans: the seed's (vehicle φ = 1, frontiers φ = 0, Laplace)
//!   or the default frontier-sourced screened field (u = 1 on frontiers, ∇²u = κ²u elsewhere),
//!   which prefers near frontiers and keeps the guarantee that every streamline ends on one.
//! - [`solve`] — Laplace's equation (or the screened one) over the domain (cell-centred finite
//!   volumes): in-place multigrid, and the reference Gauss-Seidel solver with a
//!   relative-residual stop.
//! - [`streamline`] — steepest descent of φ from the vehicle to a frontier (trilinear
//!   gradient, RK4, discrete fallback), with fixed-capacity waypoints.
//! - [`explore`] — the [`Explorer`](explore::Explorer) that owns the loop of one plan and reports
//!   status, termination and fault counters, around a [`TargetChoice`](explore::TargetChoice):
//!   the harmonic field's streamline ([`HarmonicField`](explore::HarmonicField)) or any other
//!   planner's choice of target, which is all that differs between planners.
//! - [`companion`] — the [`Companion`](companion::Companion): the one object a companion
//!   computer runs, on the firmware and in the host simulator alike — depth-link receiver,
//!   explorer, MAVLink bridge, setpoint follower, operator and signing between two
//!   `embedded-io` byte streams and a clock.
//! - [`link`] — the depth link's wire format: versioned messages (intrinsics, depth chunks,
//!   pose, heartbeat) in COBS frames with a CRC-32, a streaming decoder that resynchronises
//!   after damage, and the assembler that turns complete chunk sets into depth frames.
//! - [`downlink`] — the core's reports back over the depth link's return channel: a
//!   [`PlanReport`](downlink::PlanReport) after every frame (the camera side's "frame N done")
//!   and the map as two-bit voxel states, in the link's framing.
//! - [`stereo`] — the depth source before all of this when the board receives rectified
//!   stereo rows instead of depth: a streaming SAD block matcher (five windows, left–right
//!   check, uniqueness, sub-pixel parabola, speckle removal, DoG prefilter) whose memory is
//!   bounded by the image width times the disparity range; disparity in 1/16 px, depth in mm.
//! - [`mavlink`] — the bridge to the flight stack: HEARTBEAT and position + yaw setpoints
//!   (SET_POSITION_TARGET_LOCAL_NED) streamed at a steady rate, LOCAL_POSITION_NED / ATTITUDE /
//!   ODOMETRY in as the vehicle pose with a staleness fault, the one map ↔ NED conversion,
//!   MAVLink 2 bytes through the `mavlink` crate, and a history of the poses by the autopilot's
//!   `time_boot_ms` that gives the pose of a camera frame's instant (`PoseHistory`).
//! - [`signing`] — MAVLink 2 message signing without `std`: a [`Signer`](signing::Signer) for
//!   outgoing frames and a [`Verifier`](signing::Verifier) that refuses unsigned, forged,
//!   replayed and stale ones (checked against pymavlink); the companion signs with a key built
//!   into the firmware or given to the host with `--mavlink-key`.
//!
//! Frames: the map frame is right-handed, z up, metres; poses are `Isometry3<f32>`. The camera
//! frame is x right, y down, z forward. Depth is `u16` millimetres, 0 = no return.
//!
//! Errors: inputs are validated at the boundary into types that cannot be wrong afterwards; a
//! fault is a value with a counter, never a panic.
#![no_std]
#![deny(unsafe_code)]
#![warn(missing_docs)]
#![cfg_attr(
    not(test),
    deny(
        clippy::unwrap_used,
        clippy::expect_used,
        clippy::panic,
        clippy::indexing_slicing,
        clippy::unreachable,
        clippy::todo,
        clippy::unimplemented,
        clippy::integer_division_remainder_used
    )
)]

pub mod clock;
pub mod companion;
pub mod links;
pub mod mapping;
pub mod planning;

// The layers' modules under their own names, as the rest of the workspace knows them.
pub use links::{downlink, link, mavlink, operator, signing};
pub use mapping::{camera, integrate, map, stereo};
pub use planning::{domain, explore, field, solve, streamline};
