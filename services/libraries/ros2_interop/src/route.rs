//! Routes from ROS 2 topics into the pipeline: which topic feeds which pipeline input, and how
//! its messages become wire values ([`InRoute::decode`]). The same table serves a rosbag2 replay
//! (ingest's `rosbag2` source) and the `ros2` gateway.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};
use validation::{Issues, Validate};

use shared_types::{BuoyRange, DepthReading, HeadingReading, LaserScanHeader, OdometryInput, PlanarOdometry};

use crate::cdr::{self, CdrError};
use crate::convert::{
    self, ConvertError, DepthImageSampling, HeadingNoise, OdometryIncrements, OdometryNoise, PressureToDepth,
};
use crate::msgs::{CameraInfo, FluidPressure, Image, Imu, LaserScan, Message, Odometry, PointCloud2, Range};

/// The pipeline input a route feeds.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum InService {
    /// `pipeline/sensors/laser` from `sensor_msgs/LaserScan`.
    Laser,
    /// `pipeline/sensors/planar_odometry` from `nav_msgs/Odometry`.
    PlanarOdometry,
    /// `pipeline/sensors/odometry` (increments) from `nav_msgs/Odometry`.
    Odometry,
    /// `pipeline/sensors/cloud` from `sensor_msgs/PointCloud2`.
    Cloud,
    /// `pipeline/sensors/heading` from `sensor_msgs/Imu`.
    Heading,
    /// `pipeline/sensors/depth` from `sensor_msgs/FluidPressure`.
    Depth,
    /// `pipeline/sensors/buoy_ranges` from `sensor_msgs/Range`.
    BuoyRanges,
    /// `pipeline/sensors/cloud` from a depth `sensor_msgs/Image` and the `sensor_msgs/CameraInfo`
    /// of the route's `camera_info` topic.
    DepthImage,
}

impl InService {
    /// The ROS 2 type the route's topic must carry.
    pub fn ros_type(self) -> &'static str {
        match self {
            InService::Laser => LaserScan::TYPE_NAME,
            InService::PlanarOdometry | InService::Odometry => Odometry::TYPE_NAME,
            InService::Cloud => PointCloud2::TYPE_NAME,
            InService::Heading => Imu::TYPE_NAME,
            InService::Depth => FluidPressure::TYPE_NAME,
            InService::BuoyRanges => Range::TYPE_NAME,
            InService::DepthImage => Image::TYPE_NAME,
        }
    }

    /// The pipeline service it feeds.
    pub fn service(self) -> &'static str {
        use shared_types::services::*;
        match self {
            InService::Laser => LASER,
            InService::PlanarOdometry => PLANAR_ODOMETRY,
            InService::Odometry => ODOMETRY,
            InService::Cloud | InService::DepthImage => CLOUD,
            InService::Heading => HEADING,
            InService::Depth => DEPTH,
            InService::BuoyRanges => BUOY_RANGES,
        }
    }
}

/// One topic into the pipeline (`[[...routes]]`).
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct InRoute {
    /// The ROS topic (`/scan`).
    pub topic: String,
    /// The pipeline input it feeds.
    pub service: InService,
    /// Laser: where the laser sits on the robot, `body_from_laser` (x m, y m, yaw rad).
    #[serde(default)]
    pub body_from_laser: [f64; 3],
    /// Odometry (increments): σ of the forward speed where the twist covariance gives none, m/s.
    #[serde(default = "default_speed_sigma")]
    pub speed_sigma_mps: f64,
    /// Odometry (increments): σ of each rotation increment where the twist covariance gives
    /// none, rad.
    #[serde(default = "default_turn_sigma")]
    pub turn_sigma_rad: f64,
    /// Heading: σ of the yaw where the IMU's covariance gives none, rad.
    #[serde(default = "default_heading_sigma")]
    pub heading_sigma_rad: f64,
    /// Depth: pressure at the surface, Pa.
    #[serde(default = "default_surface")]
    pub surface_pa: f64,
    /// Depth: water density, kg/m³.
    #[serde(default = "default_density")]
    pub density_kg_m3: f64,
    /// Depth: σ where the message's variance is 0, m.
    #[serde(default = "default_depth_sigma")]
    pub depth_sigma_m: f64,
    /// Buoy ranges: `header.frame_id` → buoy id (a frame not listed gives the number it ends
    /// with: `buoy_3` → 3).
    #[serde(default)]
    pub beacon_ids: BTreeMap<String, u32>,
    /// Buoy ranges: σ where the message's variance is 0, m.
    #[serde(default = "default_range_sigma")]
    pub range_sigma_m: f64,
    /// Depth images: the topic of their `sensor_msgs/CameraInfo` (the latest one is used).
    #[serde(default)]
    pub camera_info: String,
    /// Depth images: use every `stride`-th pixel in both directions.
    #[serde(default = "default_stride")]
    pub stride: u32,
    /// Depth images: depths below this are dropped, m.
    #[serde(default = "default_min_depth")]
    pub min_depth_m: f32,
    /// Depth images: depths above this are dropped, m.
    #[serde(default = "default_max_depth")]
    pub max_depth_m: f32,
}

fn default_stride() -> u32 {
    2
}
fn default_min_depth() -> f32 {
    0.1
}
fn default_max_depth() -> f32 {
    20.0
}

fn default_speed_sigma() -> f64 {
    0.1
}
fn default_turn_sigma() -> f64 {
    0.01
}
fn default_heading_sigma() -> f64 {
    0.05
}
fn default_surface() -> f64 {
    PressureToDepth::default().surface_pa
}
fn default_density() -> f64 {
    PressureToDepth::default().density_kg_m3
}
fn default_depth_sigma() -> f64 {
    PressureToDepth::default().default_sigma_m
}
fn default_range_sigma() -> f64 {
    1.0
}

impl InRoute {
    /// A route with every option at its default.
    pub fn new(topic: &str, service: InService) -> Self {
        Self {
            topic: topic.to_string(),
            service,
            body_from_laser: [0.0; 3],
            speed_sigma_mps: default_speed_sigma(),
            turn_sigma_rad: default_turn_sigma(),
            heading_sigma_rad: default_heading_sigma(),
            surface_pa: default_surface(),
            density_kg_m3: default_density(),
            depth_sigma_m: default_depth_sigma(),
            beacon_ids: BTreeMap::new(),
            range_sigma_m: default_range_sigma(),
            camera_info: String::new(),
            stride: default_stride(),
            min_depth_m: default_min_depth(),
            max_depth_m: default_max_depth(),
        }
    }
}

/// Problems with the route's values, keyed under the route.
impl Validate for InRoute {
    fn validate(&self, issues: &mut Issues) {
        if !self.topic.starts_with('/') || self.topic.len() < 2 || self.topic.contains(char::is_whitespace) {
            issues.push("topic", format!("`{}` is not an absolute ROS topic name (`/scan`)", self.topic));
        }
        if !self.body_from_laser.iter().all(|v| v.is_finite()) {
            issues.push("body_from_laser", "must be finite");
        }
        for (k, v) in [
            ("speed_sigma_mps", self.speed_sigma_mps),
            ("turn_sigma_rad", self.turn_sigma_rad),
            ("heading_sigma_rad", self.heading_sigma_rad),
            ("density_kg_m3", self.density_kg_m3),
            ("depth_sigma_m", self.depth_sigma_m),
            ("range_sigma_m", self.range_sigma_m),
        ] {
            if !(v.is_finite() && v > 0.0) {
                issues.push(k, format!("{v}: must be > 0"));
            }
        }
        if self.service == InService::DepthImage {
            if !self.camera_info.starts_with('/') {
                issues.push("camera_info", "a depth image route needs the absolute topic of its CameraInfo");
            }
            if self.stride == 0 {
                issues.push("stride", "must be >= 1");
            }
            if !(self.min_depth_m >= 0.0 && self.max_depth_m > self.min_depth_m) {
                issues.push("max_depth_m", "needs 0 <= min_depth_m < max_depth_m");
            }
        }
        if !self.surface_pa.is_finite() || self.surface_pa < 0.0 {
            issues.push("surface_pa", format!("{}: must be >= 0", self.surface_pa));
        }
    }
}

/// A message of a route as wire values.
#[derive(Debug, Clone, PartialEq)]
pub enum Decoded {
    /// A laser scan (ranges on the wire's convention: [`convert::laser_range`]).
    Laser {
        /// ns.
        stamp_ns: u64,
        /// The scan's geometry.
        header: LaserScanHeader,
        /// Ranges, m.
        ranges: Vec<f32>,
    },
    /// Planar odometry.
    PlanarOdometry {
        /// ns.
        stamp_ns: u64,
        /// The odometry.
        odometry: PlanarOdometry,
    },
    /// An odometry increment (none for a route's first message).
    Odometry {
        /// ns.
        stamp_ns: u64,
        /// The input.
        input: OdometryInput,
    },
    /// A cloud's finite points in the sensor frame (`frame_id` of the message).
    Cloud {
        /// ns.
        stamp_ns: u64,
        /// Points, m.
        points: Vec<[f32; 3]>,
        /// Points left out (NaN / Inf in a non-dense cloud).
        non_finite: usize,
    },
    /// A heading.
    Heading {
        /// ns.
        stamp_ns: u64,
        /// The reading.
        reading: HeadingReading,
    },
    /// A pressure depth.
    Depth {
        /// ns.
        stamp_ns: u64,
        /// The reading.
        reading: DepthReading,
    },
    /// One buoy range.
    BuoyRange {
        /// ns.
        stamp_ns: u64,
        /// The range.
        range: BuoyRange,
    },
    /// The first odometry message of an increments route: nothing to publish yet.
    Nothing,
}

/// Why a route's message was not used.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum InError {
    /// It does not decode as the route's type.
    #[error(transparent)]
    Cdr(#[from] CdrError),
    /// It decodes, but a field breaks what the pipeline input needs.
    #[error(transparent)]
    Invalid(#[from] ConvertError),
}

impl InError {
    /// A short name of the kind, for counters (`undecodable`, `invalid`).
    pub fn kind(&self) -> &'static str {
        match self {
            InError::Cdr(_) => "undecodable",
            InError::Invalid(_) => "invalid",
        }
    }
}

macro_rules! try_convert {
    ($e:expr) => {
        match $e {
            Ok(v) => v,
            Err(e) => return Ok(Err(e)),
        }
    };
}

/// Decodes a route's messages; keeps what a route needs between them (odometry increments).
#[derive(Debug, Clone)]
pub struct RouteDecoder {
    /// The route.
    pub route: InRoute,
    increments: OdometryIncrements,
    /// The latest CameraInfo of a depth-image route.
    camera_info: Option<CameraInfo>,
    /// Depth images that came before any CameraInfo.
    pub images_without_camera_info: u64,
}

impl RouteDecoder {
    /// A decoder for `route`.
    pub fn new(route: InRoute) -> Self {
        Self { route, increments: OdometryIncrements::default(), camera_info: None, images_without_camera_info: 0 }
    }

    /// The CameraInfo a depth-image route back-projects with (the latest one wins).
    pub fn set_camera_info(&mut self, info: CameraInfo) {
        self.camera_info = Some(info);
    }

    /// Decodes one encapsulated-CDR message of the route's topic.
    pub fn decode(&mut self, data: &[u8]) -> Result<Decoded, InError> {
        let ty = self.route.service.ros_type();
        let body = |e: cdr_encoding::Error| InError::Cdr(CdrError::Body { type_name: ty, reason: e.to_string() });
        let r = if cdr::representation(data)? {
            self.decode_from(&mut cdr_encoding::CdrDeserializer::<byteorder::LittleEndian>::new(&data[4..]))
        } else {
            self.decode_from(&mut cdr_encoding::CdrDeserializer::<byteorder::BigEndian>::new(&data[4..]))
        };
        Ok(r.map_err(body)??)
    }

    /// Decodes one message of the route's type from a deserializer (the gateway's DDS reader
    /// hands one over): a deserializer error is the outer one, a field that breaks what the
    /// pipeline input needs the inner.
    pub fn decode_from<'de, D: serde::Deserializer<'de>>(
        &mut self,
        d: D,
    ) -> Result<Result<Decoded, ConvertError>, D::Error> {
        let r = &self.route;
        Ok(Ok(match r.service {
            InService::Laser => {
                let msg = LaserScan::deserialize(d)?;
                let (stamp_ns, header) = try_convert!(convert::laser_scan(&msg, r.body_from_laser));
                let ranges = msg.ranges.iter().map(|x| convert::laser_range(*x, msg.range_max)).collect();
                Decoded::Laser { stamp_ns, header, ranges }
            }
            InService::PlanarOdometry => {
                let msg = Odometry::deserialize(d)?;
                let (stamp_ns, odometry) = try_convert!(convert::planar_odometry(&msg));
                Decoded::PlanarOdometry { stamp_ns, odometry }
            }
            InService::Odometry => {
                let msg = Odometry::deserialize(d)?;
                let noise = OdometryNoise { speed_sigma_mps: r.speed_sigma_mps, turn_sigma_rad: r.turn_sigma_rad };
                match try_convert!(self.increments.push(&msg, noise)) {
                    Some((stamp_ns, input)) => Decoded::Odometry { stamp_ns, input },
                    None => Decoded::Nothing,
                }
            }
            InService::Cloud => {
                let msg = PointCloud2::deserialize(d)?;
                let stamp_ns = try_convert!(convert::stamp_ns(&msg.header));
                let layout = try_convert!(convert::CloudLayout::of(&msg));
                let points: Vec<[f32; 3]> = layout.finite_points(msg.data.as_slice()).collect();
                Decoded::Cloud { stamp_ns, non_finite: layout.len() - points.len(), points }
            }
            InService::Heading => {
                let msg = Imu::deserialize(d)?;
                let (stamp_ns, reading) =
                    try_convert!(convert::heading(&msg, HeadingNoise { default_sigma_rad: r.heading_sigma_rad }));
                Decoded::Heading { stamp_ns, reading }
            }
            InService::Depth => {
                let msg = FluidPressure::deserialize(d)?;
                let p = PressureToDepth {
                    surface_pa: r.surface_pa,
                    density_kg_m3: r.density_kg_m3,
                    default_sigma_m: r.depth_sigma_m,
                    ..PressureToDepth::default()
                };
                let (stamp_ns, reading) = try_convert!(convert::depth(&msg, p));
                Decoded::Depth { stamp_ns, reading }
            }
            InService::DepthImage => {
                let msg = Image::deserialize(d)?;
                let Some(info) = &self.camera_info else {
                    self.images_without_camera_info += 1;
                    return Ok(Err(ConvertError::Invalid {
                        field: "camera_info",
                        why: format!("no CameraInfo on `{}` yet", r.camera_info),
                    }));
                };
                let s = DepthImageSampling { stride: r.stride, min_depth_m: r.min_depth_m, max_depth_m: r.max_depth_m };
                let (stamp_ns, points, non_finite) = try_convert!(convert::depth_image_points(&msg, info, s));
                Decoded::Cloud { stamp_ns, points, non_finite }
            }
            InService::BuoyRanges => {
                let msg = Range::deserialize(d)?;
                let (stamp_ns, range) = try_convert!(convert::buoy_range(&msg, &r.beacon_ids, r.range_sigma_m));
                Decoded::BuoyRange { stamp_ns, range }
            }
        }))
    }
}
