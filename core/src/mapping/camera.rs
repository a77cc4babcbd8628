//! Pinhole camera model and validated depth frames.
//!
//! Camera frame: x right, y down, z forward (the usual pinhole convention). A depth image holds,
//! per pixel, the z coordinate of the hit point in the camera frame in millimetres (`u16`), with
//! `0` meaning "no return" — the convention of RealSense-class sensors and the TUM RGB-D format.
//! Pixel `(u, v)` (column, row) has its centre at `u`, `v`; its ray is
//! `((u - cx) / fx, (v - cy) / fy, 1)` in the camera frame.

use nalgebra::Vector3;

/// Depth value of a pixel that was never received — a row of a depth frame lost on the link
/// ([`crate::links::link::DepthReceiver`] delivers such frames partially). Integration skips these
/// pixels: they are neither a return nor a "no return". No sensor reading is encoded as it
/// (the largest depth is `u16::MAX − 1` mm, 65.5 m).
pub const NOT_RECEIVED: u16 = u16::MAX;

/// Why a set of camera intrinsics was rejected.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum IntrinsicsError {
    /// Width or height is zero.
    EmptyImage,
    /// A focal length is zero, negative or not finite.
    BadFocalLength,
    /// The principal point is not finite or lies outside the image.
    PrincipalPointOutsideImage,
}

/// Pinhole intrinsics of a depth camera, validated on construction.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Intrinsics {
    fx: f32,
    fy: f32,
    cx: f32,
    cy: f32,
    width: u16,
    height: u16,
}

impl Intrinsics {
    /// Checked constructor: focal lengths finite and positive, principal point inside the image.
    pub fn new(fx: f32, fy: f32, cx: f32, cy: f32, width: u16, height: u16) -> Result<Self, IntrinsicsError> {
        if width == 0 || height == 0 {
            return Err(IntrinsicsError::EmptyImage);
        }
        if !(fx.is_finite() && fy.is_finite() && fx > 0.0 && fy > 0.0) {
            return Err(IntrinsicsError::BadFocalLength);
        }
        let inside = |c: f32, n: u16| c.is_finite() && c >= -0.5 && c <= f32::from(n) - 0.5;
        if !(inside(cx, width) && inside(cy, height)) {
            return Err(IntrinsicsError::PrincipalPointOutsideImage);
        }
        Ok(Self {
            fx,
            fy,
            cx,
            cy,
            width,
            height,
        })
    }

    /// Square pixels, principal point at the image centre, given horizontal field of view.
    pub fn from_hfov(width: u16, height: u16, hfov_rad: f32) -> Result<Self, IntrinsicsError> {
        if !(hfov_rad.is_finite() && hfov_rad > 0.0 && hfov_rad < core::f32::consts::PI) {
            return Err(IntrinsicsError::BadFocalLength);
        }
        let f = 0.5 * f32::from(width) / libm::tanf(0.5 * hfov_rad);
        Self::new(
            f,
            f,
            0.5 * (f32::from(width) - 1.0),
            0.5 * (f32::from(height) - 1.0),
            width,
            height,
        )
    }

    /// Focal length along x, pixels.
    pub fn fx(&self) -> f32 {
        self.fx
    }
    /// Focal length along y, pixels.
    pub fn fy(&self) -> f32 {
        self.fy
    }
    /// Principal point column, pixels.
    pub fn cx(&self) -> f32 {
        self.cx
    }
    /// Principal point row, pixels.
    pub fn cy(&self) -> f32 {
        self.cy
    }
    /// Image width, pixels.
    pub fn width(&self) -> u16 {
        self.width
    }
    /// Image height, pixels.
    pub fn height(&self) -> u16 {
        self.height
    }
    /// Number of pixels.
    pub fn pixel_count(&self) -> usize {
        usize::from(self.width) * usize::from(self.height)
    }

    /// Camera-frame ray through pixel `(u, v)` scaled so that its z component is 1: the
    /// point at depth `d` is `d * ray`.
    pub fn ray(&self, u: u16, v: u16) -> Vector3<f32> {
        Vector3::new(
            (f32::from(u) - self.cx) / self.fx,
            (f32::from(v) - self.cy) / self.fy,
            1.0,
        )
    }

    /// Half of the horizontal and vertical fields of view, radians.
    pub fn half_fov(&self) -> (f32, f32) {
        let hw = libm::atanf((0.5 * f32::from(self.width)) / self.fx);
        let hh = libm::atanf((0.5 * f32::from(self.height)) / self.fy);
        (hw, hh)
    }
}

/// Why a depth frame was rejected.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum DepthFrameError {
    /// The number of depth values does not equal width × height of the intrinsics.
    SizeMismatch {
        /// Pixels the intrinsics announce.
        expected: usize,
        /// Depth values supplied.
        got: usize,
    },
}

/// A depth image whose size matches its intrinsics (checked once, here).
#[derive(Debug, Clone, Copy)]
pub struct DepthFrame<'a> {
    intrinsics: Intrinsics,
    depth_mm: &'a [u16],
}

impl<'a> DepthFrame<'a> {
    /// Wraps a row-major depth image (u16 millimetres, 0 = no return, [`NOT_RECEIVED`] = not
    /// received).
    pub fn new(intrinsics: Intrinsics, depth_mm: &'a [u16]) -> Result<Self, DepthFrameError> {
        let expected = intrinsics.pixel_count();
        if depth_mm.len() != expected {
            return Err(DepthFrameError::SizeMismatch {
                expected,
                got: depth_mm.len(),
            });
        }
        Ok(Self { intrinsics, depth_mm })
    }
    /// The camera model the frame was taken with.
    pub fn intrinsics(&self) -> &Intrinsics {
        &self.intrinsics
    }
    /// Row-major depth values in millimetres.
    pub fn depth_mm(&self) -> &'a [u16] {
        self.depth_mm
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bad_intrinsics_are_refused() {
        let bad = |fx, fy, cx, cy, w, h| Intrinsics::new(fx, fy, cx, cy, w, h).err();
        assert_eq!(
            bad(50.0, 50.0, 5.0, 5.0, 0, 10),
            Some(IntrinsicsError::EmptyImage)
        );
        assert_eq!(
            bad(50.0, 50.0, 5.0, 5.0, 10, 0),
            Some(IntrinsicsError::EmptyImage)
        );
        for f in [0.0, -50.0, f32::NAN, f32::INFINITY] {
            assert_eq!(
                bad(f, 50.0, 5.0, 5.0, 10, 10),
                Some(IntrinsicsError::BadFocalLength)
            );
            assert_eq!(
                bad(50.0, f, 5.0, 5.0, 10, 10),
                Some(IntrinsicsError::BadFocalLength)
            );
        }
        for (cx, cy) in [(-0.6, 5.0), (9.6, 5.0), (5.0, -1.0), (5.0, 10.0), (f32::NAN, 5.0)] {
            assert_eq!(
                bad(50.0, 50.0, cx, cy, 10, 10),
                Some(IntrinsicsError::PrincipalPointOutsideImage)
            );
        }
        assert!(Intrinsics::new(50.0, 50.0, -0.5, 9.5, 10, 10).is_ok());
        assert_eq!(
            Intrinsics::from_hfov(10, 10, 0.0).err(),
            Some(IntrinsicsError::BadFocalLength)
        );
    }

    #[test]
    fn depth_frames_must_match_their_intrinsics() {
        let i = Intrinsics::from_hfov(4, 3, 1.0).unwrap();
        assert!(DepthFrame::new(i, &[0; 12]).is_ok());
        for n in [0, 11, 13, 100] {
            let depth = [0u16; 100];
            assert_eq!(
                DepthFrame::new(i, &depth[..n]).err(),
                Some(DepthFrameError::SizeMismatch { expected: 12, got: n })
            );
        }
    }
}
