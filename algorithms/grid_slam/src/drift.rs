//! Seeded synthetic odometry drift, for logs whose odometry is already corrected by SLAM (the
//! Radish "corrected" logs): each increment between consecutive odometry poses is distorted by a
//! systematic scale error and random noise proportional to the motion, and the distorted
//! increments are chained again. Stated once so every result can say what it was measured with.

use omni::{Pose2, wrap_angle};
use rand::SeedableRng;
use rand_distr::{Distribution, Normal};
use rand_xoshiro::Xoshiro256PlusPlus;

/// The drift model. Per increment (dx, dy, dθ) in the body frame, with d = √(dx² + dy²):
///
/// - dx' = dx·(1 + `trans_scale`) + N(0, (`trans_noise`·d)²), dy' likewise with `lateral_noise`;
/// - dθ' = dθ·(1 + `rot_scale`) + `rot_bias_per_m`·d + N(0, (`rot_noise`·|dθ| + `rot_noise_per_m`·d)²).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct DriftModel {
    /// Systematic translation scale error (−0.01: 1% short).
    pub trans_scale: f64,
    /// Translation noise along the motion, per metre.
    pub trans_noise: f64,
    /// Noise across the motion, per metre.
    pub lateral_noise: f64,
    /// Systematic rotation scale error.
    pub rot_scale: f64,
    /// Systematic heading drift, rad per metre travelled.
    pub rot_bias_per_m: f64,
    /// Rotation noise per radian turned.
    pub rot_noise: f64,
    /// Rotation noise per metre travelled, rad.
    pub rot_noise_per_m: f64,
    /// Seed.
    pub seed: u64,
}

impl Default for DriftModel {
    fn default() -> Self {
        Self {
            trans_scale: -0.01,
            trans_noise: 0.03,
            lateral_noise: 0.01,
            rot_scale: 0.015,
            rot_bias_per_m: 0.005,
            rot_noise: 0.03,
            rot_noise_per_m: 0.01,
            seed: 7,
        }
    }
}

impl DriftModel {
    /// The drifted odometry: same first pose, then the distorted increments chained.
    pub fn apply(&self, odometry: &[Pose2]) -> Vec<Pose2> {
        let mut rng = Xoshiro256PlusPlus::seed_from_u64(self.seed);
        let n = Normal::new(0.0, 1.0).expect("unit normal");
        let mut out = Vec::with_capacity(odometry.len());
        let Some(&first) = odometry.first() else { return out };
        out.push(first);
        let mut cur = first;
        for w in odometry.windows(2) {
            let u = w[0].between(&w[1]);
            let d = u.x_m.hypot(u.y_m);
            let (a, b, c) = (n.sample(&mut rng), n.sample(&mut rng), n.sample(&mut rng));
            let noisy = Pose2 {
                x_m: u.x_m * (1.0 + self.trans_scale) + self.trans_noise * d * a,
                y_m: u.y_m * (1.0 + self.trans_scale) + self.lateral_noise * d * b,
                theta_rad: u.theta_rad * (1.0 + self.rot_scale)
                    + self.rot_bias_per_m * d
                    + (self.rot_noise * u.theta_rad.abs() + self.rot_noise_per_m * d) * c,
            };
            cur = cur.compose(&Pose2 { theta_rad: wrap_angle(noisy.theta_rad), ..noisy });
            out.push(cur);
        }
        out
    }
}

impl DriftModel {
    /// Drifted odometry at the scans and between them: `scans` (stamp, pose), in stamp order, get
    /// [`DriftModel::apply`] (the same increments, so the same draws, as without the samples
    /// between); every sample of `between` strictly between two scans follows the log's motion
    /// from the earlier scan with the interval's drift spread over it ([`crate::densify`]), so
    /// denser odometry does not change the drift the scans see. Returns the drifted scans and, per
    /// scan, the drifted samples between the scan before it and it.
    pub fn apply_between(
        &self,
        scans: &[(f64, Pose2)],
        between: &[(f64, Pose2)],
    ) -> (Vec<Pose2>, Vec<Vec<(f64, Pose2)>>) {
        let poses: Vec<Pose2> = scans.iter().map(|s| s.1).collect();
        let drifted = self.apply(&poses);
        let anchors: Vec<(f64, Pose2)> = scans.iter().map(|s| s.0).zip(drifted.iter().copied()).collect();
        let b = crate::densify::between_samples(&anchors, scans, between);
        (drifted, b)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn drift_is_seeded_and_grows_with_the_path() {
        let truth: Vec<Pose2> = (0..500).map(|k| Pose2 { x_m: k as f64 * 0.1, y_m: 0.0, theta_rad: 0.0 }).collect();
        let m = DriftModel::default();
        let a = m.apply(&truth);
        assert_eq!(a, m.apply(&truth), "same seed, same drift");
        assert_ne!(a, DriftModel { seed: 8, ..m }.apply(&truth));
        let err = |k: usize| (a[k].x_m - truth[k].x_m).hypot(a[k].y_m - truth[k].y_m);
        assert!(err(499) > err(50), "{} {}", err(499), err(50));
        assert!(err(499) > 1.0, "50 m with 0.5°/m heading drift ends metres off: {}", err(499));
        let none = DriftModel {
            trans_scale: 0.0,
            trans_noise: 0.0,
            lateral_noise: 0.0,
            rot_scale: 0.0,
            rot_bias_per_m: 0.0,
            rot_noise: 0.0,
            rot_noise_per_m: 0.0,
            seed: 1,
        };
        let same = none.apply(&truth);
        assert!(same.iter().zip(&truth).all(|(p, q)| (p.x_m - q.x_m).abs() < 1e-9));
    }

    #[test]
    fn samples_between_scans_follow_the_log_and_leave_the_scans_drift_as_it_was() {
        // A slalom: y = sin(x), a "scan" every 1 m, odometry every 0.1 m.
        let at = |x: f64| Pose2 { x_m: x, y_m: x.sin(), theta_rad: x.cos().atan() };
        let scans: Vec<(f64, Pose2)> = (0..40).map(|k| (k as f64, at(k as f64))).collect();
        let between: Vec<(f64, Pose2)> =
            (0..400).filter(|k| k % 10 != 0).map(|k| (k as f64 * 0.1, at(k as f64 * 0.1))).collect();
        let m = DriftModel::default();
        let (at_scans, between) = m.apply_between(&scans, &between);
        assert_eq!(at_scans, m.apply(&scans.iter().map(|s| s.1).collect::<Vec<_>>()), "the scans' drift unchanged");
        assert_eq!(between.iter().map(Vec::len).sum::<usize>(), 351, "the samples between the first scan and the last");
        let dense: Vec<(f64, Pose2)> = scans
            .iter()
            .zip(&at_scans)
            .zip(&between)
            .flat_map(|((s, p), b)| b.iter().copied().chain([(s.0, *p)]))
            .collect();
        // Between two scans the drifted odometry turns with the slalom, as the log does: its
        // increments over 0.1 m differ from the log's by the drift's few per cent, not by the
        // 0.84 rad turn a straight line between scans would smooth over.
        for w in dense.windows(2) {
            let (a, b) = (w[0].1.between(&w[1].1), at(w[0].0).between(&at(w[1].0)));
            assert!((a.theta_rad - b.theta_rad).abs() < 0.02, "{:?} {a:?} {b:?}", w[0].0);
        }
    }
}
