//! Re-solves confined to a box around what changed.
//!
//! The screened field ([`crate::planning::field`]) does not depend on where the vehicle is, and its
//! Green's function falls as `e^{−κr}`: a scan that resolves part of a frontier changes `u`
//! only near it (BENCHMARKS.md, "How far a scan reaches"). A whole-grid warm start still pays
//! for every cell, every cycle. [`resolve_near`] instead
//!
//! 1. computes the residual of the new problem at the old solution, and the box around the
//!    cells whose residual is large, from the largest down until the cells left outside carry
//!    no more than [`LocalParams::left_outside`] of the allowed residual (the old solution's
//!    own residual, spread thin, may stay), widened by [`LocalParams::margin`] voxels on
//!    every side; every box stays within the box of the domain (its interior cells and the
//!    cells next to them), beyond which no cell has a residual or changes;
//! 2. solves first a small box around the cells whose residual alone exceeds the allowed
//!    residual (what the scan changed), [`LocalParams::inner_margin`] voxels wider: it takes
//!    out the sharp local jump, so the big box starts from a smooth remainder (only while it
//!    is small beside the big box, [`LocalParams::inner_share`]);
//! 3. cuts each box out into lent scratch, its rim (the box's outer layer, where it is not
//!    the grid's border) made Dirichlet cells that hold the values outside, and solves it with
//!    the caller's solver, laid out again for the box in the same storage, to what is left of
//!    the allowed residual after the cells outside it and the rim's share;
//! 4. writes the box's interior back and checks the *whole grid's* residual against the same
//!    tolerance a whole-grid solve stops at: a solution this accepts meets the rule a global
//!    solve's does. The whole grid's sums are kept up to date without a pass over it: the
//!    box's cells before the solve, its rim after it, and its interior as the solve's own
//!    final residual reports it (a residual that small sums the same in either order, to far
//!    below the tolerance; the sums before must come from the same pass as the first one,
//!    which they cancel). Where the check fails (the change reached the rim) each rim face that
//!    still carries the change moves out by the distance `e^{−κr}` needs to bring it down to
//!    its share, and the box is solved again, up to [`LocalParams::max_boxes`] boxes or
//!    [`LocalParams::max_share`] of the grid; beyond that (or if a box solve fails) it solves
//!    the whole grid itself, warm from what the boxes left (never worse than the start), and
//!    returns [`Local::Whole`].
//!
//! Laplace's equation (no screening) changes everywhere when anything does, so it always
//! goes to the whole grid.

#[cfg(feature = "flat")]
use super::flat::Flat;
use super::multigrid::{Method, Multigrid};
use super::{
    cell_residual, converged, error_estimate, error_met, for_each_row, rounding2, rounding_row,
    row_residual_chunks, zip3, Active, ChunkSink, Contraction, Dirichlet, Residual, Screen, SolveError,
    SolveParams, SolveStats, Solved, Stop, CHUNK,
};
use crate::mapping::map::Dims;
use crate::planning::domain::Label;

/// Storage for the box: a label and a value per cell of the largest box to solve (the grid's
/// size fits any).
pub struct LocalScratch<'a> {
    /// The box's labels.
    pub labels: &'a mut [Label],
    /// The box's values.
    pub psi: &'a mut [f32],
}

/// [`LocalParams::max_share`]: the largest box worth solving on its own, as a share of the
/// grid's cells. Boxes up to three quarters of the grid still cost less than the whole grid
/// (explorations with a box limit of ½ and ¾, BENCHMARKS.md "The domain's box": ¾ gave almost
/// no re-solve back and planned 1–9 % fewer cell updates in seven of eight runs).
pub const MAX_SHARE: f32 = 0.75;

/// [`LocalParams::inner_share`]: an inner box of a quarter of the main box's cells costs about
/// the steps it saves the main box. On the re-solves of six explorations' dumped problems
/// (`bench-solve --replay`, BENCHMARKS.md "An exploration's re-solves, replayed"), the rule cut
/// the cell updates by 1–7 % against solving the inner box whenever it was smaller than the
/// main one.
pub const INNER_SHARE: f32 = 0.25;

/// The box scratch [`resolve_near`] can use for a grid of `cells`: [`MAX_SHARE`] of it.
pub fn box_scratch_len(cells: usize) -> usize {
    share_of(MAX_SHARE, cells)
}

/// The cells `share` of a grid of `cells` makes (the box limit's rule).
fn share_of(share: f32, cells: usize) -> usize {
    (share.clamp(0.0, 1.0) * cells as f32) as usize
}

/// How far a local re-solve reaches.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LocalParams {
    /// Cells whose residual is at or below this share of the whole grid's allowed residual
    /// (`tolerance · ‖b‖`) never need a box.
    pub threshold: f32,
    /// The share of the allowed residual the cells left outside the first box may keep: the
    /// box takes the cells above the threshold from the largest residual down until what is
    /// left carries no more than this. A warm start is the last solution, whose own residual
    /// (within the last solve's tolerance) lies spread around the frontier: the box is for
    /// what the scan changed, not for that.
    pub left_outside: f32,
    /// Voxels added on every side of those cells: how far the change is let spread.
    pub margin: usize,
    /// Voxels added on every side of the cells whose residual alone exceeds the whole grid's
    /// allowed residual (what the scan changed: a solution that met the tolerance has no such
    /// cell) for a small box solved first. It takes out the sharp local jump the change left
    /// (a relative residual of ~0.3 at a warm start, against ~0.04 where full multigrid
    /// starts a cold solve), so the box around it starts from a smooth remainder and takes
    /// fewer steps.
    pub inner_margin: usize,
    /// The inner box is solved first only while it holds less than this share of the main
    /// box's cells. It takes four or five steps of its own and saves the main box one or two,
    /// so it pays only while it is small beside it; a scan that
    /// changed much of the domain makes an inner box almost as big as the main one, and
    /// then the main box is solved alone.
    pub inner_share: f32,
    /// Boxes tried before the whole grid is solved instead (the inner box not counted).
    pub max_boxes: u8,
    /// Largest box worth solving on its own, as a share of the grid's cells.
    pub max_share: f32,
}

impl LocalParams {
    /// Settings for the screened field with screening `s = κ²h²` solved to `tolerance`. The
    /// change a scan makes falls as `e^{−κr}` (κ = √s per voxel) from where it acted, so
    /// the margin is the distance over which it falls by the square root of the tolerance
    /// (the box grows by as much again if the check finds it was not enough).
    pub fn for_screening(screening: f32, tolerance: f32) -> Self {
        let kappa = libm::sqrtf(screening.max(0.0));
        let fall = -0.5 * libm::logf(tolerance.clamp(1e-12, 0.5));
        let margin = if kappa > 0.0 {
            libm::ceilf(fall / kappa).clamp(2.0, 64.0) as usize
        } else {
            64
        };
        // One decay length: the change falls by e across it.
        let inner_margin = if kappa > 0.0 {
            libm::ceilf(1.0 / kappa).clamp(2.0, 16.0) as usize
        } else {
            16
        };
        Self {
            threshold: 0.01,
            left_outside: 0.5,
            margin,
            inner_margin,
            inner_share: INNER_SHARE,
            max_boxes: 3,
            max_share: MAX_SHARE,
        }
    }
}

/// How a local re-solve solved.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Local {
    /// In boxes; the whole grid meets the tolerance, or the rounding floor where that lies
    /// above it (then not [`SolveStats::converged`]).
    Solved(LocalStats),
    /// The boxes gave the grid back: a whole-grid solve from what they left. Its stats, with
    /// the work the boxes spent (box solves and residual passes) added to its cell updates.
    Whole(SolveStats),
}

impl Local {
    /// The stats of the solve, whichever way it went.
    pub fn stats(&self) -> SolveStats {
        match self {
            Local::Solved(s) => s.stats,
            Local::Whole(s) => *s,
        }
    }
}

/// A local re-solve's statistics.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct LocalStats {
    /// Iterations and cell updates summed over the boxes (the residual passes included);
    /// residual, floor, convergence and error estimate those of the whole grid.
    pub stats: SolveStats,
    /// Boxes solved (0: the old solution already met the tolerance).
    pub boxes: u8,
    /// Cells of the last box.
    pub box_cells: usize,
}

/// A box of cells, `lo` inclusive, `hi` exclusive.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Cells {
    lo: [usize; 3],
    hi: [usize; 3],
}

impl Cells {
    fn point(p: [usize; 3]) -> Self {
        Self {
            lo: p,
            hi: p.map(|c| c + 1),
        }
    }

    fn union(self, o: Self) -> Self {
        Self {
            lo: zip3(self.lo, o.lo, usize::min),
            hi: zip3(self.hi, o.hi, usize::max),
        }
    }

    /// Widened by `m` on every side, within `dims`.
    fn widened(self, m: usize, dims: &Dims) -> Self {
        self.grown([m; 6], dims)
    }

    /// Each face moved out by `by` (−x, +x, −y, +y, −z, +z), within `dims`.
    fn grown(self, by: [usize; 6], dims: &Dims) -> Self {
        let [mx, px, my, py, mz, pz] = by;
        Self {
            lo: zip3(self.lo, [mx, my, mz], usize::saturating_sub),
            hi: zip3(
                zip3(self.hi, [px, py, pz], usize::saturating_add),
                dims.extent(),
                usize::min,
            ),
        }
    }

    /// The cells of both boxes (empty, `lo == hi` on some axis, where they do not meet).
    fn within(self, o: &Self) -> Self {
        let lo = zip3(self.lo, o.lo, usize::max);
        Self {
            lo,
            hi: zip3(zip3(self.hi, o.hi, usize::min), lo, usize::max),
        }
    }

    /// The box of the domain of `labels` ([`Active::domain`]).
    fn domain(dims: &Dims, labels: &[Label]) -> Option<Self> {
        Active::domain(dims, labels).map(|(lo, hi)| Self { lo, hi })
    }

    fn extent(&self) -> [usize; 3] {
        zip3(self.hi, self.lo, usize::saturating_sub)
    }

    fn len(&self) -> usize {
        self.extent().iter().product()
    }
}

/// What a residual pass over a region of the grid found.
#[derive(Debug, Clone, Copy, Default)]
struct Scan {
    /// Sum of the squared residuals of the region's interior rows.
    r2: f64,
    /// The part of `r2` from residuals at or below the threshold. The larger ones are summed
    /// apart in `f64`: a row's `f32` sum would lose the small ones beside a large one, and the
    /// scans before and after a box solve must agree on the rest to the last bit.
    r2_low: f64,
    /// Sum of their rows' rounding terms ([`rounding_row`]).
    e2: f64,
    /// Largest residual above the threshold, and at or below it.
    max: [f32; 2],
    /// Largest residual on each rim face of the region (−x, +x, −y, +y, −z, +z), in a scan of
    /// its rim: how far the change still is from fading where the box held the values fixed.
    rim: [f32; 6],
    /// Cells on the region's rim (in a scan of its rim).
    rim_cells: usize,
}

/// Residual size classes of a scan: class `k` holds the residuals in `(τ·4ᵏ, τ·4ᵏ⁺¹]` (the
/// last, everything above), with the sum of their squares, the largest and their box.
const CLASSES: usize = 16;

/// The residuals above the threshold `τ` of a scan, by [size class](CLASSES).
#[derive(Debug, Clone, Copy, Default)]
struct Classes {
    r2: [f64; CLASSES],
    max: [f32; CLASSES],
    cells: [Option<Cells>; CLASSES],
    /// The box around the cells whose residual exceeds `hot_level`.
    hot: Option<Cells>,
    hot_level: f32,
}

impl Classes {
    /// Notes a cell at `p` whose residual `a` is `q = a / τ > 1` times the threshold.
    fn note(&mut self, p: [usize; 3], a: f32, q: f32) {
        // The exponent of q (≥ 0 since q > 1), halved: powers of 4.
        let e = ((q.to_bits() >> 23) & 0xff).saturating_sub(127) >> 1;
        let k = (e as usize).min(CLASSES - 1);
        let c = Cells::point(p);
        if a > self.hot_level {
            self.hot = Some(self.hot.map_or(c, |b| b.union(c)));
        }
        if let (Some(r2), Some(m), Some(b)) = (self.r2.get_mut(k), self.max.get_mut(k), self.cells.get_mut(k))
        {
            *r2 += f64::from(a) * f64::from(a);
            *m = m.max(a);
            *b = Some(b.map_or(c, |b| b.union(c)));
        }
    }

    /// The cells the first box must hold: those of the classes above the lowest one whose
    /// cells, with `rest` (the squared residual at or below `τ`), may stay outside within
    /// `budget` (a sum of squares). Returns their box and the largest residual of the cells
    /// left outside (`below`: those at or below `τ`).
    fn pick(&self, rest: f64, budget: f64, below: f32) -> (Option<Cells>, f32) {
        let (mut left, mut max, mut from) = (rest, below, 0);
        for (k, (r2, m)) in self.r2.iter().zip(&self.max).enumerate() {
            if left + r2 > budget {
                break;
            }
            left += r2;
            max = max.max(*m);
            from = k + 1;
        }
        let cells = self
            .cells
            .iter()
            .skip(from)
            .flatten()
            .copied()
            .reduce(Cells::union);
        (cells, max)
    }
}

/// The residual of the cells of `region`, or with `rim` only those on the rim of `region`
/// (the box a solve held them fixed on: rows on a −y/+y/−z/+z rim face whole, the −x/+x
/// end cells of every other row) and the largest residual on each rim face; `classes`, if
/// given, gets the residuals above `tau` by size. Residuals above `tau` are summed one by one
/// in `f64`, the rest by rows in `f32`. Never inlined: its callers are not hot, and inlined,
/// its row loop compiled a third slower.
#[inline(never)]
fn scan(
    dims: &Dims,
    screen: &Screen,
    (labels, psi): (&[Label], &[f32]),
    region: &Cells,
    (tau, mut classes): (f32, Option<&mut Classes>),
    rim: bool,
) -> Scan {
    let mut out = Scan::default();
    let n = dims.extent();
    let active = Active::bounded(dims, region.lo, region.hi);
    let within = rim.then_some(region);
    let mut below = 0.0f32;
    for_each_row(dims, &active, screen, labels, psi, |st, row| {
        let rim = rim_row(within, &n, st.y, st.z);
        // The cells that need more than the sums: a row's −x/+x rim cells, every cell of a
        // row on a −y/+y/−z/+z rim face (only such rows have `faces` bits), and (tested per
        // cell) a large residual.
        let (faces, first, last) = rim.unwrap_or((0, usize::MAX, usize::MAX));
        let mut sums = RowScan {
            r2: 0.0,
            e2: 0.0,
            below: 0.0,
            lanes: Lanes::default(),
            tau,
            ends: [first, last],
            whole_row: faces != 0,
            labels: st.labels,
            rare: Rare {
                out: &mut out,
                classes: classes.as_deref_mut(),
                tau,
                rim,
                yz: [st.y, st.z],
            },
        };
        if within.is_some() && faces == 0 {
            // A row off the rim faces: its two end cells (one, if the box is a cell wide).
            let last = if last == first { usize::MAX } else { last };
            for x in [first, last] {
                cell_residual(st, row, x, &mut sums);
            }
        } else {
            row_residual_chunks(st, row, &mut sums);
        }
        let RowScan {
            r2,
            e2,
            below: b,
            lanes,
            ..
        } = sums;
        let Lanes {
            r2: lr,
            e2: le,
            max: lm,
        } = lanes;
        let lanes = lr.iter().zip(&le).zip(&lm);
        let (r2, e2, b) = lanes.fold((r2, e2, b), |(r, e, m), ((lr, le), lm)| {
            (r + lr, e + le, m.max(*lm))
        });
        out.r2 += f64::from(r2);
        out.r2_low += f64::from(r2);
        out.e2 += rounding_row(e2);
        below = below.max(b);
    });
    out.max[1] = out.max[1].max(below);
    out
}

/// A row's sums by lane of the chunks ([`RowScan::chunk`]): an array per sum, which the
/// lanes' loop reads and writes as vectors.
#[derive(Debug, Clone, Copy, Default)]
struct Lanes {
    r2: [f32; CHUNK],
    e2: [f32; CHUNK],
    max: [f32; CHUNK],
}

/// One row of a [`scan`]: its sums, and where the cells are that need more than them.
struct RowScan<'s, 'c, 'l> {
    /// Squared residuals at or below `tau` (the larger go to `rare`, in `f64`).
    r2: f32,
    /// Rounding terms ([`rounding2`]).
    e2: f32,
    /// The largest residual at or below `tau` of the cells not noted.
    below: f32,
    /// [`RowScan::chunk`]'s `r2`, `e2` and `below`, per lane of the chunk.
    lanes: Lanes,
    tau: f32,
    /// The row's −x and +x rim cells (`usize::MAX` for none).
    ends: [usize; 2],
    /// The row lies on a −y/+y/−z/+z rim face: all its cells are rim cells.
    whole_row: bool,
    labels: &'l [Label],
    rare: Rare<'s, 'c>,
}

impl ChunkSink for RowScan<'_, '_, '_> {
    #[inline(always)]
    fn chunk(&mut self, x0: usize, from: usize, r: &[f32; CHUNK], n: &[f32; CHUNK], c: &[f32; CHUNK]) {
        let x1 = x0 + CHUNK;
        let [first, last] = self.ends;
        // A chunk with a rim cell takes its cells one by one.
        let plain = !(from..x1).contains(&first) && !(from..x1).contains(&last) && !self.whole_row;
        if !plain {
            for (x, ((r, n), c)) in (x0..x1).zip(r.iter().zip(n).zip(c)) {
                if x >= from && self.labels.get(x) == Some(&Label::Interior) {
                    self.single(x, *r, *n as u32, *c);
                }
            }
            return;
        }
        let tau = self.tau;
        // Lane by lane (a sum over the lanes would not vectorise: it fixes the order), one
        // simple loop per sum: the compiler turns each into a few vector instructions (one
        // loop over all three stayed scalar).
        let a = r.map(f32::abs);
        let Lanes { r2, e2, max } = &mut self.lanes;
        for (sum, (r, a)) in r2.iter_mut().zip(r.iter().zip(&a)) {
            *sum += if *a <= tau { r * r } else { 0.0 };
        }
        for (e, (k, c)) in e2.iter_mut().zip(n.iter().zip(c)) {
            *e += (k + k * k) * c * c;
        }
        for (max, a) in max.iter_mut().zip(&a) {
            *max = max.max(if *a <= tau { *a } else { 0.0 });
        }
        if a.iter().any(|a| above(*a, tau)) {
            // Residuals above the threshold (or NaN): those cells are noted.
            for (x, r) in (x0..x1).zip(r) {
                if above(r.abs(), tau) {
                    self.rare.note(x, r.abs());
                }
            }
        }
    }

    #[inline(always)]
    fn single(&mut self, x: usize, r: f32, n: u32, c: f32) {
        self.e2 += rounding2(n, c);
        let a = r.abs();
        if a <= self.tau {
            self.r2 += r * r;
        }
        let [first, last] = self.ends;
        // A NaN is noted too, and makes the sums NaN: the check fails on it.
        if above(a, self.tau) || x == first || x == last || self.whole_row {
            self.rare.note(x, a);
        } else {
            self.below = self.below.max(a);
        }
    }
}

/// What [`scan`] needs for the cells of one row on the region's rim (in a scan of it) or
/// above the threshold.
struct Rare<'s, 'c> {
    out: &'s mut Scan,
    classes: Option<&'c mut Classes>,
    tau: f32,
    /// The row's rim ([`rim_row`]; `None` unless the scan is of the rim, whose cells
    /// `row_residual_chunks` and the end cells keep within the region's x range).
    rim: Option<(u8, usize, usize)>,
    yz: [usize; 2],
}

impl Rare<'_, '_> {
    /// Records the cell `x` of the row, whose residual is `a`.
    #[cold]
    #[inline(never)]
    fn note(&mut self, x: usize, a: f32) {
        let [y, z] = self.yz;
        let p = [x, y, z];
        let out = &mut *self.out;
        let [max_above, max_below] = &mut out.max;
        if above(a, self.tau) {
            out.r2 += f64::from(a) * f64::from(a);
            *max_above = max_above.max(a);
            if let Some(c) = self.classes.as_deref_mut() {
                c.note(p, a, a / self.tau);
            }
        } else {
            *max_below = max_below.max(a);
        }
        let Some((faces, first, last)) = self.rim else {
            return;
        };
        let faces = faces | u8::from(x == first) | u8::from(x == last) << 1;
        if faces != 0 {
            out.rim_cells += 1;
            for (f, m) in out.rim.iter_mut().enumerate() {
                if faces & (1 << f) != 0 {
                    *m = m.max(a);
                }
            }
        }
    }
}

/// `a > tau`, or `a` is NaN: a NaN residual is treated as a large one, so it reaches the sums
/// (making them NaN, which fails the check) instead of being passed over.
#[inline(always)]
fn above(a: f32, tau: f32) -> bool {
    a > tau || a.is_nan()
}

/// The rim of `within` along row `(y, z)`: the face bits the whole row shares (−y/+y/−z/+z)
/// and the x of its −x and +x rim cells (`usize::MAX` where the grid ends there instead), or
/// `None` for a row outside `within`.
fn rim_row(within: Option<&Cells>, n: &[usize; 3], y: usize, z: usize) -> Option<(u8, usize, usize)> {
    let b = within?;
    let [nx, ny, nz] = *n;
    let [_, ly, lz] = b.lo;
    let [hx, hy, hz] = b.hi;
    if !((ly..hy).contains(&y) && (lz..hz).contains(&z)) {
        return None;
    }
    let side = |c: usize, lo: usize, hi: usize, n: usize, bit: u8| {
        let [low, high] = on_rim(c, lo, hi, n);
        u8::from(low) << bit | u8::from(high) << (bit + 1)
    };
    let faces = side(y, ly, hy, ny, 2) | side(z, lz, hz, nz, 4);
    let [low, high] = rim_ends(b.lo[0], hx, nx);
    let first = if low { b.lo[0] } else { usize::MAX };
    let last = if high { hx - 1 } else { usize::MAX };
    Some((faces, first, last))
}

/// Whether a box spanning `lo..hi` of an axis of `n` cells has a rim at its low and its high
/// end: a face of the box is a rim where the grid goes on beyond it.
fn rim_ends(lo: usize, hi: usize, n: usize) -> [bool; 2] {
    [lo > 0, hi < n]
}

/// Whether cell `c` of that axis lies on the box's low and its high rim face ([`rim_ends`]).
fn on_rim(c: usize, lo: usize, hi: usize, n: usize) -> [bool; 2] {
    let [low, high] = rim_ends(lo, hi, n);
    [low && c == lo, high && c + 1 == hi]
}

/// One x-row of a box ([`for_each_row_of`]).
struct BoxRow {
    /// The row's cells in the grid (linear indices).
    grid: core::ops::Range<usize>,
    /// Where the row starts in the box.
    at: usize,
    /// The whole row lies on a −y/+y/−z/+z rim face.
    rim: bool,
    /// Its first and its last cell lie on the −x and the +x rim face.
    ends: [bool; 2],
}

impl BoxRow {
    /// The row's cells in the box.
    fn in_box(&self) -> core::ops::Range<usize> {
        self.at..self.at + self.grid.len()
    }
}

/// Calls `f` with every x-row of `cells`, in the box's order.
fn for_each_row_of(dims: &Dims, cells: &Cells, mut f: impl FnMut(BoxRow)) {
    let ([x0, y0, z0], [x1, y1, z1]) = (cells.lo, cells.hi);
    let [nx, ny, nz] = dims.extent();
    let rim = |c: usize, lo: usize, hi: usize, n: usize| on_rim(c, lo, hi, n).contains(&true);
    let ends = rim_ends(x0, x1, nx);
    let mut at = 0;
    for z in z0..z1 {
        for y in y0..y1 {
            let start = nx * (y + ny * z);
            f(BoxRow {
                grid: start + x0..start + x1,
                at,
                rim: rim(y, y0, y1, ny) || rim(z, z0, z1, nz),
                ends,
            });
            at += x1 - x0;
        }
    }
}

/// A solver that can solve boxes cut out of its grid in its own storage: the multigrid
/// ([`WithMethod`]) or the host's flat solver ([`Flat`]).
pub trait BoxSolver {
    /// The grid the solver is laid out for.
    fn grid(&self) -> Dims;
    /// Lays the solver out for a grid of `fine` (no larger along any axis than the one its
    /// storage was made for).
    fn lay_out(&mut self, fine: Dims) -> Result<(), SolveError>;
    /// Solves a box whose Dirichlet cells hold the values in `psi` (warm), to the residual
    /// norm `residual` (`params.tolerance` where the box's `‖b‖` is 0).
    fn solve_box(
        &mut self,
        labels: &[Label],
        psi: &mut [f32],
        params: &SolveParams,
        residual: f32,
    ) -> Result<Solved, SolveError>;
    /// Solves the whole grid (standard Dirichlet values).
    fn solve_whole(
        &mut self,
        labels: &[Label],
        psi: &mut [f32],
        params: &SolveParams,
    ) -> Result<SolveStats, SolveError>;
}

/// The multigrid with the method its solves use.
pub struct WithMethod<'m, 'a>(pub &'m mut Multigrid<'a>, pub Method);

impl BoxSolver for WithMethod<'_, '_> {
    fn grid(&self) -> Dims {
        self.0.fine_dims()
    }
    fn lay_out(&mut self, fine: Dims) -> Result<(), SolveError> {
        self.0.relayout(fine)
    }
    fn solve_box(
        &mut self,
        labels: &[Label],
        psi: &mut [f32],
        params: &SolveParams,
        residual: f32,
    ) -> Result<Solved, SolveError> {
        self.0
            .solve_with(labels, psi, params, self.1, Dirichlet::Given { residual })
    }
    fn solve_whole(
        &mut self,
        labels: &[Label],
        psi: &mut [f32],
        params: &SolveParams,
    ) -> Result<SolveStats, SolveError> {
        self.0.solve(labels, psi, params, self.1)
    }
}

#[cfg(feature = "flat")]
impl BoxSolver for Flat<'_> {
    fn grid(&self) -> Dims {
        self.fine_dims()
    }
    fn lay_out(&mut self, fine: Dims) -> Result<(), SolveError> {
        self.relayout(fine)
    }
    fn solve_box(
        &mut self,
        labels: &[Label],
        psi: &mut [f32],
        params: &SolveParams,
        residual: f32,
    ) -> Result<Solved, SolveError> {
        self.solve_with(labels, psi, params, Dirichlet::Given { residual })
    }
    fn solve_whole(
        &mut self,
        labels: &[Label],
        psi: &mut [f32],
        params: &SolveParams,
    ) -> Result<SolveStats, SolveError> {
        self.solve(labels, psi, params)
    }
}

/// Re-solves the problem `labels` in `psi` (holding the last solution, the warm start) with
/// `solver` (laid out for the whole grid, which it is again on return) in boxes around what
/// changed, or over the whole grid where the boxes give up; see the [module
/// documentation](self). `params` are the whole-grid solve's (`warm_start` is implied); the box
/// scratch must hold [`LocalParams::max_share`] of the grid's cells.
pub fn resolve_near(
    solver: &mut impl BoxSolver,
    labels: &[Label],
    psi: &mut [f32],
    params: &SolveParams,
    local: &LocalParams,
    scratch: LocalScratch<'_>,
) -> Result<Local, SolveError> {
    let warm = SolveParams {
        warm_start: true,
        ..*params
    };
    let mut work = 0u64;
    // A box solve that fails (never seen) writes nothing back, so `psi` is still a warm start
    // for the whole grid, whose solve reports any error of its own.
    if let Ok(Some(s)) = in_boxes(solver, labels, psi, &warm, local, scratch, &mut work) {
        return Ok(Local::Solved(s));
    }
    let mut s = solver.solve_whole(labels, psi, &warm)?;
    s.cell_updates += work;
    Ok(Local::Whole(s))
}

/// The boxes of [`resolve_near`]: the stats if they met the tolerance, `None` where they gave
/// up; `work` counts the cell updates spent either way.
fn in_boxes(
    solver: &mut impl BoxSolver,
    labels: &[Label],
    psi: &mut [f32],
    params: &SolveParams,
    local: &LocalParams,
    scratch: LocalScratch<'_>,
    work: &mut u64,
) -> Result<Option<LocalStats>, SolveError> {
    let dims = solver.grid();
    let n = dims.len();
    let (labels, psi) = super::checked_problem(&dims, labels, psi, params, Dirichlet::Standard)?;
    let screen = Screen::new(params.screening);
    let b2 = super::dirichlet_norm2(&dims, labels);
    if screen.shift <= 0.0 || b2 == 0.0 {
        return Ok(None);
    }
    let allowed = params.tolerance * libm::sqrt(b2) as f32;
    let tau = local.threshold * allowed;
    let kappa = libm::sqrtf(screen.shift);
    // Boxes stay within the domain's: the cells beyond it are outside the domain, and a box
    // over them would cost (and count against `max_share`) for nothing.
    let Some(domain) = Cells::domain(&dims, labels) else {
        return Ok(None);
    };
    let mut classes = Classes {
        hot_level: allowed,
        ..Classes::default()
    };
    let first = scan(
        &dims,
        &screen,
        (labels, psi),
        &domain,
        (tau, Some(&mut classes)),
        false,
    );
    *work += domain.len() as u64;
    // The cells the first box must hold.
    let rest = first.r2_low;
    let kept_outside = f64::from(local.left_outside * allowed);
    let budget = kept_outside * kept_outside;
    let (large, max_still) = classes.pick(rest, budget, first.max[1]);

    // The whole grid's sums, kept up to date from the cells each box solve can change (the
    // box's: its interior, and its rim beside it): every other cell keeps its residual, which
    // the first pass found at or below `max_still` unless it lies in the first box.
    let (mut r2, mut e2) = (first.r2, first.e2);
    let mut res = Residual::from_sums(r2, e2, first.max[0].max(max_still), b2);
    let done = |res: &Residual| {
        let estimate = error_estimate(&Contraction::default(), res, &screen);
        res.meets(params.tolerance) && error_met(estimate, params.max_error)
    };
    let mut out = LocalStats {
        stats: SolveStats {
            initial_residual: res.relative,
            ..SolveStats::default()
        },
        ..LocalStats::default()
    };
    let capacity = scratch.labels.len().min(scratch.psi.len());
    let limit = share_of(local.max_share, n).min(capacity);
    // The box every box after the inner one holds.
    let main = large.map(|c| c.widened(local.margin, &dims).within(&domain));
    let inner = classes
        .hot
        .map(|c| c.widened(local.inner_margin, &dims).within(&domain));
    let inner = inner.filter(|i| {
        local.inner_margin > 0 && main.is_some_and(|m| (i.len() as f32) < local.inner_share * m.len() as f32)
    });
    let mut next = inner.or(main);
    let max_boxes = local.max_boxes.saturating_add(u8::from(inner.is_some()));
    let mut solved: Option<Cells> = None;
    while !done(&res) {
        let Some(cells) = next.filter(|c| Some(*c) != solved) else {
            // Residual spread thin everywhere (a changed κ), or a box that cannot grow.
            return Ok(None);
        };
        if out.boxes >= max_boxes || cells.len() > limit {
            return Ok(None);
        }
        let [ex, ey, ez] = cells.extent();
        let Ok(box_dims) = Dims::new(ex, ey, ez) else {
            return Ok(None);
        };
        let (Some(bl), Some(bp)) = (
            scratch.labels.get_mut(..cells.len()),
            scratch.psi.get_mut(..cells.len()),
        ) else {
            return Ok(None);
        };
        let before = scan(&dims, &screen, (labels, psi), &cells, (tau, None), false);
        for_each_row_of(&dims, &cells, |row| {
            let (Some(l), Some(p), Some(bl), Some(bp)) = (
                labels.get(row.grid.clone()),
                psi.get(row.grid.clone()),
                bl.get_mut(row.in_box()),
                bp.get_mut(row.in_box()),
            ) else {
                return;
            };
            bl.copy_from_slice(l);
            bp.copy_from_slice(p);
            // The rim holds the values outside the box fixed.
            let fix = |l: &mut Label| {
                if *l == Label::Interior {
                    *l = Label::Frontier;
                }
            };
            if row.rim {
                bl.iter_mut().for_each(fix);
                return;
            }
            let [first, last] = row.ends;
            if let Some(l) = bl.first_mut().filter(|_| first) {
                fix(l);
            }
            if let Some(l) = bl.last_mut().filter(|_| last) {
                fix(l);
            }
        });
        // The box's share of the whole grid's allowed residual: what is left after the cells
        // outside it (whose residual the box cannot change) and the rim's share, the
        // half the rim growth below aims each face's residual at; never below a quarter.
        let allowed2 = f64::from(allowed) * f64::from(allowed);
        let outside = (r2 - before.r2).max(0.0);
        let share = libm::sqrt((0.75 * allowed2 - outside).max(allowed2 / 16.0)) as f32;
        let box_params = SolveParams {
            max_error: f32::INFINITY,
            ..*params
        };
        solver.lay_out(box_dims)?;
        let result = solver.solve_box(bl, bp, &box_params, share);
        solver.lay_out(dims)?;
        let solved_box = result?;
        let s = solved_box.stats;
        out.boxes += 1;
        out.box_cells = cells.len();
        out.stats.iterations += s.iterations;
        *work += s.cell_updates;
        for_each_row_of(&dims, &cells, |row| {
            // The interior cells off the rim take the box's values.
            if row.rim {
                return;
            }
            let [first, last] = row.ends.map(usize::from);
            let (g, b) = (row.grid, row.at);
            let Some(len) = g.len().checked_sub(first + last) else {
                return;
            };
            let (g, b) = (g.start + first..g.start + first + len, b + first..b + first + len);
            let (Some(p), Some(v), Some(l)) = (psi.get_mut(g.clone()), bp.get(b), labels.get(g)) else {
                return;
            };
            for ((p, v), l) in p.iter_mut().zip(v).zip(l) {
                // A select, not a branch: it vectorises.
                *p = if *l == Label::Interior { *v } else { *p };
            }
        });
        // The box's interior rows have the residual its solve ended at (the same rows, summed
        // in the solver's order: a residual that small sums the same to far below the
        // tolerance); its rim, the residual its new values leave beside them.
        let after = scan(&dims, &screen, (labels, psi), &cells, (tau, None), true);
        *work += (cells.len() + after.rim_cells) as u64;
        r2 += after.r2 + solved_box.r2() - before.r2;
        e2 += after.e2 + solved_box.e2() - before.e2;
        // Rounding can leave the sums a hair below zero; a NaN passes, and fails the check.
        let kept = |sum: f64| if sum < 0.0 { 0.0 } else { sum };
        let max = (after.max[0].max(after.max[1]))
            .max(solved_box.residual.max)
            .max(max_still);
        res = Residual::from_sums(kept(r2), kept(e2), max, b2);
        // Where the rim still carries the change, move that face out by the distance over
        // which e^{−κr} brings it down to its share of the allowed residual.
        let per_cell = 0.5 * allowed / libm::sqrtf(after.rim_cells.max(1) as f32);
        let by = after.rim.map(|r| {
            if r > per_cell && kappa > 0.0 {
                (libm::ceilf(libm::logf(r / per_cell) / kappa) as usize).max(2)
            } else {
                0
            }
        });
        let grown = cells.grown(by, &dims).within(&domain);
        next = Some(main.map_or(grown, |m| grown.union(m)));
        solved = Some(cells);
    }
    out.stats.cell_updates = *work;
    out.stats.residual = res.relative;
    out.stats.floor = res.floor;
    out.stats.error_estimate = error_estimate(&Contraction::default(), &res, &screen);
    // The boxes stop where the whole grid meets the tolerance or the floor above it (as a
    // whole-grid solve does); converged only in the first case.
    out.stats.converged = converged(&res, params, out.stats.error_estimate);
    out.stats.stop = if out.stats.converged {
        Stop::Met
    } else {
        Stop::Floor
    };
    Ok(Some(out))
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
    use crate::planning::solve::multigrid::tests::Scratch as Storage;
    use crate::planning::solve::screened_residual;
    use std::vec;
    use std::vec::Vec;

    /// Five rooms in a row joined by doors, a frontier patch on the far wall of the last; the
    /// scan (`scanned`) resolved the patch's lowest row.
    fn rooms(scanned: bool) -> (Dims, Vec<Label>) {
        let dims = Dims::new(120, 24, 16).unwrap();
        let mut labels = vec![Label::Interior; dims.len()];
        for (i, l) in labels.iter_mut().enumerate() {
            let v = dims.voxel(i);
            let (x, y, z) = (usize::from(v.x), usize::from(v.y), usize::from(v.z));
            let border = x == 0 || y == 0 || z == 0 || x == 119 || y == 23 || z == 15;
            let door = (10..13).contains(&y) && z < 10;
            if border || (x % 24 == 0 && !door) {
                *l = Label::Outside;
            }
            let lowest = if scanned { 5 } else { 4 };
            if x == 119 && (8..16).contains(&y) && (lowest..12).contains(&z) {
                *l = Label::Frontier;
            }
        }
        (dims, labels)
    }

    const SCREENING: f32 = 0.09;

    fn params(tolerance: f32, warm_start: bool, screening: f32) -> SolveParams {
        SolveParams {
            tolerance,
            warm_start,
            screening,
            ..SolveParams::default()
        }
    }

    /// The old problem solved cold to 1e-5 (as the explorer does), and the box scratch.
    fn solved_before(screening: f32) -> (Dims, Vec<f32>, Storage) {
        let (dims, before) = rooms(false);
        let mut storage = Storage::new(&dims, true);
        let mut psi = vec![0.0; dims.len()];
        let s = storage
            .multigrid(dims)
            .solve(&before, &mut psi, &params(1e-5, false, screening), Method::Auto)
            .unwrap();
        assert!(s.converged);
        (dims, psi, storage)
    }

    fn resolve(
        storage: &mut Storage,
        dims: Dims,
        labels: &[Label],
        psi: &mut [f32],
        screening: f32,
    ) -> Local {
        resolve_lending(storage, dims, labels, psi, screening, dims.len()).unwrap()
    }

    /// [`resolve`], which must have solved in boxes.
    fn in_boxes_only(storage: &mut Storage, dims: Dims, labels: &[Label], psi: &mut [f32]) -> LocalStats {
        match resolve(storage, dims, labels, psi, SCREENING) {
            Local::Solved(s) => s,
            whole => panic!("a scan at the far wall is re-solved locally: {whole:?}"),
        }
    }

    /// [`resolve_near`] with a box scratch of `cells` labels and values.
    fn resolve_lending(
        storage: &mut Storage,
        dims: Dims,
        labels: &[Label],
        psi: &mut [f32],
        screening: f32,
        cells: usize,
    ) -> Result<Local, SolveError> {
        let local = LocalParams::for_screening(screening, 1e-5);
        resolve_with(storage, dims, labels, psi, (screening, &local), cells)
    }

    /// [`resolve_lending`] with the box settings `local`.
    fn resolve_with(
        storage: &mut Storage,
        dims: Dims,
        labels: &[Label],
        psi: &mut [f32],
        (screening, local): (f32, &LocalParams),
        cells: usize,
    ) -> Result<Local, SolveError> {
        let (mut bl, mut bp) = (vec![Label::Outside; cells], vec![0.0; cells]);
        let scratch = LocalScratch {
            labels: &mut bl,
            psi: &mut bp,
        };
        let mut mg = storage.multigrid(dims);
        let out = resolve_near(
            &mut WithMethod(&mut mg, Method::Auto),
            labels,
            psi,
            &params(1e-5, true, screening),
            local,
            scratch,
        );
        assert_eq!(
            mg.fine_dims(),
            dims,
            "the multigrid is laid out for the grid again"
        );
        out
    }

    /// How far a field is from `after` solved tightly (to 1e-8, warm from `old`).
    fn off_the_tight_solve(
        storage: &mut Storage,
        dims: Dims,
        after: &[Label],
        old: &[f32],
    ) -> impl Fn(&[f32]) -> f32 {
        let mut exact = old.to_vec();
        storage
            .multigrid(dims)
            .solve(after, &mut exact, &params(1e-8, true, SCREENING), Method::Auto)
            .unwrap();
        move |v: &[f32]| {
            v.iter()
                .zip(&exact)
                .map(|(a, b)| (a - b).abs())
                .fold(0.0f32, f32::max)
        }
    }

    /// The property the explorer relies on: a re-solve confined to boxes around the scan
    /// leaves the whole grid at the tolerance a whole-grid solve stops at, as close to the exact
    /// field as that solve, for a fraction of its work.
    #[test]
    fn a_scan_is_re_solved_in_a_box_to_the_whole_grids_tolerance() {
        let (dims, old, mut storage) = solved_before(SCREENING);
        let (_, after) = rooms(true);
        let mut local = old.clone();
        let s = in_boxes_only(&mut storage, dims, &after, &mut local);
        assert!(s.boxes >= 1 && s.stats.converged, "{s:?}");
        assert!(s.box_cells < dims.len() / 2, "{s:?}");
        let checked = screened_residual(&dims, &after, &local, SCREENING);
        assert!(checked.relative <= 1e-5, "{checked:?}");
        // Kept up to date from the boxes, the same residual as a whole-grid pass.
        assert!(
            (checked.relative - s.stats.residual).abs() <= 1e-3 * checked.relative,
            "{checked:?} {s:?}"
        );
        assert!(
            checked.max <= s.stats.error_estimate.unwrap() * SCREENING * 1.001,
            "{checked:?} {s:?}"
        );
        // The whole grid re-solved from the same start, and solved tightly.
        let mut whole = old.clone();
        let w = storage
            .multigrid(dims)
            .solve(&after, &mut whole, &params(1e-5, true, SCREENING), Method::Auto)
            .unwrap();
        let worst = off_the_tight_solve(&mut storage, dims, &after, &old);
        assert!(
            worst(&local) <= 2e-5,
            "local {} whole {}",
            worst(&local),
            worst(&whole)
        );
        assert!(
            s.stats.cell_updates < w.cell_updates,
            "{} against {}",
            s.stats.cell_updates,
            w.cell_updates
        );
        // The scan did change the field.
        assert!(worst(&old) > 1e-2);
    }

    /// A box never reaches past the domain: with 30 columns of unknown space (outside the
    /// domain) beyond the frontier wall, the scan is re-solved in the same boxes, for the same
    /// work and to the same field, as when the grid ends at the wall.
    #[test]
    fn boxes_stay_within_the_domain() {
        let (dims, old, mut storage) = solved_before(SCREENING);
        let (_, after) = rooms(true);
        let mut plain = old.clone();
        let p = in_boxes_only(&mut storage, dims, &after, &mut plain);
        let wide = Dims::new(150, 24, 16).unwrap();
        let at = |i: usize| {
            let v = dims.voxel(i);
            usize::from(v.x) + 150 * (usize::from(v.y) + 24 * usize::from(v.z))
        };
        let (mut labels, mut psi) = (vec![Label::Outside; wide.len()], vec![0.0; wide.len()]);
        for (i, (l, v)) in after.iter().zip(&old).enumerate() {
            labels[at(i)] = *l;
            psi[at(i)] = *v;
        }
        let mut storage = Storage::new(&wide, true);
        let w = in_boxes_only(&mut storage, wide, &labels, &mut psi);
        assert_eq!((w.boxes, w.box_cells), (p.boxes, p.box_cells), "{w:?} {p:?}");
        assert_eq!(w.stats.cell_updates, p.stats.cell_updates, "{w:?} {p:?}");
        let worst = plain
            .iter()
            .enumerate()
            .map(|(i, v)| (psi[at(i)] - v).abs())
            .fold(0.0f32, f32::max);
        assert!(worst <= 1e-6, "{worst:e}");
    }

    /// The first box holds what the residual budget needs. Residual the last solve left
    /// away from the scan (here put into the first room on purpose) stays outside the box while
    /// it fits the budget, and is re-solved when it does not; the whole grid meets the
    /// tolerance either way.
    #[test]
    fn residual_the_grid_can_keep_is_left_outside_the_box() {
        let (dims, old, _) = solved_before(SCREENING);
        let (_, after) = rooms(true);
        // `amplitude` on a patch of 100 cells in the first room, in a fixed ±1 pattern.
        let perturbed = |amplitude: f32| {
            let mut psi = old.clone();
            for (i, (p, l)) in psi.iter_mut().zip(&after).enumerate() {
                let v = dims.voxel(i);
                let patch = (5..10).contains(&v.x) && (5..10).contains(&v.y) && (5..9).contains(&v.z);
                if *l == Label::Interior && patch {
                    *p += if (i * 7919) % 13 < 6 {
                        amplitude
                    } else {
                        -amplitude
                    };
                }
            }
            psi
        };
        let run = |mut psi: Vec<f32>| {
            let mut storage = Storage::new(&dims, true);
            let how = resolve(&mut storage, dims, &after, &mut psi, SCREENING);
            let checked = screened_residual(&dims, &after, &psi, SCREENING);
            assert!(
                how.stats().converged && checked.relative <= 1e-5,
                "{checked:?} {how:?}"
            );
            how
        };
        let Local::Solved(clean) = run(old.clone()) else {
            panic!("a scan at the far wall is re-solved locally");
        };
        // Residuals above the threshold (a hundredth of the allowed residual) that together fit
        // the budget: the same box as without them.
        let small = run(perturbed(3e-7));
        assert!(
            matches!(small, Local::Solved(s) if s.box_cells == clean.box_cells),
            "{small:?} {clean:?}"
        );
        // Beyond the budget: re-solved too (here the boxes would span the grid, so the whole).
        let large = run(perturbed(3e-5));
        assert!(
            !matches!(large, Local::Solved(s) if s.box_cells == clean.box_cells),
            "{large:?} {clean:?}"
        );
    }

    #[test]
    fn a_solved_problem_needs_no_box() {
        let (dims, mut psi, mut storage) = solved_before(SCREENING);
        let (_, before) = rooms(false);
        let kept = psi.clone();
        let Local::Solved(s) = resolve(&mut storage, dims, &before, &mut psi, SCREENING) else {
            panic!("nothing changed");
        };
        assert_eq!((s.boxes, s.stats.iterations), (0, 0));
        assert_eq!(psi, kept);
    }

    /// A scan that changed much of the room: the cells it changed lie so far apart that the
    /// inner box around them would hold most of the main box, and solving it first would cost
    /// its steps for the one or two it saves the main box. The main box is solved alone, for
    /// less work, to the same tolerance.
    #[test]
    fn an_inner_box_as_big_as_the_main_box_is_not_solved_first() {
        let (dims, old, mut storage) = solved_before(SCREENING);
        // The far wall's patch resolved as in `rooms`, and a hatch in the last room's
        // ceiling, 13 voxels from it, seen as open to unknown space.
        let (_, mut after) = rooms(true);
        for (i, l) in after.iter_mut().enumerate() {
            let v = dims.voxel(i);
            if (100..106).contains(&v.x) && (2..8).contains(&v.y) && v.z == 14 {
                *l = Label::Frontier;
            }
        }
        let mut run = |inner_share: f32| {
            let local = LocalParams {
                inner_share,
                ..LocalParams::for_screening(SCREENING, 1e-5)
            };
            let mut psi = old.clone();
            let out = resolve_with(
                &mut storage,
                dims,
                &after,
                &mut psi,
                (SCREENING, &local),
                dims.len(),
            );
            let Ok(Local::Solved(s)) = out else {
                panic!("re-solved in boxes: {out:?}");
            };
            let checked = screened_residual(&dims, &after, &psi, SCREENING);
            assert!(checked.relative <= 1e-5, "{inner_share}: {checked:?} {s:?}");
            s
        };
        // Solved first whenever smaller (the rule before), the inner box took a box of its own.
        let both = run(1.0);
        assert_eq!(both.boxes, 2, "{both:?}");
        let alone = run(INNER_SHARE);
        assert_eq!(alone.boxes, 1, "{alone:?}");
        assert!(
            alone.stats.cell_updates < both.stats.cell_updates,
            "{alone:?} {both:?}"
        );
    }

    /// Laplace's field changes everywhere when anything does: it is solved over the whole
    /// grid. So does the screened field whose κ changed (the explorer never re-solves such a
    /// field in boxes); given one, boxes of up to [`MAX_SHARE`] of the grid may take it, and
    /// the whole grid meets its tolerance either way.
    #[test]
    fn laplace_goes_to_the_whole_grid_and_a_changed_screening_meets_its_tolerance() {
        let (_, after) = rooms(true);
        for (solved, resolved) in [(0.0, 0.0), (SCREENING, 0.25 * SCREENING)] {
            let (dims, mut psi, mut storage) = solved_before(solved);
            let out = resolve(&mut storage, dims, &after, &mut psi, resolved);
            assert!(out.stats().converged, "{solved} → {resolved}: {out:?}");
            if resolved == 0.0 {
                assert!(matches!(out, Local::Whole(_)), "{out:?}");
            }
            let checked = screened_residual(&dims, &after, &psi, resolved);
            assert!(
                checked.relative <= 1e-5,
                "{solved} → {resolved}: {checked:?} {out:?}"
            );
        }
    }

    #[test]
    fn a_box_scratch_too_small_leaves_the_whole_grid() {
        let (dims, mut psi, mut storage) = solved_before(SCREENING);
        let (_, after) = rooms(true);
        let out = resolve_lending(&mut storage, dims, &after, &mut psi, SCREENING, 100);
        assert!(matches!(out, Ok(Local::Whole(s)) if s.converged), "{out:?}");
        let checked = screened_residual(&dims, &after, &psi, SCREENING);
        assert!(checked.relative <= 1e-5, "{checked:?}");
    }

    /// The host's flat solver in the same boxes: the whole grid at its tolerance, as close to
    /// the exact field as the multigrid's boxes, for less work than its own whole-grid
    /// re-solve; laid out for the whole grid again afterwards, whose next solve is unchanged.
    #[cfg(feature = "flat")]
    #[test]
    fn the_flat_solver_re_solves_a_scan_in_boxes() {
        use crate::planning::solve::flat::{flat_scratch_len, Flat};
        let (dims, old, mut storage) = solved_before(SCREENING);
        let (_, after) = rooms(true);
        let mut values = vec![0.0f32; flat_scratch_len(&dims)];
        let mut flat = Flat::new(dims, &mut values).unwrap();
        let (mut bl, mut bp) = (vec![Label::Outside; dims.len()], vec![0.0; dims.len()]);
        let mut local = old.clone();
        let out = resolve_near(
            &mut flat,
            &after,
            &mut local,
            &params(1e-5, true, SCREENING),
            &LocalParams::for_screening(SCREENING, 1e-5),
            LocalScratch {
                labels: &mut bl,
                psi: &mut bp,
            },
        );
        let Ok(Local::Solved(s)) = out else {
            panic!("a scan at the far wall is re-solved locally: {out:?}");
        };
        assert_eq!(flat.fine_dims(), dims);
        assert!(
            s.boxes >= 1 && s.stats.converged && s.box_cells < dims.len() / 2,
            "{s:?}"
        );
        let checked = screened_residual(&dims, &after, &local, SCREENING);
        assert!(checked.relative <= 1e-5, "{checked:?}");
        // Kept up to date with the flat solver's own sums for the boxes' interiors: the same
        // residual as a whole-grid pass, but for the rows' rounding (its arithmetic is not
        // the scans'; 0.014 of the floor on this problem).
        assert!(
            (checked.relative - s.stats.residual).abs() <= 1e-3 * checked.relative + 0.05 * checked.floor,
            "{checked:?} {s:?}"
        );
        let mut whole = old.clone();
        let w = flat
            .solve(&after, &mut whole, &params(1e-5, true, SCREENING))
            .unwrap();
        let worst = off_the_tight_solve(&mut storage, dims, &after, &old);
        assert!(
            worst(&local) <= 2e-5 && worst(&whole) <= 2e-5,
            "local {} whole {}",
            worst(&local),
            worst(&whole)
        );
        assert!(
            s.stats.cell_updates < w.cell_updates,
            "{} against {}",
            s.stats.cell_updates,
            w.cell_updates
        );
    }
}
