//! # harmonic-sim
//!
//! The `std` host simulator around `harmonic-core`: box worlds from scenario files
//! ([`world::scenario`], [`world`]), a ray-cast depth camera with optional stereo noise
//! ([`sensors::camera`]), a textured stereo camera whose pairs the core's block matcher turns
//! into depth ([`sensors::stereo`]), a multirotor that flies the core's plans ([`run::sim`]),
//! directly or over MAVLink ([`vehicle::autopilot`]) through an emulated flight stack
//! ([`vehicle::flight`]) or a real autopilot over UDP, and ground-truth coverage metrics
//! ([`run::metrics`]); or with the core running as firmware on an emulated Cortex-M4F
//! ([`run::pil`]). Depth reaches the core over the depth link ([`link::depth_link`]): the core's
//! wire format at a baud rate, over a transport ([`link::transport`]: in-process pipe, TCP,
//! serial), through an optional fault injector ([`link::fault`]). MAVLink traffic can be
//! recorded as a `.tlog` ([`vehicle::tlog`]). The simulator renders and flies; every decision of
//! the harmonic planner is the core's.
//!
//! The evaluation suite: the seed thesis's baseline planners behind one interface with the core
//! ([`planners`]), triangle-mesh worlds ([`world::mesh`]), sensing faults and map accuracy
//! ([`sensors::sensing`], [`sensors::camera`]), batch runs with thesis-style tables
//! ([`tools::batch`]), figures and map exports ([`tools::figures`]), and TUM RGB-D recordings
//! with replay ([`run::record`]).
//!
//! ## Layout: one folder per stage of a run
//!
//! One step of a run passes through the stages in this order, [`run`] driving it; [`tools`]
//! works on whole runs:
//!
//! ```text
//! world ─► sensors ─► link ─► planners (the core, or a baseline) ─► vehicle ─► run ─► tools
//! ```
//!
//! | module | owns | in → out |
//! |---|---|---|
//! | [`world`] | scenarios, the box-and-mesh world, its geometry | scenario files → a [`world::scenario::Scenario`] |
//! | [`sensors`] | depth camera, stereo camera, sensing faults (drift, map accuracy) | world + true pose → depth frames |
//! | [`link`] | the depth link, its transports, the fault injector | depth frames → frames as the core's receiver decoded them |
//! | [`vehicle`] | the autopilot side of MAVLink: the bridge's link, the flight-stack emulator, `.tlog` | the core's setpoints → the pose the core believes |
//! | [`planners`] | the core's explorer and the baselines behind one interface, their buffers | map + pose → where to go |
//! | [`run`] | the closed loop ([`run::sim`]), the firmware in the loop, metrics, recordings | all of the above → reports, step records |
//! | [`tools`] | batch runs, the fault campaign, figures, solver benchmarks, problem files | runs → tables, CSV, figures |
//! | [`io`] | stage-free file formats (`.npy`, label grids) | bytes ↔ arrays, map → labels |
//!
//! Each folder's `mod.rs` says what flows in and out. `world`, `link`, `vehicle`, `planners`
//! and `io` use no other stage; `sensors` uses `world`; `run` uses all of them; `tools` uses `run`
//! and what it uses. No two files and no two folders import each other, directly or around a
//! loop (`scripts/module_cycles.py`, run by the test suite): the label grids both the run loop
//! (`explore --dump-problem`) and `tools` write live in [`io::labels`], and the camera's
//! visibility bound over the built-in worlds is a test of [`sensors::camera`] that borrows the
//! worlds' voxel ground truth from [`world::scenario`]'s tests. There are no re-exports at the crate root: everything is reached by
//! its folder (`harmonic_sim::run::sim::SimConfig`). As before the move, a few modules
//! re-export a type that lives in a lower one: [`world::Aabb`] (from [`world::aabb`]),
//! [`tools::batch::Curve`] (from [`tools::figures`]), [`run::pil::PilReport`] and
//! [`run::pil::InstructionStat`] (from [`run::sim`]).
//!
//! The command line (`main.rs`, and one module per subcommand under `cli/`) is the binary's,
//! not the library's; it reaches the library through these same paths.
#![warn(missing_docs)]

pub mod io;
pub mod link;
pub mod planners;
pub mod run;
pub mod sensors;
pub mod tools;
pub mod vehicle;
pub mod world;
