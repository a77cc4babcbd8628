//! The fuzz targets' harnesses (fuzz/harness/*.rs, shared through `#[path]`) run over the
//! committed seed corpus and a few thousand deterministic pseudo-random inputs, so that
//! `cargo test --workspace` catches a regression the fuzzers would find. The fuzzers
//! themselves (`cargo +nightly fuzz run TARGET` in fuzz/) explore far more; see fuzz/README.md.
//!
//! `cargo test -p harmonic-tests --test fuzz_harness -- --ignored write_seed_corpus` rewrites
//! the seed corpus (fuzz/corpus/TARGET/seed-*).

#[path = "../../fuzz/harness/input.rs"]
mod input;
#[path = "../../fuzz/harness/integrate.rs"]
mod integrate;
#[path = "../../fuzz/harness/link.rs"]
mod link;
#[path = "../../fuzz/harness/mavlink.rs"]
mod mavlink;
#[path = "../../fuzz/harness/stereo.rs"]
mod stereo;

use std::fs;
use std::path::PathBuf;

/// Deterministic pseudo-random bytes (Knuth's MMIX LCG, high bits).
struct Lcg(u64);

impl Lcg {
    fn next(&mut self) -> u8 {
        self.0 = self
            .0
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (self.0 >> 56) as u8
    }
    fn bytes(&mut self, max_len: usize) -> Vec<u8> {
        let n = usize::from(self.next()) * max_len / 256;
        (0..n).map(|_| self.next()).collect()
    }
}

fn corpus_dir(target: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../fuzz/corpus")
        .join(target)
}

/// Runs `harness` over every committed seed of `target`, then over `random` inputs of up to
/// `max_len` bytes, and over each seed with a few bytes changed.
fn exercise(target: &str, harness: fn(&[u8]), random: usize, max_len: usize) {
    // Only the committed seeds: a local fuzzing run adds its own inputs to the same directory.
    let mut seeds: Vec<Vec<u8>> = fs::read_dir(corpus_dir(target))
        .unwrap_or_else(|e| panic!("{target} corpus: {e}"))
        .map(|entry| entry.unwrap().path())
        .filter(|p| {
            p.file_name()
                .is_some_and(|n| n.to_string_lossy().starts_with("seed-"))
        })
        .map(|p| fs::read(p).unwrap())
        .collect();
    seeds.sort();
    assert!(seeds.len() >= 3, "{target}: seed corpus missing");
    let mut rng = Lcg(0x5eed ^ target.len() as u64);
    for seed in &seeds {
        harness(seed);
        for _ in 0..8 {
            let mut mutated = seed.clone();
            for _ in 0..=usize::from(rng.next() % 4) {
                if let Some(len) = std::num::NonZeroUsize::new(mutated.len()) {
                    let at = usize::from(rng.next()) * 256 + usize::from(rng.next());
                    mutated[at % len.get()] ^= rng.next() | 1;
                }
            }
            harness(&mutated);
        }
    }
    for _ in 0..random {
        harness(&rng.bytes(max_len));
    }
}

#[test]
fn link_decoder_harness() {
    exercise("link_decoder", link::run, 3000, 1024);
}

#[test]
fn mavlink_input_harness() {
    exercise("mavlink_input", mavlink::run, 3000, 512);
}

#[test]
fn depth_integration_harness() {
    exercise("depth_integration", integrate::run, 1000, 512);
}

#[test]
fn stereo_matcher_harness() {
    exercise("stereo_matcher", stereo::run, 1500, 256);
}

/// Writes the seed corpus: a few well-formed inputs per target that reach deep into the
/// code under test (the fuzzers mutate from there).
#[test]
#[ignore = "rewrites fuzz/corpus; run by hand"]
fn write_seed_corpus() {
    let write = |target: &str, name: &str, bytes: &[u8]| {
        let dir = corpus_dir(target);
        fs::create_dir_all(&dir).unwrap();
        fs::write(dir.join(format!("seed-{name}")), bytes).unwrap();
    };
    // Link, scripted mode (odd first byte): whole images, a pose, a heartbeat, edits.
    write("link_decoder", "image", &[1, 1, 7, 12, 8, 3, 0x34, 0x12]);
    write(
        "link_decoder",
        "pose-image-heartbeat",
        &[
            1, 4, 9, 64, 64, 72, 64, 64, 64, 192, 1, 2, 9, 20, 10, 4, 0x11, 0x22, 5, 1, 0, 0, 0, 2, 0, 0, 0,
            3, 0, 0, 0, 4, 0, 0, 0,
        ],
    );
    write(
        "link_decoder",
        "damaged-images",
        &[
            3, 1, 1, 10, 6, 2, 9, 9, 7, 1, 2, 10, 6, 2, 9, 9, 3, 1, 10, 6, 2, 1, 6, 4, 0, 0, 0, 0, 40, 0, 0,
            1, 5, 7, 0, 2, 9,
        ],
    );
    write(
        "link_decoder",
        "raw",
        &[
            0, 0, 4, 1, 4, 1, 3, 0xE8, 3, 1, 2, 7, 1, 1, 2, 2, 1, 1, 1, 1, 1, 1, 5, 0x7F, 0x60, 0xE7, 0x5D, 0,
        ],
    );
    // MAVLink: a pose from the autopilot, polls over time, a goal, a stale stream, bad values.
    write(
        "mavlink_input",
        "pose-goal-poll",
        &[
            1, 0, 0, 0, 0, 140, 136, 120, 1, 0, 2, 128, 128, 200, 1, 0, 7, 5, 100, 0, 8, 9, 140, 140, 136,
            130, 7, 5, 200, 0, 7, 5, 0, 4, 7, 8,
        ],
    );
    write(
        "mavlink_input",
        "odometry-nan",
        &[
            3, 1, 140, 136, 120, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 1, 1, 8, 3, 1, 0, 0, 0xC0, 0x7F, 136,
            120, 132, 128, 128, 128, 1, 1, 8, 7,
        ],
    );
    write(
        "mavlink_input",
        "raw-and-heartbeat",
        &[
            0, 12, 0xFD, 9, 0, 0, 0, 1, 1, 0, 0, 0, 0xFE, 4, 1, 10, 0, 11, 6, 255, 255, 255, 255, 255, 255,
            255, 255, 7,
        ],
    );
    // Stereo: width, height, disparities, window, uniqueness, left-right, texture, speckle
    // size and range (u16 each), prefilter, image kind and seed, then the call script.
    write(
        "stereo_matcher",
        "shifted-dog",
        &[
            35, 19, 15, 9, 10, 2, 2, 20, 0, 16, 0, 1, 1, 7, 0, 0, 0, 3, 0, 1, 2,
        ],
    );
    write(
        "stereo_matcher",
        "noise-raw-filter",
        &[
            59, 25, 31, 8, 15, 0, 0, 0, 0, 0, 0, 0, 0, 99, 1, 0, 0, 0, 1, 2, 3, 0, 0,
        ],
    );
    let mut pixels = vec![26u8, 7, 7, 3, 0, 1, 0, 0, 0, 0, 0, 2, 30, 42, 3, 9, 9, 9, 9];
    pixels.extend((0..31 * 12).map(|i| (i * 37 % 251) as u8));
    write("stereo_matcher", "own-pixels", &pixels);
    write("stereo_matcher", "bad-window", &[20, 20, 8, 4]);
    // Integration: a 10×10×4 grid, a frame, a plan, a frame with a bad quaternion, a plan.
    let mut frame = vec![1u8];
    frame.extend_from_slice(&[
        8, 6, 128, 128, 128, 0, 8, 4, 0, 0, 0, 0, 192, 192, 128, 128, 128, 128, 128, 128, 128,
    ]);
    frame.extend(std::iter::repeat_n(100u8, 4 * 4));
    frame.extend_from_slice(&[128, 128, 128, 128, 128, 128, 128, 1]);
    write(
        "depth_integration",
        "frame",
        &[&[6, 6, 2, 128, 128, 128, 2, 1, 1, 10][..], &frame].concat(),
    );
    write(
        "depth_integration",
        "frame-plan",
        &[
            &[6, 6, 2, 128, 128, 128, 2, 1, 1, 40][..],
            &frame,
            &[0, 1, 128, 128, 128, 128],
            &frame,
        ]
        .concat(),
    );
    write(
        "depth_integration",
        "bad-values",
        &[
            &[
                6, 6, 2, 0, 0, 0xC0, 0x7F, 128, 128, 1, 0, 10, 0, 0, 0, 0x80, 0x7F, 128, 128, 3,
            ][..],
            &frame,
            &[0, 0, 0, 0, 0xC0, 0x7F, 128, 128, 128],
        ]
        .concat(),
    );
}
