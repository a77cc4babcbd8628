//! Planning: from the map to where the vehicle goes next.
//!
//! - [`domain`] — boundary conditions: the safe space and its frontier.
//! - [`field`] — which potential plans.
//! - [`solve`] — the solvers of that potential.
//! - [`streamline`] — steepest ascent from the vehicle to a frontier.
//! - [`explore`] — the [`Explorer`](explore::Explorer): the loop of one plan, around a target
//!   choice.
//!
//! Planning reads the map ([`crate::mapping`]) and knows no wire format.

pub mod domain;
pub mod explore;
pub mod field;
pub mod solve;
pub mod streamline;
