//! Covariance-weighted fusion of the camera and buoy position estimates (EQUATIONS §5.2, \[3D\] eq 31-32 in
//! matrix form) under a χ²₃ overlap gate, and the χ²₃ quantile for that gate.
//!
//! With S = P_b + P_c (both in the global frame):
//!   X_v = P_b·S⁻¹·X_c + P_c·S⁻¹·X_b = X_b + P_b·S⁻¹·(X_c − X_b),   P_v = P_b·S⁻¹·P_c,
//! fused only when the squared Mahalanobis distance d² = (X_c − X_b)ᵀ·S⁻¹·(X_c − X_b) is within the gate.
//! This is the product of the two Gaussians (the two estimates treated as independent).

use nalgebra::{Cholesky, Matrix3, Vector3};

use crate::FusionError;

/// The result of [`fuse`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum FuseOutcome {
    /// The estimates overlap: the fused estimate.
    Fused {
        /// Fused position X_v, m (global frame).
        position_m: Vector3<f64>,
        /// Fused covariance P_v, m² (symmetric).
        covariance_m2: Matrix3<f64>,
        /// The SQUARED Mahalanobis distance d² of the difference (what the χ²₃ gate tests).
        mahalanobis: f64,
    },
    /// The estimates do not overlap (d² above the gate): nothing fused.
    NoOverlap {
        /// The SQUARED Mahalanobis distance d² of the difference.
        mahalanobis: f64,
    },
}

/// Covariance-weighted fusion of the camera estimate (already in the global frame) and the buoy
/// estimate, eq 31-32 in matrix form:
/// X = P_b(P_b+P_c)⁻¹X_c + P_c(P_b+P_c)⁻¹X_b, P = P_b(P_b+P_c)⁻¹P_c (symmetrised), when
/// (X_c−X_b)ᵀ(P_b+P_c)⁻¹(X_c−X_b) ≤ `gate_chi2` (e.g. [`chi2_3_quantile`]`(0.99)`; `f64::INFINITY`
/// fuses always).
///
/// Errors: a non-finite input ([`FusionError::NonFinite`]); a covariance that is not symmetric
/// positive semi-definite, or a singular sum P_b + P_c ([`FusionError::NotPositiveDefinite`]); a NaN or
/// negative gate ([`FusionError::InvalidArgument`]).
pub fn fuse(
    x_camera_m: &Vector3<f64>,
    p_camera_m2: &Matrix3<f64>,
    x_buoy_m: &Vector3<f64>,
    p_buoy_m2: &Matrix3<f64>,
    gate_chi2: f64,
) -> Result<FuseOutcome, FusionError> {
    if gate_chi2.is_nan() || gate_chi2 < 0.0 {
        return Err(FusionError::InvalidArgument("gate_chi2 must be >= 0"));
    }
    if !x_camera_m.iter().all(|v| v.is_finite()) {
        return Err(FusionError::NonFinite("camera position"));
    }
    if !x_buoy_m.iter().all(|v| v.is_finite()) {
        return Err(FusionError::NonFinite("buoy position"));
    }
    let p_c = check_covariance("camera covariance", p_camera_m2)?;
    let p_b = check_covariance("buoy covariance", p_buoy_m2)?;
    let (x, p, d2) = fuse_unchecked(x_camera_m, &p_c, x_buoy_m, &p_b)?;
    if d2 <= gate_chi2 {
        Ok(FuseOutcome::Fused { position_m: x, covariance_m2: p, mahalanobis: d2 })
    } else {
        Ok(FuseOutcome::NoOverlap { mahalanobis: d2 })
    }
}

/// How the camera and buoy errors really behave, for [`fuse_correlated`]: the camera estimate's
/// error covariance and its cross-covariance with the buoy's, E[e_c·e_bᵀ].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CorrelatedErrors {
    /// The camera estimate's error covariance, m² (global frame).
    pub camera_cov_m2: Matrix3<f64>,
    /// E[e_c·e_bᵀ], m².
    pub cross_cov_m2: Matrix3<f64>,
}

/// Eq 31's estimate, its weights from `p_camera_m2` and `p_buoy_m2` as [`fuse`] takes them,
/// with the covariance it has when the errors behave as `errors` says (docs/EQUATIONS.md §5.3):
/// with K = P_c·(P_c + P_b)⁻¹, X = X_c + K·(X_b − X_c) and
///   P = (I − K)·P̃_c·(I − K)ᵀ + K·P_b·Kᵀ + (I − K)·P_cb·Kᵀ + K·P_cbᵀ·(I − K)ᵀ
/// (P̃_c = `errors.camera_cov_m2`, P_cb = `errors.cross_cov_m2`), gated on the difference against
/// its own covariance, d² = (X_b − X_c)ᵀ·(P̃_c + P_b − P_cb − P_cbᵀ)⁻¹·(X_b − X_c). With
/// P̃_c = P_c and P_cb = 0 this is eq 31-32 ([`fuse`]).
///
/// The weights stay the paper's: on the simulated mission the gain that is optimal for the
/// correlation model (Bar-Shalom & Campo 1986) was measured and trusted the buoy more, for a
/// larger error than eq 31's (docs/fusion.md, "Covariances").
///
/// Errors as [`fuse`]'s, and [`FusionError::NotPositiveDefinite`] when the covariance of the
/// difference is not positive definite (no joint covariance has that cross-covariance).
pub fn fuse_correlated(
    x_camera_m: &Vector3<f64>,
    p_camera_m2: &Matrix3<f64>,
    x_buoy_m: &Vector3<f64>,
    p_buoy_m2: &Matrix3<f64>,
    errors: &CorrelatedErrors,
    gate_chi2: f64,
) -> Result<FuseOutcome, FusionError> {
    if gate_chi2.is_nan() || gate_chi2 < 0.0 {
        return Err(FusionError::InvalidArgument("gate_chi2 must be >= 0"));
    }
    if !(x_camera_m.iter().all(|v| v.is_finite()) && x_buoy_m.iter().all(|v| v.is_finite())) {
        return Err(FusionError::NonFinite("camera or buoy position"));
    }
    if !errors.cross_cov_m2.iter().all(|v| v.is_finite()) {
        return Err(FusionError::NonFinite("cross-covariance"));
    }
    let p_c = check_covariance("camera covariance", p_camera_m2)?;
    let p_b = check_covariance("buoy covariance", p_buoy_m2)?;
    let p_c_true = check_covariance("camera error covariance", &errors.camera_cov_m2)?;
    let p_cb = errors.cross_cov_m2;
    let s_diff = symmetrise(&(p_c_true + p_b - p_cb - p_cb.transpose()));
    let chol = Cholesky::new(s_diff).ok_or(FusionError::NotPositiveDefinite("covariance of the difference"))?;
    let diff = x_buoy_m - x_camera_m;
    let d2 = diff.dot(&chol.solve(&diff));
    if d2 > gate_chi2 {
        return Ok(FuseOutcome::NoOverlap { mahalanobis: d2 });
    }
    // K = P_c·S⁻¹ = (S⁻¹·P_c)ᵀ (both symmetric).
    let k = Cholesky::new(p_c + p_b)
        .ok_or(FusionError::NotPositiveDefinite("sum of the covariances"))?
        .solve(&p_c)
        .transpose();
    let x = x_camera_m + k * diff;
    let i_k = Matrix3::identity() - k;
    let cross = i_k * p_cb * k.transpose();
    let p = i_k * p_c_true * i_k.transpose() + k * p_b * k.transpose() + cross + cross.transpose();
    Ok(FuseOutcome::Fused { position_m: x, covariance_m2: symmetrise(&p), mahalanobis: d2 })
}

/// Eq 31-32 on inputs already checked (finite, symmetric PSD): (X_v, P_v, d²). The sum of the two
/// covariances must be positive definite.
pub(crate) fn fuse_unchecked(
    x_c: &Vector3<f64>,
    p_c: &Matrix3<f64>,
    x_b: &Vector3<f64>,
    p_b: &Matrix3<f64>,
) -> Result<(Vector3<f64>, Matrix3<f64>, f64), FusionError> {
    let s = p_b + p_c;
    let chol = Cholesky::new(s).ok_or(FusionError::NotPositiveDefinite("sum of the covariances"))?;
    let diff = x_c - x_b;
    let s_inv_diff = chol.solve(&diff);
    let d2 = diff.dot(&s_inv_diff);
    // X_v = X_b + P_b S⁻¹ (X_c − X_b), algebraically equal to eq 31 (P_c S⁻¹ = I − P_b S⁻¹).
    let x = x_b + p_b * s_inv_diff;
    // P_v = P_b S⁻¹ P_c, symmetrised.
    let p = p_b * chol.solve(p_c);
    Ok((x, symmetrise(&p), d2))
}

/// (P + Pᵀ)/2.
pub(crate) fn symmetrise(p: &Matrix3<f64>) -> Matrix3<f64> {
    (p + p.transpose()) * 0.5
}

/// Checks that `p` is finite, symmetric (to 1e-9 relative) and positive semi-definite (smallest
/// eigenvalue ≥ −1e-9 of the largest); returns it symmetrised.
pub(crate) fn check_covariance(what: &'static str, p: &Matrix3<f64>) -> Result<Matrix3<f64>, FusionError> {
    Ok(geometry::gaussian::check_covariance(what, p)?)
}

/// The quantile x with P(X ≤ x) = `p` for X ~ χ²₃ (0.95 → 7.815, 0.99 → 11.345, 0.999 → 16.266);
/// `None` unless 0 < p < 1. Bisection on the CDF (regularised incomplete gamma P(3/2, x/2), about
/// 1e-12 relative).
pub fn chi2_3_quantile(p: f64) -> Option<f64> {
    if !(p > 0.0 && p < 1.0) {
        return None;
    }
    let (mut lo, mut hi) = (0.0_f64, 8.0_f64);
    while chi2_3_cdf(hi) < p {
        hi *= 2.0;
        if hi > 1e5 {
            return None; // p within rounding of 1
        }
    }
    for _ in 0..200 {
        let mid = 0.5 * (lo + hi);
        if chi2_3_cdf(mid) < p {
            lo = mid;
        } else {
            hi = mid;
        }
        if hi - lo <= 1e-14 * hi {
            break;
        }
    }
    Some(0.5 * (lo + hi))
}

/// P(X ≤ x) for X ~ χ²₃: the regularised lower incomplete gamma P(3/2, x/2) (Numerical Recipes
/// `gser`/`gcf`: series below a + 1, Lentz continued fraction above).
pub fn chi2_3_cdf(x: f64) -> f64 {
    if x.is_nan() {
        return f64::NAN;
    }
    if x <= 0.0 {
        return 0.0;
    }
    if x == f64::INFINITY {
        return 1.0;
    }
    const A: f64 = 1.5;
    // ln Γ(3/2) = ln(√π / 2)
    let ln_gamma_a = (std::f64::consts::PI.sqrt() / 2.0).ln();
    let z = x / 2.0;
    let prefactor = (-z + A * z.ln() - ln_gamma_a).exp();
    if z < A + 1.0 {
        let (mut ap, mut del) = (A, 1.0 / A);
        let mut sum = del;
        for _ in 0..500 {
            ap += 1.0;
            del *= z / ap;
            sum += del;
            if del.abs() < sum.abs() * 1e-16 {
                break;
            }
        }
        (sum * prefactor).min(1.0)
    } else {
        const TINY: f64 = 1e-300;
        let mut b = z + 1.0 - A;
        let mut c = 1.0 / TINY;
        let mut d = 1.0 / b;
        let mut h = d;
        for i in 1..500 {
            let an = -(i as f64) * (i as f64 - A);
            b += 2.0;
            d = an * d + b;
            if d.abs() < TINY {
                d = TINY;
            }
            c = b + an / c;
            if c.abs() < TINY {
                c = TINY;
            }
            d = 1.0 / d;
            let del = d * c;
            h *= del;
            if (del - 1.0).abs() < 1e-16 {
                break;
            }
        }
        (1.0 - prefactor * h).max(0.0)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::SymmetricEigen;

    fn fused(o: FuseOutcome) -> (Vector3<f64>, Matrix3<f64>, f64) {
        match o {
            FuseOutcome::Fused { position_m, covariance_m2, mahalanobis } => (position_m, covariance_m2, mahalanobis),
            FuseOutcome::NoOverlap { mahalanobis } => panic!("not fused, d² = {mahalanobis}"),
        }
    }

    #[test]
    fn correlated_fusion_keeps_eq_31s_estimate_and_reports_its_covariance() {
        let (x_c, x_b) = (Vector3::new(1.0, 2.0, -3.0), Vector3::new(1.3, 1.8, -3.1));
        let p_c = Matrix3::new(0.04, 0.01, 0.0, 0.01, 0.05, 0.0, 0.0, 0.0, 0.02);
        let p_b = Matrix3::from_diagonal(&Vector3::new(0.09, 0.06, 0.01));
        let a = fused(fuse(&x_c, &p_c, &x_b, &p_b, f64::INFINITY).unwrap());
        let independent = CorrelatedErrors { camera_cov_m2: p_c, cross_cov_m2: Matrix3::zeros() };
        let b = fused(fuse_correlated(&x_c, &p_c, &x_b, &p_b, &independent, f64::INFINITY).unwrap());
        assert!((a.0 - b.0).norm() < 1e-12 && (a.1 - b.1).norm() < 1e-12 && (a.2 - b.2).abs() < 1e-9);
        // Errors that move together: the same estimate, a larger covariance than eq 32's.
        let together = CorrelatedErrors { camera_cov_m2: p_c, cross_cov_m2: p_c * 0.5 };
        let (x, p, _) = fused(fuse_correlated(&x_c, &p_c, &x_b, &p_b, &together, f64::INFINITY).unwrap());
        assert!((x - a.0).norm() < 1e-12 && p.trace() > a.1.trace(), "{p} against {}", a.1);
        // Fully correlated equal estimates gain nothing from fusing.
        let same = CorrelatedErrors { camera_cov_m2: p_b, cross_cov_m2: p_b * (1.0 - 1e-9) };
        let (_, p, _) = fused(fuse_correlated(&x_c, &p_b, &x_b, &p_b, &same, f64::INFINITY).unwrap());
        assert!((p - p_b).norm() < 1e-6, "{p}");
        // A cross-covariance no joint covariance can have is refused.
        let impossible = CorrelatedErrors { camera_cov_m2: p_c, cross_cov_m2: p_b * 3.0 };
        assert!(matches!(
            fuse_correlated(&x_c, &p_c, &x_b, &p_b, &impossible, f64::INFINITY),
            Err(FusionError::NotPositiveDefinite(_))
        ));
    }

    #[test]
    fn correlated_fusion_matches_a_monte_carlo_of_correlated_errors() {
        // e_b ~ N(0, P_b); e_c = 0.6·e_b + n, n ~ N(0, Q): P̃_c = 0.36 P_b + Q, P_cb = 0.6 P_b. The
        // weights come from a camera covariance taken as 0.2 P_b (too small, as when the fixes
        // behind a transform are taken as independent).
        let p_b = Matrix3::from_diagonal(&Vector3::new(0.09, 0.04, 0.01));
        let q = Matrix3::from_diagonal(&Vector3::new(0.01, 0.02, 0.005));
        let errors = CorrelatedErrors { camera_cov_m2: p_b * 0.36 + q, cross_cov_m2: p_b * 0.6 };
        let mut s = 99u64;
        let mut g = || {
            let mut u = || {
                s = s.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
                ((s >> 11) as f64 + 0.5) / (1u64 << 53) as f64
            };
            let (u1, u2) = (u(), u());
            (-2.0 * u1.ln()).sqrt() * (2.0 * std::f64::consts::PI * u2).cos()
        };
        let (mut sum, n) = (Matrix3::zeros(), 20000);
        let mut p = Matrix3::zeros();
        for _ in 0..n {
            let e_b = Vector3::new(g() * 0.3, g() * 0.2, g() * 0.1);
            let e_c = e_b * 0.6 + Vector3::new(g() * 0.1, g() * 0.02f64.sqrt(), g() * 0.005f64.sqrt());
            let (x, pp, _) = fused(fuse_correlated(&e_c, &(p_b * 0.2), &e_b, &p_b, &errors, f64::INFINITY).unwrap());
            sum += x * x.transpose();
            p = pp;
        }
        let empirical = sum / n as f64;
        for i in 0..3 {
            assert!(
                (empirical[(i, i)] / p[(i, i)] - 1.0).abs() < 0.05,
                "axis {i}: {} against {}",
                empirical[(i, i)],
                p[(i, i)]
            );
        }
        // Taken as independent, eq 32 would report far less than the errors have.
        let (_, p32, _) = fused(fuse(&Vector3::zeros(), &(p_b * 0.2), &Vector3::zeros(), &p_b, f64::INFINITY).unwrap());
        assert!(p32[(0, 0)] < 0.6 * empirical[(0, 0)], "{} against {}", p32[(0, 0)], empirical[(0, 0)]);
    }

    #[test]
    fn equal_scalar_covariances_give_the_midpoint_and_half_the_covariance() {
        let p = Matrix3::identity() * 0.04;
        let (x, c, d2) =
            fused(fuse(&Vector3::new(1.0, 2.0, 3.0), &p, &Vector3::new(1.2, 1.8, 3.0), &p, f64::INFINITY).unwrap());
        assert!((x - Vector3::new(1.1, 1.9, 3.0)).norm() < 1e-12, "{x}");
        assert!((c - Matrix3::identity() * 0.02).amax() < 1e-15, "{c}");
        // d² = |Δ|² / (2·0.04) = 0.08 / 0.08 = 1
        assert!((d2 - 1.0).abs() < 1e-12, "{d2}");
    }

    #[test]
    fn a_much_smaller_covariance_dominates() {
        let x_c = Vector3::new(10.0, 0.0, -2.0);
        let x_b = Vector3::new(10.5, 0.3, -2.2);
        let (x, c, _) =
            fused(fuse(&x_c, &(Matrix3::identity() * 1e-6), &x_b, &(Matrix3::identity() * 1.0), 1e9).unwrap());
        assert!((x - x_c).norm() < 1e-5, "{x}");
        assert!((c - Matrix3::identity() * 1e-6).amax() < 1e-11, "{c}");
    }

    #[test]
    fn an_anisotropic_two_axis_case_matches_the_hand_computation() {
        // Camera accurate along x (σ² 1), poor along y (σ² 9); buoy the opposite (σ² 9 and 1); z equal (4, 4).
        // Per axis (diagonal covariances): x_v = (P_b·x_c + P_c·x_b)/(P_b + P_c), P_v = P_b·P_c/(P_b + P_c).
        //   x: (9·0 + 1·10)/10 = 1.0,  P = 9·1/10 = 0.9
        //   y: (1·0 + 9·10)/10 = 9.0,  P = 0.9
        //   z: (4·0 + 4·2)/8   = 1.0,  P = 2.0
        // d² = 10²/10 + 10²/10 + 2²/8 = 20.5
        let p_c = Matrix3::from_diagonal(&Vector3::new(1.0, 9.0, 4.0));
        let p_b = Matrix3::from_diagonal(&Vector3::new(9.0, 1.0, 4.0));
        let (x, c, d2) = fused(fuse(&Vector3::zeros(), &p_c, &Vector3::new(10.0, 10.0, 2.0), &p_b, 25.0).unwrap());
        assert!((x - Vector3::new(1.0, 9.0, 1.0)).norm() < 1e-12, "{x}");
        assert!((c - Matrix3::from_diagonal(&Vector3::new(0.9, 0.9, 2.0))).amax() < 1e-12, "{c}");
        assert!((d2 - 20.5).abs() < 1e-12);
    }

    #[test]
    fn a_correlated_case_matches_the_information_form() {
        let p_c = Matrix3::new(2.0, 0.5, 0.1, 0.5, 1.0, -0.2, 0.1, -0.2, 0.7);
        let p_b = Matrix3::new(0.6, -0.1, 0.0, -0.1, 0.9, 0.3, 0.0, 0.3, 1.5);
        let (x_c, x_b) = (Vector3::new(1.0, 2.0, 3.0), Vector3::new(1.5, 1.0, 2.5));
        let (x, c, _) = fused(fuse(&x_c, &p_c, &x_b, &p_b, f64::INFINITY).unwrap());
        let (ic, ib) = (p_c.try_inverse().unwrap(), p_b.try_inverse().unwrap());
        let p = (ic + ib).try_inverse().unwrap();
        assert!((c - p).amax() < 1e-12);
        assert!((x - p * (ic * x_c + ib * x_b)).norm() < 1e-12);
        assert_eq!(c, c.transpose());
    }

    #[test]
    fn the_gate_rejects_a_far_pair() {
        let p = Matrix3::identity() * 0.01;
        let out = fuse(&Vector3::zeros(), &p, &Vector3::new(1.0, 0.0, 0.0), &p, chi2_3_quantile(0.99).unwrap());
        // d² = 1 / 0.02 = 50 > 11.345
        match out.unwrap() {
            FuseOutcome::NoOverlap { mahalanobis } => assert!((mahalanobis - 50.0).abs() < 1e-9),
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn the_fused_covariance_is_below_both_inputs_in_the_loewner_order() {
        let p_c = Matrix3::new(2.0, 0.5, 0.1, 0.5, 1.0, -0.2, 0.1, -0.2, 0.7);
        let p_b = Matrix3::new(0.6, -0.1, 0.0, -0.1, 0.9, 0.3, 0.0, 0.3, 1.5);
        let (_, c, _) = fused(fuse(&Vector3::zeros(), &p_c, &Vector3::zeros(), &p_b, 1.0).unwrap());
        for input in [p_c, p_b] {
            let min_eig = SymmetricEigen::new(input - c).eigenvalues.min();
            assert!(min_eig >= -1e-12, "input − fused has eigenvalue {min_eig}");
        }
        assert!(SymmetricEigen::new(c).eigenvalues.min() > 0.0);
    }

    #[test]
    fn non_finite_and_non_positive_definite_inputs_are_errors() {
        let p = Matrix3::identity();
        let z = Vector3::zeros();
        let nan = Vector3::new(f64::NAN, 0.0, 0.0);
        assert_eq!(fuse(&nan, &p, &z, &p, 10.0), Err(FusionError::NonFinite("camera position")));
        assert_eq!(fuse(&z, &p, &nan, &p, 10.0), Err(FusionError::NonFinite("buoy position")));
        let mut pn = p;
        pn[(1, 1)] = f64::INFINITY;
        assert_eq!(fuse(&z, &pn, &z, &p, 10.0), Err(FusionError::NonFinite("camera covariance")));
        // Indefinite although the sum (diag 3, 1, 3) would be positive definite.
        let indefinite = Matrix3::from_diagonal(&Vector3::new(1.0, -1.0, 1.0));
        assert_eq!(
            fuse(&z, &indefinite, &z, &(p * 2.0), 10.0),
            Err(FusionError::NotPositiveDefinite("camera covariance"))
        );
        let asym = Matrix3::new(1.0, 0.5, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0);
        assert_eq!(fuse(&z, &p, &z, &asym, 10.0), Err(FusionError::NotPositiveDefinite("buoy covariance")));
        let rank1 = Vector3::new(1.0, 1.0, 0.0) * Vector3::new(1.0, 1.0, 0.0).transpose();
        assert_eq!(fuse(&z, &rank1, &z, &rank1, 10.0), Err(FusionError::NotPositiveDefinite("sum of the covariances")));
        assert!(matches!(fuse(&z, &p, &z, &p, f64::NAN), Err(FusionError::InvalidArgument(_))));
        assert!(matches!(fuse(&z, &p, &z, &p, -1.0), Err(FusionError::InvalidArgument(_))));
    }

    #[test]
    fn a_zero_covariance_on_one_side_is_exact_knowledge() {
        let (x, c, _) = fused(
            fuse(&Vector3::new(1.0, 1.0, 1.0), &Matrix3::zeros(), &Vector3::zeros(), &Matrix3::identity(), 10.0)
                .unwrap(),
        );
        assert!((x - Vector3::new(1.0, 1.0, 1.0)).norm() < 1e-12);
        assert!(c.amax() < 1e-12);
    }

    #[test]
    fn chi2_3_quantiles_match_the_tables() {
        for (p, q) in [(0.5, 2.365_974), (0.95, 7.814_728), (0.99, 11.344_867), (0.999, 16.266_236)] {
            let x = chi2_3_quantile(p).unwrap();
            assert!((x - q).abs() < 1e-5, "χ²₃({p}) = {x}, table {q}");
            assert!((chi2_3_cdf(x) - p).abs() < 1e-12);
        }
        for bad in [0.0, 1.0, -0.1, f64::NAN, 2.0] {
            assert_eq!(chi2_3_quantile(bad), None);
        }
        assert_eq!(chi2_3_cdf(0.0), 0.0);
        assert_eq!(chi2_3_cdf(f64::INFINITY), 1.0);
    }
}
