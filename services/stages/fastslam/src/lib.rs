//! The `fastslam` process's settings and its pure `step` logic: ordering odometry and stereo
//! frames on the data clock, converting wire types, and the end-of-run evaluation.
//! [`stage::FastSlamStage`] is the stage around it; `main.rs` one line.

use std::collections::{BTreeMap, VecDeque};

pub mod journal;
pub mod stage;
pub mod summary;

use fastslam::eval::TrajectorySample;
use fastslam::frontend::{FrontEndConfig, Method, RegistrationError};
use fastslam::{CameraOnly, FastSlam, FastSlamConfig, FrameReport, MotionReport, Observation};
use geometry::ProcessInput;
use nalgebra::{Matrix3, Vector3};
use pipeline_runtime::Validate;
use pipeline_runtime::{Issues, ProcessSettings};
use serde::{Deserialize, Serialize};
use shared_types::{OdometryInput, STEREO_HAS_DESCRIPTOR, STEREO_HAS_TRACK_ID, StereoObservation};

/// How the particles are predicted between frames.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, schemars::JsonSchema, Default)]
#[serde(rename_all = "snake_case")]
pub enum MotionModel {
    /// From the odometry/input stream (EQUATIONS §1).
    #[default]
    Odometry,
    /// Camera only: constant velocity (no odometry stream needed).
    ConstantVelocity,
    /// Camera only: the motion between consecutive stereo frames registered by the stereo front
    /// end (`frontend` table), constant velocity for a frame it finds no motion for.
    Stereo,
}

/// The stereo camera's mounting on the body.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct CameraMount {
    /// Camera position in the body frame, m.
    pub offset_m: [f64; 3],
    /// Pitch below body x, deg (optical z along body x when 0).
    pub pitch_down_deg: f64,
    /// The observations are already in the body frame (identity extrinsic).
    pub identity: bool,
}

impl Default for CameraMount {
    fn default() -> Self {
        // The simulator's stereo camera.
        Self { offset_m: [0.5, 0.0, -0.2], pitch_down_deg: 35.0, identity: false }
    }
}

/// Settings of the `fastslam` process.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct FastSlamSettings {
    /// The filter.
    pub filter: FastSlamConfig,
    /// Prediction model.
    pub motion_model: MotionModel,
    /// The camera extrinsic.
    pub camera: CameraMount,
    /// The stereo front end (`motion_model = "stereo"`).
    pub frontend: FrontEndConfig,
    /// Rate of the best particle's landmark map on `pipeline/slam/landmarks`, Hz (0 = only at the end).
    pub landmarks_rate_hz: f64,
    /// Stereo frames its input holds (1 to the service's 8): a replay as fast as possible is then
    /// at most this many frames ahead of SLAM (the frame-to-pose latency stays near one frame's
    /// work instead of a queue of them); a live source drops frames (counted) when SLAM falls
    /// this far behind.
    pub stereo_queue: usize,
    /// Ground truth to evaluate against at the end (TUM; relative to the output directory);
    /// skipped when missing.
    pub ground_truth: String,
}

impl Default for FastSlamSettings {
    fn default() -> Self {
        Self {
            filter: FastSlamConfig::default(),
            motion_model: MotionModel::Odometry,
            camera: CameraMount::default(),
            frontend: FrontEndConfig::default(),
            landmarks_rate_hz: 1.0,
            stereo_queue: 2,
            ground_truth: "ground_truth.tum".into(),
        }
    }
}

impl ProcessSettings for FastSlamSettings {
    fn shm_estimate_bytes(&self, _extra_subscribers: usize) -> u64 {
        // pose, particles, landmarks (grows by powers of two), diagnostics.
        let particles = (self.filter.particles * 64).next_power_of_two() as u64;
        particles * 12 + (1 << 20) * 12 + (1 << 20)
    }
}

impl Validate for FastSlamSettings {
    fn validate(&self, issues: &mut Issues) {
        issues.nested("filter", &self.filter);
        issues.nested("frontend", &self.frontend);
        let max =
            shared_types::services::service_spec(shared_types::services::STEREO).map_or(1, |s| s.qos.subscriber_buffer);
        issues.check(
            (1..=max).contains(&self.stereo_queue),
            "stereo_queue",
            format!("must be 1..={max} (the stereo service's subscriber buffer), got {}", self.stereo_queue),
        );
        issues.check(
            self.landmarks_rate_hz.is_finite() && self.landmarks_rate_hz >= 0.0,
            "landmarks_rate_hz",
            "must be >= 0",
        );
        issues.check(self.camera.offset_m.iter().all(|v| v.is_finite()), "camera.offset_m", "must be finite");
    }
}

impl FastSlamSettings {
    /// `body_from_camera` of the mounting.
    pub fn body_from_camera(&self) -> nalgebra::Isometry3<f64> {
        if self.camera.identity {
            nalgebra::Isometry3::identity()
        } else {
            geometry::body_from_camera(&Vector3::from(self.camera.offset_m), self.camera.pitch_down_deg.to_radians())
        }
    }
}

/// A stereo frame waiting for the odometry up to its stamp.
#[derive(Debug, Clone)]
pub struct PendingFrame {
    /// Stamp, ns.
    pub stamp_ns: u64,
    /// Its origin time (for end-to-end latency), ns.
    pub origin_ns: u64,
    /// Observations (body frame); invalid ones already dropped.
    pub observations: Vec<Observation>,
    /// Observations dropped as invalid.
    pub rejected: usize,
}

/// Converts a wire frame; NaN or a covariance that is not positive definite drops that
/// observation (counted), never the frame. With the flag `STEREO_HAS_TRACK_ID` an observation's
/// `source_id` becomes its feature track id.
pub fn frame_from_wire(
    stamp_ns: u64,
    origin_ns: u64,
    obs: &[StereoObservation],
    body_from_camera: &nalgebra::Isometry3<f64>,
) -> PendingFrame {
    let mut observations = Vec::with_capacity(obs.len());
    let mut rejected = 0;
    for o in obs {
        let desc = (o.flags & STEREO_HAS_DESCRIPTOR != 0).then_some(o.descriptor);
        match Observation::from_camera(
            &Vector3::from(o.point_cam_m),
            &Matrix3::from_row_slice(&o.covariance_cam_m2),
            desc,
            body_from_camera,
        ) {
            Ok(mut ob) => {
                ob.track_id = (o.flags & STEREO_HAS_TRACK_ID != 0).then_some(o.source_id);
                observations.push(ob)
            }
            Err(_) => rejected += 1,
        }
    }
    PendingFrame { stamp_ns, origin_ns, observations, rejected }
}

/// The process state around the filter: input ordering and the trajectory log.
pub struct SlamState {
    /// The filter.
    pub filter: FastSlam,
    /// Motion model.
    pub motion: MotionModel,
    /// Odometry not yet applied: (stamp, input, variances of v, δθx, δθy, δθz).
    pub odometry: VecDeque<(u64, ProcessInput, [f64; 4])>,
    /// Stereo frames not yet processed.
    pub frames: VecDeque<PendingFrame>,
    /// Newest odometry stamp received, ns.
    pub newest_odometry_ns: Option<u64>,
    /// Stamp of the last processed frame, ns.
    pub last_frame_ns: Option<u64>,
    /// The estimated trajectory (one sample per frame).
    pub trajectory: Vec<TrajectorySample>,
    /// Data time at which each local map's frame was the body frame, s.
    pub segment_origins_s: BTreeMap<u32, f64>,
    /// Observations dropped as invalid.
    pub rejected_observations: usize,
    /// Odometry messages dropped as invalid.
    pub rejected_odometry: usize,
    /// The stereo front end (`MotionModel::Stereo`).
    pub camera_only: Option<CameraOnly>,
}

/// A processed frame.
pub struct Processed {
    /// Its stamp, ns.
    pub stamp_ns: u64,
    /// Its origin time, ns.
    pub origin_ns: u64,
    /// The filter's report.
    pub report: FrameReport,
    /// The stereo front end's motion (`MotionModel::Stereo`).
    pub motion: Option<MotionReport>,
    /// Time of the front end, ms.
    pub frontend_ms: f64,
}

impl Processed {
    /// The `SlamDiagnostics::motion_source` code of this frame.
    pub fn motion_source(&self, model: MotionModel) -> u32 {
        match (&self.motion, model) {
            (_, MotionModel::Odometry) => shared_types::MOTION_ODOMETRY,
            (_, MotionModel::ConstantVelocity) => shared_types::MOTION_CONSTANT_VELOCITY,
            (Some(m), MotionModel::Stereo) => match &m.registration {
                _ if m.fallback => shared_types::MOTION_REGISTRATION_FAILED,
                Ok(r) => match r.method {
                    Method::TrackIds => shared_types::MOTION_REGISTRATION_TRACK_IDS,
                    Method::Guided => shared_types::MOTION_REGISTRATION_GUIDED,
                    Method::Search => shared_types::MOTION_REGISTRATION_SEARCH,
                },
                Err(RegistrationError::FirstFrame) => shared_types::MOTION_FIRST_FRAME,
                Err(_) => shared_types::MOTION_REGISTRATION_FAILED,
            },
            (None, MotionModel::Stereo) => shared_types::MOTION_FIRST_FRAME,
        }
    }
}

impl SlamState {
    /// A new state around a filter; `frontend` (with the camera mounting) for
    /// `MotionModel::Stereo`.
    pub fn new(filter: FastSlam, motion: MotionModel) -> Self {
        Self::with_frontend(filter, motion, FrontEndConfig::default(), nalgebra::Isometry3::identity())
    }

    /// A new state around a filter, with the stereo front end's settings and the camera mounting
    /// `body_from_camera` (used with `MotionModel::Stereo`).
    pub fn with_frontend(
        filter: FastSlam,
        motion: MotionModel,
        frontend: FrontEndConfig,
        body_from_camera: nalgebra::Isometry3<f64>,
    ) -> Self {
        Self {
            camera_only: (motion == MotionModel::Stereo).then(|| CameraOnly::new(frontend, body_from_camera)),
            filter,
            motion,
            odometry: VecDeque::new(),
            frames: VecDeque::new(),
            newest_odometry_ns: None,
            last_frame_ns: None,
            trajectory: vec![],
            segment_origins_s: BTreeMap::new(),
            rejected_observations: 0,
            rejected_odometry: 0,
        }
    }

    /// Takes over what a killed instance had done: its trajectory and local map origins; the
    /// filter goes on in a new local map numbered after the last one.
    pub fn resume(&mut self, restored: journal::Restored) {
        let next = restored.next_segment();
        while self.filter.segment() < next {
            self.filter.start_new_segment(fastslam::SegmentReason::Requested);
        }
        self.trajectory = restored.trajectory;
        self.segment_origins_s = restored.segment_origins_s;
    }

    /// Queues an odometry message (from the wire).
    pub fn push_odometry(&mut self, stamp_ns: u64, u: &OdometryInput) {
        let input = ProcessInput { v_mps: u.v_mps, delta_theta_rad: Vector3::from(u.delta_theta_rad), dt_s: u.dt_s };
        let var = [u.input_covariance[0], u.input_covariance[5], u.input_covariance[10], u.input_covariance[15]];
        self.newest_odometry_ns = Some(self.newest_odometry_ns.map_or(stamp_ns, |s| s.max(stamp_ns)));
        self.odometry.push_back((stamp_ns, input, var));
    }

    /// The process's `step`: applies odometry and at most `max_frames` frames in stamp order. A frame is processed
    /// once odometry up to its stamp has arrived (or at once with the constant-velocity model,
    /// or when `flush` is set at the end of the stream).
    pub fn step(&mut self, flush: bool, max_frames: usize) -> Vec<Processed> {
        let mut out = vec![];
        while out.len() < max_frames
            && let Some(frame) = self.frames.front()
        {
            let ready = flush
                || self.motion != MotionModel::Odometry
                || self.newest_odometry_ns.is_some_and(|s| s >= frame.stamp_ns);
            if !ready {
                break;
            }
            let mut frame = self.frames.pop_front().expect("front exists");
            if !self.segment_origins_s.contains_key(&self.filter.segment()) {
                // The filter starts at the origin of its first local map (0, or the one after
                // the last of a killed instance) at its first input.
                let first = self
                    .odometry
                    .front()
                    .map(|(s, u, _)| *s as f64 / 1e9 - u.dt_s)
                    .unwrap_or(frame.stamp_ns as f64 / 1e9);
                self.segment_origins_s.insert(0, first);
            }
            let mut motion = None;
            let mut frontend_ms = 0.0;
            match self.motion {
                MotionModel::Stereo => {
                    let dt = self.last_frame_ns.map_or(0.0, |last| frame.stamp_ns.saturating_sub(last) as f64 / 1e9);
                    let t0 = std::time::Instant::now();
                    let cam = self.camera_only.as_mut().expect("stereo motion model has a front end");
                    motion = Some(cam.predict(&mut self.filter, &mut frame.observations, dt));
                    frontend_ms = t0.elapsed().as_secs_f64() * 1e3;
                }
                MotionModel::Odometry => {
                    while self.odometry.front().is_some_and(|(s, _, _)| *s <= frame.stamp_ns) {
                        let (_, u, var) = self.odometry.pop_front().expect("front exists");
                        if self.filter.predict(&u, var).is_err() {
                            self.rejected_odometry += 1;
                        }
                    }
                }
                MotionModel::ConstantVelocity => {
                    if let Some(last) = self.last_frame_ns {
                        let dt = frame.stamp_ns.saturating_sub(last) as f64 / 1e9;
                        if dt > 0.0 {
                            self.filter.predict_constant_velocity(dt);
                        }
                    }
                }
            }
            self.rejected_observations += frame.rejected;
            let report = self.filter.update(&frame.observations);
            let t_s = frame.stamp_ns as f64 / 1e9;
            if report.new_segment.is_some() {
                self.segment_origins_s.insert(self.filter.segment(), t_s);
            }
            let e = self.filter.estimate();
            self.trajectory.push(TrajectorySample {
                t_s,
                segment: self.filter.segment(),
                map_from_body: e.map_from_body,
                covariance: e.covariance,
            });
            self.last_frame_ns = Some(frame.stamp_ns);
            out.push(Processed { stamp_ns: frame.stamp_ns, origin_ns: frame.origin_ns, report, motion, frontend_ms });
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_stereo_queue_outside_the_services_buffer_is_refused_naming_its_key() {
        for (q, ok) in [(0, false), (1, true), (2, true), (8, true), (9, false)] {
            let s = FastSlamSettings { stereo_queue: q, ..Default::default() };
            let mut issues = Issues::at("processes.slam.settings");
            s.validate(&mut issues);
            let text = format!("{issues:?}");
            assert_eq!(!text.contains("processes.slam.settings.stereo_queue"), ok, "{q}: {text}");
        }
    }
}
