//! # harmonic-fw
//!
//! The exploration core on a Cortex-M4F: QEMU's `mps2-an386` board (Arm MPS2, AN386), whose
//! memory map is the workspace's `memory.x` (4 MiB of code SSRAM at 0, 1 MiB of the data SSRAM
//! at 0x2000_0000 declared as the RAM budget).
//!
//! - [`app`] — the loop, portable: depth link in, map and plan reports back, MAVLink bridge to
//!   the flight stack, the explorer with the default 64 × 64 × 32 grid, all state in one
//!   [`Storage`](app::Storage) the binary keeps in a `static`.
//! - `board` (on the MCU only) — CMSDK UARTs behind `embedded-io`, the tick timer, the
//!   watchdog, the defmt logger (semihosting), exception and panic handlers.
//!
//! UART0 carries the depth link, UART1 MAVLink, both at 921 600 baud. On the host this crate
//! builds too (its binary only says how to build the real one), so the workspace's tests and
//! lints cover [`app`].
#![cfg_attr(target_os = "none", no_std)]
#![warn(missing_docs)]
// As in harmonic-core: no panicking constructs outside tests (README, *No panics*).
#![cfg_attr(
    not(test),
    deny(
        clippy::unwrap_used,
        clippy::expect_used,
        clippy::panic,
        clippy::indexing_slicing,
        clippy::unreachable,
        clippy::todo,
        clippy::unimplemented
    )
)]

pub mod app;
#[cfg(target_os = "none")]
pub mod board;
