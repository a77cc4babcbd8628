//! Depth integration: one depth frame in, log-odds updates to the [`VoxelMap`] out.
//!
//! Each used pixel becomes a ray from the camera centre. A valid return marks its endpoint voxel
//! with a *hit* and every voxel the ray crosses before it with a *miss* (Amanatides–Woo voxel
//! traversal, [`traverse`]). A return beyond the maximum range clears free space up to the maximum
//! range with no occupied endpoint. Returns closer than the minimum range are physically
//! implausible for the sensor and are counted as invalid, not integrated.
//!
//! A pixel with no return (depth 0) is weaker evidence. What it means depends on the sensor
//! ([`NoReturn`]). From an active depth camera it may be open space beyond the sensor's reach,
//! but it may as well be a dropout in front of a wall: such a ray clears unknown and free voxels
//! up to the maximum range but stops at the first voxel the map holds occupied (including one
//! hit by another pixel of the same frame) and never lowers it; only a measured return behind a
//! voxel may erode it. Without this rule a single dropout pixel erases wall voxels seen before
//! and opens a path through the wall (the fault campaign's "sensor dropout" cell,
//! docs/RELIABILITY.md). From a stereo matcher ([`NoReturn::Unknown`]) a 0 means "no match",
//! which a wall without texture gives as readily as open space, so it updates nothing.
//!
//! A voxel is updated at most once per frame. Endpoints are applied in a first pass and rays in a
//! second, so a voxel that one pixel hits and another passes through counts as a hit (OctoMap's
//! rule: occupied wins within a scan).
//!
//! ## Noisy depth: the stereo sensor model
//!
//! A stereo camera measures disparity `d = f·b/z` with an error `σ_d`, so depth has the error
//! `σ_z = z²·σ_d/(f·b)`: 3 cm at 1 m, 50 cm at 4 m for a small rig. Integrated with the rules
//! above, such depth grows every surface by about a voxel (half the returns from a wall land in
//! the free voxel in front of it, and the hit wins) and lets far returns place walls where there
//! are none. With [`IntegrationParams::depth_noise_per_m`] = `σ_d/(f·b)` set, a return at depth
//! `z` whose ray has range `r` has the range uncertainty `σ = depth_noise_per_m · z · r`, and:
//!
//! - **misses stop short of the surface**: a ray clears only the voxels it leaves before
//!   `r − 2σ`, never the endpoint's voxel. Where the surface faces the camera (the depth image's
//!   slope over ±2 pixels at most 1, i.e. within 45°) it may clear one voxel further, to
//!   `r − 2σ + h` (`h` the voxel size): the voxel in front of a wall that lies on a voxel
//!   boundary is then cleared by the returns that land just behind it. At grazing incidence
//!   that voxel of leeway would run along the surface and erode it, so it is not given there.
//!   Where the surface is seen more obliquely than that, the misses also stop while the ray is
//!   still half a voxel from the surface, measured square to it: `r − h/2·√(1 + g²)` for a
//!   depth slope `g`, if that is shorter. Along a grazing ray a small depth error moves the
//!   return a long way across the surface, and the misses would clear the layer of voxels the
//!   surface lies in — a table top seen edge-on, or every wall's partly filled voxels when the
//!   grid does not line up with the walls. As `σ → 0` with the surface facing the camera this
//!   is the exact rule.
//! - **hits only where the depth places them**: a return marks its endpoint only when `σ ≤ h`;
//!   a farther one only clears free space. Returns beyond the maximum range clear by the same
//!   rule (no hit), not all the way to the maximum range.
//! - **a vote per voxel per frame**: each voxel the frame hits counts its hits `H` and the
//!   rays `M` that passed through it to a return close behind it (within the ray's `2σ` band and
//!   two voxels), and becomes a hit only if `H > M`, a miss otherwise — instead of "the hit
//!   wins", which let a minority of short returns in front of a wall grow it by a voxel. A ray
//!   that passes a voxel and ends far behind it does not vote: it may have grazed the free part
//!   of a voxel an object's edge or tip only partly fills, which must stay occupied. The counts
//!   live in caller scratch ([`integrate_with_scratch`], two `u32` per voxel the frame hits);
//!   voxels that do not fit fall back to "the hit wins", counted in
//!   [`IntegrationStats::vote_overflow`].
//!
//! ## A surface estimate across frames (optional, host-sized)
//!
//! One frame's vote cannot tell the voxel in front of a wall that lies on a voxel face (free)
//! from a voxel the wall cuts through near its far face (occupied): both see about as many
//! returns land inside as behind. Where the map has a surface estimate
//! ([`VoxelMap::with_surface`], two words per voxel: the firmware has no RAM for it), every
//! return with `σ ≤ h` whose pixel has a surface normal (from the 3D points
//! `NORMAL_SPAN_PX` pixels either side, refused across depth edges and corners and near
//! edge-on) adds to each voxel its ray crosses near the return the signed distance of the
//! voxel's centre in front of that surface, along the normal, in half voxels, weighted
//! `(h/σ)²`. The voxels a frame samples are decided by their mean over every frame so far:
//! the log-odds is set to how many standard errors the mean lies below
//! `SURFACE_OCCUPIED` (free above it); a voxel whose mean puts it behind the surface is left
//! as it is. A return's samples stop at the first voxel along its ray that the map holds
//! occupied and whose mean puts the surface in it: that voxel hides the ones behind it, so a
//! return that lands deep (its error, or a filter that mixed a nearer edge into it) does not
//! mark a second layer behind a surface already seen, nor the free voxel on the far side of a
//! one-voxel wall (docs/RESULTS.md, "A surface voxel hides what lies behind it"). What such
//! returns left behind a surface before it was established goes too: after the frame, each
//! return that reaches a surface voxel the map holds occupied with a sure estimate forgets the
//! voxels behind it along the normal whose evidence is weak (about two hits at most) and that
//! no free voxel touches, and seals them (unknown, no frontier, an obstacle to the planner;
//! [`IntegrationStats::stale_forgotten`], docs/RESULTS.md, "Stale evidence behind a
//! surface"). A return on a depth edge (a face neighbour far away in depth: the stereo
//! pipeline's filter may mix the two sides into a return in mid-air) marks nothing; a return
//! without a normal keeps the vote.
//! Measured in docs/RESULTS.md ("A surface estimate kept across frames" and after). The
//! estimate is storage the caller lends: the simulator lends it by default for noisy and
//! matched stereo depth, the firmware has no room for it.

use nalgebra::{Isometry3, Point3, Vector3};

use crate::mapping::camera::{DepthFrame, NOT_RECEIVED};
use crate::mapping::map::{Dims, MapGeometry, Occupancy, VoxelIndex, VoxelMap};

/// What a depth-0 pixel means.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum NoReturn {
    /// Nothing within the sensor's range (an active depth camera): clear free space up to the
    /// maximum range.
    #[default]
    ClearToMaxRange,
    /// Nothing measured (a stereo matcher found no reliable match): the pixel says nothing and
    /// updates no voxel.
    Unknown,
}

/// How depth pixels are turned into map updates.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct IntegrationParams {
    /// Returns closer than this (metres, along the ray) are invalid.
    pub min_range: f32,
    /// Returns beyond this clear free space up to it, with no endpoint.
    pub max_range: f32,
    /// Use every k-th pixel in both directions (1 = all pixels).
    pub pixel_stride: u16,
    /// What depth 0 means.
    pub no_return: NoReturn,
    /// The sensor's depth noise, `σ_d / (f·b)` in 1/m (disparity error over focal length ×
    /// baseline): a return at depth `z` has the depth error `σ_z = depth_noise_per_m · z²`.
    /// 0 (the default) treats depth as exact; see the module doc for what changes otherwise.
    pub depth_noise_per_m: f32,
    /// With depth noise: the width, in pixels of the depth frame, over which the depth pipeline
    /// aggregates (a stereo matcher's window). On a surface slanted by `g` (depth per lateral
    /// metre) the window spans `g·w·z/f` metres of depth, and a match may land anywhere in it:
    /// the range error gains that span's standard deviation as a uniform spread (`1/√12` of it,
    /// added in quadrature to the disparity error), so a grazing surface, where block matching
    /// fails worst, neither marks voxels nor clears space near its returns. The window cannot
    /// tell a thin or nearer object within its footprint from what lies behind it either, so a
    /// return clears no deeper than 2σ short of the nearest depth within half the footprint
    /// (the edge of a wall seen past, a post). A return whose slant cannot be measured (no
    /// depth on a side, even one pixel away) is left out and counted
    /// ([`IntegrationStats::unmeasured_slant`]). 0 (the default) adds nothing.
    pub footprint_px: f32,
}

impl Default for IntegrationParams {
    /// The seed thesis's simulated sensor: 0.3–10 m, every pixel.
    fn default() -> Self {
        Self {
            min_range: 0.3,
            max_range: 10.0,
            pixel_stride: 1,
            no_return: NoReturn::ClearToMaxRange,
            depth_noise_per_m: 0.0,
            footprint_px: 0.0,
        }
    }
}

/// The range error of a match that may land anywhere in its window's depth span, as a share of
/// that span: the standard deviation of a uniform spread, `1/√12`.
const FOOTPRINT_SIGMA: f32 = 0.288_675_13;

/// Misses stop this many standard deviations of the range before a noisy return.
const FREE_MARGIN_SIGMAS: f32 = 2.0;
/// Pixels either side over which the depth image's slope is measured.
const SLOPE_SPAN_PX: usize = 2;
/// Largest slope (depth change per lateral metre) of a surface that faces the camera enough
/// for the misses' voxel of leeway: 1, 45° of incidence.
const MAX_FACING_SLOPE: f32 = 1.0;
/// Beyond [`MAX_FACING_SLOPE`], misses stop this many voxels from the surface, measured square
/// to it. Measured (docs/RESULTS.md, "Surfaces on voxel faces"): on grids that do not line up
/// with the walls, runs with a contact 5 → 0 of 36 at the same coverage.
const OBLIQUE_MARGIN_VOXELS: f32 = 0.5;
/// A ray votes against a voxel's hits only if the voxel lies within the ray's `2σ` band and
/// this many voxels of its return.
const VOTE_REACH_VOXELS: f32 = 2.0;

/// What one frame's integration did.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct IntegrationStats {
    /// Pixels looked at (after the stride).
    pub pixels: u32,
    /// Pixels with a valid return inside the range.
    pub returns: u32,
    /// Pixels with depth 0 (integrated or not, per [`IntegrationParams::no_return`]).
    pub no_return: u32,
    /// Of those, rays that stopped at a voxel held occupied instead of clearing through it.
    pub no_return_blocked: u32,
    /// Pixels whose return lies beyond the maximum range.
    pub beyond_range: u32,
    /// Pixels closer than the minimum range: counted, not integrated.
    pub invalid: u32,
    /// Pixels that were never received ([`NOT_RECEIVED`]: rows lost on the depth link):
    /// counted, not integrated.
    pub not_received: u32,
    /// Returns whose endpoint lies outside the grid (the in-grid part of the ray is still used).
    pub endpoint_outside: u32,
    /// Voxels visited by ray traversal (work done).
    pub voxels_traversed: u32,
    /// Log-odds updates applied (at most one per voxel).
    pub voxel_updates: u32,
    /// With depth noise: returns too uncertain to mark their endpoint (`σ` above a voxel).
    pub uncertain_returns: u32,
    /// With depth noise: voxels the frame hit whose update the hit/miss vote decided.
    pub voted: u32,
    /// With depth noise: voxels the frame hit that did not fit in the vote's scratch and were
    /// updated by "the hit wins" instead.
    pub vote_overflow: u32,
    /// With a [footprint](IntegrationParams::footprint_px): returns whose slant, and so whose
    /// error, cannot be measured (a neighbour two pixels away and one a pixel away without
    /// depth): counted, not integrated (a matcher's worst errors lie at the edges of what it
    /// could match).
    pub unmeasured_slant: u32,
    /// With the surface estimate: occupied voxels behind an established surface whose weak
    /// evidence was dropped after the frame, so they are unknown again (`forget_stale_behind`).
    pub stale_forgotten: u32,
}

/// Why a frame was not integrated.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum IntegrateError {
    /// The camera pose has a non-finite translation or rotation.
    BadPose,
    /// The range limits are not finite or not `0 < min < max`, or the depth noise or the
    /// footprint is negative or not finite.
    BadRange,
    /// The camera pose is farther from the previous frame's than
    /// [`ExplorerConfig::max_frame_jump_m`](crate::planning::explore::ExplorerConfig::max_frame_jump_m)
    /// (refused by the explorer; [`integrate`] itself has no memory of earlier frames).
    PoseJump,
    /// The vehicle was turning faster than
    /// [`ExplorerConfig::max_frame_yaw_rate`](crate::planning::explore::ExplorerConfig::max_frame_yaw_rate)
    /// when the frame was taken (refused by the explorer, given the frame's
    /// [`FrameTiming`](crate::planning::explore::FrameTiming)).
    TurningTooFast,
    /// The pose stream was older than the frame by more than
    /// [`ExplorerConfig::max_frame_pose_lag_ms`](crate::planning::explore::ExplorerConfig::max_frame_pose_lag_ms)
    /// (refused by the explorer, given the frame's
    /// [`FrameTiming`](crate::planning::explore::FrameTiming)).
    StalePose,
}

/// Integrates one depth frame taken from `camera_pose` (camera frame → map frame), with no
/// scratch for the noisy-depth vote (every voxel a noisy frame hits then falls back to "the hit
/// wins"; see [`integrate_with_scratch`]).
pub fn integrate(
    map: &mut VoxelMap<'_>,
    frame: &DepthFrame<'_>,
    camera_pose: &Isometry3<f32>,
    params: &IntegrationParams,
) -> Result<IntegrationStats, IntegrateError> {
    integrate_with_scratch(map, frame, camera_pose, params, &mut [])
}

/// Integrates one depth frame taken from `camera_pose` (camera frame → map frame). With depth
/// noise ([`IntegrationParams::depth_noise_per_m`] > 0), `scratch` holds the per-voxel vote of
/// the frame: two words per voxel the frame hits, at most half of it in use (the explorer lends
/// its flood-fill queue). Exact depth does not use it.
pub fn integrate_with_scratch(
    map: &mut VoxelMap<'_>,
    frame: &DepthFrame<'_>,
    camera_pose: &Isometry3<f32>,
    params: &IntegrationParams,
    scratch: &mut [u32],
) -> Result<IntegrationStats, IntegrateError> {
    let q = camera_pose.rotation.quaternion();
    let finite = camera_pose
        .translation
        .vector
        .iter()
        .chain(q.coords.iter())
        .all(|c| c.is_finite());
    if !finite || (q.norm() - 1.0).abs() > 1e-3 {
        return Err(IntegrateError::BadPose);
    }
    if !(params.min_range.is_finite()
        && params.max_range.is_finite()
        && params.min_range >= 0.0
        && params.min_range < params.max_range
        && params.depth_noise_per_m.is_finite()
        && params.depth_noise_per_m >= 0.0
        && params.footprint_px.is_finite()
        && params.footprint_px >= 0.0)
    {
        return Err(IntegrateError::BadRange);
    }
    let geometry = *map.geometry();
    let origin = Point3::from(camera_pose.translation.vector);
    let mut stats = IntegrationStats::default();
    map.begin_frame();
    let mut votes = Votes::new(if params.depth_noise_per_m > 0.0 {
        scratch
    } else {
        &mut []
    });

    let surface_mode = params.depth_noise_per_m > 0.0 && !map.surface().is_empty();
    let h = geometry.resolution();

    // Pass 1: endpoints (with depth noise, the confident ones: a vote each).
    for_each_pixel_ray(
        frame,
        camera_pose,
        params,
        h,
        Want::Endpoints {
            surface: surface_mode,
        },
        |ray| {
            if surface_mode {
                if let PixelRay::Noisy {
                    end,
                    hit: true,
                    sigma,
                    normal: Some(n),
                    ..
                } = ray
                {
                    let Some(band) = SampleBand::of(&origin, &end, &n, sigma, h) else {
                        return;
                    };
                    // Distances in half voxels: a voxel's faces lie ±1 from its centre.
                    let half = 0.5 * h;
                    let ratio = h / sigma.max(1e-6);
                    let w = libm::roundf(ratio * ratio).clamp(1.0, SURFACE_MAX_SAMPLE_WEIGHT) as i32;
                    let dims = geometry.dims();
                    traverse(&geometry, &band.start, &band.end, |voxel| {
                        let delta = (geometry.center(voxel) - end).dot(&n) / half;
                        if delta < -SURFACE_BEHIND {
                            return true;
                        }
                        let i = dims.linear(voxel);
                        // A voxel the map holds occupied whose mean puts the surface in it
                        // hides the voxels behind it from this return.
                        let occludes = surface_voxel_weight(map, i).is_some();
                        surface_add(map.surface_mut(), i, delta.min(SURFACE_BAND), w);
                        if !votes.hit(i, map) {
                            let occ =
                                surface_estimate(map.surface(), i).is_some_and(|(m, _)| m < SURFACE_OCCUPIED);
                            let applied = if occ { map.apply_hit(i) } else { map.apply_miss(i) };
                            if applied {
                                stats.voxel_updates += 1;
                                stats.vote_overflow += 1;
                            }
                        }
                        !occludes
                    });
                    return;
                }
            }
            let end = match ray {
                PixelRay::Noisy { edge: true, .. } => return,
                PixelRay::Return { end } | PixelRay::Noisy { end, hit: true, .. } => end,
                _ => return,
            };
            if let Some(v) = geometry.voxel_at(&end) {
                let i = geometry.dims().linear(v);
                let noisy = matches!(ray, PixelRay::Noisy { .. });
                if noisy && votes.hit(i, map) {
                    return;
                }
                if map.apply_hit(i) {
                    stats.voxel_updates += 1;
                    stats.vote_overflow += u32::from(noisy);
                }
            }
        },
    );

    // Pass 2: free space along every usable ray, classifying pixels as we go.
    for_each_pixel_ray(frame, camera_pose, params, h, Want::FreeSpace, |ray| {
        stats.pixels += 1;
        let mut weak = false;
        let (end, endpoint) = match ray {
            PixelRay::Invalid => {
                stats.invalid += 1;
                return;
            }
            PixelRay::UnmeasuredSlant => {
                stats.unmeasured_slant += 1;
                return;
            }
            PixelRay::NotReceived => {
                stats.not_received += 1;
                return;
            }
            PixelRay::NoReturn { end } => {
                stats.no_return += 1;
                if params.no_return == NoReturn::Unknown {
                    return;
                }
                weak = true;
                (end, None)
            }
            PixelRay::BeyondRange { end } => {
                stats.beyond_range += 1;
                (end, None)
            }
            PixelRay::Return { end } => {
                stats.returns += 1;
                let v = geometry.voxel_at(&end);
                if v.is_none() {
                    stats.endpoint_outside += 1;
                }
                (end, v)
            }
            PixelRay::Noisy {
                end,
                free_to,
                hit,
                beyond,
                reach,
                ..
            } => {
                let v = geometry.voxel_at(&end);
                if beyond {
                    stats.beyond_range += 1;
                } else {
                    stats.returns += 1;
                    stats.uncertain_returns += u32::from(!hit);
                    stats.endpoint_outside += u32::from(v.is_none());
                }
                // Only the voxels the ray leaves before `free_to` are known free: the one
                // `free_to` lies in (the last visited) and the endpoint's are left alone.
                let dims = geometry.dims();
                let mut previous: Option<VoxelIndex> = None;
                traverse(&geometry, &origin, &free_to, |voxel| {
                    stats.voxels_traversed += 1;
                    if let Some(p) = previous.filter(|p| Some(*p) != v) {
                        let i = dims.linear(p);
                        if map.apply_miss(i) {
                            stats.voxel_updates += 1;
                        } else {
                            votes.pass(i, || (geometry.center(p) - end).norm() <= reach);
                        }
                    }
                    previous = Some(voxel);
                    true
                });
                return;
            }
        };
        let endpoint = endpoint.map(|v| geometry.dims().linear(v));
        traverse_linear(&geometry, &origin, &end, |i| {
            stats.voxels_traversed += 1;
            if Some(i) == endpoint {
                return false;
            }
            if weak && map.occupancy(i) == Occupancy::Occupied {
                stats.no_return_blocked += 1;
                return false;
            }
            if map.apply_miss(i) {
                stats.voxel_updates += 1;
            }
            true
        });
    });

    // Pass 3: the votes.
    for (i, hits, passes) in votes.decided() {
        let estimate = if surface_mode {
            surface_estimate(map.surface(), i)
        } else {
            None
        };
        if let Some((m, weight)) = estimate {
            if m < -SURFACE_HIDDEN {
                continue;
            }
            // The evidence for "occupied": how many standard errors the mean lies below the
            // threshold (a sample of weight w has the variance 4/w in half voxels, inflated
            // for the correlation of neighbouring pixels).
            let z = (SURFACE_OCCUPIED - m) * libm::sqrtf(weight / (4.0 * SURFACE_CORRELATION));
            map.set_reserved(i, z * SURFACE_LOG_ODDS_PER_SE);
        } else {
            map.apply_reserved(i, hits > passes);
        }
        stats.voxel_updates += 1;
        stats.voted += 1;
    }

    // Pass 4: weak evidence behind the surfaces this frame established.
    if surface_mode {
        forget_stale_behind(map, frame, camera_pose, params, &mut stats);
    }
    Ok(stats)
}

/// The stretch of a noisy return's ray whose voxels its surface samples reach (pass 1), and
/// what pass 4 extends it from.
struct SampleBand {
    /// Unit direction of the ray.
    dir: Vector3<f32>,
    /// Cosine of incidence on the surface (normal against the ray), at least
    /// [`SURFACE_MIN_COS`]: the band along the ray is stretched by its inverse.
    cos: f32,
    /// Where the band starts: [`SURFACE_BAND`] half voxels plus `2σ` in front of the return,
    /// along the normal, but not behind the camera.
    start: Point3<f32>,
    /// Where it ends: as far behind the return.
    end: Point3<f32>,
}

impl SampleBand {
    /// The band of the return at `end` seen from `origin`, surface normal `n`, range error
    /// `sigma`, voxel size `h`; `None` for a return at the camera (or not a number).
    fn of(origin: &Point3<f32>, end: &Point3<f32>, n: &Vector3<f32>, sigma: f32, h: f32) -> Option<Self> {
        let to_end = end - origin;
        let range = to_end.norm();
        if range.is_nan() || range <= 0.0 {
            return None;
        }
        let dir = to_end / range;
        let cos = (-n.dot(&dir)).max(SURFACE_MIN_COS);
        let reach = (SURFACE_BAND * 0.5 * h + FREE_MARGIN_SIGMAS * sigma) / cos;
        Some(Self {
            dir,
            cos,
            start: end - dir * reach.min(range),
            end: end + dir * reach,
        })
    }
}

/// Pass 4 of a noisy frame with the surface estimate: every return with a normal that reaches
/// a surface voxel the map now holds occupied with a sure estimate (its mean puts the surface
/// in it, weight above [`STALE_MAX_WEIGHT`]) drops the weak evidence of the voxels behind that
/// voxel along the normal ([`drop_stale_evidence`]). Returns that land behind an established
/// surface add nothing to the voxels it hides (pass 1); this removes what such returns left
/// there before the surface was established, and what this frame's votes of returns without a
/// normal put there.
fn forget_stale_behind(
    map: &mut VoxelMap<'_>,
    frame: &DepthFrame<'_>,
    camera_pose: &Isometry3<f32>,
    params: &IntegrationParams,
    stats: &mut IntegrationStats,
) {
    let geometry = *map.geometry();
    let h = geometry.resolution();
    let half = 0.5 * h;
    let dims = geometry.dims();
    let origin = Point3::from(camera_pose.translation.vector);
    for_each_pixel_ray(
        frame,
        camera_pose,
        params,
        h,
        Want::Endpoints { surface: true },
        |ray| {
            let PixelRay::Noisy {
                end,
                hit: true,
                sigma,
                normal: Some(n),
                ..
            } = ray
            else {
                return;
            };
            let Some(band) = SampleBand::of(&origin, &end, &n, sigma, h) else {
                return;
            };
            // Pass 1's band, and past it far enough to reach what a surface near its end hides.
            let band_end = band.end + band.dir * (STALE_DEPTH_HALF_VOXELS * half / band.cos);
            // The centre of the established surface voxel the ray reached, once it has.
            let mut surface: Option<Point3<f32>> = None;
            traverse(&geometry, &band.start, &band_end, |voxel| {
                let Some(s) = surface else {
                    let i = dims.linear(voxel);
                    if surface_voxel_weight(map, i).is_some_and(|w| w > STALE_MAX_WEIGHT) {
                        surface = Some(geometry.center(voxel));
                    }
                    return true;
                };
                // How far behind it along the normal (half voxels): not the voxels beside it that
                // a grazing ray runs through next.
                let depth = (s - geometry.center(voxel)).dot(&n) / half;
                if depth > STALE_DEPTH_HALF_VOXELS {
                    return false;
                }
                if depth >= 1.0 && drop_stale_evidence(map, voxel) {
                    stats.stale_forgotten += 1;
                }
                true
            });
        },
    );
}

/// The surface estimate's distances are in half voxels along the surface's normal, positive
/// in front of it: a voxel's faces lie ±1 from its centre, so the voxel in front of a wall on a
/// voxel face is at +1 and the wall's voxel at −1. A return's sample reaches the voxels its ray
/// crosses within this many (plus its `2σ`) of it, and is clamped to it in front.
const SURFACE_BAND: f32 = 3.0;
/// A voxel whose mean is below this is occupied. Below 1 (where the voxel's far face would
/// touch the surface): the voxel in front of a wall on a voxel face sits exactly at 1, and the
/// tilt of noisy normals shrinks every mean a little towards 0.
const SURFACE_OCCUPIED: f32 = 0.6;
/// A voxel whose mean is at most this (its centre at or behind the surface) holds the surface:
/// once the map holds it occupied, a return's samples stop there (the voxels behind it are
/// hidden from the return, whose error, not a second surface, puts it deeper).
const SURFACE_IN_VOXEL: f32 = 0.0;
/// A voxel whose mean is below minus this lies behind the surface, where exact depth would not
/// observe it either: it is not updated.
const SURFACE_HIDDEN: f32 = 1.1;
/// Samples further behind the surface than this are not taken: a one-voxel wall's far side
/// lies at −3 from its near surface.
const SURFACE_BEHIND: f32 = 1.5;
/// How far behind an established surface voxel (half voxels along the normal) pass 4 looks for
/// stale evidence ([`drop_stale_evidence`]): the next voxel and the one after it.
const STALE_DEPTH_HALF_VOXELS: f32 = 4.0;
/// Largest log-odds of stale evidence: about two hits.
const STALE_MAX_LOG_ODDS: f32 = 1.5;
/// Largest surface weight of stale evidence (one sample weighs `(h/σ)²`, at most 16), and the
/// least a surface voxel needs before it hides the voxels behind it.
const STALE_MAX_WEIGHT: f32 = 24.0;
/// Smallest cosine of incidence the band along the ray is stretched for.
const SURFACE_MIN_COS: f32 = 0.7;
/// Largest weight of one sample, `(h/σ)²`: σ a quarter voxel.
const SURFACE_MAX_SAMPLE_WEIGHT: f32 = 16.0;
/// Pixels either side over which the surface normal is measured.
const NORMAL_SPAN_PX: usize = 8;
/// Smallest cosine between a normal and the ray: surfaces seen more edge-on have none.
const NORMAL_MIN_COS: f32 = 0.3;
/// A normal's centre pixel may lie this many `σ` (at least half a voxel) off the midpoints of
/// its span; farther, the span crosses a depth edge or a corner.
const NORMAL_BEND_SIGMAS: f32 = 3.0;
/// A return whose face neighbour's depth differs by more than this many `σ` (at least two
/// voxels) lies on a depth edge.
const EDGE_JUMP_SIGMAS: f32 = 4.0;
/// Variance inflation of a surface sample for the correlation between neighbouring pixels
/// (the stereo pipeline's median window moves a patch's returns together).
const SURFACE_CORRELATION: f32 = 10.0;
/// Log-odds per standard error of a voxel's mean from [`SURFACE_OCCUPIED`].
const SURFACE_LOG_ODDS_PER_SE: f32 = 1.0;
/// Units of a half voxel in the stored sums.
const SURFACE_SCALE: f32 = 256.0;
/// Weight at which a voxel's sums are halved, so newer samples keep counting.
const SURFACE_MAX_WEIGHT: i32 = 1 << 16;

/// Adds a sample `delta` (half voxels) with weight `w` to voxel `i`'s surface estimate: the
/// weighted sum of its samples (in 1/[`SURFACE_SCALE`]) and their weight.
fn surface_add(surface: &mut [[i32; 2]], i: usize, delta: f32, w: i32) {
    let Some([sum, weight]) = surface.get_mut(i) else {
        return;
    };
    let x = libm::roundf(delta.clamp(-4.0, 4.0) * SURFACE_SCALE) as i32;
    *sum = sum.saturating_add(x * w);
    *weight = weight.saturating_add(w);
    if *weight > SURFACE_MAX_WEIGHT {
        *sum /= 2;
        *weight /= 2;
    }
}

/// Voxel `i`'s surface estimate in `map` ([`VoxelMap::with_surface`]): the mean distance of
/// its centre in front of the surface, in half voxels (+1: the voxel in front of a surface on
/// its far face, −1: the voxel behind it), and the weight of the samples behind that mean
/// (one return with `σ` a voxel weighs 1). `None` without an estimate or samples. For
/// diagnosing a map; the integrator decides the voxel's log-odds from it.
pub fn surface_estimate_at(map: &VoxelMap<'_>, i: usize) -> Option<(f32, f32)> {
    surface_estimate(map.surface(), i)
}

/// Voxel `i`'s mean distance in front of the surface (half voxels) and the weight behind it
/// (`None`: no samples).
fn surface_estimate(surface: &[[i32; 2]], i: usize) -> Option<(f32, f32)> {
    let [sum, weight] = *surface.get(i)?;
    (weight > 0).then(|| (sum as f32 / (weight as f32 * SURFACE_SCALE), weight as f32))
}

/// The surface-estimate weight of voxel `i` if it holds a surface: the map holds it occupied
/// and its mean puts the surface in it ([`SURFACE_IN_VOXEL`]). Such a voxel hides the voxels
/// behind it from a return (pass 1); with a sure weight, pass 4 forgets stale evidence there.
fn surface_voxel_weight(map: &VoxelMap<'_>, i: usize) -> Option<f32> {
    if map.occupancy(i) != Occupancy::Occupied {
        return None;
    }
    surface_estimate(map.surface(), i).and_then(|(m, w)| (m <= SURFACE_IN_VOXEL).then_some(w))
}

/// Forgets and seals `voxel`, hidden behind an established surface (pass 4,
/// [`forget_stale_behind`]), if what made it occupied is weak (log-odds at most
/// [`STALE_MAX_LOG_ODDS`], surface weight at most [`STALE_MAX_WEIGHT`]) and no free voxel
/// touches it. Such evidence came from returns that landed deep: under the forward sensor
/// model they are the depth error of the surface in front, and the noise-free sensor would not
/// observe the voxel. A voxel that touches a free one is kept (the far side or the end of a
/// thin wall, seen from there), and so is one with strong evidence (a surface seen from its own
/// side). Returns whether it was forgotten.
fn drop_stale_evidence(map: &mut VoxelMap<'_>, voxel: VoxelIndex) -> bool {
    let dims = map.dims();
    let i = dims.linear(voxel);
    let weak = map.occupancy(i) == Occupancy::Occupied
        && map.log_odds(i) <= STALE_MAX_LOG_ODDS
        && surface_estimate(map.surface(), i).is_none_or(|(_, w)| w <= STALE_MAX_WEIGHT);
    if !weak {
        return false;
    }
    // No free voxel touches it, not even at an edge or a corner (the end of a thin wall).
    if dims.any_in_block(voxel, |j| map.is_free(j)) {
        return false;
    }
    if let Some(s) = map.surface_mut().get_mut(i) {
        *s = [0, 0];
    }
    // Sealed: unknown, so the map no longer claims it, but no frontier (nothing can see it
    // past the surface) and an obstacle to the planner, as it was while occupied.
    map.forget(i) && map.seal(i)
}

/// The per-frame hit/miss vote of the voxels a noisy frame hits: an open-addressing table in
/// caller scratch, two words per slot (voxel index + 1, or 0 for an empty slot; hits in the high
/// half and passes in the low half of the second, saturating). Filled to at most half, so
/// probes stay short; a voxel that finds no room is not voted on.
struct Votes<'s> {
    slots: &'s mut [[u32; 2]],
    used: usize,
}

impl<'s> Votes<'s> {
    fn new(scratch: &'s mut [u32]) -> Self {
        let (slots, _) = scratch.as_chunks_mut::<2>();
        slots.fill([0, 0]);
        Self { slots, used: 0 }
    }

    /// The slot of voxel `i`, or the empty slot where it would go (`None`: no table, a full
    /// one, or an `i` that does not fit a key).
    fn slot(&self, i: usize) -> Option<usize> {
        let n = self.slots.len();
        let key = u32::try_from(i).ok()?.checked_add(1)?;
        // Fibonacci hashing, reduced to the capacity by a multiply-shift.
        let h = key.wrapping_mul(0x9E37_79B9);
        let mut s = ((u64::from(h) * n as u64) >> 32) as usize;
        for _ in 0..n {
            let k = self.slots.get(s)?[0];
            if k == key || k == 0 {
                return Some(s);
            }
            s = if s + 1 == n { 0 } else { s + 1 };
        }
        None
    }

    /// Counts a hit on voxel `i`, reserving the voxel's update for the vote. False if the table
    /// has no room for it (the caller applies the hit directly).
    fn hit(&mut self, i: usize, map: &mut VoxelMap<'_>) -> bool {
        let Some(s) = self.slot(i) else {
            return false;
        };
        let half_full = 2 * (self.used + 1) > self.slots.len();
        let Some(slot) = self.slots.get_mut(s) else {
            return false;
        };
        if slot[0] == 0 {
            if half_full || !map.reserve(i) {
                return false;
            }
            // `slot` found a key for `i`, so `i + 1` fits a u32.
            slot[0] = i as u32 + 1;
            self.used += 1;
        }
        if slot[1] >> 16 < 0xffff {
            slot[1] += 1 << 16;
        }
        true
    }

    /// Counts a ray that passed through voxel `i`, if the frame hit it and `close` (asked only
    /// then) says the ray's return lies close enough behind the voxel to vote.
    fn pass(&mut self, i: usize, close: impl FnOnce() -> bool) {
        if self.used == 0 {
            return;
        }
        if let Some(slot) = self.slot(i).and_then(|s| self.slots.get_mut(s)) {
            if slot[0] != 0 && slot[1] & 0xffff < 0xffff && close() {
                slot[1] += 1;
            }
        }
    }

    /// The voted voxels: (index, hits, passes).
    fn decided(&self) -> impl Iterator<Item = (usize, u32, u32)> + '_ {
        self.slots
            .iter()
            .filter(|e| e[0] != 0)
            .map(|e| ((e[0] - 1) as usize, e[1] >> 16, e[1] & 0xffff))
    }
}

/// One pixel's measurement, in map coordinates.
#[derive(Clone, Copy)]
enum PixelRay {
    /// Closer than the minimum range.
    Invalid,
    /// A noisy return whose slant the [footprint](IntegrationParams::footprint_px) needs but
    /// cannot be measured.
    UnmeasuredSlant,
    /// Never received (a row lost on the link).
    NotReceived,
    /// Depth 0: clear to `end` (maximum range along the pixel's ray).
    NoReturn { end: Point3<f32> },
    /// Return beyond the maximum range: clear to `end`.
    BeyondRange { end: Point3<f32> },
    /// A valid return at `end` (exact depth).
    Return { end: Point3<f32> },
    /// With depth noise, a return at `end`: clear the voxels left before `free_to`; `hit`: mark
    /// the endpoint (`σ` at most a voxel); `beyond`: the return lies beyond the maximum range;
    /// `reach`: the ray votes against voxels hit this frame whose centre is this close to `end`;
    /// `sigma`: its range error; `normal`: the surface's, facing the camera (map frame; only
    /// for the surface estimate); `edge`: it lies on a depth edge and marks nothing (likewise).
    Noisy {
        end: Point3<f32>,
        free_to: Point3<f32>,
        hit: bool,
        beyond: bool,
        reach: f32,
        sigma: f32,
        normal: Option<Vector3<f32>>,
        edge: bool,
    },
}

/// What a pass needs of the noisy rays beyond their ends.
#[derive(Clone, Copy, PartialEq)]
enum Want {
    /// Where their free space ends ([`PixelRay::Noisy`]'s `free_to`, `reach`: the slope test).
    FreeSpace,
    /// Their ends; with `surface`, also the normals and depth edges of the returns that may
    /// mark a surface (the surface estimate's samples).
    Endpoints { surface: bool },
}

/// Calls `f` with every used pixel's ray; `want` says which of a noisy ray's costlier fields
/// the pass needs (the others are left at their defaults: no slope, no normal, no edge).
fn for_each_pixel_ray(
    frame: &DepthFrame<'_>,
    pose: &Isometry3<f32>,
    params: &IntegrationParams,
    resolution: f32,
    want: Want,
    mut f: impl FnMut(PixelRay),
) {
    let k = usize::from(params.pixel_stride.max(1));
    let intr = frame.intrinsics();
    let width = usize::from(intr.width());
    for (v, row) in frame.depth_mm().chunks_exact(width).enumerate().step_by(k) {
        for (u, &d) in row.iter().enumerate().step_by(k) {
            // u < width and v < height, both u16.
            let ray_cam = intr.ray(u as u16, v as u16);
            let ray_len = ray_cam.norm();
            let dir: Vector3<f32> = pose.rotation * (ray_cam / ray_len);
            let origin = Point3::from(pose.translation.vector);
            let clear_to = origin + dir * params.max_range;
            let ray = if d == NOT_RECEIVED {
                PixelRay::NotReceived
            } else if d == 0 {
                PixelRay::NoReturn { end: clear_to }
            } else {
                let range = f32::from(d) * 1e-3 * ray_len;
                if range < params.min_range {
                    PixelRay::Invalid
                } else if params.depth_noise_per_m > 0.0 {
                    let z = f32::from(d) * 1e-3;
                    let footprint = params.footprint_px > 0.0;
                    let slope2 = if footprint {
                        surface_slope2(frame, u, v, z, SLOPE_SPAN_PX)
                            .or_else(|| surface_slope2(frame, u, v, z, 1))
                    } else if want == Want::FreeSpace {
                        surface_slope2(frame, u, v, z, SLOPE_SPAN_PX)
                    } else {
                        None
                    };
                    if footprint && slope2.is_none() {
                        f(PixelRay::UnmeasuredSlant);
                        continue;
                    }
                    let disparity = params.depth_noise_per_m * z * range;
                    let sigma = match slope2 {
                        // A match anywhere in the window's depth span on this slant: the
                        // standard deviation of a uniform spread, along the ray (a flat surface
                        // adds nothing, whatever the footprint).
                        Some(g2) if footprint && g2 > 0.0 => {
                            let window =
                                FOOTPRINT_SIGMA * params.footprint_px * range * libm::sqrtf(g2) / intr.fx();
                            libm::sqrtf(disparity * disparity + window * window)
                        }
                        _ => disparity,
                    };
                    let beyond = range > params.max_range;
                    let hit = sigma <= resolution && !beyond;
                    // Only a return that may mark a surface needs a normal, and only one
                    // without a normal the depth-edge test (the others never read them).
                    let surface = hit && want == (Want::Endpoints { surface: true });
                    let mut free = free_length(range, sigma, slope2, resolution);
                    if footprint && want == Want::FreeSpace {
                        // The window cannot tell a thin or nearer object within its footprint
                        // from what lies behind it: clear no deeper than the nearest depth there.
                        let reach = (libm::ceilf(0.5 * params.footprint_px) as usize).min(width);
                        let nearest = nearest_depth(frame, u, v, reach).unwrap_or(z);
                        free = free.min(nearest * ray_len - FREE_MARGIN_SIGMAS * sigma);
                    }
                    let free = free.min(params.max_range).max(0.0);
                    let normal = if surface {
                        let bend = (NORMAL_BEND_SIGMAS * sigma).max(0.5 * resolution);
                        surface_normal(frame, u, v, pose, &dir, bend)
                    } else {
                        None
                    };
                    let jump = (EDGE_JUMP_SIGMAS * sigma).max(2.0 * resolution);
                    PixelRay::Noisy {
                        end: origin + dir * range,
                        free_to: origin + dir * free,
                        hit,
                        beyond,
                        reach: range - free + VOTE_REACH_VOXELS * resolution,
                        sigma,
                        normal,
                        edge: surface && normal.is_none() && depth_edge(frame, u, v, z, jump),
                    }
                } else if range > params.max_range {
                    PixelRay::BeyondRange { end: clear_to }
                } else {
                    PixelRay::Return {
                        end: origin + dir * range,
                    }
                }
            };
            f(ray);
        }
    }
}

/// How far along a noisy ray (range `range`, range error `sigma`) its misses reach, given the
/// squared depth slope `slope2` of the surface it returned from (`None`: not known): `2σ`
/// short of the return, one voxel (`resolution`) further where the surface faces the camera,
/// and no nearer than half a voxel to the surface, square to it, where it does not. Never past
/// the return.
fn free_length(range: f32, sigma: f32, slope2: Option<f32>, resolution: f32) -> f32 {
    let short = FREE_MARGIN_SIGMAS * sigma;
    let free = match slope2 {
        Some(g2) if g2 <= MAX_FACING_SLOPE * MAX_FACING_SLOPE => range - short + resolution,
        Some(g2) => range - short.max(OBLIQUE_MARGIN_VOXELS * resolution * libm::sqrtf(1.0 + g2)),
        None => range - short,
    };
    free.min(range)
}

/// The depth (m) of pixel `(u, v)`, if it is inside the frame and has one (`None` for a
/// coordinate that under- or overflowed).
fn depth_at(frame: &DepthFrame<'_>, u: Option<usize>, v: Option<usize>) -> Option<f32> {
    let width = usize::from(frame.intrinsics().width());
    let (u, v) = (u.filter(|&x| x < width)?, v?);
    let d = *frame.depth_mm().get(v.checked_mul(width)?.checked_add(u)?)?;
    (d > 0 && d != NOT_RECEIVED).then(|| f32::from(d) * 1e-3)
}

/// The squared slope of the surface seen at pixel `(u, v)`, depth `z` (m): the depth image's
/// change over `s` pixels either way ([`SLOPE_SPAN_PX`], or 1 where a matcher's footprint needs
/// a slant and the wider span has no depth), in depth per lateral metre, along both image
/// axes together (0 square to the camera, 1 at 45°). `None` near the image border or beside a
/// pixel without depth.
fn surface_slope2(frame: &DepthFrame<'_>, u: usize, v: usize, z: f32, s: usize) -> Option<f32> {
    let intr = frame.intrinsics();
    let depth = |uu, vv| depth_at(frame, uu, vv);
    let (Some(left), Some(right), Some(up), Some(down)) = (
        depth(u.checked_sub(s), Some(v)),
        depth(u.checked_add(s), Some(v)),
        depth(Some(u), v.checked_sub(s)),
        depth(Some(u), v.checked_add(s)),
    ) else {
        return None;
    };
    // One pixel spans z / f metres laterally.
    let span = 2.0 * s as f32 * z;
    let gu = (right - left) * intr.fx() / span;
    let gv = (down - up) * intr.fy() / span;
    Some(gu * gu + gv * gv)
}

/// The nearest depth (m) within `reach` pixels of `(u, v)` either way, both axes (the square
/// window), over the pixels that have one.
fn nearest_depth(frame: &DepthFrame<'_>, u: usize, v: usize, reach: usize) -> Option<f32> {
    let mut nearest: Option<f32> = None;
    for vv in v.saturating_sub(reach)..=v.saturating_add(reach) {
        for uu in u.saturating_sub(reach)..=u.saturating_add(reach) {
            if let Some(d) = depth_at(frame, Some(uu), Some(vv)) {
                nearest = Some(nearest.map_or(d, |n| n.min(d)));
            }
        }
    }
    nearest
}

/// The unit normal (map frame, facing the camera) of the surface seen at pixel `(u, v)`, from
/// the 3D points [`NORMAL_SPAN_PX`] pixels either way; `None` near the border, beside a pixel
/// without depth, where the centre lies more than `tolerance` (m) off the midpoints of the span
/// (a depth edge or a corner between), or where the surface is seen nearly edge-on.
fn surface_normal(
    frame: &DepthFrame<'_>,
    u: usize,
    v: usize,
    pose: &Isometry3<f32>,
    dir: &Vector3<f32>,
    tolerance: f32,
) -> Option<Vector3<f32>> {
    let intr = frame.intrinsics();
    let s = NORMAL_SPAN_PX;
    // `depth_at` has checked that the pixel lies in the frame, so its coordinates fit a u16.
    let point = |uu: Option<usize>, vv: Option<usize>| -> Option<Vector3<f32>> {
        let z = depth_at(frame, uu, vv)?;
        Some(intr.ray(uu? as u16, vv? as u16) * z)
    };
    let left = point(u.checked_sub(s), Some(v))?;
    let right = point(u.checked_add(s), Some(v))?;
    let up = point(Some(u), v.checked_sub(s))?;
    let down = point(Some(u), v.checked_add(s))?;
    let centre = point(Some(u), Some(v))?;
    // A depth edge between the points is no plane: the centre must lie near both midpoints.
    let bend = ((left + right) * 0.5 - centre)
        .norm()
        .max(((up + down) * 0.5 - centre).norm());
    if bend > tolerance {
        return None;
    }
    let n = (right - left).cross(&(down - up));
    let norm = n.norm();
    if norm.is_nan() || norm <= 0.0 {
        return None;
    }
    let mut n = pose.rotation * (n / norm);
    if n.dot(dir) > 0.0 {
        n = -n;
    }
    (-n.dot(dir) >= NORMAL_MIN_COS).then_some(n)
}

/// True if pixel `(u, v)` (depth `z`, m) lies on a depth edge: a face neighbour's depth differs
/// from it by more than `jump` metres (its depth may mix the two sides: a flying pixel).
fn depth_edge(frame: &DepthFrame<'_>, u: usize, v: usize, z: f32, jump: f32) -> bool {
    [
        depth_at(frame, u.checked_sub(1), Some(v)),
        depth_at(frame, u.checked_add(1), Some(v)),
        depth_at(frame, Some(u), v.checked_sub(1)),
        depth_at(frame, Some(u), v.checked_add(1)),
    ]
    .into_iter()
    .flatten()
    .any(|d| (d - z).abs() > jump)
}

/// Visits, in order, every voxel the segment `a → b` passes through inside the grid
/// (Amanatides & Woo 1987), starting with the voxel of `a` (or where the segment enters the grid)
/// and ending with the voxel of `b` (or where it leaves). `visit` returns `false` to stop early.
/// Returns the number of voxels visited.
///
/// Where the segment passes exactly through an edge or corner, one of the voxels sharing it is
/// visited before the step to the diagonal one (x before y before z), so the visited set is
/// always face-connected.
pub fn traverse(
    geometry: &MapGeometry,
    a: &Point3<f32>,
    b: &Point3<f32>,
    mut visit: impl FnMut(VoxelIndex) -> bool,
) -> u32 {
    walk(geometry, a, b, |[x, y, z], _| {
        visit(VoxelIndex::new(x as u16, y as u16, z as u16))
    })
}

/// [`traverse`] handing `visit` each voxel's linear index ([`Dims::linear`]) instead: the same
/// voxels in the same order, the index kept up to date step by step (integration's rays, where
/// the per-step cost is what a frame costs).
pub fn traverse_linear(
    geometry: &MapGeometry,
    a: &Point3<f32>,
    b: &Point3<f32>,
    mut visit: impl FnMut(usize) -> bool,
) -> u32 {
    walk(geometry, a, b, |_, i| visit(i))
}

/// The traversal of [`traverse`]: `visit` gets each voxel's cell coordinates (inside the grid)
/// and linear index.
#[inline(always)]
fn walk(
    geometry: &MapGeometry,
    a: &Point3<f32>,
    b: &Point3<f32>,
    mut visit: impl FnMut([i32; 3], usize) -> bool,
) -> u32 {
    let dims = geometry.dims();
    let ga = geometry.to_grid(a);
    let gb = geometry.to_grid(b);
    let d = gb - ga;
    if !(ga.iter().chain(gb.iter()).all(|c| c.is_finite())) {
        return 0;
    }
    let Some((t0, t1)) = clip_to_grid(&dims, &ga, &d) else {
        return 0;
    };
    let start = ga + d * t0;
    let end = ga + d * t1;
    let n = [dims.nx(), dims.ny(), dims.nz()];
    let [mut x, mut y, mut z] = [
        (n[0], ga.x, d.x, start.x, end.x),
        (n[1], ga.y, d.y, start.y, end.y),
        (n[2], ga.z, d.z, start.z, end.z),
    ]
    .map(|(n, g, d, start, end)| DdaAxis::new(n, g, d, start, end));
    let (sy, sz) = (n[0] as isize, (n[0] * n[1]) as isize);
    let inside = |c: i32, n: usize| c >= 0 && (c as usize) < n;
    if !(inside(x.cell, n[0]) && inside(y.cell, n[1]) && inside(z.cell, n[2])) {
        return 0;
    }
    let mut i = dims.linear(VoxelIndex::new(x.cell as u16, y.cell as u16, z.cell as u16));
    let mut visited = 0u32;
    // A segment crosses at most nx + ny + nz voxel boundaries inside the grid.
    let cap = n[0] + n[1] + n[2] + 1;
    for _ in 0..cap {
        visited += 1;
        if !visit([x.cell, y.cell, z.cell], i) || (x.cell == x.last && y.cell == y.last && z.cell == z.last) {
            break;
        }
        let (axis, len, stride) = if x.t_max <= y.t_max && x.t_max <= z.t_max {
            (&mut x, n[0], 1)
        } else if y.t_max <= z.t_max {
            (&mut y, n[1], sy)
        } else {
            (&mut z, n[2], sz)
        };
        if axis.t_max > t1 || axis.step == 0 {
            break;
        }
        axis.cell += axis.step;
        axis.t_max += axis.t_delta;
        // Only the axis that stepped can have left the grid.
        if !inside(axis.cell, len) {
            break;
        }
        i = i.wrapping_add_signed(axis.step as isize * stride);
    }
    visited
}

/// One axis of an Amanatides–Woo traversal.
#[derive(Clone, Copy)]
struct DdaAxis {
    /// Current cell along the axis.
    cell: i32,
    /// Cell of the segment's end.
    last: i32,
    /// −1, 0 or +1.
    step: i32,
    /// Segment parameter of the next boundary crossing along this axis.
    t_max: f32,
    /// Segment parameter between two crossings.
    t_delta: f32,
}

impl DdaAxis {
    /// Axis with `n` cells; the segment starts at grid coordinate `g` with delta `d`, and its
    /// clipped part runs from `start` to `end`.
    fn new(n: usize, g: f32, d: f32, start: f32, end: f32) -> Self {
        let max = n as i32 - 1;
        // Truncation is the floor wherever the clamp keeps it (p ≥ 0); below 0 both clamp to
        // 0, and a NaN converts to 0 either way. It spares a software floor on the M4F.
        let cell_of = |p: f32| (p as i32).clamp(0, max);
        let cell = cell_of(start);
        let (step, t_max, t_delta) = if d > 0.0 {
            (1, (cell as f32 + 1.0 - g) / d, 1.0 / d)
        } else if d < 0.0 {
            (-1, (cell as f32 - g) / d, -1.0 / d)
        } else {
            (0, f32::INFINITY, f32::INFINITY)
        };
        Self {
            cell,
            last: cell_of(end),
            step,
            t_max,
            t_delta,
        }
    }
}

/// Parameter interval `[t0, t1] ⊆ [0, 1]` of `g + t·d` inside the grid box, if any.
fn clip_to_grid(dims: &Dims, g: &Vector3<f32>, d: &Vector3<f32>) -> Option<(f32, f32)> {
    let n = [dims.nx() as f32, dims.ny() as f32, dims.nz() as f32];
    let (mut t0, mut t1) = (0.0f32, 1.0f32);
    for ((n, g), d) in n.into_iter().zip(g.iter()).zip(d.iter()) {
        if *d == 0.0 {
            if *g < 0.0 || *g >= n {
                return None;
            }
        } else {
            let ta = (0.0 - g) / d;
            let tb = (n - g) / d;
            let (lo, hi) = if ta < tb { (ta, tb) } else { (tb, ta) };
            t0 = t0.max(lo);
            t1 = t1.min(hi);
        }
    }
    (t0 <= t1).then_some((t0, t1))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mapping::camera::Intrinsics;
    use crate::mapping::map::{LogOddsParams, Occupancy};
    use nalgebra::{Translation3, UnitQuaternion};

    fn geometry(nx: usize, ny: usize, nz: usize) -> MapGeometry {
        MapGeometry::new(Dims::new(nx, ny, nz).unwrap(), Point3::origin(), 1.0).unwrap()
    }

    fn collect(g: &MapGeometry, a: [f32; 3], b: [f32; 3]) -> heapless::Vec<[u16; 3], 64> {
        let mut out = heapless::Vec::new();
        traverse(g, &Point3::from(a), &Point3::from(b), |v| {
            out.push([v.x, v.y, v.z]).unwrap();
            true
        });
        out
    }

    #[test]
    fn axis_aligned_ray_visits_a_row() {
        let g = geometry(8, 4, 4);
        let got = collect(&g, [0.5, 1.5, 2.5], [5.5, 1.5, 2.5]);
        let want = [[0, 1, 2], [1, 1, 2], [2, 1, 2], [3, 1, 2], [4, 1, 2], [5, 1, 2]];
        assert_eq!(got.as_slice(), &want);
        let back = collect(&g, [5.5, 1.5, 2.5], [0.5, 1.5, 2.5]);
        assert_eq!(back.len(), 6);
        assert_eq!(back[0], [5, 1, 2]);
        assert_eq!(back[5], [0, 1, 2]);
    }

    #[test]
    fn diagonal_ray_through_corners_stays_face_connected() {
        let g = geometry(4, 4, 4);
        let got = collect(&g, [0.5, 0.5, 0.5], [3.5, 3.5, 0.5]);
        // Through the corners at (1,1), (2,2), (3,3): x steps first on ties.
        let want = [
            [0, 0, 0],
            [1, 0, 0],
            [1, 1, 0],
            [2, 1, 0],
            [2, 2, 0],
            [3, 2, 0],
            [3, 3, 0],
        ];
        assert_eq!(got.as_slice(), &want);
    }

    #[test]
    fn shallow_ray_visits_exact_cells() {
        let g = geometry(8, 8, 2);
        // From (0.5,0.5) to (6.5,2.9): slope 0.4, crosses y=1 at x=1.75 and y=2 at x=4.25.
        let got = collect(&g, [0.5, 0.5, 0.5], [6.5, 2.9, 0.5]);
        let want = [
            [0, 0, 0],
            [1, 0, 0],
            [1, 1, 0],
            [2, 1, 0],
            [3, 1, 0],
            [4, 1, 0],
            [4, 2, 0],
            [5, 2, 0],
            [6, 2, 0],
        ];
        assert_eq!(got.as_slice(), &want);
    }

    #[test]
    fn grazing_ray_along_a_voxel_face() {
        let g = geometry(6, 4, 4);
        // Runs exactly on the plane y = 2 (boundary between rows 1 and 2): floor picks row 2,
        // and the ray never steps in y.
        let got = collect(&g, [0.5, 2.0, 1.5], [4.5, 2.0, 1.5]);
        assert_eq!(
            got.as_slice(),
            &[[0, 2, 1], [1, 2, 1], [2, 2, 1], [3, 2, 1], [4, 2, 1]]
        );
    }

    #[test]
    fn ray_is_clipped_to_the_grid() {
        let g = geometry(4, 4, 4);
        let got = collect(&g, [-3.5, 1.5, 1.5], [9.0, 1.5, 1.5]);
        assert_eq!(got.as_slice(), &[[0, 1, 1], [1, 1, 1], [2, 1, 1], [3, 1, 1]]);
        assert!(collect(&g, [-3.0, -1.0, 1.5], [9.0, -1.0, 1.5]).is_empty());
        assert!(collect(&g, [f32::NAN, 1.0, 1.0], [2.0, 1.0, 1.0]).is_empty());
    }

    /// The linear traversal integration uses visits the voxels [`traverse`] visits, in order,
    /// as linear indices: segments inside, through, ending outside and missing the grid, along
    /// axes, faces and diagonals.
    #[test]
    fn the_linear_traversal_visits_what_the_voxel_traversal_visits() {
        extern crate std;
        let g = geometry(7, 5, 6);
        let dims = g.dims();
        let mut seed = 0x2545_f491u32;
        let mut next = |span: f32| {
            seed ^= seed << 13;
            seed ^= seed >> 17;
            seed ^= seed << 5;
            (seed as f32 / u32::MAX as f32) * span - 0.25 * span
        };
        let mut segments: std::vec::Vec<([f32; 3], [f32; 3])> = (0..400)
            .map(|_| {
                (
                    [next(10.0), next(8.0), next(9.0)],
                    [next(10.0), next(8.0), next(9.0)],
                )
            })
            .collect();
        segments.extend([
            ([0.5, 0.5, 0.5], [6.5, 0.5, 0.5]),
            ([0.5, 0.5, 0.5], [6.5, 4.5, 5.5]),
            ([1.0, 1.0, 1.0], [4.0, 4.0, 4.0]),
            ([-3.5, 1.5, 1.5], [9.0, 1.5, 1.5]),
            ([3.5, 2.5, 2.5], [3.5, 2.5, 2.5]),
        ]);
        let mut steps = 0;
        for (a, b) in segments {
            let (a, b) = (Point3::from(a), Point3::from(b));
            let mut voxels = std::vec::Vec::new();
            let n = traverse(&g, &a, &b, |v| {
                voxels.push(dims.linear(v));
                true
            });
            let mut linear = std::vec::Vec::new();
            let m = traverse_linear(&g, &a, &b, |i| {
                linear.push(i);
                true
            });
            assert_eq!((n, &linear), (m, &voxels), "{a} → {b}");
            steps += voxels.len();
        }
        assert!(steps > 1_000, "{steps}");
    }

    struct Fixture {
        lo: [i8; 4096],
        st: [u32; 128],
    }

    impl Fixture {
        fn new() -> Self {
            Self {
                lo: [0; 4096],
                st: [0; 128],
            }
        }
        /// An all-unknown map over [`cube16`].
        fn map(&mut self) -> VoxelMap<'_> {
            VoxelMap::new(cube16(), LogOddsParams::default(), &mut self.lo, &mut self.st).unwrap()
        }
    }

    /// 16³ voxels of 0.1 m from the origin.
    fn cube16() -> MapGeometry {
        MapGeometry::new(Dims::new(16, 16, 16).unwrap(), Point3::origin(), 0.1).unwrap()
    }

    /// A one-pixel camera looking along its z axis.
    fn one_pixel() -> Intrinsics {
        Intrinsics::new(1.0, 1.0, 0.0, 0.0, 1, 1).unwrap()
    }

    fn looking_along_x() -> Isometry3<f32> {
        // Camera z → map x, camera x → map −y, camera y → map −z.
        let r = nalgebra::Matrix3::new(0.0, 0.0, 1.0, -1.0, 0.0, 0.0, 0.0, -1.0, 0.0);
        let rot = UnitQuaternion::from_matrix(&r);
        Isometry3::from_parts(Translation3::new(0.05, 0.85, 0.85), rot)
    }

    #[test]
    fn single_pixel_marks_free_ray_and_occupied_endpoint() {
        let mut f = Fixture::new();
        let g = cube16();
        let mut map = f.map();
        let intr = one_pixel();
        let depth = [1000u16]; // 1.0 m straight ahead along +x.
        let frame = DepthFrame::new(intr, &depth).unwrap();
        let params = IntegrationParams {
            min_range: 0.3,
            max_range: 10.0,
            pixel_stride: 1,
            ..IntegrationParams::default()
        };
        let s = integrate(&mut map, &frame, &looking_along_x(), &params).unwrap();
        assert_eq!(s.returns, 1);
        let d = g.dims();
        let at = |x| d.linear(VoxelIndex::new(x, 8, 8));
        for x in 0..10 {
            assert_eq!(map.occupancy(at(x)), Occupancy::Free, "x = {x}");
        }
        assert_eq!(map.occupancy(at(10)), Occupancy::Occupied);
        assert_eq!(map.occupancy(at(11)), Occupancy::Unknown);
        assert_eq!(s.voxel_updates, 11);
    }

    #[test]
    fn no_return_clears_to_max_range_and_too_close_is_invalid() {
        let mut f = Fixture::new();
        let g = cube16();
        let mut map = f.map();
        let intr = one_pixel();
        let params = IntegrationParams {
            min_range: 0.3,
            max_range: 0.75,
            pixel_stride: 1,
            ..IntegrationParams::default()
        };
        let d = g.dims();
        let at = |x| d.linear(VoxelIndex::new(x, 8, 8));

        let close = [200u16];
        let s = integrate(
            &mut map,
            &DepthFrame::new(intr, &close).unwrap(),
            &looking_along_x(),
            &params,
        )
        .unwrap();
        assert_eq!((s.invalid, s.voxel_updates), (1, 0));
        assert_eq!(map.occupancy(at(0)), Occupancy::Unknown);

        for depth in [[0u16], [5000u16]] {
            let s = integrate(
                &mut map,
                &DepthFrame::new(intr, &depth).unwrap(),
                &looking_along_x(),
                &params,
            )
            .unwrap();
            assert_eq!(s.no_return + s.beyond_range, 1);
        }
        // Max range 0.75 m from x = 0.05 reaches x = 0.8: voxels 0..=7 free, nothing occupied.
        for x in 0..8 {
            assert_eq!(map.occupancy(at(x)), Occupancy::Free, "x = {x}");
        }
        assert_eq!(map.occupancy(at(8)), Occupancy::Unknown);
        assert_eq!(map.counts().occupied, 0);
    }

    #[test]
    fn no_return_stops_at_an_occupied_voxel_and_never_erodes_it() {
        let mut f = Fixture::new();
        let g = cube16();
        let mut map = f.map();
        let intr = one_pixel();
        let params = IntegrationParams {
            min_range: 0.1,
            max_range: 1.2,
            pixel_stride: 1,
            no_return: NoReturn::ClearToMaxRange,
            depth_noise_per_m: 0.0,
            footprint_px: 0.0,
        };
        let d = g.dims();
        let at = |x| d.linear(VoxelIndex::new(x, 8, 8));
        let frame = |mm: &'static [u16; 1]| DepthFrame::new(intr, mm).unwrap();
        // A wall at x = 0.55 m (voxel 5), seen once.
        integrate(&mut map, &frame(&[500]), &looking_along_x(), &params).unwrap();
        assert_eq!(map.occupancy(at(5)), Occupancy::Occupied);
        // Dropouts, however many: the wall stays, nothing behind it is cleared.
        for _ in 0..10 {
            let s = integrate(&mut map, &frame(&[0]), &looking_along_x(), &params).unwrap();
            assert_eq!((s.no_return, s.no_return_blocked), (1, 1));
        }
        assert_eq!(map.occupancy(at(5)), Occupancy::Occupied);
        assert_eq!(map.occupancy(at(4)), Occupancy::Free);
        assert_eq!(map.occupancy(at(6)), Occupancy::Unknown);
        // Measured returns behind it do erode it (the wall moved, or was noise).
        for _ in 0..10 {
            integrate(&mut map, &frame(&[1000]), &looking_along_x(), &params).unwrap();
        }
        assert_eq!(map.occupancy(at(5)), Occupancy::Free);
        assert_eq!(map.occupancy(at(10)), Occupancy::Occupied);
    }

    #[test]
    fn unknown_no_return_updates_nothing_but_far_returns_still_clear() {
        let mut f = Fixture::new();
        let g = cube16();
        let mut map = f.map();
        let intr = one_pixel();
        let params = IntegrationParams {
            min_range: 0.3,
            max_range: 0.75,
            no_return: NoReturn::Unknown,
            ..IntegrationParams::default()
        };
        let s = integrate(
            &mut map,
            &DepthFrame::new(intr, &[0u16]).unwrap(),
            &looking_along_x(),
            &params,
        )
        .unwrap();
        assert_eq!((s.no_return, s.voxel_updates, s.voxels_traversed), (1, 0, 0));
        assert_eq!(map.counts().free, 0);
        // A measured return beyond the range still clears up to it.
        let s = integrate(
            &mut map,
            &DepthFrame::new(intr, &[5000u16]).unwrap(),
            &looking_along_x(),
            &params,
        )
        .unwrap();
        assert_eq!(s.beyond_range, 1);
        let at = |x| g.dims().linear(VoxelIndex::new(x, 8, 8));
        assert_eq!(map.occupancy(at(7)), Occupancy::Free);
    }

    #[test]
    fn pixels_not_received_update_nothing_for_either_sensor_rule() {
        for no_return in [NoReturn::ClearToMaxRange, NoReturn::Unknown] {
            for noise in [0.0, 0.01] {
                let mut f = Fixture::new();
                let mut map = f.map();
                let params = IntegrationParams {
                    no_return,
                    depth_noise_per_m: noise,
                    ..IntegrationParams::default()
                };
                let mut buf = [0u16; 81];
                // The rows lost on the link; a wall at 1 m in the rest, half of it a no-return.
                let intr = square_frame(
                    9,
                    |u, v| match (v < 4, u < 5) {
                        (true, _) => NOT_RECEIVED,
                        (false, true) => 1000,
                        (false, false) => 0,
                    },
                    &mut buf,
                );
                let frame = DepthFrame::new(intr, &buf).unwrap();
                let s = integrate(&mut map, &frame, &looking_along_x(), &params).unwrap();
                assert_eq!((s.pixels, s.not_received), (81, 36));
                assert_eq!(s.returns + s.no_return, 45);
                let whole: [u16; 81] = core::array::from_fn(|i| buf[i].min(1000));
                let mut g = Fixture::new();
                let mut all = g.map();
                let full = integrate(
                    &mut all,
                    &DepthFrame::new(intr, &whole).unwrap(),
                    &looking_along_x(),
                    &params,
                )
                .unwrap();
                // The lost rows' rays are not traced (this camera's rays share their voxels).
                assert!(s.voxels_traversed < full.voxels_traversed, "{s:?} {full:?}");
                assert!(s.voxel_updates <= full.voxel_updates, "{s:?} {full:?}");
                // A frame of which nothing arrived changes nothing.
                let before = map.counts();
                let none = [NOT_RECEIVED; 81];
                let s = integrate(
                    &mut map,
                    &DepthFrame::new(intr, &none).unwrap(),
                    &looking_along_x(),
                    &params,
                )
                .unwrap();
                assert_eq!((s.not_received, s.voxel_updates, s.voxels_traversed), (81, 0, 0));
                assert_eq!(map.counts(), before);
            }
        }
    }

    #[test]
    fn occupied_wins_within_one_frame() {
        let mut f = Fixture::new();
        let g = cube16();
        let mut map = f.map();
        // Two pixels on the same ray line: the first ends at 0.5 m, the second passes to 1.0 m.
        // A huge focal length makes both pixels' rays coincide to within 1e-6 rad.
        let intr = Intrinsics::new(1e6, 1.0, 0.0, 0.0, 2, 1).unwrap();
        let depth = [500u16, 1000u16];
        let frame = DepthFrame::new(intr, &depth).unwrap();
        let s = integrate(
            &mut map,
            &frame,
            &looking_along_x(),
            &IntegrationParams::default(),
        )
        .unwrap();
        assert_eq!(s.returns, 2);
        let at = |x| g.dims().linear(VoxelIndex::new(x, 8, 8));
        assert_eq!(map.occupancy(at(5)), Occupancy::Occupied);
        assert!(
            (map.log_odds(at(5)) - 0.85).abs() < 1e-6,
            "hit once, never missed in the same frame"
        );
    }

    #[test]
    fn bad_pose_is_rejected() {
        let mut f = Fixture::new();
        let mut map = f.map();
        let intr = one_pixel();
        let depth = [1000u16];
        let frame = DepthFrame::new(intr, &depth).unwrap();
        let mut pose = looking_along_x();
        pose.translation.x = f32::NAN;
        assert_eq!(
            integrate(&mut map, &frame, &pose, &IntegrationParams::default()),
            Err(IntegrateError::BadPose)
        );
    }

    /// Stereo-like depth noise: σ_z = 0.032·z² (σ_d = 0.25 px, f = 65 px, b = 0.12 m).
    const NOISE: f32 = 0.032;

    fn noisy() -> IntegrationParams {
        IntegrationParams {
            depth_noise_per_m: NOISE,
            ..IntegrationParams::default()
        }
    }

    /// Integrates `frame`, seen along +x, into a fresh map in `f` with the noisy model and
    /// `votes` words of vote scratch.
    fn integrate_noisy<'f>(
        f: &'f mut Fixture,
        frame: &DepthFrame<'_>,
        votes: usize,
    ) -> (VoxelMap<'f>, IntegrationStats) {
        let mut map = f.map();
        let mut scratch = [0u32; 64];
        let s = integrate_with_scratch(
            &mut map,
            frame,
            &looking_along_x(),
            &noisy(),
            &mut scratch[..votes],
        )
        .unwrap();
        (map, s)
    }

    /// Voxel `x` of the row y = z = 8 of [`cube16`], the one the narrow cameras look along.
    fn on_row(x: u16) -> usize {
        cube16().dims().linear(VoxelIndex::new(x, 8, 8))
    }

    #[test]
    fn a_far_noisy_return_clears_to_two_sigma_short_of_it_and_marks_nothing() {
        // 64 × 16 × 16 voxels of 0.1 m: 6.4 m along x.
        let g = MapGeometry::new(Dims::new(64, 16, 16).unwrap(), Point3::origin(), 0.1).unwrap();
        let (mut lo, mut st) = ([0i8; 64 * 16 * 16], [0u32; 64 * 16 * 16 / 32]);
        let mut map = VoxelMap::new(g, LogOddsParams::default(), &mut lo, &mut st).unwrap();
        let depth = [4000u16]; // 4 m ahead: σ = 0.032 · 16 = 0.512 m.
        let frame = DepthFrame::new(one_pixel(), &depth).unwrap();
        let mut scratch = [0u32; 64];
        let s = integrate_with_scratch(&mut map, &frame, &looking_along_x(), &noisy(), &mut scratch).unwrap();
        assert_eq!((s.returns, s.uncertain_returns, s.voted), (1, 1, 0));
        // From x = 0.05 the ray clears up to 4 − 2σ = 2.976 m, x = 3.026 (a one-pixel frame
        // has no slope to show the surface faces the camera: no voxel of leeway): voxels 0–29
        // are left before it; voxel 30 holds that point and stays unknown, like all beyond.
        let at = |x| g.dims().linear(VoxelIndex::new(x, 8, 8));
        for x in 0..=29 {
            assert_eq!(map.occupancy(at(x)), Occupancy::Free, "x = {x}");
        }
        for x in 30..64 {
            assert_eq!(map.occupancy(at(x)), Occupancy::Unknown, "x = {x}");
        }
        // With exact depth the same return clears to the wall and marks it.
        let (mut lo, mut st) = ([0i8; 64 * 16 * 16], [0u32; 64 * 16 * 16 / 32]);
        let mut exact = VoxelMap::new(g, LogOddsParams::default(), &mut lo, &mut st).unwrap();
        integrate(
            &mut exact,
            &frame,
            &looking_along_x(),
            &IntegrationParams::default(),
        )
        .unwrap();
        assert_eq!(exact.occupancy(at(39)), Occupancy::Free);
        assert_eq!(exact.occupancy(at(40)), Occupancy::Occupied);
    }

    #[test]
    fn a_near_noisy_return_is_integrated_as_an_exact_one() {
        // At 1.02 m σ = 3.3 cm, under a voxel: the endpoint is marked, and the misses reach the
        // voxel before it (1.02 − 2σ = 0.953 m, x = 1.003, lies in the endpoint's voxel).
        let depth = [1020u16];
        let frame = DepthFrame::new(one_pixel(), &depth).unwrap();
        let (mut f, mut g) = (Fixture::new(), Fixture::new());
        let (a, s) = integrate_noisy(&mut f, &frame, 64);
        let mut b = g.map();
        integrate(&mut b, &frame, &looking_along_x(), &IntegrationParams::default()).unwrap();
        assert_eq!(
            (s.returns, s.uncertain_returns, s.voted, s.vote_overflow),
            (1, 0, 1, 0)
        );
        for i in 0..cube16().dims().len() {
            assert_eq!(a.occupancy(i), b.occupancy(i), "voxel {i}");
        }
        assert_eq!(a.occupancy(on_row(10)), Occupancy::Occupied);
    }

    /// Five pixels in a narrow field of view, all along the voxel row y = z = 8: returns from
    /// `far` mm at pixels 0, 2 and 4 and from 1.02 m (voxel 10) at pixels 1 and 3.
    fn returns_behind_a_voxel(far: u16) -> ([u16; 5], Intrinsics) {
        (
            [far, 1020, far, 1020, far],
            Intrinsics::new(1000.0, 1000.0, 2.0, 0.0, 5, 1).unwrap(),
        )
    }

    /// [`returns_behind_a_voxel`]`(far)` integrated by [`integrate_noisy`].
    fn vote_on_row(f: &mut Fixture, far: u16, votes: usize) -> (VoxelMap<'_>, IntegrationStats) {
        let (depth, intr) = returns_behind_a_voxel(far);
        integrate_noisy(f, &DepthFrame::new(intr, &depth).unwrap(), votes)
    }

    #[test]
    fn the_vote_clears_a_voxel_that_more_rays_passed_than_hit() {
        // The far returns at 1.22 m (voxel 12; σ = 4.8 cm) clear up to x = 1.175, through
        // voxel 10, and end close behind it.
        let mut f = Fixture::new();
        let (map, s) = vote_on_row(&mut f, 1220, 64);
        assert_eq!((s.returns, s.voted, s.vote_overflow), (5, 2, 0));
        // Voxel 10: two hits, three rays through it to a return close behind — a miss. Voxel
        // 12: three hits — occupied. Voxel 11 holds where the far rays' free space ends.
        let states = [9, 10, 11, 12].map(|x| map.occupancy(on_row(x)));
        use Occupancy::{Free, Occupied, Unknown};
        assert_eq!(states, [Free, Free, Unknown, Occupied]);

        // The rules of exact depth let the two short returns win.
        let (depth, intr) = returns_behind_a_voxel(1220);
        let frame = DepthFrame::new(intr, &depth).unwrap();
        let mut g = Fixture::new();
        let mut exact = g.map();
        integrate(
            &mut exact,
            &frame,
            &looking_along_x(),
            &IntegrationParams::default(),
        )
        .unwrap();
        assert_eq!([10, 12].map(|x| exact.occupancy(on_row(x))), [Occupied, Occupied]);
    }

    #[test]
    fn rays_that_end_far_behind_a_hit_voxel_do_not_vote_against_it() {
        // The far returns at 1.52 m (voxel 15) pass voxel 10 but may have grazed the free part
        // of an edge that partly fills it: the two hits stand.
        let mut f = Fixture::new();
        let (map, _) = vote_on_row(&mut f, 1520, 64);
        use Occupancy::{Free, Occupied};
        assert_eq!(
            [9, 10, 11].map(|x| map.occupancy(on_row(x))),
            [Free, Occupied, Free]
        );
    }

    #[test]
    fn voxels_the_vote_has_no_room_for_fall_back_to_the_hit_winning() {
        use Occupancy::Occupied;
        // Four words: two slots, filled to at most half — room for one voxel (the first hit,
        // voxel 12); voxel 10 is updated by "the hit wins". No scratch at all: every hit voxel
        // falls back, and nothing is lost.
        for (words, voted, overflow) in [(4, 1, 1), (0, 0, 2)] {
            let mut f = Fixture::new();
            let (map, s) = vote_on_row(&mut f, 1220, words);
            assert_eq!((s.voted, s.vote_overflow), (voted, overflow), "{words} words");
            assert_eq!([10, 12].map(|x| map.occupancy(on_row(x))), [Occupied, Occupied]);
        }
    }

    /// A `side` × `side` frame with depth `depth(u, v)` mm and a narrow field of view.
    fn square_frame(side: u16, depth: impl Fn(u16, u16) -> u16, out: &mut [u16]) -> Intrinsics {
        let c = f32::from(side - 1) / 2.0;
        for v in 0..side {
            for u in 0..side {
                out[usize::from(v * side + u)] = depth(u, v);
            }
        }
        Intrinsics::new(1000.0, 1000.0, c, c, side, side).unwrap()
    }

    /// The surface at pixel `(u, v)` faces the camera within 45°.
    fn faces_camera(frame: &DepthFrame<'_>, u: usize, v: usize, z: f32) -> bool {
        surface_slope2(frame, u, v, z, SLOPE_SPAN_PX)
            .is_some_and(|g2| g2 <= MAX_FACING_SLOPE * MAX_FACING_SLOPE)
    }

    #[test]
    fn only_a_surface_facing_the_camera_gets_the_voxel_of_leeway() {
        let mut buf = [0u16; 81];
        // A wall square to the camera at 1.12 m.
        let intr = square_frame(9, |_, _| 1120, &mut buf);
        let frame = DepthFrame::new(intr, &buf).unwrap();
        assert!(faces_camera(&frame, 4, 4, 1.12));
        assert!(!faces_camera(&frame, 1, 4, 1.12), "too near the border to tell");
        // Tilted 30° (slope 0.58): facing. Tilted 60° (slope 1.73): grazing. One pixel spans
        // z / f = 1.12 mm laterally.
        for (slope, facing) in [(0.577f32, true), (1.732, false)] {
            let intr = square_frame(
                9,
                |u, _| (1120.0 + (f32::from(u) - 4.0) * slope * 1.12) as u16,
                &mut buf,
            );
            let frame = DepthFrame::new(intr, &buf).unwrap();
            assert_eq!(faces_camera(&frame, 4, 4, 1.12), facing, "slope {slope}");
        }
        // A pixel without depth two to the side: unknown, no leeway.
        let intr = square_frame(9, |u, v| if (u, v) == (6, 4) { 0 } else { 1120 }, &mut buf);
        let frame = DepthFrame::new(intr, &buf).unwrap();
        assert!(!faces_camera(&frame, 4, 4, 1.12));

        // Integrated: the centre ray of the square wall (σ = 4 cm) clears up to
        // 1.12 − 2σ + 0.1 m, capped at its return: past the voxel in front of the wall (10).
        // A one-pixel frame of the same return has no slope to show and stops inside voxel 10.
        use Occupancy::{Free, Occupied, Unknown};
        let intr = square_frame(9, |_, _| 1120, &mut buf);
        let frame = DepthFrame::new(intr, &buf).unwrap();
        let mut f = Fixture::new();
        let (map, _) = integrate_noisy(&mut f, &frame, 64);
        assert_eq!([10, 11].map(|x| map.occupancy(on_row(x))), [Free, Occupied]);
        let one = [1120u16];
        let frame = DepthFrame::new(one_pixel(), &one).unwrap();
        let mut g = Fixture::new();
        let (map, _) = integrate_noisy(&mut g, &frame, 64);
        assert_eq!([10, 11].map(|x| map.occupancy(on_row(x))), [Unknown, Occupied]);
    }

    #[test]
    fn misses_stop_half_a_voxel_square_to_an_oblique_surface() {
        let (r, h) = (2.0f32, 0.1f32);
        let sigma = 0.01;
        // Facing the camera (slope 0.5): 2σ short, a voxel of leeway, never past the return.
        assert_eq!(free_length(r, sigma, Some(0.25), h), r);
        assert!((free_length(r, 0.1, Some(0.25), h) - (r - 0.2 + h)).abs() < 1e-6);
        // Slope unknown: 2σ short only.
        assert!((free_length(r, sigma, None, h) - (r - 0.02)).abs() < 1e-6);
        // Seen at 60° (slope √3) and 80° (slope 5.67): the ray stops where it is still half a
        // voxel from the surface, square to it, 0.1 m and 0.29 m short along the ray.
        for (slope, short) in [(3f32.sqrt(), 0.1f32), (5.671, 0.2879)] {
            let free = free_length(r, sigma, Some(slope * slope), h);
            assert!((free - (r - short)).abs() < 1e-3, "slope {slope}: {free}");
            let square = (r - free) / (1.0 + slope * slope).sqrt();
            assert!(
                (square - h / 2.0).abs() < 1e-4,
                "slope {slope}: {square} m from the surface"
            );
        }
        // A large σ still wins where it is the longer margin.
        assert!((free_length(r, 0.2, Some(3.0), h) - (r - 0.4)).abs() < 1e-6);
    }

    /// The linear index of voxel `(x, 8, 8)` of [`cube16`]: the row [`frames_of_a_wall`] looks
    /// along.
    fn on_the_axis(x: u16) -> usize {
        cube16().dims().linear(VoxelIndex::new(x, 8, 8))
    }

    /// Integrates one 30 × 30 frame per entry of `walls` into a map of [`cube16`] with a
    /// surface estimate, from a camera at x = 0 looking along +x at a wall that many metres
    /// away, each depth with independent noise of 3 cm (a fixed generator seeded with `seed`;
    /// a sum of 12 uniforms is close to normal). `each` sees the frame's number and stats and
    /// the map after it.
    fn frames_of_a_wall(
        walls: impl IntoIterator<Item = f32>,
        seed: u64,
        each: impl FnMut(usize, IntegrationStats, &VoxelMap<'_>),
    ) {
        frames_of_a_wall_after(|_| {}, walls, seed, each);
    }

    /// [`frames_of_a_wall`] into a map that `prepare` has changed first.
    fn frames_of_a_wall_after(
        prepare: impl FnOnce(&mut VoxelMap<'_>),
        walls: impl IntoIterator<Item = f32>,
        mut seed: u64,
        mut each: impl FnMut(usize, IntegrationStats, &VoxelMap<'_>),
    ) {
        let g = cube16();
        let (mut lo, mut st) = ([0i8; 4096], [0u32; 128]);
        let mut surface = [[0i32; 2]; 4096];
        let mut map = VoxelMap::new(g, LogOddsParams::default(), &mut lo, &mut st)
            .unwrap()
            .with_surface(&mut surface);
        prepare(&mut map);
        let mut scratch = [0u32; 8192];
        let side = 30u16;
        let c = f32::from(side - 1) / 2.0;
        let intr = Intrinsics::new(20.0, 20.0, c, c, side, side).unwrap();
        let mut pose = looking_along_x();
        pose.translation.vector.x = 0.0;
        let noise = 0.03;
        let params = IntegrationParams {
            depth_noise_per_m: noise,
            ..IntegrationParams::default()
        };
        let mut uniform = move || {
            seed = seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (seed >> 33) as f32 / (1u64 << 31) as f32
        };
        let mut depth = [0u16; 900];
        for (k, wall) in walls.into_iter().enumerate() {
            for d in depth.iter_mut() {
                let n: f32 = (0..12).map(|_| uniform()).sum::<f32>() - 6.0;
                *d = libm::roundf((wall + noise * n) * 1000.0) as u16;
            }
            let frame = DepthFrame::new(intr, &depth).unwrap();
            let s = integrate_with_scratch(&mut map, &frame, &pose, &params, &mut scratch).unwrap();
            each(k, s, &map);
        }
    }

    /// A camera 1 m in front of a wall on a voxel face (x = 1.0 m), 20 frames of depth with
    /// independent noise of 3 cm: with the surface estimate the voxel in front of the wall ends
    /// free and the wall's voxel occupied, and the voxel behind it is never observed.
    #[test]
    fn the_surface_estimate_frees_the_voxel_in_front_of_a_wall_on_a_voxel_face() {
        let at = on_the_axis;
        frames_of_a_wall(core::iter::repeat_n(1.0, 20), 12345, |k, s, map| {
            assert!(s.voted > 0, "{s:?}");
            if k == 19 {
                assert_eq!(map.occupancy(at(9)), Occupancy::Free);
                assert_eq!(map.occupancy(at(10)), Occupancy::Occupied);
                assert!(map.is_unknown(at(11)));
                let (front, _) = surface_estimate(map.surface(), at(9)).unwrap();
                let (wall, _) = surface_estimate(map.surface(), at(10)).unwrap();
                assert!(front > SURFACE_OCCUPIED && front < 1.5, "{front}");
                assert!(wall < 0.0 && wall > -SURFACE_HIDDEN, "{wall}");
            }
        });
    }

    /// After the wall of [`the_surface_estimate_frees_the_voxel_in_front_of_a_wall_on_a_voxel_face`]
    /// is established, frames whose returns all land a voxel too deep (as a filter that mixed a
    /// nearer edge into them gives) do not mark the voxel behind the wall: the wall's voxel
    /// hides it.
    #[test]
    fn returns_behind_an_established_surface_do_not_mark_the_voxel_behind_it() {
        let at = on_the_axis;
        // 20 frames of the wall at 1.0 m, then 3 whose returns all lie at 1.1 m: after the
        // 20th and after the last, the wall's voxel is occupied and the one behind it unseen.
        let walls = core::iter::repeat_n(1.0f32, 20).chain(core::iter::repeat_n(1.1, 3));
        frames_of_a_wall(walls, 777, |k, _, map| {
            if k == 19 || k == 22 {
                assert_eq!(map.occupancy(at(10)), Occupancy::Occupied);
                assert!(map.is_unknown(at(11)), "{k}: {:?}", map.occupancy(at(11)));
                assert!(surface_estimate(map.surface(), at(11)).is_none());
            }
        });
    }

    /// A voxel behind the wall of
    /// [`the_surface_estimate_frees_the_voxel_in_front_of_a_wall_on_a_voxel_face`] that one
    /// hit marked occupied before the wall was seen (a return that landed deep) is forgotten
    /// once the wall's voxel is sure: unknown again, as the noise-free sensor leaves it, and
    /// sealed. The same voxel marked by three hits (strong evidence, as a surface seen from its
    /// own side gives) is kept.
    #[test]
    fn weak_evidence_behind_an_established_surface_is_forgotten() {
        let at = on_the_axis;
        for (hits, forgotten) in [(1, true), (3, false)] {
            let mut dropped = 0;
            let prepare = |map: &mut VoxelMap<'_>| {
                for _ in 0..hits {
                    map.begin_frame();
                    assert!(map.apply_hit(at(11)));
                }
                assert_eq!(map.occupancy(at(11)), Occupancy::Occupied);
            };
            frames_of_a_wall_after(prepare, core::iter::repeat_n(1.0, 20), 99, |k, s, map| {
                dropped += s.stale_forgotten;
                if k == 19 {
                    assert_eq!(map.occupancy(at(10)), Occupancy::Occupied, "{hits} hits");
                    assert_eq!(map.is_unknown(at(11)), forgotten, "{hits} hits");
                    // Sealed: no frontier, and an obstacle to the planner as before.
                    assert_eq!(map.is_sealed(at(11)), forgotten, "{hits} hits");
                    assert_eq!(map.occupancy(at(9)), Occupancy::Free, "{hits} hits");
                }
            });
            assert_eq!(dropped > 0, forgotten, "{hits} hits: {dropped} forgotten");
        }
    }

    /// The centre pixel's `(σ, free distance)` of a 5 × 5 `depth` image (f = 50 px) looking
    /// along +x, with the stereo noise of [`noisy`] and a `footprint` (pixels).
    fn centre_of(depth: &[u16; 25], footprint: f32) -> (f32, f32) {
        let intr = Intrinsics::new(50.0, 50.0, 2.0, 2.0, 5, 5).unwrap();
        let frame = DepthFrame::new(intr, depth).unwrap();
        let params = IntegrationParams {
            footprint_px: footprint,
            ..noisy()
        };
        let pose = looking_along_x();
        let mut centre = None;
        let mut k = 0;
        for_each_pixel_ray(&frame, &pose, &params, 0.1, Want::FreeSpace, |ray| {
            if let (12, PixelRay::Noisy { sigma, free_to, .. }) = (k, ray) {
                centre = Some((sigma, (free_to - Point3::from(pose.translation.vector)).norm()));
            }
            k += 1;
        });
        centre.unwrap()
    }

    /// [`centre_of`] a surface whose depth grows 4 cm a row (slant 2: depth per lateral metre).
    fn centre_of_a_slant(footprint: f32) -> (f32, f32) {
        let mut depth = [0u16; 25];
        for (i, d) in depth.iter_mut().enumerate() {
            *d = 1000 + 40 * (i / 5) as u16 - 80;
        }
        centre_of(&depth, footprint)
    }

    #[test]
    fn a_slanted_surface_adds_the_spread_of_the_windows_depth_span_to_sigma() {
        // Without a footprint: σ = 0.032 m at 1 m, and the misses stop half a voxel from the
        // slanted surface, 0.05·√(1 + 2²) = 0.112 m short of the return.
        let (sigma, free) = centre_of_a_slant(0.0);
        assert!((sigma - 0.032).abs() < 1e-5, "{sigma}");
        assert!((free - (1.0 - 0.05 * 5f32.sqrt())).abs() < 1e-4, "{free}");
        // A 4-pixel window spans 4 · 1 m / 50 px · 2 = 0.16 m of depth: its standard deviation
        // as a uniform spread, 0.16/√12 = 0.046 m, in quadrature; and the misses stop 2σ short
        // of the nearest depth within the window's reach (two pixels: the row at 0.92 m).
        let (sigma, free) = centre_of_a_slant(4.0);
        let span = 0.16f32 / 12f32.sqrt();
        let expected = (0.032f32 * 0.032 + span * span).sqrt();
        assert!((sigma - expected).abs() < 1e-5, "{sigma}");
        assert!((free - (0.92 - 2.0 * expected)).abs() < 1e-4, "{free}");
    }

    #[test]
    fn a_far_return_beside_a_near_one_clears_no_deeper_than_the_near_one() {
        // A wall 2 m away seen square on, and one pixel beside the centre a thin post at 1 m:
        // the window cannot tell which of the two the centre's match belongs to.
        let mut depth = [2000u16; 25];
        depth[11] = 1000;
        let free_of_centre = |footprint| centre_of(&depth, footprint);
        // Without a footprint: 2σ short of the wall, a voxel further (it faces the camera).
        let (sigma, free) = free_of_centre(0.0);
        assert!((free - (2.0 - 2.0 * sigma + 0.1)).abs() < 1e-4, "{free}");
        // With a 3.5-pixel window (two pixels either way): 2σ short of the post's depth.
        let (sigma, free) = free_of_centre(3.5);
        assert!((free - (1.0 - 2.0 * sigma)).abs() < 1e-4, "{free}");
    }

    #[test]
    fn a_return_whose_slant_cannot_be_measured_is_counted_not_integrated() {
        // One return with no neighbour: a stereo matcher's isolated match.
        let intr = Intrinsics::new(50.0, 50.0, 1.0, 1.0, 3, 3).unwrap();
        let mut depth = [0u16; 9];
        depth[4] = 1000;
        let frame = DepthFrame::new(intr, &depth).unwrap();
        let stereo = IntegrationParams {
            no_return: NoReturn::Unknown,
            footprint_px: 3.5,
            ..noisy()
        };
        let mut f = Fixture::new();
        let mut map = f.map();
        let mut scratch = [0u32; 64];
        let s = integrate_with_scratch(&mut map, &frame, &looking_along_x(), &stereo, &mut scratch).unwrap();
        assert_eq!(
            (s.unmeasured_slant, s.returns, s.voxel_updates),
            (1, 0, 0),
            "{s:?}"
        );
        assert!((0..cube16().dims().len()).all(|i| map.is_unknown(i)));
        // Without a footprint the same return clears the row in front of it and marks it.
        let mut g = Fixture::new();
        let mut map = g.map();
        let params = IntegrationParams {
            footprint_px: 0.0,
            ..stereo
        };
        let s = integrate_with_scratch(&mut map, &frame, &looking_along_x(), &params, &mut scratch).unwrap();
        assert_eq!((s.unmeasured_slant, s.returns), (0, 1), "{s:?}");
        assert_eq!(map.occupancy(on_row(5)), Occupancy::Free);
        assert_eq!(map.occupancy(on_row(10)), Occupancy::Occupied);
    }

    #[test]
    fn a_bad_depth_noise_is_rejected() {
        let mut f = Fixture::new();
        let mut map = f.map();
        let depth = [1000u16];
        let frame = DepthFrame::new(one_pixel(), &depth).unwrap();
        for bad in [f32::NAN, -0.1, f32::INFINITY] {
            let params = IntegrationParams {
                depth_noise_per_m: bad,
                ..IntegrationParams::default()
            };
            assert_eq!(
                integrate(&mut map, &frame, &looking_along_x(), &params),
                Err(IntegrateError::BadRange),
                "{bad}"
            );
            let params = IntegrationParams {
                footprint_px: bad,
                ..noisy()
            };
            assert_eq!(
                integrate(&mut map, &frame, &looking_along_x(), &params),
                Err(IntegrateError::BadRange),
                "footprint {bad}"
            );
        }
    }
}
