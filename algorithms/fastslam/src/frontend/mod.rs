//! Camera-only motion between two stereo frames: the front end that gives FastSLAM a motion
//! prior when there is no odometry.
//!
//! Each frame is a set of triangulated points in the camera (optical) frame with their
//! first-order covariance (EQUATIONS §2). The front end finds the rigid motion `cur_from_prev` of the
//! camera that maps the previous frame's points onto the current frame's, with its covariance:
//!
//! 1. **Correspondences.** By the front end's attribute when both frames carry it (a feature
//!    track id: pairs with the same id), else by guided matching around a motion prior (the last
//!    motion, constant velocity), else — first frame pair, after a failure, or when the prior
//!    finds no consensus — by a prior-free search: triples of well-triangulated previous points
//!    and candidate triples of current points within the search bounds
//!    (`max_translation_m`, `max_rotation_deg`), pruned by rigidity (the three pairwise distances
//!    must agree within their uncertainty), each triple giving a motion by Horn/Umeyama that is
//!    scored by the number of points it brings onto a current point.
//! 2. **Consensus.** RANSAC over the correspondences (three-point Horn/Umeyama hypotheses).
//! 3. **Refinement.** Gauss-Newton over the 6-DOF motion with a Huber kernel, on residuals in
//!    normalised stereo coordinates s = (x/z, y/z, 1/z): for a rectified pair these are the pixels
//!    (uL, v, uL − uR) divided by f (and f·b), so their noise is nearly Gaussian even where the
//!    depth noise is not (far points). The residual of pair (i, j) is s(T·Pᵢ) − sⱼ with covariance
//!    Jₛ·R·Cᵢ·Rᵀ·Jₛᵀ + Cₛⱼ. Matching, consensus and refinement alternate twice (the second
//!    matching is one-to-one, at the refined motion).
//!
//! The result's covariance is the inverse Gauss-Newton information of the inliers, scaled up by
//! the reduced χ² when the residuals are larger than their covariances say (so a pixel noise set
//! too small in the producer makes the motion less certain, not wrongly certain). A motion with
//! too few inliers, outside the search bounds or with degenerate geometry is an error naming why;
//! the caller decides what to do instead (FastSLAM falls back to constant velocity and says so).
//!
//! Conventions: `cur_from_prev` maps points of the previous camera frame into the current one.
//! Perturbations are ξ = (δt, δθ) acting as x ↦ x + δθ × x + δt in the frame named.

#![allow(non_snake_case)]

use std::collections::HashMap;
use std::f64::consts::PI;

use nalgebra::{Cholesky, Isometry3, Matrix3, Matrix3x6, Matrix6, Translation3, UnitQuaternion, Vector3, Vector6};
use rand::{RngExt, SeedableRng};
use rand_xoshiro::Xoshiro256PlusPlus;
use serde::{Deserialize, Serialize};

use crate::filter::Observation;
use crate::sym3::Chol3;

mod config;
mod hypotheses;

pub use config::FrontEndConfig;
use hypotheses::*;
pub use hypotheses::{adjoint, motion_in_body};

/// How the correspondences of an accepted motion were found.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Method {
    /// Same feature track id in both frames.
    TrackIds,
    /// Guided matching around the constant-velocity prior.
    Guided,
    /// The prior-free search.
    Search,
}

/// An accepted motion between the previous frame and this one.
#[derive(Debug, Clone, PartialEq)]
pub struct Registration {
    /// The current camera frame in the previous one (the camera's motion), m.
    pub prev_from_cur: Isometry3<f64>,
    /// Covariance of the right perturbation (δt, δθ) of `prev_from_cur`, in the current camera
    /// frame (m², rad²).
    pub covariance: Matrix6<f64>,
    /// Correspondences consistent with the motion.
    pub inliers: usize,
    /// Usable points of the previous and the current frame.
    pub points: (usize, usize),
    /// Candidate current points per previous point in the first matching (1 with track ids).
    pub candidates_per_point: f64,
    /// How the correspondences were found.
    pub method: Method,
    /// Motion hypotheses scored (RANSAC and search).
    pub hypotheses: usize,
    /// Mean normalised squared residual of the inliers per degree of freedom (≈ 1 when the
    /// observation covariances are right).
    pub chi2_per_dof: f64,
    /// The inlier correspondences as (observation index in the previous frame, in this one):
    /// the same feature in both frames (what a feature tracker would link).
    pub matches: Vec<(usize, usize)>,
}

/// Why no motion was found; the previous frame is replaced by the current one either way.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum RegistrationError {
    /// The first frame: nothing to register against.
    #[error("first frame: nothing to register against")]
    FirstFrame,
    /// Too few points with positive depth and a valid covariance.
    #[error("too few usable points ({previous} in the previous frame, {current} in this one; need {needed})")]
    TooFewPoints {
        /// Usable points of the previous frame.
        previous: usize,
        /// Usable points of this frame.
        current: usize,
        /// Needed in both.
        needed: usize,
    },
    /// No motion brought enough points into agreement.
    #[error("no consistent motion: the best has {inliers} inliers, {needed} needed ({method})")]
    NoConsensus {
        /// Inliers of the best motion found.
        inliers: usize,
        /// Needed.
        needed: usize,
        /// What was tried last.
        method: &'static str,
    },
    /// The points constrain the motion too weakly (e.g. all on a line, or all far away).
    #[error("degenerate geometry: motion σ {sigma_m:.3} m / {sigma_deg:.2}°")]
    Degenerate {
        /// Largest translation σ, m.
        sigma_m: f64,
        /// Largest rotation σ, deg.
        sigma_deg: f64,
    },
}

/// One usable point of a frame, camera frame.
#[derive(Debug, Clone)]
struct Pt {
    /// Position, m.
    p: Vector3<f64>,
    /// Its covariance, m².
    C: Matrix3<f64>,
    /// Normalised stereo coordinates (x/z, y/z, 1/z).
    s: Vector3<f64>,
    /// Covariance of `s`.
    Cs: Matrix3<f64>,
    /// √tr C, m.
    sigma_m: f64,
    /// Front-end track id.
    track: Option<u64>,
    /// Index of the observation it came from.
    index: usize,
}

/// s(p) = (x/z, y/z, 1/z).
fn stereo_coords(p: &Vector3<f64>) -> Vector3<f64> {
    let iz = 1.0 / p.z;
    Vector3::new(p.x * iz, p.y * iz, iz)
}

/// ∂s/∂p.
fn stereo_jacobian(p: &Vector3<f64>) -> Matrix3<f64> {
    let iz = 1.0 / p.z;
    let iz2 = iz * iz;
    Matrix3::new(iz, 0.0, -p.x * iz2, 0.0, iz, -p.y * iz2, 0.0, 0.0, -iz2)
}

/// Smallest depth of a usable point, m.
const MIN_DEPTH_M: f64 = 0.05;

/// A frame prepared for registration.
#[derive(Debug, Clone, Default)]
pub struct Frame {
    pts: Vec<Pt>,
    /// Observations left out (depth ≤ 5 cm in the camera frame, or an unusable covariance).
    pub skipped: usize,
}

impl Frame {
    /// The observations of a frame (body frame, as the filter gets them), taken back into the
    /// camera frame with `body_from_camera`.
    pub fn from_observations(obs: &[Observation], body_from_camera: &Isometry3<f64>) -> Self {
        let cam_from_body = body_from_camera.inverse();
        let Rcb = cam_from_body.rotation.to_rotation_matrix().into_inner();
        let mut pts = Vec::with_capacity(obs.len());
        let mut skipped = 0;
        for (index, o) in obs.iter().enumerate() {
            let p = cam_from_body.transform_point(&o.z_m.into()).coords;
            let C = Rcb * o.Rz * Rcb.transpose();
            match Pt::new(p, C, o.track_id, index) {
                Some(pt) => pts.push(pt),
                None => skipped += 1,
            }
        }
        Self { pts, skipped }
    }

    /// Usable points.
    pub fn len(&self) -> usize {
        self.pts.len()
    }

    /// True without usable points.
    pub fn is_empty(&self) -> bool {
        self.pts.is_empty()
    }
}

impl Pt {
    fn new(p: Vector3<f64>, C: Matrix3<f64>, track: Option<u64>, index: usize) -> Option<Self> {
        if !(p.iter().all(|v| v.is_finite()) && C.iter().all(|v| v.is_finite())) || p.z < MIN_DEPTH_M {
            return None;
        }
        let C = (C + C.transpose()) * 0.5;
        let J = stereo_jacobian(&p);
        let Cs = J * C * J.transpose();
        let Cs = (Cs + Cs.transpose()) * 0.5;
        Chol3::new(&Cs)?;
        Some(Self { p, C, s: stereo_coords(&p), Cs, sigma_m: C.trace().max(0.0).sqrt(), track, index })
    }
}

/// A grid over the (x/z, y/z) coordinates of a frame's points.
struct AbGrid {
    min: [f64; 2],
    cell: f64,
    nx: usize,
    ny: usize,
    /// CSR: points of cell k are `items[start[k]..start[k + 1]]`.
    start: Vec<u32>,
    items: Vec<u32>,
}

impl AbGrid {
    fn new(pts: &[Pt]) -> Self {
        let (mut lo, mut hi) = ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]);
        for p in pts {
            for k in 0..2 {
                lo[k] = lo[k].min(p.s[k]);
                hi[k] = hi[k].max(p.s[k]);
            }
        }
        if pts.is_empty() {
            lo = [0.0; 2];
            hi = [1.0; 2];
        }
        let area = ((hi[0] - lo[0]) * (hi[1] - lo[1])).max(1e-6);
        // About two points per cell, at most 256 cells a side.
        let cell = (area / (pts.len().max(1) as f64 / 2.0)).sqrt().max((hi[0] - lo[0]).max(hi[1] - lo[1]) / 256.0);
        let nx = (((hi[0] - lo[0]) / cell).floor() as usize + 1).min(257);
        let ny = (((hi[1] - lo[1]) / cell).floor() as usize + 1).min(257);
        let key = |p: &Pt| -> usize {
            let ix = (((p.s[0] - lo[0]) / cell) as usize).min(nx - 1);
            let iy = (((p.s[1] - lo[1]) / cell) as usize).min(ny - 1);
            iy * nx + ix
        };
        let mut count = vec![0u32; nx * ny + 1];
        for p in pts {
            count[key(p) + 1] += 1;
        }
        for k in 1..count.len() {
            count[k] += count[k - 1];
        }
        let mut fill = count.clone();
        let mut items = vec![0u32; pts.len()];
        for (i, p) in pts.iter().enumerate() {
            let k = key(p);
            items[fill[k] as usize] = i as u32;
            fill[k] += 1;
        }
        Self { min: lo, cell, nx, ny, start: count, items }
    }

    /// Points whose (a, b) may lie within ±(ra, rb) of (a, b).
    fn query(&self, a: f64, b: f64, ra: f64, rb: f64, mut f: impl FnMut(usize)) {
        let lo_x = ((a - ra - self.min[0]) / self.cell).floor();
        let hi_x = ((a + ra - self.min[0]) / self.cell).floor();
        let lo_y = ((b - rb - self.min[1]) / self.cell).floor();
        let hi_y = ((b + rb - self.min[1]) / self.cell).floor();
        if hi_x < 0.0 || hi_y < 0.0 || lo_x >= self.nx as f64 || lo_y >= self.ny as f64 {
            return;
        }
        let (x0, x1) = (lo_x.max(0.0) as usize, (hi_x as usize).min(self.nx - 1));
        let (y0, y1) = (lo_y.max(0.0) as usize, (hi_y as usize).min(self.ny - 1));
        for y in y0..=y1 {
            let row = y * self.nx;
            for k in (row + x0)..=(row + x1) {
                for &i in &self.items[self.start[k] as usize..self.start[k + 1] as usize] {
                    f(i as usize);
                }
            }
        }
    }
}

/// x ↦ x + δθ × x + δt, composed on the left: Exp(ξ)·T.
fn left_update(T: &Isometry3<f64>, xi: &Vector6<f64>) -> Isometry3<f64> {
    let dR = UnitQuaternion::from_scaled_axis(xi.fixed_rows::<3>(3).into_owned());
    Isometry3::from_parts(Translation3::from(dR * T.translation.vector + xi.fixed_rows::<3>(0)), dR * T.rotation)
}

/// The residual of previous point `P` moved by `T` against current point `Q`, its covariance,
/// and the Jacobian of the residual with respect to a left perturbation of `T`.
fn residual(T: &Isometry3<f64>, P: &Pt, Q: &Pt) -> (Vector3<f64>, Matrix3<f64>, Matrix3x6<f64>) {
    let R = T.rotation.to_rotation_matrix().into_inner();
    let p = R * P.p + T.translation.vector;
    let Js = stereo_jacobian(&p);
    let JR = Js * R;
    let S = JR * P.C * JR.transpose() + Q.Cs;
    let mut Jx = Matrix3x6::zeros();
    Jx.fixed_view_mut::<3, 3>(0, 0).copy_from(&Js);
    Jx.fixed_view_mut::<3, 3>(0, 3).copy_from(&(-Js * p.cross_matrix()));
    (stereo_coords(&p) - Q.s, (S + S.transpose()) * 0.5, Jx)
}

/// νᵀ·S⁻¹·ν, or `None` when S is not positive definite.
fn mahalanobis(nu: &Vector3<f64>, S: &Matrix3<f64>) -> Option<f64> {
    Some(Chol3::new(S)?.mahalanobis(nu))
}

/// νᵀS⁻¹ν when it is at most `gate`, else `None` (as `mahalanobis(ν, S).filter(|m| m <= gate)`).
/// A pair is refused without the factorisation when one component alone is out of the gate:
/// νᵀS⁻¹ν ≥ νᵢ²/Sᵢᵢ for a positive-definite S (the margin of 10⁻⁹ keeps the rounding of the
/// factorised value from ever deciding otherwise). Most of a search window's points are refused
/// so, by their disparity, which the window does not bound.
fn mahalanobis_within(nu: &Vector3<f64>, S: &Matrix3<f64>, gate: f64) -> Option<f64> {
    let bound = gate * (1.0 + 1e-9);
    if (0..3).any(|i| nu[i] * nu[i] > bound * S[(i, i)]) {
        return None;
    }
    mahalanobis(nu, S).filter(|m| *m <= gate)
}

/// Candidate pairs (prev index, cur index) with their normalised squared residual.
type Pairs = Vec<(u32, u32, f64)>;

/// A motion `cur_from_prev` with its covariance.
type Motion = (Isometry3<f64>, Matrix6<f64>);

/// The prior-free search's best motion with its covariance, the hypotheses scored and the
/// candidates per seed point.
type SearchResult = (Option<(Isometry3<f64>, Matrix6<f64>)>, usize, f64);

/// The stereo front end: keeps the previous frame and the last motion.
pub struct FrontEnd {
    cfg: FrontEndConfig,
    prev: Option<Frame>,
    /// The last accepted motion `prev_from_cur` per second (translation m/s, rotation vector
    /// rad/s): the constant-velocity prior.
    velocity: Option<(Vector3<f64>, Vector3<f64>)>,
    rng: Xoshiro256PlusPlus,
}

impl FrontEnd {
    /// A front end with `cfg` (validated by the caller).
    pub fn new(cfg: FrontEndConfig) -> Self {
        let rng = Xoshiro256PlusPlus::seed_from_u64(cfg.seed);
        Self { cfg, prev: None, velocity: None, rng }
    }

    /// The settings.
    pub fn config(&self) -> &FrontEndConfig {
        &self.cfg
    }

    /// Forgets the previous frame and the motion prior (the next frame starts afresh).
    pub fn reset(&mut self) {
        self.prev = None;
        self.velocity = None;
    }

    /// Registers `cur` against the previous frame, `dt_s` after it, and keeps `cur` as the
    /// previous frame for the next call.
    pub fn register(&mut self, cur: Frame, dt_s: f64) -> Result<Registration, RegistrationError> {
        let Some(prev) = self.prev.take() else {
            self.prev = Some(cur);
            return Err(RegistrationError::FirstFrame);
        };
        let result = self.register_pair(&prev, &cur, dt_s);
        self.prev = Some(cur);
        match &result {
            Ok(r) if dt_s > 0.0 => {
                let m = &r.prev_from_cur;
                self.velocity = Some((m.translation.vector / dt_s, m.rotation.scaled_axis() / dt_s));
            }
            _ => self.velocity = None,
        }
        result
    }

    /// A motion is accepted with at least `needed` inliers, of which enough come from the nearer
    /// half of the previous frame's points: far points agree with any translation once the
    /// rotation is right, and in a scene with many of them a wrong translation can otherwise
    /// gather enough support.
    fn supported(&self, prev: &Frame, inliers: &Pairs, needed: usize) -> bool {
        if inliers.len() < needed {
            return false;
        }
        let mut w: Vec<f64> = prev.pts.iter().map(|p| p.s.z).collect();
        w.sort_by(f64::total_cmp);
        let median = w[w.len() / 2];
        let near = prev.pts.iter().filter(|p| p.s.z >= median).count();
        let near_inliers = inliers.iter().filter(|(i, _, _)| prev.pts[*i as usize].s.z >= median).count();
        near_inliers as f64 >= self.cfg.min_inlier_fraction * near as f64
    }

    fn needed(&self, prev: &Frame, cur: &Frame) -> usize {
        let smaller = prev.len().min(cur.len()) as f64;
        self.cfg.min_inliers.max((self.cfg.min_inlier_fraction * smaller).ceil() as usize)
    }

    fn register_pair(&mut self, prev: &Frame, cur: &Frame, dt_s: f64) -> Result<Registration, RegistrationError> {
        let needed = self.needed(prev, cur);
        if prev.len() < needed || cur.len() < needed {
            return Err(RegistrationError::TooFewPoints { previous: prev.len(), current: cur.len(), needed });
        }
        let grid = AbGrid::new(&cur.pts);
        let mut hypotheses = 0;
        let mut best_inliers = 0;
        let mut last_method = "track ids";
        // 1. Track ids.
        let with_ids = prev.pts.iter().filter(|p| p.track.is_some()).count();
        if with_ids >= needed && cur.pts.iter().filter(|p| p.track.is_some()).count() >= needed {
            let by_id: HashMap<u64, u32> =
                cur.pts.iter().enumerate().filter_map(|(j, q)| q.track.map(|t| (t, j as u32))).collect();
            let pairs: Pairs = prev
                .pts
                .iter()
                .enumerate()
                .filter_map(|(i, p)| p.track.and_then(|t| by_id.get(&t)).map(|&j| (i as u32, j, 0.0)))
                .collect();
            let cands = pairs.len() as f64 / with_ids.max(1) as f64;
            if let Some((T, _, h)) = self.ransac(prev, cur, &pairs) {
                hypotheses += h;
                // Track ids are given: refine on them (a wrong id is an outlier of the kernel).
                let (T, inl) = self.refine(prev, cur, &pairs, T, 12);
                best_inliers = best_inliers.max(inl.len());
                if self.supported(prev, &inl, needed) {
                    return self.finish(prev, cur, T, &inl, Method::TrackIds, cands, hypotheses);
                }
            }
        }
        // 2. Guided by the constant-velocity prior; when that finds no consensus, by the same
        //    velocity without its turn (a turn that ends), by standing still (a stop) and by the
        //    prior three times wider (a sudden change), before the costly prior-free search.
        if let Some((v, w)) = self.velocity {
            last_method = "guided";
            let dt = dt_s.max(0.0);
            let (st, sr) = (self.cfg.prior_translation_sigma_m, self.cfg.prior_rotation_sigma_deg.to_radians());
            let mut prior = Matrix6::zeros();
            for k in 0..3 {
                prior[(k, k)] = st * st;
                prior[(3 + k, 3 + k)] = sr * sr;
            }
            let mut priors = vec![(v, w, 1.0)];
            if (w * dt).norm() > sr {
                priors.push((v, Vector3::zeros(), 1.0));
            }
            if (v * dt).norm() > 2.0 * st {
                priors.push((Vector3::zeros(), Vector3::zeros(), 1.0));
            }
            // The velocity changed more than the prior allows (a sudden acceleration): wider.
            priors.push((v, w, 3.0));
            let all: Vec<u32> = (0..prev.pts.len() as u32).collect();
            let mut cands = f64::NAN;
            for (v, w, widen) in priors {
                let prior = prior * (widen * widen);
                let T0 = Isometry3::new(v * dt, w * dt).inverse(); // cur_from_prev
                hypotheses += 1;
                // The prior is one rough hypothesis: refine it on the points it agrees with.
                let (optimum, in_gate) = self.local_optimum(prev, cur, &grid, T0, prior, &all);
                if cands.is_nan() {
                    // Candidates per point in the first prior's gate (its first matching).
                    cands = in_gate as f64 / prev.len().max(1) as f64;
                }
                if let Some((T, cov)) = optimum
                    && let Some((T, inl)) = self.polish(prev, cur, &grid, T, &cov)
                {
                    best_inliers = best_inliers.max(inl.len());
                    if self.supported(prev, &inl, needed) {
                        return self.finish(prev, cur, T, &inl, Method::Guided, cands, hypotheses);
                    }
                }
            }
        }
        // 3. Prior-free search.
        last_method = if last_method == "guided" { "guided, then search" } else { "search" };
        let (found, h, cands) = self.search(prev, cur, &grid);
        hypotheses += h;
        if let Some((T, cov)) = found
            && let Some((T, inl)) = self.polish(prev, cur, &grid, T, &cov)
        {
            best_inliers = best_inliers.max(inl.len());
            if self.supported(prev, &inl, needed) {
                return self.finish(prev, cur, T, &inl, Method::Search, cands, hypotheses);
            }
        }
        Err(RegistrationError::NoConsensus { inliers: best_inliers, needed, method: last_method })
    }

    /// One-to-one matching at `T` within its uncertainty `cov`, refinement, one-to-one matching
    /// at the refined motion, refinement.
    fn polish(
        &mut self,
        prev: &Frame,
        cur: &Frame,
        grid: &AbGrid,
        T: Isometry3<f64>,
        cov: &Matrix6<f64>,
    ) -> Option<(Isometry3<f64>, Pairs)> {
        let gate = self.cfg.inlier_chi2;
        let pairs = self.guided_pairs(prev, cur, grid, &T, Some(cov), gate, true);
        if pairs.len() < 3 {
            return None;
        }
        let (T, _) = self.refine(prev, cur, &pairs, T, 12);
        let pairs = self.guided_pairs(prev, cur, grid, &T, None, gate, true);
        if pairs.len() < 3 {
            return None;
        }
        Some(self.refine(prev, cur, &pairs, T, 12))
    }

    /// Pairs (i, j) whose residual at `T` (widened by the motion `prior` covariance, if any)
    /// passes `gate`; with `one_to_one` each previous and each current point is in at most one
    /// pair (the best first).
    #[allow(clippy::too_many_arguments)]
    fn guided_pairs(
        &self,
        prev: &Frame,
        cur: &Frame,
        grid: &AbGrid,
        T: &Isometry3<f64>,
        prior: Option<&Matrix6<f64>>,
        gate: f64,
        one_to_one: bool,
    ) -> Pairs {
        let max_cur_var = cur.pts.iter().fold([0.0f64; 2], |m, q| [m[0].max(q.Cs[(0, 0)]), m[1].max(q.Cs[(1, 1)])]);
        let R = T.rotation.to_rotation_matrix().into_inner();
        let mut pairs: Pairs = vec![];
        for (i, P) in prev.pts.iter().enumerate() {
            let p = R * P.p + T.translation.vector;
            if p.z < MIN_DEPTH_M {
                continue;
            }
            let Js = stereo_jacobian(&p);
            let JR = Js * R;
            let mut Sp = JR * P.C * JR.transpose();
            if let Some(prior) = prior {
                let mut Jx = Matrix3x6::zeros();
                Jx.fixed_view_mut::<3, 3>(0, 0).copy_from(&Js);
                Jx.fixed_view_mut::<3, 3>(0, 3).copy_from(&(-Js * p.cross_matrix()));
                Sp += Jx * prior * Jx.transpose();
            }
            let s = stereo_coords(&p);
            let k = gate.sqrt();
            let ra = k * (Sp[(0, 0)] + max_cur_var[0]).sqrt();
            let rb = k * (Sp[(1, 1)] + max_cur_var[1]).sqrt();
            grid.query(s[0], s[1], ra, rb, |j| {
                let Q = &cur.pts[j];
                let nu = s - Q.s;
                if let Some(m) = mahalanobis_within(&nu, &(Sp + Q.Cs), gate) {
                    pairs.push((i as u32, j as u32, m));
                }
            });
        }
        if one_to_one {
            pairs.sort_by(|a, b| a.2.total_cmp(&b.2));
            let mut used_p = vec![false; prev.pts.len()];
            let mut used_q = vec![false; cur.pts.len()];
            pairs.retain(|&(i, j, _)| {
                let ok = !used_p[i as usize] && !used_q[j as usize];
                if ok {
                    used_p[i as usize] = true;
                    used_q[j as usize] = true;
                }
                ok
            });
        }
        pairs
    }

    /// For each of the `sample` previous points (indices), the best current point within the
    /// inlier gate at `T` (widened by the motion's covariance `prior`, if any).
    fn matches(
        &self,
        prev: &Frame,
        cur: &Frame,
        grid: &AbGrid,
        T: &Isometry3<f64>,
        prior: Option<&Matrix6<f64>>,
        sample: &[u32],
    ) -> (Pairs, usize) {
        let R = T.rotation.to_rotation_matrix().into_inner();
        let gate = self.cfg.inlier_chi2;
        let k = gate.sqrt();
        let mut out = vec![];
        let mut in_gate = 0;
        for &i in sample {
            let P = &prev.pts[i as usize];
            let p = R * P.p + T.translation.vector;
            if p.z < MIN_DEPTH_M {
                continue;
            }
            let Js = stereo_jacobian(&p);
            let JR = Js * R;
            let mut Sp = JR * P.C * JR.transpose();
            if let Some(c) = prior {
                let mut Jx = Matrix3x6::zeros();
                Jx.fixed_view_mut::<3, 3>(0, 0).copy_from(&Js);
                Jx.fixed_view_mut::<3, 3>(0, 3).copy_from(&(-Js * p.cross_matrix()));
                Sp += Jx * c * Jx.transpose();
            }
            let s = stereo_coords(&p);
            let (ra, rb) = (k * (2.0 * Sp[(0, 0)]).sqrt(), k * (2.0 * Sp[(1, 1)]).sqrt());
            let mut best: Option<(u32, f64)> = None;
            grid.query(s[0], s[1], ra.max(1e-4), rb.max(1e-4), |j| {
                let Q = &cur.pts[j];
                if let Some(m) = mahalanobis_within(&(s - Q.s), &(Sp + Q.Cs), gate) {
                    in_gate += 1;
                    if best.is_none_or(|(_, b)| m < b) {
                        best = Some((j as u32, m));
                    }
                }
            });
            if let Some((j, m)) = best {
                out.push((i, j, m));
            }
        }
        (out, in_gate)
    }

    /// RANSAC over candidate pairs: the motion with most previous points in agreement, and the
    /// number of hypotheses scored.
    fn ransac(&mut self, prev: &Frame, cur: &Frame, pairs: &Pairs) -> Option<(Isometry3<f64>, Matrix6<f64>, usize)> {
        if pairs.len() < 3 {
            return None;
        }
        let gate = self.cfg.inlier_chi2;
        let n_prev_with_pairs = {
            let mut seen = vec![false; prev.pts.len()];
            pairs.iter().filter(|(i, _, _)| !std::mem::replace(&mut seen[*i as usize], true)).count()
        };
        let mut best: Option<(usize, Isometry3<f64>, Matrix6<f64>)> = None;
        let mut iterations = self.cfg.ransac_iterations;
        let mut k = 0;
        let mut hyps = 0;
        let mut agree = vec![false; prev.pts.len()];
        while k < iterations {
            k += 1;
            let mut idx = [0usize; 3];
            let mut ok = false;
            for _ in 0..20 {
                for v in &mut idx {
                    *v = self.rng.random_range(0..pairs.len());
                }
                let [a, b, c] = idx.map(|x| pairs[x]);
                if a.0 == b.0 || a.0 == c.0 || b.0 == c.0 || a.1 == b.1 || a.1 == c.1 || b.1 == c.1 {
                    continue;
                }
                if rigid_pair_ok(prev, cur, (a.0, a.1), (b.0, b.1), PI)
                    && rigid_pair_ok(prev, cur, (a.0, a.1), (c.0, c.1), PI)
                    && rigid_pair_ok(prev, cur, (b.0, b.1), (c.0, c.1), PI)
                {
                    ok = true;
                    break;
                }
            }
            if !ok {
                continue;
            }
            let src: Vec<Vector3<f64>> = idx.iter().map(|&x| prev.pts[pairs[x].0 as usize].p).collect();
            let dst: Vec<Vector3<f64>> = idx.iter().map(|&x| cur.pts[pairs[x].1 as usize].p).collect();
            let Some(T) = geometry::align_rigid(&src, &dst, &[1.0; 3]) else { continue };
            let Some(cov) = hypothesis_covariance(prev, cur, &idx.map(|x| (pairs[x].0, pairs[x].1)), &T) else {
                continue;
            };
            if !plausible(&cov) {
                continue;
            }
            hyps += 1;
            // Pairs in agreement allowing for the hypothesis's own uncertainty (three noisy
            // points fix a motion only roughly).
            let wide = agreeing(prev, cur, pairs, &T, Some(&cov), gate, &mut agree);
            if wide.len() < 6 || best.as_ref().is_some_and(|(b, _, _)| wide.len() * 2 < *b) {
                continue;
            }
            // Locally optimised: refined on the pairs it agrees with, scored on the tight gate.
            let (T, _) = self.refine(prev, cur, &wide, T, 6);
            let tight = agreeing(prev, cur, pairs, &T, None, gate, &mut agree);
            let Some((cov, _)) = gn_covariance(prev, cur, &T, &tight).filter(|_| tight.len() >= 6) else { continue };
            let n = tight.len();
            if best.as_ref().is_none_or(|(b, _, _)| n > *b) {
                best = Some((n, T, cov));
                let w = (n as f64 / n_prev_with_pairs.max(1) as f64).clamp(1e-3, 1.0 - 1e-9);
                let needed = ((1.0f64 - 0.999).ln() / (1.0 - w.powi(3)).ln()).ceil();
                if needed.is_finite() {
                    iterations = iterations.min(needed.max(8.0) as usize);
                }
            }
        }
        best.filter(|(n, _, _)| *n >= 3).map(|(_, T, c)| (T, c, hyps))
    }

    /// Gauss-Newton with a Huber kernel over the pairs, from `T`; returns the motion and the
    /// pairs within the inlier gate at it.
    fn refine(
        &self,
        prev: &Frame,
        cur: &Frame,
        pairs: &Pairs,
        mut T: Isometry3<f64>,
        iterations: usize,
    ) -> (Isometry3<f64>, Pairs) {
        let k = self.cfg.huber_sigma;
        // Pairs far outside the gate get no say (a redescending cut after the first iterations).
        let cut = |it: usize| if it < 2 { f64::INFINITY } else { 4.0 * self.cfg.inlier_chi2 };
        for it in 0..iterations {
            let mut H = Matrix6::zeros();
            let mut g = Vector6::zeros();
            let mut used = 0;
            for &(i, j, _) in pairs {
                let (nu, S, Jx) = residual(&T, &prev.pts[i as usize], &cur.pts[j as usize]);
                let Some(c) = Chol3::new(&S) else { continue };
                let Sinv_nu = c.solve(&nu);
                let m = nu.dot(&Sinv_nu);
                if !m.is_finite() || m > cut(it) {
                    continue;
                }
                let r = m.sqrt();
                let w = if r <= k { 1.0 } else { k / r };
                let Sinv = c.inverse();
                H += Jx.transpose() * Sinv * Jx * w;
                g += Jx.transpose() * Sinv_nu * w;
                used += 1;
            }
            if used < 3 {
                break;
            }
            let Some(cH) = Cholesky::new(H) else { break };
            let dx = -cH.solve(&g);
            if !dx.iter().all(|v| v.is_finite()) {
                break;
            }
            T = left_update(&T, &dx);
            if dx.fixed_rows::<3>(0).norm() < 1e-6 && dx.fixed_rows::<3>(3).norm() < 1e-8 {
                break;
            }
        }
        let gate = self.cfg.inlier_chi2;
        let inliers: Pairs = pairs
            .iter()
            .filter_map(|&(i, j, _)| {
                let (nu, S, _) = residual(&T, &prev.pts[i as usize], &cur.pts[j as usize]);
                mahalanobis(&nu, &S).filter(|m| *m <= gate).map(|m| (i, j, m))
            })
            .collect();
        (T, inliers)
    }

    /// Refines a rough motion on the `seeds` it agrees with, twice (each time matching within the
    /// motion's current uncertainty); `None` when fewer than 6 seeds agree. Also returns the
    /// number of (seed, current point) pairs inside the gate of the first matching, at the rough
    /// motion.
    fn local_optimum(
        &self,
        prev: &Frame,
        cur: &Frame,
        grid: &AbGrid,
        T: Isometry3<f64>,
        cov: Matrix6<f64>,
        seeds: &[u32],
    ) -> (Option<Motion>, usize) {
        let mut first_in_gate = None;
        let mut optimum = || {
            let (mut T, mut cov) = (T, cov);
            for _ in 0..2 {
                let (m, in_gate) = self.matches(prev, cur, grid, &T, Some(&cov), seeds);
                first_in_gate.get_or_insert(in_gate);
                if m.len() < 6 {
                    return None;
                }
                let (t, inl) = self.refine(prev, cur, &m, T, 6);
                if inl.len() < 6 {
                    return None;
                }
                cov = gn_covariance(prev, cur, &t, &inl)?.0;
                T = t;
            }
            Some((T, cov))
        };
        let optimum = optimum();
        (optimum, first_in_gate.unwrap_or(0))
    }

    /// The prior-free search: (best motion, hypotheses scored, candidates per seed point).
    fn search(&mut self, prev: &Frame, cur: &Frame, grid: &AbGrid) -> SearchResult {
        let cfg = &self.cfg;
        // Seeds: the best-triangulated quarter of the previous points (at least 24), within
        // `search_max_sigma_m`: precise points make the rigidity test selective.
        let mut by_sigma: Vec<u32> = (0..prev.pts.len() as u32).collect();
        by_sigma.sort_by(|a, b| prev.pts[*a as usize].sigma_m.total_cmp(&prev.pts[*b as usize].sigma_m));
        let n_seeds = (prev.pts.len() / 4).max(24).min(prev.pts.len());
        let smax = cfg.search_max_sigma_m.min(prev.pts[by_sigma[n_seeds - 1] as usize].sigma_m);
        let seeds: Vec<u32> = by_sigma.into_iter().filter(|&i| prev.pts[i as usize].sigma_m <= smax).collect();
        // A current point may be farther (less precise) than its previous self.
        let cur_ok: Vec<u32> =
            (0..cur.pts.len() as u32).filter(|&j| cur.pts[j as usize].sigma_m <= 2.0 * smax).collect();
        if seeds.len() < 3 || cur_ok.len() < 3 {
            return (None, 0, 0.0);
        }
        // 3-D grid of the current points a seed may match.
        let cell = 2.0;
        let key =
            |p: &Vector3<f64>| [(p.x / cell).floor() as i32, (p.y / cell).floor() as i32, (p.z / cell).floor() as i32];
        let mut cells: HashMap<[i32; 3], Vec<u32>> = HashMap::new();
        for &j in &cur_ok {
            cells.entry(key(&cur.pts[j as usize].p)).or_default().push(j);
        }
        let max_rot = cfg.max_rotation_deg.to_radians();
        let max_t = cfg.max_translation_m;
        let mut cand_cache: HashMap<u32, Vec<u32>> = HashMap::new();
        let mut candidates = |i: u32| -> Vec<u32> {
            cand_cache
                .entry(i)
                .or_insert_with(|| {
                    let P = &prev.pts[i as usize];
                    let reach = max_t + 2.0 * (max_rot / 2.0).sin() * P.p.norm();
                    let n = ((reach + 3.0 * 2.0 * smax) / cell).ceil() as i32;
                    let k0 = key(&P.p);
                    let mut out = vec![];
                    for dx in -n..=n {
                        for dy in -n..=n {
                            for dz in -n..=n {
                                if let Some(v) = cells.get(&[k0[0] + dx, k0[1] + dy, k0[2] + dz]) {
                                    for &j in v {
                                        let Q = &cur.pts[j as usize];
                                        if (Q.p - P.p).norm() <= reach + 3.0 * (P.sigma_m + Q.sigma_m) {
                                            out.push(j);
                                        }
                                    }
                                }
                            }
                        }
                    }
                    out
                })
                .clone()
        };
        // Points the hypotheses are scored on: a random subset, then all of them for the best.
        let mut all: Vec<u32> = (0..prev.pts.len() as u32).collect();
        shuffle(&mut all, &mut self.rng);
        let quick: Vec<u32> = all.iter().copied().take(40).collect();
        let full: Vec<u32> = all.iter().copied().take(400).collect();
        let confident = self.needed(prev, cur).max((0.5 * full.len().min(cur.pts.len()) as f64) as usize);
        let mut best: Option<(usize, Isometry3<f64>, Matrix6<f64>)> = None;
        let mut hyps = 0;
        let mut cand_sum = 0usize;
        let mut cand_n = 0usize;
        // Trials until one motion is confidently supported; a second round when the first found
        // none with enough support (a rare unlucky draw should not cost a frame).
        // The support a motion needs on the `full` sample, with a margin.
        let supported = (1.5 * self.needed(prev, cur) as f64 * full.len() as f64 / prev.len().max(1) as f64) as usize;
        for trial in 0..2 * self.cfg.search_trials {
            if trial == self.cfg.search_trials && best.as_ref().is_some_and(|(b, _, _)| *b >= supported) {
                break;
            }
            // A well-spread base triple of seeds, one that fixes a motion precisely enough for
            // its local optimisation to start inside the right basin (a motion from three
            // points is as good as their spread against their noise).
            let mut tri = None;
            for _ in 0..60 {
                let t = [0, 1, 2].map(|_| seeds[self.rng.random_range(0..seeds.len())]);
                let [a, b, c] = t.map(|i| prev.pts[i as usize].p);
                let (ab, ac) = (b - a, c - a);
                let min_side = ab.norm().min(ac.norm()).min((c - b).norm());
                if min_side < 1.0 || ab.cross(&ac).norm() / ab.norm().max(ac.norm()) < 0.5 {
                    continue;
                }
                let conditioned = hypothesis_covariance(prev, prev, &t.map(|i| (i, i)), &Isometry3::identity())
                    .is_some_and(|c| c.fixed_view::<3, 3>(3, 3).trace() <= 3.0 * SEED_ROTATION_SIGMA_RAD.powi(2));
                if conditioned {
                    tri = Some(t);
                    break;
                }
            }
            let Some(tri) = tri else { continue };
            let mut c = tri.map(&mut candidates);
            cand_sum += c.iter().map(Vec::len).sum::<usize>();
            cand_n += 3;
            // Pairs for the first two seeds that pass the rigidity test, in random order (the
            // cap on triples must not favour any candidate).
            let mut pairs01 = vec![];
            for &q0 in &c[0] {
                for &q1 in &c[1] {
                    if q1 != q0 && rigid_pair_ok(prev, cur, (tri[0], q0), (tri[1], q1), max_rot) {
                        pairs01.push((q0, q1));
                    }
                }
            }
            shuffle_pairs(&mut pairs01, &mut self.rng);
            shuffle(&mut c[2], &mut self.rng);
            let mut triples = 0;
            'outer: for &(q0, q1) in &pairs01 {
                for &q2 in &c[2] {
                    if q2 == q0
                        || q2 == q1
                        || !rigid_pair_ok(prev, cur, (tri[0], q0), (tri[2], q2), max_rot)
                        || !rigid_pair_ok(prev, cur, (tri[1], q1), (tri[2], q2), max_rot)
                    {
                        continue;
                    }
                    triples += 1;
                    if triples > self.cfg.search_max_triples {
                        break 'outer;
                    }
                    let src = tri.map(|i| prev.pts[i as usize].p);
                    let dst = [q0, q1, q2].map(|j| cur.pts[j as usize].p);
                    let Some(T) = geometry::align_rigid(&src, &dst, &[1.0; 3]) else { continue };
                    let Some(cov) = hypothesis_covariance(prev, cur, &[(tri[0], q0), (tri[1], q1), (tri[2], q2)], &T)
                    else {
                        continue;
                    };
                    // Within the search bounds (T is cur_from_prev; the camera moved by T⁻¹).
                    if T.rotation.angle() > max_rot * 1.2 || T.translation.vector.norm() > max_t * 1.5 + 1.0 {
                        continue;
                    }
                    if !plausible(&cov) {
                        continue;
                    }
                    hyps += 1;
                    let q = self.matches(prev, cur, grid, &T, Some(&cov), &quick).0.len();
                    if q * 4 < quick.len() {
                        continue;
                    }
                    // Local optimisation on the seeds: three points fix the motion only roughly;
                    // refined on the seeds it agrees with, it is precise enough to be scored
                    // within its own (now small) uncertainty.
                    let Some((T, cov)) = self.local_optimum(prev, cur, grid, T, cov, &seeds).0 else { continue };
                    let n = self.matches(prev, cur, grid, &T, None, &full).0.len();
                    if best.as_ref().is_none_or(|(b, _, _)| n > *b) {
                        best = Some((n, T, cov));
                    }
                }
            }
            if best.as_ref().is_some_and(|(b, _, _)| *b >= confident) {
                break;
            }
        }
        let cands = cand_sum as f64 / cand_n.max(1) as f64;
        (best.map(|(_, T, c)| (T, c)), hyps, cands)
    }

    #[allow(clippy::too_many_arguments)]
    fn finish(
        &self,
        prev: &Frame,
        cur: &Frame,
        T: Isometry3<f64>,
        inliers: &Pairs,
        method: Method,
        candidates_per_point: f64,
        hypotheses: usize,
    ) -> Result<Registration, RegistrationError> {
        let Some((cov, chi2_per_dof)) = gn_covariance(prev, cur, &T, inliers) else {
            return Err(RegistrationError::Degenerate { sigma_m: f64::INFINITY, sigma_deg: f64::INFINITY });
        };
        let sigma_m = cov.fixed_view::<3, 3>(0, 0).symmetric_eigenvalues().max().max(0.0).sqrt();
        let sigma_rad = cov.fixed_view::<3, 3>(3, 3).symmetric_eigenvalues().max().max(0.0).sqrt();
        if !(sigma_m <= 0.5 && sigma_rad <= 5f64.to_radians()) {
            return Err(RegistrationError::Degenerate { sigma_m, sigma_deg: sigma_rad.to_degrees() });
        }
        Ok(Registration {
            prev_from_cur: T.inverse(),
            covariance: cov,
            inliers: inliers.len(),
            points: (prev.len(), cur.len()),
            candidates_per_point,
            method,
            hypotheses,
            chi2_per_dof,
            matches: inliers.iter().map(|&(i, j, _)| (prev.pts[i as usize].index, cur.pts[j as usize].index)).collect(),
        })
    }
}

#[cfg(test)]
mod tests;
