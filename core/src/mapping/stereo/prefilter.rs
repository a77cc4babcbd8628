//! The Difference-of-Gaussians prefilter (seed thesis Sec. 3.2.4), streamed row by row.
//!
//! DoG approximates a Laplacian of Gaussian: a band-pass that removes the brightness offset
//! between the two cameras and flat shading, and keeps the texture matching needs. It is
//! separable, so each Gaussian costs `2·(2k+1)` multiply-adds per pixel for radius `k`.
//!
//! Fixed point: kernel weights sum to 256. The horizontal pass keeps `value·256` in a `u16`
//! (at most 255·256), the vertical pass `value·65536` in a `u32`. The band-pass response
//! `G(σ_small) − G(σ_large)` is scaled by [`DOG_GAIN`], clamped to ±[`DOG_CAP`] and offset to
//! 128, so the matcher sees a `u8` image again (OpenCV's `preFilterCap` does the same).
//! Rows past the top and bottom edge replicate the edge row; columns replicate the edge column.

/// Largest kernel radius, pixels: `ceil(3·σ_large)` must not exceed it.
pub const MAX_RADIUS: usize = 8;
/// Gain applied to the band-pass response before it is clamped to `u8`.
pub const DOG_GAIN: i32 = 4;
/// The response is clamped to ±`DOG_CAP` around 128.
pub const DOG_CAP: i32 = 127;

/// Integer Gaussian weights for offsets `-radius..=radius`, summing to 256.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Kernel {
    weights: [u16; 2 * MAX_RADIUS + 1],
    radius: usize,
}

impl Kernel {
    /// A normalised Gaussian of standard deviation `sigma` truncated at `radius`.
    pub(crate) fn gaussian(sigma: f32, radius: usize) -> Self {
        let mut real = [0f32; 2 * MAX_RADIUS + 1];
        let mut total = 0f32;
        for (i, w) in real.iter_mut().enumerate().take(2 * radius + 1) {
            let x = i as f32 - radius as f32;
            *w = libm::expf(-x * x / (2.0 * sigma * sigma));
            total += *w;
        }
        let mut weights = [0u16; 2 * MAX_RADIUS + 1];
        let mut sum = 0u32;
        for (w, r) in weights.iter_mut().zip(real.iter()).take(2 * radius + 1) {
            *w = libm::roundf(256.0 * r / total) as u16;
            sum += u32::from(*w);
        }
        // Rounding may miss 256 by a few units: the centre weight takes the difference.
        if let Some(centre) = weights.get_mut(radius) {
            *centre = (i64::from(*centre) + 256 - i64::from(sum)).clamp(0, 256) as u16;
        }
        Self { weights, radius }
    }

    /// The weights, `2·radius + 1` of them.
    pub(crate) fn taps(&self) -> &[u16] {
        self.weights.get(..2 * self.radius + 1).unwrap_or(&[])
    }
}

/// Horizontal pass of one row: `out[x] = Σ w_i · row[clamp(x + i − r)]` (value·256).
///
/// The weights are symmetric (`w_i = w_{2r−i}`, [`Kernel::gaussian`]) and sum to 256, so away
/// from the edges the pass adds, for each distance `j`, `w_{r−j} · (row[x − j] + row[x + j])`
/// over the whole row at once into `out` (which cannot overflow: at most 255 · 256): half the
/// multiplies, and no clamping or indexing in the inner loops. Exactly the sum above.
pub(crate) fn horizontal(kernel: &Kernel, row: &[u8], out: &mut [u16]) {
    let r = kernel.radius;
    let taps = kernel.taps();
    let w = row.len().min(out.len());
    if w > 2 * r {
        let centre = taps.get(r).copied().unwrap_or(0);
        let inner = out.get_mut(r..w - r).unwrap_or(&mut []);
        for (o, &v) in inner.iter_mut().zip(row.get(r..).unwrap_or(&[])) {
            *o = centre.wrapping_mul(u16::from(v));
        }
        for j in 1..=r {
            let weight = taps.get(r - j).copied().unwrap_or(0);
            let (left, right) = (
                row.get(r - j..w - r - j).unwrap_or(&[]),
                row.get(r + j..w - r + j).unwrap_or(&[]),
            );
            for ((o, &a), &b) in inner.iter_mut().zip(left).zip(right) {
                *o = o.wrapping_add(weight.wrapping_mul(u16::from(a) + u16::from(b)));
            }
        }
    }
    let (near, far) = (r.min(out.len()), w.saturating_sub(r).max(r.min(out.len())));
    for x in (0..near).chain(far..out.len()) {
        if let Some(o) = out.get_mut(x) {
            *o = clamped(taps, row, x);
        }
    }
}

/// One pixel of the horizontal pass with the columns clamped to the row.
fn clamped(taps: &[u16], row: &[u8], x: usize) -> u16 {
    let last = row.len().saturating_sub(1);
    let r = taps.len() >> 1;
    let mut acc = 0u32;
    for (i, &w) in taps.iter().enumerate() {
        let at = (x + i).saturating_sub(r).min(last);
        acc += u32::from(w) * u32::from(row.get(at).copied().unwrap_or(0));
    }
    acc.min(u32::from(u16::MAX)) as u16
}

/// Vertical pass: `acc[x] = Σ w_i · rows(i)[x]` over the kernel's `2r + 1` rows (value·65536),
/// the symmetric pairs of rows added before they are weighted.
pub(crate) fn vertical<'r>(kernel: &Kernel, rows: impl Fn(usize) -> &'r [u16], acc: &mut [u32]) {
    let r = kernel.radius;
    let taps = kernel.taps();
    acc.fill(0);
    let centre = u32::from(taps.get(r).copied().unwrap_or(0));
    for (a, &v) in acc.iter_mut().zip(rows(r)) {
        *a = centre * u32::from(v);
    }
    for (i, &w) in taps.iter().enumerate().take(r) {
        let w = u32::from(w);
        for ((a, &lo), &hi) in acc.iter_mut().zip(rows(i)).zip(rows(2 * r - i)) {
            *a += w * (u32::from(lo) + u32::from(hi));
        }
    }
}

/// The band-pass response as a `u8` around 128, from both Gaussians' vertical passes at one
/// pixel (value·65536 each).
pub(crate) fn dog_pixel(small: u32, large: u32) -> u8 {
    // Both are value·65536; the difference fits an i32 (|·| < 2^24).
    let diff = small as i32 - large as i32;
    let scaled = (diff * DOG_GAIN + (1 << 15)) >> 16;
    (scaled.clamp(-DOG_CAP, DOG_CAP) + 128) as u8
}

/// Kernel radius for a DoG with the given large sigma.
pub(crate) fn radius_for(sigma_large: f32) -> usize {
    libm::ceilf(3.0 * sigma_large).max(1.0) as usize
}

#[cfg(test)]
mod tests {
    extern crate std;

    use super::*;
    use std::vec;
    use std::vec::Vec;

    #[test]
    fn kernels_sum_to_256_and_are_symmetric() {
        for (sigma, r) in [(0.5, 2), (1.0, 3), (1.6, 5), (2.6, 8)] {
            let k = Kernel::gaussian(sigma, r);
            let taps = k.taps();
            assert_eq!(taps.iter().map(|&w| u32::from(w)).sum::<u32>(), 256, "{sigma}");
            for i in 0..taps.len() {
                assert_eq!(taps[i], taps[taps.len() - 1 - i]);
            }
        }
    }

    /// The folded passes give exactly the plain weighted sums, rows shorter than the kernel
    /// and the edges included.
    #[test]
    fn folded_passes_are_the_plain_sums() {
        let mut seed = 0x9e37_79b9_u32;
        let mut next = || {
            seed ^= seed << 13;
            seed ^= seed >> 17;
            seed ^= seed << 5;
            seed
        };
        for (sigma, r) in [(0.5, 1), (1.0, 3), (1.6, 5), (2.6, 8)] {
            let k = Kernel::gaussian(sigma, r);
            for len in [1, 2, r, 2 * r, 2 * r + 1, 2 * r + 2, 40] {
                let row: Vec<u8> = (0..len).map(|_| next() as u8).collect();
                let mut out = vec![0u16; len];
                horizontal(&k, &row, &mut out);
                let plain: Vec<u16> = (0..len).map(|x| clamped(k.taps(), &row, x)).collect();
                assert_eq!(out, plain, "sigma {sigma} length {len}");
            }
            let rows: Vec<Vec<u16>> = (0..2 * r + 1)
                .map(|_| (0..30).map(|_| next() as u16).collect())
                .collect();
            let mut acc = vec![0u32; 30];
            vertical(&k, |i| &rows[i], &mut acc);
            for (x, &a) in acc.iter().enumerate() {
                let plain: u32 = k
                    .taps()
                    .iter()
                    .zip(&rows)
                    .map(|(&w, row)| u32::from(w) * u32::from(row[x]))
                    .sum();
                assert_eq!(a, plain, "sigma {sigma} column {x}");
            }
        }
    }

    #[test]
    fn flat_rows_give_a_flat_response() {
        let k = Kernel::gaussian(1.0, 5);
        let row = [77u8; 20];
        let mut out = [0u16; 20];
        horizontal(&k, &row, &mut out);
        assert!(out.iter().all(|&v| v == 77 * 256));
        assert_eq!(dog_pixel(77 * 65536, 77 * 65536), 128);
    }
}
