//! MAVLink 2 signing on the companion's side of the autopilot link, for a board without a
//! calendar clock.

use crate::links::signing::{SecretKey, Signer, Verifier, VerifierCounters};

/// Signs what the companion sends and checks what it receives. The board has no calendar
/// clock, so, as the signing spec recommends for such systems, it signs with time taken from
/// the newest timestamp it has accepted, advanced by the autopilot time since (the signer also
/// never repeats one). Until it has accepted a signed frame its own frames carry boot-relative
/// timestamps, which an autopilot that already signs refuses as stale: the companion speaks
/// once it has heard the autopilot.
#[derive(Debug, Clone)]
pub struct LinkSigning<const STREAMS: usize> {
    signer: Signer,
    verifier: Verifier<STREAMS>,
    /// (newest accepted timestamp, autopilot ms when it was accepted).
    anchor: Option<(u64, u64)>,
}

impl<const STREAMS: usize> LinkSigning<STREAMS> {
    /// Signing with `key`, on link 0; no timestamp accepted yet.
    pub fn new(key: SecretKey) -> Self {
        Self {
            signer: Signer::new(key.clone(), 0),
            verifier: Verifier::new(key),
            anchor: None,
        }
    }

    /// The signing time (10 µs units) at autopilot time `now_ms`.
    pub fn now(&self, now_ms: u64) -> u64 {
        match self.anchor {
            Some((stamp, at_ms)) => stamp.saturating_add(now_ms.saturating_sub(at_ms).saturating_mul(100)),
            None => now_ms.saturating_mul(100),
        }
    }

    /// Whether a received frame may be acted on (counted either way); an accepted one moves
    /// the clock.
    pub fn admits(&mut self, raw: &[u8], now_ms: u64) -> bool {
        let ok = self.verifier.check(raw).is_ok();
        if ok {
            self.anchor = Some((self.verifier.newest(), now_ms));
        }
        ok
    }

    /// Signs the `len`-byte MAVLink 2 frame in `frame` at autopilot time `now_ms`; the signed
    /// length. A frame the signer refuses (not one the encoder wrote) goes out as it is.
    pub fn sign(&mut self, frame: &mut [u8], len: usize, now_ms: u64) -> usize {
        let stamp = self.now(now_ms);
        self.signer.sign(frame, len, stamp).unwrap_or(len)
    }

    /// What the verifier accepted and refused.
    pub fn counters(&self) -> &VerifierCounters {
        self.verifier.counters()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::links::mavlink::{encode_v2, MavHeader, MavMessage, MAX_FRAME_LEN};

    #[test]
    fn signing_time_follows_the_autopilot_and_unsigned_frames_do_not_move_it() {
        let mut signing = LinkSigning::<4>::new(SecretKey::from_hex(&"ab".repeat(32)).unwrap());
        assert_eq!(
            signing.now(1500),
            150_000,
            "boot-relative until a signed frame is accepted"
        );
        // A signed frame accepted at 2 s sets the clock; 1.5 s later it reads 150 000 more.
        signing.anchor = Some((7_000_000_000, 2000));
        assert_eq!(signing.now(3500), 7_000_150_000);
        let mut frame = [0u8; MAX_FRAME_LEN];
        let header = MavHeader {
            system_id: 255,
            component_id: 190,
            sequence: 0,
        };
        let n = encode_v2(
            &header,
            &MavMessage::HEARTBEAT(crate::links::mavlink::common::HEARTBEAT_DATA::DEFAULT),
            &mut frame,
        )
        .unwrap();
        assert!(!signing.admits(&frame[..n], 4000));
        assert_eq!(signing.anchor, Some((7_000_000_000, 2000)));
        assert_eq!(signing.counters().unsigned, 1);
    }
}
