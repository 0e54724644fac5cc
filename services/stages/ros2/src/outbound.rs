//! Pipeline → ROS 2: the `out` routes' pipeline inputs are read and turned into ROS 2 messages by
//! [`ros2_interop::out::Translator`] (poses and transforms as they come; paths, the grid, the voxel
//! cloud and marker arrays as snapshots at most `max_rate_hz`), which each route publishes on DDS
//! and, with `record_bag`, writes into a rosbag2 bag.

use std::time::Instant;

use pipeline_runtime::{Input, Output, Runtime, StageError};
use ros2_client::Publisher;
use ros2_interop::msgs::*;
use ros2_interop::out::{Emitted, RosOut, Translator};
use ros2_interop::{BagCompression, BagSink, BagWriter};
use serde::Serialize;
use shared_types::services::*;
use shared_types::{
    COMMAND_VOXEL_SNAPSHOT, ControlCommand, FusedPose, Landmark, LandmarkMapHeader, MsgHeader, OccupancyCell,
    OccupancyGridHeader, PlanarOdometry, PlanarPose, PoseEstimate, TraversabilityCell, Voxel, VoxelSetHeader,
};

use crate::dds::{DdsError, RosNode, err};
use crate::settings::{Frames, GatewayOut, OutKind};

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

fn unix_ns() -> u64 {
    std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.as_nanos() as u64).unwrap_or(0)
}

/// Counters of an `out` route (summary.json `ros2.out.<topic>`).
#[derive(Debug, Default, Clone, Serialize, serde::Deserialize, schemars::JsonSchema)]
#[schemars(rename = "Ros2OutCounts")]
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
    /// `/tf` routes: `map → odom` of a pose not published, no odometry at or before its stamp
    /// having come yet.
    pub tf_without_odometry: u64,
    /// Published but not written into the ROS 2 bag (`record_bag`).
    pub not_recorded: u64,
    /// Not published because no subscriber was matched (DDS would have delivered them to
    /// nobody; a snapshot route publishes its newest at once when one comes). With a bag they
    /// are still written into it.
    pub no_subscriber: u64,
    /// Subscribers matched at the end (from DDS discovery's matching events).
    pub subscribers: usize,
    /// Remote subscribers whose QoS cannot match this route's (they get nothing).
    pub qos_incompatible: u64,
    /// Remote subscribers on this topic of another type (they get nothing).
    pub type_mismatch: u64,
}

/// One `out` route: its publisher and counters.
pub struct OutRoute {
    /// Its settings.
    pub cfg: GatewayOut,
    publisher: OutPub,
    /// Its counters.
    pub counts: OutCounts,
    warned: bool,
    /// Pipeline publish → ROS publish, per message.
    pub latency: crate::inbound::Hist,
    /// The remote readers matched to the writer now.
    pub remotes: std::collections::BTreeSet<ros2_client::dds::rustdds::GUID>,
    /// Remote subscribers already counted as not matching (discovery may report one more than
    /// once: each update of its discovery data).
    unmatched: std::collections::BTreeSet<ros2_client::dds::rustdds::GUID>,
    /// Whether a reader was matched at the last look (a new one gets the newest snapshot).
    was_heard: bool,
    /// Messages written into the bag but not published: no reader matched.
    bag_only: u64,
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
            OutKind::Map | OutKind::Traversability => OutPub::Grid(publisher(node, &topic, &name)?),
            OutKind::Voxels | OutKind::TraversabilityCloud => OutPub::Cloud(publisher(node, &topic, &name)?),
            OutKind::Landmarks | OutKind::Obstacles => OutPub::Markers(publisher(node, &topic, &name)?),
            OutKind::Tf => OutPub::Tf(publisher(node, &topic, &name)?),
        };
        Ok(Self {
            cfg: cfg.clone(),
            publisher,
            counts: OutCounts { what: Some(cfg.what), ..Default::default() },
            warned: false,
            latency: Default::default(),
            remotes: Default::default(),
            unmatched: Default::default(),
            was_heard: false,
            bag_only: 0,
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

    /// A remote subscriber whose QoS cannot match (discovery said so); counted once per subscriber.
    pub fn qos_incompatible(&mut self, remote: ros2_client::dds::rustdds::GUID, requested: &str, offered: &str) {
        if !self.unmatched.insert(remote) {
            return;
        }
        self.counts.qos_incompatible += 1;
        tracing::warn!(
            topic = %self.cfg.topic(),
            "a subscriber requests QoS ({requested}) this route does not offer ({offered}): it gets nothing (counted in summary.json)"
        );
    }

    /// A remote subscriber on the topic, of DDS type `dds_type`; one of another type is counted
    /// once per subscriber.
    pub fn remote_type(&mut self, remote: ros2_client::dds::rustdds::GUID, dds_type: &str) {
        let want = ros2_interop::msgs::dds_type_name(self.cfg.what.ros_type());
        if dds_type != want && self.unmatched.insert(remote) {
            self.counts.type_mismatch += 1;
            tracing::warn!(
                topic = %self.cfg.topic(),
                "a subscriber of type `{dds_type}` on this topic; the route publishes `{want}`: it gets nothing (counted in summary.json)"
            );
        }
    }

    /// Publishes what the translator emitted for this route (and writes it into the bag).
    fn publish(&mut self, e: Emitted, bag: Option<&mut BagSink>) {
        if let Some(bag) = bag {
            let written = e
                .msg
                .encode()
                .map_err(|e| e.to_string())
                .and_then(|b| bag.write(self.cfg.topic(), unix_ns(), b).map_err(|e| e.to_string()));
            if let Err(why) = written {
                self.counts.not_recorded += 1;
                if self.counts.not_recorded == 1 {
                    tracing::warn!(topic = %self.cfg.topic(), "writing the ROS 2 bag failed: {why} (counted in summary.json; warned once)");
                }
            }
            if self.remotes.is_empty() {
                // In the bag, and to nobody on DDS: RustDDS would keep it in the writer's history.
                self.bag_only += 1;
                return;
            }
        }
        let r = match (&self.publisher, e.msg) {
            (OutPub::Odometry(p), RosOut::Odometry(m)) => p.publish(*m).map_err(|e| e.to_string()),
            (OutPub::Pose(p), RosOut::Pose(m)) => p.publish(*m).map_err(|e| e.to_string()),
            (OutPub::Path(p), RosOut::Path(m)) => p.publish(m).map_err(|e| e.to_string()),
            (OutPub::Grid(p), RosOut::Grid(m)) => p.publish(m).map_err(|e| e.to_string()),
            (OutPub::Cloud(p), RosOut::Cloud(m)) => p.publish(m).map_err(|e| e.to_string()),
            (OutPub::Markers(p), RosOut::Markers(m)) => p.publish(m).map_err(|e| e.to_string()),
            (OutPub::Tf(p), RosOut::Tf(m)) => p.publish(m).map_err(|e| e.to_string()),
            (_, m) => {
                self.failed(format!("a message of another type ({m:?})"));
                return;
            }
        };
        match r {
            Ok(()) => {
                self.counts.published += 1;
                if e.source_publish_ns > 0 {
                    self.latency.record_ns(pipeline_runtime::monotonic_ns() as i64 - e.source_publish_ns as i64);
                }
            }
            Err(err) => self.failed(err),
        }
    }

    fn failed(&mut self, e: impl std::fmt::Debug) {
        self.counts.failed += 1;
        if !self.warned {
            self.warned = true;
            tracing::warn!(topic = %self.cfg.topic(), "publishing failed: {e:?} (counted in summary.json; warned once)");
        }
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
    traversability: Option<Input<[TraversabilityCell], OccupancyGridHeader>>,
    landmarks: Option<Input<[Landmark], LandmarkMapHeader>>,
    odometry: Option<Input<PlanarOdometry, MsgHeader>>,
    /// To ask the mapper for a full voxel set.
    commands: Option<Output<ControlCommand, MsgHeader>>,
}

/// Bytes of messages that may wait for the bag writer thread (about 20 of the main job's full
/// voxel clouds); a message beyond is not written and is counted (`bag.refused`).
pub const BAG_QUEUE_BYTES: usize = 256 << 20;

/// The whole `out` direction.
pub struct Outbound {
    /// The routes.
    pub routes: Vec<OutRoute>,
    inputs: OutInputs,
    translator: Translator,
    emitted: Vec<Emitted>,
    /// The ROS 2 bag every out route's messages are also written into (`record_bag`), on a
    /// thread of its own.
    pub bag: Option<BagSink>,
}

impl Outbound {
    /// Opens the routes' publishers and the inputs they need.
    pub fn open(rt: &mut Runtime, node: &mut RosNode, cfg: &[GatewayOut], frames: &Frames) -> Result<Self, StageError> {
        let mut routes = vec![];
        for c in cfg {
            routes.push(OutRoute::new(node, c).map_err(StageError::stage)?);
        }
        let translator = Translator::new(cfg, frames);
        let needs = translator.needs();
        let mut inputs = OutInputs::default();
        if needs.fused {
            inputs.fused = Some(rt.input(FUSION_POSE)?);
        }
        if needs.slam {
            inputs.slam = Some(rt.input(SLAM_POSE)?);
        }
        if needs.grid_pose {
            inputs.grid_pose = Some(rt.input(GRID_SLAM_POSE)?);
        }
        if needs.grid {
            inputs.grid = Some(rt.input(GRID_SLAM_GRID)?);
        }
        if needs.voxels {
            inputs.voxels = Some(rt.input(MAP_VOXELS)?);
            inputs.commands = Some(rt.output::<ControlCommand, MsgHeader>(COMMAND)?);
        }
        if needs.traversability {
            inputs.traversability = Some(rt.input(MAP_TRAVERSABILITY)?);
        }
        if needs.landmarks {
            inputs.landmarks = Some(rt.input(FUSION_MAP)?);
        }
        if needs.odometry {
            inputs.odometry = Some(rt.input(PLANAR_ODOMETRY)?);
        }
        Ok(Self { routes, inputs, translator, emitted: vec![], bag: None })
    }

    /// Records every route's messages into a new ROS 2 bag at `dir` (each topic declared with
    /// the route's type and QoS, and `/tf_static` when `static_tf`), written on a thread of its
    /// own with at most [`BAG_QUEUE_BYTES`] waiting for it.
    pub fn record_into(
        &mut self,
        dir: &std::path::Path,
        compression: BagCompression,
        static_tf: bool,
    ) -> Result<(), ros2_interop::BagError> {
        let mut bag = BagWriter::create_with(dir, compression)?;
        for r in &self.routes {
            bag.add_topic(r.cfg.topic(), r.cfg.what.ros_type(), r.cfg.qos().bag())?;
        }
        if static_tf {
            let latched = ros2_interop::BagQos { reliable: true, transient_local: true, depth: 1 };
            bag.add_topic("/tf_static", ros2_interop::msgs::TFMessage::TYPE_NAME, latched)?;
        }
        self.bag = Some(BagSink::spawn(bag, BAG_QUEUE_BYTES)?);
        Ok(())
    }

    /// True when no route reads the pipeline.
    pub fn is_empty(&self) -> bool {
        self.routes.is_empty()
    }

    /// Pipeline messages read.
    pub fn taken(&self) -> u64 {
        self.translator.taken()
    }

    /// Publishes what the translator emitted.
    fn publish_emitted(&mut self) {
        for e in self.emitted.drain(..) {
            if let Some(r) = self.routes.get_mut(e.route) {
                r.publish(e, self.bag.as_mut());
            }
        }
        for (i, r) in self.routes.iter_mut().enumerate() {
            r.counts.taken = self.translator.route_taken(i);
            r.counts.coalesced = self.translator.route_coalesced(i);
            r.counts.tf_without_odometry = self.translator.route_no_odometry(i);
            r.counts.no_subscriber = self.translator.route_not_emitted_unheard(i) + r.bag_only;
        }
    }

    /// Tells the translator which routes anybody listens to: a route with a matched subscriber,
    /// or every route while a bag is written. A route nobody listens to builds and publishes
    /// nothing (as a ROS node that checks its subscriber count); this also keeps RustDDS from
    /// holding every sample of a writer that has no reader (it frees a writer's history only
    /// as readers acknowledge it).
    fn listeners(&mut self) {
        let bag = self.bag.is_some();
        for (i, r) in self.routes.iter_mut().enumerate() {
            let heard = !r.remotes.is_empty();
            if heard && !r.was_heard {
                self.translator.resend(i);
            }
            r.was_heard = heard;
            self.translator.set_listened(i, bag || heard);
        }
    }

    /// Reads every input and publishes; returns the earliest time a kept snapshot is due.
    pub fn pump(&mut self) -> Result<Option<Instant>, StageError> {
        self.listeners();
        let (t, out) = (&mut self.translator, &mut self.emitted);
        // Odometry first: a pose's `map → odom` needs the odometry of its stamp.
        if let Some(i) = &self.inputs.odometry {
            while let Some(r) = i.receive()? {
                t.odometry(r.user_header().stamp_ns, r.user_header().publish_ns, r.payload(), out);
            }
        }
        if let Some(i) = &self.inputs.fused {
            while let Some(r) = i.receive()? {
                t.fused(r.user_header().stamp_ns, r.user_header().publish_ns, r.payload(), out);
            }
        }
        if let Some(i) = &self.inputs.slam {
            while let Some(r) = i.receive()? {
                t.slam(r.user_header().stamp_ns, r.user_header().publish_ns, r.payload(), out);
            }
        }
        if let Some(i) = &self.inputs.grid_pose {
            while let Some(r) = i.receive()? {
                t.grid_pose(r.user_header().stamp_ns, r.user_header().publish_ns, r.payload(), out);
            }
        }
        if let Some(i) = &self.inputs.grid {
            while let Some(r) = i.receive()? {
                t.grid(r.user_header(), r.payload());
            }
        }
        if let Some(i) = &self.inputs.voxels {
            while let Some(r) = i.receive()? {
                t.voxels(r.user_header(), r.payload());
            }
        }
        if let Some(i) = &self.inputs.traversability {
            while let Some(r) = i.receive()? {
                t.traversability(r.user_header(), r.payload());
            }
        }
        if t.wants_voxel_snapshot()
            && let Some(cmd) = &mut self.inputs.commands
        {
            let now = pipeline_runtime::monotonic_ns();
            cmd.send_value(
                MsgHeader { stamp_ns: now, origin_ns: now, ..Default::default() },
                ControlCommand { target: [0; 32], command: COMMAND_VOXEL_SNAPSHOT, _reserved: 0, arg: 0 },
            )?;
        }
        if let Some(i) = &self.inputs.landmarks {
            while let Some(r) = i.receive()? {
                t.landmarks(r.user_header(), r.payload());
            }
        }
        let next = t.flush(false, out);
        self.publish_emitted();
        Ok(next)
    }

    /// Voxel-stream messages missed (sequence gaps) and deltas left unused waiting for a full set.
    pub fn voxel_gaps(&self) -> (u64, u64) {
        self.translator.voxel_gaps()
    }

    /// Sends every kept snapshot (at the end).
    pub fn flush_all(&mut self) {
        self.translator.flush(true, &mut self.emitted);
        self.publish_emitted();
    }
}
