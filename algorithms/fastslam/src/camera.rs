//! Camera-only prediction: the stereo front end's frame-to-frame motion ([`crate::frontend`])
//! as FastSLAM's motion input when there is no odometry. When the front end finds no motion
//! (too few points, no consensus, degenerate geometry) the filter falls back to its
//! constant-velocity model for that frame, and the report says so.

use nalgebra::Isometry3;
use serde::Serialize;

use crate::filter::{FastSlam, Observation};
use crate::frontend::{Frame, FrontEnd, FrontEndConfig, Method, Registration, RegistrationError, motion_in_body};

/// What the prediction of one frame did.
#[derive(Debug, Clone, PartialEq)]
pub struct MotionReport {
    /// The front end's result (the first frame is `Err(FirstFrame)`).
    pub registration: Result<Registration, RegistrationError>,
    /// True when the constant-velocity model moved the particles instead.
    pub fallback: bool,
}

/// Counts over a run.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct CameraOnlyStats {
    /// Frames predicted.
    pub frames: u64,
    /// Motions found by feature track ids.
    pub by_track_ids: u64,
    /// Motions found around the constant-velocity prior.
    pub guided: u64,
    /// Motions found by the prior-free search.
    pub search: u64,
    /// Frames without a motion, predicted by constant velocity instead.
    pub failed: u64,
    /// Sum of the inliers of the motions found.
    pub inliers: u64,
    /// Sum of the candidates per point of the motions found.
    pub candidates_per_point: f64,
}

/// The front end wired to a filter.
pub struct CameraOnly {
    frontend: FrontEnd,
    body_from_camera: Isometry3<f64>,
    stats: CameraOnlyStats,
}

impl CameraOnly {
    /// A front end with `cfg` for a camera mounted at `body_from_camera`.
    pub fn new(cfg: FrontEndConfig, body_from_camera: Isometry3<f64>) -> Self {
        Self { frontend: FrontEnd::new(cfg), body_from_camera, stats: CameraOnlyStats::default() }
    }

    /// Moves the filter's particles from the previous frame to this one (`obs`, body frame,
    /// `dt_s` after the previous frame) by the registered motion, or by constant velocity when
    /// there is none. Call before [`FastSlam::update`] with the same observations.
    pub fn predict(&mut self, filter: &mut FastSlam, obs: &[Observation], dt_s: f64) -> MotionReport {
        let frame = Frame::from_observations(obs, &self.body_from_camera);
        let registration = self.frontend.register(frame, dt_s);
        self.stats.frames += 1;
        let mut fallback = false;
        match &registration {
            Ok(r) => {
                let (m, c) = motion_in_body(r, &self.body_from_camera);
                if filter.predict_relative(&m, &c, dt_s).is_ok() {
                    match r.method {
                        Method::TrackIds => self.stats.by_track_ids += 1,
                        Method::Guided => self.stats.guided += 1,
                        Method::Search => self.stats.search += 1,
                    }
                    self.stats.inliers += r.inliers as u64;
                    self.stats.candidates_per_point += r.candidates_per_point;
                } else {
                    fallback = true;
                }
            }
            Err(RegistrationError::FirstFrame) => {}
            Err(_) => fallback = true,
        }
        if fallback {
            self.stats.failed += 1;
            if dt_s > 0.0 {
                filter.predict_constant_velocity(dt_s);
            }
        }
        MotionReport { registration, fallback }
    }

    /// Counts so far.
    pub fn stats(&self) -> &CameraOnlyStats {
        &self.stats
    }

    /// The front end's settings.
    pub fn config(&self) -> &FrontEndConfig {
        self.frontend.config()
    }
}
