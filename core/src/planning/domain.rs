//! The domain of the Laplace problem and its boundary conditions.
//!
//! From the map, the domain is built in three steps:
//!
//! 1. **Candidates** — observed free voxels.
//! 2. **Erosion** — candidates closer than the vehicle radius to an occupied, uncertain or
//!    sealed voxel, or to the grid edge, are removed: obstacles are inflated by the vehicle's
//!    size. Candidates closer than the radius to *unexplored* space become *fringe*: unknown
//!    space may hide a wall, so the vehicle's body must not reach into it either. What remains
//!    is safe: the whole body fits in observed free space.
//! 3. **The vehicle's component** — a flood fill from the vehicle voxel through face-connected
//!    safe voxels. The vehicle voxel becomes the source (Dirichlet φ = 1); reached voxels with a
//!    fringe face neighbour (or, with a zero radius, an unexplored one) become frontiers
//!    (Dirichlet φ = 0): the closest the vehicle may get to the unknown, looking into it. The
//!    fill does not continue through them; the rest are interior unknowns. Safe voxels not
//!    reached — other components — are excluded, never solved.
//!
//! Every face between a domain voxel and a non-domain voxel is a wall with zero flux: the
//! cell-centred finite-volume Laplacian simply omits it (see [`crate::planning::solve`]).
//!
//! Before a planner ends an exploration it may build the domain once more with weakly seen
//! occupied voxels taken for free space ([`build_doubting`]): if that reaches a frontier, noise
//! closed a passage, and [`Reopening`] has the planner look at those voxels again.
//!
//! The flood fill uses a caller-provided ring queue of any capacity. When the queue is full,
//! reached voxels are marked pending and collected by a later sweep over the grid, so a small
//! queue costs time, never correctness.

use heapless::Vec as HVec;
use nalgebra::Point3;

use crate::mapping::integrate::traverse;

use crate::mapping::map::{
    stored_blocks, stored_free, stored_observed, Dims, VoxelIndex, VoxelMap, LOG_ODDS_SCALE, SEALED, UNKNOWN,
};

/// Role of a voxel in the Laplace problem. After [`build`] only `Outside`, `Interior`,
/// `Frontier` and `Source` remain; the other variants are transient states of the build.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[repr(u8)]
pub enum Label {
    /// Not part of the problem (unknown, occupied, inflated or another component).
    #[default]
    Outside = 0,
    /// Unknown φ: the mean of its in-domain neighbours.
    Interior = 1,
    /// Dirichlet φ = 0: a free voxel next to unexplored space.
    Frontier = 2,
    /// Dirichlet φ = 1: the vehicle.
    Source = 3,
    /// Build state: free and not inflated, not reached yet.
    Candidate = 4,
    /// Build state: reached, waiting in the queue.
    Queued = 5,
    /// Build state: reached, waiting for a queue slot.
    Pending = 6,
    /// Build state: free and clear of obstacles, but within the vehicle radius of unexplored
    /// space.
    Fringe = 7,
}

impl Label {
    /// True for voxels that take part in the problem (interior or Dirichlet).
    #[inline]
    pub fn in_domain(self) -> bool {
        matches!(self, Label::Interior | Label::Frontier | Label::Source)
    }
}

/// Largest supported inflation radius, voxels.
pub const MAX_INFLATION_VOXELS: usize = 6;
/// Most rows (dy, dz) the inflation stencil reaches: (2 · 7 + 1)² at the largest radius.
const STENCIL_ROWS: usize = 225;
/// Words of the "row holds an observed voxel" bitset [`inflate`] keeps on the stack: 8192 rows
/// (1 KiB). Grids with more rows (ny · nz) test every unknown voxel.
const OBSERVED_ROW_WORDS: usize = 256;

/// The set of voxel offsets within the vehicle radius, precomputed once.
///
/// A ball's offsets with the same `(dy, dz)` are an interval `[−w, w]` of `dx`, so the stencil
/// keeps one `[dy, dz, w]` per row (675 bytes at the largest radius) instead of every offset
/// (3.8 KiB): the explorer carries a stencil, and on the MCU its construction passes the
/// explorer through the stack by value.
#[derive(Debug, Clone)]
pub struct InflationStencil {
    /// `[dy, dz, w]` in `dz`, then `dy` order; the centre row leaves out `dx = 0`.
    rows: HVec<[i8; 3], STENCIL_ROWS>,
    len: u16,
    radius_voxels: f32,
}

/// Domain-building errors.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum DomainError {
    /// The vehicle radius is negative, not finite, or larger than the supported maximum.
    BadRadius,
    /// A storage slice is shorter than the grid.
    StorageTooSmall,
    /// The vehicle voxel is not observed free (it is occupied, uncertain or unknown).
    VehicleNotFree,
    /// The vehicle voxel is free but closer than the vehicle radius to an obstacle.
    VehicleInInflatedSpace,
}

/// The planning radius's stencil, and a narrower radius a planner may fall back on to leave a
/// *pocket* ([`is_pocket`]): a spot where the planning radius leaves the vehicle cut off from
/// the free space its body fits through. The narrower stencil is rebuilt when it is needed, not
/// stored beside the other: the MCU has no room for two.
#[derive(Debug, Clone)]
pub struct Inflation {
    stencil: InflationStencil,
    radius: f32,
    narrow_radius: f32,
    resolution: f32,
    narrowed: bool,
}

impl Inflation {
    /// `radius` as [`InflationStencil::new`] takes it; `narrow_radius` the fallback, unused
    /// unless `0 < narrow_radius < radius` (0: none).
    pub fn new(radius: f32, narrow_radius: f32, resolution: f32) -> Result<Self, DomainError> {
        let stencil = InflationStencil::new(radius, resolution)?;
        if !(narrow_radius.is_finite() && narrow_radius >= 0.0) {
            return Err(DomainError::BadRadius);
        }
        // A narrower radius the stencil cannot hold is refused now, not when it is needed.
        if narrow_radius > 0.0 && narrow_radius < radius {
            InflationStencil::new(narrow_radius, resolution)?;
        }
        Ok(Self {
            stencil,
            radius,
            narrow_radius: if narrow_radius < radius {
                narrow_radius
            } else {
                0.0
            },
            resolution,
            narrowed: false,
        })
    }

    /// The stencil in use.
    pub fn stencil(&self) -> &InflationStencil {
        &self.stencil
    }

    /// True while the narrower radius is in use.
    pub fn is_narrowed(&self) -> bool {
        self.narrowed
    }

    /// Switches to the narrower radius. False if there is none or it is in use already.
    pub fn narrow(&mut self) -> bool {
        if self.narrowed || self.narrow_radius <= 0.0 {
            return false;
        }
        self.narrowed = self.rebuild(self.narrow_radius);
        self.narrowed
    }

    /// Back to the planning radius. Returns whether the narrower one was in use.
    pub fn widen(&mut self) -> bool {
        let was = self.narrowed;
        if was {
            self.narrowed = !self.rebuild(self.radius);
        }
        was
    }

    /// Replaces the stencil by one for `radius`. Kept out of line: its frame holds a whole
    /// stencil, which plans that never switch should not carry on their stack.
    #[inline(never)]
    fn rebuild(&mut self, radius: f32) -> bool {
        match InflationStencil::new(radius, self.resolution) {
            Ok(s) => {
                self.stencil = s;
                true
            }
            Err(_) => false,
        }
    }
}

/// Whether a vehicle whose planning radius gave the component `wide`, with no frontier in it,
/// stands in a *pocket*: the narrower radius's component `narrow` holds a frontier and at least
/// twice as many voxels. Then the planning radius, not the exploration, is what ended it — a
/// start between a cabinet top and the ceiling, or a nook noise has narrowed — and the vehicle
/// may take the narrower radius until it is out. Late in an exploration the vehicle stands in
/// the space it has explored, which both radii hold nearly alike, so a remnant only the
/// narrower radius reaches does not make a pocket (flying to each of those lengthened paths by
/// a fifth for a tenth of a point of coverage: docs/RESULTS.md, "The old radius as a
/// fallback").
pub fn is_pocket(wide: &DomainStats, narrow: &DomainStats) -> bool {
    let size = |s: &DomainStats| u64::from(s.interior) + u64::from(s.frontier);
    wide.frontier == 0 && narrow.frontier > 0 && size(narrow) >= 2 * size(wide)
}

/// The planners' domain for a way to the voxel `target` (linear index; home): built at the
/// planning radius, or at `inflation`'s narrower one where the planning radius leaves the
/// vehicle inside its inflated space after a plan on the narrower radius (`was_narrow`: on its
/// way out of a pocket), or leaves `target` out of the vehicle's component (home in a pocket:
/// a cramped start). Returns the build and whether the narrower radius made it; `target` may
/// still lie outside the domain, for the caller to refuse.
pub fn build_towards(
    map: &VoxelMap<'_>,
    inflation: &mut Inflation,
    vehicle: VoxelIndex,
    target: usize,
    was_narrow: bool,
    labels: &mut [Label],
    queue: &mut [u32],
) -> (Result<DomainStats, DomainError>, bool) {
    let built = build(map, inflation.stencil(), vehicle, labels, queue);
    let reaches = |labels: &[Label]| labels.get(target).is_some_and(|l| l.in_domain());
    let retry = match built {
        Err(DomainError::VehicleInInflatedSpace) => was_narrow,
        Ok(_) => !reaches(labels),
        Err(_) => false,
    };
    match retry.then(|| try_narrower(map, inflation, vehicle, labels, queue, |_, l| reaches(l))) {
        Some(Some(narrow)) => (Ok(narrow), true),
        // `labels` hold the planning radius's domain again: `built` describes them.
        _ => (built, false),
    }
}

/// Switches `inflation` to its narrower radius and builds the vehicle's component there. If
/// `keep` accepts that build (its stats and labels), returns it with the narrower radius left
/// in use; otherwise switches back and rebuilds the planning radius's domain in `labels`. `None`
/// at once, `labels` untouched, without a narrower radius or with it in use already.
fn try_narrower(
    map: &VoxelMap<'_>,
    inflation: &mut Inflation,
    vehicle: VoxelIndex,
    labels: &mut [Label],
    queue: &mut [u32],
    keep: impl Fn(&DomainStats, &[Label]) -> bool,
) -> Option<DomainStats> {
    if !inflation.narrow() {
        return None;
    }
    match build(map, inflation.stencil(), vehicle, labels, queue) {
        Ok(narrow) if keep(&narrow, labels) => Some(narrow),
        _ => {
            inflation.widen();
            let _ = build(map, inflation.stencil(), vehicle, labels, queue);
            None
        }
    }
}

/// The planners' pocket test: with the planning radius's component `wide` (no frontier in it)
/// built, switches `inflation` to its narrower radius and builds the vehicle's component there.
/// In a [pocket](is_pocket) it returns true and leaves the narrower radius and its domain in
/// `labels`; otherwise it returns false with the planning radius and its domain back. False at
/// once without a narrower radius, or with it in use already.
pub fn narrow_in_pocket(
    map: &VoxelMap<'_>,
    inflation: &mut Inflation,
    vehicle: VoxelIndex,
    wide: &DomainStats,
    labels: &mut [Label],
    queue: &mut [u32],
) -> bool {
    try_narrower(map, inflation, vehicle, labels, queue, |narrow, _| {
        is_pocket(wide, narrow)
    })
    .is_some()
}

impl InflationStencil {
    /// Offsets of every voxel whose cube comes closer than `radius` to the centre of the
    /// voxel at the origin — an obstacle there forbids that centre.
    pub fn new(radius: f32, resolution: f32) -> Result<Self, DomainError> {
        let r = radius / resolution;
        if !(r.is_finite() && r >= 0.0 && r <= MAX_INFLATION_VOXELS as f32) {
            return Err(DomainError::BadRadius);
        }
        let mut rows = HVec::new();
        let mut len = 0u16;
        // reach ≤ ⌈6.5⌉ = 7: at most 15 · 15 rows (`STENCIL_ROWS`), so no push can fail.
        let reach = libm::ceilf(r + 0.5) as i32;
        for dz in -reach..=reach {
            for dy in -reach..=reach {
                // The distance grows with |dx|: the row is [−w, w] for the last dx inside.
                let inside = |dx: i32| cube_distance_sq([dx, dy, dz]) < r * r;
                let Some(w) = (0..=reach).take_while(|&dx| inside(dx)).last() else {
                    continue;
                };
                let centre = (dy, dz) == (0, 0);
                if centre && w == 0 {
                    continue;
                }
                rows.push([dy as i8, dz as i8, w as i8])
                    .map_err(|_| DomainError::BadRadius)?;
                len += (2 * w + 1 - i32::from(centre)) as u16;
            }
        }
        Ok(Self {
            rows,
            len,
            radius_voxels: r,
        })
    }
    /// The offsets, as signed voxel steps, in `dz`, `dy`, `dx` order.
    pub fn offsets(&self) -> impl Iterator<Item = [i32; 3]> + '_ {
        self.rows.iter().flat_map(|&[dy, dz, w]| {
            let (dy, dz, w) = (i32::from(dy), i32::from(dz), i32::from(w));
            // The centre row skips dx = 0; every other row's second range is empty.
            let (left_end, right_start) = if (dy, dz) == (0, 0) { (-1, 1) } else { (w, w + 1) };
            (-w..=left_end).chain(right_start..=w).map(move |dx| [dx, dy, dz])
        })
    }
    /// The voxels of the stencil around `v` in a grid of `dims`, as runs of linear indices:
    /// one per row that lies in the grid, clipped to it. Unlike [`InflationStencil::offsets`]
    /// the centre row's run holds `v` itself.
    pub fn runs(&self, dims: &Dims, v: VoxelIndex) -> impl Iterator<Item = core::ops::Range<usize>> + '_ {
        let (nx, ny, nz) = (dims.nx(), dims.ny(), dims.nz());
        let (x, y, z) = (usize::from(v.x), usize::from(v.y), usize::from(v.z));
        self.rows.iter().filter_map(move |&[dy, dz, w]| {
            let ty = y.checked_add_signed(isize::from(dy)).filter(|&t| t < ny)?;
            let tz = z.checked_add_signed(isize::from(dz)).filter(|&t| t < nz)?;
            let w = usize::from(w.unsigned_abs());
            let base = nx * (ty + ny * tz);
            Some(base + x.saturating_sub(w)..base + (x + w + 1).min(nx))
        })
    }
    /// Radius in voxels.
    pub fn radius_voxels(&self) -> f32 {
        self.radius_voxels
    }
    /// Number of offsets.
    pub fn len(&self) -> usize {
        usize::from(self.len)
    }
    /// True if the radius is too small to exclude any neighbour.
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }
}

/// Squared distance, in voxels², from a voxel centre to the cube of the voxel at offset `d`.
fn cube_distance_sq(d: [i32; 3]) -> f32 {
    d.iter()
        .map(|&c| {
            let e = (c.abs() as f32 - 0.5).max(0.0);
            e * e
        })
        .sum()
}

/// Occupied voxels whose evidence a planner may doubt: observed occupied (or uncertain) with a
/// log-odds below a threshold, and not forgotten before ([`Reopening`]). Sealed voxels are never
/// doubtful.
#[derive(Debug, Clone, Copy)]
pub struct Doubt<'d> {
    /// Stored (fixed-point) log-odds below which an occupied voxel is doubtful; 0: none is.
    below: i8,
    /// Voxels forgotten once already: their evidence stands.
    confirmed: &'d [u32],
    /// Which frontiers the doubting domain keeps ([`Doubt::lenient`]).
    lenient: bool,
}

impl Doubt<'_> {
    /// Nothing is doubtful: the ordinary domain.
    pub const NONE: Doubt<'static> = Doubt {
        below: 0,
        confirmed: &[],
        lenient: false,
    };

    /// The same doubt, keeping more frontiers in [`build_doubting`]: a frontier whose fringe is
    /// near doubtful voxels too (a doorway whose frame noise has thickened), not only those
    /// clear of every occupied voxel. It also keeps part of the band along weakly seen walls,
    /// so planners ask it only when the strict doubt finds nothing to reopen.
    pub fn lenient(self) -> Self {
        Self {
            lenient: true,
            ..self
        }
    }

    /// True if voxel `i`, stored value `lo`, keeps the vehicle its radius away.
    #[inline(always)]
    fn blocks(&self, i: usize, lo: i8) -> bool {
        stored_blocks(lo) && (lo == SEALED || lo >= self.below || self.confirmed.contains(&(i as u32)))
    }

    /// True for a doubtful voxel: one the ordinary domain keeps the vehicle away from and this
    /// doubt does not.
    fn passable(&self, map: &VoxelMap<'_>, i: usize) -> bool {
        map.stored()
            .get(i)
            .is_some_and(|&lo| stored_blocks(lo) && !self.blocks(i, lo))
    }
}

/// Most voxels one exploration forgets as doubtful ([`Reopening`]).
pub const REOPEN_CAPACITY: usize = 64;

/// "Doorways must not close under noise": before a planner ends an exploration for want of a
/// reachable frontier, it asks whether one is cut off only by *doubtful* occupied voxels — seen
/// occupied, but with a log-odds below a threshold, as a noisy stereo return leaves in the middle
/// of a narrow hall. If so, it finds where its path to that frontier, planned through the
/// doubtful voxels ([`build_doubting`]), first leaves the ordinary safe space (the *gate*), and
/// forgets the doubtful voxels within the vehicle radius of it ([`Reopening::forget_around`]):
/// they become unknown, so the ordinary domain gains a frontier there and the planner flies to
/// look at them again. A wall re-observed occupied stays; a voxel re-observed free opens the
/// passage. The vehicle never flies through a doubtful voxel: until a new frame clears it,
/// unknown space keeps the same radius as occupied space.
///
/// Planners ask twice: first keeping only frontiers whose fringe is clear of every occupied
/// voxel, then, if that found nothing to reopen, with [`Doubt::lenient`], which also keeps a
/// doorway whose frame noise has thickened with doubtful voxels.
///
/// Every voxel is forgotten at most once, and at most [`REOPEN_CAPACITY`] in all, so the
/// rule cannot keep an exploration going: once a forgotten voxel is seen occupied again it
/// counts as certain. Sealed voxels (unknown space the planner gave up on) are not doubted.
#[derive(Debug, Clone, Default)]
pub struct Reopening {
    forgotten: HVec<u32, REOPEN_CAPACITY>,
}

impl Reopening {
    /// The stored log-odds threshold for `log_odds` units (0 or less, or not finite: 0, off).
    pub fn threshold(log_odds: f32) -> i8 {
        if log_odds.is_finite() && log_odds > 0.0 {
            libm::roundf(log_odds * LOG_ODDS_SCALE).clamp(1.0, 127.0) as i8
        } else {
            0
        }
    }

    /// The doubt for a build: occupied voxels below `below` (stored units,
    /// [`Self::threshold`]) that were not forgotten before.
    pub fn doubt(&self, below: i8) -> Doubt<'_> {
        Doubt {
            below,
            confirmed: &self.forgotten,
            lenient: false,
        }
    }

    /// Voxels forgotten so far.
    pub fn forgotten(&self) -> usize {
        self.forgotten.len()
    }

    /// True once no more voxels can be forgotten.
    pub fn is_full(&self) -> bool {
        self.forgotten.is_full()
    }

    /// Forgets (makes unknown, [`VoxelMap::forget`]) the doubtful voxels at `gate` and within
    /// the vehicle radius of it: those that make it unsafe. Returns how many; 0 if there were
    /// none or no room is left.
    pub fn forget_around(
        &mut self,
        map: &mut VoxelMap<'_>,
        stencil: &InflationStencil,
        gate: VoxelIndex,
        below: i8,
    ) -> u32 {
        let dims = map.dims();
        let mut forgotten = 0;
        for d in core::iter::once([0, 0, 0]).chain(stencil.offsets()) {
            let Some(v) = dims.offset(gate, d) else { continue };
            let i = dims.linear(v);
            if !self.forgotten.is_full() && self.doubt(below).passable(map, i) && map.forget(i) {
                let _ = self.forgotten.push(i as u32);
                forgotten += 1;
            }
        }
        forgotten
    }
}

/// The first voxel the polyline from `from` through `points` crosses that the vehicle's centre
/// may not pass ([`is_safe`]), if any: whether a kept path is still clear, or where a path
/// planned through doubtful voxels leaves the safe space.
pub fn first_unsafe_along(
    map: &VoxelMap<'_>,
    stencil: &InflationStencil,
    from: &Point3<f32>,
    points: impl IntoIterator<Item = Point3<f32>>,
) -> Option<VoxelIndex> {
    let geometry = *map.geometry();
    let mut unsafe_voxel = None;
    let mut from = *from;
    for to in points {
        traverse(&geometry, &from, &to, |v| {
            if !is_safe(map, stencil, v) {
                unsafe_voxel = Some(v);
            }
            unsafe_voxel.is_none()
        });
        if unsafe_voxel.is_some() {
            break;
        }
        from = to;
    }
    unsafe_voxel
}

/// What a domain build found.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct DomainStats {
    /// Observed free voxels.
    pub free: u32,
    /// Free voxels removed by inflation.
    pub inflated: u32,
    /// Interior unknowns of the vehicle's component.
    pub interior: u32,
    /// Frontier voxels (φ = 0) of the vehicle's component.
    pub frontier: u32,
    /// Safe voxels in other components (excluded).
    pub excluded: u32,
    /// Free voxels within the vehicle radius of unexplored space.
    pub fringe: u32,
    /// Times the flood-fill queue overflowed and a sweep collected pending voxels.
    pub queue_sweeps: u32,
}

/// Builds the labels of the vehicle's component. `labels` and `queue` need at least
/// `dims.len()` and 1 entries respectively.
pub fn build(
    map: &VoxelMap<'_>,
    stencil: &InflationStencil,
    vehicle: VoxelIndex,
    labels: &mut [Label],
    queue: &mut [u32],
) -> Result<DomainStats, DomainError> {
    build_doubting(map, stencil, vehicle, labels, queue, &Doubt::NONE)
}

/// [`build`] with the occupied voxels `doubt` calls doubtful taken for free space: they
/// neither inflate nor leave the domain, and only frontiers the ordinary domain would have
/// (were it connected to them) stay frontiers. With [`Doubt::NONE`] this is [`build`].
/// Planners use it only to ask whether a frontier is cut off by doubtful evidence alone
/// ([`Reopening`]); they never fly through its extra voxels.
pub fn build_doubting(
    map: &VoxelMap<'_>,
    stencil: &InflationStencil,
    vehicle: VoxelIndex,
    labels: &mut [Label],
    queue: &mut [u32],
    doubt: &Doubt<'_>,
) -> Result<DomainStats, DomainError> {
    let dims = map.dims();
    let n = dims.len();
    if labels.len() < n || queue.is_empty() {
        return Err(DomainError::StorageTooSmall);
    }
    let labels = labels.get_mut(..n).ok_or(DomainError::StorageTooSmall)?;
    let mut stats = DomainStats {
        free: safe_voxels(map, stencil, labels, doubt),
        ..Default::default()
    };
    let vehicle_i = dims.linear(vehicle);
    match labels.get(vehicle_i) {
        Some(Label::Candidate) => {}
        _ if map.is_free(vehicle_i) || doubt.passable(map, vehicle_i) => {
            return Err(DomainError::VehicleInInflatedSpace);
        }
        _ => return Err(DomainError::VehicleNotFree),
    }

    let mut fill = Fill {
        queue,
        head: 0,
        len: 0,
        overflow: false,
    };
    fill.push(labels, vehicle_i);
    loop {
        while let Some(i) = fill.pop() {
            // One walk over the faces: whether one borders the unknown (a safe voxel does if a
            // face neighbour is fringe or itself unexplored), and which are not reached yet.
            let (mut touches, mut next, mut count) = (false, [0usize; 6], 0usize);
            dims.for_each_face_neighbour(dims.voxel(i), |nb| match labels.get(nb) {
                Some(Label::Candidate) => {
                    if let Some(slot) = next.get_mut(count) {
                        *slot = nb;
                        count += 1;
                    }
                }
                Some(Label::Fringe) => touches = true,
                _ => touches |= map.is_unexplored(nb),
            });
            let label = if i == vehicle_i {
                Label::Source
            } else if touches {
                Label::Frontier
            } else {
                Label::Interior
            };
            if let Some(l) = labels.get_mut(i) {
                *l = label;
            }
            match label {
                Label::Frontier => stats.frontier += 1,
                Label::Interior => stats.interior += 1,
                _ => {}
            }
            if label != Label::Frontier {
                for &nb in next.iter().take(count) {
                    fill.push(labels, nb);
                }
            }
        }
        if !fill.overflow {
            break;
        }
        fill.overflow = false;
        stats.queue_sweeps += 1;
        for i in 0..n {
            if labels.get(i) == Some(&Label::Pending) {
                fill.push(labels, i);
            }
        }
    }

    for l in labels.iter_mut() {
        match *l {
            Label::Candidate => {
                stats.excluded += 1;
                *l = Label::Outside;
            }
            Label::Fringe => {
                stats.fringe += 1;
                *l = Label::Outside;
            }
            _ => {}
        }
    }
    stats.inflated = stats.free - stats.interior - stats.frontier - stats.excluded - stats.fringe - 1;
    if doubt.below > 0 {
        // Only frontiers that doubt did not make: a voxel next to a doubtful wall is a frontier
        // here merely because the wall no longer inflates (the band along every grazing
        // surface). What a planner asks of this domain is whether a frontier the ordinary
        // domain would have is cut off from the vehicle, so the others leave the domain.
        for (i, l) in labels.iter_mut().enumerate() {
            if *l == Label::Frontier && !is_certain_frontier(map, stencil, dims.voxel(i), doubt) {
                *l = Label::Outside;
                stats.frontier -= 1;
            }
        }
    }
    Ok(stats)
}

/// A frontier voxel of the ordinary domain, connection aside: safe ([`is_safe`]), with a face
/// neighbour that is unexplored or fringe — free, clear of the grid edge by the vehicle radius,
/// within it of unexplored space and of no occupied, uncertain or sealed voxel (with a lenient
/// `doubt`, of none that `doubt` does not doubt).
fn is_certain_frontier(
    map: &VoxelMap<'_>,
    stencil: &InflationStencil,
    v: VoxelIndex,
    doubt: &Doubt<'_>,
) -> bool {
    let dims = map.dims();
    // `n` is free, so the stencil's runs, which hold `n` itself, neither block nor find the
    // unknown in it.
    let fringe = |n: VoxelIndex| {
        let (mut blocked, mut unexplored) = (false, false);
        for run in stencil.runs(&dims, n) {
            let stored = map.stored().get(run.clone()).unwrap_or_default();
            for (i, &lo) in run.zip(stored) {
                blocked |= if doubt.lenient {
                    doubt.blocks(i, lo)
                } else {
                    stored_blocks(lo)
                };
                unexplored |= lo == UNKNOWN;
            }
        }
        clear_of_grid_edges(&dims, stencil, n) && !blocked && unexplored
    };
    let mut frontier = false;
    dims.for_each_face_neighbour(v, |i| {
        frontier |= map.is_unexplored(i) || (map.is_free(i) && fringe(dims.voxel(i)));
    });
    frontier && is_safe(map, stencil, v)
}

/// True for unexplored voxels with an observed voxel among their 26 neighbours: the nearest
/// unexplored voxel to any observed one is always of this kind, so these are the only ones
/// whose radius needs marking. `inner` says `v` is at least one voxel from every grid face,
/// so the neighbours' linear indices need no bounds tests (the common case, checked by
/// index arithmetic alone).
fn on_unknown_boundary(map: &VoxelMap<'_>, v: VoxelIndex, i: usize, inner: bool) -> bool {
    let dims = map.dims();
    if inner {
        let (sx, sy) = (1isize, dims.nx() as isize);
        let sz = sy * dims.ny() as isize;
        for dz in -1..=1isize {
            for dy in -1..=1isize {
                let row = i as isize + dz * sz + dy * sy;
                for dx in -1..=1isize {
                    if !map.is_unknown((row + dx * sx) as usize) {
                        return true;
                    }
                }
            }
        }
        return false;
    }
    dims.any_in_block(v, |n| !map.is_unknown(n))
}

/// Removes candidates within the stencil of any occupied/uncertain/sealed voxel or of the grid
/// edge, and marks those within the stencil of unexplored space as fringe.
///
/// One pass over the grid in storage order: a voxel's own stamp is the only thing it adds, and
/// the result does not depend on the order (`Outside` overrides, `Fringe` only replaces
/// `Candidate`), so the two kinds of stamp share the pass.
fn inflate(map: &VoxelMap<'_>, stencil: &InflationStencil, labels: &mut [Label], doubt: &Doubt<'_>) {
    let dims = map.dims();
    let (nx, ny, nz) = (dims.nx(), dims.ny(), dims.nz());
    let stored = map.stored();
    // The stencil as rows: for each (dy, dz) it reaches, the half-width w of its x interval
    // [−w, w]. The centre (0, 0, 0) is not an offset; covering it too changes nothing, because
    // the voxel that stamps is itself unknown, sealed or occupied (outside).
    let rows: HVec<(isize, isize, usize), STENCIL_ROWS> = stencil
        .rows
        .iter()
        .map(|&[dy, dz, w]| (isize::from(dy), isize::from(dz), usize::from(w.unsigned_abs())))
        .collect();
    // Rows holding an observed voxel: an unknown voxel can border observed space only if one
    // of the nine rows around its own does, so whole rows of the unobserved grid are skipped.
    let mut observed = [0u32; OBSERVED_ROW_WORDS];
    let track = ny * nz <= 32 * OBSERVED_ROW_WORDS;
    if track {
        for (r, row) in stored.chunks(nx).enumerate().take(ny * nz) {
            if row.iter().any(|&lo| stored_observed(lo)) {
                if let Some(w) = observed.get_mut(r >> 5) {
                    *w |= 1 << (r & 31);
                }
            }
        }
    }
    let row_observed = |y: usize, z: usize| {
        let r = y + ny * z;
        observed.get(r >> 5).is_some_and(|w| w & (1 << (r & 31)) != 0)
    };
    // What a voxel stamps: nothing, fringe (unexplored, bordering observed space) or outside
    // (occupied, uncertain or sealed).
    const NONE: u8 = 0;
    const FRINGE: u8 = 1;
    const OUTSIDE: u8 = 2;
    for z in 0..nz {
        for y in 0..ny {
            let start = nx * (y + ny * z);
            let Some(row) = stored.get(start..start + nx) else {
                continue;
            };
            let near_observed = !track
                || (z.saturating_sub(1)..(z + 2).min(nz))
                    .any(|zz| (y.saturating_sub(1)..(y + 2).min(ny)).any(|yy| row_observed(yy, zz)));
            let inner_yz = y >= 1 && y + 1 < ny && z >= 1 && z + 1 < nz;
            let kind = |x: usize, lo: i8| -> u8 {
                if lo == UNKNOWN {
                    let v = VoxelIndex::new(x as u16, y as u16, z as u16);
                    if near_observed
                        && on_unknown_boundary(map, v, start + x, inner_yz && x >= 1 && x + 1 < nx)
                    {
                        FRINGE
                    } else {
                        NONE
                    }
                } else if doubt.blocks(start + x, lo) {
                    OUTSIDE
                } else {
                    NONE
                }
            };
            // Runs of voxels of one kind stamp the union of their stencils: each stencil row
            // widened by the run's length.
            let at = |x: usize| kind(x, row.get(x).copied().unwrap_or(UNKNOWN));
            let mut x = 0;
            let mut k = at(0);
            while x < nx {
                let mut end = x + 1;
                let mut next = NONE;
                while end < nx {
                    next = at(end);
                    if next != k {
                        break;
                    }
                    end += 1;
                }
                if k != NONE {
                    for &(dy, dz, w) in &rows {
                        let (ty, tz) = (y as isize + dy, z as isize + dz);
                        if ty < 0 || tz < 0 || ty >= ny as isize || tz >= nz as isize {
                            continue;
                        }
                        let base = nx * (ty as usize + ny * tz as usize);
                        let (from, to) = (base + x.saturating_sub(w), base + (end - 1 + w).min(nx - 1));
                        let Some(span) = labels.get_mut(from..=to) else {
                            continue;
                        };
                        if k == OUTSIDE {
                            span.fill(Label::Outside);
                        } else {
                            for l in span.iter_mut().filter(|l| **l == Label::Candidate) {
                                *l = Label::Fringe;
                            }
                        }
                    }
                }
                x = end;
                k = next;
            }
        }
    }
    clear_grid_edges(&dims, stencil, labels);
}

/// The grid edge is a wall: the space beyond it is not the vehicle's to fly in, so candidates
/// and fringe voxels nearer an edge than the vehicle radius leave the domain.
fn clear_grid_edges(dims: &Dims, stencil: &InflationStencil, labels: &mut [Label]) {
    for (i, l) in labels.iter_mut().enumerate() {
        if matches!(*l, Label::Candidate | Label::Fringe)
            && !clear_of_grid_edges(dims, stencil, dims.voxel(i))
        {
            *l = Label::Outside;
        }
    }
}

/// True if voxel `v` is at least the vehicle radius from every face of the grid.
fn clear_of_grid_edges(dims: &Dims, stencil: &InflationStencil, v: VoxelIndex) -> bool {
    let r2 = stencil.radius_voxels * stencil.radius_voxels;
    let edge_clear = |c: u16, n: usize| {
        let near = f32::from(c) + 0.5;
        let far = n as f32 - f32::from(c) - 0.5;
        near * near >= r2 && far * far >= r2
    };
    edge_clear(v.x, dims.nx()) && edge_clear(v.y, dims.ny()) && edge_clear(v.z, dims.nz())
}

struct Fill<'q> {
    queue: &'q mut [u32],
    head: usize,
    len: usize,
    overflow: bool,
}

impl Fill<'_> {
    fn push(&mut self, labels: &mut [Label], i: usize) {
        let cap = self.queue.len();
        let Some(l) = labels.get_mut(i) else { return };
        if self.len < cap {
            // head < cap and len < cap, so one wrap is enough (and no division by cap).
            let at = self.head + self.len;
            let at = if at >= cap { at - cap } else { at };
            if let Some(slot) = self.queue.get_mut(at) {
                // Grid indices are below MAX_AXIS³ < 2³³; see Dims. Fits u32 for supported sizes.
                *slot = i as u32;
            }
            self.len += 1;
            *l = Label::Queued;
        } else {
            *l = Label::Pending;
            self.overflow = true;
        }
    }
    fn pop(&mut self) -> Option<usize> {
        if self.len == 0 {
            return None;
        }
        let i = self.queue.get(self.head).copied()?;
        self.head += 1;
        if self.head >= self.queue.len() {
            self.head = 0;
        }
        self.len -= 1;
        Some(i as usize)
    }
}

/// Labels every observed free voxel `Candidate`, then removes the unsafe ones ([`inflate`]):
/// afterwards `Candidate` means "the vehicle's centre may be here". Returns the free count.
fn safe_voxels(
    map: &VoxelMap<'_>,
    stencil: &InflationStencil,
    labels: &mut [Label],
    doubt: &Doubt<'_>,
) -> u32 {
    let mut free = 0;
    for ((i, l), &lo) in labels.iter_mut().enumerate().zip(map.stored()) {
        *l = if stored_observed(lo) && !doubt.blocks(i, lo) {
            free += 1;
            Label::Candidate
        } else {
            Label::Outside
        };
    }
    inflate(map, stencil, labels, doubt);
    free
}

/// A voxel the vehicle's centre may pass: observed free, and nothing but observed free space
/// within the vehicle radius (the domain's rule, checked locally).
pub fn is_safe(map: &VoxelMap<'_>, stencil: &InflationStencil, v: VoxelIndex) -> bool {
    let dims = map.dims();
    let stored = map.stored();
    // Row by row (the runs hold `v` too).
    map.is_free(dims.linear(v))
        && stencil.runs(&dims, v).all(|run| {
            stored
                .get(run)
                .is_some_and(|r| r.iter().all(|&lo| stored_free(lo)))
        })
}

/// Marks the unknown voxels the vehicle's body reaches into — its voxel and every voxel the
/// inflation stencil covers — as free: the vehicle is there, so they are. In flight this never
/// changes anything (the domain keeps the body clear of unknown space); it matters at start-up,
/// when everything around the vehicle is still unknown.
pub fn mark_body(map: &mut VoxelMap<'_>, stencil: &InflationStencil, position: &Point3<f32>) {
    let geometry = *map.geometry();
    let dims = geometry.dims();
    let Some(c) = geometry.voxel_at(position) else {
        return;
    };
    map.mark_traversed(dims.linear(c));
    for d in stencil.offsets() {
        if let Some(v) = dims.offset(c, d) {
            map.mark_traversed(dims.linear(v));
        }
    }
}

/// The step a planner takes when a build found no frontier: if the vehicle's component is its
/// own voxel, walled in by unknown voxels just above or below the body that a level camera
/// never sees (a vehicle off voxel centres), that is not a finished exploration. Marks the
/// clearance a vehicle that got here must have (twice `vehicle_radius`, [`mark_clearance`])
/// and returns true if anything changed — then build again; false means the exploration is
/// complete.
pub fn clear_if_walled_in(
    map: &mut VoxelMap<'_>,
    built: &DomainStats,
    position: &Point3<f32>,
    vehicle_radius: f32,
) -> bool {
    built.interior <= 1 && built.fringe > 0 && mark_clearance(map, position, 2.0 * vehicle_radius) > 0
}

/// Marks every unknown voxel whose centre lies within `radius` metres of `position` free (see
/// [`mark_body`]); returns how many changed. The planners use it, through
/// [`clear_if_walled_in`], only when the vehicle's safe component would otherwise be its own
/// voxel alone.
pub fn mark_clearance(map: &mut VoxelMap<'_>, position: &Point3<f32>, radius: f32) -> u32 {
    let geometry = *map.geometry();
    let dims = geometry.dims();
    let Some(c) = geometry.voxel_at(position) else {
        return 0;
    };
    let reach = libm::ceilf(radius / geometry.resolution()) as i32;
    let mut changed = 0;
    for dz in -reach..=reach {
        for dy in -reach..=reach {
            for dx in -reach..=reach {
                if let Some(v) = dims.offset(c, [dx, dy, dz]) {
                    if (geometry.center(v) - position).norm() <= radius && map.mark_traversed(dims.linear(v))
                    {
                        changed += 1;
                    }
                }
            }
        }
    }
    changed
}

/// Voxels from a frontier voxel to the unexplored space that makes it one (fringe plus one).
pub fn frontier_reach(stencil: &InflationStencil) -> i32 {
    libm::ceilf(stencil.radius_voxels() + 0.5) as i32 + 1
}

/// True if any voxel within `reach` voxels (Chebyshev) of `v` satisfies `pred`.
pub fn any_near(map: &VoxelMap<'_>, v: VoxelIndex, reach: i32, pred: impl Fn(usize) -> bool) -> bool {
    let dims = map.dims();
    for dz in -reach..=reach {
        for dy in -reach..=reach {
            for dx in -reach..=reach {
                if dims.offset(v, [dx, dy, dz]).is_some_and(|n| pred(dims.linear(n))) {
                    return true;
                }
            }
        }
    }
    false
}

/// Seals every voxel within `reach` voxels (Chebyshev) of `v`: a frontier that was visited and
/// could not be observed is taken out of the problem for good.
pub fn seal_around(map: &mut VoxelMap<'_>, v: VoxelIndex, reach: i32) {
    let dims = map.dims();
    for dz in -reach..=reach {
        for dy in -reach..=reach {
            for dx in -reach..=reach {
                if let Some(n) = dims.offset(v, [dx, dy, dz]) {
                    map.seal(dims.linear(n));
                }
            }
        }
    }
}

/// The nearest safe voxel (by face-connected path through observed free space, inflated and
/// fringe voxels included) to a vehicle that a new observation left in unsafe space — inflated,
/// or even an occupied voxel (a noisy return or a pose error put it there) — searching at most
/// `max_visits` voxels. Overwrites `labels`.
pub fn escape_target(
    map: &VoxelMap<'_>,
    stencil: &InflationStencil,
    vehicle: VoxelIndex,
    labels: &mut [Label],
    queue: &mut [u32],
    max_visits: usize,
) -> Option<VoxelIndex> {
    let dims = map.dims();
    let n = dims.len();
    let labels = labels.get_mut(..n)?;
    if queue.is_empty() {
        return None;
    }
    safe_voxels(map, stencil, labels, &Doubt::NONE);
    let start = dims.linear(vehicle);
    // The vehicle is there, so its voxel is passable whatever the map holds.
    if labels.get(start) == Some(&Label::Candidate) {
        return Some(vehicle);
    }
    // Walkable: free but unsafe. `Fill` marks what it has queued, so nothing is visited twice.
    let walkable = |l: Option<&Label>| matches!(l, Some(Label::Outside | Label::Fringe));
    let mut fill = Fill {
        queue,
        head: 0,
        len: 0,
        overflow: false,
    };
    fill.push(labels, start);
    let mut visited = 0usize;
    loop {
        while let Some(i) = fill.pop() {
            visited += 1;
            if visited > max_visits {
                return None;
            }
            let mut found = None;
            dims.for_each_face_neighbour(dims.voxel(i), |nb| {
                if found.is_some() {
                    return;
                }
                if labels.get(nb) == Some(&Label::Candidate) {
                    found = Some(nb);
                } else if walkable(labels.get(nb)) && map.is_free(nb) {
                    fill.push(labels, nb);
                }
            });
            if let Some(f) = found {
                return Some(dims.voxel(f));
            }
        }
        if !fill.overflow {
            return None;
        }
        fill.overflow = false;
        for i in 0..n {
            if labels.get(i) == Some(&Label::Pending) {
                fill.push(labels, i);
            }
        }
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::mapping::map::{Dims, LogOddsParams, MapGeometry};
    use nalgebra::Point3;

    /// Builds a 1 m-resolution map from ASCII pictures, one string slice per z-layer:
    /// '.' free, '#' occupied, anything else unknown.
    pub(crate) fn map_from_layers<'a>(
        layers: &[&[&str]],
        lo: &'a mut [i8],
        st: &'a mut [u32],
    ) -> VoxelMap<'a> {
        let (nz, ny, nx) = (layers.len(), layers[0].len(), layers[0][0].len());
        let g = MapGeometry::new(Dims::new(nx, ny, nz).unwrap(), Point3::origin(), 1.0).unwrap();
        let mut map = VoxelMap::new(g, LogOddsParams::default(), lo, st).unwrap();
        for (z, layer) in layers.iter().enumerate() {
            for (y, row) in layer.iter().enumerate() {
                for (x, c) in row.bytes().enumerate() {
                    let i = g.dims().linear(VoxelIndex::new(x as u16, y as u16, z as u16));
                    match c {
                        b'.' => map.apply_miss(i),
                        b'#' => map.apply_hit(i),
                        _ => false,
                    };
                }
            }
        }
        map
    }

    #[test]
    fn frontier_is_free_next_to_unknown() {
        let (mut lo, mut st) = ([0i8; 16], [0u32; 1]);
        let layers: &[&[&str]] = &[&["....", ".#..", "...?", "...."]];
        let map = map_from_layers(layers, &mut lo, &mut st);
        let mut frontier = heapless::Vec::<(u16, u16), 16>::new();
        for y in 0..4 {
            for x in 0..4 {
                if map.is_frontier(VoxelIndex::new(x, y, 0)) {
                    frontier.push((x, y)).unwrap();
                }
            }
        }
        // The face neighbours of the unknown voxel at (3,2); the grid edge is not unknown.
        assert_eq!(frontier.as_slice(), &[(3, 1), (2, 2), (3, 3)]);
    }

    #[test]
    fn frontier_ignores_occupied_and_sealed_neighbours() {
        let (mut lo, mut st) = ([0i8; 6], [0u32; 1]);
        let layers: &[&[&str]] = &[&["..#", ".?."]];
        let mut map = map_from_layers(layers, &mut lo, &mut st);
        assert!(!map.is_frontier(VoxelIndex::new(1, 0, 0)) || map.is_unexplored(4));
        assert!(map.is_frontier(VoxelIndex::new(0, 1, 0)));
        assert!(
            !map.is_frontier(VoxelIndex::new(2, 0, 0)),
            "occupied is never a frontier"
        );
        map.seal(4);
        assert!(
            !map.is_frontier(VoxelIndex::new(0, 1, 0)),
            "sealed unknown makes no frontier"
        );
    }

    /// A hall: walls seen in four frames (log-odds 3.4, certain), one voxel `d` in the hall seen
    /// occupied once (0.85, doubtful at the default 1.0), unknown space at its far end.
    fn hall_with_a_doubtful_voxel<'a>(lo: &'a mut [i8], st: &'a mut [u32], d_hits: usize) -> VoxelMap<'a> {
        let layers: &[&[&str]] = &[&["#######", "#..#..?", "#######"]];
        let mut map = map_from_layers(layers, lo, st);
        let dims = map.dims();
        let d = dims.linear(VoxelIndex::new(3, 1, 0));
        for frame in 0..3 {
            map.begin_frame();
            for i in 0..dims.len() {
                let v = dims.voxel(i);
                if (v.y != 1 || v.x == 0) && frame < 3 || (i == d && frame + 1 < d_hits) {
                    map.apply_hit(i);
                }
            }
        }
        map
    }

    #[test]
    fn a_frontier_cut_off_by_a_doubtful_voxel_alone_is_reopened_once() {
        let (mut lo, mut st) = ([0i8; 21], [0u32; 1]);
        let mut map = hall_with_a_doubtful_voxel(&mut lo, &mut st, 1);
        let dims = map.dims();
        let stencil = InflationStencil::new(0.0, 1.0).unwrap();
        let (mut labels, mut queue) = ([Label::Outside; 21], [0u32; 8]);
        let vehicle = VoxelIndex::new(1, 1, 0);
        let below = Reopening::threshold(1.0);
        let mut reopening = Reopening::default();
        let doubting = |map: &VoxelMap<'_>, reopening: &Reopening, labels: &mut [Label]| {
            let mut queue = [0u32; 8];
            build_doubting(
                map,
                &stencil,
                vehicle,
                labels,
                &mut queue,
                &reopening.doubt(below),
            )
            .unwrap()
        };

        let plain = build(&map, &stencil, vehicle, &mut labels, &mut queue).unwrap();
        assert_eq!(
            plain.frontier, 0,
            "the ordinary domain ends at the doubtful voxel"
        );
        let doubted = doubting(&map, &reopening, &mut labels);
        assert_eq!(doubted.frontier, 1, "taken for free space, it hides a frontier");
        assert_eq!(labels[dims.linear(VoxelIndex::new(5, 1, 0))], Label::Frontier);

        let centre = |x: u16| map.geometry().center(VoxelIndex::new(x, 1, 0));
        let gate = first_unsafe_along(&map, &stencil, &centre(1), (2..=5).map(centre)).unwrap();
        assert_eq!(gate, VoxelIndex::new(3, 1, 0));
        assert_eq!(reopening.forget_around(&mut map, &stencil, gate, below), 1);
        assert!(map.is_unexplored(dims.linear(gate)));
        let reopened = build(&map, &stencil, vehicle, &mut labels, &mut queue).unwrap();
        assert_eq!(
            reopened.frontier, 1,
            "the planner now has the forgotten voxel to look at"
        );
        assert_eq!(labels[dims.linear(VoxelIndex::new(2, 1, 0))], Label::Frontier);

        // Seen occupied again: the evidence stands; the exploration may end.
        map.begin_frame();
        map.apply_hit(dims.linear(gate));
        assert_eq!(doubting(&map, &reopening, &mut labels).frontier, 0);
        assert_eq!(reopening.forget_around(&mut map, &stencil, gate, below), 0);
        assert_eq!(reopening.forgotten(), 1);
    }

    #[test]
    fn certain_or_sealed_evidence_and_a_zero_threshold_are_not_doubted() {
        let stencil = InflationStencil::new(0.0, 1.0).unwrap();
        let reopening = Reopening::default();
        let frontiers_past = |map: &VoxelMap<'_>, log_odds: f32| {
            let (mut labels, mut queue) = ([Label::Outside; 21], [0u32; 8]);
            let doubt = reopening.doubt(Reopening::threshold(log_odds));
            build_doubting(
                map,
                &stencil,
                VoxelIndex::new(1, 1, 0),
                &mut labels,
                &mut queue,
                &doubt,
            )
            .unwrap()
            .frontier
        };
        // Hit in two frames: 1.7, above the threshold.
        let (mut lo, mut st) = ([0i8; 21], [0u32; 1]);
        assert_eq!(
            frontiers_past(&hall_with_a_doubtful_voxel(&mut lo, &mut st, 2), 1.0),
            0
        );
        // Doubtful, but doubting is off.
        assert_eq!(Reopening::threshold(0.0), 0);
        assert_eq!(Reopening::threshold(f32::NAN), 0);
        let (mut lo, mut st) = ([0i8; 21], [0u32; 1]);
        let map = hall_with_a_doubtful_voxel(&mut lo, &mut st, 1);
        assert_eq!(frontiers_past(&map, 1.0), 1);
        assert_eq!(frontiers_past(&map, 0.0), 0);
        // Sealed unknown space is given up on, not doubted.
        let (mut lo, mut st) = ([0i8; 21], [0u32; 1]);
        let mut map = hall_with_a_doubtful_voxel(&mut lo, &mut st, 4);
        let d = map.dims().linear(VoxelIndex::new(3, 1, 0));
        assert!(map.forget(d) && map.seal(d));
        assert_eq!(frontiers_past(&map, 3.0), 0);
    }

    #[test]
    fn component_without_frontier_is_excluded_and_inflation_removes_wall_neighbours() {
        let (mut lo, mut st) = ([0i8; 40], [0u32; 2]);
        // One unknown voxel at (4,1); rows 2 and 3 lead around it, so the far side is reached
        // without passing through a frontier voxel.
        let layers: &[&[&str]] = &[&["..........", "....?.#...", "......#...", ".........."]];
        let map = map_from_layers(layers, &mut lo, &mut st);
        let g = *map.geometry();
        let stencil = InflationStencil::new(0.0, 1.0).unwrap();
        let mut labels = [Label::Outside; 40];
        let mut queue = [0u32; 3]; // tiny on purpose: exercises the overflow sweep
        let stats = build(&map, &stencil, VoxelIndex::new(0, 0, 0), &mut labels, &mut queue).unwrap();
        assert!(stats.queue_sweeps > 0);
        let at = |labels: &[Label], x: u16, y: u16| labels[g.dims().linear(VoxelIndex::new(x, y, 0))];
        assert_eq!(at(&labels, 0, 0), Label::Source);
        assert_eq!(at(&labels, 3, 1), Label::Frontier);
        assert_eq!(at(&labels, 4, 0), Label::Frontier);
        assert_eq!(at(&labels, 5, 1), Label::Frontier);
        assert_eq!(at(&labels, 4, 2), Label::Frontier);
        assert_eq!(
            at(&labels, 9, 3),
            Label::Interior,
            "reachable around the unknown voxel"
        );
        assert_eq!(stats.frontier, 4);
        assert_eq!(stats.interior + stats.frontier + 1 + stats.excluded, stats.free);
        assert!(labels.iter().all(|l| matches!(
            l,
            Label::Outside | Label::Interior | Label::Frontier | Label::Source
        )));

        // A room behind a wall whose only gap is unknown is another component.
        let (mut lo2, mut st2) = ([0i8; 21], [0u32; 1]);
        let pocket: &[&[&str]] = &[&[".......", "##?####", "......."]];
        let map2 = map_from_layers(pocket, &mut lo2, &mut st2);
        let mut labels2 = [Label::Outside; 21];
        let stats2 = build(
            &map2,
            &stencil,
            VoxelIndex::new(0, 0, 0),
            &mut labels2,
            &mut queue,
        )
        .unwrap();
        assert_eq!(
            stats2.frontier, 1,
            "only the voxel on the vehicle's side of the gap"
        );
        // Row 2 (7 voxels) and row 0 beyond the frontier (4): reachable only through a sink.
        assert_eq!(stats2.excluded, 11);

        // Radius 1 voxel needs a grid at least 3 layers thick (the z edges are walls too).
        let (mut lo3, mut st3) = ([0i8; 120], [0u32; 4]);
        let layer: &[&str] = layers[0];
        let map3 = map_from_layers(&[layer, layer, layer], &mut lo3, &mut st3);
        let g3 = *map3.geometry();
        let mut labels3 = [Label::Outside; 120];
        let stencil = InflationStencil::new(1.0, 1.0).unwrap();
        let stats = build(
            &map3,
            &stencil,
            VoxelIndex::new(1, 1, 1),
            &mut labels3,
            &mut queue,
        )
        .unwrap();
        let at3 = |x: u16, y: u16, z: u16| labels3[g3.dims().linear(VoxelIndex::new(x, y, z))];
        assert_eq!(at3(0, 0, 1), Label::Outside, "grid edge inflated");
        assert_eq!(at3(1, 1, 0), Label::Outside, "floor edge inflated");
        assert_eq!(at3(7, 1, 1), Label::Outside, "wall neighbour inflated");
        // The unknown column at x = 4 makes x = 3..=5 fringe: the vehicle stops one voxel short.
        assert_eq!(at3(3, 1, 1), Label::Outside);
        assert_eq!(at3(2, 1, 1), Label::Frontier);
        assert_eq!(at3(1, 2, 1), Label::Interior);
        assert!(stats.inflated > 0 && stats.fringe > 0);
    }

    #[test]
    fn vehicle_outside_free_space_is_an_error() {
        let (mut lo, mut st) = ([0i8; 16], [0u32; 1]);
        let layers: &[&[&str]] = &[&["....", ".#..", "....", "?..."]];
        let map = map_from_layers(layers, &mut lo, &mut st);
        let mut labels = [Label::Outside; 16];
        let mut queue = [0u32; 16];
        let s0 = InflationStencil::new(0.0, 1.0).unwrap();
        let r = build(&map, &s0, VoxelIndex::new(1, 1, 0), &mut labels, &mut queue);
        assert_eq!(r, Err(DomainError::VehicleNotFree));
        let r = build(&map, &s0, VoxelIndex::new(0, 3, 0), &mut labels, &mut queue);
        assert_eq!(r, Err(DomainError::VehicleNotFree));
        let s1 = InflationStencil::new(1.0, 1.0).unwrap();
        let r = build(&map, &s1, VoxelIndex::new(2, 1, 0), &mut labels, &mut queue);
        assert_eq!(r, Err(DomainError::VehicleInInflatedSpace));
    }

    #[test]
    fn escape_crosses_fringe_to_the_nearest_safe_voxel() {
        // Radius 2 voxels: with an unknown column at x = 0, voxels x = 1, 2 are fringe and x = 3
        // is the first safe one (the 5 × 5 cross-section keeps y = z = 2 clear of the edges).
        // The vehicle at (1,2,2) must walk through fringe voxel (2,2,2) to reach (3,2,2).
        let layer: &[&str] = &["?.......", "?.......", "?.......", "?.......", "?......."];
        let (mut lo, mut st) = ([0i8; 200], [0u32; 7]);
        let map = map_from_layers(&[layer, layer, layer, layer, layer], &mut lo, &mut st);
        let stencil = InflationStencil::new(2.0, 1.0).unwrap();
        let mut labels = [Label::Outside; 200];
        let mut queue = [0u32; 2]; // tiny: exercises the overflow sweep
        let vehicle = VoxelIndex::new(1, 2, 2);
        assert_eq!(
            build(&map, &stencil, vehicle, &mut labels, &mut queue),
            Err(DomainError::VehicleInInflatedSpace)
        );
        let target = escape_target(&map, &stencil, vehicle, &mut labels, &mut queue, 100);
        assert_eq!(target, Some(VoxelIndex::new(3, 2, 2)));
        assert_eq!(
            escape_target(&map, &stencil, vehicle, &mut labels, &mut queue, 1),
            None,
            "visit cap"
        );
    }

    #[test]
    fn inflation_narrows_and_widens_and_refuses_bad_radii() {
        let mut i = Inflation::new(0.25, 0.2, 0.1).unwrap();
        let wide = i.stencil().len();
        assert!(!i.is_narrowed() && !i.widen(), "starts on the planning radius");
        assert!(i.narrow(), "0.2 m is narrower");
        assert!(i.is_narrowed());
        assert_eq!(i.stencil().len(), InflationStencil::new(0.2, 0.1).unwrap().len());
        assert!(i.stencil().len() < wide);
        assert!(!i.narrow(), "already narrowed");
        assert!(i.widen(), "it was narrowed");
        assert!(!i.is_narrowed());
        assert_eq!(i.stencil().len(), wide);
        // No fallback: none given, or one not narrower than the radius.
        for narrow in [0.0, 0.25, 0.3] {
            let mut i = Inflation::new(0.25, narrow, 0.1).unwrap();
            assert!(!i.narrow(), "{narrow}");
            assert_eq!(i.stencil().len(), wide);
        }
        for bad in [f32::NAN, -0.1, f32::INFINITY] {
            assert_eq!(
                Inflation::new(0.25, bad, 0.1).unwrap_err(),
                DomainError::BadRadius,
                "{bad}"
            );
        }
    }

    #[test]
    fn a_pocket_is_a_frontierless_component_half_the_narrower_one_or_less() {
        let stats = |interior, frontier| DomainStats {
            interior,
            frontier,
            ..DomainStats::default()
        };
        assert!(is_pocket(&stats(7, 0), &stats(5000, 300)));
        assert!(is_pocket(&stats(100, 0), &stats(150, 50)), "twice as large");
        assert!(!is_pocket(&stats(100, 0), &stats(150, 49)), "less than twice");
        assert!(
            !is_pocket(&stats(7, 0), &stats(5000, 0)),
            "no frontier either way"
        );
        assert!(
            !is_pocket(&stats(7, 1), &stats(5000, 300)),
            "a frontier at the planning radius"
        );
        assert!(
            is_pocket(&stats(u32::MAX, 0), &stats(u32::MAX, u32::MAX)),
            "no overflow"
        );
    }

    #[test]
    fn stencil_matches_cube_distance() {
        // 0.2 m at 0.1 m: offsets (1,0,0),(2,0,0),(1,1,0),(2,1,0),(1,1,1),(2,1,1) and permutations.
        let s = InflationStencil::new(0.2, 0.1).unwrap();
        assert_eq!(s.len(), 12 + 12 + 24 + 8 + 24);
        assert!(InflationStencil::new(-1.0, 0.1).is_err());
        assert!(InflationStencil::new(f32::NAN, 0.1).is_err());
        assert!(InflationStencil::new(10.0, 0.1).is_err());
        // The largest radius: 1284 offsets in at most `STENCIL_ROWS` rows.
        let largest = InflationStencil::new(MAX_INFLATION_VOXELS as f32, 1.0).unwrap();
        assert_eq!(largest.len(), 1284);
        assert!(largest.rows.len() <= STENCIL_ROWS);
    }

    #[test]
    fn stencil_rows_give_every_offset_within_the_radius_in_order() {
        // The stencil keeps rows; its offsets must be those of a plain loop over the cube, in
        // the same dz, dy, dx order (the order decides which voxels `forget_around` takes first).
        extern crate std;
        for step in 0..=120 {
            let r = step as f32 * 0.05;
            let s = InflationStencil::new(r, 1.0).unwrap();
            let reach = libm::ceilf(r + 0.5) as i32;
            let mut expected = std::vec::Vec::new();
            for dz in -reach..=reach {
                for dy in -reach..=reach {
                    for dx in -reach..=reach {
                        if (dx, dy, dz) != (0, 0, 0) && cube_distance_sq([dx, dy, dz]) < r * r {
                            expected.push([dx, dy, dz]);
                        }
                    }
                }
            }
            let got: std::vec::Vec<[i32; 3]> = s.offsets().collect();
            assert_eq!(got, expected, "radius {r} voxels");
            assert_eq!(s.len(), expected.len());
            assert_eq!(s.is_empty(), expected.is_empty());
        }
    }

    /// The straightforward inflation (two passes, every neighbour bounds-checked) that
    /// [`inflate`]'s one pass with index arithmetic replaced, without the grid-edge rule
    /// both share ([`clear_grid_edges`]).
    fn inflate_reference(map: &VoxelMap<'_>, stencil: &InflationStencil, labels: &mut [Label]) {
        let dims = map.dims();
        let observed_near = |v: VoxelIndex| dims.any_in_block(v, |n| !map.is_unknown(n));
        for i in 0..dims.len() {
            let v = dims.voxel(i);
            if map.is_unexplored(i) && observed_near(v) {
                for d in stencil.offsets() {
                    if let Some(l) = dims.offset(v, d).and_then(|n| labels.get_mut(dims.linear(n))) {
                        if *l == Label::Candidate {
                            *l = Label::Fringe;
                        }
                    }
                }
            }
        }
        for i in 0..dims.len() {
            if matches!(
                map.occupancy(i),
                crate::mapping::map::Occupancy::Occupied | crate::mapping::map::Occupancy::Uncertain
            ) || map.is_sealed(i)
            {
                let v = dims.voxel(i);
                for d in stencil.offsets() {
                    if let Some(l) = dims.offset(v, d).and_then(|n| labels.get_mut(dims.linear(n))) {
                        *l = Label::Outside;
                    }
                }
            }
        }
    }

    /// A xorshift64 generator: the randomised tests' maps, the same on every run.
    pub(crate) fn xorshift(mut seed: u64) -> impl FnMut() -> u64 {
        move || {
            seed ^= seed << 13;
            seed ^= seed >> 7;
            seed ^= seed << 17;
            seed
        }
    }

    /// Marks `map`'s free voxels as candidates, inflates them with [`inflate`] and with the
    /// voxel-by-voxel reference, and asserts the labels agree.
    fn assert_inflates_like_the_reference(map: &VoxelMap<'_>, stencil: &InflationStencil, case: &str) {
        extern crate std;
        let dims = map.dims();
        let fresh = || -> std::vec::Vec<Label> {
            (0..dims.len())
                .map(|i| {
                    if map.is_free(i) {
                        Label::Candidate
                    } else {
                        Label::Outside
                    }
                })
                .collect()
        };
        let (mut fast, mut reference) = (fresh(), fresh());
        inflate(map, stencil, &mut fast, &Doubt::NONE);
        inflate_reference(map, stencil, &mut reference);
        clear_grid_edges(&dims, stencil, &mut reference);
        assert!(fast == reference, "{case}");
    }

    /// Run-wise inflation on building-like maps (long runs of wall, free space and unknown) and
    /// on a grid with more rows than the observed-row bitset holds (every unknown voxel tested
    /// then) gives the reference's labels, and [`is_safe`] the offset-by-offset answer.
    #[test]
    fn run_wise_inflation_matches_the_reference_on_rooms_and_tall_grids() {
        extern crate std;
        use std::vec;
        let mut next = xorshift(0x9e37_79b9_7f4a_7c15);
        for (case, (nx, ny, nz)) in [(40, 30, 20), (33, 41, 17), (3, 100, 90)].into_iter().enumerate() {
            let dims = Dims::new(nx, ny, nz).unwrap();
            let g = MapGeometry::new(dims, Point3::origin(), 1.0).unwrap();
            let n = dims.len();
            let (mut lo, mut st) = (
                vec![0i8; n],
                vec![0u32; crate::mapping::map::touched_words(&dims)],
            );
            let mut map = VoxelMap::new(g, LogOddsParams::default(), &mut lo, &mut st).unwrap();
            // Observed boxes of free space with occupied shells, some sealed pockets; the
            // rest unknown.
            for _ in 0..12 {
                let lo_c = [next() as usize % nx, next() as usize % ny, next() as usize % nz];
                let size = [
                    1 + next() as usize % 20,
                    1 + next() as usize % 15,
                    1 + next() as usize % 10,
                ];
                let kind = next() % 10;
                for i in 0..n {
                    let v = dims.voxel(i);
                    let c = [usize::from(v.x), usize::from(v.y), usize::from(v.z)];
                    let inside = (0..3).all(|a| c[a] >= lo_c[a] && c[a] < lo_c[a] + size[a]);
                    let shell = inside && (0..3).any(|a| c[a] == lo_c[a] || c[a] + 1 == lo_c[a] + size[a]);
                    if !inside {
                        continue;
                    }
                    if kind == 0 {
                        map.seal(i);
                    } else if shell && kind < 6 {
                        map.apply_hit(i);
                    } else {
                        map.apply_miss(i);
                    }
                }
            }
            for radius in [0.9f32, 2.7] {
                let stencil = InflationStencil::new(radius, 1.0).unwrap();
                let case = std::format!("case {case}: {nx}x{ny}x{nz}, radius {radius}");
                assert_inflates_like_the_reference(&map, &stencil, &case);
                // `is_safe` reads the stencil row by row; offset by offset it must agree.
                for i in 0..n {
                    let v = dims.voxel(i);
                    let reference = map.is_free(i)
                        && stencil
                            .offsets()
                            .all(|d| dims.offset(v, d).is_none_or(|m| map.is_free(dims.linear(m))));
                    assert_eq!(is_safe(&map, &stencil, v), reference, "{case}, voxel {v:?}");
                }
            }
        }
    }

    #[test]
    fn one_pass_inflation_matches_the_reference_on_random_maps() {
        // Small grids (every voxel near an edge) and larger ones, radii 0 to 3 voxels, maps
        // with unknown, free, occupied and sealed voxels in random proportions.
        extern crate std;
        let mut next = xorshift(0x2545_f491_4f6c_dd1d);
        for case in 0..60 {
            let (nx, ny, nz) = (
                3 + (next() % 12) as usize,
                3 + (next() % 10) as usize,
                2 + (next() % 9) as usize,
            );
            let dims = Dims::new(nx, ny, nz).unwrap();
            let g = MapGeometry::new(dims, Point3::origin(), 1.0).unwrap();
            let n = dims.len();
            // At most 14 × 12 × 10 voxels.
            let (mut lo, mut st) = ([0i8; 1680], [0u32; 64]);
            let words = crate::mapping::map::touched_words(&dims);
            let mut map = VoxelMap::new(g, LogOddsParams::default(), &mut lo[..n], &mut st[..words]).unwrap();
            let (p_unknown, p_occupied) = (next() % 60, next() % 30);
            for i in 0..n {
                let r = next() % 100;
                if r < p_unknown {
                    if r.is_multiple_of(7) {
                        map.seal(i);
                    }
                } else if r < p_unknown + p_occupied {
                    map.apply_hit(i);
                } else {
                    map.apply_miss(i);
                }
            }
            let radius = (case % 4) as f32 * 0.9;
            let stencil = InflationStencil::new(radius, 1.0).unwrap();
            let case = std::format!("case {case}: {nx}x{ny}x{nz}, radius {radius}");
            assert_inflates_like_the_reference(&map, &stencil, &case);
        }
    }
}
