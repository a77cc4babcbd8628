//! Time as the core sees it: ticks of whatever clock the board has.

/// A monotonic tick source for per-phase timing (a board timer, a cycle counter, or the host
/// clock). Ticks are opaque units; the caller knows their rate.
pub trait Clock {
    /// Current tick count.
    fn ticks(&mut self) -> u64;
}

/// A clock that always reads 0, for callers that do not time phases.
#[derive(Debug, Clone, Copy, Default)]
pub struct NoClock;

impl Clock for NoClock {
    fn ticks(&mut self) -> u64 {
        0
    }
}
