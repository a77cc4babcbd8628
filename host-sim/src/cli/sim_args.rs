//! Flags shared by `explore` and `bench`: imperfect sensing ([`SensingArgs`]) and the
//! harmonic planner's field ([`FieldArgs`]), both flattened into their argument structs.

use harmonic_core::field::PlanningField;
use harmonic_sim::run::sim::{self, SimConfig};
use harmonic_sim::sensors::camera::StereoNoise;
use harmonic_sim::sensors::faults::DriftConfig;

use super::parse::{
    parse_drift, parse_grid_offset, parse_noise, parse_non_negative, parse_positive, parse_probability,
    parse_radius,
};

/// Imperfect sensing, for `explore` and `bench`.
#[derive(clap::Args, Clone)]
pub struct SensingArgs {
    /// Sensor noise model: `stereo` (σ = 1 px disparity noise per pixel, then the stereo
    /// pipeline's 5 × 5 median), `stereo:SIGMA_PX` or `stereo:SIGMA_PX:FILTER_PX` (odd median
    /// window, 1 = unfiltered). The core integrates it with its stereo sensor model, a surface
    /// estimate and the median's window as the pipeline's (`--depth-rules surface`) unless
    /// `--depth-rules` says otherwise.
    #[arg(long, value_parser = parse_noise)]
    noise: Option<StereoNoise>,
    /// How noisy depth is integrated: `exact` (the rules of exact depth, up to
    /// `--trusted-range`), `model` (the core's stereo sensor model: depth error
    /// σ_z = z²σ_d/(f·b), misses stop 2σ short of a return, a return marks a surface only where
    /// σ is at most a voxel, a hit/miss vote per voxel per frame, depth used to the camera's
    /// range; also the window of the pipeline, the matcher's with `--depth-from stereo` and the
    /// median's with `--noise`: slanted surfaces are less certain, returns whose slant cannot be
    /// measured are left out, and none clears deeper than the nearest depth within half the
    /// window) or `surface` (the
    /// model, and every planner's map keeps a surface estimate across frames: 8 bytes per voxel
    /// on the host). Default: `surface`, with `--noise` and with `--depth-from stereo`
    /// (docs/RESULTS.md, "The stereo sensor model" and after; "The rules for `--noise`").
    #[arg(long, value_enum)]
    depth_rules: Option<DepthRules>,
    /// Same as `--depth-rules model` (with `--surface-estimate`: `--depth-rules surface`).
    #[arg(long)]
    stereo_model: bool,
    /// With `--stereo-model`: same as `--depth-rules surface`.
    #[arg(long)]
    surface_estimate: bool,
    /// Range (m) up to which depth is integrated; farther returns only clear free space.
    /// Default with `--noise --depth-rules exact`: where a 1σ (filtered) disparity error moves
    /// the depth by 0.1 m (one voxel): 1.8 m at σ = 1 px with the 5 × 5 median, 0.9 m
    /// unfiltered; 2.8 m with `--depth-from stereo --depth-rules exact`. Otherwise, and with the
    /// stereo model, the camera's 10 m.
    #[arg(long, value_parser = parse_positive)]
    trusted_range: Option<f32>,
    /// Fraction of pixels (0-1) that return half their true depth (gross matching errors).
    #[arg(long, default_value_t = 0.0, value_parser = parse_probability)]
    outliers: f64,
    /// Boxes the scenario marks `textureless = true` return no depth.
    #[arg(long)]
    textureless: bool,
    /// Pose drift: random walk per keyframe, `SIGMA_POS_M,SIGMA_YAW_RAD` (e.g. 0.1,0.015).
    #[arg(long, value_parser = parse_drift)]
    drift: Option<DriftConfig>,
    /// Depth source: `camera` (the depth camera, with `--noise` if given) or `stereo` (a
    /// textured stereo pair rendered at each scan, 2x the camera's resolution with a 0.12 m
    /// baseline, matched by the core's block matcher; pixels without a match are unknown, not
    /// free; integrated with `--depth-rules surface` unless told otherwise).
    #[arg(long, default_value = "camera", value_parser = ["camera", "stereo"])]
    depth_from: String,
    /// With `--depth-from stereo`: rendering resolution as a multiple of the 100x100 camera.
    #[arg(long, default_value_t = 2)]
    stereo_scale: u16,
    /// With `--depth-from stereo`: the matcher's window (odd, 3-15).
    #[arg(long, default_value_t = 7)]
    stereo_window: u8,
    /// With `--noise` and the sensor model: the stereo pipeline's aggregation window, in pixels
    /// of the depth frame, which the model takes as its footprint (see `--depth-rules`)
    /// [default: the median's width, 5; 0: none, as before 2026-12-06].
    #[arg(long, value_parser = parse_non_negative)]
    pipeline_window: Option<f32>,
    /// Move the map's voxel grid `X,Y,Z` metres (each below the voxel size) against the world.
    /// The built-in worlds put every surface on a voxel face, the best case for exact depth and
    /// the worst for noisy depth (a return within σ of a face lands in either voxel); a real
    /// map's grid lies anywhere. Runs start from the same poses.
    #[arg(long, value_parser = parse_grid_offset)]
    grid_offset: Option<[f32; 3]>,
}

/// How noisy depth is integrated (`--depth-rules`).
#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum DepthRules {
    /// The rules of exact depth, up to the trusted range.
    Exact,
    /// The core's stereo sensor model.
    Model,
    /// The stereo sensor model with a surface estimate kept across frames.
    Surface,
}

/// The vehicle's size: how far planning keeps from obstacles, and what counts as a collision.
#[derive(clap::Args)]
pub struct BodyArgs {
    /// Vehicle radius in metres: obstacles are inflated by this much for planning [default:
    /// 0.2; 0.25 with the stereo model (`--depth-rules model` or `surface`, the default with
    /// `--noise` and `--depth-from stereo`), which maps surfaces at their true thickness].
    #[arg(long, value_parser = parse_radius)]
    vehicle_radius: Option<f32>,
    /// Radius of the vehicle body for collision counting, metres.
    #[arg(long, default_value_t = 0.15, value_parser = parse_positive)]
    body_radius: f32,
    /// Doorways stay open under noise: occupied voxels with a log-odds below this are doubtful,
    /// and before an exploration ends, a frontier cut off by doubtful voxels alone has them
    /// forgotten and looked at again (every planner; harmonic_core::domain::Reopening). 0 turns
    /// it off [default: 1.0].
    #[arg(long)]
    doubtful_log_odds: Option<f32>,
}

impl BodyArgs {
    /// Puts the planning radius (if given; after [`SensingArgs::apply`], which may widen the
    /// default) and the body radius into `cfg`.
    pub fn apply(&self, cfg: &mut SimConfig) {
        if let Some(r) = self.vehicle_radius {
            cfg.explorer.vehicle_radius = r;
        }
        cfg.body_radius = self.body_radius;
        if let Some(d) = self.doubtful_log_odds {
            cfg.explorer.doubtful_log_odds = d;
        }
    }
}

/// Settings of the `harmonic` planner's default field (harmonic_core::field).
#[derive(clap::Args)]
pub struct FieldArgs {
    /// Decay length 1/κ of the screened, frontier-sourced field of `--planner harmonic`, in
    /// metres: how much nearness outweighs frontier size (small: the nearest frontier wins;
    /// large: the largest frontier region wins).
    #[arg(long, value_parser = parse_positive)]
    decay_length: Option<f32>,
    /// The value of the screened field at the vehicle that a lowered κ aims for when the
    /// nearest frontier is far (it accepts down to a tenth of it): the smaller, the longer
    /// the field stays local and visits remnants nearest first (default 1e-4; 1e-2 was the
    /// first setting, see docs/RESULTS.md).
    #[arg(long, value_parser = parse_positive)]
    vehicle_value: Option<f32>,
    /// Look from a distance: the core's goal is the first point of its streamline from which
    /// the frontier is in plain sight within this range (metres); 0 flies up to it.
    #[arg(long)]
    view_range: Option<f32>,
    /// Look around on arrival: at each goal every planner turns on the spot up to this many
    /// times, each to the heading (of eight) that sees the most unexplored space, before it
    /// plans the next goal (default 0: none). Shorter paths, much longer flights (see
    /// docs/RESULTS.md, "Looking around on arrival").
    #[arg(long)]
    arrival_looks: Option<u8>,
    /// Ablation: closest and random frontier choose their goal by the core's view rule (the
    /// first point of the path from which the frontier is in plain sight within the view
    /// range) instead of the thesis's (fly up to it).
    #[arg(long)]
    baseline_views: bool,
    /// Remnants: while the vehicle's part of the map holds at most this much frontier (square
    /// metres' worth of frontier voxels), a target farther than `--remnant-reach` along its path
    /// is sealed instead of flown to, whatever the planner (default 0.5; 0 turns it off, flying
    /// to every crumb, as the thesis's planners did).
    #[arg(long, value_parser = parse_non_negative)]
    remnant_area: Option<f32>,
    /// Remnants: how far along its path (metres) a remnant target may be and still be flown to
    /// (default 3).
    #[arg(long, value_parser = parse_positive)]
    remnant_reach: Option<f32>,
    /// Ablation: the core flies its streamline's own curve instead of pulling it taut through
    /// the safe space (same goal, same frontier).
    #[arg(long)]
    raw_streamline: bool,
    /// Plan on a grid this many times coarser than the map (1 or 2; default 1): frames are
    /// integrated at the scenario's resolution and the domain, field and streamline work on
    /// cells pooled from it (occupied if any voxel is, unknown if any is, free only if all
    /// are): an eighth of the planning memory and work at 2. The firmware plans this way.
    #[arg(long, value_parser = clap::value_parser!(u8).range(1..=2))]
    plan_coarsening: Option<u8>,
}

impl FieldArgs {
    /// Set the field flags given on `cfg`.
    pub fn apply(&self, cfg: &mut SimConfig) {
        if let (Some(d), PlanningField::Screened(p)) = (self.decay_length, &mut cfg.explorer.field) {
            p.decay_length_m = d;
        }
        if let (Some(u), PlanningField::Screened(p)) = (self.vehicle_value, &mut cfg.explorer.field) {
            p.target_vehicle_value = u.min(0.5);
            p.min_vehicle_value = 0.1 * p.target_vehicle_value;
        }
        if let Some(r) = self.view_range {
            cfg.explorer.view_range_m = r.max(0.0);
        }
        if let Some(n) = self.arrival_looks {
            cfg.explorer.arrival_looks = n;
        }
        cfg.baseline_views = self.baseline_views;
        if let Some(a) = self.remnant_area {
            cfg.explorer.remnant_frontier_m2 = a;
        }
        if let Some(d) = self.remnant_reach {
            cfg.explorer.remnant_reach_m = d;
        }
        if self.raw_streamline {
            cfg.explorer.taut_path = false;
        }
        if let Some(f) = self.plan_coarsening {
            cfg.explorer.plan_coarsening = f;
        }
    }
}

impl SensingArgs {
    /// Refuse combinations of the sensing flags that do not go together.
    pub fn check(&self) -> Result<(), String> {
        if self.depth_rules.is_some() && (self.stereo_model || self.surface_estimate) {
            return Err(
                "--stereo-model and --surface-estimate are short for --depth-rules: give one or the other"
                    .into(),
            );
        }
        if self.surface_estimate && !self.stereo_model {
            return Err("--surface-estimate is part of the stereo sensor model: give --stereo-model".into());
        }
        let noisy = self.noise.is_some() || self.depth_from == "stereo";
        if self.rules() != DepthRules::Exact && !noisy {
            return Err(
                "--depth-rules (or --stereo-model) chooses how noisy depth is integrated: give --noise or --depth-from stereo"
                    .into(),
            );
        }
        if self.pipeline_window.is_some() && (self.noise.is_none() || self.rules() == DepthRules::Exact) {
            return Err(
                "--pipeline-window is the sensor model's footprint for --noise: give --noise without --depth-rules exact (the matcher's is --stereo-window)"
                    .into(),
            );
        }
        if self.depth_from == "stereo" && (self.noise.is_some() || self.outliers > 0.0 || self.textureless) {
            return Err(
                "--noise, --outliers and --textureless model the depth camera; with --depth-from stereo the matcher makes its own errors (textureless boxes render flat)".into(),
            );
        }
        Ok(())
    }

    /// The depth rules the flags choose (`--depth-rules`, its short forms, or the default for
    /// the depth source).
    pub fn rules(&self) -> DepthRules {
        match (self.depth_rules, self.stereo_model, self.surface_estimate) {
            (Some(rules), _, _) => rules,
            (None, true, true) => DepthRules::Surface,
            (None, true, false) => DepthRules::Model,
            (None, false, _) if self.depth_from == "stereo" || self.noise.is_some() => DepthRules::Surface,
            (None, false, _) => DepthRules::Exact,
        }
    }

    /// Set the camera, pose drift and depth integration of `cfg` from the sensing flags.
    pub fn apply(&self, cfg: &mut SimConfig) {
        let rules = self.rules();
        let model = rules != DepthRules::Exact;
        cfg.camera = cfg.camera.with_noise(self.noise);
        cfg.camera.outliers = self.outliers as f32;
        cfg.camera.textureless = self.textureless;
        cfg.drift = self.drift;
        cfg.grid_offset = self.grid_offset.unwrap_or([0.0; 3]);
        cfg.surface_estimate = rules == DepthRules::Surface;
        // Exact depth: no error (the camera's range unless --trusted-range).
        let (sigma_px, baseline_m) = self
            .noise
            .map_or((0.0, 1.0), |n| (n.filtered_sigma_px(), n.baseline_m));
        let fx = cfg.camera.intrinsics.fx();
        sim::integrate_noisy_depth(cfg, sigma_px, fx, baseline_m, self.trusted_range, model);
        if let (Some(noise), true) = (self.noise, model) {
            sim::use_pipeline_window(cfg, noise, self.pipeline_window);
        }
        if self.depth_from == "stereo" {
            let rig = harmonic_sim::sensors::stereo::StereoRig {
                scale: self.stereo_scale,
                window: self.stereo_window,
                ..harmonic_sim::sensors::stereo::StereoRig::default()
            };
            sim::use_stereo_depth(cfg, rig, self.trusted_range, model);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser;

    #[derive(Parser)]
    struct Args {
        #[command(flatten)]
        sensing: SensingArgs,
    }

    fn rules(args: &[&str]) -> DepthRules {
        let a = Args::try_parse_from(std::iter::once("explore").chain(args.iter().copied())).unwrap();
        a.sensing.check().unwrap();
        a.sensing.rules()
    }

    #[test]
    fn noisy_depth_defaults_to_the_surface_rules_and_exact_depth_to_exact_ones() {
        assert_eq!(rules(&[]), DepthRules::Exact);
        assert_eq!(rules(&["--noise", "stereo"]), DepthRules::Surface);
        assert_eq!(
            rules(&["--noise", "stereo", "--depth-rules", "exact"]),
            DepthRules::Exact
        );
        assert_eq!(rules(&["--depth-from", "stereo"]), DepthRules::Surface);
        assert_eq!(
            rules(&["--depth-from", "stereo", "--depth-rules", "exact"]),
            DepthRules::Exact
        );
        // The short forms keep their meaning.
        assert_eq!(
            rules(&["--depth-from", "stereo", "--stereo-model"]),
            DepthRules::Model
        );
        assert_eq!(
            rules(&["--noise", "stereo", "--stereo-model", "--surface-estimate"]),
            DepthRules::Surface
        );
        // The rules reach the simulator's configuration: the surface estimate's storage, the
        // sensor model's depth noise and the window (the matcher's, or the pipeline's 5 × 5
        // median for the depth camera's noise; none unfiltered).
        for (args, surface, model, window) in [
            (&["--depth-from", "stereo"][..], true, true, 3.5),
            (
                &["--depth-from", "stereo", "--depth-rules", "exact"],
                false,
                false,
                0.0,
            ),
            (&["--noise", "stereo"], true, true, 5.0),
            (
                &["--noise", "stereo", "--depth-rules", "exact"],
                false,
                false,
                0.0,
            ),
            (&["--noise", "stereo:1:1"], true, true, 0.0),
            (&["--noise", "stereo", "--pipeline-window", "0"], true, true, 0.0),
            (
                &[
                    "--noise",
                    "stereo",
                    "--depth-rules",
                    "model",
                    "--pipeline-window",
                    "3",
                ],
                false,
                true,
                3.0,
            ),
        ] {
            let mut cfg = SimConfig::default();
            let a = Args::try_parse_from(std::iter::once("explore").chain(args.iter().copied())).unwrap();
            a.sensing.check().unwrap();
            a.sensing.apply(&mut cfg);
            assert_eq!(cfg.surface_estimate, surface, "{args:?}");
            assert_eq!(
                cfg.explorer.integration.depth_noise_per_m > 0.0,
                model,
                "{args:?}"
            );
            assert_eq!(cfg.explorer.integration.footprint_px, window, "{args:?}");
            if model {
                // The model uses depth to the camera's range.
                assert_eq!(
                    cfg.explorer.integration.max_range, cfg.camera.max_range,
                    "{args:?}"
                );
            }
        }
        // The pipeline's window belongs to the depth camera's noise under the model.
        for args in [
            &["--pipeline-window", "3"][..],
            &[
                "--noise",
                "stereo",
                "--depth-rules",
                "exact",
                "--pipeline-window",
                "3",
            ],
            &["--depth-from", "stereo", "--pipeline-window", "3"],
        ] {
            let a = Args::try_parse_from(std::iter::once("explore").chain(args.iter().copied())).unwrap();
            assert!(a.sensing.check().is_err(), "{args:?}");
        }
    }
}
