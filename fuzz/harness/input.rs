//! The fuzz input as a stream of fields, shared by the harnesses (each includes this file).

/// How a harness draws a plausible float: the first `raw` byte values take raw bits, the
/// rest map to `byte * step + offset`.
#[derive(Clone, Copy)]
pub struct Floats {
    pub raw: u8,
    pub step: f32,
    pub offset: f32,
}

/// Reads fields from the fuzz input, zeros once it runs out.
pub struct Input<'a>(pub &'a [u8]);

// Each harness uses a subset of these readers.
#[allow(dead_code)]
impl Input<'_> {
    pub fn u8(&mut self) -> u8 {
        match self.0.split_first() {
            Some((&b, rest)) => {
                self.0 = rest;
                b
            }
            None => 0,
        }
    }
    pub fn u16(&mut self) -> u16 {
        u16::from_le_bytes([self.u8(), self.u8()])
    }
    pub fn u32(&mut self) -> u32 {
        u32::from_le_bytes([self.u8(), self.u8(), self.u8(), self.u8()])
    }
    pub fn u64(&mut self) -> u64 {
        u64::from(self.u32()) | (u64::from(self.u32()) << 32)
    }
    pub fn f32(&mut self) -> f32 {
        f32::from_bits(self.u32())
    }
    /// A float that is usually plausible, sometimes raw bits (see [`Floats`]).
    pub fn float(&mut self, f: Floats) -> f32 {
        match self.u8() {
            b if b < f.raw => self.f32(),
            b => f32::from(b) * f.step + f.offset,
        }
    }
    pub fn is_empty(&self) -> bool {
        self.0.is_empty()
    }
}
