//! The depth link stage: how depth frames get from the camera side to the core, at a baud rate
//! and with faults, in the core's wire format.
//!
//! - [`depth_link`]: the link as a run uses it: the camera side's encoder (frames, heartbeats,
//!   retransmission of what the core side asks for), pacing at the baud rate in simulated time,
//!   and the core's `DepthReceiver` on the far side; counters in a report.
//! - [`transport`]: the wire itself: an in-process pipe, TCP (connect or listen) or a serial
//!   device, behind one interface; and the echo service of `harmonic-sim link-echo`.
//! - [`fault`]: the seeded fault injector (frame drops, duplicates, reordering; byte drops,
//!   noise bursts, bit errors), and [`fault::Faulty`], which puts it in front of any wire;
//! - [`pacing`]: [`pacing::Paced`], baud pacing in simulated time around any wire.
//!
//! In: depth images and the camera poses they were taken at, from the sensors (via the run).
//! Out: the frames that arrived, whole or with rows missing, decoded by the core's receiver —
//! the same code the firmware runs on its UART — for the run to integrate, plus what was
//! injected and what the receiver noticed. Depends on no other stage
//! (`depth_link → fault`, `depth_link → pacing`, `depth_link → transport`; `fault` and
//! `pacing` wrap `transport`'s `Wire`).

pub mod depth_link;
pub mod fault;
pub mod pacing;
pub mod transport;
