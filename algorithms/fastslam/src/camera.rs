//! Camera-only prediction: the stereo front end's frame-to-frame motion ([`crate::frontend`])
//! as FastSLAM's motion input when there is no odometry. When the front end finds no motion
//! (too few points, no consensus, degenerate geometry) the filter falls back to constant
//! velocity for that frame, with the wide `fallback_*` uncertainty of the front end's settings
//! (its map then has room to pull the pose back), and the report says so.

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

/// Track ids the front end gives features start here (apart from any source's ids).
pub const FRONTEND_TRACK_BASE: u64 = 1 << 62;

/// The front end wired to a filter.
pub struct CameraOnly {
    frontend: FrontEnd,
    body_from_camera: Isometry3<f64>,
    stats: CameraOnlyStats,
    /// The front end's track id of each observation of the previous frame.
    prev_tracks: Vec<u64>,
    next_track: u64,
}

impl CameraOnly {
    /// A front end with `cfg` for a camera mounted at `body_from_camera`.
    pub fn new(cfg: FrontEndConfig, body_from_camera: Isometry3<f64>) -> Self {
        Self {
            frontend: FrontEnd::new(cfg),
            body_from_camera,
            stats: CameraOnlyStats::default(),
            prev_tracks: vec![],
            next_track: FRONTEND_TRACK_BASE,
        }
    }

    /// Moves the filter's particles from the previous frame to this one (`obs`, body frame,
    /// `dt_s` after the previous frame) by the registered motion, or by constant velocity when
    /// there is none. With `assign_tracks`, observations without a track id get the front
    /// end's (a feature matched to one of the previous frame keeps its track). Call before
    /// [`FastSlam::update`] with the same observations.
    pub fn predict(&mut self, filter: &mut FastSlam, obs: &mut [Observation], dt_s: f64) -> MotionReport {
        let frame = Frame::from_observations(obs, &self.body_from_camera);
        let registration = self.frontend.register(frame, dt_s);
        if self.frontend.config().assign_tracks {
            let mut tracks: Vec<u64> = (0..obs.len() as u64).map(|k| self.next_track + k).collect();
            self.next_track += obs.len() as u64;
            if let Ok(r) = &registration {
                for &(i, j) in &r.matches {
                    if let (Some(t), Some(slot)) = (self.prev_tracks.get(i), tracks.get_mut(j)) {
                        *slot = *t;
                    }
                }
            }
            for (o, t) in obs.iter_mut().zip(&tracks) {
                if o.track_id.is_none() {
                    o.track_id = Some(*t);
                }
            }
            self.prev_tracks = tracks;
        }
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
                let c = self.frontend.config();
                let (sv, sw) = (c.fallback_velocity_sigma_mps, c.fallback_angular_velocity_sigma_rps);
                filter.predict_constant_velocity_with(dt_s, sv, sw);
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
