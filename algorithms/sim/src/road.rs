//! A KITTI-like stereo drive with ground truth: the realistic mode for tuning camera-only SLAM on
//! data that looks like real data rather than on the friendly underwater scene.
//!
//! A car drives a road of straights and curves (and one sharp turn at an intersection) at about
//! 10 m/s, the speed varying slowly, with suspension roll and pitch. A forward-looking rectified
//! stereo pair with KITTI's geometry (f 718 px, baseline 0.54 m, 1242 × 375 px, 1.65 m above the
//! road) sees facades, poles and trees beside the road, texture on the road surface, and far
//! structure (hills, distant buildings) up to a few hundred metres: depths from 2 m to beyond
//! 80 m, several hundred observations per frame, about 1 m between frames. The warts of real
//! stereo front ends are there too, each a setting:
//! - pixel noise on (uL, uR, v), the point and its first-order covariance triangulated from the
//!   noisy pixels (so far points are as poor as they really are);
//! - missed detections; a cap on the features per frame (the nearest kept, as detectors favour
//!   strong, close texture);
//! - wrong stereo matches (a wrong uR: a 3-D point at a wrong depth, with a plausible track id);
//! - spurious features (random pixels, a new track id each time);
//! - wrong feature tracks (an observation carrying another landmark's track id);
//! - dropped frames (the next frame is then twice as far: the front end must bridge it).
//!
//! Each observation carries the landmark it truly comes from (for evaluation) and the track id
//! a feature tracker would give it (the landmark id, except for the wrong tracks and spurious
//! features). The same seed gives the same drive.

use geometry::{StereoPixels, StereoRig, body_from_camera};
use nalgebra::{Isometry3, Matrix3, Translation3, UnitQuaternion, Vector3};
use rand::{RngExt, SeedableRng};
use rand_distr::{Distribution, Normal};
use rand_xoshiro::Xoshiro256PlusPlus;
use serde::{Deserialize, Serialize};

use crate::TruthSample;
use validation::{Issues, Validate};

/// Settings of the stereo drive.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RoadConfig {
    /// Seed of the road, the landmarks and the noise.
    pub seed: u64,
    /// Camera frames (including dropped ones).
    pub frames: usize,
    /// Frame rate, Hz.
    pub rate_hz: f64,
    /// Mean speed, m/s.
    pub speed_mps: f64,
    /// Amplitude of the slow speed variation, m/s.
    pub speed_variation_mps: f64,
    /// Largest yaw rate in curves, rad/s (the intersection's sharp turn is 1.5× this).
    pub max_yaw_rate_rps: f64,
    /// The rectified pair.
    pub rig: StereoRig,
    /// Height of the camera above the road, m.
    pub camera_height_m: f64,
    /// Pixel noise σ on uL, uR and v, px.
    pub pixel_sigma_px: f64,
    /// Smallest disparity of a detected feature, px (f·b/d: 2 px is ~190 m).
    pub min_disparity_px: f64,
    /// Most features per frame: beyond it the nearest are kept.
    pub max_features: usize,
    /// Probability that a visible landmark is detected in a frame.
    pub detection_probability: f64,
    /// Fraction of the features whose stereo match is wrong (a wrong uR).
    pub wrong_match_fraction: f64,
    /// Spurious features as a fraction of the real ones.
    pub spurious_fraction: f64,
    /// Fraction of the features that carry another landmark's track id.
    pub wrong_track_fraction: f64,
    /// Probability that a frame is lost (not published).
    pub dropped_frame_probability: f64,
    /// Landmarks per metre of road (all kinds together).
    pub landmarks_per_m: f64,
}

impl Default for RoadConfig {
    fn default() -> Self {
        Self {
            seed: 1,
            frames: 400,
            rate_hz: 10.0,
            speed_mps: 10.0,
            speed_variation_mps: 2.5,
            max_yaw_rate_rps: 0.3,
            rig: StereoRig {
                f_px: 718.0,
                cx_px: 607.0,
                cy_px: 185.0,
                baseline_m: 0.54,
                width_px: 1242,
                height_px: 375,
            },
            camera_height_m: 1.65,
            pixel_sigma_px: 0.5,
            min_disparity_px: 2.0,
            max_features: 700,
            detection_probability: 0.9,
            wrong_match_fraction: 0.1,
            spurious_fraction: 0.03,
            wrong_track_fraction: 0.01,
            dropped_frame_probability: 0.02,
            landmarks_per_m: 20.0,
        }
    }
}

impl Validate for RoadConfig {
    fn validate(&self, issues: &mut Issues) {
        let pos = |x: f64| x.is_finite() && x > 0.0;
        let frac = |x: f64| (0.0..=1.0).contains(&x);
        issues.check(self.frames >= 2, "frames", "must be >= 2");
        issues.check(pos(self.rate_hz), "rate_hz", "must be > 0");
        issues.check(pos(self.speed_mps), "speed_mps", "must be > 0");
        issues.check(
            self.speed_variation_mps.is_finite() && (0.0..self.speed_mps).contains(&self.speed_variation_mps),
            "speed_variation_mps",
            "must be in [0, speed_mps)",
        );
        issues.check(
            self.max_yaw_rate_rps.is_finite() && self.max_yaw_rate_rps >= 0.0,
            "max_yaw_rate_rps",
            "must be >= 0",
        );
        issues.check(
            pos(self.rig.f_px) && pos(self.rig.baseline_m) && self.rig.width_px > 0 && self.rig.height_px > 0,
            "rig",
            "focal length, baseline and image size must be > 0",
        );
        issues.check(pos(self.camera_height_m), "camera_height_m", "must be > 0");
        issues.check(pos(self.pixel_sigma_px), "pixel_sigma_px", "must be > 0");
        issues.check(pos(self.min_disparity_px), "min_disparity_px", "must be > 0");
        issues.check(self.max_features >= 1, "max_features", "must be >= 1");
        issues.check(frac(self.detection_probability), "detection_probability", "must be in [0, 1]");
        issues.check(frac(self.wrong_match_fraction), "wrong_match_fraction", "must be in [0, 1]");
        issues.check(frac(self.spurious_fraction), "spurious_fraction", "must be in [0, 1]");
        issues.check(frac(self.wrong_track_fraction), "wrong_track_fraction", "must be in [0, 1]");
        issues.check(
            (0.0..0.5).contains(&self.dropped_frame_probability),
            "dropped_frame_probability",
            "must be in [0, 0.5)",
        );
        issues.check(pos(self.landmarks_per_m), "landmarks_per_m", "must be > 0");
    }
}

/// One feature of a frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RoadObservation {
    /// Triangulated point, camera optical frame, m.
    pub point_cam_m: Vector3<f64>,
    /// Its first-order covariance, m².
    pub covariance_cam_m2: Matrix3<f64>,
    /// The noisy pixels it was triangulated from.
    pub pixels: StereoPixels,
    /// The landmark it truly comes from (`None` for a spurious feature).
    pub landmark_id: Option<u64>,
    /// The track id a feature tracker gives it.
    pub track_id: u64,
    /// True when its stereo match is wrong (the point is at a wrong depth).
    pub wrong_match: bool,
}

/// The features of one published frame.
#[derive(Debug, Clone, PartialEq)]
pub struct RoadFrame {
    /// Time, s.
    pub t_s: f64,
    /// Frame index (gaps where frames were dropped).
    pub index: usize,
    /// Features.
    pub observations: Vec<RoadObservation>,
}

/// Spurious features get track ids from here up.
pub const SPURIOUS_TRACK_BASE: u64 = 1 << 40;

/// The drive: an iterator of [`RoadFrame`]s; the ground truth of every frame (dropped ones
/// included) is in [`RoadSim::truth`].
pub struct RoadSim {
    cfg: RoadConfig,
    landmarks: Vec<Vector3<f64>>,
    /// Landmarks by 20 m cell of (x, y).
    cells: std::collections::HashMap<(i32, i32), Vec<u32>>,
    truth: Vec<TruthSample>,
    body_from_camera: Isometry3<f64>,
    next: usize,
    rng: Xoshiro256PlusPlus,
    next_spurious: u64,
    path_length_m: f64,
    dropped: usize,
    last_dropped: Option<usize>,
}

const CELL_M: f64 = 20.0;

impl RoadSim {
    /// Builds the road, its landmarks and the car's trajectory.
    pub fn new(cfg: RoadConfig) -> Result<Self, crate::SimError> {
        cfg.issues().into_result().map_err(crate::SimError::Config)?;
        let mut rng = Xoshiro256PlusPlus::seed_from_u64(cfg.seed);
        // Trajectory: yaw-rate segments (straights, curves, one sharp turn), slowly varying speed.
        let dt = 1.0 / cfg.rate_hz;
        let n = cfg.frames;
        let mut truth = Vec::with_capacity(n);
        let (mut x, mut y, mut yaw) = (0.0f64, 0.0f64, 0.0f64);
        let mut segment_left = 0.0;
        let mut yaw_rate = 0.0;
        let mut segment_kind = 0u32;
        let sharp_at = n / 2;
        let mut path = 0.0;
        let phase: f64 = rng.random_range(0.0..std::f64::consts::TAU);
        // The car follows the commanded speed and yaw rate with bounded accelerations: 2.5 m/s²
        // and 0.6 rad/s² (a real car's), so no frame-to-frame motion changes abruptly.
        let (max_accel, max_yaw_accel) = (2.5, 0.6);
        let mut speed = cfg.speed_mps + cfg.speed_variation_mps * phase.sin();
        let mut w = 0.0f64;
        for k in 0..n {
            let t = k as f64 * dt;
            let mut speed_cmd = cfg.speed_mps + cfg.speed_variation_mps * (0.25 * t + phase).sin();
            if segment_left <= 0.0 {
                segment_kind += 1;
                if segment_kind % 2 == 1 {
                    yaw_rate = 0.0;
                    segment_left = rng.random_range(3.0..8.0);
                } else {
                    let sign = if rng.random::<bool>() { 1.0 } else { -1.0 };
                    yaw_rate = sign * rng.random_range(0.3..1.0) * cfg.max_yaw_rate_rps;
                    segment_left = rng.random_range(2.0..5.0);
                }
            }
            // The intersection: slow down and turn 90° at 1.5× the largest curve rate.
            let sharp_rate = 1.5 * cfg.max_yaw_rate_rps;
            let turn_s = if sharp_rate > 0.0 { std::f64::consts::FRAC_PI_2 / sharp_rate } else { 0.0 };
            let w_cmd = if k + 10 >= sharp_at && ((k + 10).saturating_sub(sharp_at) as f64 * dt) < turn_s + 1.0 {
                speed_cmd *= 0.6; // brake a second before the turn and accelerate after it
                if k >= sharp_at && ((k - sharp_at) as f64 * dt) < turn_s { sharp_rate } else { 0.0 }
            } else {
                yaw_rate
            };
            speed += (speed_cmd - speed).clamp(-max_accel * dt, max_accel * dt);
            w += (w_cmd - w).clamp(-max_yaw_accel * dt, max_yaw_accel * dt);
            let roll = 0.6f64.to_radians() * (1.7 * t).sin();
            let pitch = 0.4f64.to_radians() * (2.3 * t + 1.0).sin();
            let bump = 0.02 * (3.1 * t).sin();
            let pose = Isometry3::from_parts(
                Translation3::new(x, y, bump),
                UnitQuaternion::from_euler_angles(roll, pitch, yaw),
            );
            truth.push(TruthSample { t_s: t, world_from_body: pose });
            x += speed * dt * yaw.cos();
            y += speed * dt * yaw.sin();
            yaw += w * dt;
            path += speed * dt;
            segment_left -= dt;
        }
        // Landmarks along the path (and a margin beyond both ends).
        let mut landmarks = vec![];
        let step = 1.0;
        let along: Vec<(Vector3<f64>, f64)> = {
            let mut v = vec![];
            let first = truth[0].world_from_body;
            let last = truth[n - 1].world_from_body;
            let h0 = first.rotation * Vector3::x();
            for k in (1..=100).rev() {
                v.push((first.translation.vector - h0 * k as f64, h0.y.atan2(h0.x)));
            }
            for w in truth.windows(2) {
                let (a, b) = (w[0].world_from_body.translation.vector, w[1].world_from_body.translation.vector);
                let d = (b - a).norm();
                let h = w[0].world_from_body.rotation * Vector3::x();
                let m = (d / step).ceil().max(1.0) as usize;
                for i in 0..m {
                    v.push((a + (b - a) * (i as f64 / m as f64), h.y.atan2(h.x)));
                }
            }
            let h1 = last.rotation * Vector3::x();
            for k in 1..=200 {
                v.push((last.translation.vector + h1 * k as f64, h1.y.atan2(h1.x)));
            }
            v
        };
        let density = cfg.landmarks_per_m;
        for (c, heading) in &along {
            let fwd = Vector3::new(heading.cos(), heading.sin(), 0.0);
            let left = Vector3::new(-heading.sin(), heading.cos(), 0.0);
            let count = density * step;
            let whole = count.floor() as usize + (rng.random::<f64>() < count.fract()) as usize;
            for _ in 0..whole {
                let jitter = fwd * rng.random_range(-0.5..0.5);
                let u: f64 = rng.random();
                let p = if u < 0.40 {
                    // Facades.
                    let side = if rng.random::<bool>() { 1.0 } else { -1.0 };
                    c + jitter + left * side * rng.random_range(7.0..13.0) + Vector3::z() * rng.random_range(0.0..12.0)
                } else if u < 0.60 {
                    // Road texture and kerbs.
                    c + jitter + left * rng.random_range(-6.0..6.0)
                } else if u < 0.75 {
                    // Poles, trees, parked cars.
                    let side = if rng.random::<bool>() { 1.0 } else { -1.0 };
                    c + jitter + left * side * rng.random_range(4.0..7.0) + Vector3::z() * rng.random_range(0.0..4.0)
                } else {
                    // Far structure.
                    let side = if rng.random::<bool>() { 1.0 } else { -1.0 };
                    c + jitter * 10.0
                        + left * side * rng.random_range(15.0..120.0)
                        + Vector3::z() * rng.random_range(0.0..35.0)
                };
                landmarks.push(p);
            }
        }
        let mut cells: std::collections::HashMap<(i32, i32), Vec<u32>> = std::collections::HashMap::new();
        for (i, p) in landmarks.iter().enumerate() {
            cells.entry(((p.x / CELL_M).floor() as i32, (p.y / CELL_M).floor() as i32)).or_default().push(i as u32);
        }
        let body_from_camera = body_from_camera(&Vector3::new(1.0, 0.0, cfg.camera_height_m), 0.0);
        Ok(Self {
            rng: Xoshiro256PlusPlus::seed_from_u64(cfg.seed ^ 0x5eed_5eed),
            cfg,
            landmarks,
            cells,
            truth,
            body_from_camera,
            next: 0,
            next_spurious: SPURIOUS_TRACK_BASE,
            path_length_m: path,
            dropped: 0,
            last_dropped: None,
        })
    }

    /// The settings.
    pub fn config(&self) -> &RoadConfig {
        &self.cfg
    }

    /// The true pose of the car at every frame (dropped ones included).
    pub fn truth(&self) -> &[TruthSample] {
        &self.truth
    }

    /// The camera's mounting: optical frame looking along body x, 1 m ahead of the body origin
    /// (on the road below the rear axle) and `camera_height_m` above it.
    pub fn body_from_camera(&self) -> Isometry3<f64> {
        self.body_from_camera
    }

    /// Number of landmarks.
    pub fn landmark_count(&self) -> usize {
        self.landmarks.len()
    }

    /// Length of the driven path, m.
    pub fn path_length_m(&self) -> f64 {
        self.path_length_m
    }

    /// Frames dropped so far.
    pub fn dropped(&self) -> usize {
        self.dropped
    }

    /// Fraction of the frames produced so far.
    pub fn progress(&self) -> f64 {
        self.next as f64 / self.cfg.frames as f64
    }

    fn frame(&mut self, index: usize) -> RoadFrame {
        let cfg = &self.cfg;
        let rig = cfg.rig;
        let world_from_cam = self.truth[index].world_from_body * self.body_from_camera;
        let cam_from_world = world_from_cam.inverse();
        let c = world_from_cam.translation.vector;
        let max_depth = rig.f_px * rig.baseline_m / cfg.min_disparity_px;
        let reach = (max_depth / CELL_M).ceil() as i32 + 1;
        let (cx, cy) = ((c.x / CELL_M).floor() as i32, (c.y / CELL_M).floor() as i32);
        let mut visible: Vec<(f64, u32, StereoPixels, Vector3<f64>)> = vec![];
        for dx in -reach..=reach {
            for dy in -reach..=reach {
                let Some(ids) = self.cells.get(&(cx + dx, cy + dy)) else { continue };
                for &i in ids {
                    let p = cam_from_world.transform_point(&self.landmarks[i as usize].into()).coords;
                    if p.z < 1.0 || p.z > max_depth {
                        continue;
                    }
                    let Some(px) = rig.project(&p) else { continue };
                    if px.u_left_px - px.u_right_px < cfg.min_disparity_px {
                        continue;
                    }
                    visible.push((p.z, i, px, p));
                }
            }
        }
        let rng = &mut self.rng;
        visible.retain(|_| rng.random::<f64>() < cfg.detection_probability);
        visible.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        visible.truncate(cfg.max_features);
        let noise = Normal::new(0.0, cfg.pixel_sigma_px).expect("validated σ");
        let mut observations = Vec::with_capacity(visible.len() + 8);
        let n_real = visible.len();
        for (_, i, px, _) in &visible {
            let mut noisy = StereoPixels {
                u_left_px: px.u_left_px + noise.sample(rng),
                u_right_px: px.u_right_px + noise.sample(rng),
                v_px: px.v_px + noise.sample(rng),
            };
            let wrong_match = rng.random::<f64>() < cfg.wrong_match_fraction;
            if wrong_match {
                // The right image's match is another feature on the same row.
                let d = rng.random_range(cfg.min_disparity_px..(cfg.min_disparity_px + 120.0));
                noisy.u_right_px = noisy.u_left_px - d;
            }
            let (Ok(p), Ok(cov)) = (rig.triangulate(&noisy), rig.triangulation_covariance(&noisy, cfg.pixel_sigma_px))
            else {
                continue;
            };
            let mut track_id = *i as u64;
            if n_real > 1 && rng.random::<f64>() < cfg.wrong_track_fraction {
                track_id = visible[rng.random_range(0..n_real)].1 as u64;
            }
            observations.push(RoadObservation {
                point_cam_m: p,
                covariance_cam_m2: cov,
                pixels: noisy,
                landmark_id: Some(*i as u64),
                track_id,
                wrong_match,
            });
        }
        let spurious = (n_real as f64 * cfg.spurious_fraction).round() as usize;
        for _ in 0..spurious {
            let d = rng.random_range(cfg.min_disparity_px..(cfg.min_disparity_px + 100.0));
            let u = rng.random_range(d..rig.width_px as f64);
            let px =
                StereoPixels { u_left_px: u, u_right_px: u - d, v_px: rng.random_range(0.0..rig.height_px as f64) };
            if let (Ok(p), Ok(cov)) = (rig.triangulate(&px), rig.triangulation_covariance(&px, cfg.pixel_sigma_px)) {
                observations.push(RoadObservation {
                    point_cam_m: p,
                    covariance_cam_m2: cov,
                    pixels: px,
                    landmark_id: None,
                    track_id: self.next_spurious,
                    wrong_match: false,
                });
                self.next_spurious += 1;
            }
        }
        // Features come in no particular order.
        for i in (1..observations.len()).rev() {
            observations.swap(i, rng.random_range(0..=i));
        }
        RoadFrame { t_s: self.truth[index].t_s, index, observations }
    }
}

impl Iterator for RoadSim {
    type Item = RoadFrame;

    fn next(&mut self) -> Option<RoadFrame> {
        while self.next < self.cfg.frames {
            let k = self.next;
            self.next += 1;
            // Never drop the first frame or two in a row.
            let drop = k > 0
                && self.rng.random::<f64>() < self.cfg.dropped_frame_probability
                && self.last_dropped != Some(k - 1);
            if drop {
                self.dropped += 1;
                self.last_dropped = Some(k);
                continue;
            }
            return Some(self.frame(k));
        }
        None
    }
}
