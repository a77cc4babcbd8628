//! The core's stereo matcher on the MCU: matches an embedded synthetic 100 × 100 pair with 64
//! disparities under QEMU and prints, over semihosting, the instructions each configuration
//! takes (`harmonic-sim fw-budget --stereo` builds, runs and tabulates it; BENCHMARKS.md).
//!
//! A separate image, so the flight firmware's RAM (nearly all of the 1 MiB budget) stays as it
//! is: this one holds the pair, the ground truth, the disparity and depth images and the
//! matcher's scratch in its own statics. The pair is computed at boot (not measured): a
//! slanted background plane (disparity 12 px at the top to 28 px at the bottom) and a square
//! at 40 px in front of it, both with smooth random texture. Under `-icount shift=0` one
//! board tick is 40 instructions.
//!
//! Each configuration is matched twice: with the DSP instructions (`UQSUB8`/`UXTAB16` in the
//! cost update, `UADD16`/`USUB16`/`SEL` in the five-window costs; the core's `dsp` feature,
//! which the firmware turns on), timed, and with the portable code, timed too; the two
//! disparity images must be identical (`identical=1`), and the core's own check of both
//! kernels on random rows must pass (`dsp_agrees=1`).
#![cfg_attr(target_os = "none", no_std)]
#![cfg_attr(target_os = "none", no_main)]

#[cfg(target_os = "none")]
mod bench {
    use cortex_m_rt::entry;
    use harmonic_core::stereo::{
        disparity_to_depth_mm, dsp_agrees, scratch_size, Prefilter, StereoGeometry, StereoMatcher,
        StereoParams, StereoScratch,
    };
    use harmonic_fw::board::halt;
    use harmonic_fw::board::timer::Ticks;

    const W: usize = 100;
    const H: usize = 100;
    const NDISP: u16 = 64;
    /// Scratch for the largest configuration measured (11 × 11 windows, DoG of radius 5).
    const BYTES: usize = 2 * (3 * 5 + 2) * W;
    const HALFWORDS: usize = 4 * 11 * W;
    const WORDS: usize =
        12 * W * NDISP as usize / 2 + NDISP as usize + 5 * W + 2 * (W * H).div_ceil(32) + 2000 + 1;
    /// Instructions per tick of the board timer under `-icount shift=0`.
    const INSTRUCTIONS_PER_TICK: u64 = 40;
    /// The square in front: columns and rows 30..70 of the left image, disparity 40 px.
    const SQUARE: (usize, usize, f32) = (30, 70, 40.0);

    fn lattice(ix: i32, iy: i32, seed: u32) -> f32 {
        let mut h = (ix as u32).wrapping_mul(0x8DA6_B343) ^ (iy as u32).wrapping_mul(0xD816_3841) ^ seed;
        h ^= h >> 16;
        h = h.wrapping_mul(0x7FEB_352D);
        h ^= h >> 15;
        (h >> 8) as f32 / (1u32 << 24) as f32
    }

    fn texture(x: f32, y: f32, seed: u32) -> u8 {
        let octave = |scale: f32, seed: u32| {
            let (fx, fy) = (x / scale, y / scale);
            let (ix, iy) = (libm::floorf(fx), libm::floorf(fy));
            let s = |t: f32| t * t * (3.0 - 2.0 * t);
            let (sx, sy) = (s(fx - ix), s(fy - iy));
            let (ix, iy) = (ix as i32, iy as i32);
            let a = lattice(ix, iy, seed) * (1.0 - sx) + lattice(ix + 1, iy, seed) * sx;
            let b = lattice(ix, iy + 1, seed) * (1.0 - sx) + lattice(ix + 1, iy + 1, seed) * sx;
            a * (1.0 - sy) + b * sy
        };
        libm::roundf((40.0 + 120.0 * octave(2.5, seed) + 80.0 * octave(6.0, seed ^ 7)).clamp(0.0, 255.0))
            as u8
    }

    fn background(y: usize) -> f32 {
        12.0 + 16.0 * y as f32 / H as f32
    }

    fn in_square(x: f32, y: usize) -> bool {
        let (lo, hi, _) = SQUARE;
        y >= lo && y < hi && x >= lo as f32 && x < hi as f32
    }

    /// The pair and the true disparity (1/16 px; −1 where the right camera cannot see).
    fn synthesize(left: &mut [u8], right: &mut [u8], truth: &mut [i16]) {
        let d_square = SQUARE.2;
        for y in 0..H {
            for x in 0..W {
                let xf = x as f32;
                let i = y * W + x;
                let (value, d) = if in_square(xf, y) {
                    (texture(xf, y as f32, 99), d_square)
                } else {
                    (texture(xf, y as f32, 1), background(y))
                };
                left[i] = value;
                let occluded = !in_square(xf, y) && in_square(xf - d + d_square, y);
                truth[i] = if occluded {
                    -1
                } else {
                    libm::roundf(d * 16.0) as i16
                };
                let xl_square = xf + d_square;
                right[i] = if in_square(xl_square, y) {
                    texture(xl_square, y as f32, 99)
                } else {
                    texture(xf + background(y), y as f32, 1)
                };
            }
        }
    }

    /// The images, their ground truth and the results.
    struct Frame {
        left: [u8; W * H],
        right: [u8; W * H],
        truth: [i16; W * H],
        disparity: [i16; W * H],
        /// The same match by the portable code.
        portable: [i16; W * H],
        depth: [u16; W * H],
    }

    /// The matcher's scratch.
    struct Scratch {
        bytes: [u8; BYTES],
        halfwords: [u16; HALFWORDS],
        words: [u32; WORDS],
    }

    #[entry]
    fn main() -> ! {
        static mut FRAME: Frame = Frame {
            left: [0; W * H],
            right: [0; W * H],
            truth: [0; W * H],
            disparity: [0; W * H],
            portable: [0; W * H],
            depth: [0; W * H],
        };
        static mut SCRATCH: Scratch = Scratch {
            bytes: [0; BYTES],
            halfwords: [0; HALFWORDS],
            words: [0; WORDS],
        };
        let Frame {
            left,
            right,
            truth,
            disparity,
            portable,
            depth,
        } = FRAME;
        let Scratch {
            bytes: scratch_bytes_buf,
            halfwords: scratch_halfwords,
            words: scratch_words,
        } = SCRATCH;

        // SAFETY: the only user of timer 0.
        let ticks = unsafe { Ticks::start() };
        synthesize(left, right, truth);
        semihosting::println!("stereo_check dsp_agrees={}", u8::from(dsp_agrees()));
        let Ok(geometry) = StereoGeometry::new(130.3, 0.12) else {
            halt(2)
        };
        let configs = [
            (11, Prefilter::DEFAULT_DOG),
            (7, Prefilter::DEFAULT_DOG),
            (11, Prefilter::None),
            (7, Prefilter::None),
        ];
        for (window, prefilter) in configs {
            let params = StereoParams {
                window,
                prefilter,
                ..StereoParams::new(W as u16, H as u16, NDISP)
            };
            let scratch_bytes = scratch_size(&params).map(|s| s.total_bytes()).unwrap_or(0);
            let t0 = ticks.now();
            let scratch = StereoScratch {
                bytes: &mut scratch_bytes_buf[..],
                halfwords: &mut scratch_halfwords[..],
                words: &mut scratch_words[..],
            };
            let mut matcher = match StereoMatcher::new(params, scratch) {
                Ok(m) => m,
                Err(e) => {
                    defmt::error!("matcher refused its parameters: {}", e);
                    halt(2)
                }
            };
            let mut pushed = true;
            for (l, r) in left.chunks_exact(W).zip(right.chunks_exact(W)) {
                pushed &= matcher.push_row(l, r, &mut disparity[..]).is_ok();
            }
            let stats = matcher.finish(&mut disparity[..]);
            let t1 = ticks.now();
            let converted = disparity_to_depth_mm(&geometry, &disparity[..], &mut depth[..]);
            let t2 = ticks.now();
            let (Ok(stats), true, Ok(())) = (stats, pushed, converted) else {
                halt(3)
            };
            // The same frame by the portable cost update.
            let t3 = ticks.now();
            matcher.restart();
            matcher.use_dsp(false);
            for (l, r) in left.chunks_exact(W).zip(right.chunks_exact(W)) {
                pushed &= matcher.push_row(l, r, &mut portable[..]).is_ok();
            }
            let portable_stats = matcher.finish(&mut portable[..]);
            let t4 = ticks.now();
            let identical = pushed && portable_stats == Ok(stats) && portable[..] == disparity[..];
            // Accuracy on the pixels the right camera sees.
            let (mut known, mut valid, mut bad1) = (0u32, 0u32, 0u32);
            for (&d, &t) in disparity.iter().zip(truth.iter()) {
                if t < 0 {
                    continue;
                }
                known += 1;
                if d >= 0 {
                    valid += 1;
                    bad1 += u32::from((d - t).abs() > 16);
                }
            }
            semihosting::println!(
                "stereo width={} height={} ndisp={} window={} prefilter={} scratch_bytes={} match_instructions={} depth_instructions={} valid={} known={} bad1={} portable_instructions={} identical={}",
                W,
                H,
                NDISP,
                window,
                if matches!(prefilter, Prefilter::None) { "none" } else { "dog" },
                scratch_bytes,
                (t1 - t0) * INSTRUCTIONS_PER_TICK,
                (t2 - t1) * INSTRUCTIONS_PER_TICK,
                valid,
                known,
                bad1,
                (t4 - t3) * INSTRUCTIONS_PER_TICK,
                u8::from(identical)
            );
            let _ = stats;
        }
        halt(0)
    }
}

#[cfg(not(target_os = "none"))]
fn main() {
    eprintln!(
        "stereo_bench runs on the MCU: harmonic-sim fw-budget --stereo builds it for \
         thumbv7em-none-eabihf and runs it under QEMU"
    );
    std::process::exit(2);
}
