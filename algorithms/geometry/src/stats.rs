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
