//! The vehicle stage, seen from the autopilot's side of the MAVLink wire.
//!
//! - [`autopilot`]: the MAVLink side of a run: the core's bridge on the companion computer and
//!   the autopilot it talks to — the in-process emulator, or a real PX4/ArduPilot (SITL or
//!   hardware) or ground station over UDP; traffic counted per message.
//! - [`flight`]: the flight-stack emulator: takes the bridge's position setpoints as PX4 does in
//!   offboard mode and streams the vehicle's pose back with a real autopilot's timing.
//! - [`tlog`]: the `.tlog` telemetry log every frame of the link can be written to, and its
//!   reader (`harmonic-sim tlog`).
//!
//! In: the core's setpoints (through the bridge) and the vehicle's true pose from the run.
//! Out: the pose the core believes (with the time each sample was taken), the setpoint the
//! vehicle flies, counters and traffic for the run's report, and the `.tlog`. The multirotor's
//! own kinematics (speed and yaw-rate limits, collision checks) are the run loop's
//! ([`crate::run::sim`]). Depends on no other stage.

pub mod autopilot;
pub mod flight;
pub mod tlog;
