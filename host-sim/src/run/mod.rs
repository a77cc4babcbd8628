//! The run stage: one exploration, from the start pose to termination, and what it measured.
//!
//! - [`sim`]: the closed loop. Takes a scenario's world, the sensors, the depth link and the
//!   vehicle (directly, or over MAVLink to an autopilot), drives the core — render a frame, send
//!   it, let the core integrate and plan, fly the plan, check collisions — and produces the
//!   run's [`sim::Report`]; also the per-step records and views the other consumers read.
//! - [`pil`]: the same run with the core as firmware on an emulated Cortex-M4F
//!   (processor in the loop): the host plays world, camera, flight stack and metrics.
//! - [`metrics`]: the ground truth voxelised from the world, and coverage of the explorer's
//!   map against it.
//! - [`record`]: recording a run's integrated frames in the TUM RGB-D layout, and replaying a
//!   recording through the core.
//!
//! In: a scenario ([`crate::world`]), the camera and stereo rig ([`crate::sensors`]), the
//! depth link ([`crate::link`]), the autopilot side ([`crate::vehicle`]) and a planner
//! ([`crate::planners`]). Out: reports (coverage, path, scans, timing, link and MAVLink
//! counters; `report.json`), per-step records, and the views of the planner that figures,
//! recordings and map exports are made from.

pub mod board;
pub mod metrics;
pub mod pil;
pub mod record;
pub mod sim;
