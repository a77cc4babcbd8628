//! The depth link as a run uses it: camera side, wire and core side, with bandwidth.
//!
//! ```text
//! camera side                         wire                         core side
//! LinkEncoder ─► FaultInjector ─► pacing queue ─► Wire (pipe, TCP, serial) ─► DepthReceiver
//!  (frames)      (optional)       (baud rate,                                   (the core's)
//!  Heartbeat 1 Hz                  simulated time)
//! ```
//!
//! - The camera side encodes each depth image with its camera pose (a Pose message, then the
//!   image's Intrinsics and chunks: `harmonic_core::link`), and a link Heartbeat every
//!   [`HEARTBEAT_PERIOD_S`] of simulated time.
//! - Every frame passes the [`FaultInjector`] if faults are configured, then waits in a queue
//!   that drains at the baud rate: a byte takes 10 bit times (8N1), so a 100 × 100 image
//!   (about 20 kB) is on the wire for about 0.22 s at 921600 baud. [`DepthLink::tick`] moves the
//!   bytes whose time has come onto the [`Wire`] and hands whatever arrived to the core's
//!   `DepthReceiver`; the run keeps flying (and streaming MAVLink) between ticks.
//! - The core side keeps each complete image that came with its pose; the run integrates them.
//!   An image without its pose (the Pose frame was lost) cannot be placed in the map and is
//!   dropped, counted in [`LinkReport::frames_without_pose`].

use std::collections::VecDeque;

use harmonic_core::camera::{DepthFrame, Intrinsics};
use harmonic_core::link::{self, DepthReceiver, Heartbeat, LinkCounters, LinkEncoder, LinkEvent};
use nalgebra::Isometry3;
use serde::Serialize;

use crate::fault::{FaultConfig, FaultCounters, FaultInjector};
use crate::transport::{self, TransportSpec, Wire};

/// Default baud rate of the link.
pub const DEFAULT_BAUD: u32 = 921_600;
/// Bits on the wire per byte: 8N1 (start bit, 8 data bits, stop bit).
pub const BITS_PER_BYTE: f64 = 10.0;
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

/// How the depth link is set up.
#[derive(Debug, Clone, PartialEq)]
pub struct LinkConfig {
    /// The wire.
    pub transport: TransportSpec,
    /// Baud rate; 10 bits per byte.
    pub baud: u32,
    /// Faults to inject.
    pub faults: FaultConfig,
}

impl Default for LinkConfig {
    fn default() -> Self {
        Self {
            transport: TransportSpec::Sim,
            baud: DEFAULT_BAUD,
            faults: FaultConfig::default(),
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
    /// The core's receiver: frames decoded, every error counter.
    pub receiver: LinkCounters,
    /// What the fault injector did; `None` without faults.
    pub injected: Option<FaultCounters>,
}

/// An image the core side received whole, with its pose.
#[derive(Debug, Clone)]
pub struct ArrivedFrame {
    /// Image id.
    pub frame_id: u32,
    /// Its intrinsics.
    pub intrinsics: Intrinsics,
    /// Depth, mm, row-major.
    pub depth: Vec<u16>,
    /// Camera → map pose sent with it.
    pub camera_pose: Isometry3<f32>,
}

impl ArrivedFrame {
    /// The image as the core takes it.
    pub fn frame(&self) -> Option<DepthFrame<'_>> {
        DepthFrame::new(self.intrinsics, &self.depth).ok()
    }
}

/// Core-side bookkeeping that the receiver's callback updates.
#[derive(Debug, Default)]
struct CoreSide {
    arrived: Vec<ArrivedFrame>,
    frames_without_pose: u32,
    heartbeats_received: u32,
    last_heartbeat_s: Option<f64>,
    max_heartbeat_gap_s: f64,
    camera_frames_sent_reported: u32,
}

/// The depth link of a run. See the [module documentation](self).
pub struct DepthLink<'b> {
    label: String,
    baud: u32,
    // Camera side.
    encoder: LinkEncoder,
    scratch: Vec<u8>,
    rows_per_chunk: u16,
    injector: Option<FaultInjector>,
    staged: Vec<u8>,
    next_heartbeat_s: f64,
    heartbeats_sent: u32,
    depth_frames_sent: u32,
    link_frames_sent: u64,
    transfer_ms: Vec<f64>,
    // Wire.
    wire: Box<dyn Wire>,
    queue: VecDeque<u8>,
    credit: f64,
    now_s: f64,
    busy_until_s: f64,
    busy_s: f64,
    bytes_sent: u64,
    // Core side.
    receiver: DepthReceiver<'b, DECODER_BYTES>,
    inbox: Vec<u8>,
    bytes_received: u64,
    core: CoreSide,
    depth_frames_integrated: u32,
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
        Ok(Self {
            label: config.transport.to_string(),
            baud: config.baud,
            encoder: LinkEncoder::new(),
            scratch: vec![0; link::max_depth_chunk_len(width, rows).max(link::max_encoded_len(64))],
            rows_per_chunk: rows,
            injector: (!config.faults.is_clean()).then(|| FaultInjector::new(config.faults, seed)),
            staged: Vec::new(),
            next_heartbeat_s: 0.0,
            heartbeats_sent: 0,
            depth_frames_sent: 0,
            link_frames_sent: 0,
            transfer_ms: Vec::new(),
            wire,
            queue: VecDeque::new(),
            credit: 0.0,
            now_s: 0.0,
            busy_until_s: 0.0,
            busy_s: 0.0,
            bytes_sent: 0,
            receiver: DepthReceiver::new(buffer),
            inbox: Vec::new(),
            bytes_received: 0,
            core: CoreSide::default(),
            depth_frames_integrated: 0,
        })
    }

    fn bytes_per_s(&self) -> f64 {
        f64::from(self.baud) / BITS_PER_BYTE
    }

    /// Camera side: one encoded frame through the injector into the staging buffer.
    fn stage(&mut self, n: usize) {
        let frame = self.scratch.get(..n).unwrap_or(&[]);
        self.link_frames_sent += 1;
        match self.injector.as_mut() {
            Some(injector) => injector.send(frame, &mut self.staged),
            None => self.staged.extend_from_slice(frame),
        }
    }

    /// Camera side: the staged bytes join the wire's queue; returns when their last byte
    /// will have left, in simulated seconds.
    fn enqueue_staged(&mut self) -> f64 {
        if let Some(injector) = self.injector.as_mut() {
            injector.flush(&mut self.staged);
        }
        let n = self.staged.len();
        let duration = n as f64 / self.bytes_per_s();
        self.busy_until_s = self.busy_until_s.max(self.now_s) + duration;
        self.busy_s += duration;
        self.queue.extend(self.staged.drain(..));
        self.busy_until_s
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
        self.stage(n);
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
        for f in frames {
            self.link_frames_sent += 1;
            match self.injector.as_mut() {
                Some(injector) => injector.send(&f, &mut self.staged),
                None => self.staged.extend_from_slice(&f),
            }
        }
        let start = self.now_s;
        let done = self.enqueue_staged();
        self.transfer_ms.push((done - start) * 1e3);
        self.depth_frames_sent += 1;
        Ok(())
    }

    /// True while bytes wait to go on the wire.
    pub fn sending(&self) -> bool {
        !self.queue.is_empty()
    }

    /// Advances the link to simulated time `now_s`: a camera Heartbeat if one is due, the
    /// bytes whose time has come onto the wire, and whatever arrived into the core side.
    pub fn tick(&mut self, now_s: f64) -> Result<(), String> {
        let elapsed = (now_s - self.now_s).max(0.0);
        self.now_s = now_s;
        if !self.queue.is_empty() {
            self.credit += elapsed * self.bytes_per_s();
        }
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
            self.stage(n);
            self.enqueue_staged();
            self.heartbeats_sent += 1;
        }
        let n = (self.credit.floor() as usize).min(self.queue.len());
        if n > 0 {
            self.credit -= n as f64;
            let (a, b) = self.queue.as_slices();
            let first = a.len().min(n);
            let err = |e: std::io::Error| format!("--link {}: {e}", self.label);
            self.wire.send(&a[..first]).map_err(err)?;
            self.wire.send(&b[..n - first]).map_err(err)?;
            self.queue.drain(..n);
            self.bytes_sent += n as u64;
        }
        if self.queue.is_empty() {
            // An idle wire saves no time for later.
            self.credit = 0.0;
        }
        self.receive()
    }

    /// Core side: takes in what the wire delivered.
    fn receive(&mut self) -> Result<(), String> {
        let err = |e: std::io::Error| format!("--link {}: {e}", self.label);
        self.inbox.clear();
        let n = self.wire.receive(&mut self.inbox).map_err(err)?;
        if n == 0 {
            return Ok(());
        }
        self.bytes_received += n as u64;
        let now_s = self.now_s;
        let core = &mut self.core;
        self.receiver.feed(&self.inbox, |event| match event {
            LinkEvent::Depth {
                frame_id,
                frame,
                pose,
            } => match pose {
                Some(pose) => core.arrived.push(ArrivedFrame {
                    frame_id,
                    intrinsics: *frame.intrinsics(),
                    depth: frame.depth_mm().to_vec(),
                    camera_pose: pose.isometry(),
                }),
                None => core.frames_without_pose += 1,
            },
            LinkEvent::Heartbeat(h) => {
                core.heartbeats_received += 1;
                core.camera_frames_sent_reported = h.frames_sent;
                if let Some(last) = core.last_heartbeat_s {
                    core.max_heartbeat_gap_s = core.max_heartbeat_gap_s.max(now_s - last);
                }
                core.last_heartbeat_s = Some(now_s);
            }
            _ => {}
        });
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
        while self.bytes_received < self.bytes_sent
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
    pub fn note_integrated(&mut self) {
        self.depth_frames_integrated += 1;
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
            bytes_sent: self.bytes_sent,
            bytes_received: self.bytes_received,
            heartbeats_sent: self.heartbeats_sent,
            heartbeats_received: self.core.heartbeats_received,
            max_heartbeat_gap_ms: self.core.max_heartbeat_gap_s * 1e3,
            camera_frames_sent_reported: self.core.camera_frames_sent_reported,
            transfer: MsStat::of(&self.transfer_ms),
            wire_busy_s: self.busy_s,
            receiver: self.receiver.counters(),
            injected: self.injector.as_ref().map(|i| *i.counters()),
        }
    }
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
            while link.sending() {
                t += dt;
                link.tick(t).unwrap();
            }
            link.settle().unwrap();
            arrived.extend(link.take_arrived());
        }
        (arrived, t)
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
        // Every image that arrived is intact and was sent.
        for a in &arrived {
            let (_, depth) = image(60, 40, a.frame_id as u16 - 1);
            assert_eq!(a.depth, depth);
        }
        // A lost image was either given up by the assembler, arrived without its pose, or
        // lost every frame: each is counted at most once.
        let lost = 60 - arrived.len() as u32;
        let counted = r.frames_without_pose + r.receiver.depth_frames_dropped;
        assert!(
            lost > 0 && counted > 0 && counted <= lost,
            "{lost} lost, {counted} counted"
        );
    }
}
