//! Camera-only prediction: the stereo front end's frame-to-frame motion ([`crate::frontend`])
//! as FastSLAM's motion input when there is no odometry. When the front end finds no motion
//! (too few points, no consensus, degenerate geometry) the filter falls back to constant
//! velocity for that frame, with the wide `fallback_*` uncertainty of the front end's settings
//! (its map then has room to pull the pose back), and the report says so.

#![allow(non_snake_case)]

use nalgebra::{Isometry3, Matrix3, Vector3};
use serde::Serialize;

use crate::ekf::{stereo_coords, stereo_jacobian};
use crate::filter::{FastSlam, Observation};
use crate::frontend::{Frame, FrontEnd, FrontEndConfig, Method, Registration, RegistrationError, motion_in_body};
use crate::sym3::Chol3;

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
    /// Feature tracks continued after frames that did not see them
    /// (`FrontEndConfig::bridge_gap_frames`).
    pub bridged: u64,
}

/// A bridged track's χ² must be at least this much below any other lost track's.
const BRIDGE_MARGIN_CHI2: f64 = 2.0;

/// An observation of this camera as a point in the camera frame and its covariance.
fn camera_point(o: &Observation, body_from_camera: &Isometry3<f64>) -> Option<(Vector3<f64>, Matrix3<f64>)> {
    let st = o.stereo.as_ref().filter(|st| st.body_from_camera == *body_from_camera)?;
    let camera_from_body = st.body_from_camera.inverse();
    let R = camera_from_body.rotation.to_rotation_matrix().into_inner();
    Some((camera_from_body.transform_point(&o.z_m.into()).coords, R * o.Rz * R.transpose()))
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
    /// Each observation of the previous frame in its camera frame (point, covariance), when it
    /// was a stereo observation of this camera.
    prev_points: Vec<Option<(Vector3<f64>, Matrix3<f64>)>>,
    /// Tracks the registration did not continue, kept a few frames for a feature the detector
    /// missed in between.
    lost: Vec<LostTrack>,
    next_track: u64,
}

/// A feature track the last registration did not continue: its point where it was last seen,
/// in that camera frame, and that frame's pose in the current one.
#[derive(Debug, Clone)]
struct LostTrack {
    track: u64,
    p: Vector3<f64>,
    C: Matrix3<f64>,
    cur_from_then: Isometry3<f64>,
    frames: u32,
}

impl CameraOnly {
    /// A front end with `cfg` for a camera mounted at `body_from_camera`.
    pub fn new(cfg: FrontEndConfig, body_from_camera: Isometry3<f64>) -> Self {
        Self {
            frontend: FrontEnd::new(cfg),
            body_from_camera,
            stats: CameraOnlyStats::default(),
            prev_tracks: vec![],
            prev_points: vec![],
            lost: vec![],
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
            let points: Vec<Option<(Vector3<f64>, Matrix3<f64>)>> =
                obs.iter().map(|o| camera_point(o, &self.body_from_camera)).collect();
            if let Ok(r) = &registration {
                for &(i, j) in &r.matches {
                    if let (Some(t), Some(slot)) = (self.prev_tracks.get(i), tracks.get_mut(j)) {
                        *slot = *t;
                    }
                }
                self.bridge(r, &points, &mut tracks);
            } else {
                self.lost.clear();
            }
            self.prev_points = points;
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

    /// Continues tracks across frames in which a feature went unseen (the detector missed it, or
    /// the registration left it out): the previous frame's points that the registration `r` did
    /// not continue join the lost tracks, kept `bridge_gap_frames` frames with the motions since
    /// they were seen; a current point the registration left unmatched takes the track of the
    /// lost point whose prediction it agrees with inside the χ² gate in stereo coordinates (both
    /// points' covariances), when no other lost point agrees nearly as well
    /// (`BRIDGE_MARGIN_CHI2`); each lost track goes to one point at most, the best agreement
    /// first.
    fn bridge(&mut self, r: &Registration, points: &[Option<(Vector3<f64>, Matrix3<f64>)>], tracks: &mut [u64]) {
        let max_gap = self.frontend.config().bridge_gap_frames;
        let cur_from_prev = r.prev_from_cur.inverse();
        for l in &mut self.lost {
            l.cur_from_then = cur_from_prev * l.cur_from_then;
            l.frames += 1;
        }
        self.lost.retain(|l| l.frames <= max_gap);
        let mut prev_matched = vec![false; self.prev_tracks.len()];
        let mut cur_matched = vec![false; tracks.len()];
        for &(i, j) in &r.matches {
            if let Some(m) = prev_matched.get_mut(i) {
                *m = true;
            }
            if let Some(m) = cur_matched.get_mut(j) {
                *m = true;
            }
        }
        if max_gap > 0 {
            for (i, (pt, t)) in self.prev_points.iter().zip(&self.prev_tracks).enumerate() {
                if let (Some((p, C)), false) = (pt, prev_matched[i]) {
                    self.lost.push(LostTrack { track: *t, p: *p, C: *C, cur_from_then: cur_from_prev, frames: 1 });
                }
            }
        }
        if self.lost.is_empty() {
            return;
        }
        let gate = self.frontend.config().inlier_chi2;
        // The lost tracks predicted into this frame (stereo coordinates, their covariance, the
        // track's index), by the first coordinate.
        let mut predicted: Vec<(Vector3<f64>, Matrix3<f64>, usize)> = self
            .lost
            .iter()
            .enumerate()
            .filter_map(|(k, l)| {
                let p = l.cur_from_then.transform_point(&l.p.into()).coords;
                (p.z > 0.05).then(|| {
                    let R = l.cur_from_then.rotation.to_rotation_matrix().into_inner();
                    let J = stereo_jacobian(&p) * R;
                    (stereo_coords(&p), J * l.C * J.transpose(), k)
                })
            })
            .collect();
        predicted.sort_by(|a, b| a.0.x.total_cmp(&b.0.x));
        let widest = predicted.iter().map(|(_, S, _)| S[(0, 0)]).fold(0.0f64, f64::max);
        // For each unmatched current point, the best and the second best lost track.
        let mut claims: Vec<(f64, usize, usize)> = vec![];
        for (j, pt) in points.iter().enumerate() {
            let (Some((p, C)), false) = (pt, cur_matched[j]) else { continue };
            let J = stereo_jacobian(p);
            let (s, Cs) = (stereo_coords(p), J * C * J.transpose());
            let reach = (gate * (Cs[(0, 0)] + widest)).sqrt();
            let from = predicted.partition_point(|(sp, _, _)| sp.x < s.x - reach);
            let (mut best, mut second) = (None::<(f64, usize)>, f64::INFINITY);
            for (sp, Sp, k) in predicted[from..].iter().take_while(|(sp, _, _)| sp.x <= s.x + reach) {
                let nu = s - sp;
                let S = Sp + Cs;
                // νᵀS⁻¹ν ≥ νᵢ²/Sᵢᵢ: most are out on one coordinate alone.
                if (0..3).any(|i| nu[i] * nu[i] > gate * S[(i, i)]) {
                    continue;
                }
                let Some(m) = Chol3::new(&S).map(|c| c.mahalanobis(&nu)).filter(|m| *m <= gate) else { continue };
                match best {
                    Some((b, _)) if m >= b => second = second.min(m),
                    _ => {
                        if let Some((b, _)) = best {
                            second = second.min(b);
                        }
                        best = Some((m, *k));
                    }
                }
            }
            if let Some((m, k)) = best
                && second - m >= BRIDGE_MARGIN_CHI2
            {
                claims.push((m, j, k));
            }
        }
        claims.sort_by(|a, b| a.0.total_cmp(&b.0));
        let mut taken = vec![false; self.lost.len()];
        for (_, j, k) in claims {
            if !std::mem::replace(&mut taken[k], true) {
                tracks[j] = self.lost[k].track;
                self.stats.bridged += 1;
            }
        }
        let mut k = 0;
        self.lost.retain(|_| {
            k += 1;
            !taken[k - 1]
        });
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
