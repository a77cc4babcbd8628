//! A simulated stereo camera: textured left and right images of the world, ground-truth
//! disparity, and depth computed from them by the core's block matcher
//! ([`harmonic_core::stereo`]) — the same code the firmware would run on rectified rows.
//!
//! ## Rendering
//!
//! The left camera is the depth camera (pose, field of view); the right one sits
//! [`StereoRig::baseline_m`] to its right (camera +x), so the pair is rectified by
//! construction. Every pixel casts a ray into the [`World`] and shades the hit:
//!
//! - **texture**: multi-octave 3D value noise of the hit's world coordinates (a solid
//!   texture, so both cameras see the same pattern on the surface), seeded per obstacle, with
//!   wavelengths from 0.8 m down to 6 mm. Octaves shorter than about 3 pixels at the hit's
//!   distance (and slant) fade out, a cheap stand-in for a mip-map: without it the finest
//!   octaves alias into noise that differs between the two views;
//! - **textureless** surfaces (`textureless = true` in a scenario) keep only their base
//!   reflectance: uniform faces, on which matching must fail;
//! - **shading**: Lambertian from a fixed light direction plus ambient (view-independent, so
//!   the two cameras agree), then Gaussian sensor noise ([`StereoRig::pixel_noise`] grey
//!   levels) and 8-bit quantisation.
//!
//! Ground truth: disparity `fx · b / z` of the left camera's hit, and a Middlebury-style mask
//! (255 visible to both cameras, 128 occluded in or outside the right image, 0 no surface).
//!
//! ## Depth for the explorer
//!
//! [`StereoDepth`] renders the pair at [`StereoRig::scale`] times the depth camera's
//! resolution (default 2: 200 × 200 px for the 100 × 100 px, 75° thesis camera, fx ≈ 130 px),
//! matches it with the core, converts disparity to depth and reduces each `scale × scale`
//! block to one pixel of the depth camera's frame (the lower median of its valid depths when
//! at least half are valid, else 0). With the 0.12 m baseline of the thesis's Bumblebee2 and
//! 64 disparities, 200 px images cover 0.25 m (63 px) to beyond 5 m (3.1 px); on 100 × 100 px
//! images the same range would leave 1.6 px of disparity at 5 m and a 21 px match footprint
//! on a 100 px image. Pixels without a match are depth 0, which the explorer must integrate as
//! unknown ([`harmonic_core::integrate::NoReturn::Unknown`]), never as free space.

use std::path::Path;
use std::time::Instant;

use harmonic_core::camera::Intrinsics;
use harmonic_core::stereo::{
    self, Prefilter, StereoGeometry, StereoParams, StereoScratch, StereoStats, DISPARITY_SCALE,
};
use nalgebra::{Isometry3, Point3, Translation3, Vector3};
use rand::Rng;
use serde::Serialize;

use crate::sensors::camera::RAYCAST_LIMIT_M;
use crate::world::World;

/// The stereo camera and its matcher settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StereoRig {
    /// Rendering resolution as a multiple of the depth camera's.
    pub scale: u16,
    /// Distance between the cameras, metres.
    pub baseline_m: f32,
    /// Disparities searched.
    pub num_disparities: u16,
    /// SAD window side (each of the five windows), pixels.
    pub window: u8,
    /// Standard deviation of the sensor noise, grey levels.
    pub pixel_noise: f32,
    /// The matcher's prefilter.
    pub prefilter: Prefilter,
}

impl Default for StereoRig {
    /// 2× the depth camera's resolution, 0.12 m baseline, 64 disparities, 7 × 7 windows
    /// (13 px footprint), σ = 1 grey level of noise, DoG prefilter (σ 1.0/1.6 px): the best
    /// bad-2.0 rate of the settings compared in BENCHMARKS.md.
    fn default() -> Self {
        Self {
            scale: 2,
            baseline_m: 0.12,
            num_disparities: 64,
            window: 7,
            pixel_noise: 1.0,
            prefilter: Prefilter::DEFAULT_DOG,
        }
    }
}

impl StereoRig {
    /// The rendering intrinsics for a depth camera with `k`: `scale` times the pixels over
    /// the same field of view.
    pub fn render_intrinsics(&self, k: &Intrinsics) -> Result<Intrinsics, String> {
        let s = f32::from(self.scale);
        let (w, h) = (
            k.width().checked_mul(self.scale),
            k.height().checked_mul(self.scale),
        );
        let (Some(w), Some(h)) = (w, h) else {
            return Err(format!("stereo scale {} is too large", self.scale));
        };
        Intrinsics::new(
            k.fx() * s,
            k.fy() * s,
            (k.cx() + 0.5) * s - 0.5,
            (k.cy() + 0.5) * s - 0.5,
            w,
            h,
        )
        .map_err(|e| format!("stereo intrinsics: {e:?}"))
    }

    /// The matcher's parameters for `width × height` images.
    pub fn params(&self, width: u16, height: u16) -> StereoParams {
        StereoParams {
            window: self.window,
            prefilter: self.prefilter,
            ..StereoParams::new(width, height, self.num_disparities)
        }
    }
}

/// A rendered, rectified pair with its ground truth (row-major, `width × height`).
#[derive(Debug, Clone)]
pub struct StereoPair {
    /// Image width, pixels.
    pub width: u16,
    /// Image height, pixels.
    pub height: u16,
    /// Left (reference) image.
    pub left: Vec<u8>,
    /// Right image.
    pub right: Vec<u8>,
    /// True disparity of the left pixel, pixels; `+inf` where the ray hits nothing.
    pub disparity: Vec<f32>,
    /// Middlebury-style mask: 255 seen by both cameras, 128 occluded in the right view (or
    /// outside it), 0 nothing hit.
    pub mask: Vec<u8>,
}

/// Hash of a lattice point and a seed to [0, 1).
fn lattice(ix: i32, iy: i32, iz: i32, seed: u32) -> f32 {
    let mut h = (ix as u32).wrapping_mul(0x8DA6_B343)
        ^ (iy as u32).wrapping_mul(0xD816_3841)
        ^ (iz as u32).wrapping_mul(0xCB1A_B31F)
        ^ seed.wrapping_mul(0x9E37_79B9);
    h ^= h >> 16;
    h = h.wrapping_mul(0x7FEB_352D);
    h ^= h >> 15;
    h = h.wrapping_mul(0x846C_A68B);
    h ^= h >> 16;
    (h >> 8) as f32 / (1u32 << 24) as f32
}

/// Trilinear value noise with a smoothstep fade, in [0, 1).
fn value_noise(p: &Vector3<f32>, seed: u32) -> f32 {
    let (fx, fy, fz) = (p.x.floor(), p.y.floor(), p.z.floor());
    let fade = |t: f32| t * t * (3.0 - 2.0 * t);
    let (tx, ty, tz) = (fade(p.x - fx), fade(p.y - fy), fade(p.z - fz));
    let (ix, iy, iz) = (fx as i32, fy as i32, fz as i32);
    let lerp = |a: f32, b: f32, t: f32| a + (b - a) * t;
    let plane = |z: i32| {
        let a = lerp(lattice(ix, iy, z, seed), lattice(ix + 1, iy, z, seed), tx);
        let b = lerp(lattice(ix, iy + 1, z, seed), lattice(ix + 1, iy + 1, z, seed), tx);
        lerp(a, b, ty)
    };
    lerp(plane(iz), plane(iz + 1), tz)
}

/// Texture wavelengths, metres.
const OCTAVES_M: [f32; 8] = [0.8, 0.4, 0.2, 0.1, 0.05, 0.025, 0.0125, 0.00625];

/// Reflectance of surface `surface` at world point `p`, seen with a pixel footprint of
/// `footprint` metres: its base value plus band-limited noise.
fn reflectance(p: &Point3<f32>, surface: usize, textureless: bool, footprint: f32) -> f32 {
    let seed = (surface as u32).wrapping_mul(0x2C1B_3C6D) ^ 0x2975_A3B1;
    let base = 0.35 + 0.3 * lattice(surface as i32, 7, 11, 0x51ED);
    if textureless {
        return base;
    }
    let (mut sum, mut weight) = (0.0, 0.0);
    for (k, &lambda) in OCTAVES_M.iter().enumerate() {
        // Full weight above 3 px per wavelength, none below 1.5 px.
        let t = ((lambda / footprint - 1.5) / 1.5).clamp(0.0, 1.0);
        let w = t * t * (3.0 - 2.0 * t);
        if w <= 0.0 {
            continue;
        }
        let q = p.coords / lambda;
        sum += w * (value_noise(&q, seed.wrapping_add((k as u32).wrapping_mul(0x68E3_1DA4))) - 0.5);
        weight += w;
    }
    let noise = if weight > 0.0 { sum / weight } else { 0.0 };
    (base + 1.6 * noise).clamp(0.03, 0.97)
}

/// Direction towards the light (map frame), normalised in [`shade`].
const LIGHT: [f32; 3] = [0.35, 0.55, 0.75];

/// Lambertian shading with ambient light: in [0.3, 1].
fn shade(normal: &Vector3<f32>) -> f32 {
    let l = Vector3::from(LIGHT).normalize();
    0.3 + 0.7 * normal.dot(&l).max(0.0)
}

/// One sample of N(0, 1) (Box–Muller).
fn standard_normal(rng: &mut impl Rng) -> f32 {
    let u1: f32 = 1.0 - rng.random::<f32>();
    let u2: f32 = rng.random::<f32>();
    (-2.0 * u1.ln()).sqrt() * (std::f32::consts::TAU * u2).cos()
}

/// Renders one camera: the intensity image, and per pixel the hit point and its camera z.
fn render_view(
    world: &World,
    k: &Intrinsics,
    pose: &Isometry3<f32>,
    noise: f32,
    rng: &mut impl Rng,
    mut on_hit: impl FnMut(usize, Option<(Point3<f32>, f32)>),
) -> Vec<u8> {
    let (w, h) = (k.width(), k.height());
    let rotation = pose.rotation.to_rotation_matrix();
    let origin = Point3::from(pose.translation.vector);
    let mut image = Vec::with_capacity(k.pixel_count());
    for v in 0..h {
        for u in 0..w {
            let ray = k.ray(u, v);
            let norm = ray.norm();
            let dir = rotation * (ray / norm);
            let hit = world.raycast_surface(&origin, &dir, RAYCAST_LIMIT_M);
            let radiance = match &hit {
                Some(s) => {
                    let p = origin + dir * s.t;
                    let slant = s.normal.dot(&dir).abs().max(0.2);
                    let footprint = (s.t / k.fx() / slant).max(1e-4);
                    on_hit(image.len(), Some((p, s.t / norm)));
                    255.0 * reflectance(&p, s.surface, s.textureless, footprint) * shade(&s.normal)
                }
                None => {
                    on_hit(image.len(), None);
                    0.0
                }
            };
            let noisy = if noise > 0.0 {
                radiance + noise * standard_normal(rng)
            } else {
                radiance
            };
            image.push(noisy.round().clamp(0.0, 255.0) as u8);
        }
    }
    image
}

/// Renders the pair seen from `left_pose` (left camera → map) with intrinsics `k` (both
/// cameras), and its ground truth.
pub fn render_pair(
    world: &World,
    k: &Intrinsics,
    left_pose: &Isometry3<f32>,
    baseline_m: f32,
    pixel_noise: f32,
    rng: &mut impl Rng,
) -> StereoPair {
    let n = k.pixel_count();
    let mut disparity = vec![f32::INFINITY; n];
    let mut mask = vec![0u8; n];
    let right_pose = left_pose * Translation3::new(baseline_m, 0.0, 0.0);
    let right_origin = Point3::from(right_pose.translation.vector);
    let fb = k.fx() * baseline_m;
    let width = usize::from(k.width());
    let left = render_view(world, k, left_pose, pixel_noise, rng, |i, hit| {
        let Some((p, z)) = hit else { return };
        let d = fb / z;
        disparity[i] = d;
        // Visible to the right camera: inside its image and nothing in between.
        let u = (i % width) as f32;
        let inside = u - d >= -0.5;
        let to_p = p - right_origin;
        let dist = to_p.norm();
        let clear = dist > 0.0
            && world
                .raycast(&right_origin, &(to_p / dist), dist)
                .is_none_or(|t| t >= dist - (0.01 + 0.002 * dist));
        mask[i] = if inside && clear { 255 } else { 128 };
    });
    let right = render_view(world, k, &right_pose, pixel_noise, rng, |_, _| {});
    StereoPair {
        width: k.width(),
        height: k.height(),
        left,
        right,
        disparity,
        mask,
    }
}

/// Owned scratch for the core's matcher.
pub struct MatcherBuffers {
    bytes: Vec<u8>,
    halfwords: Vec<u16>,
    words: Vec<u32>,
}

impl MatcherBuffers {
    /// Buffers for `params`.
    pub fn new(params: &StereoParams) -> Result<Self, String> {
        let s = stereo::scratch_size(params).map_err(|e| format!("stereo parameters: {e:?}"))?;
        Ok(Self {
            bytes: vec![0; s.bytes],
            halfwords: vec![0; s.halfwords],
            words: vec![0; s.words],
        })
    }

    /// Lends them to a matcher.
    pub fn lend(&mut self) -> StereoScratch<'_> {
        StereoScratch {
            bytes: &mut self.bytes,
            halfwords: &mut self.halfwords,
            words: &mut self.words,
        }
    }
}

/// Runs the core's matcher on a whole pair; returns the disparity (1/16 px) and statistics.
pub fn match_pair(
    params: StereoParams,
    left: &[u8],
    right: &[u8],
    buffers: &mut MatcherBuffers,
) -> Result<(Vec<i16>, StereoStats), String> {
    let mut disparity = vec![0i16; left.len()];
    let stats = stereo::match_images(params, left, right, buffers.lend(), &mut disparity)
        .map_err(|e| format!("stereo matcher: {e:?}"))?;
    Ok((disparity, stats))
}

/// Runs the core's matcher on a whole pair in `bands` horizontal bands at once (rayon), each
/// band matched with [`StereoParams::context_rows`] more rows above and below, then one
/// speckle pass over the joined image. Gives exactly [`match_pair`]'s disparity and statistics
/// (tested), in about `1/bands` of the time on as many cores. Bands shorter than twice their
/// context are not worth it: fewer are used, down to one (then it is [`match_pair`]).
pub fn match_pair_bands(
    params: StereoParams,
    left: &[u8],
    right: &[u8],
    bands: usize,
) -> Result<(Vec<i16>, StereoStats), String> {
    use rayon::prelude::*;
    let err = |e: stereo::StereoError| format!("stereo matcher: {e:?}");
    params.validate().map_err(err)?;
    let (w, h) = (usize::from(params.width), usize::from(params.height));
    if left.len() != w * h || right.len() != w * h {
        return Err(format!("the images are not {w}x{h}"));
    }
    let context = params.context_rows().map_err(err)?;
    let bands = bands.clamp(1, (h / (2 * context).max(1)).max(1));
    if bands == 1 {
        return match_pair(params, left, right, &mut MatcherBuffers::new(&params)?);
    }
    // Per band: its first row, its rows' disparities, its statistics.
    type Band = (usize, Vec<i16>, StereoStats);
    let results: Vec<Result<Band, String>> = (0..bands)
        .into_par_iter()
        .map(|i| {
            let (y0, y1) = (i * h / bands, (i + 1) * h / bands);
            let (a, b) = (y0.saturating_sub(context), (y1 + context).min(h));
            let band = StereoParams {
                height: u16::try_from(b - a).map_err(|_| "band too tall".to_string())?,
                speckle_size: 0,
                ..params
            };
            let mut buffers = MatcherBuffers::new(&band)?;
            let mut matcher = stereo::StereoMatcher::new(band, buffers.lend()).map_err(err)?;
            matcher.count_rows(y0 - a, y1 - a);
            let mut disparity = vec![0i16; (b - a) * w];
            for (l, r) in left[a * w..b * w]
                .chunks_exact(w)
                .zip(right[a * w..b * w].chunks_exact(w))
            {
                matcher.push_row(l, r, &mut disparity).map_err(err)?;
            }
            let stats = matcher.finish(&mut disparity).map_err(err)?;
            Ok((y0, disparity[(y0 - a) * w..(y1 - a) * w].to_vec(), stats))
        })
        .collect();
    let mut disparity = vec![stereo::INVALID_DISPARITY; w * h];
    let mut stats = StereoStats::default();
    for result in results {
        let (y0, rows, s) = result?;
        disparity[y0 * w..y0 * w + rows.len()].copy_from_slice(&rows);
        stats.border += s.border;
        stats.textureless += s.textureless;
        stats.ambiguous += s.ambiguous;
        stats.inconsistent += s.inconsistent;
    }
    let mut speckle =
        vec![0u32; stereo::speckle::speckle_scratch_words(params.width, params.height, params.speckle_size)];
    stats.speckles = stereo::speckle::filter_speckles(
        &mut disparity,
        params.width,
        params.height,
        params.speckle_size,
        params.speckle_range,
        &mut speckle,
    )
    .map_err(err)?;
    stats.valid = disparity.iter().filter(|&&d| d >= 0).count() as u32;
    Ok((disparity, stats))
}

/// Disparity in pixels, `+inf` where invalid (the file convention of `harmonic-sim stereo`).
pub fn disparity_to_f32(disparity: &[i16]) -> Vec<f32> {
    disparity
        .iter()
        .map(|&d| {
            if d < 0 {
                f32::INFINITY
            } else {
                f32::from(d) / f32::from(DISPARITY_SCALE)
            }
        })
        .collect()
}

/// Middlebury-style accuracy of a disparity map against ground truth.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct StereoMetrics {
    /// Pixels evaluated: finite ground truth, and non-occluded when a mask is given.
    pub evaluated: usize,
    /// Of those, pixels with a valid (finite) estimate.
    pub valid: usize,
    /// Percent of valid evaluated pixels off by more than 1 px.
    pub bad1: f64,
    /// Percent of valid evaluated pixels off by more than 2 px.
    pub bad2: f64,
    /// Percent of evaluated pixels off by more than 2 px or invalid (Middlebury's rate for a
    /// sparse result without hole filling).
    pub bad2_with_holes: f64,
    /// Mean absolute error of the valid evaluated pixels, px.
    pub mean_abs_error: f64,
    /// Percent of evaluated pixels with a valid estimate.
    pub density: f64,
}

impl StereoMetrics {
    /// Compares `estimate` with `truth` (both pixels, `inf`/NaN = none) over the pixels whose
    /// `mask` is 255 (all with finite truth if `None`).
    pub fn evaluate(estimate: &[f32], truth: &[f32], mask: Option<&[u8]>) -> Self {
        let (mut evaluated, mut valid, mut bad1, mut bad2, mut err_sum) =
            (0usize, 0usize, 0usize, 0usize, 0f64);
        for (i, (&e, &t)) in estimate.iter().zip(truth).enumerate() {
            if !t.is_finite() || mask.is_some_and(|m| m.get(i) != Some(&255)) {
                continue;
            }
            evaluated += 1;
            if !e.is_finite() {
                continue;
            }
            valid += 1;
            let err = (e - t).abs();
            err_sum += f64::from(err);
            bad1 += usize::from(err > 1.0);
            bad2 += usize::from(err > 2.0);
        }
        let pct = |n: usize, of: usize| {
            if of == 0 {
                0.0
            } else {
                100.0 * n as f64 / of as f64
            }
        };
        Self {
            evaluated,
            valid,
            bad1: pct(bad1, valid),
            bad2: pct(bad2, valid),
            bad2_with_holes: pct(bad2 + evaluated - valid, evaluated),
            mean_abs_error: if valid == 0 { 0.0 } else { err_sum / valid as f64 },
            density: pct(valid, evaluated),
        }
    }
}

/// Per-run statistics of stereo depth, in `report.json` as `stereo`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct StereoReport {
    /// Frames matched.
    pub frames: u32,
    /// Rendering resolution, pixels.
    pub render_size: [u16; 2],
    /// Baseline, metres.
    pub baseline_m: f32,
    /// Disparities searched.
    pub num_disparities: u16,
    /// Window side, pixels.
    pub window: u8,
    /// Mean fraction of matched pixels with a valid disparity.
    pub mean_match_density: f64,
    /// Mean fraction of depth-frame pixels with a depth.
    pub mean_depth_density: f64,
    /// Mean time to render the pair, ms.
    pub mean_render_ms: f64,
    /// Mean time of the core's matcher, ms.
    pub mean_match_ms: f64,
}

/// Depth frames from rendered stereo pairs through the core's matcher.
pub struct StereoDepth {
    rig: StereoRig,
    render: Intrinsics,
    output: Intrinsics,
    params: StereoParams,
    geometry: StereoGeometry,
    buffers: MatcherBuffers,
    disparity: Vec<i16>,
    report: StereoReport,
}

impl StereoDepth {
    /// Stereo depth for a depth camera with intrinsics `output`.
    pub fn new(rig: StereoRig, output: &Intrinsics) -> Result<Self, String> {
        if rig.scale == 0 {
            return Err("stereo scale must be at least 1".into());
        }
        let render = rig.render_intrinsics(output)?;
        let params = rig.params(render.width(), render.height());
        let geometry = StereoGeometry::new(render.fx(), rig.baseline_m)
            .map_err(|e| format!("stereo geometry: {e:?}"))?;
        let buffers = MatcherBuffers::new(&params)?;
        Ok(Self {
            rig,
            render,
            output: *output,
            params,
            geometry,
            buffers,
            disparity: vec![0; render.pixel_count()],
            report: StereoReport {
                render_size: [render.width(), render.height()],
                baseline_m: rig.baseline_m,
                num_disparities: rig.num_disparities,
                window: rig.window,
                ..StereoReport::default()
            },
        })
    }

    /// The rendering camera.
    pub fn render_intrinsics(&self) -> &Intrinsics {
        &self.render
    }

    /// Renders the pair at `left_pose`, matches it and writes the depth frame (the output
    /// camera's size, u16 mm, 0 = no depth) into `out`.
    pub fn render_depth(
        &mut self,
        world: &World,
        left_pose: &Isometry3<f32>,
        rng: &mut impl Rng,
        out: &mut Vec<u16>,
    ) -> Result<StereoStats, String> {
        let t0 = Instant::now();
        let pair = render_pair(
            world,
            &self.render,
            left_pose,
            self.rig.baseline_m,
            self.rig.pixel_noise,
            rng,
        );
        let t1 = Instant::now();
        let stats = stereo::match_images(
            self.params,
            &pair.left,
            &pair.right,
            self.buffers.lend(),
            &mut self.disparity,
        )
        .map_err(|e| format!("stereo matcher: {e:?}"))?;
        let t2 = Instant::now();
        let s = usize::from(self.rig.scale);
        let (w_hi, w, h) = (
            usize::from(self.render.width()),
            usize::from(self.output.width()),
            usize::from(self.output.height()),
        );
        out.clear();
        out.resize(w * h, 0);
        let mut block = Vec::with_capacity(s * s);
        for v in 0..h {
            for u in 0..w {
                block.clear();
                for j in 0..s {
                    for i in 0..s {
                        let z = self
                            .geometry
                            .depth_mm(self.disparity[(v * s + j) * w_hi + u * s + i]);
                        if z > 0 {
                            block.push(z);
                        }
                    }
                }
                if 2 * block.len() >= s * s && !block.is_empty() {
                    block.sort_unstable();
                    out[v * w + u] = block[(block.len() - 1) / 2];
                }
            }
        }
        let r = &mut self.report;
        let n = f64::from(r.frames);
        let mean = |old: f64, new: f64| (old * n + new) / (n + 1.0);
        r.mean_match_density = mean(
            r.mean_match_density,
            f64::from(stats.valid) / pair.left.len() as f64,
        );
        r.mean_depth_density = mean(
            r.mean_depth_density,
            out.iter().filter(|&&z| z > 0).count() as f64 / out.len() as f64,
        );
        r.mean_render_ms = mean(r.mean_render_ms, (t1 - t0).as_secs_f64() * 1e3);
        r.mean_match_ms = mean(r.mean_match_ms, (t2 - t1).as_secs_f64() * 1e3);
        r.frames += 1;
        Ok(stats)
    }

    /// What the frames so far looked like.
    pub fn report(&self) -> StereoReport {
        self.report
    }
}

/// Writes a rendered pair the way Middlebury ships one: `left.png`, `right.png`, the ground
/// truth `gt.pfm` and `gt.npy` (pixels, `+inf` = no surface), `mask.png` (255 non-occluded,
/// 128 occluded, 0 no surface) and `calib.txt` (`cam0`, `cam1`, `baseline` in mm, `ndisp`).
pub fn write_pair(
    dir: &Path,
    pair: &StereoPair,
    k: &Intrinsics,
    baseline_m: f32,
    ndisp: u16,
) -> Result<(), String> {
    std::fs::create_dir_all(dir).map_err(|e| format!("{}: {e}", dir.display()))?;
    let (w, h) = (pair.width, pair.height);
    write_png_gray(&dir.join("left.png"), w, h, &pair.left)?;
    write_png_gray(&dir.join("right.png"), w, h, &pair.right)?;
    write_png_gray(&dir.join("mask.png"), w, h, &pair.mask)?;
    write_pfm(&dir.join("gt.pfm"), w, h, &pair.disparity)?;
    let npy = crate::io::npy::write_f32_image(usize::from(h), usize::from(w), &pair.disparity);
    std::fs::write(dir.join("gt.npy"), npy).map_err(|e| format!("{}: {e}", dir.display()))?;
    let cam = format!("[{} 0 {}; 0 {} {}; 0 0 1]", k.fx(), k.cx(), k.fy(), k.cy());
    let calib = format!(
        "cam0={cam}\ncam1={cam}\ndoffs=0\nbaseline={}\nwidth={w}\nheight={h}\nndisp={ndisp}\n",
        baseline_m * 1000.0
    );
    std::fs::write(dir.join("calib.txt"), calib).map_err(|e| format!("{}: {e}", dir.display()))
}

/// Reads a disparity image in pixels from `.pfm` or `.npy` (by extension).
pub fn read_disparity(path: &Path) -> Result<(u16, u16, Vec<f32>), String> {
    match path.extension().and_then(|e| e.to_str()) {
        Some("pfm") => read_pfm(path),
        Some("npy") => {
            let bytes = std::fs::read(path).map_err(|e| format!("{}: {e}", path.display()))?;
            let (h, w, data) =
                crate::io::npy::read_f32_image(&bytes).map_err(|e| format!("{}: {e}", path.display()))?;
            match (u16::try_from(w), u16::try_from(h)) {
                (Ok(w), Ok(h)) => Ok((w, h, data)),
                _ => Err(format!("{}: image too large", path.display())),
            }
        }
        _ => Err(format!("{}: expected a .pfm or .npy file", path.display())),
    }
}

/// Writes a disparity image in pixels as `.pfm` or `.npy` (by extension).
pub fn write_disparity(path: &Path, width: u16, height: u16, data: &[f32]) -> Result<(), String> {
    match path.extension().and_then(|e| e.to_str()) {
        Some("pfm") => write_pfm(path, width, height, data),
        Some("npy") => std::fs::write(
            path,
            crate::io::npy::write_f32_image(usize::from(height), usize::from(width), data),
        )
        .map_err(|e| format!("{}: {e}", path.display())),
        _ => Err(format!("{}: expected a .pfm or .npy file name", path.display())),
    }
}

/// Reads a PNG as 8-bit grey: grey stays, RGB(A) becomes `0.299 R + 0.587 G + 0.114 B`,
/// 16-bit samples keep their high byte, alpha is dropped.
pub fn read_png_gray(path: &Path) -> Result<(u16, u16, Vec<u8>), String> {
    let err = |e: &dyn std::fmt::Display| format!("{}: {e}", path.display());
    let file = std::fs::File::open(path).map_err(|e| err(&e))?;
    let mut decoder = png::Decoder::new(std::io::BufReader::new(file));
    decoder.set_transformations(png::Transformations::normalize_to_color8());
    let mut reader = decoder.read_info().map_err(|e| err(&e))?;
    let mut buf = vec![0u8; reader.output_buffer_size()];
    let info = reader.next_frame(&mut buf).map_err(|e| err(&e))?;
    let (w, h) = (info.width as usize, info.height as usize);
    let channels = match info.color_type {
        png::ColorType::Grayscale => 1,
        png::ColorType::GrayscaleAlpha => 2,
        png::ColorType::Rgb => 3,
        png::ColorType::Rgba => 4,
        png::ColorType::Indexed => return Err(err(&"indexed colour was not expanded")),
    };
    let (Ok(w16), Ok(h16)) = (u16::try_from(w), u16::try_from(h)) else {
        return Err(err(&"image larger than 65535 pixels"));
    };
    let mut gray = Vec::with_capacity(w * h);
    for y in 0..h {
        let row = &buf[y * info.line_size..y * info.line_size + w * channels];
        for px in row.chunks_exact(channels) {
            gray.push(match channels {
                1 | 2 => px[0],
                _ => (0.299 * f32::from(px[0]) + 0.587 * f32::from(px[1]) + 0.114 * f32::from(px[2])).round()
                    as u8,
            });
        }
    }
    Ok((w16, h16, gray))
}

/// Writes an 8-bit grey PNG.
pub fn write_png_gray(path: &Path, width: u16, height: u16, data: &[u8]) -> Result<(), String> {
    let err = |e: &dyn std::fmt::Display| format!("{}: {e}", path.display());
    let file = std::fs::File::create(path).map_err(|e| err(&e))?;
    let mut enc = png::Encoder::new(std::io::BufWriter::new(file), u32::from(width), u32::from(height));
    enc.set_color(png::ColorType::Grayscale);
    enc.set_depth(png::BitDepth::Eight);
    let mut writer = enc.write_header().map_err(|e| err(&e))?;
    writer.write_image_data(data).map_err(|e| err(&e))?;
    writer.finish().map_err(|e| err(&e))
}

/// A single-channel PFM (little-endian, rows stored bottom to top as the format wants).
pub fn write_pfm(path: &Path, width: u16, height: u16, data: &[f32]) -> Result<(), String> {
    let (w, h) = (usize::from(width), usize::from(height));
    let mut bytes = format!("Pf\n{w} {h}\n-1.0\n").into_bytes();
    for y in (0..h).rev() {
        for v in &data[y * w..(y + 1) * w] {
            bytes.extend_from_slice(&v.to_le_bytes());
        }
    }
    std::fs::write(path, bytes).map_err(|e| format!("{}: {e}", path.display()))
}

/// Reads a single-channel PFM (either byte order) into rows top to bottom.
pub fn read_pfm(path: &Path) -> Result<(u16, u16, Vec<f32>), String> {
    let bytes = std::fs::read(path).map_err(|e| format!("{}: {e}", path.display()))?;
    let bad = |why: &str| format!("{}: not a single-channel PFM ({why})", path.display());
    // Three whitespace-separated header tokens after the magic, then one whitespace byte.
    let mut pos = 0;
    let mut tokens = Vec::new();
    while tokens.len() < 4 {
        while pos < bytes.len() && bytes[pos].is_ascii_whitespace() {
            pos += 1;
        }
        let start = pos;
        while pos < bytes.len() && !bytes[pos].is_ascii_whitespace() {
            pos += 1;
        }
        if start == pos {
            return Err(bad("short header"));
        }
        tokens.push(String::from_utf8_lossy(&bytes[start..pos]).into_owned());
    }
    pos += 1;
    if tokens[0] != "Pf" {
        return Err(bad(&format!("magic {}", tokens[0])));
    }
    let w: u16 = tokens[1].parse().map_err(|_| bad("width"))?;
    let h: u16 = tokens[2].parse().map_err(|_| bad("height"))?;
    let scale: f32 = tokens[3].parse().map_err(|_| bad("scale"))?;
    let (wu, hu) = (usize::from(w), usize::from(h));
    let body = bytes
        .get(pos..pos + 4 * wu * hu)
        .ok_or_else(|| bad("short data"))?;
    let mut data = vec![0f32; wu * hu];
    for (k, c) in body.chunks_exact(4).enumerate() {
        let raw = [c[0], c[1], c[2], c[3]];
        let v = if scale < 0.0 {
            f32::from_le_bytes(raw)
        } else {
            f32::from_be_bytes(raw)
        };
        let (row, col) = (k / wu, k % wu);
        data[(hu - 1 - row) * wu + col] = v;
    }
    Ok((w, h, data))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::world::scenario::Scenario;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    #[test]
    fn pfm_round_trips() {
        let dir = std::env::temp_dir().join(format!("stereo-pfm-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let data: Vec<f32> = (0..12)
            .map(|i| i as f32 * 0.5)
            .chain([f32::INFINITY])
            .take(12)
            .collect();
        write_pfm(&dir.join("a.pfm"), 4, 3, &data).unwrap();
        let (w, h, back) = read_pfm(&dir.join("a.pfm")).unwrap();
        assert_eq!((w, h), (4, 3));
        assert_eq!(back, data);
        write_png_gray(&dir.join("a.png"), 4, 3, &[7; 12]).unwrap();
        assert_eq!(read_png_gray(&dir.join("a.png")).unwrap(), (4, 3, vec![7; 12]));
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn metrics_count_bad_pixels_and_holes() {
        let truth = [1.0, 2.0, 3.0, 4.0, f32::INFINITY];
        let est = [1.5, 3.5, 6.0, f32::INFINITY, 1.0];
        let m = StereoMetrics::evaluate(&est, &truth, None);
        assert_eq!((m.evaluated, m.valid), (4, 3));
        assert!((m.bad1 - 200.0 / 3.0).abs() < 1e-9);
        assert!((m.bad2 - 100.0 / 3.0).abs() < 1e-9);
        assert!((m.bad2_with_holes - 50.0).abs() < 1e-9);
        assert!((m.density - 75.0).abs() < 1e-9);
        let masked = StereoMetrics::evaluate(&est, &truth, Some(&[255, 255, 128, 128, 255]));
        assert_eq!((masked.evaluated, masked.valid), (2, 2));
    }

    /// The default rig's pair from a built-in scenario's start, with `noise` grey levels.
    fn pair_at_start(scenario: &str, noise: f32, seed: u64) -> StereoPair {
        let scenario = Scenario::builtin(scenario).unwrap();
        let rig = StereoRig::default();
        let k = rig
            .render_intrinsics(&crate::sensors::camera::DepthCamera::default_thesis().intrinsics)
            .unwrap();
        assert_eq!((k.width(), k.height()), (200, 200));
        let pose = crate::sensors::camera::camera_pose(&scenario.start_position, scenario.start_yaw);
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        render_pair(&scenario.world, &k, &pose, rig.baseline_m, noise, &mut rng)
    }

    #[test]
    fn bands_give_exactly_the_whole_image_result() {
        let pair = pair_at_start("office", 1.0, 9);
        for (prefilter, window) in [
            (Prefilter::DEFAULT_DOG, 7),
            (Prefilter::None, 11),
            (Prefilter::DEFAULT_DOG, 3),
        ] {
            let params = StereoParams {
                prefilter,
                window,
                ..StereoParams::new(pair.width, pair.height, 48)
            };
            let whole = match_pair(
                params,
                &pair.left,
                &pair.right,
                &mut MatcherBuffers::new(&params).unwrap(),
            )
            .unwrap();
            assert!(whole.1.valid > 10_000 && whole.1.speckles > 0, "{:?}", whole.1);
            for bands in [2, 3, 5, 64] {
                let banded = match_pair_bands(params, &pair.left, &pair.right, bands).unwrap();
                assert_eq!(banded.1, whole.1, "{prefilter:?}, window {window}, {bands} bands");
                assert!(
                    banded.0 == whole.0,
                    "{prefilter:?}, window {window}, {bands} bands"
                );
            }
        }
        // Mismatched images are an error, not a panic.
        let params = StereoParams::new(pair.width, pair.height, 48);
        assert!(match_pair_bands(params, &pair.left[1..], &pair.right, 2).is_err());
    }

    #[test]
    fn rendered_pairs_are_textured_and_shifted_by_the_true_disparity() {
        let pair = pair_at_start("apartment", 0.0, 3);
        // Texture: neighbouring pixels differ.
        let steps = pair.left.windows(2).filter(|p| p[0] != p[1]).count();
        assert!(steps > pair.left.len() / 2, "{steps}");
        // Every pixel sees something (closed apartment); most are visible to both cameras.
        assert!(pair.disparity.iter().all(|d| d.is_finite() && *d > 0.5));
        let visible = pair.mask.iter().filter(|&&m| m == 255).count();
        assert!(visible > pair.left.len() * 8 / 10, "{visible}");
        // Noise-free: the right image at x − d matches the left at x, for visible pixels.
        let w = usize::from(pair.width);
        let (mut close, mut total) = (0, 0);
        for (i, &d) in pair.disparity.iter().enumerate() {
            let xr = ((i % w) as f32 - d).round();
            if pair.mask[i] != 255 || xr < 0.0 {
                continue;
            }
            total += 1;
            close += usize::from(pair.left[i].abs_diff(pair.right[i - (i % w) + xr as usize]) <= 20);
        }
        assert!(close * 10 >= total * 8, "{close} of {total}");
    }
}
