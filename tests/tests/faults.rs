//! The fault campaign's cells that must stay clean: a stale pose stream and link damage are
//! ridden out (hold, then continue) to completion without a collision, and counted. The whole
//! matrix (`harmonic-sim faults`) is too long for CI; docs/RELIABILITY.md has its numbers.

use harmonic_sim::run::sim::SimConfig;
use harmonic_sim::tools::faults::{self, Cell};
use harmonic_sim::world::scenario::Scenario;

fn cells(names: &[&str]) -> Vec<Cell> {
    let cells: Vec<Cell> = faults::default_matrix()
        .into_iter()
        .filter(|c| names.contains(&c.name.as_str()))
        .collect();
    assert_eq!(cells.len(), names.len(), "cells renamed?");
    cells
}

#[test]
fn stale_pose_and_link_bursts_are_ridden_out_without_collisions() {
    let scenario = Scenario::builtin("apartment").unwrap();
    let results = faults::run(
        &scenario,
        &SimConfig::default(),
        cells(&["stale pose 3 s at 20 s", "bursts 1e-5 × 32 B"]),
        |_| {},
    );
    let counter = |r: &faults::CellResult, name: &str| {
        r.counters.iter().find(|(k, _)| k == name).map_or(0, |(_, v)| *v)
    };
    for r in &results {
        assert_eq!(r.termination, "complete", "{}", r.cell.name);
        assert_eq!(r.collisions, 0, "{}", r.cell.name);
        assert!(r.coverage_free > 0.99, "{}: {}", r.cell.name, r.coverage_free);
    }
    let by_name = |name: &str| results.iter().find(|r| r.cell.name.starts_with(name)).unwrap();
    let (stale, bursts) = (by_name("stale"), by_name("bursts"));
    assert_eq!(counter(stale, "mav.stale_events"), 1);
    assert!(
        counter(stale, "mav.goals_refused") > 0,
        "goals refused while stale"
    );
    // Stale WARNING and back-to-fresh INFO, besides start and completion.
    assert!(stale.status_texts >= 4, "{}", stale.status_texts);
    // Bursts damage chunks; the core asks for them again and the images arrive.
    assert!(counter(bursts, "link.crc_errors") + counter(bursts, "link.cobs_errors") > 0);
    assert!(bursts.resends.0 > 0 && bursts.resends.1 > 0, "{bursts:?}");
    assert_eq!(
        counter(bursts, "link.depth_frames_dropped") + counter(bursts, "link.frames_without_pose"),
        u64::from(bursts.frames_lost)
    );
    assert!(bursts.frames_lost * 50 <= bursts.frames_sent, "{bursts:?}");
}

/// Dropouts read as "no return": they must never erase a wall the map has seen (before the fix,
/// one dropout ray cleared a wall voxel and the vehicle flew into it), and slow pose drift is
/// tolerated.
#[test]
fn sensor_dropouts_and_slow_pose_drift_end_without_collisions() {
    let scenario = Scenario::builtin("apartment").unwrap();
    let results = faults::run(
        &scenario,
        &SimConfig::default(),
        cells(&["sensor dropout 5 %", "pose drift 2 mm/s"]),
        |_| {},
    );
    for r in &results {
        assert_eq!(r.termination, "complete", "{}", r.cell.name);
        assert_eq!(r.collisions, 0, "{}", r.cell.name);
    }
}
