//! The wire types: one per edge of the process graph (DESIGN.md), plus control messages.
//!
//! Conventions (EQUATIONS §0): frames are right-handed, world z up, body x forward / y left / z up,
//! camera optical x right / y down / z forward. Quaternions are stored (x, y, z, w). Matrices are
//! row-major, full and symmetric for covariances. Units are SI. A 6×6 pose covariance is ordered
//! (x, y, z, rot_x, rot_y, rot_z), where the rotation part is a small-angle error vector δ in the
//! body frame: `world_from_body_true = world_from_body_est · Exp(δ)`.

use crate::wire_type;
use iceoryx2::prelude::ZeroCopySend;

/// `frame` value: points/poses in the sensor's own frame.
pub const FRAME_SENSOR: u32 = 0;
/// `frame` value: body frame of the vehicle.
pub const FRAME_BODY: u32 = 1;
/// `frame` value: a local-map (segment) frame of FastSLAM.
pub const FRAME_LOCAL_MAP: u32 = 2;
/// `frame` value: the global (world) frame of the buoys.
pub const FRAME_WORLD: u32 = 3;

wire_type! {
    /// The common header of every message, carried as (the first 32 bytes of) the iceoryx2 user
    /// header. Latency per hop is `receive time − publish_ns`, end to end `receive time − origin_ns`.
    type_name = "slam_pipeline::v1::MsgHeader", size = 32;
    pub struct MsgHeader {
        /// Measurement time in ns (CLOCK_MONOTONIC, or the replayed data set's clock).
        pub stamp_ns: u64,
        /// Per-publisher sequence number, +1 per message, starting at 0.
        pub seq: u64,
        /// CLOCK_MONOTONIC ns at which the oldest sensor input this message depends on entered the pipeline.
        pub origin_ns: u64,
        /// CLOCK_MONOTONIC ns at send (set by the publishing runtime).
        pub publish_ns: u64,
    }
}

wire_type! {
    /// Odometry / control input U = (v, δθx, δθy, δθz) over δt (EQUATIONS §1). The rotation increment
    /// is in the body frame: R(k+1) = R(k)·R(δθ).
    type_name = "slam_pipeline::v1::OdometryInput", size = 168;
    pub struct OdometryInput {
        /// Forward speed along body x, m/s.
        pub v_mps: f64,
        /// Body-frame rotation increment (δθx, δθy, δθz) over `dt_s`, rad.
        pub delta_theta_rad: [f64; 3],
        /// Sampling interval δt, s (> 0).
        pub dt_s: f64,
        /// Input noise covariance over (v, δθx, δθy, δθz), 4×4 row-major, SI units squared.
        pub input_covariance: [f64; 16],
    }
}

/// `StereoObservation::flags` bit: `descriptor` is valid.
pub const STEREO_HAS_DESCRIPTOR: u32 = 1;
/// `StereoObservation::flags` bit: `pixels_ul_ur_v` is valid.
pub const STEREO_HAS_PIXELS: u32 = 2;
/// `StereoObservation::flags` bit: `source_id` is the front end's feature track id (the same id
/// in two frames is the same landmark), which FastSLAM then associates by (wire version 2).
pub const STEREO_HAS_TRACK_ID: u32 = 4;

wire_type! {
    /// One triangulated stereo landmark observation (EQUATIONS §2), an element of the slice on
    /// `pipeline/sensors/stereo`; one message is one camera frame.
    type_name = "slam_pipeline::v1::StereoObservation", size = 168;
    pub struct StereoObservation {
        /// Landmark position in the camera (optical) frame, m.
        pub point_cam_m: [f64; 3],
        /// Covariance of `point_cam_m`, 3×3 row-major, m².
        pub covariance_cam_m2: [f64; 9],
        /// Pixel triple (uL, uR, v) in the rectified pair, px; valid when flags has STEREO_HAS_PIXELS.
        pub pixels_ul_ur_v: [f64; 3],
        /// The data source's own landmark id, u64::MAX when unknown; with flag
        /// `STEREO_HAS_TRACK_ID` a feature track id the consumer may associate by, else for
        /// evaluation only.
        pub source_id: u64,
        /// 32-byte binary descriptor (e.g. ORB), valid when flags has STEREO_HAS_DESCRIPTOR.
        pub descriptor: [u8; 32],
        /// Bit set: 1 = descriptor valid, 2 = pixels valid, 4 = `source_id` is a track id.
        pub flags: u32,
        /// Zero.
        pub _reserved: u32,
    }
}

wire_type! {
    /// One acoustic range to a buoy at a known position (EQUATIONS §5), an element of the slice on
    /// `pipeline/sensors/buoy_ranges`.
    type_name = "slam_pipeline::v1::BuoyRange", size = 24;
    pub struct BuoyRange {
        /// Buoy id as in the config's buoy table.
        pub buoy_id: u32,
        /// Zero.
        pub _reserved: u32,
        /// Measured range, m.
        pub range_m: f64,
        /// Standard deviation of the range, m (> 0).
        pub sigma_m: f64,
    }
}

wire_type! {
    /// Pressure depth (EQUATIONS §5): a direct measurement of −z in the world frame.
    type_name = "slam_pipeline::v1::DepthReading", size = 16;
    pub struct DepthReading {
        /// Depth below the surface, m (positive down).
        pub depth_m: f64,
        /// Standard deviation, m.
        pub sigma_m: f64,
    }
}

wire_type! {
    /// A heading (magnetic compass, or any yaw reference): the yaw of body x in the world frame,
    /// about world z, counter-clockwise from world x.
    type_name = "slam_pipeline::v1::HeadingReading", size = 16;
    pub struct HeadingReading {
        /// Yaw, rad, in (−π, π].
        pub yaw_rad: f64,
        /// Standard deviation, rad (> 0).
        pub sigma_rad: f64,
    }
}

wire_type! {
    /// One point of a point cloud (an element of the slice on `pipeline/sensors/cloud`), in the
    /// frame named by the cloud's header.
    type_name = "slam_pipeline::v1::CloudPoint", size = 12;
    pub struct CloudPoint {
        /// x, m.
        pub x_m: f32,
        /// y, m.
        pub y_m: f32,
        /// z, m.
        pub z_m: f32,
    }
}

/// `CloudHeader::flags` bit: `sensor_origin_m`/`orientation_xyzw` hold the world_from_sensor pose.
pub const CLOUD_HAS_POSE: u32 = 1;

wire_type! {
    /// User header of `pipeline/sensors/cloud`: the common header plus the sensor pose.
    type_name = "slam_pipeline::v1::CloudHeader", size = 96;
    pub struct CloudHeader {
        /// Common header.
        pub msg: MsgHeader,
        /// Sensor origin (ray start for occupancy updates) in the world frame, m; valid with CLOUD_HAS_POSE.
        pub sensor_origin_m: [f64; 3],
        /// world_from_sensor rotation as quaternion (x, y, z, w); valid with CLOUD_HAS_POSE.
        pub orientation_xyzw: [f64; 4],
        /// Frame of the points: 0 sensor, 1 body, 2 local map, 3 world.
        pub frame: u32,
        /// Bit set: 1 = pose valid.
        pub flags: u32,
    }
}

wire_type! {
    /// A 6-DOF pose estimate with covariance (`pipeline/slam/pose`).
    type_name = "slam_pipeline::v1::PoseEstimate", size = 352;
    pub struct PoseEstimate {
        /// Position of the body in `frame`, m.
        pub position_m: [f64; 3],
        /// frame_from_body rotation, quaternion (x, y, z, w).
        pub orientation_xyzw: [f64; 4],
        /// 6×6 row-major covariance over (x, y, z, rot_x, rot_y, rot_z), m² / rad², body-frame rotation error.
        pub covariance: [f64; 36],
        /// Local map (segment) id; increases by one per new local map.
        pub segment_id: u32,
        /// Frame of the pose: 2 local map, 3 world.
        pub frame: u32,
    }
}

wire_type! {
    /// One particle of the FastSLAM particle set (slice on `pipeline/slam/particles`).
    type_name = "slam_pipeline::v1::Particle", size = 64;
    pub struct Particle {
        /// Position in the local-map frame, m.
        pub position_m: [f64; 3],
        /// map_from_body rotation, quaternion (x, y, z, w).
        pub orientation_xyzw: [f64; 4],
        /// Normalised log weight (natural log).
        pub log_weight: f64,
    }
}

wire_type! {
    /// User header of `pipeline/slam/particles`.
    type_name = "slam_pipeline::v1::ParticleSetHeader", size = 48;
    pub struct ParticleSetHeader {
        /// Common header.
        pub msg: MsgHeader,
        /// Local map (segment) id.
        pub segment_id: u32,
        /// Zero.
        pub _reserved: u32,
        /// Effective sample size 1/Σw².
        pub n_eff: f64,
    }
}

wire_type! {
    /// A 3-D landmark with its EKF estimate (slices on `pipeline/slam/landmarks`, `pipeline/fusion/map`).
    type_name = "slam_pipeline::v1::Landmark", size = 144;
    pub struct Landmark {
        /// Landmark id, unique within its map.
        pub id: u64,
        /// Mean position in the map's frame, m.
        pub mean_m: [f64; 3],
        /// Covariance of the mean, 3×3 row-major, m².
        pub covariance_m2: [f64; 9],
        /// Descriptor (all zero when none).
        pub descriptor: [u8; 32],
        /// Number of times the landmark was observed.
        pub observation_count: u32,
        /// Local map (segment) the landmark was built in.
        pub segment_id: u32,
    }
}

wire_type! {
    /// User header of landmark-map services.
    type_name = "slam_pipeline::v1::LandmarkMapHeader", size = 40;
    pub struct LandmarkMapHeader {
        /// Common header.
        pub msg: MsgHeader,
        /// Segment id (u32::MAX for a global map of all segments).
        pub segment_id: u32,
        /// Frame of the landmarks: 2 local map, 3 world.
        pub frame: u32,
    }
}

/// `SlamDiagnostics::new_segment_reason`: no new local map in this frame.
pub const SEGMENT_REASON_NONE: u32 = 0;
/// `SlamDiagnostics::new_segment_reason`: too few matched landmarks for several frames.
pub const SEGMENT_REASON_FEW_MATCHES: u32 = 1;
/// `SlamDiagnostics::new_segment_reason`: the position uncertainty exceeded its threshold.
pub const SEGMENT_REASON_POSE_UNCERTAINTY: u32 = 2;
/// `SlamDiagnostics::new_segment_reason`: requested by a control command.
pub const SEGMENT_REASON_REQUESTED: u32 = 3;

/// `SlamDiagnostics::motion_source`: odometry.
pub const MOTION_ODOMETRY: u32 = 0;
/// `SlamDiagnostics::motion_source`: the constant-velocity model (configured).
pub const MOTION_CONSTANT_VELOCITY: u32 = 1;
/// `SlamDiagnostics::motion_source`: the stereo front end, by feature track ids.
pub const MOTION_REGISTRATION_TRACK_IDS: u32 = 2;
/// `SlamDiagnostics::motion_source`: the stereo front end, around its constant-velocity prior.
pub const MOTION_REGISTRATION_GUIDED: u32 = 3;
/// `SlamDiagnostics::motion_source`: the stereo front end, by its prior-free search.
pub const MOTION_REGISTRATION_SEARCH: u32 = 4;
/// `SlamDiagnostics::motion_source`: the stereo front end found no motion; constant velocity
/// was used instead.
pub const MOTION_REGISTRATION_FAILED: u32 = 5;
/// `SlamDiagnostics::motion_source`: the first frame (nothing to register against).
pub const MOTION_FIRST_FRAME: u32 = 6;

wire_type! {
    /// What one FastSLAM frame did (`pipeline/slam/diagnostics`). Version 2: the motion source,
    /// the front end's registration, association candidates, rejected attribute matches and the
    /// landmark updates' NIS.
    type_name = "slam_pipeline::v2::SlamDiagnostics", size = 88;
    pub struct SlamDiagnostics {
        /// Local map (segment) after this frame.
        pub segment_id: u32,
        /// Observations matched to confirmed landmarks (best particle).
        pub matched: u32,
        /// Observations that created landmarks (best particle).
        pub new_landmarks: u32,
        /// Observations left out as possible duplicates (best particle).
        pub ambiguous: u32,
        /// Confirmed landmarks in the best particle's map.
        pub landmarks: u32,
        /// 0 none, 1 few matches, 2 pose uncertainty, 3 requested: why this frame started a new local map.
        pub new_segment_reason: u32,
        /// Number of particles.
        pub particles: u32,
        /// 1 when the particles were resampled in this frame.
        pub resampled: u32,
        /// Effective sample size before resampling.
        pub n_eff: f64,
        /// Time the filter update took (front end included), ms.
        pub update_ms: f64,
        /// How the particles were moved to this frame (`MOTION_*`).
        pub motion_source: u32,
        /// Inliers of the front end's registration (0 without one).
        pub registration_inliers: u32,
        /// Feature-track matches left out because they failed the χ² gate (best particle).
        pub rejected: u32,
        /// Zero.
        pub _reserved: u32,
        /// Association candidates per observation.
        pub candidates_per_observation: f64,
        /// Mean normalised innovation squared of the landmark updates (≈ 3 when consistent;
        /// NaN without updates).
        pub mean_nis: f64,
        /// Time of the stereo front end, ms (0 without one).
        pub frontend_ms: f64,
    }
}

wire_type! {
    /// A global position fix of the buoy EKF (`pipeline/buoy/fix`). Version 3: the
    /// cross-covariance with the previous fix.
    type_name = "slam_pipeline::v3::BuoyFix", size = 208;
    pub struct BuoyFix {
        /// Position in the world frame, m.
        pub position_m: [f64; 3],
        /// Covariance of the position, 3×3 row-major, m².
        pub covariance_m2: [f64; 9],
        /// Velocity in the world frame, m/s.
        pub velocity_mps: [f64; 3],
        /// Ranges accepted by the gate since the previous fix.
        pub ranges_used: u32,
        /// Ranges rejected by the gate since the previous fix.
        pub ranges_rejected: u32,
        /// Stamp of the previous fix of the same estimator that `cross_covariance_prev_m2`
        /// refers to, ns; 0 when there is none (then the synchronizer treats this fix's error
        /// as independent of the previous one's, [3D] eq 30).
        pub prev_fix_stamp_ns: u64,
        /// cov(e_prev, e_this): the cross-covariance of the previous fix's position error (rows)
        /// with this one's (columns), 3×3 row-major, m² (docs/EQUATIONS.md §5.1a).
        pub cross_covariance_prev_m2: [f64; 9],
    }
}

/// `SyncedPair::flags` bit: the buoy position was extrapolated (no bracketing fix in time).
pub const SYNC_EXTRAPOLATED: u32 = 1;
/// `SyncedPair::flags` bit: only two fixes were available (linear interpolation).
pub const SYNC_LINEAR: u32 = 2;
/// `SyncedPair::flags` bit: the fixes around the stamp were too far apart to interpolate across.
pub const SYNC_GAP: u32 = 4;
/// `SyncedPair::flags` bit: interpolated between fixes on both sides of the stamp.
pub const SYNC_INTERPOLATED: u32 = 8;
/// `SyncedPair::flags` bit: a prediction, sent as soon as the SLAM pose arrived with the buoy
/// position extrapolated from the latest fixes; the pair of the same stamp without this bit
/// follows when the bracketing fix has come (or the wait is over).
pub const SYNC_PREDICTED: u32 = 16;

wire_type! {
    /// A local SLAM pose paired with the buoy position interpolated to its stamp (`pipeline/sync/pair`).
    type_name = "slam_pipeline::v1::SyncedPair", size = 464;
    pub struct SyncedPair {
        /// The SLAM pose (local-map frame) at the header's stamp.
        pub slam: PoseEstimate,
        /// Buoy position interpolated to the stamp, world frame, m.
        pub buoy_position_m: [f64; 3],
        /// Its covariance ([3D] eq 30), 3×3 row-major, m².
        pub buoy_covariance_m2: [f64; 9],
        /// Stamp of the newest buoy fix used, ns.
        pub newest_fix_stamp_ns: u64,
        /// Bit set: 1 extrapolated, 2 linear, 4 gap, 8 interpolated, 16 predicted (`SYNC_*`).
        pub flags: u32,
        /// Number of fixes used (1 when extrapolated or an exact fix, 2 linear, 3 quadratic).
        pub fixes_used: u32,
    }
}

/// `FusedPose::flags` bit: camera and buoy estimates were fused.
pub const FUSED_WITH_BUOY: u32 = 1;
/// `FusedPose::flags` bit: the camera estimate mapped to the world alone (the buoy estimate was
/// outside the χ²₃ gate, or missing).
pub const FUSED_CAMERA_ONLY: u32 = 2;
/// `FusedPose::flags` bit: the buoy estimate alone (the local map has no transform to the world
/// yet); the orientation is then the last known one, or identity, with a large covariance.
pub const FUSED_BUOY_ONLY: u32 = 4;
/// `FusedPose::flags` bit: a first estimate, published as soon as the SLAM pose arrived, with the
/// buoy position predicted from the latest fixes (for a controller: no wait). The fusion state is
/// not changed by it.
pub const FUSED_PREDICTED: u32 = 8;
/// `FusedPose::flags` bit: the refined estimate of its stamp (the buoy position interpolated
/// between the fixes around it, or extrapolated once the wait for them was over); fusion's state
/// and its outputs follow these. Exactly one of `FUSED_PREDICTED` and `FUSED_REFINED` is set.
pub const FUSED_REFINED: u32 = 16;

wire_type! {
    /// The globally consistent pose (`pipeline/fusion/pose`), world frame.
    type_name = "slam_pipeline::v1::FusedPose", size = 360;
    pub struct FusedPose {
        /// The pose, `frame` = 3 (world).
        pub pose: PoseEstimate,
        /// Bit set: 1 fused with a buoy estimate, 2 camera only, 4 buoy only; 8 predicted or
        /// 16 refined (`FUSED_*`).
        pub flags: u32,
        /// Zero.
        pub _reserved: u32,
    }
}

wire_type! {
    /// Statistics of the occupancy octree (`pipeline/map/stats`).
    type_name = "slam_pipeline::v1::MapStats", size = 96;
    pub struct MapStats {
        /// Octree resolution, m.
        pub resolution_m: f64,
        /// Leaf nodes.
        pub leaves: u64,
        /// Occupied leaves.
        pub occupied_leaves: u64,
        /// Free leaves.
        pub free_leaves: u64,
        /// Inner nodes.
        pub inner_nodes: u64,
        /// Memory used by the tree, bytes.
        pub memory_bytes: u64,
        /// Clouds inserted.
        pub clouds_inserted: u64,
        /// Clouds dropped: insertion behind (`when_behind = "drop_oldest"`), no pose in time, and gaps in the cloud publisher's sequence numbers.
        pub clouds_dropped: u64,
        /// Points inserted.
        pub points_inserted: u64,
        /// Time of the last insertion, ms.
        pub last_insert_ms: f64,
        /// Navigable regions.
        pub navigable_regions: u32,
        /// Obstacles.
        pub obstacles: u32,
        /// Zero.
        pub _reserved: u64,
    }
}

/// `Voxel::class` value: unclassified occupied voxel.
pub const VOXEL_OCCUPIED: u32 = 0;
/// `Voxel::class` value: navigable (planar, climbable).
pub const VOXEL_NAVIGABLE: u32 = 1;
/// `Voxel::class` value: obstacle.
pub const VOXEL_OBSTACLE: u32 = 2;
/// `Voxel::class` value: wall (a large steep plane with no top: a building's walls).
pub const VOXEL_WALL: u32 = 3;

wire_type! {
    /// An occupied octree leaf (slice on `pipeline/map/voxels`), world frame.
    type_name = "slam_pipeline::v1::Voxel", size = 24;
    pub struct Voxel {
        /// Voxel centre, m.
        pub center_m: [f32; 3],
        /// Edge length, m.
        pub size_m: f32,
        /// Occupancy probability.
        pub occupancy: f32,
        /// 0 occupied, 1 navigable, 2 obstacle, 3 wall; in a delta also [`VOXEL_CLASS_REMOVED`].
        pub class: u32,
    }
}

wire_type! {
    /// User header of `pipeline/map/voxels`.
    type_name = "slam_pipeline::v1::VoxelSetHeader", size = 48;
    pub struct VoxelSetHeader {
        /// Common header.
        pub msg: MsgHeader,
        /// Octree resolution, m.
        pub resolution_m: f64,
        /// Frame of the voxels (3 world, 2 local map).
        pub frame: u32,
        /// [`VOXELS_FULL`] (0): the payload is every occupied voxel of the map; [`VOXELS_DELTA`]
        /// (1): only the voxels changed since the previous message (new, or a changed occupancy or
        /// class; one no longer occupied comes with class [`VOXEL_CLASS_REMOVED`]). A consumer
        /// that missed a message waits for the next full one (sent periodically and on
        /// [`COMMAND_VOXEL_SNAPSHOT`]).
        pub kind: u32,
    }
}

/// `VoxelSetHeader::kind`: every occupied voxel of the map.
pub const VOXELS_FULL: u32 = 0;
/// `VoxelSetHeader::kind`: the voxels changed since the previous message.
pub const VOXELS_DELTA: u32 = 1;
/// `Voxel::class` in a delta: the voxel is no longer occupied (drop it).
pub const VOXEL_CLASS_REMOVED: u32 = 255;

/// `LaserScanHeader::flags` bit: ranges at or above `range_max_m` mean "no return".
pub const LASER_MAX_IS_NO_RETURN: u32 = 1;

wire_type! {
    /// User header of `pipeline/sensors/laser`: a planar laser scan whose ranges are the slice
    /// payload ([`LaserRange`], one per beam, counter-clockwise from `angle_min_rad`).
    type_name = "slam_pipeline::v1::LaserScanHeader", size = 96;
    pub struct LaserScanHeader {
        /// Common header (`stamp_ns`: the scan's time).
        pub msg: MsgHeader,
        /// Angle of the first beam in the laser frame, rad (counter-clockwise from the laser's x).
        pub angle_min_rad: f64,
        /// Angle between consecutive beams, rad.
        pub angle_increment_rad: f64,
        /// Ranges below this are invalid, m.
        pub range_min_m: f64,
        /// Ranges at or above this are "no return", m.
        pub range_max_m: f64,
        /// The laser's position on the robot (`body_from_laser`, x and y), m.
        pub body_from_laser_xy_m: [f64; 2],
        /// The laser's yaw on the robot (`body_from_laser`), rad.
        pub body_from_laser_yaw_rad: f64,
        /// Beams in the slice.
        pub beams: u32,
        /// Bit set: 1 = maximum range means no return.
        pub flags: u32,
    }
}

wire_type! {
    /// One beam of a laser scan (slice on `pipeline/sensors/laser`). NaN or negative: invalid.
    type_name = "slam_pipeline::v1::LaserRange", size = 4;
    pub struct LaserRange {
        /// Range, m.
        pub range_m: f32,
    }
}

/// `PlanarOdometry::flags` bit: `wheel_speeds_mps` holds the three omni wheels' rim speeds.
pub const ODOM_HAS_WHEELS: u32 = 1;
/// `PlanarOdometry::flags` bit: `velocity` holds the body velocity.
pub const ODOM_HAS_VELOCITY: u32 = 2;

wire_type! {
    /// Planar wheel odometry (`pipeline/sensors/planar_odometry`): the odometry's own pose
    /// (`odom_from_body`, any fixed origin: consumers use increments), and optionally the body
    /// velocity and the three omni wheels' rim speeds ([2D3D] eq 1-2).
    type_name = "slam_pipeline::v1::PlanarOdometry", size = 80;
    pub struct PlanarOdometry {
        /// Position (x, y) in the odometry frame, m.
        pub position_m: [f64; 2],
        /// Yaw in the odometry frame, rad.
        pub yaw_rad: f64,
        /// Body velocity (v_x m/s, v_y m/s, ω rad/s), valid with ODOM_HAS_VELOCITY.
        pub velocity: [f64; 3],
        /// Wheel rim speeds, m/s, valid with ODOM_HAS_WHEELS.
        pub wheel_speeds_mps: [f64; 3],
        /// Bit set: 1 wheels, 2 velocity.
        pub flags: u32,
        /// Zero.
        pub _reserved: u32,
    }
}

wire_type! {
    /// A planar pose with covariance (`pipeline/grid_slam/pose`): `map_from_body` of the 2-D SLAM.
    type_name = "slam_pipeline::v1::PlanarPose", size = 112;
    pub struct PlanarPose {
        /// Position (x, y) in the map frame, m.
        pub position_m: [f64; 2],
        /// Yaw in the map frame, rad.
        pub yaw_rad: f64,
        /// 3×3 row-major covariance over (x, y, yaw), m² / rad².
        pub covariance: [f64; 9],
        /// Effective sample size of the filter.
        pub n_eff: f64,
        /// Filter updates so far.
        pub updates: u32,
        /// Bit set: 1 = the filter was updated at this scan, 2 = resampled.
        pub flags: u32,
    }
}

wire_type! {
    /// User header of `pipeline/grid_slam/grid` (an occupancy grid whose cells are the slice
    /// payload, [`OccupancyCell`]) and of `pipeline/map/traversability` ([`TraversabilityCell`]):
    /// row-major, first row at the lowest y, as nav_msgs/OccupancyGrid.
    type_name = "slam_pipeline::v1::OccupancyGridHeader", size = 64;
    pub struct OccupancyGridHeader {
        /// Common header.
        pub msg: MsgHeader,
        /// Cell side, m.
        pub resolution_m: f64,
        /// Map-frame position of the lower-left corner of cell (0, 0), m.
        pub origin_m: [f64; 2],
        /// Cells along x.
        pub width: u32,
        /// Cells along y.
        pub height: u32,
    }
}

wire_type! {
    /// One cell of an occupancy grid (slice on `pipeline/grid_slam/grid`): −1 unknown, else 0..=100 (%).
    type_name = "slam_pipeline::v1::OccupancyCell", size = 1;
    pub struct OccupancyCell {
        /// Occupancy, percent, or −1.
        pub value: i8,
    }
}

/// `TraversabilityCell::class`: nothing classified in the column.
pub const TRAVERSABILITY_UNKNOWN: u8 = 0;
/// `TraversabilityCell::class`: the column is part of a navigable region.
pub const TRAVERSABILITY_NAVIGABLE: u8 = 1;
/// `TraversabilityCell::class`: the column holds an obstacle (or wall) voxel.
pub const TRAVERSABILITY_OBSTACLE: u8 = 2;

wire_type! {
    /// One cell of the 2.5-D traversability grid (slice on `pipeline/map/traversability`, headed
    /// by an [`OccupancyGridHeader`]: row-major, the first row at the lowest y, x and y in the
    /// map's world frame).
    type_name = "slam_pipeline::v1::TraversabilityCell", size = 12;
    pub struct TraversabilityCell {
        /// World z of the navigable surface at the cell's centre, or of the obstacle's top, m
        /// (0 in an unknown cell: the wire carries no NaN, which the checks on a bridged or
        /// external message refuse).
        pub height_m: f32,
        /// The navigable surface's slope, deg (0 unless navigable).
        pub slope_deg: f32,
        /// `TRAVERSABILITY_*`: 0 unknown, 1 navigable, 2 obstacle.
        pub class: u8,
        /// Zero.
        pub _reserved: [u8; 3],
    }
}

/// `Heartbeat::state`: the process is setting up its ports.
pub const STATE_STARTING: u32 = 1;
/// `Heartbeat::state`: the process is ready and processing.
pub const STATE_READY: u32 = 2;
/// `Heartbeat::state`: the process is shutting down.
pub const STATE_STOPPING: u32 = 3;

wire_type! {
    /// Liveness and readiness of a process (`pipeline/control/heartbeat`), sent periodically.
    type_name = "slam_pipeline::v1::Heartbeat", size = 64;
    pub struct Heartbeat {
        /// Process name, UTF-8, NUL-padded.
        pub process: [u8; 32],
        /// OS process id.
        pub pid: u32,
        /// 1 starting, 2 ready, 3 stopping.
        pub state: u32,
        /// Time since the process started, ns.
        pub uptime_ns: u64,
        /// Messages received so far.
        pub messages_in: u64,
        /// Messages sent so far.
        pub messages_out: u64,
    }
}

/// `EndOfStream::status`: the process sent its last message itself.
pub const EOS_COMPLETE: u32 = 0;
/// `EndOfStream::status`: the process failed for good (the supervisor gave up restarting it) and
/// the supervisor ends its stream in its name; what it would have sent next never comes, and
/// `last_seq` / `messages_sent` are what the supervisor last saw of it.
pub const EOS_FAILED: u32 = 1;

wire_type! {
    /// End of stream (`pipeline/control/end_of_stream`): the process named has sent its last
    /// message, or failed for good (`status`, `EOS_*`).
    type_name = "slam_pipeline::v2::EndOfStream", size = 56;
    pub struct EndOfStream {
        /// The process whose stream ends, UTF-8, NUL-padded.
        pub process: [u8; 32],
        /// Sequence number of the sender's last data message.
        pub last_seq: u64,
        /// Messages the sender published in all.
        pub messages_sent: u64,
        /// `EOS_COMPLETE` (0) or `EOS_FAILED`.
        pub status: u32,
        /// The data services the process published: bit i for `services::SERVICES[i]`
        /// ([`crate::services::data_service_bit`]), with [`EOS_OUTPUTS_KNOWN`] set. 0 = not
        /// known (a producer that does not say): every stage takes it for one of its upstreams.
        /// A stage that ends with its first upstream process ends only on the end of a process
        /// that published one of its inputs.
        pub outputs: u32,
    }
}

/// `EndOfStream::outputs`: set when the other bits list the data services the process published.
pub const EOS_OUTPUTS_KNOWN: u32 = 1 << 31;

/// `ControlCommand::command`: start a new local map (segment).
pub const COMMAND_NEW_SEGMENT: u32 = 1;
/// `ControlCommand::command`: write a checkpoint of the process's state / outputs.
pub const COMMAND_CHECKPOINT: u32 = 2;
/// `ControlCommand::command`: the octree mapper sends a full voxel set with its next message
/// (a viewer that joined late or missed a delta).
pub const COMMAND_VOXEL_SNAPSHOT: u32 = 3;

wire_type! {
    /// A command to one process (`pipeline/control/command`).
    type_name = "slam_pipeline::v1::ControlCommand", size = 48;
    pub struct ControlCommand {
        /// Target process name, UTF-8, NUL-padded (all zero = every process).
        pub target: [u8; 32],
        /// 1 new segment, 2 checkpoint, 3 voxel snapshot.
        pub command: u32,
        /// Zero.
        pub _reserved: u32,
        /// Command argument.
        pub arg: u64,
    }
}

/// Encodes a name into a NUL-padded 32-byte field, truncated at a char boundary.
pub fn name32(name: &str) -> [u8; 32] {
    let mut out = [0u8; 32];
    let mut end = name.len().min(32);
    while !name.is_char_boundary(end) {
        end -= 1;
    }
    out[..end].copy_from_slice(&name.as_bytes()[..end]);
    out
}

/// Decodes a NUL-padded name field; invalid UTF-8 is replaced.
pub fn name_from32(field: &[u8; 32]) -> String {
    let end = field.iter().position(|&b| b == 0).unwrap_or(32);
    String::from_utf8_lossy(&field[..end]).into_owned()
}

/// Anything whose user header starts with a [`MsgHeader`].
pub trait HasMsgHeader {
    /// The common header.
    fn msg(&self) -> &MsgHeader;
    /// The common header, mutable.
    fn msg_mut(&mut self) -> &mut MsgHeader;
}

impl HasMsgHeader for MsgHeader {
    fn msg(&self) -> &MsgHeader {
        self
    }
    fn msg_mut(&mut self) -> &mut MsgHeader {
        self
    }
}

macro_rules! has_msg_header {
    ($($t:ty),*) => {$(
        impl HasMsgHeader for $t {
            fn msg(&self) -> &MsgHeader { &self.msg }
            fn msg_mut(&mut self) -> &mut MsgHeader { &mut self.msg }
        }
    )*};
}
has_msg_header!(
    CloudHeader,
    ParticleSetHeader,
    LandmarkMapHeader,
    VoxelSetHeader,
    LaserScanHeader,
    OccupancyGridHeader
);
