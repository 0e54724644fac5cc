//! How correlated the buoy fixes' errors are from one fix to the next, estimated from alignment
//! residuals, and what that does to an estimate made from several fixes (docs/EQUATIONS.md §5.3).
//!
//! A buoy EKF's fixes are not independent: its errors come from range biases, the geometry and
//! the odometry between ranges, which change slowly. A transform fitted to the n fixes of a short
//! window then averages fewer than n independent errors, and a camera position mapped with it
//! shares errors with the buoy fix it is fused with. Both follow from the fixes' autocorrelation
//! ρₖ (k fixes apart):
//! - the variance of a mean of n fixes is (σ²/n)·(1 + 2 Σₖ₌₁ⁿ⁻¹ (1 − k/n)·ρₖ) (the inflation of
//!   the variance of a mean of correlated samples; Bayley & Hammersley 1946), instead of σ²/n;
//! - the covariance between that mean and the fix i is σ²·(1/n) Σⱼ ρ|i−j|.
//!
//! ρₖ is the pooled sample autocorrelation of the residuals r = g − T·l of whole local maps'
//! alignments (their transform rests on many fixes, so the residuals keep the fixes' slow errors),
//! cut at the first lag where it is no longer positive (Geyer's initial positive sequence, 1992).
//! The residuals also hold the local path's drift, which is slow as well: the correlation comes
//! out longer rather than shorter, and the covariances larger rather than smaller.

use nalgebra::Vector3;

/// The fixes' error autocorrelation by lag (in fixes): ρ₀ = 1, then ρ₁, ρ₂, … while positive.
#[derive(Debug, Clone, PartialEq)]
pub struct FixCorrelation {
    rho: Vec<f64>,
}

impl Default for FixCorrelation {
    /// Independent fixes (ρₖ = 0 for k ≥ 1).
    fn default() -> Self {
        Self { rho: vec![1.0] }
    }
}

impl FixCorrelation {
    /// The pooled autocorrelation of several residual sequences (each in time order, one per
    /// local map; lags never cross from one sequence to the next), up to `max_lag` fixes.
    /// Independent fixes when there are fewer than 8 residuals in all or they are all zero.
    pub fn from_residuals<'a>(sequences: impl IntoIterator<Item = &'a [Vector3<f64>]>, max_lag: usize) -> Self {
        let seqs: Vec<&[Vector3<f64>]> = sequences.into_iter().collect();
        let count: usize = seqs.iter().map(|s| s.len()).sum();
        // Each sequence about its own mean (a local map's residuals need not average to zero
        // when its transform was fitted with a prior).
        let centred: Vec<Vec<Vector3<f64>>> = seqs
            .iter()
            .filter(|s| !s.is_empty())
            .map(|s| {
                let mean = s.iter().sum::<Vector3<f64>>() / s.len() as f64;
                s.iter().map(|r| r - mean).collect()
            })
            .collect();
        let c0: f64 = centred.iter().flatten().map(|r| r.norm_squared()).sum::<f64>();
        if count < 8 || c0 <= 0.0 || !c0.is_finite() {
            return Self::default();
        }
        let c0 = c0 / count as f64;
        let mut rho = vec![1.0];
        for k in 1..=max_lag {
            let (mut sum, mut n) = (0.0, 0usize);
            for s in &centred {
                for j in 0..s.len().saturating_sub(k) {
                    sum += s[j].dot(&s[j + k]);
                    n += 1;
                }
            }
            if n < 4 {
                break;
            }
            let r = sum / n as f64 / c0;
            if r <= 0.0 || !r.is_finite() {
                break;
            }
            rho.push(r.min(1.0));
        }
        Self { rho }
    }

    /// ρ at a lag of `lag` fixes (fractional lags interpolated linearly; 0 beyond the sequence).
    pub fn at(&self, lag: f64) -> f64 {
        let lag = lag.abs();
        let k = lag.floor() as usize;
        let (a, b) = (self.rho.get(k).copied().unwrap_or(0.0), self.rho.get(k + 1).copied().unwrap_or(0.0));
        a + (b - a) * (lag - k as f64)
    }

    /// The autocorrelation by lag, ρ₀ = 1 first.
    pub fn rho(&self) -> &[f64] {
        &self.rho
    }

    /// How much larger the variance of the mean of `n` consecutive fixes is than for independent
    /// fixes: 1 + 2 Σₖ₌₁ⁿ⁻¹ (1 − k/n)·ρₖ, in [1, n].
    pub fn mean_inflation(&self, n: usize) -> f64 {
        if n < 2 {
            return 1.0;
        }
        let s: f64 = (1..n).map(|k| (1.0 - k as f64 / n as f64) * self.at(k as f64)).sum();
        (1.0 + 2.0 * s).clamp(1.0, n as f64)
    }

    /// The correlation between the mean of the fixes at positions `0..n` and a fix at position
    /// `at` (fractional: between two fixes), as a share of one fix's variance:
    /// (1/n) Σⱼ ρ|at − j|, in [0, 1].
    pub fn with_mean(&self, n: usize, at: f64) -> f64 {
        if n == 0 {
            return 0.0;
        }
        ((0..n).map(|j| self.at(at - j as f64)).sum::<f64>() / n as f64).clamp(0.0, 1.0)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// An AR(1) sequence x_{k+1} = a·x_k + √(1−a²)·w (ρₖ = aᵏ) from a fixed generator.
    fn ar1(a: f64, n: usize, seed: u64) -> Vec<Vector3<f64>> {
        let mut s = seed;
        let mut gauss = || {
            // Box-Muller from a 64-bit LCG.
            let mut u = || {
                s = s.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
                ((s >> 11) as f64 + 0.5) / (1u64 << 53) as f64
            };
            let (u1, u2) = (u(), u());
            (-2.0 * u1.ln()).sqrt() * (2.0 * std::f64::consts::PI * u2).cos()
        };
        let mut x = Vector3::new(gauss(), gauss(), gauss());
        let q = (1.0 - a * a).sqrt();
        (0..n)
            .map(|_| {
                x = x * a + Vector3::new(gauss(), gauss(), gauss()) * q;
                x
            })
            .collect()
    }

    #[test]
    fn recovers_an_ar1_correlation_and_its_variance_inflation() {
        let seqs: Vec<Vec<Vector3<f64>>> = (0..20).map(|i| ar1(0.8, 400, 17 + i)).collect();
        let c = FixCorrelation::from_residuals(seqs.iter().map(|s| s.as_slice()), 40);
        for k in 1..5 {
            assert!(
                (c.at(k as f64) - 0.8f64.powi(k)).abs() < 0.05,
                "rho_{k} {} against {}",
                c.at(k as f64),
                0.8f64.powi(k)
            );
        }
        // The inflation of a mean of 20 fixes for ρₖ = 0.8ᵏ: 1 + 2 Σ (1 − k/20) 0.8ᵏ = 7.4.
        let exact = 1.0 + 2.0 * (1..20).map(|k| (1.0 - k as f64 / 20.0) * 0.8f64.powi(k)).sum::<f64>();
        assert!((c.mean_inflation(20) - exact).abs() < 0.1 * exact, "{} against {exact}", c.mean_inflation(20));
        // And it is what the spread of the means of 20 shows.
        let means: Vec<Vector3<f64>> =
            seqs.iter().flat_map(|s| s.chunks_exact(20).map(|w| w.iter().sum::<Vector3<f64>>() / 20.0)).collect();
        let var_of_mean = means.iter().map(|m| m.norm_squared()).sum::<f64>() / means.len() as f64 / 3.0;
        let predicted = exact / 20.0;
        assert!((var_of_mean / predicted - 1.0).abs() < 0.25, "variance of the mean {var_of_mean} against {predicted}");
    }

    #[test]
    fn independent_fixes_neither_inflate_nor_correlate_with_a_mean_beyond_their_own_share() {
        let seqs: Vec<Vec<Vector3<f64>>> = (0..10).map(|i| ar1(0.0, 400, 5 + i)).collect();
        let c = FixCorrelation::from_residuals(seqs.iter().map(|s| s.as_slice()), 40);
        assert!(c.mean_inflation(20) < 1.2, "{:?}", c.rho());
        // A fix inside a window of 20 independent ones: its own 1/20.
        assert!((c.with_mean(20, 7.0) - 0.05).abs() < 0.02);
        // Too little data, or none: independent.
        assert_eq!(FixCorrelation::from_residuals([&[Vector3::zeros(); 3][..]], 10), FixCorrelation::default());
        assert_eq!(FixCorrelation::default().mean_inflation(20), 1.0);
    }

    #[test]
    fn fully_correlated_fixes_are_one_fix() {
        let c = FixCorrelation { rho: vec![1.0; 50] };
        assert!((c.mean_inflation(20) - 20.0).abs() < 1e-9);
        assert!((c.with_mean(20, 3.5) - 1.0).abs() < 1e-9);
        assert!((c.at(2.5) - 1.0).abs() < 1e-12);
    }
}
