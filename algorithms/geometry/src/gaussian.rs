//! Gaussians in 3-D: checking a covariance, and the Bhattacharyya distance between two Gaussians
//! (used to associate landmarks and obstacles: [6D] §VI, Bhattacharyya 1943).

use nalgebra::{Cholesky, Matrix3, SymmetricEigen, Vector3};

/// What is wrong with a Gaussian.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum GaussianError {
    /// A value is NaN or infinite (which one: the argument's name).
    #[error("{0} is not finite")]
    NonFinite(&'static str),
    /// A covariance is not symmetric positive (semi-)definite.
    #[error("{0} is not symmetric positive definite")]
    NotPositiveDefinite(&'static str),
}

/// Checks that `p` is finite, symmetric (to 1e-9 relative) and positive semi-definite (smallest
/// eigenvalue ≥ −1e-9 of the largest); returns it symmetrised. `what` names it in the error.
pub fn check_covariance(what: &'static str, p: &Matrix3<f64>) -> Result<Matrix3<f64>, GaussianError> {
    if !p.iter().all(|v| v.is_finite()) {
        return Err(GaussianError::NonFinite(what));
    }
    let scale = p.amax();
    if (p - p.transpose()).amax() > 1e-9 * scale {
        return Err(GaussianError::NotPositiveDefinite(what));
    }
    let s = (p + p.transpose()) * 0.5;
    if scale == 0.0 {
        return Ok(s);
    }
    let eig = SymmetricEigen::new(s).eigenvalues;
    if eig.min() < -1e-9 * eig.amax() {
        return Err(GaussianError::NotPositiveDefinite(what));
    }
    Ok(s)
}

/// Bhattacharyya distance of two Gaussians:
/// D_B = ⅛·Δᵀ·P⁻¹·Δ + ½·ln(det P / √(det P₁·det P₂)), P = (P₁ + P₂)/2, Δ = m₁ − m₂.
/// Errors: non-finite input; a covariance that is not symmetric positive definite.
pub fn bhattacharyya(
    m1: &Vector3<f64>,
    p1: &Matrix3<f64>,
    m2: &Vector3<f64>,
    p2: &Matrix3<f64>,
) -> Result<f64, GaussianError> {
    if !m1.iter().chain(m2.iter()).all(|v| v.is_finite()) {
        return Err(GaussianError::NonFinite("mean"));
    }
    let p1 = check_covariance("first covariance", p1)?;
    let p2 = check_covariance("second covariance", p2)?;
    let log_det = |p: &Matrix3<f64>, what: &'static str| -> Result<(f64, Cholesky<f64, nalgebra::U3>), GaussianError> {
        let chol = Cholesky::new(*p).ok_or(GaussianError::NotPositiveDefinite(what))?;
        let ld = 2.0 * chol.l_dirty().diagonal().iter().map(|d| d.ln()).sum::<f64>();
        if !ld.is_finite() {
            return Err(GaussianError::NotPositiveDefinite(what));
        }
        Ok((ld, chol))
    };
    let (ld1, _) = log_det(&p1, "first covariance")?;
    let (ld2, _) = log_det(&p2, "second covariance")?;
    let (ld, chol) = log_det(&((p1 + p2) * 0.5), "mean covariance")?;
    let diff = m1 - m2;
    Ok(diff.dot(&chol.solve(&diff)) / 8.0 + 0.5 * (ld - 0.5 * (ld1 + ld2)))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bhattacharyya_of_known_gaussians_and_bad_input() {
        let z = Vector3::zeros();
        let a = Matrix3::identity();
        let b = Matrix3::identity() * 2.0;
        assert!(bhattacharyya(&z, &a, &z, &a).unwrap().abs() < 1e-15);
        // Same covariance: only the Mahalanobis term, ⅛·Δᵀ·P⁻¹·Δ = ⅛·4 = 0.5.
        assert!((bhattacharyya(&z, &a, &Vector3::new(2.0, 0.0, 0.0), &a).unwrap() - 0.5).abs() < 1e-14);
        // Same mean: ½·ln(det P / √(det P₁ det P₂)) with P = 1.5 I: ½·ln(3.375 / √8).
        let expected = 0.5 * (3.375f64 / 8f64.sqrt()).ln();
        assert!((bhattacharyya(&z, &a, &z, &b).unwrap() - expected).abs() < 1e-14);
        assert_eq!(
            bhattacharyya(&z, &Matrix3::zeros(), &z, &a),
            Err(GaussianError::NotPositiveDefinite("first covariance"))
        );
        assert_eq!(bhattacharyya(&Vector3::new(f64::NAN, 0.0, 0.0), &a, &z, &a), Err(GaussianError::NonFinite("mean")));
        let mut asym = a;
        asym[(0, 1)] = 0.5;
        assert!(check_covariance("p", &asym).is_err());
    }
}
