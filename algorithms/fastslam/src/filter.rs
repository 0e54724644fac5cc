//! The particle filter (SPEC §4, [3D] Alg 1-2): prediction through the process model with input
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
}

impl Observation {
    /// An observation from a camera-frame point and covariance and the `body_from_camera`
    /// extrinsic; NaN/inf or a covariance that is not positive definite is an error.
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
        Ok(Self {
            z_m: body_from_camera.transform_point(&(*point_cam_m).into()).coords,
            Rz,
            descriptor,
            track_id: None,
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
}

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
    /// The motion covariance of the last frame interval: a floor of the reported covariance, as
    /// the particle spread alone collapses after resampling.
    last_motion_cov: Matrix6<f64>,
    /// Motion noise accumulated since the local map started: the drift the particle spread
    /// cannot show (particles and their maps drift together).
    segment_motion_cov: Matrix6<f64>,
    threads: usize,
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

impl FastSlam {
    /// A filter with every particle at the origin of local map 0.
    pub fn new(cfg: FastSlamConfig) -> Result<Self, Vec<(String, String)>> {
        let problems = cfg.validate();
        if !problems.is_empty() {
            return Err(problems);
        }
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
            grid: Grid { cell_m: cfg.association.search_radius_m, cells: HashMap::new() },
            tracks: HashMap::new(),
            motion_cov: Matrix6::zeros(),
            weak_frames: 0,
            segment_frames: 0,
            twist: None,
            last_mean: None,
            last_cv_dt: None,
            last_motion_cov: Matrix6::zeros(),
            segment_motion_cov: Matrix6::zeros(),
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
        let chunk = self.particles.len().div_ceil(self.threads.max(1));
        let f = &f;
        crossbeam::thread::scope(|s| {
            let handles: Vec<_> = self
                .particles
                .chunks_mut(chunk)
                .zip(seeds.chunks(chunk))
                .map(|(ps, ss)| {
                    s.spawn(move |_| {
                        ps.iter_mut()
                            .zip(ss)
                            .map(|(p, seed)| f(p, &mut Xoshiro256PlusPlus::seed_from_u64(*seed)))
                            .collect::<Vec<R>>()
                    })
                })
                .collect();
            handles.into_iter().flat_map(|h| h.join().expect("particle worker panicked")).collect()
        })
        .expect("particle scope")
    }

    /// Prediction with an odometry input (SPEC §1): each particle propagates a sample of the input
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
        // Body-frame pose error added by this step (for the FastSLAM 2.0 proposal).
        let mut G = Matrix6::zeros();
        G[(0, 0)] = (sd[0] * u.dt_s).powi(2) + qp * qp;
        G[(1, 1)] = qp * qp;
        G[(2, 2)] = qp * qp;
        for k in 0..3 {
            G[(3 + k, 3 + k)] = sd[1 + k].powi(2) + qr * qr;
        }
        self.motion_cov += G;
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
    /// sample of `covariance` (over (δt, δθ) in the new body frame, m² and rad²), plus the
    /// additive process noise ω over `dt_s`. A covariance that is not positive semi-definite or
    /// a non-finite motion is an error and changes nothing.
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
        let qp = self.cfg.process_position_sigma * dt_s.sqrt();
        let qr = self.cfg.process_rotation_sigma * dt_s.sqrt();
        let mut cov = (covariance + covariance.transpose()) * 0.5;
        for k in 0..3 {
            cov[(k, k)] += qp * qp + 1e-12;
            cov[(3 + k, 3 + k)] += qr * qr + 1e-12;
        }
        let L = Cholesky::new(cov).ok_or(FilterError::NotPositiveDefinite("relative motion covariance"))?.l();
        // In the filter's error convention (position error in the map frame, rotation error in
        // the body frame): the right perturbation's translation turns with the new pose.
        let R = (self.best().pose.rotation * delta.rotation).to_rotation_matrix().into_inner();
        let mut J = Matrix6::identity();
        J.fixed_view_mut::<3, 3>(0, 0).copy_from(&R);
        self.motion_cov += J * cov * J.transpose();
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
        let (v, w) = self.twist.unwrap_or((Vector3::zeros(), Vector3::zeros()));
        self.last_cv_dt = Some(dt_s);
        let sp = self.cfg.cv_velocity_sigma_mps * dt_s;
        let sr = self.cfg.cv_angular_velocity_sigma_rps * dt_s;
        let mut G = Matrix6::zeros();
        for k in 0..3 {
            G[(k, k)] = sp * sp;
            G[(3 + k, 3 + k)] = sr * sr;
        }
        self.motion_cov += G;
        let seeds = self.seeds();
        self.for_each_particle(&seeds, |p, rng| {
            let step = Isometry3::new(v * dt_s + normal3(rng) * sp, w * dt_s + normal3(rng) * sr);
            p.pose *= step;
        });
    }

    /// Associates one observation for one particle (SPEC §3): descriptor with ratio test when
    /// the observation has one, else maximum likelihood, both inside the χ²₃ gate.
    fn associate(cfg: &FastSlamConfig, candidates: &[u32], p: &Particle, o: &Observation) -> Association {
        let a = &cfg.association;
        if o.track_id.is_some() {
            // By attribute ([3D] §3.1): the landmark of this feature track, if any, checked
            // against the χ² gate (a tracker's wrong match is left out, not fused).
            for &id in candidates {
                let Some(lm) = p.map.get(id) else { continue };
                return match innovation(&p.pose, lm, &o.z_m, &o.Rz) {
                    Ok(inn) if inn.mahalanobis <= a.gate_chi2 => Association::Matched(id, inn),
                    _ => Association::Rejected,
                };
            }
            return Association::New;
        }
        let w = p.pose.transform_point(&o.z_m.into()).coords;
        let mut ml: Option<(f64, u32, Innovation)> = None;
        let mut near_dup = false;
        let mut best_d: Option<(u32, u32, Innovation)> = None; // (hamming, id, innovation)
        let mut second_d = u32::MAX;
        let tr_rz = o.Rz.trace();
        for &id in candidates {
            let Some(lm) = p.map.get(id) else { continue };
            // Exact pre-check without a Cholesky: |ν| = |w − L| (a rotation keeps lengths) and
            // νᵀS⁻¹ν ≥ |ν|²/λmax(S) ≥ |ν|²/tr(S), with tr(S) = tr(Σ_L) + tr(Rz).
            let d2 = (lm.mean_m - w).norm_squared();
            if d2 > a.duplicate_gate_chi2 * (lm.cov_m2.trace() + tr_rz) {
                continue;
            }
            let Ok(inn) = innovation(&p.pose, lm, &o.z_m, &o.Rz) else { continue };
            if inn.mahalanobis > a.duplicate_gate_chi2 {
                continue;
            }
            near_dup = true;
            if inn.mahalanobis > a.gate_chi2 {
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
            if ml.as_ref().is_none_or(|(m, _, _)| inn.mahalanobis < *m) {
                ml = Some((inn.mahalanobis, id, inn));
            }
        }
        if o.descriptor.is_some() {
            if let Some((d, id, inn)) = best_d
                && d <= a.max_hamming
                && (second_d == u32::MAX || (d as f64) < a.ratio * second_d as f64)
            {
                return Association::Matched(id, inn);
            }
        } else if let Some((_, id, inn)) = ml {
            return Association::Matched(id, inn);
        }
        if near_dup { Association::Ambiguous } else { Association::New }
    }

    /// Updates every particle with one frame of observations, weights, resamples when N_eff is
    /// low, and checks the multi-map triggers.
    pub fn update(&mut self, obs: &[Observation]) -> FrameReport {
        self.frame += 1;
        let frame = self.frame;
        let first_new_id = self.next_id;
        self.next_id = self.next_id.saturating_add(obs.len() as u32);
        let cfg = self.cfg.clone();
        let motion_cov = self.motion_cov + Matrix6::identity() * 1e-9;
        self.last_motion_cov = self.motion_cov;
        self.segment_motion_cov += self.motion_cov;
        self.motion_cov = Matrix6::zeros();
        // Candidates once per observation for all particles: around the mean pose, widened by
        // the observation's noise (far stereo points are uncertain along the ray) and by the
        // particles' spread, so every particle's own search would find no more.
        let spread = self.particle_spread();
        let candidates: Vec<Vec<u32>> = obs
            .iter()
            .map(|o| {
                if let Some(t) = o.track_id {
                    // By attribute: the track's landmark, or none for a new track.
                    return self.tracks.get(&t).map(|id| vec![*id]).unwrap_or_default();
                }
                let w = spread.0.transform_point(&o.z_m.into()).coords;
                let particles_m = 3.0 * (spread.1 + spread.2 * o.z_m.norm()) + 0.25;
                let radius = cfg.association.search_radius_m.max(3.0 * o.Rz.trace().sqrt()) + particles_m;
                // A landmark passes the duplicate gate only within √(χ²·(tr Σ_L + tr Rz)) ≤
                // √(χ²·tr Σ₀) + √(χ²·tr Rz) of the particle's view of the observation.
                let slack = (cfg.association.duplicate_gate_chi2 * o.Rz.trace()).sqrt() + particles_m;
                let mut c = vec![];
                self.grid.candidates(&w, radius, slack, &mut c);
                c
            })
            .collect();
        // 1. Association and importance weights: read-only on the maps. The weight of FastSLAM
        //    (1.0 and 2.0) uses the landmark estimates before this frame's update, and the update
        //    is deterministic given pose, map and decisions; so resampling can come first and the
        //    maps are updated once per surviving parent (its copies would make identical
        //    updates), and never for particles about to be discarded.
        let seeds = self.seeds();
        let decisions =
            self.for_each_particle(&seeds, |p, rng| Self::weigh_particle(&cfg, &candidates, p, obs, &motion_cov, rng));
        let best_idx = (0..self.particles.len())
            .max_by(|a, b| self.particles[*a].log_w.total_cmp(&self.particles[*b].log_w))
            .unwrap_or(0);
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
        let mut groups: Vec<(usize, usize)> = vec![];
        for &i in &parents {
            match groups.last_mut() {
                Some((g, c)) if *g == i => *c += 1,
                _ => groups.push((i, 1)),
            }
        }
        let mut old: Vec<Option<Particle>> = std::mem::take(&mut self.particles).into_iter().map(Some).collect();
        let mut survivors: Vec<(Particle, Vec<Decision>)> =
            groups.iter().map(|(i, _)| (old[*i].take().expect("each parent once"), decisions[*i].clone())).collect();
        // 3. Landmark EKF updates, once per surviving parent, in parallel.
        let results =
            par_map(self.threads, &mut survivors, |(p, d)| Self::apply_particle(&cfg, p, obs, d, first_new_id, frame));
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
        let mut seen = std::collections::HashSet::new();
        for r in &results {
            for (id, pos) in &r.created {
                if seen.insert(*id) {
                    let j = (*id - first_new_id) as usize;
                    match obs[j].track_id {
                        Some(t) => {
                            self.tracks.insert(t, *id);
                        }
                        None => self.grid.insert(*id, *pos, obs[j].Rz.trace(), cfg.association.duplicate_gate_chi2),
                    }
                }
            }
        }
        // The best particle (largest weight) always survives systematic resampling (it has
        // w ≥ 1/N, so at least one copy).
        let best_group = groups.iter().position(|(i, _)| *i == best_idx).unwrap_or(0);
        let best = &results[best_group];
        let (matched, new, ambiguous, associations) =
            (best.matched, best.new, best.ambiguous, best.associations.clone());
        let (rejected, mean_nis) =
            (best.rejected, if best.matched > 0 { best.nis_sum / best.matched as f64 } else { f64::NAN });
        let landmarks = self.best().confirmed;
        let estimate = self.estimate();
        if let Some(prev) = self.last_mean {
            // Twist for the constant-velocity model (per frame; scaled by dt at prediction).
            let d = prev.inverse() * estimate.map_from_body;
            if let Some(dt) = self.last_cv_dt.filter(|dt| *dt > 0.0) {
                self.twist = Some((d.translation.vector / dt, d.rotation.scaled_axis() / dt));
            }
        }
        self.last_mean = Some(estimate.map_from_body);
        let mut new_segment = None;
        self.segment_frames += 1;
        if matched < cfg.segments.min_matched {
            self.weak_frames += 1;
        } else {
            self.weak_frames = 0;
        }
        let sigma = estimate.covariance.fixed_view::<3, 3>(0, 0).symmetric_eigenvalues().max().max(0.0).sqrt();
        if sigma > cfg.segments.max_position_sigma_m {
            new_segment = Some(SegmentReason::PoseUncertainty { sigma_m: sigma });
        } else if self.weak_frames >= cfg.segments.weak_frames
            && landmarks >= cfg.segments.min_matched
            && self.segment_frames >= cfg.segments.min_frames
        {
            new_segment = Some(SegmentReason::FewMatches { matched, frames: self.weak_frames });
        }
        if let Some(reason) = &new_segment {
            self.start_new_segment(reason.clone());
        }
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
        }
    }

    /// Association decisions and the importance weight of one particle for one frame (and, with
    /// the FastSLAM 2.0 proposal, its pose sampled from the proposal); maps are only read.
    fn weigh_particle(
        cfg: &FastSlamConfig,
        candidates: &[Vec<u32>],
        p: &mut Particle,
        obs: &[Observation],
        motion_cov: &Matrix6<f64>,
        rng: &mut Xoshiro256PlusPlus,
    ) -> Vec<Decision> {
        let a = &cfg.association;
        let decisions: Vec<Association> =
            obs.iter().zip(candidates).map(|(o, c)| Self::associate(cfg, c, p, o)).collect();
        if cfg.proposal == Proposal::Optimal {
            // FastSLAM 2.0: sample the pose from the motion prior conditioned on the matches.
            if let Some(info) = Cholesky::new(*motion_cov).map(|c| c.inverse()) {
                let mut A = info;
                let mut b = Vector6::zeros();
                let mut log_w = 0.0;
                let mut any = false;
                for d in &decisions {
                    let Association::Matched(id, inn) = d else { continue };
                    let Some(lm) = p.map.get(*id) else { continue };
                    let (_, Hx) = ekf::jacobians(&p.pose, &lm.mean_m);
                    let S_inv = inn.S_inv();
                    A += Hx.transpose() * S_inv * Hx;
                    b += Hx.transpose() * S_inv * inn.nu;
                    let Sx = Hx * motion_cov * Hx.transpose() + inn.S;
                    if let Some(c) = Cholesky::new(Sx) {
                        let m = inn.nu.dot(&c.solve(&inn.nu));
                        let log_det: f64 = c.l().diagonal().iter().map(|d| 2.0 * d.ln()).sum();
                        log_w += -0.5 * (m + log_det + 3.0 * (2.0 * std::f64::consts::PI).ln());
                    }
                    any = true;
                }
                if any && let Some(cA) = Cholesky::new(A) {
                    let Sigma = cA.inverse();
                    let mu = Sigma * b;
                    if let Some(cs) = Cholesky::new(Sigma) {
                        let n = Vector6::from_iterator((0..6).map(|_| rng.sample::<f64, _>(StandardNormal)));
                        let delta = mu + cs.l() * n;
                        if delta.iter().all(|v| v.is_finite()) {
                            p.pose = perturb(&p.pose, &delta);
                        }
                    }
                    p.log_w += log_w;
                }
            }
        }
        obs.iter()
            .zip(decisions)
            .map(|(o, d)| match d {
                Association::Matched(id, inn) => {
                    if cfg.proposal != Proposal::Optimal && p.map.get(id).is_some_and(|l| l.hits >= a.confirm_after) {
                        p.log_w += inn.log_likelihood();
                    }
                    Decision::Matched(id)
                }
                Association::Ambiguous => Decision::Ambiguous,
                Association::Rejected => {
                    // Unexplained, like a new landmark: the density at the gate boundary.
                    let log_det = o.Rz.determinant().max(1e-300).ln();
                    p.log_w += -0.5 * (a.gate_chi2 + log_det + 3.0 * (2.0 * std::f64::consts::PI).ln());
                    Decision::Rejected
                }
                Association::New => {
                    // ln p(new): the density at the gate boundary of the observation's own noise.
                    let log_det = o.Rz.determinant().max(1e-300).ln();
                    p.log_w += -0.5 * (a.gate_chi2 + log_det + 3.0 * (2.0 * std::f64::consts::PI).ln());
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
                    let Ok(inn) = innovation(&pose, lm, &o.z_m, &o.Rz) else { continue };
                    if lm.hits >= a.confirm_after {
                        out.nis_sum += inn.mahalanobis;
                    }
                    if ekf::update(lm, &inn, &o.Rz).is_err() {
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
                    let lm = init_landmark(&p.pose, &o.z_m, &o.Rz, o.descriptor, frame);
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
        let chunk = garbage.len().div_ceil(self.threads.max(1)).max(1);
        crossbeam::thread::scope(|s| {
            while !garbage.is_empty() {
                let tail = garbage.split_off(garbage.len().saturating_sub(chunk));
                s.spawn(move |_| drop(tail));
            }
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
            covariance: cov + self.last_motion_cov + self.segment_motion_cov * DRIFT_FRACTION,
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
        self.tracks.clear();
        self.segment += 1;
        self.segment_motion_cov = Matrix6::zeros();
        self.weak_frames = 0;
        self.segment_frames = 0;
        self.last_mean = None;
        self.motion_cov = Matrix6::zeros();
    }
}

/// Share of the motion noise accumulated over a local map that the reported pose covariance adds
/// to the particle spread. The spread alone cannot show the drift that particles and their maps
/// share, and is far too confident (mean NEES ≈ 3·10⁴ on the simulator). Adding the whole
/// dead-reckoning amount brings it to ≈ 54, still optimistic, so the full share is used.
pub const DRIFT_FRACTION: f64 = 1.0;

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

/// Applies `f` to every item on up to `threads` scoped worker threads (contiguous chunks);
/// results in item order.
fn par_map<T: Send, R: Send>(threads: usize, items: &mut [T], f: impl Fn(&mut T) -> R + Sync) -> Vec<R> {
    if items.is_empty() {
        return vec![];
    }
    let chunk = items.len().div_ceil(threads.max(1));
    let f = &f;
    crossbeam::thread::scope(|s| {
        let handles: Vec<_> =
            items.chunks_mut(chunk).map(|c| s.spawn(move |_| c.iter_mut().map(f).collect::<Vec<R>>())).collect();
        handles.into_iter().flat_map(|h| h.join().expect("particle worker panicked")).collect()
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn candidates_keep_every_landmark_that_could_pass_the_duplicate_gate() {
        let chi2 = 21.1;
        let mut g = Grid { cell_m: 3.0, cells: HashMap::new() };
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
