//! The sensing stage: what the vehicle's sensors make of the world at its true pose.
//!
//! - [`camera`]: the forward-looking depth camera; ray casts the world into the depth images
//!   the core consumes (u16 millimetres, 0 = no return), with optional stereo-like noise,
//!   outliers and textureless surfaces; also the camera pose convention ([`camera::camera_pose`]).
//! - [`stereo`]: a textured stereo pair rendered from the world, matched by the core's block
//!   matcher into depth (`--depth-from stereo`), with ground truth and the PNG/PFM/`.npy`
//!   disparity files of the `stereo` subcommands.
//! - [`faults`]: every sensor and pose fault the simulator injects (dropouts, outliers, pose
//!   drift, a silent pose stream) and the random-walk drift of a believed pose.
//! - [`sensing`]: how far a map made with imperfect sensing is from the noise-free map of the
//!   same run.
//!
//! In: a [`World`](crate::world::World) from the world stage and the camera's pose from the
//! run. Out: depth frames for the depth link (or straight to the core), the believed pose
//! under drift, and map-accuracy figures for the run's report. Depends on the world stage and,
//! for disparity files, on [`crate::io::npy`].

pub mod camera;
pub mod faults;
pub mod sensing;
pub mod stereo;
