//! χ² distribution with 1, 2 or 3 degrees of freedom: CDF and quantile, for the innovation gates.

/// The complementary error function (Numerical Recipes `erfcc`, fractional error < 1.2e-7).
fn erfc(x: f64) -> f64 {
    let z = x.abs();
    let t = 1.0 / (1.0 + 0.5 * z);
    let poly = -z * z - 1.265_512_23
        + t * (1.000_023_68
            + t * (0.374_091_96
                + t * (0.096_784_18
                    + t * (-0.186_288_06
                        + t * (0.278_868_07
                            + t * (-1.135_203_98 + t * (1.488_515_87 + t * (-0.822_152_23 + t * 0.170_872_77))))))));
    let r = t * poly.exp();
    if x >= 0.0 { r } else { 2.0 - r }
}

/// P(X ≤ x) for X ~ χ²_k, k ∈ {1, 2, 3}; `None` for other k.
pub fn chi2_cdf(x: f64, k: usize) -> Option<f64> {
    if x.is_nan() {
        return None;
    }
    if x <= 0.0 {
        return (1..=3).contains(&k).then_some(0.0);
    }
    let erf_half = 1.0 - erfc((x / 2.0).sqrt());
    match k {
        1 => Some(erf_half),
        2 => Some(1.0 - (-x / 2.0).exp()),
        3 => Some(erf_half - (2.0 * x / std::f64::consts::PI).sqrt() * (-x / 2.0).exp()),
        _ => None,
    }
}

/// The quantile x with P(X ≤ x) = `p` for X ~ χ²_k, k ∈ {1, 2, 3}, p ∈ (0, 1); `None` otherwise.
/// Bisection on [`chi2_cdf`] (about 1e-6 relative).
pub fn chi2_quantile(p: f64, k: usize) -> Option<f64> {
    if !(p > 0.0 && p < 1.0 && (1..=3).contains(&k)) {
        return None;
    }
    let (mut lo, mut hi) = (0.0_f64, 1.0_f64);
    while chi2_cdf(hi, k)? < p {
        hi *= 2.0;
        if hi > 1e4 {
            return None;
        }
    }
    for _ in 0..100 {
        let mid = 0.5 * (lo + hi);
        if chi2_cdf(mid, k)? < p {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    Some(0.5 * (lo + hi))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quantiles_match_the_tables() {
        // Standard table values.
        let cases = [(0.95, 1, 3.841), (0.99, 1, 6.635), (0.999, 1, 10.828), (0.95, 2, 5.991), (0.99, 3, 11.345)];
        for (p, k, x) in cases {
            let q = chi2_quantile(p, k).unwrap();
            assert!((q - x).abs() < 2e-3, "χ²_{k}({p}) = {q}, table {x}");
        }
        assert_eq!(chi2_quantile(1.0, 1), None);
        assert_eq!(chi2_quantile(0.9, 4), None);
        assert_eq!(chi2_cdf(f64::NAN, 1), None);
    }
}
