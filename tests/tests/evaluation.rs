//! The evaluation suite end to end: every baseline explores a small world to completion, a
//! tiny bench of every planner runs (sharded and merged), a recorded run replays to the same
//! map, and noisy stereo no longer ends exploration early.

use std::path::{Path, PathBuf};

use harmonic_core::explore::ExplorerConfig;
use harmonic_sim::planners::PlannerKind;
use harmonic_sim::run::record::{self, MapSettings, Recorder, ReplayConfig};
use harmonic_sim::run::sim::{self, SimConfig};
use harmonic_sim::tools::batch::{self, BenchConfig};
use harmonic_sim::world::scenario::Scenario;

fn fixture(name: &str) -> String {
    format!(
        "{}/../host-sim/scenarios/fixtures/{name}.toml",
        env!("CARGO_MANIFEST_DIR")
    )
}

fn temp_dir(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("harmonic-eval-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

#[test]
fn each_baseline_completes_a_small_scenario() {
    let scenario = Scenario::load(fixture("two-rooms")).unwrap();
    for kind in [
        PlannerKind::RandomFrontier,
        PlannerKind::ClosestFrontier,
        PlannerKind::InfoGain,
        PlannerKind::WeightedInfoGain,
    ] {
        let cfg = SimConfig {
            planner: kind,
            ..SimConfig::default()
        };
        let r = sim::run(&scenario, &cfg, |_| {}).unwrap();
        assert_eq!(r.planner, kind.name());
        assert_eq!(r.solver, "none");
        assert_eq!(r.termination, "complete", "{kind}: {:?}", r.errors);
        assert!(r.coverage_free >= 0.97, "{kind}: coverage {}", r.coverage_free);
        assert_eq!(r.collisions, 0, "{kind}: {:?}", r.collision_points);
        assert!(r.path_length_m > 2.0, "{kind}: {} m", r.path_length_m);
        assert!(r.planning_ops > 0, "{kind}");
        // The baselines plan on the map the core's integrator fills: every scan reached it.
        assert_eq!(r.link.depth_frames_integrated, r.scans);
    }
}

#[test]
fn a_grid_offset_moves_the_map_against_the_world_and_exploration_still_completes() {
    let scenario = Scenario::load(fixture("two-rooms")).unwrap();
    let aligned = sim::scenario_geometry(&scenario, [0.0; 3]).unwrap();
    let moved = sim::scenario_geometry(&scenario, [0.05, 0.0, 0.025]).unwrap();
    let (a, m) = (aligned.dims(), moved.dims());
    // One voxel more along each axis the grid moved, so it still covers the bounds.
    assert_eq!([m.nx(), m.ny(), m.nz()], [a.nx() + 1, a.ny(), a.nz() + 1]);
    let shift = aligned.origin() - moved.origin();
    assert!(
        (shift - nalgebra::Vector3::new(0.05, 0.0, 0.025)).norm() < 1e-6,
        "{shift:?}"
    );
    for bad in [[0.1, 0.0, 0.0], [0.0, -0.01, 0.0], [0.0, 0.0, f32::NAN]] {
        let err = sim::scenario_geometry(&scenario, bad).unwrap_err().to_string();
        assert!(err.contains("grid offset"), "{err}");
    }
    // Exact depth explores the world as completely on a grid that does not line up with it.
    let cfg = SimConfig {
        grid_offset: [0.05; 3],
        ..SimConfig::default()
    };
    let r = sim::run(&scenario, &cfg, |_| {}).unwrap();
    assert_eq!(r.termination, "complete", "{:?}", r.errors);
    assert!(r.coverage_free >= 0.97, "coverage {}", r.coverage_free);
    assert_eq!(r.collisions, 0, "{:?}", r.collision_points);
    let o = aligned.origin();
    assert_eq!(r.grid_origin, [o.x - 0.05, o.y - 0.05, o.z - 0.05]);
}

#[test]
fn the_stereo_sensor_model_plans_with_a_wider_radius_and_leaves_pockets_on_the_old_one() {
    let fx = 65.0;
    let plans = |model: bool, given: Option<f32>| {
        let mut cfg = SimConfig::default();
        if let Some(r) = given {
            cfg.explorer.vehicle_radius = r;
        }
        sim::integrate_noisy_depth(&mut cfg, 0.25, fx, 0.12, None, model);
        (cfg.explorer.vehicle_radius, cfg.explorer.narrow_radius)
    };
    // Surfaces mapped at their true thickness need the margin exact depth's grown ones gave;
    // exact depth's radius stays the way out of a pocket.
    assert_eq!(plans(false, None), (0.2, 0.0));
    assert_eq!(plans(true, None), (sim::STEREO_MODEL_VEHICLE_RADIUS_M, 0.2));
    assert_eq!(plans(true, Some(0.35)).0, 0.35, "a wider radius is kept");
}

#[test]
fn tiny_bench_of_every_planner_shards_and_merges() {
    let dir = temp_dir("bench");
    let cfg = |shard| BenchConfig {
        scenarios: vec![fixture("corridor"), fixture("closet")],
        planners: PlannerKind::ALL.to_vec(),
        runs: 2,
        first_seed: 1,
        shard,
        jobs: 2,
        sim: SimConfig::default(),
        companion: false,
    };
    let a = batch::run(&cfg((1, 2)), &dir.join("a"), true).unwrap();
    let b = batch::run(&cfg((2, 2)), &dir.join("b"), true).unwrap();
    let runs = 2 * PlannerKind::ALL.len() * 2;
    assert_eq!(a.len() + b.len(), runs);
    assert!(dir.join("a/runs-shard-1-of-2.csv").exists());
    let rows = batch::merge(&[dir.join("a"), dir.join("b")], &dir.join("all")).unwrap();
    assert_eq!(rows.len(), runs);
    for kind in PlannerKind::ALL {
        let mine: Vec<_> = rows.iter().filter(|r| r.planner == kind.name()).collect();
        assert_eq!(mine.len(), 4, "{kind}");
        for r in &mine {
            assert_eq!(
                r.termination, "complete",
                "{} {} seed {}",
                r.scenario, r.planner, r.seed
            );
            assert!(r.coverage_free > 0.95 && r.path_length_m > 0.5, "{r:?}");
        }
    }
    // Every planner of a seed started from the same random pose.
    for seed in 1..=2 {
        let starts: Vec<_> = rows
            .iter()
            .filter(|r| r.scenario == "corridor" && r.seed == seed)
            .map(|r| r.start)
            .collect();
        assert!(starts.windows(2).all(|w| w[0] == w[1]), "{starts:?}");
    }
    let md = std::fs::read_to_string(dir.join("all/results.md")).unwrap();
    assert!(md.contains("### corridor") && md.contains("### closet"), "{md}");
    assert!(
        md.contains("| closest-frontier | 2 | 2 |") && md.contains("| 1.00 |"),
        "{md}"
    );
    for s in ["corridor", "closet"] {
        let png = std::fs::read(dir.join(format!("all/coverage_{s}.png"))).unwrap();
        assert_eq!(&png[1..4], b"PNG");
    }
    assert_eq!(batch::read_csv(&dir.join("all/runs.csv")).unwrap(), rows);
    let _ = std::fs::remove_dir_all(dir);
}

/// The label grid of the explorer's final map, captured by the run observer.
fn explore_recording(scenario: &Scenario, dir: &Path) -> (Vec<u8>, usize) {
    let cfg = SimConfig::default();
    let g = sim::scenario_geometry(scenario, [0.0; 3]).unwrap();
    let lo = cfg.explorer.log_odds;
    let settings = MapSettings {
        origin: g.origin().coords.into(),
        dims: [g.dims().nx(), g.dims().ny(), g.dims().nz()],
        resolution: g.resolution(),
        log_odds: [lo.hit, lo.miss, lo.min, lo.max],
        min_range: cfg.explorer.integration.min_range,
        max_range: cfg.explorer.integration.max_range,
        vehicle_radius: cfg.explorer.vehicle_radius,
    };
    let mut recorder = Recorder::create(dir, &settings).unwrap();
    let mut labels = Vec::new();
    let report = sim::run_observed(
        scenario,
        &cfg,
        |_| {},
        |view| {
            recorder.step(view).unwrap();
            if view.finished {
                labels = harmonic_sim::io::labels::labels_from_map(view.planner.map()).data;
            }
        },
    )
    .unwrap();
    assert_eq!(report.termination, "complete");
    (labels, recorder.finish().unwrap())
}

#[test]
fn record_then_replay_reproduces_the_explorers_map_exactly() {
    let dir = temp_dir("record");
    let scenario = Scenario::load(fixture("two-rooms")).unwrap();
    let (explored, frames) = explore_recording(&scenario, &dir);
    assert!(frames > 10);
    // TUM RGB-D layout: a 16-bit PNG in millimetres per frame, listed in depth.txt.
    let depth_txt = std::fs::read_to_string(dir.join("depth.txt")).unwrap();
    let first = depth_txt.lines().find(|l| !l.starts_with('#')).unwrap();
    let png = first.split_whitespace().nth(1).unwrap();
    let (mm, w, h) = record::read_png16(&dir.join(png)).unwrap();
    assert_eq!((w, h), (100, 100));
    assert!(mm.iter().any(|&d| d > 300 && d < 6000), "depths in millimetres");
    let gt = std::fs::read_to_string(dir.join("groundtruth.txt")).unwrap();
    assert_eq!(gt.lines().filter(|l| !l.starts_with('#')).count(), frames);

    let cfg = ReplayConfig {
        dir: dir.clone(),
        intrinsics: None,
        map: None,
        depth_scale: 1000.0,
        max_time_difference: 0.02,
    };
    let mut replayed = Vec::new();
    let summary = record::replay(&cfg, |map| {
        replayed = harmonic_sim::io::labels::labels_from_map(map).data;
        Ok(())
    })
    .unwrap();
    assert_eq!(summary.frames, frames);
    assert_eq!(summary.frames_without_pose, 0);
    assert_eq!(replayed.len(), explored.len());
    let differ = replayed.iter().zip(&explored).filter(|(a, b)| a != b).count();
    assert_eq!(differ, 0, "{differ} voxels differ");

    assert!(summary.body_marks > 0);
    let _ = std::fs::remove_dir_all(dir);
}

#[test]
fn stereo_noise_no_longer_ends_exploration_early() {
    use harmonic_sim::sensors::camera::StereoNoise;
    let scenario = Scenario::builtin("apartment").unwrap();
    let run = |noise: StereoNoise, trusted_range: f32| {
        let mut cfg = SimConfig::default();
        cfg.camera = cfg.camera.with_noise(Some(noise));
        cfg.explorer.integration.max_range = trusted_range;
        sim::run(&scenario, &cfg, |_| {}).unwrap()
    };
    // The raw matcher (no filter) trusted to 10 m: spurious obstacles close the doorways and
    // the run ends `complete` with rooms unseen.
    let raw = run(
        StereoNoise {
            filter_px: 1,
            ..StereoNoise::default()
        },
        10.0,
    );
    assert!(raw.coverage_observed < 0.9, "{}", raw.coverage_observed);
    // The stereo pipeline: 5 × 5 median, depth trusted up to a 0.1 m error.
    let noise = StereoNoise::default();
    let fx = SimConfig::default().camera.intrinsics.fx();
    let r = run(noise, noise.trusted_range(fx, 0.1));
    assert_eq!(r.termination, "complete");
    assert!(r.coverage_observed > 0.97, "{}", r.coverage_observed);
    assert_eq!(r.collisions, 0);
    let a = r.map_accuracy.expect("accuracy is measured with noise");
    let raw_a = raw.map_accuracy.unwrap();
    assert!(a.observed_voxels > raw_a.observed_voxels, "{a:?} vs {raw_a:?}");
}

/// The default `--noise stereo` camera (σ = 1 px, 5 × 5 median) integrated with the core's
/// stereo sensor model (no surface estimate, no window), sensor noise seeded with `seed`.
fn stereo_model_config(seed: u64) -> SimConfig {
    use harmonic_sim::sensors::camera::StereoNoise;
    let mut cfg = SimConfig {
        seed,
        ..SimConfig::default()
    };
    let noise = StereoNoise::default();
    cfg.camera = cfg.camera.with_noise(Some(noise));
    let fx = cfg.camera.intrinsics.fx();
    sim::integrate_noisy_depth(
        &mut cfg,
        noise.filtered_sigma_px(),
        fx,
        noise.baseline_m,
        None,
        true,
    );
    cfg
}

/// `--noise stereo`'s default rules (the sensor model, the surface estimate and the median's
/// window as the pipeline's footprint) keep the body off obstacles and the halls open.
/// Apartment-thesis start 5 of closest frontier: on the surface rules without the window its
/// map seals the 0.9 m hall (36.5 % free coverage); with the window it explores the hall and
/// keeps 0.2 m and more from every surface (docs/RESULTS.md, "A surface voxel hides what lies
/// behind it"). Until closest frontier flew inside the explorer's loop (2026-12-07) the
/// windowless run also touched a wall (0.114 m of clearance for a 0.15 m body); now it keeps
/// 0.238 m, and none of apartment-thesis and kitchen starts 1–8 touches without the window.
/// Until the occlusion rule of that section this test used kitchen start 1. If a change to the
/// map rules stops this run sealing the hall without the window, it no longer shows the
/// window's effect: pick another start from the rows.
#[test]
fn the_pipeline_window_keeps_noisy_runs_off_walls_and_the_hall_open() {
    use harmonic_sim::sensors::camera::StereoNoise;
    let scenario = Scenario::builtin("apartment-thesis")
        .unwrap()
        .with_random_start(5);
    let run = |window: bool| {
        let mut cfg = SimConfig {
            planner: PlannerKind::ClosestFrontier,
            surface_estimate: true,
            ..stereo_model_config(5)
        };
        if window {
            sim::use_pipeline_window(&mut cfg, StereoNoise::default(), None);
        }
        sim::run(&scenario, &cfg, |_| {}).unwrap()
    };
    let without = run(false);
    assert!(
        without.coverage_free < 0.5,
        "without the window: {} collisions, {} m, {} free coverage",
        without.collisions,
        without.min_clearance_m,
        without.coverage_free
    );
    let with = run(true);
    assert_eq!(with.termination, "complete");
    assert_eq!(with.collisions, 0, "{:?}", with.collision_points);
    assert!(with.min_clearance_m >= 0.2, "{}", with.min_clearance_m);
    assert!(with.coverage_free > 0.95, "{}", with.coverage_free);
}

#[test]
fn mesh_world_matches_the_same_world_built_from_boxes() {
    use harmonic_sim::run::metrics::GroundTruth;
    use harmonic_sim::sensors::camera::{camera_pose, DepthCamera};
    use rand::SeedableRng;
    let boxes = Scenario::load(fixture("two-rooms")).unwrap();
    let meshes = Scenario::load(fixture("mesh-rooms")).unwrap();
    assert!(meshes.world.boxes.is_empty() && meshes.world.meshes.len() == 2);
    // Voxelised on the scenario grid, the OBJ and STL give exactly the boxes' voxels.
    let g = sim::scenario_geometry(&boxes, [0.0; 3]).unwrap();
    let (a, b) = (
        GroundTruth::new(&boxes.world, &g, &boxes.start_position),
        GroundTruth::new(&meshes.world, &g, &meshes.start_position),
    );
    for i in 0..g.dims().len() {
        assert_eq!(
            a.is_occupied(i),
            b.is_occupied(i),
            "voxel {:?}",
            g.dims().voxel(i)
        );
    }
    assert_eq!(a.reachable_free(), b.reachable_free());
    // The camera ray casts the triangles exactly: the same depth images, to the millimetre.
    let cam = DepthCamera::default_thesis();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
    for (p, yaw) in [
        ([1.2, 1.5, 1.0], 0.0f32),
        ([3.0, 0.8, 1.2], 2.0),
        ([4.2, 2.4, 0.6], -2.5),
    ] {
        let pose = camera_pose(&nalgebra::Point3::from(p), yaw);
        let (mut da, mut db) = (Vec::new(), Vec::new());
        cam.render(&boxes.world, &pose, &mut rng, &mut da);
        cam.render(&meshes.world, &pose, &mut rng, &mut db);
        let worst = da.iter().zip(&db).map(|(x, y)| x.abs_diff(*y)).max().unwrap();
        assert!(worst <= 1, "{worst} mm at {p:?}");
    }
    // And the whole exploration is the same.
    let ra = sim::run(&boxes, &SimConfig::default(), |_| {}).unwrap();
    let rb = sim::run(&meshes, &SimConfig::default(), |_| {}).unwrap();
    assert_eq!(rb.termination, "complete");
    assert!(
        (ra.path_length_m - rb.path_length_m).abs() < 0.05,
        "{} vs {}",
        ra.path_length_m,
        rb.path_length_m
    );
    assert_eq!(rb.collisions, 0);
}

/// Loads a 10⁶-triangle OBJ (a tessellated sphere in a room) and prints the time to parse it,
/// build the hierarchy and voxelise it. `cargo test --release -p harmonic-tests --test
/// evaluation -- --ignored --nocapture million`
#[test]
#[ignore]
fn million_triangle_mesh_loads_in_seconds() {
    let dir = temp_dir("million");
    let (rings, segments) = (500usize, 1000usize);
    let mut text = String::with_capacity(60_000_000);
    let (c, r) = ([2.5f32, 2.5, 1.5], 1.0f32);
    for i in 0..=rings {
        let th = std::f32::consts::PI * i as f32 / rings as f32;
        for j in 0..segments {
            let ph = std::f32::consts::TAU * j as f32 / segments as f32;
            text += &format!(
                "v {} {} {}\n",
                c[0] + r * th.sin() * ph.cos(),
                c[1] + r * th.sin() * ph.sin(),
                c[2] + r * th.cos()
            );
        }
    }
    for i in 0..rings {
        for j in 0..segments {
            let a = i * segments + j + 1;
            let b = i * segments + (j + 1) % segments + 1;
            text += &format!(
                "f {a} {b} {}\nf {a} {} {}\n",
                b + segments,
                b + segments,
                a + segments
            );
        }
    }
    std::fs::write(dir.join("sphere.obj"), &text).unwrap();
    std::fs::write(
        dir.join("world.toml"),
        "name = \"million\"\nresolution = 0.1\n[bounds]\nmin = [0.0, 0.0, 0.0]\nmax = [5.0, 5.0, 3.0]\n[start]\nposition = [0.6, 0.6, 1.0]\nyaw_deg = 45.0\n[[mesh]]\nfile = \"sphere.obj\"\n",
    )
    .unwrap();
    let t0 = std::time::Instant::now();
    let s = Scenario::load(dir.join("world.toml")).unwrap();
    let load = t0.elapsed();
    let m = &s.world.meshes[0];
    assert_eq!(m.mesh.triangles.len(), 2 * rings * segments);
    let solid = m.solid.iter().filter(|&&v| v).count();
    // A 1 m ball is about 4189 voxels of 0.1 m, plus the voxels its surface passes through.
    assert!((4000..5600).contains(&solid), "{solid}");
    println!(
        "{} triangles ({} MB of OBJ): parsed, BVH built and voxelised in {:.2} s",
        m.mesh.triangles.len(),
        text.len() / 1_000_000,
        load.as_secs_f64()
    );
    let _ = std::fs::remove_dir_all(dir);
}

/// "Doorways must not close under noise": in the thesis's apartment, starts 27 and 53 (σ = 1
/// px, the stereo sensor model, 0.25 m radius), noisy returns leave weakly seen occupied voxels
/// where the vehicle's safe space ends. Without the reopening rule the runs end `complete` at
/// 39.0 % and 39.4 % of the free space; with it (the default) the explorer looks at those
/// voxels again, finds the way open and explores the rest (89.4 % and 89.9 %, measured),
/// without a collision. (Which starts close depends on the exact path: until the re-solves in
/// boxes, 2026-12-06, they were starts 9 and 2, then 33 and 11 until the boxes' budget and
/// inner box, 2026-12-07, then 9 and 44 until the boxes were kept within the domain's box,
/// then 9 and 33 until the inner box's share, 2026-12-07 at `41ad775`. Of starts 1–60, 13 close without
/// the rule and 10 with it: 12, 14, 15, 17, 20, 23, 24, 25, 51, 57, at 33–58 %;
/// docs/RESULTS.md.)
#[test]
fn a_hall_closed_by_doubtful_voxels_is_reopened_before_the_end() {
    let run = |start: u64, doubtful_log_odds: f32| {
        let scenario = Scenario::builtin("apartment-thesis")
            .unwrap()
            .with_random_start(start);
        let mut cfg = stereo_model_config(start);
        cfg.explorer.doubtful_log_odds = doubtful_log_odds;
        sim::run(&scenario, &cfg, |_| {}).unwrap()
    };
    for start in [27, 53] {
        let closed = run(start, 0.0);
        assert_eq!(closed.termination, "complete");
        assert!(
            closed.coverage_free < 0.6,
            "start {start}: {}",
            closed.coverage_free
        );
        assert_eq!(closed.errors.reopenings, 0);
        let reopened = run(start, ExplorerConfig::default().doubtful_log_odds);
        assert_eq!(reopened.termination, "complete");
        assert!(
            reopened.errors.reopenings > 0,
            "start {start}: {:?}",
            reopened.errors
        );
        assert!(
            reopened.coverage_free > 0.85,
            "start {start}: {}",
            reopened.coverage_free
        );
        assert_eq!(
            reopened.collisions, 0,
            "start {start}: {:?}",
            reopened.collision_points
        );
    }
}
