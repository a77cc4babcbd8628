//! Stereo block matching: rectified 8-bit image rows in, disparity (1/16 px) and depth (`u16`
//! millimetres) out — the seed thesis's "SAD5" matcher (Ch. 3), with no heap and memory
//! bounded by the image width times the disparity range.
//!
//! ## Pipeline
//!
//! 1. **Prefilter** (optional, [`Prefilter::DoG`]): Difference of Gaussians, the thesis's
//!    choice (Sec. 3.2.4), separable and streamed ([`prefilter`]).
//! 2. **Cost**: sum of absolute differences (SAD) between a window around the left pixel
//!    `(x, y)` and around the right pixel `(x − d, y)`, the left image being the reference.
//!    Hirschmüller's five-window variant (thesis Eq. 3.28): the cost is the centre window's
//!    SAD plus the two best of four neighbouring windows of the same size, centred diagonally
//!    half a window away, at `(x ± r, y ± r)` with `r = window / 2`. Near a depth edge the
//!    neighbours on the object's side win, which shrinks the foreground fattening of a single
//!    large window. The footprint of one match is therefore `2·window − 1` pixels square
//!    (21 × 21 for the default 11 × 11 windows).
//!    Window sums are running box sums, so the work is O(width · height · disparities) for any
//!    window size: per row, one vertical running sum over the last `2r + 1` rows is updated by
//!    one row in and one row out and summed horizontally with a running sum into a ring of the
//!    last `2r + 1` rows of window sums, from which the centre window (rows centred at `y`) and
//!    the neighbours (centred at `y ± r`) are read. The sums are packed two disparities to a
//!    32-bit word (`lanes`), so one add updates two; with the `dsp` feature on an Arm target
//!    (Cortex-M4/M7) the cost update takes four disparities per `UQSUB8`/`UXTAB16` step and
//!    the five-window combination two per `UADD16`/`USUB16`/`SEL` step, giving the portable
//!    code's sums and costs exactly ([`StereoMatcher::use_dsp`], [`dsp_agrees`]).
//! 3. **Winner takes all** over `d ∈ 0..num_disparities` (fewer near the left border, where
//!    the right window would leave the image).
//! 4. **Texture** (off by default): the mean horizontal gradient `|I(x+1) − I(x−1)|` of the
//!    (prefiltered) left image over the centre window must reach [`StereoParams::min_texture`].
//!    Flat regions are invalid rather than garbage without it: their costs tie across
//!    disparities, so the uniqueness test (5) rejects them. The old default of 2 grey levels
//!    after the DoG rejected a sixth of a real pair's pixels, most of them matched right
//!    (BENCHMARKS.md, "A real pair: Middlebury 2014 motorcycle").
//! 5. **Uniqueness** (thesis Eq. 3.29): the best cost `C1` and the best cost `C2` not adjacent
//!    to it must satisfy `C2 > C1 · (1 + uniqueness_percent / 100)`.
//! 6. **Sub-pixel**: a parabola through the minimum and its two neighbours.
//! 7. **Left–right consistency** (Fua): the right image's own winner for the matched right
//!    pixel `x − d`, taken from the same costs (`C_R(x_r, d) = C_L(x_r + d, d)`, exact for SAD),
//!    must lie within [`StereoParams::lr_max_diff`] pixels of `d`. Pixels the right camera
//!    cannot see (occlusions) fail it.
//! 8. **Speckle removal** ([`speckle`]): small 8-connected blobs of similar disparity are
//!    removed once the whole image is done.
//!
//! ## Conventions
//!
//! Disparity is `i16` in 1/16 px ([`DISPARITY_SCALE`], OpenCV's `StereoBM` convention);
//! invalid pixels hold [`INVALID_DISPARITY`] (−16, OpenCV's `(minDisparity − 1)·16`). Pixels
//! whose match footprint leaves the image — `2·r` = `window − 1` rows and columns on every
//! side — are invalid. Depth (`z = f·b/d`) is `u16` millimetres with 0 = no depth, as in
//! [`crate::mapping::camera`].
//!
//! ## Streaming and memory
//!
//! [`StereoMatcher::push_row`] takes one left and one right row at a time; the matcher keeps
//! only a ring of `3r + 2` prefiltered rows (plus `2k + 1` rows per Gaussian of radius `k`
//! for the prefilter), so a microcontroller never holds whole images. Output row `y` is
//! written into the caller's disparity image as soon as row `y + 2r` (plus the prefilter's
//! `k`) has arrived; [`StereoMatcher::finish`] writes the last rows and removes speckles.
//! All storage is borrowed ([`StereoScratch`], sized by [`scratch_size`]):
//!
//! - `u32`: `(2r + 2) · W · D₄ / 2` for the vertical window sums and the ring of `2r + 1`
//!   rows of window sums (`D₄`: the disparity range rounded up to a multiple of four, two to a
//!   word), `D₄ + 3 · W` per-row work (`+ 2 · W` with the prefilter), plus
//!   `2 · ⌈W·H/32⌉ + speckle_size + 1` for speckle removal (two bits per pixel; 0 without it);
//! - `u16`: `4 · (2k + 1) · W` with the DoG prefilter;
//! - `u8`: `2 · (3r + 2) · W` for the row rings.
//!
//! With `W` the width and `D` the disparity range: 100 × 100 px, 64 disparities, 11 × 11
//! windows and DoG (σ 1.0/1.6, k = 5) need 167 KiB (7 × 7 windows: 116 KiB); without the
//! speckle bitmaps, which grow with the height, the matcher's memory is `O(r · W · D)`. (Until
//! 2026-12-03 three vertical and three horizontal sums took `6 · W · D` halfwords, 93 KiB here,
//! and twice the work: the ring trades 74 KiB for half the instructions.)

mod lanes;
mod limits;
pub mod prefilter;
pub mod speckle;

pub use lanes::dsp_agrees;
pub use limits::{StereoError, DISPARITY_SCALE, INVALID_DISPARITY, MAX_DISPARITIES, MAX_WINDOW};
pub use speckle::{filter_speckles, speckle_scratch_words};

use prefilter::Kernel;

/// Optional prefilter applied to both images before matching.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Prefilter {
    /// Match the raw intensities.
    None,
    /// Difference of Gaussians `G(sigma_small) − G(sigma_large)` (thesis: ratio ≈ 1.6).
    DoG {
        /// The narrower Gaussian, pixels.
        sigma_small: f32,
        /// The wider Gaussian, pixels (greater than `sigma_small`).
        sigma_large: f32,
    },
}

impl Prefilter {
    /// The thesis's DoG with σ = 1.0 and 1.6 px.
    pub const DEFAULT_DOG: Prefilter = Prefilter::DoG {
        sigma_small: 1.0,
        sigma_large: 1.6,
    };

    /// Kernel radius, or 0 without a prefilter.
    pub fn radius(&self) -> Result<usize, StereoError> {
        match *self {
            Prefilter::None => Ok(0),
            Prefilter::DoG {
                sigma_small,
                sigma_large,
            } => {
                let ok = sigma_small.is_finite()
                    && sigma_large.is_finite()
                    && sigma_small > 0.0
                    && sigma_large > sigma_small;
                let radius = if ok { prefilter::radius_for(sigma_large) } else { 0 };
                if !ok || radius > prefilter::MAX_RADIUS {
                    return Err(StereoError::BadPrefilter);
                }
                Ok(radius)
            }
        }
    }
}

/// Matcher settings. [`StereoParams::new`] gives the defaults for an image size.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StereoParams {
    /// Image width, pixels.
    pub width: u16,
    /// Image height, pixels.
    pub height: u16,
    /// Disparities searched: `0..num_disparities` pixels.
    pub num_disparities: u16,
    /// Side of each of the five SAD windows, pixels (odd, 3..=[`MAX_WINDOW`]).
    pub window: u8,
    /// Uniqueness margin, percent: the best non-adjacent rival must cost more than the best
    /// by this much.
    pub uniqueness_percent: u8,
    /// Left–right check tolerance, pixels; `None` turns the check off.
    pub lr_max_diff: Option<u8>,
    /// Minimum mean horizontal gradient of the (prefiltered) left image over the centre
    /// window, grey levels; 0 (the default) turns the test off.
    pub min_texture: u8,
    /// Blobs of at most this many pixels are removed; 0 turns speckle removal off.
    pub speckle_size: u16,
    /// Neighbours belong to one blob when their disparities differ by at most this, 1/16 px.
    pub speckle_range: u16,
    /// Prefilter.
    pub prefilter: Prefilter,
}

impl StereoParams {
    /// Defaults for a `width × height` pair: 11 × 11 windows, 10 % uniqueness, left–right
    /// tolerance 1 px, no texture threshold, speckles up to 1/256 of the image (20–2000 px)
    /// within 1 px, DoG σ 1.0/1.6.
    pub fn new(width: u16, height: u16, num_disparities: u16) -> Self {
        let pixels = u32::from(width) * u32::from(height);
        Self {
            width,
            height,
            num_disparities,
            window: 11,
            uniqueness_percent: 10,
            lr_max_diff: Some(1),
            min_texture: 0,
            speckle_size: (pixels >> 8).clamp(20, 2000) as u16,
            speckle_range: DISPARITY_SCALE as u16,
            prefilter: Prefilter::DEFAULT_DOG,
        }
    }

    /// Half the window side, `r`.
    fn half(&self) -> usize {
        usize::from(self.window >> 1)
    }

    /// Rows above and below an output row that its disparity depends on: the match
    /// footprint's `2r` plus the prefilter's radius. A band of rows matched on its own with
    /// this many more rows on each side (clipped to the image) gets exactly the disparities
    /// the whole image gives those rows, before speckle removal.
    pub fn context_rows(&self) -> Result<usize, StereoError> {
        Ok(2 * self.half() + self.prefilter.radius()?)
    }

    /// Checks every parameter.
    pub fn validate(&self) -> Result<(), StereoError> {
        if self.width == 0 || self.height == 0 {
            return Err(StereoError::EmptyImage);
        }
        if self.num_disparities == 0
            || self.num_disparities > self.width
            || self.num_disparities > MAX_DISPARITIES
        {
            return Err(StereoError::BadDisparityRange);
        }
        if self.window & 1 == 0 || self.window < 3 || self.window > MAX_WINDOW {
            return Err(StereoError::BadWindow);
        }
        let footprint = 2 * u16::from(self.window) - 1;
        if footprint > self.width || footprint > self.height {
            return Err(StereoError::ImageTooSmall);
        }
        self.prefilter.radius()?;
        Ok(())
    }
}

/// Scratch a matcher needs, in elements of each type (see the [module docs](self)).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ScratchSize {
    /// `u8` elements: the rings of prefiltered rows.
    pub bytes: usize,
    /// `u16` elements: the prefilter's rows.
    pub halfwords: usize,
    /// `u32` elements: window sums (two disparities a word), per-row work and speckle removal.
    pub words: usize,
}

impl ScratchSize {
    /// Total size in bytes.
    pub fn total_bytes(&self) -> usize {
        self.bytes + 2 * self.halfwords + 4 * self.words
    }
}

/// The scratch [`StereoMatcher::new`] needs for `params` (which it validates).
///
/// It grows as `W · D` (window sums) plus `W` times the window and prefilter sizes (row
/// rings), plus two bits per pixel for speckle removal.
pub fn scratch_size(params: &StereoParams) -> Result<ScratchSize, StereoError> {
    params.validate()?;
    let (w, d) = (usize::from(params.width), usize::from(params.num_disparities));
    let r = params.half();
    let k = params.prefilter.radius()?;
    let (filter, dog) = if k > 0 {
        (4 * (2 * k + 1) * w, 2 * w)
    } else {
        (0, 0)
    };
    let speckle = if params.speckle_size > 0 {
        speckle_scratch_words(params.width, params.height, params.speckle_size)
    } else {
        0
    };
    let lanes = lanes::lanes(d);
    Ok(ScratchSize {
        bytes: 2 * (3 * r + 2) * w,
        halfwords: filter,
        words: (2 * r + 2) * w * (lanes >> 1) + lanes + 3 * w + dog + speckle,
    })
}

/// Storage lent to a [`StereoMatcher`], at least [`scratch_size`] of each type.
pub struct StereoScratch<'a> {
    /// At least [`ScratchSize::bytes`] elements.
    pub bytes: &'a mut [u8],
    /// At least [`ScratchSize::halfwords`] elements.
    pub halfwords: &'a mut [u16],
    /// At least [`ScratchSize::words`] elements.
    pub words: &'a mut [u32],
}

/// What happened to the pixels of one image.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct StereoStats {
    /// Pixels with a valid disparity.
    pub valid: u32,
    /// Pixels whose match footprint leaves the image.
    pub border: u32,
    /// Rejected by the texture test.
    pub textureless: u32,
    /// Rejected by the uniqueness test.
    pub ambiguous: u32,
    /// Rejected by the left–right check.
    pub inconsistent: u32,
    /// Removed as speckles.
    pub speckles: u32,
}

/// Splits the first `n` elements off `slice`.
fn take<'a, T>(slice: &mut &'a mut [T], n: usize) -> Result<&'a mut [T], StereoError> {
    if slice.len() < n {
        return Err(StereoError::ScratchTooSmall);
    }
    let (head, tail) = core::mem::take(slice).split_at_mut(n);
    *slice = tail;
    Ok(head)
}

/// `i mod n` for the row rings (one division per row).
fn ring_slot(i: usize, n: usize) -> usize {
    i.checked_rem(n).unwrap_or(0)
}

/// A marker in the per-row winner array: no match at this column.
const NO_MATCH: u32 = u32::MAX;
/// Packed costs hold the disparity in the low bits (`cost << DISP_BITS | d`).
const DISP_BITS: u32 = 10;
const DISP_MASK: u32 = (1 << DISP_BITS) - 1;

/// The streaming matcher: push rows, then [`finish`](Self::finish).
pub struct StereoMatcher<'a> {
    params: StereoParams,
    w: usize,
    h: usize,
    nd: usize,
    r: usize,
    ring_rows: usize,
    kernels: Option<(Kernel, Kernel, usize)>,
    /// Words per column of packed sums ([`lanes`]).
    cw: usize,
    /// Vertical window sums over the last `2r + 1` rows (`[x][lanes]`).
    vsum: &'a mut [u32],
    /// Ring of `2r + 1` rows of window sums (`[row][x][lanes]`): the vertical sums summed
    /// horizontally, the row being the window's top row.
    boxes: &'a mut [u32],
    /// Use the DSP instructions where the build has them.
    dsp: bool,
    /// Prefilter rings: left small, left large, right small, right large.
    filter: [&'a mut [u16]; 4],
    ring_left: &'a mut [u8],
    ring_right: &'a mut [u8],
    pixel_costs: &'a mut [u32],
    /// The right image's best packed cost per pixel, right to left: `[w − 1 − x_r]`, so that
    /// a left pixel's disparities run forwards through it.
    right_best: &'a mut [u32],
    left_best: &'a mut [u32],
    texture: &'a mut [u32],
    /// The prefilter's vertical sums of one row.
    dog_small: &'a mut [u32],
    dog_large: &'a mut [u32],
    speckle: &'a mut [u32],
    rows_in: usize,
    rows_filtered: usize,
    stats: StereoStats,
    /// Output rows `[from, to)` the statistics count ([`StereoMatcher::count_rows`]).
    counted: (usize, usize),
}

impl<'a> StereoMatcher<'a> {
    /// Validates `params` and lays out `scratch`.
    pub fn new(params: StereoParams, scratch: StereoScratch<'a>) -> Result<Self, StereoError> {
        let need = scratch_size(&params)?;
        if scratch.bytes.len() < need.bytes
            || scratch.halfwords.len() < need.halfwords
            || scratch.words.len() < need.words
        {
            return Err(StereoError::ScratchTooSmall);
        }
        let (w, h, nd) = (
            usize::from(params.width),
            usize::from(params.height),
            usize::from(params.num_disparities),
        );
        let r = params.half();
        let ring_rows = 3 * r + 2;
        let k = params.prefilter.radius()?;
        let kernels = match params.prefilter {
            Prefilter::None => None,
            Prefilter::DoG {
                sigma_small,
                sigma_large,
            } => Some((
                Kernel::gaussian(sigma_small, k),
                Kernel::gaussian(sigma_large, k),
                k,
            )),
        };
        let (mut b, mut hw, mut wd) = (scratch.bytes, scratch.halfwords, scratch.words);
        let frows = if k > 0 { (2 * k + 1) * w } else { 0 };
        let dog = if k > 0 { w } else { 0 };
        let lanes = lanes::lanes(nd);
        let cw = lanes >> 1;
        let speckle_words = need.words - ((2 * r + 2) * w * cw + lanes + 3 * w + 2 * dog);
        Ok(Self {
            params,
            w,
            h,
            nd,
            r,
            ring_rows,
            kernels,
            cw,
            vsum: take(&mut wd, w * cw)?,
            boxes: take(&mut wd, (2 * r + 1) * w * cw)?,
            dsp: true,
            filter: [
                take(&mut hw, frows)?,
                take(&mut hw, frows)?,
                take(&mut hw, frows)?,
                take(&mut hw, frows)?,
            ],
            ring_left: take(&mut b, ring_rows * w)?,
            ring_right: take(&mut b, ring_rows * w)?,
            pixel_costs: take(&mut wd, lanes)?,
            right_best: take(&mut wd, w)?,
            left_best: take(&mut wd, w)?,
            texture: take(&mut wd, w)?,
            dog_small: take(&mut wd, dog)?,
            dog_large: take(&mut wd, dog)?,
            speckle: take(&mut wd, speckle_words)?,
            rows_in: 0,
            rows_filtered: 0,
            stats: StereoStats::default(),
            counted: (0, usize::MAX),
        }
        .reset())
    }

    /// Starts a new image pair (the parameters stay).
    pub fn reset(mut self) -> Self {
        self.restart();
        self
    }

    /// Starts a new image pair in place.
    pub fn restart(&mut self) {
        self.vsum.fill(0);
        self.texture.fill(0);
        self.rows_in = 0;
        self.rows_filtered = 0;
        self.stats = StereoStats::default();
    }

    /// Chooses the Cortex-M4/M7 DSP instructions for the per-row cost update (the default, in
    /// builds with the `dsp` feature for an Arm target) or the portable code (`false`; the
    /// only path elsewhere). Both give the same disparities, bit for bit; this is for checking
    /// that on the target.
    pub fn use_dsp(&mut self, on: bool) {
        self.dsp = on;
    }

    /// The parameters.
    pub fn params(&self) -> &StereoParams {
        &self.params
    }

    /// Counts only output rows `from..to` in the statistics (all rows by default). For a band
    /// of a larger image matched on its own — its rows plus [`StereoParams::context_rows`] above
    /// and below, which give the band's rows exactly the whole image's disparities — the
    /// overlap rows belong to the neighbouring bands, so counting only the band's own rows
    /// makes the bands' statistics add up to the whole image's (speckles and `valid` apart,
    /// which the caller takes from one speckle pass over the joined image).
    pub fn count_rows(&mut self, from: usize, to: usize) {
        self.counted = (from, to);
    }

    fn counts(&self, row: usize) -> bool {
        row >= self.counted.0 && row < self.counted.1
    }

    /// Rows of the disparity image written so far (all rows above this one are final, except
    /// for speckle removal in [`finish`](Self::finish)).
    pub fn rows_done(&self) -> usize {
        self.rows_filtered.saturating_sub(2 * self.r)
    }

    /// Feeds the next row of both images (`width` pixels each) and writes every disparity row
    /// that became available into `disparity` (`width × height`, row-major).
    pub fn push_row(&mut self, left: &[u8], right: &[u8], disparity: &mut [i16]) -> Result<(), StereoError> {
        if left.len() != self.w || right.len() != self.w || disparity.len() != self.w * self.h {
            return Err(StereoError::SizeMismatch);
        }
        if self.rows_in >= self.h {
            return Err(StereoError::RowCount);
        }
        let row = self.rows_in;
        self.rows_in += 1;
        match self.kernels {
            None => {
                self.store_row(row, left, right);
                self.ingest(row, disparity);
            }
            Some((small, large, k)) => {
                let frows = 2 * k + 1;
                let slot = ring_slot(row, frows) * self.w;
                let [ls, ll, rs, rl] = &mut self.filter;
                for (kernel, image, ring) in [
                    (&small, left, &mut **ls),
                    (&large, left, &mut **ll),
                    (&small, right, &mut **rs),
                    (&large, right, &mut **rl),
                ] {
                    if let Some(out) = ring.get_mut(slot..slot + self.w) {
                        prefilter::horizontal(kernel, image, out);
                    }
                }
                if row >= k {
                    self.filter_row(row - k);
                    self.ingest(row - k, disparity);
                }
            }
        }
        Ok(())
    }

    /// Writes the remaining rows, removes speckles and returns what happened to the pixels.
    /// Every row must have been pushed. The matcher can then [`restart`](Self::restart).
    pub fn finish(&mut self, disparity: &mut [i16]) -> Result<StereoStats, StereoError> {
        if disparity.len() != self.w * self.h {
            return Err(StereoError::SizeMismatch);
        }
        if self.rows_in != self.h {
            return Err(StereoError::RowCount);
        }
        while self.rows_filtered < self.h {
            let p = self.rows_filtered;
            self.filter_row(p);
            self.ingest(p, disparity);
        }
        // Rows whose footprint leaves the bottom edge.
        let first = self.h.saturating_sub(2 * self.r);
        if let Some(tail) = disparity.get_mut(first * self.w..) {
            tail.fill(INVALID_DISPARITY);
        }
        let counted_tail = (first..self.h).filter(|&row| self.counts(row)).count();
        self.stats.border += (counted_tail * self.w) as u32;
        let removed = filter_speckles(
            disparity,
            self.params.width,
            self.params.height,
            self.params.speckle_size,
            self.params.speckle_range,
            self.speckle,
        )?;
        self.stats.speckles = removed;
        self.stats.valid = disparity
            .chunks_exact(self.w)
            .enumerate()
            .filter(|&(row, _)| self.counts(row))
            .map(|(_, row)| row.iter().filter(|&&d| d >= 0).count() as u32)
            .sum();
        Ok(self.stats)
    }

    /// Vertical DoG pass for row `p` from the prefilter rings (rows clamped to the image) into
    /// the matcher's row rings.
    fn filter_row(&mut self, p: usize) {
        let Some((small, large, k)) = self.kernels else {
            return;
        };
        let (w, h) = (self.w, self.h);
        let slot = ring_slot(p, self.ring_rows) * w;
        let frows = 2 * k + 1;
        let [ls, ll, rs, rl] = &self.filter;
        for (ring_small, ring_large, out) in [
            (&**ls, &**ll, self.ring_left.get_mut(slot..slot + w)),
            (&**rs, &**rl, self.ring_right.get_mut(slot..slot + w)),
        ] {
            let Some(out) = out else { continue };
            for (kernel, ring, acc) in [
                (&small, ring_small, &mut *self.dog_small),
                (&large, ring_large, &mut *self.dog_large),
            ] {
                let rows = |i: usize| {
                    let at = ring_slot((p + i).saturating_sub(k).min(h - 1), frows) * w;
                    ring.get(at..at + w).unwrap_or(&[])
                };
                prefilter::vertical(kernel, rows, acc);
            }
            for (o, (&a, &b)) in out
                .iter_mut()
                .zip(self.dog_small.iter().zip(self.dog_large.iter()))
            {
                *o = prefilter::dog_pixel(a, b);
            }
        }
        self.rows_filtered = p + 1;
    }

    /// Copies a raw row into the rings (no prefilter).
    fn store_row(&mut self, row: usize, left: &[u8], right: &[u8]) {
        let slot = ring_slot(row, self.ring_rows) * self.w;
        if let Some(l) = self.ring_left.get_mut(slot..slot + self.w) {
            l.copy_from_slice(left);
        }
        if let Some(r) = self.ring_right.get_mut(slot..slot + self.w) {
            r.copy_from_slice(right);
        }
        self.rows_filtered = row + 1;
    }

    fn ring_row(ring: &[u8], row: usize, ring_rows: usize, w: usize) -> &[u8] {
        let slot = ring_slot(row, ring_rows) * w;
        ring.get(slot..slot + w).unwrap_or(&[])
    }

    /// Prefiltered row `p` is in the rings: update the running sums and write output row
    /// `p − 2r`.
    fn ingest(&mut self, p: usize, disparity: &mut [i16]) {
        let (w, cw, r, rr) = (self.w, self.cw, self.r, self.ring_rows);
        let win = 2 * r + 1;
        // Vertical sums over rows p − 2r..=p, then the window sums of that band of rows.
        let (ln, rn) = (
            Self::ring_row(self.ring_left, p, rr, w),
            Self::ring_row(self.ring_right, p, rr, w),
        );
        match p.checked_sub(win) {
            None => lanes::add_row(self.vsum, cw, ln, rn),
            Some(sub) => {
                let (lo, ro) = (
                    Self::ring_row(self.ring_left, sub, rr, w),
                    Self::ring_row(self.ring_right, sub, rr, w),
                );
                lanes::slide_row(self.vsum, cw, [ln, rn, lo, ro], self.dsp);
            }
        }
        if let Some(top) = p.checked_sub(2 * r) {
            let slot = ring_slot(top, win) * w * cw;
            if let Some(boxes) = self.boxes.get_mut(slot..slot + w * cw) {
                lanes::box_row(self.vsum, boxes, w, cw, r);
            }
        }
        // Texture: vertical sums of the left gradient over the centre window's rows.
        if let Some(add) = p.checked_sub(r) {
            let new = Self::ring_row(self.ring_left, add, rr, w);
            let old = add
                .checked_sub(win)
                .map(|s| Self::ring_row(self.ring_left, s, rr, w));
            for (x, t) in self.texture.iter_mut().enumerate() {
                *t = t.wrapping_add(gradient(new, x));
                if let Some(old) = old {
                    *t = t.wrapping_sub(gradient(old, x));
                }
            }
        }
        let Some(y) = p.checked_sub(2 * r) else { return };
        let Some(out) = disparity.get_mut(y * w..(y + 1) * w) else {
            return;
        };
        let before = self.stats;
        if y < 2 * r {
            out.fill(INVALID_DISPARITY);
            self.stats.border += w as u32;
        } else {
            self.match_row(y, out);
        }
        if !self.counts(y) {
            self.stats = before;
        }
    }

    /// Matches output row `y` (`2r ≤ y`) from the ring of window sums: the centre windows are
    /// row `y − r`'s sums, the neighbours rows `y − 2r` and `y`'s.
    fn match_row(&mut self, y: usize, out: &mut [i16]) {
        let (w, nd, r, cw) = (self.w, self.nd, self.r, self.cw);
        let win = 2 * r + 1;
        let row = |top: usize| {
            let slot = ring_slot(top, win) * w * cw;
            self.boxes.get(slot..slot + w * cw).unwrap_or(&[])
        };
        let (top, mid, bottom) = (row(y - 2 * r), row(y - r), row(y));
        out.fill(INVALID_DISPARITY);
        self.right_best.fill(u32::MAX);
        self.left_best.fill(NO_MATCH);
        self.stats.border += (4 * r) as u32;
        let min_texture = u32::from(self.params.min_texture) * (win * win) as u32;
        let uniq = u64::from(self.params.uniqueness_percent) + 100;
        // Texture of the centre window at x: running horizontal sum of the vertical sums.
        let mut tex: u32 = self.texture.iter().skip(r).take(2 * r).sum();
        for x in 2 * r..w - 2 * r {
            tex = tex
                .wrapping_add(self.texture.get(x + r).copied().unwrap_or(0))
                .wrapping_sub(if x > 2 * r {
                    self.texture.get(x - r - 1).copied().unwrap_or(0)
                } else {
                    0
                });
            let dmax = (nd - 1).min(x - 2 * r);
            // Five-window costs for d = 0..=dmax (whole groups of four lanes; the lanes past
            // dmax are never read), then the winner and the right image's winners.
            let groups = (dmax >> 2) + 1;
            let parts = [
                column(mid, x, cw),
                column(top, x - r, cw),
                column(top, x + r, cw),
                column(bottom, x - r, cw),
                column(bottom, x + r, cw),
            ];
            lanes::combine(parts, self.pixel_costs, groups, win, self.dsp);
            let costs = self.pixel_costs.get(..=dmax).unwrap_or(&[]);
            let mut best = u32::MAX;
            let from = w - 1 - x;
            let right = self.right_best.get_mut(from..=from + dmax).unwrap_or(&mut []);
            for (d, (&c, slot)) in costs.iter().zip(right.iter_mut()).enumerate() {
                let packed = (c << DISP_BITS) | d as u32;
                best = best.min(packed);
                *slot = (*slot).min(packed);
            }
            let d1 = (best & DISP_MASK) as usize;
            let c1 = best >> DISP_BITS;
            if tex < min_texture {
                self.stats.textureless += 1;
                continue;
            }
            // The best cost not adjacent to d1: below d1 − 1 and above d1 + 1.
            let below = costs.get(..d1.saturating_sub(1)).unwrap_or(&[]);
            let above = costs.get(d1 + 2..).unwrap_or(&[]);
            let rival = |m: u32, &c: &u32| m.min(c);
            let c2 = (below.len() + above.len() > 0)
                .then(|| above.iter().fold(below.iter().fold(u32::MAX, rival), rival));
            if c2.is_some_and(|c2| u64::from(c2) * 100 <= u64::from(c1) * uniq) {
                self.stats.ambiguous += 1;
                continue;
            }
            let mut disparity = d1 as f32;
            if d1 > 0 && d1 < dmax {
                let cm = costs.get(d1 - 1).copied().unwrap_or(c1);
                let cp = costs.get(d1 + 1).copied().unwrap_or(c1);
                let curvature = (cm + cp).saturating_sub(2 * c1);
                if curvature > 0 {
                    let offset = (cm as f32 - cp as f32) / (2.0 * curvature as f32);
                    disparity += offset.clamp(-0.5, 0.5);
                }
            }
            if let Some(o) = out.get_mut(x) {
                *o = libm::roundf(disparity * f32::from(DISPARITY_SCALE)) as i16;
            }
            if let Some(l) = self.left_best.get_mut(x) {
                *l = d1 as u32;
            }
        }
        // Left–right consistency.
        let Some(tolerance) = self.params.lr_max_diff else {
            return;
        };
        for (x, (&d1, o)) in self.left_best.iter().zip(out.iter_mut()).enumerate() {
            if d1 == NO_MATCH {
                continue;
            }
            let dr = self
                .right_best
                .get(w - 1 - (x - d1 as usize))
                .map_or(u32::MAX, |&p| p & DISP_MASK);
            if dr.abs_diff(d1) > u32::from(tolerance) {
                *o = INVALID_DISPARITY;
                self.stats.inconsistent += 1;
            }
        }
    }
}

/// Column `c` of a row of packed sums, `cw` words a column.
#[inline(always)]
fn column(sums: &[u32], c: usize, cw: usize) -> &[u32] {
    sums.get(c * cw..(c + 1) * cw).unwrap_or(&[])
}

/// `|I(x+1) − I(x−1)|`, 0 at the image edge.
fn gradient(row: &[u8], x: usize) -> u32 {
    match (x.checked_sub(1).and_then(|a| row.get(a)), row.get(x + 1)) {
        (Some(&a), Some(&b)) => u32::from(a.abs_diff(b)),
        _ => 0,
    }
}

/// Matches a whole image pair (`width × height` each, row-major) into `disparity` through
/// the streaming matcher: exactly what pushing the rows one by one gives.
pub fn match_images(
    params: StereoParams,
    left: &[u8],
    right: &[u8],
    scratch: StereoScratch<'_>,
    disparity: &mut [i16],
) -> Result<StereoStats, StereoError> {
    let mut matcher = StereoMatcher::new(params, scratch)?;
    let (w, h) = (usize::from(params.width), usize::from(params.height));
    if left.len() != w * h || right.len() != w * h {
        return Err(StereoError::SizeMismatch);
    }
    for (l, r) in left.chunks_exact(w).zip(right.chunks_exact(w)) {
        matcher.push_row(l, r, disparity)?;
    }
    matcher.finish(disparity)
}

/// Focal length and baseline of a rectified pair: disparity ↔ depth.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StereoGeometry {
    focal_px: f32,
    baseline_m: f32,
}

impl StereoGeometry {
    /// Checked constructor: both finite and positive.
    pub fn new(focal_px: f32, baseline_m: f32) -> Result<Self, StereoError> {
        if !(focal_px.is_finite() && baseline_m.is_finite() && focal_px > 0.0 && baseline_m > 0.0) {
            return Err(StereoError::BadGeometry);
        }
        Ok(Self { focal_px, baseline_m })
    }

    /// Focal length, pixels.
    pub fn focal_px(&self) -> f32 {
        self.focal_px
    }

    /// Baseline, metres.
    pub fn baseline_m(&self) -> f32 {
        self.baseline_m
    }

    /// Disparity (pixels) of a point at depth `z` metres.
    pub fn disparity_px(&self, z: f32) -> f32 {
        self.focal_px * self.baseline_m / z
    }

    /// Depth in metres of a disparity in 1/16 px; `None` for invalid or zero disparity.
    pub fn depth_m(&self, disparity: i16) -> Option<f32> {
        (disparity > 0)
            .then(|| self.focal_px * self.baseline_m * f32::from(DISPARITY_SCALE) / f32::from(disparity))
    }

    /// Depth in millimetres, rounded, at most `u16::MAX − 1`; 0 for invalid or zero disparity.
    pub fn depth_mm(&self, disparity: i16) -> u16 {
        match self.depth_m(disparity) {
            Some(z) => libm::roundf(z * 1000.0).clamp(1.0, f32::from(u16::MAX - 1)) as u16,
            None => 0,
        }
    }
}

/// Converts a disparity image (1/16 px) into depth (`u16` mm, 0 = no depth).
pub fn disparity_to_depth_mm(
    geometry: &StereoGeometry,
    disparity: &[i16],
    depth_mm: &mut [u16],
) -> Result<(), StereoError> {
    if disparity.len() != depth_mm.len() {
        return Err(StereoError::SizeMismatch);
    }
    for (z, &d) in depth_mm.iter_mut().zip(disparity) {
        *z = geometry.depth_mm(d);
    }
    Ok(())
}

#[cfg(test)]
mod tests;
