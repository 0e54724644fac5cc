//! Ingest's part of summary.json (`ingest`), described in docs/summary.schema.json.

use std::collections::BTreeMap;

use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

use crate::rosbag2::Rosbag2Details;

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
