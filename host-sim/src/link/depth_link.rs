//! The depth link as a run uses it: camera side, wire and core side, with bandwidth.
//!
//! ```text
//! camera side                         wire                         core side
//! LinkEncoder ─► Faulty ─► Paced ─► transport (pipe, TCP, serial) ─► DepthReceiver
//!  (frames)     (faults)  (baud rate,                                  (the core's)
//!  Heartbeat 1 Hz          simulated time)
//! ```
//!
//! The wire is a stack of [`Wire`]s built from the options: the transport, baud pacing around
//! it ([`Paced`]), fault injection around that ([`Faulty`], passing frames through unchanged
//! when no fault is configured).
//!
//! - The camera side encodes each depth image with its camera pose (a Pose message, then the
//!   image's Intrinsics and chunks: `harmonic_core::link`), and a link Heartbeat every
//!   [`HEARTBEAT_PERIOD_S`] of simulated time.
//! - Every frame passes the fault injector, then waits in a queue that drains at the baud rate: a byte takes 10 bit times (8N1), so a 100 × 100 image
//!   (about 20 kB) is on the wire for about 0.22 s at 921600 baud. [`DepthLink::tick`] moves the
//!   bytes whose time has come onto the [`Wire`] and hands whatever arrived to the core's
//!   `DepthReceiver`; the run keeps flying (and streaming MAVLink) between ticks.
//! - The core side keeps each image that came with its pose, whole or with the rows that
//!   arrived ([`harmonic_core::link::DepthAssembler`]: rows lost hold `NOT_RECEIVED`, which the
//!   integrator skips); the run integrates them. An image without its pose (the Pose frame was
//!   lost) cannot be placed in the map and is dropped, counted in
//!   [`LinkReport::frames_without_pose`].
//!
//! # Selective retransmission and chunk size
//!
//! ```text
//! core side: DepthReceiver::resend_request ─► Faulty ─► Paced (same baud) ─► Pipe ─► camera side
//! camera side: the rows, pose, intrinsics asked for ─► forward queue, as above
//! ```
//!
//! When the camera side has sent an image, the core side asks ([`DepthLink::request_missing`])
//! for what it lacks — rows, the pose, the intrinsics — in a `ResendRequest` over a return
//! channel that runs at the same baud rate and suffers the same faults (its own draws), at most
//! [`LinkConfig::arq_rounds`] times per image; the camera side keeps its last image and sends
//! what is asked again. Then the image is finished ([`DepthLink::finish_frame`]) with what
//! arrived. An image that arrived whole is acknowledged by an empty request (not waited for).
//! The real system would ask at a deadline (the image's bytes at the baud rate, plus a
//! margin); the simulation asks when the camera side's queue has drained. Over TCP and serial
//! the forward wire is the real one and the return channel is simulated in this process.
//!
//! From the first request or acknowledgement of each image the camera side learns how many of
//! its chunks were lost, turns that into a bit error rate
//! (`harmonic_core::link::estimate_bit_error_rate`, smoothed over images) and picks the chunk
//! size that carries the most depth per byte at that rate
//! (`harmonic_core::link::best_rows_per_chunk`, at most [`ROWS_PER_CHUNK`] rows), unless
//! [`LinkConfig::chunk_rows`] fixes it. A clean line keeps [`ROWS_PER_CHUNK`].

use harmonic_core::camera::{DepthFrame, Intrinsics};
use harmonic_core::link::{
    self, DepthReceiver, FrameDecoder, Heartbeat, LinkCounters, LinkEncoder, LinkEvent, Message,
    ResendRequest,
};
use nalgebra::Isometry3;
use serde::Serialize;

use crate::link::fault::{FaultConfig, FaultCounters, Faulty};
use crate::link::pacing::Paced;
use crate::link::transport::{self, Pipe, TransportSpec, Wire};

/// Default baud rate of the link.
pub const DEFAULT_BAUD: u32 = 921_600;
pub use crate::link::pacing::BITS_PER_BYTE;
/// Seconds between two camera-side link Heartbeats (1 Hz).
pub const HEARTBEAT_PERIOD_S: f64 = 1.0;
/// Decoder capacity of the core side: a chunk of [`ROWS_PER_CHUNK`] rows of an image up to
/// 400 px wide.
pub const DECODER_BYTES: usize = 8192;
/// Rows per depth chunk (fewer if a chunk would not fit [`DECODER_BYTES`]).
pub const ROWS_PER_CHUNK: u16 = 10;
/// How long the core side waits for bytes still travelling through an outside wire (TCP,
/// serial) after the camera side finished sending, if none arrive meanwhile.
pub const SETTLE_TIMEOUT_S: f64 = 2.0;
/// Default rounds of selective retransmission per image.
pub const DEFAULT_ARQ_ROUNDS: u8 = 4;
/// Weight of the newest image in the camera side's smoothed bit error rate.
const BER_SMOOTHING: f32 = 0.3;
/// Seed offset of the return channel's fault draws (its own stream of faults).
const RETURN_SEED: u64 = 0x5245_5455_524E;
/// Decoder capacity of the camera side's return channel: a full resend request.
const RETURN_DECODER_BYTES: usize = 128;

/// How the depth link is set up.
#[derive(Debug, Clone, PartialEq)]
pub struct LinkConfig {
    /// The wire.
    pub transport: TransportSpec,
    /// Baud rate; 10 bits per byte.
    pub baud: u32,
    /// Faults to inject (both ways).
    pub faults: FaultConfig,
    /// Resend requests per image at most (0: no retransmission, no return traffic).
    pub arq_rounds: u8,
    /// Rows per depth chunk, fixed; `None` adapts it to the bit error rate the camera side
    /// infers (see the [module documentation](self)).
    pub chunk_rows: Option<u16>,
}

impl Default for LinkConfig {
    fn default() -> Self {
        Self {
            transport: TransportSpec::Sim,
            baud: DEFAULT_BAUD,
            faults: FaultConfig::default(),
            arq_rounds: DEFAULT_ARQ_ROUNDS,
            chunk_rows: None,
        }
    }
}

/// Mean and maximum of a duration, milliseconds.
#[derive(Debug, Clone, Copy, Default, Serialize)]
pub struct MsStat {
    /// Mean, ms.
    pub mean_ms: f64,
    /// Maximum, ms.
    pub max_ms: f64,
}

impl MsStat {
    fn of(values: &[f64]) -> Self {
        let max = values.iter().copied().fold(0.0, f64::max);
        let mean = if values.is_empty() {
            0.0
        } else {
            values.iter().sum::<f64>() / values.len() as f64
        };
        Self {
            mean_ms: mean,
            max_ms: max,
        }
    }
}

/// What went over the depth link in a run; part of `report.json`.
#[derive(Debug, Clone, Default, Serialize)]
pub struct LinkReport {
    /// The wire (`--link`).
    pub transport: String,
    /// Baud rate.
    pub baud: u32,
    /// Depth images the camera side sent.
    pub depth_frames_sent: u32,
    /// Depth images the explorer integrated.
    pub depth_frames_integrated: u32,
    /// Depth images sent but never integrated, whatever the reason.
    pub depth_frames_lost: u32,
    /// Complete images that arrived without their pose (dropped: they cannot be placed).
    pub frames_without_pose: u32,
    /// Link frames the camera side encoded (Pose, Intrinsics, chunks, Heartbeats).
    pub link_frames_sent: u64,
    /// Bytes put on the wire (after fault injection).
    pub bytes_sent: u64,
    /// Bytes the core side received.
    pub bytes_received: u64,
    /// Link Heartbeats the camera side sent.
    pub heartbeats_sent: u32,
    /// Link Heartbeats the core side received.
    pub heartbeats_received: u32,
    /// Longest time between two Heartbeats received, ms (0 with fewer than two).
    pub max_heartbeat_gap_ms: f64,
    /// Images the camera side reported as sent in its last Heartbeat received.
    pub camera_frames_sent_reported: u32,
    /// Time from handing an image to the link until its last byte was on the wire, ms:
    /// its bytes at the baud rate, plus any wait behind a Heartbeat.
    pub transfer: MsStat,
    /// Seconds the wire was busy.
    pub wire_busy_s: f64,
    /// The core's receiver: frames decoded, every error counter (partial images in
    /// `depth_frames_partial`, their missing rows in `rows_missing`).
    pub receiver: LinkCounters,
    /// What the fault injector did; `None` without faults.
    pub injected: Option<FaultCounters>,
    /// Images integrated with rows missing.
    pub partial_frames_integrated: u32,
    /// Resend rounds allowed per image.
    pub arq_rounds: u8,
    /// Resend requests the core side sent (acknowledgements not counted).
    pub resend_requests_sent: u32,
    /// Empty requests (acknowledgements of whole images) the core side sent.
    pub acks_sent: u32,
    /// Requests and acknowledgements the camera side received intact.
    pub resend_requests_received: u32,
    /// Depth chunks the camera side sent again.
    pub chunks_resent: u32,
    /// Bytes of those chunks, poses and intrinsics sent again.
    pub bytes_resent: u64,
    /// Bytes put on the return channel.
    pub return_bytes_sent: u64,
    /// What the return channel's fault injector did; `None` without faults or requests.
    pub return_injected: Option<FaultCounters>,
    /// Rows per chunk of each image sent, mean.
    pub rows_per_chunk_mean: f64,
    /// Rows per chunk of the last image sent.
    pub rows_per_chunk_last: u16,
    /// The camera side's smoothed bit error rate estimate at the end.
    pub ber_estimate: f64,
}

/// An image the core side received, whole or partially, with its pose.
#[derive(Debug, Clone)]
pub struct ArrivedFrame {
    /// Image id.
    pub frame_id: u32,
    /// Its intrinsics.
    pub intrinsics: Intrinsics,
    /// Depth, mm, row-major; rows that never arrived hold `NOT_RECEIVED`.
    pub depth: Vec<u16>,
    /// Camera → map pose sent with it.
    pub camera_pose: Isometry3<f32>,
    /// Rows that never arrived (0: whole).
    pub missing_rows: u16,
}

impl ArrivedFrame {
    /// The image as the core takes it.
    pub fn frame(&self) -> Option<DepthFrame<'_>> {
        DepthFrame::new(self.intrinsics, &self.depth).ok()
    }
}

/// An image delivered before its pose arrived (the core side asks for the pose again).
#[derive(Debug)]
struct AwaitingPose {
    frame_id: u32,
    intrinsics: Intrinsics,
    depth: Vec<u16>,
    missing_rows: u16,
}

/// Core-side bookkeeping that the receiver's callback updates.
#[derive(Debug, Default)]
struct CoreSide {
    arrived: Vec<ArrivedFrame>,
    awaiting_pose: Vec<AwaitingPose>,
    frames_without_pose: u32,
    heartbeats_received: u32,
    last_heartbeat_s: Option<f64>,
    max_heartbeat_gap_s: f64,
    camera_frames_sent_reported: u32,
}

impl CoreSide {
    /// Takes one receiver event at simulated time `now_s`.
    fn on_event(&mut self, now_s: f64, event: LinkEvent<'_>) {
        match event {
            LinkEvent::Depth {
                frame_id,
                frame,
                pose,
                missing_rows,
            } => match pose {
                Some(pose) => self.arrived.push(ArrivedFrame {
                    frame_id,
                    intrinsics: *frame.intrinsics(),
                    depth: frame.depth_mm().to_vec(),
                    camera_pose: pose.isometry(),
                    missing_rows,
                }),
                None => self.awaiting_pose.push(AwaitingPose {
                    frame_id,
                    intrinsics: *frame.intrinsics(),
                    depth: frame.depth_mm().to_vec(),
                    missing_rows,
                }),
            },
            LinkEvent::Pose(pose) => {
                if let Some(k) = self
                    .awaiting_pose
                    .iter()
                    .position(|a| a.frame_id == pose.frame_id())
                {
                    let a = self.awaiting_pose.swap_remove(k);
                    self.arrived.push(ArrivedFrame {
                        frame_id: a.frame_id,
                        intrinsics: a.intrinsics,
                        depth: a.depth,
                        camera_pose: pose.isometry(),
                        missing_rows: a.missing_rows,
                    });
                }
            }
            LinkEvent::Heartbeat(h) => {
                self.heartbeats_received += 1;
                self.camera_frames_sent_reported = h.frames_sent;
                if let Some(last) = self.last_heartbeat_s {
                    self.max_heartbeat_gap_s = self.max_heartbeat_gap_s.max(now_s - last);
                }
                self.last_heartbeat_s = Some(now_s);
            }
            _ => {}
        }
    }

    /// Whether image `frame_id` arrived with its pose.
    fn placed(&self, frame_id: u32) -> bool {
        self.arrived.iter().any(|a| a.frame_id == frame_id)
    }
}

/// The camera side's copy of its last image, for resends.
#[derive(Debug)]
struct SentImage {
    frame_id: u32,
    intrinsics: Intrinsics,
    depth: Vec<u16>,
    pose: link::Pose,
    /// Rows per chunk of its first transmission.
    rows_per_chunk: u16,
    /// Whether its first request or acknowledgement has updated the error estimate.
    estimated: bool,
}

/// The return channel (core side → camera side) and the camera side's retransmission state.
struct ReturnChannel {
    /// The channel: faults, then pacing at the link's baud rate, to the camera side.
    wire: Faulty<Paced<Pipe>>,
    /// What came back, not yet decoded.
    arrived: Vec<u8>,
    decoder: FrameDecoder<RETURN_DECODER_BYTES>,
    encoder: LinkEncoder,
    /// Requests the core side sent for the image in progress.
    rounds: u8,
    /// Whether the image in progress was acknowledged.
    acked: bool,
    requests_sent: u32,
    acks_sent: u32,
    requests_received: u32,
    chunks_resent: u32,
    bytes_resent: u64,
    /// The camera side's smoothed bit error rate.
    ber: f32,
}

/// The depth link of a run. See the [module documentation](self).
pub struct DepthLink<'b> {
    label: String,
    baud: u32,
    // Camera side.
    encoder: LinkEncoder,
    scratch: Vec<u8>,
    /// Most rows per chunk the decoder takes (and the adaptive size's ceiling).
    max_rows_per_chunk: u16,
    rows_per_chunk: u16,
    rows_per_chunk_sum: u64,
    chunk_rows: Option<u16>,
    arq_rounds: u8,
    last_sent: Option<SentImage>,
    back: ReturnChannel,
    next_heartbeat_s: f64,
    heartbeats_sent: u32,
    depth_frames_sent: u32,
    link_frames_sent: u64,
    transfer_ms: Vec<f64>,
    // Wire: faults, then pacing at the baud rate, then the transport.
    wire: Faulty<Paced<Box<dyn Wire>>>,
    now_s: f64,
    // Core side.
    receiver: DepthReceiver<'b, DECODER_BYTES>,
    inbox: Vec<u8>,
    bytes_received: u64,
    core: CoreSide,
    depth_frames_integrated: u32,
    partial_frames_integrated: u32,
}

impl<'b> DepthLink<'b> {
    /// Opens the link's wire; `buffer` is the core side's image buffer (at least as many
    /// pixels as the camera's), `seed` seeds the fault injector.
    pub fn open(
        config: &LinkConfig,
        intrinsics: &Intrinsics,
        buffer: &'b mut [u16],
        seed: u64,
    ) -> Result<Self, String> {
        if config.baud == 0 {
            return Err("--link-baud: must be positive".into());
        }
        config.faults.check()?;
        let wire = transport::open(&config.transport, config.baud)?;
        let width = intrinsics.width();
        let rows = (1..=ROWS_PER_CHUNK)
            .rev()
            .find(|&r| link::max_depth_chunk_len(width, r) <= DECODER_BYTES)
            .unwrap_or(1);
        if let Some(r) = config.chunk_rows {
            if r == 0 || r > rows {
                return Err(format!(
                    "--link-chunk-rows {r}: must be 1 to {rows} (a chunk must fit the core's {DECODER_BYTES}-byte decoder)"
                ));
            }
        }
        Ok(Self {
            label: config.transport.to_string(),
            baud: config.baud,
            encoder: LinkEncoder::new(),
            scratch: vec![0; link::max_depth_chunk_len(width, rows).max(link::max_encoded_len(128))],
            max_rows_per_chunk: rows,
            rows_per_chunk: config.chunk_rows.unwrap_or(rows),
            rows_per_chunk_sum: 0,
            chunk_rows: config.chunk_rows,
            arq_rounds: config.arq_rounds,
            last_sent: None,
            back: ReturnChannel {
                wire: Faulty::new(
                    Paced::new(Pipe::default(), config.baud),
                    config.faults,
                    seed ^ RETURN_SEED,
                ),
                arrived: Vec::new(),
                decoder: FrameDecoder::new(),
                encoder: LinkEncoder::new(),
                rounds: 0,
                acked: false,
                requests_sent: 0,
                acks_sent: 0,
                requests_received: 0,
                chunks_resent: 0,
                bytes_resent: 0,
                ber: 0.0,
            },
            next_heartbeat_s: 0.0,
            heartbeats_sent: 0,
            depth_frames_sent: 0,
            link_frames_sent: 0,
            transfer_ms: Vec::new(),
            wire: Faulty::new(Paced::new(wire, config.baud), config.faults, seed),
            now_s: 0.0,
            receiver: DepthReceiver::new(buffer),
            inbox: Vec::new(),
            bytes_received: 0,
            core: CoreSide::default(),
            depth_frames_integrated: 0,
            partial_frames_integrated: 0,
        })
    }

    /// Camera side: one encoded frame onto the wire (its faults and its queue).
    fn stage(&mut self, n: usize) -> Result<(), String> {
        let frame = self.scratch.get(..n).unwrap_or(&[]);
        self.link_frames_sent += 1;
        self.wire.send(frame).map_err(|e| self.wire_error(e))
    }

    /// Camera side: the frames staged since the last call join the wire's queue; returns
    /// when their last byte will have left, in simulated seconds.
    fn enqueue_staged(&mut self) -> Result<f64, String> {
        self.wire.flush().map_err(|e| self.wire_error(e))?;
        Ok(self.wire.inner().busy_until_s())
    }

    fn wire_error(&self, e: std::io::Error) -> String {
        format!("--link {}: {e}", self.label)
    }

    /// Camera side: sends depth image `frame_id` and its camera pose, at the current time.
    pub fn send_image(
        &mut self,
        frame_id: u32,
        frame: &DepthFrame<'_>,
        camera_pose: &Isometry3<f32>,
    ) -> Result<(), String> {
        let wire_err = |e: link::LinkError| format!("depth link encoder: {e:?}");
        let pose =
            link::Pose::from_isometry(frame_id, camera_pose).map_err(|e| format!("camera pose: {e:?}"))?;
        let n = self
            .encoder
            .encode(&link::Message::Pose(pose), &mut self.scratch)
            .map_err(wire_err)?;
        self.stage(n)?;
        // The encoder hands out each frame in `scratch`; stage it through a copy, since the
        // closure cannot borrow `self` while the encoder does.
        let mut frames: Vec<Vec<u8>> = Vec::new();
        let mut scratch = std::mem::take(&mut self.scratch);
        let result =
            self.encoder
                .encode_depth_frame(frame_id, frame, self.rows_per_chunk, &mut scratch, |bytes| {
                    frames.push(bytes.to_vec())
                });
        self.scratch = scratch;
        result.map_err(wire_err)?;
        self.stage_all(&frames)?;
        let start = self.now_s;
        let done = self.enqueue_staged()?;
        self.transfer_ms.push((done - start) * 1e3);
        self.depth_frames_sent += 1;
        self.rows_per_chunk_sum += u64::from(self.rows_per_chunk);
        self.last_sent = Some(SentImage {
            frame_id,
            intrinsics: *frame.intrinsics(),
            depth: frame.depth_mm().to_vec(),
            pose,
            rows_per_chunk: self.rows_per_chunk,
            estimated: false,
        });
        self.back.rounds = 0;
        self.back.acked = false;
        Ok(())
    }

    /// Camera side: encoded frames onto the wire (its faults and its queue).
    fn stage_all(&mut self, frames: &[Vec<u8>]) -> Result<(), String> {
        for f in frames {
            self.link_frames_sent += 1;
            self.wire.send(f).map_err(|e| self.wire_error(e))?;
        }
        Ok(())
    }

    /// Core side: asks the camera side for what image `frame_id` still lacks (its rows, its
    /// pose, the intrinsics), if any and if rounds are left; true if a request went out (the
    /// caller lets the link run until it is answered, then asks again). With nothing missing
    /// the image is acknowledged once, which is not waited for.
    pub fn request_missing(&mut self, frame_id: u32) -> Result<bool, String> {
        if self.arq_rounds == 0 {
            return Ok(false);
        }
        let want_pose = !self.core.placed(frame_id);
        let request = match self.receiver.resend_request(frame_id, want_pose) {
            Some(r) if self.back.rounds < self.arq_rounds => {
                self.back.rounds += 1;
                self.back.requests_sent += 1;
                r
            }
            Some(_) => return Ok(false),
            None if !self.back.acked => {
                self.back.acked = true;
                self.back.acks_sent += 1;
                ResendRequest::new(frame_id)
            }
            None => return Ok(false),
        };
        let mut frame = [0u8; RETURN_DECODER_BYTES];
        let n = self
            .back
            .encoder
            .encode(&Message::ResendRequest(request), &mut frame)
            .map_err(|e| format!("depth link return channel: {e:?}"))?;
        let back_err = |e: std::io::Error| format!("depth link return channel: {e}");
        let back = &mut self.back.wire;
        back.send(frame.get(..n).unwrap_or(&[])).map_err(back_err)?;
        back.flush().map_err(back_err)?;
        Ok(!request.is_empty())
    }

    /// Core side: gives up waiting for image `frame_id`: delivers the rows that arrived (if no
    /// newer image displaced it already), and counts an image whose pose never came.
    pub fn finish_frame(&mut self) {
        let now_s = self.now_s;
        let core = &mut self.core;
        self.receiver.finish_frame(|event| core.on_event(now_s, event));
        self.core.frames_without_pose += self.core.awaiting_pose.len() as u32;
        self.core.awaiting_pose.clear();
    }

    /// Camera side: answers a request from the return channel (or takes an acknowledgement).
    fn answer(&mut self, request: &ResendRequest) -> Result<(), String> {
        self.back.requests_received += 1;
        let Some(sent) = self
            .last_sent
            .as_mut()
            .filter(|s| s.frame_id == request.frame_id())
        else {
            return Ok(());
        };
        if !sent.estimated {
            sent.estimated = true;
            self.back.ber = estimate_ber(self.back.ber, sent, request);
            if self.chunk_rows.is_none() {
                let width = sent.intrinsics.width();
                self.rows_per_chunk =
                    link::best_rows_per_chunk(width, self.back.ber, self.max_rows_per_chunk);
            }
        }
        let frame = DepthFrame::new(sent.intrinsics, &sent.depth).map_err(|e| format!("{e:?}"))?;
        let (frames, chunks) = encode_answer(
            &mut self.encoder,
            &mut self.scratch,
            request,
            &frame,
            &sent.pose,
            self.rows_per_chunk,
        )
        .map_err(|e| format!("depth link encoder: {e:?}"))?;
        self.back.chunks_resent += chunks;
        self.back.bytes_resent += frames.iter().map(|f| f.len() as u64).sum::<u64>();
        self.stage_all(&frames)?;
        self.enqueue_staged()?;
        Ok(())
    }

    /// True while bytes wait to go on the wire, either way.
    pub fn sending(&self) -> bool {
        self.wire.pending() || self.back.wire.pending()
    }

    /// Advances the link to simulated time `now_s`: a camera Heartbeat if one is due, the
    /// bytes whose time has come onto the wire, and whatever arrived into the core side.
    pub fn tick(&mut self, now_s: f64) -> Result<(), String> {
        self.now_s = now_s;
        self.wire.advance(now_s);
        self.back.wire.advance(now_s);
        if now_s >= self.next_heartbeat_s {
            self.next_heartbeat_s = now_s + HEARTBEAT_PERIOD_S;
            let heartbeat = Heartbeat {
                uptime_ms: (now_s * 1e3) as u32,
                frames_sent: self.depth_frames_sent,
                frames_skipped: 0,
                sensor_errors: 0,
            };
            let n = self
                .encoder
                .encode(&link::Message::Heartbeat(heartbeat), &mut self.scratch)
                .map_err(|e| format!("depth link encoder: {e:?}"))?;
            self.stage(n)?;
            self.enqueue_staged()?;
            self.heartbeats_sent += 1;
        }
        self.wire.release().map_err(|e| self.wire_error(e))?;
        self.receive()?;
        self.receive_returns()
    }

    /// Camera side: the return channel's bytes whose time has come, and the answers to them.
    fn receive_returns(&mut self) -> Result<(), String> {
        let back_err = |e: std::io::Error| format!("depth link return channel: {e}");
        self.back.wire.release().map_err(back_err)?;
        self.back.arrived.clear();
        self.back.wire.receive(&mut self.back.arrived).map_err(back_err)?;
        let mut requests = Vec::new();
        for &b in &self.back.arrived {
            if let Some(Ok(Message::ResendRequest(r))) = self.back.decoder.push(b) {
                requests.push(r);
            }
        }
        requests.iter().try_for_each(|r| self.answer(r))
    }

    /// Core side: takes in what the wire delivered.
    fn receive(&mut self) -> Result<(), String> {
        self.inbox.clear();
        let n = self
            .wire
            .receive(&mut self.inbox)
            .map_err(|e| format!("--link {}: {e}", self.label))?;
        if n == 0 {
            return Ok(());
        }
        self.bytes_received += n as u64;
        let now_s = self.now_s;
        let core = &mut self.core;
        self.receiver
            .feed(&self.inbox, |event| core.on_event(now_s, event));
        Ok(())
    }

    /// Core side, after the camera side finished sending: over an outside wire, waits (real
    /// time) until every byte sent came back, or none came for [`SETTLE_TIMEOUT_S`] (bytes
    /// lost on a real line). Immediate for the in-process pipe.
    pub fn settle(&mut self) -> Result<(), String> {
        if self.wire.is_immediate() {
            return Ok(());
        }
        let mut last_progress = std::time::Instant::now();
        while self.bytes_received < self.wire.inner().bytes_released()
            && last_progress.elapsed().as_secs_f64() < SETTLE_TIMEOUT_S
        {
            let before = self.bytes_received;
            self.receive()?;
            if self.bytes_received > before {
                last_progress = std::time::Instant::now();
            } else {
                std::thread::sleep(std::time::Duration::from_millis(1));
            }
        }
        Ok(())
    }

    /// The images that arrived whole since the last call, oldest first.
    pub fn take_arrived(&mut self) -> Vec<ArrivedFrame> {
        std::mem::take(&mut self.core.arrived)
    }

    /// Counts an image the explorer integrated.
    pub fn note_integrated(&mut self, frame: &ArrivedFrame) {
        self.depth_frames_integrated += 1;
        self.partial_frames_integrated += u32::from(frame.missing_rows > 0);
    }

    /// The link's statistics.
    pub fn report(&self) -> LinkReport {
        LinkReport {
            transport: self.label.clone(),
            baud: self.baud,
            depth_frames_sent: self.depth_frames_sent,
            depth_frames_integrated: self.depth_frames_integrated,
            depth_frames_lost: self
                .depth_frames_sent
                .saturating_sub(self.depth_frames_integrated),
            frames_without_pose: self.core.frames_without_pose,
            link_frames_sent: self.link_frames_sent,
            bytes_sent: self.wire.inner().bytes_released(),
            bytes_received: self.bytes_received,
            heartbeats_sent: self.heartbeats_sent,
            heartbeats_received: self.core.heartbeats_received,
            max_heartbeat_gap_ms: self.core.max_heartbeat_gap_s * 1e3,
            camera_frames_sent_reported: self.core.camera_frames_sent_reported,
            transfer: MsStat::of(&self.transfer_ms),
            wire_busy_s: self.wire.inner().busy_s(),
            receiver: self.receiver.counters(),
            injected: self.wire.injector().injected(),
            partial_frames_integrated: self.partial_frames_integrated,
            arq_rounds: self.arq_rounds,
            resend_requests_sent: self.back.requests_sent,
            acks_sent: self.back.acks_sent,
            resend_requests_received: self.back.requests_received,
            chunks_resent: self.back.chunks_resent,
            bytes_resent: self.back.bytes_resent,
            return_bytes_sent: self.back.wire.inner().bytes_queued(),
            return_injected: self
                .back
                .wire
                .injector()
                .injected()
                .filter(|_| self.back.wire.inner().bytes_queued() > 0),
            rows_per_chunk_mean: if self.depth_frames_sent == 0 {
                0.0
            } else {
                self.rows_per_chunk_sum as f64 / f64::from(self.depth_frames_sent)
            },
            rows_per_chunk_last: self
                .last_sent
                .as_ref()
                .map_or(self.rows_per_chunk, |s| s.rows_per_chunk),
            ber_estimate: f64::from(self.back.ber),
        }
    }
}

/// A camera side's answer to `request` for the image `frame` it sent with `pose`: the pose and
/// the intrinsics if asked for, then the rows asked for in chunks of `rows_per_chunk`, each an
/// encoded link frame; and how many of them are depth chunks. Used by [`DepthLink`] and by the
/// processor-in-the-loop camera (`crate::run::pil`).
pub(crate) fn encode_answer(
    encoder: &mut LinkEncoder,
    scratch: &mut [u8],
    request: &ResendRequest,
    frame: &DepthFrame<'_>,
    pose: &link::Pose,
    rows_per_chunk: u16,
) -> Result<(Vec<Vec<u8>>, u32), link::LinkError> {
    let mut frames = Vec::new();
    if request.wants_pose() {
        let n = encoder.encode(&Message::Pose(*pose), scratch)?;
        frames.push(scratch[..n].to_vec());
    }
    if request.wants_intrinsics() {
        let n = encoder.encode(&Message::Intrinsics(*frame.intrinsics()), scratch)?;
        frames.push(scratch[..n].to_vec());
    }
    let mut chunks = 0u32;
    for &rows in request.rows() {
        encoder.encode_rows(request.frame_id(), frame, rows, rows_per_chunk, scratch, |f| {
            chunks += 1;
            frames.push(f.to_vec());
        })?;
    }
    Ok((frames, chunks))
}

/// The camera side's bit error rate after the first request (or acknowledgement) for `sent`:
/// the chunks of its first transmission that the request asks for again count as lost.
fn estimate_ber(smoothed: f32, sent: &SentImage, request: &ResendRequest) -> f32 {
    smoothed_ber(smoothed, &sent.intrinsics, sent.rows_per_chunk, Some(request))
}

/// A camera side's bit error rate, smoothed, after one image of `intrinsics` sent in chunks of
/// `rows_per_chunk` rows: the chunks the first resend request for it asks for again count as
/// lost (`None`: the image arrived whole). Used by [`DepthLink`] and by the
/// processor-in-the-loop camera (`crate::run::pil`).
pub(crate) fn smoothed_ber(
    smoothed: f32,
    intrinsics: &Intrinsics,
    rows_per_chunk: u16,
    first_request: Option<&ResendRequest>,
) -> f32 {
    let (width, height) = (intrinsics.width(), intrinsics.height());
    let per = rows_per_chunk.max(1);
    let chunks = height.div_ceil(per);
    let lost = (0..chunks)
        .filter(|k| {
            let first = k.saturating_mul(per);
            let end = first.saturating_add(per).min(height);
            first_request.is_some_and(|request| {
                request.rows().iter().any(|&(f, n)| {
                    let e = f.saturating_add(n);
                    f < end && first < e
                })
            })
        })
        .count() as u32;
    let wire = link::max_depth_chunk_len(width, per);
    let now = link::estimate_bit_error_rate(u32::from(chunks), lost, wire);
    (1.0 - BER_SMOOTHING) * smoothed + BER_SMOOTHING * now
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Translation3, UnitQuaternion};

    fn image(w: u16, h: u16, seed: u16) -> (Intrinsics, Vec<u16>) {
        let intrinsics = Intrinsics::from_hfov(w, h, 1.3).unwrap();
        let depth = (0..usize::from(w) * usize::from(h))
            .map(|i| {
                if i % 17 == 0 {
                    0
                } else {
                    500 + (i as u16 % 300) * 10 + seed
                }
            })
            .collect();
        (intrinsics, depth)
    }

    fn pose(x: f32) -> Isometry3<f32> {
        Isometry3::from_parts(
            Translation3::new(x, 2.0, 1.0),
            UnitQuaternion::from_euler_angles(0.1, 0.2, 0.3),
        )
    }

    /// Sends `n` images, each followed by ticks of `dt` until the wire is idle.
    fn run(link: &mut DepthLink<'_>, intrinsics: Intrinsics, n: u16, dt: f64) -> (Vec<ArrivedFrame>, f64) {
        let mut t = 0.0;
        link.tick(t).unwrap();
        let mut arrived = Vec::new();
        for k in 0..n {
            let (_, depth) = image(intrinsics.width(), intrinsics.height(), k);
            let frame = DepthFrame::new(intrinsics, &depth).unwrap();
            link.send_image(u32::from(k) + 1, &frame, &pose(f32::from(k)))
                .unwrap();
            let mut wait = |link: &mut DepthLink<'_>| {
                while link.sending() {
                    t += dt;
                    link.tick(t).unwrap();
                }
                link.settle().unwrap();
            };
            wait(link);
            while link.request_missing(u32::from(k) + 1).unwrap() {
                wait(link);
            }
            link.finish_frame();
            arrived.extend(link.take_arrived());
        }
        (arrived, t)
    }

    /// Every row of an arrived image is the original's or wholly not received, as many as it
    /// says are missing.
    fn assert_rows_intact(a: &ArrivedFrame, original: &[u16]) {
        let width = usize::from(a.intrinsics.width());
        let mut lost = 0;
        for (row, want) in a.depth.chunks(width).zip(original.chunks(width)) {
            if row.iter().all(|&d| d == link::NOT_RECEIVED) {
                lost += 1;
            } else {
                assert_eq!(row, want, "image {} delivered a damaged row", a.frame_id);
            }
        }
        assert_eq!(lost, a.missing_rows, "image {}", a.frame_id);
    }

    #[test]
    fn images_take_their_time_on_the_wire_and_arrive_whole() {
        let (intrinsics, _) = image(100, 100, 0);
        let mut buffer = vec![0u16; 100 * 100];
        let config = LinkConfig::default();
        let mut link = DepthLink::open(&config, &intrinsics, &mut buffer, 1).unwrap();
        let (arrived, t) = run(&mut link, intrinsics, 5, 0.01);
        assert_eq!(arrived.len(), 5);
        for (k, a) in arrived.iter().enumerate() {
            let (_, depth) = image(100, 100, k as u16);
            assert_eq!(a.depth, depth);
            assert_eq!(a.frame_id, k as u32 + 1);
            assert!((a.camera_pose.translation.vector - pose(k as f32).translation.vector).norm() < 1e-6);
        }
        let r = link.report();
        // About 20 kB per image at 92160 bytes/s: 0.22 s each.
        let per_image = r.bytes_sent as f64 / 5.0 / 92_160.0;
        assert!(per_image > 0.2 && per_image < 0.23, "{per_image}");
        assert!(
            (r.transfer.mean_ms - per_image * 1e3).abs() < 2.0,
            "{:?}",
            r.transfer
        );
        // The run took at least the wire time; ticks of 10 ms add at most one each.
        assert!(
            t >= r.wire_busy_s && t < r.wire_busy_s + 5.0 * 0.011,
            "{t} vs {}",
            r.wire_busy_s
        );
        assert_eq!((r.depth_frames_sent, r.receiver.depth_frames_complete), (5, 5));
        assert_eq!(r.bytes_sent, r.bytes_received);
        assert_eq!(r.link_frames_sent, u64::from(r.receiver.frames_ok));
        assert_eq!(r.heartbeats_sent, 2, "at 0 s and 1 s");
        assert_eq!(r.heartbeats_received, 2);
        assert!(r.injected.is_none());
    }

    #[test]
    fn slower_baud_takes_longer() {
        let (intrinsics, _) = image(40, 30, 0);
        let mut times = Vec::new();
        for baud in [115_200, 921_600] {
            let mut buffer = vec![0u16; 40 * 30];
            let config = LinkConfig {
                baud,
                ..LinkConfig::default()
            };
            let mut link = DepthLink::open(&config, &intrinsics, &mut buffer, 1).unwrap();
            run(&mut link, intrinsics, 3, 0.005);
            times.push(link.report().transfer.mean_ms);
        }
        assert!((times[0] / times[1] - 8.0).abs() < 0.01, "{times:?}");
    }

    #[test]
    fn lost_frames_are_counted_on_both_ends() {
        let (intrinsics, _) = image(60, 40, 0);
        let mut buffer = vec![0u16; 60 * 40];
        let config = LinkConfig {
            faults: FaultConfig {
                frame_drop: 0.05,
                ..FaultConfig::default()
            },
            arq_rounds: 0,
            ..LinkConfig::default()
        };
        let mut link = DepthLink::open(&config, &intrinsics, &mut buffer, 9).unwrap();
        let (arrived, _) = run(&mut link, intrinsics, 60, 0.02);
        let r = link.report();
        let injected = r.injected.unwrap();
        assert!(injected.frames_dropped > 5, "{injected:?}");
        assert_eq!(
            u64::from(r.receiver.frames_ok),
            r.link_frames_sent - injected.frames_dropped
        );
        // Without retransmission nothing goes back.
        assert_eq!(
            (r.resend_requests_sent, r.acks_sent, r.return_bytes_sent),
            (0, 0, 0)
        );
        // Every image that arrived was sent, and each of its rows is intact or not received.
        for a in &arrived {
            let (_, depth) = image(60, 40, a.frame_id as u16 - 1);
            assert_rows_intact(a, &depth);
        }
        let partial = arrived.iter().filter(|a| a.missing_rows > 0).count() as u32;
        assert_eq!(partial, r.receiver.depth_frames_partial);
        assert!(partial > 0, "{r:?}");
        // A lost image arrived without its pose, was given up by the assembler, or lost every
        // frame: each is counted at most once.
        let lost = 60 - arrived.len() as u32;
        let counted = r.frames_without_pose + r.receiver.depth_frames_dropped;
        assert!(
            lost > 0 && counted > 0 && counted <= lost,
            "{lost} lost, {counted} counted"
        );
    }

    #[test]
    fn a_noisy_line_delivers_every_image_by_asking_again_with_smaller_chunks() {
        let (intrinsics, _) = image(100, 100, 0);
        let faults = FaultConfig {
            bit_error_rate: 1e-4,
            frame_drop: 0.1,
            ..FaultConfig::default()
        };
        let mut outcome = Vec::new();
        for arq_rounds in [0, DEFAULT_ARQ_ROUNDS] {
            let mut buffer = vec![0u16; 100 * 100];
            let config = LinkConfig {
                faults,
                arq_rounds,
                ..LinkConfig::default()
            };
            let mut link = DepthLink::open(&config, &intrinsics, &mut buffer, 4242).unwrap();
            let (arrived, _) = run(&mut link, intrinsics, 30, 0.01);
            for a in &arrived {
                let (_, depth) = image(100, 100, a.frame_id as u16 - 1);
                assert_rows_intact(a, &depth);
            }
            let rows: u32 = arrived.iter().map(|a| 100 - u32::from(a.missing_rows)).sum();
            outcome.push((arrived.len(), rows, link.report()));
        }
        let (placed_without, rows_without, without) = &outcome[0];
        let (placed, rows, with) = &outcome[1];
        // Without retransmission, chunks of 10 rows (2 kB) rarely survive a BER of 1e-4:
        // images come with a few of their rows, and a lost pose loses the image.
        assert_eq!(without.rows_per_chunk_last, ROWS_PER_CHUNK);
        assert!(
            *rows_without < 30 * 40,
            "{rows_without} rows of {placed_without} images"
        );
        // Asking again brings every image with its pose and nearly every row, and the
        // camera side, seeing most 10-row chunks lost, goes down to one row per chunk.
        assert_eq!(*placed, 30, "{with:?}");
        assert!(*rows >= 30 * 99, "{rows} rows");
        assert!(
            with.resend_requests_sent >= 30 && with.chunks_resent > 0,
            "{with:?}"
        );
        assert_eq!(with.rows_per_chunk_last, 1, "{with:?}");
        assert!(with.ber_estimate > 3e-5 && with.ber_estimate < 3e-4, "{with:?}");
        assert!(with.return_bytes_sent > 0 && with.return_injected.is_some());
    }

    #[test]
    fn a_clean_line_is_only_acknowledged_and_keeps_long_chunks() {
        let (intrinsics, _) = image(100, 100, 0);
        let mut buffer = vec![0u16; 100 * 100];
        let mut link = DepthLink::open(&LinkConfig::default(), &intrinsics, &mut buffer, 1).unwrap();
        let (arrived, _) = run(&mut link, intrinsics, 5, 0.01);
        let r = link.report();
        assert_eq!(arrived.len(), 5);
        assert_eq!((r.resend_requests_sent, r.chunks_resent, r.acks_sent), (0, 0, 5));
        assert_eq!((r.rows_per_chunk_last, r.ber_estimate), (ROWS_PER_CHUNK, 0.0));
        // A fixed chunk size is kept, and a size the decoder cannot take is refused.
        let config = LinkConfig {
            chunk_rows: Some(3),
            ..LinkConfig::default()
        };
        let mut buffer = vec![0u16; 100 * 100];
        let mut link = DepthLink::open(&config, &intrinsics, &mut buffer, 1).unwrap();
        run(&mut link, intrinsics, 2, 0.01);
        assert_eq!(link.report().rows_per_chunk_last, 3);
        for bad in [0, 41] {
            let config = LinkConfig {
                chunk_rows: Some(bad),
                ..LinkConfig::default()
            };
            let mut buffer = vec![0u16; 100 * 100];
            assert!(DepthLink::open(&config, &intrinsics, &mut buffer, 1).is_err());
        }
    }
}
