//! The tools around runs: many runs at once, the solver on its own, and what is drawn and
//! written from them — the library side of the `bench`, `faults`, `bench-solve` and `solve`
//! subcommands and of the figures `explore` and `replay` write.
//!
//! - [`batch`]: every planner on every scenario from the same random starts, in parallel; CSV
//!   rows and the thesis-style tables (`bench`, `bench merge`).
//! - [`faults`]: the fault campaign, one run per cell of a matrix of injected faults (`faults`).
//! - [`figures`]: PNG figures (field slices, top views, coverage curves) and PLY map exports.
//! - [`bench`](mod@bench): the solver benchmarks on building-like grids (`bench-solve`,
//!   BENCHMARKS.md).
//! - [`fork`]: two threads for the solver's fine level (`bench-solve`, `solve --threads`).
//! - [`problem`]: planning problems as `.npy` label grids, and solving one (`solve`,
//!   `explore --dump-problem`).
//! - [`replay`](mod@replay): an exploration's dumped problems re-solved in order, warm and in
//!   boxes, as the explorer re-solves them (`bench-solve --replay`).
//!
//! In: scenarios ([`crate::world`]), run configurations and the runs themselves
//! ([`crate::run`]), planner kinds ([`crate::planners`]), the link and autopilot settings a
//! fault cell changes ([`crate::link`], [`crate::vehicle`]), arrays ([`crate::io`]). Out:
//! tables, CSV and JSON files, PNG figures, label grids and solver statistics. Nothing in the
//! stages uses this folder (the grids `explore --dump-problem` writes are
//! [`crate::io::labels`]').

pub mod batch;
pub mod bench;
pub mod faults;
pub mod figures;
pub mod fork;
pub mod problem;
pub mod replay;

/// The `q` quantile (0–1) of `values` by nearest rank (the median of an even count is the upper
/// of the middle two); `None` for no values. The solver benchmarks, their replays and the
/// explore summary report times through it.
pub fn quantile(mut values: Vec<f64>, q: f64) -> Option<f64> {
    values.sort_by(f64::total_cmp);
    let last = values.len().checked_sub(1)?;
    values
        .get((q.clamp(0.0, 1.0) * last as f64).round() as usize)
        .copied()
}
