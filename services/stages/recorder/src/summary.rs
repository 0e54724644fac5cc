//! The recorder's and the replayer's parts of summary.json (`recorder`, `recorders.<name>`,
//! `replayer`), described in docs/summary.schema.json.

use std::collections::BTreeMap;

use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

use crate::ros2::Ros2Report;

/// What a `recorder` stage adds to summary.json: its recording under `recorder` (with several
/// recorders in a run, merged from all of them) and under `recorders.<name>` (each one's).
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
pub struct RecorderPart {
    /// The recording (with several recorders, the keys of all of them merged).
    pub recorder: RecordingSummary,
    /// Each recorder's recording, by process name.
    pub recorders: BTreeMap<String, RecordingSummary>,
}

/// One recording: the MCAP file and what went into it.
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct RecordingSummary {
    /// The MCAP file.
    pub file: String,
    /// Files of earlier instances (a restarted recorder starts a new part).
    pub earlier_parts: Vec<String>,
    /// What ended it (`end of stream` or `stopped`).
    pub ended_by: String,
    /// The file's size, bytes.
    pub file_bytes: u64,
    /// Chunks written.
    pub chunks: u64,
    /// Messages written, by service.
    pub messages: BTreeMap<String, u64>,
    /// Message bytes written, by service.
    pub message_bytes: BTreeMap<String, u64>,
    /// Messages received, by service.
    pub received: BTreeMap<String, u64>,
    /// Messages missed (gaps in the publishers' sequence numbers), by service.
    pub missed: BTreeMap<String, u64>,
    /// Services listed but not recorded, with why.
    pub not_recorded: BTreeMap<String, String>,
    /// From the first message received to the last, s.
    pub active_s: f64,
    /// Messages written per second of `active_s`.
    pub messages_per_s: f64,
    /// Most messages queued for the writer thread at once.
    pub max_queued: usize,
    /// Messages written on the Foxglove channels (the viewer's schemas), by topic.
    pub foxglove_messages: BTreeMap<String, u64>,
    /// Wall time from the start to the summary, s.
    pub wall_s: f64,
    /// The ROS 2 bag written beside it (`ros2`), `null` without one.
    pub ros2_bag: Option<Ros2BagSummary>,
}

/// The ROS 2 bag: [`Ros2Report`] and the bags of earlier instances.
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
pub struct Ros2BagSummary {
    /// What the bag got.
    #[serde(flatten)]
    pub report: Ros2Report,
    /// Bag directories of earlier instances.
    pub earlier_parts: Vec<String>,
}

/// What a `replayer` stage adds to summary.json.
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
pub struct ReplayerPart {
    /// The replay.
    pub replayer: ReplayerSummary,
}

/// `replayer`: the recording and what of it was sent.
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct ReplayerSummary {
    /// The MCAP file.
    pub file: String,
    /// The replay speed (1: as recorded, 0: as fast as the consumers take).
    pub speed: f64,
    /// Messages in the file, by service.
    pub in_file: BTreeMap<String, u64>,
    /// Messages selected for the replay, by service.
    pub selected: BTreeMap<String, u64>,
    /// Messages sent, by service.
    pub sent: BTreeMap<String, u64>,
    /// Messages some consumer did not receive, by service.
    pub undelivered: BTreeMap<String, u64>,
    /// Recorded ends of stream not replayed, by process.
    pub skipped_end_of_stream: BTreeMap<String, u64>,
    /// Messages the recorder received out of their publish order (replayed in publish order).
    pub received_out_of_publish_order: u64,
    /// Most messages held to restore the publish order.
    pub max_held: usize,
    /// Whether the whole recording was replayed.
    pub complete: bool,
}
