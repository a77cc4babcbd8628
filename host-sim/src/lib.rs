//! # harmonic-sim
//!
//! The `std` host simulator around `harmonic-core`: box worlds from scenario files
//! ([`world::scenario`], [`world`]), a ray-cast depth camera with optional stereo noise ([`sensors::camera`]),
//! a textured stereo camera whose pairs the core's block matcher turns into depth ([`sensors::stereo`]),
//! a multirotor that flies the core's plans ([`run::sim`]), directly or over MAVLink
//! ([`vehicle::autopilot`]) through an emulated flight stack ([`vehicle::flight`]) or a real autopilot over UDP,
//! and ground-truth coverage metrics ([`run::metrics`]); or with the core running as firmware on an
//! emulated Cortex-M4F ([`run::pil`]). Depth reaches the core over the depth link
//! ([`link::depth_link`]): the core's wire format at a baud rate, over a transport ([`link::transport`]:
//! in-process pipe, TCP, serial), through an optional fault injector ([`link::fault`]). MAVLink
//! traffic can be recorded as a `.tlog` ([`vehicle::tlog`]). The simulator renders and flies; every
//! decision of the harmonic planner is the core's.
//!
//! The evaluation suite: the seed thesis's baseline planners behind one interface with the core
//! ([`planners`]), triangle-mesh worlds ([`world::mesh`]), sensing faults and map accuracy
//! ([`sensors::sensing`], [`sensors::camera`]), batch runs with thesis-style tables ([`tools::batch`]), figures and map
//! exports ([`tools::figures`]), and TUM RGB-D recordings with replay ([`run::record`]).
#![warn(missing_docs)]

pub mod io;
pub mod link;
pub mod planners;
pub mod run;
pub mod sensors;
pub mod tools;
pub mod vehicle;
pub mod world;
