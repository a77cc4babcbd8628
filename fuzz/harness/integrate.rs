//! Fuzz harness for depth integration and planning through the [`Explorer`]: arbitrary
//! intrinsics, depth values, camera poses (including non-finite values and non-unit
//! quaternions), range settings and what a no-return pixel means, grid placement and vehicle
//! positions. Shared by `fuzz/fuzz_targets/depth_integration.rs` and
//! `tests/tests/fuzz_harness.rs`.
//!
//! The oracle checks:
//!
//! - no panic;
//! - a frame with a bad pose is refused, counted, and leaves the map as it was;
//! - the map's voxel counts always add up to the grid size;
//! - a goal is finite, inside the grid, and in a voxel the map knows to be free.

use harmonic_core::camera::{DepthFrame, Intrinsics};
use harmonic_core::domain::Label;
use harmonic_core::explore::{Explorer, ExplorerConfig, ExplorerStorage, Fault, PlanOutcome, SolverKind};
use harmonic_core::integrate::{IntegrationParams, NoReturn};
use harmonic_core::map::{self, Dims, MapGeometry};
use harmonic_core::solve::multigrid;
use nalgebra::{Isometry3, Point3, Quaternion, Translation3, UnitQuaternion};

// The crate that includes this harness also includes `input.rs` as `crate::input`.
use crate::input::{Floats, Input};

/// Plausible floats here: multiples of 1/16 in ±8.
const FLOATS: Floats = Floats {
    raw: 16,
    step: 1.0 / 16.0,
    offset: -8.0,
};

/// Runs the harness on one input. Panics only when the oracle finds a bug.
pub fn run(data: &[u8]) {
    let mut input = Input(data);
    let dims = match Dims::new(
        usize::from(input.u8() % 12) + 4,
        usize::from(input.u8() % 12) + 4,
        usize::from(input.u8() % 8) + 2,
    ) {
        Ok(d) => d,
        Err(e) => panic!("small dims refused: {e:?}"),
    };
    let origin = Point3::new(input.float(FLOATS), input.float(FLOATS), input.float(FLOATS));
    let resolution = match input.u8() % 4 {
        0 => input.float(FLOATS),
        k => f32::from(k) * 0.1,
    };
    let Ok(geometry) = MapGeometry::new(dims, origin, resolution) else {
        return;
    };
    let mut config = ExplorerConfig {
        solver: if input.u8() % 4 == 0 {
            SolverKind::GaussSeidel
        } else {
            SolverKind::Multigrid
        },
        ..ExplorerConfig::default()
    };
    if input.u8() % 4 == 0 {
        config.integration = IntegrationParams {
            min_range: input.float(FLOATS),
            max_range: input.float(FLOATS),
            pixel_stride: u16::from(input.u8() % 4),
            no_return: if input.u8() % 2 == 0 {
                NoReturn::ClearToMaxRange
            } else {
                NoReturn::Unknown
            },
            depth_noise_per_m: if input.u8() % 2 == 0 {
                0.0
            } else {
                input.float(FLOATS)
            },
            footprint_px: if input.u8() % 2 == 0 {
                0.0
            } else {
                input.float(FLOATS)
            },
        };
    }
    config.solve.max_iterations = u32::from(input.u8() % 64) + 1;

    let n = dims.len();
    let scratch = multigrid::scratch_size(&dims);
    let mut log_odds = vec![0i8; n];
    let mut touched = vec![0u32; map::touched_words(&dims)];
    let mut labels = vec![Label::Outside; n];
    let mut phi = vec![0.0f32; n];
    let mut queue = vec![0u32; usize::from(input.u8()) * 4 + 1];
    let mut coarse_values = vec![0.0f32; scratch.values];
    let mut coarse_labels = vec![Label::Outside; scratch.labels];
    let mut coarse_faces = vec![[0u8; 4]; scratch.faces];
    let mut krylov = vec![0.0f32; scratch.krylov];
    let mut masks = vec![0u8; scratch.masks];
    let storage = ExplorerStorage {
        log_odds: &mut log_odds,
        touched: &mut touched,
        labels: &mut labels,
        phi: &mut phi,
        queue: &mut queue,
        coarse_values: coarse_values.as_mut_slice().into(),
        coarse_labels: &mut coarse_labels,
        coarse_faces: &mut coarse_faces,
        krylov: &mut krylov,
        masks: &mut masks,
        surface: &mut [],
        jacobi: &mut [],
        local_labels: &mut [],
        local_psi: &mut [],
        flat: &mut [],
        fine_log_odds: &mut [],
        fine_touched: &mut [],
    };
    let Ok(mut explorer) = Explorer::new(geometry, config, storage) else {
        return;
    };
    let centre = geometry.center(map::VoxelIndex::new(
        (dims.nx() / 2) as u16,
        (dims.ny() / 2) as u16,
        (dims.nz() / 2) as u16,
    ));

    for _ in 0..16 {
        if input.is_empty() {
            break;
        }
        if input.u8() % 3 == 0 {
            plan(&mut explorer, &mut input, centre);
            continue;
        }
        let (w, h) = (u16::from(input.u8() % 24), u16::from(input.u8() % 16));
        let fx = input.float(FLOATS) * 8.0;
        let fy = input.float(FLOATS) * 8.0;
        let cx = input.float(FLOATS) + f32::from(w) / 2.0;
        let cy = input.float(FLOATS) + f32::from(h) / 2.0;
        let Ok(intrinsics) = Intrinsics::new(fx, fy, cx, cy, w, h) else {
            continue;
        };
        let depth: Vec<u16> = (0..intrinsics.pixel_count())
            .map(|_| match input.u8() {
                0..=31 => 0,
                32..=47 => u16::MAX,
                48..=63 => input.u16(),
                b => u16::from(b) * 20,
            })
            .collect();
        let frame = match DepthFrame::new(intrinsics, &depth) {
            Ok(f) => f,
            Err(e) => panic!("frame of the announced size refused: {e:?}"),
        };
        let t = Translation3::new(
            centre.x + input.float(FLOATS) * resolution,
            centre.y + input.float(FLOATS) * resolution,
            centre.z + input.float(FLOATS) * resolution,
        );
        let q = Quaternion::new(
            input.float(FLOATS),
            input.float(FLOATS),
            input.float(FLOATS),
            input.float(FLOATS),
        );
        let rotation = if input.u8() % 4 == 0 {
            UnitQuaternion::new_unchecked(q)
        } else {
            UnitQuaternion::from_quaternion(q)
        };
        let pose = Isometry3::from_parts(t, rotation);
        let before = explorer.map().counts();
        let rejected_before = explorer.status().errors.frames_rejected;
        let q = pose.rotation.quaternion();
        let bad_pose = !pose
            .translation
            .vector
            .iter()
            .chain(q.coords.iter())
            .all(|c| c.is_finite())
            || (q.norm() - 1.0).abs() > 1e-3;
        match explorer.integrate(&frame, &pose) {
            Ok(_) => assert!(!bad_pose, "a frame with a bad pose was integrated: {pose:?}"),
            Err(fault) => {
                assert!(matches!(fault, Fault::Integrate(_)), "unexpected fault {fault:?}");
                assert_eq!(explorer.status().errors.frames_rejected, rejected_before + 1);
                assert_eq!(explorer.map().counts(), before, "a refused frame changed the map");
            }
        }
        let c = explorer.map().counts();
        assert_eq!(
            (c.free + c.occupied + c.unknown + c.uncertain) as usize,
            n,
            "voxel counts do not add up: {c:?}"
        );
    }
}

/// Plans from a fuzzed vehicle position and checks the outcome.
fn plan(explorer: &mut Explorer<'_>, input: &mut Input<'_>, centre: Point3<f32>) {
    let geometry = *explorer.map().geometry();
    let r = geometry.resolution();
    let position = match input.u8() % 8 {
        0 => Point3::new(input.float(FLOATS), input.float(FLOATS), input.float(FLOATS)),
        _ => Point3::new(
            centre.x + input.float(FLOATS) * r,
            centre.y + input.float(FLOATS) * r,
            centre.z + input.float(FLOATS) * r,
        ),
    };
    let yaw = input.float(FLOATS);
    match explorer.plan(&position, yaw) {
        PlanOutcome::Goal(goal) => {
            assert!(
                goal.position.coords.iter().all(|c| c.is_finite()) && goal.yaw.is_finite(),
                "non-finite goal {goal:?}"
            );
            let Some(v) = geometry.voxel_at(&goal.position) else {
                panic!("goal outside the grid: {goal:?}");
            };
            assert!(
                explorer.map().is_free(geometry.dims().linear(v)),
                "goal in a voxel not known free: {goal:?}"
            );
        }
        PlanOutcome::Complete | PlanOutcome::Hold(_) => {}
    }
}
