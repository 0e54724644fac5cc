//! Pipeline → ROS 2: the `out` routes (which pipeline output becomes which ROS 2 topic, with
//! which QoS and frames) and the [`Translator`] that turns pipeline messages into the routes' ROS
//! 2 messages. The `ros2` gateway publishes what it emits on DDS; the recorder writes it into a
//! rosbag2 bag. Both get the same messages from the same routes.
//!
//! Poses and transforms are emitted as they come. Paths, the occupancy grid, the voxel cloud and
//! the marker arrays are snapshots of a state the translator keeps: an update marks the route
//! due, and [`Translator::flush`] builds and emits it at most `max_rate_hz` (an update not yet
//! emitted is folded into the next one, counted as `coalesced`; the last is always emitted by a
//! forced flush at the end).

use std::collections::{BTreeMap, HashMap};
use std::time::{Duration, Instant};

use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};
use shared_types::voxel_stream::{self, VoxelKey};
use shared_types::{
    FRAME_LOCAL_MAP, FUSED_REFINED, FusedPose, Landmark, LandmarkMapHeader, OccupancyCell, OccupancyGridHeader,
    PlanarOdometry, PlanarPose, PoseEstimate, TraversabilityCell, VOXEL_OBSTACLE, VOXEL_WALL, Voxel, VoxelSetHeader,
};

use crate::convert;
use crate::msgs::*;

/// Frame ids (REP 105).
#[derive(Debug, Clone, Deserialize, Serialize)]
#[serde(deny_unknown_fields, default)]
pub struct Frames {
    /// The world-fixed frame of the fused and grid-SLAM poses.
    pub map: String,
    /// The odometry frame.
    pub odom: String,
    /// The robot's body.
    pub base_link: String,
    /// The frame of FastSLAM's local-map poses (`pipeline/slam/pose`).
    pub local_map: String,
}

impl Default for Frames {
    fn default() -> Self {
        Self {
            map: "map".into(),
            odom: "odom".into(),
            base_link: "base_link".into(),
            local_map: "slam_local_map".into(),
        }
    }
}

/// Reliability of a topic.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Reliability {
    /// Resent until acknowledged.
    Reliable,
    /// Sent once.
    BestEffort,
}

/// Durability of a topic.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Durability {
    /// Only for subscribers present at the time.
    Volatile,
    /// The last `depth` messages kept for late subscribers (a latched map).
    TransientLocal,
}

/// A topic's QoS (the rest as ROS 2's defaults: keep last, automatic liveliness).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct TopicQos {
    /// Reliability.
    pub reliability: Reliability,
    /// Durability.
    pub durability: Durability,
    /// History depth (keep last).
    pub depth: u32,
}

impl TopicQos {
    /// ROS 2's sensor-data profile (`rmw_qos_profile_sensor_data`): best effort, volatile, 5.
    pub const SENSOR_DATA: TopicQos =
        TopicQos { reliability: Reliability::BestEffort, durability: Durability::Volatile, depth: 5 };
    /// ROS 2's default profile: reliable, volatile, 10.
    pub const DEFAULT: TopicQos =
        TopicQos { reliability: Reliability::Reliable, durability: Durability::Volatile, depth: 10 };
    /// A map as map_server publishes it: reliable, transient local, 1.
    pub const MAP: TopicQos =
        TopicQos { reliability: Reliability::Reliable, durability: Durability::TransientLocal, depth: 1 };

    /// The QoS as a rosbag2 topic declares it.
    pub fn bag(self) -> crate::BagQos {
        crate::BagQos {
            reliable: self.reliability == Reliability::Reliable,
            transient_local: self.durability == Durability::TransientLocal,
            depth: self.depth,
        }
    }
}

/// What an out route publishes.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Deserialize, Serialize, schemars::JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum OutKind {
    /// `pipeline/fusion/pose` (refined estimates) as `nav_msgs/Odometry` in `frames.map`.
    FusedOdometry,
    /// `pipeline/fusion/pose` as `geometry_msgs/PoseWithCovarianceStamped`.
    FusedPose,
    /// `pipeline/fusion/pose` accumulated as `nav_msgs/Path`.
    FusedPath,
    /// `pipeline/slam/pose` as `nav_msgs/Odometry` in `frames.local_map`.
    SlamOdometry,
    /// `pipeline/slam/pose` accumulated as `nav_msgs/Path`.
    SlamPath,
    /// `pipeline/grid_slam/pose` as `nav_msgs/Odometry` in `frames.map`.
    GridSlamOdometry,
    /// `pipeline/grid_slam/pose` as `geometry_msgs/PoseWithCovarianceStamped`.
    GridSlamPose,
    /// `pipeline/grid_slam/pose` accumulated as `nav_msgs/Path`.
    GridSlamPath,
    /// `pipeline/grid_slam/grid` as `nav_msgs/OccupancyGrid` (transient local, as map_server).
    Map,
    /// `pipeline/map/voxels` (full sets and deltas) as the occupied voxels' centres,
    /// `sensor_msgs/PointCloud2` (as octomap_server's centres cloud).
    Voxels,
    /// `pipeline/fusion/map` as a `visualization_msgs/MarkerArray` of spheres.
    Landmarks,
    /// The obstacle voxels of `pipeline/map/voxels` as a `visualization_msgs/MarkerArray` of cubes.
    Obstacles,
    /// `pipeline/map/traversability` (the octree mapper's 2.5-D traversability grid) as
    /// `nav_msgs/OccupancyGrid` (navigable 0, obstacle 100, unknown −1; transient local, as
    /// map_server): the map a Nav2 planner takes.
    Traversability,
    /// `pipeline/map/traversability`'s known cells as `sensor_msgs/PointCloud2` (x, y, z the
    /// surface's height, slope, class): the elevation a 3-D planner or RViz takes.
    TraversabilityCloud,
    /// `/tf`: `map → odom → base_link` from the fused pose (`from = "fused"`) or grid SLAM's
    /// (`from = "grid_slam"`); with `odom = "planar_odometry"` the odometry gives `odom →
    /// base_link` and the pose `map → odom`, else `map → odom` is the identity (on `/tf_static`).
    Tf,
}

impl OutKind {
    /// The topic it is published on unless the route names one.
    pub fn default_topic(self) -> &'static str {
        match self {
            OutKind::FusedOdometry => "/slam/fused/odometry",
            OutKind::FusedPose => "/slam/fused/pose",
            OutKind::FusedPath => "/slam/fused/path",
            OutKind::SlamOdometry => "/slam/local/odometry",
            OutKind::SlamPath => "/slam/local/path",
            OutKind::GridSlamOdometry => "/slam/grid/odometry",
            OutKind::GridSlamPose => "/slam/grid/pose",
            OutKind::GridSlamPath => "/slam/grid/path",
            OutKind::Map => "/map",
            OutKind::Voxels => "/octomap_point_cloud_centers",
            OutKind::Landmarks => "/slam/landmarks",
            OutKind::Obstacles => "/slam/obstacles",
            OutKind::Traversability => "/slam/traversability",
            OutKind::TraversabilityCloud => "/slam/traversability/cloud",
            OutKind::Tf => "/tf",
        }
    }

    /// The QoS it is published with unless the route says. Pose streams and `/tf` keep 100
    /// samples: a reliable writer of depth 10 overwrites what a reader 10 behind has not
    /// acknowledged (a replay as fast as possible sends them in bursts).
    pub fn default_qos(self) -> TopicQos {
        match self {
            OutKind::Map
            | OutKind::Voxels
            | OutKind::Landmarks
            | OutKind::Obstacles
            | OutKind::Traversability
            | OutKind::TraversabilityCloud => TopicQos::MAP,
            OutKind::Tf
            | OutKind::FusedOdometry
            | OutKind::FusedPose
            | OutKind::SlamOdometry
            | OutKind::GridSlamOdometry
            | OutKind::GridSlamPose => TopicQos { depth: 1000, ..TopicQos::DEFAULT },
            _ => TopicQos::DEFAULT,
        }
    }

    /// The most messages per second unless the route says: snapshots of growing state a few per
    /// second (paths 2, voxels and markers 1), the rest every message (0).
    pub fn default_rate_hz(self) -> f64 {
        match self {
            OutKind::FusedPath | OutKind::SlamPath | OutKind::GridSlamPath => 2.0,
            OutKind::Voxels | OutKind::Landmarks | OutKind::Obstacles => 1.0,
            _ => 0.0,
        }
    }

    /// True for the snapshot routes (state kept and sent at most `max_rate_hz`).
    pub fn is_snapshot(self) -> bool {
        matches!(
            self,
            OutKind::FusedPath
                | OutKind::SlamPath
                | OutKind::GridSlamPath
                | OutKind::Map
                | OutKind::Voxels
                | OutKind::Landmarks
                | OutKind::Obstacles
                | OutKind::Traversability
                | OutKind::TraversabilityCloud
        )
    }

    /// The ROS 2 type it publishes.
    pub fn ros_type(self) -> &'static str {
        use crate::Message;
        match self {
            OutKind::FusedOdometry | OutKind::SlamOdometry | OutKind::GridSlamOdometry => Odometry::TYPE_NAME,
            OutKind::FusedPose | OutKind::GridSlamPose => PoseWithCovarianceStamped::TYPE_NAME,
            OutKind::FusedPath | OutKind::SlamPath | OutKind::GridSlamPath => Path::TYPE_NAME,
            OutKind::Map | OutKind::Traversability => OccupancyGrid::TYPE_NAME,
            OutKind::Voxels | OutKind::TraversabilityCloud => PointCloud2::TYPE_NAME,
            OutKind::Landmarks | OutKind::Obstacles => MarkerArray::TYPE_NAME,
            OutKind::Tf => TFMessage::TYPE_NAME,
        }
    }
}

/// Where `/tf` takes its pose from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, Serialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum TfFrom {
    /// `pipeline/fusion/pose` (refined).
    #[default]
    Fused,
    /// `pipeline/grid_slam/pose`.
    GridSlam,
}

/// Where `/tf` takes `odom → base_link` from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, Serialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum TfOdom {
    /// No odometry frame of its own: `map → odom` is the identity.
    #[default]
    None,
    /// `pipeline/sensors/planar_odometry`.
    PlanarOdometry,
}

/// A pipeline output as a ROS 2 topic.
#[derive(Debug, Clone, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct OutRoute {
    /// What is published.
    pub what: OutKind,
    /// The topic (default: [`OutKind::default_topic`]).
    #[serde(default)]
    pub topic: Option<String>,
    /// QoS (default: [`OutKind::default_qos`]).
    #[serde(default)]
    pub qos: Option<TopicQos>,
    /// Most messages per second (0: [`OutKind::default_rate_hz`]). Paths, the grid, voxel
    /// clouds and markers are snapshots: an update not yet sent is folded into the next;
    /// poses and transforms are not limited by default.
    #[serde(default)]
    pub max_rate_hz: f64,
    /// `tf`: the pose it comes from.
    #[serde(default)]
    pub from: TfFrom,
    /// `tf`: the odometry frame's source.
    #[serde(default)]
    pub odom: TfOdom,
}

impl OutRoute {
    /// A route with every default.
    pub fn of(what: OutKind) -> Self {
        Self { what, topic: None, qos: None, max_rate_hz: 0.0, from: TfFrom::Fused, odom: TfOdom::None }
    }
    /// The topic name.
    pub fn topic(&self) -> &str {
        self.topic.as_deref().unwrap_or(self.what.default_topic())
    }
    /// The QoS.
    pub fn qos(&self) -> TopicQos {
        self.qos.unwrap_or(self.what.default_qos())
    }
    /// The shortest time between two messages (`None`: every message).
    pub fn period(&self) -> Option<Duration> {
        let rate = if self.max_rate_hz > 0.0 { self.max_rate_hz } else { self.what.default_rate_hz() };
        (rate > 0.0).then(|| Duration::from_secs_f64(1.0 / rate))
    }
}

/// A fixed transform (`parent_from_child`) published on `/tf_static`.
#[derive(Debug, Clone, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct StaticTransform {
    /// Parent frame.
    pub parent: String,
    /// Child frame.
    pub child: String,
    /// Translation (x, y, z), m.
    #[serde(default)]
    pub xyz_m: [f64; 3],
    /// Rotation as roll, pitch, yaw (fixed axes x, y, z), rad.
    #[serde(default)]
    pub rpy_rad: [f64; 3],
}

/// True when `t` is a valid ROS 2 topic name.
pub fn topic_ok(t: &str) -> bool {
    !t.is_empty()
        && !t.contains(char::is_whitespace)
        && !t.contains("//")
        && t.chars().all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '/' || c == '~')
        && !t.starts_with(|c: char| c.is_ascii_digit())
}

/// Checks out routes, frames and static transforms into `issues` (keys `out[i]...`, `frames...`,
/// `static_transforms[i]` under the current path). Topics already used (e.g. by `in` routes) are
/// in `topics`.
pub fn validate(
    routes: &[OutRoute],
    frames: &Frames,
    statics: &[StaticTransform],
    topics: &mut std::collections::BTreeSet<String>,
    issues: &mut validation::Issues,
) {
    for (i, r) in routes.iter().enumerate() {
        issues.check(
            topic_ok(r.topic()),
            format!("out[{i}].topic"),
            format!("`{}` is not a ROS topic name", r.topic()),
        );
        issues.check(topics.insert(r.topic().to_string()), format!("out[{i}].topic"), "used twice");
        issues.check(r.qos().depth >= 1, format!("out[{i}].qos.depth"), "must be >= 1");
        issues.check(
            r.max_rate_hz.is_finite() && r.max_rate_hz >= 0.0,
            format!("out[{i}].max_rate_hz"),
            "must be >= 0",
        );
    }
    for (i, s) in statics.iter().enumerate() {
        issues.check(
            !s.parent.is_empty() && !s.child.is_empty() && s.parent != s.child,
            format!("static_transforms[{i}]"),
            "needs two different frames",
        );
        issues.check(
            s.xyz_m.iter().chain(&s.rpy_rad).all(|v| v.is_finite()),
            format!("static_transforms[{i}]"),
            "must be finite",
        );
    }
    for (k, v) in [
        ("map", &frames.map),
        ("odom", &frames.odom),
        ("base_link", &frames.base_link),
        ("local_map", &frames.local_map),
    ] {
        issues.check(!v.is_empty() && !v.contains(char::is_whitespace), format!("frames.{k}"), "not a frame id");
    }
}

/// `/tf_static`: the configured mounts, and `map → odom` = identity when a `tf` route has no
/// odometry of its own. `None` when there is nothing to publish.
pub fn static_tf(statics: &[StaticTransform], routes: &[OutRoute], frames: &Frames) -> Option<TFMessage> {
    let mut transforms = vec![];
    for t in statics {
        let [r, p, y] = t.rpy_rad;
        let iso = Isometry3::from_parts(
            Translation3::new(t.xyz_m[0], t.xyz_m[1], t.xyz_m[2]),
            UnitQuaternion::from_euler_angles(r, p, y),
        );
        transforms.push(convert::transform(0, &t.parent, &t.child, &iso));
    }
    if routes.iter().any(|o| o.what == OutKind::Tf && o.odom == TfOdom::None) {
        transforms.push(convert::transform(0, &frames.map, &frames.odom, &Isometry3::identity()));
    }
    (!transforms.is_empty()).then_some(TFMessage { transforms })
}

/// A ROS 2 message of one of the out types.
#[derive(Debug, Clone)]
pub enum RosOut {
    /// `nav_msgs/Odometry`.
    Odometry(Box<Odometry>),
    /// `geometry_msgs/PoseWithCovarianceStamped`.
    Pose(Box<PoseWithCovarianceStamped>),
    /// `nav_msgs/Path`.
    Path(Path),
    /// `nav_msgs/OccupancyGrid`.
    Grid(OccupancyGrid<'static>),
    /// `sensor_msgs/PointCloud2`.
    Cloud(PointCloud2<'static>),
    /// `visualization_msgs/MarkerArray`.
    Markers(MarkerArray<'static>),
    /// `tf2_msgs/TFMessage`.
    Tf(TFMessage),
}

impl RosOut {
    /// Its CDR bytes (with the encapsulation header), as on the wire and in a bag.
    pub fn encode(&self) -> Result<Vec<u8>, crate::CdrError> {
        match self {
            RosOut::Odometry(m) => crate::cdr::encode(&**m),
            RosOut::Pose(m) => crate::cdr::encode(&**m),
            RosOut::Path(m) => crate::cdr::encode(m),
            RosOut::Grid(m) => crate::cdr::encode(m),
            RosOut::Cloud(m) => crate::cdr::encode(m),
            RosOut::Markers(m) => crate::cdr::encode(m),
            RosOut::Tf(m) => crate::cdr::encode(m),
        }
    }
}

/// A ROS 2 message for route `route`.
#[derive(Debug, Clone)]
pub struct Emitted {
    /// Index of the route in the translator's routes.
    pub route: usize,
    /// The message.
    pub msg: RosOut,
    /// `publish_ns` of the (newest) pipeline message it comes from.
    pub source_publish_ns: u64,
}

/// Which pipeline services the routes read.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Needs {
    /// `pipeline/fusion/pose`.
    pub fused: bool,
    /// `pipeline/slam/pose`.
    pub slam: bool,
    /// `pipeline/grid_slam/pose`.
    pub grid_pose: bool,
    /// `pipeline/grid_slam/grid`.
    pub grid: bool,
    /// `pipeline/map/voxels`.
    pub voxels: bool,
    /// `pipeline/map/traversability`.
    pub traversability: bool,
    /// `pipeline/fusion/map`.
    pub landmarks: bool,
    /// `pipeline/sensors/planar_odometry`.
    pub odometry: bool,
}

/// Per-route state and counters.
#[derive(Debug, Default)]
struct RouteState {
    period: Option<Duration>,
    last_sent: Option<Instant>,
    /// A snapshot update not yet emitted.
    due: bool,
    source_publish_ns: u64,
    /// The path so far (path routes).
    path: Vec<PoseStamped>,
    path_frame: String,
    taken: u64,
    coalesced: u64,
    /// `/tf` of a pose not sent: no odometry at or before its stamp had come yet.
    no_odometry: u64,
    emitted: u64,
    /// False while nobody listens (no subscriber matched, no bag): nothing is emitted.
    unheard: bool,
    /// Messages not emitted because nobody listened.
    not_emitted_unheard: u64,
}

/// The occupied voxels as the stream's full sets and deltas build them
/// ([`shared_types::voxel_stream`]); a delta missed (a gap in `seq`: the stream keeps only the
/// newest message for a slow reader) drops the copy until the next full set.
#[derive(Debug, Default)]
struct VoxelMap {
    voxels: HashMap<VoxelKey, Voxel>,
    resolution_m: f64,
    has_full: bool,
    last_seq: Option<u64>,
    stamp_ns: u64,
    missed: u64,
    waited: u64,
    snapshot_asked: Option<Instant>,
}

impl VoxelMap {
    fn apply(&mut self, h: &VoxelSetHeader, voxels: &[Voxel]) {
        self.resolution_m = h.resolution_m;
        self.stamp_ns = h.msg.stamp_ns;
        if let Some(last) = self.last_seq
            && h.msg.seq > last + 1
        {
            self.missed += h.msg.seq - last - 1;
            self.has_full = false;
            self.voxels.clear();
        }
        self.last_seq = Some(h.msg.seq);
        if !voxel_stream::apply(&mut self.voxels, &mut self.has_full, h.kind, voxels) {
            self.waited += 1;
        }
    }
}

/// Turns pipeline messages into the out routes' ROS 2 messages (see the module docs).
#[derive(Debug)]
pub struct Translator {
    routes: Vec<OutRoute>,
    state: Vec<RouteState>,
    frames: Frames,
    voxels: VoxelMap,
    grid: Option<(u64, OccupancyGridHeader, Vec<i8>)>,
    traversability: Option<(u64, OccupancyGridHeader, Vec<TraversabilityCell>)>,
    landmarks: Option<(u64, u32, Vec<Point>)>,
    /// Recent planar odometry (`odom_from_body`) by stamp, for `map → odom`.
    odometry: BTreeMap<u64, Isometry3<f64>>,
    /// Pipeline messages taken.
    taken: u64,
}

fn planar_iso(x: f64, y: f64, yaw: f64) -> Isometry3<f64> {
    Isometry3::from_parts(Translation3::new(x, y, 0.0), UnitQuaternion::from_axis_angle(&Vector3::z_axis(), yaw))
}

impl Translator {
    /// A translator for `routes` with `frames`.
    pub fn new(routes: &[OutRoute], frames: &Frames) -> Self {
        Self {
            state: routes.iter().map(|r| RouteState { period: r.period(), ..Default::default() }).collect(),
            routes: routes.to_vec(),
            frames: frames.clone(),
            voxels: VoxelMap::default(),
            grid: None,
            traversability: None,
            landmarks: None,
            odometry: BTreeMap::new(),
            taken: 0,
        }
    }

    /// The routes.
    pub fn routes(&self) -> &[OutRoute] {
        &self.routes
    }

    /// Which pipeline services the routes read.
    pub fn needs(&self) -> Needs {
        use OutKind::*;
        let any = |f: &dyn Fn(&OutRoute) -> bool| self.routes.iter().any(f);
        Needs {
            fused: any(&|c| {
                matches!(c.what, FusedOdometry | FusedPose | FusedPath) || (c.what == Tf && c.from == TfFrom::Fused)
            }),
            slam: any(&|c| matches!(c.what, SlamOdometry | SlamPath)),
            grid_pose: any(&|c| {
                matches!(c.what, GridSlamOdometry | GridSlamPose | GridSlamPath)
                    || (c.what == Tf && c.from == TfFrom::GridSlam)
            }),
            grid: any(&|c| c.what == Map),
            voxels: any(&|c| matches!(c.what, Voxels | Obstacles)),
            traversability: any(&|c| matches!(c.what, Traversability | TraversabilityCloud)),
            landmarks: any(&|c| c.what == Landmarks),
            odometry: any(&|c| c.what == Tf && c.odom == TfOdom::PlanarOdometry),
        }
    }

    /// Pipeline messages taken in all.
    pub fn taken(&self) -> u64 {
        self.taken
    }

    /// Pipeline messages a route took.
    pub fn route_taken(&self, route: usize) -> u64 {
        self.state.get(route).map_or(0, |s| s.taken)
    }

    /// Updates of a snapshot route folded into a later message (not lost: the later one holds
    /// them).
    pub fn route_coalesced(&self, route: usize) -> u64 {
        self.state.get(route).map_or(0, |s| s.coalesced)
    }

    /// `map → odom` transforms of route `route` not sent because no odometry at or before the
    /// pose's stamp had come yet (the pose and odometry services are read apart: on a busy
    /// machine several poses can come before the first odometry).
    pub fn route_no_odometry(&self, route: usize) -> u64 {
        self.state.get(route).map_or(0, |s| s.no_odometry)
    }

    /// Voxel-stream messages missed (sequence gaps) and deltas left unused waiting for a full set.
    pub fn voxel_gaps(&self) -> (u64, u64) {
        (self.voxels.missed, self.voxels.waited)
    }

    /// True when a full voxel set should be asked for (the copy lost a delta): at most every 5 s
    /// while one is missing.
    pub fn wants_voxel_snapshot(&mut self) -> bool {
        let v = &mut self.voxels;
        let due = !v.has_full
            && v.last_seq.is_some()
            && v.snapshot_asked.is_none_or(|t| t.elapsed() > Duration::from_secs(5));
        if due {
            v.snapshot_asked = Some(Instant::now());
        }
        due
    }

    /// Calls `f` on every route `pick` selects, counting the message as taken by it.
    fn each(
        &mut self,
        publish_ns: u64,
        pick: impl Fn(&OutRoute) -> bool,
        mut f: impl FnMut(usize, &OutRoute, &mut RouteState, &Frames),
    ) {
        for (i, (r, s)) in self.routes.iter().zip(&mut self.state).enumerate() {
            if pick(r) {
                s.taken += 1;
                s.source_publish_ns = publish_ns;
                f(i, r, s, &self.frames);
            }
        }
    }

    /// Marks a snapshot route updated.
    fn touch(s: &mut RouteState) {
        if s.due && !s.unheard {
            s.coalesced += 1;
        }
        s.due = true;
    }

    fn emit(out: &mut Vec<Emitted>, route: usize, s: &mut RouteState, msg: RosOut) {
        if s.unheard {
            s.not_emitted_unheard += 1;
            return;
        }
        s.emitted += 1;
        out.push(Emitted { route, msg, source_publish_ns: s.source_publish_ns });
    }

    /// Says whether anybody listens to route `route` (a subscriber matched, a bag written).
    /// While nobody does, its messages are not emitted (counted,
    /// [`Translator::route_not_emitted_unheard`]) and its snapshots are not built, as a ROS node
    /// that checks its subscriber count; paths and maps are still kept, so the first listener
    /// gets the newest snapshot at once.
    pub fn set_listened(&mut self, route: usize, listened: bool) {
        let is_snapshot = self.routes.get(route).is_some_and(|r| r.what.is_snapshot());
        let Some(s) = self.state.get_mut(route) else { return };
        if s.unheard && listened && is_snapshot {
            s.due = true;
            s.last_sent = None;
        }
        s.unheard = !listened;
    }

    /// Emits route `route`'s newest snapshot at the next [`Translator::flush`], whatever its
    /// rate (a new subscriber came); nothing for a route of poses.
    pub fn resend(&mut self, route: usize) {
        let is_snapshot = self.routes.get(route).is_some_and(|r| r.what.is_snapshot());
        if let Some(s) = self.state.get_mut(route).filter(|_| is_snapshot) {
            s.due = true;
            s.last_sent = None;
        }
    }

    /// Messages of route `route` not emitted because nobody listened.
    pub fn route_not_emitted_unheard(&self, route: usize) -> u64 {
        self.state.get(route).map_or(0, |s| s.not_emitted_unheard)
    }

    /// `pipeline/sensors/planar_odometry` (`odom_from_body`): `/tf` `odom → base_link` on the
    /// routes with `odom = "planar_odometry"`.
    pub fn odometry(&mut self, stamp_ns: u64, publish_ns: u64, o: &PlanarOdometry, out: &mut Vec<Emitted>) {
        self.taken += 1;
        let odom_from_body = planar_iso(o.position_m[0], o.position_m[1], o.yaw_rad);
        self.odometry.insert(stamp_ns, odom_from_body);
        while self.odometry.len() > 4096 {
            self.odometry.pop_first();
        }
        self.each(
            publish_ns,
            |c| c.what == OutKind::Tf && c.odom == TfOdom::PlanarOdometry,
            |i, _, s, f| {
                let t = convert::transform(stamp_ns, &f.odom, &f.base_link, &odom_from_body);
                Self::emit(out, i, s, RosOut::Tf(TFMessage { transforms: vec![t] }))
            },
        );
    }

    /// `pipeline/fusion/pose`: refined estimates only (a prediction's refined estimate follows).
    pub fn fused(&mut self, stamp_ns: u64, publish_ns: u64, p: &FusedPose, out: &mut Vec<Emitted>) {
        self.taken += 1;
        if p.flags & FUSED_REFINED == 0 {
            return;
        }
        use OutKind::*;
        let map = self.frames.map.clone();
        let odo = convert::odometry_from_pose(stamp_ns, &map, &self.frames.base_link, &p.pose);
        self.each(
            publish_ns,
            |c| c.what == FusedOdometry,
            |i, _, s, _| Self::emit(out, i, s, RosOut::Odometry(Box::new(odo.clone()))),
        );
        self.each(
            publish_ns,
            |c| c.what == FusedPose,
            |i, _, s, _| {
                let m = PoseWithCovarianceStamped { header: odo.header.clone(), pose: odo.pose };
                Self::emit(out, i, s, RosOut::Pose(Box::new(m)))
            },
        );
        self.each(
            publish_ns,
            |c| c.what == FusedPath,
            |_, _, s, _| Self::add_to_path(s, stamp_ns, &map, odo.pose.pose),
        );
        self.tf(stamp_ns, publish_ns, &p.pose.frame_from_body(), TfFrom::Fused, out);
    }

    /// `pipeline/slam/pose` (in the local map, or the map).
    pub fn slam(&mut self, stamp_ns: u64, publish_ns: u64, p: &PoseEstimate, out: &mut Vec<Emitted>) {
        self.taken += 1;
        let frame = if p.frame == FRAME_LOCAL_MAP { self.frames.local_map.clone() } else { self.frames.map.clone() };
        let odo = convert::odometry_from_pose(stamp_ns, &frame, &self.frames.base_link, p);
        self.each(
            publish_ns,
            |c| c.what == OutKind::SlamOdometry,
            |i, _, s, _| Self::emit(out, i, s, RosOut::Odometry(Box::new(odo.clone()))),
        );
        self.each(
            publish_ns,
            |c| c.what == OutKind::SlamPath,
            |_, _, s, _| Self::add_to_path(s, stamp_ns, &frame, odo.pose.pose),
        );
    }

    /// `pipeline/grid_slam/pose`.
    pub fn grid_pose(&mut self, stamp_ns: u64, publish_ns: u64, p: &PlanarPose, out: &mut Vec<Emitted>) {
        self.taken += 1;
        use OutKind::*;
        let pwc = convert::planar_pose(p);
        self.each(
            publish_ns,
            |c| c.what == GridSlamOdometry,
            |i, _, s, f| {
                let m = Odometry {
                    header: convert::header(stamp_ns, &f.map),
                    child_frame_id: f.base_link.clone(),
                    pose: pwc,
                    twist: TwistWithCovariance::default(),
                };
                Self::emit(out, i, s, RosOut::Odometry(Box::new(m)))
            },
        );
        self.each(
            publish_ns,
            |c| c.what == GridSlamPose,
            |i, _, s, f| {
                let m = PoseWithCovarianceStamped { header: convert::header(stamp_ns, &f.map), pose: pwc };
                Self::emit(out, i, s, RosOut::Pose(Box::new(m)))
            },
        );
        self.each(
            publish_ns,
            |c| c.what == GridSlamPath,
            |_, _, s, f| Self::add_to_path(s, stamp_ns, &f.map, pwc.pose),
        );
        let map_from_body = planar_iso(p.position_m[0], p.position_m[1], p.yaw_rad);
        self.tf(stamp_ns, publish_ns, &map_from_body, TfFrom::GridSlam, out);
    }

    /// `pipeline/grid_slam/grid`: the newest grid is kept for the `map` routes.
    pub fn grid(&mut self, h: &OccupancyGridHeader, cells: &[OccupancyCell]) {
        self.taken += 1;
        let values = cells.iter().map(|c| c.value).collect();
        self.grid = Some((h.msg.stamp_ns, *h, values));
        self.each(h.msg.publish_ns, |c| c.what == OutKind::Map, |_, _, s, _| Self::touch(s));
    }

    /// `pipeline/map/traversability`: the newest grid is kept for the `traversability` and
    /// `traversability_cloud` routes.
    pub fn traversability(&mut self, h: &OccupancyGridHeader, cells: &[TraversabilityCell]) {
        self.taken += 1;
        self.traversability = Some((h.msg.stamp_ns, *h, cells.to_vec()));
        self.each(
            h.msg.publish_ns,
            |c| matches!(c.what, OutKind::Traversability | OutKind::TraversabilityCloud),
            |_, _, s, _| Self::touch(s),
        );
    }

    /// `pipeline/map/voxels` (a full set or a delta).
    pub fn voxels(&mut self, h: &VoxelSetHeader, voxels: &[Voxel]) {
        self.taken += 1;
        self.voxels.apply(h, voxels);
        if self.voxels.has_full {
            self.each(
                h.msg.publish_ns,
                |c| matches!(c.what, OutKind::Voxels | OutKind::Obstacles),
                |_, _, s, _| Self::touch(s),
            );
        }
    }

    /// `pipeline/fusion/map`: the newest landmark map is kept for the `landmarks` routes.
    pub fn landmarks(&mut self, h: &LandmarkMapHeader, map: &[Landmark]) {
        self.taken += 1;
        let pts = map.iter().map(|l| Point { x: l.mean_m[0], y: l.mean_m[1], z: l.mean_m[2] }).collect();
        self.landmarks = Some((h.msg.stamp_ns, h.frame, pts));
        self.each(h.msg.publish_ns, |c| c.what == OutKind::Landmarks, |_, _, s, _| Self::touch(s));
    }

    fn add_to_path(s: &mut RouteState, stamp_ns: u64, frame: &str, pose: Pose) {
        s.path.push(PoseStamped { header: convert::header(stamp_ns, frame), pose });
        s.path_frame = frame.to_string();
        Self::touch(s);
    }

    /// `/tf` of a pose: `odom → base_link` when odometry has no route of its own, else
    /// `map → odom` = map_from_body · odom_from_body⁻¹ with the odometry at (or just before) the
    /// pose's stamp (nothing before the first odometry).
    fn tf(
        &mut self,
        stamp_ns: u64,
        publish_ns: u64,
        map_from_body: &Isometry3<f64>,
        from: TfFrom,
        out: &mut Vec<Emitted>,
    ) {
        let odom_at = self.odometry.range(..=stamp_ns).next_back().map(|(_, o)| *o);
        self.each(
            publish_ns,
            |c| c.what == OutKind::Tf && c.from == from,
            |i, r, s, f| {
                let t = match r.odom {
                    TfOdom::None => convert::transform(stamp_ns, &f.odom, &f.base_link, map_from_body),
                    TfOdom::PlanarOdometry => match odom_at {
                        Some(odom_from_body) => {
                            convert::transform(stamp_ns, &f.map, &f.odom, &(map_from_body * odom_from_body.inverse()))
                        }
                        None => {
                            s.no_odometry += 1;
                            return;
                        }
                    },
                };
                Self::emit(out, i, s, RosOut::Tf(TFMessage { transforms: vec![t] }))
            },
        );
    }

    /// The snapshot of route `i` (built from the kept state).
    fn snapshot(&self, i: usize) -> Option<RosOut> {
        let (r, s) = (&self.routes[i], &self.state[i]);
        let f = &self.frames;
        Some(match r.what {
            OutKind::FusedPath | OutKind::SlamPath | OutKind::GridSlamPath => {
                let stamp = s.path.last().map_or(Time::default(), |p| p.header.stamp);
                RosOut::Path(Path { header: Header { stamp, frame_id: s.path_frame.clone() }, poses: s.path.clone() })
            }
            OutKind::Map => {
                let (stamp, h, cells) = self.grid.as_ref()?;
                RosOut::Grid(convert::occupancy_grid(*stamp, &f.map, h, cells))
            }
            OutKind::Traversability => {
                let (stamp, h, cells) = self.traversability.as_ref()?;
                RosOut::Grid(convert::traversability_grid(*stamp, &f.map, h, cells))
            }
            OutKind::TraversabilityCloud => {
                let (stamp, h, cells) = self.traversability.as_ref()?;
                RosOut::Cloud(convert::traversability_cloud(*stamp, &f.map, h, cells))
            }
            OutKind::Voxels => {
                let v = &self.voxels;
                v.has_full.then(|| RosOut::Cloud(convert::voxel_cloud(v.stamp_ns, &f.map, v.voxels.values())))?
            }
            OutKind::Obstacles => {
                let v = &self.voxels;
                if !v.has_full {
                    return None;
                }
                // The obstacles, and the walls (which block as they do) in a marker of their own.
                let of_class = |class: u32| {
                    v.voxels
                        .values()
                        .filter(|v| v.class == class)
                        .map(|v| Point { x: v.center_m[0] as f64, y: v.center_m[1] as f64, z: v.center_m[2] as f64 })
                        .collect()
                };
                let m = list_marker(
                    v.stamp_ns,
                    &f.map,
                    "obstacles",
                    MARKER_CUBE_LIST,
                    v.resolution_m,
                    of_class(VOXEL_OBSTACLE),
                    [1.0, 0.3, 0.1],
                );
                let w = list_marker(
                    v.stamp_ns,
                    &f.map,
                    "walls",
                    MARKER_CUBE_LIST,
                    v.resolution_m,
                    of_class(VOXEL_WALL),
                    [0.6, 0.6, 0.6],
                );
                RosOut::Markers(MarkerArray { markers: vec![m, w] })
            }
            OutKind::Landmarks => {
                let (stamp, frame, pts) = self.landmarks.as_ref()?;
                let frame = if *frame == FRAME_LOCAL_MAP { &f.local_map } else { &f.map };
                let m = list_marker(*stamp, frame, "landmarks", MARKER_SPHERE_LIST, 0.25, pts.clone(), [0.2, 0.6, 1.0]);
                RosOut::Markers(MarkerArray { markers: vec![m] })
            }
            _ => return None,
        })
    }

    /// Emits every updated snapshot that is due (all of them with `force`, at the end); returns
    /// when the next kept one is due.
    pub fn flush(&mut self, force: bool, out: &mut Vec<Emitted>) -> Option<Instant> {
        let now = Instant::now();
        let mut next: Option<Instant> = None;
        for i in 0..self.routes.len() {
            let s = &self.state[i];
            if !s.due || s.unheard {
                continue;
            }
            let due_at = match (s.period, s.last_sent) {
                (Some(p), Some(t)) => t + p,
                _ => now,
            };
            if force || now >= due_at {
                let msg = self.snapshot(i);
                let s = &mut self.state[i];
                s.due = false;
                s.last_sent = Some(now);
                if let Some(msg) = msg {
                    Self::emit(out, i, s, msg);
                }
            } else {
                next = Some(next.map_or(due_at, |n| n.min(due_at)));
            }
        }
        next
    }
}

fn list_marker(
    stamp_ns: u64,
    frame: &str,
    ns: &str,
    kind: i32,
    size: f64,
    points: Vec<Point>,
    rgb: [f32; 3],
) -> Marker<'static> {
    Marker {
        header: convert::header(stamp_ns, frame),
        ns: ns.into(),
        id: 0,
        kind,
        action: MARKER_ADD,
        pose: Pose::default(),
        scale: crate::msgs::Vector3 { x: size, y: size, z: size },
        color: ColorRGBA { r: rgb[0], g: rgb[1], b: rgb[2], a: 1.0 },
        points,
        ..Default::default()
    }
}

#[cfg(test)]
mod tests;
