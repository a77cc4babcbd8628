//! The voxel occupancy map: geometry (origin, resolution, dimensions) and per-voxel state.
//!
//! Storage is borrowed from the caller, so the same type lives in a firmware `static` or in a
//! host `Vec`: one byte of log-odds per voxel and one bit per voxel of "updated this frame"
//! ([`touched_words`] `u32` words), 1.125 bytes per voxel in all. Per voxel the map keeps
//!
//! - a log-odds value in `i8` fixed point ([`LOG_ODDS_SCALE`] steps per unit), OctoMap defaults:
//!   hit +0.85, miss −0.4, clamped to [−2.0, +3.5]; occupied above 0, free below 0;
//! - *never observed* (unknown) as a value of its own, [`UNKNOWN`] (−128), which no update can
//!   produce: the clamp keeps observed values within ±127, so unknown is a separate state, not
//!   "log-odds 0". An observed voxel with log-odds exactly 0 is [`Occupancy::Uncertain`];
//! - a *touched* bit, set by the first update in a frame and cleared by
//!   [`VoxelMap::begin_frame`], which makes "each voxel at most once per frame" an O(1) check.
//!
//! An unknown voxel may be *sealed* (value [`SEALED`], −127): the planner has decided it cannot
//! be observed from any reachable pose (see [`crate::planning::explore`]), so it no longer makes its free
//! neighbours frontiers. Sealing is forgotten as soon as the voxel is observed.
//!
//! Voxels are indexed `x + nx·(y + ny·z)`. The map frame is right-handed, z up, metres.

use core::num::NonZeroUsize;

use nalgebra::{Point3, Vector3};

/// Fixed-point steps per unit of log-odds.
pub const LOG_ODDS_SCALE: f32 = 20.0;

/// Largest number of voxels along one axis (indices must fit comfortably in `u32`).
pub const MAX_AXIS: usize = 2048;

/// Integer voxel coordinates inside a grid.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct VoxelIndex {
    /// Column along map x.
    pub x: u16,
    /// Row along map y.
    pub y: u16,
    /// Layer along map z.
    pub z: u16,
}

impl VoxelIndex {
    /// Builds an index from its three coordinates.
    pub const fn new(x: u16, y: u16, z: u16) -> Self {
        Self { x, y, z }
    }
    /// Squared distance to another voxel, in voxels².
    pub fn distance_sq(&self, other: &VoxelIndex) -> u32 {
        let d = |a: u16, b: u16| u32::from(a.abs_diff(b)).pow(2);
        d(self.x, other.x) + d(self.y, other.y) + d(self.z, other.z)
    }
}

/// The six face neighbours' offsets.
pub const FACE_OFFSETS: [[i32; 3]; 6] = [
    [-1, 0, 0],
    [1, 0, 0],
    [0, -1, 0],
    [0, 1, 0],
    [0, 0, -1],
    [0, 0, 1],
];

/// Grid dimensions, validated: every axis in `1..=MAX_AXIS`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Dims {
    // Non-zero by type, so `voxel`'s division and remainder cannot panic.
    nx: NonZeroUsize,
    ny: NonZeroUsize,
    nz: NonZeroUsize,
}

impl Dims {
    /// Checked constructor.
    pub fn new(nx: usize, ny: usize, nz: usize) -> Result<Self, MapError> {
        let ok = |n: usize| NonZeroUsize::new(n).filter(|n| n.get() <= MAX_AXIS);
        match (ok(nx), ok(ny), ok(nz)) {
            (Some(nx), Some(ny), Some(nz)) => Ok(Self { nx, ny, nz }),
            _ => Err(MapError::BadDimensions),
        }
    }
    /// Voxels along x.
    pub fn nx(&self) -> usize {
        self.nx.get()
    }
    /// Voxels along y.
    pub fn ny(&self) -> usize {
        self.ny.get()
    }
    /// Voxels along z.
    pub fn nz(&self) -> usize {
        self.nz.get()
    }
    /// Voxels along x, y and z.
    pub fn extent(&self) -> [usize; 3] {
        [self.nx(), self.ny(), self.nz()]
    }
    /// Total number of voxels.
    pub fn len(&self) -> usize {
        self.nx() * self.ny() * self.nz()
    }
    /// Always false: a grid has at least one voxel.
    pub fn is_empty(&self) -> bool {
        false
    }
    /// Linear index of a voxel that is known to be inside.
    #[inline]
    pub fn linear(&self, v: VoxelIndex) -> usize {
        usize::from(v.x) + self.nx() * (usize::from(v.y) + self.ny() * usize::from(v.z))
    }
    /// Voxel coordinates of a linear index (which must be `< len()`).
    #[inline]
    pub fn voxel(&self, i: usize) -> VoxelIndex {
        let x = i % self.nx;
        let yz = i / self.nx;
        // Each coordinate is below MAX_AXIS, so the casts are exact.
        VoxelIndex::new(x as u16, (yz % self.ny) as u16, (yz / self.ny) as u16)
    }
    /// The voxel at signed coordinates, if inside the grid.
    #[inline]
    pub fn checked(&self, x: i32, y: i32, z: i32) -> Option<VoxelIndex> {
        let inside = |c: i32, n: usize| c >= 0 && (c as usize) < n;
        if inside(x, self.nx()) && inside(y, self.ny()) && inside(z, self.nz()) {
            Some(VoxelIndex::new(x as u16, y as u16, z as u16))
        } else {
            None
        }
    }
    /// The voxel at `v + offset`, if inside the grid.
    #[inline]
    pub fn offset(&self, v: VoxelIndex, d: [i32; 3]) -> Option<VoxelIndex> {
        self.checked(
            i32::from(v.x) + d[0],
            i32::from(v.y) + d[1],
            i32::from(v.z) + d[2],
        )
    }
    /// True if `f` holds for the linear index of any voxel of the 3 × 3 × 3 block around `v`
    /// (`v` and its 26 neighbours) that is inside the grid.
    pub fn any_in_block(&self, v: VoxelIndex, mut f: impl FnMut(usize) -> bool) -> bool {
        (-1..=1).any(|dz| {
            (-1..=1)
                .any(|dy| (-1..=1).any(|dx| self.offset(v, [dx, dy, dz]).is_some_and(|n| f(self.linear(n)))))
        })
    }
    /// Calls `f` with the linear index of every face neighbour of `v` that is inside the grid.
    #[inline]
    pub fn for_each_face_neighbour(&self, v: VoxelIndex, f: impl FnMut(usize)) {
        self.for_each_face_neighbour_of([usize::from(v.x), usize::from(v.y), usize::from(v.z)], f);
    }
    /// [`Dims::for_each_face_neighbour`] of the voxel at `[x, y, z]` (none if it is outside
    /// the grid).
    #[inline]
    pub fn for_each_face_neighbour_of(&self, [x, y, z]: [usize; 3], mut f: impl FnMut(usize)) {
        // In the order of FACE_OFFSETS, as linear steps from the voxel's index.
        let (nx, ny, nz) = (self.nx(), self.ny(), self.nz());
        if x >= nx || y >= ny || z >= nz {
            return;
        }
        let (sy, sz) = (nx, nx * ny);
        let i = x + sy * y + sz * z;
        if x > 0 {
            f(i - 1);
        }
        if x + 1 < nx {
            f(i + 1);
        }
        if y > 0 {
            f(i - sy);
        }
        if y + 1 < ny {
            f(i + sy);
        }
        if z > 0 {
            f(i - sz);
        }
        if z + 1 < nz {
            f(i + sz);
        }
    }
}

/// Map errors: bad geometry or storage that does not fit it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum MapError {
    /// An axis has zero voxels or more than [`MAX_AXIS`].
    BadDimensions,
    /// Resolution not finite and positive, origin not finite, or coordinates so large that
    /// `f32` cannot resolve 1/64 of a voxel there.
    BadGeometry,
    /// A storage slice is shorter than the number of voxels.
    StorageTooSmall {
        /// Entries the grid needs.
        needed: usize,
        /// Entries supplied.
        got: usize,
    },
}

/// Where the grid sits in the map frame and how fine it is.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MapGeometry {
    dims: Dims,
    origin: Point3<f32>,
    resolution: f32,
}

impl MapGeometry {
    /// `origin` is the minimum corner of voxel (0,0,0); `resolution` is the voxel edge in metres.
    pub fn new(dims: Dims, origin: Point3<f32>, resolution: f32) -> Result<Self, MapError> {
        if !(resolution.is_finite() && resolution > 0.0 && origin.coords.iter().all(|c| c.is_finite())) {
            return Err(MapError::BadGeometry);
        }
        // Far from zero, f32 steps grow: a grid there could not tell its voxels apart (a goal
        // at a voxel centre would convert back to another voxel, or outside the grid).
        let extent = dims.extent();
        let resolvable = origin.coords.iter().zip(extent).all(|(o, n)| {
            let far = o.abs() + n as f32 * resolution;
            far.is_finite() && far * f32::EPSILON <= resolution / 64.0
        });
        if !resolvable {
            return Err(MapError::BadGeometry);
        }
        Ok(Self {
            dims,
            origin,
            resolution,
        })
    }
    /// Grid dimensions.
    pub fn dims(&self) -> Dims {
        self.dims
    }
    /// The grid `factor` times coarser over the same space: the same origin, voxels `factor`
    /// times larger, each axis rounded up (the last cells may reach past this grid's edge).
    pub fn coarsened(&self, factor: usize) -> Result<Self, MapError> {
        let f = factor.max(1);
        let d = self.dims;
        let dims = Dims::new(d.nx().div_ceil(f), d.ny().div_ceil(f), d.nz().div_ceil(f))?;
        Self::new(dims, self.origin, self.resolution * f as f32)
    }
    /// Minimum corner of voxel (0,0,0), map frame.
    pub fn origin(&self) -> Point3<f32> {
        self.origin
    }
    /// Voxel edge length, metres.
    pub fn resolution(&self) -> f32 {
        self.resolution
    }
    /// Continuous grid coordinates (voxel units; voxel `i` spans `[i, i+1)`).
    pub fn to_grid(&self, p: &Point3<f32>) -> Vector3<f32> {
        (p - self.origin) / self.resolution
    }
    /// Map-frame point of continuous grid coordinates.
    pub fn from_grid(&self, g: &Vector3<f32>) -> Point3<f32> {
        self.origin + g * self.resolution
    }
    /// The voxel containing a map-frame point, or `None` outside the grid (or not finite).
    pub fn voxel_at(&self, p: &Point3<f32>) -> Option<VoxelIndex> {
        let g = self.to_grid(p);
        if !g.iter().all(|c| c.is_finite()) {
            return None;
        }
        let f = |c: f32| libm::floorf(c);
        let (x, y, z) = (f(g.x), f(g.y), f(g.z));
        // Values far outside the grid saturate in the cast and are rejected by `checked`.
        self.dims.checked(x as i32, y as i32, z as i32)
    }
    /// Centre of a voxel in the map frame.
    pub fn center(&self, v: VoxelIndex) -> Point3<f32> {
        let g = Vector3::new(f32::from(v.x) + 0.5, f32::from(v.y) + 0.5, f32::from(v.z) + 0.5);
        self.from_grid(&g)
    }
}

/// The occupancy state of one voxel.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Occupancy {
    /// Never observed.
    Unknown,
    /// Observed, log-odds below 0.
    Free,
    /// Observed, log-odds above 0.
    Occupied,
    /// Observed, but the evidence cancels out (log-odds exactly 0).
    Uncertain,
}

/// Log-odds update parameters, in log-odds units.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LogOddsParams {
    /// Added for a measured endpoint.
    pub hit: f32,
    /// Added for a voxel a ray passed through.
    pub miss: f32,
    /// Lower clamp.
    pub min: f32,
    /// Upper clamp.
    pub max: f32,
}

impl Default for LogOddsParams {
    /// OctoMap's defaults.
    fn default() -> Self {
        Self {
            hit: 0.85,
            miss: -0.4,
            min: -2.0,
            max: 3.5,
        }
    }
}

/// [`LogOddsParams`] converted to the map's fixed point.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct FixedParams {
    hit: i8,
    miss: i8,
    min: i8,
    max: i8,
}

impl FixedParams {
    fn from(p: &LogOddsParams) -> Self {
        let q = |v: f32| {
            let s = libm::roundf(v * LOG_ODDS_SCALE);
            if s.is_nan() {
                0
            } else {
                s.clamp(f32::from(OBSERVED_MIN), 127.0) as i8
            }
        };
        let min = q(p.min).min(-1);
        let max = q(p.max).max(1);
        Self {
            hit: q(p.hit).max(1),
            miss: q(p.miss).min(-1),
            min,
            max,
        }
    }
}

/// Stored value of a voxel that was never observed.
pub const UNKNOWN: i8 = i8::MIN;
/// Stored value of an unknown voxel the planner sealed.
pub const SEALED: i8 = i8::MIN + 1;
/// Most negative stored value of an observed voxel (the clamp never goes below it).
const OBSERVED_MIN: i8 = i8::MIN + 2;

/// True for the stored value of an observed voxel (free, occupied or uncertain).
#[inline(always)]
pub(crate) const fn stored_observed(lo: i8) -> bool {
    lo > SEALED
}

/// True for the stored value of an observed free voxel ([`Occupancy::Free`]).
#[inline(always)]
pub(crate) const fn stored_free(lo: i8) -> bool {
    lo > SEALED && lo < 0
}

/// True for a stored value the vehicle keeps its radius from: occupied, uncertain or sealed.
#[inline(always)]
pub(crate) const fn stored_blocks(lo: i8) -> bool {
    lo == SEALED || lo >= 0
}

/// `u32` words of the per-frame "touched" bitset a grid of `dims` needs: one bit per voxel.
pub const fn touched_words(dims: &Dims) -> usize {
    (dims.nx.get() * dims.ny.get() * dims.nz.get()).div_ceil(32)
}

/// The pooled stored value of the fine voxels in the block of `factor` voxels a side from
/// `corner` (clipped to the fine grid): see [`VoxelMap::pool_from`].
fn pool(fine: &VoxelMap<'_>, corner: [usize; 3], factor: usize) -> i8 {
    let d = fine.dims();
    let (mut blocks, mut unknown, mut free) = (None::<i8>, 0u32, None::<i8>);
    for z in corner[2]..(corner[2] + factor).min(d.nz()) {
        for y in corner[1]..(corner[1] + factor).min(d.ny()) {
            for x in corner[0]..(corner[0] + factor).min(d.nx()) {
                let lo = fine
                    .log_odds
                    .get((z * d.ny() + y) * d.nx() + x)
                    .copied()
                    .unwrap_or(UNKNOWN);
                if stored_blocks(lo) && lo != SEALED {
                    blocks = Some(blocks.map_or(lo, |b| b.max(lo)));
                } else if stored_free(lo) {
                    free = Some(free.map_or(lo, |f| f.max(lo)));
                } else {
                    unknown += 1;
                }
            }
        }
    }
    match (blocks, free) {
        (Some(b), _) => b,
        (None, Some(f)) if unknown == 0 => f,
        _ => UNKNOWN,
    }
}

/// Counts of voxels by state.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct MapCounts {
    /// Observed free voxels.
    pub free: u32,
    /// Observed occupied voxels.
    pub occupied: u32,
    /// Never observed voxels.
    pub unknown: u32,
    /// Observed voxels with cancelling evidence.
    pub uncertain: u32,
    /// Unknown voxels the planner sealed.
    pub sealed: u32,
}

/// A fixed-capacity occupancy map over caller-provided storage.
#[derive(Debug)]
pub struct VoxelMap<'a> {
    geometry: MapGeometry,
    params: FixedParams,
    log_odds: &'a mut [i8],
    touched: &'a mut [u32],
    surface: &'a mut [[i32; 2]],
}

impl<'a> VoxelMap<'a> {
    /// Wraps storage of at least `dims.len()` log-odds bytes and [`touched_words`] bitset
    /// words; everything starts unknown.
    pub fn new(
        geometry: MapGeometry,
        params: LogOddsParams,
        log_odds: &'a mut [i8],
        touched: &'a mut [u32],
    ) -> Result<Self, MapError> {
        let dims = geometry.dims();
        let needed = dims.len();
        let words = touched_words(&dims);
        let (log_odds_len, touched_len) = (log_odds.len(), touched.len());
        let log_odds = log_odds.get_mut(..needed).ok_or(MapError::StorageTooSmall {
            needed,
            got: log_odds_len,
        })?;
        let touched = touched.get_mut(..words).ok_or(MapError::StorageTooSmall {
            needed: words,
            got: touched_len,
        })?;
        log_odds.fill(UNKNOWN);
        touched.fill(0);
        Ok(Self {
            geometry,
            params: FixedParams::from(&params),
            log_odds,
            touched,
            surface: &mut [],
        })
    }

    /// Adds the per-voxel surface estimate noisy depth is integrated with (two words per voxel;
    /// see [`crate::mapping::integrate`]). Shorter storage leaves the map without it: noisy frames are
    /// then decided by the per-frame vote alone.
    pub fn with_surface(mut self, surface: &'a mut [[i32; 2]]) -> Self {
        let n = self.geometry.dims.len();
        if let Some(s) = surface.get_mut(..n) {
            s.fill([0, 0]);
            self.surface = s;
        }
        self
    }

    /// The surface estimate's words (empty without one).
    pub(crate) fn surface(&self) -> &[[i32; 2]] {
        self.surface
    }
    /// The surface estimate's words, to update.
    pub(crate) fn surface_mut(&mut self) -> &mut [[i32; 2]] {
        self.surface
    }

    /// Geometry of the grid.
    pub fn geometry(&self) -> &MapGeometry {
        &self.geometry
    }
    /// Grid dimensions.
    pub fn dims(&self) -> Dims {
        self.geometry.dims
    }

    /// Starts a new frame: afterwards every voxel accepts one more update.
    pub fn begin_frame(&mut self) {
        self.touched.fill(0);
    }

    /// Applies a hit to voxel `i` unless it was already updated this frame. Returns whether it
    /// was applied.
    pub fn apply_hit(&mut self, i: usize) -> bool {
        self.apply(i, self.params.hit)
    }
    /// Applies a miss to voxel `i` unless it was already updated this frame.
    pub fn apply_miss(&mut self, i: usize) -> bool {
        self.apply(i, self.params.miss)
    }

    fn apply(&mut self, i: usize, delta: i8) -> bool {
        if i >= self.log_odds.len() || !self.reserve(i) {
            return false;
        }
        self.add(i, delta);
        true
    }

    /// Adds `delta` to voxel `i`'s log-odds (unknown and sealed count as 0), clamped.
    fn add(&mut self, i: usize, delta: i8) {
        if let Some(lo) = self.log_odds.get_mut(i) {
            let before = if *lo <= SEALED { 0 } else { *lo };
            *lo = before
                .saturating_add(delta)
                .clamp(self.params.min, self.params.max);
        }
    }

    /// Reserves voxel `i`'s one update of this frame without changing it, so that
    /// [`apply_hit`](Self::apply_hit) and [`apply_miss`](Self::apply_miss) refuse it until
    /// [`apply_reserved`](Self::apply_reserved) decides. Returns whether it was still free to
    /// update.
    pub(crate) fn reserve(&mut self, i: usize) -> bool {
        let bit = 1u32 << (i & 31);
        match self.touched.get_mut(i >> 5) {
            Some(word) if *word & bit == 0 => {
                *word |= bit;
                true
            }
            _ => false,
        }
    }

    /// Applies a hit (`true`) or a miss to a voxel [`reserve`](Self::reserve)d this frame.
    pub(crate) fn apply_reserved(&mut self, i: usize, hit: bool) {
        self.add(i, if hit { self.params.hit } else { self.params.miss });
    }

    /// Sets a voxel [`reserve`](Self::reserve)d this frame to log-odds `value`, clamped.
    pub(crate) fn set_reserved(&mut self, i: usize, value: f32) {
        let q = libm::roundf(value * LOG_ODDS_SCALE)
            .clamp(f32::from(self.params.min), f32::from(self.params.max)) as i8;
        if let Some(lo) = self.log_odds.get_mut(i) {
            *lo = q;
        }
    }

    /// Marks an unknown voxel free (space the vehicle's own body occupies). Observed voxels are
    /// left alone. Returns whether the voxel changed.
    pub fn mark_traversed(&mut self, i: usize) -> bool {
        match self.log_odds.get(i) {
            Some(&lo) if lo <= SEALED => self.apply(i, self.params.miss),
            _ => false,
        }
    }

    /// Forgets an occupied or uncertain voxel: it becomes unknown, as if never observed, so the
    /// planner treats it as unexplored space and looks at it again (see
    /// [`Reopening`](crate::planning::domain::Reopening)). Free, unknown and sealed voxels are left
    /// alone. Returns whether it changed.
    pub fn forget(&mut self, i: usize) -> bool {
        match self.log_odds.get_mut(i) {
            Some(lo) if *lo >= 0 => {
                *lo = UNKNOWN;
                true
            }
            _ => false,
        }
    }

    /// Seals an unknown voxel so it no longer makes frontiers. Returns whether it changed.
    pub fn seal(&mut self, i: usize) -> bool {
        match self.log_odds.get_mut(i) {
            Some(lo) if *lo == UNKNOWN => {
                *lo = SEALED;
                true
            }
            _ => false,
        }
    }

    /// Brings this map, a grid [`coarsened`](MapGeometry::coarsened) by `factor` from `fine`'s,
    /// up to date with the voxels of `fine` updated in its last frame (its touched bits): each
    /// cell over them takes the pooled state of the fine voxels it covers (those inside the fine
    /// grid). Pooling is safe, not average: a cell is occupied (the largest log-odds) if any of
    /// its voxels blocks, unknown if any is unknown (a sealed cell stays sealed), and free (the
    /// least free log-odds) only if all are free. Starts a frame on this map: the cells
    /// updated are its touched ones. Returns how many were. A `fine` of another shape updates
    /// nothing.
    pub fn pool_from(&mut self, fine: &VoxelMap<'_>, factor: usize) -> u32 {
        self.begin_frame();
        let (fd, cd) = (fine.dims(), self.dims());
        let Some(f) = u16::try_from(factor).ok().and_then(core::num::NonZeroU16::new) else {
            return 0;
        };
        if fine.geometry.coarsened(factor).ok().map(|g| g.dims) != Some(cd) {
            return 0;
        }
        let mut updated = 0u32;
        for (w, &word) in fine.touched.iter().enumerate() {
            let mut bits = word;
            while bits != 0 {
                let i = (w << 5) | bits.trailing_zeros() as usize;
                bits &= bits - 1;
                if i >= fd.len() {
                    break;
                }
                let v = fd.voxel(i);
                let c = VoxelIndex::new(v.x / f, v.y / f, v.z / f);
                let ci = cd.linear(c);
                if !self.reserve(ci) {
                    continue;
                }
                let pooled = pool(fine, [c.x, c.y, c.z].map(|k| usize::from(k) * factor), factor);
                if let Some(lo) = self.log_odds.get_mut(ci) {
                    if !(pooled == UNKNOWN && *lo == SEALED) {
                        *lo = pooled;
                    }
                    updated = updated.saturating_add(1);
                }
            }
        }
        updated
    }

    /// The stored values, one per voxel in linear order: [`UNKNOWN`], [`SEALED`], or an
    /// observed log-odds (negative free, positive occupied, 0 uncertain; see
    /// [`stored_observed`], [`stored_blocks`]). For passes over the whole grid that classify
    /// voxels row by row.
    #[inline]
    pub(crate) fn stored(&self) -> &[i8] {
        self.log_odds
    }

    /// State of voxel `i` (out-of-range indices read as unknown).
    #[inline]
    pub fn occupancy(&self, i: usize) -> Occupancy {
        match self.log_odds.get(i) {
            Some(&lo) if lo > SEALED => match lo {
                l if l < 0 => Occupancy::Free,
                l if l > 0 => Occupancy::Occupied,
                _ => Occupancy::Uncertain,
            },
            _ => Occupancy::Unknown,
        }
    }
    /// True if voxel `i` is observed free.
    #[inline]
    pub fn is_free(&self, i: usize) -> bool {
        self.occupancy(i) == Occupancy::Free
    }
    /// True if voxel `i` was never observed.
    #[inline]
    pub fn is_unknown(&self, i: usize) -> bool {
        self.log_odds.get(i).is_none_or(|&lo| !stored_observed(lo))
    }
    /// True if voxel `i` is unknown and sealed by the planner.
    #[inline]
    pub fn is_sealed(&self, i: usize) -> bool {
        self.log_odds.get(i) == Some(&SEALED)
    }
    /// True if voxel `i` is unknown and not sealed: space that exploration should still look at.
    #[inline]
    pub fn is_unexplored(&self, i: usize) -> bool {
        self.log_odds.get(i).is_none_or(|&lo| lo == UNKNOWN)
    }
    /// Log-odds of voxel `i` in log-odds units (0 for unknown voxels).
    pub fn log_odds(&self, i: usize) -> f32 {
        match self.occupancy(i) {
            Occupancy::Unknown => 0.0,
            _ => f32::from(self.log_odds.get(i).copied().unwrap_or(0)) / LOG_ODDS_SCALE,
        }
    }

    /// A frontier voxel: free, with at least one unexplored face neighbour inside the grid.
    /// (Voxels beyond the grid edge are not unknown space: the grid is the exploration volume.)
    pub fn is_frontier(&self, v: VoxelIndex) -> bool {
        let dims = self.dims();
        if !self.is_free(dims.linear(v)) {
            return false;
        }
        let mut frontier = false;
        dims.for_each_face_neighbour(v, |n| frontier |= self.is_unexplored(n));
        frontier
    }

    /// Counts the [frontier](Self::is_frontier) voxels (one pass over the grid, six neighbour
    /// reads per free voxel).
    pub fn frontier_voxels(&self) -> u32 {
        let dims = self.dims();
        (0..self.log_odds.len())
            .filter(|&i| self.is_frontier(dims.voxel(i)))
            .fold(0u32, |n, _| n.saturating_add(1))
    }

    /// Counts voxels by state (one pass over the grid).
    pub fn counts(&self) -> MapCounts {
        let mut c = MapCounts::default();
        for i in 0..self.log_odds.len() {
            match self.occupancy(i) {
                Occupancy::Free => c.free += 1,
                Occupancy::Occupied => c.occupied += 1,
                Occupancy::Uncertain => c.uncertain += 1,
                Occupancy::Unknown => {
                    c.unknown += 1;
                    if self.is_sealed(i) {
                        c.sealed += 1;
                    }
                }
            }
        }
        c
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn geometry(n: usize) -> MapGeometry {
        MapGeometry::new(Dims::new(n, n, n).unwrap(), Point3::origin(), 0.1).unwrap()
    }

    #[test]
    fn geometry_too_far_out_for_f32_is_refused() {
        // Found by the depth_integration fuzzer: an origin at 1.3e7 m with 0.5 m voxels put a
        // voxel centre (an escape goal) outside the grid after rounding.
        let d = Dims::new(10, 10, 10).unwrap();
        assert_eq!(
            MapGeometry::new(d, Point3::new(1.3e7, 0.0, 0.0), 0.5).err(),
            Some(MapError::BadGeometry)
        );
        assert_eq!(
            MapGeometry::new(d, Point3::origin(), f32::MAX).err(),
            Some(MapError::BadGeometry)
        );
        let g = MapGeometry::new(d, Point3::new(-1000.0, 2000.0, 0.0), 0.05).unwrap();
        let v = VoxelIndex::new(9, 9, 9);
        assert_eq!(g.voxel_at(&g.center(v)), Some(v));
    }

    #[test]
    fn world_voxel_conversion_rejects_outside() {
        let g = geometry(10);
        assert_eq!(
            g.voxel_at(&Point3::new(0.05, 0.15, 0.95)),
            Some(VoxelIndex::new(0, 1, 9))
        );
        assert_eq!(g.voxel_at(&Point3::new(-0.01, 0.5, 0.5)), None);
        assert_eq!(g.voxel_at(&Point3::new(0.5, 1.0, 0.5)), None);
        assert_eq!(g.voxel_at(&Point3::new(f32::NAN, 0.5, 0.5)), None);
        assert_eq!(g.voxel_at(&Point3::new(1e30, 0.5, 0.5)), None);
        let c = g.center(VoxelIndex::new(3, 4, 5));
        assert!((c - Point3::new(0.35, 0.45, 0.55)).norm() < 1e-6);
    }

    #[test]
    fn log_odds_follow_octomap_defaults_and_clamp() {
        let g = geometry(4);
        let (mut lo, mut st) = ([0i8; 64], [0u32; 2]);
        let mut map = VoxelMap::new(g, LogOddsParams::default(), &mut lo, &mut st).unwrap();
        assert_eq!(map.occupancy(0), Occupancy::Unknown);
        assert!(map.apply_hit(0));
        assert!(!map.apply_hit(0), "second update in one frame must be refused");
        assert!((map.log_odds(0) - 0.85).abs() < 1e-6);
        for _ in 0..10 {
            map.begin_frame();
            map.apply_hit(0);
        }
        assert!((map.log_odds(0) - 3.5).abs() < 1e-6);
        for _ in 0..20 {
            map.begin_frame();
            map.apply_miss(0);
        }
        assert!((map.log_odds(0) + 2.0).abs() < 1e-6);
        assert_eq!(map.occupancy(0), Occupancy::Free);
    }

    #[test]
    fn every_frame_accepts_one_update_per_voxel() {
        let g = geometry(2);
        let (mut lo, mut st) = ([0i8; 8], [0u32; 1]);
        let mut map = VoxelMap::new(g, LogOddsParams::default(), &mut lo, &mut st).unwrap();
        map.apply_miss(1);
        for _ in 0..1000 {
            map.begin_frame();
            assert!(map.apply_hit(0), "a new frame must accept an update");
        }
        assert_eq!(map.occupancy(1), Occupancy::Free);
    }

    #[test]
    fn contradictory_evidence_is_not_unknown() {
        let g = geometry(2);
        let (mut lo, mut st) = ([0i8; 8], [0u32; 1]);
        let params = LogOddsParams {
            hit: 0.5,
            miss: -0.5,
            min: -2.0,
            max: 3.5,
        };
        let mut map = VoxelMap::new(g, params, &mut lo, &mut st).unwrap();
        map.apply_hit(0);
        map.begin_frame();
        map.apply_miss(0);
        assert_eq!(map.occupancy(0), Occupancy::Uncertain);
        assert!(!map.is_unknown(0));
    }

    #[test]
    fn storage_too_small_is_an_error() {
        let g = geometry(4);
        let (mut lo, mut st) = ([0i8; 63], [0u32; 2]);
        assert_eq!(
            VoxelMap::new(g, LogOddsParams::default(), &mut lo, &mut st).unwrap_err(),
            MapError::StorageTooSmall { needed: 64, got: 63 }
        );
        let (mut lo, mut st) = ([0i8; 64], [0u32; 1]);
        assert_eq!(
            VoxelMap::new(g, LogOddsParams::default(), &mut lo, &mut st).unwrap_err(),
            MapError::StorageTooSmall { needed: 2, got: 1 }
        );
        assert_eq!(touched_words(&Dims::new(64, 64, 32).unwrap()), 4096);
    }

    #[test]
    fn sealing_is_forgotten_on_observation() {
        let g = geometry(3);
        let (mut lo, mut st) = ([0i8; 27], [0u32; 1]);
        let mut map = VoxelMap::new(g, LogOddsParams::default(), &mut lo, &mut st).unwrap();
        assert!(map.seal(5));
        assert!(map.is_sealed(5) && !map.is_unexplored(5));
        map.apply_miss(5);
        assert_eq!(map.occupancy(5), Occupancy::Free);
        assert!(!map.is_sealed(5));
    }

    #[test]
    fn extreme_parameters_never_produce_the_unknown_sentinels() {
        let g = geometry(2);
        let (mut lo, mut st) = ([0i8; 8], [0u32; 1]);
        let params = LogOddsParams {
            hit: 100.0,
            miss: -100.0,
            min: -100.0,
            max: 100.0,
        };
        let mut map = VoxelMap::new(g, params, &mut lo, &mut st).unwrap();
        for _ in 0..4 {
            map.begin_frame();
            map.apply_miss(0);
            map.apply_hit(1);
        }
        assert_eq!(map.occupancy(0), Occupancy::Free);
        assert_eq!(map.occupancy(1), Occupancy::Occupied);
        assert!(!map.is_unknown(0) && !map.is_sealed(0));
    }

    #[test]
    fn a_coarser_grid_pools_safely_from_the_voxels_a_frame_touched() {
        // A 5 × 4 × 2 grid under cells of 2 × 2 × 2: 3 × 2 × 1, the last column half outside.
        let fine_g = MapGeometry::new(Dims::new(5, 4, 2).unwrap(), Point3::origin(), 0.1).unwrap();
        let coarse_g = fine_g.coarsened(2).unwrap();
        assert_eq!(coarse_g.dims().extent(), [3, 2, 1]);
        assert_eq!(coarse_g.resolution(), 0.2);
        let (mut flo, mut fst) = ([0i8; 40], [0u32; 2]);
        let (mut clo, mut cst) = ([0i8; 6], [0u32; 1]);
        let mut fine = VoxelMap::new(fine_g, LogOddsParams::default(), &mut flo, &mut fst).unwrap();
        let mut coarse = VoxelMap::new(coarse_g, LogOddsParams::default(), &mut clo, &mut cst).unwrap();
        let fi = |x, y, z| fine_g.dims().linear(VoxelIndex::new(x, y, z));
        fine.begin_frame();
        // Cell (0,0,0): all eight voxels free. Cell (1,0,0): seven free, one occupied. Cell
        // (2,0,0): its two voxels inside the grid free... bar one left unknown.
        for z in 0..2 {
            for y in 0..2 {
                for x in 0..5 {
                    if (x, y, z) != (4, 1, 1) {
                        fine.apply_miss(fi(x, y, z));
                    }
                }
            }
        }
        // Cell (0,1,0) is left untouched: unknown. Cell (1,1,0): free but for one unknown voxel.
        for z in 0..2 {
            for y in 2..4 {
                for x in 2..4 {
                    if (x, y, z) != (3, 3, 1) {
                        fine.apply_miss(fi(x, y, z));
                    }
                }
            }
        }
        fine.begin_frame();
        for z in 0..2 {
            for y in 0..4 {
                for x in 0..5 {
                    let i = fi(x, y, z);
                    if !fine.is_unknown(i) {
                        if (x, y, z) == (3, 1, 0) {
                            fine.apply_hit(i);
                            fine.apply_hit(i);
                        } else {
                            fine.reserve(i);
                        }
                    }
                }
            }
        }
        assert_eq!(fine.occupancy(fi(3, 1, 0)), Occupancy::Occupied);
        assert_eq!(
            coarse.pool_from(&fine, 2),
            4,
            "the four cells over touched voxels"
        );
        let ci = |x, y| coarse_g.dims().linear(VoxelIndex::new(x, y, 0));
        assert_eq!(coarse.occupancy(ci(0, 0)), Occupancy::Free);
        assert_eq!(
            coarse.occupancy(ci(1, 0)),
            Occupancy::Occupied,
            "one occupied voxel blocks"
        );
        assert!(
            coarse.is_unexplored(ci(2, 0)),
            "one unknown voxel keeps the cell unknown"
        );
        assert!(coarse.is_unexplored(ci(0, 1)), "nothing seen");
        assert!(coarse.is_unexplored(ci(1, 1)));
        assert!(coarse.is_unknown(ci(2, 1)));
        // A sealed cell stays sealed while its voxels are unknown, and opens once they are seen.
        assert!(coarse.seal(ci(2, 0)));
        fine.begin_frame();
        fine.reserve(fi(4, 0, 0));
        coarse.pool_from(&fine, 2);
        assert!(coarse.is_sealed(ci(2, 0)));
        fine.begin_frame();
        fine.apply_miss(fi(4, 1, 1));
        coarse.pool_from(&fine, 2);
        assert_eq!(coarse.occupancy(ci(2, 0)), Occupancy::Free);
        // A grid of another shape updates nothing.
        let other = MapGeometry::new(Dims::new(2, 2, 1).unwrap(), Point3::origin(), 0.2).unwrap();
        let (mut olo, mut ost) = ([0i8; 4], [0u32; 1]);
        let mut wrong = VoxelMap::new(other, LogOddsParams::default(), &mut olo, &mut ost).unwrap();
        assert_eq!(wrong.pool_from(&fine, 2), 0);
    }
}
