//! The synchronizer's part of summary.json (`synchronizer`), described in
//! docs/summary.schema.json.

use pipeline_runtime::summary::Percentiles;
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

use crate::SyncStats;

/// What the `synchronizer` stage adds to summary.json.
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
pub struct SynchronizerPart {
    /// The pairing of SLAM poses with buoy positions.
    pub synchronizer: SyncSummary,
}

/// `synchronizer`: poses paired with the buoy position at their stamp.
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct SyncSummary {
    /// Pairs published (a pose with the buoy position at its stamp), predictions not counted.
    pub pairs: u64,
    /// What became of the poses, by kind.
    pub poses: SyncStats,
    /// What became of the buoy fixes.
    pub fixes: FixCounts,
    /// The configured bound on a pose's wait for its fix (`sync.max_latency_s`), ms.
    pub max_latency_ms: f64,
    /// Wall time a pose spent in the synchronizer before its pair was published, ms.
    pub added_latency_ms: Percentiles,
}

/// The fix buffer's decisions.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct FixCounts {
    /// Fixes inserted (including duplicates and restarts).
    pub inserted: u64,
    /// Fixes that arrived out of stamp order.
    pub out_of_order: u64,
    /// Duplicate stamps replaced.
    pub duplicates: u64,
    /// Upstream restarts detected.
    pub restarts: u64,
    /// Fixes dropped (the buffer's capacity).
    pub dropped: u64,
}

impl From<timesync::SyncCounters> for FixCounts {
    fn from(c: timesync::SyncCounters) -> Self {
        Self {
            inserted: c.inserted,
            out_of_order: c.out_of_order,
            duplicates: c.duplicates,
            restarts: c.restarts,
            dropped: c.dropped,
        }
    }
}
