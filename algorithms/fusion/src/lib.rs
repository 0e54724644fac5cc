//! Multi-sensor fusion and globally consistent 3-D SLAM (EQUATIONS §5.2 and §6, \[3D\] eq 31-38, Alg 3),
//! as pure functions and state machines with no IPC:
//! - [`bspline`]: the cubic B-spline of a local path over time, with covariance (eq 33-37);
//! - [`align`]: the local-to-global rigid transform by weighted SVD, with degeneracy detection;
//! - [`fuse`]: covariance-weighted fusion of the camera and buoy estimates under a χ²₃ gate;
//! - [`global_map`]: segments' landmarks in the global frame, merged across segments (eq 38);
//! - [`plot`]: a top-view PNG of the trajectories.

pub mod align;
pub mod bspline;
pub mod correlation;
pub mod engine;
pub mod error;
pub mod fuse;
pub mod global_map;
pub mod plot;

pub use error::FusionError;
