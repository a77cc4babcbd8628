extern crate std;

use std::vec;
use std::vec::Vec;

use super::*;

/// Deterministic hash of a lattice point to [0, 1).
fn lattice(ix: i64, iy: i64, seed: u64) -> f32 {
    let mut h = (ix as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15)
        ^ (iy as u64).wrapping_mul(0xC2B2_AE3D_27D4_EB4F)
        ^ seed.wrapping_mul(0x1656_67B1_9E37_79F9);
    h ^= h >> 33;
    h = h.wrapping_mul(0xFF51_AFD7_ED55_8CCD);
    h ^= h >> 33;
    (h >> 40) as f32 / (1u64 << 24) as f32
}

/// Smooth random texture: value noise with a 2.5 px and a 6 px octave, in 0..=255.
fn texture(x: f32, y: f32, seed: u64) -> f32 {
    let octave = |scale: f32, seed: u64| {
        let (fx, fy) = (x / scale, y / scale);
        let (ix, iy) = (fx.floor(), fy.floor());
        let (tx, ty) = (fx - ix, fy - iy);
        let s = |t: f32| t * t * (3.0 - 2.0 * t);
        let (sx, sy) = (s(tx), s(ty));
        let (ix, iy) = (ix as i64, iy as i64);
        let a = lattice(ix, iy, seed) * (1.0 - sx) + lattice(ix + 1, iy, seed) * sx;
        let b = lattice(ix, iy + 1, seed) * (1.0 - sx) + lattice(ix + 1, iy + 1, seed) * sx;
        a * (1.0 - sy) + b * sy
    };
    (40.0 + 120.0 * octave(2.5, seed) + 80.0 * octave(6.0, seed ^ 7)).clamp(0.0, 255.0)
}

struct Pair {
    w: usize,
    h: usize,
    left: Vec<u8>,
    right: Vec<u8>,
    /// True disparity at each left pixel, px (NaN: occluded in the right image).
    truth: Vec<f32>,
}

/// A background plane at disparity `plane(x, y)` (left coordinates), with an optional
/// fronto-parallel square `(x0, y0, size, disparity)` in front of it, textured differently.
fn render(
    w: usize,
    h: usize,
    plane: impl Fn(f32, f32) -> f32,
    square: Option<(usize, usize, usize, f32)>,
) -> Pair {
    let in_square = |x: f32, y: usize| {
        square.is_some_and(|(x0, y0, s, _)| y >= y0 && y < y0 + s && x >= x0 as f32 && x < (x0 + s) as f32)
    };
    let mut left = vec![0u8; w * h];
    let mut truth = vec![0f32; w * h];
    for y in 0..h {
        for x in 0..w {
            let xf = x as f32;
            let (v, d) = if in_square(xf, y) {
                let d = square.map_or(0.0, |s| s.3);
                (texture(xf, y as f32, 99), d)
            } else {
                (texture(xf, y as f32, 1), plane(xf, y as f32))
            };
            left[y * w + x] = v.round() as u8;
            truth[y * w + x] = d;
        }
    }
    // Right image: for each right pixel, the front-most left surface point that lands on it.
    let mut right = vec![0u8; w * h];
    for y in 0..h {
        for xr in 0..w {
            let xrf = xr as f32;
            let mut value = None;
            if let Some((x0, _, s, d)) = square {
                let xl = xrf + d;
                if in_square(xl, y) && xl < (x0 + s) as f32 {
                    value = Some(texture(xl, y as f32, 99));
                }
            }
            let value = value.unwrap_or_else(|| {
                // Solve xl = xr + plane(xl, y) by fixed-point iteration (plane varies slowly).
                let mut xl = xrf + plane(xrf, y as f32);
                for _ in 0..20 {
                    xl = xrf + plane(xl, y as f32);
                }
                texture(xl, y as f32, 1)
            });
            right[y * w + xr] = value.round() as u8;
        }
    }
    // Background pixels hidden from the right camera by the square.
    if let Some((_, _, _, d)) = square {
        for y in 0..h {
            for x in 0..w {
                let i = y * w + x;
                if in_square(x as f32, y) {
                    continue;
                }
                let xr = x as f32 - truth[i];
                if in_square(xr + d, y) {
                    truth[i] = f32::NAN;
                }
            }
        }
    }
    Pair {
        w,
        h,
        left,
        right,
        truth,
    }
}

struct Buffers {
    bytes: Vec<u8>,
    halfwords: Vec<u16>,
    words: Vec<u32>,
}

impl Buffers {
    fn new(params: &StereoParams) -> Self {
        let s = scratch_size(params).unwrap();
        Self {
            bytes: vec![0; s.bytes],
            halfwords: vec![0; s.halfwords],
            words: vec![0; s.words],
        }
    }
    fn lend(&mut self) -> StereoScratch<'_> {
        StereoScratch {
            bytes: &mut self.bytes,
            halfwords: &mut self.halfwords,
            words: &mut self.words,
        }
    }
}

fn run(params: StereoParams, pair: &Pair) -> (Vec<i16>, StereoStats) {
    let mut buffers = Buffers::new(&params);
    let mut disparity = vec![0i16; pair.w * pair.h];
    let stats = match_images(params, &pair.left, &pair.right, buffers.lend(), &mut disparity).unwrap();
    (disparity, stats)
}

/// Fraction of valid pixels within `tol` px of the truth, and density over pixels with a
/// known truth inside the matchable interior.
fn accuracy(params: &StereoParams, pair: &Pair, disparity: &[i16], tol: f32) -> (f32, f32, f32) {
    let margin = usize::from(params.window) - 1;
    let (mut known, mut valid, mut good, mut worst) = (0, 0, 0, 0f32);
    for y in margin..pair.h - margin {
        for x in margin + usize::from(params.num_disparities)..pair.w - margin {
            let i = y * pair.w + x;
            let t = pair.truth[i];
            if t.is_nan() {
                continue;
            }
            known += 1;
            let d = disparity[i];
            if d >= 0 {
                valid += 1;
                let err = (f32::from(d) / 16.0 - t).abs();
                worst = worst.max(err);
                if err <= tol {
                    good += 1;
                }
            }
        }
    }
    (
        good as f32 / valid.max(1) as f32,
        valid as f32 / known.max(1) as f32,
        worst,
    )
}

#[test]
fn constant_disparity_is_recovered_to_a_quarter_pixel() {
    for d in [4.0, 7.25, 10.5, 12.8] {
        let pair = render(96, 64, |_, _| d, None);
        let params = StereoParams::new(96, 64, 24);
        let (disparity, stats) = run(params, &pair);
        let (good, density, worst) = accuracy(&params, &pair, &disparity, 0.25);
        assert!(
            good >= 0.99,
            "d {d}: {good} within 0.25 px (worst {worst}), {stats:?}"
        );
        assert!(density >= 0.9, "d {d}: density {density}, {stats:?}");
    }
}

#[test]
fn planar_disparity_is_recovered_to_a_quarter_pixel() {
    let plane = |x: f32, y: f32| 5.0 + 0.05 * x + 0.03 * y;
    let pair = render(120, 80, plane, None);
    for prefilter in [Prefilter::None, Prefilter::DEFAULT_DOG] {
        let params = StereoParams {
            prefilter,
            window: 7,
            ..StereoParams::new(120, 80, 24)
        };
        let (disparity, stats) = run(params, &pair);
        let (good, density, worst) = accuracy(&params, &pair, &disparity, 0.25);
        assert!(
            good >= 0.97,
            "{prefilter:?}: {good} within 0.25 px (worst {worst}), {stats:?}"
        );
        assert!(density >= 0.85, "{prefilter:?}: density {density}, {stats:?}");
    }
}

#[test]
fn left_right_check_invalidates_occluded_pixels() {
    // Background at 4 px, a square at 14 px: a 10 px strip left of the square is visible to
    // the left camera only.
    let pair = render(120, 80, |_, _| 4.0, Some((60, 20, 36, 14.0)));
    let occluded: Vec<usize> = (0..pair.w * pair.h)
        .filter(|&i| pair.truth[i].is_nan() && (30..50).contains(&(i / pair.w)))
        .collect();
    assert!(occluded.len() >= 150, "{}", occluded.len());
    let params = StereoParams {
        speckle_size: 0,
        window: 7,
        ..StereoParams::new(120, 80, 24)
    };
    let wrong = |disparity: &[i16]| occluded.iter().filter(|&&i| disparity[i] >= 0).count();
    let (with_check, stats) = run(params, &pair);
    let (without, _) = run(
        StereoParams {
            lr_max_diff: None,
            ..params
        },
        &pair,
    );
    assert!(stats.inconsistent > 0, "{stats:?}");
    assert!(
        wrong(&with_check) * 5 <= occluded.len(),
        "{} of {} occluded pixels kept a disparity with the check",
        wrong(&with_check),
        occluded.len()
    );
    assert!(
        wrong(&without) > 2 * wrong(&with_check),
        "{} vs {}",
        wrong(&without),
        wrong(&with_check)
    );
    // Away from the occlusion the square and the background are still found.
    let (good, density, _) = accuracy(&params, &pair, &with_check, 1.0);
    assert!(good > 0.95 && density > 0.8, "{good} {density}");
}

#[test]
fn textureless_regions_are_invalid_not_garbage() {
    let mut pair = render(96, 64, |_, _| 6.0, None);
    // A flat grey band in both images (the same surface, so the same rows and columns shifted).
    for y in 20..44 {
        for x in 30..80 {
            pair.left[y * pair.w + x] = 128;
            pair.right[y * pair.w + x - 6] = 128;
        }
    }
    for (prefilter, min_texture) in [
        (Prefilter::None, 0),
        (Prefilter::DEFAULT_DOG, 0),
        (Prefilter::None, 2),
        (Prefilter::DEFAULT_DOG, 2),
    ] {
        // The defaults (no texture threshold): the band's costs tie across disparities and
        // the uniqueness test rejects it; with a threshold, the texture test does first.
        let params = StereoParams {
            prefilter,
            window: 7,
            min_texture,
            ..StereoParams::new(96, 64, 16)
        };
        let (disparity, stats) = run(params, &pair);
        // The band's interior, away from its textured border by a footprint.
        let mut valid = 0;
        for y in 27..37 {
            for x in 43..68 {
                if disparity[y * pair.w + x] >= 0 {
                    valid += 1;
                    assert!((f32::from(disparity[y * pair.w + x]) / 16.0 - 6.0).abs() < 1.0);
                }
            }
        }
        assert_eq!(valid, 0, "{prefilter:?}, texture {min_texture}: {stats:?}");
        if min_texture > 0 {
            assert!(stats.textureless > 0, "{stats:?}");
        } else {
            assert_eq!(stats.textureless, 0);
            assert!(stats.ambiguous > 0, "{stats:?}");
        }
    }
}

#[test]
fn speckle_filter_removes_small_blobs_and_keeps_large_ones() {
    let (w, h) = (40u16, 30u16);
    let mut d = vec![INVALID_DISPARITY; 40 * 30];
    // A large region at 100 with a 3×3 blob at 300 inside it, and a lone 5-pixel blob.
    for y in 2..28 {
        for x in 2..20 {
            d[y * 40 + x] = 100 + (x as i16 & 3);
        }
    }
    for y in 10..13 {
        for x in 8..11 {
            d[y * 40 + x] = 300;
        }
    }
    for x in 30..35 {
        d[15 * 40 + x] = 500;
    }
    let mut scratch = vec![0u32; speckle_scratch_words(w, h, 20)];
    let removed = filter_speckles(&mut d, w, h, 20, 16, &mut scratch).unwrap();
    assert_eq!(removed, 9 + 5);
    assert!(d[11 * 40 + 9] < 0 && d[15 * 40 + 32] < 0);
    assert_eq!(d.iter().filter(|&&v| v >= 0).count(), 26 * 18 - 9);
    // With a smaller size limit the 9-pixel blob stays.
    for y in 10..13 {
        for x in 8..11 {
            d[y * 40 + x] = 300;
        }
    }
    let removed = filter_speckles(&mut d, w, h, 8, 16, &mut scratch).unwrap();
    assert_eq!(removed, 0);
    // A long thin region larger than the limit survives whatever pixel the search starts at.
    let mut line = vec![INVALID_DISPARITY; 40 * 30];
    for x in 0..40 {
        line[5 * 40 + x] = 64;
    }
    assert_eq!(filter_speckles(&mut line, w, h, 20, 16, &mut scratch).unwrap(), 0);
    assert!(filter_speckles(&mut line, w, h, 20, 16, &mut scratch[..10]).is_err());
}

#[test]
fn speckles_from_mismatches_are_removed_in_the_matcher() {
    let mut pair = render(96, 64, |_, _| 6.0, None);
    // Pixel noise over part of the right image: the matcher's guesses there are scattered
    // small blobs.
    for y in 10..54 {
        for x in 40..90 {
            pair.right[y * 96 + x] = (lattice(x as i64, y as i64, 5) * 255.0) as u8;
        }
    }
    let params = StereoParams {
        window: 3,
        uniqueness_percent: 0,
        lr_max_diff: None,
        ..StereoParams::new(96, 64, 16)
    };
    let (_, stats) = run(params, &pair);
    let (_, unfiltered) = run(
        StereoParams {
            speckle_size: 0,
            ..params
        },
        &pair,
    );
    assert_eq!(unfiltered.speckles, 0);
    assert!(stats.speckles > 50, "{stats:?}");
    assert_eq!(stats.valid + stats.speckles, unfiltered.valid);
}

/// The pipeline written the slow, obvious way: every window summed from scratch.
#[allow(clippy::needless_range_loop)]
fn reference(params: &StereoParams, left: &[u8], right: &[u8]) -> Vec<i16> {
    let (w, h, nd) = (
        usize::from(params.width),
        usize::from(params.height),
        usize::from(params.num_disparities),
    );
    let r = usize::from(params.window / 2);
    let sad = |x: usize, y: usize, d: usize| -> u32 {
        let mut s = 0;
        for yy in y - r..=y + r {
            for xx in x - r..=x + r {
                s += u32::from(left[yy * w + xx].abs_diff(right[yy * w + xx - d]));
            }
        }
        s
    };
    let cost = |x: usize, y: usize, d: usize| -> u32 {
        let mut n = [
            sad(x - r, y - r, d),
            sad(x + r, y - r, d),
            sad(x - r, y + r, d),
            sad(x + r, y + r, d),
        ];
        n.sort();
        sad(x, y, d) + n[0] + n[1]
    };
    let mut out = vec![INVALID_DISPARITY; w * h];
    for y in 2 * r..h - 2 * r {
        let mut costs = vec![vec![u32::MAX; nd]; w];
        for x in 2 * r..w - 2 * r {
            for d in 0..nd.min(x - 2 * r + 1) {
                costs[x][d] = cost(x, y, d);
            }
        }
        for x in 2 * r..w - 2 * r {
            let dmax = (nd - 1).min(x - 2 * r);
            let c = &costs[x][..=dmax];
            let d1 = (0..=dmax).min_by_key(|&d| (c[d], d)).unwrap();
            let mut tex = 0;
            for yy in y - r..=y + r {
                for xx in x - r..=x + r {
                    if xx > 0 && xx + 1 < w {
                        tex += u32::from(left[yy * w + xx + 1].abs_diff(left[yy * w + xx - 1]));
                    }
                }
            }
            if tex < u32::from(params.min_texture) * (2 * r as u32 + 1).pow(2) {
                continue;
            }
            let c2 = (0..=dmax)
                .filter(|&d| d + 1 < d1 || d > d1 + 1)
                .map(|d| c[d])
                .min();
            let uniq = 100 + u64::from(params.uniqueness_percent);
            if c2.is_some_and(|c2| u64::from(c2) * 100 <= u64::from(c[d1]) * uniq) {
                continue;
            }
            let mut disp = d1 as f32;
            if d1 > 0 && d1 < dmax {
                let (cm, cp, c1) = (c[d1 - 1], c[d1 + 1], c[d1]);
                let curv = cm + cp - 2 * c1;
                if curv > 0 {
                    disp += (cm as f32 - cp as f32) / (2.0 * curv as f32);
                }
            }
            // Left-right: the right pixel's own winner over the same costs.
            if let Some(tol) = params.lr_max_diff {
                let xr = x - d1;
                let dr = (0..nd)
                    .filter(|&d| xr + d < w && costs[xr + d][d] != u32::MAX)
                    .min_by_key(|&d| (costs[xr + d][d], d))
                    .unwrap();
                if dr.abs_diff(d1) > usize::from(tol) {
                    continue;
                }
            }
            out[y * w + x] = (disp * 16.0).round() as i16;
        }
    }
    out
}

#[test]
fn running_sums_match_the_obvious_implementation() {
    let pair = render(64, 40, |x, _| 3.0 + 0.1 * x, Some((30, 12, 14, 9.0)));
    // 13 and 15 disparities leave part of the last group of four lanes unused.
    for (window, nd) in [(3, 16), (5, 16), (7, 16), (5, 13), (3, 15)] {
        let params = StereoParams {
            window,
            prefilter: Prefilter::None,
            speckle_size: 0,
            ..StereoParams::new(64, 40, nd)
        };
        let (fast, _) = run(params, &pair);
        let slow = reference(&params, &pair.left, &pair.right);
        let differ = fast.iter().zip(&slow).filter(|(a, b)| a != b).count();
        assert_eq!(differ, 0, "window {window}, {nd} disparities");
        assert!(fast.iter().filter(|&&d| d >= 0).count() > 500);
    }
}

#[test]
fn streamed_rows_give_the_whole_image_result() {
    let pair = render(80, 48, |x, y| 4.0 + 0.04 * x + 0.02 * y, Some((40, 10, 20, 11.0)));
    let defaults = StereoParams::new(80, 48, 20);
    for (prefilter, speckle_size) in [
        (Prefilter::None, 0),
        (Prefilter::DEFAULT_DOG, defaults.speckle_size),
    ] {
        let params = StereoParams {
            prefilter,
            speckle_size,
            window: 5,
            ..defaults
        };
        let (whole, whole_stats) = run(params, &pair);
        let mut buffers = Buffers::new(&params);
        // Poison the scratch: nothing may depend on its initial contents.
        buffers.halfwords.fill(0xA5A5);
        buffers.bytes.fill(0x5A);
        buffers.words.fill(0xDEAD_BEEF);
        let mut matcher = StereoMatcher::new(params, buffers.lend()).unwrap();
        let mut streamed = vec![i16::MAX; 80 * 48];
        for round in 0..2 {
            let mut done = 0;
            for y in 0..48 {
                matcher
                    .push_row(
                        &pair.left[y * 80..(y + 1) * 80],
                        &pair.right[y * 80..(y + 1) * 80],
                        &mut streamed,
                    )
                    .unwrap();
                assert!(matcher.rows_done() >= done);
                done = matcher.rows_done();
                // Rows reported done are final (unless speckle removal changes them at the end).
                if speckle_size == 0 {
                    assert_eq!(streamed[..done * 80], whole[..done * 80]);
                }
            }
            assert!(matcher
                .push_row(&pair.left[..80], &pair.right[..80], &mut streamed)
                .is_err());
            let stats = matcher.finish(&mut streamed).unwrap();
            assert_eq!(streamed, whole, "{prefilter:?} round {round}");
            assert_eq!(stats, whole_stats);
            matcher.restart();
        }
        assert!(whole_stats.valid > 1000, "{whole_stats:?}");
        let total = whole_stats.valid
            + whole_stats.border
            + whole_stats.textureless
            + whole_stats.ambiguous
            + whole_stats.inconsistent
            + whole_stats.speckles;
        assert_eq!(total, 80 * 48, "{whole_stats:?}");
    }
}

#[test]
fn bad_parameters_are_errors() {
    let ok = StereoParams::new(64, 48, 16);
    assert!(ok.validate().is_ok());
    let bad = |p: StereoParams| scratch_size(&p).unwrap_err();
    assert_eq!(bad(StereoParams { width: 0, ..ok }), StereoError::EmptyImage);
    assert_eq!(bad(StereoParams { height: 0, ..ok }), StereoError::EmptyImage);
    assert_eq!(
        bad(StereoParams {
            num_disparities: 0,
            ..ok
        }),
        StereoError::BadDisparityRange
    );
    assert_eq!(
        bad(StereoParams {
            num_disparities: 65,
            ..ok
        }),
        StereoError::BadDisparityRange
    );
    assert_eq!(bad(StereoParams { window: 8, ..ok }), StereoError::BadWindow);
    assert_eq!(bad(StereoParams { window: 1, ..ok }), StereoError::BadWindow);
    assert_eq!(bad(StereoParams { window: 17, ..ok }), StereoError::BadWindow);
    assert_eq!(
        bad(StereoParams {
            window: 15,
            height: 20,
            ..ok
        }),
        StereoError::ImageTooSmall
    );
    let dog = |a, b| StereoParams {
        prefilter: Prefilter::DoG {
            sigma_small: a,
            sigma_large: b,
        },
        ..ok
    };
    assert_eq!(bad(dog(1.6, 1.0)), StereoError::BadPrefilter);
    assert_eq!(bad(dog(f32::NAN, 1.0)), StereoError::BadPrefilter);
    assert_eq!(bad(dog(1.0, 5.0)), StereoError::BadPrefilter);

    let mut buffers = Buffers::new(&ok);
    buffers.halfwords.pop();
    assert_eq!(
        StereoMatcher::new(ok, buffers.lend()).err(),
        Some(StereoError::ScratchTooSmall)
    );
    let mut buffers = Buffers::new(&ok);
    let mut disparity = vec![0i16; 64 * 48];
    let image = vec![0u8; 64 * 48];
    assert_eq!(
        match_images(ok, &image[1..], &image, buffers.lend(), &mut disparity).unwrap_err(),
        StereoError::SizeMismatch
    );
    let mut matcher = StereoMatcher::new(ok, buffers.lend()).unwrap();
    assert_eq!(
        matcher
            .push_row(&image[..63], &image[..64], &mut disparity)
            .unwrap_err(),
        StereoError::SizeMismatch
    );
    assert_eq!(
        matcher
            .push_row(&image[..64], &image[..64], &mut disparity[1..])
            .unwrap_err(),
        StereoError::SizeMismatch
    );
    matcher
        .push_row(&image[..64], &image[..64], &mut disparity)
        .unwrap();
    assert_eq!(matcher.finish(&mut disparity).unwrap_err(), StereoError::RowCount);

    assert_eq!(
        StereoGeometry::new(0.0, 0.1).unwrap_err(),
        StereoError::BadGeometry
    );
    assert_eq!(
        StereoGeometry::new(100.0, -0.1).unwrap_err(),
        StereoError::BadGeometry
    );
    assert_eq!(
        StereoGeometry::new(100.0, f32::INFINITY).unwrap_err(),
        StereoError::BadGeometry
    );
    let g = StereoGeometry::new(100.0, 0.1).unwrap();
    let mut depth = [7u16; 4];
    disparity_to_depth_mm(&g, &[INVALID_DISPARITY, 0, 160, 1], &mut depth).unwrap();
    // 10 px → 1 m; 1/16 px → 160 m.
    assert_eq!(
        depth,
        [0, 0, 1000, 160_000u32.min(u32::from(u16::MAX - 1)) as u16]
    );
    assert!(disparity_to_depth_mm(&g, &[0; 3], &mut depth).is_err());
}

#[test]
fn scratch_size_matches_the_documented_formula() {
    let p = StereoParams::new(100, 100, 64);
    let s = scratch_size(&p).unwrap();
    // r = 5, k = 5: rings 2·17·100 bytes; the prefilter's 4·11·100 halfwords; window sums
    // (1 + 11)·100·32 words (two disparities a word), 64 + 300 + 200 + 2·313 + speckle + 1
    // (speckle 10 000 / 256 = 39).
    assert_eq!(s.bytes, 3400);
    assert_eq!(s.halfwords, 4400);
    assert_eq!(
        s.words,
        12 * 3200 + 64 + 300 + 200 + 2 * 313 + usize::from(p.speckle_size) + 1
    );
    assert!(s.total_bytes() < 170 * 1024, "{}", s.total_bytes());
    // Disparity ranges that are not a multiple of four take whole groups of four lanes.
    let odd = scratch_size(&StereoParams::new(100, 100, 61)).unwrap();
    assert_eq!(odd.words, s.words);
}

#[test]
fn best_two_is_the_sum_of_the_two_smallest() {
    let values = [0u32, 1, 2, 7, 30_855, 30_856];
    for &a in &values {
        for &b in &values {
            for &c in &values {
                for &d in &values {
                    let mut sorted = [a, b, c, d];
                    sorted.sort_unstable();
                    assert_eq!(
                        lanes::best_two(a, b, c, d),
                        sorted[0] + sorted[1],
                        "{a} {b} {c} {d}"
                    );
                }
            }
        }
    }
}
