//! The command line as a user meets it: clear one-line errors with exit code 2, and a report.

use std::process::Command;

fn sim() -> Command {
    Command::new(env!("CARGO_BIN_EXE_harmonic-sim"))
}

#[test]
fn bad_scenario_file_is_a_one_line_error_with_exit_code_2() {
    let fixture = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/scenarios/fixtures/inverted-box.toml"
    );
    let out = sim()
        .args(["explore", "--scenario", fixture, "--out", "/tmp/unused"])
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2));
    let err = String::from_utf8(out.stderr).unwrap();
    assert_eq!(err.trim_end().lines().count(), 1, "{err}");
    assert!(
        err.contains("inverted-box.toml") && err.contains("box[1]"),
        "{err}"
    );
}

#[test]
fn unknown_scenario_and_bad_option_exit_with_code_2() {
    let out = sim()
        .args(["explore", "--scenario", "no-such-world"])
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&out.stderr).contains("no-such-world"));
    let out = sim()
        .args(["explore", "--vehicle-radius", "-1"])
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2));
    let out = sim().args(["explore", "--noise", "lidar"]).output().unwrap();
    assert_eq!(out.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&out.stderr).contains("lidar"));
}

#[test]
fn explore_writes_a_report_with_the_documented_fields() {
    let dir = std::env::temp_dir().join(format!("harmonic-cli-{}", std::process::id()));
    let out = sim()
        .args([
            "explore",
            "--scenario",
            "apartment",
            "--max-scans",
            "3",
            "--quiet",
            "--out",
        ])
        .arg(&dir)
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("report.json")).unwrap()).unwrap();
    for key in [
        "scenario",
        "termination",
        "coverage_free",
        "coverage_surface",
        "path_length_m",
        "scans",
        "collisions",
        "integration_ops",
        "planning_ops",
        "steps",
    ] {
        assert!(report.get(key).is_some(), "report.json lacks `{key}`");
    }
    assert_eq!(report["scans"], 3);
    assert_eq!(report["termination"], "scan_limit");
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        stdout.contains("coverage (free)"),
        "summary table missing: {stdout}"
    );
    // The flight's simulated time, as report.json has it (no way home after a scan limit).
    let time = report["flight_time_s"].as_f64().unwrap();
    assert!(
        time > 0.0 && stdout.contains(&format!("flight time          {time:.0} s (simulated)")),
        "flight time {time} s missing: {stdout}"
    );
    let _ = std::fs::remove_dir_all(dir);
}

/// `solve --repeat N` solves N times in one process and reports the fastest run with the
/// first run's total beside it; φ is the same as one run's.
#[test]
fn solve_repeats_in_one_process_and_reports_the_fastest_run() {
    let fixture = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/fixtures/labels_4x3x2.npy");
    let dir = std::env::temp_dir();
    let mut phis = Vec::new();
    for repeat in ["1", "3"] {
        let out_path = dir.join(format!("harmonic-phi-repeat{repeat}-{}.npy", std::process::id()));
        let out = sim()
            .args([
                "solve", "--labels", fixture, "--source", "0,0,0", "--solver", "flat",
            ])
            .args(["--repeat", repeat, "--out"])
            .arg(&out_path)
            .output()
            .unwrap();
        assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
        let line: serde_json::Value =
            serde_json::from_str(String::from_utf8(out.stdout).unwrap().trim()).unwrap();
        assert_eq!(line["runs"].as_u64(), Some(repeat.parse().unwrap()), "{line}");
        let total = line["setup_ms"].as_f64().unwrap() + line["solve_ms"].as_f64().unwrap();
        let first = line["first_ms"].as_f64().unwrap();
        assert!(
            total <= first + 1e-9,
            "the fastest run is at most the first: {line}"
        );
        phis.push(std::fs::read(&out_path).unwrap());
        let _ = std::fs::remove_file(out_path);
    }
    assert_eq!(phis[0], phis[1], "the same φ");
    let bad = sim()
        .args(["solve", "--labels", fixture, "--source", "0,0,0", "--repeat", "0"])
        .output()
        .unwrap();
    assert!(!bad.status.success(), "--repeat 0 is refused");
}

#[test]
fn solve_round_trips_a_numpy_label_grid() {
    let fixture = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/fixtures/labels_4x3x2.npy");
    let out_path = std::env::temp_dir().join(format!("harmonic-phi-{}.npy", std::process::id()));
    for solver in ["mg", "gs"] {
        let out = sim()
            .args([
                "solve", "--labels", fixture, "--source", "0,0,0", "--solver", solver, "--out",
            ])
            .arg(&out_path)
            .output()
            .unwrap();
        assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
        let stdout = String::from_utf8(out.stdout).unwrap();
        assert_eq!(stdout.lines().count(), 1, "one JSON line: {stdout}");
        let line: serde_json::Value = serde_json::from_str(stdout.trim()).unwrap();
        for key in [
            "cells", "unknowns", "frontier", "solver", "cycles", "residual", "solve_ms", "setup_ms",
        ] {
            assert!(line.get(key).is_some(), "missing `{key}` in {line}");
        }
        assert_eq!(line["cells"], 24);
        assert_eq!(line["solver"], solver);
        let phi = harmonic_sim::io::npy::read_f32(&std::fs::read(&out_path).unwrap()).unwrap();
        assert_eq!(phi.shape, [4, 3, 2]);
        assert_eq!(*phi.get(0, 0, 0).unwrap(), 1.0, "φ = 1 at the source");
        assert_eq!(
            *phi.get(0, 1, 1).unwrap(),
            0.0,
            "occupied voxel is outside the domain"
        );
        assert!(phi.data.iter().all(|p| (0.0..=1.0).contains(p)));
    }
    let _ = std::fs::remove_file(out_path);
}

#[test]
fn solve_stopped_at_the_cycle_cap_prints_not_converged_and_exits_0() {
    let fixture = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/fixtures/labels_4x3x2.npy");
    for solver in ["mg", "vc", "gs"] {
        let run = |cap: &str| {
            let out = sim()
                .args([
                    "solve", "--labels", fixture, "--source", "0,0,0", "--solver", solver,
                ])
                .args(["--max-cycles", cap])
                .output()
                .unwrap();
            assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
            serde_json::from_slice::<serde_json::Value>(&out.stdout).unwrap()
        };
        let capped = run("1");
        assert_eq!(capped["cycles"], 1, "{solver}: {capped}");
        assert_eq!(capped["converged"], false, "{solver}: {capped}");
        let free = run("1000000");
        assert_eq!(free["converged"], true, "{solver}: {free}");
    }
}

/// `--threads 2` splits the solver's passes between two threads and must write the same φ,
/// byte for byte, as one thread, on a grid large enough to be split (two rooms, a doorway,
/// unknown space beyond the far wall); a third thread is refused.
#[test]
fn solve_on_two_threads_writes_the_same_phi_as_on_one() {
    use harmonic_sim::io::labels;
    use harmonic_sim::io::npy::{self, Array3};
    let grid = Array3::from_fn([48, 40, 20], |x, y, _| match (x, y) {
        (47, _) => labels::UNKNOWN,
        (24, y) if !(18..22).contains(&y) => labels::OCCUPIED,
        _ => labels::FREE,
    });
    let dir = std::env::temp_dir().join(format!("harmonic-threads-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let input = dir.join("rooms.npy");
    std::fs::write(&input, npy::write_u8(&grid)).unwrap();
    for solver in ["mg", "vc"] {
        let run = |threads: &str| {
            let phi = dir.join(format!("phi-{solver}-{threads}.npy"));
            let out = sim()
                .args([
                    "solve",
                    "--source",
                    "3,3,10",
                    "--solver",
                    solver,
                    "--threads",
                    threads,
                ])
                .arg("--labels")
                .arg(&input)
                .arg("--out")
                .arg(&phi)
                .output()
                .unwrap();
            assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
            let line: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
            (
                std::fs::read(&phi).unwrap(),
                line["cycles"].clone(),
                line["stop"].clone(),
            )
        };
        let (one, two) = (run("1"), run("2"));
        // Stopped by its own rule: the tolerance, or the rounding floor above it (Laplace's
        // field behind one doorway: then honestly not converged).
        assert!(one.2 == "met" || one.2 == "floor", "{solver}: {}", one.2);
        assert_eq!((&one.1, &one.2), (&two.1, &two.2), "{solver}");
        assert!(one.0 == two.0, "{solver}: φ differs between one and two threads");
    }
    let out = sim()
        .args(["solve", "--source", "3,3,10", "--threads", "3", "--labels"])
        .arg(&input)
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2));
    let _ = std::fs::remove_dir_all(dir);
}

#[test]
fn solve_rejects_fortran_order_and_bad_source_with_exit_code_2() {
    let fortran = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/tests/fixtures/labels_4x3x2_fortran.npy"
    );
    let out = sim()
        .args(["solve", "--labels", fortran, "--source", "0,0,0"])
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&out.stderr).contains("Fortran"));
    let fixture = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/fixtures/labels_4x3x2.npy");
    let out = sim()
        .args(["solve", "--labels", fixture, "--source", "9,0,0"])
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&out.stderr).contains("outside the grid"));
}

#[test]
fn bad_link_and_mavlink_options_name_the_problem() {
    for (args, needle) in [
        (vec!["--link", "tcp:5760"], "expected tcp:HOST:PORT"),
        (vec!["--link", "udp:1.2.3.4:5"], "unknown transport `udp`"),
        (vec!["--mavlink", "udpin:14540"], "expected udpin:HOST:PORT"),
        (vec!["--link-ber", "2"], "probability between 0 and 1"),
        (vec!["--link-burst", "0.001:0"], "burst length `0`"),
        (vec!["--link-baud", "0"], "baud rate"),
        (vec!["--tlog", "x.tlog"], "--mavlink"),
    ] {
        let out = sim().arg("explore").args(&args).output().unwrap();
        assert_eq!(out.status.code(), Some(2), "{args:?}");
        let err = String::from_utf8_lossy(&out.stderr);
        // The problem is named at the top (clap puts a missing option on the second line).
        let top: String = err.lines().take(2).collect();
        assert!(top.contains(needle), "{args:?}: {err}");
    }
    // Errors found when the run starts: one line, naming the transport.
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let spec = format!("tcp:127.0.0.1:{port}");
    for args in [
        vec!["--link", spec.as_str()],
        vec!["--link", "serial:/dev/no-such-tty"],
    ] {
        let out = sim()
            .arg("explore")
            .args(&args)
            .args(["--quiet", "--out"])
            .arg(std::env::temp_dir().join("harmonic-unused"))
            .output()
            .unwrap();
        assert_eq!(out.status.code(), Some(2), "{args:?}");
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(err.trim_end().lines().count(), 1, "{err}");
        assert!(err.contains(args[1]), "{err}");
    }
}

#[test]
fn explore_records_a_tlog_that_the_tlog_command_reads_back() {
    let dir = std::env::temp_dir().join(format!("harmonic-cli-tlog-{}", std::process::id()));
    let tlog = dir.join("run.tlog");
    let out = sim()
        .args([
            "explore",
            "--scenario",
            "apartment",
            "--link",
            "sim",
            "--mavlink",
            "--link-drop",
            "0.05",
            "--max-scans",
            "5",
            "--quiet",
            "--tlog",
        ])
        .arg(&tlog)
        .arg("--out")
        .arg(&dir)
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        stdout.contains("depth link") && stdout.contains("mavlink") && stdout.contains("link faults"),
        "{stdout}"
    );
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("report.json")).unwrap()).unwrap();
    let link = &report["link"];
    for key in [
        "depth_frames_sent",
        "depth_frames_integrated",
        "depth_frames_lost",
        "transfer",
        "receiver",
        "injected",
    ] {
        assert!(link.get(key).is_some(), "report.json link lacks `{key}`: {link}");
    }
    assert_eq!(link["transport"], "sim");
    assert_eq!(link["baud"], 921600);
    assert!(link["injected"]["frames_dropped"].as_u64().is_some());
    let traffic = &report["mavlink"]["traffic"];
    assert_eq!(report["mavlink"]["endpoint"], "emulator");

    let out = sim().arg("tlog").arg(&tlog).arg("--json").output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let summary: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(summary["sent"], traffic["sent_by_type"]);
    assert_eq!(summary["received"], traffic["received_by_type"]);
    assert_eq!(summary["undecoded"], 0);
    let out = sim().arg("tlog").arg(&tlog).output().unwrap();
    let table = String::from_utf8_lossy(&out.stdout);
    assert!(
        table.contains("SET_POSITION_TARGET_LOCAL_NED") && table.contains("ATTITUDE"),
        "{table}"
    );

    // Not a tlog: one line naming the file and the problem.
    let bogus = dir.join("report.json");
    let out = sim().arg("tlog").arg(&bogus).output().unwrap();
    assert_eq!(out.status.code(), Some(2));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("report.json") && err.contains("MAVLink start marker"),
        "{err}"
    );
    let _ = std::fs::remove_dir_all(dir);
}

#[test]
fn explore_lists_the_voxels_behind_map_accuracy() {
    let dir = std::env::temp_dir().join(format!("harmonic-cli-errors-{}", std::process::id()));
    let csv = dir.with_extension("csv");
    let out = sim()
        .args([
            "explore",
            "--scenario",
            "apartment",
            "--noise",
            "stereo",
            "--max-scans",
            "3",
            "--quiet",
        ])
        .arg("--out")
        .arg(&dir)
        .arg("--map-errors")
        .arg(&csv)
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("report.json")).unwrap()).unwrap();
    let text = std::fs::read_to_string(&csv).unwrap();
    let mut lines = text.lines();
    let header: Vec<&str> = lines.next().unwrap().split(',').collect();
    assert_eq!(header[..4], ["error", "ix", "iy", "iz"]);
    let mut kinds = std::collections::BTreeMap::<&str, u64>::new();
    for line in lines {
        assert_eq!(line.split(',').count(), header.len(), "{line}");
        *kinds.entry(line.split(',').next().unwrap()).or_default() += 1;
    }
    // The file holds exactly the voxels the report counts.
    let accuracy = &report["map_accuracy"];
    for (kind, key) in [
        ("false_occupied", "false_occupied"),
        ("false_free", "false_free"),
        ("unseen", "unseen"),
        ("seen_only_here", "seen_only_here"),
    ] {
        assert_eq!(
            kinds.get(kind).copied().unwrap_or(0),
            accuracy[key].as_u64().unwrap(),
            "{kind}: {kinds:?}"
        );
    }
    assert!(kinds.get("unseen").copied().unwrap_or(0) > 0, "{kinds:?}");
    let _ = std::fs::remove_dir_all(dir);
    let _ = std::fs::remove_file(csv);
}

#[test]
fn bench_and_replay_reject_bad_input_with_one_line_and_exit_code_2() {
    let one_line = |args: &[&str], needle: &str| {
        let out = sim().args(args).output().unwrap();
        assert_eq!(out.status.code(), Some(2), "{args:?}");
        let err = String::from_utf8(out.stderr).unwrap();
        assert!(err.contains(needle), "{args:?}: {err}");
        err
    };
    let err = one_line(
        &["bench", "--planners", "closest-frontier,foo"],
        "unknown planner `foo`",
    );
    assert_eq!(err.trim_end().lines().count(), 1, "{err}");
    let err = one_line(&["bench", "--scenarios", "s1,atlantis"], "atlantis");
    assert_eq!(err.trim_end().lines().count(), 1, "{err}");
    one_line(&["bench", "--shard", "3/2"], "1 <= I <= N");
    one_line(&["bench", "--vehicle-radius", "0.7"], "between 0 and 0.6");
    one_line(&["bench", "--grid-offset", "0.05,0"], "X,Y,Z");
    one_line(&["explore", "--grid-offset", "0.1,0,0"], "grid offset 0.1 m");
    let err = one_line(
        &["bench", "merge", "--out", "/tmp/unused", "/nonexistent-shard"],
        "/nonexistent-shard",
    );
    assert_eq!(err.trim_end().lines().count(), 1, "{err}");
    let err = one_line(&["replay", "/nonexistent-recording"], "intrinsics");
    assert_eq!(err.trim_end().lines().count(), 1, "{err}");
    one_line(&["explore", "--noise", "stereo:1:4"], "odd number");
    one_line(
        &[
            "explore",
            "--mavlink",
            "emulator",
            "--mavlink-key",
            "/nonexistent-key",
        ],
        "--mavlink-key /nonexistent-key",
    );
    one_line(
        &["explore", "--stereo-model"],
        "give --noise or --depth-from stereo",
    );
    one_line(
        &["explore", "--noise", "stereo", "--surface-estimate"],
        "give --stereo-model",
    );
    one_line(
        &["explore", "--depth-rules", "surface"],
        "give --noise or --depth-from stereo",
    );
    one_line(
        &[
            "bench",
            "--depth-from",
            "stereo",
            "--depth-rules",
            "exact",
            "--stereo-model",
        ],
        "give one or the other",
    );
    one_line(&["explore", "--drift", "0.1"], "SIGMA_POS_M,SIGMA_YAW_RAD");
    one_line(&["explore", "--planner", "greedy"], "unknown planner");
    one_line(
        &[
            "explore",
            "--map-errors",
            "/tmp/unused.csv",
            "--out",
            "/tmp/unused",
        ],
        "give --noise, --depth-from stereo or --drift",
    );
}

/// `bench-solve --replay` re-solves the problems `explore --dump-problem` wrote, in order, as
/// the explorer does: one row per solver, every re-solve counted and converged.
#[test]
fn bench_solve_replays_the_problems_an_exploration_dumped() {
    let base = std::env::temp_dir().join(format!("harmonic-replay-{}", std::process::id()));
    let dumps = base.join("dumps");
    let out = sim()
        .args([
            "explore",
            "--scenario",
            "apartment",
            "--max-scans",
            "12",
            "--quiet",
        ])
        .arg("--dump-problem")
        .arg(&dumps)
        .arg("--out")
        .arg(base.join("run"))
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let dumped = std::fs::read_dir(&dumps)
        .unwrap()
        .filter(|e| {
            e.as_ref()
                .unwrap()
                .path()
                .extension()
                .is_some_and(|x| x == "json")
        })
        .count();
    assert!(dumped >= 3, "{dumped} problems dumped");
    let out = sim()
        .args(["bench-solve", "--repeat", "1", "--threads", "1", "--replay"])
        .arg(&dumps)
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let stdout = String::from_utf8_lossy(&out.stdout);
    let rows: Vec<Vec<&str>> = stdout
        .lines()
        .filter(|l| l.contains("dumps ("))
        .map(|l| l.split('|').map(str::trim).collect())
        .collect();
    assert_eq!(rows.len(), 2, "one row per solver: {stdout}");
    for (row, solver) in rows.iter().zip(["flat", "mg"]) {
        assert_eq!(row[4], solver, "{stdout}");
        // Every problem after the first is re-solved, in boxes or whole, and converges.
        let problems: usize = row[1]
            .rsplit_once('(')
            .and_then(|(_, n)| n.trim_end_matches(')').parse().ok())
            .unwrap();
        let (boxes, whole) = row[5].split_once(" / ").unwrap();
        let (boxes, whole): (usize, usize) = (boxes.parse().unwrap(), whole.parse().unwrap());
        assert_eq!(boxes + whole, problems - 1, "{stdout}");
        // The steps not replayed are counted: every dumped step is one or the other.
        let skipped: usize = row[2].parse().unwrap();
        assert_eq!(problems + skipped, dumped, "{stdout}");
        assert!(boxes > 0, "no re-solve stayed in boxes: {stdout}");
        assert_eq!(row[9], "0", "a re-solve did not converge: {stdout}");
    }
    // A damaged dump is an error naming it, not a step skipped: the last voxel of the first
    // step's grid made an undefined label (the data follow the header, so it is the file's last
    // byte).
    let first = std::fs::read_dir(&dumps)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|x| x == "npy"))
        .min()
        .unwrap();
    let mut bytes = std::fs::read(&first).unwrap();
    *bytes.last_mut().unwrap() = 9;
    std::fs::write(&first, bytes).unwrap();
    let out = sim()
        .args(["bench-solve", "--replay"])
        .arg(&dumps)
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("label 9") && err.contains("step_"), "{err}");
    // A directory without dumps is a one-line error, exit code 2.
    let out = sim()
        .args(["bench-solve", "--replay"])
        .arg(base.join("run"))
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&out.stderr).contains("dump-problem"));
    let _ = std::fs::remove_dir_all(base);
}
