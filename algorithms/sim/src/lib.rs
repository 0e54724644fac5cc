//! A deterministic simulated underwater mission with ground truth (EQUATIONS §1, §2, §5, §7).
//!
//! A vehicle driven by the process model of EQUATIONS §1 (inputs v, δθ) flies a survey — a descent, a
//! lawnmower over seabed terrain, rocks and a wreck at alternating depths (passing a barren sand
//! band), then a shallow transit in open water out of stereo range — while its sensors sample the
//! scene, each at its own rate and with configurable noise: odometry/input, stereo landmark
//! observations (pixel noise → triangulated point with first-order covariance, plus spurious
//! detections), ranges to surface buoys (bias, outliers, dropouts), depth-camera point clouds
//! (ray cast), and pressure depth. [`Simulator`] yields [`SimEvent`]s in time order; the same seed
//! gives the same events. Each sensor draws from its own random stream, so changing one sensor's
//! settings does not change another's noise.

pub mod config;
pub mod indoor;
pub mod road;
pub mod scene;

use std::collections::VecDeque;

use geometry::{ProcessInput, StereoPixels, body_from_camera, euler_zyx_from_rotation, propagate};
use nalgebra::{Isometry3, Matrix3, Point3, Translation3, UnitQuaternion, Vector3};
use rand::{RngExt, SeedableRng};
use rand_distr::{Distribution, Normal};
use rand_xoshiro::Xoshiro256PlusPlus;

pub use config::*;
pub use scene::*;

/// Errors of the simulator.
#[derive(Debug, thiserror::Error)]
pub enum SimError {
    /// The configuration is invalid: every problem, keyed below the sim table.
    #[error("invalid simulator config: {}", .0.iter().map(|i| format!("{}: {}", i.key, i.message)).collect::<Vec<_>>().join("; "))]
    Config(Vec<validation::ConfigIssue>),
}

/// The true pose at one instant.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TruthSample {
    /// Time, s.
    pub t_s: f64,
    /// The vehicle's true pose.
    pub world_from_body: Isometry3<f64>,
}

/// Measured odometry over the step ending at `t_s`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct OdometrySample {
    /// Time, s.
    pub t_s: f64,
    /// The measured input (true input plus noise).
    pub input: ProcessInput,
    /// Noise variances of (v, δθx, δθy, δθz).
    pub variances: [f64; 4],
}

/// One stereo observation.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StereoObservation {
    /// Triangulated point, camera optical frame, m.
    pub point_cam_m: Vector3<f64>,
    /// Its covariance, m².
    pub covariance_cam_m2: Matrix3<f64>,
    /// The noisy pixels it was triangulated from.
    pub pixels: StereoPixels,
    /// The scene landmark, `None` for a spurious detection.
    pub landmark_id: Option<u64>,
    /// Descriptor.
    pub descriptor: [u8; 32],
}

/// All stereo observations of one camera frame.
#[derive(Debug, Clone, PartialEq)]
pub struct StereoFrame {
    /// Time, s.
    pub t_s: f64,
    /// Observations.
    pub observations: Vec<StereoObservation>,
}

/// One range to a buoy.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BuoyRangeSample {
    /// Buoy id (index into the scene's buoys).
    pub buoy_id: u32,
    /// Measured range, m.
    pub range_m: f64,
    /// Nominal σ, m.
    pub sigma_m: f64,
}

/// The ranges of one ping cycle.
#[derive(Debug, Clone, PartialEq)]
pub struct BuoyRanges {
    /// Time, s.
    pub t_s: f64,
    /// Ranges (dropped ones are missing).
    pub ranges: Vec<BuoyRangeSample>,
}

/// A depth-camera point cloud.
#[derive(Debug, Clone, PartialEq)]
pub struct DepthCloud {
    /// Time, s.
    pub t_s: f64,
    /// The true pose of the sensor (optical frame).
    pub world_from_sensor: Isometry3<f64>,
    /// Points in the sensor's optical frame, m.
    pub points_sensor_m: Vec<[f32; 3]>,
}

/// A pressure-depth reading.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PressureSample {
    /// Time, s.
    pub t_s: f64,
    /// Depth below the surface, m.
    pub depth_m: f64,
    /// σ, m.
    pub sigma_m: f64,
}

/// A compass reading: the body's yaw.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CompassSample {
    /// Time, s.
    pub t_s: f64,
    /// Yaw of body x in the world (about world z, counter-clockwise from world x), rad, in (−π, π].
    pub yaw_rad: f64,
    /// σ, rad.
    pub sigma_rad: f64,
}

/// One measurement, in time order.
#[derive(Debug, Clone, PartialEq)]
pub enum SimEvent {
    /// Odometry.
    Odometry(OdometrySample),
    /// Stereo frame.
    Stereo(StereoFrame),
    /// Buoy ranges.
    Buoys(BuoyRanges),
    /// Depth cloud.
    Cloud(DepthCloud),
    /// Pressure depth.
    Pressure(PressureSample),
    /// Compass heading.
    Compass(CompassSample),
}

impl SimEvent {
    /// Time of the event, s.
    pub fn t_s(&self) -> f64 {
        match self {
            SimEvent::Odometry(e) => e.t_s,
            SimEvent::Stereo(e) => e.t_s,
            SimEvent::Buoys(e) => e.t_s,
            SimEvent::Cloud(e) => e.t_s,
            SimEvent::Pressure(e) => e.t_s,
            SimEvent::Compass(e) => e.t_s,
        }
    }
}

/// A ray's hit distance (m) and its unit direction in the sensor frame, `None` for no hit.
type RayHit = Option<(f64, Vector3<f64>)>;

/// Independent random streams, one per sensor.
struct Streams {
    odometry: Xoshiro256PlusPlus,
    stereo: Xoshiro256PlusPlus,
    buoys: Xoshiro256PlusPlus,
    depth: Xoshiro256PlusPlus,
    pressure: Xoshiro256PlusPlus,
    compass: Xoshiro256PlusPlus,
}

/// The simulator: an iterator of [`SimEvent`]s.
pub struct Simulator {
    cfg: SimConfig,
    scene: Scene,
    waypoints: Vec<Vector3<f64>>,
    next_waypoint: usize,
    t_s: f64,
    pose: Isometry3<f64>,
    truth: Vec<TruthSample>,
    pending: VecDeque<SimEvent>,
    next_stereo_s: f64,
    next_buoys_s: f64,
    next_cloud_s: f64,
    next_pressure_s: f64,
    next_compass_s: f64,
    body_from_stereo: Isometry3<f64>,
    body_from_depth: Isometry3<f64>,
    rng: Streams,
    finished: bool,
    path_length_m: f64,
}

fn wrap_pi(a: f64) -> f64 {
    let two_pi = 2.0 * std::f64::consts::PI;
    (a + std::f64::consts::PI).rem_euclid(two_pi) - std::f64::consts::PI
}

impl Simulator {
    /// Builds the scene and the mission from `cfg`.
    pub fn new(cfg: SimConfig) -> Result<Self, SimError> {
        validation::Validate::issues(&cfg).into_result().map_err(SimError::Config)?;
        let seed = cfg.seed;
        let stream =
            |k: u64| Xoshiro256PlusPlus::seed_from_u64(seed.wrapping_mul(0x9E37_79B9_7F4A_7C15).wrapping_add(k));
        let scene = Scene::build(&cfg.scene, &mut stream(0));
        let m = &cfg.mission;
        let start = Vector3::from(m.start_m);
        let mut waypoints = vec![];
        let (x0, x1) = (start.x, start.x + m.leg_length_m);
        for i in 0..m.legs {
            let y = start.y + i as f64 * m.leg_spacing_m;
            let z = -m.leg_depths_m[i % m.leg_depths_m.len()];
            let (a, b) = if i % 2 == 0 { (x0, x1) } else { (x1, x0) };
            waypoints.push(Vector3::new(a, y, z));
            waypoints.push(Vector3::new(b, y, z));
        }
        let last = *waypoints.last().expect("at least one leg");
        waypoints.push(Vector3::new(last.x, last.y, -m.transit_depth_m));
        waypoints.push(Vector3::new(last.x, start.y, -m.transit_depth_m));
        waypoints.push(Vector3::new(start.x, start.y, -m.transit_depth_m));
        let mut path_length_m = 0.0;
        let mut prev = start;
        for w in &waypoints {
            path_length_m += (w - prev).norm();
            prev = *w;
        }
        // Start level, heading towards the first waypoint.
        let d = waypoints[0] - start;
        let yaw = d.y.atan2(d.x);
        let pose = Isometry3::from_parts(Translation3::from(start), UnitQuaternion::from_euler_angles(0.0, 0.0, yaw));
        let s = &cfg.sensors;
        let body_from_stereo =
            body_from_camera(&Vector3::from(s.stereo.offset_m), s.stereo.pitch_down_deg.to_radians());
        let body_from_depth =
            body_from_camera(&Vector3::new(0.6, 0.0, -0.3), s.depth_camera.pitch_down_deg.to_radians());
        let rng = Streams {
            odometry: stream(1),
            stereo: stream(2),
            buoys: stream(3),
            depth: stream(4),
            pressure: stream(5),
            compass: stream(6),
        };
        Ok(Self {
            truth: vec![TruthSample { t_s: 0.0, world_from_body: pose }],
            cfg,
            scene,
            waypoints,
            next_waypoint: 0,
            t_s: 0.0,
            pose,
            pending: VecDeque::new(),
            next_stereo_s: 0.0,
            next_buoys_s: 0.0,
            next_cloud_s: 0.0,
            next_pressure_s: 0.0,
            next_compass_s: 0.0,
            body_from_stereo,
            body_from_depth,
            rng,
            finished: false,
            path_length_m,
        })
    }

    /// The scene.
    pub fn scene(&self) -> &Scene {
        &self.scene
    }

    /// The configuration.
    pub fn config(&self) -> &SimConfig {
        &self.cfg
    }

    /// Ground truth so far (one sample per odometry step, starting at t = 0).
    pub fn truth(&self) -> &[TruthSample] {
        &self.truth
    }

    /// Simulated time, s.
    pub fn time_s(&self) -> f64 {
        self.t_s
    }

    /// Expected mission length (path length at cruise speed, capped by the time limit), s.
    pub fn expected_duration_s(&self) -> f64 {
        (self.path_length_m / self.cfg.mission.speed_mps * 1.2).min(self.cfg.mission.max_duration_s)
    }

    /// The stereo camera's mounting.
    pub fn body_from_stereo(&self) -> Isometry3<f64> {
        self.body_from_stereo
    }

    /// Advances one odometry step; false once the mission is over.
    fn step(&mut self) -> bool {
        if self.finished {
            return false;
        }
        let m = self.cfg.mission.clone();
        let dt = 1.0 / self.cfg.sensors.odometry.rate_hz;
        // Waypoint logic.
        let p = self.pose.translation.vector;
        while self.next_waypoint < self.waypoints.len() {
            let d = self.waypoints[self.next_waypoint] - p;
            if d.xy().norm() < 3.0 && d.z.abs() < 2.5 {
                self.next_waypoint += 1;
            } else {
                break;
            }
        }
        if self.next_waypoint >= self.waypoints.len() || self.t_s >= m.max_duration_s {
            self.finished = true;
            return false;
        }
        let target = self.waypoints[self.next_waypoint];
        let d = target - p;
        let horiz = d.xy().norm();
        let euler = euler_zyx_from_rotation(&self.pose.rotation.to_rotation_matrix());
        let (roll, pitch, yaw) = (euler.x, euler.y, euler.z);
        let max_rate = m.max_turn_rate_rps;
        // Keep the heading while only the depth changes.
        let yaw_des = if horiz > 1.0 { d.y.atan2(d.x) } else { yaw };
        let max_pitch = m.max_pitch_deg.to_radians();
        let pitch_des = (-d.z).atan2(horiz.max(4.0)).clamp(-max_pitch, max_pitch);
        let roll_des =
            m.roll_amplitude_deg.to_radians() * (2.0 * std::f64::consts::PI * self.t_s / m.roll_period_s).sin();
        let yaw_err = wrap_pi(yaw_des - yaw);
        let yaw_rate = (0.8 * yaw_err).clamp(-max_rate, max_rate);
        let pitch_rate = (0.8 * (pitch_des - pitch)).clamp(-max_rate, max_rate);
        let roll_rate = (1.0 * (roll_des - roll)).clamp(-max_rate, max_rate);
        // Euler rates (ZYX) to body angular velocity.
        let (sr, cr, sp, cp) = (roll.sin(), roll.cos(), pitch.sin(), pitch.cos());
        let w_body = Vector3::new(
            roll_rate - yaw_rate * sp,
            pitch_rate * cr + yaw_rate * sr * cp,
            -pitch_rate * sr + yaw_rate * cr * cp,
        );
        let v = if yaw_err.abs() > 1.0 { 0.5 * m.speed_mps } else { m.speed_mps };
        let u_true = ProcessInput { v_mps: v, delta_theta_rad: w_body * dt, dt_s: dt };
        self.pose = propagate(&self.pose, &u_true);
        self.t_s += dt;
        let t = self.t_s;
        self.truth.push(TruthSample { t_s: t, world_from_body: self.pose });

        // Odometry: true input plus noise.
        let o = &self.cfg.sensors.odometry;
        let nv = Normal::new(0.0, o.speed_sigma_mps.max(1e-12)).expect("valid sigma");
        let nt = Normal::new(0.0, o.turn_sigma_rad.max(1e-12)).expect("valid sigma");
        let r = &mut self.rng.odometry;
        let input = ProcessInput {
            v_mps: u_true.v_mps + nv.sample(r),
            delta_theta_rad: u_true.delta_theta_rad + Vector3::new(nt.sample(r), nt.sample(r), nt.sample(r)),
            dt_s: dt,
        };
        let (sv, st) = (o.speed_sigma_mps.powi(2), o.turn_sigma_rad.powi(2));
        self.pending.push_back(SimEvent::Odometry(OdometrySample { t_s: t, input, variances: [sv, st, st, st] }));

        let s = self.cfg.sensors.clone();
        if s.stereo.rate_hz > 0.0 && t >= self.next_stereo_s {
            self.next_stereo_s += 1.0 / s.stereo.rate_hz;
            let frame = self.stereo_frame(t);
            self.pending.push_back(SimEvent::Stereo(frame));
        }
        if s.buoys.rate_hz > 0.0 && t >= self.next_buoys_s {
            self.next_buoys_s += 1.0 / s.buoys.rate_hz;
            let ranges = self.buoy_ranges(t);
            self.pending.push_back(SimEvent::Buoys(ranges));
        }
        if s.depth_camera.rate_hz > 0.0 && t >= self.next_cloud_s {
            self.next_cloud_s += 1.0 / s.depth_camera.rate_hz;
            let cloud = self.depth_cloud(t);
            self.pending.push_back(SimEvent::Cloud(cloud));
        }
        if s.pressure.rate_hz > 0.0 && t >= self.next_pressure_s {
            self.next_pressure_s += 1.0 / s.pressure.rate_hz;
            let n = Normal::new(0.0, s.pressure.sigma_m.max(1e-12)).expect("valid sigma");
            let depth_m = -self.pose.translation.vector.z + n.sample(&mut self.rng.pressure);
            self.pending.push_back(SimEvent::Pressure(PressureSample { t_s: t, depth_m, sigma_m: s.pressure.sigma_m }));
        }
        if s.compass.rate_hz > 0.0 && t >= self.next_compass_s {
            self.next_compass_s += 1.0 / s.compass.rate_hz;
            let sigma_rad = s.compass.sigma_deg.to_radians();
            let n = Normal::new(0.0, sigma_rad.max(1e-12)).expect("valid sigma");
            // Yaw of body x projected on the horizontal plane.
            let x = self.pose.rotation * Vector3::x();
            let yaw = x.y.atan2(x.x) + n.sample(&mut self.rng.compass);
            let yaw_rad = (yaw + std::f64::consts::PI).rem_euclid(std::f64::consts::TAU) - std::f64::consts::PI;
            self.pending.push_back(SimEvent::Compass(CompassSample { t_s: t, yaw_rad, sigma_rad }));
        }
        true
    }

    fn stereo_frame(&mut self, t_s: f64) -> StereoFrame {
        let c = &self.cfg.sensors.stereo;
        let rig = c.rig;
        let world_from_cam = self.pose * self.body_from_stereo;
        let cam_from_world = world_from_cam.inverse();
        let mut near = vec![];
        self.scene.landmarks_near(&world_from_cam.translation.vector, c.max_range_m, &mut near);
        let noise = Normal::new(0.0, c.pixel_sigma_px).expect("valid sigma");
        let rng = &mut self.rng.stereo;
        let mut observations = vec![];
        let cam_origin = Point3::from(world_from_cam.translation.vector);
        for &i in &near {
            let l = self.scene.landmarks()[i as usize];
            let p_cam = cam_from_world * Point3::from(l.position_m);
            let Some(px) = rig.project(&p_cam.coords) else { continue };
            if px.u_left_px - px.u_right_px < c.min_disparity_px {
                continue;
            }
            // Occlusion: something closer on the line of sight hides the landmark.
            let to = l.position_m - cam_origin.coords;
            let dist = to.norm();
            if let Some(hit) = self.scene.ray_cast(&cam_origin, &(to / dist), dist)
                && hit < dist - 0.1
            {
                continue;
            }
            let noisy = StereoPixels {
                u_left_px: px.u_left_px + noise.sample(rng),
                u_right_px: px.u_right_px + noise.sample(rng),
                v_px: px.v_px + noise.sample(rng),
            };
            let (Ok(point_cam_m), Ok(covariance_cam_m2)) =
                (rig.triangulate(&noisy), rig.triangulation_covariance(&noisy, c.pixel_sigma_px))
            else {
                continue;
            };
            observations.push(StereoObservation {
                point_cam_m,
                covariance_cam_m2,
                pixels: noisy,
                landmark_id: Some(i as u64),
                descriptor: l.descriptor,
            });
        }
        let spurious = (observations.len() as f64 * c.spurious_fraction).round() as usize;
        for _ in 0..spurious {
            let d = rng.random_range(c.min_disparity_px..(c.min_disparity_px * 8.0));
            let u = rng.random_range(d..rig.width_px as f64);
            let px =
                StereoPixels { u_left_px: u, u_right_px: u - d, v_px: rng.random_range(0.0..rig.height_px as f64) };
            let mut descriptor = [0u8; 32];
            rand::Rng::fill_bytes(rng, &mut descriptor);
            if let (Ok(point_cam_m), Ok(covariance_cam_m2)) =
                (rig.triangulate(&px), rig.triangulation_covariance(&px, c.pixel_sigma_px))
            {
                observations.push(StereoObservation {
                    point_cam_m,
                    covariance_cam_m2,
                    pixels: px,
                    landmark_id: None,
                    descriptor,
                });
            }
        }
        StereoFrame { t_s, observations }
    }

    fn buoy_ranges(&mut self, t_s: f64) -> BuoyRanges {
        let b = &self.cfg.sensors.buoys;
        let n = Normal::new(0.0, b.sigma_m).expect("valid sigma");
        let rng = &mut self.rng.buoys;
        let p = self.pose.translation.vector;
        let mut ranges = vec![];
        for (id, pos) in self.scene.buoys_m.iter().enumerate() {
            // Draw every random number every time, so the sequence does not depend on outcomes.
            let drop = rng.random_bool(b.dropout_probability);
            let outlier = rng.random_bool(b.outlier_probability);
            let extra = rng.random_range(b.outlier_min_m.max(0.0)..=b.outlier_max_m.max(b.outlier_min_m.max(0.0)));
            let noise = n.sample(rng);
            // Only drawn when asked for, so the default sequence stays as it was.
            let short = b.outliers_both_signs && rng.random_bool(0.5);
            if drop || (outlier && b.outliers_removed) {
                continue;
            }
            let mut range_m = (p - Vector3::from(*pos)).norm() + b.bias_m + noise;
            if outlier {
                range_m = if short && range_m - extra >= 0.05 { range_m - extra } else { range_m + extra };
            }
            ranges.push(BuoyRangeSample { buoy_id: id as u32, range_m: range_m.max(0.0), sigma_m: b.sigma_m });
        }
        BuoyRanges { t_s, ranges }
    }

    fn depth_cloud(&mut self, t_s: f64) -> DepthCloud {
        let c = self.cfg.sensors.depth_camera.clone();
        let world_from_sensor = self.pose * self.body_from_depth;
        let (w, h) = (c.width_px as usize, c.height_px as usize);
        let f = (w as f64 / 2.0) / (c.hfov_deg.to_radians() / 2.0).tan();
        let (cx, cy) = (w as f64 / 2.0, h as f64 / 2.0);
        let origin = Point3::from(world_from_sensor.translation.vector);
        let rot = world_from_sensor.rotation;
        let scene = &self.scene;
        let threads = c.threads.max(1).min(h.max(1));
        let rows_per = h.div_ceil(threads);
        // Ray casting split by rows over threads; the noise is drawn afterwards, in pixel order,
        // so the result does not depend on the number of threads.
        let ranges: Vec<Vec<RayHit>> = crossbeam::thread::scope(|s| {
            let handles: Vec<_> = (0..threads)
                .map(|k| {
                    s.spawn(move |_| {
                        let mut out = Vec::with_capacity(rows_per * w);
                        for v in (k * rows_per)..((k + 1) * rows_per).min(h) {
                            for u in 0..w {
                                let d_cam =
                                    Vector3::new((u as f64 + 0.5 - cx) / f, (v as f64 + 0.5 - cy) / f, 1.0).normalize();
                                out.push(scene.ray_cast(&origin, &(rot * d_cam), c.max_range_m).map(|t| (t, d_cam)));
                            }
                        }
                        out
                    })
                })
                .collect();
            handles.into_iter().map(|h| h.join().expect("ray-casting thread panicked")).collect()
        })
        .expect("ray-casting scope");
        let noise = Normal::new(0.0, c.noise_sigma_m.max(1e-12)).expect("valid sigma");
        let rng = &mut self.rng.depth;
        let mut points_sensor_m = Vec::with_capacity(w * h);
        for (t, d) in ranges.into_iter().flatten().flatten() {
            let r = t + noise.sample(rng);
            let p = d * r;
            points_sensor_m.push([p.x as f32, p.y as f32, p.z as f32]);
        }
        DepthCloud { t_s, world_from_sensor, points_sensor_m }
    }
}

impl Iterator for Simulator {
    type Item = SimEvent;

    fn next(&mut self) -> Option<SimEvent> {
        loop {
            if let Some(e) = self.pending.pop_front() {
                return Some(e);
            }
            if !self.step() {
                return None;
            }
        }
    }
}
