//! The board's clock rate and interrupt lines, which the peripherals share.

/// Peripheral clock of the MPS2 FPGA images: 25 MHz.
pub const PCLK_HZ: u32 = 25_000_000;

/// An external interrupt line of the board's NVIC.
#[derive(Debug, Clone, Copy)]
pub struct Irq(pub u16);

// SAFETY: the numbers are lines of mps2-an386's NVIC (32 external interrupts), as the trait
// requires.
unsafe impl cortex_m::interrupt::InterruptNumber for Irq {
    fn number(self) -> u16 {
        self.0
    }
}
