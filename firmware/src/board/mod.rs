//! The board: QEMU's `mps2-an386` (Arm MPS2 with a Cortex-M4F, AN386). Everything that knows a
//! register address lives here — UARTs, timer, watchdog — together with the defmt logger
//! (semihosting), the exception handlers and the panic handler. Retargeting to another part
//! (say an STM32H7) means a new `memory.x`, a new `uart.rs` and new addresses here; the
//! exploration loop in [`crate::app`] sees only `embedded-io` streams and a
//! [`Clock`](harmonic_core::clock::Clock).

pub mod nvic;
pub mod stack;
pub mod timer;
pub mod uart;
pub mod watchdog;

pub use nvic::{Irq, PCLK_HZ};

use cortex_m_rt::{exception, ExceptionFrame};
// The global defmt logger: frames go out through semihosting (QEMU's stdout).
use defmt_semihosting as _;

/// Sleeps until an interrupt unless one of `inputs` already has a byte. Interrupts are off
/// between the check and `wfi`, so a byte arriving in between still wakes it.
pub fn wait_for_input(inputs: &[&uart::Uart]) {
    cortex_m::interrupt::free(|_| {
        if !inputs.iter().any(|u| u.has_input()) {
            cortex_m::asm::wfi();
        }
    });
}

/// Unmasks the receive interrupts of `uarts` (they only wake [`wait_for_input`]).
pub fn enable_rx_interrupts(uarts: &[&uart::Uart]) {
    for u in uarts {
        // SAFETY: the handler only acknowledges the interrupt; no critical section relies on
        // these lines being masked.
        unsafe { cortex_m::peripheral::NVIC::unmask(Irq(u.rx_irq())) };
    }
}

/// Stops the board and hands `code` to whoever runs it: QEMU exits with it (semihosting).
pub fn halt(code: i32) -> ! {
    cortex_m::interrupt::disable();
    semihosting::process::exit(code)
}

#[exception]
unsafe fn DefaultHandler(irqn: i16) {
    if irqn == timer::TIMER0_IRQ as i16 {
        timer::on_wrap();
    } else if irqn == 0 {
        uart::on_rx_interrupt(uart::UART0);
    } else if irqn == 2 {
        uart::on_rx_interrupt(uart::UART1);
    } else {
        defmt::warn!("unexpected interrupt {}", irqn);
    }
}

#[exception]
unsafe fn NonMaskableInt() {
    watchdog::on_expiry();
}

#[exception]
unsafe fn HardFault(frame: &ExceptionFrame) -> ! {
    defmt::error!("hard fault at pc {=u32:#x}, lr {=u32:#x}", frame.pc(), frame.lr());
    halt(3)
}

#[panic_handler]
fn panic(info: &core::panic::PanicInfo) -> ! {
    // The vehicle must not act on a half-finished plan: log, then stop. The flight stack stops
    // receiving setpoints and fails safe on its own (PX4 leaves offboard mode after 0.5 s).
    defmt::error!("panic: {}", defmt::Display2Format(info));
    halt(101)
}
