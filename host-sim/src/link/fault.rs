//! Link fault injection: a middleware between the camera side's encoder and the wire, in the
//! manner of smoltcp's `FaultInjector` (an ordinary stage of the data path, not test-only
//! hackery). It damages what the depth link's encoder sends, reproducibly from a seed:
//!
//! - **frame faults**, on whole link frames (one Intrinsics, Pose, Heartbeat or depth chunk,
//!   delimiters included): each frame is dropped with probability [`FaultConfig::frame_drop`];
//!   otherwise duplicated with [`FaultConfig::frame_duplicate`] (sent twice in a row), and held
//!   back with [`FaultConfig::frame_reorder`] to go out after the next frame sent (a frame
//!   with no frame after it goes out in order at [`FaultInjector::flush`]: the depth link
//!   flushes after each image and each heartbeat, so frames are reordered within them);
//! - **byte faults**, on the bytes as they go out, in this order per byte: the byte is lost
//!   with [`FaultConfig::byte_drop`] (a receiver overrun); a noise burst starts with
//!   [`FaultConfig::burst_rate`] and replaces [`FaultConfig::burst_len`] bytes by random ones
//!   (bursts run on across frames, as line noise would); each of the 8 data bits flips with
//!   [`FaultConfig::bit_error_rate`] (start and stop bits are not modelled).
//!
//! Byte faults are drawn as geometric gaps between events, so a rate of 1e-9 costs nothing per
//! byte. Everything injected is counted in [`FaultCounters`], so a report can set what was done
//! against what the receiver noticed: with frame drops alone, the receiver's `frames_ok` is
//! exactly the frames sent minus [`FaultCounters::frames_dropped`] plus
//! [`FaultCounters::frames_duplicated`].
//!
//! [`Faulty`] puts an injector in front of any [`Wire`], as a wire itself: each
//! [`Wire::send`] is one link frame, and what the injector makes of a burst of frames goes on
//! to the inner wire at [`Wire::flush`]. The processor-in-the-loop camera, whose wire is a
//! board's UART, uses the [`FaultInjector`] directly.

use std::io;

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::Serialize;

use crate::link::transport::Wire;

/// Random-number stream of the fault injector (the sensor noise uses stream 0 of the same
/// seed), so adding link faults does not change the rendered depth.
const FAULT_STREAM: u64 = 0x4C49_4E4B; // "LINK"

/// What to inject. [`Default`] injects nothing.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct FaultConfig {
    /// Probability that a data bit is flipped.
    pub bit_error_rate: f64,
    /// Probability that a byte is lost.
    pub byte_drop: f64,
    /// Probability that a whole link frame is lost.
    pub frame_drop: f64,
    /// Probability that a link frame is sent twice.
    pub frame_duplicate: f64,
    /// Probability that a link frame is swapped with the frame after it.
    pub frame_reorder: f64,
    /// Probability, per byte, that a noise burst starts there.
    pub burst_rate: f64,
    /// Bytes a burst replaces by noise.
    pub burst_len: u32,
}

/// Default length of a noise burst, bytes: about 0.35 ms at 921600 baud, a motor-noise spike.
pub const DEFAULT_BURST_LEN: u32 = 32;

impl FaultConfig {
    /// True if nothing would be injected.
    pub fn is_clean(&self) -> bool {
        self.bit_error_rate == 0.0
            && self.byte_drop == 0.0
            && self.frame_drop == 0.0
            && self.frame_duplicate == 0.0
            && self.frame_reorder == 0.0
            && (self.burst_rate == 0.0 || self.burst_len == 0)
    }

    /// Checks that every probability is within 0..=1 (a frame or byte rate of 1 loses
    /// everything, which is allowed: the run then reports a dead link).
    pub fn check(&self) -> Result<(), String> {
        for (name, p) in [
            ("--link-ber", self.bit_error_rate),
            ("--link-byte-drop", self.byte_drop),
            ("--link-drop", self.frame_drop),
            ("--link-dup", self.frame_duplicate),
            ("--link-reorder", self.frame_reorder),
            ("--link-burst", self.burst_rate),
        ] {
            if !(p.is_finite() && (0.0..=1.0).contains(&p)) {
                return Err(format!("{name}: a probability between 0 and 1 expected, got {p}"));
            }
        }
        Ok(())
    }
}

/// Everything a [`FaultInjector`] did.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize)]
pub struct FaultCounters {
    /// Link frames handed in by the encoder.
    pub frames_in: u64,
    /// Link frames put on the wire (duplicates counted twice, drops not at all).
    pub frames_out: u64,
    /// Frames dropped whole.
    pub frames_dropped: u64,
    /// Frames sent twice.
    pub frames_duplicated: u64,
    /// Frames sent after the frame that followed them.
    pub frames_reordered: u64,
    /// Frames put on the wire with at least one byte fault in them.
    pub frames_damaged: u64,
    /// Data bits flipped.
    pub bits_flipped: u64,
    /// Bytes lost.
    pub bytes_dropped: u64,
    /// Noise bursts started.
    pub bursts: u64,
    /// Bytes replaced by burst noise.
    pub burst_bytes: u64,
    /// Bytes handed in by the encoder.
    pub bytes_in: u64,
    /// Bytes put on the wire.
    pub bytes_out: u64,
}

/// Draws gaps between independent events of probability `p` per trial.
#[derive(Debug, Clone, Copy)]
struct Gap {
    p: f64,
    /// Trials left before the next event.
    left: u64,
}

impl Gap {
    fn new(p: f64, rng: &mut ChaCha8Rng) -> Self {
        let mut gap = Self { p, left: 0 };
        gap.left = gap.draw(rng);
        gap
    }

    /// Trials before the next event: geometric with parameter `p` (never for `p` = 0).
    fn draw(&self, rng: &mut ChaCha8Rng) -> u64 {
        if self.p <= 0.0 {
            return u64::MAX;
        }
        if self.p >= 1.0 {
            return 0;
        }
        // U in (0, 1]: ln U ≤ 0.
        let u = 1.0 - rng.random::<f64>();
        let k = (u.ln() / (1.0 - self.p).ln()).floor();
        if k.is_finite() && k < u64::MAX as f64 {
            k as u64
        } else {
            u64::MAX
        }
    }

    /// Advances one trial; true if it is an event.
    fn step(&mut self, rng: &mut ChaCha8Rng) -> bool {
        if self.left == 0 {
            self.left = self.draw(rng);
            true
        } else {
            self.left = self.left.saturating_sub(1);
            false
        }
    }
}

/// The fault injector. See the [module documentation](self).
#[derive(Debug, Clone)]
pub struct FaultInjector {
    config: FaultConfig,
    rng: ChaCha8Rng,
    bits: Gap,
    byte_drops: Gap,
    bursts: Gap,
    burst_left: u32,
    /// A frame held back for reordering, and how many copies of it go out.
    held: Option<(Vec<u8>, usize)>,
    counters: FaultCounters,
}

impl FaultInjector {
    /// An injector with `config`, its random numbers drawn from `seed` (on a stream of its
    /// own: the same seed gives the same faults, whatever else uses it).
    pub fn new(config: FaultConfig, seed: u64) -> Self {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        rng.set_stream(FAULT_STREAM);
        let bits = Gap::new(config.bit_error_rate, &mut rng);
        let byte_drops = Gap::new(config.byte_drop, &mut rng);
        let burst_rate = if config.burst_len == 0 {
            0.0
        } else {
            config.burst_rate
        };
        let bursts = Gap::new(burst_rate, &mut rng);
        Self {
            config,
            rng,
            bits,
            byte_drops,
            bursts,
            burst_left: 0,
            held: None,
            counters: FaultCounters::default(),
        }
    }

    /// What was injected so far.
    pub fn counters(&self) -> &FaultCounters {
        &self.counters
    }

    /// What was injected so far, if this injector injects anything at all (`None` for a clean
    /// configuration, which passes every frame through as it is: reports leave it out).
    pub fn injected(&self) -> Option<FaultCounters> {
        (!self.config.is_clean()).then_some(self.counters)
    }

    /// Takes one link frame from the encoder and appends what goes on the wire to `wire`.
    pub fn send(&mut self, frame: &[u8], wire: &mut Vec<u8>) {
        self.counters.frames_in += 1;
        self.counters.bytes_in += frame.len() as u64;
        if self.chance(self.config.frame_drop) {
            self.counters.frames_dropped += 1;
            return;
        }
        let copies = if self.chance(self.config.frame_duplicate) {
            self.counters.frames_duplicated += 1;
            2
        } else {
            1
        };
        if self.held.is_none() && self.chance(self.config.frame_reorder) {
            self.held = Some((frame.to_vec(), copies));
            return;
        }
        for _ in 0..copies {
            self.transmit(frame, wire);
        }
        if self.held.is_some() {
            // The held frame goes out after this one: reordered.
            self.counters.frames_reordered += 1;
            self.flush(wire);
        }
    }

    /// Sends a frame held back for reordering, if any, in its place (call when no frame
    /// follows soon; it does not count as reordered).
    pub fn flush(&mut self, wire: &mut Vec<u8>) {
        if let Some((frame, copies)) = self.held.take() {
            for _ in 0..copies {
                self.transmit(&frame, wire);
            }
        }
    }

    /// Puts one frame on the wire through the byte faults.
    fn transmit(&mut self, frame: &[u8], wire: &mut Vec<u8>) {
        self.counters.frames_out += 1;
        let mut damaged = false;
        for &byte in frame {
            if self.byte_drops.step(&mut self.rng) {
                self.counters.bytes_dropped += 1;
                damaged = true;
                continue;
            }
            let mut out = byte;
            if self.burst_left == 0 && self.bursts.step(&mut self.rng) {
                self.counters.bursts += 1;
                self.burst_left = self.config.burst_len;
            }
            if self.burst_left > 0 {
                self.burst_left -= 1;
                self.counters.burst_bytes += 1;
                out = self.rng.random::<u8>();
                damaged |= out != byte;
            }
            for bit in 0..8 {
                if self.bits.step(&mut self.rng) {
                    out ^= 1 << bit;
                    self.counters.bits_flipped += 1;
                    damaged = true;
                }
            }
            wire.push(out);
            self.counters.bytes_out += 1;
        }
        if damaged {
            self.counters.frames_damaged += 1;
        }
    }

    fn chance(&mut self, p: f64) -> bool {
        p > 0.0 && self.rng.random::<f64>() < p
    }
}

/// A [`FaultInjector`] in front of a wire, as a wire: each [`Wire::send`] is one link frame,
/// damaged (or dropped, duplicated, held back) by the injector; at [`Wire::flush`] what came of
/// the frames since the last flush goes on to the inner wire in one piece, with a frame held
/// back for reordering in its place. See the [module documentation](self).
#[derive(Debug)]
pub struct Faulty<W> {
    injector: FaultInjector,
    inner: W,
    staged: Vec<u8>,
}

impl<W: Wire> Faulty<W> {
    /// `inner` behind an injector with `config` and `seed` ([`FaultInjector::new`]); a clean
    /// `config` passes every frame through unchanged.
    pub fn new(inner: W, config: FaultConfig, seed: u64) -> Self {
        Self {
            injector: FaultInjector::new(config, seed),
            inner,
            staged: Vec::new(),
        }
    }

    /// The injector (its counters).
    pub fn injector(&self) -> &FaultInjector {
        &self.injector
    }

    /// The wire behind the injector.
    pub fn inner(&self) -> &W {
        &self.inner
    }
}

impl<W: Wire> Wire for Faulty<W> {
    fn send(&mut self, frame: &[u8]) -> io::Result<()> {
        self.injector.send(frame, &mut self.staged);
        Ok(())
    }

    fn receive(&mut self, into: &mut Vec<u8>) -> io::Result<usize> {
        self.inner.receive(into)
    }

    fn is_immediate(&self) -> bool {
        self.inner.is_immediate()
    }

    fn flush(&mut self) -> io::Result<()> {
        self.injector.flush(&mut self.staged);
        // Even an empty burst goes on: a paced wire then marks its time.
        self.inner.send(&self.staged)?;
        self.staged.clear();
        self.inner.flush()
    }

    fn advance(&mut self, now_s: f64) {
        self.inner.advance(now_s);
    }

    fn release(&mut self) -> io::Result<()> {
        self.inner.release()
    }

    fn pending(&self) -> bool {
        !self.staged.is_empty() || self.inner.pending()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use harmonic_core::link::{DepthReceiver, Heartbeat, LinkEncoder, Message};

    /// `n` heartbeat frames, as the encoder sends them.
    fn frames(n: usize) -> Vec<Vec<u8>> {
        let mut enc = LinkEncoder::new();
        (0..n)
            .map(|i| {
                let mut out = [0u8; 64];
                let hb = Heartbeat {
                    uptime_ms: i as u32 * 1000,
                    frames_sent: i as u32,
                    ..Heartbeat::default()
                };
                let k = enc.encode(&Message::Heartbeat(hb), &mut out).unwrap();
                out[..k].to_vec()
            })
            .collect()
    }

    fn run(config: FaultConfig, seed: u64, frames: &[Vec<u8>]) -> (Vec<u8>, FaultCounters) {
        let mut inj = FaultInjector::new(config, seed);
        let mut wire = Vec::new();
        for f in frames {
            inj.send(f, &mut wire);
        }
        inj.flush(&mut wire);
        (wire, *inj.counters())
    }

    fn decode(wire: &[u8]) -> (Vec<u32>, harmonic_core::link::LinkCounters) {
        let mut buf = [0u16; 1];
        let mut rx = DepthReceiver::<64>::new(&mut buf);
        let mut uptimes = Vec::new();
        rx.feed(wire, |e| {
            if let harmonic_core::link::LinkEvent::Heartbeat(h) = e {
                uptimes.push(h.uptime_ms / 1000);
            }
        });
        (uptimes, rx.counters())
    }

    #[test]
    fn clean_config_passes_bytes_through() {
        let f = frames(50);
        let (wire, c) = run(FaultConfig::default(), 1, &f);
        assert!(FaultConfig::default().is_clean());
        assert_eq!(wire, f.concat());
        assert_eq!(
            (c.frames_in, c.frames_out, c.bytes_in, c.bytes_out),
            (50, 50, wire.len() as u64, wire.len() as u64)
        );
    }

    #[test]
    fn same_seed_same_faults_other_seed_other_faults() {
        let f = frames(400);
        let config = FaultConfig {
            bit_error_rate: 1e-3,
            frame_drop: 0.05,
            frame_duplicate: 0.05,
            frame_reorder: 0.05,
            byte_drop: 1e-3,
            burst_rate: 1e-3,
            burst_len: 8,
        };
        let a = run(config, 7, &f);
        assert_eq!(a, run(config, 7, &f));
        assert_ne!(a.0, run(config, 8, &f).0);
    }

    #[test]
    fn frame_drops_are_what_the_receiver_counts() {
        let f = frames(2000);
        let config = FaultConfig {
            frame_drop: 0.03,
            frame_duplicate: 0.02,
            ..FaultConfig::default()
        };
        let (wire, c) = run(config, 3, &f);
        let (_, rx) = decode(&wire);
        assert!(c.frames_dropped > 30 && c.frames_duplicated > 20, "{c:?}");
        assert_eq!(
            u64::from(rx.frames_ok),
            2000 - c.frames_dropped + c.frames_duplicated
        );
        // Every drop is a gap in the sequence numbers, unless the last frame itself was lost.
        let last_lost = u64::from(decode(&wire).0.last() != Some(&1999));
        assert_eq!(u64::from(rx.sequence_gaps) + last_lost, c.frames_dropped);
        assert_eq!(c.frames_damaged + c.bits_flipped + c.bytes_dropped, 0);
    }

    #[test]
    fn reordered_frames_arrive_one_later() {
        let f = frames(1000);
        let config = FaultConfig {
            frame_reorder: 0.1,
            ..FaultConfig::default()
        };
        let (wire, c) = run(config, 5, &f);
        let (order, rx) = decode(&wire);
        assert_eq!(order.len(), 1000, "nothing lost");
        let swapped = order.windows(2).filter(|w| w[1] < w[0]).count() as u64;
        assert_eq!(swapped, c.frames_reordered);
        assert!(c.frames_reordered > 50);
        assert_eq!(u64::from(rx.frames_ok), 1000);
        // A frame held with nothing after it goes out in order at the flush, uncounted.
        let always = FaultConfig {
            frame_reorder: 1.0,
            ..FaultConfig::default()
        };
        let (wire, c) = run(always, 5, &f[..1]);
        assert_eq!((wire, c.frames_reordered), (f[0].clone(), 0));
    }

    #[test]
    fn bit_error_rate_matches_and_every_flip_is_caught() {
        let f = frames(3000);
        let bits_on_wire = f.concat().len() as f64 * 8.0;
        let ber = 2e-4;
        let config = FaultConfig {
            bit_error_rate: ber,
            ..FaultConfig::default()
        };
        let (wire, c) = run(config, 11, &f);
        let expected = bits_on_wire * ber;
        let flips = c.bits_flipped as f64;
        // Poisson: 5 standard deviations.
        assert!(
            (flips - expected).abs() < 5.0 * expected.sqrt(),
            "{flips} vs {expected}"
        );
        let (got, rx) = decode(&wire);
        // No damaged heartbeat gets through as a wrong one.
        assert!(got.windows(2).all(|w| w[0] < w[1]));
        assert!(got.len() as u64 >= 3000 - c.frames_damaged);
        assert!(rx.crc_errors + rx.cobs_errors > 0);
    }

    #[test]
    fn bursts_and_byte_drops_damage_the_expected_amount() {
        let f = frames(3000);
        let config = FaultConfig {
            byte_drop: 1e-3,
            burst_rate: 2e-4,
            burst_len: 16,
            ..FaultConfig::default()
        };
        let (wire, c) = run(config, 13, &f);
        assert_eq!(c.bytes_out + c.bytes_dropped, c.bytes_in);
        assert_eq!(wire.len() as u64, c.bytes_out);
        assert!(c.bursts > 0 && c.burst_bytes <= c.bursts * 16 && c.burst_bytes > (c.bursts - 1) * 16);
        let expected = c.bytes_in as f64 * 1e-3;
        assert!((c.bytes_dropped as f64 - expected).abs() < 5.0 * expected.sqrt());
        let (got, _) = decode(&wire);
        assert!(got.len() < 3000 && got.len() as u64 >= 3000 - c.frames_damaged);
    }

    #[test]
    fn probabilities_outside_0_1_are_refused() {
        let bad = FaultConfig {
            frame_drop: 1.5,
            ..FaultConfig::default()
        };
        assert!(bad.check().unwrap_err().contains("--link-drop"));
        let nan = FaultConfig {
            bit_error_rate: f64::NAN,
            ..FaultConfig::default()
        };
        assert!(nan.check().unwrap_err().contains("--link-ber"));
        assert!(FaultConfig::default().check().is_ok());
    }
}
