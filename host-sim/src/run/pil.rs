//! Processor in the loop: the firmware makes every decision, on an emulated Cortex-M4F.
//!
//! [`run`] starts `qemu-system-arm -machine mps2-an386` on the firmware ELF (harmonic-fw) with
//! its UART0 and UART1 connected to two local TCP sockets, and plays everything outside the
//! board:
//!
//! - **the camera** on UART0: each scan is rendered at the vehicle's true pose and sent as the
//!   depth link's bytes ([`LinkEncoder`]: a camera Pose, the intrinsics, chunks of 10 rows). The
//!   firmware integrates it, plans, and answers on the same UART with the map (two bits per
//!   voxel) and a [`PlanReport`] for that frame: the lockstep's "frame N done";
//! - **the flight stack** on UART1: the [`FlightEmulator`] streams LOCAL_POSITION_NED and
//!   ATTITUDE at 20 Hz and flies the vehicle towards the setpoints the firmware streams. Every
//!   50 ms of simulated time is one *tick*: the emulator's bytes and a TIMESYNC request go out,
//!   and the tick ends when the firmware's TIMESYNC answer comes back — by then it has acted on
//!   the pose and sent its setpoint (see `harmonic_fw::app`).
//!
//! Simulated time stands still while the firmware computes, so a run is deterministic whatever
//! the host's speed. QEMU runs with `-icount shift=0`: the board's clock advances 1 ns per
//! instruction, so the tick counts in each report are instruction counts (1 tick = 40
//! instructions at the board's 25 MHz) and the report's per-phase "milliseconds" are millions
//! of instructions.
//!
//! A scan ends its leg when the vehicle has flown the replan distance, or has reached the
//! firmware's setpoint and turned to its yaw, or after [`MAX_TICKS_PER_LEG`]. The run ends when
//! the firmware reports `Complete`, after three holds in a row, at the scan limit, or with an
//! error if the firmware stops answering (its defmt log, decoded with `defmt-print` when that
//! is installed, is in the output directory).
//!
//! For debugging: `HARMONIC_QEMU_ICOUNT=0` runs QEMU without `-icount` (the tick counts are then
//! host time), and `HARMONIC_QEMU_EXTRA` appends options, say
//! `-monitor unix:/tmp/m.sock,server=on,wait=off` to read the CPU's registers while it runs.

use std::io::Read;
use std::mem::MaybeUninit;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use harmonic_core::camera::DepthFrame;
use harmonic_core::companion::CompanionConfig;
use harmonic_core::downlink::{Downlink, DownlinkDecoder, GeometryAnswer, PlanReport, ReportOutcome};
use harmonic_core::explore::{forward_camera_pose, Fault};
use harmonic_core::link::{self, FrameDecoder, LinkCounters, LinkEncoder};
use harmonic_core::map::{MapGeometry, Occupancy};
use harmonic_core::mavlink::common::MavResult;
use harmonic_core::mavlink::common::TIMESYNC_DATA;
use harmonic_core::mavlink::{encode_v2, BridgeConfig, MavHeader, MavMessage, MavlinkDecoder, MAX_FRAME_LEN};
use harmonic_core::operator::{CommandResult, OperatorCommand, OperatorState};
use harmonic_fw::app as fw;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::Serialize;

use crate::link::depth_link::LinkReport;
use crate::link::fault::Faulty;
use crate::link::transport::{Pipe, Wire};
use crate::planners::HostStorage;
use crate::run::board::{machine_args, Board, InProcess, Port, Qemu, IN_PROCESS_TICK_HZ};
use crate::run::metrics::{Contact, Coverage, GroundTruth};
use crate::run::sim::{
    make_explorer, scenario_geometry, Report, ReturnHome, RunExplorer, SimConfig, SimError, StepRecord,
    Timing, Vehicle,
};
use crate::vehicle::autopilot::{GroundStation, MavlinkReport, OperatorEvent, TrafficReport};
use crate::vehicle::flight::{FlightEmulator, LinkSigning};
use crate::world::scenario::Scenario;

/// Flight ticks after which a leg ends even if the vehicle has not arrived (100 s).
pub const MAX_TICKS_PER_LEG: usize = 2000;
/// Simulated time that passes per scan while the operator holds the vehicle (paused, or
/// waiting for start), ms: the scripted ground station's commands come due meanwhile.
pub const OPERATOR_HOLD_MS: u64 = 1000;
/// Wall-clock seconds to wait for the firmware to answer one scan or tick.
pub const ANSWER_TIMEOUT_S: u64 = 600;
/// Instructions per board tick under `-icount shift=0` (1 ns each, 25 MHz timer).
pub const INSTRUCTIONS_PER_TICK: u64 = 40;

/// How to run the firmware.
#[derive(Debug, Clone)]
pub struct PilConfig {
    /// The firmware ELF; `None` builds it with cargo (release, thumbv7em-none-eabihf).
    pub firmware: Option<PathBuf>,
    /// The QEMU binary.
    pub qemu: String,
    /// Where the firmware's log goes (`firmware.defmt`, `firmware.log`, `qemu.log`).
    pub out: PathBuf,
    /// Commands another station sends on the same wire, unsigned, at simulated seconds: a
    /// firmware built with a signing key must refuse (and count) them. Empty by default.
    pub intruder: Vec<(f64, OperatorCommand)>,
}

/// The PIL report types live beside the [`Report`] that carries them (so that `sim` needs
/// nothing from here).
pub use crate::run::sim::{InstructionStat, PilReport};

/// The grid a run around the firmware maps: the scenario's, as the host's runs map it, if it is
/// within the firmware's capacity ([`fw::fits`]); otherwise the error names what the grid needs
/// and what the firmware has room for. The board checks the same again when the grid comes.
pub fn firmware_grid(scenario: &Scenario, cfg: &SimConfig) -> Result<MapGeometry, SimError> {
    let geometry = scenario_geometry(scenario, cfg.grid_offset)?;
    fw::fits(&geometry).map_err(|shortfall| {
        let d = geometry.dims();
        SimError::Grid(format!(
            "`{}` does not fit the firmware: {shortfall} (grid {}×{}×{} of {} m)",
            scenario.world.name,
            d.nx(),
            d.ny(),
            d.nz(),
            geometry.resolution()
        ))
    })?;
    Ok(geometry)
}

/// Builds the firmware with cargo into `target_dir` (the workspace's `target/` if `None`) and
/// returns the ELF's path.
pub fn build_firmware(target_dir: Option<&Path>) -> Result<PathBuf, SimError> {
    let target_dir = cargo_build_firmware(&[], "the firmware", target_dir)?;
    Ok(target_dir.join("thumbv7em-none-eabihf/release/harmonic-fw"))
}

/// Builds the firmware with `key` as its MAVLink signing key (`HARMONIC_FW_MAVLINK_KEY`) into
/// the workspace's `target/fw-signed/` and returns the ELF's path.
pub fn build_firmware_keyed(key: &harmonic_core::signing::SecretKey) -> Result<PathBuf, SimError> {
    let workspace = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let hex: String = key.as_bytes().iter().map(|b| format!("{b:02x}")).collect();
    let target_dir = cargo_build_firmware_env(
        &[],
        "the firmware (with the signing key)",
        Some(&workspace.join("target/fw-signed")),
        &[("HARMONIC_FW_MAVLINK_KEY", hex.as_str())],
    )?;
    Ok(target_dir.join("thumbv7em-none-eabihf/release/harmonic-fw"))
}

/// Builds the firmware example `name` (firmware/examples/NAME.rs, e.g. `stereo_bench`) like
/// [`build_firmware`] and returns the ELF's path.
pub fn build_firmware_example(name: &str, target_dir: Option<&Path>) -> Result<PathBuf, SimError> {
    let target_dir = cargo_build_firmware(&["--example", name], name, target_dir)?;
    Ok(target_dir
        .join("thumbv7em-none-eabihf/release/examples")
        .join(name))
}

/// `cargo build -p harmonic-fw --release --target thumbv7em-none-eabihf EXTRA` into
/// `target_dir` (the workspace's `target/` if `None`); returns the target directory.
fn cargo_build_firmware(extra: &[&str], what: &str, target_dir: Option<&Path>) -> Result<PathBuf, SimError> {
    cargo_build_firmware_env(extra, what, target_dir, &[])
}

/// [`cargo_build_firmware`] with `env` set for the build.
fn cargo_build_firmware_env(
    extra: &[&str],
    what: &str,
    target_dir: Option<&Path>,
    env: &[(&str, &str)],
) -> Result<PathBuf, SimError> {
    let workspace = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let target_dir = target_dir.map_or_else(|| workspace.join("target"), Path::to_path_buf);
    let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
    let status = Command::new(cargo)
        .current_dir(&workspace)
        .args([
            "build",
            "-p",
            "harmonic-fw",
            "--release",
            "--target",
            "thumbv7em-none-eabihf",
        ])
        .args(extra)
        .envs(env.iter().copied())
        .arg("--target-dir")
        .arg(&target_dir)
        .status()
        .map_err(|e| SimError::Config(format!("cargo build of {what}: {e}")))?;
    if !status.success() {
        return Err(SimError::Config(format!(
            "cargo build of {what} failed ({status})"
        )));
    }
    Ok(target_dir)
}

/// One configuration's line of `stereo_bench`'s output (`stereo key=value …`).
#[derive(Debug, Clone, Copy)]
pub struct StereoBenchLine<'a>(&'a str);

impl<'a> StereoBenchLine<'a> {
    /// The value printed for `key`, or `?`.
    pub fn field(&self, key: &str) -> &'a str {
        self.0
            .split_whitespace()
            .find_map(|kv| kv.strip_prefix(key).and_then(|v| v.strip_prefix('=')))
            .unwrap_or("?")
    }

    /// The value printed for `key` as a number (NaN if missing).
    pub fn num(&self, key: &str) -> f64 {
        self.field(key).parse().unwrap_or(f64::NAN)
    }
}

/// The configuration lines `stereo_bench` (firmware/examples) printed, once its checks hold:
/// the core's check of the DSP kernels against the portable ones on random rows ran and
/// passed, and every configuration's DSP and portable disparities were identical.
pub fn stereo_bench_lines(out: &str) -> Result<Vec<StereoBenchLine<'_>>, String> {
    let lines: Vec<StereoBenchLine<'_>> = out
        .lines()
        .filter(|l| l.starts_with("stereo "))
        .map(StereoBenchLine)
        .collect();
    if lines.is_empty() {
        return Err(format!("stereo_bench printed no results:\n{out}"));
    }
    if !out.lines().any(|l| l.trim() == "stereo_check dsp_agrees=1") {
        return Err(format!(
            "the DSP kernels disagree with the portable ones on random rows (or the check did not run):\n{out}"
        ));
    }
    let differ: Vec<String> = lines
        .iter()
        .filter(|l| l.field("identical") != "1")
        .map(|l| format!("window {} prefilter {}", l.field("window"), l.field("prefilter")))
        .collect();
    if !differ.is_empty() {
        return Err(format!(
            "the DSP and portable matchers gave different disparities: {}",
            differ.join(", ")
        ));
    }
    Ok(lines)
}

/// Runs an image that talks only over semihosting (no UARTs) under QEMU with `-icount shift=0`
/// until it exits, and returns what it printed. A non-zero exit status is an error.
pub fn run_semihosted(qemu: &str, elf: &Path, timeout: Duration) -> Result<String, SimError> {
    let args: Vec<String> = machine_args()
        .chain(["-kernel".into(), elf.display().to_string()])
        .collect();
    let mut child = Command::new(qemu)
        .args(&args)
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .map_err(|e| {
            SimError::Config(format!(
                "cannot start {qemu}: {e} (is qemu-system-arm installed?)"
            ))
        })?;
    let start = Instant::now();
    loop {
        match child.try_wait() {
            Ok(Some(status)) => {
                let mut out = String::new();
                if let Some(mut s) = child.stdout.take() {
                    let _ = s.read_to_string(&mut out);
                }
                if !status.success() {
                    return Err(SimError::Config(format!(
                        "{} exited with {status}: {out}",
                        elf.display()
                    )));
                }
                return Ok(out);
            }
            Ok(None) if start.elapsed() > timeout => {
                let _ = child.kill();
                let _ = child.wait();
                return Err(SimError::Config(format!(
                    "{} did not finish in {timeout:?}",
                    elf.display()
                )));
            }
            Ok(None) => std::thread::sleep(Duration::from_millis(20)),
            Err(e) => return Err(SimError::Config(format!("waiting for {qemu}: {e}"))),
        }
    }
}

/// The in-process pipe that gathers the camera's bytes for UART0 does not fail; if it did,
/// this says so.
fn pipe_error(e: std::io::Error) -> SimError {
    SimError::Config(format!("the camera's link buffer: {e}"))
}

fn io(what: &str) -> impl Fn(std::io::Error) -> SimError + '_ {
    move |e| SimError::Config(format!("{what}: {e}"))
}

/// The autopilot's side of UART1.
struct Autopilot {
    emulator: FlightEmulator,
    /// Decodes the firmware's bytes for the TIMESYNC answers.
    decoder: MavlinkDecoder,
    sequence: u8,
    ticks: u64,
    /// Signs the TIMESYNC requests with the run's key, on link 1 (the emulator signs on 0).
    signing: Option<LinkSigning>,
    /// The scripted ground station on the same wire (`--operator`).
    ground: Option<GroundStation>,
    /// [`PilConfig::intruder`]'s station: unsigned, unanswered by a signed firmware.
    intruder: Option<GroundStation>,
    /// The firmware's COMMAND_ACKs, matched to the commands sent in order.
    operator_events: Vec<OperatorEvent>,
    /// The firmware's operator state, from its latest HEARTBEAT.
    operator_state: Option<OperatorState>,
}

impl Autopilot {
    /// One flight tick at `now_ms`: pose out, TIMESYNC out, the firmware's answer in.
    fn tick(&mut self, board: &mut dyn Board, now_ms: u64, vehicle: &Vehicle) -> Result<(), SimError> {
        let mut out = Vec::new();
        self.emulator
            .poll(now_ms, &vehicle.position, vehicle.yaw, &mut out);
        if let Some(ground) = self.ground.as_mut() {
            out.extend(ground.due(
                now_ms,
                (
                    harmonic_core::mavlink::DEFAULT_SYSTEM_ID,
                    harmonic_core::mavlink::ONBOARD_COMPUTER_COMPONENT_ID,
                ),
            ));
        }
        if let Some(intruder) = self.intruder.as_mut() {
            out.extend(intruder.due(
                now_ms,
                (
                    harmonic_core::mavlink::DEFAULT_SYSTEM_ID,
                    harmonic_core::mavlink::ONBOARD_COMPUTER_COMPONENT_ID,
                ),
            ));
        }
        let ts1 = i64::try_from(now_ms)
            .unwrap_or(i64::MAX)
            .saturating_mul(1_000_000);
        let header = MavHeader {
            system_id: u32::from(harmonic_core::mavlink::DEFAULT_SYSTEM_ID),
            component_id: harmonic_core::mavlink::AUTOPILOT_COMPONENT_ID,
            sequence: self.sequence,
        };
        self.sequence = self.sequence.wrapping_add(1);
        let mut frame = [0u8; MAX_FRAME_LEN];
        let n = encode_v2(
            &header,
            &MavMessage::TIMESYNC(TIMESYNC_DATA { tc1: 0, ts1 }),
            &mut frame,
        )
        .map_err(|e| SimError::Config(format!("TIMESYNC: {e:?}")))?;
        let n = match self.signing.as_mut() {
            Some(s) => s.sign(&mut frame, n, now_ms),
            None => n,
        };
        out.extend_from_slice(&frame[..n]);
        board.send(Port::Mavlink, &out)?;
        self.ticks += 1;
        let start = Instant::now();
        let mut buf = [0u8; 4096];
        loop {
            let n = board.receive(Port::Mavlink, &mut buf)?;
            if n == 0 {
                board.check_alive()?;
                if start.elapsed() > Duration::from_secs(ANSWER_TIMEOUT_S) {
                    return Err(SimError::Config(format!("no TIMESYNC answer for {now_ms} ms")));
                }
                continue;
            }
            let bytes = &buf[..n];
            self.emulator.receive(now_ms, bytes);
            let mut answered = false;
            let (mut acks, mut state) = (Vec::new(), None);
            self.decoder.push(bytes, |_, m| match m {
                MavMessage::TIMESYNC(d) => answered |= d.tc1 != 0 && d.ts1 == ts1,
                MavMessage::COMMAND_ACK(d) => acks.push((d.command, d.result)),
                MavMessage::HEARTBEAT(d) => state = OperatorState::from_custom_mode(d.custom_mode),
                // "operator: paused" and the like: the change itself, before the next HEARTBEAT.
                MavMessage::STATUSTEXT(d) => {
                    let text = String::from_utf8_lossy(d.text.as_ref());
                    if let Some(name) = text.trim_end_matches('\0').strip_prefix("operator: ") {
                        state = (0..=6)
                            .filter_map(OperatorState::from_custom_mode)
                            .find(|s| s.name() == name)
                            .or(state);
                    }
                }
                _ => {}
            });
            if state.is_some() {
                self.operator_state = state;
            }
            for (command, result) in acks {
                self.acknowledged(now_ms, command, result);
            }
            if answered {
                return Ok(());
            }
        }
    }
}

impl Autopilot {
    /// Records the firmware's answer to the oldest unanswered command of the ground station
    /// with that MAV_CMD.
    fn acknowledged(
        &mut self,
        now_ms: u64,
        command: harmonic_core::mavlink::common::MavCmd,
        result: MavResult,
    ) {
        let Some(ground) = self.ground.as_ref() else {
            return;
        };
        let answered = self.operator_events.len();
        let asked = ground.sent().nth(answered);
        let result = match result {
            MavResult::MAV_RESULT_ACCEPTED => CommandResult::Accepted,
            MavResult::MAV_RESULT_UNSUPPORTED => CommandResult::Unsupported,
            _ => CommandResult::Denied,
        };
        self.operator_events.push(OperatorEvent {
            time_s: now_ms as f64 * 1e-3,
            command: asked.filter(|c| crate::vehicle::autopilot::command_long(*c).0 == command),
            result,
            // The state the firmware announced with the answer (or its latest HEARTBEAT's).
            state: self.operator_state.unwrap_or(OperatorState::Exploring),
        });
    }
}

/// The camera's side of UART0.
struct Camera {
    encoder: LinkEncoder,
    scratch: Vec<u8>,
    rows_per_chunk: u16,
    decoder: Box<DownlinkDecoder<2048>>,
    /// Reads the firmware's resend requests from the same bytes (the downlink decoder drops
    /// them as a type it does not know, and the other way round).
    requests: Box<FrameDecoder<256>>,
    /// Faults on the camera → firmware direction (`SimConfig::link.faults`); the return
    /// direction (map, reports, resend requests) stays clean.
    link: Faulty<Pipe>,
    /// What the camera side did about losses.
    arq: CameraArq,
    /// Most rows per chunk (the firmware decoder's capacity); `None` in
    /// [`Camera::adapt`]'s place when `--link-chunk-rows` fixes the size.
    max_rows_per_chunk: Option<u16>,
    /// Smoothed bit error rate the camera side infers from what it is asked again.
    ber: f32,
}

/// What the PIL camera side did about a faulty link.
#[derive(Debug, Clone, Copy, Default)]
struct CameraArq {
    requests_received: u32,
    chunks_resent: u32,
    bytes_resent: u64,
    /// Images sent again whole because the firmware neither acknowledged them nor asked for
    /// anything for [`REPEAT_IMAGE_AFTER`] (every chunk of one, or its Heartbeats, lost).
    images_repeated: u32,
    heartbeats_sent: u32,
    link_frames_sent: u64,
    bytes_sent: u64,
    /// Rows per chunk of each image, summed (for the mean).
    rows_per_chunk_sum: u64,
    images: u32,
}

/// Heartbeats sent after each image and each answer: the firmware asks for what is missing
/// when one arrives, so one must survive the line.
const HEARTBEAT_COPIES: usize = 3;
/// Wall time after which the camera side sends an image again whole if the firmware has
/// answered nothing.
const REPEAT_IMAGE_AFTER: Duration = Duration::from_secs(3);

impl Camera {
    /// Encodes `message` and puts it through the injector onto the link.
    fn put(&mut self, message: &link::Message<'_>) -> Result<(), SimError> {
        let n = self
            .encoder
            .encode(message, &mut self.scratch)
            .map_err(|e| SimError::Config(format!("depth link encoder: {e:?}")))?;
        let frame = self.scratch[..n].to_vec();
        self.put_frame(&frame)
    }

    fn put_frame(&mut self, frame: &[u8]) -> Result<(), SimError> {
        self.arq.link_frames_sent += 1;
        self.link.send(frame).map_err(pipe_error)
    }

    /// The Heartbeats that end what was put on the link, then everything onto UART0.
    fn send(&mut self, board: &mut dyn Board, frame_id: u32) -> Result<(), SimError> {
        for _ in 0..HEARTBEAT_COPIES {
            let heartbeat = link::Heartbeat {
                uptime_ms: 0,
                frames_sent: frame_id,
                frames_skipped: 0,
                sensor_errors: 0,
            };
            self.put(&link::Message::Heartbeat(heartbeat))?;
            self.arq.heartbeats_sent += 1;
        }
        self.flush_to(board)
    }

    /// Everything put on the link, through the injector, onto UART0.
    fn flush_to(&mut self, board: &mut dyn Board) -> Result<(), SimError> {
        self.link.flush().map_err(pipe_error)?;
        let mut wire = Vec::new();
        self.link.receive(&mut wire).map_err(pipe_error)?;
        self.arq.bytes_sent += wire.len() as u64;
        board.send(Port::Link, &wire)
    }

    /// Before the mission: sends the grid and waits for the board's answer, sending it again
    /// while no answer comes (a line that loses it). A refusal is an error that names what the
    /// grid needs and what the board has.
    fn open(&mut self, board: &mut dyn Board, geometry: &MapGeometry, name: &str) -> Result<(), SimError> {
        let start = Instant::now();
        let mut sent: Option<Instant> = None;
        let mut buf = [0u8; 256];
        loop {
            if sent.is_none_or(|t| t.elapsed() > REPEAT_IMAGE_AFTER) {
                self.put(&link::Message::Geometry(*geometry))?;
                self.flush_to(board)?;
                sent = Some(Instant::now());
            }
            let n = board.receive(Port::Link, &mut buf)?;
            if n == 0 {
                board.check_alive()?;
                if start.elapsed() > Duration::from_secs(ANSWER_TIMEOUT_S) {
                    return Err(SimError::Config(format!(
                        "{}: no answer to the grid",
                        board.name()
                    )));
                }
                continue;
            }
            for &b in &buf[..n] {
                match self.decoder.push(b) {
                    Some(Ok(Downlink::Geometry(GeometryAnswer::Taken { .. }))) => return Ok(()),
                    Some(Ok(Downlink::Geometry(GeometryAnswer::Refused(shortfall)))) => {
                        return Err(SimError::Grid(format!(
                            "the {} board refused `{name}`: {shortfall}",
                            board.name()
                        )))
                    }
                    _ => {}
                }
            }
        }
    }

    /// The image's pose and its depth (intrinsics, then chunks).
    fn image(&mut self, frame_id: u32, frame: &DepthFrame<'_>, pose: &link::Pose) -> Result<(), SimError> {
        self.put(&link::Message::Pose(*pose))?;
        let mut frames = Vec::new();
        self.encoder
            .encode_depth_frame(frame_id, frame, self.rows_per_chunk, &mut self.scratch, |b| {
                frames.push(b.to_vec())
            })
            .map_err(|e| SimError::Config(format!("depth link encoder: {e:?}")))?;
        for f in frames {
            self.put_frame(&f)?;
        }
        Ok(())
    }

    /// What `request` asks for of image `frame_id`.
    fn answer(
        &mut self,
        request: &link::ResendRequest,
        frame: &DepthFrame<'_>,
        pose: &link::Pose,
    ) -> Result<(), SimError> {
        self.arq.requests_received += 1;
        let (frames, chunks) = crate::link::depth_link::encode_answer(
            &mut self.encoder,
            &mut self.scratch,
            request,
            frame,
            pose,
            self.rows_per_chunk,
        )
        .map_err(|e| SimError::Config(format!("depth link encoder: {e:?}")))?;
        self.arq.chunks_resent += chunks;
        self.arq.bytes_resent += frames.iter().map(|f| f.len() as u64).sum::<u64>();
        for f in frames {
            self.put_frame(&f)?;
        }
        Ok(())
    }

    /// After an image's report: the bit error rate from what its first resend request asked
    /// for again (none: it arrived whole), and the chunk size that carries the most depth per
    /// byte at that rate — as `harmonic-sim`'s host link does (`crate::link::depth_link`).
    fn adapt(
        &mut self,
        intrinsics: &harmonic_core::camera::Intrinsics,
        first_request: Option<&link::ResendRequest>,
    ) {
        self.ber =
            crate::link::depth_link::smoothed_ber(self.ber, intrinsics, self.rows_per_chunk, first_request);
        if let Some(max) = self.max_rows_per_chunk {
            self.rows_per_chunk = link::best_rows_per_chunk(intrinsics.width(), self.ber, max);
        }
    }

    /// Sends one scan and waits for its report, updating `map` from the slices on the way and
    /// answering the firmware's resend requests.
    fn scan(
        &mut self,
        board: &mut dyn Board,
        frame_id: u32,
        frame: &DepthFrame<'_>,
        camera_pose: &nalgebra::Isometry3<f32>,
        map: &mut [Occupancy],
    ) -> Result<PlanReport, SimError> {
        let pose = link::Pose::from_isometry(frame_id, camera_pose)
            .map_err(|e| SimError::Config(format!("camera pose: {e:?}")))?;
        self.arq.images += 1;
        self.arq.rows_per_chunk_sum += u64::from(self.rows_per_chunk);
        let mut first_request = None;
        // The firmware acknowledges an image as soon as it is in (an empty request), before it
        // plans; until then silence means it heard nothing.
        let mut acknowledged = false;
        self.image(frame_id, frame, &pose)?;
        self.send(board, frame_id)?;
        let start = Instant::now();
        let mut heard = Instant::now();
        let mut buf = [0u8; 8192];
        loop {
            let n = board.receive(Port::Link, &mut buf)?;
            if n == 0 {
                board.check_alive()?;
                if start.elapsed() > Duration::from_secs(ANSWER_TIMEOUT_S) {
                    return Err(SimError::Config(format!("no report for frame {frame_id}")));
                }
                if self.link.injector().injected().is_some()
                    && !acknowledged
                    && heard.elapsed() > REPEAT_IMAGE_AFTER
                {
                    heard = Instant::now();
                    self.arq.images_repeated += 1;
                    self.image(frame_id, frame, &pose)?;
                    self.send(board, frame_id)?;
                }
                continue;
            }
            heard = Instant::now();
            let mut requests = Vec::new();
            self.requests.feed(&buf[..n], |m| {
                if let Ok(link::Message::ResendRequest(r)) = m {
                    requests.push(r);
                }
            });
            for &b in &buf[..n] {
                match self.decoder.push(b) {
                    Some(Ok(Downlink::Report(r))) if r.frame_id == frame_id => {
                        let request = first_request.or(requests.first().copied());
                        self.adapt(frame.intrinsics(), request.as_ref());
                        return Ok(r);
                    }
                    Some(Ok(m @ Downlink::MapSlice { first, count, .. })) => {
                        for k in 0..usize::from(count) {
                            if let (Some(slot), Some(state)) =
                                (map.get_mut(first as usize + k), m.slice_state(k))
                            {
                                *slot = state;
                            }
                        }
                    }
                    _ => {}
                }
            }
            if first_request.is_none() {
                first_request = requests.iter().find(|r| r.frame_id() == frame_id).copied();
            }
            for request in requests.iter().filter(|r| r.frame_id() == frame_id) {
                if request.is_empty() {
                    acknowledged = true;
                    continue;
                }
                self.answer(request, frame, &pose)?;
                self.send(board, frame_id)?;
            }
        }
    }
}

fn stat(values: impl Iterator<Item = u64>) -> InstructionStat {
    let (mut n, mut sum, mut max) = (0u64, 0u64, 0u64);
    for v in values {
        n += 1;
        sum += v;
        max = max.max(v);
    }
    InstructionStat {
        mean: if n == 0 { 0.0 } else { sum as f64 / n as f64 },
        max,
    }
}

/// Explores `scenario` with the firmware deciding, through QEMU. The scenario's grid must be
/// within the firmware's capacity ([`firmware_grid`]). `progress` is called after every scan.
pub fn run(
    scenario: &Scenario,
    cfg: &SimConfig,
    pil: &PilConfig,
    progress: impl FnMut(&StepRecord),
) -> Result<Report, SimError> {
    let wall = Instant::now();
    let geometry = firmware_grid(scenario, cfg)?;
    std::fs::create_dir_all(&pil.out).map_err(io("output directory"))?;
    let key = cfg.mavlink.as_ref().and_then(|m| m.signing_key.clone());
    let elf = match (&pil.firmware, &key) {
        (Some(p), _) => p.clone(),
        (None, None) => build_firmware(None)?,
        // The key is built in (the firmware's `MAVLINK_KEY`), into a target directory of its
        // own so the unkeyed build stays as it is.
        (None, Some(k)) => build_firmware_keyed(k)?,
    };
    if !elf.is_file() {
        return Err(SimError::Config(format!(
            "firmware ELF {} not found",
            elf.display()
        )));
    }
    let mut board = Qemu::start(&pil.qemu, &elf, &pil.out)?;
    let qemu = board.command().to_string();
    let flown = fly_firmware(&mut board, geometry, scenario, cfg, &pil.intruder, progress);
    drop(board);
    // The log explains a failed run too.
    decode_log(&elf, &pil.out);
    let mut report = flown?;
    if let Some(p) = report.pil.as_mut() {
        p.firmware = elf.display().to_string();
        p.qemu = qemu;
    }
    report.wall_time_s = wall.elapsed().as_secs_f64();
    Ok(report)
}

/// Offers `board` (waiting for its mission's grid) the grid `geometry`, as a run does before
/// its first scan: `Ok` once the board takes it; an error that names what the grid needs and
/// what the board has if it refuses (the board then waits for another grid).
pub fn offer_grid(
    board: &mut dyn Board,
    cfg: &SimConfig,
    geometry: &MapGeometry,
    name: &str,
) -> Result<(), SimError> {
    firmware_camera(cfg)?.open(board, geometry, name)
}

/// [`run`] with the firmware's companion in this process instead of on QEMU
/// ([`InProcess`]): the same code, grid, storage and configuration, built for the host, flown
/// the same way. The report's tick counts are host time, so it has no instruction counts
/// (`pil` is `None`).
pub fn run_in_process(
    scenario: &Scenario,
    cfg: &SimConfig,
    progress: impl FnMut(&StepRecord),
) -> Result<Report, SimError> {
    let wall = Instant::now();
    let geometry = firmware_grid(scenario, cfg)?;
    let key = cfg.mavlink.as_ref().and_then(|m| m.signing_key.clone());
    let mut storage = Box::new(fw::Storage::new());
    let mut slot = Box::new(MaybeUninit::uninit());
    let mut board = InProcess::start(&mut storage, &mut slot, key);
    fly_in_process(&mut board, wall, geometry, scenario, cfg, progress)
}

/// [`run_in_process`] with the run's own companion instead of the firmware's: the scenario's
/// grid (as the host's loop builds it), the run's planner and explorer configuration, the
/// host's storage, and the run's look-around, resend rounds, way home and signing key. The
/// world is played around it as around the firmware ([`fly_firmware`]).
pub fn run_companion(
    scenario: &Scenario,
    cfg: &SimConfig,
    progress: impl FnMut(&StepRecord),
) -> Result<Report, SimError> {
    let wall = Instant::now();
    let geometry = scenario_geometry(scenario, cfg.grid_offset)?;
    let mut storage = HostStorage::new(&geometry.dims());
    let mut depth = vec![0u16; cfg.camera.intrinsics.pixel_count()];
    let config = CompanionConfig {
        bridge: BridgeConfig::default(),
        arq_rounds: cfg.link.arq_rounds,
        return_home_after_complete: cfg.return_home,
        tick_hz: IN_PROCESS_TICK_HZ,
        signing_key: cfg.mavlink.as_ref().and_then(|m| m.signing_key.clone()),
        look_around: cfg.look_around,
    };
    // The two arms differ in the explorer's target choice only.
    let mut report = match make_explorer(cfg, geometry, &mut storage)? {
        RunExplorer::Harmonic(mut explorer) => {
            let mut board = InProcess::new(&mut explorer, &mut depth, config)?;
            fly_in_process(&mut board, wall, geometry, scenario, cfg, progress)
        }
        RunExplorer::Baseline(mut explorer) => {
            let mut board = InProcess::new(&mut explorer, &mut depth, config)?;
            fly_in_process(&mut board, wall, geometry, scenario, cfg, progress)
        }
    }?;
    report.explorer_bytes = Some(storage.bytes());
    Ok(report)
}

/// [`fly_firmware`] around a companion in this process, started at `wall`: the report has no
/// instruction counts (its ticks are host time) and the wall time of the whole run.
fn fly_in_process(
    board: &mut dyn Board,
    wall: Instant,
    geometry: MapGeometry,
    scenario: &Scenario,
    cfg: &SimConfig,
    progress: impl FnMut(&StepRecord),
) -> Result<Report, SimError> {
    let mut report = fly_firmware(board, geometry, scenario, cfg, &[], progress)?;
    report.pil = None;
    report.wall_time_s = wall.elapsed().as_secs_f64();
    Ok(report)
}

/// The depth link's camera side for the firmware's decoder: chunks of as many rows as it takes
/// (fewer with `--link-chunk-rows`), faults on the way in if the run injects any.
fn firmware_camera(cfg: &SimConfig) -> Result<Camera, SimError> {
    let intrinsics = cfg.camera.intrinsics;
    let rows = (1..=10u16)
        .rev()
        .find(|&r| link::max_depth_chunk_len(intrinsics.width(), r) <= fw::LINK_DECODER_BYTES)
        .unwrap_or(1);
    if intrinsics.pixel_count() > fw::MAX_DEPTH_PIXELS {
        return Err(SimError::Config(format!(
            "the camera's {} pixels exceed the firmware's {}",
            intrinsics.pixel_count(),
            fw::MAX_DEPTH_PIXELS
        )));
    }
    Ok(Camera {
        encoder: LinkEncoder::new(),
        scratch: vec![0; link::max_depth_chunk_len(intrinsics.width(), rows).max(link::max_encoded_len(64))],
        // `--link-chunk-rows` may ask for shorter chunks (a noisy line), never longer ones
        // than the firmware's decoder takes.
        rows_per_chunk: cfg.link.chunk_rows.map_or(rows, |r| r.clamp(1, rows)),
        decoder: Box::default(),
        requests: Box::new(FrameDecoder::new()),
        link: Faulty::new(Pipe::default(), cfg.link.faults, cfg.seed),
        arq: CameraArq::default(),
        max_rows_per_chunk: cfg.link.chunk_rows.is_none().then_some(rows),
        ber: 0.0,
    })
}

/// The flight stack's side: the emulator (signing with the run's key, if any), the scripted
/// ground station (`--operator`) and an unsigned `intruder` station.
fn firmware_autopilot(cfg: &SimConfig, intruder: &[(f64, OperatorCommand)]) -> Autopilot {
    let mavlink = cfg.mavlink.as_ref();
    let key = mavlink.and_then(|m| m.signing_key.clone());
    let mut emulator = FlightEmulator::new();
    if let Some(k) = &key {
        emulator = emulator.with_signing(k.clone());
    }
    let script = mavlink.map(|m| m.operator_script.clone()).unwrap_or_default();
    Autopilot {
        emulator,
        decoder: MavlinkDecoder::new(),
        sequence: 0,
        ticks: 0,
        signing: key.clone().map(|k| LinkSigning::new(k, 1)),
        ground: (!script.is_empty()).then(|| GroundStation::new(script, key.clone())),
        intruder: (!intruder.is_empty()).then(|| GroundStation::new(intruder.to_vec(), None)),
        operator_events: Vec::new(),
        operator_state: None,
    }
}

/// The run around a firmware companion on `board`: camera on its depth link, emulated flight
/// stack on its MAVLink, until it reports the end.
fn fly_firmware(
    board: &mut dyn Board,
    geometry: MapGeometry,
    scenario: &Scenario,
    cfg: &SimConfig,
    intruder: &[(f64, OperatorCommand)],
    mut progress: impl FnMut(&StepRecord),
) -> Result<Report, SimError> {
    let mut run = FirmwareRun::start(board, geometry, scenario, cfg, intruder)?;
    for step in 1..=cfg.max_scans {
        let (report, coverage) = run.scan(step)?;
        if let Some(record) = run.steps.last() {
            progress(record);
        }
        if !run.react(report, coverage)? {
            break;
        }
        if step == cfg.max_scans && run.return_start.is_some() {
            run.return_end = Some("scan_limit".into());
        }
    }
    // One more tick collects what the firmware sent after its last plan (the hold setpoint and
    // the "exploration complete" STATUSTEXT).
    run.tick()?;
    run.report()
}

/// A run around a firmware companion on a board: the camera on its depth link, the emulated
/// flight stack on its MAVLink, the vehicle, and the bookkeeping of the steps.
struct FirmwareRun<'a> {
    board: &'a mut dyn Board,
    scenario: &'a Scenario,
    cfg: &'a SimConfig,
    geometry: MapGeometry,
    truth: GroundTruth,
    camera: Camera,
    autopilot: Autopilot,
    /// The map as the downlink tells it.
    map: Vec<Occupancy>,
    rng: ChaCha8Rng,
    depth: Vec<u16>,
    vehicle: Vehicle,
    dt_ms: u64,
    now_ms: u64,
    budget: f32,
    path: f64,
    contact: Contact<'a>,
    steps: Vec<StepRecord>,
    /// Per scan: instructions of integrate, domain, solve, streamline.
    instructions: Vec<[u64; 4]>,
    /// Instructions of each full planning cycle of the exploration.
    plan_cycles: Vec<u64>,
    last: Option<PlanReport>,
    consecutive_holds: u32,
    termination: String,
    /// Where the way home began (after a complete exploration, or on the operator's word):
    /// the exploration's numbers are the ones up to there.
    return_start: Option<PilReturnStart>,
    return_end: Option<String>,
}

impl<'a> FirmwareRun<'a> {
    fn start(
        board: &'a mut dyn Board,
        geometry: MapGeometry,
        scenario: &'a Scenario,
        cfg: &'a SimConfig,
        intruder: &[(f64, OperatorCommand)],
    ) -> Result<Self, SimError> {
        let vehicle = Vehicle {
            position: scenario.start_position,
            yaw: scenario.start_yaw,
        };
        let mut run = Self {
            board,
            scenario,
            cfg,
            geometry,
            truth: GroundTruth::new(&scenario.world, &geometry, &scenario.start_position),
            camera: firmware_camera(cfg)?,
            autopilot: firmware_autopilot(cfg, intruder),
            map: vec![Occupancy::Unknown; geometry.dims().len()],
            rng: ChaCha8Rng::seed_from_u64(cfg.seed),
            depth: Vec::new(),
            contact: Contact::start(&scenario.world, &vehicle.position, cfg.body_radius),
            vehicle,
            dt_ms: (f64::from(cfg.dt) * 1e3).round() as u64,
            now_ms: 0,
            budget: if cfg.follow_full_path {
                f32::INFINITY
            } else {
                cfg.replan_distance
            },
            path: 0.0,
            steps: Vec::new(),
            instructions: Vec::new(),
            plan_cycles: Vec::new(),
            last: None,
            consecutive_holds: 0,
            termination: String::from("scan_limit"),
            return_start: None,
            return_end: None,
        };
        run.camera.open(run.board, &geometry, &scenario.world.name)?;
        run.autopilot.tick(run.board, run.now_ms, &run.vehicle)?;
        Ok(run)
    }

    /// One flight tick of simulated time.
    fn tick(&mut self) -> Result<(), SimError> {
        self.now_ms += self.dt_ms;
        self.autopilot.tick(self.board, self.now_ms, &self.vehicle)
    }

    /// Renders a scan at the vehicle's pose, sends it, and records the firmware's report of it;
    /// the report and the coverage of the downlinked map.
    fn scan(&mut self, step: u32) -> Result<(PlanReport, Coverage), SimError> {
        let pose = forward_camera_pose(&self.vehicle.position, self.vehicle.yaw);
        self.cfg
            .camera
            .render(&self.scenario.world, &pose, &mut self.rng, &mut self.depth);
        let frame = DepthFrame::new(self.cfg.camera.intrinsics, &self.depth)
            .map_err(|e| SimError::Config(format!("camera frame: {e:?}")))?;
        let report = self.camera.scan(self.board, step, &frame, &pose, &mut self.map)?;
        let map = &self.map;
        let coverage = self
            .truth
            .coverage_of(|i| map.get(i).copied().unwrap_or(Occupancy::Unknown));
        let ms = |ticks: u64| ticks as f64 * 1e3 / f64::from(report.tick_hz.max(1));
        let to_instr = |ticks: u64| ticks * INSTRUCTIONS_PER_TICK;
        let phases = [
            to_instr(report.integrate_ticks),
            to_instr(report.domain_ticks),
            to_instr(report.solve_ticks),
            to_instr(report.streamline_ticks),
        ];
        self.instructions.push(phases);
        let label = match report.outcome {
            ReportOutcome::Goal => "goal".to_string(),
            ReportOutcome::Kept => "kept".to_string(),
            ReportOutcome::Escape => "escape".to_string(),
            ReportOutcome::Complete => "complete".to_string(),
            ReportOutcome::Hold(f) => format!("hold:{f:?}"),
            ReportOutcome::Look => "look_around".to_string(),
        };
        // The planning budget is the exploration's (the way home plans with the same field).
        if matches!(report.outcome, ReportOutcome::Goal) && self.return_start.is_none() {
            self.plan_cycles.push(phases[1] + phases[2] + phases[3]);
        }
        let solved = !matches!(report.outcome, ReportOutcome::Kept);
        self.steps.push(StepRecord {
            step,
            position: report.position,
            yaw: report.yaw,
            outcome: label,
            frontier: report.frontier,
            unknowns: report.interior,
            coverage_free: coverage.free,
            integrate_ms: ms(report.integrate_ticks),
            domain_ms: ms(report.domain_ticks),
            solve_ms: ms(report.solve_ticks),
            streamline_ms: ms(report.streamline_ticks),
            solves: None,
            solves_in_boxes: None,
            solver_iterations: if solved { report.solver_iterations } else { 0 },
            solver_residual: report.solver_residual,
            solver_updates: if solved { report.solver_updates } else { 0 },
            frames_integrated: 1,
            streamline_m: report.streamline_length,
            path_length_m: self.path,
            goal: report.goal.map(|(p, _)| p),
            seals: report.errors.seals,
        });
        Ok((report, coverage))
    }

    /// Acts on a report: flies its goal, lets time pass while the operator holds, counts
    /// holds, notes the way home. False once the run is over.
    fn react(&mut self, report: PlanReport, coverage: Coverage) -> Result<bool, SimError> {
        let outcome = report.outcome;
        let operator = report.operator;
        let homeward = matches!(operator, Some(OperatorState::ReturningHome | OperatorState::Home));
        let ends_here = outcome == ReportOutcome::Complete && !self.cfg.return_home;
        if homeward && self.return_start.is_none() && !ends_here {
            self.return_start = Some(PilReturnStart {
                path: self.path,
                frames: report.frames,
                steps: self.steps.len(),
                now_ms: self.now_ms,
                coverage,
                report,
                after_complete: outcome == ReportOutcome::Complete,
            });
        }
        self.last = Some(report);
        match outcome {
            ReportOutcome::Complete if operator == Some(OperatorState::Home) => {
                self.return_end = Some("home".into());
                return Ok(false);
            }
            // Explored; the next frame plans the way home (unless the run ends here,
            // `SimConfig::return_home` false).
            ReportOutcome::Complete
                if operator == Some(OperatorState::ReturningHome) && self.cfg.return_home =>
            {
                self.consecutive_holds = 0;
                self.tick()?;
            }
            ReportOutcome::Complete => {
                self.termination = "complete".into();
                return Ok(false);
            }
            ReportOutcome::Hold(Fault::Operator) if operator == Some(OperatorState::Aborted) => {
                self.termination = "aborted".into();
                return Ok(false);
            }
            ReportOutcome::Hold(Fault::Operator) => {
                // Paused or waiting for start: not stuck. Time passes, holding, so the ground
                // station's next command comes due.
                self.consecutive_holds = 0;
                for _ in 0..OPERATOR_HOLD_MS / self.dt_ms.max(1) {
                    self.tick()?;
                }
            }
            ReportOutcome::Hold(fault) => {
                self.consecutive_holds += 1;
                if self.consecutive_holds >= 3 {
                    self.termination = format!("stuck:{fault:?}");
                    if self.return_start.is_some() {
                        self.return_end = Some(self.termination.clone());
                    }
                    return Ok(false);
                }
                // The firmware holds; one tick lets its hold setpoint reach the autopilot.
                self.tick()?;
            }
            _ => {
                self.consecutive_holds = 0;
                let leg = fly(
                    self.board,
                    &mut self.autopilot,
                    &mut self.vehicle,
                    &mut self.now_ms,
                    self.budget,
                    self.cfg,
                    &mut self.contact,
                )?;
                self.path += leg.distance;
            }
        }
        Ok(true)
    }

    /// The report: with a way home flown, the run's numbers are the exploration's, up to where
    /// it began.
    fn report(self) -> Result<Report, SimError> {
        let end = self
            .last
            .ok_or_else(|| SimError::Config("the firmware planned nothing".into()))?;
        let return_home = self.return_start.as_ref().map(|r| ReturnHome {
            termination: self
                .return_end
                .clone()
                .unwrap_or_else(|| self.termination.clone()),
            path_length_m: self.path - r.path,
            scans: end.frames.saturating_sub(r.frames),
            distance_to_home_m: f64::from((self.vehicle.position - self.scenario.start_position).norm()),
            time_s: self.now_ms.saturating_sub(r.now_ms) as f64 * 1e-3,
        });
        let map = &self.map;
        let (last, coverage, explored_path, explored_steps, termination) = match &self.return_start {
            Some(r) => {
                let termination = if r.after_complete {
                    "complete".into()
                } else {
                    self.return_end.clone().unwrap_or(self.termination.clone())
                };
                (r.report, r.coverage, r.path, r.steps, termination)
            }
            None => (
                end,
                self.truth
                    .coverage_of(|i| map.get(i).copied().unwrap_or(Occupancy::Unknown)),
                self.path,
                self.steps.len(),
                self.termination.clone(),
            ),
        };
        let unreachable_frontier_voxels = (termination == "complete").then_some(last.unreachable_frontier);
        let timing = Timing::of_steps(&self.steps);
        let dims = self.geometry.dims();
        let link = self.link_report(&end);
        let mavlink = self.mavlink_report(&end);
        let instructions = &self.instructions;
        let pil = PilReport {
            firmware: String::new(),
            qemu: String::new(),
            ticks: self.autopilot.ticks,
            downlink_dropped: self.camera.decoder.dropped(),
            integrate: stat(instructions.iter().take(explored_steps).map(|p| p[0])),
            domain: stat(instructions.iter().take(explored_steps).map(|p| p[1])),
            solve: stat(instructions.iter().take(explored_steps).map(|p| p[2])),
            streamline: stat(instructions.iter().take(explored_steps).map(|p| p[3])),
            plan_cycle: stat(self.plan_cycles.iter().copied()),
            steps: self.instructions.clone(),
        };
        Ok(Report {
            return_home,
            scenario: self.scenario.world.name.clone(),
            planner: "harmonic".into(),
            solver: "mg".into(),
            termination,
            coverage_free: coverage.free,
            coverage_surface: coverage.surface,
            coverage_observed: coverage.observed,
            free_marked_occupied: coverage.free_marked_occupied,
            path_length_m: explored_path,
            scans: last.frames,
            collisions: self.contact.collisions.len() as u32,
            collision_points: self.contact.collisions.clone(),
            min_clearance_m: self.contact.closest.0,
            min_clearance_at: self.contact.closest.1,
            integration_ops: last.integration_ops,
            planning_ops: last.planning_ops,
            local_solves: [0, 0],
            flight_time_s: self.now_ms as f64 * 1e-3,
            wall_time_s: 0.0,
            explorer_bytes: None,
            grid: [dims.nx(), dims.ny(), dims.nz()],
            resolution: self.geometry.resolution(),
            reachable_free_voxels: self.truth.reachable_free(),
            sealed_voxels: last.sealed,
            unreachable_frontier_voxels,
            timing,
            errors: last.errors,
            link,
            steps_taken: explored_steps as u32,
            grid_origin: self.geometry.origin().coords.into(),
            map_accuracy: None,
            final_drift: None,
            stereo: None,
            trajectory: Vec::new(),
            mavlink: Some(mavlink),
            pil: Some(pil),
            steps: self.steps,
        })
    }

    /// The depth link's numbers, the whole run's (the way home included), from the camera side
    /// and the firmware's last report `end`.
    fn link_report(&self, end: &PlanReport) -> LinkReport {
        let camera = &self.camera;
        let receiver: LinkCounters = end.link;
        let sent = self.steps.len() as u32;
        if camera.arq.images_repeated > 0 {
            eprintln!(
                "pil: {} images sent again whole (the firmware acknowledged none of them)",
                camera.arq.images_repeated
            );
        }
        LinkReport {
            transport: format!("{} uart0", self.board.name()),
            baud: self.cfg.link.baud,
            depth_frames_sent: sent,
            depth_frames_integrated: end.frames,
            depth_frames_lost: sent.saturating_sub(end.frames),
            receiver,
            link_frames_sent: camera.arq.link_frames_sent,
            bytes_sent: camera.arq.bytes_sent,
            bytes_received: receiver.bytes,
            heartbeats_sent: camera.arq.heartbeats_sent,
            injected: camera.link.injector().injected(),
            partial_frames_integrated: receiver.depth_frames_partial,
            arq_rounds: fw::ARQ_ROUNDS,
            resend_requests_sent: end.resend_requests,
            resend_requests_received: camera.arq.requests_received,
            chunks_resent: camera.arq.chunks_resent,
            bytes_resent: camera.arq.bytes_resent,
            rows_per_chunk_mean: camera.arq.rows_per_chunk_sum as f64 / f64::from(camera.arq.images.max(1)),
            rows_per_chunk_last: camera.rows_per_chunk,
            ber_estimate: f64::from(camera.ber),
            ..LinkReport::default()
        }
    }

    /// MAVLink as the flight stack saw it, and the firmware's verifier as its last report `end`
    /// told it.
    fn mavlink_report(&self, end: &PlanReport) -> MavlinkReport {
        let autopilot = &self.autopilot;
        let key = self.cfg.mavlink.as_ref().and_then(|m| m.signing_key.as_ref());
        MavlinkReport {
            endpoint: format!("emulator ({} uart1)", self.board.name()),
            traffic: TrafficReport::default(),
            tlog: None,
            // The firmware keeps no pose history: its frames come stamped over the depth link.
            pose_history: Default::default(),
            // The firmware's bridge keeps its counters on the board; these are its traffic as
            // the flight stack saw it arrive (the link is loss-free).
            bridge: harmonic_core::mavlink::BridgeCounters {
                setpoints_sent: autopilot.emulator.counters().setpoints_received,
                heartbeats_sent: autopilot.emulator.counters().heartbeats_received,
                status_texts_sent: autopilot.emulator.counters().status_texts_received,
                local_positions_received: autopilot.emulator.counters().local_positions_sent,
                attitudes_received: autopilot.emulator.counters().attitudes_sent,
                ..Default::default()
            },
            bridge_decoder: *autopilot.decoder.counters(),
            operator_commands: autopilot.operator_events.clone(),
            operator_state: autopilot.operator_state,
            bridge_signing: key.map(|_| end.signing),
            emulator_signing: autopilot.emulator.signing_counters(),
            emulator: Some(*autopilot.emulator.counters()),
            emulator_decoder: Some(*autopilot.emulator.decoder_counters()),
            status_texts: autopilot.emulator.status_texts().to_vec(),
        }
    }
}

/// Where a PIL run's way home began.
#[derive(Debug, Clone, Copy)]
struct PilReturnStart {
    /// Distance flown before it, m.
    path: f64,
    /// Frames the firmware had integrated.
    frames: u32,
    /// Scans taken (steps recorded) before it.
    steps: usize,
    /// Simulated time, ms.
    now_ms: u64,
    /// Coverage of the downlinked map then.
    coverage: crate::run::metrics::Coverage,
    /// The firmware's report then: the exploration's counters.
    report: PlanReport,
    /// The exploration was complete (rather than the operator calling the vehicle home).
    after_complete: bool,
}

/// Flies one leg: ticks until the vehicle has flown `budget` metres, or stands at the
/// firmware's setpoint facing its yaw, or [`MAX_TICKS_PER_LEG`] passed.
/// `contact` watches the body on the way.
fn fly(
    board: &mut dyn Board,
    autopilot: &mut Autopilot,
    vehicle: &mut Vehicle,
    now_ms: &mut u64,
    budget: f32,
    cfg: &SimConfig,
    contact: &mut Contact<'_>,
) -> Result<Leg, SimError> {
    let mut leg = Leg::default();
    let step_len = cfg.max_speed * cfg.dt;
    let yaw_step = cfg.max_yaw_rate * cfg.dt;
    let dt_ms = (f64::from(cfg.dt) * 1e3).round() as u64;
    let mut travelled = 0.0f32;
    let mut previous = None;
    for _ in 0..MAX_TICKS_PER_LEG {
        autopilot.tick(board, *now_ms, vehicle)?;
        let Some(sp) = autopilot.emulator.setpoint() else {
            break;
        };
        let here = (sp.position - vehicle.position).norm() < 1e-4
            && crate::run::sim::wrap_angle(sp.yaw - vehicle.yaw).abs() < 1e-3;
        let same = previous == Some((sp.position, sp.yaw));
        if travelled >= budget || (here && same) {
            break;
        }
        previous = Some((sp.position, sp.yaw));
        let s = vehicle.step_towards(&sp.position, step_len.min(budget - travelled));
        travelled += s;
        leg.distance += f64::from(s);
        vehicle.slew_yaw(sp.yaw, yaw_step);
        *now_ms += dt_ms;
        leg.time += f64::from(cfg.dt);
        contact.observe(&vehicle.position);
    }
    Ok(leg)
}

/// What one flight leg did.
#[derive(Debug, Clone, Default)]
struct Leg {
    distance: f64,
    time: f64,
}

/// The deepest stack the firmware used in a run, in bytes: the largest "stack high-water N of
/// M bytes" its decoded log (`firmware.log` in `out`) reports (it measures by stack painting,
/// `firmware/src/board/stack.rs`, after every plan). `None` if the log is missing or was not
/// decoded (defmt-print not installed).
pub fn stack_high_water(out: &Path) -> Option<u64> {
    let log = std::fs::read_to_string(out.join("firmware.log")).ok()?;
    log.lines()
        .filter_map(|l| l.split("stack high-water ").nth(1))
        .filter_map(|rest| rest.split_whitespace().next()?.parse::<u64>().ok())
        .max()
}

/// Decodes `firmware.defmt` into `firmware.log` with defmt-print, if it is installed.
fn decode_log(elf: &Path, out: &Path) {
    let Ok(input) = std::fs::File::open(out.join("firmware.defmt")) else {
        return;
    };
    let Ok(output) = std::fs::File::create(out.join("firmware.log")) else {
        return;
    };
    let decoded = Command::new("defmt-print")
        .arg("-e")
        .arg(elf)
        .stdin(input)
        .stdout(output)
        .stderr(Stdio::null())
        .status();
    if decoded.is_err() {
        let _ = std::fs::write(
            out.join("firmware.log"),
            "defmt-print is not installed (cargo install defmt-print): decode firmware.defmt with\n  defmt-print -e FIRMWARE.elf < firmware.defmt\n",
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stereo_bench_output_passes_only_with_both_checks() {
        let line = |window: u8, identical: u8| {
            format!("stereo width=100 window={window} prefilter=dog match_instructions=24736720 identical={identical}")
        };
        let good = format!("stereo_check dsp_agrees=1\n{}\n{}\n", line(11, 1), line(7, 1));
        let lines = stereo_bench_lines(&good).unwrap();
        assert_eq!(lines.len(), 2);
        assert_eq!(lines[0].field("window"), "11");
        assert_eq!(lines[0].num("match_instructions"), 24_736_720.0);
        assert!(lines[0].num("missing").is_nan());
        let differ = format!("stereo_check dsp_agrees=1\n{}\n{}\n", line(11, 1), line(7, 0));
        assert!(stereo_bench_lines(&differ)
            .unwrap_err()
            .contains("window 7 prefilter dog"));
        let kernels = format!("stereo_check dsp_agrees=0\n{}\n", line(11, 1));
        assert!(stereo_bench_lines(&kernels).is_err());
        assert!(
            stereo_bench_lines(&line(11, 1)).is_err(),
            "the kernel check must have run"
        );
        assert!(stereo_bench_lines("stereo_check dsp_agrees=1\n").is_err());
    }

    #[test]
    fn the_stack_high_water_is_the_deepest_the_log_reports() {
        let dir = std::env::temp_dir().join(format!("hx-stack-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        assert_eq!(stack_high_water(&dir), None, "no log");
        std::fs::write(
            dir.join("firmware.log"),
            "INFO  boot\nINFO  stack high-water 30972 of 36380 bytes\n\
             INFO  plan 3\nINFO  stack high-water 34548 of 36380 bytes\n",
        )
        .unwrap();
        assert_eq!(stack_high_water(&dir), Some(34548));
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn grids_within_the_firmware_capacity_are_flown_and_s2_is_refused_with_both_numbers() {
        let cfg = SimConfig::default();
        for name in [
            "pil-small",
            "apartment",
            "office",
            "two-level",
            "s1",
            "kitchen",
            "garage",
            "apartment-thesis",
        ] {
            let g = firmware_grid(&Scenario::builtin(name).unwrap(), &cfg).unwrap();
            assert!(g.dims().len() <= fw::CAPACITY, "{name}");
        }
        let e = firmware_grid(&Scenario::builtin("s2").unwrap(), &cfg).unwrap_err();
        let text = e.to_string();
        assert!(
            text.contains("500000 voxels") && text.contains("room for 458752"),
            "{text}"
        );
    }
}

/// What a firmware image occupies, from its ELF section headers.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize)]
pub struct ImageSize {
    /// Code and constants in flash: `.vector_table`, `.text`, `.rodata` and the load image of
    /// `.data`.
    pub flash: u64,
    /// `.data` (initialised statics).
    pub data: u64,
    /// `.bss` and `.uninit` (zeroed and uninitialised statics).
    pub bss: u64,
    /// The stack reserve the linker checks (`_stack_reserve` in memory.x), 0 if absent.
    pub stack_reserve: u64,
    /// RAM the image needs: `.data` + `.bss` + the stack reserve.
    pub ram: u64,
}

/// Reads the section sizes and the `_stack_reserve` symbol of a 32-bit little-endian ELF.
pub fn image_size(elf: &Path) -> Result<ImageSize, String> {
    let bytes = std::fs::read(elf).map_err(|e| format!("{}: {e}", elf.display()))?;
    let bad = || format!("{}: not a 32-bit little-endian ELF", elf.display());
    let u16_at = |o: usize| {
        bytes
            .get(o..o + 2)
            .map(|b| u16::from_le_bytes([b[0], b[1]]) as usize)
    };
    let u32_at = |o: usize| {
        bytes
            .get(o..o + 4)
            .map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as usize)
    };
    if bytes.get(..6) != Some(&[0x7F, b'E', b'L', b'F', 1, 1][..]) {
        return Err(bad());
    }
    let shoff = u32_at(0x20).ok_or_else(bad)?;
    let shentsize = u16_at(0x2E).ok_or_else(bad)?;
    let shnum = u16_at(0x30).ok_or_else(bad)?;
    let shstrndx = u16_at(0x32).ok_or_else(bad)?;
    struct Section {
        kind: usize,
        flags: usize,
        addr: usize,
        offset: usize,
        size: usize,
        link: usize,
    }
    let section = |k: usize| -> Option<Section> {
        let o = shoff + k * shentsize;
        Some(Section {
            kind: u32_at(o + 4)?,
            flags: u32_at(o + 8)?,
            addr: u32_at(o + 12)?,
            offset: u32_at(o + 16)?,
            size: u32_at(o + 20)?,
            link: u32_at(o + 24)?,
        })
    };
    // Section names are not needed: placement (flash or RAM) and type (bits or not) say it all.
    let _ = section(shstrndx).ok_or_else(bad)?;
    let name_of = |table: &Section, at: usize| -> String {
        let start = table.offset + at;
        let end = bytes[start.min(bytes.len())..]
            .iter()
            .position(|&b| b == 0)
            .map_or(bytes.len(), |p| start + p);
        String::from_utf8_lossy(bytes.get(start..end).unwrap_or(&[])).into_owned()
    };
    const ALLOC: usize = 2;
    const NOBITS: usize = 8;
    const SYMTAB: usize = 2;
    let mut size = ImageSize::default();
    for k in 0..shnum {
        let s = section(k).ok_or_else(bad)?;
        if s.kind == SYMTAB {
            let names = section(s.link).ok_or_else(bad)?;
            for sym in (s.offset..s.offset + s.size).step_by(16) {
                if u32_at(sym).is_some_and(|n| name_of(&names, n) == "_stack_reserve") {
                    size.stack_reserve = u32_at(sym + 4).unwrap_or(0) as u64;
                }
            }
        }
        if s.flags & ALLOC == 0 || s.size == 0 {
            continue;
        }
        let in_ram = s.addr >= 0x2000_0000;
        match (in_ram, s.kind == NOBITS) {
            (false, _) => size.flash += s.size as u64,
            (true, true) => size.bss += s.size as u64,
            (true, false) => {
                size.data += s.size as u64;
                size.flash += s.size as u64;
            }
        }
    }
    size.ram = size.data + size.bss + size.stack_reserve;
    Ok(size)
}
