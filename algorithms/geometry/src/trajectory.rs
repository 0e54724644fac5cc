//! Trajectory comparison without alignment: nearest-stamp matching and the absolute trajectory
//! error used for the global estimates (buoy EKF, dead reckoning, fused path).

use nalgebra::Vector3;

/// The sample of `samples` (sorted by time) nearest to `t_s`.
pub fn nearest<T>(samples: &[(f64, T)], t_s: f64) -> Option<&T> {
    let i = samples.partition_point(|(t, _)| *t < t_s);
    let before = i.checked_sub(1).map(|j| &samples[j]);
    let after = samples.get(i);
    match (before, after) {
        (Some(b), Some(a)) => Some(if t_s - b.0 <= a.0 - t_s { &b.1 } else { &a.1 }),
        (Some(b), None) => Some(&b.1),
        (None, Some(a)) => Some(&a.1),
        (None, None) => None,
    }
}

/// Absolute trajectory error: the RMSE of the position (x, y only when `planar`) over every
/// ground-truth row, each matched to the estimate with the nearest stamp; no alignment. NaN
/// without estimates or ground truth.
pub fn ate_nearest(estimate: &[(f64, Vector3<f64>)], truth: &[(f64, Vector3<f64>)], planar: bool) -> f64 {
    if estimate.is_empty() || truth.is_empty() {
        return f64::NAN;
    }
    let sum: f64 = truth
        .iter()
        .map(|(t, p)| {
            let e = nearest(estimate, *t).expect("non-empty") - p;
            if planar { e.x * e.x + e.y * e.y } else { e.norm_squared() }
        })
        .sum();
    (sum / truth.len() as f64).sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ate_counts_every_ground_truth_row_against_the_nearest_estimate() {
        let est = vec![(1.0, Vector3::new(0.0, 0.0, 0.0)), (3.0, Vector3::new(2.0, 0.0, 5.0))];
        let truth = vec![
            (0.0, Vector3::new(1.0, 0.0, 0.0)),  // before the first estimate: error 1
            (1.9, Vector3::new(0.0, 0.0, 0.0)),  // nearest is t = 1: error 0
            (2.6, Vector3::new(2.0, 3.0, 0.0)),  // nearest is t = 3: error 3 (planar)
            (10.0, Vector3::new(2.0, 0.0, 0.0)), // after the last: error 0 (planar)
        ];
        let ate = ate_nearest(&est, &truth, true);
        assert!((ate - (10.0f64 / 4.0).sqrt()).abs() < 1e-12, "{ate}");
        let ate3 = ate_nearest(&est, &truth, false);
        assert!((ate3 - ((1.0 + 0.0 + 9.0 + 25.0 + 25.0) / 4.0f64).sqrt()).abs() < 1e-12, "{ate3}");
        assert!(ate_nearest(&[], &truth, true).is_nan());
    }
}
