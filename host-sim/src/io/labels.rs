//! Label grids: the map's occupancy as one `u8` per voxel, the `.npy` map export
//! (`explore` writes `map.npy`) and the planning problems `solve` reads and
//! `explore --dump-problem` writes ([`crate::tools::problem`]). Shape `(NX, NY, NZ)`, C order,
//! indexed `[x, y, z]`.
//!
//! In: the core's [`VoxelMap`]. Out: an [`Array3`] for [`crate::io::npy`] to write. Here, not
//! in `tools::problem`, because the run loop writes the grids too (`--dump-problem`) and a
//! format both sides use belongs below both.

use harmonic_core::map::{Occupancy, VoxelIndex, VoxelMap};

use crate::io::npy::Array3;

/// Never observed.
pub const UNKNOWN: u8 = 0;
/// Observed free.
pub const FREE: u8 = 1;
/// Observed occupied (or uncertain).
pub const OCCUPIED: u8 = 2;

/// The map's state as a label grid (the `.npy` map export): 0 unknown (sealed or not),
/// 1 free, 2 occupied or uncertain.
pub fn labels_from_map(map: &VoxelMap<'_>) -> Array3<u8> {
    label_grid(map, UNKNOWN)
}

/// The planning problem as a label grid (for `--dump-problem`). Like [`labels_from_map`], but
/// unknown voxels the planner sealed as unobservable are written as occupied: the domain treats
/// them so (they inflate and make no frontier), which keeps `solve` on the dump the explorer's
/// own problem.
pub fn problem_labels_from_map(map: &VoxelMap<'_>) -> Array3<u8> {
    label_grid(map, OCCUPIED)
}

fn label_grid(map: &VoxelMap<'_>, sealed: u8) -> Array3<u8> {
    let dims = map.dims();
    Array3::from_fn([dims.nx(), dims.ny(), dims.nz()], |x, y, z| {
        let i = dims.linear(VoxelIndex::new(x as u16, y as u16, z as u16));
        match map.occupancy(i) {
            Occupancy::Unknown if map.is_sealed(i) => sealed,
            Occupancy::Unknown => UNKNOWN,
            Occupancy::Free => FREE,
            Occupancy::Occupied | Occupancy::Uncertain => OCCUPIED,
        }
    })
}
