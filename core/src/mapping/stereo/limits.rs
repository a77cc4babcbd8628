//! The matcher's units and limits, and why it refuses parameters or input.

/// Disparities are stored in units of 1/`DISPARITY_SCALE` pixel.
pub const DISPARITY_SCALE: i16 = 16;
/// The disparity of a pixel without a valid match.
pub const INVALID_DISPARITY: i16 = -DISPARITY_SCALE;
/// Largest window side, pixels: window sums of 8-bit differences stay within `u16`.
pub const MAX_WINDOW: u8 = 15;
/// Largest disparity range.
pub const MAX_DISPARITIES: u16 = 1024;

/// Why the matcher refused its parameters or its input.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum StereoError {
    /// Width or height is zero.
    EmptyImage,
    /// The disparity range is zero, larger than the width or larger than [`MAX_DISPARITIES`].
    BadDisparityRange,
    /// The window is even, smaller than 3 or larger than [`MAX_WINDOW`].
    BadWindow,
    /// The match footprint (`2·window − 1` pixels) does not fit in the image.
    ImageTooSmall,
    /// The prefilter's sigmas are not finite, not positive, not increasing, or need a kernel
    /// radius above [`MAX_RADIUS`](super::prefilter::MAX_RADIUS).
    BadPrefilter,
    /// The scratch lent is smaller than [`scratch_size`](super::scratch_size) asks for.
    ScratchTooSmall,
    /// An image, row or output buffer has the wrong length.
    SizeMismatch,
    /// More rows were pushed than the image has, or `finish` came before the last row.
    RowCount,
    /// Baseline or focal length is zero, negative or not finite.
    BadGeometry,
}
