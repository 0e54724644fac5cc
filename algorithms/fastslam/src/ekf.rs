//! The per-landmark EKF of FastSLAM (SPEC §2-4), in the literature's names.
//!
//! Measurement of landmark L from a body pose (p, R), in the body frame (SPEC §2, [3D] eq 11 with
//! erratum §9): z = h(p, R, L) = Rᵀ·(L − p) + η, η ~ N(0, Rz). Jacobians: H_L = ∂h/∂L = Rᵀ, and
//! for the body-frame pose perturbation (p = p̂ + δp, R = R̂·Exp(δφ)) H_x = ∂h/∂(δp, δφ) =
//! [−R̂ᵀ, [ẑ]×]. Updates use the Joseph form; a covariance that is not positive definite is an
//! error, never a panic.

#![allow(non_snake_case)]

use nalgebra::{Cholesky, Isometry3, Matrix3, Matrix3x6, Vector3};

/// Errors of the filter mathematics.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum FilterError {
    /// A covariance that must be positive definite is not.
    #[error("{0} is not positive definite")]
    NotPositiveDefinite(&'static str),
    /// A value is NaN or infinite.
    #[error("non-finite {0}")]
    NonFinite(&'static str),
}

/// One landmark's Gaussian estimate and bookkeeping.
#[derive(Debug, Clone, PartialEq)]
pub struct LandmarkEkf {
    /// Mean position in the local-map frame, m.
    pub mean_m: Vector3<f64>,
    /// Covariance, m².
    pub cov_m2: Matrix3<f64>,
    /// Descriptor, when the observations carry one.
    pub descriptor: Option<[u8; 32]>,
    /// Times observed (including the first).
    pub hits: u32,
    /// Frame of the last observation.
    pub last_seen_frame: u32,
}

/// h(p, R, L) = Rᵀ·(L − p): the landmark in the body frame.
pub fn predict_measurement(world_from_body: &Isometry3<f64>, landmark_m: &Vector3<f64>) -> Vector3<f64> {
    world_from_body.rotation.inverse() * (landmark_m - world_from_body.translation.vector)
}

/// (H_L, H_x) at the pose and landmark.
pub fn jacobians(world_from_body: &Isometry3<f64>, landmark_m: &Vector3<f64>) -> (Matrix3<f64>, Matrix3x6<f64>) {
    let Rt = world_from_body.rotation.inverse().to_rotation_matrix().into_inner();
    let z = predict_measurement(world_from_body, landmark_m);
    let mut Hx = Matrix3x6::zeros();
    Hx.fixed_view_mut::<3, 3>(0, 0).copy_from(&(-Rt));
    Hx.fixed_view_mut::<3, 3>(0, 3).copy_from(&z.cross_matrix());
    (Rt, Hx)
}

/// The innovation of one observation against one landmark.
#[derive(Debug, Clone)]
pub struct Innovation {
    /// ν = z − ẑ, m.
    pub nu: Vector3<f64>,
    /// S = H_L·Σ·H_Lᵀ + Rz, m².
    pub S: Matrix3<f64>,
    /// H_L = Rᵀ at the pose the innovation was computed for.
    pub HL: Matrix3<f64>,
    /// Cholesky factor of S.
    chol: Cholesky<f64, nalgebra::U3>,
    /// ε = νᵀ·S⁻¹·ν (SPEC eq 15).
    pub mahalanobis: f64,
}

impl Innovation {
    /// ln N(ν; 0, S).
    pub fn log_likelihood(&self) -> f64 {
        let log_det: f64 = self.chol.l().diagonal().iter().map(|d| 2.0 * d.ln()).sum();
        -0.5 * (self.mahalanobis + log_det + 3.0 * (2.0 * std::f64::consts::PI).ln())
    }

    /// S⁻¹.
    pub fn S_inv(&self) -> Matrix3<f64> {
        self.chol.inverse()
    }
}

/// Innovation of measurement `z_m` (body frame, covariance `Rz`) against landmark `lm` seen from
/// `world_from_body` (SPEC eq 14-16).
pub fn innovation(
    world_from_body: &Isometry3<f64>,
    lm: &LandmarkEkf,
    z_m: &Vector3<f64>,
    Rz: &Matrix3<f64>,
) -> Result<Innovation, FilterError> {
    let HL = world_from_body.rotation.inverse().to_rotation_matrix().into_inner();
    let S = HL * lm.cov_m2 * HL.transpose() + Rz;
    let S = (S + S.transpose()) * 0.5;
    let chol = Cholesky::new(S).ok_or(FilterError::NotPositiveDefinite("innovation covariance S"))?;
    let nu = z_m - HL * (lm.mean_m - world_from_body.translation.vector);
    let mahalanobis = nu.dot(&chol.solve(&nu));
    if !mahalanobis.is_finite() {
        return Err(FilterError::NonFinite("innovation"));
    }
    Ok(Innovation { nu, S, HL, chol, mahalanobis })
}

/// EKF update of `lm` with the innovation `inn` (SPEC §4): K = Σ·H_Lᵀ·S⁻¹, μ += K·ν,
/// Σ = (I − K·H_L)·Σ·(I − K·H_L)ᵀ + K·Rz·Kᵀ (Joseph form). `inn` must have been computed for
/// this landmark at the current pose.
pub fn update(lm: &mut LandmarkEkf, inn: &Innovation, Rz: &Matrix3<f64>) -> Result<(), FilterError> {
    let HL = inn.HL;
    let K = lm.cov_m2 * HL.transpose() * inn.S_inv();
    let mean = lm.mean_m + K * inn.nu;
    let IKH = Matrix3::identity() - K * HL;
    let cov = IKH * lm.cov_m2 * IKH.transpose() + K * Rz * K.transpose();
    let cov = (cov + cov.transpose()) * 0.5;
    if !(mean.iter().all(|v| v.is_finite()) && cov.iter().all(|v| v.is_finite())) {
        return Err(FilterError::NonFinite("landmark update"));
    }
    lm.mean_m = mean;
    lm.cov_m2 = cov;
    Ok(())
}

/// A new landmark from an observation (SPEC §4): μ = p + R·z, Σ = R·Rz·Rᵀ.
pub fn init_landmark(
    world_from_body: &Isometry3<f64>,
    z_m: &Vector3<f64>,
    Rz: &Matrix3<f64>,
    descriptor: Option<[u8; 32]>,
    frame: u32,
) -> LandmarkEkf {
    let R = world_from_body.rotation.to_rotation_matrix().into_inner();
    LandmarkEkf {
        mean_m: world_from_body.translation.vector + R * z_m,
        cov_m2: R * Rz * R.transpose(),
        descriptor,
        hits: 1,
        last_seen_frame: frame,
    }
}

/// Hamming distance of two 32-byte descriptors.
pub fn hamming(a: &[u8; 32], b: &[u8; 32]) -> u32 {
    a.iter().zip(b).map(|(x, y)| (x ^ y).count_ones()).sum()
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Translation3, UnitQuaternion};
    use proptest::prelude::*;

    fn pose(x: f64, y: f64, z: f64, r: f64, p: f64, yaw: f64) -> Isometry3<f64> {
        Isometry3::from_parts(Translation3::new(x, y, z), UnitQuaternion::from_euler_angles(r, p, yaw))
    }

    proptest! {
        #[test]
        fn jacobians_match_finite_differences(
            x in -5.0..5.0f64, y in -5.0..5.0f64, r in -0.5..0.5f64, p in -0.5..0.5f64, yaw in -3.0..3.0f64,
            lx in -10.0..10.0f64, ly in -10.0..10.0f64, lz in -10.0..10.0f64,
        ) {
            let T = pose(x, y, 1.0, r, p, yaw);
            let L = Vector3::new(lx, ly, lz);
            let (HL, Hx) = jacobians(&T, &L);
            let h = 1e-6;
            for i in 0..3 {
                let mut d = Vector3::zeros();
                d[i] = h;
                let fd = (predict_measurement(&T, &(L + d)) - predict_measurement(&T, &(L - d))) / (2.0 * h);
                prop_assert!((HL.column(i) - fd).norm() < 1e-6);
            }
            for i in 0..6 {
                let perturb = |s: f64| {
                    let mut dp = Vector3::zeros();
                    let mut dphi = Vector3::zeros();
                    if i < 3 { dp[i] = s } else { dphi[i - 3] = s }
                    Isometry3::from_parts(
                        Translation3::from(T.translation.vector + dp),
                        T.rotation * UnitQuaternion::from_scaled_axis(dphi),
                    )
                };
                let fd = (predict_measurement(&perturb(h), &L) - predict_measurement(&perturb(-h), &L)) / (2.0 * h);
                prop_assert!((Hx.column(i) - fd).norm() < 1e-5 * (1.0 + fd.norm()), "column {}: {} vs {}", i, Hx.column(i), fd);
            }
        }
    }

    #[test]
    fn a_landmark_ekf_converges_on_a_static_landmark() {
        use rand::SeedableRng;
        use rand_distr::{Distribution, Normal};
        let truth = Vector3::new(4.0, -1.0, 2.0);
        let Rz = Matrix3::from_diagonal(&Vector3::new(0.04, 0.04, 0.25));
        let n = Normal::new(0.0, 1.0).unwrap();
        let mut rng = rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(3);
        let noisy = |T: &Isometry3<f64>, rng: &mut rand_xoshiro::Xoshiro256PlusPlus| {
            let z = predict_measurement(T, &truth);
            z + Vector3::new(0.2 * n.sample(rng), 0.2 * n.sample(rng), 0.5 * n.sample(rng))
        };
        let T0 = pose(0.0, 0.0, 0.0, 0.0, 0.0, 0.0);
        let mut lm = init_landmark(&T0, &noisy(&T0, &mut rng), &Rz, None, 0);
        for k in 0..400 {
            let T = pose(0.02 * k as f64, 0.01 * k as f64, 0.0, 0.0, 0.0, 0.3 * (k as f64 * 0.05).sin());
            let z = noisy(&T, &mut rng);
            let inn = innovation(&T, &lm, &z, &Rz).unwrap();
            update(&mut lm, &inn, &Rz).unwrap();
            assert!((lm.cov_m2 - lm.cov_m2.transpose()).norm() < 1e-12, "Joseph form keeps Σ symmetric");
        }
        let err = lm.mean_m - truth;
        assert!(err.norm() < 0.1, "error {err}");
        assert!(lm.cov_m2.trace() < 0.003, "Σ shrank to {}", lm.cov_m2.trace());
        let nees = err.dot(&(lm.cov_m2.try_inverse().unwrap() * err));
        assert!(nees < 16.3, "consistent: NEES {nees}");
    }

    #[test]
    fn a_non_positive_definite_covariance_is_an_error_not_a_panic() {
        let T = pose(0.0, 0.0, 0.0, 0.0, 0.0, 0.0);
        let lm = LandmarkEkf {
            mean_m: Vector3::new(1.0, 0.0, 0.0),
            cov_m2: -Matrix3::identity(),
            descriptor: None,
            hits: 1,
            last_seen_frame: 0,
        };
        let e = innovation(&T, &lm, &Vector3::new(1.0, 0.0, 0.0), &Matrix3::zeros()).unwrap_err();
        assert_eq!(e, FilterError::NotPositiveDefinite("innovation covariance S"));
        let nan = LandmarkEkf { mean_m: Vector3::new(f64::NAN, 0.0, 0.0), cov_m2: Matrix3::identity(), ..lm };
        assert!(innovation(&T, &nan, &Vector3::zeros(), &Matrix3::identity()).is_err());
    }

    #[test]
    fn log_likelihood_matches_the_gaussian_density() {
        let T = pose(0.0, 0.0, 0.0, 0.0, 0.0, 0.0);
        let lm = LandmarkEkf {
            mean_m: Vector3::new(2.0, 0.0, 0.0),
            cov_m2: Matrix3::identity() * 0.5,
            descriptor: None,
            hits: 1,
            last_seen_frame: 0,
        };
        let inn = innovation(&T, &lm, &Vector3::new(3.0, 0.0, 0.0), &(Matrix3::identity() * 0.5)).unwrap();
        // S = I, ν = (1, 0, 0): ln N = −½(1 + 3 ln 2π).
        let expected = -0.5 * (1.0 + 3.0 * (2.0 * std::f64::consts::PI).ln());
        assert!((inn.log_likelihood() - expected).abs() < 1e-12);
        assert!((inn.mahalanobis - 1.0).abs() < 1e-12);
    }
}
