//! Property tests of the depth link's receiver (`harmonic_core::link`): random images, poses and
//! heartbeats are encoded as the camera side sends them, then fed to a `DepthReceiver`
//!
//! - in random slicings: the same images come out as from one piece, all of them, intact;
//! - after line noise: every image still comes out (the leading delimiter ends the noise);
//! - after random damage (bit flips, lost, inserted and repeated bytes, cuts): no panic, and
//!   whatever comes out is exactly something that was sent, or of an image the rows that
//!   arrived (the others not received).
//!
//! Failure persistence is off, as in `properties.rs`.

use harmonic_core::camera::{DepthFrame, Intrinsics};
use harmonic_core::link::{
    self, DepthReceiver, Heartbeat, LinkEncoder, LinkEvent, Message, Pose, NOT_RECEIVED,
};
use proptest::prelude::*;

const MAX_SIDE: u16 = 24;
/// Decoder capacity: a whole image of the largest size in one chunk.
const N: usize = link::max_depth_chunk_len(MAX_SIDE, MAX_SIDE);

fn config(cases: u32) -> ProptestConfig {
    ProptestConfig {
        failure_persistence: None,
        ..ProptestConfig::with_cases(cases)
    }
}

/// One image as the camera side sends it.
#[derive(Debug, Clone)]
struct Image {
    width: u16,
    height: u16,
    rows_per_chunk: u16,
    depth: Vec<u16>,
    pose: Option<[f32; 3]>,
    heartbeat_after: bool,
}

fn image() -> impl Strategy<Value = Image> {
    (1..=MAX_SIDE, 1..=MAX_SIDE)
        .prop_flat_map(|(w, h)| {
            (
                Just(w),
                Just(h),
                1..=h,
                proptest::collection::vec(
                    prop_oneof![Just(0u16), any::<u16>(), 300u16..10_000],
                    usize::from(w) * usize::from(h),
                ),
                proptest::option::of(proptest::array::uniform3(-50.0f32..50.0)),
                any::<bool>(),
            )
        })
        .prop_map(
            |(width, height, rows_per_chunk, depth, pose, heartbeat_after)| Image {
                width,
                height,
                rows_per_chunk,
                depth,
                pose,
                heartbeat_after,
            },
        )
}

/// The wire bytes of `images` (ids 1, 2, …), as `LinkEncoder` writes them.
fn encode(images: &[Image]) -> Vec<u8> {
    let mut enc = LinkEncoder::new();
    let mut wire = Vec::new();
    let mut scratch = vec![0u8; N];
    for (k, img) in images.iter().enumerate() {
        let id = k as u32 + 1;
        if let Some(t) = img.pose {
            let pose = Pose::new(id, t, [0.0, 0.0, 0.0, 1.0]).unwrap();
            let n = enc.encode(&Message::Pose(pose), &mut scratch).unwrap();
            wire.extend_from_slice(&scratch[..n]);
        }
        let intrinsics = Intrinsics::from_hfov(img.width, img.height, 1.2).unwrap();
        let frame = DepthFrame::new(intrinsics, &img.depth).unwrap();
        enc.encode_depth_frame(id, &frame, img.rows_per_chunk, &mut scratch, |b| {
            wire.extend_from_slice(b)
        })
        .unwrap();
        if img.heartbeat_after {
            let hb = Heartbeat {
                uptime_ms: id * 1000,
                frames_sent: id,
                ..Heartbeat::default()
            };
            let n = enc.encode(&Message::Heartbeat(hb), &mut scratch).unwrap();
            wire.extend_from_slice(&scratch[..n]);
        }
    }
    wire
}

/// An image as delivered: id, width, height, depth, pose translation.
type Delivered = (u32, u16, u16, Vec<u16>, Option<[f32; 3]>);

/// What came out of a receiver.
#[derive(Debug, Default, PartialEq)]
struct Out {
    images: Vec<Delivered>,
    heartbeats: Vec<Heartbeat>,
}

/// Feeds `wire` in pieces ending at the `cuts` (fractions of its length).
fn receive(wire: &[u8], cuts: &[f64]) -> Out {
    let mut buffer = vec![0u16; usize::from(MAX_SIDE) * usize::from(MAX_SIDE)];
    let mut rx = DepthReceiver::<N>::new(&mut buffer);
    let mut out = Out::default();
    let mut ends: Vec<usize> = cuts.iter().map(|c| (c * wire.len() as f64) as usize).collect();
    ends.push(wire.len());
    ends.sort_unstable();
    let mut start = 0;
    for end in ends {
        let end = end.clamp(start, wire.len());
        rx.feed(&wire[start..end], |event| match event {
            LinkEvent::Depth {
                frame_id,
                frame,
                pose,
                ..
            } => out.images.push((
                frame_id,
                frame.intrinsics().width(),
                frame.intrinsics().height(),
                frame.depth_mm().to_vec(),
                pose.map(|p| p.translation()),
            )),
            LinkEvent::Heartbeat(h) => out.heartbeats.push(h),
            _ => {}
        });
        start = end;
    }
    out
}

/// What the receiver should deliver for `images` sent cleanly.
fn expected(images: &[Image]) -> Out {
    Out {
        images: images
            .iter()
            .enumerate()
            .map(|(k, img)| (k as u32 + 1, img.width, img.height, img.depth.clone(), img.pose))
            .collect(),
        heartbeats: images
            .iter()
            .enumerate()
            .filter(|(_, img)| img.heartbeat_after)
            .map(|(k, _)| Heartbeat {
                uptime_ms: (k as u32 + 1) * 1000,
                frames_sent: k as u32 + 1,
                ..Heartbeat::default()
            })
            .collect(),
    }
}

/// A kind of damage at a relative position of the stream.
#[derive(Debug, Clone)]
enum Damage {
    Flip(f64, u8),
    Delete(f64),
    Insert(f64, u8),
    Repeat(f64, f64),
    Truncate(f64),
}

fn damage() -> impl Strategy<Value = Damage> {
    let at = 0.0..1.0f64;
    prop_oneof![
        (at.clone(), 0u8..8).prop_map(|(a, b)| Damage::Flip(a, b)),
        at.clone().prop_map(Damage::Delete),
        (at.clone(), any::<u8>()).prop_map(|(a, b)| Damage::Insert(a, b)),
        (at.clone(), 0.0..0.2f64).prop_map(|(a, l)| Damage::Repeat(a, l)),
        (0.5..1.0f64).prop_map(Damage::Truncate),
    ]
}

fn apply(wire: &mut Vec<u8>, d: &Damage) {
    let idx = |f: f64, len: usize| ((f * len as f64) as usize).min(len.saturating_sub(1));
    if wire.is_empty() {
        return;
    }
    match *d {
        Damage::Flip(a, bit) => {
            let i = idx(a, wire.len());
            wire[i] ^= 1 << bit;
        }
        Damage::Delete(a) => {
            let i = idx(a, wire.len());
            wire.remove(i);
        }
        Damage::Insert(a, b) => {
            let i = idx(a, wire.len());
            wire.insert(i, b);
        }
        Damage::Repeat(a, l) => {
            let i = idx(a, wire.len());
            let end = (i + (l * wire.len() as f64) as usize).min(wire.len());
            let copy = wire[i..end].to_vec();
            wire.splice(end..end, copy);
        }
        Damage::Truncate(f) => {
            let n = (f * wire.len() as f64) as usize;
            wire.truncate(n);
        }
    }
}

proptest! {
    #![proptest_config(config(256))]

    #[test]
    fn every_slicing_decodes_the_same(
        images in proptest::collection::vec(image(), 1..5),
        cuts in proptest::collection::vec(0.0..1.0f64, 0..40),
    ) {
        let wire = encode(&images);
        let whole = receive(&wire, &[]);
        prop_assert_eq!(&whole, &expected(&images));
        prop_assert_eq!(receive(&wire, &cuts), whole);
    }

    #[test]
    fn line_noise_before_the_stream_costs_nothing(
        images in proptest::collection::vec(image(), 1..4),
        noise in proptest::collection::vec(any::<u8>(), 0..300),
        cuts in proptest::collection::vec(0.0..1.0f64, 0..10),
    ) {
        let mut wire = noise;
        wire.extend(encode(&images));
        prop_assert_eq!(receive(&wire, &cuts), expected(&images));
    }

    #[test]
    fn damage_never_panics_nor_delivers_anything_not_sent(
        images in proptest::collection::vec(image(), 1..5),
        damages in proptest::collection::vec(damage(), 1..6),
        cuts in proptest::collection::vec(0.0..1.0f64, 0..10),
    ) {
        let mut wire = encode(&images);
        for d in &damages {
            apply(&mut wire, d);
        }
        let sent = expected(&images);
        let got = receive(&wire, &cuts);
        for image in &got.images {
            // An image may repeat (a repeated stretch of the stream) and may lack its pose
            // (the Pose frame was damaged), but is otherwise exactly an image that was sent.
            let original = sent.images.iter().find(|s| s.0 == image.0);
            prop_assert!(original.is_some(), "image {} was never sent", image.0);
            let original = original.unwrap();
            prop_assert_eq!((image.1, image.2), (original.1, original.2));
            // A partial image (chunks lost) is the original with whole rows not received.
            let width = usize::from(image.1.max(1));
            for (row, want) in image.3.chunks(width).zip(original.3.chunks(width)) {
                prop_assert!(
                    row == want || row.iter().all(|&d| d == NOT_RECEIVED),
                    "image {} delivered a row that was never sent", image.0
                );
            }
            prop_assert!(image.4.is_none() || image.4 == original.4);
        }
        for hb in &got.heartbeats {
            prop_assert!(sent.heartbeats.contains(hb), "heartbeat {:?} was never sent", hb);
        }
    }
}
