//! The depth link: how depth images, camera intrinsics and poses travel from the camera side
//! to the core over a UART or any other byte stream.
//!
//! On a vehicle the stereo camera has its own processor and streams to the board that runs the
//! explorer. This module holds both ends of that link, without allocation:
//!
//! - [`Message`] — what travels: camera [`Intrinsics`], [`DepthChunk`]s (a run of rows of one
//!   depth image), an optional camera [`Pose`], a [`Heartbeat`], and before a mission the
//!   grid to map ([`MapGeometry`]); back, on a return channel if there is one, a
//!   [`ResendRequest`]. Checked once, when decoded.
//! - [`encode_frame`] and [`LinkEncoder`] — the sender: one message into one delimited frame
//!   in a caller buffer; [`LinkEncoder::encode_depth_frame`] cuts a whole image into chunks.
//! - [`FrameDecoder`] — the receiver's framing: bytes in any slicing in, checked messages out,
//!   a fixed buffer of `N` bytes, resynchronisation at the next delimiter after damage.
//! - [`DepthAssembler`] — chunks, in any order, into a caller-provided image buffer; yields a
//!   [`DepthFrame`] when every row arrived, or with the rows that did (the others
//!   [`NOT_RECEIVED`]) when the frame's time is up. Each row is independently useful.
//! - [`DepthReceiver`] — decoder and assembler together: what the core's input task runs. It
//!   says what is missing from a frame ([`DepthReceiver::resend_request`]) for selective
//!   retransmission, which the sender answers with [`LinkEncoder::encode_rows`].
//! - [`best_rows_per_chunk`], [`estimate_bit_error_rate`] — the chunk size for a line's bit
//!   error rate, and the rate a sender infers from the chunks it was asked to send again.
//! - [`LinkCounters`] — one counter per kind of fault, for the status output.
//!
//! # Wire format, version 1
//!
//! Every message travels as one frame:
//!
//! ```text
//! 0x00 │ COBS( payload │ CRC-32 of payload, u32 LE ) │ 0x00
//! payload = header (4 bytes) │ body (per message type)
//!
//! header   offset  type  field
//!          0       u8    protocol version = 1
//!          1       u8    message type (below)
//!          2       u16   sequence number: +1 per frame sent, any type, wrapping
//! ```
//!
//! All multi-byte fields are little-endian; `f32` is IEEE-754 binary32.
//!
//! - **CRC-32/ISO-HDLC** (the zlib / Ethernet `crc32`): reflected polynomial `0xEDB88320`,
//!   initial value `0xFFFFFFFF`, final xor `0xFFFFFFFF`; `crc32("123456789") = 0xCBF43926`.
//!   It covers header and body and is appended after them, before COBS encoding. Computed by
//!   the `crc` crate (`CRC_32_ISO_HDLC`, table-driven).
//! - **COBS** (Cheshire & Baker, 1999; the `cobs` crate's streaming encoder and in-place
//!   decoder, both no_std and allocation-free) removes every `0x00` from payload and CRC: the encoded
//!   bytes are groups, each a code byte `k` (1..=255) followed by `k − 1` non-zero bytes; a
//!   group with `k < 255` stands for its bytes followed by one `0x00`, except the last group.
//!   `n` bytes encode to at most `n + n / 254 + 1` bytes ([`max_encoded_len`]).
//! - **Delimiters**: the sender writes `0x00` before *and* after each frame. The receiver
//!   ignores empty frames, so back-to-back frames cost one extra byte, and line noise before a
//!   frame (a receiver that starts listening mid-stream, a glitch on an idle line) ends at that
//!   leading delimiter instead of corrupting the frame.
//!
//! Message bodies (offsets from the start of the body, i.e. after the 4-byte header):
//!
//! ```text
//! 0x01 Intrinsics, 20 bytes          0x02 DepthChunk, 12 + 2 · width · row_count bytes
//!   0  f32 fx  focal length, px        0  u32 frame_id   same for all chunks of an image
//!   4  f32 fy                          4  u16 width      of the whole image, > 0
//!   8  f32 cx  principal point, px     6  u16 height     of the whole image, > 0
//!  12  f32 cy                          8  u16 first_row
//!  16  u16 width   > 0                10  u16 row_count  > 0, first_row + row_count ≤ height
//!  18  u16 height  > 0                12  u16[width · row_count] depth, row-major,
//!                                             millimetres, 0 = no return
//!
//! 0x03 Pose, 32 bytes                0x04 Heartbeat, 16 bytes
//!   0  u32 frame_id  depth frame       0  u32 uptime_ms
//!   4  f32 tx, ty, tz  metres          4  u32 frames_sent     depth frames sent whole
//!  16  f32 qx, qy, qz, qw              8  u32 frames_skipped  captured, not sent (link busy)
//!      camera → map rotation          12  u32 sensor_errors
//!
//! 0x05 ResendRequest (core → camera), 6 + 4 · n bytes
//!   0  u32 frame_id
//!   4  u8  flags   bit 0: the pose, bit 1: the intrinsics; other bits 0
//!   5  u8  n       row ranges, at most 16
//!   6  (u16 first_row, u16 row_count > 0) × n
//!
//! 0x06 Geometry, 28 bytes: the grid the mission maps (sent before it starts)
//!   0  u32 nx, ny, nz   voxels along x, y, z, each > 0
//!  12  f32 ox, oy, oz   map-frame position of the grid's minimum corner, metres
//!  24  f32 resolution   voxel edge, metres, > 0
//! ```
//!
//! Intrinsics must be finite with positive focal lengths and the principal point inside the
//! image (−0.5 ≤ cx ≤ width − 0.5, likewise cy), as [`Intrinsics::new`] checks. A pose is the
//! camera → map transform of the depth frame with the same id (the `camera_pose` of
//! [`integrate`](crate::mapping::integrate::integrate)): all seven numbers finite and
//! `|q|` within [`UNIT_QUATERNION_TOLERANCE`] of 1. A body whose length differs from the table
//! is malformed; so is a chunk with zero width, height or rows, or rows past the height, and a
//! geometry that [`MapGeometry::new`] refuses.
//!
//! Sender conventions: an Intrinsics message before the chunks of every image (so a receiver
//! that starts late, or lost one, recovers at the next image); a Pose, if the camera side owns
//! the pose, before the chunks of its image; the chunks of an image in row order without gaps;
//! frame ids +1 per image. [`LinkEncoder::encode_depth_frame`] does all but the pose.
//!
//! Test vector: a Heartbeat with sequence number 1, uptime 1000 ms, 7 frames sent, 2 skipped
//! and 0 sensor errors is, on the wire,
//!
//! ```text
//! 00 04 01 04 01 03 E8 03 01 02 07 01 01 02 02 01 01 01 01 01 01 05 7F 60 E7 5D 00
//! ```
//!
//! # Bandwidth
//!
//! A 100 × 100 image in chunks of 10 rows is one Intrinsics frame (at most 31 bytes) and ten
//! chunk frames (at most 2030 bytes each): at most 20 331 bytes, 1.7 % over the 20 000 bytes of
//! raw depth, 0.221 s at 921 600 baud (8N1, 92 160 bytes/s). Zeros in the data make COBS
//! cheaper, so real images come in slightly under the bound. Smaller chunks cost more framing
//! (1 row per chunk: +11.7 %) but need a smaller decoder buffer ([`max_depth_chunk_len`]).
//!
//! # Faults
//!
//! Damage does not produce a wrong message (short of a CRC-32 collision, 2⁻³² per damaged
//! frame): a frame that fails COBS, CRC, version, type or body checks is dropped and counted,
//! and decoding resumes at the next delimiter. A chunk is a unit on its own: a depth image is
//! delivered with the rows whose chunks arrived intact, in whatever order, once all have or
//! once the receiver gives it up (a newer image starts, or the caller's deadline); rows that
//! never arrived hold [`NOT_RECEIVED`], which integration skips. A chunk that contradicts its
//! image, or an image that does not fit, is dropped and counted in [`LinkCounters`].
//!
//! # Selective retransmission
//!
//! With a return channel, the receiving side asks for what an image lacks before giving it up:
//! [`DepthReceiver::resend_request`] lists the missing rows (and the pose or intrinsics, if
//! lost) in a [`ResendRequest`]; the camera side, which keeps its last image, answers with
//! [`LinkEncoder::encode_rows`] and the pose again. The caller bounds the rounds. Lost chunks
//! also tell the sender the line's quality: [`estimate_bit_error_rate`] turns the fraction
//! asked for again into a bit error rate, [`best_rows_per_chunk`] that into the chunk size
//! that carries the most depth per byte (at 1e-4, one 100-pixel row per chunk: 4× the
//! throughput of ten).

use core::num::NonZeroUsize;

use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion};

use crate::mapping::camera::{DepthFrame, Intrinsics, IntrinsicsError};
use crate::mapping::map::{Dims, MapGeometry};

/// Protocol version this module speaks (header byte 0).
pub const PROTOCOL_VERSION: u8 = 1;
/// Frame delimiter. COBS guarantees it appears nowhere inside a frame.
pub const DELIMITER: u8 = 0x00;
/// Bytes of the header every payload starts with: version, type, sequence number.
pub const HEADER_LEN: usize = 4;
/// Bytes of the CRC-32 that follows the payload inside the COBS encoding.
pub const CRC_LEN: usize = 4;
/// Body bytes of an Intrinsics message.
pub const INTRINSICS_BODY_LEN: usize = 20;
/// Body bytes of a depth chunk before its depth values.
pub const DEPTH_CHUNK_HEADER_LEN: usize = 12;
/// Body bytes of a Pose message.
pub const POSE_BODY_LEN: usize = 32;
/// Body bytes of a Heartbeat message.
pub const HEARTBEAT_BODY_LEN: usize = 16;
/// Body bytes of a Geometry message.
pub const GEOMETRY_BODY_LEN: usize = 28;
/// Row ranges a [`ResendRequest`] holds at most; rows past them are asked for in the next
/// request.
pub const MAX_RESEND_RANGES: usize = 16;
/// Body bytes of a ResendRequest before its row ranges (4 bytes each).
pub const RESEND_REQUEST_HEADER_LEN: usize = 6;
/// Rows an image may have at most: the assembler keeps a bitmap of the rows that arrived.
pub const MAX_IMAGE_ROWS: u16 = 2048;
/// Depth value of a pixel whose row never arrived, in a partially delivered frame (see
/// [`crate::mapping::camera::NOT_RECEIVED`]).
pub use crate::mapping::camera::NOT_RECEIVED;
/// How far the norm of a pose quaternion may be from 1.
pub const UNIT_QUATERNION_TOLERANCE: f32 = 1e-3;
/// A chunk whose frame id is at most this far behind the newest frame seen is a late or
/// duplicated chunk and is dropped; further behind, it is taken as a new frame (the sender
/// restarted its frame ids).
pub const STALE_FRAME_WINDOW: u32 = 16;

/// Worst-case bytes on the wire for one frame whose payload (header and body) is
/// `payload_len` bytes: COBS overhead, CRC and both delimiters included.
#[allow(
    clippy::integer_division_remainder_used,
    reason = "the divisor is the constant 254 (a const fn cannot divide by a NonZero)"
)]
pub const fn max_encoded_len(payload_len: usize) -> usize {
    let n = payload_len.saturating_add(CRC_LEN);
    n.saturating_add(n / 254).saturating_add(3)
}

/// Payload bytes (header and body) of a depth chunk of `rows` rows of `width` pixels.
pub const fn depth_chunk_payload_len(width: u16, rows: u16) -> usize {
    let samples = (width as usize).saturating_mul(rows as usize);
    (HEADER_LEN + DEPTH_CHUNK_HEADER_LEN).saturating_add(samples.saturating_mul(2))
}

/// Worst-case bytes on the wire for a depth chunk of `rows` rows of `width` pixels. A
/// [`FrameDecoder`] with at least this capacity accepts such chunks; a scratch buffer of this
/// size suffices for [`LinkEncoder::encode_depth_frame`].
pub const fn max_depth_chunk_len(width: u16, rows: u16) -> usize {
    max_encoded_len(depth_chunk_payload_len(width, rows))
}

/// The kinds of message on the link (header byte 1).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[repr(u8)]
pub enum MessageType {
    /// Camera intrinsics of the images that follow.
    Intrinsics = 0x01,
    /// A run of rows of one depth image.
    DepthChunk = 0x02,
    /// Camera pose of one depth image.
    Pose = 0x03,
    /// Camera-side liveness and counters.
    Heartbeat = 0x04,
    /// Core side to camera side, on the return channel: send these rows (and pose, intrinsics)
    /// of an image again.
    ResendRequest = 0x05,
    /// The grid the mission maps: dimensions, origin, resolution.
    Geometry = 0x06,
}

impl MessageType {
    /// The message type with wire code `code`, if there is one.
    pub fn from_code(code: u8) -> Option<Self> {
        match code {
            0x01 => Some(Self::Intrinsics),
            0x02 => Some(Self::DepthChunk),
            0x03 => Some(Self::Pose),
            0x04 => Some(Self::Heartbeat),
            0x05 => Some(Self::ResendRequest),
            0x06 => Some(Self::Geometry),
            _ => None,
        }
    }

    /// The wire code of this message type.
    pub fn code(self) -> u8 {
        self as u8
    }
}

/// Why a message body was rejected although its frame was intact.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Malformed {
    /// The frame is shorter than a header and a CRC.
    Truncated,
    /// The body length does not match the message type (for a chunk: its width × rows).
    BodyLength,
    /// A depth chunk with zero width, height or rows, or rows past the image height.
    ChunkGeometry,
    /// Intrinsics that [`Intrinsics::new`] rejects.
    Intrinsics(IntrinsicsError),
    /// A pose that [`Pose::new`] rejects.
    Pose(PoseError),
    /// A resend request with more than [`MAX_RESEND_RANGES`] ranges, an empty range, or flags
    /// this version does not know.
    ResendRequest,
    /// A grid geometry that [`MapGeometry::new`] refuses (a zero dimension, a resolution that
    /// is not positive, an origin too far out for `f32` to tell the voxels apart).
    Geometry,
}

/// Everything that can go wrong on the link. Each variant but [`LinkError::BufferTooSmall`]
/// (a sender-side error) has a counter in [`LinkCounters`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum LinkError {
    /// Sender: the output buffer cannot hold the encoded frame.
    BufferTooSmall,
    /// More bytes between two delimiters than the decoder's capacity; dropped whole.
    Oversize,
    /// The bytes between two delimiters are not valid COBS.
    Cobs,
    /// The CRC does not match the payload.
    Crc,
    /// Intact frame of another protocol version.
    BadVersion(u8),
    /// Intact frame of a message type this version does not know.
    UnknownType(u8),
    /// Intact frame whose body is not a valid message.
    Malformed(Malformed),
    /// A chunk whose rows all arrived already (a duplicate, a resend that crossed the first
    /// copy), or a late chunk of an earlier frame; dropped, the frame in progress continues.
    OutOfOrderChunk,
    /// Rows of a frame never arrived before it was finished ([`DepthReceiver::finish_frame`])
    /// or a newer frame started: [`DepthReceiver`] delivers what arrived (the missing rows hold
    /// [`NOT_RECEIVED`]); a bare [`DepthAssembler`] that is not finished first drops it.
    MissingChunks,
    /// A chunk whose image size differs from the earlier chunks of its frame; the frame was
    /// dropped whole.
    ChunkMismatch,
    /// The image is larger than the assembler's buffer; the frame was dropped whole.
    FrameTooLarge,
    /// A frame completed before any intrinsics arrived; dropped.
    NoIntrinsics,
    /// A frame completed whose size differs from the last intrinsics; dropped.
    IntrinsicsMismatch,
}

/// Counts of link traffic and of every fault since start. The decoder and the assembler each
/// count what they see; [`LinkCounters::merged`] adds them up.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[cfg_attr(feature = "serde", derive(serde::Serialize))]
pub struct LinkCounters {
    /// Bytes received.
    pub bytes: u64,
    /// Frames that decoded into a valid message.
    pub frames_ok: u32,
    /// Frames with a wrong CRC.
    pub crc_errors: u32,
    /// Frames that were not valid COBS.
    pub cobs_errors: u32,
    /// Frames longer than the decoder's capacity.
    pub oversize: u32,
    /// Intact frames of another protocol version.
    pub bad_version: u32,
    /// Intact frames of an unknown message type.
    pub unknown_type: u32,
    /// Intact frames with an invalid body (truncated, wrong length, bad values), and chunks
    /// contradicting their frame.
    pub malformed: u32,
    /// Frames missing by sequence number (lost whole, or damaged beyond recognition).
    pub sequence_gaps: u32,
    /// Chunks dropped as duplicate or late.
    pub out_of_order_chunks: u32,
    /// Depth frames that ended with rows that never arrived: delivered partially
    /// ([`LinkCounters::depth_frames_partial`]) or dropped.
    pub missing_chunks: u32,
    /// Depth frames larger than the assembler's buffer.
    pub frame_too_large: u32,
    /// Depth frames complete before any intrinsics arrived.
    pub no_intrinsics: u32,
    /// Depth frames whose size differed from the last intrinsics.
    pub intrinsics_mismatch: u32,
    /// Depth frames delivered whole.
    pub depth_frames_complete: u32,
    /// Depth frames of which some chunk arrived but which were not delivered.
    pub depth_frames_dropped: u32,
    /// Depth frames delivered with rows missing (finished, or displaced by a newer frame).
    pub depth_frames_partial: u32,
    /// Rows missing from the partially delivered frames, all together.
    pub rows_missing: u32,
}

fn bump(counter: &mut u32) {
    *counter = counter.saturating_add(1);
}

impl LinkCounters {
    /// All zero, in a `const fn` so that decoders can live in `static`s.
    pub const fn new() -> Self {
        Self {
            bytes: 0,
            frames_ok: 0,
            crc_errors: 0,
            cobs_errors: 0,
            oversize: 0,
            bad_version: 0,
            unknown_type: 0,
            malformed: 0,
            sequence_gaps: 0,
            out_of_order_chunks: 0,
            missing_chunks: 0,
            frame_too_large: 0,
            no_intrinsics: 0,
            intrinsics_mismatch: 0,
            depth_frames_complete: 0,
            depth_frames_dropped: 0,
            depth_frames_partial: 0,
            rows_missing: 0,
        }
    }

    /// Counts one occurrence of `error` (nothing for [`LinkError::BufferTooSmall`]).
    pub fn record(&mut self, error: LinkError) {
        let counter = match error {
            LinkError::BufferTooSmall => return,
            LinkError::Oversize => &mut self.oversize,
            LinkError::Cobs => &mut self.cobs_errors,
            LinkError::Crc => &mut self.crc_errors,
            LinkError::BadVersion(_) => &mut self.bad_version,
            LinkError::UnknownType(_) => &mut self.unknown_type,
            LinkError::Malformed(_) | LinkError::ChunkMismatch => &mut self.malformed,
            LinkError::OutOfOrderChunk => &mut self.out_of_order_chunks,
            LinkError::MissingChunks => &mut self.missing_chunks,
            LinkError::FrameTooLarge => &mut self.frame_too_large,
            LinkError::NoIntrinsics => &mut self.no_intrinsics,
            LinkError::IntrinsicsMismatch => &mut self.intrinsics_mismatch,
        };
        bump(counter);
    }

    /// Field-by-field sum (saturating) of two sets of counters.
    pub fn merged(&self, other: &Self) -> Self {
        let add = |a: u32, b: u32| a.saturating_add(b);
        Self {
            bytes: self.bytes.saturating_add(other.bytes),
            frames_ok: add(self.frames_ok, other.frames_ok),
            crc_errors: add(self.crc_errors, other.crc_errors),
            cobs_errors: add(self.cobs_errors, other.cobs_errors),
            oversize: add(self.oversize, other.oversize),
            bad_version: add(self.bad_version, other.bad_version),
            unknown_type: add(self.unknown_type, other.unknown_type),
            malformed: add(self.malformed, other.malformed),
            sequence_gaps: add(self.sequence_gaps, other.sequence_gaps),
            out_of_order_chunks: add(self.out_of_order_chunks, other.out_of_order_chunks),
            missing_chunks: add(self.missing_chunks, other.missing_chunks),
            frame_too_large: add(self.frame_too_large, other.frame_too_large),
            no_intrinsics: add(self.no_intrinsics, other.no_intrinsics),
            intrinsics_mismatch: add(self.intrinsics_mismatch, other.intrinsics_mismatch),
            depth_frames_complete: add(self.depth_frames_complete, other.depth_frames_complete),
            depth_frames_dropped: add(self.depth_frames_dropped, other.depth_frames_dropped),
            depth_frames_partial: add(self.depth_frames_partial, other.depth_frames_partial),
            rows_missing: add(self.rows_missing, other.rows_missing),
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Messages

/// Why a pose was rejected.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum PoseError {
    /// A translation or quaternion component is not finite.
    NotFinite,
    /// The quaternion's norm is not within [`UNIT_QUATERNION_TOLERANCE`] of 1.
    NotUnitQuaternion,
}

/// The camera pose (camera frame → map frame) of the depth frame with the same id, for setups
/// where the camera side owns the pose. Finite, with a unit quaternion (checked here).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Pose {
    frame_id: u32,
    translation: [f32; 3],
    rotation_xyzw: [f32; 4],
}

impl Pose {
    /// Checked constructor: all components finite, `|q|` within [`UNIT_QUATERNION_TOLERANCE`]
    /// of 1. `translation` is the camera origin in the map frame, metres; `rotation_xyzw`
    /// rotates camera-frame vectors into the map frame.
    pub fn new(frame_id: u32, translation: [f32; 3], rotation_xyzw: [f32; 4]) -> Result<Self, PoseError> {
        if !translation
            .iter()
            .chain(rotation_xyzw.iter())
            .all(|c| c.is_finite())
        {
            return Err(PoseError::NotFinite);
        }
        let norm = libm::sqrtf(rotation_xyzw.iter().map(|c| c * c).sum());
        if (norm - 1.0).abs() > UNIT_QUATERNION_TOLERANCE {
            return Err(PoseError::NotUnitQuaternion);
        }
        Ok(Self {
            frame_id,
            translation,
            rotation_xyzw,
        })
    }

    /// The pose of a camera given as an isometry (camera frame → map frame).
    pub fn from_isometry(frame_id: u32, camera_pose: &Isometry3<f32>) -> Result<Self, PoseError> {
        let t = camera_pose.translation.vector;
        let q = camera_pose.rotation.quaternion();
        Self::new(frame_id, [t.x, t.y, t.z], [q.i, q.j, q.k, q.w])
    }

    /// Id of the depth frame this pose belongs to.
    pub fn frame_id(&self) -> u32 {
        self.frame_id
    }
    /// Camera origin in the map frame, metres.
    pub fn translation(&self) -> [f32; 3] {
        self.translation
    }
    /// Rotation camera → map as a quaternion `[x, y, z, w]`, as received.
    pub fn rotation_xyzw(&self) -> [f32; 4] {
        self.rotation_xyzw
    }
    /// The pose as an isometry (camera frame → map frame), quaternion renormalised.
    pub fn isometry(&self) -> Isometry3<f32> {
        let [x, y, z, w] = self.rotation_xyzw;
        let [tx, ty, tz] = self.translation;
        Isometry3::from_parts(
            Translation3::new(tx, ty, tz),
            UnitQuaternion::new_normalize(Quaternion::new(w, x, y, z)),
        )
    }
}

/// Camera-side liveness and counters, sent periodically.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Heartbeat {
    /// Milliseconds since the camera side started.
    pub uptime_ms: u32,
    /// Depth frames sent whole.
    pub frames_sent: u32,
    /// Depth frames captured but not sent (the link was still busy).
    pub frames_skipped: u32,
    /// Sensor faults on the camera side.
    pub sensor_errors: u32,
}

/// What the core side asks the camera side to send again for one image, on the link's return
/// channel: up to [`MAX_RESEND_RANGES`] runs of rows, and the image's pose or the camera
/// intrinsics if they were lost. The camera side answers by sending them again, rows clamped to
/// its image (a run of `0xFFFF` rows from row 0 asks for a whole image none of whose rows
/// arrived).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ResendRequest {
    frame_id: u32,
    pose: bool,
    intrinsics: bool,
    ranges: [(u16, u16); MAX_RESEND_RANGES],
    len: u8,
}

impl ResendRequest {
    /// Flag bit: send the image's pose again.
    const POSE: u8 = 1;
    /// Flag bit: send the camera intrinsics again.
    const INTRINSICS: u8 = 2;

    /// A request for image `frame_id` that asks for nothing yet.
    pub const fn new(frame_id: u32) -> Self {
        Self {
            frame_id,
            pose: false,
            intrinsics: false,
            ranges: [(0, 0); MAX_RESEND_RANGES],
            len: 0,
        }
    }

    /// Also asks for the image's pose.
    pub fn with_pose(mut self) -> Self {
        self.pose = true;
        self
    }

    /// Also asks for the camera intrinsics.
    pub fn with_intrinsics(mut self) -> Self {
        self.intrinsics = true;
        self
    }

    /// Asks for `row_count` rows from `first_row`; false (nothing added) if the request is
    /// full or `row_count` is 0.
    pub fn push_rows(&mut self, first_row: u16, row_count: u16) -> bool {
        match self.ranges.get_mut(usize::from(self.len)) {
            Some(slot) if row_count > 0 => {
                *slot = (first_row, row_count);
                self.len += 1;
                true
            }
            _ => false,
        }
    }

    /// The image asked for.
    pub fn frame_id(&self) -> u32 {
        self.frame_id
    }
    /// Whether the pose is asked for.
    pub fn wants_pose(&self) -> bool {
        self.pose
    }
    /// Whether the intrinsics are asked for.
    pub fn wants_intrinsics(&self) -> bool {
        self.intrinsics
    }
    /// The runs of rows asked for, `(first_row, row_count)`.
    pub fn rows(&self) -> &[(u16, u16)] {
        self.ranges.get(..usize::from(self.len)).unwrap_or(&[])
    }
    /// Whether it asks for nothing.
    pub fn is_empty(&self) -> bool {
        self.len == 0 && !self.pose && !self.intrinsics
    }
    fn flags(&self) -> u8 {
        (u8::from(self.pose) * Self::POSE) | (u8::from(self.intrinsics) * Self::INTRINSICS)
    }
}

#[derive(Debug, Clone, Copy)]
enum SampleSource<'a> {
    /// Little-endian pairs, straight from a received frame.
    Wire(&'a [u8]),
    /// Values from the sender's image.
    Native(&'a [u16]),
}

/// A run of whole rows of one depth image. Its geometry is consistent (checked on
/// construction and on decoding): width, height and rows non-zero, rows within the height,
/// exactly `width × row_count` depth values.
#[derive(Debug, Clone, Copy)]
pub struct DepthChunk<'a> {
    frame_id: u32,
    width: u16,
    height: u16,
    first_row: u16,
    row_count: u16,
    samples: SampleSource<'a>,
}

impl<'a> DepthChunk<'a> {
    /// Rows `first_row ..` of image `frame_id` (`width × height` pixels); `depth_mm` holds whole
    /// rows, row-major, millimetres.
    pub fn new(
        frame_id: u32,
        width: u16,
        height: u16,
        first_row: u16,
        depth_mm: &'a [u16],
    ) -> Result<Self, LinkError> {
        let bad = LinkError::Malformed(Malformed::ChunkGeometry);
        let w = NonZeroUsize::new(usize::from(width)).ok_or(bad)?;
        if !depth_mm.len().is_multiple_of(w.get()) {
            return Err(bad);
        }
        let row_count = u16::try_from(depth_mm.len() / w).map_err(|_| bad)?;
        check_chunk_geometry(width, height, first_row, row_count)?;
        Ok(Self {
            frame_id,
            width,
            height,
            first_row,
            row_count,
            samples: SampleSource::Native(depth_mm),
        })
    }

    /// Id of the image this chunk belongs to.
    pub fn frame_id(&self) -> u32 {
        self.frame_id
    }
    /// Width of the whole image, pixels.
    pub fn width(&self) -> u16 {
        self.width
    }
    /// Height of the whole image, pixels.
    pub fn height(&self) -> u16 {
        self.height
    }
    /// First image row in this chunk.
    pub fn first_row(&self) -> u16 {
        self.first_row
    }
    /// Number of rows in this chunk.
    pub fn row_count(&self) -> u16 {
        self.row_count
    }
    /// Number of depth values in this chunk (`width × row_count`).
    pub fn sample_count(&self) -> usize {
        usize::from(self.width) * usize::from(self.row_count)
    }
    /// The depth values, row-major, millimetres (0 = no return).
    pub fn samples(&self) -> DepthSamples<'a> {
        DepthSamples { source: self.samples }
    }
}

impl PartialEq for DepthChunk<'_> {
    fn eq(&self, other: &Self) -> bool {
        self.frame_id == other.frame_id
            && self.width == other.width
            && self.height == other.height
            && self.first_row == other.first_row
            && self.row_count == other.row_count
            && self.samples().eq(other.samples())
    }
}

fn check_chunk_geometry(width: u16, height: u16, first_row: u16, row_count: u16) -> Result<(), LinkError> {
    let fits = u32::from(first_row) + u32::from(row_count) <= u32::from(height);
    if width == 0 || height == 0 || row_count == 0 || !fits {
        return Err(LinkError::Malformed(Malformed::ChunkGeometry));
    }
    Ok(())
}

/// Iterator over the depth values of a [`DepthChunk`], row-major, millimetres.
#[derive(Debug, Clone)]
pub struct DepthSamples<'a> {
    source: SampleSource<'a>,
}

impl Iterator for DepthSamples<'_> {
    type Item = u16;

    fn next(&mut self) -> Option<u16> {
        match &mut self.source {
            SampleSource::Wire(bytes) => {
                let all: &[u8] = bytes;
                let (pair, rest) = all.split_first_chunk::<2>()?;
                *bytes = rest;
                Some(u16::from_le_bytes(*pair))
            }
            SampleSource::Native(values) => {
                let all: &[u16] = values;
                let (first, rest) = all.split_first()?;
                *values = rest;
                Some(*first)
            }
        }
    }

    fn size_hint(&self) -> (usize, Option<usize>) {
        let n = match self.source {
            SampleSource::Wire(bytes) => bytes.len() >> 1,
            SampleSource::Native(values) => values.len(),
        };
        (n, Some(n))
    }
}

impl ExactSizeIterator for DepthSamples<'_> {}

/// One message of the depth link, checked.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Message<'a> {
    /// Camera intrinsics of the images that follow.
    Intrinsics(Intrinsics),
    /// A run of rows of one depth image.
    DepthChunk(DepthChunk<'a>),
    /// Camera pose of one depth image.
    Pose(Pose),
    /// Camera-side liveness and counters.
    Heartbeat(Heartbeat),
    /// Core side to camera side: send parts of an image again.
    ResendRequest(ResendRequest),
    /// The grid the mission maps.
    Geometry(MapGeometry),
}

impl<'a> Message<'a> {
    /// The wire type of this message.
    pub fn message_type(&self) -> MessageType {
        match self {
            Message::Intrinsics(_) => MessageType::Intrinsics,
            Message::DepthChunk(_) => MessageType::DepthChunk,
            Message::Pose(_) => MessageType::Pose,
            Message::Heartbeat(_) => MessageType::Heartbeat,
            Message::ResendRequest(_) => MessageType::ResendRequest,
            Message::Geometry(_) => MessageType::Geometry,
        }
    }

    /// Payload bytes (header and body) of this message; [`max_encoded_len`] of it bounds the
    /// frame on the wire.
    pub fn payload_len(&self) -> usize {
        match self {
            Message::Intrinsics(_) => HEADER_LEN + INTRINSICS_BODY_LEN,
            Message::DepthChunk(c) => depth_chunk_payload_len(c.width, c.row_count),
            Message::Pose(_) => HEADER_LEN + POSE_BODY_LEN,
            Message::Heartbeat(_) => HEADER_LEN + HEARTBEAT_BODY_LEN,
            Message::ResendRequest(r) => HEADER_LEN + RESEND_REQUEST_HEADER_LEN + 4 * r.rows().len(),
            Message::Geometry(_) => HEADER_LEN + GEOMETRY_BODY_LEN,
        }
    }

    fn write_body(&self, w: &mut CobsWriter<'_>) -> Result<(), LinkError> {
        match self {
            Message::Intrinsics(i) => {
                for v in [i.fx(), i.fy(), i.cx(), i.cy()] {
                    w.payload(&v.to_le_bytes())?;
                }
                w.payload(&i.width().to_le_bytes())?;
                w.payload(&i.height().to_le_bytes())
            }
            Message::DepthChunk(c) => {
                w.payload(&c.frame_id.to_le_bytes())?;
                for v in [c.width, c.height, c.first_row, c.row_count] {
                    w.payload(&v.to_le_bytes())?;
                }
                match c.samples {
                    SampleSource::Wire(bytes) => w.payload(bytes),
                    SampleSource::Native(values) => {
                        values.iter().try_for_each(|v| w.payload(&v.to_le_bytes()))
                    }
                }
            }
            Message::Pose(p) => {
                w.payload(&p.frame_id.to_le_bytes())?;
                for v in p.translation.iter().chain(p.rotation_xyzw.iter()) {
                    w.payload(&v.to_le_bytes())?;
                }
                Ok(())
            }
            Message::Heartbeat(h) => {
                for v in [h.uptime_ms, h.frames_sent, h.frames_skipped, h.sensor_errors] {
                    w.payload(&v.to_le_bytes())?;
                }
                Ok(())
            }
            Message::ResendRequest(r) => {
                w.payload(&r.frame_id.to_le_bytes())?;
                w.payload(&[r.flags(), r.len])?;
                for &(first, count) in r.rows() {
                    w.payload(&first.to_le_bytes())?;
                    w.payload(&count.to_le_bytes())?;
                }
                Ok(())
            }
            Message::Geometry(g) => {
                let dims = g.dims();
                for n in [dims.nx(), dims.ny(), dims.nz()] {
                    // A grid whose side does not fit 32 bits fits no memory either.
                    let n = u32::try_from(n).map_err(|_| LinkError::Malformed(Malformed::Geometry))?;
                    w.payload(&n.to_le_bytes())?;
                }
                for v in g.origin().coords.iter().chain([g.resolution()].iter()) {
                    w.payload(&v.to_le_bytes())?;
                }
                Ok(())
            }
        }
    }

    /// Decodes the body of a message of wire type `code`.
    fn decode(code: u8, body: &'a [u8]) -> Result<Self, LinkError> {
        let mut r = Reader { rest: body };
        let message = match MessageType::from_code(code).ok_or(LinkError::UnknownType(code))? {
            MessageType::Intrinsics => {
                let (fx, fy, cx, cy) = (r.f32()?, r.f32()?, r.f32()?, r.f32()?);
                let (width, height) = (r.u16()?, r.u16()?);
                r.end()?;
                let intrinsics = Intrinsics::new(fx, fy, cx, cy, width, height)
                    .map_err(|e| LinkError::Malformed(Malformed::Intrinsics(e)))?;
                Message::Intrinsics(intrinsics)
            }
            MessageType::DepthChunk => {
                let frame_id = r.u32()?;
                let (width, height, first_row, row_count) = (r.u16()?, r.u16()?, r.u16()?, r.u16()?);
                check_chunk_geometry(width, height, first_row, row_count)?;
                let expected = usize::from(width)
                    .checked_mul(usize::from(row_count))
                    .and_then(|n| n.checked_mul(2));
                if expected != Some(r.rest.len()) {
                    return Err(LinkError::Malformed(Malformed::BodyLength));
                }
                Message::DepthChunk(DepthChunk {
                    frame_id,
                    width,
                    height,
                    first_row,
                    row_count,
                    samples: SampleSource::Wire(r.rest),
                })
            }
            MessageType::Pose => {
                let frame_id = r.u32()?;
                let translation = [r.f32()?, r.f32()?, r.f32()?];
                let rotation = [r.f32()?, r.f32()?, r.f32()?, r.f32()?];
                r.end()?;
                let pose = Pose::new(frame_id, translation, rotation)
                    .map_err(|e| LinkError::Malformed(Malformed::Pose(e)))?;
                Message::Pose(pose)
            }
            MessageType::Heartbeat => {
                let heartbeat = Heartbeat {
                    uptime_ms: r.u32()?,
                    frames_sent: r.u32()?,
                    frames_skipped: r.u32()?,
                    sensor_errors: r.u32()?,
                };
                r.end()?;
                Message::Heartbeat(heartbeat)
            }
            MessageType::ResendRequest => {
                let bad = LinkError::Malformed(Malformed::ResendRequest);
                let mut request = ResendRequest::new(r.u32()?);
                let [flags, n] = r.array::<2>()?;
                if flags & !(ResendRequest::POSE | ResendRequest::INTRINSICS) != 0
                    || usize::from(n) > MAX_RESEND_RANGES
                {
                    return Err(bad);
                }
                request.pose = flags & ResendRequest::POSE != 0;
                request.intrinsics = flags & ResendRequest::INTRINSICS != 0;
                for _ in 0..n {
                    let (first, count) = (r.u16()?, r.u16()?);
                    if !request.push_rows(first, count) {
                        return Err(bad);
                    }
                }
                r.end()?;
                Message::ResendRequest(request)
            }
            MessageType::Geometry => {
                let bad = LinkError::Malformed(Malformed::Geometry);
                let side = |n: u32| usize::try_from(n).map_err(|_| bad);
                let (nx, ny, nz) = (side(r.u32()?)?, side(r.u32()?)?, side(r.u32()?)?);
                let origin = [r.f32()?, r.f32()?, r.f32()?];
                let resolution = r.f32()?;
                r.end()?;
                let dims = Dims::new(nx, ny, nz).map_err(|_| bad)?;
                let geometry = MapGeometry::new(dims, origin.into(), resolution).map_err(|_| bad)?;
                Message::Geometry(geometry)
            }
        };
        Ok(message)
    }
}

/// Little-endian field reader over a message body; running short is a length error.
struct Reader<'a> {
    rest: &'a [u8],
}

impl Reader<'_> {
    fn array<const K: usize>(&mut self) -> Result<[u8; K], LinkError> {
        let (head, rest) = self
            .rest
            .split_first_chunk::<K>()
            .ok_or(LinkError::Malformed(Malformed::BodyLength))?;
        self.rest = rest;
        Ok(*head)
    }
    fn u16(&mut self) -> Result<u16, LinkError> {
        self.array().map(u16::from_le_bytes)
    }
    fn u32(&mut self) -> Result<u32, LinkError> {
        self.array().map(u32::from_le_bytes)
    }
    fn f32(&mut self) -> Result<f32, LinkError> {
        self.array().map(f32::from_le_bytes)
    }
    fn end(&self) -> Result<(), LinkError> {
        if self.rest.is_empty() {
            Ok(())
        } else {
            Err(LinkError::Malformed(Malformed::BodyLength))
        }
    }
}

// ---------------------------------------------------------------------------------------------
// CRC-32/ISO-HDLC and COBS, from the `crc` and `cobs` crates

/// CRC-32/ISO-HDLC: the `crc` crate's table-driven implementation (a 1 KiB table in flash).
static CRC32: crc::Crc<u32> = crc::Crc::<u32>::new(&crc::CRC_32_ISO_HDLC);

/// CRC-32/ISO-HDLC (zlib's `crc32`) of `bytes`.
pub fn crc32(bytes: &[u8]) -> u32 {
    CRC32.checksum(bytes)
}

/// Streaming COBS encoder (the `cobs` crate's) into a slice, computing the CRC of the payload
/// it is given; [`write_frame`] puts the delimiters around it.
pub(crate) struct CobsWriter<'o> {
    cobs: cobs::CobsEncoder<'o>,
    crc: crc::Digest<'static, u32>,
}

impl CobsWriter<'_> {
    /// Payload bytes: into the CRC and the encoding.
    pub(crate) fn payload(&mut self, bytes: &[u8]) -> Result<(), LinkError> {
        self.crc.update(bytes);
        self.cobs.push(bytes).map_err(|_| LinkError::BufferTooSmall)
    }
}

/// One frame at the start of `out`: the leading delimiter, COBS of what `fill` writes as
/// payload followed by its CRC-32 (little-endian), the trailing delimiter. Returns the bytes
/// written.
pub(crate) fn write_frame(
    out: &mut [u8],
    fill: impl FnOnce(&mut CobsWriter<'_>) -> Result<(), LinkError>,
) -> Result<usize, LinkError> {
    *out.first_mut().ok_or(LinkError::BufferTooSmall)? = DELIMITER;
    let body = out.get_mut(1..).ok_or(LinkError::BufferTooSmall)?;
    let mut w = CobsWriter {
        cobs: cobs::CobsEncoder::new(body),
        crc: CRC32.digest(),
    };
    fill(&mut w)?;
    let CobsWriter { mut cobs, crc } = w;
    cobs.push(&crc.finalize().to_le_bytes())
        .map_err(|_| LinkError::BufferTooSmall)?;
    let end = 1 + cobs.finalize();
    *out.get_mut(end).ok_or(LinkError::BufferTooSmall)? = DELIMITER;
    Ok(end + 1)
}

/// Decodes COBS in place (the `cobs` crate's decoder); returns the decoded length.
pub(crate) fn cobs_decode_in_place(buf: &mut [u8]) -> Result<usize, LinkError> {
    if buf.is_empty() {
        return Ok(0);
    }
    cobs::decode_in_place(buf).map_err(|_| LinkError::Cobs)
}

// ---------------------------------------------------------------------------------------------
// Sender

/// Encodes `message` with sequence number `seq` as one complete frame (leading delimiter, COBS
/// of payload and CRC, trailing delimiter) at the start of `out`; returns the bytes written.
/// `out` of [`max_encoded_len`]`(message.payload_len())` bytes always suffices.
pub fn encode_frame(seq: u16, message: &Message<'_>, out: &mut [u8]) -> Result<usize, LinkError> {
    write_frame(out, |w| {
        let [s0, s1] = seq.to_le_bytes();
        w.payload(&[PROTOCOL_VERSION, message.message_type().code(), s0, s1])?;
        message.write_body(w)
    })
}

/// The sending end of the link: numbers frames and cuts depth images into chunks.
#[derive(Debug, Clone, Default)]
pub struct LinkEncoder {
    next_seq: u16,
}

impl LinkEncoder {
    /// An encoder whose first frame has sequence number 0.
    pub const fn new() -> Self {
        Self { next_seq: 0 }
    }

    /// Sequence number of the next frame.
    pub fn next_sequence(&self) -> u16 {
        self.next_seq
    }

    /// Encodes `message` as the next frame into `out` (see [`encode_frame`]).
    pub fn encode(&mut self, message: &Message<'_>, out: &mut [u8]) -> Result<usize, LinkError> {
        let n = encode_frame(self.next_seq, message, out)?;
        self.next_seq = self.next_seq.wrapping_add(1);
        Ok(n)
    }

    /// Sends one depth image as image `frame_id`: its intrinsics, then chunks of
    /// `rows_per_chunk` rows (0 counts as 1; the last chunk may be shorter), each frame handed
    /// to `emit` as soon as it is encoded in `scratch`. Returns the bytes emitted. Fails
    /// before emitting anything if `scratch` is shorter than
    /// [`max_depth_chunk_len`]`(width, rows_per_chunk)`.
    pub fn encode_depth_frame(
        &mut self,
        frame_id: u32,
        frame: &DepthFrame<'_>,
        rows_per_chunk: u16,
        scratch: &mut [u8],
        mut emit: impl FnMut(&[u8]),
    ) -> Result<usize, LinkError> {
        let intrinsics = *frame.intrinsics();
        let rows = rows_per_chunk.clamp(1, intrinsics.height());
        let needed = max_depth_chunk_len(intrinsics.width(), rows)
            .max(max_encoded_len(HEADER_LEN + INTRINSICS_BODY_LEN));
        if scratch.len() < needed {
            return Err(LinkError::BufferTooSmall);
        }
        let n = self.encode(&Message::Intrinsics(intrinsics), scratch)?;
        emit(scratch.get(..n).ok_or(LinkError::BufferTooSmall)?);
        let sent = self.encode_rows(frame_id, frame, (0, intrinsics.height()), rows, scratch, emit)?;
        Ok(n + sent)
    }

    /// Sends rows `first .. first + count` of depth image `frame_id` (clamped to the image) as
    /// chunks of `rows_per_chunk` rows, no intrinsics: the answer to the rows of a
    /// [`ResendRequest`]. Returns the bytes emitted (0 for rows past the image). Fails before
    /// emitting anything if `scratch` is shorter than
    /// [`max_depth_chunk_len`]`(width, rows_per_chunk)`.
    pub fn encode_rows(
        &mut self,
        frame_id: u32,
        frame: &DepthFrame<'_>,
        (first, count): (u16, u16),
        rows_per_chunk: u16,
        scratch: &mut [u8],
        mut emit: impl FnMut(&[u8]),
    ) -> Result<usize, LinkError> {
        let intrinsics = *frame.intrinsics();
        let (width, height) = (intrinsics.width(), intrinsics.height());
        let rows_per_chunk = rows_per_chunk.clamp(1, height);
        if scratch.len() < max_depth_chunk_len(width, rows_per_chunk) {
            return Err(LinkError::BufferTooSmall);
        }
        let end = first.saturating_add(count).min(height);
        let w = usize::from(width);
        let mut sent = 0;
        let mut first_row = first;
        while first_row < end {
            let rows = rows_per_chunk.min(end - first_row);
            let start = usize::from(first_row) * w;
            let depth = frame
                .depth_mm()
                .get(start..start + usize::from(rows) * w)
                .ok_or(LinkError::Malformed(Malformed::ChunkGeometry))?;
            let chunk = DepthChunk::new(frame_id, width, height, first_row, depth)?;
            let n = self.encode(&Message::DepthChunk(chunk), scratch)?;
            emit(scratch.get(..n).ok_or(LinkError::BufferTooSmall)?);
            sent += n;
            first_row += rows;
        }
        Ok(sent)
    }
}

/// The rows per depth chunk, from 1 to `max_rows`, that carry the most depth per byte sent
/// over a line with independent bit errors at `bit_error_rate`, when every lost chunk is sent
/// again: a chunk of `L` bytes on the wire arrives intact with probability `(1 − BER)^(8L)`,
/// so each row costs `L / (rows · (1 − BER)^(8L))` bytes. Long chunks waste less on framing
/// (12 + 4 bytes of headers, the CRC, COBS and delimiters), short ones lose less to an error.
/// For 100-pixel rows: 10 rows up to a BER of about 5e-7, 8 at 1e-6, 3 at 1e-5, 1 from about
/// 4e-5; at 1e-4 a row then costs 267 bytes against 1030 in chunks of 10.
pub fn best_rows_per_chunk(width: u16, bit_error_rate: f32, max_rows: u16) -> u16 {
    let ber = if bit_error_rate.is_finite() {
        bit_error_rate.clamp(0.0, 0.5)
    } else {
        0.5
    };
    let log_keep = libm::log1pf(-ber);
    let cost = |rows: u16| {
        let len = max_depth_chunk_len(width, rows) as f32;
        // ln(bytes per row) = ln(L / rows) − 8L·ln(1 − BER)
        libm::logf(len / f32::from(rows)) - 8.0 * len * log_keep
    };
    (1..=max_rows.max(1))
        .min_by(|&a, &b| cost(a).total_cmp(&cost(b)))
        .unwrap_or(1)
}

/// The bit error rate that explains losing `lost` of `sent` frames of `wire_bytes` bytes each
/// to independent bit errors: `1 − (1 − lost/sent)^(1/(8·wire_bytes))`. Losing every frame
/// counts as losing all but half of one (the estimate stays finite); nothing sent: 0.
pub fn estimate_bit_error_rate(sent: u32, lost: u32, wire_bytes: usize) -> f32 {
    if sent == 0 || wire_bytes == 0 {
        return 0.0;
    }
    let sent = sent as f32;
    let kept = (sent - lost.min(sent as u32) as f32).max(0.5) / sent;
    -libm::expm1f(libm::logf(kept) / (8.0 * wire_bytes as f32))
}

// ---------------------------------------------------------------------------------------------
// Receiver: framing

/// Streaming frame decoder with a fixed buffer of `N` bytes: feed it bytes in any slicing, get
/// checked messages. A frame of more than `N` encoded bytes between delimiters is dropped whole
/// ([`LinkError::Oversize`]); [`max_encoded_len`] of the largest payload is always enough.
/// Never panics, never allocates.
#[derive(Debug, Clone)]
pub struct FrameDecoder<const N: usize> {
    buf: [u8; N],
    len: usize,
    overflow: bool,
    next_seq: Option<u16>,
    counters: LinkCounters,
}

impl<const N: usize> Default for FrameDecoder<N> {
    fn default() -> Self {
        Self::new()
    }
}

impl<const N: usize> FrameDecoder<N> {
    /// An empty decoder, waiting for the first delimiter-terminated frame.
    pub const fn new() -> Self {
        Self {
            buf: [0; N],
            len: 0,
            overflow: false,
            next_seq: None,
            counters: LinkCounters::new(),
        }
    }

    /// What the decoder has seen so far (framing counters only).
    pub fn counters(&self) -> &LinkCounters {
        &self.counters
    }

    /// Takes one byte. At a delimiter that ends a non-empty frame, returns that frame's
    /// message or why it was dropped (already counted); otherwise `None`. The message borrows
    /// the decoder's buffer until the next byte.
    pub fn push(&mut self, byte: u8) -> Option<Result<Message<'_>, LinkError>> {
        self.counters.bytes = self.counters.bytes.saturating_add(1);
        if byte != DELIMITER {
            if !self.overflow {
                match self.buf.get_mut(self.len) {
                    Some(slot) => {
                        *slot = byte;
                        self.len += 1;
                    }
                    None => self.overflow = true,
                }
            }
            return None;
        }
        let len = core::mem::take(&mut self.len);
        if core::mem::take(&mut self.overflow) {
            self.counters.record(LinkError::Oversize);
            return Some(Err(LinkError::Oversize));
        }
        if len == 0 {
            return None;
        }
        let Self {
            buf,
            counters,
            next_seq,
            ..
        } = self;
        let frame = buf.get_mut(..len)?;
        let result = match cobs_decode_in_place(frame) {
            Ok(n) => {
                let frame: &[u8] = frame;
                parse_frame(frame.get(..n)?, next_seq, counters)
            }
            Err(e) => Err(e),
        };
        match result {
            Ok(_) => bump(&mut counters.frames_ok),
            Err(e) => counters.record(e),
        }
        Some(result)
    }

    /// Takes a slice of bytes, calling `on_message` for every frame that ends in it.
    pub fn feed(&mut self, bytes: &[u8], mut on_message: impl FnMut(Result<Message<'_>, LinkError>)) {
        for &byte in bytes {
            if let Some(result) = self.push(byte) {
                on_message(result);
            }
        }
    }
}

/// Checks CRC and header of a COBS-decoded frame, tracks its sequence number, decodes the body.
fn parse_frame<'b>(
    frame: &'b [u8],
    next_seq: &mut Option<u16>,
    counters: &mut LinkCounters,
) -> Result<Message<'b>, LinkError> {
    let truncated = LinkError::Malformed(Malformed::Truncated);
    let (payload, crc) = frame.split_last_chunk::<CRC_LEN>().ok_or(truncated)?;
    if crc32(payload) != u32::from_le_bytes(*crc) {
        return Err(LinkError::Crc);
    }
    let (&[version, code, s0, s1], body) = payload.split_first_chunk::<HEADER_LEN>().ok_or(truncated)?;
    if version != PROTOCOL_VERSION {
        return Err(LinkError::BadVersion(version));
    }
    let seq = u16::from_le_bytes([s0, s1]);
    if let Some(expected) = *next_seq {
        let ahead = seq.wrapping_sub(expected);
        // Ahead: frames were lost. A little behind: a duplicate or a late frame; keep waiting
        // for `expected`. Far behind: the sender restarted; follow it.
        if ahead < 0x8000 {
            counters.sequence_gaps = counters.sequence_gaps.saturating_add(u32::from(ahead));
            *next_seq = Some(seq.wrapping_add(1));
        } else if expected.wrapping_sub(seq) > 256 {
            *next_seq = Some(seq.wrapping_add(1));
        }
    } else {
        *next_seq = Some(seq.wrapping_add(1));
    }
    Message::decode(code, body)
}

// ---------------------------------------------------------------------------------------------
// Receiver: depth frame assembly

const ROW_WORDS: usize = (MAX_IMAGE_ROWS as usize) >> 5;

/// Which rows of the image in progress arrived: one bit per row.
#[derive(Debug, Clone)]
struct RowSet {
    words: [u32; ROW_WORDS],
}

impl RowSet {
    const fn new() -> Self {
        Self {
            words: [0; ROW_WORDS],
        }
    }

    fn clear(&mut self) {
        self.words.fill(0);
    }

    fn contains(&self, row: u16) -> bool {
        self.words
            .get(usize::from(row >> 5))
            .is_some_and(|w| w & (1 << (row & 31)) != 0)
    }

    /// Marks `first .. first + count`; returns how many of them were not marked before.
    fn insert(&mut self, first: u16, count: u16) -> u16 {
        let mut new = 0;
        for row in first..first.saturating_add(count) {
            if let Some(w) = self.words.get_mut(usize::from(row >> 5)) {
                let bit = 1 << (row & 31);
                new += u16::from(*w & bit == 0);
                *w |= bit;
            }
        }
        new
    }

    /// The runs of rows below `height` not marked, `(first, count)`, in order.
    fn missing(&self, height: u16) -> impl Iterator<Item = (u16, u16)> + '_ {
        let mut row = 0u16;
        core::iter::from_fn(move || {
            while row < height && self.contains(row) {
                row += 1;
            }
            if row >= height {
                return None;
            }
            let first = row;
            while row < height && !self.contains(row) {
                row += 1;
            }
            Some((first, row - first))
        })
    }
}

#[derive(Debug, Clone, Copy)]
enum Phase {
    /// `received` distinct rows are in the buffer (the others hold [`NOT_RECEIVED`]).
    Receiving { width: u16, height: u16, received: u16 },
    /// Delivered (whole or partially) with these intrinsics.
    Complete(Intrinsics),
    /// Given up; its remaining chunks are ignored.
    Dropped,
}

#[derive(Debug, Clone, Copy)]
struct Tracked {
    frame_id: u32,
    phase: Phase,
}

/// A depth frame as the assembler delivers it.
#[derive(Debug, Clone, Copy)]
pub struct Assembled<'f> {
    /// Image id from the chunks.
    pub frame_id: u32,
    /// The image and its intrinsics; rows that never arrived hold [`NOT_RECEIVED`].
    pub frame: DepthFrame<'f>,
    /// Rows that never arrived (0: the frame is whole).
    pub missing_rows: u16,
}

/// Assembles depth chunks into depth frames in a caller-provided buffer, one frame id at a
/// time. Chunks of the frame in progress may come in any order; the frame is delivered when
/// every row arrived, or — with the rows that did, the others [`NOT_RECEIVED`] — when the caller
/// finishes it ([`DepthAssembler::finish`]: its deadline passed, or a newer frame is about to
/// start). Each row of an image is independently useful to the integrator. What cannot be used
/// is dropped and counted:
///
/// - a chunk whose rows all arrived already (duplicate, a resend that crossed the first copy)
///   or of a slightly older frame: dropped, [`LinkCounters::out_of_order_chunks`]; the frame in
///   progress continues;
/// - a new frame id while a frame is incomplete and was not finished first: that frame is
///   dropped, [`LinkCounters::missing_chunks`];
/// - an image larger than the buffer, or with more than [`MAX_IMAGE_ROWS`] rows:
///   [`LinkCounters::frame_too_large`];
/// - delivery without intrinsics, or with intrinsics of another size:
///   [`LinkCounters::no_intrinsics`], [`LinkCounters::intrinsics_mismatch`].
#[derive(Debug)]
pub struct DepthAssembler<'a> {
    buf: &'a mut [u16],
    rows: RowSet,
    intrinsics: Option<Intrinsics>,
    tracked: Option<Tracked>,
    counters: LinkCounters,
}

impl<'a> DepthAssembler<'a> {
    /// An assembler for images of up to `buf.len()` pixels.
    pub const fn new(buf: &'a mut [u16]) -> Self {
        Self {
            buf,
            rows: RowSet::new(),
            intrinsics: None,
            tracked: None,
            counters: LinkCounters::new(),
        }
    }

    /// Intrinsics for the frames that complete from now on (the last received).
    pub fn set_intrinsics(&mut self, intrinsics: Intrinsics) {
        self.intrinsics = Some(intrinsics);
    }

    /// The last intrinsics set.
    pub fn intrinsics(&self) -> Option<&Intrinsics> {
        self.intrinsics.as_ref()
    }

    /// What the assembler has seen so far (assembly counters only).
    pub fn counters(&self) -> &LinkCounters {
        &self.counters
    }

    /// Id of the frame being received, if one is incomplete.
    pub fn frame_in_progress(&self) -> Option<u32> {
        match self.tracked {
            Some(Tracked {
                frame_id,
                phase: Phase::Receiving { .. },
            }) => Some(frame_id),
            _ => None,
        }
    }

    /// Id of the newest frame any chunk arrived for, whatever became of it.
    pub fn newest_frame(&self) -> Option<u32> {
        self.tracked.map(|t| t.frame_id)
    }

    /// The runs of rows, `(first, count)`, still missing from the frame in progress (none if no
    /// frame is in progress).
    pub fn missing_rows(&self) -> impl Iterator<Item = (u16, u16)> + '_ {
        let height = match self.tracked {
            Some(Tracked {
                phase: Phase::Receiving { height, .. },
                ..
            }) => height,
            _ => 0,
        };
        self.rows.missing(height)
    }

    /// The last frame delivered, while no later chunk has started overwriting it.
    pub fn completed_frame(&self) -> Option<DepthFrame<'_>> {
        let Some(Tracked {
            phase: Phase::Complete(intrinsics),
            ..
        }) = self.tracked
        else {
            return None;
        };
        let depth = self.buf.get(..intrinsics.pixel_count())?;
        DepthFrame::new(intrinsics, depth).ok()
    }

    /// Whether `chunk` would start a new frame while one is in progress (the caller may
    /// [`finish`](Self::finish) that one first, or it is dropped).
    pub fn displaces(&self, chunk: &DepthChunk<'_>) -> bool {
        self.tracked.is_some_and(|t| {
            matches!(t.phase, Phase::Receiving { .. })
                && t.frame_id != chunk.frame_id()
                && t.frame_id.wrapping_sub(chunk.frame_id()) > STALE_FRAME_WINDOW
        })
    }

    /// Takes one chunk. Returns the frame it completes (every row arrived), if any. An error
    /// says what happened to this chunk; the counters are the full record (a chunk that starts
    /// a new frame is accepted, yet an incomplete frame it displaces is counted as missing
    /// chunks).
    pub fn push_chunk(&mut self, chunk: &DepthChunk<'_>) -> Result<Option<Assembled<'_>>, LinkError> {
        if !self.accept(chunk)? {
            return Ok(None);
        }
        self.deliver()
    }

    /// Ends the frame in progress: delivers the rows that arrived (the others hold
    /// [`NOT_RECEIVED`]), counted in [`LinkCounters::depth_frames_partial`] and
    /// [`LinkCounters::missing_chunks`]. `Ok(None)` if no frame is in progress; later chunks
    /// of the frame are dropped as late.
    pub fn finish(&mut self) -> Result<Option<Assembled<'_>>, LinkError> {
        if self.frame_in_progress().is_none() {
            return Ok(None);
        }
        self.deliver()
    }

    /// Delivers the frame in progress, whole or not.
    fn deliver(&mut self) -> Result<Option<Assembled<'_>>, LinkError> {
        let Some(Tracked {
            frame_id,
            phase:
                Phase::Receiving {
                    width,
                    height,
                    received,
                },
        }) = self.tracked
        else {
            return Ok(None);
        };
        let intrinsics = match self.intrinsics {
            None => return Err(self.drop_frame(frame_id, LinkError::NoIntrinsics)),
            Some(i) if i.width() != width || i.height() != height => {
                return Err(self.drop_frame(frame_id, LinkError::IntrinsicsMismatch));
            }
            Some(i) => i,
        };
        let missing = height.saturating_sub(received);
        if missing == 0 {
            bump(&mut self.counters.depth_frames_complete);
        } else {
            self.counters.record(LinkError::MissingChunks);
            bump(&mut self.counters.depth_frames_partial);
            self.counters.rows_missing = self.counters.rows_missing.saturating_add(u32::from(missing));
        }
        self.tracked = Some(Tracked {
            frame_id,
            phase: Phase::Complete(intrinsics),
        });
        Ok(self.completed_frame().map(|frame| Assembled {
            frame_id,
            frame,
            missing_rows: missing,
        }))
    }

    /// Routes a chunk; returns whether it completed its frame.
    fn accept(&mut self, chunk: &DepthChunk<'_>) -> Result<bool, LinkError> {
        let id = chunk.frame_id();
        if let Some(tracked) = self.tracked {
            if tracked.frame_id == id {
                return match tracked.phase {
                    Phase::Receiving { width, height, .. } => {
                        if chunk.width() != width || chunk.height() != height {
                            return Err(self.drop_frame(id, LinkError::ChunkMismatch));
                        }
                        self.store(chunk)
                    }
                    Phase::Complete(_) => Err(self.count(LinkError::OutOfOrderChunk)),
                    Phase::Dropped => Ok(false),
                };
            }
            if tracked.frame_id.wrapping_sub(id) <= STALE_FRAME_WINDOW {
                return Err(self.count(LinkError::OutOfOrderChunk));
            }
            if let Phase::Receiving { .. } = tracked.phase {
                self.drop_frame(tracked.frame_id, LinkError::MissingChunks);
            }
        }
        self.start_frame(chunk)
    }

    fn start_frame(&mut self, chunk: &DepthChunk<'_>) -> Result<bool, LinkError> {
        let id = chunk.frame_id();
        let pixels = usize::from(chunk.width()).checked_mul(usize::from(chunk.height()));
        let Some(image) = pixels.and_then(|p| self.buf.get_mut(..p)) else {
            return Err(self.drop_frame(id, LinkError::FrameTooLarge));
        };
        if chunk.height() > MAX_IMAGE_ROWS {
            return Err(self.drop_frame(id, LinkError::FrameTooLarge));
        }
        image.fill(NOT_RECEIVED);
        self.rows.clear();
        self.tracked = Some(Tracked {
            frame_id: id,
            phase: Phase::Receiving {
                width: chunk.width(),
                height: chunk.height(),
                received: 0,
            },
        });
        self.store(chunk)
    }

    /// Copies a chunk of the frame in progress; returns whether the frame is now whole.
    fn store(&mut self, chunk: &DepthChunk<'_>) -> Result<bool, LinkError> {
        let Some(Tracked {
            frame_id,
            phase:
                Phase::Receiving {
                    width,
                    height,
                    received,
                },
        }) = self.tracked
        else {
            return Ok(false);
        };
        let start = usize::from(chunk.first_row()) * usize::from(width);
        let end = start.checked_add(chunk.sample_count());
        let Some(target) = end.and_then(|end| self.buf.get_mut(start..end)) else {
            return Err(self.drop_frame(frame_id, LinkError::FrameTooLarge));
        };
        let new = self.rows.insert(chunk.first_row(), chunk.row_count());
        if new == 0 {
            return Err(self.count(LinkError::OutOfOrderChunk));
        }
        target
            .iter_mut()
            .zip(chunk.samples())
            .for_each(|(dst, v)| *dst = v);
        let received = received.saturating_add(new);
        self.tracked = Some(Tracked {
            frame_id,
            phase: Phase::Receiving {
                width,
                height,
                received,
            },
        });
        Ok(received >= height)
    }

    fn count(&mut self, error: LinkError) -> LinkError {
        self.counters.record(error);
        error
    }

    fn drop_frame(&mut self, frame_id: u32, why: LinkError) -> LinkError {
        self.counters.record(why);
        bump(&mut self.counters.depth_frames_dropped);
        self.tracked = Some(Tracked {
            frame_id,
            phase: Phase::Dropped,
        });
        why
    }
}

// ---------------------------------------------------------------------------------------------
// Receiver: both together

/// What the receiving end of the link reports.
#[derive(Debug, Clone, Copy)]
pub enum LinkEvent<'f> {
    /// A depth frame, whole or partial, with the pose received for it if the camera side
    /// sends poses.
    Depth {
        /// Image id from the chunks.
        frame_id: u32,
        /// The image and its intrinsics; rows that never arrived hold [`NOT_RECEIVED`].
        frame: DepthFrame<'f>,
        /// The last Pose message, if it carried this frame id.
        pose: Option<Pose>,
        /// Rows that never arrived (0: the frame is whole).
        missing_rows: u16,
    },
    /// New intrinsics (also applied to the frames that follow).
    Intrinsics(Intrinsics),
    /// A camera pose (also kept for the depth frame of the same id).
    Pose(Pose),
    /// Camera-side liveness.
    Heartbeat(Heartbeat),
    /// A resend request (it travels the other way; a camera side that decodes its return
    /// channel with a receiver sees it here).
    ResendRequest(ResendRequest),
    /// The grid the mission maps (the camera side repeats it until the core answers).
    Geometry(MapGeometry),
    /// A frame or chunk was dropped (already counted).
    Error(LinkError),
}

/// The receiving end of the depth link: a [`FrameDecoder`] of `N` bytes and a
/// [`DepthAssembler`] over a caller buffer. A frame in progress is delivered when it is whole,
/// when a chunk of a newer frame arrives, or when the caller finishes it
/// ([`DepthReceiver::finish_frame`]) — with the rows that arrived. Before finishing, a caller
/// with a return channel may ask for what is missing ([`DepthReceiver::resend_request`]).
#[derive(Debug)]
pub struct DepthReceiver<'a, const N: usize> {
    decoder: FrameDecoder<N>,
    assembler: DepthAssembler<'a>,
    pose: Option<Pose>,
}

impl<'a, const N: usize> DepthReceiver<'a, N> {
    /// A receiver for images of up to `depth_buffer.len()` pixels.
    pub const fn new(depth_buffer: &'a mut [u16]) -> Self {
        Self {
            decoder: FrameDecoder::new(),
            assembler: DepthAssembler::new(depth_buffer),
            pose: None,
        }
    }

    /// Takes bytes in any slicing, calling `on_event` for everything they complete.
    pub fn feed(&mut self, bytes: &[u8], mut on_event: impl FnMut(LinkEvent<'_>)) {
        for &byte in bytes {
            let Some(result) = self.decoder.push(byte) else {
                continue;
            };
            match result {
                Err(e) => on_event(LinkEvent::Error(e)),
                Ok(Message::Intrinsics(i)) => {
                    self.assembler.set_intrinsics(i);
                    on_event(LinkEvent::Intrinsics(i));
                }
                Ok(Message::Pose(p)) => {
                    self.pose = Some(p);
                    on_event(LinkEvent::Pose(p));
                }
                Ok(Message::Heartbeat(h)) => on_event(LinkEvent::Heartbeat(h)),
                Ok(Message::ResendRequest(r)) => on_event(LinkEvent::ResendRequest(r)),
                Ok(Message::Geometry(g)) => on_event(LinkEvent::Geometry(g)),
                Ok(Message::DepthChunk(chunk)) => {
                    if self.assembler.displaces(&chunk) {
                        Self::emit(self.pose, self.assembler.finish(), &mut on_event);
                    }
                    Self::emit(self.pose, self.assembler.push_chunk(&chunk), &mut on_event);
                }
            }
        }
    }

    /// The frame in progress has had its time (its deadline passed, or the caller asked for
    /// what is missing as often as it will): delivers the rows that arrived, if any.
    pub fn finish_frame(&mut self, mut on_event: impl FnMut(LinkEvent<'_>)) {
        Self::emit(self.pose, self.assembler.finish(), &mut on_event);
    }

    fn emit(
        pose: Option<Pose>,
        result: Result<Option<Assembled<'_>>, LinkError>,
        on_event: &mut impl FnMut(LinkEvent<'_>),
    ) {
        match result {
            Ok(Some(a)) => on_event(LinkEvent::Depth {
                frame_id: a.frame_id,
                frame: a.frame,
                pose: pose.filter(|p| p.frame_id() == a.frame_id),
                missing_rows: a.missing_rows,
            }),
            Ok(None) => {}
            Err(e) => on_event(LinkEvent::Error(e)),
        }
    }

    /// What to ask the camera side to send again for image `frame_id`: the rows still missing
    /// if it is the frame in progress, every row if no chunk of it arrived yet (and no newer
    /// frame did), its pose if `want_pose` and none arrived for it, the intrinsics if none ever
    /// did. `None` if nothing is missing.
    pub fn resend_request(&self, frame_id: u32, want_pose: bool) -> Option<ResendRequest> {
        let mut request = ResendRequest::new(frame_id);
        match self.assembler.newest_frame() {
            Some(id) if id == frame_id => {
                for (first, count) in self.assembler.missing_rows() {
                    if !request.push_rows(first, count) {
                        break;
                    }
                }
            }
            Some(id) if id.wrapping_sub(frame_id) <= STALE_FRAME_WINDOW => {}
            _ => {
                request.push_rows(0, u16::MAX);
            }
        }
        if want_pose && self.pose.is_none_or(|p| p.frame_id() != frame_id) {
            request = request.with_pose();
        }
        if self.assembler.intrinsics().is_none() {
            request = request.with_intrinsics();
        }
        (!request.is_empty()).then_some(request)
    }

    /// The last frame delivered, while no later chunk has started overwriting it.
    pub fn completed_frame(&self) -> Option<DepthFrame<'_>> {
        self.assembler.completed_frame()
    }

    /// Id of the frame being received, if one is incomplete.
    pub fn frame_in_progress(&self) -> Option<u32> {
        self.assembler.frame_in_progress()
    }

    /// Framing and assembly counters together.
    pub fn counters(&self) -> LinkCounters {
        self.decoder.counters().merged(self.assembler.counters())
    }
}

#[cfg(test)]
mod tests {
    extern crate std;

    use super::*;
    use std::vec;
    use std::vec::Vec;

    /// Deterministic pseudo-random numbers (Knuth's MMIX LCG, high bits).
    struct Lcg(u64);

    impl Lcg {
        fn next_u32(&mut self) -> u32 {
            self.0 = self
                .0
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (self.0 >> 32) as u32
        }
        fn below(&mut self, n: usize) -> usize {
            ((u64::from(self.next_u32()) * n as u64) >> 32) as usize
        }
        fn byte(&mut self) -> u8 {
            self.next_u32() as u8
        }
    }

    const BIG: usize = max_depth_chunk_len(100, 10);

    fn intrinsics(w: u16, h: u16) -> Intrinsics {
        Intrinsics::from_hfov(w, h, 1.2).unwrap()
    }

    /// A plausible depth image: a slanted wall 0.5–6 m with noise, 5 % no-return pixels.
    fn depth_image(w: u16, h: u16, seed: u64) -> Vec<u16> {
        let mut rng = Lcg(seed);
        (0..usize::from(w) * usize::from(h))
            .map(|i| {
                if rng.below(20) == 0 {
                    0
                } else {
                    (500 + (i % usize::from(w)) * 50 + rng.below(40)) as u16
                }
            })
            .collect()
    }

    /// The wire frames (each with both delimiters) of one image: intrinsics, then chunks.
    fn image_frames(enc: &mut LinkEncoder, id: u32, w: u16, h: u16, rpc: u16) -> (Vec<u16>, Vec<Vec<u8>>) {
        let depth = depth_image(w, h, u64::from(id) + 1);
        let frame = DepthFrame::new(intrinsics(w, h), &depth).unwrap();
        let mut scratch = vec![0u8; max_depth_chunk_len(w, rpc)];
        let mut frames = Vec::new();
        let sent = enc
            .encode_depth_frame(id, &frame, rpc, &mut scratch, |f| frames.push(f.to_vec()))
            .unwrap();
        assert_eq!(sent, frames.iter().map(Vec::len).sum::<usize>());
        (depth, frames)
    }

    struct Received {
        /// Whole images.
        images: Vec<(u32, Vec<u16>, Option<Pose>)>,
        /// Partial images: id, depth, rows missing.
        partial: Vec<(u32, Vec<u16>, u16)>,
        errors: Vec<LinkError>,
        counters: LinkCounters,
    }

    /// Feeds `stream` in slices of the given lengths (cycled), into a receiver of `N` bytes.
    fn receive_sliced<const N: usize>(
        stream: &[u8],
        pixels: usize,
        slices: &mut dyn FnMut() -> usize,
    ) -> Received {
        let mut buf = vec![0u16; pixels];
        let mut rx = DepthReceiver::<N>::new(&mut buf);
        let (mut images, mut errors, mut partial) = (Vec::new(), Vec::new(), Vec::new());
        let mut rest = stream;
        while !rest.is_empty() {
            let (now, later) = rest.split_at(slices().min(rest.len()));
            rx.feed(now, |event| match event {
                LinkEvent::Depth {
                    frame_id,
                    frame,
                    pose,
                    missing_rows,
                } => {
                    assert_eq!(frame.depth_mm().len(), frame.intrinsics().pixel_count());
                    if missing_rows == 0 {
                        images.push((frame_id, frame.depth_mm().to_vec(), pose));
                    } else {
                        partial.push((frame_id, frame.depth_mm().to_vec(), missing_rows));
                    }
                }
                LinkEvent::Error(e) => errors.push(e),
                _ => {}
            });
            rest = later;
        }
        // The caller's deadline for the last frame.
        rx.finish_frame(|event| {
            if let LinkEvent::Depth {
                frame_id,
                frame,
                missing_rows,
                ..
            } = event
            {
                partial.push((frame_id, frame.depth_mm().to_vec(), missing_rows));
            }
        });
        Received {
            images,
            partial,
            errors,
            counters: rx.counters(),
        }
    }

    fn receive(stream: &[u8]) -> Received {
        receive_sliced::<BIG>(stream, 100 * 100, &mut || 1)
    }

    fn decode_one<const N: usize>(wire: &[u8]) -> Vec<Result<Message<'static>, LinkError>> {
        // Messages borrow the decoder; chunk samples are copied (and leaked, test only) to outlive it.
        let mut out = Vec::new();
        let mut dec = FrameDecoder::<N>::new();
        for &b in wire {
            if let Some(r) = dec.push(b) {
                out.push(r.map(|m| match m {
                    Message::DepthChunk(c) => {
                        let samples: Vec<u16> = c.samples().collect();
                        let samples: &'static [u16] = std::boxed::Box::leak(samples.into_boxed_slice());
                        Message::DepthChunk(
                            DepthChunk::new(c.frame_id, c.width, c.height, c.first_row, samples).unwrap(),
                        )
                    }
                    Message::Intrinsics(i) => Message::Intrinsics(i),
                    Message::Pose(p) => Message::Pose(p),
                    Message::Heartbeat(h) => Message::Heartbeat(h),
                    Message::ResendRequest(r) => Message::ResendRequest(r),
                    Message::Geometry(g) => Message::Geometry(g),
                }));
            }
        }
        out
    }

    /// COBS-encodes raw bytes (no CRC added) between two delimiters.
    fn cobs_frame(raw: &[u8]) -> Vec<u8> {
        let mut out = vec![0u8; max_encoded_len(raw.len())];
        let n = if raw.is_empty() {
            out[1] = 1;
            1
        } else {
            cobs::encode(raw, &mut out[1..])
        };
        out[n + 1] = 0;
        out.truncate(n + 2);
        out
    }

    /// A frame around an arbitrary payload, with a correct CRC.
    fn raw_frame(payload: &[u8]) -> Vec<u8> {
        let mut raw = payload.to_vec();
        raw.extend_from_slice(&crc32(payload).to_le_bytes());
        cobs_frame(&raw)
    }

    /// Undoes the framing of one wire frame: payload and CRC.
    fn unframe(frame: &[u8]) -> Vec<u8> {
        let mut inner = frame.iter().copied().filter(|&b| b != 0).collect::<Vec<_>>();
        let n = cobs_decode_in_place(&mut inner).unwrap();
        inner.truncate(n);
        inner
    }

    fn heartbeat_frame(seq: u16) -> Vec<u8> {
        let mut out = [0u8; 64];
        let n = encode_frame(seq, &Message::Heartbeat(Heartbeat::default()), &mut out).unwrap();
        out[..n].to_vec()
    }

    fn errors_total(c: &LinkCounters) -> u32 {
        c.crc_errors
            + c.cobs_errors
            + c.oversize
            + c.bad_version
            + c.unknown_type
            + c.malformed
            + c.out_of_order_chunks
            + c.missing_chunks
            + c.frame_too_large
            + c.no_intrinsics
            + c.intrinsics_mismatch
    }

    // Firmware keeps the receiving end in `static`s: the constructors are `const`.
    const _: FrameDecoder<64> = FrameDecoder::new();
    const _: LinkEncoder = LinkEncoder::new();

    #[test]
    fn crc32_matches_the_catalogue_check_value() {
        assert_eq!(crc32(b"123456789"), 0xCBF4_3926);
        assert_eq!(crc32(b""), 0);
    }

    #[test]
    fn cobs_round_trips_block_boundaries_and_zero_runs() {
        let mut rng = Lcg(3);
        let mut cases: Vec<Vec<u8>> = vec![vec![], vec![0], vec![0, 0], vec![1], vec![0, 1, 0]];
        for n in [253, 254, 255, 256, 507, 508, 509, 1000] {
            cases.push(vec![0x55; n]);
            cases.push((0..n).map(|i| if i % 300 == 299 { 0 } else { 7 }).collect());
            cases.push(
                (0..n)
                    .map(|_| if rng.below(4) == 0 { 0 } else { rng.byte() })
                    .collect(),
            );
        }
        for data in cases {
            let framed = cobs_frame(&data);
            let inner = &framed[1..framed.len() - 1];
            assert!(!inner.contains(&0), "delimiter inside frame");
            assert!(framed.len() <= max_encoded_len(data.len()) - CRC_LEN);
            let mut buf = inner.to_vec();
            let n = cobs_decode_in_place(&mut buf).unwrap();
            assert_eq!(&buf[..n], &data[..]);
        }
        // A code byte promising more bytes than there are.
        assert_eq!(cobs_decode_in_place(&mut [5, 1, 2]), Err(LinkError::Cobs));
    }

    #[test]
    fn heartbeat_test_vector_in_the_module_doc() {
        let hb = Heartbeat {
            uptime_ms: 1000,
            frames_sent: 7,
            frames_skipped: 2,
            sensor_errors: 0,
        };
        let mut out = [0u8; 64];
        let n = encode_frame(1, &Message::Heartbeat(hb), &mut out).unwrap();
        let hex: Vec<std::string::String> = out[..n].iter().map(|b| std::format!("{b:02X}")).collect();
        std::println!("heartbeat frame: {}", hex.join(" "));
        assert_eq!(
            &out[..n],
            &[
                0x00, 0x04, 0x01, 0x04, 0x01, 0x03, 0xE8, 0x03, 0x01, 0x02, 0x07, 0x01, 0x01, 0x02, 0x02,
                0x01, 0x01, 0x01, 0x01, 0x01, 0x01, 0x05, 0x7F, 0x60, 0xE7, 0x5D, 0x00
            ]
        );
    }

    #[test]
    fn every_message_round_trips() {
        let rows = depth_image(7, 3, 9);
        let messages = [
            Message::Intrinsics(Intrinsics::new(120.5, 121.0, 49.5, 39.25, 100, 80).unwrap()),
            Message::DepthChunk(DepthChunk::new(0xDEAD_BEEF, 7, 10, 4, &rows).unwrap()),
            Message::DepthChunk(DepthChunk::new(1, 7, 3, 0, &[0u16; 21]).unwrap()),
            Message::Pose(Pose::new(42, [1.5, -2.0, 0.75], [0.0, 0.0, 0.6, 0.8]).unwrap()),
            Message::Heartbeat(Heartbeat {
                uptime_ms: u32::MAX,
                frames_sent: 3,
                frames_skipped: 0,
                sensor_errors: 1,
            }),
            Message::Geometry(
                MapGeometry::new(Dims::new(120, 80, 25).unwrap(), [-0.05, 2.0, 0.0].into(), 0.1).unwrap(),
            ),
        ];
        for (seq, message) in messages.iter().enumerate() {
            let seq = 65_534u16.wrapping_add(seq as u16);
            let mut out = [0u8; 256];
            let n = encode_frame(seq, message, &mut out).unwrap();
            assert!(n <= max_encoded_len(message.payload_len()));
            assert_eq!(unframe(&out[..n]).len(), message.payload_len() + CRC_LEN);
            // One byte short of the encoded length fails cleanly.
            assert_eq!(
                encode_frame(seq, message, &mut out[..n - 1]),
                Err(LinkError::BufferTooSmall)
            );
            let decoded = decode_one::<256>(&out[..n]);
            assert_eq!(decoded.len(), 1);
            assert_eq!(decoded[0].as_ref().unwrap(), message);
        }
    }

    #[test]
    fn a_geometry_the_map_refuses_is_malformed_and_counted() {
        let body = |n: [u32; 3], resolution: f32| {
            let mut p = vec![1, MessageType::Geometry.code(), 0, 0];
            n.iter().for_each(|v| p.extend_from_slice(&v.to_le_bytes()));
            [0.0f32, 0.0, 0.0, resolution]
                .iter()
                .for_each(|v| p.extend_from_slice(&v.to_le_bytes()));
            p
        };
        let bad = LinkError::Malformed(Malformed::Geometry);
        for payload in [
            body([0, 10, 10], 0.1),
            body([10, 10, 10], 0.0),
            body([10, 10, 10], f32::NAN),
        ] {
            let frame = raw_frame(&payload);
            let decoded = decode_one::<64>(&frame);
            assert_eq!(decoded, [Err(bad)]);
        }
        let good = decode_one::<64>(&raw_frame(&body([10, 20, 30], 0.2)));
        match good.as_slice() {
            [Ok(Message::Geometry(g))] => assert_eq!(g.dims().len(), 6000),
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn pose_is_validated_and_converts_to_an_isometry() {
        assert_eq!(
            Pose::new(0, [f32::NAN, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]),
            Err(PoseError::NotFinite)
        );
        assert_eq!(
            Pose::new(0, [0.0; 3], [0.0, 0.0, 0.0, f32::INFINITY]),
            Err(PoseError::NotFinite)
        );
        assert_eq!(
            Pose::new(0, [0.0; 3], [0.0, 0.0, 0.0, 1.01]),
            Err(PoseError::NotUnitQuaternion)
        );
        assert_eq!(
            Pose::new(0, [0.0; 3], [0.0; 4]),
            Err(PoseError::NotUnitQuaternion)
        );
        assert!(Pose::new(0, [0.0; 3], [0.0, 0.0, 0.0, 1.0009]).is_ok());
        let iso = crate::planning::explore::forward_camera_pose(&nalgebra::Point3::new(1.0, 2.0, 0.5), 0.7);
        let pose = Pose::from_isometry(5, &iso).unwrap();
        let back = pose.isometry();
        assert!((back.translation.vector - iso.translation.vector).norm() < 1e-6);
        assert!(back.rotation.angle_to(&iso.rotation) < 1e-5);
    }

    #[test]
    fn depth_frame_reassembles_in_any_slicing() {
        let mut enc = LinkEncoder::new();
        let pose = Pose::new(7, [1.0, 2.0, 3.0], [0.0, 0.0, 0.0, 1.0]).unwrap();
        let mut stream = Vec::new();
        let mut out = [0u8; 64];
        let n = enc.encode(&Message::Pose(pose), &mut out).unwrap();
        stream.extend_from_slice(&out[..n]);
        let (depth, frames) = image_frames(&mut enc, 7, 100, 100, 10);
        assert_eq!(frames.len(), 11);
        frames.iter().for_each(|f| stream.extend_from_slice(f));

        let byte_by_byte = receive(&stream);
        assert_eq!(byte_by_byte.images, vec![(7, depth.clone(), Some(pose))]);
        assert!(byte_by_byte.errors.is_empty());
        let c = byte_by_byte.counters;
        assert_eq!(
            (c.frames_ok, c.depth_frames_complete, errors_total(&c)),
            (12, 1, 0)
        );
        assert_eq!(c.bytes, stream.len() as u64);

        let whole = receive_sliced::<BIG>(&stream, 100 * 100, &mut || usize::MAX);
        assert_eq!(whole.images, byte_by_byte.images);
        for seed in 0..50 {
            let mut rng = Lcg(seed);
            let max = [2, 17, 300, 5000][seed as usize % 4];
            let got = receive_sliced::<BIG>(&stream, 100 * 100, &mut || rng.below(max));
            assert_eq!(got.images, byte_by_byte.images, "seed {seed}");
            assert_eq!(got.counters, byte_by_byte.counters, "seed {seed}");
        }
    }

    #[test]
    fn bandwidth_of_a_100_by_100_frame() {
        const BYTES_PER_S: f64 = 92_160.0;
        for rpc in [1u16, 5, 10, 20, 50, 100] {
            let mut enc = LinkEncoder::new();
            let (_, frames) = image_frames(&mut enc, 1, 100, 100, rpc);
            let bytes: usize = frames.iter().map(Vec::len).sum();
            let bound = max_encoded_len(HEADER_LEN + INTRINSICS_BODY_LEN)
                + usize::from(100 / rpc) * max_depth_chunk_len(100, rpc);
            assert!(bytes <= bound);
            std::println!(
                "100x100 frame, {rpc:3} rows/chunk: {bytes} bytes on the wire (bound {bound}, raw 20000, \
                 +{:.2} %), {:.3} s at 921600 baud 8N1; decoder buffer {} B",
                (bytes as f64 / 20_000.0 - 1.0) * 100.0,
                bytes as f64 / BYTES_PER_S,
                max_depth_chunk_len(100, rpc),
            );
            if rpc == 10 {
                assert_eq!(bound, 31 + 10 * 2030);
            }
        }
    }

    /// Five 20×20 images in chunks of 5 rows: per image one Intrinsics frame and 4 chunks.
    fn five_images() -> (Vec<Vec<u16>>, Vec<Vec<Vec<u8>>>) {
        let mut enc = LinkEncoder::new();
        (0..5).map(|id| image_frames(&mut enc, id, 20, 20, 5)).unzip()
    }

    fn ids(r: &Received) -> Vec<u32> {
        r.images.iter().map(|(id, _, _)| *id).collect()
    }

    fn partial_ids(r: &Received) -> Vec<u32> {
        r.partial.iter().map(|(id, _, _)| *id).collect()
    }

    /// Whole images equal their originals; in partial ones every row is its original's or
    /// wholly [`NOT_RECEIVED`], and as many rows are as said missing.
    fn assert_images_intact(r: &Received, originals: &[Vec<u16>]) {
        for (id, depth, _) in &r.images {
            assert_eq!(depth, &originals[*id as usize], "image {id} delivered damaged");
        }
        for (id, depth, missing) in &r.partial {
            let original = &originals[*id as usize];
            let width = original.len() / 20;
            let mut lost = 0;
            for (row, want) in depth.chunks(width).zip(original.chunks(width)) {
                if row.iter().all(|&d| d == NOT_RECEIVED) {
                    lost += 1;
                } else {
                    assert_eq!(row, want, "image {id} delivered a damaged row");
                }
            }
            assert_eq!(lost, *missing, "image {id}");
        }
    }

    #[test]
    fn a_crc_error_loses_only_its_image() {
        let (originals, mut images) = five_images();
        let mut raw = unframe(&images[2][2]);
        raw[40] ^= 0x10;
        images[2][2] = cobs_frame(&raw);
        let r = receive(&images.concat().concat());
        assert_eq!(ids(&r), [0, 1, 3, 4]);
        // The rows that arrived are still of use: image 2 comes without the damaged chunk's.
        assert_eq!(partial_ids(&r), [2]);
        assert_eq!(r.partial[0].2, 5);
        assert_images_intact(&r, &originals);
        let c = r.counters;
        assert_eq!(
            (c.crc_errors, c.missing_chunks, c.depth_frames_dropped),
            (1, 1, 0)
        );
        assert_eq!(
            (c.sequence_gaps, errors_total(&c), c.depth_frames_complete),
            (1, 2, 4)
        );
        assert_eq!((c.depth_frames_partial, c.rows_missing), (1, 5));
    }

    #[test]
    fn dropped_bytes_and_truncated_frames_lose_only_their_image() {
        let (originals, images) = five_images();
        type Damage = fn(&mut Vec<u8>);
        let damages: [(&str, Damage); 4] = [
            ("dropped byte", |f| {
                f.remove(f.len() / 2);
            }),
            ("truncated, delimiter kept", |f| {
                let n = f.len() / 2;
                f[n] = 0;
                f.truncate(n + 1);
            }),
            ("truncated, tail and delimiter lost", |f| f.truncate(f.len() / 2)),
            ("leading delimiter lost", |f| {
                f.remove(0);
            }),
        ];
        for (name, damage) in damages {
            for (image, chunk) in [(2, 1), (2, 4), (0, 1), (4, 2)] {
                let mut damaged = images.clone();
                damage(&mut damaged[image][chunk]);
                let r = receive(&damaged.concat().concat());
                assert_images_intact(&r, &originals);
                let c = r.counters;
                if name == "leading delimiter lost" {
                    // The trailing delimiter of the previous frame still separates them.
                    assert_eq!(ids(&r), [0, 1, 2, 3, 4], "{name}");
                    assert_eq!(errors_total(&c), 0);
                    continue;
                }
                let expect: Vec<u32> = (0..5).filter(|&i| i != image as u32).collect();
                assert_eq!(ids(&r), expect, "{name}, image {image} chunk {chunk}");
                assert_eq!(
                    partial_ids(&r),
                    [image as u32],
                    "{name}, image {image} chunk {chunk}"
                );
                assert_eq!(c.crc_errors + c.cobs_errors + c.malformed, 1, "{name}: {c:?}");
                assert_eq!(
                    (c.missing_chunks, c.depth_frames_partial, c.depth_frames_dropped),
                    (1, 1, 0),
                    "{name}: {c:?}"
                );
            }
        }
    }

    #[test]
    fn garbage_between_frames_is_counted_and_skipped() {
        let (originals, images) = five_images();
        let mut rng = Lcg(11);
        let mut stream = Vec::new();
        let mut garbage_runs = 0;
        for image in &images {
            for frame in image {
                // Non-zero garbage: exactly one bad frame per run thanks to the leading delimiter.
                let n = 1 + rng.below(200);
                stream.extend((0..n).map(|_| rng.byte() | 1));
                garbage_runs += 1;
                stream.extend_from_slice(frame);
            }
        }
        let r = receive(&stream);
        assert_eq!(ids(&r), [0, 1, 2, 3, 4]);
        assert_images_intact(&r, &originals);
        let c = r.counters;
        assert_eq!(c.crc_errors + c.cobs_errors + c.malformed, garbage_runs);
        assert_eq!(
            (c.missing_chunks, c.depth_frames_dropped, c.sequence_gaps),
            (0, 0, 0)
        );

        // A receiver that starts listening in the middle of a frame loses only that image.
        let stream = images.concat().concat();
        let start = images[0][0].len() + images[0][1].len() / 2;
        let r = receive(&stream[start..]);
        assert_eq!(ids(&r), [1, 2, 3, 4]);
        assert_eq!(r.counters.missing_chunks, 1);
    }

    #[test]
    fn single_bit_flips_anywhere_never_deliver_a_damaged_image() {
        let (originals, images) = five_images();
        let stream = images.concat().concat();
        let mut rng = Lcg(5);
        for _ in 0..400 {
            let mut damaged = stream.clone();
            let at = rng.below(damaged.len());
            damaged[at] ^= 1 << rng.below(8);
            let r = receive(&damaged);
            assert_images_intact(&r, &originals);
            assert!(r.images.len() >= 4, "one flip lost {} images", 5 - r.images.len());
            if r.images.len() < 5 {
                assert!(errors_total(&r.counters) >= 1);
            }
        }
    }

    fn oversize_boundary<const N: usize>(frame: &[u8]) -> LinkCounters {
        let mut dec = FrameDecoder::<N>::new();
        let mut stream = frame.to_vec();
        stream.extend_from_slice(&heartbeat_frame(9));
        dec.feed(&stream, |_| {});
        *dec.counters()
    }

    #[test]
    fn oversize_frames_are_dropped_whole_and_the_decoder_recovers() {
        const SMALL: usize = max_depth_chunk_len(20, 5);
        let mut enc = LinkEncoder::new();
        let (first, mut stream) = image_frames(&mut enc, 0, 20, 20, 5);
        let (_, big) = image_frames(&mut enc, 1, 20, 20, 20);
        let (third, tail) = image_frames(&mut enc, 2, 20, 20, 5);
        stream.extend(big);
        stream.extend(tail);
        let r = receive_sliced::<SMALL>(&stream.concat(), 400, &mut || 7);
        assert_eq!(ids(&r), [0, 2]);
        assert_eq!((r.images[0].1.clone(), r.images[1].1.clone()), (first, third));
        let c = r.counters;
        assert_eq!(
            (
                c.oversize,
                c.frame_too_large,
                c.depth_frames_dropped,
                errors_total(&c)
            ),
            (1, 0, 0, 1)
        );
        assert!(r.errors.contains(&LinkError::Oversize));

        // A 27-byte heartbeat frame has 25 bytes between its delimiters: N = 25 takes it.
        let hb = heartbeat_frame(1);
        assert_eq!(hb.len(), 27);
        let c = oversize_boundary::<25>(&hb);
        assert_eq!((c.frames_ok, c.oversize), (2, 0));
        // N = 24 drops it, and the equally long heartbeat after it.
        let c = oversize_boundary::<24>(&hb);
        assert_eq!((c.frames_ok, c.oversize), (0, 2));
    }

    #[test]
    fn chunk_order_duplicates_and_gaps() {
        let mut enc = LinkEncoder::new();
        let images: Vec<(Vec<u16>, Vec<Vec<u8>>)> =
            (0..6).map(|id| image_frames(&mut enc, id, 20, 20, 5)).collect();
        let originals: Vec<Vec<u16>> = images.iter().map(|(d, _)| d.clone()).collect();
        let f = |id: usize, k: usize| images[id].1[k].clone(); // k = 0 intrinsics, 1..=4 chunks
        let stream = [
            // Image 0 with a duplicated chunk: delivered, one out-of-order chunk.
            vec![f(0, 0), f(0, 1), f(0, 2), f(0, 2), f(0, 3), f(0, 4)],
            // Image 1 with a late chunk of image 0 in it and a duplicate after completion.
            vec![f(1, 0), f(1, 1), f(0, 3), f(1, 2), f(1, 3), f(1, 4), f(1, 4)],
            // Image 2 with two chunks swapped: delivered whole.
            vec![f(2, 0), f(2, 1), f(2, 3), f(2, 2), f(2, 4)],
            // Image 3 cut short by image 4: delivered with the rows that came.
            vec![f(3, 0), f(3, 1), f(3, 2)],
            vec![f(4, 0), f(4, 1), f(4, 2), f(4, 3), f(4, 4)],
            // Image 5 without its first chunk: delivered without it at the deadline.
            vec![f(5, 0), f(5, 2), f(5, 3), f(5, 4)],
        ]
        .concat()
        .concat();
        let r = receive(&stream);
        assert_eq!(ids(&r), [0, 1, 2, 4]);
        assert_eq!(partial_ids(&r), [3, 5]);
        assert_eq!((r.partial[0].2, r.partial[1].2), (10, 5));
        assert_images_intact(&r, &originals);
        let c = r.counters;
        assert_eq!(c.out_of_order_chunks, 3);
        assert_eq!(c.missing_chunks, 2);
        assert_eq!((c.depth_frames_complete, c.depth_frames_dropped), (4, 0));
        assert_eq!((c.depth_frames_partial, c.rows_missing), (2, 15));
        assert_eq!(c.crc_errors + c.cobs_errors + c.malformed, 0);
    }

    #[test]
    fn frames_too_large_or_without_matching_intrinsics_are_dropped() {
        let mut enc = LinkEncoder::new();
        let (_, big) = image_frames(&mut enc, 0, 30, 30, 10);
        let (small, small_frames) = image_frames(&mut enc, 1, 20, 20, 5);
        let r = receive_sliced::<BIG>(&[big, small_frames.clone()].concat().concat(), 400, &mut || 64);
        assert_eq!(ids(&r), [1]);
        assert_eq!(r.images[0].1, small);
        let c = r.counters;
        assert_eq!(
            (c.frame_too_large, c.depth_frames_dropped, errors_total(&c)),
            (1, 1, 1)
        );

        // Chunks before any intrinsics.
        let r = receive(&small_frames[1..].concat());
        assert!(r.images.is_empty());
        assert_eq!(
            (r.counters.no_intrinsics, r.counters.depth_frames_dropped),
            (1, 1)
        );

        // Intrinsics of another size.
        let mut out = [0u8; 64];
        let n = enc
            .encode(&Message::Intrinsics(intrinsics(30, 20)), &mut out)
            .unwrap();
        let mut stream = out[..n].to_vec();
        stream.extend(small_frames[1..].concat());
        let r = receive(&stream);
        assert!(r.images.is_empty());
        assert_eq!(r.counters.intrinsics_mismatch, 1);
        assert_eq!(r.errors, [LinkError::IntrinsicsMismatch]);
    }

    #[test]
    fn bad_versions_types_and_bodies_are_counted_not_delivered() {
        let mut body = Vec::new();
        body.extend_from_slice(&[1, 4, 0, 0]);
        body.extend_from_slice(&[0; HEARTBEAT_BODY_LEN]);
        let mut cases: Vec<(Vec<u8>, LinkError)> = Vec::new();
        let mut with = |edit: &dyn Fn(&mut Vec<u8>), e: LinkError| {
            let mut p = body.clone();
            edit(&mut p);
            cases.push((p, e));
        };
        with(&|p| p[0] = 2, LinkError::BadVersion(2));
        with(&|p| p[1] = 0x7F, LinkError::UnknownType(0x7F));
        with(&|p| p[1] = 0, LinkError::UnknownType(0));
        with(&|p| p.truncate(3), LinkError::Malformed(Malformed::Truncated));
        with(&|p| p.truncate(0), LinkError::Malformed(Malformed::Truncated));
        with(
            &|p| {
                p.pop();
            },
            LinkError::Malformed(Malformed::BodyLength),
        );
        with(&|p| p.push(0), LinkError::Malformed(Malformed::BodyLength));
        let intrinsics_body = |fx: f32, cx: f32| {
            let mut p = vec![1, 1, 0, 0];
            for v in [fx, 50.0, cx, 40.0] {
                p.extend_from_slice(&v.to_le_bytes());
            }
            p.extend_from_slice(&100u16.to_le_bytes());
            p.extend_from_slice(&80u16.to_le_bytes());
            p
        };
        cases.push((
            intrinsics_body(f32::NAN, 50.0),
            LinkError::Malformed(Malformed::Intrinsics(IntrinsicsError::BadFocalLength)),
        ));
        cases.push((
            intrinsics_body(50.0, 150.0),
            LinkError::Malformed(Malformed::Intrinsics(IntrinsicsError::PrincipalPointOutsideImage)),
        ));
        let mut pose = vec![1, 3, 0, 0, 0, 0, 0, 0];
        for v in [0.0f32, 0.0, 0.0, 0.0, 0.0, 0.0, 1.1] {
            pose.extend_from_slice(&v.to_le_bytes());
        }
        cases.push((
            pose,
            LinkError::Malformed(Malformed::Pose(PoseError::NotUnitQuaternion)),
        ));
        let chunk = |w: u16, h: u16, first: u16, rows: u16, samples: usize| {
            let mut p = vec![1, 2, 0, 0, 0, 0, 0, 0];
            for v in [w, h, first, rows] {
                p.extend_from_slice(&v.to_le_bytes());
            }
            p.extend(std::iter::repeat_n(0x11, samples * 2));
            p
        };
        cases.push((
            chunk(4, 4, 3, 2, 8),
            LinkError::Malformed(Malformed::ChunkGeometry),
        ));
        cases.push((
            chunk(0, 4, 0, 1, 0),
            LinkError::Malformed(Malformed::ChunkGeometry),
        ));
        cases.push((
            chunk(4, 4, 0, 0, 0),
            LinkError::Malformed(Malformed::ChunkGeometry),
        ));
        cases.push((chunk(4, 4, 0, 2, 7), LinkError::Malformed(Malformed::BodyLength)));
        cases.push((chunk(4, 4, 0, 2, 9), LinkError::Malformed(Malformed::BodyLength)));
        cases.push((
            chunk(65535, 65535, 0, 65535, 0),
            LinkError::Malformed(Malformed::BodyLength),
        ));

        for (payload, expected) in cases {
            let mut stream = raw_frame(&payload);
            stream.extend_from_slice(&heartbeat_frame(100));
            let got = decode_one::<256>(&stream);
            assert_eq!(got.len(), 2, "{expected:?}");
            assert_eq!(got[0], Err(expected));
            assert!(got[1].is_ok(), "decoder did not recover after {expected:?}");
        }
        // A bad CRC over an otherwise fine payload.
        let mut frame = unframe(&heartbeat_frame(3));
        *frame.last_mut().unwrap() ^= 0x80;
        assert_eq!(decode_one::<256>(&cobs_frame(&frame)), [Err(LinkError::Crc)]);
        // Not COBS: a code byte pointing past the end.
        assert_eq!(decode_one::<256>(&[0, 9, 1, 1, 0]), [Err(LinkError::Cobs)]);
    }

    #[test]
    fn sequence_gaps_count_lost_frames() {
        let mut dec = FrameDecoder::<64>::new();
        for seq in [0, 1, 2, 5, 5, 4, 6, 65535, 0] {
            dec.feed(&heartbeat_frame(seq), |r| assert!(r.is_ok()));
        }
        // 3 and 4 lost before 5 (4 arrives late), then a restart at 65535 is followed.
        assert_eq!(dec.counters().sequence_gaps, 2);
        assert_eq!(dec.counters().frames_ok, 9);
    }

    #[test]
    fn fuzz_random_bytes_never_panic() {
        let mut rng = Lcg(0xF00D);
        let mut buf = vec![0u16; 400];
        let mut rx = DepthReceiver::<BIG>::new(&mut buf);
        let mut small = FrameDecoder::<48>::new();
        let mut delivered = 0u32;
        let mut frames_seen = 0u32;
        for i in 0..20_000 {
            let len = rng.below(400);
            let bytes: Vec<u8> = match i % 3 {
                // Raw noise with occasional delimiters.
                0 => (0..len)
                    .map(|_| if rng.below(16) == 0 { 0 } else { rng.byte() })
                    .collect(),
                // Intact frames around random payloads with a plausible header: body parsing.
                1 => {
                    let mut p = vec![PROTOCOL_VERSION, 1 + rng.below(5) as u8, rng.byte(), rng.byte()];
                    let body = [20, 32, 16, 12 + 2 * rng.below(40), rng.below(80)][rng.below(5)];
                    p.extend((0..body).map(|_| {
                        if rng.below(3) == 0 {
                            rng.below(4) as u8
                        } else {
                            rng.byte()
                        }
                    }));
                    raw_frame(&p)
                }
                // Intact small chunks of random geometry: assembly paths.
                _ => {
                    let (w, h) = (1 + rng.below(25) as u16, 1 + rng.below(25) as u16);
                    // Half of them whole single-chunk images, which complete.
                    let whole = rng.below(2) == 0;
                    let first = if whole {
                        0
                    } else {
                        rng.below(usize::from(h)) as u16
                    };
                    let rows = if whole {
                        h
                    } else {
                        1 + rng.below(usize::from(h - first)) as u16
                    };
                    let depth = vec![rng.byte() as u16; usize::from(w) * usize::from(rows)];
                    let id = if rng.below(2) == 0 {
                        rng.below(4)
                    } else {
                        rng.below(1 << 20)
                    } as u32;
                    let chunk = DepthChunk::new(id, w, h, first, &depth).unwrap();
                    let mut out = vec![0u8; max_encoded_len(depth_chunk_payload_len(w, rows))];
                    let mut frames = Vec::new();
                    if whole || rng.below(4) == 0 {
                        let mut o = [0u8; 64];
                        let n = encode_frame(0, &Message::Intrinsics(intrinsics(w, h)), &mut o).unwrap();
                        frames.extend_from_slice(&o[..n]);
                    }
                    let n =
                        encode_frame(rng.below(65536) as u16, &Message::DepthChunk(chunk), &mut out).unwrap();
                    frames.extend_from_slice(&out[..n]);
                    frames
                }
            };
            let mut rest = &bytes[..];
            while !rest.is_empty() {
                let (now, later) = rest.split_at(rng.below(rest.len() + 1).max(1));
                rx.feed(now, |e| {
                    if let LinkEvent::Depth { frame, .. } = e {
                        assert_eq!(frame.depth_mm().len(), frame.intrinsics().pixel_count());
                        delivered += 1;
                    }
                });
                small.feed(now, |_| frames_seen += 1);
                rest = later;
            }
        }
        let c = rx.counters();
        std::println!("fuzz: {c:?}");
        assert_eq!(c.depth_frames_complete + c.depth_frames_partial, delivered);
        assert!(c.frames_ok > 1000 && c.malformed > 100 && c.crc_errors > 100 && c.cobs_errors > 100);
        assert!(c.missing_chunks > 0 && c.out_of_order_chunks > 0 && c.frame_too_large > 0);
        assert!(delivered > 0 && frames_seen > 0 && small.counters().oversize > 0);
    }

    #[test]
    fn random_link_damage_never_delivers_a_wrong_image() {
        let mut enc = LinkEncoder::new();
        let images: Vec<(Vec<u16>, Vec<Vec<u8>>)> =
            (0..8).map(|id| image_frames(&mut enc, id, 20, 20, 5)).collect();
        let originals: Vec<Vec<u16>> = images.iter().map(|(d, _)| d.clone()).collect();
        let clean: Vec<Vec<u8>> = images.iter().flat_map(|(_, f)| f.clone()).collect();
        let mut rng = Lcg(77);
        let mut total = LinkCounters::default();
        for _ in 0..300 {
            // Frame-level faults: drop, duplicate, swap with the next.
            let mut frames = clean.clone();
            for _ in 0..rng.below(3) {
                let i = rng.below(frames.len() - 1);
                match rng.below(3) {
                    0 => {
                        frames.remove(i);
                    }
                    1 => frames.insert(i, frames[i].clone()),
                    _ => frames.swap(i, i + 1),
                }
            }
            // Byte-level faults: bit flips, dropped bytes, inserted noise.
            let mut bytes = frames.concat();
            for _ in 0..rng.below(4) {
                let i = rng.below(bytes.len());
                match rng.below(3) {
                    0 => bytes[i] ^= 1 << rng.below(8),
                    1 => {
                        bytes.remove(i);
                    }
                    _ => bytes.insert(i, rng.byte()),
                }
            }
            let r = receive_sliced::<BIG>(&bytes, 400, &mut || 1 + rng.below(64));
            assert_images_intact(&r, &originals);
            total = total.merged(&r.counters);
        }
        std::println!("damage: {total:?}");
        assert!(total.depth_frames_complete > 1000 && total.depth_frames_partial > 50);
    }

    #[test]
    fn resend_requests_round_trip_and_bad_ones_are_refused() {
        let mut request = ResendRequest::new(7).with_pose();
        assert!(request.push_rows(3, 2) && request.push_rows(40, 9));
        assert!(!request.push_rows(50, 0));
        let mut out = [0u8; 128];
        let n = encode_frame(5, &Message::ResendRequest(request), &mut out).unwrap();
        assert!(n <= max_encoded_len(Message::ResendRequest(request).payload_len()));
        let decoded = decode_one::<128>(&out[..n]);
        assert_eq!(decoded, [Ok(Message::ResendRequest(request))]);
        assert_eq!(request.rows(), [(3, 2), (40, 9)]);
        assert!(request.wants_pose() && !request.wants_intrinsics());
        // A full request takes no more ranges.
        let mut full = ResendRequest::new(1);
        for k in 0..MAX_RESEND_RANGES as u16 {
            assert!(full.push_rows(2 * k, 1));
        }
        assert!(!full.push_rows(99, 1));
        // Unknown flags, too many ranges, an empty range, a short body: malformed.
        let body = |flags: u8, n: u8, ranges: &[(u16, u16)]| {
            let mut b = vec![
                PROTOCOL_VERSION,
                MessageType::ResendRequest.code(),
                0,
                0,
                7,
                0,
                0,
                0,
                flags,
                n,
            ];
            for (f, c) in ranges {
                b.extend_from_slice(&f.to_le_bytes());
                b.extend_from_slice(&c.to_le_bytes());
            }
            b
        };
        let framed = |raw: Vec<u8>| {
            let mut raw = raw;
            raw.extend_from_slice(&crc32(&raw).to_le_bytes());
            cobs_frame(&raw)
        };
        let bad = LinkError::Malformed(Malformed::ResendRequest);
        assert_eq!(decode_one::<256>(&framed(body(4, 0, &[]))), [Err(bad)]);
        assert_eq!(decode_one::<256>(&framed(body(0, 1, &[(3, 0)]))), [Err(bad)]);
        let many = vec![(1u16, 1u16); MAX_RESEND_RANGES + 1];
        assert_eq!(
            decode_one::<256>(&framed(body(0, many.len() as u8, &many))),
            [Err(bad)]
        );
        assert_eq!(
            decode_one::<256>(&framed(body(0, 2, &[(1, 1)]))),
            [Err(LinkError::Malformed(Malformed::BodyLength))]
        );
    }

    #[test]
    fn a_receiver_asks_for_what_is_missing_and_the_answer_completes_the_frame() {
        let mut enc = LinkEncoder::new();
        let (depth, frames) = image_frames(&mut enc, 3, 20, 20, 5); // intrinsics, 4 chunks
        let mut buf = vec![0u16; 400];
        let mut rx = DepthReceiver::<BIG>::new(&mut buf);
        // Nothing of image 3 yet: everything, its pose, the intrinsics.
        let r = rx.resend_request(3, true).unwrap();
        assert_eq!(r.rows(), [(0, u16::MAX)]);
        assert!(r.wants_pose() && r.wants_intrinsics());
        // Chunks 1 and 3 (rows 0-4, 10-14) lost.
        let mut whole = 0;
        for k in [0, 2, 4] {
            rx.feed(&frames[k], |e| {
                whole += u32::from(matches!(e, LinkEvent::Depth { .. }))
            });
        }
        assert_eq!(whole, 0);
        let r = rx.resend_request(3, false).unwrap();
        assert_eq!(r.rows(), [(0, 5), (10, 5)]);
        assert!(!r.wants_pose() && !r.wants_intrinsics());
        // The camera side answers: the rows again, in chunks of another size.
        let frame = DepthFrame::new(intrinsics(20, 20), &depth).unwrap();
        let mut scratch = vec![0u8; max_depth_chunk_len(20, 5)];
        let mut answer = Vec::new();
        for &rows in r.rows() {
            enc.encode_rows(3, &frame, rows, 2, &mut scratch, |f| answer.extend_from_slice(f))
                .unwrap();
        }
        let mut got = None;
        rx.feed(&answer, |e| {
            if let LinkEvent::Depth {
                frame, missing_rows, ..
            } = e
            {
                got = Some((frame.depth_mm().to_vec(), missing_rows));
            }
        });
        assert_eq!(got, Some((depth.clone(), 0)));
        assert_eq!(rx.resend_request(3, false), None);
        // Rows past the image are clamped away; a late resend is counted, not delivered.
        assert_eq!(
            enc.encode_rows(3, &frame, (20, 5), 5, &mut scratch, |_| ())
                .unwrap(),
            0
        );
        rx.feed(&answer, |e| assert!(!matches!(e, LinkEvent::Depth { .. })));
        assert_eq!(rx.counters().out_of_order_chunks, 6);
        assert_eq!(rx.counters().depth_frames_complete, 1);
    }

    #[test]
    fn chunk_size_follows_the_bit_error_rate() {
        // Clean or nearly: the longest chunks; at 1e-4 one row per chunk.
        assert_eq!(best_rows_per_chunk(100, 0.0, 10), 10);
        assert_eq!(best_rows_per_chunk(100, 3e-7, 10), 10);
        assert_eq!(best_rows_per_chunk(100, 1e-6, 10), 8);
        assert_eq!(best_rows_per_chunk(100, 1e-5, 10), 3);
        assert_eq!(best_rows_per_chunk(100, 1e-4, 10), 1);
        let mut last = 10;
        for ber in [1e-7, 1e-6, 3e-6, 1e-5, 3e-5, 1e-4, 1e-3, f32::NAN, -1.0, 2.0] {
            let rows = best_rows_per_chunk(100, ber, 10);
            assert!((1..=10).contains(&rows));
            if ber.is_finite() && ber > 0.0 && ber < 1.0 {
                assert!(rows <= last, "{ber}: {rows} > {last}");
                last = rows;
            }
        }
        assert_eq!(best_rows_per_chunk(100, 1e-4, 0), 1);
        // The estimate inverts the loss model.
        let len = max_depth_chunk_len(100, 10);
        let keep = (1.0f32 - 1e-4).powf(8.0 * len as f32);
        let lost = ((1.0 - keep) * 1000.0).round() as u32;
        let est = estimate_bit_error_rate(1000, lost, len);
        assert!((est - 1e-4).abs() < 1e-5, "{est}");
        assert_eq!(estimate_bit_error_rate(0, 0, len), 0.0);
        assert_eq!(estimate_bit_error_rate(10, 0, len), 0.0);
        let all = estimate_bit_error_rate(10, 10, len);
        assert!(all.is_finite() && all > 1e-4);
    }
}
