//! Two threads for the solver: a [`Fork`] on a rayon pool, lent to
//! [`harmonic_core::solve::multigrid::Multigrid::set_fork`] by `bench-solve` and `solve`
//! (`--threads 2`). The core splits the fine level's passes in two; the split gives the same
//! bits as one thread, so only the times change.

use std::sync::atomic::{AtomicBool, Ordering};

use harmonic_core::solve::Fork;

/// The solver's default thread count: 2 on a machine with two cores or more, else 1 (a
/// second thread on one core, polling for work, would only take time from the first).
pub fn default_threads() -> u8 {
    match std::thread::available_parallelism() {
        Ok(n) if n.get() >= 2 => 2,
        _ => 1,
    }
}

/// Runs `f` with a [`Fork`] for `threads` threads (1 or 2): `None` for 1; for 2, a
/// [`PoolFork`] on a pool of two, with the second worker kept awake ([`with_helper_awake`])
/// while `f` runs. Errors if the pool cannot start.
pub fn with_fork<R: Send>(
    threads: u8,
    f: impl FnOnce(Option<&'static dyn Fork>) -> R + Send,
) -> Result<R, String> {
    if threads <= 1 {
        return Ok(f(None));
    }
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(usize::from(threads))
        .build()
        .map_err(|e| format!("cannot start {threads} solver threads: {e}"))?;
    Ok(pool.install(|| with_helper_awake(|| f(Some(&PoolFork)))))
}

/// Runs `f` on the current rayon worker while another worker of the pool stays awake, polling
/// for work, until `f` returns. The solver's joins come every few hundred microseconds; an idle
/// rayon worker falls asleep between them, and waking it (a futex on a virtual machine) cost
/// tens of microseconds per join. The price is a core kept busy for the duration of `f`.
pub fn with_helper_awake<R: Send>(f: impl FnOnce() -> R + Send) -> R {
    let done = AtomicBool::new(false);
    rayon::scope(|s| {
        s.spawn(|_| {
            while !done.load(Ordering::Acquire) {
                if rayon::yield_now() != Some(rayon::Yield::Executed) {
                    std::hint::spin_loop();
                }
            }
        });
        let out = f();
        done.store(true, Ordering::Release);
        out
    })
}

/// A [`Fork`] on rayon's thread pool: the solver's two halves run as a [`rayon::join`]. Call
/// the solve inside [`rayon::ThreadPool::install`] (or from a rayon task) so that each join is
/// a push onto the worker's own queue rather than a hand-over from outside the pool.
#[derive(Debug, Clone, Copy, Default)]
pub struct PoolFork;

impl Fork for PoolFork {
    fn join(&self, a: &mut (dyn FnMut() + Send), b: &mut (dyn FnMut() + Send)) {
        rayon::join(a, b);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn both_halves_run_once_on_two_threads() {
        let (mut a, mut b) = (0, 0);
        let threads = with_fork(2, |fork| {
            let fork = fork.expect("two threads lend a fork");
            let (mut ta, mut tb) = (None, None);
            fork.join(
                &mut || {
                    a += 1;
                    ta = Some(std::thread::current().id());
                },
                &mut || {
                    b += 1;
                    tb = Some(std::thread::current().id());
                },
            );
            (ta, tb)
        })
        .unwrap();
        assert_eq!((a, b), (1, 1));
        assert!(threads.0.is_some() && threads.1.is_some());
        assert!(with_fork(1, |fork| fork.is_none()).unwrap());
    }
}
