//! The ROS 2 messages the pipeline reads and writes, field for field as in their `.msg` files
//! (ROS 2 Jazzy; the Humble layouts are the same except `sensor_msgs/Range`, which Jazzy grew a
//! `variance`: see [`Range`]). Serialized with serde as CDR ([`crate::cdr`]), the encoding
//! RustDDS, Fast DDS, Cyclone DDS and rosbag2 use: fields in order, each aligned to its size,
//! strings as a `u32` length (with the NUL) and the bytes, sequences as a `u32` count and the
//! elements, fixed arrays as the elements alone.
//!
//! Byte sequences (`uint8[]`, `int8[]`) are [`Bytes`]: borrowed from the buffer when decoding
//! from one (no copy: a 300,000-point `PointCloud2` is read in place), written in one piece.
//!
//! Every message type implements [`Message`]: its ROS 2 type name; [`crate::schema`] has the
//! `.msg` text of each.

use std::borrow::Cow;
use std::fmt;

use serde::de::{self, SeqAccess, Visitor};
use serde::ser::SerializeTuple;
use serde::{Deserialize, Deserializer, Serialize, Serializer};

/// A ROS 2 message type.
pub trait Message {
    /// The ROS 2 type name, `package/msg/Type` (as in a bag's schema and `ros2 topic info`).
    const TYPE_NAME: &'static str;
}

/// The DDS type name ROS 2 uses for a message type: `sensor_msgs/msg/LaserScan` →
/// `sensor_msgs::msg::dds_::LaserScan_`.
pub fn dds_type_name(ros_type: &str) -> String {
    let mut parts: Vec<&str> = ros_type.split('/').collect();
    let last = parts.pop().unwrap_or_default();
    format!("{}::dds_::{last}_", parts.join("::"))
}

macro_rules! message {
    ($t:ty, $name:expr) => {
        impl Message for $t {
            const TYPE_NAME: &'static str = $name;
        }
    };
}

/// A byte sequence (`uint8[]`, `int8[]`): borrowed from the decoded buffer where possible.
#[derive(Clone, PartialEq, Eq, Default)]
pub struct Bytes<'a>(pub Cow<'a, [u8]>);

impl fmt::Debug for Bytes<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "Bytes({} bytes)", self.0.len())
    }
}

impl<'a> Bytes<'a> {
    /// Owned bytes.
    pub fn owned(v: Vec<u8>) -> Self {
        Bytes(Cow::Owned(v))
    }
    /// Borrowed bytes.
    pub fn borrowed(v: &'a [u8]) -> Self {
        Bytes(Cow::Borrowed(v))
    }
    /// The bytes.
    pub fn as_slice(&self) -> &[u8] {
        &self.0
    }
}

impl Serialize for Bytes<'_> {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_bytes(&self.0)
    }
}

impl<'de: 'a, 'a> Deserialize<'de> for Bytes<'a> {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        struct V;
        impl<'de> Visitor<'de> for V {
            type Value = Bytes<'de>;
            fn expecting(&self, f: &mut fmt::Formatter) -> fmt::Result {
                f.write_str("a byte sequence")
            }
            fn visit_borrowed_bytes<E: de::Error>(self, v: &'de [u8]) -> Result<Self::Value, E> {
                Ok(Bytes(Cow::Borrowed(v)))
            }
            fn visit_bytes<E: de::Error>(self, v: &[u8]) -> Result<Self::Value, E> {
                Ok(Bytes(Cow::Owned(v.to_vec())))
            }
            fn visit_byte_buf<E: de::Error>(self, v: Vec<u8>) -> Result<Self::Value, E> {
                Ok(Bytes(Cow::Owned(v)))
            }
            fn visit_seq<A: SeqAccess<'de>>(self, mut seq: A) -> Result<Self::Value, A::Error> {
                let mut v = Vec::with_capacity(seq.size_hint().unwrap_or(0).min(1 << 20));
                while let Some(b) = seq.next_element()? {
                    v.push(b);
                }
                Ok(Bytes(Cow::Owned(v)))
            }
        }
        d.deserialize_bytes(V)
    }
}

/// Fixed arrays longer than serde's 32 (`float64[36]`): the elements alone, as CDR writes them.
mod array {
    use super::*;

    pub fn serialize<S: Serializer, const N: usize>(a: &[f64; N], s: S) -> Result<S::Ok, S::Error> {
        let mut t = s.serialize_tuple(N)?;
        for x in a {
            t.serialize_element(x)?;
        }
        t.end()
    }

    pub fn deserialize<'de, D: Deserializer<'de>, const N: usize>(d: D) -> Result<[f64; N], D::Error> {
        struct V<const N: usize>;
        impl<'de, const N: usize> Visitor<'de> for V<N> {
            type Value = [f64; N];
            fn expecting(&self, f: &mut fmt::Formatter) -> fmt::Result {
                write!(f, "{N} float64")
            }
            fn visit_seq<A: SeqAccess<'de>>(self, mut seq: A) -> Result<Self::Value, A::Error> {
                let mut out = [0.0; N];
                for (i, o) in out.iter_mut().enumerate() {
                    *o = seq.next_element()?.ok_or_else(|| de::Error::invalid_length(i, &self))?;
                }
                Ok(out)
            }
        }
        d.deserialize_tuple(N, V::<N>)
    }
}

/// `builtin_interfaces/msg/Time`: seconds and nanoseconds since the clock's epoch.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct Time {
    /// Seconds.
    pub sec: i32,
    /// Nanoseconds, < 1e9.
    pub nanosec: u32,
}
message!(Time, "builtin_interfaces/msg/Time");

impl Time {
    /// From nanoseconds (saturating at the largest `sec`).
    pub fn from_ns(ns: u64) -> Self {
        let sec = (ns / 1_000_000_000).min(i32::MAX as u64) as i32;
        Time { sec, nanosec: (ns % 1_000_000_000) as u32 }
    }
    /// To nanoseconds; `None` for a negative time or `nanosec` ≥ 1e9.
    pub fn to_ns(self) -> Option<u64> {
        (self.sec >= 0 && self.nanosec < 1_000_000_000).then(|| self.sec as u64 * 1_000_000_000 + self.nanosec as u64)
    }
}

/// `builtin_interfaces/msg/Duration`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct Duration {
    /// Seconds.
    pub sec: i32,
    /// Nanoseconds, < 1e9.
    pub nanosec: u32,
}
message!(Duration, "builtin_interfaces/msg/Duration");

/// `std_msgs/msg/Header`.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct Header {
    /// Measurement time.
    pub stamp: Time,
    /// Frame of the data.
    pub frame_id: String,
}
message!(Header, "std_msgs/msg/Header");

/// `std_msgs/msg/ColorRGBA`.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct ColorRGBA {
    /// Red, 0-1.
    pub r: f32,
    /// Green, 0-1.
    pub g: f32,
    /// Blue, 0-1.
    pub b: f32,
    /// Alpha, 0-1.
    pub a: f32,
}
message!(ColorRGBA, "std_msgs/msg/ColorRGBA");

/// `geometry_msgs/msg/Vector3`.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct Vector3 {
    /// x.
    pub x: f64,
    /// y.
    pub y: f64,
    /// z.
    pub z: f64,
}
message!(Vector3, "geometry_msgs/msg/Vector3");

/// `geometry_msgs/msg/Point`.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct Point {
    /// x, m.
    pub x: f64,
    /// y, m.
    pub y: f64,
    /// z, m.
    pub z: f64,
}
message!(Point, "geometry_msgs/msg/Point");

/// `geometry_msgs/msg/Quaternion` (x, y, z, w).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Quaternion {
    /// x.
    pub x: f64,
    /// y.
    pub y: f64,
    /// z.
    pub z: f64,
    /// w.
    pub w: f64,
}
message!(Quaternion, "geometry_msgs/msg/Quaternion");

impl Default for Quaternion {
    fn default() -> Self {
        Quaternion { x: 0.0, y: 0.0, z: 0.0, w: 1.0 }
    }
}

/// `geometry_msgs/msg/Pose`.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct Pose {
    /// Position, m.
    pub position: Point,
    /// Orientation.
    pub orientation: Quaternion,
}
message!(Pose, "geometry_msgs/msg/Pose");

/// `geometry_msgs/msg/PoseWithCovariance`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct PoseWithCovariance {
    /// The pose.
    pub pose: Pose,
    /// 6×6 row-major over (x, y, z, rotation about x, y, z of the parent frame), m² / rad².
    #[serde(with = "array")]
    pub covariance: [f64; 36],
}
message!(PoseWithCovariance, "geometry_msgs/msg/PoseWithCovariance");

impl Default for PoseWithCovariance {
    fn default() -> Self {
        PoseWithCovariance { pose: Pose::default(), covariance: [0.0; 36] }
    }
}

/// `geometry_msgs/msg/Twist`.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct Twist {
    /// Linear velocity, m/s.
    pub linear: Vector3,
    /// Angular velocity, rad/s.
    pub angular: Vector3,
}
message!(Twist, "geometry_msgs/msg/Twist");

/// `geometry_msgs/msg/TwistWithCovariance`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct TwistWithCovariance {
    /// The twist.
    pub twist: Twist,
    /// 6×6 row-major over (vx, vy, vz, ωx, ωy, ωz).
    #[serde(with = "array")]
    pub covariance: [f64; 36],
}
message!(TwistWithCovariance, "geometry_msgs/msg/TwistWithCovariance");

impl Default for TwistWithCovariance {
    fn default() -> Self {
        TwistWithCovariance { twist: Twist::default(), covariance: [0.0; 36] }
    }
}

/// `geometry_msgs/msg/PoseStamped`.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct PoseStamped {
    /// Time and frame.
    pub header: Header,
    /// The pose.
    pub pose: Pose,
}
message!(PoseStamped, "geometry_msgs/msg/PoseStamped");

/// `geometry_msgs/msg/PoseWithCovarianceStamped`.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct PoseWithCovarianceStamped {
    /// Time and frame.
    pub header: Header,
    /// The pose.
    pub pose: PoseWithCovariance,
}
message!(PoseWithCovarianceStamped, "geometry_msgs/msg/PoseWithCovarianceStamped");

/// `geometry_msgs/msg/Transform`.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct Transform {
    /// Translation, m.
    pub translation: Vector3,
    /// Rotation.
    pub rotation: Quaternion,
}
message!(Transform, "geometry_msgs/msg/Transform");

/// `geometry_msgs/msg/TransformStamped`: `header.frame_id` from `child_frame_id`.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct TransformStamped {
    /// Time and parent frame.
    pub header: Header,
    /// Child frame.
    pub child_frame_id: String,
    /// parent_from_child.
    pub transform: Transform,
}
message!(TransformStamped, "geometry_msgs/msg/TransformStamped");

/// `tf2_msgs/msg/TFMessage` (`/tf`, `/tf_static`).
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct TFMessage {
    /// The transforms.
    pub transforms: Vec<TransformStamped>,
}
message!(TFMessage, "tf2_msgs/msg/TFMessage");

/// `nav_msgs/msg/Odometry`: `pose` in `header.frame_id`, `twist` in `child_frame_id`.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct Odometry {
    /// Time and the pose's frame.
    pub header: Header,
    /// The body frame (the twist's frame).
    pub child_frame_id: String,
    /// frame_from_body.
    pub pose: PoseWithCovariance,
    /// Body velocity in the child frame.
    pub twist: TwistWithCovariance,
}
message!(Odometry, "nav_msgs/msg/Odometry");

/// `nav_msgs/msg/Path`.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct Path {
    /// Time and frame.
    pub header: Header,
    /// The poses, oldest first.
    pub poses: Vec<PoseStamped>,
}
message!(Path, "nav_msgs/msg/Path");

/// `nav_msgs/msg/MapMetaData`.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct MapMetaData {
    /// When the map was loaded.
    pub map_load_time: Time,
    /// Cell side, m.
    pub resolution: f32,
    /// Cells along x.
    pub width: u32,
    /// Cells along y.
    pub height: u32,
    /// Pose of cell (0, 0)'s corner in the map frame.
    pub origin: Pose,
}
message!(MapMetaData, "nav_msgs/msg/MapMetaData");

/// `nav_msgs/msg/OccupancyGrid`: row-major, first row at the lowest y; −1 unknown, 0-100 %.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct OccupancyGrid<'a> {
    /// Time and frame.
    pub header: Header,
    /// Geometry.
    pub info: MapMetaData,
    /// The cells (`int8[]`, as bytes).
    #[serde(borrow)]
    pub data: Bytes<'a>,
}
message!(OccupancyGrid<'_>, "nav_msgs/msg/OccupancyGrid");

/// `sensor_msgs/msg/LaserScan`.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct LaserScan {
    /// Time of the first beam, the laser's frame.
    pub header: Header,
    /// Angle of the first beam, rad.
    pub angle_min: f32,
    /// Angle of the last beam, rad.
    pub angle_max: f32,
    /// Angle between beams, rad.
    pub angle_increment: f32,
    /// Time between beams, s.
    pub time_increment: f32,
    /// Time between scans, s.
    pub scan_time: f32,
    /// Minimum valid range, m.
    pub range_min: f32,
    /// Maximum valid range, m.
    pub range_max: f32,
    /// Ranges, m (REP 117: +Inf no return, −Inf too close, NaN invalid).
    pub ranges: Vec<f32>,
    /// Intensities (device units), empty or one per beam.
    pub intensities: Vec<f32>,
}
message!(LaserScan, "sensor_msgs/msg/LaserScan");

/// `sensor_msgs/msg/PointField` datatype: FLOAT32.
pub const POINT_FIELD_FLOAT32: u8 = 7;
/// `sensor_msgs/msg/PointField` datatype: FLOAT64.
pub const POINT_FIELD_FLOAT64: u8 = 8;

/// `sensor_msgs/msg/PointField`.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct PointField {
    /// Field name (`x`, `y`, `z`, `intensity`, ...).
    pub name: String,
    /// Offset in a point, bytes.
    pub offset: u32,
    /// Data type (1 INT8 ... 7 FLOAT32, 8 FLOAT64).
    pub datatype: u8,
    /// Elements in the field.
    pub count: u32,
}
message!(PointField, "sensor_msgs/msg/PointField");

/// `sensor_msgs/msg/PointCloud2`.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct PointCloud2<'a> {
    /// Time and frame.
    pub header: Header,
    /// Rows (1 for an unordered cloud).
    pub height: u32,
    /// Points per row.
    pub width: u32,
    /// The layout of a point.
    pub fields: Vec<PointField>,
    /// Byte order of `data`.
    pub is_bigendian: bool,
    /// Bytes per point.
    pub point_step: u32,
    /// Bytes per row.
    pub row_step: u32,
    /// The points.
    #[serde(borrow)]
    pub data: Bytes<'a>,
    /// No invalid (NaN) points.
    pub is_dense: bool,
}
message!(PointCloud2<'_>, "sensor_msgs/msg/PointCloud2");

/// `sensor_msgs/msg/Image`.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct Image<'a> {
    /// Time and the camera's optical frame.
    pub header: Header,
    /// Rows.
    pub height: u32,
    /// Columns.
    pub width: u32,
    /// Pixel encoding (`16UC1`, `32FC1`, `mono16`, `rgb8`, ...).
    pub encoding: String,
    /// Byte order of `data`.
    pub is_bigendian: u8,
    /// Bytes per row.
    pub step: u32,
    /// The pixels.
    #[serde(borrow)]
    pub data: Bytes<'a>,
}
message!(Image<'_>, "sensor_msgs/msg/Image");

/// `sensor_msgs/msg/RegionOfInterest`.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct RegionOfInterest {
    /// Left column.
    pub x_offset: u32,
    /// Top row.
    pub y_offset: u32,
    /// Rows.
    pub height: u32,
    /// Columns.
    pub width: u32,
    /// Rectify the region.
    pub do_rectify: bool,
}
message!(RegionOfInterest, "sensor_msgs/msg/RegionOfInterest");

/// `sensor_msgs/msg/CameraInfo`.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct CameraInfo {
    /// Time and the camera's optical frame.
    pub header: Header,
    /// Rows.
    pub height: u32,
    /// Columns.
    pub width: u32,
    /// `plumb_bob`, `rational_polynomial`, ...
    pub distortion_model: String,
    /// Distortion parameters.
    pub d: Vec<f64>,
    /// Intrinsics K, 3×3 row-major.
    pub k: [f64; 9],
    /// Rectification R, 3×3 row-major.
    pub r: [f64; 9],
    /// Projection P, 3×4 row-major.
    pub p: [f64; 12],
    /// Binning along x.
    pub binning_x: u32,
    /// Binning along y.
    pub binning_y: u32,
    /// Region of interest.
    pub roi: RegionOfInterest,
}
message!(CameraInfo, "sensor_msgs/msg/CameraInfo");

/// `sensor_msgs/msg/Imu`.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct Imu {
    /// Time and the IMU's frame.
    pub header: Header,
    /// Orientation (of the IMU frame in a fixed frame).
    pub orientation: Quaternion,
    /// Its covariance, 3×3 row-major about x, y, z, rad²; element 0 = −1: no orientation.
    pub orientation_covariance: [f64; 9],
    /// Angular velocity, rad/s.
    pub angular_velocity: Vector3,
    /// Its covariance.
    pub angular_velocity_covariance: [f64; 9],
    /// Linear acceleration, m/s².
    pub linear_acceleration: Vector3,
    /// Its covariance.
    pub linear_acceleration_covariance: [f64; 9],
}
message!(Imu, "sensor_msgs/msg/Imu");

/// `sensor_msgs/msg/FluidPressure`.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct FluidPressure {
    /// Time and frame.
    pub header: Header,
    /// Absolute pressure, Pa.
    pub fluid_pressure: f64,
    /// Variance, Pa² (0: unknown).
    pub variance: f64,
}
message!(FluidPressure, "sensor_msgs/msg/FluidPressure");

/// `sensor_msgs/msg/Range` as in Jazzy (with `variance`); one of Humble's layout (without it)
/// decodes too, with `variance` 0 ("unknown").
#[derive(Debug, Clone, PartialEq, Default, Serialize)]
pub struct Range {
    /// Time and the sensor's frame (the beacon id, for buoy ranges).
    pub header: Header,
    /// 0 ultrasound, 1 infrared.
    pub radiation_type: u8,
    /// Field of view, rad.
    pub field_of_view: f32,
    /// Minimum valid range, m.
    pub min_range: f32,
    /// Maximum valid range, m.
    pub max_range: f32,
    /// The range, m.
    pub range: f32,
    /// Variance, m² (0: unknown).
    pub variance: f32,
}
message!(Range, "sensor_msgs/msg/Range");

impl<'de> Deserialize<'de> for Range {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        struct V;
        impl<'de> Visitor<'de> for V {
            type Value = Range;
            fn expecting(&self, f: &mut fmt::Formatter) -> fmt::Result {
                f.write_str("a sensor_msgs/Range")
            }
            fn visit_seq<A: SeqAccess<'de>>(self, mut seq: A) -> Result<Range, A::Error> {
                let next = |i: usize| de::Error::invalid_length(i, &"6 or 7 fields");
                let header = seq.next_element()?.ok_or_else(|| next(0))?;
                let radiation_type = seq.next_element()?.ok_or_else(|| next(1))?;
                let field_of_view = seq.next_element()?.ok_or_else(|| next(2))?;
                let min_range = seq.next_element()?.ok_or_else(|| next(3))?;
                let max_range = seq.next_element()?.ok_or_else(|| next(4))?;
                let range = seq.next_element()?.ok_or_else(|| next(5))?;
                // Humble's layout ends here: reading past its end is the absent `variance`.
                let variance = seq.next_element().ok().flatten().unwrap_or(0.0);
                Ok(Range { header, radiation_type, field_of_view, min_range, max_range, range, variance })
            }
        }
        const FIELDS: &[&str] =
            &["header", "radiation_type", "field_of_view", "min_range", "max_range", "range", "variance"];
        d.deserialize_struct("Range", FIELDS, V)
    }
}

/// `sensor_msgs/msg/Range` before Jazzy (no `variance`): what a Humble peer sends.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct RangeHumble {
    /// Time and frame.
    pub header: Header,
    /// 0 ultrasound, 1 infrared.
    pub radiation_type: u8,
    /// Field of view, rad.
    pub field_of_view: f32,
    /// Minimum valid range, m.
    pub min_range: f32,
    /// Maximum valid range, m.
    pub max_range: f32,
    /// The range, m.
    pub range: f32,
}

/// `visualization_msgs/msg/UVCoordinate`.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct UVCoordinate {
    /// u.
    pub u: f32,
    /// v.
    pub v: f32,
}
message!(UVCoordinate, "visualization_msgs/msg/UVCoordinate");

/// `sensor_msgs/msg/CompressedImage`.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct CompressedImage<'a> {
    /// Time and frame.
    pub header: Header,
    /// `jpeg`, `png`.
    pub format: String,
    /// The image file.
    #[serde(borrow)]
    pub data: Bytes<'a>,
}
message!(CompressedImage<'_>, "sensor_msgs/msg/CompressedImage");

/// `visualization_msgs/msg/MeshFile`.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct MeshFile<'a> {
    /// File name.
    pub filename: String,
    /// File contents.
    #[serde(borrow)]
    pub data: Bytes<'a>,
}
message!(MeshFile<'_>, "visualization_msgs/msg/MeshFile");

/// `visualization_msgs/msg/Marker` type: a sphere per point.
pub const MARKER_SPHERE_LIST: i32 = 7;
/// `visualization_msgs/msg/Marker` type: a cube per point.
pub const MARKER_CUBE_LIST: i32 = 6;
/// `visualization_msgs/msg/Marker` action: add or modify.
pub const MARKER_ADD: i32 = 0;
/// `visualization_msgs/msg/Marker` action: delete every marker.
pub const MARKER_DELETEALL: i32 = 3;

/// `visualization_msgs/msg/Marker`.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct Marker<'a> {
    /// Time and frame.
    pub header: Header,
    /// Namespace.
    pub ns: String,
    /// Id within the namespace.
    pub id: i32,
    /// Shape (`MARKER_*`).
    #[serde(rename = "type")]
    pub kind: i32,
    /// Add, delete.
    pub action: i32,
    /// Pose of the marker.
    pub pose: Pose,
    /// Size, m.
    pub scale: Vector3,
    /// Colour.
    pub color: ColorRGBA,
    /// How long it stays (0: for ever).
    pub lifetime: Duration,
    /// Follow the frame.
    pub frame_locked: bool,
    /// Points of a list marker.
    pub points: Vec<Point>,
    /// Colours per point (empty: `color`).
    pub colors: Vec<ColorRGBA>,
    /// Texture resource.
    pub texture_resource: String,
    /// Texture.
    #[serde(borrow)]
    pub texture: CompressedImage<'a>,
    /// Texture coordinates.
    pub uv_coordinates: Vec<UVCoordinate>,
    /// Text.
    pub text: String,
    /// Mesh resource.
    pub mesh_resource: String,
    /// Mesh file.
    #[serde(borrow)]
    pub mesh_file: MeshFile<'a>,
    /// Use the mesh's materials.
    pub mesh_use_embedded_materials: bool,
}
message!(Marker<'_>, "visualization_msgs/msg/Marker");

/// `visualization_msgs/msg/MarkerArray`.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct MarkerArray<'a> {
    /// The markers.
    #[serde(borrow)]
    pub markers: Vec<Marker<'a>>,
}
message!(MarkerArray<'_>, "visualization_msgs/msg/MarkerArray");

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn dds_type_names_follow_the_ros2_convention() {
        assert_eq!(dds_type_name(LaserScan::TYPE_NAME), "sensor_msgs::msg::dds_::LaserScan_");
        assert_eq!(dds_type_name(TFMessage::TYPE_NAME), "tf2_msgs::msg::dds_::TFMessage_");
    }

    #[test]
    fn time_converts_to_and_from_nanoseconds() {
        let t = Time::from_ns(1_700_000_000_123_456_789);
        assert_eq!(t, Time { sec: 1_700_000_000, nanosec: 123_456_789 });
        assert_eq!(t.to_ns(), Some(1_700_000_000_123_456_789));
        assert_eq!(Time { sec: -1, nanosec: 0 }.to_ns(), None);
        assert_eq!(Time { sec: 1, nanosec: 1_000_000_000 }.to_ns(), None);
    }
}
