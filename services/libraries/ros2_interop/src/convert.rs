//! ROS 2 messages to the pipeline's wire types (in) and back (out). Frames and units as in
//! docs/WIRE_FORMAT.md and REP 103 (SI units, x forward / y left / z up) and REP 105 (`map`,
//! `odom`, `base_link`).
//!
//! In: each function checks what the wire type promises (finite values, a unit quaternion, a
//! stamp that is a time) and names the field that breaks it ([`ConvertError`]); the caller counts
//! and skips the message. Out: plain constructions, with the covariance moved from the wire's
//! body-frame rotation error to ROS's fixed-axis one.

use std::collections::BTreeMap;

use nalgebra::{Isometry3, Matrix6, Quaternion as NQuaternion, Translation3, UnitQuaternion, Vector3 as NVector3};
use shared_types::convert::{mat6_from_row_major, mat6_to_row_major};
use shared_types::{
    BuoyRange, DepthReading, HeadingReading, LASER_MAX_IS_NO_RETURN, LaserScanHeader, ODOM_HAS_VELOCITY,
    OccupancyGridHeader, OdometryInput, PlanarOdometry, PlanarPose, PoseEstimate, TRAVERSABILITY_NAVIGABLE,
    TRAVERSABILITY_OBSTACLE, TraversabilityCell, Voxel,
};

use crate::msgs::*;

/// Why a ROS 2 message cannot become a pipeline message.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ConvertError {
    /// `header.stamp` is not a time (negative, or nanoseconds ≥ 1e9).
    #[error("header.stamp {sec} s {nanosec} ns is not a time")]
    Stamp {
        /// Seconds.
        sec: i32,
        /// Nanoseconds.
        nanosec: u32,
    },
    /// A field that must be finite is not.
    #[error("{field} is not finite")]
    NotFinite {
        /// The field.
        field: &'static str,
    },
    /// A field's value cannot be used.
    #[error("{field}: {why}")]
    Invalid {
        /// The field.
        field: &'static str,
        /// Why.
        why: String,
    },
}

fn invalid(field: &'static str, why: impl Into<String>) -> ConvertError {
    ConvertError::Invalid { field, why: why.into() }
}

fn finite(field: &'static str, v: &[f64]) -> Result<(), ConvertError> {
    if v.iter().all(|x| x.is_finite()) { Ok(()) } else { Err(ConvertError::NotFinite { field }) }
}

/// `header.stamp` in ns.
pub fn stamp_ns(h: &Header) -> Result<u64, ConvertError> {
    h.stamp.to_ns().ok_or(ConvertError::Stamp { sec: h.stamp.sec, nanosec: h.stamp.nanosec })
}

/// A ROS quaternion as a rotation: finite and of norm within 10 % of 1 (normalised), else an error
/// naming `field`.
pub fn rotation(q: &Quaternion, field: &'static str) -> Result<UnitQuaternion<f64>, ConvertError> {
    finite(field, &[q.x, q.y, q.z, q.w])?;
    let nq = NQuaternion::new(q.w, q.x, q.y, q.z);
    let n = nq.norm();
    if !(0.9..=1.1).contains(&n) {
        return Err(invalid(field, format!("not a rotation (norm {n:.3})")));
    }
    Ok(UnitQuaternion::from_quaternion(nq))
}

/// A rotation as a ROS quaternion.
pub fn quaternion(q: &UnitQuaternion<f64>) -> Quaternion {
    Quaternion { x: q.i, y: q.j, z: q.k, w: q.w }
}

/// A ROS pose as `frame_from_body`.
pub fn isometry(p: &Pose, field: &'static str) -> Result<Isometry3<f64>, ConvertError> {
    finite(field, &[p.position.x, p.position.y, p.position.z])?;
    let r = rotation(&p.orientation, field)?;
    Ok(Isometry3::from_parts(Translation3::new(p.position.x, p.position.y, p.position.z), r))
}

/// `frame_from_body` as a ROS pose.
pub fn pose(iso: &Isometry3<f64>) -> Pose {
    let t = iso.translation.vector;
    Pose { position: Point { x: t.x, y: t.y, z: t.z }, orientation: quaternion(&iso.rotation) }
}

/// `sensor_msgs/LaserScan` → `pipeline/sensors/laser`: the stamp, the scan's header (the laser
/// mounted at `body_from_laser` = (x m, y m, yaw rad)) and its ranges (REP 117: +Inf, no return,
/// becomes `range_max` with [`LASER_MAX_IS_NO_RETURN`]; −Inf and NaN stay invalid as NaN).
pub fn laser_scan(msg: &LaserScan, body_from_laser: [f64; 3]) -> Result<(u64, LaserScanHeader), ConvertError> {
    let stamp = stamp_ns(&msg.header)?;
    let a = [msg.angle_min as f64, msg.angle_increment as f64, msg.range_min as f64, msg.range_max as f64];
    finite("angle_min, angle_increment, range_min, range_max", &a)?;
    if msg.ranges.is_empty() {
        return Err(invalid("ranges", "no beams"));
    }
    if msg.angle_increment == 0.0 {
        return Err(invalid("angle_increment", "0"));
    }
    if !(msg.range_min >= 0.0 && msg.range_max > msg.range_min) {
        return Err(invalid(
            "range_max",
            format!("needs 0 <= range_min ({}) < range_max ({})", msg.range_min, msg.range_max),
        ));
    }
    let header = LaserScanHeader {
        angle_min_rad: msg.angle_min as f64,
        angle_increment_rad: msg.angle_increment as f64,
        range_min_m: msg.range_min as f64,
        range_max_m: msg.range_max as f64,
        body_from_laser_xy_m: [body_from_laser[0], body_from_laser[1]],
        body_from_laser_yaw_rad: body_from_laser[2],
        beams: msg.ranges.len() as u32,
        flags: LASER_MAX_IS_NO_RETURN,
        ..Default::default()
    };
    Ok((stamp, header))
}

/// One beam of a LaserScan on the wire (see [`laser_scan`]).
pub fn laser_range(r: f32, range_max: f32) -> f32 {
    if r == f32::INFINITY {
        range_max
    } else if r.is_finite() {
        r
    } else {
        f32::NAN
    }
}

/// Yaw (about z) of a rotation, rad in (−π, π].
pub fn yaw(q: &UnitQuaternion<f64>) -> f64 {
    q.euler_angles().2
}

/// `nav_msgs/Odometry` → `pipeline/sensors/planar_odometry`: x, y and yaw of the pose, and the
/// body velocity (vx, vy, ω) of the twist (in `child_frame_id`, the body).
pub fn planar_odometry(msg: &Odometry) -> Result<(u64, PlanarOdometry), ConvertError> {
    let stamp = stamp_ns(&msg.header)?;
    let iso = isometry(&msg.pose.pose, "pose.pose")?;
    let t = &msg.twist.twist;
    let velocity = [t.linear.x, t.linear.y, t.angular.z];
    let flags = if velocity.iter().all(|v| v.is_finite()) { ODOM_HAS_VELOCITY } else { 0 };
    Ok((
        stamp,
        PlanarOdometry {
            position_m: [iso.translation.vector.x, iso.translation.vector.y],
            yaw_rad: yaw(&iso.rotation),
            velocity: if flags != 0 { velocity } else { [0.0; 3] },
            flags,
            ..Default::default()
        },
    ))
}

/// Noise of the 3-D odometry input where a message's twist covariance does not give it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct OdometryNoise {
    /// σ of the forward speed, m/s.
    pub speed_sigma_mps: f64,
    /// σ of each rotation increment per step, rad.
    pub turn_sigma_rad: f64,
}

/// `nav_msgs/Odometry` → `pipeline/sensors/odometry` (EQUATIONS §1: forward speed and body-frame
/// rotation increment over δt): the increment between consecutive messages' poses, so the first
/// message gives nothing. The noise comes from the twist covariance where its diagonal is
/// positive (var v = Σ[0], var δθᵢ = Σ[3+i, 3+i]·δt²), else from `noise`.
#[derive(Debug, Clone, Default)]
pub struct OdometryIncrements {
    last: Option<(u64, Isometry3<f64>)>,
}

impl OdometryIncrements {
    /// The input since the previous message; `None` for the first, an error for a message whose
    /// stamp does not increase (it is then not kept).
    pub fn push(&mut self, msg: &Odometry, noise: OdometryNoise) -> Result<Option<(u64, OdometryInput)>, ConvertError> {
        let stamp = stamp_ns(&msg.header)?;
        let iso = isometry(&msg.pose.pose, "pose.pose")?;
        let Some((t0, prev)) = self.last else {
            self.last = Some((stamp, iso));
            return Ok(None);
        };
        if stamp <= t0 {
            return Err(invalid("header.stamp", format!("{stamp} ns does not follow the previous {t0} ns")));
        }
        self.last = Some((stamp, iso));
        let dt = (stamp - t0) as f64 * 1e-9;
        let delta = prev.inverse() * iso;
        let theta = delta.rotation.scaled_axis();
        let c = &msg.twist.covariance;
        let (var_v, var_w) =
            if c[0] > 0.0 && c[21] > 0.0 && c[28] > 0.0 && c[35] > 0.0 && c.iter().all(|v| v.is_finite()) {
                (c[0], [c[21] * dt * dt, c[28] * dt * dt, c[35] * dt * dt])
            } else {
                (noise.speed_sigma_mps.powi(2), [noise.turn_sigma_rad.powi(2); 3])
            };
        let mut cov = [0.0; 16];
        cov[0] = var_v;
        cov[5] = var_w[0];
        cov[10] = var_w[1];
        cov[15] = var_w[2];
        Ok(Some((
            stamp,
            OdometryInput {
                v_mps: delta.translation.vector.x / dt,
                delta_theta_rad: [theta.x, theta.y, theta.z],
                dt_s: dt,
                input_covariance: cov,
            },
        )))
    }
}

/// A little-endian f32 at byte `o` of a point (NaN when it lies outside: not for a checked layout).
#[inline(always)]
fn read_f32(p: &[u8], o: usize) -> f32 {
    match p.get(o..o + 4) {
        Some(b) => f32::from_le_bytes([b[0], b[1], b[2], b[3]]),
        None => f32::NAN,
    }
}

/// Where x, y and z are in a `PointCloud2`'s points.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct CloudLayout {
    offsets: [usize; 3],
    float64: bool,
    big_endian: bool,
    point_step: usize,
    row_step: usize,
    width: usize,
    height: usize,
}

impl CloudLayout {
    /// The layout of `msg`: fields `x`, `y`, `z` of FLOAT32 (or FLOAT64, all three alike), count
    /// 1, inside the point step; the data long enough for every row. Other fields are skipped.
    pub fn of(msg: &PointCloud2<'_>) -> Result<Self, ConvertError> {
        let names: Vec<String> = msg.fields.iter().map(|f| format!("{}:{}", f.name, f.datatype)).collect();
        let mut offsets = [0usize; 3];
        let mut kind = None;
        for (i, axis) in ["x", "y", "z"].into_iter().enumerate() {
            let f = msg
                .fields
                .iter()
                .find(|f| f.name == axis)
                .ok_or_else(|| invalid("fields", format!("no field `{axis}` (fields: {})", names.join(", "))))?;
            if f.datatype != POINT_FIELD_FLOAT32 && f.datatype != POINT_FIELD_FLOAT64 || f.count > 1 {
                return Err(invalid(
                    "fields",
                    format!(
                        "`{axis}` is datatype {} count {}: x, y, z must be FLOAT32 (7) or FLOAT64 (8)",
                        f.datatype, f.count
                    ),
                ));
            }
            if kind.is_some_and(|k| k != f.datatype) {
                return Err(invalid("fields", "x, y and z are of different datatypes"));
            }
            kind = Some(f.datatype);
            offsets[i] = f.offset as usize;
        }
        let float64 = kind == Some(POINT_FIELD_FLOAT64);
        let size = if float64 { 8 } else { 4 };
        let (point_step, row_step) = (msg.point_step as usize, msg.row_step as usize);
        let (width, height) = (msg.width as usize, msg.height as usize);
        if offsets.iter().any(|o| o + size > point_step) {
            return Err(invalid("point_step", format!("{point_step} bytes: x, y or z lies outside a point")));
        }
        if row_step < point_step.saturating_mul(width) {
            return Err(invalid("row_step", format!("{row_step} < point_step {point_step} × width {width}")));
        }
        let need = if width * height == 0 { 0 } else { row_step * (height - 1) + point_step * width };
        if msg.data.0.len() < need {
            return Err(invalid(
                "data",
                format!("{} bytes, {need} needed for {height} × {width} points (truncated?)", msg.data.0.len()),
            ));
        }
        Ok(Self { offsets, float64, big_endian: msg.is_bigendian, point_step, row_step, width, height })
    }

    /// Points in the cloud (`width × height`, valid or not).
    pub fn len(&self) -> usize {
        self.width * self.height
    }

    /// True for a cloud without points.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Byte offset of point `i` (row-major).
    #[inline]
    fn base(&self, i: usize) -> usize {
        if self.height <= 1 {
            i * self.point_step
        } else {
            (i / self.width) * self.row_step + (i % self.width) * self.point_step
        }
    }

    /// Point `i` (row-major) of `data`, m (`data` as checked by [`CloudLayout::of`]).
    #[inline]
    pub fn point(&self, data: &[u8], i: usize) -> [f32; 3] {
        let b = self.base(i);
        let [ox, oy, oz] = self.offsets;
        match (self.float64, self.big_endian) {
            (false, false) => {
                let r = |o: usize| f32::from_le_bytes(data[b + o..b + o + 4].try_into().unwrap_or_default());
                [r(ox), r(oy), r(oz)]
            }
            (false, true) => {
                let r = |o: usize| f32::from_be_bytes(data[b + o..b + o + 4].try_into().unwrap_or_default());
                [r(ox), r(oy), r(oz)]
            }
            (true, big) => {
                let r = |o: usize| {
                    let v: [u8; 8] = data[b + o..b + o + 8].try_into().unwrap_or_default();
                    (if big { f64::from_be_bytes(v) } else { f64::from_le_bytes(v) }) as f32
                };
                [r(ox), r(oy), r(oz)]
            }
        }
    }

    /// Writes every point of `data` into `out` (as many as both hold); returns how many.
    pub fn read_into<T: From<[f32; 3]>>(&self, data: &[u8], out: &mut [T]) -> usize {
        self.fill(data, out, |o, p| *o = T::from(p))
    }

    /// Calls `put(slot, point)` for every point of `data` with its slot of `out`, in order, as
    /// many as both hold (every point of a cloud checked by [`CloudLayout::of`] when `out` holds
    /// [`CloudLayout::len`]); returns how many. The fast path walks an unordered little-endian
    /// FLOAT32 cloud's bytes in fixed steps; any other layout indexes [`CloudLayout::point`].
    #[inline]
    pub fn fill<T>(&self, data: &[u8], out: &mut [T], mut put: impl FnMut(&mut T, [f32; 3])) -> usize {
        let n = self.len().min(out.len());
        if self.is_fast() {
            let [ox, oy, oz] = self.offsets;
            let mut written = 0;
            for (slot, p) in out[..n].iter_mut().zip(data.chunks_exact(self.point_step)) {
                put(slot, [read_f32(p, ox), read_f32(p, oy), read_f32(p, oz)]);
                written += 1;
            }
            written
        } else {
            for (i, slot) in out[..n].iter_mut().enumerate() {
                put(slot, self.point(data, i));
            }
            n
        }
    }

    /// Calls `f(index, point)` for every point of `data`, in order.
    #[inline]
    pub fn for_each_point(&self, data: &[u8], mut f: impl FnMut(usize, [f32; 3])) {
        if self.is_fast() {
            let [ox, oy, oz] = self.offsets;
            for (i, p) in data.chunks_exact(self.point_step).take(self.len()).enumerate() {
                f(i, [read_f32(p, ox), read_f32(p, oy), read_f32(p, oz)]);
            }
        } else {
            for i in 0..self.len() {
                f(i, self.point(data, i));
            }
        }
    }

    /// An unordered little-endian FLOAT32 cloud (walked in fixed steps).
    fn is_fast(&self) -> bool {
        !self.float64 && !self.big_endian && self.height <= 1 && self.point_step > 0
    }

    /// How many points of `data` are finite.
    pub fn count_finite(&self, data: &[u8]) -> usize {
        let mut n = 0;
        self.for_each_point(data, |_, p| n += usize::from(p.iter().all(|v| v.is_finite())));
        n
    }

    /// The indices of the finite points of `data`.
    pub fn finite_indices(&self, data: &[u8]) -> Vec<u32> {
        let mut keep = Vec::with_capacity(self.len());
        self.for_each_point(data, |i, p| {
            if p.iter().all(|v| v.is_finite()) {
                keep.push(i as u32);
            }
        });
        keep
    }

    /// The finite points of `data`, in order (NaN / Inf points of a non-dense cloud skipped).
    pub fn finite_points<'d>(&self, data: &'d [u8]) -> impl Iterator<Item = [f32; 3]> + 'd + use<'d> {
        let me = *self;
        (0..self.len()).map(move |i| me.point(data, i)).filter(|p| p.iter().all(|v| v.is_finite()))
    }
}

/// Settings of `sensor_msgs/Imu` → heading.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HeadingNoise {
    /// σ of the yaw when the message's orientation covariance gives none, rad.
    pub default_sigma_rad: f64,
}

/// `sensor_msgs/Imu` → `pipeline/sensors/heading`: the yaw of the orientation, σ from the
/// covariance's yaw variance (element 8) when positive. An IMU without orientation
/// (`orientation_covariance[0] = −1`, REP 145) is an error.
pub fn heading(msg: &Imu, noise: HeadingNoise) -> Result<(u64, HeadingReading), ConvertError> {
    let stamp = stamp_ns(&msg.header)?;
    if msg.orientation_covariance[0] == -1.0 {
        return Err(invalid("orientation_covariance", "-1: this IMU reports no orientation"));
    }
    let q = rotation(&msg.orientation, "orientation")?;
    let var = msg.orientation_covariance[8];
    let sigma_rad = if var.is_finite() && var > 0.0 { var.sqrt() } else { noise.default_sigma_rad };
    Ok((stamp, HeadingReading { yaw_rad: yaw(&q), sigma_rad }))
}

/// Settings of `sensor_msgs/FluidPressure` → depth.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PressureToDepth {
    /// Pressure at the surface, Pa (atmospheric: 101,325).
    pub surface_pa: f64,
    /// Water density, kg/m³ (sea water ≈ 1,025; fresh water 1,000).
    pub density_kg_m3: f64,
    /// Gravity, m/s².
    pub gravity_mps2: f64,
    /// σ of the depth when the message's variance is 0 (unknown), m.
    pub default_sigma_m: f64,
}

impl Default for PressureToDepth {
    fn default() -> Self {
        Self { surface_pa: 101_325.0, density_kg_m3: 1025.0, gravity_mps2: 9.80665, default_sigma_m: 0.05 }
    }
}

/// `sensor_msgs/FluidPressure` → `pipeline/sensors/depth`: depth = (p − p_surface) / (ρ g), σ
/// from the variance the same way.
pub fn depth(msg: &FluidPressure, p: PressureToDepth) -> Result<(u64, DepthReading), ConvertError> {
    let stamp = stamp_ns(&msg.header)?;
    finite("fluid_pressure", &[msg.fluid_pressure])?;
    if msg.fluid_pressure <= 0.0 {
        return Err(invalid("fluid_pressure", format!("{} Pa: an absolute pressure is positive", msg.fluid_pressure)));
    }
    let rho_g = p.density_kg_m3 * p.gravity_mps2;
    let sigma_m =
        if msg.variance.is_finite() && msg.variance > 0.0 { msg.variance.sqrt() / rho_g } else { p.default_sigma_m };
    Ok((stamp, DepthReading { depth_m: (msg.fluid_pressure - p.surface_pa) / rho_g, sigma_m }))
}

/// Which buoy (beacon) a `sensor_msgs/Range` is from: `header.frame_id` looked up in `ids`, else
/// the number it ends with (`buoy_3`, `beacon/12`).
pub fn beacon_id(frame_id: &str, ids: &BTreeMap<String, u32>) -> Result<u32, ConvertError> {
    if let Some(id) = ids.get(frame_id) {
        return Ok(*id);
    }
    let digits: String = frame_id.chars().rev().take_while(|c| c.is_ascii_digit()).collect();
    let digits: String = digits.chars().rev().collect();
    digits.parse().map_err(|_| {
        invalid(
            "header.frame_id",
            format!("`{frame_id}` names no beacon: neither in the route's beacon table nor ending in its number"),
        )
    })
}

/// `sensor_msgs/Range` → one `pipeline/sensors/buoy_ranges` element: the beacon from
/// `header.frame_id` ([`beacon_id`]), σ from `variance` when positive, else `default_sigma_m`. A
/// range that is not finite or lies outside [min_range, max_range] is an error.
pub fn buoy_range(
    msg: &Range,
    ids: &BTreeMap<String, u32>,
    default_sigma_m: f64,
) -> Result<(u64, BuoyRange), ConvertError> {
    let stamp = stamp_ns(&msg.header)?;
    let buoy_id = beacon_id(&msg.header.frame_id, ids)?;
    finite("range", &[msg.range as f64])?;
    if msg.max_range > msg.min_range && !(msg.min_range..=msg.max_range).contains(&msg.range) {
        return Err(invalid("range", format!("{} m outside [{}, {}] m", msg.range, msg.min_range, msg.max_range)));
    }
    let sigma_m =
        if msg.variance.is_finite() && msg.variance > 0.0 { (msg.variance as f64).sqrt() } else { default_sigma_m };
    Ok((stamp, BuoyRange { buoy_id, range_m: msg.range as f64, sigma_m, ..Default::default() }))
}

/// How a depth image becomes points.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DepthImageSampling {
    /// Use every `stride`-th pixel in both directions (≥ 1).
    pub stride: u32,
    /// Depths below this are dropped, m.
    pub min_depth_m: f32,
    /// Depths above this are dropped, m.
    pub max_depth_m: f32,
}

/// A depth `sensor_msgs/Image` (`16UC1` / `mono16` in mm, `32FC1` in m, REP 118) with its
/// `sensor_msgs/CameraInfo` → points in the camera's optical frame (x right, y down, z forward),
/// back-projected through K: x = (u − cx)·z/fx, y = (v − cy)·z/fy. Zero, NaN and out-of-range
/// depths are dropped; their number is returned with the points.
pub fn depth_image_points(
    img: &Image<'_>,
    info: &CameraInfo,
    s: DepthImageSampling,
) -> Result<(u64, Vec<[f32; 3]>, usize), ConvertError> {
    let stamp = stamp_ns(&img.header)?;
    let (fx, fy, cx, cy) = (info.k[0], info.k[4], info.k[2], info.k[5]);
    finite("camera_info.k", &[fx, fy, cx, cy])?;
    if fx <= 0.0 || fy <= 0.0 {
        return Err(invalid("camera_info.k", format!("focal lengths fx {fx}, fy {fy} must be > 0")));
    }
    if info.width != 0 && (info.width != img.width || info.height != img.height) {
        return Err(invalid(
            "width",
            format!("image {}×{} but camera_info {}×{}", img.width, img.height, info.width, info.height),
        ));
    }
    let (bytes_pp, mm) = match img.encoding.as_str() {
        "16UC1" | "mono16" => (2usize, true),
        "32FC1" => (4usize, false),
        other => return Err(invalid("encoding", format!("`{other}`: a depth image is 16UC1 (mm) or 32FC1 (m)"))),
    };
    let (w, h, step) = (img.width as usize, img.height as usize, img.step as usize);
    if step < w * bytes_pp {
        return Err(invalid("step", format!("{step} < width {w} × {bytes_pp} bytes")));
    }
    let data = img.data.as_slice();
    if h > 0 && data.len() < step * (h - 1) + w * bytes_pp {
        return Err(invalid("data", format!("{} bytes for {h} rows of {step} (truncated?)", data.len())));
    }
    let big = img.is_bigendian != 0;
    let stride = s.stride.max(1) as usize;
    let mut points = Vec::with_capacity((w / stride + 1) * (h / stride + 1));
    let mut dropped = 0;
    for v in (0..h).step_by(stride) {
        for u in (0..w).step_by(stride) {
            let at = v * step + u * bytes_pp;
            let z = if mm {
                let b = [data[at], data[at + 1]];
                (if big { u16::from_be_bytes(b) } else { u16::from_le_bytes(b) }) as f32 * 0.001
            } else {
                let b = [data[at], data[at + 1], data[at + 2], data[at + 3]];
                if big { f32::from_be_bytes(b) } else { f32::from_le_bytes(b) }
            };
            if !(z.is_finite() && z > 0.0 && z >= s.min_depth_m && z <= s.max_depth_m) {
                dropped += 1;
                continue;
            }
            let x = ((u as f64 - cx) * z as f64 / fx) as f32;
            let y = ((v as f64 - cy) * z as f64 / fy) as f32;
            points.push([x, y, z]);
        }
    }
    Ok((stamp, points, dropped))
}

/// A header at `stamp_ns` in `frame_id`.
pub fn header(stamp_ns: u64, frame_id: &str) -> Header {
    Header { stamp: Time::from_ns(stamp_ns), frame_id: frame_id.to_string() }
}

/// The wire's 6×6 pose covariance (rotation error in the body frame) as ROS's (rotation about
/// the parent frame's fixed axes): J Σ Jᵀ with J = diag(I, R).
pub fn covariance_to_ros(wire: &[f64; 36], frame_from_body: &UnitQuaternion<f64>) -> [f64; 36] {
    let mut j = Matrix6::<f64>::identity();
    j.fixed_view_mut::<3, 3>(3, 3).copy_from(frame_from_body.to_rotation_matrix().matrix());
    let s = mat6_from_row_major(wire);
    mat6_to_row_major(&(j * s * j.transpose()))
}

/// A 6-DOF estimate as `nav_msgs/Odometry` (`frame_id` ← `child_frame_id`, no twist).
pub fn odometry_from_pose(stamp_ns: u64, frame_id: &str, child_frame_id: &str, p: &PoseEstimate) -> Odometry {
    let iso = p.frame_from_body();
    Odometry {
        header: header(stamp_ns, frame_id),
        child_frame_id: child_frame_id.to_string(),
        pose: PoseWithCovariance { pose: pose(&iso), covariance: covariance_to_ros(&p.covariance, &iso.rotation) },
        twist: TwistWithCovariance::default(),
    }
}

/// A planar pose as a 6-DOF ROS pose with covariance (x, y, yaw; z, roll, pitch 0 and their
/// variances 0, as AMCL and slam_toolbox publish theirs).
pub fn planar_pose(p: &PlanarPose) -> PoseWithCovariance {
    let iso = Isometry3::from_parts(
        Translation3::new(p.position_m[0], p.position_m[1], 0.0),
        UnitQuaternion::from_axis_angle(&NVector3::z_axis(), p.yaw_rad),
    );
    let mut covariance = [0.0; 36];
    let idx = [0usize, 1, 5];
    for (a, &ra) in idx.iter().enumerate() {
        for (b, &rb) in idx.iter().enumerate() {
            covariance[ra * 6 + rb] = p.covariance[a * 3 + b];
        }
    }
    PoseWithCovariance { pose: pose(&iso), covariance }
}

/// The pipeline's occupancy grid as `nav_msgs/OccupancyGrid` (the same cell order and values).
pub fn occupancy_grid(stamp_ns: u64, frame_id: &str, h: &OccupancyGridHeader, cells: &[i8]) -> OccupancyGrid<'static> {
    OccupancyGrid {
        header: header(stamp_ns, frame_id),
        info: MapMetaData {
            map_load_time: Time::from_ns(stamp_ns),
            resolution: h.resolution_m as f32,
            width: h.width,
            height: h.height,
            origin: Pose {
                position: Point { x: h.origin_m[0], y: h.origin_m[1], z: 0.0 },
                orientation: Quaternion::default(),
            },
        },
        data: Bytes::owned(cells.iter().map(|c| *c as u8).collect()),
    }
}

/// The octree mapper's traversability grid as `nav_msgs/OccupancyGrid`, as Nav2's costmaps and
/// map_server take a map: navigable 0 (free), obstacle 100 (occupied), unknown −1, in the same
/// cell order (the first row at the lowest y) at z 0.
pub fn traversability_grid(
    stamp_ns: u64,
    frame_id: &str,
    h: &OccupancyGridHeader,
    cells: &[TraversabilityCell],
) -> OccupancyGrid<'static> {
    let occupancy: Vec<i8> = cells
        .iter()
        .map(|c| match c.class {
            TRAVERSABILITY_NAVIGABLE => 0,
            TRAVERSABILITY_OBSTACLE => 100,
            _ => -1,
        })
        .collect();
    occupancy_grid(stamp_ns, frame_id, h, &occupancy)
}

/// The traversability grid's known cells as `sensor_msgs/PointCloud2` (an elevation cloud RViz
/// shows as the surface): one point per navigable or obstacle cell at its centre and height,
/// fields `x`, `y`, `z` (m), `slope` (deg, 0 on an obstacle) and `class` (1 navigable, 2
/// obstacle), FLOAT32, little-endian.
pub fn traversability_cloud(
    stamp_ns: u64,
    frame_id: &str,
    h: &OccupancyGridHeader,
    cells: &[TraversabilityCell],
) -> PointCloud2<'static> {
    let mut data = Vec::new();
    let mut n = 0u32;
    let width = h.width.max(1) as usize;
    for (i, c) in cells.iter().enumerate() {
        if c.class != TRAVERSABILITY_NAVIGABLE && c.class != TRAVERSABILITY_OBSTACLE {
            continue;
        }
        let (col, row) = ((i % width) as f64, (i / width) as f64);
        let x = (h.origin_m[0] + (col + 0.5) * h.resolution_m) as f32;
        let y = (h.origin_m[1] + (row + 0.5) * h.resolution_m) as f32;
        for f in [x, y, c.height_m, c.slope_deg, c.class as f32] {
            data.extend_from_slice(&f.to_le_bytes());
        }
        n += 1;
    }
    let field = |name: &str, offset| PointField { name: name.into(), offset, datatype: POINT_FIELD_FLOAT32, count: 1 };
    PointCloud2 {
        header: header(stamp_ns, frame_id),
        height: 1,
        width: n,
        fields: vec![field("x", 0), field("y", 4), field("z", 8), field("slope", 12), field("class", 16)],
        is_bigendian: false,
        point_step: 20,
        row_step: 20 * n,
        data: Bytes::owned(data),
        is_dense: true,
    }
}

/// Occupied voxels as `sensor_msgs/PointCloud2` (like octomap_server's centres cloud): fields
/// `x`, `y`, `z` (voxel centre, m) and `occupancy` (probability), FLOAT32, little-endian.
pub fn voxel_cloud<'v>(
    stamp_ns: u64,
    frame_id: &str,
    voxels: impl ExactSizeIterator<Item = &'v Voxel>,
) -> PointCloud2<'static> {
    let n = voxels.len();
    let mut data = Vec::with_capacity(n * 16);
    for v in voxels {
        for f in [v.center_m[0], v.center_m[1], v.center_m[2], v.occupancy] {
            data.extend_from_slice(&f.to_le_bytes());
        }
    }
    let field = |name: &str, offset| PointField { name: name.into(), offset, datatype: POINT_FIELD_FLOAT32, count: 1 };
    PointCloud2 {
        header: header(stamp_ns, frame_id),
        height: 1,
        width: n as u32,
        fields: vec![field("x", 0), field("y", 4), field("z", 8), field("occupancy", 12)],
        is_bigendian: false,
        point_step: 16,
        row_step: 16 * n as u32,
        data: Bytes::owned(data),
        is_dense: true,
    }
}

/// `parent_from_child` at `stamp_ns` as a `geometry_msgs/TransformStamped`.
pub fn transform(stamp_ns: u64, parent: &str, child: &str, parent_from_child: &Isometry3<f64>) -> TransformStamped {
    let t = parent_from_child.translation.vector;
    TransformStamped {
        header: header(stamp_ns, parent),
        child_frame_id: child.to_string(),
        transform: Transform {
            translation: Vector3 { x: t.x, y: t.y, z: t.z },
            rotation: quaternion(&parent_from_child.rotation),
        },
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f64::consts::FRAC_PI_2;

    fn odom(stamp_ns: u64, x: f64, y: f64, yaw: f64) -> Odometry {
        let q = UnitQuaternion::from_axis_angle(&NVector3::z_axis(), yaw);
        Odometry {
            header: header(stamp_ns, "odom"),
            child_frame_id: "base_link".into(),
            pose: PoseWithCovariance {
                pose: Pose { position: Point { x, y, z: 0.0 }, orientation: quaternion(&q) },
                covariance: [0.0; 36],
            },
            twist: TwistWithCovariance::default(),
        }
    }

    #[test]
    fn the_traversability_grid_is_a_nav2_map_and_an_elevation_cloud_of_its_known_cells() {
        let h = OccupancyGridHeader {
            resolution_m: 0.5,
            origin_m: [10.0, -4.0],
            width: 2,
            height: 2,
            ..Default::default()
        };
        let cell = |class, height_m, slope_deg| TraversabilityCell { height_m, slope_deg, class, _reserved: [0; 3] };
        let cells = [
            cell(TRAVERSABILITY_NAVIGABLE, -20.0, 4.0),
            cell(0, 0.0, 0.0),
            cell(0, 0.0, 0.0),
            cell(TRAVERSABILITY_OBSTACLE, -18.5, 0.0),
        ];
        let g = traversability_grid(7, "map", &h, &cells);
        assert_eq!(g.data.0.iter().map(|&b| b as i8).collect::<Vec<_>>(), [0, -1, -1, 100]);
        assert_eq!((g.info.width, g.info.height, g.info.resolution), (2, 2, 0.5));
        assert_eq!((g.info.origin.position.x, g.info.origin.position.y), (10.0, -4.0));
        let c = traversability_cloud(7, "map", &h, &cells);
        assert_eq!((c.width, c.point_step), (2, 20));
        let f = |p: usize, k: usize| f32::from_le_bytes(c.data.0[p * 20 + k * 4..][..4].try_into().unwrap());
        // The obstacle: column 1, row 1: the centre (10.75, −3.25), its top, class 2.
        assert_eq!([f(1, 0), f(1, 1), f(1, 2), f(1, 4)], [10.75, -3.25, -18.5, 2.0]);
        assert_eq!([f(0, 0), f(0, 1), f(0, 2), f(0, 3)], [10.25, -3.75, -20.0, 4.0]);
        assert_eq!(c.fields.iter().map(|f| f.name.as_str()).collect::<Vec<_>>(), ["x", "y", "z", "slope", "class"]);
    }

    #[test]
    fn odometry_becomes_planar_odometry_and_a_bad_quaternion_is_named() {
        let (t, p) = planar_odometry(&odom(5_000_000_000, 1.0, 2.0, FRAC_PI_2)).unwrap();
        assert_eq!(t, 5_000_000_000);
        assert_eq!(p.position_m, [1.0, 2.0]);
        assert!((p.yaw_rad - FRAC_PI_2).abs() < 1e-12);
        let mut bad = odom(1, 0.0, 0.0, 0.0);
        bad.pose.pose.orientation = Quaternion { x: 0.0, y: 0.0, z: 0.0, w: 0.0 };
        let e = planar_odometry(&bad).unwrap_err();
        assert!(e.to_string().contains("pose.pose") && e.to_string().contains("not a rotation"), "{e}");
        bad.pose.pose.orientation.w = f64::NAN;
        assert_eq!(planar_odometry(&bad).unwrap_err(), ConvertError::NotFinite { field: "pose.pose" });
    }

    #[test]
    fn odometry_increments_are_body_frame_motion_over_the_interval() {
        let noise = OdometryNoise { speed_sigma_mps: 0.1, turn_sigma_rad: 0.01 };
        let mut inc = OdometryIncrements::default();
        assert_eq!(inc.push(&odom(1_000_000_000, 0.0, 0.0, FRAC_PI_2), noise).unwrap(), None);
        // Facing +y, moving 1 m along +y and turning 0.1 rad in 0.5 s: 2 m/s forward.
        let (t, u) = inc.push(&odom(1_500_000_000, 0.0, 1.0, FRAC_PI_2 + 0.1), noise).unwrap().unwrap();
        assert_eq!(t, 1_500_000_000);
        assert!((u.v_mps - 2.0).abs() < 1e-9 && (u.dt_s - 0.5).abs() < 1e-12, "{u:?}");
        assert!((u.delta_theta_rad[2] - 0.1).abs() < 1e-9);
        assert!((u.input_covariance[0] - 0.01).abs() < 1e-15);
        assert!(inc.push(&odom(1_500_000_000, 0.0, 1.0, 0.0), noise).is_err(), "a stamp that does not increase");
    }

    #[test]
    fn a_pointcloud2_with_extra_fields_and_padding_is_read_and_one_without_z_is_refused() {
        // x, intensity, y, z (FLOAT32) in a 20-byte point, 2 rows of 2 points, 48-byte rows.
        let fields = vec![
            PointField { name: "x".into(), offset: 0, datatype: 7, count: 1 },
            PointField { name: "intensity".into(), offset: 4, datatype: 7, count: 1 },
            PointField { name: "y".into(), offset: 8, datatype: 7, count: 1 },
            PointField { name: "z".into(), offset: 12, datatype: 7, count: 1 },
        ];
        let mut data = vec![0u8; 96];
        for i in 0..4usize {
            let base = (i / 2) * 48 + (i % 2) * 20;
            let v = if i == 2 { f32::NAN } else { i as f32 };
            for (k, o) in [0usize, 8, 12].iter().enumerate() {
                data[base + o..base + o + 4].copy_from_slice(&(v + k as f32 * 10.0).to_le_bytes());
            }
        }
        let mut msg = PointCloud2 {
            height: 2,
            width: 2,
            fields,
            point_step: 20,
            row_step: 48,
            data: Bytes::owned(data),
            ..Default::default()
        };
        let layout = CloudLayout::of(&msg).unwrap();
        assert_eq!(layout.len(), 4);
        let pts: Vec<_> = layout.finite_points(msg.data.as_slice()).collect();
        assert_eq!(pts, vec![[0.0, 10.0, 20.0], [1.0, 11.0, 21.0], [3.0, 13.0, 23.0]]);
        assert_eq!(
            (layout.count_finite(msg.data.as_slice()), layout.finite_indices(msg.data.as_slice())),
            (3, vec![0, 1, 3])
        );
        // The same points as one unordered row (the one-pass path): `fill` reads what `point` does.
        let mut flat = vec![0u8; 80];
        for i in 0..4 {
            let src = (i / 2) * 48 + (i % 2) * 20;
            flat[i * 20..i * 20 + 20].copy_from_slice(&msg.data.as_slice()[src..src + 20]);
        }
        let row = PointCloud2 { height: 1, width: 4, row_step: 80, data: Bytes::owned(flat), ..msg.clone() };
        let l = CloudLayout::of(&row).unwrap();
        let mut out = vec![[0f32; 3]; 4];
        assert_eq!(l.fill(row.data.as_slice(), &mut out, |o, p| *o = p), 4);
        for (i, o) in out.iter().enumerate() {
            let p = layout.point(msg.data.as_slice(), i);
            assert!(o.iter().zip(&p).all(|(a, b)| a == b || a.is_nan() && b.is_nan()), "{i}: {o:?} vs {p:?}");
        }
        assert_eq!(l.count_finite(row.data.as_slice()), 3);
        msg.data = Bytes::owned(vec![0; 60]);
        assert!(CloudLayout::of(&msg).unwrap_err().to_string().contains("truncated"));
        msg.fields.pop();
        let e = CloudLayout::of(&msg).unwrap_err().to_string();
        assert!(e.contains("no field `z`") && e.contains("intensity:7"), "{e}");
    }

    #[test]
    fn laser_scan_infinities_follow_rep_117() {
        let scan = LaserScan {
            header: header(7, "laser"),
            angle_min: -1.0,
            angle_increment: 0.5,
            range_min: 0.1,
            range_max: 30.0,
            ranges: vec![1.0, f32::INFINITY, f32::NEG_INFINITY, f32::NAN],
            ..Default::default()
        };
        let (t, h) = laser_scan(&scan, [0.1, 0.0, 0.0]).unwrap();
        assert_eq!((t, h.beams, h.flags), (7, 4, LASER_MAX_IS_NO_RETURN));
        let r: Vec<f32> = scan.ranges.iter().map(|r| laser_range(*r, scan.range_max)).collect();
        assert_eq!(r[..2], [1.0, 30.0]);
        assert!(r[2].is_nan() && r[3].is_nan());
        let mut bad = scan.clone();
        bad.angle_increment = f32::NAN;
        assert!(matches!(laser_scan(&bad, [0.0; 3]), Err(ConvertError::NotFinite { .. })));
    }

    #[test]
    fn ranges_name_their_beacon_and_bad_ones_are_refused() {
        let mut ids = BTreeMap::new();
        ids.insert("north".to_string(), 4u32);
        let r = |frame: &str, range: f32| Range {
            header: header(1, frame),
            min_range: 0.5,
            max_range: 200.0,
            range,
            variance: 0.09,
            ..Default::default()
        };
        assert_eq!(buoy_range(&r("buoy_12", 40.0), &ids, 1.0).unwrap().1.buoy_id, 12);
        let (_, b) = buoy_range(&r("north", 40.0), &ids, 1.0).unwrap();
        assert_eq!(b.buoy_id, 4);
        assert!((b.sigma_m - 0.3).abs() < 1e-6);
        assert!(buoy_range(&r("buoy", 40.0), &ids, 1.0).unwrap_err().to_string().contains("`buoy` names no beacon"));
        assert!(buoy_range(&r("b1", 250.0), &ids, 1.0).unwrap_err().to_string().contains("outside"));
        assert!(buoy_range(&r("b1", f32::NAN), &ids, 1.0).is_err());
    }

    #[test]
    fn pressure_becomes_depth_and_imu_becomes_heading() {
        let p = PressureToDepth::default();
        let msg = FluidPressure {
            header: header(1, "p"),
            fluid_pressure: 101_325.0 + 1025.0 * 9.80665 * 10.0,
            variance: 0.0,
        };
        let (_, d) = depth(&msg, p).unwrap();
        assert!((d.depth_m - 10.0).abs() < 1e-9 && d.sigma_m == 0.05);
        let q = UnitQuaternion::from_axis_angle(&NVector3::z_axis(), -0.7);
        let mut imu = Imu { header: header(1, "imu"), orientation: quaternion(&q), ..Default::default() };
        imu.orientation_covariance[8] = 0.0004;
        let (_, h) = heading(&imu, HeadingNoise { default_sigma_rad: 0.1 }).unwrap();
        assert!((h.yaw_rad + 0.7).abs() < 1e-12 && (h.sigma_rad - 0.02).abs() < 1e-12);
        imu.orientation_covariance[0] = -1.0;
        assert!(heading(&imu, HeadingNoise { default_sigma_rad: 0.1 }).is_err());
    }

    #[test]
    fn a_depth_image_is_back_projected_through_its_camera_info() {
        let mut info = CameraInfo { width: 4, height: 2, ..Default::default() };
        info.k = [100.0, 0.0, 2.0, 0.0, 100.0, 1.0, 0.0, 0.0, 1.0];
        // 16UC1 in mm: (u=0,v=0) 2000 mm, (3,1) 1000 mm, one zero and the rest 0.
        let mut mm = [0u16; 8];
        mm[0] = 2000;
        mm[7] = 1000;
        let bytes: Vec<u8> = mm.iter().flat_map(|d| d.to_le_bytes()).collect();
        let img = Image {
            header: header(9, "cam"),
            width: 4,
            height: 2,
            encoding: "16UC1".into(),
            step: 8,
            data: Bytes::owned(bytes),
            ..Default::default()
        };
        let s = DepthImageSampling { stride: 1, min_depth_m: 0.1, max_depth_m: 10.0 };
        let (t, pts, dropped) = depth_image_points(&img, &info, s).unwrap();
        assert_eq!((t, dropped), (9, 6));
        assert_eq!(pts, vec![[-0.04, -0.02, 2.0], [0.01, 0.0, 1.0]]);
        // 32FC1 in m, big-endian, padded rows.
        let mut be = vec![0u8; 2 * 20];
        be[..4].copy_from_slice(&1.5f32.to_be_bytes());
        be[4..8].copy_from_slice(&f32::NAN.to_be_bytes());
        let img = Image {
            header: header(9, "cam"),
            width: 4,
            height: 2,
            encoding: "32FC1".into(),
            is_bigendian: 1,
            step: 20,
            data: Bytes::owned(be),
        };
        let (_, pts, dropped) = depth_image_points(&img, &info, s).unwrap();
        assert_eq!((pts.len(), dropped), (1, 7));
        assert!((pts[0][2] - 1.5).abs() < 1e-6);
        let bad = Image { encoding: "rgb8".into(), ..img.clone() };
        assert!(depth_image_points(&bad, &info, s).unwrap_err().to_string().contains("rgb8"));
        info.width = 640;
        assert!(depth_image_points(&img, &info, s).unwrap_err().to_string().contains("camera_info 640"));
    }

    #[test]
    fn the_body_frame_rotation_covariance_is_turned_into_the_parent_frame() {
        // Facing +y (yaw 90°): a variance about body x is one about world y.
        let q = UnitQuaternion::from_axis_angle(&NVector3::z_axis(), FRAC_PI_2);
        let mut wire = [0.0; 36];
        wire[3 * 6 + 3] = 0.04;
        wire[0] = 1.0;
        let ros = covariance_to_ros(&wire, &q);
        assert!((ros[4 * 6 + 4] - 0.04).abs() < 1e-12 && ros[3 * 6 + 3].abs() < 1e-12);
        assert_eq!(ros[0], 1.0);
    }
}
