//! MAVLink telemetry logs in the `.tlog` format QGroundControl and MAVProxy write, so a run
//! opens in the standard tools (MAVExplorer, `mavlogdump.py`, QGroundControl's log replay).
//!
//! A `.tlog` is a plain sequence of records, nothing before the first:
//!
//! ```text
//! u64 big-endian  timestamp, microseconds since the Unix epoch
//! [u8]            one MAVLink frame exactly as it went over the wire (v1 or v2)
//! ```
//!
//! A frame's length follows from its own header (v2: `0xFD`, payload length in byte 1, 12
//! bytes of header and checksum, 13 more if the signed flag of byte 2 is set; v1: `0xFE`,
//! payload length in byte 1, 8 more bytes).
//!
//! Timestamps: against the in-process emulator, simulated time from [`SIM_EPOCH_US`]
//! (2024-01-01T00:00:00Z), so a run and its log are reproducible byte for byte; against a real
//! autopilot (`udpin`/`udpout`), the wall clock. Both directions go into the same log; the
//! format has no direction field, so [`summarize`] tells them apart by the sender's component
//! id (the companion computer's, 191, is "out").

use std::collections::BTreeMap;
use std::fmt;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

use harmonic_core::mavlink::{MavHeader, MavMessage, MavlinkDecoder, MavlinkMessage};
use serde::Serialize;

/// Timestamp origin of logs in simulated time: 2024-01-01T00:00:00Z, in µs since the epoch.
pub const SIM_EPOCH_US: u64 = 1_704_067_200_000_000;

const V2_MAGIC: u8 = 0xFD;
const V1_MAGIC: u8 = 0xFE;

/// Writes a `.tlog`.
#[derive(Debug)]
pub struct TlogWriter {
    path: PathBuf,
    out: BufWriter<std::fs::File>,
    records: u64,
}

impl TlogWriter {
    /// Creates (or truncates) `path`, and the directories above it.
    pub fn create(path: &Path) -> Result<Self, String> {
        let err = |e: std::io::Error| format!("--tlog {}: {e}", path.display());
        if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
            std::fs::create_dir_all(dir).map_err(err)?;
        }
        let file = std::fs::File::create(path).map_err(err)?;
        Ok(Self {
            path: path.to_path_buf(),
            out: BufWriter::new(file),
            records: 0,
        })
    }

    /// Appends one record.
    pub fn write(&mut self, timestamp_us: u64, frame: &[u8]) -> Result<(), String> {
        let err = |e: std::io::Error| format!("--tlog {}: {e}", self.path.display());
        self.out.write_all(&timestamp_us.to_be_bytes()).map_err(err)?;
        self.out.write_all(frame).map_err(err)?;
        self.records += 1;
        Ok(())
    }

    /// Records written.
    pub fn records(&self) -> u64 {
        self.records
    }

    /// The file written.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Flushes what is buffered to the file.
    pub fn flush(&mut self) -> Result<(), String> {
        self.out
            .flush()
            .map_err(|e| format!("--tlog {}: {e}", self.path.display()))
    }
}

/// One record of a `.tlog`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct TlogRecord {
    /// Microseconds since the Unix epoch.
    pub timestamp_us: u64,
    /// The MAVLink frame.
    pub frame: Vec<u8>,
}

/// Why a `.tlog` could not be read.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum TlogError {
    /// The file ends inside a record.
    Truncated {
        /// Byte offset of the record.
        offset: usize,
    },
    /// A record's frame does not start with a MAVLink start marker.
    NotMavlink {
        /// Byte offset of the frame.
        offset: usize,
        /// The byte found.
        byte: u8,
    },
}

impl fmt::Display for TlogError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            TlogError::Truncated { offset } => write!(f, "truncated record at byte {offset}"),
            TlogError::NotMavlink { offset, byte } => write!(
                f,
                "byte {offset}: 0x{byte:02X} is not a MAVLink start marker (0xFD or 0xFE)"
            ),
        }
    }
}

impl std::error::Error for TlogError {}

/// Splits a `.tlog` into its records.
pub fn read_records(bytes: &[u8]) -> Result<Vec<TlogRecord>, TlogError> {
    let mut records = Vec::new();
    let mut at = 0usize;
    while at < bytes.len() {
        let truncated = TlogError::Truncated { offset: at };
        let stamp: [u8; 8] = bytes
            .get(at..at + 8)
            .and_then(|s| s.try_into().ok())
            .ok_or(truncated.clone())?;
        let start = at + 8;
        let magic = *bytes.get(start).ok_or(truncated.clone())?;
        let payload_len = usize::from(*bytes.get(start + 1).ok_or(truncated.clone())?);
        let len = match magic {
            V2_MAGIC => {
                let flags = *bytes.get(start + 2).ok_or(truncated.clone())?;
                12 + payload_len + if flags & 0x01 != 0 { 13 } else { 0 }
            }
            V1_MAGIC => 8 + payload_len,
            byte => return Err(TlogError::NotMavlink { offset: start, byte }),
        };
        let frame = bytes.get(start..start + len).ok_or(truncated)?;
        records.push(TlogRecord {
            timestamp_us: u64::from_be_bytes(stamp),
            frame: frame.to_vec(),
        });
        at = start + len;
    }
    Ok(records)
}

/// Decodes the frame of a record; `None` if its checksum is wrong or its message is not in
/// the common dialect.
pub fn decode(record: &TlogRecord) -> Option<(MavHeader, MavMessage)> {
    let mut decoder = MavlinkDecoder::new();
    let mut out = None;
    decoder.push(&record.frame, |h, m| {
        if out.is_none() {
            out = Some((*h, m.clone()));
        }
    });
    out
}

/// Message counts of a `.tlog`.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct TlogSummary {
    /// Records in the file.
    pub records: usize,
    /// Records whose frame did not decode (bad checksum, message outside the common dialect).
    pub undecoded: usize,
    /// First and last timestamp, µs since the epoch.
    pub span_us: Option<(u64, u64)>,
    /// Messages sent by the companion computer, by message name.
    pub sent: BTreeMap<String, u32>,
    /// Messages received from anyone else, by message name.
    pub received: BTreeMap<String, u32>,
}

impl TlogSummary {
    /// Seconds between the first and the last record.
    pub fn duration_s(&self) -> f64 {
        self.span_us
            .map(|(a, b)| b.saturating_sub(a) as f64 * 1e-6)
            .unwrap_or(0.0)
    }
}

/// Counts the messages of `records` per direction and name; `companion_component` is the
/// component id whose messages count as sent.
pub fn summarize(records: &[TlogRecord], companion_component: u8) -> TlogSummary {
    let mut summary = TlogSummary {
        records: records.len(),
        ..TlogSummary::default()
    };
    for record in records {
        summary.span_us = Some(match summary.span_us {
            None => (record.timestamp_us, record.timestamp_us),
            Some((a, b)) => (a.min(record.timestamp_us), b.max(record.timestamp_us)),
        });
        match decode(record) {
            Some((header, message)) => {
                let side = if header.component_id == companion_component {
                    &mut summary.sent
                } else {
                    &mut summary.received
                };
                *side.entry(message.message_name().to_string()).or_insert(0) += 1;
            }
            None => summary.undecoded += 1,
        }
    }
    summary
}

/// The summary as a table: one line per direction and message, with its rate.
pub fn format_summary(summary: &TlogSummary) -> String {
    let mut out = String::new();
    let duration = summary.duration_s();
    out.push_str(&format!(
        "{} records over {:.1} s ({} undecoded)\n",
        summary.records, duration, summary.undecoded
    ));
    out.push_str(&format!(
        "{:<4} {:<32} {:>8} {:>9}\n",
        "dir", "message", "count", "rate Hz"
    ));
    for (dir, side) in [("out", &summary.sent), ("in", &summary.received)] {
        for (name, count) in side {
            let rate = if duration > 0.0 {
                f64::from(*count) / duration
            } else {
                0.0
            };
            out.push_str(&format!("{dir:<4} {name:<32} {count:>8} {rate:>9.2}\n"));
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use harmonic_core::mavlink::common::{ATTITUDE_DATA, HEARTBEAT_DATA, STATUSTEXT_DATA};
    use harmonic_core::mavlink::{encode_v2, MAX_FRAME_LEN};

    fn frame(component: u8, seq: u8, message: &MavMessage) -> Vec<u8> {
        let header = MavHeader {
            system_id: 1,
            component_id: component,
            sequence: seq,
        };
        let mut buf = [0u8; MAX_FRAME_LEN];
        let n = encode_v2(&header, message, &mut buf).unwrap();
        buf[..n].to_vec()
    }

    #[test]
    fn records_round_trip_through_a_file() {
        let messages = [
            (191, MavMessage::HEARTBEAT(HEARTBEAT_DATA::DEFAULT)),
            (
                1,
                MavMessage::ATTITUDE(ATTITUDE_DATA {
                    time_boot_ms: 1234,
                    yaw: 1.5,
                    ..ATTITUDE_DATA::DEFAULT
                }),
            ),
            (
                191,
                MavMessage::STATUSTEXT(STATUSTEXT_DATA {
                    text: harmonic_core::mavlink::StatusText::from_str_truncated("exploration started")
                        .field()
                        .into(),
                    ..STATUSTEXT_DATA::DEFAULT
                }),
            ),
        ];
        let dir = std::env::temp_dir().join(format!("harmonic-tlog-{}", std::process::id()));
        let path = dir.join("sub/run.tlog");
        let mut writer = TlogWriter::create(&path).unwrap();
        for (i, (component, m)) in messages.iter().enumerate() {
            writer
                .write(SIM_EPOCH_US + i as u64 * 100_000, &frame(*component, i as u8, m))
                .unwrap();
        }
        writer.flush().unwrap();
        assert_eq!(writer.records(), 3);
        let bytes = std::fs::read(&path).unwrap();
        // The first record: a big-endian timestamp, then the frame's start marker.
        assert_eq!(&bytes[..8], &SIM_EPOCH_US.to_be_bytes());
        assert_eq!(bytes[8], 0xFD);
        let records = read_records(&bytes).unwrap();
        assert_eq!(records.len(), 3);
        for (i, (record, (component, message))) in records.iter().zip(&messages).enumerate() {
            assert_eq!(record.timestamp_us, SIM_EPOCH_US + i as u64 * 100_000);
            let (h, m) = decode(record).unwrap();
            assert_eq!((h.component_id, h.sequence), (*component, i as u8));
            assert_eq!(&m, message);
        }
        let s = summarize(&records, 191);
        assert_eq!(s.sent.get("HEARTBEAT"), Some(&1));
        assert_eq!(s.sent.get("STATUSTEXT"), Some(&1));
        assert_eq!(s.received.get("ATTITUDE"), Some(&1));
        assert!((s.duration_s() - 0.2).abs() < 1e-9);
        assert!(format_summary(&s).contains("ATTITUDE"));
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn damaged_logs_are_errors_not_panics() {
        let f = frame(191, 0, &MavMessage::HEARTBEAT(HEARTBEAT_DATA::DEFAULT));
        let mut log = 5u64.to_be_bytes().to_vec();
        log.extend_from_slice(&f);
        assert_eq!(read_records(&log).unwrap().len(), 1);
        for cut in 1..log.len() {
            assert_eq!(read_records(&log[..cut]), Err(TlogError::Truncated { offset: 0 }));
        }
        let mut bad = log.clone();
        bad[8] = 0x42;
        assert_eq!(
            read_records(&bad),
            Err(TlogError::NotMavlink {
                offset: 8,
                byte: 0x42
            })
        );
        // A flipped payload bit: the record splits fine but does not decode.
        let mut flipped = log.clone();
        flipped[8 + 11] ^= 0x10;
        let records = read_records(&flipped).unwrap();
        assert_eq!(decode(&records[0]), None);
        assert_eq!(summarize(&records, 191).undecoded, 1);
    }
}
