//! A seeded range-only mission with ground truth, for tests and benchmarks of the estimator
//! under heavy outliers (issue 18's "simulated heavy-outlier mode").
//!
//! A differential-drive robot wanders between random waypoints in a small room (default
//! 7 × 5 m, 0.3 m/s) for `duration_s`. Odometry rows come at `odometry_rate_hz` with a speed
//! scale error, a turn-rate bias and white noise (so dead reckoning drifts by metres); one
//! range comes every `range_period_s`, to the beacons in turn (round robin), from an antenna at
//! `antenna_height_m` to beacons at different heights: the true range is the 3-D distance. A
//! share `outlier_fraction` of the ranges are gross errors of either sign (non-line-of-sight
//! reads long, multipath locks read short): the true range plus a magnitude uniform in
//! `outlier_m`, with a random sign (a range that would go below 0.05 m is drawn long instead).
//! Each range says whether it is an outlier, so a caller can also run the mission without them.
//!
//! [`trilaterate_each_range`] is the baseline the estimator must beat: a plain per-step
//! least-squares trilateration from the latest range of every beacon.

use nalgebra::Vector3;
use rand::{RngExt, SeedableRng};
use rand_distr::{Distribution, Normal};
use rand_xoshiro::Xoshiro256PlusPlus;

use crate::config::{BuoyConfig, BuoyEntry, Mode};
use crate::ekf::{BuoyEkf, OdometryInput, RangeOutcome};
use crate::error::BuoyError;
use crate::trilaterate::{Geometry, Limits, RangeObs, trilaterate, wrap_angle};
use validation::{Issues, Validate};

/// Settings of a mission (defaults: the indoor UWB robot of issue 18, 3 beacons).
#[derive(Debug, Clone, PartialEq)]
pub struct OutlierScenario {
    /// Length, s.
    pub duration_s: f64,
    /// Room (x, y) from the origin, m.
    pub area_m: [f64; 2],
    /// Cruise speed, m/s.
    pub speed_mps: f64,
    /// Beacons (x, y, z), m; ids 1, 2, … in this order.
    pub beacons_m: Vec<[f64; 3]>,
    /// Height of the robot's antenna, m.
    pub antenna_height_m: f64,
    /// One range every this long (to the next beacon in turn), s.
    pub range_period_s: f64,
    /// σ of a good range, m (also the σ the range carries).
    pub range_sigma_m: f64,
    /// Share of ranges that are gross errors.
    pub outlier_fraction: f64,
    /// Magnitude of a gross error (uniform in [min, max]), m; the sign is random.
    pub outlier_m: [f64; 2],
    /// Odometry rate, Hz.
    pub odometry_rate_hz: f64,
    /// Odometry speed scale error (reads this much too fast), dimensionless.
    pub speed_scale_error: f64,
    /// Odometry turn-rate bias, rad/s.
    pub turn_bias_rps: f64,
    /// σ of the odometry speed (white, per row), m/s; also the variance it carries.
    pub speed_sigma_mps: f64,
    /// σ of the odometry turn per row, rad; also the variance it carries.
    pub turn_sigma_rad: f64,
}

impl Default for OutlierScenario {
    fn default() -> Self {
        Self {
            duration_s: 1000.0,
            area_m: [7.0, 5.0],
            speed_mps: 0.3,
            beacons_m: vec![[0.2, 0.3, 1.04], [6.8, 0.5, 1.94], [3.2, 4.8, 1.49]],
            antenna_height_m: 1.12,
            range_period_s: 1.0,
            range_sigma_m: 0.1,
            outlier_fraction: 0.15,
            outlier_m: [1.0, 4.0],
            odometry_rate_hz: 10.0,
            speed_scale_error: 0.03,
            turn_bias_rps: 0.004,
            speed_sigma_mps: 0.02,
            turn_sigma_rad: 0.005,
        }
    }
}

/// A true pose.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TruthRow {
    /// Stamp, s.
    pub t_s: f64,
    /// Position x, m.
    pub x_m: f64,
    /// Position y, m.
    pub y_m: f64,
    /// Heading, rad.
    pub heading_rad: f64,
}

/// A simulated range.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SimRange {
    /// Stamp, s (on an odometry row's stamp; replay the odometry row first).
    pub t_s: f64,
    /// Beacon id.
    pub buoy_id: u32,
    /// Measured range, m.
    pub range_m: f64,
    /// σ it carries, m.
    pub sigma_m: f64,
    /// A gross error (ground truth, for evaluation only).
    pub outlier: bool,
    /// The true 3-D distance, m.
    pub true_range_m: f64,
}

/// A generated mission.
#[derive(Debug, Clone, PartialEq)]
pub struct Mission {
    /// The beacon table (ids 1, 2, …).
    pub buoys: Vec<BuoyEntry>,
    /// The antenna's height (the estimator's `planar_height_m`), m.
    pub antenna_height_m: f64,
    /// The true path, one row per odometry row (and one at t = 0).
    pub truth: Vec<TruthRow>,
    /// Odometry rows (stamp at the end of the interval).
    pub odometry: Vec<(f64, OdometryInput)>,
    /// Ranges in time order.
    pub ranges: Vec<SimRange>,
}

impl Mission {
    /// The same mission with the gross errors removed (the reference a robust filter is held to).
    pub fn without_outliers(&self) -> Mission {
        Mission { ranges: self.ranges.iter().copied().filter(|r| !r.outlier).collect(), ..self.clone() }
    }

    /// The true position at `t_s` (linear between rows; clamped at the ends).
    pub fn truth_at(&self, t_s: f64) -> [f64; 2] {
        let i = self.truth.partition_point(|r| r.t_s <= t_s);
        match (i.checked_sub(1).map(|a| self.truth[a]), self.truth.get(i)) {
            (Some(a), Some(b)) if b.t_s > a.t_s => {
                let u = (t_s - a.t_s) / (b.t_s - a.t_s);
                [a.x_m + u * (b.x_m - a.x_m), a.y_m + u * (b.y_m - a.y_m)]
            }
            (Some(a), _) => [a.x_m, a.y_m],
            (None, Some(b)) => [b.x_m, b.y_m],
            (None, None) => [f64::NAN, f64::NAN],
        }
    }
}

/// What [`Mission::run`] produced.
#[derive(Debug, Clone)]
pub struct MissionRun {
    /// (t, x, y) after every odometry row and range once initialised, in time order.
    pub estimates: Vec<(f64, f64, f64)>,
    /// (t, x, y) right after each range once initialised.
    pub at_ranges: Vec<(f64, f64, f64)>,
    /// What happened to each range, in order.
    pub outcomes: Vec<RangeOutcome>,
    /// The filter at the end.
    pub ekf: BuoyEkf,
}

impl Mission {
    /// The estimator's configuration for this mission: planar, the antenna's height, the
    /// beacon table, `init.min_buoys` = the number of beacons; everything else default.
    pub fn config(&self) -> BuoyConfig {
        let mut c = BuoyConfig {
            mode: Mode::Planar,
            planar_height_m: self.antenna_height_m,
            buoys: self.buoys.clone(),
            ..BuoyConfig::default()
        };
        c.init.min_buoys = self.buoys.len().min(c.init.min_buoys);
        c
    }

    /// Replays odometry and ranges (odometry first on equal stamps) through a filter with `cfg`.
    pub fn run(&self, cfg: BuoyConfig) -> Result<MissionRun, BuoyError> {
        let mut ekf = BuoyEkf::new(cfg, 0.0)?;
        let (mut estimates, mut at_ranges, mut outcomes) = (Vec::new(), Vec::new(), Vec::new());
        let (mut i, mut k) = (0, 0);
        while i < self.odometry.len() || k < self.ranges.len() {
            let odometry_next =
                k >= self.ranges.len() || (i < self.odometry.len() && self.odometry[i].0 <= self.ranges[k].t_s);
            let t = if odometry_next {
                let (t, u) = self.odometry[i];
                i += 1;
                ekf.predict_with_input(t, &u)?;
                t
            } else {
                let r = self.ranges[k];
                k += 1;
                ekf.predict_to(r.t_s)?;
                outcomes.push(ekf.update_range(r.buoy_id, r.range_m, r.sigma_m)?);
                if let Ok(e) = ekf.estimate() {
                    at_ranges.push((r.t_s, e.position_m.x, e.position_m.y));
                }
                r.t_s
            };
            if let Ok(e) = ekf.estimate() {
                estimates.push((t, e.position_m.x, e.position_m.y));
            }
        }
        Ok(MissionRun { estimates, at_ranges, outcomes, ekf })
    }

    /// ATE: RMSE of the 2-D error over every truth row, each matched to the latest estimate at
    /// or before it; rows before the first estimate are not counted. NaN without estimates.
    pub fn ate_m(&self, estimates: &[(f64, f64, f64)]) -> f64 {
        let mut sum = 0.0;
        let mut n = 0usize;
        for r in &self.truth {
            let i = estimates.partition_point(|e| e.0 <= r.t_s);
            if let Some(e) = i.checked_sub(1).map(|a| estimates[a]) {
                sum += (e.1 - r.x_m).powi(2) + (e.2 - r.y_m).powi(2);
                n += 1;
            }
        }
        if n == 0 { f64::NAN } else { (sum / n as f64).sqrt() }
    }

    /// The 2-D error of each (t, x, y) against the truth at t.
    pub fn errors_m(&self, points: &[(f64, f64, f64)]) -> Vec<f64> {
        points
            .iter()
            .map(|&(t, x, y)| {
                let p = self.truth_at(t);
                (x - p[0]).hypot(y - p[1])
            })
            .collect()
    }

    /// The ranges as (t, id, range, σ), for [`trilaterate_each_range`].
    pub fn range_tuples(&self) -> Vec<(f64, u32, f64, f64)> {
        self.ranges.iter().map(|r| (r.t_s, r.buoy_id, r.range_m, r.sigma_m)).collect()
    }
}

/// The median of `values` (NaN when empty).
pub fn median(values: &[f64]) -> f64 {
    let mut v: Vec<f64> = values.iter().copied().filter(|x| !x.is_nan()).collect();
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(f64::total_cmp);
    let n = v.len();
    if n % 2 == 1 { v[n / 2] } else { 0.5 * (v[n / 2 - 1] + v[n / 2]) }
}

impl OutlierScenario {
    /// Generates the mission of `seed` (deterministic). Panics on settings that
    /// [`Self::validate`] refuses (a test and benchmark helper, not a process input).
    pub fn generate(&self, seed: u64) -> Mission {
        let problems = self.issues();
        assert!(problems.is_empty(), "invalid scenario: {problems}");
        let mut rng = Xoshiro256PlusPlus::seed_from_u64(seed);
        let n01 = Normal::new(0.0, 1.0).expect("unit normal");
        let dt = 1.0 / self.odometry_rate_hz;
        let margin = 0.6;
        let waypoint = |rng: &mut Xoshiro256PlusPlus| {
            [rng.random_range(margin..self.area_m[0] - margin), rng.random_range(margin..self.area_m[1] - margin)]
        };
        let start = waypoint(&mut rng);
        let mut target = waypoint(&mut rng);
        let (mut x, mut y) = (start[0], start[1]);
        let mut psi = rng.random_range(-std::f64::consts::PI..std::f64::consts::PI);
        let buoys: Vec<BuoyEntry> =
            self.beacons_m.iter().enumerate().map(|(i, b)| BuoyEntry { id: i as u32 + 1, position_m: *b }).collect();
        let mut truth = vec![TruthRow { t_s: 0.0, x_m: x, y_m: y, heading_rad: psi }];
        let mut odometry = Vec::new();
        let mut ranges = Vec::new();
        let steps = (self.duration_s / dt).round() as usize;
        let range_every = ((self.range_period_s / dt).round() as usize).max(1);
        let mut next_beacon = 0usize;
        for k in 1..=steps {
            let t = k as f64 * dt;
            // Pure pursuit towards the waypoint: turn at most 0.6 rad/s, slow down when facing away.
            if (target[0] - x).hypot(target[1] - y) < 0.3 {
                target = waypoint(&mut rng);
            }
            let err = wrap_angle((target[1] - y).atan2(target[0] - x) - psi);
            let omega = (1.5 * err).clamp(-0.6, 0.6);
            let v = self.speed_mps * err.cos().max(0.0);
            let hm = psi + omega * dt / 2.0;
            x += v * dt * hm.cos();
            y += v * dt * hm.sin();
            psi = wrap_angle(psi + omega * dt);
            truth.push(TruthRow { t_s: t, x_m: x, y_m: y, heading_rad: psi });
            let v_meas = v * (1.0 + self.speed_scale_error) + self.speed_sigma_mps * n01.sample(&mut rng);
            let turn_meas = (omega + self.turn_bias_rps) * dt + self.turn_sigma_rad * n01.sample(&mut rng);
            odometry.push((
                t,
                OdometryInput {
                    dt_s: dt,
                    v_mps: v_meas,
                    dtheta_rad: turn_meas,
                    var_v: self.speed_sigma_mps.powi(2),
                    var_dtheta: self.turn_sigma_rad.powi(2),
                },
            ));
            if k % range_every == 0 {
                let j = next_beacon % buoys.len();
                next_beacon += 1;
                let b = Vector3::from(buoys[j].position_m);
                let d = (Vector3::new(x, y, self.antenna_height_m) - b).norm();
                // Draw every number every time, so the sequence does not depend on outcomes.
                let noise = self.range_sigma_m * n01.sample(&mut rng);
                let outlier = rng.random_bool(self.outlier_fraction);
                let magnitude = rng.random_range(self.outlier_m[0]..=self.outlier_m[1]);
                let negative = rng.random_bool(0.5);
                let mut r = d + noise;
                if outlier {
                    r = if negative && r - magnitude >= 0.05 { r - magnitude } else { r + magnitude };
                }
                ranges.push(SimRange {
                    t_s: t,
                    buoy_id: buoys[j].id,
                    range_m: r.max(0.0),
                    sigma_m: self.range_sigma_m,
                    outlier,
                    true_range_m: d,
                });
            }
        }
        Mission { buoys, antenna_height_m: self.antenna_height_m, truth, odometry, ranges }
    }
}

impl Validate for OutlierScenario {
    fn validate(&self, issues: &mut Issues) {
        let pos = |x: f64| x.is_finite() && x > 0.0;
        let nonneg = |x: f64| x.is_finite() && x >= 0.0;
        issues.check(pos(self.duration_s), "duration_s", "must be > 0");
        issues.check(self.area_m.iter().all(|&a| a.is_finite() && a > 1.0), "area_m", "both sides must be > 1 m");
        issues.check(pos(self.speed_mps), "speed_mps", "must be > 0");
        issues.check(self.beacons_m.len() >= 3, "beacons_m", "needs at least 3 beacons");
        issues.check(self.beacons_m.iter().flatten().all(|c| c.is_finite()), "beacons_m", "must be finite");
        issues.check(self.antenna_height_m.is_finite(), "antenna_height_m", "must be finite");
        issues.check(pos(self.range_period_s), "range_period_s", "must be > 0");
        issues.check(pos(self.range_sigma_m), "range_sigma_m", "must be > 0");
        issues.check((0.0..=0.5).contains(&self.outlier_fraction), "outlier_fraction", "must be in [0, 0.5]");
        issues.check(
            nonneg(self.outlier_m[0]) && self.outlier_m[1].is_finite() && self.outlier_m[1] >= self.outlier_m[0],
            "outlier_m",
            "must be [min, max] with 0 <= min <= max",
        );
        issues.check(pos(self.odometry_rate_hz), "odometry_rate_hz", "must be > 0");
        issues.check(
            self.speed_scale_error.is_finite() && self.speed_scale_error.abs() < 0.5,
            "speed_scale_error",
            "must be in (-0.5, 0.5)",
        );
        issues.check(self.turn_bias_rps.is_finite(), "turn_bias_rps", "must be finite");
        issues.check(pos(self.speed_sigma_mps), "speed_sigma_mps", "must be > 0");
        issues.check(pos(self.turn_sigma_rad), "turn_sigma_rad", "must be > 0");
    }
}

/// The baseline: at every range, a plain least-squares trilateration (no robust weights) from
/// the latest range of every beacon (once each has one) in `geometry`. Returns (t, position)
/// for the ranges where it has a solution (degenerate or ill-conditioned ones are skipped).
pub fn trilaterate_each_range(
    ranges: &[(f64, u32, f64, f64)],
    buoys: &[BuoyEntry],
    geometry: Geometry,
) -> Vec<(f64, Vector3<f64>)> {
    let mut latest: Vec<Option<(f64, f64)>> = vec![None; buoys.len()];
    let limits = Limits { min_buoys: 3, max_condition: 1e8, max_normalised_rms: f64::INFINITY, huber_k: 0.0 };
    let mut out = Vec::new();
    for &(t, id, r, sigma) in ranges {
        let Some(j) = buoys.iter().position(|b| b.id == id) else { continue };
        latest[j] = Some((r, sigma));
        if latest.iter().any(Option::is_none) {
            continue;
        }
        let obs: Vec<RangeObs> = latest
            .iter()
            .zip(buoys)
            .filter_map(|(l, b)| {
                l.map(|(range_m, sigma_m)| RangeObs {
                    buoy_id: b.id,
                    buoy_m: Vector3::from(b.position_m),
                    range_m,
                    sigma_m,
                })
            })
            .collect();
        if let Ok(sol) = trilaterate(&obs, geometry, &limits) {
            out.push((t, sol.position_m));
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_mission_is_deterministic_stays_in_its_room_and_has_its_outlier_share() {
        let s = OutlierScenario::default();
        let a = s.generate(3);
        assert_eq!(a, s.generate(3));
        assert_ne!(a.ranges, s.generate(4).ranges);
        assert!(a.truth.iter().all(|r| (0.0..=7.0).contains(&r.x_m) && (0.0..=5.0).contains(&r.y_m)));
        assert_eq!(a.ranges.len(), 1000);
        let outliers = a.ranges.iter().filter(|r| r.outlier).count() as f64 / 1000.0;
        assert!((0.11..0.19).contains(&outliers), "{outliers}");
        // Both signs, at least 1 m off; the good ones within 5 σ.
        assert!(a.ranges.iter().any(|r| r.outlier && r.range_m < r.true_range_m - 1.0));
        assert!(a.ranges.iter().any(|r| r.outlier && r.range_m > r.true_range_m + 1.0));
        assert!(a.ranges.iter().filter(|r| !r.outlier).all(|r| (r.range_m - r.true_range_m).abs() < 0.5));
        // It moves: the path is long, and dead reckoning drifts.
        let path: f64 = a.truth.windows(2).map(|w| (w[1].x_m - w[0].x_m).hypot(w[1].y_m - w[0].y_m)).sum();
        assert!(path > 200.0, "{path}");
        assert_eq!(a.without_outliers().ranges.len(), a.ranges.iter().filter(|r| !r.outlier).count());
        assert_eq!(
            a.truth_at(0.05),
            [0.5 * (a.truth[0].x_m + a.truth[1].x_m), 0.5 * (a.truth[0].y_m + a.truth[1].y_m)]
        );
    }

    #[test]
    fn invalid_settings_are_named() {
        let s = OutlierScenario { beacons_m: vec![[0.0; 3]; 2], outlier_fraction: 0.7, ..Default::default() };
        let keys: Vec<String> = s.issues().into_iter().map(|i| i.key).collect();
        assert_eq!(keys, ["beacons_m", "outlier_fraction"]);
    }
}
