//! A 64-bit tick counter from CMSDK APB timer 0 (25 MHz, counting down from 2³² − 1) plus a
//! wrap count kept by its interrupt. Under QEMU with `-icount shift=0` the virtual clock
//! advances 1 ns per instruction, so one tick is 40 instructions, exactly and repeatably.

use core::ptr::{read_volatile, write_volatile};
use core::sync::atomic::{AtomicU32, Ordering};

use harmonic_core::clock::Clock;

const TIMER0: usize = 0x4000_0000;
const CTRL: usize = 0x00;
const VALUE: usize = 0x04;
const RELOAD: usize = 0x08;
const INTCLEAR: usize = 0x0C;
const CTRL_ENABLE: u32 = 1 << 0;
const CTRL_IRQ_ENABLE: u32 = 1 << 3;
/// NVIC line of timer 0 on mps2-an386.
pub const TIMER0_IRQ: u16 = 8;

static WRAPS: AtomicU32 = AtomicU32::new(0);

fn reg(offset: usize) -> *mut u32 {
    (TIMER0 + offset) as *mut u32
}

/// The board's tick counter (timer 0). Only one exists: [`Ticks::start`] is called once.
pub struct Ticks(());

impl Ticks {
    /// Starts timer 0 free-running and unmasks its wrap interrupt.
    ///
    /// # Safety
    /// Call once; nothing else may use timer 0.
    pub unsafe fn start() -> Self {
        // SAFETY: timer 0's register block, ours by the contract above.
        unsafe {
            write_volatile(reg(CTRL), 0);
            write_volatile(reg(RELOAD), u32::MAX);
            write_volatile(reg(VALUE), u32::MAX);
            write_volatile(reg(CTRL), CTRL_ENABLE | CTRL_IRQ_ENABLE);
            cortex_m::peripheral::NVIC::unmask(super::nvic::Irq(TIMER0_IRQ));
        }
        Self(())
    }

    /// Ticks since start.
    pub fn now(&self) -> u64 {
        now()
    }
}

/// Ticks since [`Ticks::start`] (0 before).
pub fn now() -> u64 {
    {
        loop {
            let wraps = WRAPS.load(Ordering::Acquire);
            // SAFETY: reading the counter has no side effect.
            let value = unsafe { read_volatile(reg(VALUE)) };
            if WRAPS.load(Ordering::Acquire) == wraps {
                return (u64::from(wraps) << 32) | u64::from(u32::MAX - value);
            }
        }
    }
}

impl Clock for Ticks {
    fn ticks(&mut self) -> u64 {
        self.now()
    }
}

/// Timer 0's wrap interrupt: count the wrap.
pub fn on_wrap() {
    // SAFETY: writing INTCLEAR only acknowledges the interrupt.
    unsafe { write_volatile(reg(INTCLEAR), 1) };
    WRAPS.fetch_add(1, Ordering::AcqRel);
}
