//! Before a mission: the grid to map comes over the depth link.
//!
//! A board is built with a capacity, not a grid. At mission start the camera side sends the
//! grid's dimensions, origin and resolution (a [`Message::Geometry`]) and repeats it until the
//! core answers (a [`GeometryAnswer`] on the return channel). [`GeometryWait`] runs until a
//! grid fits: it answers a grid over capacity with what the grid needs and what the board has,
//! and keeps waiting; a grid that fits is answered as taken and handed to the board, which
//! carves its storage for it and builds the [`Companion`](super::Companion). The companion
//! answers repeats of the same grid (an answer lost on the line) as taken, and any other grid
//! as refused ([`Resource::GridInUse`](crate::links::downlink::Resource::GridInUse)).

use embedded_io::{Read, ReadReady, Write};

use super::io::IoError;
use crate::links::downlink::{self, GeometryAnswer, Shortfall, GEOMETRY_ANSWER_LEN};
use crate::links::link::{max_encoded_len, FrameDecoder, Message, GEOMETRY_BODY_LEN, HEADER_LEN};
use crate::mapping::map::MapGeometry;

/// Decoder bytes: one Geometry frame. Anything longer (a depth chunk sent before the answer)
/// overflows it and is dropped.
const GEOMETRY_FRAME_BYTES: usize = max_encoded_len(HEADER_LEN + GEOMETRY_BODY_LEN);

/// What one [`GeometryWait::poll`] came to.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Waited {
    /// No grid yet.
    Nothing,
    /// This grid does not fit, for this reason; it was answered so, and the wait goes on.
    Refused(MapGeometry, Shortfall),
    /// This grid fits and was answered as taken: carve the storage for it.
    Taken(MapGeometry),
}

/// Waits on the depth link for a grid that fits (see [the companion](super), "The grid").
#[derive(Debug)]
pub struct GeometryWait {
    decoder: FrameDecoder<GEOMETRY_FRAME_BYTES>,
    sequence: u16,
    refused: u32,
}

impl Default for GeometryWait {
    fn default() -> Self {
        Self::new()
    }
}

impl GeometryWait {
    /// Nothing heard yet.
    pub const fn new() -> Self {
        Self {
            decoder: FrameDecoder::new(),
            sequence: 0,
            refused: 0,
        }
    }

    /// Grids refused so far.
    pub fn refused(&self) -> u32 {
        self.refused
    }

    /// Reads what `link` has ready, up to the end of the first Geometry message, and answers
    /// it: `fits` says whether the board can map the grid. The bytes after that message stay
    /// in the stream for the companion (this reads one byte at a time).
    pub fn poll<L: Read + ReadReady + Write>(
        &mut self,
        link: &mut L,
        fits: impl FnOnce(&MapGeometry) -> Result<(), Shortfall>,
    ) -> Result<Waited, IoError> {
        let mut byte = [0u8; 1];
        let geometry = loop {
            if !link.read_ready().map_err(|_| IoError::Link)? {
                return Ok(Waited::Nothing);
            }
            if link.read(&mut byte).map_err(|_| IoError::Link)? == 0 {
                return Ok(Waited::Nothing);
            }
            if let Some(Ok(Message::Geometry(g))) = self.decoder.push(byte[0]) {
                break g;
            }
        };
        let (answer, waited) = match fits(&geometry) {
            Ok(()) => (
                GeometryAnswer::Taken {
                    voxels: voxels(&geometry),
                },
                Waited::Taken(geometry),
            ),
            Err(shortfall) => {
                self.refused = self.refused.saturating_add(1);
                (
                    GeometryAnswer::Refused(shortfall),
                    Waited::Refused(geometry, shortfall),
                )
            }
        };
        let seq = self.sequence;
        self.sequence = seq.wrapping_add(1);
        send_answer(seq, &answer, link)?;
        Ok(waited)
    }
}

/// The grid's voxels, as the wire carries them (saturating: no grid that large fits a board).
pub(super) fn voxels(geometry: &MapGeometry) -> u32 {
    u32::try_from(geometry.dims().len()).unwrap_or(u32::MAX)
}

/// One geometry answer on the return channel.
pub(super) fn send_answer<L: Write>(seq: u16, answer: &GeometryAnswer, link: &mut L) -> Result<(), IoError> {
    let mut out = [0u8; downlink::max_frame_len(GEOMETRY_ANSWER_LEN)];
    let n = downlink::encode_geometry_answer(seq, answer, &mut out).map_err(|_| IoError::Link)?;
    link.write_all(out.get(..n).unwrap_or(&[]))
        .map_err(|_| IoError::Link)?;
    link.flush().map_err(|_| IoError::Link)
}
