//! The replayer's settings and its pure part: reading a recording, checking every selected
//! message against its topic's schema and size, and handing the messages out in the order they
//! were originally published.
//!
//! Order: the recorder writes messages in the order it *received* them, service by service per
//! wake-up, which is not the order in which they were published across services. The replay
//! order is the original publish order (MCAP `publish_time` = the message's `publish_ns`,
//! CLOCK_MONOTONIC of one machine), ties broken by file order. A first pass ([`scan`]) checks the
//! whole file and computes the rank of every selected message; the second pass ([`Replay`])
//! streams the file again and holds back the few messages that were received before their turn.
//! Both passes are pure functions of the file and the settings, so every replay of a file sends
//! the same messages in the same order.

use std::collections::{BTreeMap, BTreeSet};
use std::fs::File;
use std::io::BufReader;
use std::path::{Path, PathBuf};

use pipeline_runtime::Validate;
use pipeline_runtime::{Issues, ProcessSettings};
use serde::{Deserialize, Serialize};
use shared_types::services::{self, service_spec};
use shared_types::{EndOfStream, WireType, name_from32};

use crate::record::{MESSAGE_ENCODING, SCHEMA_ENCODING};
use wire_topics::{TOPICS, Topic, topic};

/// Settings of the `replayer` process.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ReplayerSettings {
    /// The MCAP recording, relative to the config file (or absolute).
    pub file: String,
    /// Topics (services) to publish; empty = every recorded topic except heartbeats. Recorded
    /// ends of stream of processes that are part of this config are never replayed (those
    /// processes send their own).
    pub topics: Vec<String>,
    /// 0 = as fast as possible with back-pressure (publishers wait for full subscriber queues);
    /// 1 = the recorded pace (original publish times); N = N× faster.
    pub speed: f64,
    /// With speed 0: longest wait for one subscriber before a message is dropped for it
    /// (counted as `undelivered`), s; 0 = as long as the subscriber's process is alive.
    pub backpressure_max_wait_s: f64,
    /// Wait after creating the publishers before the first message, s (subscribers attach).
    pub connect_grace_s: f64,
    /// Send our own end of stream after the last message.
    pub send_end_of_stream: bool,
}

impl Default for ReplayerSettings {
    fn default() -> Self {
        Self {
            file: String::new(),
            topics: vec![],
            speed: 0.0,
            backpressure_max_wait_s: 0.0,
            connect_grace_s: 1.0,
            send_end_of_stream: true,
        }
    }
}

impl ProcessSettings for ReplayerSettings {
    fn shm_estimate_bytes(&self, extra_subscribers: usize) -> u64 {
        let names: Vec<&str> = if self.topics.is_empty() {
            TOPICS.iter().map(|t| t.service).collect()
        } else {
            self.topics.iter().map(String::as_str).collect()
        };
        names
            .iter()
            .filter_map(|n| Some((topic(n)?, service_spec(n)?)))
            .map(|(t, s)| {
                let chunk = t.header_size() + t.payload_size() * s.qos.initial_slice_len.max(1);
                (chunk.next_power_of_two() * s.qos.with_extra(extra_subscribers).chunks_per_publisher()) as u64
            })
            .sum()
    }
}

impl Validate for ReplayerSettings {
    fn validate(&self, issues: &mut Issues) {
        issues.check(!self.file.trim().is_empty(), "file", "must name the MCAP recording");
        for (i, s) in self.topics.iter().enumerate() {
            issues.check(topic(s).is_some(), format!("topics[{i}]"), format!("`{s}` is not a replayable service"));
        }
        issues.check(self.speed.is_finite() && self.speed >= 0.0, "speed", "must be >= 0");
        issues.check(
            self.backpressure_max_wait_s.is_finite() && self.backpressure_max_wait_s >= 0.0,
            "backpressure_max_wait_s",
            "must be >= 0",
        );
        issues.check(
            self.connect_grace_s.is_finite() && self.connect_grace_s >= 0.0,
            "connect_grace_s",
            "must be >= 0",
        );
    }
}

impl ReplayerSettings {
    /// The recording, resolved against the config file's directory.
    pub fn path(&self, config_dir: &Path) -> PathBuf {
        config_dir.join(&self.file)
    }
}

/// Errors of reading a recording. Each names the file (and the topic where there is one).
#[derive(Debug, thiserror::Error)]
pub enum ReplayError {
    /// The file cannot be opened.
    #[error("{file}: cannot open the recording: {reason}")]
    Open {
        /// The file.
        file: PathBuf,
        /// Why.
        reason: String,
    },
    /// The file is not a complete MCAP file (truncated, corrupt).
    #[error("{file}: not a valid MCAP recording after {messages} messages: {reason}")]
    Corrupt {
        /// The file.
        file: PathBuf,
        /// Messages read before the error.
        messages: u64,
        /// The MCAP reader's reason.
        reason: String,
    },
    /// A selected topic is not in the recording.
    #[error("{file}: topic `{topic}` is not in the recording (it has: {present})")]
    MissingTopic {
        /// The file.
        file: PathBuf,
        /// The topic.
        topic: String,
        /// The topics it has.
        present: String,
    },
    /// A topic's channel has a schema or encoding other than the wire type of the service.
    #[error("{file}: topic `{topic}`: {what} is `{found}`, expected `{expected}`")]
    Schema {
        /// The file.
        file: PathBuf,
        /// The topic.
        topic: String,
        /// What differs (schema name, schema encoding, message encoding).
        what: &'static str,
        /// What the file has.
        found: String,
        /// What the service needs.
        expected: String,
    },
    /// A message's size does not fit the topic's wire types.
    #[error("{file}: topic `{topic}`, message {index} of the topic: {reason}")]
    Size {
        /// The file.
        file: PathBuf,
        /// The topic.
        topic: String,
        /// Index of the message within its topic.
        index: u64,
        /// What is wrong.
        reason: String,
    },
    /// The file changed between the two passes.
    #[error("{file}: the recording changed while it was replayed")]
    Changed {
        /// The file.
        file: PathBuf,
    },
}

impl From<ReplayError> for pipeline_runtime::StageError {
    fn from(e: ReplayError) -> Self {
        pipeline_runtime::StageError::stage(e)
    }
}

/// What [`scan`] found in a recording.
#[derive(Debug, Clone, Default, Serialize)]
pub struct ScanReport {
    /// Messages per topic in the file (every channel).
    pub in_file: BTreeMap<String, u64>,
    /// Messages per topic that will be replayed.
    pub selected: BTreeMap<String, u64>,
    /// Recorded ends of stream left out because their process is part of this config.
    pub skipped_end_of_stream: BTreeMap<String, u64>,
    /// Recorded messages published out of file order (received before an older one).
    pub reordered: u64,
    /// Most messages held back at once to restore the publish order.
    pub max_held: usize,
}

/// Which recorded messages to replay.
#[derive(Debug, Clone)]
pub struct Selection {
    topics: BTreeSet<&'static str>,
    explicit: bool,
    skip_end_of_stream_from: BTreeSet<String>,
}

impl Selection {
    /// `topics` (empty = every recordable topic except heartbeats) without the recorded ends of
    /// stream from the processes `skip_end_of_stream_from`.
    pub fn new(topics: &[String], skip_end_of_stream_from: BTreeSet<String>) -> Self {
        let explicit = !topics.is_empty();
        let topics = if topics.is_empty() {
            TOPICS.iter().filter(|t| t.service != services::HEARTBEAT).map(|t| t.service).collect()
        } else {
            TOPICS.iter().filter(|t| topics.iter().any(|s| s == t.service)).map(|t| t.service).collect()
        };
        Self { topics, explicit, skip_end_of_stream_from }
    }

    fn topic_of(&self, m: &mcap::Message<'_>) -> Option<&'static Topic> {
        let t = topic(&m.channel.topic)?;
        self.topics.contains(t.service).then_some(t)
    }

    /// The sender of a recorded end of stream that is not replayed, if `data` is one.
    fn skipped_end_of_stream(&self, t: &Topic, data: &[u8]) -> Option<String> {
        if t.service != services::END_OF_STREAM {
            return None;
        }
        let eos = EndOfStream::from_bytes(data.get(t.header_size()..)?)?;
        let from = name_from32(&eos.process);
        self.skip_end_of_stream_from.contains(&from).then_some(from)
    }
}

fn open(path: &Path) -> Result<mcap::io::MessageReader<BufReader<File>>, ReplayError> {
    let file = File::open(path).map_err(|e| ReplayError::Open { file: path.into(), reason: e.to_string() })?;
    Ok(mcap::io::MessageReader::new(BufReader::with_capacity(1 << 20, file)))
}

fn check_channel(path: &Path, t: &Topic, ch: &mcap::Channel<'_>) -> Result<(), ReplayError> {
    let err = |what, found: &str, expected: &str| ReplayError::Schema {
        file: path.into(),
        topic: t.service.into(),
        what,
        found: found.into(),
        expected: expected.into(),
    };
    if ch.message_encoding != MESSAGE_ENCODING {
        return Err(err("the message encoding", &ch.message_encoding, MESSAGE_ENCODING));
    }
    let Some(schema) = &ch.schema else { return Err(err("the schema", "(none)", t.payload_type_name())) };
    if schema.name != t.payload_type_name() {
        return Err(err("the schema name", &schema.name, t.payload_type_name()));
    }
    if schema.encoding != SCHEMA_ENCODING {
        return Err(err("the schema encoding", &schema.encoding, SCHEMA_ENCODING));
    }
    Ok(())
}

/// First pass: reads the whole recording, checks every selected message (channel schema and
/// encoding, size against the topic's wire types, a complete file) and returns the replay rank
/// of every selected message in file order, with what was found.
pub fn scan(path: &Path, selection: &Selection) -> Result<(Vec<u32>, ScanReport), ReplayError> {
    let mut report = ScanReport::default();
    let mut keys: Vec<(u64, u32)> = vec![];
    let mut checked_channels = BTreeSet::new();
    let mut newest_publish = 0u64;
    for (read, m) in open(path)?.enumerate() {
        let m =
            m.map_err(|e| ReplayError::Corrupt { file: path.into(), messages: read as u64, reason: e.to_string() })?;
        *report.in_file.entry(m.channel.topic.clone()).or_default() += 1;
        let Some(t) = selection.topic_of(&m) else { continue };
        if checked_channels.insert(m.channel.id) {
            check_channel(path, t, &m.channel)?;
        }
        let index = report.selected.get(t.service).copied().unwrap_or(0);
        t.check_len(m.data.len()).map_err(|e| ReplayError::Size {
            file: path.into(),
            topic: t.service.into(),
            index,
            reason: e.to_string(),
        })?;
        if let Some(from) = selection.skipped_end_of_stream(t, &m.data) {
            *report.skipped_end_of_stream.entry(from).or_default() += 1;
            continue;
        }
        *report.selected.entry(t.service.to_string()).or_default() += 1;
        if m.publish_time < newest_publish {
            report.reordered += 1;
        }
        newest_publish = newest_publish.max(m.publish_time);
        keys.push((m.publish_time, keys.len() as u32));
    }
    for t in &selection.topics {
        if selection.explicit && !report.in_file.contains_key(*t) {
            return Err(ReplayError::MissingTopic {
                file: path.into(),
                topic: t.to_string(),
                present: report.in_file.keys().cloned().collect::<Vec<_>>().join(", "),
            });
        }
    }
    let mut order: Vec<u32> = (0..keys.len() as u32).collect();
    order.sort_by_key(|&j| keys[j as usize]);
    let mut rank = vec![0u32; keys.len()];
    for (r, &j) in order.iter().enumerate() {
        rank[j as usize] = r as u32;
    }
    Ok((rank, report))
}

/// One message to publish.
#[derive(Debug, Clone)]
pub struct Replayed {
    /// Its topic.
    pub topic: &'static Topic,
    /// Its original publish time (the recorded `publish_ns`), ns.
    pub publish_time: u64,
    /// The recorded header and payload bytes.
    pub data: Vec<u8>,
}

/// Second pass: the selected messages in replay order.
pub struct Replay {
    path: PathBuf,
    reader: mcap::io::MessageReader<BufReader<File>>,
    selection: Selection,
    rank: Vec<u32>,
    next_index: usize,
    next_rank: u32,
    held: BTreeMap<u32, Replayed>,
    /// Most messages held back at once.
    pub max_held: usize,
}

impl Replay {
    /// Streams `path` again with the ranks from [`scan`].
    pub fn new(path: &Path, selection: Selection, rank: Vec<u32>) -> Result<Self, ReplayError> {
        Ok(Self {
            path: path.into(),
            reader: open(path)?,
            selection,
            rank,
            next_index: 0,
            next_rank: 0,
            held: BTreeMap::new(),
            max_held: 0,
        })
    }

    /// Messages in all.
    pub fn len(&self) -> usize {
        self.rank.len()
    }

    /// True when nothing is selected.
    pub fn is_empty(&self) -> bool {
        self.rank.is_empty()
    }

    /// Messages handed out so far.
    pub fn done(&self) -> usize {
        self.next_rank as usize
    }

    /// The next message in replay order, `None` after the last.
    pub fn next_message(&mut self) -> Result<Option<Replayed>, ReplayError> {
        loop {
            if let Some(m) = self.held.remove(&self.next_rank) {
                self.next_rank += 1;
                return Ok(Some(m));
            }
            if self.next_rank as usize >= self.rank.len() {
                return Ok(None);
            }
            let Some(m) = self.reader.next() else { return Err(ReplayError::Changed { file: self.path.clone() }) };
            let m =
                m.map_err(|e| ReplayError::Corrupt { file: self.path.clone(), messages: 0, reason: e.to_string() })?;
            let Some(t) = self.selection.topic_of(&m) else { continue };
            if self.selection.skipped_end_of_stream(t, &m.data).is_some() {
                continue;
            }
            let Some(&r) = self.rank.get(self.next_index) else {
                return Err(ReplayError::Changed { file: self.path.clone() });
            };
            self.next_index += 1;
            let msg = Replayed { topic: t, publish_time: m.publish_time, data: m.data.into_owned() };
            if r == self.next_rank {
                self.next_rank += 1;
                return Ok(Some(msg));
            }
            self.held.insert(r, msg);
            self.max_held = self.max_held.max(self.held.len());
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::record::{Compression, McapSink, SinkOptions};
    use shared_types::{BuoyFix, MsgHeader, OdometryInput};

    fn msg(stamp: u64) -> MsgHeader {
        MsgHeader { stamp_ns: stamp, seq: stamp, origin_ns: 0, publish_ns: stamp }
    }

    fn write(path: &Path, items: &[(usize, u64, u64, Vec<u8>)]) {
        let topics = vec![topic(services::ODOMETRY).unwrap(), topic(services::BUOY_FIX).unwrap()];
        let opts = SinkOptions {
            compression: Compression::Lz4,
            chunk_size: 1024,
            flush_interval: None,
            queue: 8,
            json_mirror: false,
            foxglove_channels: false,
        };
        let sink = McapSink::create(path, &topics, &opts, BTreeMap::new()).unwrap();
        for (t, log, publish, data) in items {
            sink.write(*t, *log, *publish, data.clone()).unwrap();
        }
        sink.finish().unwrap();
    }

    fn odo(stamp: u64) -> Vec<u8> {
        [msg(stamp).as_bytes(), OdometryInput { dt_s: 0.1, ..Default::default() }.as_bytes()].concat()
    }

    fn fix(stamp: u64) -> Vec<u8> {
        [msg(stamp).as_bytes(), BuoyFix::default().as_bytes()].concat()
    }

    #[test]
    fn messages_come_back_in_publish_order_however_they_were_received() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("r.mcap");
        // Received service by service: odometry 1, 3, 5 then fixes 2, 4.
        let items =
            vec![(0, 10, 1, odo(1)), (0, 11, 3, odo(3)), (0, 12, 5, odo(5)), (1, 13, 2, fix(2)), (1, 14, 4, fix(4))];
        write(&path, &items);
        let sel = Selection::new(&[], BTreeSet::new());
        let (rank, report) = scan(&path, &sel).unwrap();
        assert_eq!(report.selected[services::ODOMETRY], 3);
        assert_eq!(report.reordered, 2);
        let mut replay = Replay::new(&path, sel, rank).unwrap();
        let mut got = vec![];
        while let Some(m) = replay.next_message().unwrap() {
            got.push((m.publish_time, m.topic.service));
        }
        let publish: Vec<_> = got.iter().map(|g| g.0).collect();
        assert_eq!(publish, [1, 2, 3, 4, 5]);
        assert_eq!(got[1].1, services::BUOY_FIX);
        assert!(replay.max_held >= 1);
    }

    #[test]
    fn a_wrong_size_a_missing_topic_and_a_truncated_file_are_named() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("bad.mcap");
        write(&path, &[(0, 1, 1, odo(1)), (1, 2, 2, fix(2)[..100].to_vec())]);
        let err = scan(&path, &Selection::new(&[], BTreeSet::new())).unwrap_err().to_string();
        assert!(err.contains("bad.mcap") && err.contains(services::BUOY_FIX) && err.contains("payload"), "{err}");
        let only_odo = Selection::new(&[services::ODOMETRY.into()], BTreeSet::new());
        assert!(scan(&path, &only_odo).is_ok(), "the bad topic is not selected");
        let missing = Selection::new(&[services::DEPTH.into()], BTreeSet::new());
        let err = scan(&path, &missing).unwrap_err().to_string();
        assert!(err.contains(services::DEPTH) && err.contains("not in the recording"), "{err}");

        let good = dir.path().join("good.mcap");
        write(&good, &(0..200).map(|i| (0, i, i, odo(i))).collect::<Vec<_>>());
        let bytes = std::fs::read(&good).unwrap();
        let cut = dir.path().join("cut.mcap");
        std::fs::write(&cut, &bytes[..bytes.len() * 2 / 3]).unwrap();
        let err = scan(&cut, &Selection::new(&[], BTreeSet::new())).unwrap_err().to_string();
        assert!(err.contains("cut.mcap") && err.contains("not a valid MCAP"), "{err}");
    }
}
