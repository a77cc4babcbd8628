//! Harness of the `stereo_matcher` target: the core's block matcher
//! (`harmonic_core::stereo`) with fuzzed image sizes, parameters, contents and call sequences.
//!
//! Input (fields read in order, zeros once the input runs out):
//!
//! - width, height, disparities: a `u8` each, 0 → 0, else `5 + b % 67`, `5 + b % 35`,
//!   `1 + b % 64`; window: a `u8`, below 8 taken as it is (0 and even values included: the
//!   parameter checks are part of what is fuzzed), else `3 + 2 · (b % 7)`;
//! - uniqueness `u8`, left–right check (`u8`: 0 off, else `byte − 1` px), minimum texture `u8`,
//!   speckle size `u16 % 400`, speckle range `u16 % 64`;
//! - prefilter: `u8 % 4` → none, the default DoG, or two fuzzed sigmas (sometimes raw bits);
//! - images: a `u8` kind (0 noise, 1 the left image shifted by a fuzzed disparity, 2 constant,
//!   3 the remaining input bytes as pixels) and a `u32` seed;
//! - call script: `u8`s, each a bad call between the row pushes (wrong row length, wrong output
//!   length, an early `finish`), until the input ends.
//!
//! Oracle: no panic; [`scratch_size`] fails exactly when the parameters are invalid, and with
//! the same error as [`StereoMatcher::new`]; one element less scratch than it asks for is
//! refused; every bad call is refused with its error and changes nothing (the streamed result
//! equals [`match_images`]'s); pushing past the last row is refused; every output pixel is
//! [`INVALID_DISPARITY`] or within `0 ..= (num_disparities − 1) · 16`, and `stats.valid` counts
//! exactly the valid ones.

use harmonic_core::stereo::{
    match_images, scratch_size, Prefilter, StereoError, StereoMatcher, StereoParams, StereoScratch,
    DISPARITY_SCALE, INVALID_DISPARITY,
};

use super::input::{Floats, Input};

/// Scratch buffers of the sizes `scratch_size` asks for, minus `short` elements of the first
/// non-empty kind.
struct Buffers {
    bytes: Vec<u8>,
    halfwords: Vec<u16>,
    words: Vec<u32>,
}

impl Buffers {
    fn new(params: &StereoParams, short: usize) -> Option<Self> {
        let need = scratch_size(params).ok()?;
        let (mut b, mut h, mut w) = (need.bytes, need.halfwords, need.words);
        if short > 0 {
            if b > 0 {
                b -= short.min(b);
            } else if h > 0 {
                h -= short.min(h);
            } else {
                w -= short.min(w);
            }
        }
        Some(Self {
            bytes: vec![0; b],
            halfwords: vec![0; h],
            words: vec![0; w],
        })
    }
    fn scratch(&mut self) -> StereoScratch<'_> {
        StereoScratch {
            bytes: &mut self.bytes,
            halfwords: &mut self.halfwords,
            words: &mut self.words,
        }
    }
}

fn params(input: &mut Input) -> StereoParams {
    // Mostly sizes the matcher takes; 0 (and whatever the window makes too small) it refuses.
    let mut size = |base: u8, span: u8| match input.u8() {
        0 => 0,
        b => u16::from(base + b % span),
    };
    let width = size(5, 67);
    let height = size(5, 35);
    let disparities = size(1, 64);
    let mut p = StereoParams::new(width, height, disparities);
    p.window = match input.u8() {
        b if b < 8 => b,
        b => 3 + 2 * (b % 7),
    };
    p.uniqueness_percent = input.u8();
    p.lr_max_diff = match input.u8() {
        0 => None,
        b => Some(b - 1),
    };
    p.min_texture = input.u8();
    p.speckle_size = input.u16() % 400;
    p.speckle_range = input.u16() % 64;
    let sigma = Floats {
        raw: 16,
        step: 0.05,
        offset: -0.5,
    };
    p.prefilter = match input.u8() % 4 {
        0 => Prefilter::None,
        1 => Prefilter::DEFAULT_DOG,
        _ => Prefilter::DoG {
            sigma_small: input.float(sigma),
            sigma_large: input.float(sigma),
        },
    };
    p
}

/// A 32-bit xorshift, for image contents.
fn next(state: &mut u32) -> u32 {
    let mut x = (*state).max(1);
    x ^= x << 13;
    x ^= x >> 17;
    x ^= x << 5;
    *state = x;
    x
}

fn images(input: &mut Input, w: usize, h: usize) -> (Vec<u8>, Vec<u8>) {
    let kind = input.u8() % 4;
    let mut seed = input.u32();
    let n = w * h;
    let noise: Vec<u8> = (0..n).map(|_| (next(&mut seed) >> 24) as u8).collect();
    match kind {
        1 => {
            // The right image sees the left one shifted: what a rectified pair of a fronto-
            // parallel plane gives, so matches are found.
            let shift = (seed % 24) as usize;
            let right = (0..n)
                .map(|i| {
                    let (x, y) = (i % w, i / w);
                    noise[y * w + (x + shift).min(w - 1)]
                })
                .collect();
            (noise, right)
        }
        2 => (vec![(seed & 0xff) as u8; n], vec![(seed >> 8) as u8; n]),
        3 => {
            let left: Vec<u8> = (0..n).map(|_| input.u8()).collect();
            let right = (0..n).map(|i| left[i] ^ noise[i] & 0x0f).collect();
            (left, right)
        }
        _ => {
            let right = (0..n).map(|_| (next(&mut seed) >> 24) as u8).collect();
            (noise, right)
        }
    }
}

pub fn run(data: &[u8]) {
    let mut input = Input(data);
    let p = params(&mut input);
    let need = scratch_size(&p);
    assert_eq!(
        need.err(),
        p.validate().err(),
        "scratch_size and validate disagree"
    );
    let Some(mut bufs) = Buffers::new(&p, 0) else {
        // Invalid parameters: the matcher refuses them with the same error.
        let mut none = Buffers {
            bytes: Vec::new(),
            halfwords: Vec::new(),
            words: Vec::new(),
        };
        let err = StereoMatcher::new(p, none.scratch()).err();
        assert_eq!(err, p.validate().err(), "{p:?}");
        return;
    };
    let need = need.unwrap_or_else(|_| unreachable!("checked above"));
    if need.bytes + need.halfwords + need.words > 0 {
        let mut short = Buffers::new(&p, 1).unwrap_or_else(|| unreachable!("valid parameters"));
        assert_eq!(
            StereoMatcher::new(p, short.scratch()).err(),
            Some(StereoError::ScratchTooSmall)
        );
    }
    let (w, h, nd) = (
        usize::from(p.width),
        usize::from(p.height),
        i32::from(p.num_disparities),
    );
    let (left, right) = images(&mut input, w, h);

    // The reference: the whole pair at once.
    let mut expected = vec![0i16; w * h];
    let mut ref_bufs = Buffers::new(&p, 0).unwrap_or_else(|| unreachable!("valid parameters"));
    let stats = match_images(p, &left, &right, ref_bufs.scratch(), &mut expected)
        .unwrap_or_else(|e| panic!("valid parameters and sizes refused: {e:?}"));
    let mut valid = 0u32;
    for &d in &expected {
        if d != INVALID_DISPARITY {
            valid += 1;
            assert!(
                (0..=(nd - 1) * i32::from(DISPARITY_SCALE)).contains(&i32::from(d)),
                "disparity {d} outside 0..{nd} px"
            );
        }
    }
    assert_eq!(stats.valid, valid, "{stats:?}");

    // Streamed, with bad calls in between: each is refused and changes nothing.
    let mut matcher =
        StereoMatcher::new(p, bufs.scratch()).unwrap_or_else(|e| panic!("valid scratch refused: {e:?}"));
    let mut out = vec![0i16; w * h];
    let mut short_out = vec![0i16; (w * h).saturating_sub(1)];
    for (row, (l, r)) in left.chunks_exact(w).zip(right.chunks_exact(w)).enumerate() {
        if !input.is_empty() {
            match input.u8() % 4 {
                0 => assert_eq!(
                    matcher.push_row(&l[..w - 1], r, &mut out),
                    Err(StereoError::SizeMismatch)
                ),
                1 => assert_eq!(
                    matcher.push_row(l, r, &mut short_out),
                    Err(StereoError::SizeMismatch)
                ),
                2 => assert_eq!(
                    matcher.finish(&mut out).err(),
                    Some(StereoError::RowCount),
                    "row {row}"
                ),
                _ => {}
            }
        }
        matcher
            .push_row(l, r, &mut out)
            .unwrap_or_else(|e| panic!("row {row} refused: {e:?}"));
    }
    if let (Some(l), Some(r)) = (left.get(..w), right.get(..w)) {
        assert_eq!(matcher.push_row(l, r, &mut out), Err(StereoError::RowCount));
    }
    let streamed = matcher
        .finish(&mut out)
        .unwrap_or_else(|e| panic!("finish refused: {e:?}"));
    assert_eq!(streamed, stats, "streamed statistics differ");
    assert!(out == expected, "streamed disparities differ from match_images");
}
