//! Pipeline → ROS 2: each `out` route turns one pipeline service into a ROS 2 topic. Poses and
//! transforms go out as they come; paths, the voxel cloud and marker arrays are snapshots of a
//! state the gateway keeps, sent at most `max_rate_hz` (a snapshot not sent is replaced by the
//! next, and the last is always sent at the end).

use std::cell::RefCell;
use std::collections::{BTreeMap, HashMap};
use std::rc::Rc;
use std::time::{Duration, Instant};

use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use pipeline_runtime::{Input, Output, Runtime, StageError};
use ros2_client::Publisher;
use ros2_interop::convert;
use ros2_interop::msgs::*;
use ros2_interop::{BagQos, BagWriter};
use serde::Serialize;
use shared_types::services::*;
use shared_types::voxel_stream::{self, VoxelKey};
use shared_types::{
    COMMAND_VOXEL_SNAPSHOT, ControlCommand, FRAME_LOCAL_MAP, FUSED_REFINED, FusedPose, Landmark, LandmarkMapHeader,
    MsgHeader, OccupancyCell, OccupancyGridHeader, PlanarOdometry, PlanarPose, PoseEstimate, VOXEL_OBSTACLE, Voxel,
    VoxelSetHeader,
};

use crate::dds::{DdsError, RosNode, err};
use crate::settings::{Frames, GatewayOut, OutKind, TfFrom, TfOdom};

/// A ROS 2 publisher of one of the out types.
pub enum OutPub {
    /// `nav_msgs/Odometry`.
    Odometry(Publisher<Odometry>),
    /// `geometry_msgs/PoseWithCovarianceStamped`.
    Pose(Publisher<PoseWithCovarianceStamped>),
    /// `nav_msgs/Path`.
    Path(Publisher<Path>),
    /// `nav_msgs/OccupancyGrid`.
    Grid(Publisher<OccupancyGrid<'static>>),
    /// `sensor_msgs/PointCloud2`.
    Cloud(Publisher<PointCloud2<'static>>),
    /// `visualization_msgs/MarkerArray`.
    Markers(Publisher<MarkerArray<'static>>),
    /// `tf2_msgs/TFMessage`.
    Tf(Publisher<TFMessage>),
}

/// Creates a publisher of `T` on `topic`.
fn publisher<T: Serialize>(
    node: &mut RosNode,
    topic: &ros2_client::dds::rustdds::Topic,
    name: &str,
) -> Result<Publisher<T>, DdsError> {
    node.node.create_publisher::<T>(topic, None).map_err(|e| err(format!("publisher on `{name}`"))(&e))
}

/// Publishes `m`; with `record`, also returns its CDR bytes for the ROS 2 bag.
fn send<T: Serialize>(record: bool, p: &Publisher<T>, m: T) -> (Result<(), String>, Option<Vec<u8>>) {
    let bytes = if record { ros2_interop::cdr::encode(&m).ok() } else { None };
    (p.publish(m).map_err(|e| e.to_string()), bytes)
}

fn unix_ns() -> u64 {
    std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.as_nanos() as u64).unwrap_or(0)
}

/// Counters of an `out` route (summary.json `ros2.out.<topic>`).
#[derive(Debug, Default, Serialize)]
pub struct OutCounts {
    /// What it publishes.
    pub what: Option<OutKind>,
    /// Pipeline messages it took.
    pub taken: u64,
    /// ROS 2 messages published.
    pub published: u64,
    /// Snapshots replaced by a newer one before they were due (`max_rate_hz`): not lost, the
    /// newer one holds them.
    pub coalesced: u64,
    /// Publishing failed (DDS refused or timed out): lost.
    pub failed: u64,
    /// Published but not written into the ROS 2 bag (`record_bag`).
    pub not_recorded: u64,
    /// Subscribers matched at the end (from DDS discovery's matching events).
    pub subscribers: usize,
    /// Remote subscribers whose QoS cannot match this route's (they get nothing).
    pub qos_incompatible: u64,
    /// Remote subscribers on this topic of another type (they get nothing).
    pub type_mismatch: u64,
}

/// The state a snapshot route sends.
enum Snapshot {
    None,
    Path(Path),
    Grid(OccupancyGrid<'static>),
    Cloud(PointCloud2<'static>),
    Markers(MarkerArray<'static>),
}

/// One `out` route.
pub struct OutRoute {
    /// Its settings.
    pub cfg: GatewayOut,
    publisher: OutPub,
    /// Its counters.
    pub counts: OutCounts,
    period: Option<Duration>,
    last_sent: Option<Instant>,
    pending: Snapshot,
    path: Vec<PoseStamped>,
    warned: bool,
    /// The ROS 2 bag the route's messages are also written into.
    bag: Option<Rc<RefCell<BagWriter>>>,
    /// `publish_ns` of the pipeline message the next ROS message comes from.
    source_publish_ns: u64,
    /// Pipeline publish → ROS publish, per message.
    pub latency: crate::inbound::Hist,
    /// The remote readers matched to the writer now.
    pub remotes: std::collections::BTreeSet<ros2_client::dds::rustdds::GUID>,
}

impl OutRoute {
    /// Creates the route's topic and publisher.
    pub fn new(node: &mut RosNode, cfg: &GatewayOut) -> Result<Self, DdsError> {
        let name = cfg.topic().to_string();
        let topic = node.topic(&name, cfg.what.ros_type(), cfg.qos())?;
        let publisher = match cfg.what {
            OutKind::FusedOdometry | OutKind::SlamOdometry | OutKind::GridSlamOdometry => {
                OutPub::Odometry(publisher(node, &topic, &name)?)
            }
            OutKind::FusedPose | OutKind::GridSlamPose => OutPub::Pose(publisher(node, &topic, &name)?),
            OutKind::FusedPath | OutKind::SlamPath | OutKind::GridSlamPath => {
                OutPub::Path(publisher(node, &topic, &name)?)
            }
            OutKind::Map => OutPub::Grid(publisher(node, &topic, &name)?),
            OutKind::Voxels => OutPub::Cloud(publisher(node, &topic, &name)?),
            OutKind::Landmarks | OutKind::Obstacles => OutPub::Markers(publisher(node, &topic, &name)?),
            OutKind::Tf => OutPub::Tf(publisher(node, &topic, &name)?),
        };
        // Snapshots of growing state default to a few per second; the rest to every message.
        let rate = match (cfg.max_rate_hz, cfg.what) {
            (r, _) if r > 0.0 => r,
            (_, OutKind::FusedPath | OutKind::SlamPath | OutKind::GridSlamPath) => 2.0,
            (_, OutKind::Voxels | OutKind::Landmarks | OutKind::Obstacles) => 1.0,
            _ => 0.0,
        };
        Ok(Self {
            cfg: cfg.clone(),
            publisher,
            counts: OutCounts { what: Some(cfg.what), ..Default::default() },
            period: (rate > 0.0).then(|| Duration::from_secs_f64(1.0 / rate)),
            last_sent: None,
            pending: Snapshot::None,
            path: vec![],
            warned: false,
            bag: None,
            source_publish_ns: 0,
            latency: Default::default(),
            remotes: Default::default(),
        })
    }

    /// The DDS writer's GUID.
    pub fn guid(&self) -> ros2_client::dds::rustdds::GUID {
        match &self.publisher {
            OutPub::Odometry(p) => p.guid(),
            OutPub::Pose(p) => p.guid(),
            OutPub::Path(p) => p.guid(),
            OutPub::Grid(p) => p.guid(),
            OutPub::Cloud(p) => p.guid(),
            OutPub::Markers(p) => p.guid(),
            OutPub::Tf(p) => p.guid(),
        }
    }

    /// A remote subscriber whose QoS cannot match (discovery said so).
    pub fn qos_incompatible(&mut self, requested: &str, offered: &str) {
        self.counts.qos_incompatible += 1;
        tracing::warn!(
            topic = %self.cfg.topic(),
            "a subscriber requests QoS ({requested}) this route does not offer ({offered}): it gets nothing (counted in summary.json)"
        );
    }

    /// A remote subscriber on the topic, of DDS type `dds_type`.
    pub fn remote_type(&mut self, dds_type: &str) {
        let want = ros2_interop::msgs::dds_type_name(self.cfg.what.ros_type());
        if dds_type != want {
            self.counts.type_mismatch += 1;
            tracing::warn!(
                topic = %self.cfg.topic(),
                "a subscriber of type `{dds_type}` on this topic; the route publishes `{want}`: it gets nothing (counted in summary.json)"
            );
        }
    }

    fn failed(&mut self, e: impl std::fmt::Debug) {
        self.counts.failed += 1;
        if !self.warned {
            self.warned = true;
            tracing::warn!(topic = %self.cfg.topic(), "publishing failed: {e:?} (counted in summary.json; warned once)");
        }
    }

    fn publish_now(&mut self, snap: Snapshot) {
        let (r, bytes) = match (&self.publisher, snap) {
            (OutPub::Path(p), Snapshot::Path(m)) => send(self.bag.is_some(), p, m),
            (OutPub::Grid(p), Snapshot::Grid(m)) => send(self.bag.is_some(), p, m),
            (OutPub::Cloud(p), Snapshot::Cloud(m)) => send(self.bag.is_some(), p, m),
            (OutPub::Markers(p), Snapshot::Markers(m)) => send(self.bag.is_some(), p, m),
            (_, Snapshot::None) => return,
            _ => (Err("snapshot of another type".to_string()), None),
        };
        self.last_sent = Some(Instant::now());
        self.done(r, bytes);
    }

    /// Counts a publish (and records what was published).
    fn done(&mut self, r: Result<(), String>, bytes: Option<Vec<u8>>) {
        if let Some(bytes) = bytes {
            self.record_bytes(&bytes);
        } else if self.bag.is_some() {
            self.counts.not_recorded += 1;
        }
        match r {
            Ok(()) => {
                self.counts.published += 1;
                if self.source_publish_ns > 0 {
                    self.latency.record_ns(pipeline_runtime::monotonic_ns() as i64 - self.source_publish_ns as i64);
                }
            }
            Err(e) => self.failed(e),
        }
    }

    fn record_bytes(&mut self, bytes: &[u8]) {
        let Some(bag) = &self.bag else { return };
        if let Err(e) = bag.borrow_mut().write(self.cfg.topic(), unix_ns(), bytes) {
            self.counts.not_recorded += 1;
            if self.counts.not_recorded == 1 {
                tracing::warn!(topic = %self.cfg.topic(), "writing the ROS 2 bag failed: {e} (counted in summary.json; warned once)");
            }
        }
    }

    /// A new snapshot: sent now if due, else kept (replacing one not yet sent).
    fn offer(&mut self, snap: Snapshot) {
        let due = match (self.period, self.last_sent) {
            (Some(p), Some(t)) => t.elapsed() >= p,
            _ => true,
        };
        if !matches!(self.pending, Snapshot::None) {
            self.counts.coalesced += 1;
        }
        if due {
            self.pending = Snapshot::None;
            self.publish_now(snap);
        } else {
            self.pending = snap;
        }
    }

    /// Sends a kept snapshot once it is due (or `force`); returns when the next one is due.
    pub fn flush(&mut self, force: bool) -> Option<Instant> {
        if matches!(self.pending, Snapshot::None) {
            return None;
        }
        let due_at = match (self.period, self.last_sent) {
            (Some(p), Some(t)) => t + p,
            _ => Instant::now(),
        };
        if force || Instant::now() >= due_at {
            let snap = std::mem::replace(&mut self.pending, Snapshot::None);
            self.publish_now(snap);
            None
        } else {
            Some(due_at)
        }
    }

    fn publish_odometry(&mut self, m: Odometry) {
        if let OutPub::Odometry(p) = &self.publisher {
            let (r, bytes) = send(self.bag.is_some(), p, m);
            self.done(r, bytes);
        }
    }

    fn publish_pose(&mut self, m: PoseWithCovarianceStamped) {
        if let OutPub::Pose(p) = &self.publisher {
            let (r, bytes) = send(self.bag.is_some(), p, m);
            self.done(r, bytes);
        }
    }

    fn publish_tf(&mut self, m: TFMessage) {
        if let OutPub::Tf(p) = &self.publisher {
            let (r, bytes) = send(self.bag.is_some(), p, m);
            self.done(r, bytes);
        }
    }

    fn add_to_path(&mut self, stamp_ns: u64, frame: &str, pose: Pose) {
        self.path.push(PoseStamped { header: convert::header(stamp_ns, frame), pose });
        let path = Path { header: convert::header(stamp_ns, frame), poses: self.path.clone() };
        self.offer(Snapshot::Path(path));
    }
}

/// The occupied voxels as the stream's full sets and deltas build them
/// ([`shared_types::voxel_stream`]); a delta missed (a gap in `seq`: the stream keeps only the
/// newest message for a slow reader) drops the copy until the next full set, which is asked for.
#[derive(Default)]
struct VoxelMap {
    voxels: HashMap<VoxelKey, Voxel>,
    resolution_m: f64,
    has_full: bool,
    last_seq: Option<u64>,
    /// Messages missed (sequence gaps).
    missed: u64,
    /// Deltas left unused while waiting for a full set.
    waited: u64,
    snapshot_asked: Option<Instant>,
}

impl VoxelMap {
    fn apply(&mut self, h: &VoxelSetHeader, voxels: &[Voxel]) {
        self.resolution_m = h.resolution_m;
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

    /// True when a full set should be asked for (at most every 5 s while one is missing).
    fn wants_snapshot(&mut self) -> bool {
        let due = !self.has_full
            && self.last_seq.is_some()
            && self.snapshot_asked.is_none_or(|t| t.elapsed() > Duration::from_secs(5));
        if due {
            self.snapshot_asked = Some(Instant::now());
        }
        due
    }
}

/// The pipeline inputs the `out` routes read (opened only when some route needs them).
#[derive(Default)]
struct OutInputs {
    fused: Option<Input<FusedPose, MsgHeader>>,
    slam: Option<Input<PoseEstimate, MsgHeader>>,
    grid_pose: Option<Input<PlanarPose, MsgHeader>>,
    grid: Option<Input<[OccupancyCell], OccupancyGridHeader>>,
    voxels: Option<Input<[Voxel], VoxelSetHeader>>,
    landmarks: Option<Input<[Landmark], LandmarkMapHeader>>,
    odometry: Option<Input<PlanarOdometry, MsgHeader>>,
    /// To ask the mapper for a full voxel set.
    commands: Option<Output<ControlCommand, MsgHeader>>,
}

/// The whole `out` direction.
pub struct Outbound {
    /// The routes.
    pub routes: Vec<OutRoute>,
    inputs: OutInputs,
    frames: Frames,
    voxels: VoxelMap,
    /// Recent planar odometry (`odom_from_body`) by stamp, for `map → odom`.
    odometry: BTreeMap<u64, Isometry3<f64>>,
    /// Pipeline messages read.
    pub taken: u64,
    /// `publish_ns` of the pipeline message being turned into ROS messages.
    source_publish_ns: u64,
    /// The ROS 2 bag every out route's messages are also written into (`record_bag`).
    pub bag: Option<Rc<RefCell<BagWriter>>>,
}

fn planar_iso(x: f64, y: f64, yaw: f64) -> Isometry3<f64> {
    Isometry3::from_parts(Translation3::new(x, y, 0.0), UnitQuaternion::from_axis_angle(&Vector3::z_axis(), yaw))
}

impl Outbound {
    /// Opens the routes' publishers and the inputs they need.
    pub fn open(rt: &mut Runtime, node: &mut RosNode, cfg: &[GatewayOut], frames: &Frames) -> Result<Self, StageError> {
        let mut routes = vec![];
        for c in cfg {
            routes.push(OutRoute::new(node, c).map_err(StageError::stage)?);
        }
        let needs = |f: &dyn Fn(&GatewayOut) -> bool| cfg.iter().any(f);
        let mut inputs = OutInputs::default();
        use OutKind::*;
        if needs(&|c| {
            matches!(c.what, FusedOdometry | FusedPose | FusedPath) || (c.what == Tf && c.from == TfFrom::Fused)
        }) {
            inputs.fused = Some(rt.input(FUSION_POSE)?);
        }
        if needs(&|c| matches!(c.what, SlamOdometry | SlamPath)) {
            inputs.slam = Some(rt.input(SLAM_POSE)?);
        }
        if needs(&|c| {
            matches!(c.what, GridSlamOdometry | GridSlamPose | GridSlamPath)
                || (c.what == Tf && c.from == TfFrom::GridSlam)
        }) {
            inputs.grid_pose = Some(rt.input(GRID_SLAM_POSE)?);
        }
        if needs(&|c| c.what == Map) {
            inputs.grid = Some(rt.input(GRID_SLAM_GRID)?);
        }
        if needs(&|c| matches!(c.what, Voxels | Obstacles)) {
            inputs.voxels = Some(rt.input(MAP_VOXELS)?);
            inputs.commands = Some(rt.output::<ControlCommand, MsgHeader>(COMMAND)?);
        }
        if needs(&|c| c.what == Landmarks) {
            inputs.landmarks = Some(rt.input(FUSION_MAP)?);
        }
        if needs(&|c| c.what == Tf && c.odom == TfOdom::PlanarOdometry) {
            inputs.odometry = Some(rt.input(PLANAR_ODOMETRY)?);
        }
        Ok(Self {
            routes,
            inputs,
            frames: frames.clone(),
            voxels: VoxelMap::default(),
            odometry: BTreeMap::new(),
            taken: 0,
            source_publish_ns: 0,
            bag: None,
        })
    }

    /// Records every route's messages into a new ROS 2 bag at `dir` (each topic declared with
    /// the route's type and QoS).
    pub fn record_into(&mut self, dir: &std::path::Path) -> Result<(), ros2_interop::BagError> {
        let mut bag = BagWriter::create(dir)?;
        for r in &self.routes {
            let q = r.cfg.qos();
            let qos = BagQos {
                reliable: q.reliability == crate::settings::Reliability::Reliable,
                transient_local: q.durability == crate::settings::Durability::TransientLocal,
                depth: q.depth,
            };
            bag.add_topic(r.cfg.topic(), r.cfg.what.ros_type(), qos)?;
        }
        let bag = Rc::new(RefCell::new(bag));
        for r in &mut self.routes {
            r.bag = Some(bag.clone());
        }
        self.bag = Some(bag);
        Ok(())
    }

    /// True when no route reads the pipeline.
    pub fn is_empty(&self) -> bool {
        self.routes.is_empty()
    }

    fn for_routes(&mut self, pick: impl Fn(&GatewayOut) -> bool, mut f: impl FnMut(&mut OutRoute, &Frames)) {
        for r in self.routes.iter_mut().filter(|r| pick(&r.cfg)) {
            r.counts.taken += 1;
            r.source_publish_ns = self.source_publish_ns;
            f(r, &self.frames);
        }
    }

    /// Reads every input and publishes; returns the earliest time a kept snapshot is due.
    pub fn pump(&mut self) -> Result<Option<Instant>, StageError> {
        use OutKind::*;
        // Odometry first: a pose's `map → odom` needs the odometry of its stamp.
        let mut odo = vec![];
        if let Some(i) = &self.inputs.odometry {
            while let Some(r) = i.receive()? {
                odo.push((r.user_header().stamp_ns, r.user_header().publish_ns, *r.payload()));
            }
        }
        for (stamp, published, o) in odo {
            self.taken += 1;
            self.source_publish_ns = published;
            let odom_from_body = planar_iso(o.position_m[0], o.position_m[1], o.yaw_rad);
            self.odometry.insert(stamp, odom_from_body);
            while self.odometry.len() > 4096 {
                self.odometry.pop_first();
            }
            self.for_routes(
                |c| c.what == Tf && c.odom == TfOdom::PlanarOdometry,
                |r, f| {
                    r.publish_tf(TFMessage {
                        transforms: vec![convert::transform(stamp, &f.odom, &f.base_link, &odom_from_body)],
                    })
                },
            );
        }
        let mut fused = vec![];
        if let Some(i) = &self.inputs.fused {
            while let Some(r) = i.receive()? {
                fused.push((r.user_header().stamp_ns, r.user_header().publish_ns, *r.payload()));
            }
        }
        for (stamp, published, p) in fused {
            self.taken += 1;
            self.source_publish_ns = published;
            if p.flags & FUSED_REFINED == 0 {
                continue; // a prediction: its refined estimate follows
            }
            self.pose_out(stamp, &p.pose, TfFrom::Fused);
        }
        let mut slam = vec![];
        if let Some(i) = &self.inputs.slam {
            while let Some(r) = i.receive()? {
                slam.push((r.user_header().stamp_ns, r.user_header().publish_ns, *r.payload()));
            }
        }
        for (stamp, published, p) in slam {
            self.taken += 1;
            self.source_publish_ns = published;
            let frame =
                if p.frame == FRAME_LOCAL_MAP { self.frames.local_map.clone() } else { self.frames.map.clone() };
            self.for_routes(
                |c| c.what == SlamOdometry,
                |r, f| r.publish_odometry(convert::odometry_from_pose(stamp, &frame, &f.base_link, &p)),
            );
            let pose = convert::pose(&p.frame_from_body());
            self.for_routes(|c| c.what == SlamPath, |r, _| r.add_to_path(stamp, &frame, pose));
        }
        let mut grid_poses = vec![];
        if let Some(i) = &self.inputs.grid_pose {
            while let Some(r) = i.receive()? {
                grid_poses.push((r.user_header().stamp_ns, r.user_header().publish_ns, *r.payload()));
            }
        }
        for (stamp, published, p) in grid_poses {
            self.taken += 1;
            self.source_publish_ns = published;
            let pwc = convert::planar_pose(&p);
            self.for_routes(
                |c| c.what == GridSlamOdometry,
                |r, f| {
                    r.publish_odometry(Odometry {
                        header: convert::header(stamp, &f.map),
                        child_frame_id: f.base_link.clone(),
                        pose: pwc,
                        twist: TwistWithCovariance::default(),
                    })
                },
            );
            self.for_routes(
                |c| c.what == GridSlamPose,
                |r, f| r.publish_pose(PoseWithCovarianceStamped { header: convert::header(stamp, &f.map), pose: pwc }),
            );
            self.for_routes(|c| c.what == GridSlamPath, |r, f| r.add_to_path(stamp, &f.map.clone(), pwc.pose));
            let map_from_body = planar_iso(p.position_m[0], p.position_m[1], p.yaw_rad);
            self.tf_out(stamp, &map_from_body, TfFrom::GridSlam);
        }
        let mut grids = vec![];
        if let Some(i) = &self.inputs.grid {
            while let Some(r) = i.receive()? {
                let cells: Vec<i8> = r.payload().iter().map(|c| c.value).collect();
                grids.push((*r.user_header(), cells));
            }
        }
        for (h, cells) in grids {
            self.taken += 1;
            self.source_publish_ns = h.msg.publish_ns;
            self.for_routes(
                |c| c.what == Map,
                |r, f| r.offer(Snapshot::Grid(convert::occupancy_grid(h.msg.stamp_ns, &f.map, &h, &cells))),
            );
        }
        let mut voxel_msgs = 0;
        let mut voxel_stamp = 0;
        if let Some(i) = &self.inputs.voxels {
            while let Some(r) = i.receive()? {
                voxel_msgs += 1;
                voxel_stamp = r.user_header().msg.stamp_ns;
                self.source_publish_ns = r.user_header().msg.publish_ns;
                self.voxels.apply(r.user_header(), r.payload());
            }
        }
        if self.voxels.wants_snapshot()
            && let Some(out) = &mut self.inputs.commands
        {
            let now = pipeline_runtime::monotonic_ns();
            out.send_value(
                MsgHeader { stamp_ns: now, origin_ns: now, ..Default::default() },
                ControlCommand { target: [0; 32], command: COMMAND_VOXEL_SNAPSHOT, _reserved: 0, arg: 0 },
            )?;
        }
        self.taken += voxel_msgs;
        if voxel_msgs > 0 && self.voxels.has_full {
            let all: Vec<Voxel> = self.voxels.voxels.values().copied().collect();
            self.for_routes(
                |c| c.what == Voxels,
                |r, f| r.offer(Snapshot::Cloud(convert::voxel_cloud(voxel_stamp, &f.map, all.iter()))),
            );
            let obstacles: Vec<Point> = all
                .iter()
                .filter(|v| v.class == VOXEL_OBSTACLE)
                .map(|v| Point { x: v.center_m[0] as f64, y: v.center_m[1] as f64, z: v.center_m[2] as f64 })
                .collect();
            let size = self.voxels.resolution_m;
            self.for_routes(
                |c| c.what == Obstacles,
                |r, f| {
                    let m = list_marker(
                        voxel_stamp,
                        &f.map,
                        "obstacles",
                        MARKER_CUBE_LIST,
                        size,
                        obstacles.clone(),
                        [1.0, 0.3, 0.1],
                    );
                    r.offer(Snapshot::Markers(MarkerArray { markers: vec![m] }))
                },
            );
        }
        let mut maps = vec![];
        if let Some(i) = &self.inputs.landmarks {
            while let Some(r) = i.receive()? {
                let pts: Vec<Point> =
                    r.payload().iter().map(|l| Point { x: l.mean_m[0], y: l.mean_m[1], z: l.mean_m[2] }).collect();
                maps.push((*r.user_header(), pts));
            }
        }
        for (h, pts) in maps {
            self.taken += 1;
            self.source_publish_ns = h.msg.publish_ns;
            let frame_of = |f: &Frames| if h.frame == FRAME_LOCAL_MAP { f.local_map.clone() } else { f.map.clone() };
            self.for_routes(
                |c| c.what == Landmarks,
                |r, f| {
                    let m = list_marker(
                        h.msg.stamp_ns,
                        &frame_of(f),
                        "landmarks",
                        MARKER_SPHERE_LIST,
                        0.25,
                        pts.clone(),
                        [0.2, 0.6, 1.0],
                    );
                    r.offer(Snapshot::Markers(MarkerArray { markers: vec![m] }))
                },
            );
        }
        Ok(self.routes.iter_mut().filter_map(|r| r.flush(false)).min())
    }

    fn pose_out(&mut self, stamp: u64, p: &PoseEstimate, from: TfFrom) {
        use OutKind::*;
        let map = self.frames.map.clone();
        self.for_routes(
            |c| c.what == FusedOdometry,
            |r, f| r.publish_odometry(convert::odometry_from_pose(stamp, &map, &f.base_link, p)),
        );
        let odo = convert::odometry_from_pose(stamp, &map, &self.frames.base_link, p);
        self.for_routes(
            |c| c.what == FusedPose,
            |r, _| r.publish_pose(PoseWithCovarianceStamped { header: odo.header.clone(), pose: odo.pose }),
        );
        self.for_routes(|c| c.what == FusedPath, |r, _| r.add_to_path(stamp, &map, odo.pose.pose));
        self.tf_out(stamp, &p.frame_from_body(), from);
    }

    /// `/tf` of a pose: `odom → base_link` when odometry has no route of its own, else
    /// `map → odom` = map_from_body · odom_from_body⁻¹ with the odometry at (or just before) the
    /// pose's stamp.
    fn tf_out(&mut self, stamp: u64, map_from_body: &Isometry3<f64>, from: TfFrom) {
        let odom_at = self.odometry.range(..=stamp).next_back().map(|(_, o)| *o);
        self.for_routes(
            |c| c.what == OutKind::Tf && c.from == from,
            |r, f| {
                let t = match r.cfg.odom {
                    TfOdom::None => convert::transform(stamp, &f.odom, &f.base_link, map_from_body),
                    TfOdom::PlanarOdometry => match odom_at {
                        Some(odom_from_body) => {
                            convert::transform(stamp, &f.map, &f.odom, &(map_from_body * odom_from_body.inverse()))
                        }
                        None => return, // no odometry yet: nothing to place `odom` by
                    },
                };
                r.publish_tf(TFMessage { transforms: vec![t] });
            },
        );
    }

    /// Voxel-stream messages missed (sequence gaps) and deltas left unused waiting for a full set.
    pub fn voxel_gaps(&self) -> (u64, u64) {
        (self.voxels.missed, self.voxels.waited)
    }

    /// Sends every kept snapshot (at the end).
    pub fn flush_all(&mut self) {
        for r in &mut self.routes {
            r.flush(true);
        }
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
        scale: ros2_interop::msgs::Vector3 { x: size, y: size, z: size },
        color: ColorRGBA { r: rgb[0], g: rgb[1], b: rgb[2], a: 1.0 },
        points,
        ..Default::default()
    }
}
