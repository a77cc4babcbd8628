//! Window sums packed two disparities to a word, and the per-row cost update that fills them.
//!
//! A column of sums holds the `D` disparities rounded up to a multiple of four, in groups of
//! four: for `d₀ = 4g`, word `2g` holds `d₀` (low half) and `d₀ + 2` (high half), word
//! `2g + 1` holds `d₀ + 1` and `d₀ + 3`. That is the order the Cortex-M4's `UXTAB16` widens
//! the four bytes of a word into two halfword pairs, so the DSP path ([`slide_row`] with the
//! `dsp` feature on an Arm target) needs no shuffling.
//!
//! **Why plain 32-bit arithmetic is exact on two halves at once.** Every update is
//! `sum − old + new` where `old` is one of the terms `sum` holds, so `sum − old` never borrows
//! from the high half, and the result is a true window sum, at most `255 · 15²` = 57 375 <
//! 2¹⁶, so adding `new` never carries into it. Lanes for `d > x` (the right pixel would be
//! left of the image) are left alone; nothing reads them for a match.

/// Lanes per column: the disparity range rounded up to a whole group of four.
pub(crate) fn lanes(nd: usize) -> usize {
    nd.next_multiple_of(4)
}

/// Word and bit shift of disparity `d`'s lane within a column.
#[inline(always)]
fn slot(d: usize) -> (usize, u32) {
    (2 * (d >> 2) + (d & 1), (((d >> 1) & 1) as u32) << 4)
}

/// The right row's pixels `x − d` for `d ∈ 0..4·groups`, four to a word in group order, each
/// word holding `d₀..d₀ + 4` with `d₀` in the lowest byte (big-endian loads of
/// `right[x − d₀ − 3..=x − d₀]`).
#[inline(always)]
fn right_words(right: &[u8], x: usize, groups: usize) -> impl Iterator<Item = u32> + '_ {
    let span = right.get(x + 1 - 4 * groups..=x).unwrap_or(&[]);
    span.rchunks_exact(4)
        .map(|b| <[u8; 4]>::try_from(b).map_or(0, u32::from_be_bytes))
}

/// `|l − r|` for bytes.
#[inline(always)]
fn ad(l: u8, r: u8) -> u32 {
    u32::from(l.abs_diff(r))
}

/// `column[d] += |l − right[x − d]|` for every lane `d ≤ x`: the first rows of a window.
/// (Inlined: called from one place per frame; out of line it cost the firmware 0.2 M more
/// instructions a frame, 0.8 %.)
#[inline(always)]
pub(crate) fn add_row(sums: &mut [u32], cw: usize, left: &[u8], right: &[u8]) {
    for (x, (column, &l)) in sums.chunks_exact_mut(cw).zip(left).enumerate() {
        let n = (2 * cw).min(x + 1);
        for d in 0..n {
            let (word, shift) = slot(d);
            let r = right.get(x - d).copied().unwrap_or(0);
            if let Some(w) = column.get_mut(word) {
                *w = w.wrapping_add(ad(l, r) << shift);
            }
        }
    }
}

/// `column[d] += |l − right[x − d]| − |l' − right'[x − d]|` for every lane `d ≤ x`: one row
/// into the window, one out. With the `dsp` feature on an Arm target, four lanes at a time
/// with `UQSUB8` and `UXTAB16` unless `dsp` is false; otherwise the portable code, which
/// gives the same sums.
pub(crate) fn slide_row(sums: &mut [u32], cw: usize, rows: [&[u8]; 4], dsp: bool) {
    #[cfg(all(feature = "dsp", target_arch = "arm"))]
    if dsp {
        return dsp::slide_row(sums, cw, rows);
    }
    let _ = dsp;
    slide_row_portable(sums, cw, rows);
}

/// The portable [`slide_row`]: `rows` are the new left and right rows, then the old ones.
fn slide_row_portable(sums: &mut [u32], cw: usize, rows: [&[u8]; 4]) {
    slide_with(sums, cw, rows, |l, lo, new, old, a, b| {
        let (l, lo) = (l as u8, lo as u8);
        let lane = |k: u32| ad(l, (new >> (8 * k)) as u8) | ad(l, (new >> (8 * k + 16)) as u8) << 16;
        let gone = |k: u32| ad(lo, (old >> (8 * k)) as u8) | ad(lo, (old >> (8 * k + 16)) as u8) << 16;
        *a = a.wrapping_sub(gone(0)).wrapping_add(lane(0));
        *b = b.wrapping_sub(gone(1)).wrapping_add(lane(1));
    });
}

/// The loop of [`slide_row`] both paths share: for each column `x` with new and old left
/// pixels `l`, `lo`, `group(l, lo, new, old, a, b)` (each pixel in all four bytes) updates the two words `a`, `b` of each
/// whole group of four lanes from the right rows' four pixels ([`right_words`]); the lanes the
/// left edge cuts are then updated one at a time.
#[inline(always)]
fn slide_with(
    sums: &mut [u32],
    cw: usize,
    rows: [&[u8]; 4],
    group: impl Fn(u32, u32, u32, u32, &mut u32, &mut u32),
) {
    let [left, right, old_left, old_right] = rows;
    for (x, ((column, &l), &lo)) in sums.chunks_exact_mut(cw).zip(left).zip(old_left).enumerate() {
        let groups = (x + 1).min(2 * cw) >> 2;
        let words = right_words(right, x, groups).zip(right_words(old_right, x, groups));
        let (lb, lob) = (u32::from(l) * 0x0101_0101, u32::from(lo) * 0x0101_0101);
        for (pair, (new, old)) in column.chunks_exact_mut(2).zip(words) {
            if let [a, b] = pair {
                group(lb, lob, new, old, a, b);
            }
        }
        slide_tail(column, cw, x, 4 * groups, [l, lo], right, old_right);
    }
}

/// The lanes `from..=min(x, last)` one at a time (the group the left edge cuts).
#[inline(always)]
fn slide_tail(column: &mut [u32], cw: usize, x: usize, from: usize, l: [u8; 2], right: &[u8], old: &[u8]) {
    for d in from..(x + 1).min(2 * cw) {
        let (word, shift) = slot(d);
        let new = ad(l[0], right.get(x - d).copied().unwrap_or(0));
        let gone = ad(l[1], old.get(x - d).copied().unwrap_or(0));
        if let Some(w) = column.get_mut(word) {
            *w = w.wrapping_sub(gone << shift).wrapping_add(new << shift);
        }
    }
}

/// Horizontal running box sums of width `2r + 1` of packed columns: `boxes[c] =
/// Σ sums[c−r..=c+r]` for `c ∈ r..w−r`, each column from the one before it.
pub(crate) fn box_row(sums: &[u32], boxes: &mut [u32], w: usize, cw: usize, r: usize) {
    let column = |c: usize| sums.get(c * cw..(c + 1) * cw).unwrap_or(&[]);
    let Some(first) = boxes.get_mut(r * cw..(r + 1) * cw) else {
        return;
    };
    first.fill(0);
    for c in 0..2 * r + 1 {
        for (a, &v) in first.iter_mut().zip(column(c)) {
            *a = a.wrapping_add(v);
        }
    }
    for c in r + 1..w - r {
        let (done, rest) = boxes.split_at_mut(c * cw);
        let prev = done.get(done.len() - cw..).unwrap_or(&[]);
        let cur = rest.get_mut(..cw).unwrap_or(&mut []);
        for (((b, &p), &add), &sub) in cur.iter_mut().zip(prev).zip(column(c + r)).zip(column(c - r - 1)) {
            *b = p.wrapping_sub(sub).wrapping_add(add);
        }
    }
}

/// The five-window costs of one pixel for the first `groups` groups of four disparities:
/// `costs[d] = m[d] + (sum of the two smallest of a[d], b[d], e[d], f[d])`, in disparity
/// order. `parts` are the packed columns of the centre window and of the four neighbours.
/// With the `dsp` feature on an Arm target and windows of at most 11 pixels (so that a sum of
/// two window sums fits a halfword), two lanes at a time with `UADD16`, `USUB16` and `SEL`
/// unless `dsp` is false; the same costs either way.
pub(crate) fn combine(parts: [&[u32]; 5], costs: &mut [u32], groups: usize, window: usize, dsp: bool) {
    #[cfg(all(feature = "dsp", target_arch = "arm"))]
    if dsp && window <= 11 {
        return dsp::combine(parts, costs, groups);
    }
    let _ = (dsp, window);
    let (lo, hi) = (|v: u32| v & 0xffff, |v: u32| v >> 16);
    combine_with(parts, costs, groups, |a, b, e, f| {
        (
            best_two(lo(a), lo(b), lo(e), lo(f)),
            best_two(hi(a), hi(b), hi(e), hi(f)),
        )
    });
}

/// The loop of [`combine`] both paths share: `best(a, b, e, f)` gives, for the low and the high
/// halves of the four neighbours' words, the sum of the two smallest; the centre window's half
/// is added to each and the costs stored in disparity order (word `k` of a group holds
/// `d₀ + k` in its low half and `d₀ + k + 2` in its high half).
#[inline(always)]
fn combine_with(
    parts: [&[u32]; 5],
    costs: &mut [u32],
    groups: usize,
    best: impl Fn(u32, u32, u32, u32) -> (u32, u32),
) {
    let [m, a, b, e, f] = parts.map(|p| p.chunks_exact(2));
    let words = m.zip(a).zip(b).zip(e).zip(f);
    for (quad, ((((m, a), b), e), f)) in costs.chunks_exact_mut(4).zip(words).take(groups) {
        if let ([m0, m1], [a0, a1], [b0, b1], [e0, e1], [f0, f1], [c0, c1, c2, c3]) = (m, a, b, e, f, quad) {
            let ((l0, h0), (l1, h1)) = (best(*a0, *b0, *e0, *f0), best(*a1, *b1, *e1, *f1));
            *c0 = (m0 & 0xffff) + l0;
            *c2 = (m0 >> 16) + h0;
            *c1 = (m1 & 0xffff) + l1;
            *c3 = (m1 >> 16) + h1;
        }
    }
}

/// The Cortex-M4/M7 DSP paths of [`slide_row`] and [`combine`].
#[cfg(all(feature = "dsp", target_arch = "arm"))]
#[allow(unsafe_code)]
mod dsp {
    use core::arch::asm;

    /// One Armv7E-M DSP instruction on registers as a function (`$insn` writes `{r}` from
    /// `{a}` and, if given, `{b}`), with the asm options it needs.
    macro_rules! dsp_op {
        ($(#[$doc:meta])* $name:ident($($arg:ident),+) = $insn:literal, $($opt:ident),+) => {
            $(#[$doc])*
            #[inline(always)]
            fn $name($($arg: u32),+) -> u32 {
                let r: u32;
                // SAFETY: a register-only instruction of the DSP extension; it touches no
                // memory, and the GE flags `uadd16` sets are read by nothing (`umin16` sets and
                // reads them within one block).
                unsafe {
                    asm!($insn, r = lateout(reg) r, $($arg = in(reg) $arg),+, options($($opt),+));
                }
                r
            }
        };
    }

    dsp_op!(
        /// Per byte, `a − b` saturated at 0.
        uqsub8(a, b) = "uqsub8 {r}, {a}, {b}", pure, nomem, nostack, preserves_flags
    );
    dsp_op!(
        /// `a` plus bytes 0 and 2 of `b` into its low and high halves.
        uxtab16(a, b) = "uxtab16 {r}, {a}, {b}", pure, nomem, nostack, preserves_flags
    );
    dsp_op!(
        /// `a` plus bytes 1 and 3 of `b` into its low and high halves.
        uxtab16_ror8(a, b) = "uxtab16 {r}, {a}, {b}, ror #8", pure, nomem, nostack, preserves_flags
    );
    dsp_op!(
        /// Bytes 0 and 2 of `a` as halfwords.
        uxtb16(a) = "uxtb16 {r}, {a}", pure, nomem, nostack, preserves_flags
    );
    dsp_op!(
        /// Bytes 1 and 3 of `a` as halfwords.
        uxtb16_ror8(a) = "uxtb16 {r}, {a}, ror #8", pure, nomem, nostack, preserves_flags
    );
    dsp_op!(
        /// Per halfword, `a + b` (no carry between the halves; sets the GE flags).
        uadd16(a, b) = "uadd16 {r}, {a}, {b}", pure, nomem, nostack
    );

    /// Per halfword, the smaller of `a` and `b`.
    #[inline(always)]
    fn umin16(a: u32, b: u32) -> u32 {
        let r: u32;
        // SAFETY: as above; `SEL` reads the GE flags `USUB16` just set, in the same block.
        unsafe {
            asm!("usub16 {r}, {a}, {b}", "sel {r}, {b}, {a}", r = out(reg) r, a = in(reg) a, b = in(reg) b,
                 options(pure, nomem, nostack));
        }
        r
    }

    /// [`super::combine`] two lanes at a time; the caller keeps windows at 11 pixels or less,
    /// so that the sum of two window sums (at most 2 · 121 · 255) fits a halfword.
    pub(super) fn combine(parts: [&[u32]; 5], costs: &mut [u32], groups: usize) {
        super::combine_with(parts, costs, groups, |a, b, e, f| {
            let s = umin16(
                umin16(uadd16(a, b), uadd16(e, f)),
                uadd16(umin16(a, b), umin16(e, f)),
            );
            (s & 0xffff, s >> 16)
        });
    }

    /// Four absolute byte differences in three instructions.
    #[inline(always)]
    fn absdiff8(a: u32, b: u32) -> u32 {
        uqsub8(a, b) | uqsub8(b, a)
    }

    pub(super) fn slide_row(sums: &mut [u32], cw: usize, rows: [&[u8]; 4]) {
        super::slide_with(sums, cw, rows, |l, lo, new, old, a, b| {
            let (new, old) = (absdiff8(l, new), absdiff8(lo, old));
            *a = uxtab16(*a, new).wrapping_sub(uxtb16(old));
            *b = uxtab16_ror8(*b, new).wrapping_sub(uxtb16_ror8(old));
        });
    }
}

/// Whether the DSP paths give the portable code's window sums on pseudo-random rows (every
/// lane, the left edge's partial groups included) and its five-window costs on
/// pseudo-random sums; `true` where there is no DSP path. For checking a build on the target.
pub fn dsp_agrees() -> bool {
    const W: usize = 40;
    const CW: usize = 10; // 20 lanes
    let mut seed = 0x2545_f491_u32;
    let mut next = move || {
        seed ^= seed << 13;
        seed ^= seed >> 17;
        seed ^= seed << 5;
        seed
    };
    let mut rows = [[0u8; W]; 4];
    for row in rows.iter_mut() {
        for p in row.iter_mut() {
            *p = next() as u8;
        }
    }
    let mut fast = [0u32; W * CW];
    add_row(&mut fast, CW, &rows[2], &rows[3]);
    add_row(&mut fast, CW, &rows[2], &rows[3]);
    let mut plain = fast;
    let borrowed = [&rows[0][..], &rows[1][..], &rows[2][..], &rows[3][..]];
    slide_row(&mut fast, CW, borrowed, true);
    slide_row_portable(&mut plain, CW, borrowed);
    // Five columns of window sums of 11 × 11 windows (each lane at most 121 · 255), ties
    // included.
    let mut columns = [[0u32; CW]; 5];
    for column in columns.iter_mut() {
        for word in column.iter_mut() {
            let (lo, hi) = ((next() >> 17).min(30_855), (next() >> 17).min(30_855));
            *word = if next() & 7 == 0 {
                lo * 0x0001_0001
            } else {
                lo | hi << 16
            };
        }
    }
    let parts = columns.each_ref().map(|c| &c[..]);
    let (mut quick, mut careful) = ([0u32; 2 * CW], [0u32; 2 * CW]);
    combine(parts, &mut quick, CW >> 1, 11, true);
    combine(parts, &mut careful, CW >> 1, 11, false);
    fast == plain && quick == careful
}

/// Sum of the two smallest of four: the cheapest pair is `a, b`, `c, d`, or the smaller of
/// each.
#[inline(always)]
pub(super) fn best_two(a: u32, b: u32, c: u32, d: u32) -> u32 {
    (a + b).min(c + d).min(a.min(b) + c.min(d))
}
