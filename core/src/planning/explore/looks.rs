//! Looking around on arrival ([`ExplorerConfig::arrival_looks`]): turns on the spot towards the
//! headings that see the most unexplored space.

use nalgebra::{Point3, Vector3};

use crate::mapping::camera::Intrinsics;
use crate::mapping::integrate;
use crate::mapping::map::{Occupancy, VoxelMap};

use super::config::ExplorerConfig;
use super::status::Goal;

/// The look-around on arrival ([`ExplorerConfig::arrival_looks`]), which the explorer runs for
/// every planner. It remembers, for the goal last arrived at, the headings already looked along
/// there, the turns made and the unexplored voxels left at the last turn.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct ArrivalLooks {
    state: Option<(Goal, u8, u8, u32)>,
}

impl ArrivalLooks {
    /// The next turn on the spot, if one is due: the vehicle (at `position`, facing `yaw`)
    /// stands at `arrived` (its last goal, not an escape; within 1.5 voxels), has turned fewer
    /// than `config.arrival_looks` times there, its last turn there (if any) taught something
    /// (the map's unexplored voxels, unknown and not sealed, fell since), and some heading of
    /// eight, 45° apart, not yet looked along there (the one it faces counts as looked along)
    /// sees an unexplored voxel the camera can resolve ([`unexplored_in_view`], within the
    /// integration's range). The turn faces the heading that sees the most; it keeps the
    /// vehicle where it is and names `arrived`'s frontier. `None` without intrinsics (no frame
    /// yet). Costs one pass over the map's voxels and up to seven views of rays.
    pub fn next(
        &mut self,
        map: &VoxelMap<'_>,
        config: &ExplorerConfig,
        intrinsics: Option<&Intrinsics>,
        arrived: Option<Goal>,
        position: &Point3<f32>,
        yaw: f32,
    ) -> Option<Goal> {
        let max_turns = config.arrival_looks;
        let (min_range, range) = (config.integration.min_range, config.integration.max_range);
        let res = map.geometry().resolution();
        let goal = arrived.filter(|g| !g.escape)?;
        if max_turns == 0 || (goal.position - position).norm() > 1.5 * res {
            return None;
        }
        // The same arrival while the goal is the same; a new goal is a new arrival.
        let (mut looked, mut turns, before) = match self.state.filter(|(g, ..)| *g == goal) {
            Some((_, looked, turns, before)) => (looked, turns, Some(before)),
            None => (0, 0, None),
        };
        if turns >= max_turns {
            return None;
        }
        let counts = map.counts();
        let unexplored = counts.unknown.saturating_sub(counts.sealed);
        looked |= 1 << octant(yaw);
        // A turn that taught nothing ends the look-around: the views left would not either.
        let taught_nothing = turns > 0 && before.is_some_and(|b| unexplored >= b);
        let best = match intrinsics {
            Some(intrinsics) if !taught_nothing => (0..8u8)
                .filter(|k| looked & (1 << k) == 0)
                .map(|k| {
                    let view =
                        unexplored_in_view(map, position, octant_yaw(k), intrinsics, (min_range, range));
                    (view, k)
                })
                .filter(|(n, _)| *n > 0)
                .fold(None, |best: Option<(u32, u8)>, (n, k)| match best {
                    Some((b, _)) if b >= n => best,
                    _ => Some((n, k)),
                }),
            _ => None,
        };
        if taught_nothing {
            turns = max_turns;
        }
        if let Some((_, k)) = best {
            looked |= 1 << k;
            turns += 1;
        }
        self.state = Some((goal, looked, turns, unexplored));
        let (_, k) = best?;
        Some(Goal {
            position: *position,
            yaw: octant_yaw(k),
            frontier: goal.frontier,
            escape: false,
        })
    }
}

/// How many of `LOOK_RAYS`² rays spread evenly over the field of view of a level camera with
/// `intrinsics` at `position`, looking along `heading`, meet an unexplored voxel (unknown, not
/// sealed) between `min_range` and `range` (the camera resolves nothing nearer) before an
/// occupied one.
pub fn unexplored_in_view(
    map: &VoxelMap<'_>,
    position: &Point3<f32>,
    heading: f32,
    intrinsics: &Intrinsics,
    (min_range, range): (f32, f32),
) -> u32 {
    let geometry = *map.geometry();
    let dims = geometry.dims();
    let (half_h, half_v) = intrinsics.half_fov();
    let mut seen = 0;
    for i in 0..LOOK_RAYS {
        let el = (2.0 * (i as f32 + 0.5) / LOOK_RAYS as f32 - 1.0) * half_v;
        let (ce, se) = (libm::cosf(el), libm::sinf(el));
        for j in 0..LOOK_RAYS {
            let az = heading + (2.0 * (j as f32 + 0.5) / LOOK_RAYS as f32 - 1.0) * half_h;
            let d = Vector3::new(libm::cosf(az) * ce, libm::sinf(az) * ce, se);
            let mut found = false;
            integrate::traverse(&geometry, position, &(position + d * range), |v| {
                let i = dims.linear(v);
                if map.occupancy(i) == Occupancy::Occupied {
                    return false;
                }
                found = map.is_unexplored(i) && (geometry.center(v) - position).norm() >= min_range;
                !found
            });
            seen += u32::from(found);
        }
    }
    seen
}

/// Rays per side of the grid [`unexplored_in_view`] casts over the field of view.
const LOOK_RAYS: usize = 24;

/// The octant (0–7, of 45° each, centred on `k`·45°) a yaw falls in; 0 for a non-finite yaw.
pub(super) fn octant(yaw: f32) -> u8 {
    // A float-to-int cast saturates (NaN gives 0); rem_euclid then lies in 0..8.
    let k = libm::roundf(yaw / core::f32::consts::FRAC_PI_4) as i32;
    k.rem_euclid(8) as u8
}

/// The yaw of octant `k` (0–7), in (−π, π].
pub(super) fn octant_yaw(k: u8) -> f32 {
    let k = if k > 4 { i16::from(k) - 8 } else { i16::from(k) };
    f32::from(k) * core::f32::consts::FRAC_PI_4
}
