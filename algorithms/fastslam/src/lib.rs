//! 6-DOF stereo FastSLAM (EQUATIONS §1-4): a Rao-Blackwellised particle filter whose particles carry a
//! pose and a map of per-landmark EKFs. Maps are persistent tries shared between particles
//! ([`map`]), so resampling copies pointers and an update copies O(log M) nodes.

pub mod camera;
pub mod config;
pub mod ekf;
pub mod filter;
pub mod frontend;
pub mod map;
pub mod sym3;

pub use camera::{CameraOnly, CameraOnlyStats, MotionReport};
pub use config::{AssociationConfig, FastSlamConfig, Proposal, SegmentConfig};
pub use filter::{FastSlam, FrameReport, FrameTiming, Observation, PoseEstimate, PriorLandmark, SegmentReason};
pub mod eval;
