//! Stack high-water mark by painting: at boot the free RAM between the statics and the stack
//! pointer is filled with a pattern; the deepest word no longer holding it is the most stack
//! ever used. What the RAM budget's stack reserve is checked against.

use core::ptr::{addr_of, read_volatile, write_volatile};

const PATTERN: u32 = 0x5AC3_A55A;

extern "C" {
    // cortex-m-rt's linker script: the top of the stack and the end of the statics.
    static _stack_start: u32;
    static _stack_end: u32;
}

fn bottom() -> usize {
    addr_of!(_stack_end) as usize
}

fn top() -> usize {
    addr_of!(_stack_start) as usize
}

/// Fills the unused stack with the pattern, up to 256 bytes below the current stack pointer.
///
/// # Safety
/// Call once, early, from the main stack; the memory below the stack pointer is free then.
pub unsafe fn paint() {
    let limit = (cortex_m::register::msp::read() as usize).saturating_sub(256);
    let mut p = bottom();
    while p + 4 <= limit {
        // SAFETY: between the statics and the live stack: memory nothing uses yet.
        unsafe { write_volatile(p as *mut u32, PATTERN) };
        p += 4;
    }
}

/// Bytes of stack used at most since [`paint`].
pub fn high_water() -> usize {
    let mut p = bottom();
    // SAFETY: reading RAM between the statics and the stack top.
    while p < top() && unsafe { read_volatile(p as *const u32) } == PATTERN {
        p += 4;
    }
    top() - p
}

/// Bytes between the statics and the top of RAM: the room the stack has.
pub fn room() -> usize {
    top() - bottom()
}
