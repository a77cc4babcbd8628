//! The MAVLink side of a run: the core's [`Bridge`] on the companion computer, and the
//! autopilot it talks to — the in-process [`FlightEmulator`], or a real PX4/ArduPilot (SITL or
//! hardware through a router) or ground station over UDP.
//!
//! | `--mavlink` | autopilot |
//! |---|---|
//! | `emulator` (or no value) | [`FlightEmulator`] in process; bytes through a pipe each way; simulated time |
//! | `udpin:HOST:PORT` | listen on `HOST:PORT`, answer whoever sent last (MAVProxy's `udpin`); wall-clock time |
//! | `udpout:HOST:PORT` | send to `HOST:PORT`, take answers on the local port (MAVProxy's `udpout`); wall-clock time |
//!
//! Every MAVLink frame each way is decoded, counted by message name in [`TrafficReport`], and
//! written to the `.tlog` if one is open (see [`crate::vehicle::tlog`]). Every pose sample the
//! bridge accepts also goes into a [`PoseHistory`] by the autopilot's `time_boot_ms`, from which
//! the simulator takes the pose of the instant each depth frame is captured at
//! ([`MavlinkLink::history`]). Against a remote autopilot the vehicle is wherever it says
//! (LOCAL_POSITION_NED + ATTITUDE or ODOMETRY); the simulator renders depth there.

use std::collections::BTreeMap;
use std::fmt;
use std::net::{SocketAddr, ToSocketAddrs, UdpSocket};
use std::path::PathBuf;
use std::str::FromStr;
use std::time::Duration;

use harmonic_core::mavlink::{
    common, encode_v2, Bridge, BridgeConfig, BridgeCounters, DecoderCounters, MavMessage, MavlinkDecoder,
    MavlinkMessage, PoseHistory, PoseHistoryCounters, Received, MAX_FRAME_LEN,
};
use harmonic_core::operator::{CommandResult, OperatorCommand, OperatorState};
use harmonic_core::signing::{SecretKey, VerifierCounters};
use nalgebra::Point3;
use serde::Serialize;

use crate::vehicle::flight::{EmulatorTiming, FlightCounters, FlightEmulator, FlightSetpoint, LinkSigning};
use crate::vehicle::tlog::{TlogWriter, SIM_EPOCH_US};

/// Which autopilot the bridge talks to (`--mavlink`).
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum MavlinkSpec {
    /// The in-process flight-stack emulator.
    Emulator,
    /// Listen on an address; answer the autopilot (the address its latest frame came from).
    UdpIn(SocketAddr),
    /// Send to an address.
    UdpOut(SocketAddr),
}

impl FromStr for MavlinkSpec {
    type Err = String;

    fn from_str(spec: &str) -> Result<Self, String> {
        let resolve = |rest: &str| -> Result<SocketAddr, String> {
            let Some((host, port)) = rest.rsplit_once(':') else {
                return Err(format!(
                    "`{spec}`: expected {}:HOST:PORT",
                    spec.split(':').next().unwrap_or("")
                ));
            };
            let port: u16 = port
                .parse()
                .map_err(|_| format!("`{spec}`: `{port}` is not a port number (0-65535)"))?;
            let host = host.trim_start_matches('[').trim_end_matches(']');
            (host, port)
                .to_socket_addrs()
                .map_err(|e| format!("`{spec}`: {e}"))?
                .next()
                .ok_or_else(|| format!("`{spec}`: `{host}` has no address"))
        };
        match spec.split_once(':') {
            None if spec == "emulator" => Ok(Self::Emulator),
            Some(("udpin", rest)) => Ok(Self::UdpIn(resolve(rest)?)),
            Some(("udpout", rest)) => Ok(Self::UdpOut(resolve(rest)?)),
            _ => Err(format!(
                "`{spec}`: unknown MAVLink endpoint (expected emulator, udpin:HOST:PORT or udpout:HOST:PORT)"
            )),
        }
    }
}

impl fmt::Display for MavlinkSpec {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Emulator => write!(f, "emulator"),
            Self::UdpIn(a) => write!(f, "udpin:{a}"),
            Self::UdpOut(a) => write!(f, "udpout:{a}"),
        }
    }
}

impl MavlinkSpec {
    /// True for a real autopilot: time is the wall clock, the vehicle flies itself.
    pub fn is_remote(&self) -> bool {
        !matches!(self, Self::Emulator)
    }
}

/// How the MAVLink side of a run is set up.
#[derive(Debug, Clone, PartialEq)]
pub struct MavlinkConfig {
    /// The autopilot.
    pub spec: MavlinkSpec,
    /// The bridge's configuration.
    pub bridge: BridgeConfig,
    /// The emulator also streams ODOMETRY.
    pub odometry: bool,
    /// The emulator's pose stream: rate, latency, clock, velocities.
    pub emulator: EmulatorTiming,
    /// Record every frame both ways in this `.tlog`.
    pub tlog: Option<PathBuf>,
    /// MAVLink 2 signing with this key (`--mavlink-key`): the bridge signs what it sends and
    /// acts only on frames the key signed; the emulator does the same.
    pub signing_key: Option<SecretKey>,
    /// With the emulator: a ground station (system 255, component 190) sends these operator
    /// commands as COMMAND_LONG at these simulated times (seconds), signed like everything
    /// else when a key is set.
    pub operator_script: Vec<(f64, OperatorCommand)>,
}

/// Pose samples kept per stream: 3.2 s at 20 Hz, 1.3 s at 50 Hz.
pub const POSE_HISTORY_LEN: usize = 64;

impl Default for MavlinkConfig {
    fn default() -> Self {
        Self {
            spec: MavlinkSpec::Emulator,
            bridge: BridgeConfig::default(),
            odometry: false,
            emulator: EmulatorTiming::default(),
            tlog: None,
            signing_key: None,
            operator_script: Vec::new(),
        }
    }
}

/// Messages each way, as seen at the companion computer; part of `report.json`.
#[derive(Debug, Clone, Default, Serialize)]
pub struct TrafficReport {
    /// Messages sent.
    pub messages_sent: u32,
    /// Messages received (decoded, from anyone).
    pub messages_received: u32,
    /// Messages sent, by name.
    pub sent_by_type: BTreeMap<String, u32>,
    /// Messages received, by name.
    pub received_by_type: BTreeMap<String, u32>,
    /// Bytes sent.
    pub bytes_sent: u64,
    /// Bytes received.
    pub bytes_received: u64,
    /// Messages that could not be sent (the socket would block, or the peer refused them).
    pub unsent: u32,
    /// SET_POSITION_TARGET_LOCAL_NEDs sent.
    pub setpoints_sent: u32,
    /// Setpoints per second between the first and the last.
    pub setpoint_rate_hz: f64,
    /// Longest time between two setpoints sent, ms.
    pub max_setpoint_gap_ms: u64,
    /// Time from the first to the last message either way, s.
    pub duration_s: f64,
}

#[derive(Debug, Default)]
struct Traffic {
    report: TrafficReport,
    first_ms: Option<u64>,
    last_ms: u64,
    first_setpoint_ms: Option<u64>,
    last_setpoint_ms: Option<u64>,
    status_texts: Vec<String>,
}

impl Traffic {
    fn seen(&mut self, now_ms: u64) {
        self.first_ms.get_or_insert(now_ms);
        self.last_ms = self.last_ms.max(now_ms);
    }

    fn sent(&mut self, now_ms: u64, message: &MavMessage, bytes: usize) {
        self.seen(now_ms);
        let r = &mut self.report;
        r.messages_sent += 1;
        r.bytes_sent += bytes as u64;
        *r.sent_by_type
            .entry(message.message_name().to_string())
            .or_insert(0) += 1;
        match message {
            MavMessage::SET_POSITION_TARGET_LOCAL_NED(_) => {
                r.setpoints_sent += 1;
                if let Some(last) = self.last_setpoint_ms {
                    r.max_setpoint_gap_ms = r.max_setpoint_gap_ms.max(now_ms.saturating_sub(last));
                }
                self.first_setpoint_ms.get_or_insert(now_ms);
                self.last_setpoint_ms = Some(now_ms);
            }
            MavMessage::STATUSTEXT(data) => self
                .status_texts
                .push(data.text.to_str().unwrap_or("<not UTF-8>").to_string()),
            _ => {}
        }
    }

    fn received(&mut self, now_ms: u64, message: &MavMessage) {
        self.seen(now_ms);
        self.report.messages_received += 1;
        *self
            .report
            .received_by_type
            .entry(message.message_name().to_string())
            .or_insert(0) += 1;
    }

    fn report(&self) -> TrafficReport {
        let mut r = self.report.clone();
        r.duration_s = self
            .first_ms
            .map(|first| self.last_ms.saturating_sub(first) as f64 * 1e-3)
            .unwrap_or(0.0);
        if let (Some(a), Some(b)) = (self.first_setpoint_ms, self.last_setpoint_ms) {
            if b > a {
                r.setpoint_rate_hz = f64::from(r.setpoints_sent.saturating_sub(1)) / ((b - a) as f64 * 1e-3);
            }
        }
        r
    }
}

/// What went over MAVLink in a run; part of `report.json`.
#[derive(Debug, Clone, Serialize)]
pub struct MavlinkReport {
    /// The autopilot (`--mavlink`).
    pub endpoint: String,
    /// Messages each way by type, setpoint rate and longest gap.
    pub traffic: TrafficReport,
    /// The core's bridge: messages sent and received, faults, stale-pose events.
    pub bridge: BridgeCounters,
    /// The bridge's decoder of the autopilot's bytes.
    pub bridge_decoder: DecoderCounters,
    /// Pose samples kept by the autopilot's clock: stored, reordered, restarts.
    pub pose_history: PoseHistoryCounters,
    /// The flight-stack emulator: setpoints taken and rejected, setpoint gaps, poses sent.
    pub emulator: Option<FlightCounters>,
    /// The emulator's decoder of the bridge's bytes.
    pub emulator_decoder: Option<DecoderCounters>,
    /// With `--mavlink-key`: the frames the bridge accepted and refused (unsigned, forged,
    /// replayed, stale).
    pub bridge_signing: Option<VerifierCounters>,
    /// With `--mavlink-key` and the emulator: the frames the emulator accepted and refused.
    pub emulator_signing: Option<VerifierCounters>,
    /// STATUSTEXTs the bridge sent, in order.
    pub status_texts: Vec<String>,
    /// The `.tlog` written, and its records.
    pub tlog: Option<TlogInfo>,
    /// Operator COMMAND_LONGs the bridge took, in order, with its answers.
    pub operator_commands: Vec<OperatorEvent>,
    /// The operator state at the end (HEARTBEAT custom_mode); `None` where the bridge runs
    /// elsewhere (the firmware's, in processor-in-the-loop runs).
    pub operator_state: Option<OperatorState>,
}

/// An operator command the bridge answered.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct OperatorEvent {
    /// Simulated (or wall-clock) time it arrived, s.
    pub time_s: f64,
    /// What it asked (`None`: a command the explorer does not know).
    pub command: Option<OperatorCommand>,
    /// The COMMAND_ACK's answer.
    pub result: CommandResult,
    /// The operator state after it.
    pub state: OperatorState,
}

/// The scripted ground station of an emulator run ([`MavlinkConfig::operator_script`]), and
/// of a processor-in-the-loop run (`crate::run::pil`).
#[derive(Debug)]
pub(crate) struct GroundStation {
    script: Vec<(f64, OperatorCommand)>,
    next: usize,
    sequence: u8,
    signing: Option<LinkSigning>,
}

/// The MAV_CMD and param1 of the COMMAND_LONG a ground station sends for `command`.
pub(crate) fn command_long(command: OperatorCommand) -> (common::MavCmd, f32) {
    match command {
        OperatorCommand::Start => (common::MavCmd::MAV_CMD_MISSION_START, 0.0),
        OperatorCommand::Pause => (common::MavCmd::MAV_CMD_DO_PAUSE_CONTINUE, 0.0),
        OperatorCommand::Resume => (common::MavCmd::MAV_CMD_DO_PAUSE_CONTINUE, 1.0),
        OperatorCommand::Abort => (common::MavCmd::MAV_CMD_NAV_LOITER_UNLIM, 0.0),
        OperatorCommand::ReturnHome => (common::MavCmd::MAV_CMD_NAV_RETURN_TO_LAUNCH, 0.0),
    }
}

/// The ground station's ids: QGroundControl's system and MAV_COMP_ID_MISSIONPLANNER.
const GROUND_STATION: (u8, u8) = (255, 190);

impl GroundStation {
    /// A ground station that sends `script` (simulated seconds, command), signing with `key`
    /// on link 2 if given.
    pub(crate) fn new(script: Vec<(f64, OperatorCommand)>, key: Option<SecretKey>) -> Self {
        Self {
            script,
            next: 0,
            sequence: 0,
            signing: key.map(|key| LinkSigning::new(key, 2)),
        }
    }

    /// The commands sent so far, in order.
    pub(crate) fn sent(&self) -> impl Iterator<Item = OperatorCommand> + '_ {
        self.script.iter().take(self.next).map(|&(_, c)| c)
    }

    /// The frames of every command due at `now_ms`, addressed to `target`.
    pub(crate) fn due(&mut self, now_ms: u64, target: (u8, u8)) -> Vec<u8> {
        let mut out = Vec::new();
        while let Some(&(t_s, command)) = self.script.get(self.next) {
            if t_s * 1e3 > now_ms as f64 {
                break;
            }
            self.next += 1;
            let (cmd, param1) = command_long(command);
            let message = MavMessage::COMMAND_LONG(common::COMMAND_LONG_DATA {
                param1,
                command: cmd,
                target_system: target.0,
                target_component: target.1,
                ..common::COMMAND_LONG_DATA::DEFAULT
            });
            let header = harmonic_core::mavlink::MavHeader {
                system_id: u32::from(GROUND_STATION.0),
                component_id: GROUND_STATION.1,
                sequence: self.sequence,
            };
            self.sequence = self.sequence.wrapping_add(1);
            let mut frame = [0u8; MAX_FRAME_LEN];
            if let Ok(n) = encode_v2(&header, &message, &mut frame) {
                let n = match self.signing.as_mut() {
                    Some(s) => s.sign(&mut frame, n, now_ms),
                    None => n,
                };
                out.extend_from_slice(frame.get(..n).unwrap_or(&[]));
            }
        }
        out
    }
}

/// The `.tlog` of a run.
#[derive(Debug, Clone, Serialize)]
pub struct TlogInfo {
    /// Where it is.
    pub path: String,
    /// Frames recorded (both ways).
    pub records: u64,
}

/// A frame as it arrived: its sender (UDP), its bytes, its message if it decoded.
type ReceivedFrame = (
    Option<SocketAddr>,
    Vec<u8>,
    Option<(harmonic_core::mavlink::MavHeader, MavMessage)>,
);

#[derive(Debug)]
enum Endpoint {
    Emulator(Box<FlightEmulator>),
    Udp {
        socket: UdpSocket,
        /// Where messages go: fixed for udpout; for udpin the address the autopilot's latest
        /// admitted frame came from.
        peer: Option<SocketAddr>,
        learn_peer: bool,
    },
}

/// The MAVLink link of a run. See the [module documentation](self).
#[derive(Debug)]
pub struct MavlinkLink {
    /// The core's bridge.
    pub bridge: Bridge,
    label: String,
    decoder: MavlinkDecoder,
    endpoint: Endpoint,
    traffic: Traffic,
    tlog: Option<TlogWriter>,
    /// Timestamp of time 0 in the `.tlog`, µs since the epoch.
    epoch_us: u64,
    frames_out: Vec<(Vec<u8>, MavMessage)>,
    io_error: Option<String>,
    history: PoseHistory<POSE_HISTORY_LEN>,
    signing: Option<LinkSigning>,
    ground: Option<GroundStation>,
    operator_commands: Vec<OperatorEvent>,
}

impl MavlinkLink {
    /// Opens the link `config` describes (binds the UDP socket, creates the `.tlog`).
    pub fn open(config: &MavlinkConfig) -> Result<Self, String> {
        let bridge = Bridge::new(config.bridge).map_err(|e| format!("mavlink bridge: {e:?}"))?;
        let label = config.spec.to_string();
        let err = |e: std::io::Error| format!("--mavlink {label}: {e}");
        let endpoint = match &config.spec {
            MavlinkSpec::Emulator => {
                let emulator = FlightEmulator::new()
                    .with_odometry(config.odometry)
                    .with_timing(config.emulator);
                Endpoint::Emulator(Box::new(match &config.signing_key {
                    Some(key) => emulator.with_signing(key.clone()),
                    None => emulator,
                }))
            }
            MavlinkSpec::UdpIn(addr) => {
                let socket = UdpSocket::bind(addr).map_err(err)?;
                socket.set_nonblocking(true).map_err(err)?;
                Endpoint::Udp {
                    socket,
                    peer: None,
                    learn_peer: true,
                }
            }
            MavlinkSpec::UdpOut(addr) => {
                let local: SocketAddr = if addr.is_ipv4() {
                    ([0, 0, 0, 0], 0).into()
                } else {
                    ([0u16; 8], 0).into()
                };
                let socket = UdpSocket::bind(local).map_err(err)?;
                socket.set_nonblocking(true).map_err(err)?;
                Endpoint::Udp {
                    socket,
                    peer: Some(*addr),
                    learn_peer: false,
                }
            }
        };
        let epoch_us = if config.spec.is_remote() {
            std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .map(|d| d.as_micros() as u64)
                .unwrap_or(0)
        } else {
            SIM_EPOCH_US
        };
        let tlog = config.tlog.as_deref().map(TlogWriter::create).transpose()?;
        Ok(Self {
            bridge,
            label,
            decoder: MavlinkDecoder::new(),
            endpoint,
            traffic: Traffic::default(),
            tlog,
            epoch_us,
            frames_out: Vec::new(),
            io_error: None,
            history: PoseHistory::new(),
            signing: config.signing_key.clone().map(|key| LinkSigning::new(key, 1)),
            ground: (!config.operator_script.is_empty() && !config.spec.is_remote())
                .then(|| GroundStation::new(config.operator_script.clone(), config.signing_key.clone())),
            operator_commands: Vec::new(),
        })
    }

    /// The local address of the UDP socket, if there is one.
    pub fn local_addr(&self) -> Option<SocketAddr> {
        match &self.endpoint {
            Endpoint::Udp { socket, .. } => socket.local_addr().ok(),
            Endpoint::Emulator(_) => None,
        }
    }

    /// True against a real autopilot.
    pub fn is_remote(&self) -> bool {
        matches!(self.endpoint, Endpoint::Udp { .. })
    }

    fn log(&mut self, now_ms: u64, frame: &[u8]) {
        if let Some(tlog) = self.tlog.as_mut() {
            if let Err(e) = tlog.write(self.epoch_us + now_ms * 1000, frame) {
                self.io_error.get_or_insert(e);
            }
        }
    }

    /// Autopilot → bridge: the emulator reports the vehicle at `position`/`yaw` (map frame)
    /// when due, or the datagrams that arrived are read; every frame is logged, counted and
    /// handed to the bridge.
    pub fn pull(&mut self, now_ms: u64, position: &Point3<f32>, yaw: f32) -> Result<(), String> {
        // Each datagram with its sender (UDP).
        let mut datagrams: Vec<(Option<SocketAddr>, Vec<u8>)> = Vec::new();
        match &mut self.endpoint {
            Endpoint::Emulator(emulator) => {
                let mut bytes = Vec::new();
                emulator.poll(now_ms, position, yaw, &mut bytes);
                datagrams.push((None, bytes));
                if let Some(ground) = self.ground.as_mut() {
                    let config = self.bridge.config();
                    datagrams.push((None, ground.due(now_ms, (config.system_id, config.component_id))));
                }
            }
            Endpoint::Udp { socket, .. } => {
                let mut buf = [0u8; 65536];
                loop {
                    match socket.recv_from(&mut buf) {
                        Ok((n, from)) => datagrams.push((Some(from), buf[..n].to_vec())),
                        Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => break,
                        // An ICMP "port unreachable" for an earlier send (nobody listening yet).
                        Err(e) if e.kind() == std::io::ErrorKind::ConnectionRefused => break,
                        Err(e) => return Err(format!("--mavlink {}: {e}", self.label)),
                    }
                }
            }
        }
        let mut frames: Vec<ReceivedFrame> = Vec::new();
        for (from, bytes) in &datagrams {
            self.traffic.report.bytes_received += bytes.len() as u64;
            self.decoder.push_frames(bytes, |raw, decoded| {
                frames.push((*from, raw.to_vec(), decoded.map(|(h, m)| (*h, m.clone()))));
            });
        }
        for (from, raw, decoded) in frames {
            self.log(now_ms, &raw);
            if self.signing.as_mut().is_some_and(|s| !s.admits(&raw)) {
                // Unsigned, forged, replayed or stale: logged, counted, never acted on.
                continue;
            }
            if let Some((header, message)) = decoded {
                // udpin answers the autopilot: learn its address from its own (admitted)
                // frames only, so a ground station sending commands to this port does not
                // draw the setpoints away from the autopilot.
                let config = self.bridge.config();
                let from_autopilot = header.system_id == u32::from(config.target_system)
                    && header.component_id == config.target_component;
                if let (
                    Endpoint::Udp {
                        peer,
                        learn_peer: true,
                        ..
                    },
                    Some(from),
                    true,
                ) = (&mut self.endpoint, from, from_autopilot)
                {
                    *peer = Some(from);
                }
                self.traffic.received(now_ms, &message);
                match self.bridge.handle(now_ms, &header, &message) {
                    Ok(Received::LocalPosition | Received::Attitude | Received::Odometry) => {
                        self.history.record(now_ms, &message);
                    }
                    Ok(Received::Command(command, result)) => self.operator_commands.push(OperatorEvent {
                        time_s: now_ms as f64 * 1e-3,
                        command,
                        result,
                        state: self.bridge.operator_state(),
                    }),
                    _ => {}
                }
            }
        }
        self.take_io_error()
    }

    /// Bridge → autopilot: whatever the bridge has due at `now_ms` is encoded and delivered;
    /// what was delivered is logged and counted.
    pub fn push(&mut self, now_ms: u64) -> Result<(), String> {
        if let Endpoint::Udp { peer: None, .. } = self.endpoint {
            // udpin before anyone spoke: nowhere to send. The bridge keeps its HEARTBEAT and
            // STATUSTEXTs due until there is.
            return Ok(());
        }
        let mut out = std::mem::take(&mut self.frames_out);
        out.clear();
        let signing = &mut self.signing;
        self.bridge.poll(now_ms, |header, message| {
            let mut frame = [0u8; MAX_FRAME_LEN];
            if let Ok(n) = encode_v2(header, message, &mut frame) {
                let n = match signing.as_mut() {
                    Some(s) => s.sign(&mut frame, n, now_ms),
                    None => n,
                };
                out.push((frame.get(..n).unwrap_or(&[]).to_vec(), message.clone()));
            }
        });
        for (frame, message) in &out {
            let delivered = match &mut self.endpoint {
                Endpoint::Emulator(emulator) => {
                    emulator.receive(now_ms, frame);
                    true
                }
                Endpoint::Udp { socket, peer, .. } => match peer {
                    Some(to) => match socket.send_to(frame, *to) {
                        Ok(_) => true,
                        Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => false,
                        Err(e) if e.kind() == std::io::ErrorKind::ConnectionRefused => false,
                        Err(e) => return Err(format!("--mavlink {}: {e}", self.label)),
                    },
                    None => false,
                },
            };
            if delivered {
                self.log(now_ms, frame);
                self.traffic.sent(now_ms, message, frame.len());
            } else {
                self.traffic.report.unsent += 1;
            }
        }
        self.frames_out = out;
        self.take_io_error()
    }

    fn take_io_error(&mut self) -> Result<(), String> {
        match self.io_error.take() {
            Some(e) => Err(e),
            None => Ok(()),
        }
    }

    /// The bridge's pose of the vehicle (map frame), or why there is none.
    pub fn pose(&self, now_ms: u64) -> Result<(Point3<f32>, f32), String> {
        self.bridge
            .pose(now_ms)
            .map(|p| (p.position, p.yaw))
            .map_err(|e| format!("no vehicle pose from {} at {now_ms} ms: {e:?}", self.label))
    }

    /// The pose samples the bridge accepted, by the autopilot's clock.
    pub fn history(&self) -> &PoseHistory<POSE_HISTORY_LEN> {
        &self.history
    }

    /// The in-process emulator's clock (`time_boot_ms`) at simulated time 0; `None` against a
    /// remote autopilot, whose clock only its messages tell.
    pub fn emulator_boot_ms(&self) -> Option<u64> {
        match &self.endpoint {
            Endpoint::Emulator(emulator) => Some(emulator.timing().boot_ms),
            Endpoint::Udp { .. } => None,
        }
    }

    /// The emulator's current setpoint (what the emulated vehicle flies to); `None` against a
    /// remote autopilot, or before the first setpoint.
    pub fn emulator_setpoint(&self) -> Option<FlightSetpoint> {
        match &self.endpoint {
            Endpoint::Emulator(emulator) => emulator.setpoint(),
            Endpoint::Udp { .. } => None,
        }
    }

    /// Flushes the `.tlog`.
    pub fn finish(&mut self) -> Result<(), String> {
        match self.tlog.as_mut() {
            Some(t) => t.flush(),
            None => Ok(()),
        }
    }

    /// Everything counted so far.
    pub fn report(&self) -> MavlinkReport {
        let (emulator, emulator_decoder, emulator_signing) = match &self.endpoint {
            Endpoint::Emulator(e) => (
                Some(*e.counters()),
                Some(*e.decoder_counters()),
                e.signing_counters(),
            ),
            Endpoint::Udp { .. } => (None, None, None),
        };
        MavlinkReport {
            endpoint: self.label.clone(),
            traffic: self.traffic.report(),
            bridge: *self.bridge.counters(),
            bridge_decoder: *self.decoder.counters(),
            pose_history: *self.history.counters(),
            emulator,
            emulator_decoder,
            bridge_signing: self.signing.as_ref().map(LinkSigning::counters),
            emulator_signing,
            status_texts: self.traffic.status_texts.clone(),
            tlog: self.tlog.as_ref().map(|t| TlogInfo {
                path: t.path().display().to_string(),
                records: t.records(),
            }),
            operator_commands: self.operator_commands.clone(),
            operator_state: Some(self.bridge.operator_state()),
        }
    }
}

/// Sleeps a little; the granularity of waiting for a remote autopilot.
pub(crate) fn nap() {
    std::thread::sleep(Duration::from_millis(2));
}

#[cfg(test)]
mod tests {
    use super::*;

    /// One MAVLink 2 frame of `message` from (`system`, `component`).
    fn frame(system: u8, component: u8, message: &MavMessage) -> Vec<u8> {
        let header = harmonic_core::mavlink::MavHeader {
            system_id: u32::from(system),
            component_id: component,
            sequence: 0,
        };
        let mut out = [0u8; MAX_FRAME_LEN];
        let n = encode_v2(&header, message, &mut out).unwrap();
        out[..n].to_vec()
    }

    #[test]
    fn udpin_answers_the_autopilot_not_a_ground_station_on_the_same_port() {
        let config = MavlinkConfig {
            spec: MavlinkSpec::UdpIn(([127, 0, 0, 1], 0).into()),
            ..MavlinkConfig::default()
        };
        let mut link = MavlinkLink::open(&config).unwrap();
        let port = link.local_addr().unwrap();
        let autopilot = UdpSocket::bind("127.0.0.1:0").unwrap();
        let gcs = UdpSocket::bind("127.0.0.1:0").unwrap();
        for s in [&autopilot, &gcs] {
            s.set_read_timeout(Some(Duration::from_millis(300))).unwrap();
        }
        let heartbeat = MavMessage::HEARTBEAT(common::HEARTBEAT_DATA::DEFAULT);
        autopilot.send_to(&frame(1, 1, &heartbeat), port).unwrap();
        let pause = MavMessage::COMMAND_LONG(common::COMMAND_LONG_DATA {
            command: common::MavCmd::MAV_CMD_DO_PAUSE_CONTINUE,
            target_system: 1,
            target_component: 191,
            ..common::COMMAND_LONG_DATA::DEFAULT
        });
        // The ground station speaks last; its command is taken, its address is not.
        std::thread::sleep(Duration::from_millis(20));
        gcs.send_to(&frame(255, 190, &pause), port).unwrap();
        std::thread::sleep(Duration::from_millis(20));
        link.pull(0, &Point3::origin(), 0.0).unwrap();
        assert_eq!(link.bridge.operator_state(), OperatorState::Paused);
        link.push(0).unwrap();
        let mut buf = [0u8; 2048];
        let got = autopilot.recv_from(&mut buf).map(|(n, _)| n).unwrap_or(0);
        assert!(got > 0, "the autopilot hears the bridge (HEARTBEAT, COMMAND_ACK)");
        assert!(
            gcs.recv_from(&mut buf).is_err(),
            "the ground station is not answered directly"
        );
    }

    #[test]
    fn endpoint_specs_parse_and_name_their_problems() {
        assert_eq!("emulator".parse::<MavlinkSpec>().unwrap(), MavlinkSpec::Emulator);
        assert_eq!(
            "udpin:0.0.0.0:14540".parse::<MavlinkSpec>().unwrap(),
            MavlinkSpec::UdpIn("0.0.0.0:14540".parse().unwrap())
        );
        assert_eq!(
            "udpout:127.0.0.1:14550"
                .parse::<MavlinkSpec>()
                .unwrap()
                .to_string(),
            "udpout:127.0.0.1:14550"
        );
        for (text, needle) in [
            ("tcp:1.2.3.4:5760", "unknown MAVLink endpoint"),
            ("udpin:14540", "expected udpin:HOST:PORT"),
            ("udpout:127.0.0.1:x", "`x` is not a port number"),
            ("emulator:1", "unknown MAVLink endpoint"),
        ] {
            let e = text.parse::<MavlinkSpec>().unwrap_err();
            assert!(e.contains(needle) && e.contains(text), "{text}: {e}");
        }
    }

    #[test]
    fn traffic_counts_rate_and_gaps() {
        use harmonic_core::mavlink::common::{HEARTBEAT_DATA, SET_POSITION_TARGET_LOCAL_NED_DATA};
        let mut t = Traffic::default();
        let sp = MavMessage::SET_POSITION_TARGET_LOCAL_NED(SET_POSITION_TARGET_LOCAL_NED_DATA::DEFAULT);
        for now in [0u64, 100, 200, 450, 550] {
            t.sent(now, &sp, 10);
        }
        t.sent(600, &MavMessage::HEARTBEAT(HEARTBEAT_DATA::DEFAULT), 5);
        t.received(700, &MavMessage::HEARTBEAT(HEARTBEAT_DATA::DEFAULT));
        let r = t.report();
        assert_eq!((r.setpoints_sent, r.max_setpoint_gap_ms), (5, 250));
        assert!((r.setpoint_rate_hz - 4.0 / 0.55).abs() < 1e-9);
        assert_eq!(r.sent_by_type.get("SET_POSITION_TARGET_LOCAL_NED"), Some(&5));
        assert_eq!(r.received_by_type.get("HEARTBEAT"), Some(&1));
        assert_eq!((r.messages_sent, r.bytes_sent), (6, 55));
        assert!((r.duration_s - 0.7).abs() < 1e-9);
    }
}
