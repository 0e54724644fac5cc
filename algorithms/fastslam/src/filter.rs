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

/// One observation of a frame, in the body frame.
#[derive(Debug, Clone, PartialEq)]
pub struct Observation {
    /// Landmark position in the body frame, m.
    pub z_m: Vector3<f64>,
    /// Its covariance, m² (positive definite).
    pub Rz: Matrix3<f64>,
    /// Descriptor, if the source provides one.
    pub descriptor: Option<[u8; 32]>,
    /// The front end's feature track id, if the source provides one: the same id in two frames
    /// is the same landmark (association by attribute, [3D] §3.1).
    pub track_id: Option<u64>,
    /// The stereo measurement (normalised stereo coordinates in the camera frame and their
    /// covariance), when the observation comes from a stereo camera in front of it: the filter
    /// then compares landmarks with it in that space, where pixel noise is Gaussian at every
    /// depth (the triangulated point's depth is not, far away).
    pub stereo: Option<StereoMeasurement>,
}

/// A stereo observation in normalised stereo coordinates s = (x/z, y/z, 1/z) of the camera
/// frame ([`ekf::stereo_coords`]).
#[derive(Debug, Clone, PartialEq)]
pub struct StereoMeasurement {
    /// s.
    pub s: Vector3<f64>,
    /// Its covariance (first order from the camera-frame point's covariance).
    pub cov: Matrix3<f64>,
    /// The camera's mounting on the body.
    pub body_from_camera: Isometry3<f64>,
}

impl Observation {
    /// An observation from a camera-frame point and covariance and the `body_from_camera`
    /// extrinsic, with its stereo measurement when the point is in front of the camera; NaN/inf
    /// or a covariance that is not positive definite is an error.
    pub fn from_camera(
        point_cam_m: &Vector3<f64>,
        cov_cam_m2: &Matrix3<f64>,
        descriptor: Option<[u8; 32]>,
        body_from_camera: &Isometry3<f64>,
    ) -> Result<Self, FilterError> {
        if !(point_cam_m.iter().all(|v| v.is_finite()) && cov_cam_m2.iter().all(|v| v.is_finite())) {
            return Err(FilterError::NonFinite("observation"));
        }
        let R = body_from_camera.rotation.to_rotation_matrix().into_inner();
        let Rz = R * cov_cam_m2 * R.transpose();
        let Rz = (Rz + Rz.transpose()) * 0.5;
        if Cholesky::new(Rz).is_none() {
            return Err(FilterError::NotPositiveDefinite("observation covariance"));
        }
        let stereo = (point_cam_m.z > ekf::MIN_STEREO_DEPTH_M)
            .then(|| {
                let J = ekf::stereo_jacobian(point_cam_m);
                let cov = J * cov_cam_m2 * J.transpose();
                let cov = (cov + cov.transpose()) * 0.5;
                Cholesky::new(cov).map(|_| StereoMeasurement {
                    s: ekf::stereo_coords(point_cam_m),
                    cov,
                    body_from_camera: *body_from_camera,
                })
            })
            .flatten();
        Ok(Self {
            z_m: body_from_camera.transform_point(&(*point_cam_m).into()).coords,
            Rz,
            descriptor,
            track_id: None,
            stereo,
        })
    }
}

/// Why a new local map was started.
#[derive(Debug, Clone, PartialEq)]
pub enum SegmentReason {
    /// Fewer than m_l matched landmarks for several frames.
    FewMatches {
        /// Matched landmarks in the last frame.
        matched: usize,
        /// Weak frames in a row.
        frames: u32,
    },
    /// The position uncertainty grew beyond the threshold.
    PoseUncertainty {
        /// Largest position σ, m.
        sigma_m: f64,
    },
    /// Asked for from outside (e.g. fusion: camera and buoy estimates stopped overlapping).
    Requested,
}

impl std::fmt::Display for SegmentReason {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            SegmentReason::FewMatches { matched, frames } => {
                write!(f, "only {matched} matched landmarks for {frames} frames")
            }
            SegmentReason::PoseUncertainty { sigma_m } => write!(f, "position σ {sigma_m:.2} m over the threshold"),
            SegmentReason::Requested => write!(f, "requested"),
        }
    }
}

/// What one frame did (for diagnostics).
#[derive(Debug, Clone, PartialEq)]
pub struct FrameReport {
    /// Observations matched to confirmed landmarks (best particle).
    pub matched: usize,
    /// Observations that created landmarks (best particle).
    pub new: usize,
    /// Observations left out as possible duplicates (best particle).
    pub ambiguous: usize,
    /// Effective sample size before resampling.
    pub n_eff: f64,
    /// Whether the particles were resampled.
    pub resampled: bool,
    /// Confirmed landmarks in the best particle's map.
    pub landmarks: usize,
    /// The best particle's landmark id per observation (`None`: new or left out).
    pub associations: Vec<Option<u32>>,
    /// A landmark created from observation j of this frame has id `first_new_id + j`.
    pub first_new_id: u32,
    /// Set when this frame started a new local map.
    pub new_segment: Option<SegmentReason>,
    /// Association candidates (landmarks looked up in each particle's map) per observation.
    pub candidates_per_observation: f64,
    /// Attribute (track id) matches left out because they failed the χ² gate (best particle).
    pub rejected: usize,
    /// Mean normalised innovation squared νᵀS⁻¹ν of the landmark updates of confirmed
    /// landmarks (best particle; ≈ 3 when consistent, a little less under the gate); NaN
    /// without updates.
    pub mean_nis: f64,
    /// Where the time of this update went.
    pub timing: FrameTiming,
}

/// Wall time of the phases of one [`FastSlam::update`], ms.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct FrameTiming {
    /// Candidate landmarks per observation (grid, camera projection).
    pub candidates_ms: f64,
    /// Association, proposal and weights of every particle (parallel).
    pub weigh_ms: f64,
    /// Normalising and resampling.
    pub resample_ms: f64,
    /// Landmark EKF updates and new landmarks, once per surviving parent (parallel).
    pub update_ms: f64,
    /// The new particle set: copies of the parents, freeing the discarded ones, bookkeeping.
    pub copies_ms: f64,
    /// The whole update (with the estimate and the local-map checks).
    pub total_ms: f64,
}

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
    created: Vec<(u32, Vector3<f64>)>,
    associations: Vec<Option<u32>>,
}

/// A grid over landmark ids by their first position: the candidates for association.
#[derive(Default)]
struct Grid {
    cell_m: f64,
    /// Landmark ids with the position they were created at and the trace of their initial
    /// covariance, m² (the same in every particle: a rotation keeps the trace).
    cells: HashMap<[i32; 3], Vec<GridEntry>>,
    /// Landmarks of stereo observations by [`VIEW_CELL_M`] cell of their first position: those
    /// near the camera are projected into it to find the candidates of the stereo observations.
    view: HashMap<[i32; 3], Vec<u32>>,
}

/// Cell of the coarse grid of stereo landmarks, m.
const VIEW_CELL_M: f64 = 10.0;
/// Farthest a stereo observation's candidates are looked for, m.
const MAX_VIEW_M: f64 = 300.0;

#[derive(Clone, Copy)]
struct GridEntry {
    id: u32,
    created_m: Vector3<f64>,
    /// How far (m) from its creation position a particle's version of this landmark can be and
    /// still pass the duplicate gate for an observation with covariance trace zero: the gate
    /// distance √(χ²_dup·tr Σ₀) (an EKF update never grows Σ) plus `MEAN_MOTION_SIGMAS`·√tr Σ₀
    /// for the mean's motion since creation.
    reach_m: f64,
}

/// How many initial σ a landmark's mean may move from where it was created (its initial error
/// plus its current error, each within 3σ) before the candidate search stops finding it.
const MEAN_MOTION_SIGMAS: f64 = 6.0;

impl Grid {
    fn key(&self, p: &Vector3<f64>) -> [i32; 3] {
        [(p.x / self.cell_m).floor() as i32, (p.y / self.cell_m).floor() as i32, (p.z / self.cell_m).floor() as i32]
    }

    fn insert(&mut self, id: u32, created_m: Vector3<f64>, cov_trace_m2: f64, duplicate_gate_chi2: f64) {
        let t = cov_trace_m2.max(0.0);
        let reach_m = (duplicate_gate_chi2 * t).sqrt() + MEAN_MOTION_SIGMAS * t.sqrt();
        let key = self.key(&created_m);
        self.cells.entry(key).or_default().push(GridEntry { id, created_m, reach_m });
    }

    /// Ids created within `radius_m` (rounded up to whole cells, at least one) of `p` whose own
    /// reach plus `slack_m` also covers `p`.
    fn candidates(&self, p: &Vector3<f64>, radius_m: f64, slack_m: f64, out: &mut Vec<u32>) {
        out.clear();
        let k = self.key(p);
        let n = ((radius_m / self.cell_m).ceil() as i32).clamp(1, 8);
        let r2 = radius_m * radius_m;
        for dx in -n..=n {
            for dy in -n..=n {
                for dz in -n..=n {
                    if let Some(entries) = self.cells.get(&[k[0] + dx, k[1] + dy, k[2] + dz]) {
                        out.extend(
                            entries
                                .iter()
                                .filter(|e| {
                                    let d2 = (e.created_m - p).norm_squared();
                                    d2 <= r2 && d2 <= (e.reach_m + slack_m).powi(2)
                                })
                                .map(|e| e.id),
                        );
                    }
                }
            }
        }
    }
}

/// A grid over the (x/z, y/z) of stereo coordinates (about two points per cell).
struct SGrid {
    min: [f64; 2],
    cell: f64,
    nx: usize,
    ny: usize,
    /// Points of cell k: `items[start[k]..start[k + 1]]`.
    start: Vec<u32>,
    items: Vec<u32>,
}

impl SGrid {
    fn new(pts: &[(Vector3<f64>, Matrix3<f64>)]) -> Self {
        let (mut lo, mut hi) = ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]);
        for (s, _) in pts {
            for k in 0..2 {
                lo[k] = lo[k].min(s[k]);
                hi[k] = hi[k].max(s[k]);
            }
        }
        if pts.is_empty() {
            (lo, hi) = ([0.0; 2], [1.0; 2]);
        }
        let area = ((hi[0] - lo[0]) * (hi[1] - lo[1])).max(1e-9);
        let cell = (area / (pts.len().max(1) as f64 / 2.0)).sqrt().max((hi[0] - lo[0]).max(hi[1] - lo[1]) / 256.0);
        let nx = (((hi[0] - lo[0]) / cell).floor() as usize + 1).min(257);
        let ny = (((hi[1] - lo[1]) / cell).floor() as usize + 1).min(257);
        let key = |s: &Vector3<f64>| {
            let ix = (((s[0] - lo[0]) / cell) as usize).min(nx - 1);
            let iy = (((s[1] - lo[1]) / cell) as usize).min(ny - 1);
            iy * nx + ix
        };
        let mut start = vec![0u32; nx * ny + 1];
        for (s, _) in pts {
            start[key(s) + 1] += 1;
        }
        for k in 1..start.len() {
            start[k] += start[k - 1];
        }
        let mut fill = start.clone();
        let mut items = vec![0u32; pts.len()];
        for (i, (s, _)) in pts.iter().enumerate() {
            let k = key(s);
            items[fill[k] as usize] = i as u32;
            fill[k] += 1;
        }
        Self { min: lo, cell, nx, ny, start, items }
    }

    /// Points whose (a, b) may lie within ±(ra, rb) of (a, b).
    fn query(&self, a: f64, b: f64, ra: f64, rb: f64, mut f: impl FnMut(usize)) {
        let lo_x = ((a - ra - self.min[0]) / self.cell).floor();
        let hi_x = ((a + ra - self.min[0]) / self.cell).floor();
        let lo_y = ((b - rb - self.min[1]) / self.cell).floor();
        let hi_y = ((b + rb - self.min[1]) / self.cell).floor();
        if !(hi_x >= 0.0 && hi_y >= 0.0 && lo_x < self.nx as f64 && lo_y < self.ny as f64) {
            return;
        }
        let (x0, x1) = (lo_x.max(0.0) as usize, (hi_x as usize).min(self.nx - 1));
        let (y0, y1) = (lo_y.max(0.0) as usize, (hi_y as usize).min(self.ny - 1));
        for y in y0..=y1 {
            for k in (y * self.nx + x0)..=(y * self.nx + x1) {
                for &i in &self.items[self.start[k] as usize..self.start[k + 1] as usize] {
                    f(i as usize);
                }
            }
        }
    }
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

    /// Associates one observation for one particle (EQUATIONS §3): by feature track id when the
    /// observation has one, else by descriptor with a ratio test when it has one, else by
    /// maximum likelihood; every association inside the χ²₃ gate. The gate's covariance is the
    /// innovation covariance plus `pose_q` = H_x·P·H_xᵀ, the pose uncertainty of this frame's
    /// motion seen in the observation: a particle's pose is one sample of it, and with a sensor
    /// more precise than the motion a gate without it would refuse the right landmark.
    fn associate(
        cfg: &FastSlamConfig,
        candidates: &[u32],
        p: &Particle,
        o: &Observation,
        pose_q: &(Matrix3<f64>, Matrix3<f64>),
        by_track: bool,
    ) -> Association {
        let (pose_q, pose_q_body) = (&pose_q.0, &pose_q.1);
        let a = &cfg.association;
        let gated = |inn: &Innovation| -> Option<f64> {
            let m = Chol3::new(&(inn.S + pose_q))?.mahalanobis(&inn.nu);
            m.is_finite().then_some(m)
        };
        if by_track {
            // By attribute ([3D] §3.1): the landmark of this feature track, if any, checked
            // against the χ² gate (a tracker's wrong match is left out, not fused).
            for &id in candidates {
                let Some(lm) = p.map.get(id) else { continue };
                return match observe(&p.pose, lm, o) {
                    Ok(inn) if gated(&inn).is_some_and(|m| m <= a.gate_chi2) => Association::Matched(id, inn),
                    _ => Association::Rejected,
                };
            }
            return Association::New;
        }
        let w = p.pose.transform_point(&o.z_m.into()).coords;
        let mut ml: Option<(f64, u32, Innovation)> = None;
        let mut second_ml = f64::INFINITY;
        let mut near_dup = false;
        let mut best_d: Option<(u32, u32, Innovation)> = None; // (hamming, id, innovation)
        let mut second_d = u32::MAX;
        let tr_rz = o.Rz.trace() + pose_q_body.trace();
        for &id in candidates {
            let Some(lm) = p.map.get(id) else { continue };
            // Exact pre-check without a Cholesky: |ν| = |w − L| (a rotation keeps lengths) and
            // νᵀS⁻¹ν ≥ |ν|²/λmax(S) ≥ |ν|²/tr(S), with tr(S) = tr(Σ_L) + tr(Rz) + tr(pose_q).
            let d2 = (lm.mean_m - w).norm_squared();
            if d2 > a.duplicate_gate_chi2 * (lm.cov_m2.trace() + tr_rz) {
                continue;
            }
            let Ok(inn) = observe(&p.pose, lm, o) else { continue };
            let Some(m) = gated(&inn) else { continue };
            if m > a.duplicate_gate_chi2 {
                continue;
            }
            near_dup = true;
            if m > a.gate_chi2 {
                continue;
            }
            if let (Some(od), Some(ld)) = (&o.descriptor, &lm.descriptor) {
                let d = hamming(od, ld);
                match &best_d {
                    Some((bd, _, _)) if d >= *bd => second_d = second_d.min(d),
                    _ => {
                        if let Some((bd, _, _)) = &best_d {
                            second_d = second_d.min(*bd);
                        }
                        best_d = Some((d, id, inn.clone()));
                    }
                }
            }
            match &ml {
                Some((mm, _, _)) if m >= *mm => second_ml = second_ml.min(m),
                _ => {
                    if let Some((mm, _, _)) = &ml {
                        second_ml = second_ml.min(*mm);
                    }
                    ml = Some((m, id, inn));
                }
            }
        }
        if o.descriptor.is_some() {
            if let Some((d, id, inn)) = best_d
                && d <= a.max_hamming
                && (second_d == u32::MAX || (d as f64) < a.ratio * second_d as f64)
            {
                return Association::Matched(id, inn);
            }
        } else if let Some((m, id, inn)) = ml {
            // Two landmarks about as likely: rather none than maybe the wrong one.
            if second_ml - m >= a.ml_margin_chi2 {
                return Association::Matched(id, inn);
            }
            return Association::Ambiguous;
        }
        if near_dup { Association::Ambiguous } else { Association::New }
    }

    /// Updates every particle with one frame of observations, weights, resamples when N_eff is
    /// low, and checks the multi-map triggers.
    pub fn update(&mut self, obs: &[Observation]) -> FrameReport {
        let t_start = std::time::Instant::now();
        self.frame += 1;
        let frame = self.frame;
        let first_new_id = self.next_id;
        self.next_id = self.next_id.saturating_add(obs.len() as u32);
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
        let t_candidates = std::time::Instant::now();
        let seeds = self.seeds();
        let decisions = self.for_each_particle(&seeds, |p, rng| {
            Self::weigh_particle(&cfg, &candidates, &known, &pose_q, p, obs, &motion_cov, rng)
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
        let t_resample = std::time::Instant::now();
        // 3. Landmark EKF updates, once per surviving parent, in parallel.
        let results =
            par_map(self.threads, &mut survivors, |(p, d)| Self::apply_particle(&cfg, p, obs, d, first_new_id, frame));
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
        self.register_new_landmarks(&results, obs, first_new_id);
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

    /// Registers the landmarks this frame created in the association grid (at the first
    /// creator's position) or under their feature track.
    fn register_new_landmarks(&mut self, results: &[ParticleFrame], obs: &[Observation], first_new_id: u32) {
        let gate = self.cfg.association.duplicate_gate_chi2;
        let mut seen = std::collections::HashSet::new();
        for r in results {
            for (id, pos) in &r.created {
                if seen.insert(*id) {
                    let j = (*id - first_new_id) as usize;
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

    /// Association decisions and the importance weight of one particle for one frame (and, with
    /// the FastSLAM 2.0 proposal, its pose sampled from the proposal); maps are only read.
    ///
    /// FastSLAM 2.0 ([3D] Alg 2 with the proposal of Montemerlo et al. 2003): with the motion
    /// prior N(0, P) on the pose perturbation and the matched confirmed landmarks' innovations
    /// νᵢ ≈ H_{x,i}·δ + noise(Sᵢ), the proposal is N(μ, Σ) with Σ = (P⁻¹ + Σ H_xᵀS⁻¹H_x)⁻¹,
    /// μ = Σ·Σ H_xᵀS⁻¹ν, and the weight is the joint marginal likelihood
    /// N(ν; 0, blockdiag(S) + H_x·P·H_xᵀ), evaluated through the determinant lemma and
    /// Woodbury: ln w = −½(Σ νᵀS⁻¹ν − bᵀΣb + Σ ln|S| + ln|P| − ln|Σ| + 3n ln 2π), b = Σ H_xᵀS⁻¹ν.
    #[allow(clippy::too_many_arguments)]
    fn weigh_particle(
        cfg: &FastSlamConfig,
        candidates: &[Vec<u32>],
        known: &[bool],
        pose_q: &[(Matrix3<f64>, Matrix3<f64>)],
        p: &mut Particle,
        obs: &[Observation],
        motion_cov: &Matrix6<f64>,
        rng: &mut Xoshiro256PlusPlus,
    ) -> Vec<Decision> {
        let a = &cfg.association;
        let ln2pi = (2.0 * std::f64::consts::PI).ln();
        let decisions: Vec<Association> = obs
            .iter()
            .zip(candidates)
            .zip(pose_q)
            .zip(known)
            .map(|(((o, c), q), k)| Self::associate(cfg, c, p, o, q, *k))
            .collect();
        // One observation per landmark and frame: of several matched to one landmark the one
        // with the smallest normalised innovation keeps it, the others are left out.
        let mut decisions = decisions;
        let mut owner: HashMap<u32, (usize, f64)> = HashMap::new();
        let mut losers = vec![];
        for (j, d) in decisions.iter().enumerate() {
            if let Association::Matched(id, inn) = d {
                match owner.get(id) {
                    Some(&(_, m)) if m <= inn.mahalanobis => losers.push(j),
                    Some(&(k, _)) => {
                        losers.push(k);
                        owner.insert(*id, (j, inn.mahalanobis));
                    }
                    None => {
                        owner.insert(*id, (j, inn.mahalanobis));
                    }
                }
            }
        }
        for j in losers {
            decisions[j] = Association::Ambiguous;
        }
        let confirmed = |p: &Particle, id: u32| p.map.get(id).is_some_and(|l| l.hits >= a.confirm_after);
        if cfg.proposal == Proposal::Optimal
            && let Some(cP) = Cholesky::new(*motion_cov)
        {
            let mut A = cP.inverse();
            let mut b = Vector6::zeros();
            let mut quad = 0.0;
            let mut log_det_s = 0.0;
            let mut n = 0usize;
            for (d, o) in decisions.iter().zip(obs) {
                let Association::Matched(id, inn) = d else { continue };
                let Some(lm) = p.map.get(*id).filter(|l| l.hits >= a.confirm_after) else { continue };
                let Hx = pose_jacobian(&p.pose, &lm.mean_m, o);
                let S_inv = inn.S_inv();
                let HtSi = Hx.transpose() * S_inv;
                A += HtSi * Hx;
                b += HtSi * inn.nu;
                quad += inn.mahalanobis;
                log_det_s += inn.log_det();
                n += 1;
            }
            if n > 0
                && let Some(cA) = Cholesky::new(A)
            {
                let Sigma = cA.inverse();
                let mu = Sigma * b;
                let log_det_p: f64 = cP.l().diagonal().iter().map(|d| 2.0 * d.ln()).sum();
                let log_det_a: f64 = cA.l().diagonal().iter().map(|d| 2.0 * d.ln()).sum();
                let log_w = -0.5 * (quad - b.dot(&mu) + log_det_s + log_det_p + log_det_a + 3.0 * n as f64 * ln2pi);
                if log_w.is_finite() {
                    p.log_w += log_w;
                }
                if let Some(cs) = Cholesky::new(Sigma) {
                    let z = Vector6::from_iterator((0..6).map(|_| rng.sample::<f64, _>(StandardNormal)));
                    let delta = mu + cs.l() * z;
                    if delta.iter().all(|v| v.is_finite()) {
                        p.pose = perturb(&p.pose, &delta);
                    }
                }
            }
        }
        obs.iter()
            .zip(decisions)
            .map(|(o, d)| match d {
                Association::Matched(id, inn) => {
                    if cfg.proposal != Proposal::Optimal && confirmed(p, id) {
                        p.log_w += inn.log_likelihood();
                    }
                    Decision::Matched(id)
                }
                Association::Ambiguous => Decision::Ambiguous,
                Association::Rejected => {
                    // Unexplained, like a new landmark: the density at the gate boundary.
                    let log_det = meas_cov(o).determinant().max(1e-300).ln();
                    p.log_w += -0.5 * (a.gate_chi2 + log_det + 3.0 * ln2pi);
                    Decision::Rejected
                }
                Association::New => {
                    // ln p(new): the density at the gate boundary of the observation's own noise.
                    let log_det = meas_cov(o).determinant().max(1e-300).ln();
                    p.log_w += -0.5 * (a.gate_chi2 + log_det + 3.0 * ln2pi);
                    Decision::New
                }
            })
            .collect()
    }

    /// Applies one particle's decisions to its map: landmark EKF updates (at the particle's
    /// current pose), new landmarks, provisional bookkeeping.
    fn apply_particle(
        cfg: &FastSlamConfig,
        p: &mut Particle,
        obs: &[Observation],
        decisions: &[Decision],
        first_new_id: u32,
        frame: u32,
    ) -> ParticleFrame {
        let a = &cfg.association;
        let mut out = ParticleFrame { associations: vec![None; obs.len()], ..Default::default() };
        for (j, (o, d)) in obs.iter().zip(decisions).enumerate() {
            match *d {
                Decision::Matched(id) => {
                    let pose = p.pose;
                    let Some(lm) = p.map.get_mut(id) else { continue };
                    let Ok(inn) = observe(&pose, lm, o) else { continue };
                    if lm.hits >= a.confirm_after {
                        out.nis_sum += inn.mahalanobis;
                    }
                    let updated = match (&o.stereo, lm.inverse_depth.is_some()) {
                        (Some(st), true) => {
                            ekf::update_inverse_depth(lm, &(pose * st.body_from_camera), &st.s, &st.cov, 3)
                        }
                        (Some(st), false) => {
                            ekf::update_stereo_iterated(lm, &(pose * st.body_from_camera), &st.s, &st.cov, 4)
                        }
                        (None, _) => {
                            // A Cartesian observation: the Cartesian view takes over.
                            lm.inverse_depth = None;
                            ekf::update(lm, &inn, &o.Rz)
                        }
                    };
                    if updated.is_err() {
                        continue;
                    }
                    lm.hits += 1;
                    lm.last_seen_frame = frame;
                    if lm.hits == a.confirm_after {
                        p.confirmed += 1;
                    }
                    if lm.hits >= a.confirm_after {
                        out.matched += 1;
                    }
                    out.associations[j] = Some(id);
                }
                Decision::Ambiguous => out.ambiguous += 1,
                Decision::Rejected => out.rejected += 1,
                Decision::New => {
                    let id = first_new_id + j as u32;
                    let lm = match &o.stereo {
                        Some(st) => ekf::init_landmark_inverse_depth(
                            &(p.pose * st.body_from_camera),
                            &st.s,
                            &st.cov,
                            o.descriptor,
                            frame,
                        ),
                        None => init_landmark(&p.pose, &o.z_m, &o.Rz, o.descriptor, frame),
                    };
                    out.created.push((id, lm.mean_m));
                    p.map.insert(id, lm);
                    if a.confirm_after <= 1 {
                        p.confirmed += 1;
                    } else {
                        p.provisional.push(id);
                    }
                    out.new += 1;
                }
            }
        }
        // Provisional landmarks: confirmed ones leave the list, stale ones are dropped.
        let (confirm, max_age) = (a.confirm_after, a.provisional_max_age_frames);
        let mut keep = Vec::with_capacity(p.provisional.len());
        for id in std::mem::take(&mut p.provisional) {
            match p.map.get(id) {
                Some(l) if l.hits >= confirm => {}
                Some(l) if frame - l.last_seen_frame > max_age => {
                    p.map.remove(id);
                }
                Some(_) => keep.push(id),
                None => {}
            }
        }
        p.provisional = keep;
        out
    }

    /// Candidates of the stereo observations without a track id (once for all particles):
    /// every landmark of the local map created within reach of the camera, seen from the best
    /// particle with its estimate there, whose predicted stereo coordinates pass the duplicate
    /// gate (with a margin) of the observation's, the covariance widened by this frame's motion
    /// and the particles' spread; each particle then checks its own candidates exactly.
    fn stereo_candidates(
        &self,
        obs: &[Observation],
        known: &[bool],
        motion_cov: &Matrix6<f64>,
        spread: &(Isometry3<f64>, f64, f64),
        out: &mut [Vec<u32>],
    ) {
        let idx: Vec<usize> = (0..obs.len()).filter(|&j| !known[j] && obs[j].stereo.is_some()).collect();
        if idx.is_empty() || self.grid.view.is_empty() {
            return;
        }
        let best = self.best();
        let pose = best.pose;
        let mut cov = *motion_cov;
        for k in 0..3 {
            cov[(k, k)] += spread.1 * spread.1;
            cov[(3 + k, 3 + k)] += spread.2 * spread.2;
        }
        let gate = self.cfg.association.duplicate_gate_chi2 * 1.5;
        // Observations by camera (one camera in practice) and their pose uncertainty in s.
        let mut by_camera: Vec<(Isometry3<f64>, Vec<usize>)> = vec![];
        for &j in &idx {
            let cam = obs[j].stereo.as_ref().expect("filtered").body_from_camera;
            match by_camera.iter_mut().find(|(c, _)| c == &cam) {
                Some((_, v)) => v.push(j),
                None => by_camera.push((cam, vec![j])),
            }
        }
        for (cam, js) in by_camera {
            let world_from_cam = pose * cam;
            // Observation s with their covariance plus the pose term.
            let obs_s: Vec<(Vector3<f64>, Matrix3<f64>)> = js
                .iter()
                .map(|&j| {
                    let o = &obs[j];
                    let st = o.stereo.as_ref().expect("filtered");
                    let l = pose.transform_point(&o.z_m.into()).coords;
                    let Hx = pose_jacobian(&pose, &l, o);
                    let q = Hx * cov * Hx.transpose();
                    (st.s, st.cov + (q + q.transpose()) * 0.5)
                })
                .collect();
            let reach = js
                .iter()
                .map(|&j| obs[j].z_m.norm() + 3.0 * obs[j].Rz.trace().sqrt())
                .fold(0.0f64, f64::max)
                .min(MAX_VIEW_M)
                + VIEW_CELL_M * 3f64.sqrt();
            let grid = SGrid::new(&obs_s);
            let max_var = obs_s.iter().fold([0.0f64; 2], |m, (_, c)| [m[0].max(c[(0, 0)]), m[1].max(c[(1, 1)])]);
            let centre = world_from_cam.translation.vector;
            for (key, ids) in &self.grid.view {
                let c = Vector3::new(key[0] as f64 + 0.5, key[1] as f64 + 0.5, key[2] as f64 + 0.5) * VIEW_CELL_M;
                if (c - centre).norm() > reach {
                    continue;
                }
                for &id in ids {
                    let Some(lm) = best.map.get(id) else { continue };
                    let Some((s, Sl)) = predict_stereo(lm, &world_from_cam) else { continue };
                    let k = gate.sqrt();
                    let ra = k * (Sl[(0, 0)] + max_var[0]).sqrt();
                    let rb = k * (Sl[(1, 1)] + max_var[1]).sqrt();
                    grid.query(s[0], s[1], ra, rb, |i| {
                        let (so, co) = &obs_s[i];
                        let nu = so - s;
                        if let Some(ch) = Chol3::new(&(Sl + co))
                            && ch.mahalanobis(&nu) <= gate
                        {
                            out[js[i]].push(id);
                        }
                    });
                }
            }
        }
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

// Decisions live in a short per-particle Vec; boxing the large variant would cost an allocation
// per matched observation in the hottest loop.
#[allow(clippy::large_enum_variant)]
enum Association {
    Matched(u32, Innovation),
    Ambiguous,
    /// An attribute match outside the χ² gate.
    Rejected,
    New,
}

/// A particle's association decision for one observation, kept between weighing and updating.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Decision {
    Matched(u32),
    Ambiguous,
    Rejected,
    New,
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
}
