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
    /// For an explorer planning on cells of `factor` voxels a side
    /// ([`ExplorerConfig::plan_coarsening`](harmonic_core::explore::ExplorerConfig::plan_coarsening)):
    /// the map at this grid's resolution, which frames go into, and every other buffer sized for
    /// the coarser planning grid `plan` (as the firmware carves its arena), so the host's memory
    /// per voxel falls as the firmware's does. A factor of 1 or a `plan` no smaller than this
    /// grid: as it was.
    pub fn with_coarser_plan(&mut self, plan: &Dims) -> &mut Self {
        if plan.len() >= self.dims.len() || !self.fine_log_odds.is_empty() {
            return self;
        }
        let fine = self.dims;
        let mut coarse = Self::new(plan);
        coarse.fine_log_odds = vec![0; fine.len()];
        coarse.fine_touched = vec![0; map::touched_words(&fine)];
        *self = coarse;
        self
    }
    /// Bytes the buffers hold (their lengths, not their allocations' spare capacity): the
    /// explorer's memory on the host, beside the firmware's arena.
    pub fn bytes(&self) -> usize {
        use std::mem::size_of_val;
        let s = &self.solver;
        size_of_val(self.log_odds.as_slice())
            + size_of_val(self.touched.as_slice())
            + size_of_val(self.labels.as_slice())
            + size_of_val(self.phi.as_slice())
            + size_of_val(self.queue.as_slice())
            + size_of_val(s.values.as_slice())
            + size_of_val(s.labels.as_slice())
            + size_of_val(s.faces.as_slice())
            + size_of_val(s.krylov.as_slice())
            + size_of_val(s.masks.as_slice())
            + size_of_val(self.surface.as_slice())
            + size_of_val(self.jacobi.as_slice())
            + size_of_val(self.local_labels.as_slice())
            + size_of_val(self.local_psi.as_slice())
            + size_of_val(self.flat.as_slice())
            + size_of_val(self.fine_log_odds.as_slice())
            + size_of_val(self.fine_touched.as_slice())
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
        // Kept by the map frames go into: the one at the grid's resolution when there is one.
        let n = self.fine_log_odds.len().max(self.phi.len());
        self.surface.resize(n, [0, 0]);
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

#[cfg(test)]
mod tests {
    use harmonic_core::explore::{Explorer, ExplorerConfig};
    use harmonic_core::map::MapGeometry;
    use nalgebra::Point3;

    use super::*;

    /// Planning on 2 × 2 × 2 cells, the host lends what the firmware carves: the map at the
    /// grid's resolution and the rest for the coarser grid, under a fifth of the bytes of
    /// planning on voxels; an explorer takes it, and does not take it planning on voxels.
    #[test]
    fn a_coarser_planning_grid_shrinks_the_hosts_storage_and_an_explorer_takes_it() {
        let geometry = MapGeometry::new(Dims::new(120, 80, 25).unwrap(), Point3::origin(), 0.1).unwrap();
        let mut storage = HostStorage::new(&geometry.dims());
        let voxels = storage.bytes();
        let plan = geometry.coarsened(2).unwrap();
        storage.with_coarser_plan(&plan.dims());
        let cells = storage.bytes();
        assert!(cells * 5 < voxels, "{cells} B against {voxels} B");
        assert!(
            cells > geometry.dims().len(),
            "the map's byte per voxel is kept: {cells} B"
        );
        let coarse = ExplorerConfig {
            plan_coarsening: 2,
            ..ExplorerConfig::default()
        };
        assert!(Explorer::new(geometry, coarse, storage.lend()).is_ok());
        assert!(Explorer::new(geometry, ExplorerConfig::default(), storage.lend()).is_err());
    }
}
