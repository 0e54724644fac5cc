//! The `.msg` definitions of the messages in [`crate::msgs`], and the schema text rosbag2 writes
//! into an MCAP file for a type (`ros2msg` encoding): the type's own definition, then each type
//! it uses once, after a line of 80 `=` and `MSG: package/Type`.

/// `(type, .msg text)`, with the types named `package/msg/Type`.
const DEFINITIONS: &[(&str, &str)] = &[
    ("builtin_interfaces/msg/Time", "int32 sec\nuint32 nanosec\n"),
    ("builtin_interfaces/msg/Duration", "int32 sec\nuint32 nanosec\n"),
    ("std_msgs/msg/Header", "builtin_interfaces/Time stamp\nstring frame_id\n"),
    ("std_msgs/msg/ColorRGBA", "float32 r\nfloat32 g\nfloat32 b\nfloat32 a\n"),
    ("geometry_msgs/msg/Vector3", "float64 x\nfloat64 y\nfloat64 z\n"),
    ("geometry_msgs/msg/Point", "float64 x\nfloat64 y\nfloat64 z\n"),
    ("geometry_msgs/msg/Quaternion", "float64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1\n"),
    ("geometry_msgs/msg/Pose", "Point position\nQuaternion orientation\n"),
    ("geometry_msgs/msg/PoseWithCovariance", "Pose pose\nfloat64[36] covariance\n"),
    ("geometry_msgs/msg/Twist", "Vector3 linear\nVector3 angular\n"),
    ("geometry_msgs/msg/TwistWithCovariance", "Twist twist\nfloat64[36] covariance\n"),
    ("geometry_msgs/msg/PoseStamped", "std_msgs/Header header\nPose pose\n"),
    ("geometry_msgs/msg/PoseWithCovarianceStamped", "std_msgs/Header header\nPoseWithCovariance pose\n"),
    ("geometry_msgs/msg/Transform", "Vector3 translation\nQuaternion rotation\n"),
    ("geometry_msgs/msg/TransformStamped", "std_msgs/Header header\nstring child_frame_id\nTransform transform\n"),
    ("tf2_msgs/msg/TFMessage", "geometry_msgs/TransformStamped[] transforms\n"),
    (
        "nav_msgs/msg/Odometry",
        "std_msgs/Header header\nstring child_frame_id\ngeometry_msgs/PoseWithCovariance pose\n\
         geometry_msgs/TwistWithCovariance twist\n",
    ),
    ("nav_msgs/msg/Path", "std_msgs/Header header\ngeometry_msgs/PoseStamped[] poses\n"),
    (
        "nav_msgs/msg/MapMetaData",
        "builtin_interfaces/Time map_load_time\nfloat32 resolution\nuint32 width\nuint32 height\n\
         geometry_msgs/Pose origin\n",
    ),
    ("nav_msgs/msg/OccupancyGrid", "std_msgs/Header header\nMapMetaData info\nint8[] data\n"),
    (
        "sensor_msgs/msg/LaserScan",
        "std_msgs/Header header\nfloat32 angle_min\nfloat32 angle_max\nfloat32 angle_increment\n\
         float32 time_increment\nfloat32 scan_time\nfloat32 range_min\nfloat32 range_max\n\
         float32[] ranges\nfloat32[] intensities\n",
    ),
    (
        "sensor_msgs/msg/PointField",
        "uint8 INT8=1\nuint8 UINT8=2\nuint8 INT16=3\nuint8 UINT16=4\nuint8 INT32=5\nuint8 UINT32=6\n\
         uint8 FLOAT32=7\nuint8 FLOAT64=8\nstring name\nuint32 offset\nuint8 datatype\nuint32 count\n",
    ),
    (
        "sensor_msgs/msg/PointCloud2",
        "std_msgs/Header header\nuint32 height\nuint32 width\nPointField[] fields\nbool is_bigendian\n\
         uint32 point_step\nuint32 row_step\nuint8[] data\nbool is_dense\n",
    ),
    (
        "sensor_msgs/msg/Image",
        "std_msgs/Header header\nuint32 height\nuint32 width\nstring encoding\nuint8 is_bigendian\n\
         uint32 step\nuint8[] data\n",
    ),
    (
        "sensor_msgs/msg/RegionOfInterest",
        "uint32 x_offset\nuint32 y_offset\nuint32 height\nuint32 width\nbool do_rectify\n",
    ),
    (
        "sensor_msgs/msg/CameraInfo",
        "std_msgs/Header header\nuint32 height\nuint32 width\nstring distortion_model\nfloat64[] d\n\
         float64[9] k\nfloat64[9] r\nfloat64[12] p\nuint32 binning_x\nuint32 binning_y\n\
         RegionOfInterest roi\n",
    ),
    (
        "sensor_msgs/msg/Imu",
        "std_msgs/Header header\ngeometry_msgs/Quaternion orientation\nfloat64[9] orientation_covariance\n\
         geometry_msgs/Vector3 angular_velocity\nfloat64[9] angular_velocity_covariance\n\
         geometry_msgs/Vector3 linear_acceleration\nfloat64[9] linear_acceleration_covariance\n",
    ),
    ("sensor_msgs/msg/FluidPressure", "std_msgs/Header header\nfloat64 fluid_pressure\nfloat64 variance\n"),
    (
        "sensor_msgs/msg/Range",
        "uint8 ULTRASOUND=0\nuint8 INFRARED=1\nstd_msgs/Header header\nuint8 radiation_type\n\
         float32 field_of_view\nfloat32 min_range\nfloat32 max_range\nfloat32 range\nfloat32 variance\n",
    ),
    ("sensor_msgs/msg/CompressedImage", "std_msgs/Header header\nstring format\nuint8[] data\n"),
    ("visualization_msgs/msg/UVCoordinate", "float32 u\nfloat32 v\n"),
    ("visualization_msgs/msg/MeshFile", "string filename\nuint8[] data\n"),
    (
        "visualization_msgs/msg/Marker",
        "int32 ARROW=0\nint32 CUBE=1\nint32 SPHERE=2\nint32 CYLINDER=3\nint32 LINE_STRIP=4\n\
         int32 LINE_LIST=5\nint32 CUBE_LIST=6\nint32 SPHERE_LIST=7\nint32 POINTS=8\n\
         int32 TEXT_VIEW_FACING=9\nint32 MESH_RESOURCE=10\nint32 TRIANGLE_LIST=11\nint32 ARROW_STRIP=12\n\
         int32 ADD=0\nint32 MODIFY=0\nint32 DELETE=2\nint32 DELETEALL=3\n\
         std_msgs/Header header\nstring ns\nint32 id\nint32 type\nint32 action\n\
         geometry_msgs/Pose pose\ngeometry_msgs/Vector3 scale\nstd_msgs/ColorRGBA color\n\
         builtin_interfaces/Duration lifetime\nbool frame_locked\ngeometry_msgs/Point[] points\n\
         std_msgs/ColorRGBA[] colors\nstring texture_resource\nsensor_msgs/CompressedImage texture\n\
         UVCoordinate[] uv_coordinates\nstring text\nstring mesh_resource\nMeshFile mesh_file\n\
         bool mesh_use_embedded_materials\n",
    ),
    ("visualization_msgs/msg/MarkerArray", "Marker[] markers\n"),
];

const PRIMITIVES: &[&str] = &[
    "bool", "byte", "char", "int8", "uint8", "int16", "uint16", "int32", "uint32", "int64", "uint64", "float32",
    "float64", "string", "wstring",
];

/// The `.msg` text of a type (`package/msg/Type`), if this crate knows it.
pub fn definition(type_name: &str) -> Option<&'static str> {
    DEFINITIONS.iter().find(|(n, _)| *n == type_name).map(|(_, d)| *d)
}

/// Every type this crate has a definition of.
pub fn known_types() -> impl Iterator<Item = &'static str> {
    DEFINITIONS.iter().map(|(n, _)| *n)
}

/// The types a definition's fields use, as `package/msg/Type` (a bare `Type` is in `package`).
fn field_types(package: &str, text: &str) -> Vec<String> {
    let mut out = vec![];
    for line in text.lines() {
        let line = line.split('#').next().unwrap_or("").trim();
        let Some(ty) = line.split_whitespace().next() else { continue };
        if line.contains('=') {
            // a constant (`uint8 FLOAT32=7`); none of these definitions has a string default
            continue;
        }
        let ty = ty.split('[').next().unwrap_or(ty);
        let ty = ty.split("<=").next().unwrap_or(ty);
        if PRIMITIVES.contains(&ty) {
            continue;
        }
        let full = match ty.split_once('/') {
            Some((pkg, name)) => format!("{pkg}/msg/{}", name.trim_start_matches("msg/")),
            None => format!("{package}/msg/{ty}"),
        };
        out.push(full);
    }
    out
}

/// The rosbag2 `ros2msg` schema text of a type: its definition, then every type it uses
/// (depth first, each once) as `MSG: package/Type` sections. `None` when a type in it is unknown.
pub fn ros2msg_schema(type_name: &str) -> Option<String> {
    let mut text = definition(type_name)?.to_string();
    let mut seen = vec![type_name.to_string()];
    let mut stack: Vec<String> = {
        let pkg = type_name.split('/').next()?;
        let mut v = field_types(pkg, definition(type_name)?);
        v.reverse();
        v
    };
    while let Some(t) = stack.pop() {
        if seen.contains(&t) {
            continue;
        }
        let def = definition(&t)?;
        seen.push(t.clone());
        text.push_str(&"=".repeat(80));
        text.push_str(&format!("\nMSG: {}\n", t.replace("/msg/", "/")));
        text.push_str(def);
        let pkg = t.split('/').next()?;
        let mut more = field_types(pkg, def);
        more.reverse();
        stack.extend(more);
    }
    Some(text)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_type_of_a_schema_is_defined_once() {
        for t in known_types() {
            let s = ros2msg_schema(t).unwrap_or_else(|| panic!("{t}: a type it uses has no definition"));
            let mut sections: Vec<&str> = s.lines().filter_map(|l| l.strip_prefix("MSG: ")).collect();
            let n = sections.len();
            sections.sort();
            sections.dedup();
            assert_eq!(n, sections.len(), "{t}: a section twice");
        }
        let odom = ros2msg_schema("nav_msgs/msg/Odometry").unwrap();
        assert!(odom.starts_with("std_msgs/Header header\n"));
        for dep in ["std_msgs/Header", "builtin_interfaces/Time", "geometry_msgs/Pose", "geometry_msgs/Twist"] {
            assert!(odom.contains(&format!("MSG: {dep}\n")), "{dep} missing:\n{odom}");
        }
        assert!(!ros2msg_schema("sensor_msgs/msg/PointField").unwrap().contains("MSG:"), "constants are no types");
    }
}
