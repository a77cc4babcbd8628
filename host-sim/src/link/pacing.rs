//! Baud pacing as a wire around any wire: bytes sent wait in a queue that drains onto the inner
//! wire at the link's baud rate in simulated time.
//!
//! A byte takes [`BITS_PER_BYTE`] bit times (8N1), so a 100 × 100 depth image (about 20 kB) is
//! on the wire for about 0.22 s at 921600 baud. Time moves by [`Wire::advance`]; the bytes whose
//! time has come go on at [`Wire::release`]. A queue earns sending time only while it holds
//! bytes, and an idle wire saves no time for later: bytes sent into an empty queue start
//! earning at the next advance, and what is left of a byte's time when the queue runs dry is
//! dropped.

use std::collections::VecDeque;
use std::io;

use crate::link::transport::Wire;

/// Bits on the wire per byte: start bit, 8 data bits, stop bit (8N1).
pub const BITS_PER_BYTE: f64 = 10.0;

/// A wire that paces the bytes sent through it at a baud rate. See the
/// [module documentation](self).
#[derive(Debug)]
pub struct Paced<W> {
    inner: W,
    bytes_per_s: f64,
    queue: VecDeque<u8>,
    /// Bytes the time so far allows onto the inner wire (fractional).
    credit: f64,
    now_s: f64,
    /// When the last byte queued will have left, simulated seconds.
    busy_until_s: f64,
    /// Simulated seconds of bytes queued, in all.
    busy_s: f64,
    bytes_queued: u64,
    bytes_released: u64,
}

impl<W: Wire> Paced<W> {
    /// Paces `inner` at `baud` (bits per second; 0 is refused by the link's options, and here
    /// holds every byte back).
    pub fn new(inner: W, baud: u32) -> Self {
        Self {
            inner,
            bytes_per_s: f64::from(baud) / BITS_PER_BYTE,
            queue: VecDeque::new(),
            credit: 0.0,
            now_s: 0.0,
            busy_until_s: 0.0,
            busy_s: 0.0,
            bytes_queued: 0,
            bytes_released: 0,
        }
    }

    /// The wire it paces.
    pub fn inner(&self) -> &W {
        &self.inner
    }

    /// When the last byte sent so far will have left, simulated seconds.
    pub fn busy_until_s(&self) -> f64 {
        self.busy_until_s
    }

    /// Simulated seconds of bytes sent, in all.
    pub fn busy_s(&self) -> f64 {
        self.busy_s
    }

    /// Bytes sent into the queue.
    pub fn bytes_queued(&self) -> u64 {
        self.bytes_queued
    }

    /// Bytes let onto the inner wire.
    pub fn bytes_released(&self) -> u64 {
        self.bytes_released
    }
}

impl<W: Wire> Wire for Paced<W> {
    fn send(&mut self, bytes: &[u8]) -> io::Result<()> {
        let duration = if self.bytes_per_s > 0.0 {
            bytes.len() as f64 / self.bytes_per_s
        } else {
            f64::INFINITY
        };
        self.busy_until_s = self.busy_until_s.max(self.now_s) + duration;
        self.busy_s += duration;
        self.bytes_queued += bytes.len() as u64;
        self.queue.extend(bytes);
        Ok(())
    }

    fn receive(&mut self, into: &mut Vec<u8>) -> io::Result<usize> {
        self.inner.receive(into)
    }

    fn is_immediate(&self) -> bool {
        self.inner.is_immediate()
    }

    fn flush(&mut self) -> io::Result<()> {
        self.inner.flush()
    }

    fn advance(&mut self, now_s: f64) {
        let elapsed = (now_s - self.now_s).max(0.0);
        self.now_s = now_s;
        if !self.queue.is_empty() {
            self.credit += elapsed * self.bytes_per_s;
        }
        self.inner.advance(now_s);
    }

    fn release(&mut self) -> io::Result<()> {
        let n = (self.credit.floor() as usize).min(self.queue.len());
        if n > 0 {
            self.credit -= n as f64;
            let (a, b) = self.queue.as_slices();
            let first = a.len().min(n);
            self.inner.send(&a[..first])?;
            self.inner.send(&b[..n - first])?;
            self.queue.drain(..n);
            self.bytes_released += n as u64;
        }
        if self.queue.is_empty() {
            // An idle wire saves no time for later.
            self.credit = 0.0;
        }
        self.inner.release()
    }

    fn pending(&self) -> bool {
        !self.queue.is_empty() || self.inner.pending()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::link::transport::Pipe;

    fn drain(w: &mut Paced<Pipe>) -> Vec<u8> {
        let mut got = Vec::new();
        w.receive(&mut got).unwrap();
        got
    }

    #[test]
    fn bytes_leave_at_the_baud_rate_in_order() {
        // 10 000 baud: 1000 bytes a second.
        let mut w = Paced::new(Pipe::default(), 10_000);
        let bytes: Vec<u8> = (0..=255).cycle().take(2500).collect();
        w.send(&bytes).unwrap();
        assert!((w.busy_until_s() - 2.5).abs() < 1e-12);
        let mut got = Vec::new();
        for (t, expect) in [(0.5, 500), (1.0, 1000), (2.2, 2200), (3.0, 2500)] {
            w.advance(t);
            w.release().unwrap();
            got.extend(drain(&mut w));
            assert_eq!(got.len(), expect, "at {t} s");
        }
        assert_eq!(got, bytes);
        assert!(!w.pending());
        assert_eq!((w.bytes_queued(), w.bytes_released()), (2500, 2500));
    }

    #[test]
    fn an_idle_wire_saves_no_time_for_later() {
        let mut w = Paced::new(Pipe::default(), 10_000);
        // Ten idle seconds earn nothing.
        w.advance(10.0);
        w.release().unwrap();
        w.send(&[7; 100]).unwrap();
        // Sent at 10 s: done at 10.1 s, not at once.
        assert!((w.busy_until_s() - 10.1).abs() < 1e-12);
        w.release().unwrap();
        assert!(drain(&mut w).is_empty());
        w.advance(10.05);
        w.release().unwrap();
        assert_eq!(drain(&mut w).len(), 50);
        w.advance(10.2);
        w.release().unwrap();
        assert_eq!(drain(&mut w).len(), 50);
        assert!(!w.pending());
    }
}
