//! The fault campaign (`harmonic-sim faults`): one exploration per cell of a matrix of injected
//! faults — depth-link bit errors, frame loss and noise bursts, pose drift, sensor dropouts and
//! outliers, a stale pose stream — each flown over MAVLink to the flight-stack emulator, so
//! holds and STATUSTEXTs take their real path. Each cell reports completion, collisions,
//! frames integrated and lost, and every non-zero error counter of the explorer, the link
//! receiver and the MAVLink bridge. docs/RELIABILITY.md holds the default matrix's numbers.

use serde::Serialize;
use serde_json::Value;

use crate::link::depth_link::LinkConfig;
use crate::link::fault::FaultConfig;
use crate::run::sim::{self, SimConfig, SimError, SimFaults};
use crate::vehicle::autopilot::MavlinkConfig;
use crate::world::scenario::Scenario;

/// One cell of the matrix: a name and the faults it injects.
#[derive(Debug, Clone, Serialize)]
pub struct Cell {
    /// Short label, e.g. `ber 1e-5`.
    pub name: String,
    /// Depth-link faults.
    #[serde(skip)]
    pub link: FaultConfig,
    /// Sensor and pose faults.
    pub sim: SimFaults,
}

impl Cell {
    fn link(name: &str, link: FaultConfig) -> Self {
        Self {
            name: name.into(),
            link,
            sim: SimFaults::default(),
        }
    }
    fn sim(name: &str, sim: SimFaults) -> Self {
        Self {
            name: name.into(),
            link: FaultConfig::default(),
            sim,
        }
    }
}

/// The default matrix: a clean baseline, then each fault on its own at the ends of the ranges
/// the issue names, then all of the mid-range ones together.
pub fn default_matrix() -> Vec<Cell> {
    let ber = |b: f64| FaultConfig {
        bit_error_rate: b,
        ..FaultConfig::default()
    };
    let drop = |p: f64| FaultConfig {
        frame_drop: p,
        ..FaultConfig::default()
    };
    vec![
        Cell::link("clean", FaultConfig::default()),
        Cell::link("ber 1e-6", ber(1e-6)),
        Cell::link("ber 1e-5", ber(1e-5)),
        Cell::link("ber 1e-4", ber(1e-4)),
        Cell::link("frame loss 1 %", drop(0.01)),
        Cell::link("frame loss 10 %", drop(0.10)),
        Cell::link(
            "bursts 1e-5 × 32 B",
            FaultConfig {
                burst_rate: 1e-5,
                burst_len: 32,
                ..FaultConfig::default()
            },
        ),
        drift_cell(1.0),
        drift_cell(2.0),
        Cell::sim(
            "sensor dropout 5 %",
            SimFaults {
                sensor_dropout: 0.05,
                ..SimFaults::default()
            },
        ),
        Cell::sim(
            "sensor outliers 0.1 %",
            SimFaults {
                sensor_outlier: 0.001,
                ..SimFaults::default()
            },
        ),
        Cell::sim(
            "stale pose 3 s at 20 s",
            SimFaults {
                pose_outage_s: Some((20.0, 3.0)),
                ..SimFaults::default()
            },
        ),
        Cell {
            name: "combined".into(),
            link: FaultConfig {
                bit_error_rate: 1e-5,
                frame_drop: 0.01,
                burst_rate: 1e-6,
                burst_len: 32,
                ..FaultConfig::default()
            },
            sim: SimFaults {
                sensor_dropout: 0.02,
                sensor_outlier: 0.0005,
                pose_drift_m_per_s: 0.001,
                pose_outage_s: Some((20.0, 2.0)),
            },
        },
    ]
}

/// A pose-drift cell: the position the autopilot estimates walks away from the truth at
/// `mm_per_s` (along the map diagonal, hovering or not), and the vehicle flies that estimate.
/// The default matrix holds the rates the planner tolerates (docs/RELIABILITY.md: planning
/// radius 0.2 m against a 0.15 m body leaves 5 cm, and drift moves the vehicle towards walls the
/// camera is not looking at); `faults --drift-rates` sweeps beyond them.
pub fn drift_cell(mm_per_s: f32) -> Cell {
    Cell::sim(
        &format!("pose drift {mm_per_s} mm/s"),
        SimFaults {
            pose_drift_m_per_s: mm_per_s * 1e-3,
            ..SimFaults::default()
        },
    )
}

/// What one cell did.
#[derive(Debug, Clone, Serialize)]
pub struct CellResult {
    /// The cell.
    pub cell: Cell,
    /// `complete`, `scan_limit`, `stuck:…`, or `error: …` if the run could not finish.
    pub termination: String,
    /// Free-space coverage at the end.
    pub coverage_free: f64,
    /// Collision events (must be 0).
    pub collisions: u32,
    /// Closest the body's centre came to a surface, metres (NaN, `null` in JSON, if the cell
    /// could not run).
    pub min_clearance_m: f32,
    /// Depth frames sent by the camera side.
    pub frames_sent: u32,
    /// Depth frames the core integrated.
    pub frames_integrated: u32,
    /// Depth frames lost on the link or refused.
    pub frames_lost: u32,
    /// Depth frames integrated with rows missing, and the rows missing from all of them.
    pub partial_frames: (u32, u32),
    /// Resend requests the core sent, and the chunks the camera side sent again.
    pub resends: (u32, u32),
    /// Every non-zero counter: explorer errors, link receiver, MAVLink bridge rejections.
    pub counters: Vec<(String, u64)>,
    /// STATUSTEXTs the emulator received.
    pub status_texts: usize,
}

/// Runs every cell of `cells` on `scenario` with `base` settings (MAVLink to the emulator is
/// switched on) and calls `progress` after each.
pub fn run(
    scenario: &Scenario,
    base: &SimConfig,
    cells: Vec<Cell>,
    mut progress: impl FnMut(&CellResult),
) -> Vec<CellResult> {
    cells
        .into_iter()
        .map(|cell| {
            let mut cfg = base.clone();
            cfg.link = LinkConfig {
                faults: cell.link,
                ..base.link.clone()
            };
            cfg.faults = cell.sim;
            if cfg.mavlink.is_none() {
                cfg.mavlink = Some(MavlinkConfig::default());
            }
            let result = summarise(cell, sim::run(scenario, &cfg, |_| {}));
            progress(&result);
            result
        })
        .collect()
}

fn summarise(cell: Cell, report: Result<sim::Report, SimError>) -> CellResult {
    let report = match report {
        Ok(r) => r,
        Err(e) => {
            return CellResult {
                cell,
                termination: format!("error: {e}"),
                coverage_free: 0.0,
                collisions: 0,
                min_clearance_m: f32::NAN,
                frames_sent: 0,
                frames_integrated: 0,
                frames_lost: 0,
                partial_frames: (0, 0),
                resends: (0, 0),
                counters: Vec::new(),
                status_texts: 0,
            }
        }
    };
    let mut counters = Vec::new();
    let mut add = |prefix: &str, value: Value| {
        if let Value::Object(fields) = value {
            for (k, v) in fields {
                if let Some(n) = v.as_u64().filter(|&n| n > 0) {
                    counters.push((format!("{prefix}{k}"), n));
                }
            }
        }
    };
    add("", serde_json::to_value(report.errors).unwrap_or(Value::Null));
    let mut link = serde_json::to_value(report.link.receiver).unwrap_or(Value::Null);
    if let Value::Object(fields) = &mut link {
        // Traffic, not faults; partial images have a column of their own.
        for k in [
            "bytes",
            "frames_ok",
            "depth_frames_complete",
            "depth_frames_partial",
            "rows_missing",
        ] {
            fields.remove(k);
        }
    }
    add("link.", link);
    let mut status_texts = 0;
    if let Some(m) = &report.mavlink {
        let bridge = serde_json::to_value(m.bridge).unwrap_or(Value::Null);
        if let Value::Object(fields) = bridge {
            let faults = fields
                .into_iter()
                .filter(|(k, _)| k.starts_with("rejected") || k == "stale_events" || k == "goals_refused")
                .collect();
            add("mav.", Value::Object(faults));
        }
        status_texts = m.status_texts.len();
    }
    let l = &report.link;
    if l.frames_without_pose > 0 {
        counters.push((
            "link.frames_without_pose".to_string(),
            u64::from(l.frames_without_pose),
        ));
    }
    CellResult {
        cell,
        termination: report.termination,
        coverage_free: report.coverage_free,
        collisions: report.collisions,
        min_clearance_m: report.min_clearance_m,
        frames_sent: report.link.depth_frames_sent,
        frames_integrated: report.link.depth_frames_integrated,
        frames_lost: report.link.depth_frames_lost,
        partial_frames: (l.partial_frames_integrated, l.receiver.rows_missing),
        resends: (l.resend_requests_sent, l.chunks_resent),
        counters,
        status_texts,
    }
}

/// The results as a Markdown table (the one in docs/RELIABILITY.md).
pub fn table(results: &[CellResult]) -> String {
    let mut out = String::from(
        "| cell | termination | free coverage | collisions | closest approach | frames sent / integrated / lost | integrated partial (rows missing) | resend requests / chunks resent | STATUSTEXTs | non-zero error counters |\n|---|---|---|---|---|---|---|---|---|---|\n",
    );
    for r in results {
        let counters = r
            .counters
            .iter()
            .map(|(k, v)| format!("{k} {v}"))
            .collect::<Vec<_>>()
            .join(", ");
        out.push_str(&format!(
            "| {} | {} | {:.2} % | {} | {} | {} / {} / {} | {} ({}) | {} / {} | {} | {} |\n",
            r.cell.name,
            r.termination,
            r.coverage_free * 100.0,
            r.collisions,
            // A cell that could not run has no closest approach.
            if r.min_clearance_m.is_finite() {
                format!("{:.3} m", r.min_clearance_m)
            } else {
                "–".into()
            },
            r.frames_sent,
            r.frames_integrated,
            r.frames_lost,
            r.partial_frames.0,
            r.partial_frames.1,
            r.resends.0,
            r.resends.1,
            r.status_texts,
            if counters.is_empty() {
                "—".into()
            } else {
                counters
            },
        ));
    }
    out
}
