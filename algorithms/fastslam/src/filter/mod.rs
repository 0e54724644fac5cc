//! The particle filter (EQUATIONS §4, [3D] Alg 1-2): prediction through the process model with input
//! and process noise, per-particle data association and landmark EKF updates, log-space weights,
//! systematic resampling on low N_eff, the weighted estimate, and the multi-map mechanism.

#![allow(non_snake_case)]

use std::collections::HashMap;

use geometry::{ProcessInput, propagate};
use nalgebra::{Cholesky, Isometry3, Matrix3, Matrix6, Translation3, UnitQuaternion, Vector3, Vector6};
use rand::{RngExt, SeedableRng};
use rand_distr::{Distribution, StandardNormal};
use rand_xoshiro::Xoshiro256PlusPlus;

use crate::config::{FastSlamConfig, Proposal};
use crate::ekf::{self, FilterError, Innovation, LandmarkEkf, hamming, init_landmark, innovation};
use crate::map::PersistentMap;
use crate::sym3::Chol3;

mod association;
mod grids;
mod types;

use association::Decision;
use grids::*;
pub use types::*;

fn ms(a: std::time::Instant, b: std::time::Instant) -> f64 {
    (b - a).as_secs_f64() * 1e3
}

#[derive(Clone)]
struct Particle {
    pose: Isometry3<f64>,
    log_w: f64,
    map: PersistentMap<LandmarkEkf>,
    provisional: Vec<u32>,
    confirmed: usize,
}

/// Outcome of one particle's frame.
#[derive(Default)]
struct ParticleFrame {
    matched: usize,
    new: usize,
    ambiguous: usize,
    rejected: usize,
    /// Σ of the normalised innovation squared of the matched confirmed landmarks.
    nis_sum: f64,
    /// (id, observation index, position) of the landmarks created.
    created: Vec<(u32, u32, Vector3<f64>)>,
    associations: Vec<Option<u32>>,
}

/// The filter state.
pub struct FastSlam {
    cfg: FastSlamConfig,
    particles: Vec<Particle>,
    rng: Xoshiro256PlusPlus,
    next_id: u32,
    frame: u32,
    segment: u32,
    grid: Grid,
    /// Landmark of each feature track (observations with a track id).
    tracks: HashMap<u64, u32>,
    /// Pose covariance accumulated by the motion since the last frame (body-frame error).
    motion_cov: Matrix6<f64>,
    weak_frames: u32,
    /// Frames since the local map started.
    segment_frames: u32,
    /// Body twist (linear m/s, angular rad/s) for the constant-velocity model.
    twist: Option<(Vector3<f64>, Vector3<f64>)>,
    last_mean: Option<Isometry3<f64>>,
    last_cv_dt: Option<f64>,
    /// Uncertainty of the mean pose relative to the local map's origin, over world-frame errors
    /// (δp, δθ): the drift that the particle spread cannot show (particles and their maps drift
    /// together). See [`FastSlam::estimate`].
    drift: Matrix6<f64>,
    threads: usize,
}

/// [[I, −[d]×], [0, I]]: carries world-frame pose errors (δp, δθ) over a displacement `d` (a
/// rotation error δθ moves a point `d` away by δθ × d).
fn lever(d: &Vector3<f64>) -> Matrix6<f64> {
    let mut F = Matrix6::identity();
    F.fixed_view_mut::<3, 3>(0, 3).copy_from(&(-d.cross_matrix()));
    F
}

/// diag(A, B).
fn blockdiag(a: &Matrix3<f64>, b: &Matrix3<f64>) -> Matrix6<f64> {
    let mut J = Matrix6::zeros();
    J.fixed_view_mut::<3, 3>(0, 0).copy_from(a);
    J.fixed_view_mut::<3, 3>(3, 3).copy_from(b);
    J
}

/// A weighted-mean pose with its 6×6 covariance (position, body-frame rotation error).
#[derive(Debug, Clone, PartialEq)]
pub struct PoseEstimate {
    /// Mean `map_from_body`.
    pub map_from_body: Isometry3<f64>,
    /// Covariance over (x, y, z, rot_x, rot_y, rot_z).
    pub covariance: Matrix6<f64>,
}

fn normal3(rng: &mut Xoshiro256PlusPlus) -> Vector3<f64> {
    Vector3::new(StandardNormal.sample(rng), StandardNormal.sample(rng), StandardNormal.sample(rng))
}

/// Applies a body-frame perturbation (δp, δφ) to a pose: p + δp, R·Exp(δφ).
fn perturb(pose: &Isometry3<f64>, d: &Vector6<f64>) -> Isometry3<f64> {
    Isometry3::from_parts(
        Translation3::from(pose.translation.vector + d.fixed_rows::<3>(0)),
        pose.rotation * UnitQuaternion::from_scaled_axis(d.fixed_rows::<3>(3).into_owned()),
    )
}

/// Innovation of observation `o` against landmark `lm` from the body pose `pose`: in normalised
/// stereo coordinates for a stereo observation, else in the body frame.
fn observe(pose: &Isometry3<f64>, lm: &ekf::LandmarkEkf, o: &Observation) -> Result<Innovation, FilterError> {
    match (&o.stereo, &lm.inverse_depth) {
        (Some(st), Some(inv)) => ekf::innovation_inverse_depth(&(pose * st.body_from_camera), inv, &st.s, &st.cov),
        (Some(st), None) => ekf::innovation_stereo(&(pose * st.body_from_camera), lm, &st.s, &st.cov),
        (None, _) => innovation(pose, lm, &o.z_m, &o.Rz),
    }
}

/// A particle's pose in one frame with the stereo rig of the frame's first stereo observation
/// placed there: the rotations every observation's prediction and pose Jacobian share.
pub(super) struct View {
    pub(super) pose: Isometry3<f64>,
    rig: Option<ekf::StereoRig>,
    /// The rig camera's view of the last anchor looked at.
    anchors: std::cell::RefCell<ekf::AnchorMemo>,
}

impl View {
    pub(super) fn new(pose: &Isometry3<f64>, obs: &[Observation]) -> Self {
        let rig = obs.iter().find_map(|o| o.stereo.as_ref()).map(|st| ekf::StereoRig::new(pose, &st.body_from_camera));
        Self { pose: *pose, rig, anchors: Default::default() }
    }

    /// The rig, when `o` was made by its camera.
    pub(super) fn rig_for(&self, o: &Observation) -> Option<&ekf::StereoRig> {
        let st = o.stereo.as_ref()?;
        self.rig.as_ref().filter(|r| r.body_from_camera == st.body_from_camera)
    }

    /// [`observe`] from this view.
    pub(super) fn observe(&self, lm: &ekf::LandmarkEkf, o: &Observation) -> Result<Innovation, FilterError> {
        match (self.rig_for(o), &o.stereo, &lm.inverse_depth) {
            (Some(r), Some(st), Some(inv)) => {
                let mut anchors = self.anchors.borrow_mut();
                ekf::innovation_inverse_depth_in(anchors.get(&r.camera, &inv.world_from_anchor), inv, &st.s, &st.cov)
            }
            _ => observe(&self.pose, lm, o),
        }
    }

    /// [`pose_jacobian`] from this view.
    pub(super) fn pose_jacobian(&self, l_map: &Vector3<f64>, o: &Observation) -> nalgebra::Matrix3x6<f64> {
        match self.rig_for(o) {
            Some(r) => r.pose_jacobian(l_map),
            None => pose_jacobian(&self.pose, l_map, o),
        }
    }
}

/// The predicted stereo coordinates of `lm` from a camera at `world_from_camera` and their
/// covariance from the landmark's uncertainty; `None` when it is not in front of the camera.
fn predict_stereo(lm: &ekf::LandmarkEkf, world_from_camera: &Isometry3<f64>) -> Option<(Vector3<f64>, Matrix3<f64>)> {
    match &lm.inverse_depth {
        Some(inv) => inv.predict(world_from_camera).map(|(s, H)| (s, H * inv.cov * H.transpose())),
        None => {
            let Rcw = world_from_camera.rotation.inverse().to_rotation_matrix().into_inner();
            let p = Rcw * (lm.mean_m - world_from_camera.translation.vector);
            (p.z > ekf::MIN_STEREO_DEPTH_M).then(|| {
                let J = ekf::stereo_jacobian(&p) * Rcw;
                (ekf::stereo_coords(&p), J * lm.cov_m2 * J.transpose())
            })
        }
    }
}

/// ∂h/∂(δp, δφ) of observation `o` of a landmark at `l_map` from `pose` (see [`observe`]).
fn pose_jacobian(pose: &Isometry3<f64>, l_map: &Vector3<f64>, o: &Observation) -> nalgebra::Matrix3x6<f64> {
    match &o.stereo {
        Some(st) => ekf::stereo_pose_jacobian(pose, &st.body_from_camera, l_map),
        None => ekf::jacobians(pose, l_map).1,
    }
}

/// The covariance of observation `o` in the space it is compared in.
fn meas_cov(o: &Observation) -> &Matrix3<f64> {
    o.stereo.as_ref().map_or(&o.Rz, |st| &st.cov)
}

impl FastSlam {
    /// A filter with every particle at the origin of local map 0.
    pub fn new(cfg: FastSlamConfig) -> Result<Self, Vec<validation::ConfigIssue>> {
        validation::Validate::issues(&cfg).into_result()?;
        let n = cfg.particles;
        let threads = if cfg.threads == 0 {
            std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1)
        } else {
            cfg.threads
        };
        let particle = Particle {
            pose: Isometry3::identity(),
            log_w: -(n as f64).ln(),
            map: PersistentMap::new(),
            provisional: vec![],
            confirmed: 0,
        };
        Ok(Self {
            rng: Xoshiro256PlusPlus::seed_from_u64(cfg.seed),
            particles: vec![particle; n],
            next_id: 0,
            frame: 0,
            segment: 0,
            grid: Grid { cell_m: cfg.association.search_radius_m, cells: HashMap::new(), view: HashMap::new() },
            tracks: HashMap::new(),
            motion_cov: Matrix6::zeros(),
            weak_frames: 0,
            segment_frames: 0,
            twist: None,
            last_mean: None,
            last_cv_dt: None,
            drift: Matrix6::zeros(),
            threads,
            cfg,
        })
    }

    /// Moves every particle to `map_from_body` (e.g. a pose from an external source); maps and
    /// weights are kept.
    pub fn set_pose(&mut self, map_from_body: Isometry3<f64>) {
        for p in &mut self.particles {
            p.pose = map_from_body;
        }
    }

    /// The settings.
    pub fn config(&self) -> &FastSlamConfig {
        &self.cfg
    }

    /// The current local map (segment) id.
    pub fn segment(&self) -> u32 {
        self.segment
    }

    /// Frames processed.
    pub fn frames(&self) -> u32 {
        self.frame
    }

    /// Particles as (map_from_body, normalised log weight).
    pub fn particles(&self) -> impl Iterator<Item = (&Isometry3<f64>, f64)> {
        self.particles.iter().map(|p| (&p.pose, p.log_w))
    }

    fn best(&self) -> &Particle {
        self.particles.iter().max_by(|a, b| a.log_w.total_cmp(&b.log_w)).expect("at least one particle")
    }

    /// The best particle's confirmed landmarks (id, estimate).
    pub fn best_map(&self) -> Vec<(u32, &LandmarkEkf)> {
        let c = self.cfg.association.confirm_after;
        self.best().map.iter().filter(|(_, l)| l.hits >= c).collect()
    }

    /// Per-particle seeds for one parallel step, drawn in order (deterministic for any thread count).
    fn seeds(&mut self) -> Vec<u64> {
        (0..self.particles.len()).map(|_| self.rng.random()).collect()
    }

    fn for_each_particle<R: Send>(
        &mut self,
        seeds: &[u64],
        f: impl Fn(&mut Particle, &mut Xoshiro256PlusPlus) -> R + Sync,
    ) -> Vec<R> {
        let chunk = self.particles.len().div_ceil(self.threads.max(1)).max(1);
        let f = &f;
        let mut items: Vec<(&mut [Particle], &[u64])> =
            self.particles.chunks_mut(chunk).zip(seeds.chunks(chunk)).collect();
        par_map(items.len(), &mut items, |(ps, ss)| {
            ps.iter_mut()
                .zip(ss.iter())
                .map(|(p, seed)| f(p, &mut Xoshiro256PlusPlus::seed_from_u64(*seed)))
                .collect::<Vec<R>>()
        })
        .into_iter()
        .flatten()
        .collect()
    }

    /// Books one motion step of the mean pose: `step_world` its displacement in the map, `G_world`
    /// its noise over world-frame errors (δp, δθ), `R_new` the new orientation. The drift is
    /// carried over the step (a rotation error turns into a position error along it) and grows
    /// by the noise and by the unmodelled drift per metre (`drift_*_sigma_per_sqrt_m`); the
    /// motion covariance of this frame (the FastSLAM 2.0 prior and the association gates,
    /// position error in the map, rotation error in the body) grows by the noise.
    fn account_motion(&mut self, step_world: &Vector3<f64>, G_world: &Matrix6<f64>, R_new: &Matrix3<f64>) {
        let F = lever(step_world);
        // What no motion model accounts for (outliers that pass the gates, landmarks placed
        // from sampled poses, linearisation) grows like a random walk over the distance.
        let dist = step_world.norm();
        let mut extra = Matrix6::zeros();
        for k in 0..3 {
            extra[(k, k)] = self.cfg.drift_position_sigma_per_sqrt_m.powi(2) * dist;
            extra[(3 + k, 3 + k)] = self.cfg.drift_rotation_sigma_per_sqrt_m.powi(2) * dist;
        }
        let d = F * self.drift * F.transpose() + G_world + extra;
        self.drift = (d + d.transpose()) * 0.5;
        let J = blockdiag(&Matrix3::identity(), &R_new.transpose());
        let m = J * G_world * J.transpose();
        self.motion_cov += (m + m.transpose()) * 0.5;
    }

    /// Prediction with an odometry input (EQUATIONS §1): each particle propagates a sample of the input
    /// (noise with the variances `input_variances` of v, δθx, δθy, δθz, scaled by
    /// `input_noise_scale`), then gets the additive process noise ω.
    pub fn predict(&mut self, u: &ProcessInput, input_variances: [f64; 4]) -> Result<(), FilterError> {
        if !(u.v_mps.is_finite()
            && u.dt_s.is_finite()
            && u.dt_s > 0.0
            && u.delta_theta_rad.iter().all(|v| v.is_finite()))
        {
            return Err(FilterError::NonFinite("odometry input"));
        }
        let scale = self.cfg.input_noise_scale;
        let sd: Vec<f64> = input_variances.iter().map(|v| (v.max(0.0) * scale).sqrt()).collect();
        let qp = self.cfg.process_position_sigma * u.dt_s.sqrt();
        let qr = self.cfg.process_rotation_sigma * u.dt_s.sqrt();
        // Pose error added by this step, in the filter's convention (position error in the map
        // frame, rotation error in the body frame): the speed noise acts along body x.
        let mut G = Matrix6::zeros();
        G[(0, 0)] = (sd[0] * u.dt_s).powi(2) + qp * qp;
        G[(1, 1)] = qp * qp;
        G[(2, 2)] = qp * qp;
        for k in 0..3 {
            G[(3 + k, 3 + k)] = sd[1 + k].powi(2) + qr * qr;
        }
        let R = self.best().pose.rotation.to_rotation_matrix().into_inner();
        let R_new = R * geometry::rotation_from_euler_zyx(&u.delta_theta_rad).into_inner();
        let G_world = blockdiag(&R, &R_new) * G * blockdiag(&R, &R_new).transpose();
        self.account_motion(&(R * Vector3::new(u.v_mps * u.dt_s, 0.0, 0.0)), &G_world, &R_new);
        let seeds = self.seeds();
        self.for_each_particle(&seeds, |p, rng| {
            let noisy = ProcessInput {
                v_mps: u.v_mps + sd[0] * rng.sample::<f64, _>(StandardNormal),
                delta_theta_rad: u.delta_theta_rad + Vector3::new(sd[1], sd[2], sd[3]).component_mul(&normal3(rng)),
                dt_s: u.dt_s,
            };
            let moved = propagate(&p.pose, &noisy);
            let d =
                Vector6::from_iterator(normal3(rng).iter().map(|x| x * qp).chain(normal3(rng).iter().map(|x| x * qr)));
            p.pose = perturb(&moved, &d);
        });
        Ok(())
    }

    /// Prediction with a relative motion measured by a front end (e.g. stereo registration):
    /// each particle moves by `delta` (`prev_body_from_cur_body`) perturbed on the right by a
    /// sample of `covariance` (over (δt, δθ) in the new body frame, m² and rad²) scaled by
    /// `relative_motion_noise_scale`. The covariance is the whole motion uncertainty: no
    /// process noise is added (on top of a precise measured motion it only widens the gates and
    /// the proposal). `dt_s` is the time since the previous frame. A covariance that is not
    /// positive semi-definite or a non-finite motion is an error and changes nothing.
    pub fn predict_relative(
        &mut self,
        delta: &Isometry3<f64>,
        covariance: &Matrix6<f64>,
        dt_s: f64,
    ) -> Result<(), FilterError> {
        let finite = delta.translation.vector.iter().all(|v| v.is_finite())
            && delta.rotation.coords.iter().all(|v| v.is_finite())
            && covariance.iter().all(|v| v.is_finite())
            && dt_s.is_finite()
            && dt_s >= 0.0;
        if !finite {
            return Err(FilterError::NonFinite("relative motion"));
        }
        let mut cov = (covariance + covariance.transpose()) * 0.5 * self.cfg.relative_motion_noise_scale;
        for k in 0..6 {
            cov[(k, k)] += 1e-12;
        }
        let L = Cholesky::new(cov).ok_or(FilterError::NotPositiveDefinite("relative motion covariance"))?.l();
        // In the filter's error convention (position error in the map frame, rotation error in
        // the body frame): the right perturbation's translation turns with the new pose.
        let R = self.best().pose.rotation.to_rotation_matrix().into_inner();
        let R_new = R * delta.rotation.to_rotation_matrix().into_inner();
        let G_world = blockdiag(&R_new, &R_new) * cov * blockdiag(&R_new, &R_new).transpose();
        self.account_motion(&(R * delta.translation.vector), &G_world, &R_new);
        self.last_cv_dt = Some(dt_s);
        let seeds = self.seeds();
        self.for_each_particle(&seeds, |p, rng| {
            let n = Vector6::from_iterator((0..6).map(|_| rng.sample::<f64, _>(StandardNormal)));
            let e = L * n;
            let noise = Isometry3::from_parts(
                Translation3::from(e.fixed_rows::<3>(0).into_owned()),
                UnitQuaternion::from_scaled_axis(e.fixed_rows::<3>(3).into_owned()),
            );
            p.pose = p.pose * delta * noise;
        });
        Ok(())
    }

    /// Prediction without odometry: the constant-velocity model over `dt_s`, with the body twist
    /// estimated from the last two frames' mean poses and noise from the `cv_*` settings.
    pub fn predict_constant_velocity(&mut self, dt_s: f64) {
        self.predict_constant_velocity_with(
            dt_s,
            self.cfg.cv_velocity_sigma_mps,
            self.cfg.cv_angular_velocity_sigma_rps,
        );
    }

    /// [`FastSlam::predict_constant_velocity`] with explicit σ of the change of the linear (m/s)
    /// and angular (rad/s) velocity: wider than the configured model where the motion is less
    /// known (a frame the stereo front end found no motion for).
    pub fn predict_constant_velocity_with(&mut self, dt_s: f64, velocity_sigma_mps: f64, angular_sigma_rps: f64) {
        let (v, w) = self.twist.unwrap_or((Vector3::zeros(), Vector3::zeros()));
        self.last_cv_dt = Some(dt_s);
        let sp = velocity_sigma_mps * dt_s;
        let sr = angular_sigma_rps * dt_s;
        let mut G = Matrix6::zeros();
        for k in 0..3 {
            G[(k, k)] = sp * sp;
            G[(3 + k, 3 + k)] = sr * sr;
        }
        let R = self.best().pose.rotation.to_rotation_matrix().into_inner();
        let R_new = R * nalgebra::Rotation3::new(w * dt_s).into_inner();
        let G_world = blockdiag(&R, &R_new) * G * blockdiag(&R, &R_new).transpose();
        self.account_motion(&(R * v * dt_s), &G_world, &R_new);
        let seeds = self.seeds();
        self.for_each_particle(&seeds, |p, rng| {
            let step = Isometry3::new(v * dt_s + normal3(rng) * sp, w * dt_s + normal3(rng) * sr);
            p.pose *= step;
        });
    }

    /// Updates every particle with one frame of observations, weights, resamples when N_eff is
    /// low, and checks the multi-map triggers.
    pub fn update(&mut self, obs: &[Observation]) -> FrameReport {
        let t_start = std::time::Instant::now();
        self.frame += 1;
        let frame = self.frame;
        let cfg = self.cfg.clone();
        let motion_cov = self.motion_cov + Matrix6::identity() * 1e-9;
        self.motion_cov = Matrix6::zeros();
        // Candidates once per observation for all particles: around the mean pose, widened by
        // the observation's noise (far stereo points are uncertain along the ray) and by the
        // particles' spread, so every particle's own search would find no more.
        let spread = self.particle_spread();
        // Observations with a feature track id are associated by it (a new track makes a new
        // landmark); the others by maximum likelihood.
        let known: Vec<bool> = obs.iter().map(|o| o.track_id.is_some()).collect();
        let mut candidates = self.track_and_map_candidates(obs, &spread);
        // 1. Association and importance weights: read-only on the maps. The weight of FastSLAM
        //    (1.0 and 2.0) uses the landmark estimates before this frame's update, and the update
        //    is deterministic given pose, map and decisions; so resampling can come first and the
        //    maps are updated once per surviving parent (its copies would make identical
        //    updates), and never for particles about to be discarded.
        // The pose uncertainty of this frame's motion seen in each observation: H_x·P·H_xᵀ at
        // the best particle (the same for every particle to first order).
        let pose_q = motion_in_observations(&spread.0, obs, &motion_cov);
        self.stereo_candidates(obs, &known, &motion_cov, &spread, &mut candidates);
        let order = visiting_order(&candidates);
        let t_candidates = std::time::Instant::now();
        let seeds = self.seeds();
        let decisions = self.for_each_particle(&seeds, |p, rng| {
            Self::weigh_particle(&cfg, &candidates, &order, &known, &pose_q, p, obs, &motion_cov, rng)
        });
        let best_idx = (0..self.particles.len())
            .max_by(|a, b| self.particles[*a].log_w.total_cmp(&self.particles[*b].log_w))
            .unwrap_or(0);
        let t_weigh = std::time::Instant::now();
        let n_eff = self.normalise();
        let resampled = n_eff < cfg.resample_fraction * self.particles.len() as f64;
        let n = self.particles.len();
        let parents: Vec<usize> = if resampled {
            systematic_resample(
                &self.particles.iter().map(|p| p.log_w.exp()).collect::<Vec<_>>(),
                self.rng.random::<f64>(),
            )
        } else {
            (0..n).collect()
        };
        // 2. Runs of equal parents (systematic resampling returns them sorted): (parent, copies).
        let groups = runs_of_parents(&parents);
        let mut old: Vec<Option<Particle>> = std::mem::take(&mut self.particles).into_iter().map(Some).collect();
        let mut survivors: Vec<(Particle, Vec<Decision>)> =
            groups.iter().map(|(i, _)| (old[*i].take().expect("each parent once"), decisions[*i].clone())).collect();
        // The ids of this frame's new landmarks: one per observation that a surviving particle
        // makes a landmark of (the same id in each), in observation order. Dense, so that the
        // maps' tries stay shallow and a frame's landmarks share their leaves.
        let first_new_id = self.next_id;
        let new_ids = self.new_landmark_ids(obs.len(), &survivors);
        let t_resample = std::time::Instant::now();
        // 3. Landmark EKF updates, once per surviving parent, in parallel.
        let results = par_map(self.threads, &mut survivors, |(p, d)| {
            Self::apply_particle(&cfg, p, obs, &order, d, &new_ids, frame)
        });
        let t_apply = std::time::Instant::now();
        // 4. The new particle set; the discarded particles are freed on the worker threads.
        let uniform = -(n as f64).ln();
        let mut next = Vec::with_capacity(n);
        for ((mut p, _), (_, copies)) in survivors.into_iter().zip(&groups) {
            if resampled {
                p.log_w = uniform;
            }
            for _ in 1..*copies {
                next.push(p.clone());
            }
            next.push(p);
        }
        self.particles = next;
        let garbage: Vec<Particle> = old.into_iter().flatten().collect();
        self.free(garbage);
        // Register the new landmarks in the association grid (first creator's position), or
        // under their feature track.
        self.register_new_landmarks(&results, obs);
        // The best particle (largest weight) always survives systematic resampling (it has
        // w ≥ 1/N, so at least one copy).
        let best_group = groups.iter().position(|(i, _)| *i == best_idx).unwrap_or(0);
        let best = &results[best_group];
        let (matched, new, ambiguous, associations) =
            (best.matched, best.new, best.ambiguous, best.associations.clone());
        let (rejected, mean_nis) =
            (best.rejected, if best.matched > 0 { best.nis_sum / best.matched as f64 } else { f64::NAN });

        let landmarks = self.best().confirmed;
        let t_copies = std::time::Instant::now();
        let estimate = self.estimate();
        self.update_twist(&estimate);
        let new_segment = self.check_segments(&estimate, matched, landmarks);
        let candidates_per_observation =
            candidates.iter().map(Vec::len).sum::<usize>() as f64 / obs.len().max(1) as f64;
        FrameReport {
            matched,
            new,
            ambiguous,
            n_eff,
            resampled,
            landmarks,
            associations,
            first_new_id,
            new_ids,
            new_segment,
            candidates_per_observation,
            rejected,
            mean_nis,
            timing: FrameTiming {
                candidates_ms: ms(t_start, t_candidates),
                weigh_ms: ms(t_candidates, t_weigh),
                resample_ms: ms(t_weigh, t_resample),
                update_ms: ms(t_resample, t_apply),
                copies_ms: ms(t_apply, t_copies),
                total_ms: ms(t_start, std::time::Instant::now()),
            },
        }
    }

    /// Candidate landmarks per observation for all particles: by feature track id (a new
    /// track has none), none yet for stereo observations (the camera search fills them), and
    /// for the rest from the association grid around the mean pose, widened by the
    /// observation's noise (far stereo points are uncertain along the ray) and by the particles'
    /// spread `spread` (mean pose, translation and rotation spread), so every particle's own
    /// search would find no more.
    fn track_and_map_candidates(&self, obs: &[Observation], spread: &(Isometry3<f64>, f64, f64)) -> Vec<Vec<u32>> {
        let a = &self.cfg.association;
        obs.iter()
            .map(|o| {
                if let Some(t) = o.track_id {
                    return self.tracks.get(&t).map(|id| vec![*id]).unwrap_or_default();
                }
                if o.stereo.is_some() {
                    return vec![]; // filled later, in the camera
                }
                let w = spread.0.transform_point(&o.z_m.into()).coords;
                let particles_m = 3.0 * (spread.1 + spread.2 * o.z_m.norm()) + 0.25;
                let radius = a.search_radius_m.max(3.0 * o.Rz.trace().sqrt()) + particles_m;
                // A landmark passes the duplicate gate only within √(χ²·(tr Σ_L + tr Rz)) ≤
                // √(χ²·tr Σ₀) + √(χ²·tr Rz) of the particle's view of the observation.
                let slack = (a.duplicate_gate_chi2 * o.Rz.trace()).sqrt() + particles_m;
                let mut c = vec![];
                self.grid.candidates(&w, radius, slack, &mut c);
                c
            })
            .collect()
    }

    /// Ids for the landmarks of observations that a surviving particle (with its decisions)
    /// makes new: consecutive from `next_id`, in observation order; `None` for the others.
    fn new_landmark_ids(&mut self, observations: usize, survivors: &[(Particle, Vec<Decision>)]) -> Vec<Option<u32>> {
        let mut new = vec![false; observations];
        for (_, decisions) in survivors {
            for (n, d) in new.iter_mut().zip(decisions) {
                *n |= *d == Decision::New;
            }
        }
        new.into_iter()
            .map(|n| {
                n.then(|| {
                    let id = self.next_id;
                    self.next_id = self.next_id.saturating_add(1);
                    id
                })
            })
            .collect()
    }

    /// Registers the landmarks this frame created in the association grid (at the first
    /// creator's position) or under their feature track.
    fn register_new_landmarks(&mut self, results: &[ParticleFrame], obs: &[Observation]) {
        let gate = self.cfg.association.duplicate_gate_chi2;
        let mut seen = std::collections::HashSet::new();
        for r in results {
            for (id, j, pos) in &r.created {
                if seen.insert(*id) {
                    let j = *j as usize;
                    if let Some(t) = obs[j].track_id {
                        self.tracks.insert(t, *id);
                    }
                    match &obs[j].stereo {
                        Some(_) => {
                            let k = (pos / VIEW_CELL_M).map(|v| v.floor() as i32);
                            self.grid.view.entry([k.x, k.y, k.z]).or_default().push(*id);
                        }
                        None => self.grid.insert(*id, *pos, obs[j].Rz.trace(), gate),
                    }
                }
            }
        }
    }

    /// The twist of the constant-velocity model from the last two mean poses (per frame; scaled
    /// by dt at prediction).
    fn update_twist(&mut self, estimate: &PoseEstimate) {
        if let Some(prev) = self.last_mean {
            let d = prev.inverse() * estimate.map_from_body;
            if let Some(dt) = self.last_cv_dt.filter(|dt| *dt > 0.0) {
                self.twist = Some((d.translation.vector / dt, d.rotation.scaled_axis() / dt));
            }
        }
        self.last_mean = Some(estimate.map_from_body);
    }

    /// The multi-map triggers ([3D] §IV): a new local map when the pose has grown too uncertain,
    /// or after `weak_frames` frames with fewer than `min_matched` matches in a map that has
    /// enough landmarks; starts it and says why.
    fn check_segments(&mut self, estimate: &PoseEstimate, matched: usize, landmarks: usize) -> Option<SegmentReason> {
        let s = &self.cfg.segments;
        self.segment_frames += 1;
        if matched < s.min_matched {
            self.weak_frames += 1;
        } else {
            self.weak_frames = 0;
        }
        let sigma = estimate.covariance.fixed_view::<3, 3>(0, 0).symmetric_eigenvalues().max().max(0.0).sqrt();
        let new_segment = if sigma > s.max_position_sigma_m {
            Some(SegmentReason::PoseUncertainty { sigma_m: sigma })
        } else if self.weak_frames >= s.weak_frames && landmarks >= s.min_matched && self.segment_frames >= s.min_frames
        {
            Some(SegmentReason::FewMatches { matched, frames: self.weak_frames })
        } else {
            None
        };
        if let Some(reason) = &new_segment {
            self.start_new_segment(reason.clone());
        }
        new_segment
    }

    /// The best particle's pose and the largest distance (m) and rotation (rad) of any particle
    /// from it.
    fn particle_spread(&self) -> (Isometry3<f64>, f64, f64) {
        let best = self.best().pose;
        let (mut dp, mut dr) = (0.0f64, 0.0f64);
        for p in &self.particles {
            dp = dp.max((p.pose.translation.vector - best.translation.vector).norm());
            dr = dr.max(p.pose.rotation.angle_to(&best.rotation));
        }
        (best, dp / 3.0, dr / 3.0)
    }

    /// Normalises the weights; returns N_eff = 1/Σw².
    fn normalise(&mut self) -> f64 {
        let max = self.particles.iter().map(|p| p.log_w).fold(f64::NEG_INFINITY, f64::max);
        if !max.is_finite() {
            let u = -(self.particles.len() as f64).ln();
            self.particles.iter_mut().for_each(|p| p.log_w = u);
            return self.particles.len() as f64;
        }
        let sum: f64 = self.particles.iter().map(|p| (p.log_w - max).exp()).sum();
        let log_sum = max + sum.ln();
        let mut sq = 0.0;
        for p in &mut self.particles {
            p.log_w -= log_sum;
            sq += (2.0 * p.log_w).exp();
        }
        1.0 / sq
    }

    /// Frees discarded particles on the worker threads: dropping their maps' unshared paths is
    /// real work at large N and M.
    fn free(&self, mut garbage: Vec<Particle>) {
        if self.threads <= 1 || garbage.len() < 2 {
            return drop(garbage);
        }
        let chunk = garbage.len().div_ceil(self.threads).max(1);
        crossbeam::thread::scope(|s| {
            while garbage.len() > chunk {
                let tail = garbage.split_off(garbage.len() - chunk);
                s.spawn(move |_| drop(tail));
            }
            drop(std::mem::take(&mut garbage)); // the first chunk on this thread
        })
        .expect("drop scope");
    }

    /// The weighted mean pose and its covariance (position, body-frame rotation error).
    pub fn estimate(&self) -> PoseEstimate {
        let weights: Vec<f64> = {
            let max = self.particles.iter().map(|p| p.log_w).fold(f64::NEG_INFINITY, f64::max);
            let w: Vec<f64> = self.particles.iter().map(|p| (p.log_w - max).exp()).collect();
            let s: f64 = w.iter().sum();
            w.into_iter().map(|x| x / s).collect()
        };
        let p_mean: Vector3<f64> =
            self.particles.iter().zip(&weights).map(|(p, w)| p.pose.translation.vector * *w).sum();
        let r0 = self.best().pose.rotation;
        let phi: Vector3<f64> =
            self.particles.iter().zip(&weights).map(|(p, w)| (r0.inverse() * p.pose.rotation).scaled_axis() * *w).sum();
        let r_mean = r0 * UnitQuaternion::from_scaled_axis(phi);
        let mut cov = Matrix6::zeros();
        for (p, w) in self.particles.iter().zip(&weights) {
            let mut e = Vector6::zeros();
            e.fixed_rows_mut::<3>(0).copy_from(&(p.pose.translation.vector - p_mean));
            e.fixed_rows_mut::<3>(3).copy_from(&(r_mean.inverse() * p.pose.rotation).scaled_axis());
            cov += e * e.transpose() * *w;
        }
        PoseEstimate {
            map_from_body: Isometry3::from_parts(Translation3::from(p_mean), r_mean),
            covariance: {
                // The drift in the reported convention (rotation error in the body frame).
                let Rt = r_mean.inverse().to_rotation_matrix().into_inner();
                let J = blockdiag(&Matrix3::identity(), &Rt);
                let c = cov + J * self.drift * J.transpose();
                (c + c.transpose()) * 0.5
            },
        }
    }

    /// Replaces every particle's map with the same prior map of confirmed landmarks (mean,
    /// covariance, descriptor), shared by all particles (one copy in memory); returns their ids.
    /// For a known map, and for benchmarks of large maps.
    pub fn set_prior_map(&mut self, landmarks: &[PriorLandmark]) -> Vec<u32> {
        let mut map = PersistentMap::new();
        let mut ids = Vec::with_capacity(landmarks.len());
        self.grid.cells.clear();
        for (mean_m, cov_m2, descriptor) in landmarks {
            let id = self.next_id;
            self.next_id += 1;
            map.insert(
                id,
                LandmarkEkf {
                    mean_m: *mean_m,
                    cov_m2: *cov_m2,
                    descriptor: *descriptor,
                    hits: self.cfg.association.confirm_after.max(1),
                    last_seen_frame: self.frame,
                    inverse_depth: None,
                },
            );
            self.grid.insert(id, *mean_m, cov_m2.trace(), self.cfg.association.duplicate_gate_chi2);
            ids.push(id);
        }
        for p in &mut self.particles {
            p.map = map.clone();
            p.provisional.clear();
            p.confirmed = landmarks.len();
        }
        ids
    }

    /// Starts a new local map: every particle at the origin of the new map, maps empty. The new
    /// map's frame is the body frame at this instant.
    pub fn start_new_segment(&mut self, reason: SegmentReason) {
        let _ = reason;
        let n = self.particles.len();
        for p in &mut self.particles {
            p.pose = Isometry3::identity();
            p.log_w = -(n as f64).ln();
            p.map = PersistentMap::new();
            p.provisional.clear();
            p.confirmed = 0;
        }
        self.grid.cells.clear();
        self.grid.view.clear();
        self.tracks.clear();
        self.segment += 1;
        self.drift = Matrix6::zeros();
        self.weak_frames = 0;
        self.segment_frames = 0;
        self.last_mean = None;
        self.motion_cov = Matrix6::zeros();
    }
}

/// A landmark of a prior map: mean (m), covariance (m²), descriptor.
pub type PriorLandmark = (Vector3<f64>, Matrix3<f64>, Option<[u8; 32]>);

/// The order in which a particle visits a frame's observations: by their first candidate
/// landmark's id, those without a candidate (new ones, whose ids are given in observation order)
/// last. Landmarks with near ids were made together and lie near each other in memory and in the
/// map's trie: visited in this order, a particle's map is read (and copied on write) with far
/// fewer cache misses than in the observations' own order. Only the speed depends on it.
fn visiting_order(candidates: &[Vec<u32>]) -> Vec<u32> {
    let mut keys: Vec<u64> = candidates
        .iter()
        .enumerate()
        .map(|(j, c)| ((c.first().copied().unwrap_or(u32::MAX) as u64) << 32) | j as u64)
        .collect();
    keys.sort_unstable();
    keys.into_iter().map(|k| (k & 0xffff_ffff) as u32).collect()
}

/// Applies `f` to every item on up to `threads` threads (contiguous chunks; the first chunk on
/// the calling thread, the others on scoped workers, none with one thread); results in item order.
fn par_map<T: Send, R: Send>(threads: usize, items: &mut [T], f: impl Fn(&mut T) -> R + Sync) -> Vec<R> {
    if items.is_empty() {
        return vec![];
    }
    if threads <= 1 || items.len() == 1 {
        return items.iter_mut().map(f).collect();
    }
    let chunk = items.len().div_ceil(threads);
    let f = &f;
    crossbeam::thread::scope(|s| {
        let (first, rest) = items.split_at_mut(chunk);
        let handles: Vec<_> =
            rest.chunks_mut(chunk).map(|c| s.spawn(move |_| c.iter_mut().map(f).collect::<Vec<R>>())).collect();
        let mut out: Vec<R> = first.iter_mut().map(f).collect();
        for h in handles {
            out.extend(h.join().expect("particle worker panicked"));
        }
        out
    })
    .expect("particle scope")
}

/// Systematic resampling of normalised `weights` with offset `u` in [0, 1): indices of the
/// survivors, each particle i kept ⌊N·wᵢ⌋ or ⌈N·wᵢ⌉ times.
pub fn systematic_resample(weights: &[f64], u: f64) -> Vec<usize> {
    let n = weights.len();
    let total: f64 = weights.iter().sum();
    let step = total / n as f64;
    let mut out = Vec::with_capacity(n);
    let mut c = weights[0];
    let mut i = 0;
    for k in 0..n {
        let target = (u + k as f64) * step;
        while target > c && i + 1 < n {
            i += 1;
            c += weights[i];
        }
        out.push(i);
    }
    out
}

/// The pose uncertainty of this frame's motion `motion_cov` seen in each observation, at the
/// best particle's pose `best_pose` (the same for every particle to first order): H_x·P·H_xᵀ
/// and H_b·P·H_bᵀ.
fn motion_in_observations(
    best_pose: &Isometry3<f64>,
    obs: &[Observation],
    motion_cov: &Matrix6<f64>,
) -> Vec<(Matrix3<f64>, Matrix3<f64>)> {
    obs.iter()
        .map(|o| {
            let l = best_pose.transform_point(&o.z_m.into()).coords;
            let sym = |q: Matrix3<f64>| (q + q.transpose()) * 0.5;
            let (_, Hb) = ekf::jacobians(best_pose, &l);
            let Hx = pose_jacobian(best_pose, &l, o);
            (sym(Hx * motion_cov * Hx.transpose()), sym(Hb * motion_cov * Hb.transpose()))
        })
        .collect()
}

/// Runs of equal parents (systematic resampling returns them sorted): (parent, copies).
fn runs_of_parents(parents: &[usize]) -> Vec<(usize, usize)> {
    let mut groups: Vec<(usize, usize)> = vec![];
    for &i in parents {
        match groups.last_mut() {
            Some((g, c)) if *g == i => *c += 1,
            _ => groups.push((i, 1)),
        }
    }
    groups
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn candidates_keep_every_landmark_that_could_pass_the_duplicate_gate() {
        let chi2 = 21.1;
        let mut g = Grid { cell_m: 3.0, cells: HashMap::new(), view: HashMap::new() };
        // Same distance (2 m) from the query, different initial covariances.
        g.insert(1, Vector3::new(2.0, 0.0, 0.0), 0.003, chi2); // precise: reach 0.58 m
        g.insert(2, Vector3::new(0.0, 2.0, 0.0), 0.3, chi2); // far stereo point: reach 5.8 m
        g.insert(3, Vector3::new(0.3, 0.0, 0.0), 0.003, chi2); // precise and near
        g.insert(4, Vector3::new(9.0, 0.0, 0.0), 10.0, chi2); // beyond the search radius
        let mut out = vec![];
        g.candidates(&Vector3::zeros(), 3.0, 0.2, &mut out);
        out.sort();
        assert_eq!(out, vec![2, 3]);
        // The reach bounds the exact pre-check of `associate`: a landmark whose mean moved by up
        // to 6 initial σ (here from the creation point straight towards the observation) and
        // whose Σ did not shrink is still within √(χ²(tr Σ + tr Rz)) when it is a candidate.
        let (tr0, tr_rz) = (0.003f64, 0.0075f64);
        let slack = (chi2 * tr_rz).sqrt();
        let reach = (chi2 * tr0).sqrt() + MEAN_MOTION_SIGMAS * tr0.sqrt();
        let gate = (chi2 * (tr0 + tr_rz)).sqrt();
        let moved = MEAN_MOTION_SIGMAS * tr0.sqrt();
        // Created at distance d from the observation, now at d − moved: passes the gate iff
        // d − moved ≤ gate; a candidate iff d ≤ reach + slack. gate + moved ≤ reach + slack.
        assert!(gate + moved <= reach + slack + 1e-12);
    }

    #[test]
    fn systematic_resampling_keeps_the_expected_counts() {
        let w = [0.5, 0.25, 0.125, 0.0625, 0.0625];
        for u in [0.0, 0.3, 0.77, 0.999] {
            let idx = systematic_resample(&w, u);
            for (i, wi) in w.iter().enumerate() {
                let count = idx.iter().filter(|&&j| j == i).count() as f64;
                let expected = wi * w.len() as f64;
                assert!((count - expected).abs() < 1.0, "particle {i}: {count} copies, expected {expected} (u = {u})");
            }
        }
        // Statistical: over many offsets the mean count equals N·w exactly.
        let w: Vec<f64> = (1..=10).map(|i| i as f64 / 55.0).collect();
        let mut counts = [0usize; 10];
        let mut rng = Xoshiro256PlusPlus::seed_from_u64(11);
        let trials = 20_000;
        for _ in 0..trials {
            for i in systematic_resample(&w, rng.random::<f64>()) {
                counts[i] += 1;
            }
        }
        for (i, c) in counts.iter().enumerate() {
            let mean = *c as f64 / trials as f64;
            assert!((mean - w[i] * 10.0).abs() < 0.01, "particle {i}: mean {mean} vs {}", w[i] * 10.0);
        }
    }

    #[test]
    fn the_visiting_order_sorts_by_first_candidate_and_keeps_ties_and_new_ones_in_order() {
        let candidates = vec![vec![7, 2], vec![], vec![3], vec![7], vec![], vec![1, 9]];
        // By first candidate (1, 3, 7, 7), ties in observation order, those without one last.
        assert_eq!(visiting_order(&candidates), vec![5, 2, 0, 3, 1, 4]);
        assert!(visiting_order(&[]).is_empty());
    }
}
