//! Accuracy of a SLAM trajectory against ground truth: ATE per local map (after a rigid
//! alignment of that segment, Horn/Umeyama) and the pose NEES (with the segment's true origin).

use std::collections::BTreeMap;

use nalgebra::{Isometry3, Matrix6, Vector3, Vector6};

/// One estimated pose.
#[derive(Debug, Clone, PartialEq)]
pub struct TrajectorySample {
    /// Time, s (on the same clock as the ground truth).
    pub t_s: f64,
    /// Local map the pose is in.
    pub segment: u32,
    /// Estimated `map_from_body`.
    pub map_from_body: Isometry3<f64>,
    /// Its 6×6 covariance (position, body-frame rotation error).
    pub covariance: Matrix6<f64>,
}

/// Scores of one segment.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct SegmentScore {
    /// Segment id.
    pub segment: u32,
    /// Poses evaluated.
    pub samples: usize,
    /// RMSE of position after the best rigid alignment of the segment, m.
    pub ate_m: f64,
    /// Mean normalised estimation error squared of the 6-DOF pose (expected 6 when consistent).
    pub nees: f64,
    /// Mean NEES of the position alone (expected 3 when consistent).
    pub nees_position: f64,
    /// Fraction of the poses whose position NEES lies in the two-sided 95 % interval of χ²₃
    /// ([`CHI2_3_95`]; 0.95 when consistent).
    pub nees_position_in_95: f64,
}

/// The two-sided 95 % interval of χ² with 3 degrees of freedom: [χ²₃(0.025), χ²₃(0.975)].
pub const CHI2_3_95: (f64, f64) = (0.2158, 9.3484);

/// The true pose nearest in time to `t_s` (ground truth sorted by time).
pub fn nearest(truth: &[(f64, Isometry3<f64>)], t_s: f64) -> Option<&Isometry3<f64>> {
    let i = truth.partition_point(|(t, _)| *t < t_s);
    let candidates = [i.checked_sub(1), Some(i)];
    candidates
        .into_iter()
        .flatten()
        .filter_map(|j| truth.get(j))
        .min_by(|a, b| (a.0 - t_s).abs().total_cmp(&(b.0 - t_s).abs()))
        .map(|(_, p)| p)
}

/// Scores every segment. `segment_origins_s` gives the time at which each segment's frame was
/// the body frame (its start); segments without one get no NEES (NaN).
pub fn evaluate(
    est: &[TrajectorySample],
    truth: &[(f64, Isometry3<f64>)],
    segment_origins_s: &BTreeMap<u32, f64>,
) -> Vec<SegmentScore> {
    let mut by_segment: BTreeMap<u32, Vec<&TrajectorySample>> = BTreeMap::new();
    for s in est {
        by_segment.entry(s.segment).or_default().push(s);
    }
    let mut out = vec![];
    for (segment, samples) in by_segment {
        let pairs: Vec<(&TrajectorySample, Isometry3<f64>)> =
            samples.iter().filter_map(|s| nearest(truth, s.t_s).map(|t| (*s, *t))).collect();
        if pairs.len() < 3 {
            continue;
        }
        let src: Vec<Vector3<f64>> = pairs.iter().map(|(s, _)| s.map_from_body.translation.vector).collect();
        let dst: Vec<Vector3<f64>> = pairs.iter().map(|(_, t)| t.translation.vector).collect();
        let ate_m = match geometry::align_rigid(&src, &dst, &vec![1.0; src.len()]) {
            Some(a) => {
                let se: f64 = src
                    .iter()
                    .zip(&dst)
                    .map(|(s, d)| (a.transform_point(&(*s).into()).coords - d).norm_squared())
                    .sum();
                (se / src.len() as f64).sqrt()
            }
            // Degenerate (e.g. a straight line): compare the displacement from the first pose.
            None => {
                let se: f64 =
                    src.iter().zip(&dst).map(|(s, d)| ((s - src[0]).norm() - (d - dst[0]).norm()).powi(2)).sum();
                (se / src.len() as f64).sqrt()
            }
        };
        let errors: Vec<(f64, f64)> = match segment_origins_s.get(&segment).and_then(|t0| nearest(truth, *t0)) {
            Some(origin) => {
                let origin_inv = origin.inverse();
                pairs
                    .iter()
                    .filter_map(|(s, t)| {
                        let local_true = origin_inv * t;
                        let mut e = Vector6::zeros();
                        e.fixed_rows_mut::<3>(0)
                            .copy_from(&(s.map_from_body.translation.vector - local_true.translation.vector));
                        e.fixed_rows_mut::<3>(3)
                            .copy_from(&(s.map_from_body.rotation.inverse() * local_true.rotation).scaled_axis());
                        let c = nalgebra::Cholesky::new(s.covariance + Matrix6::identity() * 1e-12)?;
                        let ep = e.fixed_rows::<3>(0).into_owned();
                        let cp = nalgebra::Cholesky::new(
                            s.covariance.fixed_view::<3, 3>(0, 0).into_owned() + nalgebra::Matrix3::identity() * 1e-12,
                        )?;
                        Some((e.dot(&c.solve(&e)), ep.dot(&cp.solve(&ep))))
                    })
                    .collect()
            }
            None => vec![],
        };
        let mean = |f: &dyn Fn(&(f64, f64)) -> f64| {
            if errors.is_empty() { f64::NAN } else { errors.iter().map(f).sum::<f64>() / errors.len() as f64 }
        };
        let nees = mean(&|e| e.0);
        let nees_position = mean(&|e| e.1);
        let nees_position_in_95 = mean(&|e| (CHI2_3_95.0..=CHI2_3_95.1).contains(&e.1) as u8 as f64);
        out.push(SegmentScore { segment, samples: pairs.len(), ate_m, nees, nees_position, nees_position_in_95 });
    }
    out
}

/// Sample-weighted mean of a per-segment value over the segments where it is finite.
pub fn weighted_mean(scores: &[SegmentScore], f: impl Fn(&SegmentScore) -> f64) -> f64 {
    let ok: Vec<&SegmentScore> = scores.iter().filter(|s| f(s).is_finite()).collect();
    let n: usize = ok.iter().map(|s| s.samples).sum();
    if n == 0 {
        return f64::NAN;
    }
    ok.iter().map(|s| f(s) * s.samples as f64).sum::<f64>() / n as f64
}

/// Sample-weighted mean of the segments' ATE (RMS over all samples).
pub fn overall_ate(scores: &[SegmentScore]) -> f64 {
    let n: usize = scores.iter().map(|s| s.samples).sum();
    if n == 0 {
        return f64::NAN;
    }
    (scores.iter().map(|s| s.ate_m * s.ate_m * s.samples as f64).sum::<f64>() / n as f64).sqrt()
}

pub use geometry::tum::read_tum;
