//! The world built to break an f32 solve: a large hall whose only frontier lies at the end of a
//! long one-voxel corridor. The hall is a reservoir at almost uniform potential, its gradients are
//! tiny, and the corridor carries all the flux. Plain V-cycles stall here (the corridor does not
//! exist on coarse levels: 8e-5 relative residual after 400 cycles), and a solver stopped early
//! leaves hall streamlines pointing anywhere. Every streamline started in the hall must still
//! find the corridor and reach the frontier.

use harmonic_core::domain::Label;
use harmonic_core::map::{Dims, MapGeometry, VoxelIndex};
use harmonic_core::solve::multigrid::{scratch_size, Method, Multigrid, MultigridStorage};
use harmonic_core::solve::SolveParams;
use harmonic_core::streamline::{trace, Field, StreamlineParams, Waypoints};
use nalgebra::Point3;

const HALL: usize = 64; // hall is HALL × HALL × NZ voxels
const NZ: usize = 16;
const CORRIDOR: usize = 120; // corridor length in voxels, 1 × 1 cross-section
const NX: usize = HALL + CORRIDOR;

fn hall_and_corridor(source: VoxelIndex) -> (Dims, Vec<Label>) {
    let dims = Dims::new(NX, HALL, NZ).unwrap();
    let mut labels = vec![Label::Outside; dims.len()];
    let mid_y = HALL / 2;
    let mid_z = NZ / 2;
    for (i, l) in labels.iter_mut().enumerate() {
        let v = dims.voxel(i);
        let (x, y, z) = (usize::from(v.x), usize::from(v.y), usize::from(v.z));
        let in_hall = x < HALL;
        let in_corridor = x >= HALL && y == mid_y && z == mid_z;
        if in_hall || in_corridor {
            *l = if x == NX - 1 {
                Label::Frontier
            } else {
                Label::Interior
            };
        }
    }
    labels[dims.linear(source)] = Label::Source;
    (dims, labels)
}

struct Solver {
    values: Vec<f32>,
    labels: Vec<Label>,
    faces: Vec<[u8; 4]>,
    krylov: Vec<f32>,
    masks: Vec<u8>,
}

impl Solver {
    fn new(dims: &Dims) -> Self {
        let s = scratch_size(dims);
        Self {
            values: vec![0.0; s.values],
            labels: vec![Label::Outside; s.labels],
            faces: vec![[0; 4]; s.faces],
            krylov: vec![0.0; s.krylov],
            masks: vec![0; s.masks],
        }
    }
    fn solve(&mut self, dims: Dims, labels: &[Label], method: Method) -> Vec<f32> {
        let storage = MultigridStorage {
            values: self.values.as_mut_slice().into(),
            labels: &mut self.labels,
            faces: &mut self.faces,
            krylov: &mut self.krylov,
            masks: &mut self.masks,
        };
        let mut mg = Multigrid::new(dims, storage).unwrap();
        let mut psi = vec![0.0f32; dims.len()];
        let params = SolveParams {
            tolerance: 1e-6,
            max_iterations: 400,
            warm_start: false,
            ..SolveParams::default()
        };
        let stats = mg.solve(labels, &mut psi, &params, method).unwrap();
        assert!(stats.converged, "{method:?} did not converge: {stats:?}");
        psi
    }
}

/// Every streamline must end in the corridor's frontier voxels (x = NX − 1).
fn assert_reaches_corridor_end(dims: Dims, labels: &[Label], psi: &[f32], starts: &[VoxelIndex]) {
    let g = MapGeometry::new(dims, Point3::origin(), 0.1).unwrap();
    let field = Field {
        geometry: &g,
        labels,
        phi: psi,
    };
    let mut wps = Waypoints::new();
    for &s in starts {
        let end = trace(&field, &g.center(s), &StreamlineParams::default(), &mut wps)
            .unwrap_or_else(|e| panic!("streamline from {s:?} failed: {e:?}"));
        assert_eq!(
            usize::from(end.frontier.x),
            NX - 1,
            "streamline from {s:?} ended at {:?}",
            end.frontier
        );
        assert!(
            end.length >= 0.1 * (CORRIDOR as f32 - 1.0),
            "too short from {s:?}: {} m",
            end.length
        );
    }
}

#[test]
fn every_streamline_from_the_hall_reaches_the_far_frontier() {
    // Sources in the hall's corners, centre and far from the corridor mouth.
    let sources = [
        VoxelIndex::new(1, 1, 1),
        VoxelIndex::new(1, (HALL - 2) as u16, (NZ - 2) as u16),
        VoxelIndex::new((HALL / 2) as u16, (HALL / 2) as u16, (NZ / 2) as u16),
        VoxelIndex::new(5, (HALL / 2) as u16, 2),
    ];
    let dims = Dims::new(NX, HALL, NZ).unwrap();
    let mut solver = Solver::new(&dims);
    for source in sources {
        let (dims, labels) = hall_and_corridor(source);
        // MGPCG is the host's solver; plain V-cycles are the firmware's.
        for method in [Method::Pcg, Method::VCycle] {
            let psi = solver.solve(dims, &labels, method);
            // The hall really is a reservoir: φ = 1 − ψ stays close to 1 all over it.
            let corner = dims.linear(VoxelIndex::new((HALL - 2) as u16, 1, 1));
            assert!(psi[corner] < 5e-2, "hall is not a reservoir: ψ = {}", psi[corner]);
            // Streamlines from the source and from a lattice of hall voxels.
            let mut starts = vec![source];
            for x in (1..HALL - 1).step_by(6) {
                for y in (1..HALL - 1).step_by(6) {
                    for z in [1, NZ / 2, NZ - 2] {
                        starts.push(VoxelIndex::new(x as u16, y as u16, z as u16));
                    }
                }
            }
            assert_reaches_corridor_end(dims, &labels, &psi, &starts);
        }
    }
}
