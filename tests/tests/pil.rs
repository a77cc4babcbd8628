//! Processor in the loop: the firmware (harmonic-fw), built for the Cortex-M4F and run on QEMU's
//! mps2-an386, explores pil-small to completion with every decision its own, the same decisions
//! its companion makes when it runs in this process; and the image fits the board's 1 MiB RAM
//! budget.
//!
//! QEMU (`qemu-system-arm`) must be installed: `.ci/run` installs it. Without it this test
//! fails, loudly, rather than skip.

use std::path::{Path, PathBuf};
use std::process::Command;

use harmonic_sim::run::board::{Board, InProcess, Qemu};
use harmonic_sim::run::pil::{self, PilConfig};
use harmonic_sim::run::sim::{scenario_geometry, SimConfig};
use harmonic_sim::world::scenario::Scenario;

const TARGET: &str = "thumbv7em-none-eabihf";
const RAM_BUDGET: u64 = 1024 * 1024;

/// Builds the firmware in its own target directory (the outer `cargo test` holds the lock of
/// the workspace's), shared with the no_std build check.
fn firmware() -> PathBuf {
    let installed = Command::new("rustup")
        .args(["target", "list", "--installed"])
        .output();
    if !installed.is_ok_and(|o| String::from_utf8_lossy(&o.stdout).contains(TARGET)) {
        let ok = Command::new("rustup")
            .args(["target", "add", TARGET])
            .status()
            .is_ok_and(|s| s.success());
        assert!(
            ok,
            "the {TARGET} target is missing and `rustup target add {TARGET}` failed"
        );
    }
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../target/no-std-check");
    pil::build_firmware(Some(&dir)).expect("firmware builds (and fits memory.x)")
}

fn qemu() -> String {
    let qemu = "qemu-system-arm".to_string();
    let found = Command::new(&qemu)
        .arg("--version")
        .output()
        .is_ok_and(|o| o.status.success());
    assert!(
        found,
        "qemu-system-arm is not installed: the processor-in-the-loop test needs it \
         (apt-get install qemu-system-arm; .ci/run does this)"
    );
    qemu
}

/// The firmware explores pil-small under QEMU, and the same companion in this process decides
/// exactly as it does.
#[test]
fn firmware_explores_pil_small_under_qemu() {
    let qemu = qemu();
    let elf = firmware();

    let size = pil::image_size(&elf).expect("readable ELF");
    assert!(
        size.ram <= RAM_BUDGET,
        "the image needs {} bytes of RAM (.data + .bss + stack reserve), over the {RAM_BUDGET} budget: {size:?}",
        size.ram
    );
    assert!(size.stack_reserve >= 16 * 1024, "{size:?}");

    let scenario = Scenario::builtin("pil-small").expect("built-in");
    let out = Path::new(env!("CARGO_MANIFEST_DIR")).join("../target/pil-test");
    let cfg = PilConfig {
        firmware: Some(elf),
        qemu,
        out: out.clone(),
        intruder: Vec::new(),
    };
    let r = pil::run(&scenario, &SimConfig::default(), &cfg, |s| {
        if s.step.is_multiple_of(10) {
            eprintln!(
                "pil-small under QEMU: scan {} {} coverage {:.3}",
                s.step, s.outcome, s.coverage_free
            );
        }
    })
    .unwrap_or_else(|e| {
        let log = std::fs::read_to_string(out.join("qemu.log")).unwrap_or_default();
        panic!("processor-in-the-loop run failed: {e}\nQEMU: {log}")
    });
    assert_eq!(r.termination, "complete", "{:?}", r.errors);
    assert!(r.coverage_free >= 0.98, "free coverage {:.4}", r.coverage_free);
    assert_eq!(r.collisions, 0, "collisions at {:?}", r.collision_points);
    assert!(
        r.scans > 10 && r.path_length_m > 1.0,
        "implausibly short: {} scans",
        r.scans
    );
    assert_eq!(r.steps.len() as u32, r.scans, "one report per scan");
    // Every frame crossed the UART whole and was integrated by the firmware.
    assert_eq!(r.link.receiver.depth_frames_complete, r.scans, "{:?}", r.link);
    assert_eq!(r.link.depth_frames_integrated, r.scans, "{:?}", r.link);
    assert_eq!(
        r.link.receiver.crc_errors + r.link.receiver.malformed + r.link.receiver.missing_chunks,
        0,
        "{:?}",
        r.link
    );
    // The deepest stack the firmware measured (stack painting, in its log) fits the reserve the
    // linker keeps for it; without defmt-print the log is not decoded and there is no number.
    match pil::stack_high_water(&out) {
        Some(deepest) => assert!(
            deepest <= size.stack_reserve,
            "the stack went {deepest} bytes deep, past the {} memory.x reserves",
            size.stack_reserve
        ),
        None => eprintln!("stack high-water not checked: firmware.log not decoded (defmt-print missing)"),
    }
    let pil = r.pil.as_ref().expect("PIL details");
    assert_eq!(pil.downlink_dropped, 0, "damaged downlink frames");
    assert!(pil.plan_cycle.max > 0 && pil.integrate.mean > 0.0, "{pil:?}");
    // The firmware flew the vehicle: the flight stack took its setpoints.
    let mav = r.mavlink.as_ref().expect("MAVLink counters");
    let emulator = mav.emulator.expect("the PIL run flies against the emulator");
    assert!(emulator.setpoints_received > 10, "{emulator:?}");
    assert_eq!(emulator.setpoints_rejected, 0, "{emulator:?}");
    // Complete: said so, and (the run ends there, `return_home` being off) on the way home.
    assert!(
        mav.status_texts.iter().any(|t| t == "exploration complete"),
        "{:?}",
        mav.status_texts
    );
    assert_eq!(
        mav.operator_state,
        Some(harmonic_core::operator::OperatorState::ReturningHome)
    );

    // One loop: the same companion, with the firmware's grid, storage and configuration, built
    // for the host and flown the same way in this process, makes the same decisions: every
    // scan from the same pose, to the same outcome and goal.
    let host = pil::run_in_process(&scenario, &SimConfig::default(), |_| {}).expect("in-process run");
    let decisions = |r: &harmonic_sim::run::sim::Report| -> Vec<_> {
        r.steps
            .iter()
            .map(|s| (s.step, s.position, s.outcome.clone(), s.goal))
            .collect()
    };
    assert!(
        r.steps.iter().filter(|s| s.goal.is_some()).count() > 10,
        "the reports carry the goals"
    );
    assert_eq!(
        decisions(&host),
        decisions(&r),
        "the goals differ between QEMU and the host"
    );
    assert_eq!(
        (host.termination.as_str(), host.scans, host.path_length_m),
        (r.termination.as_str(), r.scans, r.path_length_m)
    );
    assert_eq!(
        host.planning_ops, r.planning_ops,
        "the same solves, cell for cell"
    );
}

/// A board is built with a capacity, not a grid: the firmware, under QEMU and in this process,
/// refuses s2's grid (500 000 voxels) naming both numbers, keeps waiting, and takes
/// pil-small's; a run refuses s2 before it starts, with the same numbers.
#[test]
fn the_board_refuses_a_grid_over_capacity_with_both_numbers_and_takes_the_next() {
    let cfg = SimConfig::default();
    let s2 = Scenario::builtin("s2").expect("built-in");
    let small = Scenario::builtin("pil-small").expect("built-in");
    let s2_grid = scenario_geometry(&s2, cfg.grid_offset).unwrap();
    let small_grid = pil::firmware_grid(&small, &cfg).expect("pil-small fits");
    let both_numbers = |e: &harmonic_sim::run::sim::SimError| {
        let text = e.to_string();
        assert!(
            text.contains("500000 voxels") && text.contains("room for 458752"),
            "{text}"
        );
    };
    let qemu = qemu();
    let out = Path::new(env!("CARGO_MANIFEST_DIR")).join("../target/pil-refusal-test");
    std::fs::create_dir_all(&out).unwrap();
    let mut on_qemu = Qemu::start(&qemu, &firmware(), &out).expect("QEMU starts");
    let mut storage = Box::new(harmonic_fw::app::Storage::new());
    let mut slot = Box::new(std::mem::MaybeUninit::uninit());
    let mut in_process = InProcess::start(&mut storage, &mut slot, None);
    for board in [&mut on_qemu as &mut dyn Board, &mut in_process] {
        let refused = pil::offer_grid(board, &cfg, &s2_grid, "s2").unwrap_err();
        assert!(refused.to_string().contains(board.name()), "{refused}");
        both_numbers(&refused);
        pil::offer_grid(board, &cfg, &small_grid, "pil-small").expect("the next grid is taken");
    }
    both_numbers(&pil::run_in_process(&s2, &cfg, |_| {}).unwrap_err());
}

/// The companion object with the run's own configuration (`--core companion`): s2, which is
/// over the firmware's capacity, explored to completion in this process with the
/// world played around it as around the firmware: depth over the link, setpoints over MAVLink,
/// the map back over the downlink.
#[test]
fn the_companion_object_explores_a_world_over_the_firmware_capacity() {
    let scenario = Scenario::builtin("s2").expect("built-in scenario");
    let cfg = SimConfig {
        return_home: true,
        ..SimConfig::default()
    };
    let r = pil::run_companion(&scenario, &cfg, |_| {}).expect("companion run");
    assert_eq!(r.termination, "complete", "{:?}", r.steps.last());
    assert!(r.coverage_free > 0.99, "free coverage {}", r.coverage_free);
    assert_eq!(r.collisions, 0);
    // It looked around first (the run's setting, not the firmware's) and came home.
    let looks = r.steps.iter().filter(|s| s.outcome == "look_around").count();
    assert_eq!(looks, cfg.look_around as usize - 1);
    let home = r.return_home.as_ref().expect("a way home");
    assert_eq!(home.termination, "home", "{home:?}");
}

/// The firmware built with a MAVLink signing key, under QEMU, with a ground station on the
/// autopilot's wire and a noisy depth link: it signs everything it sends (the flight stack
/// refuses anything else and still flies it), acts on the signed operator commands — pause,
/// resume, return home — and refuses the unsigned ones another station sends; it asks the
/// camera for the depth rows the line lost and plans from what came; it flies home to the
/// start and reports `home` there.
#[test]
fn signed_firmware_takes_operator_commands_and_flies_home_under_qemu() {
    use harmonic_core::operator::{CommandResult, OperatorCommand, OperatorState};
    use harmonic_sim::vehicle::autopilot::MavlinkConfig;

    let qemu = qemu();
    firmware(); // the target, installed if missing
    let key = harmonic_core::signing::SecretKey::new([0x5a; 32]);
    let elf = pil::build_firmware_keyed(&key).expect("the keyed firmware builds");
    let scenario = Scenario::builtin("pil-small").expect("built-in");
    let out = Path::new(env!("CARGO_MANIFEST_DIR")).join("../target/pil-operator-test");
    let mut sim = SimConfig {
        return_home: true,
        seed: 4242,
        ..SimConfig::default()
    };
    // The acceptance line of the host's faulty-link run: BER 1e-4, a tenth of the frames lost.
    sim.link.faults.bit_error_rate = 1e-4;
    sim.link.faults.frame_drop = 0.1;
    sim.mavlink = Some(MavlinkConfig {
        signing_key: Some(key),
        operator_script: vec![
            (4.0, OperatorCommand::Pause),
            (8.0, OperatorCommand::Resume),
            (12.0, OperatorCommand::ReturnHome),
        ],
        ..MavlinkConfig::default()
    });
    let cfg = PilConfig {
        firmware: Some(elf),
        qemu,
        out: out.clone(),
        // Unsigned: a pause at 9 s (while exploring) and an abort at 11 s, before the way home
        // (the coarser planning grid explores pil-small in well under 20 s).
        intruder: vec![(9.0, OperatorCommand::Pause), (11.0, OperatorCommand::Abort)],
    };
    let r = pil::run(&scenario, &sim, &cfg, |_| {}).unwrap_or_else(|e| {
        let log = std::fs::read_to_string(out.join("qemu.log")).unwrap_or_default();
        panic!("processor-in-the-loop run failed: {e}\nQEMU: {log}")
    });
    let mav = r.mavlink.as_ref().expect("MAVLink counters");
    let answers: Vec<_> = mav
        .operator_commands
        .iter()
        .map(|e| (e.command, e.result, e.state))
        .collect();
    assert_eq!(
        answers,
        [
            (
                Some(OperatorCommand::Pause),
                CommandResult::Accepted,
                OperatorState::Paused
            ),
            (
                Some(OperatorCommand::Resume),
                CommandResult::Accepted,
                OperatorState::Exploring
            ),
            (
                Some(OperatorCommand::ReturnHome),
                CommandResult::Accepted,
                OperatorState::ReturningHome
            ),
        ],
        "every signed command answered, and only those"
    );
    // The line lost chunks; the firmware asked for them again and integrated every image.
    let link = &r.link;
    assert!(
        link.resend_requests_sent > 0 && link.chunks_resent > 0,
        "{link:?}"
    );
    // The return channel is clean: every request the firmware sent arrived, bar one that can
    // cross the run's end (the firmware asks for the last image's rows while the camera side,
    // its report in, stops reading).
    assert!(
        link.resend_requests_received + 1 >= link.resend_requests_sent
            && link.resend_requests_received <= link.resend_requests_sent,
        "the return channel is clean: {link:?}"
    );
    assert_eq!(link.depth_frames_integrated, link.depth_frames_sent, "{link:?}");
    let home = r.return_home.as_ref().expect("a way home");
    assert_eq!(home.termination, "home", "{home:?}");
    assert!(home.distance_to_home_m <= 0.3, "{home:?}");
    assert_eq!(mav.operator_state, Some(OperatorState::Home));
    assert_eq!(r.collisions, 0, "collisions at {:?}", r.collision_points);
    // The flight stack took only signed frames from the firmware, and refused none.
    let emulator_side = mav.emulator_signing.expect("the emulator signs");
    assert!(emulator_side.accepted > 100, "{emulator_side:?}");
    let refused = emulator_side.unsigned
        + emulator_side.malformed
        + emulator_side.bad_signature
        + emulator_side.replayed
        + emulator_side.stale
        + emulator_side.too_many_streams;
    assert_eq!(refused, 0, "{emulator_side:?}");
    // The firmware refused the intruder's two unsigned commands and took everything signed.
    let firmware_side = mav.bridge_signing.expect("the firmware's verifier counts");
    assert_eq!(firmware_side.unsigned, 2, "{firmware_side:?}");
    assert_eq!(
        firmware_side.bad_signature + firmware_side.replayed + firmware_side.stale,
        0,
        "{firmware_side:?}"
    );
}

/// The stereo matcher's Cortex-M4 DSP path (`UQSUB8`, `UXTAB16`, `UADD16`, `SEL`, the core's
/// `dsp` feature) gives the portable code's disparities on the emulated MCU, bit for bit, in
/// every configuration `fw-budget --stereo` measures; and the core's own check of the two
/// kernels on random rows passes there.
#[test]
fn stereo_dsp_path_matches_the_portable_code_under_qemu() {
    let qemu = qemu();
    firmware();
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../target/no-std-check");
    let elf = pil::build_firmware_example("stereo_bench", Some(&dir)).expect("stereo_bench builds");
    let out = pil::run_semihosted(&qemu, &elf, std::time::Duration::from_secs(600))
        .expect("stereo_bench runs under QEMU");
    let lines = pil::stereo_bench_lines(&out).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(lines.len(), 4, "one line per configuration:\n{out}");
}
