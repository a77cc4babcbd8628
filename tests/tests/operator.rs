//! Operator commands over MAVLink against the flight emulator: a ground station (system 255)
//! starts, pauses, resumes, aborts an exploration or calls the vehicle home with COMMAND_LONG;
//! every command is acknowledged, the vehicle holds while paused, the run ends where the abort
//! left it or at the start; and a complete exploration flies home when asked to.

use harmonic_core::mavlink::BridgeConfig;
use harmonic_core::operator::{CommandResult, OperatorCommand, OperatorState};
use harmonic_sim::run::sim::{self, SimConfig};
use harmonic_sim::vehicle::autopilot::MavlinkConfig;
use harmonic_sim::world::scenario::Scenario;

#[test]
fn a_ground_station_starts_pauses_resumes_and_aborts_the_exploration() {
    use OperatorCommand as C;
    let mavlink = MavlinkConfig {
        bridge: BridgeConfig {
            wait_for_start: true,
            ..BridgeConfig::default()
        },
        operator_script: vec![
            (3.0, C::Resume), // denied: nothing started yet
            (5.0, C::Start),
            (30.0, C::Pause),
            (45.0, C::Resume),
            (70.0, C::Abort),
        ],
        ..MavlinkConfig::default()
    };
    let cfg = SimConfig {
        mavlink: Some(mavlink),
        ..SimConfig::default()
    };
    let r = sim::run(&Scenario::builtin("apartment").unwrap(), &cfg, |_| {}).expect("run");
    assert_eq!(r.termination, "aborted");
    assert_eq!(r.collisions, 0);
    let m = r.mavlink.as_ref().unwrap();
    let answered: Vec<(Option<OperatorCommand>, CommandResult, OperatorState)> = m
        .operator_commands
        .iter()
        .map(|e| (e.command, e.result, e.state))
        .collect();
    assert_eq!(
        answered,
        [
            (Some(C::Resume), CommandResult::Denied, OperatorState::Waiting),
            (Some(C::Start), CommandResult::Accepted, OperatorState::Exploring),
            (Some(C::Pause), CommandResult::Accepted, OperatorState::Paused),
            (Some(C::Resume), CommandResult::Accepted, OperatorState::Exploring),
            (Some(C::Abort), CommandResult::Accepted, OperatorState::Aborted),
        ]
    );
    assert_eq!(m.operator_state, Some(OperatorState::Aborted));
    // Every command acknowledged over the link.
    assert_eq!(m.bridge.command_acks_sent, 5, "{:?}", m.bridge);
    assert_eq!(
        m.traffic.sent_by_type.get("COMMAND_ACK").copied(),
        Some(5),
        "{:?}",
        m.traffic.sent_by_type
    );
    for text in ["operator: exploring", "operator: paused", "operator: aborted"] {
        assert!(
            m.status_texts.iter().any(|t| t == text),
            "{text}: {:?}",
            m.status_texts
        );
    }
    // Nothing moved before the start; nothing while paused; exploration went on between.
    let path_at = |label: &str| -> Vec<f64> {
        r.steps
            .iter()
            .filter(|s| s.outcome == label)
            .map(|s| s.path_length_m)
            .collect()
    };
    let waiting = path_at("operator:waiting");
    assert!(
        !waiting.is_empty() && waiting.iter().all(|&p| p == 0.0),
        "{waiting:?}"
    );
    let paused = path_at("operator:paused");
    assert!(paused.len() >= 10, "{} paused steps", paused.len());
    let (lo, hi) = paused
        .iter()
        .fold((f64::MAX, 0.0f64), |(a, b), &p| (a.min(p), b.max(p)));
    assert!(hi - lo < 0.3, "moved {} m while paused", hi - lo);
    let first_paused = r
        .steps
        .iter()
        .position(|s| s.outcome == "operator:paused")
        .unwrap();
    assert!(
        r.steps[first_paused..].iter().any(|s| s.outcome == "goal"),
        "planning resumed"
    );
    assert!(
        r.path_length_m > hi + 1.0,
        "flew on after the resume: {} m",
        r.path_length_m
    );
    eprintln!(
        "waiting {} steps, paused {} steps at {lo:.2}-{hi:.2} m, aborted at {:.1} m after {} scans",
        waiting.len(),
        paused.len(),
        r.path_length_m,
        r.scans
    );
}

#[test]
fn start_pause_resume_then_home_ends_in_a_hold_at_the_start() {
    use OperatorCommand as C;
    // The operator flow of the link issue's acceptance: start → pause → resume → return home →
    // land-ready hold.
    let mavlink = MavlinkConfig {
        bridge: BridgeConfig {
            wait_for_start: true,
            ..BridgeConfig::default()
        },
        operator_script: vec![
            (2.0, C::Start),
            (40.0, C::Pause),
            (50.0, C::Resume),
            (90.0, C::ReturnHome),
        ],
        ..MavlinkConfig::default()
    };
    let cfg = SimConfig {
        mavlink: Some(mavlink),
        ..SimConfig::default()
    };
    let scenario = Scenario::builtin("apartment").unwrap();
    let r = sim::run(&scenario, &cfg, |_| {}).expect("run");
    assert_eq!(r.termination, "home", "{:?}", r.return_home);
    assert_eq!(r.collisions, 0);
    let back = r.return_home.as_ref().expect("a way home");
    assert_eq!(back.termination, "home");
    assert!(back.distance_to_home_m <= 0.3, "{back:?}");
    let end = r.trajectory.last().unwrap();
    let from_start = (0..3)
        .map(|k| (end[k] - scenario.start_position[k]).powi(2))
        .sum::<f32>()
        .sqrt();
    assert!(from_start <= 0.3, "ended {from_start} m from the start");
    assert!(back.path_length_m > 1.0, "it had gone somewhere: {back:?}");
    let m = r.mavlink.as_ref().unwrap();
    assert!(
        m.operator_commands
            .iter()
            .all(|e| e.result == CommandResult::Accepted),
        "{:?}",
        m.operator_commands
    );
    assert_eq!(m.operator_commands.len(), 4);
    assert_eq!(m.bridge.command_acks_sent, 4);
    assert_eq!(m.operator_state, Some(OperatorState::Home));
    for text in ["operator: returning home", "operator: home"] {
        assert!(
            m.status_texts.iter().any(|t| t == text),
            "{text}: {:?}",
            m.status_texts
        );
    }
}

#[test]
fn a_complete_exploration_flies_home_when_asked_to() {
    let cfg = SimConfig {
        return_home: true,
        ..SimConfig::default()
    };
    let scenario = Scenario::builtin("apartment").unwrap();
    let with = sim::run(&scenario, &cfg, |_| {}).expect("run");
    let without = sim::run(&scenario, &SimConfig::default(), |_| {}).expect("run");
    // The exploration's numbers are the same; the way home comes on top, reported apart.
    assert_eq!(with.termination, "complete");
    assert_eq!(
        (with.path_length_m, with.scans, with.coverage_free),
        (without.path_length_m, without.scans, without.coverage_free)
    );
    assert!(without.return_home.is_none());
    let back = with.return_home.expect("a way home");
    assert_eq!(back.termination, "home");
    assert!(
        back.distance_to_home_m <= 0.3 && back.path_length_m > 1.0,
        "{back:?}"
    );
    assert_eq!(with.collisions, 0);
}
