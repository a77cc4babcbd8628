//! Small-speckle removal (seed thesis Sec. 3.2.5; OpenCV's `filterSpeckles`).
//!
//! Valid pixels are joined to their 8 neighbours whose disparity differs by at most
//! `max_diff` (1/16 px). Connected components of at most `max_size` pixels are isolated
//! mismatches, not surfaces, and are invalidated.
//!
//! Memory stays bounded by the speckle size, not the image: a breadth-first search stops as
//! soon as its component grows past `max_size` (or reaches a pixel already known to belong to
//! a large component) and marks what it found as large, so every pixel is queued once and the
//! queue never holds more than `max_size + 1` entries. Two bits per pixel record "seen" and
//! "large".

use super::limits::{StereoError, INVALID_DISPARITY};

/// `u32` words [`filter_speckles`] needs as scratch for a `width × height` image and components
/// of up to `max_size` pixels: two bitmaps of one bit per pixel and the search queue.
pub fn speckle_scratch_words(width: u16, height: u16, max_size: u16) -> usize {
    let pixels = usize::from(width) * usize::from(height);
    2 * pixels.div_ceil(32) + usize::from(max_size) + 1
}

fn bit(words: &[u32], i: usize) -> bool {
    words.get(i >> 5).is_some_and(|w| w & (1 << (i & 31)) != 0)
}

fn set_bit(words: &mut [u32], i: usize) {
    if let Some(w) = words.get_mut(i >> 5) {
        *w |= 1 << (i & 31);
    }
}

/// Invalidates (sets to [`INVALID_DISPARITY`]) every 8-connected component of valid
/// (non-negative) disparities of at most `max_size` pixels, where neighbours join when their
/// disparities differ by at most `max_diff`. Returns the number of pixels invalidated.
/// `max_size` 0 does nothing.
pub fn filter_speckles(
    disparity: &mut [i16],
    width: u16,
    height: u16,
    max_size: u16,
    max_diff: u16,
    scratch: &mut [u32],
) -> Result<u32, StereoError> {
    let (w, h) = (usize::from(width), usize::from(height));
    if w == 0 || h == 0 {
        return Err(StereoError::EmptyImage);
    }
    if disparity.len() != w * h {
        return Err(StereoError::SizeMismatch);
    }
    if max_size == 0 {
        return Ok(0);
    }
    if scratch.len() < speckle_scratch_words(width, height, max_size) {
        return Err(StereoError::ScratchTooSmall);
    }
    let words = (w * h).div_ceil(32);
    let (seen, rest) = scratch.split_at_mut(words);
    let (large, queue) = rest.split_at_mut(words);
    seen.fill(0);
    large.fill(0);
    let limit = usize::from(max_size);
    let max_diff = i32::from(max_diff);
    let mut removed = 0u32;
    // Queue entries pack a pixel as `y << 16 | x` (both fit in 16 bits).
    let index = |x: usize, y: usize| y * w + x;
    for sy in 0..h {
        for sx in 0..w {
            let seed = index(sx, sy);
            if bit(seen, seed) || disparity.get(seed).is_none_or(|&d| d < 0) {
                continue;
            }
            set_bit(seen, seed);
            let Some(first) = queue.first_mut() else {
                return Err(StereoError::ScratchTooSmall);
            };
            *first = ((sy as u32) << 16) | sx as u32;
            let (mut len, mut head) = (1usize, 0usize);
            let mut is_large = len > limit;
            'search: while head < len && !is_large {
                let packed = queue.get(head).copied().unwrap_or(0);
                head += 1;
                let (px, py) = ((packed & 0xFFFF) as usize, (packed >> 16) as usize);
                let dp = i32::from(disparity.get(index(px, py)).copied().unwrap_or(INVALID_DISPARITY));
                for (dx, dy) in [
                    (-1, -1),
                    (0, -1),
                    (1, -1),
                    (-1, 0),
                    (1, 0),
                    (-1, 1),
                    (0, 1),
                    (1, 1),
                ] {
                    let (nx, ny) = (px as isize + dx, py as isize + dy);
                    if nx < 0 || ny < 0 || nx as usize >= w || ny as usize >= h {
                        continue;
                    }
                    let (nx, ny) = (nx as usize, ny as usize);
                    let n = index(nx, ny);
                    let dn = i32::from(disparity.get(n).copied().unwrap_or(INVALID_DISPARITY));
                    if dn < 0 || (dn - dp).abs() > max_diff {
                        continue;
                    }
                    if bit(large, n) {
                        is_large = true;
                        break 'search;
                    }
                    if bit(seen, n) {
                        continue;
                    }
                    set_bit(seen, n);
                    if let Some(q) = queue.get_mut(len) {
                        *q = ((ny as u32) << 16) | nx as u32;
                    }
                    len += 1;
                    if len > limit {
                        is_large = true;
                        break 'search;
                    }
                }
            }
            let members = queue.get(..len).unwrap_or(&[]);
            for &m in members {
                let i = index((m & 0xFFFF) as usize, (m >> 16) as usize);
                if is_large {
                    set_bit(large, i);
                } else if let Some(d) = disparity.get_mut(i) {
                    *d = INVALID_DISPARITY;
                    removed += 1;
                }
            }
        }
    }
    Ok(removed)
}
