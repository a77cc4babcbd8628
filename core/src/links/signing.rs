//! MAVLink 2 message signing (<https://mavlink.io/en/guide/message_signing.html>), without `std`
//! or allocation.
//!
//! A signed frame carries 13 more bytes after its checksum: the link id, a 48-bit timestamp
//! (units of 10 µs since 2015-01-01 00:00 UTC, little-endian) and the first 6 bytes of
//! `SHA-256(secret key ‖ frame from STX through the timestamp)`. The header's incompatibility
//! flag `0x01` marks it, and the checksum covers that flag. The `mavlink` crate's own signing
//! needs `std` (a mutex, a hash map, the system clock), so this module signs and checks raw
//! frames itself, with `sha2`, and keeps the replay state in fixed capacity:
//!
//! - [`Signer`] turns a frame [`crate::links::mavlink::encode_v2`] wrote into a signed one, with
//!   timestamps that never repeat on its link.
//! - [`Verifier`] accepts a frame only if it is signed with the shared key, its timestamp is
//!   newer than the last one accepted on its stream (system, component, link) and no more than
//!   a minute older than the newest timestamp the verifier has seen; anything else is a
//!   [`Rejection`], counted in [`VerifierCounters`].
//!
//! Checked byte for byte against pymavlink's signing (`scripts/mavlink_signing_vectors.py`
//! writes the frames the tests compare with). The host simulator's MAVLink link and its flight
//! emulator sign and verify with them (`harmonic-sim explore --mavlink … --mavlink-key FILE`);
//! a receiver drops a refused frame before the [`Bridge`](crate::links::mavlink::Bridge) sees it.

use ::mavlink::{calculate_crc, Message as _};
use sha2::{Digest, Sha256};

use crate::links::mavlink::MavMessage;

/// Bytes a signature adds to a frame: link id, timestamp, signature.
pub const SIGNATURE_LEN: usize = 13;
/// The header's incompatibility flag of a signed frame.
pub const IFLAG_SIGNED: u8 = 0x01;
/// How much older than the newest timestamp seen a frame's may be (one minute, in 10 µs).
pub const MAX_AGE: u64 = 6_000_000;
/// Bytes from STX through the message id of a MAVLink 2 frame.
const HEADER_LEN: usize = 10;
/// Largest 48-bit timestamp.
const MAX_TIMESTAMP: u64 = (1 << 48) - 1;

/// A 32-byte secret key shared by the signing peers.
#[derive(Clone, PartialEq, Eq)]
pub struct SecretKey([u8; 32]);

impl core::fmt::Debug for SecretKey {
    /// Never prints the key.
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.write_str("SecretKey(..)")
    }
}

/// Why a key could not be read.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum KeyError {
    /// Not 64 hexadecimal digits (surrounding white space allowed).
    NotHex64,
}

impl SecretKey {
    /// The key of these bytes.
    pub const fn new(bytes: [u8; 32]) -> Self {
        Self(bytes)
    }

    /// The key's bytes (to hand it on, say to a firmware build; never logged).
    pub const fn as_bytes(&self) -> &[u8; 32] {
        &self.0
    }

    /// Reads a key written as 64 hexadecimal digits (either case; ASCII white space around
    /// them is ignored), as `--mavlink-key` files hold it. A `const fn`, so the firmware reads
    /// its built-in key at compile time.
    pub const fn from_hex(text: &str) -> Result<Self, KeyError> {
        const fn nibble(c: u8) -> Option<u8> {
            match c {
                b'0'..=b'9' => Some(c - b'0'),
                b'a'..=b'f' => Some(c - b'a' + 10),
                b'A'..=b'F' => Some(c - b'A' + 10),
                _ => None,
            }
        }
        let mut digits = text.as_bytes().trim_ascii();
        if digits.len() != 64 {
            return Err(KeyError::NotHex64);
        }
        let mut key = [0u8; 32];
        let mut out: &mut [u8] = &mut key;
        while let ([hi, lo, rest @ ..], [byte, tail @ ..]) = (digits, out) {
            let (Some(hi), Some(lo)) = (nibble(*hi), nibble(*lo)) else {
                return Err(KeyError::NotHex64);
            };
            *byte = hi << 4 | lo;
            digits = rest;
            out = tail;
        }
        Ok(Self(key))
    }

    /// The first 6 bytes of `SHA-256(key ‖ data)`.
    fn signature(&self, data: &[u8]) -> [u8; 6] {
        let mut hasher = Sha256::new();
        hasher.update(self.0);
        hasher.update(data);
        let digest = hasher.finalize();
        let mut out = [0u8; 6];
        out.copy_from_slice(digest.get(..6).unwrap_or(&[0; 6]));
        out
    }
}

/// Why a frame could not be signed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum SignError {
    /// Not an unsigned MAVLink 2 frame of the given length (STX 0xFD, length byte consistent,
    /// no incompatibility flags).
    NotUnsignedV2,
    /// The message id is not one of the common dialect's (its CRC_EXTRA is unknown).
    UnknownMessage,
    /// The buffer has no room for the 13 signature bytes.
    BufferTooSmall,
}

/// Signs outgoing frames of one link.
#[derive(Debug, Clone)]
pub struct Signer {
    key: SecretKey,
    link_id: u8,
    last: Option<u64>,
}

impl Signer {
    /// A signer for link `link_id` with `key`.
    pub const fn new(key: SecretKey, link_id: u8) -> Self {
        Self {
            key,
            link_id,
            last: None,
        }
    }

    /// Signs the unsigned MAVLink 2 frame in `frame[..len]` in place (the buffer needs
    /// [`SIGNATURE_LEN`] bytes more) with the timestamp `now` (10 µs units since 2015-01-01),
    /// raised if needed above the last one this signer used so that none repeats. Returns the
    /// signed length.
    pub fn sign(&mut self, frame: &mut [u8], len: usize, now: u64) -> Result<usize, SignError> {
        let payload_len = usize::from(*frame.get(1).ok_or(SignError::NotUnsignedV2)?);
        if frame.first() != Some(&::mavlink::MAV_STX_V2)
            || frame.get(2) != Some(&0)
            || len != HEADER_LEN + payload_len + 2
            || len > frame.len()
        {
            return Err(SignError::NotUnsignedV2);
        }
        let signed_len = len + SIGNATURE_LEN;
        let frame = frame.get_mut(..signed_len).ok_or(SignError::BufferTooSmall)?;
        let id = frame
            .get(7..HEADER_LEN)
            .map(|b| b.iter().rev().fold(0u32, |id, &b| id << 8 | u32::from(b)))
            .ok_or(SignError::NotUnsignedV2)?;
        if MavMessage::default_message_from_id(id).is_none() {
            return Err(SignError::UnknownMessage);
        }
        let timestamp = match self.last {
            Some(last) if now <= last => last + 1,
            _ => now,
        }
        .min(MAX_TIMESTAMP);
        self.last = Some(timestamp);
        let crc_at = HEADER_LEN + payload_len;
        let (head, tail) = frame.split_at_mut(crc_at);
        if let Some(flags) = head.get_mut(2) {
            *flags = IFLAG_SIGNED;
        }
        let crc = calculate_crc(head.get(1..).unwrap_or(&[]), MavMessage::extra_crc(id));
        let (crc_bytes, signature) = tail.split_at_mut(2);
        crc_bytes.copy_from_slice(&crc.to_le_bytes());
        if let Some((link, stamp)) = signature.split_first_mut() {
            *link = self.link_id;
            if let Some(stamp) = stamp.get_mut(..6) {
                stamp.copy_from_slice(timestamp.to_le_bytes().get(..6).unwrap_or(&[0; 6]));
            }
        }
        let value = self.key.signature(frame.get(..signed_len - 6).unwrap_or(&[]));
        if let Some(out) = frame.get_mut(signed_len - 6..) {
            out.copy_from_slice(&value);
        }
        Ok(signed_len)
    }
}

/// Why an incoming frame was refused. A refused frame must not be acted on.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Rejection {
    /// The frame is not signed (MAVLink 1, or no signed flag).
    Unsigned,
    /// Not a well-formed signed MAVLink 2 frame (length, flags).
    Malformed,
    /// The signature does not match the key.
    BadSignature,
    /// The timestamp is not newer than the last one accepted on its stream.
    Replayed,
    /// The timestamp is more than [`MAX_AGE`] older than the newest seen.
    Stale,
    /// A new stream, but the verifier tracks as many as it can.
    TooManyStreams,
}

/// Counts of what a [`Verifier`] accepted and refused.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[cfg_attr(feature = "serde", derive(serde::Serialize))]
pub struct VerifierCounters {
    /// Frames accepted.
    pub accepted: u32,
    /// Refused: not signed.
    pub unsigned: u32,
    /// Refused: malformed.
    pub malformed: u32,
    /// Refused: wrong signature.
    pub bad_signature: u32,
    /// Refused: replayed timestamp.
    pub replayed: u32,
    /// Refused: too old.
    pub stale: u32,
    /// Refused: no room for a new stream.
    pub too_many_streams: u32,
}

/// Checks incoming frames against one key, tracking up to `N` streams (system, component,
/// link) for replay protection.
#[derive(Debug, Clone)]
pub struct Verifier<const N: usize> {
    key: SecretKey,
    streams: heapless::Vec<([u8; 3], u64), N>,
    newest: u64,
    counters: VerifierCounters,
}

impl<const N: usize> Verifier<N> {
    /// A verifier for `key` that has seen nothing yet.
    pub const fn new(key: SecretKey) -> Self {
        Self {
            key,
            streams: heapless::Vec::new(),
            newest: 0,
            counters: VerifierCounters {
                accepted: 0,
                unsigned: 0,
                malformed: 0,
                bad_signature: 0,
                replayed: 0,
                stale: 0,
                too_many_streams: 0,
            },
        }
    }

    /// What was accepted and refused so far.
    pub fn counters(&self) -> &VerifierCounters {
        &self.counters
    }

    /// The newest timestamp of an accepted frame (0 before the first). A signer without a
    /// clock of its own signs from it, as the signing spec recommends.
    pub fn newest(&self) -> u64 {
        self.newest
    }

    /// Accepts `frame` (one whole MAVLink frame, from STX) or says why not, and counts it.
    pub fn check(&mut self, frame: &[u8]) -> Result<(), Rejection> {
        let verdict = self.verdict(frame);
        let c = &mut self.counters;
        let count = match verdict {
            Ok(()) => &mut c.accepted,
            Err(Rejection::Unsigned) => &mut c.unsigned,
            Err(Rejection::Malformed) => &mut c.malformed,
            Err(Rejection::BadSignature) => &mut c.bad_signature,
            Err(Rejection::Replayed) => &mut c.replayed,
            Err(Rejection::Stale) => &mut c.stale,
            Err(Rejection::TooManyStreams) => &mut c.too_many_streams,
        };
        *count = count.saturating_add(1);
        verdict
    }

    fn verdict(&mut self, frame: &[u8]) -> Result<(), Rejection> {
        if frame.first() != Some(&::mavlink::MAV_STX_V2) {
            return Err(Rejection::Unsigned);
        }
        let flags = *frame.get(2).ok_or(Rejection::Malformed)?;
        if flags & IFLAG_SIGNED == 0 {
            return Err(Rejection::Unsigned);
        }
        let payload_len = usize::from(*frame.get(1).ok_or(Rejection::Malformed)?);
        let len = HEADER_LEN + payload_len + 2 + SIGNATURE_LEN;
        if flags != IFLAG_SIGNED || frame.len() != len {
            return Err(Rejection::Malformed);
        }
        let (signed, value) = frame.split_at(len - 6);
        if self.key.signature(signed) != value {
            return Err(Rejection::BadSignature);
        }
        let link_at = HEADER_LEN + payload_len + 2;
        let link = *frame.get(link_at).ok_or(Rejection::Malformed)?;
        let mut stamp = [0u8; 8];
        stamp
            .get_mut(..6)
            .zip(frame.get(link_at + 1..link_at + 7))
            .map(|(to, from)| to.copy_from_slice(from))
            .ok_or(Rejection::Malformed)?;
        let timestamp = u64::from_le_bytes(stamp);
        let stream = [
            *frame.get(5).ok_or(Rejection::Malformed)?,
            *frame.get(6).ok_or(Rejection::Malformed)?,
            link,
        ];
        if timestamp.saturating_add(MAX_AGE) < self.newest {
            return Err(Rejection::Stale);
        }
        match self.streams.iter_mut().find(|(s, _)| *s == stream) {
            Some((_, last)) if timestamp <= *last => return Err(Rejection::Replayed),
            Some((_, last)) => *last = timestamp,
            None => self
                .streams
                .push((stream, timestamp))
                .map_err(|_| Rejection::TooManyStreams)?,
        }
        self.newest = self.newest.max(timestamp);
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::links::mavlink::{common, encode_v2, MavHeader, MAX_FRAME_LEN};

    /// pymavlink 2.4.50, key 00 01 … 1f, link 3, timestamps 0x12_3456_789A and one more
    /// (`scripts/mavlink_signing_vectors.py`): a HEARTBEAT (onboard controller, no autopilot,
    /// active) and a SET_POSITION_TARGET_LOCAL_NED (t = 1234 ms, target 1/1, local NED,
    /// type mask 0x09F8, x 1.5, y −2.25, z −1, yaw 0.5) from system 1, component 191.
    const PYMAVLINK_HEARTBEAT: &str = "fd0901000001bf000000000000001208000403493e039a7856341200bba5de89f215";
    const PYMAVLINK_SETPOINT: &str = "fd3501000001bf540000d20400000000c03f000010c0000080bf0000000000000000000000000000000000000000000000000000003f00000000f809010101c63e039b78563412000965c43966e7";
    const T0: u64 = 0x12_3456_789A;

    fn key() -> SecretKey {
        let mut k = [0u8; 32];
        for (i, b) in k.iter_mut().enumerate() {
            *b = i as u8;
        }
        SecretKey::new(k)
    }

    fn bytes(hex: &str) -> heapless::Vec<u8, 300> {
        hex.as_bytes()
            .chunks(2)
            .map(|p| u8::from_str_radix(core::str::from_utf8(p).unwrap(), 16).unwrap())
            .collect()
    }

    fn header() -> MavHeader {
        MavHeader {
            system_id: 1,
            component_id: 191,
            sequence: 0,
        }
    }

    fn heartbeat() -> common::MavMessage {
        common::MavMessage::HEARTBEAT(common::HEARTBEAT_DATA {
            custom_mode: 0,
            mavtype: common::MavType::MAV_TYPE_ONBOARD_CONTROLLER,
            autopilot: common::MavAutopilot::MAV_AUTOPILOT_INVALID,
            base_mode: common::MavModeFlag::empty(),
            system_status: common::MavState::MAV_STATE_ACTIVE,
            mavlink_version: 3,
        })
    }

    fn setpoint() -> common::MavMessage {
        common::MavMessage::SET_POSITION_TARGET_LOCAL_NED(common::SET_POSITION_TARGET_LOCAL_NED_DATA {
            time_boot_ms: 1234,
            target_system: 1,
            target_component: 1,
            coordinate_frame: common::MavFrame::MAV_FRAME_LOCAL_NED,
            type_mask: crate::links::mavlink::POSITION_YAW_TYPEMASK,
            x: 1.5,
            y: -2.25,
            z: -1.0,
            yaw: 0.5,
            ..Default::default()
        })
    }

    fn signed(signer: &mut Signer, message: &common::MavMessage, now: u64) -> heapless::Vec<u8, 300> {
        let mut buf = [0u8; MAX_FRAME_LEN];
        let len = encode_v2(&header(), message, &mut buf).unwrap();
        let len = signer.sign(&mut buf, len, now).unwrap();
        buf[..len].iter().copied().collect()
    }

    #[test]
    fn frames_are_signed_byte_for_byte_as_pymavlink_signs_them() {
        let mut signer = Signer::new(key(), 3);
        assert_eq!(signed(&mut signer, &heartbeat(), T0), bytes(PYMAVLINK_HEARTBEAT));
        // A clock that did not move: the next timestamp is one more, as pymavlink's.
        assert_eq!(signed(&mut signer, &setpoint(), T0), bytes(PYMAVLINK_SETPOINT));
    }

    #[test]
    fn pymavlink_frames_are_accepted_and_every_forgery_refused() {
        let mut v: Verifier<4> = Verifier::new(key());
        let hb = bytes(PYMAVLINK_HEARTBEAT);
        let sp = bytes(PYMAVLINK_SETPOINT);
        assert_eq!(v.check(&hb), Ok(()));
        // The same frame again: a replay.
        assert_eq!(v.check(&hb), Err(Rejection::Replayed));
        assert_eq!(v.check(&sp), Ok(()));
        // Any changed byte (payload, header, timestamp, signature) breaks the signature.
        for i in [4, 12, 40, sp.len() - 8, sp.len() - 1] {
            let mut forged = sp.clone();
            forged[i] ^= 0x20;
            assert_eq!(v.check(&forged), Err(Rejection::BadSignature), "byte {i}");
        }
        // Another key signs nothing this verifier accepts.
        let mut other = Signer::new(SecretKey::new([7; 32]), 3);
        assert_eq!(
            v.check(&signed(&mut other, &heartbeat(), T0 + 10)),
            Err(Rejection::BadSignature)
        );
        // Unsigned frames, MAVLink 1 and truncated frames.
        let mut plain = [0u8; MAX_FRAME_LEN];
        let n = encode_v2(&header(), &heartbeat(), &mut plain).unwrap();
        assert_eq!(v.check(&plain[..n]), Err(Rejection::Unsigned));
        assert_eq!(v.check(&[0xFE, 9, 0, 1, 1]), Err(Rejection::Unsigned));
        assert_eq!(v.check(&sp[..sp.len() - 1]), Err(Rejection::Malformed));
        assert_eq!(v.check(&[]), Err(Rejection::Unsigned));
        let c = v.counters();
        assert_eq!(
            (c.accepted, c.replayed, c.bad_signature, c.unsigned, c.malformed),
            (2, 1, 6, 3, 1)
        );
    }

    #[test]
    fn old_timestamps_and_too_many_streams_are_refused() {
        let mut v: Verifier<2> = Verifier::new(key());
        let mut a = Signer::new(key(), 1);
        let mut b = Signer::new(key(), 2);
        let mut c = Signer::new(key(), 3);
        assert_eq!(v.check(&signed(&mut a, &heartbeat(), T0 + MAX_AGE + 5)), Ok(()));
        // Link 2 starts more than a minute behind the newest timestamp seen.
        assert_eq!(v.check(&signed(&mut b, &heartbeat(), T0)), Err(Rejection::Stale));
        assert_eq!(v.check(&signed(&mut b, &heartbeat(), T0 + 10)), Ok(()));
        // A third stream does not fit a two-stream verifier; the first two still work.
        assert_eq!(
            v.check(&signed(&mut c, &heartbeat(), T0 + MAX_AGE + 6)),
            Err(Rejection::TooManyStreams)
        );
        assert_eq!(v.check(&signed(&mut a, &heartbeat(), T0 + MAX_AGE + 6)), Ok(()));
    }

    #[test]
    fn keys_are_read_from_hex_and_never_printed() {
        let hex = "000102030405060708090a0b0c0d0e0f101112131415161718191A1B1C1D1E1F\n";
        assert_eq!(SecretKey::from_hex(hex), Ok(key()));
        for bad in [
            "",
            "00",
            &hex[..62],
            "zz0102030405060708090a0b0c0d0e0f101112131415161718191a1b1c1d1e1f",
        ] {
            assert_eq!(SecretKey::from_hex(bad), Err(KeyError::NotHex64), "{bad:?}");
        }
        let mut s = heapless::String::<32>::new();
        core::fmt::write(&mut s, format_args!("{:?}", key())).unwrap();
        assert_eq!(s.as_str(), "SecretKey(..)");
    }

    #[test]
    fn only_unsigned_v2_frames_of_known_messages_are_signed() {
        let mut signer = Signer::new(key(), 0);
        let mut buf = [0u8; MAX_FRAME_LEN];
        let len = encode_v2(&header(), &heartbeat(), &mut buf).unwrap();
        assert_eq!(signer.sign(&mut buf, len + 1, T0), Err(SignError::NotUnsignedV2));
        assert_eq!(
            signer.sign(&mut buf[..len + 5], len, T0),
            Err(SignError::BufferTooSmall)
        );
        let signed_len = signer.sign(&mut buf, len, T0).unwrap();
        assert_eq!(signed_len, len + SIGNATURE_LEN);
        assert_eq!(
            signer.sign(&mut buf, signed_len, T0),
            Err(SignError::NotUnsignedV2)
        );
        let mut unknown = [
            0xFD, 0, 0, 0, 0, 1, 1, 0xFF, 0xFF, 0xFF, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0,
        ];
        assert_eq!(signer.sign(&mut unknown, 12, T0), Err(SignError::UnknownMessage));
    }
}
