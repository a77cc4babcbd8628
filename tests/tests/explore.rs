//! End to end: every built-in scenario explored to completion by the core, through the
//! simulator's camera and vehicle, judged against the true world.

use harmonic_sim::scenario::{builtin_names, Scenario};
use harmonic_sim::sim::{self, Report, SimConfig};

fn explore(name: &str) -> Report {
    let scenario = Scenario::builtin(name).expect("built-in scenario");
    sim::run(&scenario, &SimConfig::default(), |_| {}).expect("run starts")
}

fn assert_complete(r: &Report) {
    assert_eq!(r.termination, "complete", "{}: {:?}", r.scenario, r.errors);
    assert!(
        r.coverage_free >= 0.98,
        "{}: free coverage {:.4}",
        r.scenario,
        r.coverage_free
    );
    assert_eq!(
        r.collisions, 0,
        "{}: collisions at {:?}",
        r.scenario, r.collision_points
    );
    assert!(
        r.path_length_m > 1.0 && r.scans > 10,
        "{}: implausibly short run",
        r.scenario
    );
    assert_eq!(r.steps.len() as u32, r.scans, "one step record per scan");
    // Every frame went over the depth link's wire format and arrived whole.
    assert_eq!(
        r.link.depth_frames_complete, r.scans,
        "{}: {:?}",
        r.scenario, r.link
    );
    assert_eq!(
        r.link.crc_errors + r.link.malformed + r.link.missing_chunks,
        0,
        "{:?}",
        r.link
    );
}

#[test]
fn apartment_is_explored_completely_without_collisions() {
    assert_complete(&explore("apartment"));
}

#[test]
fn office_is_explored_completely_without_collisions() {
    assert_complete(&explore("office"));
}

#[test]
fn two_level_is_explored_completely_without_collisions() {
    let r = explore("two-level");
    assert_complete(&r);
    // The upper storey is only reachable through the slab opening: it must have been visited.
    let highest = r.steps.iter().map(|s| s.position[2]).fold(f32::MIN, f32::max);
    assert!(highest > 2.6, "never flew above the slab (max z {highest})");
}

#[test]
fn pil_small_is_explored_completely_on_the_host() {
    // The same world the firmware explores under QEMU (tests/pil.rs).
    assert_complete(&explore("pil-small"));
}

#[test]
fn every_builtin_is_covered_by_these_tests() {
    assert_eq!(builtin_names(), ["apartment", "office", "two-level", "pil-small"]);
}

#[test]
fn gauss_seidel_reference_plans_the_same_first_step() {
    // The seed paper's solver and multigrid solve the same problem: the first plan from the
    // apartment's start must head to the same frontier region.
    use harmonic_core::explore::SolverKind;
    let scenario = Scenario::builtin("apartment").unwrap();
    let mut first = Vec::new();
    for solver in [SolverKind::Multigrid, SolverKind::GaussSeidel] {
        let mut cfg = SimConfig {
            max_scans: 1,
            ..SimConfig::default()
        };
        cfg.explorer.solver = solver;
        let r = sim::run(&scenario, &cfg, |_| {}).unwrap();
        assert_eq!(r.steps[0].outcome, "goal");
        first.push(r.steps[0].streamline_m);
    }
    assert!((first[0] - first[1]).abs() < 0.05, "streamline lengths {first:?}");
}

#[test]
fn apartment_explored_over_mavlink() {
    // The core's MAVLink bridge drives an emulated flight stack; the explorer plans from the
    // pose the flight stack reports back.
    let scenario = Scenario::builtin("apartment").unwrap();
    let cfg = SimConfig {
        mavlink: true,
        ..SimConfig::default()
    };
    let r = sim::run(&scenario, &cfg, |_| {}).expect("run starts");
    assert_complete(&r);
    let mav = r.mavlink.as_ref().expect("MAVLink counters in the report");
    assert_eq!(
        mav.emulator.setpoint_gaps, 0,
        "setpoints slower than 2 Hz: {:?}",
        mav.emulator
    );
    assert!(mav.emulator.max_setpoint_gap_ms <= 500, "{:?}", mav.emulator);
    assert_eq!(mav.emulator.setpoints_rejected, 0, "{:?}", mav.emulator);
    assert!(mav.emulator.setpoints_received > 10, "{:?}", mav.emulator);
    assert_eq!(mav.bridge.stale_events, 0, "{:?}", mav.bridge);
    assert_eq!(
        mav.bridge.rejected() + mav.bridge.sequence_gaps,
        0,
        "{:?}",
        mav.bridge
    );
    assert_eq!(
        mav.emulator.status_texts_received as usize,
        mav.status_texts.len()
    );
    assert_eq!(
        mav.status_texts.last().map(String::as_str),
        Some("exploration complete"),
        "{:?}",
        mav.status_texts
    );
}
