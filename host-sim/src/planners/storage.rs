//! The buffers an explorer borrows on the host, and the host's clock.

use std::time::Instant;

use harmonic_core::clock::Clock;
use harmonic_core::domain::Label;
use harmonic_core::explore::ExplorerStorage;
use harmonic_core::map::{self, Dims};
use harmonic_core::solve::multigrid;

/// Nanosecond host clock for per-phase timing (implements the core's [`Clock`]).
pub struct HostClock(Instant);

impl HostClock {
    /// A clock starting now.
    pub fn new() -> Self {
        Self(Instant::now())
    }
}

impl Default for HostClock {
    fn default() -> Self {
        Self::new()
    }
}

impl Clock for HostClock {
    fn ticks(&mut self) -> u64 {
        self.0.elapsed().as_nanos() as u64
    }
}

/// Heap storage for a [`Multigrid`](multigrid::Multigrid) on one grid
/// ([`multigrid::scratch_size`]): what an explorer lends its solver ([`HostStorage`]), and the
/// host tools' solves.
pub struct MultigridScratch {
    values: Vec<f32>,
    labels: Vec<Label>,
    faces: Vec<[u8; 4]>,
    krylov: Vec<f32>,
    masks: Vec<u8>,
}

impl MultigridScratch {
    /// Zeroed storage sized for `dims`.
    pub fn new(dims: &Dims) -> Self {
        let size = multigrid::scratch_size(dims);
        Self {
            values: vec![0.0; size.values],
            labels: vec![Label::Outside; size.labels],
            faces: vec![[0; 4]; size.faces],
            krylov: vec![0.0; size.krylov],
            masks: vec![0; size.masks],
        }
    }

    /// The storage to lend [`Multigrid::new`](multigrid::Multigrid::new).
    pub fn storage(&mut self) -> multigrid::MultigridStorage<'_> {
        multigrid::MultigridStorage {
            values: self.values.as_mut_slice().into(),
            labels: &mut self.labels,
            faces: &mut self.faces,
            krylov: &mut self.krylov,
            masks: &mut self.masks,
        }
    }
}

/// Host-owned buffers for one explorer.
pub struct HostStorage {
    dims: Dims,
    log_odds: Vec<i8>,
    touched: Vec<u32>,
    labels: Vec<Label>,
    phi: Vec<f32>,
    queue: Vec<u32>,
    solver: MultigridScratch,
    /// The map's surface estimate: empty until [`HostStorage::with_surface`].
    surface: Vec<[i32; 2]>,
    /// The thesis's Jacobi scratch: empty until [`HostStorage::with_jacobi`].
    jacobi: Vec<f32>,
    /// The box of local re-solves: three quarters of a grid, the most
    /// [`MAX_SHARE`](harmonic_core::solve::local::MAX_SHARE) lets a box take.
    local_labels: Vec<Label>,
    /// Its values.
    local_psi: Vec<f32>,
    /// The flat solver's storage: empty until [`HostStorage::with_flat`].
    flat: Vec<f32>,
    /// The map at the mission grid's resolution when the explorer plans on a coarser grid:
    /// empty until [`HostStorage::with_fine_map`].
    fine_log_odds: Vec<i8>,
    /// Its touched bits.
    fine_touched: Vec<u32>,
}

impl HostStorage {
    /// Buffers for `dims`, with MGPCG storage, the fine level's neighbour masks and a box for
    /// local re-solves.
    pub fn new(dims: &Dims) -> Self {
        let n = dims.len();
        let box_cells = harmonic_core::solve::local::box_scratch_len(n);
        Self {
            dims: *dims,
            solver: MultigridScratch::new(dims),
            surface: Vec::new(),
            log_odds: vec![0; n],
            touched: vec![0; map::touched_words(dims)],
            labels: vec![Label::Outside; n],
            phi: vec![0.0; n],
            queue: vec![0; 16 * 1024],
            jacobi: Vec::new(),
            local_labels: vec![Label::Outside; box_cells],
            local_psi: vec![0.0; box_cells],
            flat: Vec::new(),
            fine_log_odds: Vec::new(),
            fine_touched: Vec::new(),
        }
    }
    /// Adds the map at the grid's resolution that an explorer planning on a coarser grid
    /// integrates into ([`ExplorerConfig::plan_coarsening`](harmonic_core::explore::ExplorerConfig::plan_coarsening));
    /// the other buffers, sized for this grid, hold the coarser one. A no-op if it is there.
    pub fn with_fine_map(&mut self) -> &mut Self {
        self.fine_log_odds.resize(self.dims.len(), 0);
        self.fine_touched.resize(map::touched_words(&self.dims), 0);
        self
    }
    /// Adds the storage of the flat solver ([`SolverKind::Flat`](harmonic_core::explore::SolverKind::Flat),
    /// [`harmonic_core::solve::flat::flat_scratch_len`] values); a no-op if it is there.
    pub fn with_flat(&mut self) -> &mut Self {
        self.flat
            .resize(harmonic_core::solve::flat::flat_scratch_len(&self.dims), 0.0);
        self
    }
    /// Adds the one-per-voxel scratch the thesis's Jacobi solve needs
    /// ([`SolverKind::ThesisJacobi`](harmonic_core::explore::SolverKind::ThesisJacobi)); a no-op if it is there.
    pub fn with_jacobi(&mut self) -> &mut Self {
        self.jacobi.resize(self.phi.len(), 0.0);
        self
    }
    /// Adds the map's surface estimate for noisy depth (two words per voxel; see
    /// [`harmonic_core::integrate`]); a no-op if it is there.
    pub fn with_surface(&mut self) -> &mut Self {
        self.surface.resize(self.phi.len(), [0, 0]);
        self
    }
    /// Lends the buffers to an explorer.
    pub fn lend(&mut self) -> ExplorerStorage<'_> {
        let solver = self.solver.storage();
        ExplorerStorage {
            log_odds: &mut self.log_odds,
            touched: &mut self.touched,
            labels: &mut self.labels,
            phi: &mut self.phi,
            queue: &mut self.queue,
            coarse_values: solver.values,
            coarse_labels: solver.labels,
            coarse_faces: solver.faces,
            krylov: solver.krylov,
            masks: solver.masks,
            surface: &mut self.surface,
            jacobi: &mut self.jacobi,
            local_labels: &mut self.local_labels,
            local_psi: &mut self.local_psi,
            flat: &mut self.flat,
            fine_log_odds: &mut self.fine_log_odds,
            fine_touched: &mut self.fine_touched,
        }
    }
}
