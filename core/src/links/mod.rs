//! Links: the wire formats the core speaks, as leaves that encode and decode and plan nothing.
//! Only the downlink names planning's vocabulary: its report carries the explorer's fault
//! and fault counters (the data types `Fault` and `ErrorCounters` of
//! [`crate::planning::explore`] and the error enums inside `Fault`). It reads no status and
//! no plan: the companion fills the report in.
//!
//! - [`link`] — the depth link: depth frames and poses in, resend requests back.
//! - [`downlink`] — the core's reports back over the depth link's return channel.
//! - [`mavlink`] — the flight stack's protocol: setpoints out, the vehicle pose in.
//! - [`signing`] — MAVLink 2 message signing.
//! - [`operator`] — a ground station's commands over MAVLink, as a state.

pub mod downlink;
pub mod link;
pub mod mavlink;
pub mod operator;
pub mod signing;
