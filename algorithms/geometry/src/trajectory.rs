//! Trajectories: a time-indexed pose buffer with interpolation ([`PoseBuffer`], where a sensor
//! sample finds the pose at its stamp), and comparison without alignment: nearest-stamp matching
//! and the absolute trajectory error used for the global estimates (buoy EKF, dead reckoning,
//! fused path).

use std::collections::VecDeque;

use nalgebra::{Isometry3, Translation3, Vector3};

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
