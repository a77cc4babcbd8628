//! Every fault the simulator injects besides the depth link's (`crate::link::fault`), in one
//! place: what `harmonic-sim faults` varies, and the pose errors of a drifting estimate.
//!
//! - [`SimFaults`]: depth pixels that read nothing or a random depth
//!   ([`SimFaults::corrupt_depth`]), a believed position that drifts from the truth at a
//!   constant rate ([`SimFaults::drift_at`]), and a pose stream that falls silent for a while
//!   ([`SimFaults::outage_at`]).
//! - [`Drift`]: the pose the core believes wanders from the truth by a random walk, one step
//!   per keyframe (every integrated scan): a translation with N(0, σ_pos) per axis and a yaw
//!   rotation N(0, σ_yaw) about the vehicle (Ziegler 2018 uses 0.1 m and 0.015 rad). Frames
//!   are stamped and plans made in the believed frame; the vehicle flies the plan, so it moves
//!   in the true world by the believed displacement.
//!
//! The camera's own noise model (stereo-like depth noise, `--outliers`, textureless surfaces)
//! is the camera's ([`crate::sensors::camera`]): it is what the sensor measures, not a fault.

use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::Serialize;

use crate::sensors::camera::DepthCamera;

/// Faults the simulator injects besides the depth link's: what `harmonic-sim faults` varies.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct SimFaults {
    /// Probability that a depth pixel reads 0 (no return) although it saw something.
    pub sensor_dropout: f64,
    /// Probability that a depth pixel reads a uniformly random depth in the camera's range.
    pub sensor_outlier: f64,
    /// Pose drift: the position the core is told moves away from the truth at this rate, m/s
    /// (along the map's x = y diagonal). The vehicle flies the setpoints in the believed frame.
    pub pose_drift_m_per_s: f32,
    /// A stale pose stream: over MAVLink, the autopilot sends nothing from `start` for
    /// `duration` seconds of simulated time.
    pub pose_outage_s: Option<(f64, f64)>,
}

impl SimFaults {
    /// Sensor dropouts (0, no return) and outliers (a random depth in `camera`'s range), drawn
    /// per pixel of `depth` from `rng` (no draw without them).
    pub fn corrupt_depth(&self, camera: &DepthCamera, rng: &mut ChaCha8Rng, depth: &mut [u16]) {
        if self.sensor_dropout <= 0.0 && self.sensor_outlier <= 0.0 {
            return;
        }
        let (lo, hi) = (camera.min_range * 1000.0, camera.max_range * 1000.0);
        for d in depth.iter_mut() {
            let u: f64 = rng.random();
            if u < self.sensor_dropout {
                *d = 0;
            } else if u < self.sensor_dropout + self.sensor_outlier {
                *d = rng.random_range(lo..hi) as u16;
            }
        }
    }

    /// Believed minus true position after `t_s` seconds of the constant drift.
    pub fn drift_at(&self, t_s: f64) -> Vector3<f32> {
        let d = self.pose_drift_m_per_s * t_s as f32 * std::f32::consts::FRAC_1_SQRT_2;
        Vector3::new(d, d, 0.0)
    }

    /// True while the injected pose outage silences the autopilot, at `t_s` seconds.
    pub fn outage_at(&self, t_s: f64) -> bool {
        self.pose_outage_s
            .is_some_and(|(start, duration)| t_s >= start && t_s < start + duration)
    }
}

/// Random-walk pose drift per keyframe.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DriftConfig {
    /// Standard deviation of the translation step per axis and keyframe, metres.
    pub sigma_position_m: f32,
    /// Standard deviation of the yaw step per keyframe, radians.
    pub sigma_yaw_rad: f32,
}

/// The believed pose's error: believed = offset · true.
#[derive(Debug, Clone)]
pub struct Drift {
    config: DriftConfig,
    offset: Isometry3<f32>,
    rng: ChaCha8Rng,
    keyframes: u32,
}

fn normal(rng: &mut ChaCha8Rng) -> f32 {
    let u1: f32 = 1.0 - rng.random::<f32>();
    let u2: f32 = rng.random::<f32>();
    (-2.0 * u1.ln()).sqrt() * (std::f32::consts::TAU * u2).cos()
}

impl Drift {
    /// No drift yet; steps drawn from `seed`.
    pub fn new(config: DriftConfig, seed: u64) -> Self {
        Self {
            config,
            offset: Isometry3::identity(),
            rng: ChaCha8Rng::seed_from_u64(seed ^ 0xd21f_7000_0000_0001),
            keyframes: 0,
        }
    }

    /// The believed position and yaw of a vehicle truly at `position` with `yaw`.
    pub fn believed(&self, position: &Point3<f32>, yaw: f32) -> (Point3<f32>, f32) {
        (
            self.offset * position,
            yaw + self.offset.rotation.euler_angles().2,
        )
    }

    /// The true point of a believed one.
    pub fn to_true(&self, p: &Point3<f32>) -> Point3<f32> {
        self.offset.inverse_transform_point(p)
    }

    /// The true yaw of a believed one.
    pub fn to_true_yaw(&self, yaw: f32) -> f32 {
        yaw - self.offset.rotation.euler_angles().2
    }

    /// One keyframe: a random step of the walk, the rotation about the vehicle's believed
    /// position `about`.
    pub fn keyframe(&mut self, about: &Point3<f32>) {
        let c = self.config;
        let t = Vector3::new(
            normal(&mut self.rng),
            normal(&mut self.rng),
            normal(&mut self.rng),
        ) * c.sigma_position_m;
        let yaw = normal(&mut self.rng) * c.sigma_yaw_rad;
        let r = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), yaw);
        // Rotate about `about`, then translate.
        let about_v = about.coords;
        let step = Isometry3::from_parts(Translation3::from(about_v + t - r * about_v), r);
        self.offset = step * self.offset;
        self.keyframes += 1;
    }

    /// Position error (metres) of the believed pose at true `position`, and yaw error (rad).
    pub fn error_at(&self, position: &Point3<f32>) -> (f32, f32) {
        let (p, _) = self.believed(position, 0.0);
        ((p - position).norm(), self.offset.rotation.euler_angles().2.abs())
    }

    /// Keyframes so far.
    pub fn keyframes(&self) -> u32 {
        self.keyframes
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn drift_walks_and_maps_back() {
        let mut d = Drift::new(
            DriftConfig {
                sigma_position_m: 0.1,
                sigma_yaw_rad: 0.015,
            },
            1,
        );
        let p = Point3::new(2.0, 3.0, 1.0);
        assert_eq!(d.error_at(&p), (0.0, 0.0));
        for _ in 0..100 {
            d.keyframe(&p);
        }
        let (e, y) = d.error_at(&p);
        // A 100-step walk of 0.1 m per axis: about 0.1·√(100·3) ≈ 1.7 m.
        assert!(e > 0.2 && e < 6.0, "{e}");
        assert!(y > 0.0 && y < 1.0, "{y}");
        let (b, by) = d.believed(&p, 0.5);
        assert!((d.to_true(&b) - p).norm() < 1e-4);
        assert!((d.to_true_yaw(by) - 0.5).abs() < 1e-5);
    }

    #[test]
    fn sensor_faults_draw_nothing_when_off_and_count_what_they_do() {
        let camera = DepthCamera::default_thesis();
        let mut depth = vec![1500u16; 10_000];
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        SimFaults::default().corrupt_depth(&camera, &mut rng, &mut depth);
        assert!(depth.iter().all(|&d| d == 1500));
        assert_eq!(
            rng.random::<u64>(),
            ChaCha8Rng::seed_from_u64(3).random::<u64>(),
            "no draw"
        );
        let faults = SimFaults {
            sensor_dropout: 0.1,
            ..SimFaults::default()
        };
        faults.corrupt_depth(&camera, &mut rng, &mut depth);
        let dropped = depth.iter().filter(|&&d| d == 0).count();
        assert!((800..1200).contains(&dropped), "{dropped} of 10 000 at 10 %");
        let drift = SimFaults {
            pose_drift_m_per_s: 2.0,
            pose_outage_s: Some((5.0, 2.0)),
            ..SimFaults::default()
        };
        assert!(
            (drift.drift_at(10.0).norm() - 20.0).abs() < 1e-4,
            "2 m/s for 10 s"
        );
        assert!(
            !drift.outage_at(4.9) && drift.outage_at(5.0) && drift.outage_at(6.9) && !drift.outage_at(7.0)
        );
    }
}
