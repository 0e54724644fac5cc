//! Validation of messages from producers the pipeline does not control (external drivers,
//! replays, other stages): NaN/inf, empty or oversized clouds, stamps going backwards or repeated,
//! unknown buoy ids. A rejected message is counted by reason and logged at most once per
//! [`WARN_EVERY`] per reason; nothing panics and nothing else is lost.

use std::collections::{BTreeMap, HashMap};
use std::fmt::Display;
use std::time::{Duration, Instant};

use serde::Serialize;
use shared_types::{
    BuoyRange, CLOUD_HAS_POSE, CloudHeader, CloudPoint, DepthReading, HeadingReading, OdometryInput, StereoObservation,
};

/// Shortest interval between two warnings of the same reason on one input.
pub const WARN_EVERY: Duration = Duration::from_secs(5);

/// Why a message was rejected.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Rejection {
    /// Short machine-readable reason (a counter key), e.g. `non_finite`.
    pub reason: &'static str,
    /// What exactly was wrong.
    pub detail: String,
}

fn reject<T>(reason: &'static str, detail: impl Display) -> Result<T, Rejection> {
    Err(Rejection { reason, detail: detail.to_string() })
}

fn finite(values: &[f64], what: &str) -> Result<(), Rejection> {
    match values.iter().position(|v| !v.is_finite()) {
        Some(i) => reject("non_finite", format!("{what}[{i}] = {}", values[i])),
        None => Ok(()),
    }
}

/// Checks an odometry input: finite, δt > 0, covariance diagonal >= 0.
pub fn check_odometry(u: &OdometryInput) -> Result<(), Rejection> {
    finite(&[u.v_mps, u.dt_s], "v_mps/dt_s")?;
    finite(&u.delta_theta_rad, "delta_theta_rad")?;
    finite(&u.input_covariance, "input_covariance")?;
    if u.dt_s <= 0.0 {
        return reject("bad_value", format!("dt_s = {} (must be > 0)", u.dt_s));
    }
    if (0..4).any(|i| u.input_covariance[i * 5] < 0.0) {
        return reject("bad_value", "negative input variance");
    }
    Ok(())
}

/// Most observations in one stereo frame.
pub const MAX_STEREO_OBSERVATIONS: usize = 100_000;

/// Checks a stereo frame: not oversized, every point finite and in front of the camera, every
/// covariance finite with a non-negative diagonal.
pub fn check_stereo(obs: &[StereoObservation]) -> Result<(), Rejection> {
    if obs.len() > MAX_STEREO_OBSERVATIONS {
        return reject("oversized", format!("{} observations (max {MAX_STEREO_OBSERVATIONS})", obs.len()));
    }
    for (i, o) in obs.iter().enumerate() {
        finite(&o.point_cam_m, &format!("observation {i} point_cam_m"))?;
        finite(&o.covariance_cam_m2, &format!("observation {i} covariance"))?;
        if o.point_cam_m[2] <= 0.0 {
            return reject("bad_value", format!("observation {i} behind the camera (z = {})", o.point_cam_m[2]));
        }
        if (0..3).any(|k| o.covariance_cam_m2[k * 4] < 0.0) {
            return reject("bad_value", format!("observation {i}: negative variance"));
        }
    }
    Ok(())
}

/// Checks buoy ranges: not empty, finite, range >= 0, σ > 0, id in `known_ids` (when given).
pub fn check_buoy_ranges(ranges: &[BuoyRange], known_ids: Option<&[u32]>) -> Result<(), Rejection> {
    if ranges.is_empty() {
        return reject("empty", "no ranges");
    }
    for (i, r) in ranges.iter().enumerate() {
        finite(&[r.range_m, r.sigma_m], &format!("range {i}"))?;
        if r.range_m < 0.0 || r.sigma_m <= 0.0 {
            return reject("bad_value", format!("range {i}: range {} m, sigma {} m", r.range_m, r.sigma_m));
        }
        if let Some(ids) = known_ids
            && !ids.contains(&r.buoy_id)
        {
            return reject("unknown_buoy", format!("buoy id {} is not configured", r.buoy_id));
        }
    }
    Ok(())
}

/// Checks a pressure-depth reading.
pub fn check_depth(d: &DepthReading) -> Result<(), Rejection> {
    finite(&[d.depth_m, d.sigma_m], "depth")?;
    if d.sigma_m <= 0.0 {
        return reject("bad_value", format!("sigma {} m", d.sigma_m));
    }
    Ok(())
}

/// Checks a heading: finite, yaw in [−π, π], σ > 0.
pub fn check_heading(h: &HeadingReading) -> Result<(), Rejection> {
    finite(&[h.yaw_rad, h.sigma_rad], "heading")?;
    if h.sigma_rad <= 0.0 {
        return reject("bad_value", format!("sigma {} rad", h.sigma_rad));
    }
    if h.yaw_rad.abs() > std::f64::consts::PI + 1e-9 {
        return reject("bad_value", format!("yaw {} rad outside [-pi, pi]", h.yaw_rad));
    }
    Ok(())
}

/// Checks a cloud: not empty, at most `max_points`, every point finite, a flagged pose finite
/// with a unit quaternion.
pub fn check_cloud(header: &CloudHeader, points: &[CloudPoint], max_points: usize) -> Result<(), Rejection> {
    if points.is_empty() {
        return reject("empty", "cloud has no points");
    }
    if points.len() > max_points {
        return reject("oversized", format!("{} points (max {max_points})", points.len()));
    }
    if let Some(i) = points.iter().position(|p| !(p.x_m.is_finite() && p.y_m.is_finite() && p.z_m.is_finite())) {
        return reject("non_finite", format!("point {i} = ({}, {}, {})", points[i].x_m, points[i].y_m, points[i].z_m));
    }
    if header.flags & CLOUD_HAS_POSE != 0 {
        finite(&header.sensor_origin_m, "sensor_origin_m")?;
        finite(&header.orientation_xyzw, "orientation_xyzw")?;
        let n: f64 = header.orientation_xyzw.iter().map(|q| q * q).sum::<f64>().sqrt();
        if (n - 1.0).abs() > 1e-3 {
            return reject("bad_value", format!("orientation quaternion has norm {n}"));
        }
    }
    Ok(())
}

/// Counters and rate-limited warnings for one input.
#[derive(Debug)]
pub struct Guard {
    service: String,
    accepted: u64,
    rejected: BTreeMap<&'static str, u64>,
    last_stamp: HashMap<u128, u64>,
    last_seq: HashMap<u128, u64>,
    missed: u64,
    last_warn: HashMap<&'static str, (Instant, u64)>,
}

/// A guard's counters, for summaries.
#[derive(Debug, Clone, Serialize, serde::Deserialize, schemars::JsonSchema, PartialEq, Eq)]
pub struct GuardReport {
    /// Messages accepted.
    pub accepted: u64,
    /// Messages rejected, by reason.
    pub rejected: BTreeMap<String, u64>,
    /// Messages never received: gaps in the publishers' sequence numbers.
    pub missed: u64,
}

impl Guard {
    /// A guard for the input on `service`.
    pub fn new(service: &str) -> Self {
        Self {
            service: service.to_string(),
            accepted: 0,
            rejected: BTreeMap::new(),
            last_stamp: HashMap::new(),
            last_seq: HashMap::new(),
            missed: 0,
            last_warn: HashMap::new(),
        }
    }

    /// Checks that `stamp_ns` increases for the publisher `publisher_id`; a stamp that goes
    /// backwards or repeats is rejected (`stamp_not_increasing`).
    pub fn check_stamp(&mut self, publisher_id: u128, stamp_ns: u64) -> Result<(), Rejection> {
        match self.last_stamp.get(&publisher_id) {
            Some(&last) if stamp_ns <= last => {
                reject("stamp_not_increasing", format!("stamp {stamp_ns} ns after {last} ns from the same publisher"))
            }
            _ => {
                self.last_stamp.insert(publisher_id, stamp_ns);
                Ok(())
            }
        }
    }

    /// Notes the sequence number of a message from `publisher_id`; a gap counts as missed
    /// messages (lost before they reached this subscriber).
    pub fn note_seq(&mut self, publisher_id: u128, seq: u64) {
        if let Some(last) = self.last_seq.insert(publisher_id, seq)
            && seq > last + 1
        {
            self.missed += seq - last - 1;
        }
    }

    /// Counts the outcome of a check; logs a rejection at most once per [`WARN_EVERY`] per reason
    /// (with the number suppressed since). Returns true when accepted.
    pub fn admit(&mut self, result: Result<(), Rejection>) -> bool {
        match result {
            Ok(()) => {
                self.accepted += 1;
                true
            }
            Err(r) => {
                *self.rejected.entry(r.reason).or_default() += 1;
                let now = Instant::now();
                let entry = self.last_warn.entry(r.reason).or_insert((now - WARN_EVERY * 2, 0));
                if now - entry.0 >= WARN_EVERY {
                    tracing::warn!(service = %self.service, reason = r.reason, suppressed = entry.1, "rejected message: {}", r.detail);
                    *entry = (now, 0);
                } else {
                    entry.1 += 1;
                }
                false
            }
        }
    }

    /// Messages accepted so far.
    pub fn accepted(&self) -> u64 {
        self.accepted
    }

    /// Messages rejected so far (all reasons).
    pub fn rejected(&self) -> u64 {
        self.rejected.values().sum()
    }

    /// The counters.
    pub fn report(&self) -> GuardReport {
        GuardReport {
            accepted: self.accepted,
            rejected: self.rejected.iter().map(|(k, n)| (k.to_string(), *n)).collect(),
            missed: self.missed,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use shared_types::MsgHeader;

    #[test]
    fn bad_clouds_are_rejected_with_their_reason() {
        let h = CloudHeader::default();
        let good = vec![CloudPoint { x_m: 1.0, y_m: 2.0, z_m: 3.0 }; 10];
        assert!(check_cloud(&h, &good, 10).is_ok());
        assert_eq!(check_cloud(&h, &[], 10).unwrap_err().reason, "empty");
        assert_eq!(check_cloud(&h, &good, 9).unwrap_err().reason, "oversized");
        let mut nan = good.clone();
        nan[7].y_m = f32::NAN;
        let e = check_cloud(&h, &nan, 10).unwrap_err();
        assert_eq!((e.reason, e.detail.starts_with("point 7")), ("non_finite", true));
        let posed = CloudHeader {
            flags: CLOUD_HAS_POSE,
            orientation_xyzw: [0.0, 0.0, 0.0, 2.0],
            msg: MsgHeader::default(),
            ..h
        };
        assert_eq!(check_cloud(&posed, &good, 10).unwrap_err().reason, "bad_value");
    }

    #[test]
    fn stamps_must_increase_per_publisher() {
        let mut g = Guard::new("s");
        assert!(g.check_stamp(1, 10).is_ok());
        assert!(g.check_stamp(2, 5).is_ok(), "another publisher has its own clock");
        assert_eq!(g.check_stamp(1, 10).unwrap_err().reason, "stamp_not_increasing");
        assert_eq!(g.check_stamp(1, 9).unwrap_err().reason, "stamp_not_increasing");
        assert!(g.check_stamp(1, 11).is_ok());
    }

    #[test]
    fn guard_counts_by_reason() {
        let mut g = Guard::new("s");
        assert!(g.admit(Ok(())));
        for _ in 0..5 {
            assert!(!g.admit(check_buoy_ranges(
                &[BuoyRange { buoy_id: 9, _reserved: 0, range_m: 1.0, sigma_m: 1.0 }],
                Some(&[0, 1])
            )));
        }
        assert!(!g.admit(check_odometry(&OdometryInput { dt_s: 0.0, ..Default::default() })));
        let r = g.report();
        assert_eq!(r.accepted, 1);
        assert_eq!(r.rejected.get("unknown_buoy"), Some(&5));
        assert_eq!(r.rejected.get("bad_value"), Some(&1));
        assert_eq!(g.rejected(), 6);
    }

    #[test]
    fn odometry_stereo_and_depth_checks_catch_non_finite_values() {
        let u = OdometryInput { v_mps: f64::INFINITY, dt_s: 0.1, ..Default::default() };
        assert_eq!(check_odometry(&u).unwrap_err().reason, "non_finite");
        let o = StereoObservation { point_cam_m: [0.0, 0.0, -1.0], ..Default::default() };
        assert_eq!(check_stereo(&[o]).unwrap_err().reason, "bad_value");
        let o = StereoObservation { point_cam_m: [f64::NAN, 0.0, 1.0], ..Default::default() };
        assert_eq!(check_stereo(&[o]).unwrap_err().reason, "non_finite");
        assert_eq!(check_depth(&DepthReading { depth_m: 1.0, sigma_m: 0.0 }).unwrap_err().reason, "bad_value");
    }
}
