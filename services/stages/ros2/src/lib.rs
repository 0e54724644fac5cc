//! The `ros2` gateway (issue 33): a native ROS 2 node on the DDS wire (ros2-client over RustDDS;
//! no ROS installation), a stage like every other.
//!
//! - **In** (`[[in]]` routes, ROS → pipeline): each topic's messages are decoded once, straight
//!   from RustDDS's receive buffer, and written into a loaned iceoryx2 sample of the route's
//!   pipeline input ([`inbound`]): `sensor_msgs/LaserScan` → `pipeline/sensors/laser`,
//!   `nav_msgs/Odometry` → `planar_odometry` or `odometry` (increments), `sensor_msgs/PointCloud2`
//!   (x, y, z FLOAT32 or FLOAT64 anywhere in the point; the rest skipped) → `cloud`,
//!   `sensor_msgs/Imu` → `heading`, `sensor_msgs/FluidPressure` → `depth`, `sensor_msgs/Range`
//!   (the beacon in `header.frame_id`) → `buoy_ranges`. QoS per route, default ROS 2's
//!   sensor-data profile.
//! - **Out** (`[[out]]` routes, pipeline → ROS): fused / SLAM / grid-SLAM poses as
//!   `nav_msgs/Odometry` and `geometry_msgs/PoseWithCovarianceStamped`, paths as
//!   `nav_msgs/Path`, `/tf` (`map → odom → base_link`, REP 105) and `/tf_static` (the sensor
//!   mounts), the grid as `nav_msgs/OccupancyGrid` on `/map` (transient local, as map_server),
//!   occupied voxels as `sensor_msgs/PointCloud2` (as octomap_server's centres cloud),
//!   landmarks and obstacles as `visualization_msgs/MarkerArray` ([`outbound`]).
//! - Nothing lost silently: a message that does not decode, breaks what its pipeline input needs,
//!   was skipped by its publisher's sequence numbers (lost in DDS) or could not be published is
//!   counted per route, warned once with the topic, and in summary.json (`ros2`).
//!
//! `ROS_DOMAIN_ID` is respected (or `domain_id`); `only_networks` restricts what DDS discovery
//! advertises (e.g. `["127.0.0.1"]` on one host).

pub mod dds;
pub mod inbound;
pub mod outbound;
pub mod settings;
pub mod stage;
pub mod summary;

pub use settings::Ros2Settings;
