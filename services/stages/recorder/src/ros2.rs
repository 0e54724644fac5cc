//! The recorder's ROS 2 bag (`[processes.<recorder>.settings.ros2]`): the pipeline's outputs as
//! ROS 2 messages (the `out` routes of [`ros2_interop::out`], the same the `ros2` gateway
//! publishes) written into a rosbag2 bag (MCAP storage, `cdr` encoding, `ros2msg` schemas,
//! `metadata.yaml`), which `ros2 bag info / play` and Python `rosbags` read. No DDS and no network:
//! the bag is made from what the recorder receives over shared memory.
//!
//! A thread of its own turns the received bytes into ROS 2 messages and writes them, so that
//! building snapshots (a voxel cloud) and compression never hold up the recorder's receive loop.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::mpsc::{Receiver, RecvTimeoutError, SyncSender, sync_channel};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use ros2_interop::out::{Emitted, Frames, OutRoute, StaticTransform, Translator};
use ros2_interop::{BagCompression, BagWriter, Message, msgs::TFMessage};
use serde::{Deserialize, Serialize};
use shared_types::services::*;
use shared_types::{
    FusedPose, Landmark, LandmarkMapHeader, MsgHeader, OccupancyCell, OccupancyGridHeader, PlanarOdometry, PlanarPose,
    PoseEstimate, TraversabilityCell, Voxel, VoxelSetHeader, WireType,
};

use crate::error::RecorderError;
use validation::{Issues, Validate};

/// Settings of the recorder's ROS 2 bag.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Ros2Recording {
    /// The bag directory, relative to the run's output directory (or absolute).
    #[serde(default = "default_dir")]
    pub dir: String,
    /// Frame ids of the messages.
    #[serde(default)]
    pub frames: Frames,
    /// The ROS 2 topics written (as the gateway's `out` routes: `what`, `topic`, `qos`,
    /// `max_rate_hz`, `from`, `odom`).
    pub out: Vec<OutRoute>,
    /// Fixed transforms written once on `/tf_static` (the sensor mounts).
    #[serde(default)]
    pub static_transforms: Vec<StaticTransform>,
    /// Chunk compression of the bag: "zstd" (level 1, as `ros2 bag record`), "lz4" or "none".
    #[serde(default)]
    pub compression: BagCompression,
}

fn default_dir() -> String {
    "ros2_bag".into()
}

impl Validate for Ros2Recording {
    fn validate(&self, issues: &mut Issues) {
        issues.check(!self.dir.trim().is_empty(), "dir", "must name a directory");
        issues.check(
            !self.out.is_empty(),
            "out",
            "no routes: list the topics to write (`{ what = \"fused_odometry\" }`, ...)",
        );
        ros2_interop::out::validate(&self.out, &self.frames, &self.static_transforms, &mut Default::default(), issues);
    }
}

impl Ros2Recording {
    /// The pipeline services the routes are made from.
    pub fn services(&self) -> Vec<&'static str> {
        let n = Translator::new(&self.out, &self.frames).needs();
        [
            (n.odometry, PLANAR_ODOMETRY),
            (n.fused, FUSION_POSE),
            (n.slam, SLAM_POSE),
            (n.grid_pose, GRID_SLAM_POSE),
            (n.grid, GRID_SLAM_GRID),
            (n.voxels, MAP_VOXELS),
            (n.traversability, MAP_TRAVERSABILITY),
            (n.landmarks, FUSION_MAP),
        ]
        .into_iter()
        .filter_map(|(needed, s)| needed.then_some(s))
        .collect()
    }

    /// The bag directory of a run with output directory `out_dir`.
    pub fn path(&self, out_dir: &Path) -> PathBuf {
        out_dir.join(&self.dir)
    }
}

/// What the ROS 2 bag got.
#[derive(Debug, Clone, Default, Serialize, serde::Deserialize, schemars::JsonSchema)]
pub struct Ros2Report {
    /// The bag directory.
    pub dir: PathBuf,
    /// Messages written per topic.
    pub messages: BTreeMap<String, u64>,
    /// Pipeline messages turned into ROS 2 messages.
    pub pipeline_messages: u64,
    /// Pipeline messages that could not be read as their service's wire type (lost).
    pub undecodable: u64,
    /// Snapshot updates folded into a later message per topic (not lost).
    pub coalesced: BTreeMap<String, u64>,
    /// `map → odom` transforms not written per `/tf` topic: no odometry at or before the pose's
    /// stamp had come yet.
    pub tf_without_odometry: BTreeMap<String, u64>,
    /// Voxel-stream messages the recorder missed (the cloud restarts at the next full set).
    pub voxel_messages_missed: u64,
    /// Voxel deltas left unused while waiting for a full set.
    pub voxel_deltas_waiting_for_a_full_set: u64,
}

enum Job {
    Message { service: &'static str, unix_ns: u64, data: Vec<u8> },
}

/// The ROS 2 bag writer thread.
pub struct Ros2Sink {
    dir: PathBuf,
    tx: Option<SyncSender<Job>>,
    thread: Option<JoinHandle<Result<Ros2Report, String>>>,
    services: Vec<&'static str>,
}

/// Now, in ns since the Unix epoch (ROS 2 bags' log time).
pub fn unix_ns() -> u64 {
    std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.as_nanos() as u64).unwrap_or(0)
}

impl Ros2Sink {
    /// Creates the bag at `dir` (declaring every route's topic, and `/tf_static` with the mounts)
    /// and starts its thread; at most `queue` messages wait for it.
    pub fn create(dir: &Path, s: &Ros2Recording, queue: usize) -> Result<Self, RecorderError> {
        let bag_err = |e: ros2_interop::BagError| RecorderError::Message {
            service: dir.display().to_string(),
            what: e.to_string(),
        };
        let mut bag = BagWriter::create_with(dir, s.compression).map_err(bag_err)?;
        for r in &s.out {
            bag.add_topic(r.topic(), r.what.ros_type(), r.qos().bag()).map_err(bag_err)?;
        }
        if let Some(tf) = ros2_interop::out::static_tf(&s.static_transforms, &s.out, &s.frames) {
            let latched = ros2_interop::out::TopicQos::MAP.bag();
            bag.add_topic("/tf_static", TFMessage::TYPE_NAME, latched).map_err(bag_err)?;
            let bytes = ros2_interop::cdr::encode(&tf)
                .map_err(|e| RecorderError::Message { service: "/tf_static".into(), what: e.to_string() })?;
            bag.write("/tf_static", unix_ns(), &bytes).map_err(bag_err)?;
        }
        let translator = Translator::new(&s.out, &s.frames);
        let (tx, rx) = sync_channel(queue.max(1));
        let d = dir.to_path_buf();
        let thread =
            std::thread::Builder::new().name("ros2-bag".into()).spawn(move || run(rx, translator, bag, d)).map_err(
                |source| RecorderError::Io { path: dir.to_path_buf(), what: "starting the ROS 2 bag thread", source },
            )?;
        Ok(Self { dir: dir.to_path_buf(), tx: Some(tx), thread: Some(thread), services: s.services() })
    }

    /// The pipeline services it reads.
    pub fn services(&self) -> &[&'static str] {
        &self.services
    }

    /// Queues one received message (header and payload bytes) of `service`, received at
    /// `unix_ns` (waits while the queue is full).
    pub fn write(&self, service: &'static str, unix_ns: u64, data: Vec<u8>) -> Result<(), RecorderError> {
        let gone =
            || RecorderError::Writer { path: self.dir.clone(), what: "the ROS 2 bag thread stopped (see finish)" };
        let tx = self.tx.as_ref().ok_or_else(gone)?;
        tx.send(Job::Message { service, unix_ns, data }).map_err(|_| gone())
    }

    /// Writes the last snapshots, closes the bag (its `metadata.yaml`) and reports.
    pub fn finish(mut self) -> Result<Ros2Report, RecorderError> {
        self.tx = None;
        let thread = self.thread.take().expect("finish runs once");
        match thread.join() {
            Ok(Ok(r)) => Ok(r),
            Ok(Err(what)) => Err(RecorderError::Message { service: self.dir.display().to_string(), what }),
            Err(_) => Err(RecorderError::Writer { path: self.dir.clone(), what: "the ROS 2 bag thread panicked" }),
        }
    }
}

impl Drop for Ros2Sink {
    fn drop(&mut self) {
        self.tx = None;
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

/// `(header, payload bytes)` of a recorded message.
fn split<H: WireType>(data: &[u8]) -> Option<(H, &[u8])> {
    let n = size_of::<H>();
    Some((H::from_bytes(data.get(..n)?)?, &data[n..]))
}

/// The header and a single payload.
fn single<H: WireType, T: WireType>(data: &[u8]) -> Option<(H, T)> {
    let (h, p) = split::<H>(data)?;
    Some((h, T::from_bytes(p)?))
}

/// The header and a slice payload.
fn slice<H: WireType, T: WireType>(data: &[u8]) -> Option<(H, Vec<T>)> {
    let (h, p) = split::<H>(data)?;
    Some((h, shared_types::foxglove::elements::<T>(p)?))
}

/// Feeds one message to the translator; false when its bytes are not its service's type.
fn translate(t: &mut Translator, service: &str, data: &[u8], out: &mut Vec<Emitted>) -> bool {
    let ok = match service {
        PLANAR_ODOMETRY => {
            single::<MsgHeader, PlanarOdometry>(data).map(|(h, p)| t.odometry(h.stamp_ns, h.publish_ns, &p, out))
        }
        FUSION_POSE => single::<MsgHeader, FusedPose>(data).map(|(h, p)| t.fused(h.stamp_ns, h.publish_ns, &p, out)),
        SLAM_POSE => single::<MsgHeader, PoseEstimate>(data).map(|(h, p)| t.slam(h.stamp_ns, h.publish_ns, &p, out)),
        GRID_SLAM_POSE => {
            single::<MsgHeader, PlanarPose>(data).map(|(h, p)| t.grid_pose(h.stamp_ns, h.publish_ns, &p, out))
        }
        GRID_SLAM_GRID => slice::<OccupancyGridHeader, OccupancyCell>(data).map(|(h, c)| t.grid(&h, &c)),
        MAP_VOXELS => slice::<VoxelSetHeader, Voxel>(data).map(|(h, v)| t.voxels(&h, &v)),
        MAP_TRAVERSABILITY => {
            slice::<OccupancyGridHeader, TraversabilityCell>(data).map(|(h, c)| t.traversability(&h, &c))
        }
        FUSION_MAP => slice::<LandmarkMapHeader, Landmark>(data).map(|(h, l)| t.landmarks(&h, &l)),
        _ => None,
    };
    ok.is_some()
}

fn run(rx: Receiver<Job>, mut t: Translator, mut bag: BagWriter, dir: PathBuf) -> Result<Ros2Report, String> {
    let mut report = Ros2Report { dir, ..Default::default() };
    let mut out = vec![];
    let topics: Vec<String> = t.routes().iter().map(|r| r.topic().to_string()).collect();
    let mut write = |out: &mut Vec<Emitted>, unix_ns: u64| -> Result<(), String> {
        for e in out.drain(..) {
            let bytes = e.msg.encode().map_err(|e| format!("encoding: {e}"))?;
            bag.write(&topics[e.route], unix_ns, &bytes).map_err(|e| e.to_string())?;
        }
        Ok(())
    };
    let mut next_due: Option<Instant> = None;
    loop {
        let wait = next_due.map_or(Duration::from_millis(500), |d| d.saturating_duration_since(Instant::now()));
        match rx.recv_timeout(wait) {
            Ok(Job::Message { service, unix_ns, data }) => {
                if translate(&mut t, service, &data, &mut out) {
                    report.pipeline_messages += 1;
                } else {
                    report.undecodable += 1;
                    if report.undecodable == 1 {
                        tracing::warn!(
                            service,
                            bytes = data.len(),
                            "ROS 2 bag: a message is not its service's wire type (counted in summary.json; warned once)"
                        );
                    }
                }
                write(&mut out, unix_ns)?;
            }
            Err(RecvTimeoutError::Timeout) => {}
            Err(RecvTimeoutError::Disconnected) => break,
        }
        next_due = t.flush(false, &mut out);
        write(&mut out, unix_ns())?;
    }
    t.flush(true, &mut out);
    write(&mut out, unix_ns())?;
    bag.finish().map_err(|e| e.to_string())?;
    report.messages = bag.counts();
    for (i, topic) in t.routes().iter().map(|r| r.topic().to_string()).enumerate() {
        let c = t.route_coalesced(i);
        if c > 0 {
            report.coalesced.insert(topic.clone(), c);
        }
        let n = t.route_no_odometry(i);
        if n > 0 {
            report.tf_without_odometry.insert(topic, n);
        }
    }
    (report.voxel_messages_missed, report.voxel_deltas_waiting_for_a_full_set) = t.voxel_gaps();
    Ok(report)
}

#[cfg(test)]
mod tests {
    use super::*;
    use ros2_interop::BagReader;
    use ros2_interop::msgs::{Odometry, Path as RosPath};
    use ros2_interop::out::OutKind;
    use shared_types::FUSED_REFINED;

    fn bytes<H: WireType, T: WireType>(h: &H, p: &T) -> Vec<u8> {
        let mut v = h.as_bytes().to_vec();
        v.extend_from_slice(p.as_bytes());
        v
    }

    #[test]
    fn fused_poses_become_odometry_a_path_and_tf_in_a_bag_rosbags_layout() {
        let dir = tempfile::tempdir().unwrap();
        let bag_dir = dir.path().join("bag");
        let s: Ros2Recording = toml::from_str(
            r#"
out = [{ what = "fused_odometry" }, { what = "fused_path" }, { what = "tf" }]
static_transforms = [{ parent = "base_link", child = "cam", xyz_m = [0.5, 0.0, 0.0] }]
"#,
        )
        .unwrap();
        assert!(s.issues().is_empty(), "{}", s.issues());
        assert_eq!(s.services(), [FUSION_POSE]);
        let sink = Ros2Sink::create(&bag_dir, &s, 16).unwrap();
        for k in 0..10u64 {
            let mut p = FusedPose::default();
            p.pose.position_m = [k as f64, 0.0, -2.0];
            p.pose.orientation_xyzw = [0.0, 0.0, 0.0, 1.0];
            p.pose.frame = 3;
            p.flags = FUSED_REFINED;
            let h = MsgHeader { stamp_ns: 1_000 + k, seq: k, ..Default::default() };
            sink.write(FUSION_POSE, unix_ns(), bytes(&h, &p)).unwrap();
        }
        sink.write(FUSION_POSE, unix_ns(), vec![1, 2, 3]).unwrap();
        let r = sink.finish().unwrap();
        assert_eq!((r.pipeline_messages, r.undecodable), (10, 1));
        assert_eq!(r.messages["/slam/fused/odometry"], 10);
        assert_eq!(r.messages["/tf"], 10);
        assert_eq!(r.messages["/tf_static"], 1);
        let paths = r.messages["/slam/fused/path"];
        assert!((1..=10).contains(&paths), "{paths}");
        assert!(bag_dir.join("metadata.yaml").exists());
        let mut reader = BagReader::open(&bag_dir).unwrap();
        let (mut odo, mut last_path) = (vec![], None);
        while let Some(m) = reader.next_message().unwrap() {
            match &*m.topic {
                "/slam/fused/odometry" => odo.push(ros2_interop::decode::<Odometry>(&m.data, "Odometry").unwrap()),
                "/slam/fused/path" => last_path = Some(ros2_interop::decode::<RosPath>(&m.data, "Path").unwrap()),
                _ => {}
            }
        }
        assert_eq!(odo.len(), 10);
        assert_eq!(odo[9].pose.pose.position.x, 9.0);
        assert_eq!(odo[9].header.frame_id, "map");
        assert_eq!(last_path.unwrap().poses.len(), 10, "the last path holds every pose");
    }

    #[test]
    fn a_recording_without_routes_or_with_a_bad_topic_is_refused_by_key() {
        let s: Ros2Recording = toml::from_str("out = []").unwrap();
        assert_eq!(s.issues().into_vec()[0].key, "out");
        let s: Ros2Recording = toml::from_str("out = [{ what = \"map\", topic = \"no spaces\" }]").unwrap();
        assert_eq!(s.issues().into_vec()[0].key, "out[0].topic");
        let e = toml::from_str::<Ros2Recording>("out = [{ what = \"maps\" }]").unwrap_err();
        assert!(e.to_string().contains("maps"), "{e}");
        assert_eq!(
            toml::from_str::<Ros2Recording>("out = [{ what = \"voxels\" }, { what = \"map\" }]").unwrap().services(),
            [GRID_SLAM_GRID, MAP_VOXELS]
        );
        let _ = OutKind::Map;
    }
}
