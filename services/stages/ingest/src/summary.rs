//! Ingest's part of summary.json (`ingest`), described in docs/summary.schema.json.

use std::collections::BTreeMap;

use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

use std::path::PathBuf;

/// What the `ingest` stage adds to summary.json.
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
pub struct IngestPart {
    /// What the source published.
    pub ingest: IngestSummary,
}

/// `ingest`: the source and what it published.
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
pub struct IngestSummary {
    /// One line describing the source.
    pub source: String,
    /// True when the source was read to its end; false when the run stopped first.
    pub completed: bool,
    /// How far through the source it got, 0-1 (`null` when the source cannot tell).
    pub progress: Option<f64>,
    /// Messages published, by output.
    pub messages: MessageCounts,
    /// Depth clouds with no point, not published.
    pub empty_clouds_skipped: u64,
    /// What was wrong in the data and was skipped or repaired, by kind (lines out of order,
    /// malformed lines, dropouts...).
    pub data_warts: BTreeMap<String, u64>,
    /// Ground-truth poses written to `ground_truth.tum`.
    pub ground_truth_samples: u64,
    /// Data time from the first to the last message published, s.
    pub data_duration_s: f64,
    /// Wall time from the first message to the end, s.
    pub wall_duration_s: f64,
    /// Wall time spent waiting for slow consumers (back-pressure), s.
    pub backpressure_wait_s: f64,
    /// More about the source (a rosbag2 bag's routes).
    #[serde(flatten)]
    pub details: SourceDetails,
}

/// Messages published, by output.
#[derive(Debug, Clone, Copy, Default, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct MessageCounts {
    /// `pipeline/sensors/odometry`.
    pub odometry: u64,
    /// `pipeline/sensors/stereo`.
    pub stereo: u64,
    /// `pipeline/sensors/buoy_ranges`.
    pub buoy_ranges: u64,
    /// `pipeline/sensors/depth`.
    pub depth: u64,
    /// `pipeline/sensors/cloud`.
    pub cloud: u64,
    /// `pipeline/sensors/heading`.
    pub heading: u64,
    /// `pipeline/sensors/laser`.
    pub laser: u64,
    /// `pipeline/sensors/planar_odometry`.
    pub planar_odometry: u64,
}

/// A source's own details for summary.json.
#[derive(Debug, Clone, Default, Serialize, Deserialize, JsonSchema)]
pub struct SourceDetails {
    /// The `rosbag2` source: the bag, its routes and counts.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub rosbag2: Option<Rosbag2Details>,
}

/// One route's counts (summary.json `ingest.rosbag2.routes.<topic>`).
#[derive(Debug, Default, Clone, Serialize, Deserialize, JsonSchema)]
pub struct RouteCounts {
    /// The pipeline service it feeds.
    pub service: String,
    /// Messages published on it.
    pub published: u64,
    /// Messages of another type than the route's.
    pub wrong_type: u64,
    /// Messages that did not decode.
    pub undecodable: u64,
    /// Messages the route's checks refused.
    pub invalid: u64,
    /// Points left out of clouds for not being finite.
    pub non_finite_points: u64,
    /// Camera infos taken (depth-image routes).
    pub camera_infos: u64,
}

/// The bag and its routes (summary.json `ingest.rosbag2`).
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
pub struct Rosbag2Details {
    /// The bag as configured.
    pub path: PathBuf,
    /// Its files, in the order read.
    pub files: Vec<PathBuf>,
    /// Each routed topic's counts.
    pub routes: BTreeMap<String, RouteCounts>,
    /// Messages of topics no route takes, by topic.
    pub unrouted_messages: BTreeMap<String, u64>,
    /// What was wrong in the bag.
    pub bag: ros2_interop::bag::BagWarts,
}
