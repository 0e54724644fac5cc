//! The recorder's settings and its MCAP sink: a writer thread that owns the [`mcap::Writer`], so
//! that compression and disk writes never hold up the receive loop, with one channel per service
//! (topic = service name), one schema per wire type, metadata, chunk indexes and a summary
//! section, and optional JSON mirror channels of the small estimates for Foxglove's plots.

use crate::error::RecorderError;
use std::collections::{BTreeMap, BTreeSet};
use std::io::BufWriter;
use std::path::{Path, PathBuf};
use std::sync::mpsc::{Receiver, RecvTimeoutError, SyncSender, sync_channel};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use pipeline_runtime::Validate;
use pipeline_runtime::{Issues, ProcessSettings};
use serde::{Deserialize, Serialize};
use shared_types::services;
use shared_types::{BuoyFix, FusedPose, MsgHeader, PoseEstimate, WireType};

use wire_topics::{TOPICS, Topic, topic};

/// MCAP schema encoding of the wire types: the schema data is the JSON layout description of
/// [`Topic::schema_json`].
pub const SCHEMA_ENCODING: &str = "slam_pipeline.wire_layout.v1+json";
/// MCAP message encoding: the user header's bytes followed by the payload's bytes (`repr(C)`).
pub const MESSAGE_ENCODING: &str = "slam_pipeline.repr_c.v1";
/// Suffix of the JSON mirror channels (`pipeline/slam/pose/json`, ...).
pub const JSON_SUFFIX: &str = "/json";

/// Chunk compression of the MCAP file.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Compression {
    /// zstd (default): the smaller file.
    Zstd,
    /// LZ4: faster, larger.
    Lz4,
    /// Uncompressed chunks.
    None,
}

/// Settings of the `recorder` process.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RecorderSettings {
    /// The MCAP file, relative to the run's output directory (or absolute).
    pub file: String,
    /// Services to record; empty = every data service of the contract plus end of stream and
    /// commands (everything but heartbeats and statistics).
    pub services: Vec<String>,
    /// Services not to record (e.g. the big `pipeline/sensors/cloud`, `pipeline/map/voxels`).
    pub exclude: Vec<String>,
    /// Processes whose end of stream ends the recording: once all have ended, the recorder
    /// drains what they sent and writes the file. Empty: record until SIGTERM/SIGINT.
    pub end_after: Vec<String>,
    /// Send our own end of stream once the file is written (after `end_after`), so that a run
    /// can end on the recorder (`run.end_of_stream_from = ["<recorder>"]`).
    pub send_end_of_stream: bool,
    /// Chunk compression: "zstd", "lz4" or "none".
    pub compression: Compression,
    /// Uncompressed size at which a chunk is closed, KiB.
    pub chunk_size_kib: u64,
    /// Close the open chunk at least this often, s, so that a killed recorder leaves a file that
    /// can be recovered up to then (0 = only by size).
    pub flush_interval_s: f64,
    /// Messages queued between the receive loop and the writer thread; when full, the loop waits
    /// (the contract's queues then absorb, or back-pressure reaches a replaying source).
    pub queue_messages: usize,
    /// Also write `<service>/json` channels (JSON schema, `json` encoding) for the slam pose,
    /// buoy fix and fused pose, which Foxglove can plot.
    pub json_mirror: bool,
    /// Also write channels with Foxglove's own schemas (protobuf) next to the raw ones, so that
    /// Foxglove's 3D panel shows the recording: poses (`/slam/pose`, `/buoy/pose`, `/fused/pose`,
    /// `/grid_slam/pose`), `/cloud`, `/slam/landmarks`, `/landmarks`, `/octree` (the full voxel
    /// sets) and `/grid` (see `shared_types::foxglove::mirror_of`).
    pub foxglove_channels: bool,
    /// Also write the pipeline's outputs as ROS 2 messages into a rosbag2 bag (MCAP storage,
    /// `cdr`; `ros2 bag info / play` and Python `rosbags` read it): `[...settings.ros2]` with
    /// `dir` (default `ros2_bag`, under the run's output directory), `out` routes as the `ros2`
    /// gateway's (docs/ros2.md), `frames` and `static_transforms`. The services the routes
    /// are made from are read whether or not they are recorded into the MCAP file.
    pub ros2: Option<crate::ros2::Ros2Recording>,
}

impl Default for RecorderSettings {
    fn default() -> Self {
        Self {
            file: "recording.mcap".into(),
            services: vec![],
            exclude: vec![],
            end_after: vec![],
            send_end_of_stream: false,
            compression: Compression::Zstd,
            chunk_size_kib: 1024,
            flush_interval_s: 1.0,
            queue_messages: 1024,
            json_mirror: true,
            foxglove_channels: true,
            ros2: None,
        }
    }
}

impl ProcessSettings for RecorderSettings {
    fn shm_estimate_bytes(&self, _extra_subscribers: usize) -> u64 {
        0 // subscribers only: the publishers reserve the shared memory
    }
}

impl Validate for RecorderSettings {
    fn validate(&self, issues: &mut Issues) {
        issues.check(!self.file.trim().is_empty(), "file", "must name a file");
        for (field, list) in [("services", &self.services), ("exclude", &self.exclude)] {
            for (i, s) in list.iter().enumerate() {
                issues.check(
                    topic(s).is_some(),
                    format!("{field}[{i}]"),
                    format!(
                        "`{s}` is not a recordable service (one of: {})",
                        TOPICS.iter().map(|t| t.service).collect::<Vec<_>>().join(", ")
                    ),
                );
            }
        }
        issues.check((1..=1 << 20).contains(&self.chunk_size_kib), "chunk_size_kib", "must be 1..=1048576");
        issues.check(
            self.flush_interval_s.is_finite() && self.flush_interval_s >= 0.0,
            "flush_interval_s",
            "must be >= 0",
        );
        issues.check((1..=1 << 20).contains(&self.queue_messages), "queue_messages", "must be 1..=1048576");
        issues.check(
            !self.send_end_of_stream || !self.end_after.is_empty(),
            "send_end_of_stream",
            "needs `end_after` (without it the recording ends only on a signal)",
        );
        if let Some(r) = &self.ros2 {
            issues.nested("ros2", r);
        }
    }
}

impl RecorderSettings {
    /// The topics to record, in contract order.
    pub fn topics(&self) -> Vec<&'static Topic> {
        let exclude: BTreeSet<&str> = self.exclude.iter().map(String::as_str).collect();
        TOPICS
            .iter()
            .filter(|t| {
                if self.services.is_empty() { t.default_recorded } else { self.services.iter().any(|s| s == t.service) }
            })
            .filter(|t| !exclude.contains(t.service))
            .collect()
    }

    /// The MCAP file of a run with output directory `out_dir`.
    pub fn path(&self, out_dir: &Path) -> PathBuf {
        out_dir.join(&self.file)
    }
}

/// What the writer thread wrote.
#[derive(Debug, Clone, Default, Serialize)]
pub struct SinkReport {
    /// Messages written per topic (JSON mirrors not counted).
    pub messages: BTreeMap<String, u64>,
    /// Message bytes written per topic (before compression).
    pub bytes: BTreeMap<String, u64>,
    /// Size of the finished file, bytes.
    pub file_bytes: u64,
    /// Chunks written.
    pub chunks: u64,
    /// Most messages waiting for the writer thread at once.
    pub max_queued: usize,
    /// log_time of the first and last message, ns.
    pub log_time_range_ns: Option<(u64, u64)>,
    /// Messages written per Foxglove-schema channel (by topic).
    pub foxglove_messages: BTreeMap<String, u64>,
}

enum Job {
    Message { topic: usize, log_time: u64, publish_time: u64, data: Vec<u8> },
    Metadata(mcap::records::Metadata),
}

/// Options of the MCAP file.
#[derive(Debug, Clone)]
pub struct SinkOptions {
    /// Chunk compression.
    pub compression: Compression,
    /// Chunk size, bytes.
    pub chunk_size: u64,
    /// Close the open chunk at least this often (None: only by size).
    pub flush_interval: Option<Duration>,
    /// Queue length between the caller and the writer thread.
    pub queue: usize,
    /// Write JSON mirror channels.
    pub json_mirror: bool,
    /// Write Foxglove-schema channels.
    pub foxglove_channels: bool,
}

/// An MCAP file being written by a writer thread.
pub struct McapSink {
    path: PathBuf,
    tx: Option<SyncSender<Job>>,
    queued: std::sync::Arc<std::sync::atomic::AtomicUsize>,
    thread: Option<JoinHandle<Result<SinkReport, RecorderError>>>,
}

impl McapSink {
    /// Creates `path` with a schema and a channel for every topic of `topics` (in this order:
    /// [`McapSink::write`] takes the index) and the `metadata` record named `slam_pipeline`.
    pub fn create(
        path: &Path,
        topics: &[&'static Topic],
        options: &SinkOptions,
        metadata: BTreeMap<String, String>,
    ) -> Result<Self, RecorderError> {
        let io = |what| move |source| RecorderError::Io { path: path.to_path_buf(), what, source };
        let mcap_err = |source| RecorderError::Mcap { path: path.to_path_buf(), source };
        if let Some(dir) = path.parent() {
            std::fs::create_dir_all(dir).map_err(io("creating its directory"))?;
        }
        let file = std::fs::File::create(path).map_err(io("creating"))?;
        let compression = match options.compression {
            Compression::Zstd => Some(mcap::Compression::Zstd),
            Compression::Lz4 => Some(mcap::Compression::Lz4),
            Compression::None => None,
        };
        let mut writer = mcap::WriteOptions::new()
            .compression(compression)
            .compression_threads(0)
            .chunk_size(Some(options.chunk_size))
            .profile("")
            .library(format!("slam_pipeline recorder {}", env!("CARGO_PKG_VERSION")))
            .create(BufWriter::new(file))
            .map_err(mcap_err)?;
        let mut channels = vec![];
        let mut mirrors = vec![];
        let mut foxglove = vec![];
        for t in topics {
            let schema = serde_json::to_vec_pretty(&t.schema_json())?;
            let schema_id = writer.add_schema(t.payload_type_name(), SCHEMA_ENCODING, &schema).map_err(mcap_err)?;
            let meta = BTreeMap::from([
                ("user_header".to_string(), (t.header)().type_name.to_string()),
                ("payload".to_string(), t.payload_type_name().to_string()),
                ("payload_is_slice".to_string(), t.slice.to_string()),
            ]);
            channels.push(writer.add_channel(schema_id, t.service, MESSAGE_ENCODING, &meta).map_err(mcap_err)?);
            let mirror = match json_schema(t.service) {
                Some((name, schema)) if options.json_mirror => {
                    let sid = writer
                        .add_schema(name, "jsonschema", serde_json::to_string(&schema)?.as_bytes())
                        .map_err(mcap_err)?;
                    Some(
                        writer
                            .add_channel(sid, &format!("{}{JSON_SUFFIX}", t.service), "json", &BTreeMap::new())
                            .map_err(mcap_err)?,
                    )
                }
                _ => None,
            };
            mirrors.push(mirror);
            let fox = match shared_types::foxglove::mirror_of(t.service) {
                Some(m) if options.foxglove_channels => {
                    let sid =
                        writer.add_schema(&m.schema.name, &m.schema.encoding, &m.schema.data).map_err(mcap_err)?;
                    Some((
                        m.topic,
                        writer.add_channel(sid, m.topic, &m.message_encoding, &BTreeMap::new()).map_err(mcap_err)?,
                    ))
                }
                _ => None,
            };
            foxglove.push(fox);
        }
        writer.write_metadata(&mcap::records::Metadata { name: "slam_pipeline".into(), metadata }).map_err(mcap_err)?;
        let services: Vec<&'static str> = topics.iter().map(|t| t.service).collect();
        let (tx, rx) = sync_channel(options.queue);
        let queued = std::sync::Arc::new(std::sync::atomic::AtomicUsize::new(0));
        let q = queued.clone();
        let flush_interval = options.flush_interval;
        let p = path.to_path_buf();
        let thread = std::thread::Builder::new()
            .name("mcap-writer".into())
            .spawn(move || write_loop(writer, rx, &services, &channels, &mirrors, &foxglove, flush_interval, &q, &p))
            .map_err(io("starting the writer thread of"))?;
        Ok(Self { path: path.to_path_buf(), tx: Some(tx), queued, thread: Some(thread) })
    }

    /// The file.
    pub fn path(&self) -> &Path {
        &self.path
    }

    fn writer_error(&self, what: &'static str) -> RecorderError {
        RecorderError::Writer { path: self.path.clone(), what }
    }

    fn send(&self, job: Job) -> Result<(), RecorderError> {
        let tx = self.tx.as_ref().ok_or_else(|| self.writer_error("already finished"))?;
        self.queued.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        tx.send(job).map_err(|_| self.writer_error("the writer thread stopped (see finish)"))
    }

    /// Queues one message of topic index `topic` (waits while the queue is full).
    pub fn write(&self, topic: usize, log_time: u64, publish_time: u64, data: Vec<u8>) -> Result<(), RecorderError> {
        self.send(Job::Message { topic, log_time, publish_time, data })
    }

    /// Queues a metadata record.
    pub fn metadata(&self, name: &str, metadata: BTreeMap<String, String>) -> Result<(), RecorderError> {
        self.send(Job::Metadata(mcap::records::Metadata { name: name.into(), metadata }))
    }

    /// Writes everything queued, the summary section and the footer, and closes the file.
    pub fn finish(mut self) -> Result<SinkReport, RecorderError> {
        self.tx.take();
        let thread = self.thread.take().ok_or_else(|| self.writer_error("already finished"))?;
        thread.join().map_err(|_| self.writer_error("the writer thread panicked"))?
    }
}

impl Drop for McapSink {
    fn drop(&mut self) {
        self.tx.take();
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

#[allow(clippy::too_many_arguments)]
fn write_loop(
    mut writer: mcap::Writer<BufWriter<std::fs::File>>,
    rx: Receiver<Job>,
    services: &[&'static str],
    channels: &[u16],
    mirrors: &[Option<u16>],
    foxglove: &[Option<(&'static str, u16)>],
    flush_interval: Option<Duration>,
    queued: &std::sync::atomic::AtomicUsize,
    path: &Path,
) -> Result<SinkReport, RecorderError> {
    let mut report = SinkReport::default();
    let mut sequence = vec![0u32; channels.len()];
    let mut mirror_sequence = vec![0u32; channels.len()];
    let mut foxglove_sequence = vec![0u32; channels.len()];
    let mut last_flush = Instant::now();
    let mut unflushed = false;
    let wait = flush_interval.unwrap_or(Duration::from_secs(3600));
    let err = |source: mcap::McapError| RecorderError::Mcap { path: path.to_path_buf(), source };
    let io = |what| move |source| RecorderError::Io { path: path.to_path_buf(), what, source };
    loop {
        let job = match rx.recv_timeout(wait.saturating_sub(last_flush.elapsed()).max(Duration::from_millis(1))) {
            Ok(job) => Some(job),
            Err(RecvTimeoutError::Timeout) => None,
            Err(RecvTimeoutError::Disconnected) => break,
        };
        if let Some(job) = job {
            let depth = queued.fetch_sub(1, std::sync::atomic::Ordering::Relaxed);
            report.max_queued = report.max_queued.max(depth);
            match job {
                Job::Message { topic, log_time, publish_time, data } => {
                    let (Some(&channel_id), Some(service)) = (channels.get(topic), services.get(topic)) else {
                        return Err(RecorderError::Writer {
                            path: path.to_path_buf(),
                            what: "a message for an unknown topic",
                        });
                    };
                    let header =
                        mcap::records::MessageHeader { channel_id, sequence: sequence[topic], log_time, publish_time };
                    sequence[topic] = sequence[topic].wrapping_add(1);
                    writer.write_to_known_channel(&header, &data).map_err(err)?;
                    if let Some(Some(mirror)) = mirrors.get(topic)
                        && let Some(json) = json_of(service, &data)
                    {
                        let h = mcap::records::MessageHeader {
                            channel_id: *mirror,
                            sequence: mirror_sequence[topic],
                            ..header
                        };
                        mirror_sequence[topic] = mirror_sequence[topic].wrapping_add(1);
                        writer.write_to_known_channel(&h, json.to_string().as_bytes()).map_err(err)?;
                    }
                    if let Some(Some((fox_topic, fox_channel))) = foxglove.get(topic)
                        && let Some(bytes) = shared_types::foxglove::encode_recorded(service, &data)
                    {
                        let h = mcap::records::MessageHeader {
                            channel_id: *fox_channel,
                            sequence: foxglove_sequence[topic],
                            // The raw message's log and publish times.
                            ..header
                        };
                        foxglove_sequence[topic] = foxglove_sequence[topic].wrapping_add(1);
                        writer.write_to_known_channel(&h, &bytes).map_err(err)?;
                        *report.foxglove_messages.entry(fox_topic.to_string()).or_default() += 1;
                    }
                    *report.messages.entry(service.to_string()).or_default() += 1;
                    *report.bytes.entry(service.to_string()).or_default() += data.len() as u64;
                    report.log_time_range_ns = Some(
                        report
                            .log_time_range_ns
                            .map_or((log_time, log_time), |(a, b)| (a.min(log_time), b.max(log_time))),
                    );
                    unflushed = true;
                }
                Job::Metadata(m) => writer.write_metadata(&m).map_err(err)?,
            }
        }
        if unflushed && flush_interval.is_some() && last_flush.elapsed() >= wait {
            writer.flush().map_err(err)?;
            unflushed = false;
            last_flush = Instant::now();
        }
    }
    let summary = writer.finish().map_err(err)?;
    report.chunks = summary.chunk_indexes.len() as u64;
    let mut inner = writer.into_inner();
    std::io::Write::flush(&mut inner).map_err(io("writing"))?;
    let file = inner.into_inner().map_err(|e| io("writing")(e.into_error()))?;
    file.sync_all().map_err(io("syncing"))?;
    report.file_bytes = file.metadata().map(|m| m.len()).unwrap_or(0);
    Ok(report)
}

fn xyz(v: &[f64]) -> serde_json::Value {
    serde_json::json!({ "x": v[0], "y": v[1], "z": v[2] })
}

fn sigma3(cov: &[f64], stride: usize) -> serde_json::Value {
    let s = |i: usize| cov[i * stride + i].max(0.0).sqrt();
    serde_json::json!({ "x": s(0), "y": s(1), "z": s(2) })
}

fn pose_json(h: &MsgHeader, p: &PoseEstimate) -> serde_json::Value {
    let q = &p.orientation_xyzw;
    serde_json::json!({
        "stamp_ns": h.stamp_ns, "seq": h.seq,
        "position": xyz(&p.position_m),
        "orientation": { "x": q[0], "y": q[1], "z": q[2], "w": q[3] },
        "position_sigma": sigma3(&p.covariance, 6),
        "segment_id": p.segment_id, "frame": p.frame,
    })
}

/// The JSON mirror of a recorded message of the slam pose, buoy fix or fused pose (None for other
/// services, or bytes that are not such a message).
pub fn json_of(service: &str, data: &[u8]) -> Option<serde_json::Value> {
    let h = MsgHeader::from_bytes(data.get(..32)?)?;
    let payload = &data[32..];
    Some(match service {
        services::SLAM_POSE => pose_json(&h, &PoseEstimate::from_bytes(payload)?),
        services::FUSION_POSE => {
            let f = FusedPose::from_bytes(payload)?;
            let mut v = pose_json(&h, &f.pose);
            v["flags"] = f.flags.into();
            v
        }
        services::BUOY_FIX => {
            let f = BuoyFix::from_bytes(payload)?;
            serde_json::json!({
                "stamp_ns": h.stamp_ns, "seq": h.seq,
                "position": xyz(&f.position_m), "position_sigma": sigma3(&f.covariance_m2, 3),
                "velocity": xyz(&f.velocity_mps),
                "ranges_used": f.ranges_used, "ranges_rejected": f.ranges_rejected,
            })
        }
        _ => return None,
    })
}

fn json_schema(service: &str) -> Option<(&'static str, serde_json::Value)> {
    let num = serde_json::json!({ "type": "number" });
    let int = serde_json::json!({ "type": "integer" });
    let vec3 = serde_json::json!({ "type": "object", "properties": { "x": num, "y": num, "z": num } });
    let quat = serde_json::json!({ "type": "object", "properties": { "x": num, "y": num, "z": num, "w": num } });
    let pose_props = serde_json::json!({
        "stamp_ns": int, "seq": int, "position": vec3, "orientation": quat, "position_sigma": vec3,
        "segment_id": int, "frame": int,
    });
    let (name, props) = match service {
        services::SLAM_POSE => ("slam_pipeline.json.PoseEstimate", pose_props),
        services::FUSION_POSE => {
            let mut p = pose_props;
            p["flags"] = int;
            ("slam_pipeline.json.FusedPose", p)
        }
        services::BUOY_FIX => (
            "slam_pipeline.json.BuoyFix",
            serde_json::json!({
                "stamp_ns": int, "seq": int, "position": vec3, "position_sigma": vec3, "velocity": vec3,
                "ranges_used": int, "ranges_rejected": int,
            }),
        ),
        _ => return None,
    };
    Some((name, serde_json::json!({ "type": "object", "properties": props })))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn default_topics_are_the_data_services_end_of_stream_and_commands_minus_exclusions() {
        let s = RecorderSettings { exclude: vec![services::CLOUD.into()], ..Default::default() };
        let names: Vec<_> = s.topics().iter().map(|t| t.service).collect();
        assert!(names.contains(&services::ODOMETRY) && names.contains(&services::END_OF_STREAM));
        assert!(!names.contains(&services::CLOUD) && !names.contains(&services::HEARTBEAT));
        let only = RecorderSettings { services: vec![services::BUOY_FIX.into()], ..Default::default() };
        assert_eq!(only.topics().len(), 1);
    }

    #[test]
    fn unknown_services_are_named_with_their_key() {
        let s = RecorderSettings { exclude: vec!["pipeline/nope".into()], ..Default::default() };
        let mut issues = Issues::at("processes.rec.settings");
        s.validate(&mut issues);
        assert_eq!(issues.len(), 1);
        assert_eq!(issues.iter().next().unwrap().key, "processes.rec.settings.exclude[0]");
    }

    #[test]
    fn a_written_file_reads_back_with_every_message_bit_exact() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("t.mcap");
        let topics = vec![topic(services::BUOY_FIX).unwrap(), topic(services::BUOY_RANGES).unwrap()];
        let opts = SinkOptions {
            compression: Compression::Zstd,
            chunk_size: 256,
            flush_interval: None,
            queue: 4,
            json_mirror: true,
            foxglove_channels: true,
        };
        let sink = McapSink::create(&path, &topics, &opts, BTreeMap::from([("k".into(), "v".into())])).unwrap();
        let mut sent = vec![];
        for i in 0..50u64 {
            let h = MsgHeader { stamp_ns: i, seq: i, origin_ns: 1, publish_ns: 100 + i };
            let fix = BuoyFix { position_m: [i as f64, 1.0, 2.0], ..Default::default() };
            let data = [h.as_bytes(), fix.as_bytes()].concat();
            sink.write(0, 1000 + i, 100 + i, data.clone()).unwrap();
            sent.push(data);
        }
        let report = sink.finish().unwrap();
        assert_eq!(report.messages[services::BUOY_FIX], 50);
        assert!(report.chunks > 1);
        let bytes = std::fs::read(&path).unwrap();
        let summary = mcap::Summary::read(&bytes).unwrap().expect("summary section");
        assert!(!summary.chunk_indexes.is_empty());
        let mut got = vec![];
        let mut json = 0;
        for m in mcap::MessageStream::new(&bytes).unwrap() {
            let m = m.unwrap();
            if m.channel.topic == services::BUOY_FIX {
                assert_eq!(m.channel.schema.as_ref().unwrap().name, BuoyFix::TYPE_NAME);
                got.push(m.data.into_owned());
            } else if m.channel.topic == format!("{}{JSON_SUFFIX}", services::BUOY_FIX) {
                let v: serde_json::Value = serde_json::from_slice(&m.data).unwrap();
                assert_eq!(v["position"]["x"].as_f64(), Some(json as f64));
                json += 1;
            }
        }
        assert_eq!(got, sent);
        assert_eq!(json, 50);
    }
}
