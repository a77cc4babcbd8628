//! Links: the wire formats the core speaks, as leaves that encode and decode and plan nothing.
//! Only the downlink reads planning's vocabulary: its report carries the explorer's status,
//! outcome and fault counters ([`crate::planning::explore`]'s types, not its code).
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
