//! Closed-form Cholesky algebra of 3×3 symmetric positive-definite matrices: factorisation,
//! solve, Mahalanobis distance, inverse and log-determinant. FastSLAM factorises tens of
//! thousands of 3×3 innovation covariances per frame, and nalgebra's generic Cholesky costs
//! several times more at this size (it was 20 % of a frame's time, measured with perf on
//! `stereo_bench`).

use nalgebra::{Matrix3, Vector3};

/// The Cholesky factor L (lower, S = L·Lᵀ) of a 3×3 symmetric positive-definite matrix.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Chol3 {
    /// l00, l10, l11, l20, l21, l22.
    l: [f64; 6],
}

impl Chol3 {
    /// Factorises `s` (its lower triangle is read); `None` unless positive definite (NaN
    /// included).
    #[inline]
    pub fn new(s: &Matrix3<f64>) -> Option<Self> {
        let a00 = s[(0, 0)];
        if a00.partial_cmp(&0.0) != Some(std::cmp::Ordering::Greater) {
            return None;
        }
        let l00 = a00.sqrt();
        let l10 = s[(1, 0)] / l00;
        let l20 = s[(2, 0)] / l00;
        let d1 = s[(1, 1)] - l10 * l10;
        if d1.partial_cmp(&0.0) != Some(std::cmp::Ordering::Greater) {
            return None;
        }
        let l11 = d1.sqrt();
        let l21 = (s[(2, 1)] - l20 * l10) / l11;
        let d2 = s[(2, 2)] - l20 * l20 - l21 * l21;
        if d2.partial_cmp(&0.0) != Some(std::cmp::Ordering::Greater) {
            return None;
        }
        Some(Self { l: [l00, l10, l11, l20, l21, d2.sqrt()] })
    }

    /// y = L⁻¹·b.
    #[inline]
    fn forward(&self, b: &Vector3<f64>) -> Vector3<f64> {
        let [l00, l10, l11, l20, l21, l22] = self.l;
        let y0 = b.x / l00;
        let y1 = (b.y - l10 * y0) / l11;
        let y2 = (b.z - l20 * y0 - l21 * y1) / l22;
        Vector3::new(y0, y1, y2)
    }

    /// L⁻¹·B column by column: with W = L⁻¹·B, Bᵀ·S⁻¹·B = Wᵀ·W (the whitened Jacobian).
    #[inline]
    pub fn whiten<const C: usize>(&self, b: &nalgebra::SMatrix<f64, 3, C>) -> nalgebra::SMatrix<f64, 3, C> {
        let mut w = nalgebra::SMatrix::<f64, 3, C>::zeros();
        for c in 0..C {
            w.set_column(c, &self.forward(&b.column(c).into_owned()));
        }
        w
    }

    /// L⁻¹·b.
    #[inline]
    pub fn whiten_vector(&self, b: &Vector3<f64>) -> Vector3<f64> {
        self.forward(b)
    }

    /// S⁻¹·b.
    #[inline]
    pub fn solve(&self, b: &Vector3<f64>) -> Vector3<f64> {
        let [l00, l10, l11, l20, l21, l22] = self.l;
        let y = self.forward(b);
        let x2 = y.z / l22;
        let x1 = (y.y - l21 * x2) / l11;
        let x0 = (y.x - l10 * x1 - l20 * x2) / l00;
        Vector3::new(x0, x1, x2)
    }

    /// bᵀ·S⁻¹·b.
    #[inline]
    pub fn mahalanobis(&self, b: &Vector3<f64>) -> f64 {
        self.forward(b).norm_squared()
    }

    /// S⁻¹.
    #[inline]
    pub fn inverse(&self) -> Matrix3<f64> {
        let [l00, l10, l11, l20, l21, l22] = self.l;
        // M = L⁻¹ (lower), then S⁻¹ = Mᵀ·M.
        let m00 = 1.0 / l00;
        let m11 = 1.0 / l11;
        let m22 = 1.0 / l22;
        let m10 = -l10 * m00 * m11;
        let m21 = -l21 * m11 * m22;
        let m20 = -(l20 * m00 + l21 * m10) * m22;
        let s00 = m00 * m00 + m10 * m10 + m20 * m20;
        let s01 = m10 * m11 + m20 * m21;
        let s02 = m20 * m22;
        let s11 = m11 * m11 + m21 * m21;
        let s12 = m21 * m22;
        let s22 = m22 * m22;
        Matrix3::new(s00, s01, s02, s01, s11, s12, s02, s12, s22)
    }

    /// ln |S|.
    #[inline]
    pub fn log_det(&self) -> f64 {
        2.0 * (self.l[0] * self.l[2] * self.l[5]).ln()
    }

    /// L.
    pub fn l(&self) -> Matrix3<f64> {
        let [l00, l10, l11, l20, l21, l22] = self.l;
        Matrix3::new(l00, 0.0, 0.0, l10, l11, 0.0, l20, l21, l22)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    proptest! {
        #[test]
        fn agrees_with_nalgebra(v in proptest::collection::vec(-3.0..3.0f64, 9), d in proptest::collection::vec(0.01..5.0f64, 3), b in proptest::collection::vec(-10.0..10.0f64, 3)) {
            let a = Matrix3::from_row_slice(&v);
            let s = a * a.transpose() + Matrix3::from_diagonal(&Vector3::from_row_slice(&d));
            let b = Vector3::from_row_slice(&b);
            let ours = Chol3::new(&s).unwrap();
            let theirs = nalgebra::Cholesky::new(s).unwrap();
            let scale = 1.0 + s.norm();
            prop_assert!((ours.l() - theirs.l()).norm() < 1e-9 * scale);
            prop_assert!((ours.solve(&b) - theirs.solve(&b)).norm() < 1e-8 * (1.0 + theirs.solve(&b).norm()));
            prop_assert!((ours.mahalanobis(&b) - b.dot(&theirs.solve(&b))).abs() < 1e-8 * (1.0 + b.dot(&theirs.solve(&b))));
            prop_assert!((ours.inverse() - theirs.inverse()).norm() < 1e-8 * (1.0 + theirs.inverse().norm()));
            prop_assert!((ours.log_det() - s.determinant().ln()).abs() < 1e-9 * (1.0 + s.determinant().ln().abs()));
        }
    }

    #[test]
    fn refuses_what_is_not_positive_definite() {
        assert!(Chol3::new(&-Matrix3::identity()).is_none());
        assert!(Chol3::new(&Matrix3::from_diagonal(&Vector3::new(1.0, 0.0, 1.0))).is_none());
        assert!(Chol3::new(&(Matrix3::identity() * f64::NAN)).is_none());
        let mut s = Matrix3::identity();
        s[(2, 0)] = 2.0;
        s[(0, 2)] = 2.0;
        assert!(Chol3::new(&s).is_none());
    }
}
