//! Fuzz harness for the depth link's receiver ([`DepthReceiver`]: COBS framing, CRC, message
//! checks, chunk assembly). Shared by `fuzz/fuzz_targets/link_decoder.rs` and the workspace
//! test `tests/tests/fuzz_harness.rs` (through `#[path]`).
//!
//! Input: the first byte picks the mode. Odd: the rest is a script of messages (intrinsics,
//! depth chunks, poses, heartbeats with fuzzed fields) that are encoded as valid frames, then
//! damaged by a few byte edits, so the fuzzer gets past the CRC. Even: the rest is raw line
//! bytes. Either way the stream is fed three times — whole, byte by byte, and in slices whose
//! lengths come from the input — and the oracle checks:
//!
//! - no panic;
//! - every delivered depth frame is consistent: as many samples as its intrinsics announce,
//!   intrinsics that [`Intrinsics::new`] accepts, a pose (if any) for the same frame id that
//!   is finite with a unit quaternion; a partial one has at least one row and at least as many
//!   rows wholly [`NOT_RECEIVED`] as it says are missing;
//! - at the end, the resend request for the frame in progress lists rows inside the image, in
//!   order, not overlapping, and survives its own encoding; finishing the frame then delivers
//!   it (or says why not);
//! - the three slicings yield the same events and the same counters.

use harmonic_core::camera::Intrinsics;
use harmonic_core::link::{
    DepthChunk, DepthReceiver, FrameDecoder, Heartbeat, LinkCounters, LinkEncoder, LinkError, LinkEvent,
    Message, Pose, ResendRequest, NOT_RECEIVED, UNIT_QUATERNION_TOLERANCE,
};

/// Decoder buffer: small enough that oversize frames are reachable.
const DECODER_BYTES: usize = 600;
/// Assembler buffer: images of up to 24 × 16 pixels.
const IMAGE_PIXELS: usize = 24 * 16;

// The crate that includes this harness also includes `input.rs` as `crate::input`.
use crate::input::{Floats, Input};

/// Plausible floats here: small integers and halves.
const FLOATS: Floats = Floats {
    raw: 32,
    step: 0.5,
    offset: -64.0,
};

/// An owned copy of a receiver event, to compare slicings.
#[derive(Debug, Clone, PartialEq)]
enum Event {
    Depth {
        frame_id: u32,
        intrinsics: Intrinsics,
        depth_mm: Vec<u16>,
        pose: Option<Pose>,
        missing_rows: u16,
    },
    Intrinsics(Intrinsics),
    Pose(Pose),
    Heartbeat(Heartbeat),
    ResendRequest(ResendRequest),
    Geometry(harmonic_core::map::MapGeometry),
    Error(LinkError),
    /// What the receiver asked for at the end.
    Asked(Option<ResendRequest>),
}

/// Runs the harness on one input. Panics only when the oracle finds a bug.
pub fn run(data: &[u8]) {
    let Some((&mode, rest)) = data.split_first() else {
        return;
    };
    let stream = if mode & 1 == 1 {
        scripted_stream(rest)
    } else {
        rest.to_vec()
    };
    let whole = receive(&stream, &[usize::MAX]);
    let bytewise = receive(&stream, &[1]);
    let slices: Vec<usize> = data.iter().map(|&b| usize::from(b % 64) + 1).collect();
    let sliced = receive(&stream, &slices);
    assert_eq!(whole, bytewise, "byte-by-byte feeding changed the events");
    assert_eq!(whole, sliced, "a different slicing changed the events");
}

/// Feeds `stream` in slices of the lengths in `slices` (cycled) and checks every event.
fn receive(stream: &[u8], slices: &[usize]) -> (Vec<Event>, LinkCounters) {
    let mut image = vec![0u16; IMAGE_PIXELS];
    let mut receiver = DepthReceiver::<DECODER_BYTES>::new(&mut image);
    let mut events = Vec::new();
    let mut rest = stream;
    let mut lengths = slices.iter().cycle();
    while !rest.is_empty() {
        let n = lengths.next().copied().unwrap_or(1).clamp(1, rest.len());
        let (now, later) = rest.split_at(n);
        receiver.feed(now, |event| events.push(check(event)));
        rest = later;
    }
    if let Some(id) = receiver.frame_in_progress() {
        let request = receiver.resend_request(id, true);
        events.push(Event::Asked(request));
        let request = request.expect("a frame in progress lacks rows");
        check_request(&request);
        let mut before = 0u32;
        for &(first, count) in request.rows() {
            assert!(
                count > 0 && u32::from(first) >= before,
                "rows asked for twice or out of order"
            );
            before = u32::from(first) + u32::from(count);
        }
        receiver.finish_frame(|event| events.push(check(event)));
        assert_eq!(
            receiver.frame_in_progress(),
            None,
            "finishing left the frame in progress"
        );
    }
    let counters = receiver.counters();
    assert_eq!(counters.bytes, stream.len() as u64, "bytes counted");
    (events, counters)
}

/// Checks one event for consistency and copies it.
fn check(event: LinkEvent<'_>) -> Event {
    match event {
        LinkEvent::Depth {
            frame_id,
            frame,
            pose,
            missing_rows,
        } => {
            let i = *frame.intrinsics();
            assert!(
                missing_rows < i.height(),
                "a frame of which no row arrived delivered"
            );
            let lost = frame
                .depth_mm()
                .chunks(usize::from(i.width()))
                .filter(|row| row.iter().all(|&d| d == NOT_RECEIVED))
                .count();
            assert!(
                lost >= usize::from(missing_rows),
                "missing rows hold received values"
            );
            assert_eq!(
                frame.depth_mm().len(),
                usize::from(i.width()) * usize::from(i.height()),
                "frame size differs from its intrinsics"
            );
            assert!(frame.depth_mm().len() <= IMAGE_PIXELS);
            check_intrinsics(&i);
            if let Some(p) = pose {
                assert_eq!(p.frame_id(), frame_id, "pose of another frame attached");
                check_pose(&p);
            }
            Event::Depth {
                frame_id,
                intrinsics: i,
                depth_mm: frame.depth_mm().to_vec(),
                pose,
                missing_rows,
            }
        }
        LinkEvent::Intrinsics(i) => {
            check_intrinsics(&i);
            Event::Intrinsics(i)
        }
        LinkEvent::Pose(p) => {
            check_pose(&p);
            Event::Pose(p)
        }
        LinkEvent::Heartbeat(h) => Event::Heartbeat(h),
        LinkEvent::ResendRequest(r) => {
            check_request(&r);
            Event::ResendRequest(r)
        }
        LinkEvent::Geometry(g) => {
            let d = g.dims();
            assert!(!d.is_empty(), "a grid without voxels delivered");
            assert!(
                g.resolution().is_finite() && g.resolution() > 0.0,
                "a grid of resolution {} delivered",
                g.resolution()
            );
            Event::Geometry(g)
        }
        LinkEvent::Error(e) => Event::Error(e),
    }
}

/// A request survives its own encoding and decoding unchanged.
fn check_request(r: &ResendRequest) {
    let mut out = [0u8; 128];
    let n = LinkEncoder::new()
        .encode(&Message::ResendRequest(*r), &mut out)
        .expect("a request fits 128 bytes");
    let mut decoder = FrameDecoder::<128>::new();
    let mut back = None;
    for &b in &out[..n] {
        if let Some(Ok(Message::ResendRequest(d))) = decoder.push(b) {
            back = Some(d);
        }
    }
    assert_eq!(back, Some(*r), "a resend request changed on the wire");
}

fn check_intrinsics(i: &Intrinsics) {
    let again = Intrinsics::new(i.fx(), i.fy(), i.cx(), i.cy(), i.width(), i.height());
    assert_eq!(again, Ok(*i), "delivered intrinsics fail their own check");
}

fn check_pose(p: &Pose) {
    let t = p.translation();
    let q = p.rotation_xyzw();
    assert!(
        t.iter().chain(q.iter()).all(|c| c.is_finite()),
        "non-finite pose delivered"
    );
    let norm = q.iter().map(|c| c * c).sum::<f32>().sqrt();
    assert!(
        (norm - 1.0).abs() <= UNIT_QUATERNION_TOLERANCE * 1.01,
        "non-unit quaternion delivered"
    );
    let iso = p.isometry();
    assert!(iso.translation.vector.iter().all(|c| c.is_finite()));
}

/// Valid frames from a script in `data`, then a few byte edits from its tail.
fn scripted_stream(data: &[u8]) -> Vec<u8> {
    let mut input = Input(data);
    let mut encoder = LinkEncoder::new();
    let mut out = Vec::new();
    let mut scratch = vec![0u8; 4096];
    let mut emit = |encoder: &mut LinkEncoder, message: &Message<'_>, out: &mut Vec<u8>| {
        if let Ok(n) = encoder.encode(message, &mut scratch) {
            out.push(0);
            out.extend_from_slice(&scratch[..n]);
        }
    };
    let mut edits = 0;
    for _ in 0..64 {
        if input.is_empty() {
            break;
        }
        match input.u8() % 9 {
            0 => {
                let (w, h) = (u16::from(input.u8() % 32), u16::from(input.u8() % 24));
                let fx = input.float(FLOATS);
                let fy = input.float(FLOATS);
                let cx = input.float(FLOATS);
                let cy = input.float(FLOATS);
                if let Ok(i) = Intrinsics::new(fx, fy, cx, cy, w, h) {
                    emit(&mut encoder, &Message::Intrinsics(i), &mut out);
                }
            }
            1 | 2 => {
                // A whole image: intrinsics and chunks, as the camera side sends it.
                let frame_id = u32::from(input.u8());
                let (w, h) = (u16::from(input.u8() % 30) + 1, u16::from(input.u8() % 20) + 1);
                let rows = u16::from(input.u8() % 8) + 1;
                let seed = input.u16();
                let depth: Vec<u16> = (0..usize::from(w) * usize::from(h))
                    .map(|k| (k as u16).wrapping_mul(seed) >> 3)
                    .collect();
                if let Ok(i) = Intrinsics::from_hfov(w, h, 1.2) {
                    emit(&mut encoder, &Message::Intrinsics(i), &mut out);
                }
                let mut first = 0u16;
                while first < h {
                    let n = rows.min(h - first);
                    let range = usize::from(first) * usize::from(w)..usize::from(first + n) * usize::from(w);
                    if let Ok(c) = DepthChunk::new(frame_id, w, h, first, &depth[range]) {
                        emit(&mut encoder, &Message::DepthChunk(c), &mut out);
                    }
                    first += n;
                }
            }
            3 => {
                // One chunk with fuzzed geometry.
                let frame_id = u32::from(input.u8() % 4);
                let (w, h) = (u16::from(input.u8() % 32), u16::from(input.u8() % 24));
                let first = u16::from(input.u8() % 24);
                let rows = usize::from(input.u8() % 6);
                let depth: Vec<u16> = (0..usize::from(w) * rows).map(|_| input.u16()).collect();
                if let Ok(c) = DepthChunk::new(frame_id, w, h, first, &depth) {
                    emit(&mut encoder, &Message::DepthChunk(c), &mut out);
                }
            }
            4 => {
                let frame_id = u32::from(input.u8());
                let t = [input.float(FLOATS), input.float(FLOATS), input.float(FLOATS)];
                let q = [
                    input.float(FLOATS),
                    input.float(FLOATS),
                    input.float(FLOATS),
                    input.float(FLOATS),
                ];
                let q = match input.u8() % 2 {
                    0 => q,
                    _ => {
                        let n = q.iter().map(|c| c * c).sum::<f32>().sqrt();
                        q.map(|c| c / n)
                    }
                };
                if let Ok(p) = Pose::new(frame_id, t, q) {
                    emit(&mut encoder, &Message::Pose(p), &mut out);
                }
            }
            5 => {
                let h = Heartbeat {
                    uptime_ms: input.u32(),
                    frames_sent: input.u32(),
                    frames_skipped: input.u32(),
                    sensor_errors: input.u32(),
                };
                emit(&mut encoder, &Message::Heartbeat(h), &mut out);
            }
            6 => {
                // Raw bytes on the line.
                let n = usize::from(input.u8() % 16);
                for _ in 0..n {
                    out.push(input.u8());
                }
            }
            7 => {
                // A resend request (it belongs on the return channel; the receiver reports it).
                let mut r = ResendRequest::new(u32::from(input.u8()));
                if input.u8() & 1 == 1 {
                    r = r.with_pose();
                }
                for _ in 0..input.u8() % 20 {
                    let _ = r.push_rows(input.u16(), input.u16());
                }
                emit(&mut encoder, &Message::ResendRequest(r), &mut out);
            }
            _ => edits += 1,
        }
    }
    // Byte edits: flip, delete or insert at fuzzed positions.
    for _ in 0..edits {
        if out.is_empty() {
            break;
        }
        let at = usize::from(input.u16()) % out.len();
        match input.u8() % 3 {
            0 => out[at] ^= input.u8() | 1,
            1 => {
                out.remove(at);
            }
            _ => out.insert(at, input.u8()),
        }
    }
    out
}
