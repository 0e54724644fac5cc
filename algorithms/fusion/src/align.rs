//! The local-to-global rigid transform of a segment (EQUATIONS §6.3) from pairs (local path point,
//! global buoy fix), with its covariance and degeneracy detection.
//!
//! [`align`]: a scalar-weighted SVD (Horn 1987 / Umeyama 1991, [`geometry::align_rigid`]) with weights
//! 1/tr(Σ_local + Σ_global) (the trace is rotation invariant, so no second pass is needed for them)
//! gives the first estimate; Gauss–Newton on the full anisotropic problem
//!   min Σ_i r_iᵀ·S_i⁻¹·r_i,  r_i = g_i − (R·l_i + t),  S_i = R·Σ_l,i·Rᵀ + Σ_g,i
//! (S_i re-evaluated at each iterate) refines it. The 6×6 covariance is the inverse of the Gauss–Newton
//! normal matrix H = Σ J_iᵀ·S_i⁻¹·J_i at the solution (first order, the pair covariances taken as
//! given, not rescaled by the residuals).
//!
//! Convention of [`Alignment::covariance`]: the state is (δt, φ) ∈ ℝ⁶ (translation first, m and rad),
//! with the true transform x ↦ Exp(φ)·R̂·x + t̂ + δt, i.e. the rotation error is a small rotation applied
//! on the GLOBAL side, R = Exp(φ)·R̂, and the translation error is additive in the global frame.
//! The residual Jacobian is J_i = [−I, [R̂·l_i]×].

use geometry::align_rigid;
use nalgebra::{
    Cholesky, Isometry3, Matrix3, Matrix3x6, Matrix6, Rotation3, Translation3, UnitQuaternion, Vector3, Vector6,
};
use serde::{Deserialize, Serialize};

use crate::FusionError;
use crate::fuse::check_covariance;
use validation::{Issues, Validate};

/// Floor added to every pair covariance S_i, m² (σ = 1 µm), so exact (zero-covariance) pairs stay
/// solvable; negligible against any real sensor.
pub const COVARIANCE_FLOOR_M2: f64 = 1e-12;

/// One pair of the alignment: a point of the segment's local path and the global estimate of the
/// same point (a buoy fix at the same time).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Correspondence {
    /// The point in the local (segment) frame, m.
    pub local_m: Vector3<f64>,
    /// Its covariance in the local frame, m².
    pub local_cov_m2: Matrix3<f64>,
    /// The point in the global frame, m.
    pub global_m: Vector3<f64>,
    /// Its covariance in the global frame, m².
    pub global_cov_m2: Matrix3<f64>,
}

/// Settings of [`align`] (keys relative to the config table).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct AlignConfig {
    /// Fewest pairs to estimate a transform (at least 3).
    pub min_pairs: usize,
    /// Second to first singular value of the centred local points below which they count as
    /// collinear (the rotation about their line is unobservable).
    pub min_spread_ratio: f64,
    /// Largest extent of the local points (along their principal axis), m, below which the rotation
    /// is not estimated.
    pub min_extent_m: f64,
}

impl Default for AlignConfig {
    fn default() -> Self {
        Self { min_pairs: 3, min_spread_ratio: 0.05, min_extent_m: 1.0 }
    }
}

impl Validate for AlignConfig {
    fn validate(&self, issues: &mut Issues) {
        if self.min_pairs < 3 {
            issues.push("min_pairs", "must be >= 3");
        }
        if !(self.min_spread_ratio.is_finite() && (0.0..1.0).contains(&self.min_spread_ratio)) {
            issues.push("min_spread_ratio", "must be in [0, 1)");
        }
        if !(self.min_extent_m.is_finite() && self.min_extent_m >= 0.0) {
            issues.push("min_extent_m", "must be >= 0");
        }
    }
}

/// A segment's local-to-global transform with its uncertainty.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Alignment {
    /// The transform: global = R·local + t.
    pub global_from_local: Isometry3<f64>,
    /// 6×6 covariance of (translation error δt in m, rotation error φ in rad), with the rotation
    /// error a small rotation applied on the global side: R = Exp(φ)·R̂, t = t̂ + δt (module docs).
    pub covariance: Matrix6<f64>,
    /// Number of pairs used.
    pub pairs: usize,
    /// RMS of the residuals ‖g_i − (R·l_i + t)‖, m.
    pub rms_residual_m: f64,
    /// Spread ratio of the local points (see [`spread`]).
    pub spread_ratio: f64,
}

impl Alignment {
    /// An alignment from a known transform and covariance (no pairs): e.g. an exactly known frame.
    pub fn from_transform(global_from_local: Isometry3<f64>, covariance: Matrix6<f64>) -> Self {
        Self { global_from_local, covariance, pairs: 0, rms_residual_m: 0.0, spread_ratio: 0.0 }
    }

    /// A local point with covariance mapped to global: position R·l + t and covariance
    /// R·Σ·Rᵀ + J·C·Jᵀ with J = [I, −[R·l]×] (first order; the point's error taken as independent of
    /// the transform's).
    pub fn map_point(&self, local_m: &Vector3<f64>, local_cov_m2: &Matrix3<f64>) -> (Vector3<f64>, Matrix3<f64>) {
        let r = self.global_from_local.rotation.to_rotation_matrix();
        let q = r * local_m;
        let global = q + self.global_from_local.translation.vector;
        let mut j = Matrix3x6::zeros();
        j.fixed_view_mut::<3, 3>(0, 0).copy_from(&Matrix3::identity());
        j.fixed_view_mut::<3, 3>(0, 3).copy_from(&(-q.cross_matrix()));
        let cov = r.matrix() * local_cov_m2 * r.matrix().transpose() + j * self.covariance * j.transpose();
        (global, (cov + cov.transpose()) * 0.5)
    }
}

/// The spread ratio of a point set (second/first singular value of the centred points, in [0, 1];
/// 0 for collinear or coincident points) and its extent (range of the points along their principal
/// axis, m). (0, 0) for an empty set; (NaN, NaN) when a point is not finite.
pub fn spread(points: &[Vector3<f64>]) -> (f64, f64) {
    if points.is_empty() {
        return (0.0, 0.0);
    }
    if !points.iter().all(|p| p.iter().all(|v| v.is_finite())) {
        return (f64::NAN, f64::NAN);
    }
    let mean: Vector3<f64> = points.iter().sum::<Vector3<f64>>() / points.len() as f64;
    let scatter: Matrix3<f64> = points.iter().map(|p| (p - mean) * (p - mean).transpose()).sum();
    if scatter.amax() == 0.0 {
        return (0.0, 0.0);
    }
    let eig = scatter.symmetric_eigen();
    let mut order = [0usize, 1, 2];
    order.sort_by(|&a, &b| eig.eigenvalues[b].total_cmp(&eig.eigenvalues[a]));
    let l1 = eig.eigenvalues[order[0]].max(0.0);
    let l2 = eig.eigenvalues[order[1]].max(0.0);
    let ratio = if l1 > 0.0 { (l2 / l1).sqrt().min(1.0) } else { 0.0 };
    let axis = eig.eigenvectors.column(order[0]).into_owned();
    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
    for p in points {
        let s = axis.dot(&(p - mean));
        lo = lo.min(s);
        hi = hi.max(s);
    }
    (ratio, hi - lo)
}

/// Pairs with finite values and symmetrised PSD covariances.
fn checked(pairs: &[Correspondence]) -> Result<Vec<Correspondence>, FusionError> {
    pairs
        .iter()
        .map(|c| {
            if !c.local_m.iter().all(|v| v.is_finite()) {
                return Err(FusionError::NonFinite("local point"));
            }
            if !c.global_m.iter().all(|v| v.is_finite()) {
                return Err(FusionError::NonFinite("global point"));
            }
            Ok(Correspondence {
                local_m: c.local_m,
                local_cov_m2: check_covariance("local covariance", &c.local_cov_m2)?,
                global_m: c.global_m,
                global_cov_m2: check_covariance("global covariance", &c.global_cov_m2)?,
            })
        })
        .collect()
}

/// S_i⁻¹ = (R·Σ_l·Rᵀ + Σ_g + floor)⁻¹.
fn pair_information(r: &Matrix3<f64>, c: &Correspondence) -> Result<Matrix3<f64>, FusionError> {
    let s = r * c.local_cov_m2 * r.transpose() + c.global_cov_m2 + Matrix3::identity() * COVARIANCE_FLOOR_M2;
    Cholesky::new(s).map(|ch| ch.inverse()).ok_or(FusionError::NotPositiveDefinite("pair covariance"))
}

/// Gauss–Newton normal matrix H and gradient Jᵀ·W·r of the 6-DOF problem at (R, t), with Σ r²
/// (unweighted) for the RMS.
fn normal_equations(
    pairs: &[Correspondence],
    r: &Matrix3<f64>,
    t: &Vector3<f64>,
) -> Result<(Matrix6<f64>, Vector6<f64>, f64), FusionError> {
    let mut h = Matrix6::zeros();
    let mut g = Vector6::zeros();
    let mut sum_sq = 0.0;
    for c in pairs {
        let w = pair_information(r, c)?;
        let q = r * c.local_m;
        let res = c.global_m - (q + t);
        sum_sq += res.norm_squared();
        let mut j = Matrix3x6::zeros();
        j.fixed_view_mut::<3, 3>(0, 0).copy_from(&(-Matrix3::identity()));
        j.fixed_view_mut::<3, 3>(0, 3).copy_from(&q.cross_matrix());
        let jt_w = j.transpose() * w;
        h += jt_w * j;
        g += jt_w * res;
    }
    Ok((h, g, sum_sq))
}

/// Weighted SVD (Horn/Umeyama) with weights from the pair covariances, refined by Gauss–Newton on
/// the anisotropic weighted least squares, with the first-order 6×6 covariance (module docs).
///
/// Errors: an invalid `cfg` ([`FusionError::InvalidArgument`]); fewer than `cfg.min_pairs` pairs
/// ([`FusionError::TooFew`]); local points spanning less than `cfg.min_extent_m`
/// ([`FusionError::TooSmall`]) or with a spread ratio below `cfg.min_spread_ratio`
/// ([`FusionError::Collinear`]) — both resolvable with [`align_with_heading`]
/// ([`FusionError::is_degenerate_geometry`]); non-finite values or non-PSD covariances.
pub fn align(pairs: &[Correspondence], cfg: &AlignConfig) -> Result<Alignment, FusionError> {
    if !cfg.issues().is_empty() {
        return Err(FusionError::InvalidArgument("align config (see AlignConfig::validate)"));
    }
    let need = cfg.min_pairs.max(3);
    if pairs.len() < need {
        return Err(FusionError::TooFew { what: "correspondences", got: pairs.len(), need });
    }
    let pairs = checked(pairs)?;
    let local: Vec<Vector3<f64>> = pairs.iter().map(|c| c.local_m).collect();
    let global: Vec<Vector3<f64>> = pairs.iter().map(|c| c.global_m).collect();
    let (ratio, extent_m) = spread(&local);
    if extent_m < cfg.min_extent_m {
        return Err(FusionError::TooSmall { extent_m, limit_m: cfg.min_extent_m });
    }
    if ratio < cfg.min_spread_ratio {
        return Err(FusionError::Collinear { ratio, limit: cfg.min_spread_ratio });
    }
    let weights: Vec<f64> = pairs
        .iter()
        .map(|c| 1.0 / (c.local_cov_m2.trace() + c.global_cov_m2.trace() + 3.0 * COVARIANCE_FLOOR_M2))
        .collect();
    let first =
        align_rigid(&local, &global, &weights).ok_or(FusionError::Collinear { ratio, limit: cfg.min_spread_ratio })?;
    let mut rot = first.rotation.to_rotation_matrix();
    let mut t = first.translation.vector;
    for _ in 0..50 {
        let (h, g, _) = normal_equations(&pairs, rot.matrix(), &t)?;
        let chol = Cholesky::new(h).ok_or(FusionError::Singular("alignment normal matrix"))?;
        let delta = -chol.solve(&g);
        if !delta.iter().all(|v| v.is_finite()) {
            return Err(FusionError::Singular("alignment update"));
        }
        t += delta.fixed_rows::<3>(0);
        let phi: Vector3<f64> = delta.fixed_rows::<3>(3).into_owned();
        rot = Rotation3::new(phi) * rot;
        if phi.norm() < 1e-12 && delta.fixed_rows::<3>(0).norm() < 1e-10 * (1.0 + t.norm()) {
            break;
        }
    }
    let (h, _, sum_sq) = normal_equations(&pairs, rot.matrix(), &t)?;
    let covariance = Cholesky::new(h).ok_or(FusionError::Singular("alignment normal matrix"))?.inverse();
    Ok(Alignment {
        global_from_local: Isometry3::from_parts(Translation3::from(t), UnitQuaternion::from_rotation_matrix(&rot)),
        covariance: (covariance + covariance.transpose()) * 0.5,
        pairs: pairs.len(),
        rms_residual_m: (sum_sq / pairs.len() as f64).sqrt(),
        spread_ratio: ratio,
    })
}

/// χ²₆ at 0.999: a prior transform whose difference from the estimate with it exceeds this (in
/// the prior's own covariance) disagrees with the fixes; [`align_with_prior`] reports it.
pub const PRIOR_GATE_CHI2_6: f64 = 22.458;

/// The transform as a maximum a posteriori estimate (EQUATIONS §6.3a): a Gaussian prior on it (`prior`: its mean and
/// 6×6 covariance, [`Alignment::covariance`]'s convention) and the pairs, any number of them,
/// none included. Gauss–Newton from the prior on
///   Σ_i r_iᵀ·S_i⁻¹·r_i + eᵀ·C⁻¹·e,  e = (t − t_p, Log(R·R_pᵀ)),
/// the pair terms as in [`align`]; the covariance is (H + C⁻¹)⁻¹ at the solution. The prior makes
/// collinear, small or few pairs well posed: what they do not determine it keeps.
///
/// Returns the alignment and the prior's χ² at the solution (eᵀ·C⁻¹·e: above
/// [`PRIOR_GATE_CHI2_6`] the fixes disagree with the prior). Errors: a prior covariance that is
/// not positive definite, non-finite values.
pub fn align_with_prior(pairs: &[Correspondence], prior: &Alignment) -> Result<(Alignment, f64), FusionError> {
    let prior_cov = (prior.covariance + prior.covariance.transpose()) * 0.5;
    let prior_info = Cholesky::new(prior_cov).ok_or(FusionError::NotPositiveDefinite("prior covariance"))?.inverse();
    let pairs = checked(pairs)?;
    let r_p = prior.global_from_local.rotation.to_rotation_matrix();
    let t_p = prior.global_from_local.translation.vector;
    let prior_residual = |rot: &Rotation3<f64>, t: &Vector3<f64>| -> Vector6<f64> {
        let phi = (rot * r_p.inverse()).scaled_axis();
        let dt = t - t_p;
        Vector6::new(dt.x, dt.y, dt.z, phi.x, phi.y, phi.z)
    };
    let (mut rot, mut t) = (r_p, t_p);
    for _ in 0..50 {
        let (h, g, _) = normal_equations(&pairs, rot.matrix(), &t)?;
        let e = prior_residual(&rot, &t);
        let chol = Cholesky::new(h + prior_info).ok_or(FusionError::Singular("alignment normal matrix"))?;
        let delta = -chol.solve(&(g + prior_info * e));
        if !delta.iter().all(|v| v.is_finite()) {
            return Err(FusionError::Singular("alignment update"));
        }
        t += delta.fixed_rows::<3>(0);
        let phi: Vector3<f64> = delta.fixed_rows::<3>(3).into_owned();
        rot = Rotation3::new(phi) * rot;
        if phi.norm() < 1e-12 && delta.fixed_rows::<3>(0).norm() < 1e-10 * (1.0 + t.norm()) {
            break;
        }
    }
    let (h, _, sum_sq) = normal_equations(&pairs, rot.matrix(), &t)?;
    let covariance = Cholesky::new(h + prior_info).ok_or(FusionError::Singular("alignment normal matrix"))?.inverse();
    let e = prior_residual(&rot, &t);
    let chi2 = e.dot(&(prior_info * e));
    let local: Vec<Vector3<f64>> = pairs.iter().map(|c| c.local_m).collect();
    Ok((
        Alignment {
            global_from_local: Isometry3::from_parts(Translation3::from(t), UnitQuaternion::from_rotation_matrix(&rot)),
            covariance: (covariance + covariance.transpose()) * 0.5,
            pairs: pairs.len(),
            rms_residual_m: if pairs.is_empty() { 0.0 } else { (sum_sq / pairs.len() as f64).sqrt() },
            spread_ratio: spread(&local).0,
        },
        chi2,
    ))
}

/// (EQUATIONS §6.3a) `previous` (a segment's transform) composed with `local_from_body`, a pose in that segment's
/// frame with its 6×6 covariance over (position, body-frame rotation error): the transform of a
/// local frame whose origin is that body pose (a new local map started there), with the
/// covariance of both (first order; [`Alignment::covariance`]'s convention):
/// δt = δt_prev − [R̂_prev·p]×·φ_prev + R̂_prev·δp and φ = φ_prev + R̂·ψ.
pub fn compose_prior(previous: &Alignment, local_from_body: &Isometry3<f64>, local_cov: &Matrix6<f64>) -> Alignment {
    let r_prev = previous.global_from_local.rotation.to_rotation_matrix().into_inner();
    let q = r_prev * local_from_body.translation.vector;
    let composed = previous.global_from_local * local_from_body;
    let r_new = composed.rotation.to_rotation_matrix().into_inner();
    let mut j_prev = Matrix6::identity();
    j_prev.fixed_view_mut::<3, 3>(0, 3).copy_from(&(-q.cross_matrix()));
    let mut j_local = Matrix6::zeros();
    j_local.fixed_view_mut::<3, 3>(0, 0).copy_from(&r_prev);
    j_local.fixed_view_mut::<3, 3>(3, 3).copy_from(&r_new);
    let cov = j_prev * previous.covariance * j_prev.transpose() + j_local * local_cov * j_local.transpose();
    Alignment::from_transform(composed, (cov + cov.transpose()) * 0.5)
}

/// Collinear (or too small) geometry resolved with a heading sensor. Assumes the LOCAL FRAME IS
/// LEVEL (its z axis is the global z axis, as for a segment whose local frame is gravity-aligned), so
/// the rotation is R = Rz(`yaw_rad`), the local frame's yaw in the global frame (the caller derives it
/// from a compass: compass heading − the vehicle's yaw in the local frame), with σ `yaw_sigma_rad`.
/// The translation is the information-weighted mean t = (Σ W_i)⁻¹·Σ W_i·(g_i − R·l_i),
/// W_i = (R·Σ_l,i·Rᵀ + Σ_g,i)⁻¹; one pair suffices.
///
/// Covariance (same convention as [`Alignment::covariance`]): φ = (0, 0, δψ) with var(δψ) = σ²
/// (roll and pitch taken as exact, variance 0); δt has (Σ W_i)⁻¹ plus the yaw error carried through
/// the mean, ∂t/∂φ = (Σ W_i)⁻¹·Σ W_i·[R·l_i]×, and its cross-covariance with δψ.
pub fn align_with_heading(
    pairs: &[Correspondence],
    yaw_rad: f64,
    yaw_sigma_rad: f64,
) -> Result<Alignment, FusionError> {
    if !yaw_rad.is_finite() {
        return Err(FusionError::NonFinite("yaw"));
    }
    if !(yaw_sigma_rad.is_finite() && yaw_sigma_rad >= 0.0) {
        return Err(FusionError::InvalidArgument("yaw_sigma_rad must be finite and >= 0"));
    }
    if pairs.is_empty() {
        return Err(FusionError::TooFew { what: "correspondences", got: 0, need: 1 });
    }
    let pairs = checked(pairs)?;
    let rot = Rotation3::from_axis_angle(&Vector3::z_axis(), yaw_rad);
    let r = rot.matrix();
    let mut info_sum = Matrix3::zeros();
    let mut info_t = Vector3::zeros();
    let mut info_cross = Matrix3::zeros();
    for c in &pairs {
        let w = pair_information(r, c)?;
        let q = r * c.local_m;
        info_sum += w;
        info_t += w * (c.global_m - q);
        info_cross += w * q.cross_matrix();
    }
    let chol = Cholesky::new(info_sum).ok_or(FusionError::Singular("heading alignment information"))?;
    let t = chol.solve(&info_t);
    let cov_t = chol.inverse();
    let dt_dphi = chol.solve(&info_cross);
    let j_yaw = dt_dphi.column(2).into_owned();
    let var_yaw = yaw_sigma_rad * yaw_sigma_rad;
    let mut covariance = Matrix6::zeros();
    covariance.fixed_view_mut::<3, 3>(0, 0).copy_from(&(cov_t + j_yaw * j_yaw.transpose() * var_yaw));
    covariance.fixed_view_mut::<3, 1>(0, 5).copy_from(&(j_yaw * var_yaw));
    covariance.fixed_view_mut::<1, 3>(5, 0).copy_from(&(j_yaw.transpose() * var_yaw));
    covariance[(5, 5)] = var_yaw;
    let sum_sq: f64 = pairs.iter().map(|c| (c.global_m - (r * c.local_m + t)).norm_squared()).sum();
    let local: Vec<Vector3<f64>> = pairs.iter().map(|c| c.local_m).collect();
    Ok(Alignment {
        global_from_local: Isometry3::from_parts(Translation3::from(t), UnitQuaternion::from_rotation_matrix(&rot)),
        covariance: (covariance + covariance.transpose()) * 0.5,
        pairs: pairs.len(),
        rms_residual_m: (sum_sq / pairs.len() as f64).sqrt(),
        spread_ratio: spread(&local).0,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;
    use rand::SeedableRng;
    use rand_distr::{Distribution, Normal, Uniform};
    use rand_xoshiro::Xoshiro256PlusPlus;

    fn iso(x: f64, y: f64, z: f64, roll: f64, pitch: f64, yaw: f64) -> Isometry3<f64> {
        Isometry3::from_parts(Translation3::new(x, y, z), UnitQuaternion::from_euler_angles(roll, pitch, yaw))
    }

    /// A zero-mean Gaussian sample with covariance `p` (Cholesky factor).
    fn gauss(rng: &mut Xoshiro256PlusPlus, p: &Matrix3<f64>) -> Vector3<f64> {
        let n = Normal::new(0.0, 1.0).unwrap();
        let l = Cholesky::new(*p).unwrap().l();
        l * Vector3::from_fn(|_, _| n.sample(rng))
    }

    fn exact_pairs(truth: &Isometry3<f64>, local: &[Vector3<f64>]) -> Vec<Correspondence> {
        local
            .iter()
            .map(|l| Correspondence {
                local_m: *l,
                local_cov_m2: Matrix3::identity() * 1e-4,
                global_m: truth.transform_point(&(*l).into()).coords,
                global_cov_m2: Matrix3::identity() * 1e-2,
            })
            .collect()
    }

    fn line(n: usize) -> Vec<Vector3<f64>> {
        (0..n).map(|i| Vector3::new(i as f64, 0.5 * i as f64, 0.0)).collect()
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(128))]
        #[test]
        fn umeyama_recovers_a_known_transform_under_noise(
            seed in any::<u64>(),
            count in 6usize..40,
            roll in -3.1..3.1f64, pitch in -1.5..1.5f64, yaw in -3.1..3.1f64,
            x in -100.0..100.0f64, y in -100.0..100.0f64, z in -100.0..100.0f64,
        ) {
            let truth = iso(x, y, z, roll, pitch, yaw);
            let mut rng = Xoshiro256PlusPlus::seed_from_u64(seed);
            let cube = Uniform::new(-10.0, 10.0).unwrap();
            let local: Vec<Vector3<f64>> =
                (0..count).map(|_| Vector3::from_fn(|_, _| cube.sample(&mut rng))).collect();
            prop_assume!(spread(&local).0 > 0.2);
            let sigma = 0.01;
            let cov = Matrix3::identity() * sigma * sigma;
            let pairs: Vec<Correspondence> = local
                .iter()
                .map(|l| Correspondence {
                    local_m: l + gauss(&mut rng, &cov),
                    local_cov_m2: cov,
                    global_m: truth.transform_point(&(*l).into()).coords + gauss(&mut rng, &cov),
                    global_cov_m2: cov,
                })
                .collect();
            let a = align(&pairs, &AlignConfig::default()).unwrap();
            // Rotation error ≈ σ√2 / (rms radius ≈ 10 m · √n) ≈ 1e-3 rad: bound 10×.
            let angle = a.global_from_local.rotation.angle_to(&truth.rotation);
            prop_assert!(angle < 0.01, "rotation error {} rad", angle);
            for l in &local {
                let err = (a.global_from_local.transform_point(&(*l).into()) - truth.transform_point(&(*l).into())).norm();
                prop_assert!(err < 0.1, "mapping error {} m", err);
            }
            prop_assert!(a.rms_residual_m < 6.0 * sigma);
            prop_assert_eq!(a.pairs, count);
        }
    }

    #[test]
    fn exact_pairs_give_the_exact_transform_and_isotropic_weights_match_plain_umeyama() {
        let truth = iso(12.0, -40.0, 3.0, 0.1, -0.2, 2.5);
        let local: Vec<Vector3<f64>> =
            (0..12).map(|i| Vector3::new((i as f64 * 0.9).sin() * 8.0, i as f64 * 1.5, (i as f64).cos())).collect();
        let a = align(&exact_pairs(&truth, &local), &AlignConfig::default()).unwrap();
        assert!(a.global_from_local.rotation.angle_to(&truth.rotation) < 1e-12);
        assert!((a.global_from_local.translation.vector - truth.translation.vector).norm() < 1e-10);
        assert!(a.rms_residual_m < 1e-10);
        // With noisy points and equal isotropic covariances the optimum is the plain SVD solution.
        let mut rng = Xoshiro256PlusPlus::seed_from_u64(4);
        let mut pairs = exact_pairs(&truth, &local);
        for p in pairs.iter_mut() {
            p.global_m += gauss(&mut rng, &(Matrix3::identity() * 0.04));
        }
        let a = align(&pairs, &AlignConfig::default()).unwrap();
        let g: Vec<Vector3<f64>> = pairs.iter().map(|p| p.global_m).collect();
        let svd = align_rigid(&local, &g, &[1.0; 12]).unwrap();
        assert!(a.global_from_local.rotation.angle_to(&svd.rotation) < 1e-10);
        assert!((a.global_from_local.translation.vector - svd.translation.vector).norm() < 1e-9);
    }

    #[test]
    fn collinear_too_small_and_too_few_pairs_are_errors() {
        let truth = iso(1.0, 2.0, 3.0, 0.0, 0.0, 0.7);
        let cfg = AlignConfig::default();
        let err = align(&exact_pairs(&truth, &line(10)), &cfg).unwrap_err();
        assert!(matches!(err, FusionError::Collinear { ratio, limit } if ratio < 1e-9 && limit == 0.05), "{err:?}");
        assert!(err.is_degenerate_geometry());
        // Nearly collinear: 2 cm off a 10 m line.
        let mut near = line(10);
        near[4].z += 0.02;
        assert!(matches!(align(&exact_pairs(&truth, &near), &cfg), Err(FusionError::Collinear { .. })));
        let tiny: Vec<Vector3<f64>> = [(0.0, 0.0, 0.0), (0.3, 0.0, 0.0), (0.0, 0.3, 0.0), (0.1, 0.1, 0.2)]
            .map(|(x, y, z)| Vector3::new(x, y, z))
            .into();
        let err = align(&exact_pairs(&truth, &tiny), &cfg).unwrap_err();
        assert!(matches!(err, FusionError::TooSmall { .. }) && err.is_degenerate_geometry(), "{err:?}");
        let three = [Vector3::new(0.0, 0.0, 0.0), Vector3::new(5.0, 0.0, 0.0), Vector3::new(0.0, 5.0, 0.0)];
        assert_eq!(
            align(&exact_pairs(&truth, &three[..2]), &cfg).unwrap_err(),
            FusionError::TooFew { what: "correspondences", got: 2, need: 3 }
        );
        assert!(align(&exact_pairs(&truth, &three), &cfg).is_ok());
        let strict = AlignConfig { min_pairs: 5, ..cfg.clone() };
        assert!(matches!(align(&exact_pairs(&truth, &three), &strict), Err(FusionError::TooFew { need: 5, .. })));
        let mut bad = exact_pairs(&truth, &three);
        bad[1].global_m.x = f64::NAN;
        assert_eq!(align(&bad, &cfg).unwrap_err(), FusionError::NonFinite("global point"));
        let mut bad = exact_pairs(&truth, &three);
        bad[0].local_cov_m2[(2, 2)] = -1.0;
        assert_eq!(align(&bad, &cfg).unwrap_err(), FusionError::NotPositiveDefinite("local covariance"));
        let invalid = AlignConfig { min_pairs: 2, min_spread_ratio: 1.5, min_extent_m: f64::NAN };
        let keys: Vec<String> = invalid.issues().into_iter().map(|i| i.key).collect();
        assert_eq!(keys, ["min_pairs", "min_spread_ratio", "min_extent_m"]);
        assert!(matches!(align(&exact_pairs(&truth, &three), &invalid), Err(FusionError::InvalidArgument(_))));
        assert!(cfg.issues().is_empty());
    }

    #[test]
    fn the_config_parses_with_defaults_and_refuses_unknown_keys() {
        use serde::de::value::{Error, MapDeserializer};
        let parse = |key: &'static str| {
            AlignConfig::deserialize(MapDeserializer::<_, Error>::new(std::iter::once((key, 4usize))))
        };
        assert_eq!(parse("min_pairs").unwrap(), AlignConfig { min_pairs: 4, ..AlignConfig::default() });
        assert!(parse("min_pair").unwrap_err().to_string().contains("unknown field"));
    }

    #[test]
    fn align_with_heading_recovers_the_transform_from_collinear_points() {
        let truth = iso(30.0, -5.0, -12.0, 0.0, 0.0, -2.2);
        let mut rng = Xoshiro256PlusPlus::seed_from_u64(8);
        let mut pairs = exact_pairs(&truth, &line(20));
        for p in pairs.iter_mut() {
            p.global_m += gauss(&mut rng, &p.global_cov_m2);
        }
        assert!(matches!(align(&pairs, &AlignConfig::default()), Err(FusionError::Collinear { .. })));
        let a = align_with_heading(&pairs, -2.2, 0.01).unwrap();
        assert!(a.global_from_local.rotation.angle_to(&truth.rotation) < 1e-12);
        assert!((a.global_from_local.translation.vector - truth.translation.vector).norm() < 0.1);
        assert!(a.spread_ratio < 1e-9);
        // A wrong heading moves the far end of the line.
        let wrong = align_with_heading(&pairs, -2.0, 0.01).unwrap();
        let far = Vector3::new(19.0, 9.5, 0.0);
        let err = (wrong.global_from_local.transform_point(&far.into()) - truth.transform_point(&far.into())).norm();
        assert!(err > 1.0, "{err}");
        assert!(wrong.rms_residual_m > 0.5);
        // The yaw variance is carried: the covariance of a far point grows across the line.
        let (_, c) = a.map_point(&Vector3::new(100.0, 50.0, 0.0), &Matrix3::zeros());
        let across = truth.rotation * Vector3::new(-0.5, 1.0, 0.0).normalize();
        assert!((across.transpose() * c * across)[0] > 0.5 * (0.01_f64 * 56.0).powi(2));
        assert!(matches!(align_with_heading(&[], 0.0, 0.1), Err(FusionError::TooFew { .. })));
        assert!(matches!(align_with_heading(&pairs, f64::NAN, 0.1), Err(FusionError::NonFinite(_))));
        assert!(matches!(align_with_heading(&pairs, 0.0, -0.1), Err(FusionError::InvalidArgument(_))));
    }

    #[test]
    fn the_spread_of_a_point_set() {
        assert_eq!(spread(&[]), (0.0, 0.0));
        assert_eq!(spread(&[Vector3::new(1.0, 2.0, 3.0); 4]), (0.0, 0.0));
        let (r, e) = spread(&line(11));
        assert!(r < 1e-9 && (e - (10.0f64.powi(2) + 5.0f64.powi(2)).sqrt()).abs() < 1e-9, "{r} {e}");
        // A 4 × 2 rectangle's corners: singular values in ratio 2 / 4.
        let rect = [(0.0, 0.0), (4.0, 0.0), (4.0, 2.0), (0.0, 2.0)].map(|(x, y)| Vector3::new(x, y, 7.0));
        let (r, e) = spread(&rect);
        assert!((r - 0.5).abs() < 1e-12 && (e - 4.0).abs() < 1e-12, "{r} {e}");
        assert!(spread(&[Vector3::new(f64::NAN, 0.0, 0.0)]).0.is_nan());
    }

    /// Monte Carlo: anisotropic noise on both sides, a test point outside the cloud. NEES of the mapped
    /// point ≈ 3 and of the transform itself ≈ 6; without the transform's covariance the point's NEES
    /// is far above 3 (so the test can tell).
    #[test]
    fn monte_carlo_nees_of_map_point_is_about_three() {
        let truth = iso(50.0, 20.0, -8.0, 0.05, -0.03, 0.9);
        let local: Vec<Vector3<f64>> = (0..8)
            .map(|i| {
                let a = i as f64 * 0.8;
                Vector3::new(10.0 * a.cos(), 6.0 * a.sin(), 0.3 * i as f64)
            })
            .collect();
        let rot_l = Rotation3::from_euler_angles(0.3, 0.1, 0.6);
        let cov_l = rot_l * Matrix3::from_diagonal(&Vector3::new(0.05, 0.02, 0.1).map(|s| s * s)) * rot_l.transpose();
        let cov_g = Matrix3::from_diagonal(&Vector3::new(0.6, 0.3, 0.2).map(|s| s * s));
        let test_local = Vector3::new(35.0, -20.0, 4.0);
        let test_cov = Matrix3::from_diagonal(&Vector3::new(0.02, 0.02, 0.05).map(|s| s * s));
        let mut rng = Xoshiro256PlusPlus::seed_from_u64(2024);
        let trials = 2000;
        let (mut nees_point, mut nees_naive, mut nees_transform) = (0.0, 0.0, 0.0);
        for _ in 0..trials {
            let pairs: Vec<Correspondence> = local
                .iter()
                .map(|l| Correspondence {
                    local_m: l + gauss(&mut rng, &cov_l),
                    local_cov_m2: cov_l,
                    global_m: truth.transform_point(&(*l).into()).coords + gauss(&mut rng, &cov_g),
                    global_cov_m2: cov_g,
                })
                .collect();
            let a = align(&pairs, &AlignConfig::default()).unwrap();
            let observed = test_local + gauss(&mut rng, &test_cov);
            let (g, c) = a.map_point(&observed, &test_cov);
            let e = g - truth.transform_point(&test_local.into()).coords;
            nees_point += (e.transpose() * c.try_inverse().unwrap() * e)[0];
            let r = a.global_from_local.rotation.to_rotation_matrix();
            let c_naive = r * test_cov * r.transpose();
            nees_naive += (e.transpose() * c_naive.try_inverse().unwrap() * e)[0];
            // Transform error in the covariance's convention: φ with R_true = Exp(φ)·R̂, δt = t_true − t̂.
            let phi = (truth.rotation * a.global_from_local.rotation.inverse()).scaled_axis();
            let dt = truth.translation.vector - a.global_from_local.translation.vector;
            let x = Vector6::new(dt.x, dt.y, dt.z, phi.x, phi.y, phi.z);
            nees_transform += (x.transpose() * a.covariance.try_inverse().unwrap() * x)[0];
        }
        let (p, n, t) = (nees_point / trials as f64, nees_naive / trials as f64, nees_transform / trials as f64);
        println!("mean NEES: mapped point {p:.3} (naive {n:.1}), transform {t:.3}");
        assert!((2.6..3.5).contains(&p), "mapped point NEES {p}");
        assert!((5.3..7.0).contains(&t), "transform NEES {t}");
        assert!(n > 10.0, "naive NEES {n}: the transform's uncertainty should matter here");
    }

    #[test]
    fn map_point_with_an_exact_transform_rotates_the_covariance() {
        let truth = iso(1.0, 2.0, 3.0, 0.4, -0.3, 1.2);
        let a = Alignment::from_transform(truth, Matrix6::zeros());
        let cov = Matrix3::new(0.04, 0.01, 0.0, 0.01, 0.09, 0.02, 0.0, 0.02, 0.01);
        let l = Vector3::new(5.0, -1.0, 2.0);
        let (g, c) = a.map_point(&l, &cov);
        let r = truth.rotation.to_rotation_matrix();
        assert!((g - (r * l + truth.translation.vector)).norm() < 1e-12);
        assert!((c - r * cov * r.transpose()).amax() < 1e-15);
        // Rotation uncertainty about global z only: the variance grows across the lever arm R·l.
        let mut cov6 = Matrix6::zeros();
        cov6[(5, 5)] = 1e-4;
        let a = Alignment::from_transform(truth, cov6);
        let (_, c) = a.map_point(&l, &Matrix3::zeros());
        let q = r * l;
        let expected = Vector3::z().cross(&q) * Vector3::z().cross(&q).transpose() * 1e-4;
        assert!((c - expected).amax() < 1e-15, "{c} vs {expected}");
    }
}
