//! The CMSDK APB UART of the MPS2 boards (ARM DDI 0479, "Cortex-M System Design Kit"), polled,
//! behind the `embedded-io` traits. Retargeting replaces this file: the rest of the firmware
//! sees only `Read`, `ReadReady`, `Write`.

use core::convert::Infallible;
use core::ptr::{read_volatile, write_volatile};

/// UART0 base address on mps2-an386: the depth link.
pub const UART0: usize = 0x4000_4000;
/// UART1 base address: MAVLink.
pub const UART1: usize = 0x4000_5000;

const DATA: usize = 0x00;
const STATE: usize = 0x04;
const CTRL: usize = 0x08;
const INTSTATUS: usize = 0x0C;
const BAUDDIV: usize = 0x10;

const STATE_TX_FULL: u32 = 1 << 0;
const STATE_RX_FULL: u32 = 1 << 1;
const CTRL_TX_EN: u32 = 1 << 0;
const CTRL_RX_EN: u32 = 1 << 1;
const CTRL_RX_INT_EN: u32 = 1 << 3;
const INT_RX: u32 = 1 << 1;

/// One CMSDK UART, owned: [`Uart::new`] takes its base address once.
pub struct Uart {
    base: usize,
}

impl Uart {
    /// Enables transmit and receive at `baud` with the 25 MHz peripheral clock.
    ///
    /// # Safety
    /// `base` must be a CMSDK UART's register block that nothing else uses.
    pub unsafe fn new(base: usize, baud: u32) -> Self {
        let uart = Self { base };
        // The divider must be at least 16 or the UART does not run.
        let div = (super::nvic::PCLK_HZ / baud.max(1)).max(16);
        uart.write_reg(BAUDDIV, div);
        uart.write_reg(CTRL, CTRL_TX_EN | CTRL_RX_EN | CTRL_RX_INT_EN);
        uart
    }

    /// The NVIC line of this UART's receive interrupt on mps2-an386 (UART0: 0, UART1: 2).
    pub fn rx_irq(&self) -> u16 {
        (((self.base - UART0) / 0x1000) * 2) as u16
    }

    /// True if a received byte is waiting.
    pub fn has_input(&self) -> bool {
        self.rx_ready()
    }

    fn read_reg(&self, offset: usize) -> u32 {
        // SAFETY: `new`'s contract: a UART register block only this value uses.
        unsafe { read_volatile((self.base + offset) as *const u32) }
    }

    fn write_reg(&self, offset: usize, value: u32) {
        // SAFETY: as in `read_reg`.
        unsafe { write_volatile((self.base + offset) as *mut u32, value) }
    }

    fn rx_ready(&self) -> bool {
        self.read_reg(STATE) & STATE_RX_FULL != 0
    }

    fn write_byte(&self, byte: u8) {
        while self.read_reg(STATE) & STATE_TX_FULL != 0 {}
        self.write_reg(DATA, u32::from(byte));
    }
}

impl embedded_io::ErrorType for Uart {
    type Error = Infallible;
}

impl embedded_io::ReadReady for Uart {
    fn read_ready(&mut self) -> Result<bool, Infallible> {
        Ok(self.rx_ready())
    }
}

impl embedded_io::Read for Uart {
    /// Blocks for the first byte, then takes whatever else is already there.
    fn read(&mut self, buf: &mut [u8]) -> Result<usize, Infallible> {
        let mut n = 0;
        for slot in buf.iter_mut() {
            if n > 0 && !self.rx_ready() {
                break;
            }
            while !self.rx_ready() {}
            *slot = self.read_reg(DATA) as u8;
            n += 1;
        }
        Ok(n)
    }
}

impl embedded_io::Write for Uart {
    fn write(&mut self, buf: &[u8]) -> Result<usize, Infallible> {
        for &b in buf {
            self.write_byte(b);
        }
        Ok(buf.len())
    }

    fn flush(&mut self) -> Result<(), Infallible> {
        while self.read_reg(STATE) & STATE_TX_FULL != 0 {}
        Ok(())
    }
}

/// A receive interrupt of the UART at `base`: acknowledge it. (It only wakes the main loop from
/// `wfi`; the loop reads the byte.)
pub fn on_rx_interrupt(base: usize) {
    // SAFETY: writing INTSTATUS only clears the UART's interrupt flags.
    unsafe { write_volatile((base + INTSTATUS) as *mut u32, INT_RX) };
}
