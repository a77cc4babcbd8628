//! How a companion's byte streams fail.

/// A stream failed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum IoError {
    /// The depth link.
    Link,
    /// MAVLink.
    Mavlink,
}
