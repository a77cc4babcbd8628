//! # harmonic-sim
//!
//! The `std` host simulator around `harmonic-core`: box worlds from scenario files
//! ([`scenario`], [`world`]), a ray-cast depth camera with optional stereo noise ([`camera`]),
//! a multirotor that flies the core's plans ([`sim`]), directly or over MAVLink through an
//! emulated flight stack ([`flight`]), and ground-truth coverage metrics
//! ([`metrics`]); or with the core running as firmware on an emulated Cortex-M4F ([`pil`]).
//! The simulator renders and flies; every decision is the core's.
#![warn(missing_docs)]

pub mod bench;
pub mod camera;
pub mod flight;
pub mod metrics;
pub mod npy;
pub mod pil;
pub mod problem;
pub mod scenario;
pub mod sim;
pub mod world;
