//! The sensor monitor's part of summary.json (`sensor_monitor`), described in
//! docs/summary.schema.json.

use std::collections::BTreeMap;

use pipeline_runtime::validate::GuardReport;
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

/// What the `sensor_monitor` stage adds to summary.json.
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
pub struct SensorMonitorPart {
    /// Every sensor message checked and counted.
    pub sensor_monitor: SensorMonitorSummary,
}

/// `sensor_monitor`: each sensor service's messages, accepted, rejected by reason and missed.
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
pub struct SensorMonitorSummary {
    /// Points in the accepted clouds.
    pub cloud_points: u64,
    /// Stereo observations in the accepted frames.
    pub stereo_observations: u64,
    /// A digest (XXH64, hex) of each service's accepted messages in order: two runs that read
    /// the same data agree.
    pub digests: BTreeMap<String, String>,
    /// Each sensor service by name (`pipeline/sensors/odometry`, ...): its counters.
    #[serde(flatten)]
    pub streams: BTreeMap<String, GuardReport>,
}
