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
}
