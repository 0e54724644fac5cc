//! Summary statistics of samples: the one percentile rule every stage and bench reports with.

/// The `q`-quantile (`q` in [0, 1]) of samples sorted ascending: the sample at rank
/// `round((n − 1)·q)` (p50 of 1..=5 is 3, p100 is the maximum). `None` for no samples.
pub fn percentile_sorted(sorted: &[f64], q: f64) -> Option<f64> {
    if sorted.is_empty() {
        return None;
    }
    let rank = ((sorted.len() as f64 - 1.0) * q.clamp(0.0, 1.0)).round() as usize;
    sorted.get(rank).copied()
}

/// Sorts `samples` (NaN last) and returns their p50, p99 and maximum (NaN for no samples).
pub fn p50_p99_max(samples: &mut [f64]) -> (f64, f64, f64) {
    samples.sort_by(f64::total_cmp);
    let q = |q| percentile_sorted(samples, q).unwrap_or(f64::NAN);
    (q(0.5), q(0.99), q(1.0))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn nearest_rank_percentiles() {
        let v = [1.0, 2.0, 3.0, 4.0, 5.0];
        assert_eq!(percentile_sorted(&v, 0.5), Some(3.0));
        assert_eq!(percentile_sorted(&v, 1.0), Some(5.0));
        assert_eq!(percentile_sorted(&v, 0.0), Some(1.0));
        assert_eq!(percentile_sorted(&v, 0.99), Some(5.0));
        assert_eq!(percentile_sorted(&[], 0.5), None);
        let mut w = vec![5.0, 1.0, 3.0];
        assert_eq!(p50_p99_max(&mut w), (3.0, 5.0, 5.0));
        assert!(p50_p99_max(&mut []).0.is_nan());
    }
}

/// The quantile z of the standard normal distribution with P(Z ≤ z) = `p`, p ∈ (0, 1)
/// (Acklam's rational approximation, relative error below 1.2·10⁻⁹); `None` outside (0, 1).
pub fn normal_quantile(p: f64) -> Option<f64> {
    if !(p > 0.0 && p < 1.0) {
        return None;
    }
    const A: [f64; 6] = [
        -3.969_683_028_665_376e1,
        2.209_460_984_245_205e2,
        -2.759_285_104_469_687e2,
        1.383_577_518_672_69e2,
        -3.066_479_806_614_716e1,
        2.506_628_277_459_239,
    ];
    const B: [f64; 5] = [
        -5.447_609_879_822_406e1,
        1.615_858_368_580_409e2,
        -1.556_989_798_598_866e2,
        6.680_131_188_771_972e1,
        -1.328_068_155_288_572e1,
    ];
    const C: [f64; 6] = [
        -7.784_894_002_430_293e-3,
        -3.223_964_580_411_365e-1,
        -2.400_758_277_161_838,
        -2.549_732_539_343_734,
        4.374_664_141_464_968,
        2.938_163_982_698_783,
    ];
    const D: [f64; 4] =
        [7.784_695_709_041_462e-3, 3.224_671_290_700_398e-1, 2.445_134_137_142_996, 3.754_408_661_907_416];
    let tail = |q: f64| {
        (((((C[0] * q + C[1]) * q + C[2]) * q + C[3]) * q + C[4]) * q + C[5])
            / ((((D[0] * q + D[1]) * q + D[2]) * q + D[3]) * q + 1.0)
    };
    let p_low = 0.02425;
    Some(if p < p_low {
        tail((-2.0 * p.ln()).sqrt())
    } else if p > 1.0 - p_low {
        -tail((-2.0 * (1.0 - p).ln()).sqrt())
    } else {
        let q = p - 0.5;
        let r = q * q;
        (((((A[0] * r + A[1]) * r + A[2]) * r + A[3]) * r + A[4]) * r + A[5]) * q
            / (((((B[0] * r + B[1]) * r + B[2]) * r + B[3]) * r + B[4]) * r + 1.0)
    })
}

/// The quantile of χ² with `k` degrees of freedom at `p` by the Wilson–Hilferty approximation
/// k·(1 − 2/(9k) + z_p·√(2/(9k)))³ (within 1 % of the exact value from k = 30 on; 16 % low at
/// the lower 2.5 % point of k = 3). `None` for k = 0 or p outside (0, 1).
pub fn chi2_quantile_wh(k: usize, p: f64) -> Option<f64> {
    if k == 0 {
        return None;
    }
    let (k, z) = (k as f64, normal_quantile(p)?);
    let c = 2.0 / (9.0 * k);
    Some(k * (1.0 - c + z * c.sqrt()).powi(3).max(0.0))
}

/// Bar-Shalom's consistency interval for a mean NEES or NIS (Bar-Shalom, Li, Kirubarajan,
/// "Estimation with Applications to Tracking and Navigation", 2001, §5.4.2): the mean of `n`
/// independent χ² samples of `d` degrees of freedom lies, for a consistent estimator, in
/// [χ²_{dn}((1 − c)/2), χ²_{dn}((1 + c)/2)] / n with probability `c` (`confidence`). For 390
/// three-dimensional samples at 95 %: [2.76, 3.25]. The samples of one trajectory are
/// correlated in time, which the test does not model: it is stricter than its nominal level.
pub fn mean_chi2_interval(d: usize, n: usize, confidence: f64) -> Option<(f64, f64)> {
    if n == 0 || !(confidence > 0.0 && confidence < 1.0) {
        return None;
    }
    let k = d.checked_mul(n)?;
    let lo = chi2_quantile_wh(k, (1.0 - confidence) / 2.0)?;
    let hi = chi2_quantile_wh(k, (1.0 + confidence) / 2.0)?;
    Some((lo / n as f64, hi / n as f64))
}

#[cfg(test)]
mod consistency_tests {
    use super::*;

    #[test]
    fn quantiles_match_the_tables() {
        for (p, z) in [(0.975, 1.959_964), (0.5, 0.0), (0.01, -2.326_348), (0.999, 3.090_232)] {
            assert!((normal_quantile(p).unwrap() - z).abs() < 1e-5, "{p}");
        }
        // χ²(100): 74.222 and 129.561 (tables); χ²(3) 97.5 %: 9.348.
        assert!((chi2_quantile_wh(100, 0.025).unwrap() - 74.222).abs() < 0.1);
        assert!((chi2_quantile_wh(100, 0.975).unwrap() - 129.561).abs() < 0.1);
        assert!((chi2_quantile_wh(3, 0.975).unwrap() - 9.348).abs() < 0.05);
        assert_eq!(normal_quantile(1.0), None);
        assert_eq!(chi2_quantile_wh(0, 0.5), None);
    }

    #[test]
    fn the_interval_of_a_mean_narrows_with_the_samples() {
        let (lo1, hi1) = mean_chi2_interval(3, 1, 0.95).unwrap();
        let (lo, hi) = mean_chi2_interval(3, 390, 0.95).unwrap();
        assert!(lo1 < 0.3 && hi1 > 9.0, "one sample: about χ²₃'s own interval");
        assert!((lo - 2.76).abs() < 0.01 && (hi - 3.25).abs() < 0.01, "[{lo}, {hi}]");
        // A mean of 0.96 over 390 poses (covariances 3× too large) is far outside it.
        assert!(0.96 < lo);
        assert_eq!(mean_chi2_interval(3, 0, 0.95), None);
    }
}
