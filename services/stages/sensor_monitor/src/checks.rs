//! The sensor messages' checks: NaN/inf, empty or oversized clouds, unit quaternions, δt > 0,
//! unknown buoy ids. Each returns the [`Rejection`] a [`pipeline_runtime::validate::Guard`]
//! counts by reason.

use std::fmt::Display;

use pipeline_runtime::validate::Rejection;
use shared_types::{
    BuoyRange, CLOUD_HAS_POSE, CloudHeader, CloudPoint, DepthReading, HeadingReading, OdometryInput, StereoObservation,
};

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

#[cfg(test)]
mod tests {
    use super::*;
    use pipeline_runtime::validate::Guard;
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
