//! The CMSDK APB watchdog (0x4000_8000, 25 MHz, interrupt on the NMI line on mps2-an386).
//!
//! The main loop feeds it on every pass. If a pass takes longer than the period, the watchdog
//! raises NMI: the handler logs which phase the loop is stuck in and for how long. If the loop
//! still has not fed it one period later, the watchdog resets the board.

use core::ptr::write_volatile;
use core::sync::atomic::{AtomicU32, AtomicU8, Ordering};

use crate::app::Phase;

const WATCHDOG: usize = 0x4000_8000;
const LOAD: usize = 0x00;
const CTRL: usize = 0x08;
const INTCLR: usize = 0x0C;
const LOCK: usize = 0xC00;
const UNLOCK_KEY: u32 = 0x1ACC_E551;
const CTRL_INTEN: u32 = 1 << 0;
const CTRL_RESEN: u32 = 1 << 1;

static PHASE: AtomicU8 = AtomicU8::new(0);
static STALLS: AtomicU32 = AtomicU32::new(0);

fn write(offset: usize, value: u32) {
    // SAFETY: the watchdog's registers; `Watchdog::start` is called once and only this module
    // touches them.
    unsafe { write_volatile((WATCHDOG + offset) as *mut u32, value) }
}

/// The running watchdog.
pub struct Watchdog {
    load: u32,
}

impl Watchdog {
    /// Starts the watchdog with a period of `seconds` (of the board's clock, virtual under
    /// QEMU's icount), interrupt and reset enabled.
    ///
    /// # Safety
    /// Call once; nothing else may use the watchdog.
    pub unsafe fn start(seconds: u32) -> Self {
        let load = seconds.saturating_mul(super::nvic::PCLK_HZ);
        write(LOCK, UNLOCK_KEY);
        write(LOAD, load);
        write(CTRL, CTRL_INTEN | CTRL_RESEN);
        write(LOCK, 0);
        Self { load }
    }

    /// Tells the watchdog the loop is alive (clears the interrupt and reloads the counter).
    pub fn feed(&mut self) {
        write(LOCK, UNLOCK_KEY);
        write(INTCLR, 1);
        write(LOCK, 0);
        set_phase(Phase::Idle);
    }

    /// Seconds per period.
    pub fn period_s(&self) -> u32 {
        self.load / super::nvic::PCLK_HZ
    }
}

/// Records what the loop is about to do.
pub fn set_phase(phase: Phase) {
    let code = match phase {
        Phase::Idle => 0,
        Phase::Integrate => 1,
        Phase::Plan => 2,
        Phase::Report => 3,
    };
    PHASE.store(code, Ordering::Relaxed);
}

/// Stalls noticed since boot.
pub fn stalls() -> u32 {
    STALLS.load(Ordering::Relaxed)
}

/// The NMI: the loop missed a feed.
pub fn on_expiry() {
    let n = STALLS.fetch_add(1, Ordering::Relaxed) + 1;
    let phase = match PHASE.load(Ordering::Relaxed) {
        1 => Phase::Integrate,
        2 => Phase::Plan,
        3 => Phase::Report,
        _ => Phase::Idle,
    };
    defmt::error!(
        "watchdog: main loop stalled in {} for a whole period (stall #{}); reset at the next expiry",
        phase,
        n
    );
}
