//! Trajectories: a time-indexed pose buffer with interpolation ([`PoseBuffer`], where a sensor
//! sample finds the pose at its stamp), and comparison without alignment: nearest-stamp matching
//! and the absolute trajectory error used for the global estimates (buoy EKF, dead reckoning,
//! fused path).

use std::collections::VecDeque;

use nalgebra::{Isometry3, Matrix2, Matrix3, Translation3, Vector2, Vector3};

/// Poses by time, interpolated.
#[derive(Debug, Default)]
pub struct PoseBuffer {
    poses: VecDeque<(f64, Isometry3<f64>)>,
}

/// The answer of [`PoseBuffer::at`].
#[derive(Debug, Clone, PartialEq)]
pub enum PoseLookup {
    /// Interpolated (linear in position, slerp in rotation).
    Ready(Isometry3<f64>),
    /// No pose after the stamp yet.
    Wait,
    /// Before the buffer, or the poses around it are too far apart.
    Unavailable,
}

impl PoseBuffer {
    /// Adds a pose (out-of-order poses go to their place; at most 4096 kept).
    pub fn push(&mut self, t_s: f64, pose: Isometry3<f64>) {
        if !t_s.is_finite() {
            return;
        }
        let i = self.poses.partition_point(|(t, _)| *t <= t_s);
        self.poses.insert(i, (t_s, pose));
        while self.poses.len() > 4096 {
            self.poses.pop_front();
        }
    }

    /// The pose at `t_s` between the two poses around it, at most `max_gap_s` apart.
    pub fn at(&self, t_s: f64, max_gap_s: f64) -> PoseLookup {
        let i = self.poses.partition_point(|(t, _)| *t < t_s);
        let Some(&(tb, b)) = self.poses.get(i) else { return PoseLookup::Wait };
        if tb == t_s {
            return PoseLookup::Ready(b);
        }
        let Some(&(ta, a)) = i.checked_sub(1).and_then(|j| self.poses.get(j)) else {
            return PoseLookup::Unavailable;
        };
        if tb - ta > max_gap_s {
            return PoseLookup::Unavailable;
        }
        let s = (t_s - ta) / (tb - ta);
        let p = a.translation.vector.lerp(&b.translation.vector, s);
        let q = a.rotation.slerp(&b.rotation, s);
        PoseLookup::Ready(Isometry3::from_parts(Translation3::from(p), q))
    }
}

/// Dead reckoning: `inputs` (each stamped at the end of its interval) integrated through the
/// process model ([`crate::propagate`]) from `start` (`world_from_body` at the start of the first
/// input's interval).
pub fn dead_reckoning(start: &Isometry3<f64>, inputs: &[(f64, crate::ProcessInput)]) -> Vec<(f64, Isometry3<f64>)> {
    let mut pose = *start;
    inputs
        .iter()
        .map(|(t, u)| {
            pose = crate::propagate(&pose, u);
            (*t, pose)
        })
        .collect()
}

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

/// The mean position NEES of an estimate against the ground truth ([`position_nees`]), with
/// Bar-Shalom's two-sided 95 % interval for that mean.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MeanNees {
    /// Mean of εᵢ = eᵢᵀ Pᵢ⁻¹ eᵢ over the samples (`dof` when consistent).
    pub mean: f64,
    /// Degrees of freedom of one sample: 3, or 2 when planar.
    pub dof: usize,
    /// Estimates scored.
    pub samples: usize,
    /// Mean of eₖ² / Pₖₖ per axis (x, y, z; z is 0 when planar): 1 per axis when consistent,
    /// which tells which axis the covariance misjudges.
    pub per_axis: [f64; 3],
    /// Estimates not scored: outside the ground truth's span, more than `max_gap_s` from a
    /// ground-truth row on either side, or with a covariance that is not positive definite.
    pub skipped: usize,
    /// The 95 % interval of the mean of `samples` χ²(`dof`) samples
    /// ([`crate::stats::mean_chi2_interval`]): a consistent estimator's mean lies in it.
    pub interval_95: (f64, f64),
}

impl MeanNees {
    /// Whether the mean lies in its 95 % interval.
    pub fn consistent(&self) -> bool {
        self.mean >= self.interval_95.0 && self.mean <= self.interval_95.1
    }
}

/// Mean position NEES (normalised estimation error squared; Bar-Shalom, Li, Kirubarajan 2001,
/// §5.4.2; docs/EQUATIONS.md, "Consistency") of `estimate` (time, position, position covariance)
/// against `truth` (time, position) in the same frame, without alignment. The truth is
/// interpolated linearly to each estimate's stamp between the two rows around it, which must lie
/// within `max_gap_s` of it. `planar` scores x and y only (2 degrees of freedom). `None` when no
/// estimate could be scored.
pub fn position_nees(
    estimate: &[(f64, Vector3<f64>, Matrix3<f64>)],
    truth: &[(f64, Vector3<f64>)],
    planar: bool,
    max_gap_s: f64,
) -> Option<MeanNees> {
    let (mut sum, mut samples, mut skipped) = (0.0, 0usize, 0usize);
    let mut axes = [0.0; 3];
    for (t, p, cov) in estimate {
        let i = truth.partition_point(|(tt, _)| tt < t);
        let at = match (i.checked_sub(1).and_then(|b| truth.get(b)), truth.get(i)) {
            (_, Some(a)) if a.0 == *t => Some(a.1),
            (Some(b), Some(a)) if t - b.0 <= max_gap_s && a.0 - t <= max_gap_s => {
                let w = (t - b.0) / (a.0 - b.0);
                Some(b.1 + (a.1 - b.1) * w)
            }
            _ => None,
        };
        let Some(true_p) = at else {
            skipped += 1;
            continue;
        };
        let e = p - true_p;
        let nees = if planar {
            let c = Matrix2::new(cov[(0, 0)], cov[(0, 1)], cov[(1, 0)], cov[(1, 1)]);
            c.cholesky().map(|ch| {
                let v = Vector2::new(e.x, e.y);
                v.dot(&ch.solve(&v))
            })
        } else {
            cov.cholesky().map(|ch| e.dot(&ch.solve(&e)))
        };
        match nees.filter(|n| n.is_finite()) {
            Some(n) => {
                sum += n;
                samples += 1;
                for (k, a) in axes.iter_mut().enumerate().take(if planar { 2 } else { 3 }) {
                    *a += e[k] * e[k] / cov[(k, k)];
                }
            }
            None => skipped += 1,
        }
    }
    let dof = if planar { 2 } else { 3 };
    let interval_95 = crate::stats::mean_chi2_interval(dof, samples, 0.95)?;
    let per_axis = axes.map(|a| a / samples as f64);
    Some(MeanNees { mean: sum / samples as f64, dof, samples, per_axis, skipped, interval_95 })
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::UnitQuaternion;

    #[test]
    fn poses_are_interpolated_between_their_neighbours_and_gaps_refused() {
        let mut b = PoseBuffer::default();
        b.push(1.0, Isometry3::translation(0.0, 0.0, 0.0));
        b.push(
            2.0,
            Isometry3::from_parts(Translation3::new(2.0, 0.0, 0.0), UnitQuaternion::from_euler_angles(0.0, 0.0, 1.0)),
        );
        let PoseLookup::Ready(p) = b.at(1.5, 1.0) else { panic!() };
        assert!((p.translation.vector.x - 1.0).abs() < 1e-12);
        assert!((p.rotation.euler_angles().2 - 0.5).abs() < 1e-12);
        assert_eq!(b.at(2.5, 1.0), PoseLookup::Wait);
        assert_eq!(b.at(0.5, 1.0), PoseLookup::Unavailable);
        assert_eq!(b.at(1.5, 0.5), PoseLookup::Unavailable, "poses 1 s apart, gap limit 0.5 s");
    }

    #[test]
    fn position_nees_scores_against_the_interpolated_truth_and_skips_what_it_cannot() {
        let truth =
            vec![(0.0, Vector3::zeros()), (2.0, Vector3::new(2.0, 0.0, 0.0)), (10.0, Vector3::new(2.0, 0.0, 0.0))];
        let cov = Matrix3::from_diagonal(&Vector3::new(0.25, 1.0, 4.0));
        let est = vec![
            // Truth at t = 1 is (1, 0, 0): error (0.5, 1, 2), NEES 1 + 1 + 1 = 3; planar 2.
            (1.0, Vector3::new(1.5, 1.0, 2.0), cov),
            // Between rows 8 s apart: more than the 1 s gap allowed.
            (5.0, Vector3::new(2.0, 0.0, 0.0), cov),
            // Before the truth starts.
            (-1.0, Vector3::zeros(), cov),
            // Not positive definite.
            (1.0, Vector3::zeros(), Matrix3::zeros()),
        ];
        let n = position_nees(&est, &truth, false, 1.0).unwrap();
        assert_eq!((n.samples, n.skipped, n.dof), (1, 3, 3));
        assert!((n.mean - 3.0).abs() < 1e-12);
        assert!(n.per_axis.iter().all(|a| (a - 1.0).abs() < 1e-12), "{:?}", n.per_axis);
        let planar = position_nees(&est, &truth, true, 1.0).unwrap();
        assert!((planar.mean - 2.0).abs() < 1e-12 && planar.dof == 2);
        // A row exactly at the stamp needs no neighbour.
        let at_row = position_nees(&[(10.0, Vector3::new(2.0, 0.0, 1.0), cov)], &truth, false, 1.0).unwrap();
        assert!((at_row.mean - 0.25).abs() < 1e-12);
        assert!(position_nees(&est[1..3], &truth, false, 1.0).is_none());
    }

    #[test]
    fn consistent_errors_have_a_mean_nees_inside_the_interval_and_scaled_ones_do_not() {
        // Errors drawn with the stated covariance (a fixed pseudo-random sequence of normals by
        // Box-Muller) pass; the same errors with a covariance 3x too large, or too small, fail.
        let truth: Vec<(f64, Vector3<f64>)> = (0..=2000).map(|i| (i as f64 * 0.1, Vector3::zeros())).collect();
        let mut x = 0x2545_f491_4f6c_dd1du64;
        let mut uniform = || {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            (x >> 11) as f64 / (1u64 << 53) as f64
        };
        let mut normal = || {
            let (u1, u2) = (uniform().max(1e-300), uniform());
            (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
        };
        let sd = Vector3::new(0.3, 0.5, 0.1);
        let cov = Matrix3::from_diagonal(&sd.component_mul(&sd));
        let est: Vec<_> = (0..2000)
            .map(|i| (i as f64 * 0.1 + 0.05, Vector3::new(normal() * sd.x, normal() * sd.y, normal() * sd.z), cov))
            .collect();
        let n = position_nees(&est, &truth, false, 1.0).unwrap();
        assert!(n.consistent(), "{n:?}");
        for scale in [3.0, 1.0 / 3.0] {
            let scaled: Vec<_> = est.iter().map(|(t, p, c)| (*t, *p, c * scale)).collect();
            let s = position_nees(&scaled, &truth, false, 1.0).unwrap();
            assert!(!s.consistent(), "covariance x {scale}: {s:?}");
        }
    }

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
