//! The subcommands of `harmonic-sim`, one module each: the module owns the subcommand's flags
//! (its clap argument struct, whose doc comments are the help text) and the function that runs
//! it. `main.rs` only declares the command line and dispatches here.
//!
//! | module | subcommand(s) |
//! |---|---|
//! | [`explore`] | `explore` (and its end-of-run summary and figures) |
//! | [`scenarios`] | `scenarios` |
//! | [`bench_solve`] | `bench-solve` |
//! | [`solve`] | `solve` |
//! | [`tlog`] | `tlog` |
//! | [`link_echo`] | `link-echo` |
//! | [`fw_budget`] | `fw-budget` (and `fw-budget --stereo`) |
//! | [`bench`] | `bench`, `bench merge` |
//! | [`replay`] | `replay` |
//! | [`faults`] | `faults` |
//! | [`stereo`] | `stereo`, `stereo-render`, `bench-stereo` (and the matcher flags they share) |
//!
//! Shared by several subcommands: [`sim_args`] (the sensing and field flags `explore` and
//! `bench` both flatten in) and [`parse`] (the value parsers of the flags). Subcommand modules
//! depend on these two and never on each other.

pub mod bench;
pub mod bench_solve;
pub mod explore;
pub mod faults;
pub mod fw_budget;
pub mod link_echo;
pub mod parse;
pub mod replay;
pub mod scenarios;
pub mod sim_args;
pub mod solve;
pub mod stereo;
pub mod tlog;
