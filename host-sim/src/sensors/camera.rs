//! Simulated forward-looking depth camera: renders a [`World`] into the depth images the core
//! consumes (u16 millimetres of camera-frame z, 0 = no return), optionally with stereo noise.
//!
//! Frames: the camera frame is x right, y down, z forward; the vehicle body frame is x forward,
//! y left, z up; the map frame is z up. [`camera_pose`] builds the camera → map transform of a
//! level camera looking along the body's +x axis.

use harmonic_core::camera::Intrinsics;
use nalgebra::{Isometry3, Point3};
use rand::Rng;

use crate::world::World;

/// Rays are cast this far (metres) whatever the camera's range, so that hits beyond the maximum
/// range are reported and the core can clear free space up to its range along them.
pub const RAYCAST_LIMIT_M: f32 = 60.0;

/// Largest encodable depth, millimetres (`u16::MAX` is kept free as a sentinel).
pub const MAX_DEPTH_MM: u16 = u16::MAX - 1;

/// Stereo-matching noise: Gaussian disparity error, as a stereo depth camera has, and the
/// post-filter a stereo pipeline applies to it.
///
/// Depth `z` corresponds to disparity `d = fx · baseline / z`; the matcher measures `d` with
/// independent error `N(0, sigma_px)` per pixel. The pipeline then takes the median of the
/// valid disparities in a `filter_px` × `filter_px` window around each pixel (window
/// aggregation and speckle filtering do this in real matchers — SAD windows of 7–21 px in the
/// seed thesis; a 5 × 5 median cuts an independent error's σ about fourfold and keeps depth
/// edges), and quantises to 1/16 px (sub-pixel resolution of common matchers). Depth error
/// therefore grows with `z²`, and far surfaces drop out.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StereoNoise {
    /// Standard deviation of the per-pixel disparity error, pixels.
    pub sigma_px: f32,
    /// Distance between the two stereo cameras, metres.
    pub baseline_m: f32,
    /// Median window of the disparity post-filter, pixels (odd; 1 = none).
    pub filter_px: u8,
}

impl Default for StereoNoise {
    /// σ = 1 px, baseline 0.12 m, 5 × 5 median.
    fn default() -> Self {
        Self {
            sigma_px: 1.0,
            baseline_m: 0.12,
            filter_px: 5,
        }
    }
}

impl StereoNoise {
    /// Disparity at or below which the matcher gives no return, pixels.
    pub const MIN_DISPARITY_PX: f32 = 0.5;
    /// Disparity quantisation step, pixels.
    pub const DISPARITY_STEP_PX: f32 = 1.0 / 16.0;

    /// Standard deviation of the disparity error after the median filter, pixels: σ·1.25/w
    /// for a w × w window (the median of n normal samples has σ ≈ 1.25 σ / √n).
    pub fn filtered_sigma_px(&self) -> f32 {
        let w = f32::from(self.filter_px.max(1));
        if w <= 1.0 {
            self.sigma_px
        } else {
            self.sigma_px * 1.2533 / w
        }
    }

    /// The depth up to which this sensor's returns can be trusted: where the depth error a
    /// (filtered) disparity error causes, z²·σ / (fx·baseline), reaches `max_error_m`
    /// (Matthies' advice, which the seed thesis follows: distrust small disparities).
    /// Infinite for σ = 0.
    pub fn trusted_range(&self, fx: f32, max_error_m: f32) -> f32 {
        trusted_range(self.filtered_sigma_px(), fx, self.baseline_m, max_error_m)
    }

    /// Standard deviation of the depth error at depth `z`, metres (first order, filtered).
    pub fn depth_sigma(&self, z: f32, fx: f32) -> f32 {
        z * z * self.filtered_sigma_px() / (fx * self.baseline_m)
    }

    /// The measured disparity (before filtering) of a surface at true depth `z`.
    pub fn noisy_disparity(&self, z: f32, fx: f32, rng: &mut impl Rng) -> f32 {
        fx * self.baseline_m / z + self.sigma_px * standard_normal(rng)
    }

    /// Depth of a filtered disparity: quantised to 1/16 px; `None` if too small for a return.
    pub fn depth_of(&self, d: f32, fx: f32) -> Option<f32> {
        let d = (d / Self::DISPARITY_STEP_PX).round() * Self::DISPARITY_STEP_PX;
        (d > Self::MIN_DISPARITY_PX).then(|| fx * self.baseline_m / d)
    }

    /// The noisy depth measured for a surface at true depth `z` (metres), or `None` if the
    /// noisy disparity is too small to give a return.
    /// (One pixel, without the window filter.)
    pub fn perturb(&self, z: f32, fx: f32, rng: &mut impl Rng) -> Option<f32> {
        let d = self.noisy_disparity(z, fx, rng);
        self.depth_of(d, fx)
    }
}

/// One sample of N(0, 1) by the Box–Muller transform.
fn standard_normal(rng: &mut impl Rng) -> f32 {
    // u1 ∈ (0, 1] keeps the logarithm finite.
    let u1: f32 = 1.0 - rng.random::<f32>();
    let u2: f32 = rng.random::<f32>();
    (-2.0 * u1.ln()).sqrt() * (std::f32::consts::TAU * u2).cos()
}

/// A pinhole depth camera rendered by ray casting.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DepthCamera {
    /// Pinhole model; also sent to the core with every frame.
    pub intrinsics: Intrinsics,
    /// Closest valid depth, metres. Closer hits are still reported; the core rejects them.
    pub min_range: f32,
    /// Farthest valid depth, metres. Farther hits are still reported; the core treats them as
    /// free-space clearing up to this range.
    pub max_range: f32,
    /// Stereo noise, or `None` for exact depth.
    pub noise: Option<StereoNoise>,
    /// Fraction of pixels (0–1) that return half their true depth: gross matching errors
    /// (Gorodnichy's outlier scenario). With stereo noise they enter the matcher's disparity
    /// (twice the true one) before the pipeline's median filter.
    pub outliers: f32,
    /// Surfaces the world marks textureless return no depth (depth 0), as stereo finds no match
    /// on them.
    pub textureless: bool,
}

impl DepthCamera {
    /// The reference configuration: 100 × 100 px, 75° horizontal and vertical field of view,
    /// range 0.3–10 m, no noise.
    pub fn default_thesis() -> Self {
        let intrinsics = Intrinsics::from_hfov(100, 100, 75f32.to_radians())
            .expect("75° over 100 × 100 px are valid intrinsics");
        Self {
            intrinsics,
            min_range: 0.3,
            max_range: 10.0,
            noise: None,
            outliers: 0.0,
            textureless: false,
        }
    }

    /// True if the camera renders exact depth (no noise, outliers or textureless surfaces).
    pub fn is_exact(&self) -> bool {
        self.noise.is_none() && self.outliers <= 0.0 && !self.textureless
    }

    /// The same camera with the given noise model.
    pub fn with_noise(self, noise: Option<StereoNoise>) -> Self {
        Self { noise, ..self }
    }

    /// Renders the depth image seen from `camera_pose` (camera frame → map frame) into `out`
    /// (resized to width × height, row-major `v * width + u`).
    ///
    /// Each pixel holds the camera-frame z of the first surface along its ray in millimetres,
    /// rounded up so that the endpoint lies just inside the surface (and so inside the occupied
    /// voxel even when the surface lies on a voxel boundary); 0 where nothing is hit within
    /// [`RAYCAST_LIMIT_M`] or where stereo noise drops the return.
    pub fn render(
        &self,
        world: &World,
        camera_pose: &Isometry3<f32>,
        rng: &mut impl Rng,
        out: &mut Vec<u16>,
    ) {
        let k = &self.intrinsics;
        let (width, height) = (k.width(), k.height());
        out.clear();
        out.reserve(k.pixel_count());
        let rotation = camera_pose.rotation.to_rotation_matrix();
        let origin = Point3::from(camera_pose.translation.vector);
        // Pass 1: true depth (NaN: no return), or with stereo the matcher's disparity: noisy,
        // and for a fraction of pixels a gross mismatch at twice the disparity (half the depth).
        // Outliers are drawn only when enabled, so exact runs stay reproducible.
        let mut values = Vec::with_capacity(k.pixel_count());
        for v in 0..height {
            for u in 0..width {
                let ray_cam = k.ray(u, v);
                let norm = ray_cam.norm();
                let dir = rotation * (ray_cam / norm);
                let value = match world.raycast_hit(&origin, &dir, RAYCAST_LIMIT_M) {
                    Some(hit) if !(self.textureless && hit.textureless) => {
                        let z = hit.t / norm;
                        let outlier = self.outliers > 0.0 && rng.random::<f32>() < self.outliers;
                        match &self.noise {
                            Some(noise) if outlier => noise.noisy_disparity(0.5 * z, k.fx(), rng),
                            Some(noise) => noise.noisy_disparity(z, k.fx(), rng),
                            None if outlier => 0.5 * z,
                            None => z,
                        }
                    }
                    _ => f32::NAN,
                };
                values.push(value);
            }
        }
        // Pass 2: the stereo pipeline's median filter, then disparity → depth.
        let depth: Vec<f32> = match &self.noise {
            None => values,
            Some(noise) => {
                let filtered =
                    median_filter(&values, usize::from(width), usize::from(noise.filter_px.max(1)));
                filtered
                    .iter()
                    .map(|&d| {
                        if d.is_nan() {
                            f32::NAN
                        } else {
                            noise.depth_of(d, k.fx()).unwrap_or(f32::NAN)
                        }
                    })
                    .collect()
            }
        };
        out.extend(
            depth
                .iter()
                .map(|&z| if z.is_nan() { 0 } else { encode_depth_mm(z) }),
        );
    }
}

/// Depth (m) at which a disparity error of `sigma_px` moves the depth of a stereo pair with
/// focal length `fx` (px) and baseline `baseline_m` by `max_error_m`: `sqrt(max_error · fx · b /
/// σ)`, from z²·σ / (fx·b). Infinite for σ ≤ 0.
pub fn trusted_range(sigma_px: f32, fx: f32, baseline_m: f32, max_error_m: f32) -> f32 {
    if sigma_px <= 0.0 {
        return f32::INFINITY;
    }
    (max_error_m * fx * baseline_m / sigma_px).sqrt()
}

/// Median of the valid (non-NaN) values in a `window` × `window` neighbourhood of every valid
/// pixel; invalid pixels stay NaN. `window` 1 (or less) returns the input.
pub fn median_filter(values: &[f32], width: usize, window: usize) -> Vec<f32> {
    if window <= 1 || width == 0 {
        return values.to_vec();
    }
    let height = values.len() / width;
    let r = window / 2;
    let mut out = Vec::with_capacity(values.len());
    let mut buf = Vec::with_capacity(window * window);
    for v in 0..height {
        for u in 0..width {
            let centre = values[v * width + u];
            if centre.is_nan() {
                out.push(f32::NAN);
                continue;
            }
            buf.clear();
            for y in v.saturating_sub(r)..(v + r + 1).min(height) {
                for x in u.saturating_sub(r)..(u + r + 1).min(width) {
                    let d = values[y * width + x];
                    if !d.is_nan() {
                        buf.push(d);
                    }
                }
            }
            buf.sort_by(f32::total_cmp);
            out.push(buf[buf.len() / 2]);
        }
    }
    out
}

/// Millimetres for a depth in metres: rounded up, at least 1 (0 means no return) and at most
/// [`MAX_DEPTH_MM`].
pub fn encode_depth_mm(z: f32) -> u16 {
    let mm = (z * 1000.0).ceil();
    if mm >= f32::from(MAX_DEPTH_MM) {
        MAX_DEPTH_MM
    } else if mm >= 1.0 {
        mm as u16
    } else {
        1
    }
}

/// Camera → map pose of the forward-looking camera on a vehicle at `position` with heading
/// `yaw` (the core's convention, re-exported so simulator code and the core cannot disagree).
pub use harmonic_core::explore::forward_camera_pose as camera_pose;

#[cfg(test)]
mod tests {
    use super::*;
    use crate::world::Aabb;
    use nalgebra::Vector3;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    fn centre_ray_map(yaw: f32) -> Vector3<f32> {
        // 100 × 100 has no centre pixel; the mean of the four central rays is the optical axis.
        let cam = DepthCamera::default_thesis();
        let pose = camera_pose(&Point3::origin(), yaw);
        let sum: Vector3<f32> = [(49, 49), (49, 50), (50, 49), (50, 50)]
            .iter()
            .map(|&(u, v)| cam.intrinsics.ray(u, v))
            .sum();
        (pose.rotation * sum).normalize()
    }

    #[test]
    fn optical_axis_follows_yaw() {
        let x = centre_ray_map(0.0);
        assert!((x - Vector3::x()).norm() < 1e-5, "{x}");
        let y = centre_ray_map(90f32.to_radians());
        assert!((y - Vector3::y()).norm() < 1e-5, "{y}");
    }

    #[test]
    fn image_rows_go_down_and_columns_go_right() {
        let cam = DepthCamera::default_thesis();
        let pose = camera_pose(&Point3::origin(), 0.0);
        let top = pose.rotation * cam.intrinsics.ray(50, 0);
        assert!(top.z > 0.3, "{top}");
        let bottom = pose.rotation * cam.intrinsics.ray(50, 99);
        assert!(bottom.z < -0.3, "{bottom}");
        // Looking along +x with z up, the right edge of the image is towards −y.
        let right = pose.rotation * cam.intrinsics.ray(99, 50);
        assert!(right.y < -0.3, "{right}");
    }

    fn wall_ahead() -> World {
        // Wall face at x = 3 m, filling the view of a camera at x = 1.
        World::new(
            "wall",
            Aabb::from_arrays([-20.0, -20.0, -20.0], [20.0, 20.0, 20.0]),
            vec![Aabb::from_arrays([3.0, -20.0, -20.0], [3.2, 20.0, 20.0])],
        )
    }

    #[test]
    fn flat_wall_has_constant_depth() {
        let cam = DepthCamera::default_thesis();
        let pose = camera_pose(&Point3::new(1.0, 0.0, 1.0), 0.0);
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let mut depth = Vec::new();
        cam.render(&wall_ahead(), &pose, &mut rng, &mut depth);
        assert_eq!(depth.len(), 100 * 100);
        let centre = depth[50 * 100 + 50];
        assert!(centre == 2000 || centre == 2001, "{centre}");
        for &d in &depth {
            assert!(d.abs_diff(centre) <= 1, "{d} vs {centre}");
        }
    }

    #[test]
    fn noise_off_is_exact_and_deterministic() {
        let cam = DepthCamera::default_thesis();
        let pose = camera_pose(&Point3::new(1.0, 0.0, 1.0), 0.0);
        let mut a = Vec::new();
        let mut b = Vec::new();
        cam.render(&wall_ahead(), &pose, &mut ChaCha8Rng::seed_from_u64(1), &mut a);
        cam.render(&wall_ahead(), &pose, &mut ChaCha8Rng::seed_from_u64(2), &mut b);
        assert_eq!(a, b);
        // A corner pixel: its ray is longer than the axis but its z is the same 2 m.
        let corner = a[0];
        assert!(corner == 2000 || corner == 2001, "{corner}");
    }

    #[test]
    fn nothing_in_view_gives_no_return() {
        let cam = DepthCamera::default_thesis();
        let pose = camera_pose(&Point3::new(1.0, 0.0, 1.0), 180f32.to_radians());
        let mut depth = Vec::new();
        cam.render(
            &wall_ahead(),
            &pose,
            &mut ChaCha8Rng::seed_from_u64(1),
            &mut depth,
        );
        assert!(depth.iter().all(|&d| d == 0));
    }

    #[test]
    fn stereo_noise_is_unbiased_in_disparity_and_drops_far_returns() {
        let noise = StereoNoise::default();
        let fx = DepthCamera::default_thesis().intrinsics.fx();
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        let z = 2.0;
        let n = 4000;
        // True disparity ≈ 3.9 px; a 3.4 σ error drops a return now and then.
        let d: Vec<f32> = (0..n)
            .filter_map(|_| noise.perturb(z, fx, &mut rng))
            .map(|z| fx * noise.baseline_m / z)
            .collect();
        assert!(d.len() > n * 99 / 100, "{}", d.len());
        let mean_d = d.iter().sum::<f32>() / d.len() as f32;
        assert!((mean_d - fx * noise.baseline_m / z).abs() < 0.1, "{mean_d}");
        let var = d.iter().map(|x| (x - mean_d).powi(2)).sum::<f32>() / d.len() as f32;
        assert!((var.sqrt() - noise.sigma_px).abs() < 0.1, "{var}");
        // At 100 m the true disparity is ~0.08 px: most samples give no return.
        let dropped = (0..n)
            .filter(|_| noise.perturb(100.0, fx, &mut rng).is_none())
            .count();
        assert!(dropped > n / 2, "{dropped}");
    }

    #[test]
    fn trusted_range_bounds_the_depth_error() {
        let noise = StereoNoise::default();
        let fx = DepthCamera::default_thesis().intrinsics.fx();
        let r = noise.trusted_range(fx, 0.1);
        assert!((noise.depth_sigma(r, fx) - 0.1).abs() < 1e-4, "{r}");
        // σ = 1 px, 12 cm baseline, 65 px focal length, 5 × 5 median: 0.1 m of error at 1.8 m;
        // without the filter at 0.9 m.
        assert!((1.7..1.85).contains(&r), "{r}");
        let raw = StereoNoise {
            filter_px: 1,
            ..noise
        };
        assert!((0.85..0.95).contains(&raw.trusted_range(fx, 0.1)));
        let exact = StereoNoise {
            sigma_px: 0.0,
            ..noise
        };
        assert!(exact.trusted_range(fx, 0.2).is_infinite());
    }

    #[test]
    fn median_filter_cuts_the_depth_noise() {
        let pose = camera_pose(&Point3::new(1.0, 0.0, 1.0), 0.0);
        let spread = |filter_px: u8| {
            let cam = DepthCamera::default_thesis().with_noise(Some(StereoNoise {
                filter_px,
                ..StereoNoise::default()
            }));
            let mut depth = Vec::new();
            cam.render(
                &wall_ahead(),
                &pose,
                &mut ChaCha8Rng::seed_from_u64(5),
                &mut depth,
            );
            let z: Vec<f64> = depth
                .iter()
                .filter(|&&d| d > 0)
                .map(|&d| f64::from(d) / 1000.0)
                .collect();
            let mean = z.iter().sum::<f64>() / z.len() as f64;
            (z.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / z.len() as f64).sqrt()
        };
        let (raw, filtered) = (spread(1), spread(5));
        // At 2 m: σ_z ≈ 0.5 m raw; the 5 × 5 median should cut it at least threefold.
        assert!(raw > 0.3, "{raw}");
        assert!(filtered < raw / 3.0, "{filtered} vs {raw}");
    }

    #[test]
    fn outliers_return_half_the_depth_and_textureless_boxes_none() {
        let mut cam = DepthCamera::default_thesis();
        let pose = camera_pose(&Point3::new(1.0, 0.0, 1.0), 0.0);
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let mut depth = Vec::new();
        cam.outliers = 0.25;
        cam.render(&wall_ahead(), &pose, &mut rng, &mut depth);
        let halves = depth.iter().filter(|&&d| d <= 1001).count();
        let fulls = depth.iter().filter(|&&d| d >= 2000).count();
        assert_eq!(halves + fulls, depth.len());
        assert!((2000..3000).contains(&halves), "{halves}");
        cam.outliers = 0.0;
        let mut world = wall_ahead();
        world.textureless = vec![true];
        cam.render(&world, &pose, &mut rng, &mut depth);
        assert!(
            depth.iter().all(|&d| d >= 2000),
            "textureless ignored unless enabled"
        );
        cam.textureless = true;
        cam.render(&world, &pose, &mut rng, &mut depth);
        assert!(depth.iter().all(|&d| d == 0));
    }

    #[test]
    fn depth_encoding_rounds_up_and_saturates() {
        assert_eq!(encode_depth_mm(2.0), 2000);
        assert_eq!(encode_depth_mm(1.9995), 2000);
        assert_eq!(encode_depth_mm(0.0), 1);
        assert_eq!(encode_depth_mm(1000.0), MAX_DEPTH_MM);
    }

    /// Upper bound on exploration coverage: the share of free voxels that the reference
    /// camera sees from reachable viewpoints on a 0.5 m grid at eye height (1.25 m above
    /// each storey's floor, i.e. at z = 1.25 m and 3.75 m) looking in eight directions.
    /// Regions no viewpoint sees would need the vehicle to change altitude to be covered,
    /// or could not be covered at all. Slow (≈ 30 s); run with
    /// `cargo test -p harmonic-sim --lib -- --ignored --nocapture visible`.
    #[test]
    #[ignore]
    fn builtin_free_space_is_visible() {
        use crate::world::scenario::tests::builtin_geometry::{
            builtins, occupancy, reachable_centres, trace,
        };
        use nalgebra::Point3;
        use rand::SeedableRng;

        for s in builtins() {
            let dims = s.grid_dims();
            let r = s.resolution;
            let occupied = occupancy(&s);
            let reach = reachable_centres(&s);
            let mut viewpoints = Vec::new();
            for z in 0..dims[2] {
                for y in 0..dims[1] {
                    for x in 0..dims[0] {
                        // 0.1 m voxels: voxel 12 of every 25 (2.5 m) is eye height.
                        let eye_height = z % 25 == 12;
                        if eye_height && x % 5 == 2 && y % 5 == 2 && reach[x + dims[0] * (y + dims[1] * z)] {
                            let p = Point3::new(x as f32 + 0.5, y as f32 + 0.5, z as f32 + 0.5) * r;
                            viewpoints.push(p);
                        }
                    }
                }
            }
            let cam = DepthCamera::default_thesis();
            let k = cam.intrinsics;
            let observe = |points: &[Point3<f32>]| {
                let mut seen = vec![false; occupied.len()];
                let mut depth = Vec::new();
                let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0);
                for p in points {
                    for heading in 0..8 {
                        let pose = camera_pose(p, heading as f32 * std::f32::consts::FRAC_PI_4);
                        cam.render(&s.world, &pose, &mut rng, &mut depth);
                        for vv in 0..k.height() {
                            for u in 0..k.width() {
                                let ray = k.ray(u, vv);
                                let z = f32::from(
                                    depth[usize::from(vv) * usize::from(k.width()) + usize::from(u)],
                                ) / 1000.0;
                                if z > 0.0 && z < cam.min_range {
                                    continue;
                                }
                                let z = if z == 0.0 {
                                    cam.max_range
                                } else {
                                    z.min(cam.max_range)
                                };
                                let dir = pose.rotation * ray;
                                trace(p, &dir.normalize(), z * ray.norm(), r, dims, &mut seen);
                            }
                        }
                    }
                }
                seen
            };
            let (a, b) = viewpoints.split_at(viewpoints.len() / 2);
            let (sa, sb) = std::thread::scope(|scope| {
                let ha = scope.spawn(|| observe(a));
                let sb = observe(b);
                (ha.join().unwrap(), sb)
            });
            let free = occupied.iter().filter(|&&o| !o).count();
            let mut unseen_by_metre = std::collections::BTreeMap::<[usize; 3], usize>::new();
            for i in 0..occupied.len() {
                if !occupied[i] && !sa[i] && !sb[i] {
                    let (x, y, z) = (i % dims[0], (i / dims[0]) % dims[1], i / (dims[0] * dims[1]));
                    *unseen_by_metre.entry([x / 10, y / 10, z / 10]).or_default() += 1;
                }
            }
            let unseen: usize = unseen_by_metre.values().sum();
            let coverage = 1.0 - unseen as f64 / free as f64;
            println!(
                "{}: {} viewpoints, {free} free voxels, {unseen} never seen, coverage bound {:.2} %",
                s.name(),
                viewpoints.len(),
                100.0 * coverage
            );
            let mut worst: Vec<_> = unseen_by_metre.into_iter().collect();
            worst.sort_by_key(|&(_, n)| std::cmp::Reverse(n));
            for (m, n) in worst.iter().take(8) {
                println!("    {n:5} unseen in the metre cell at {m:?}");
            }
            assert!(coverage > 0.995, "{}: coverage bound {coverage}", s.name());
        }
    }
}
