//! The `sensor_monitor` process (`kind = "sensor_monitor"`): a sink for every sensor service
//! that validates each message, counts accepted and rejected ones by reason with a digest of what
//! it accepted, and forwards end of stream. The main job runs it to check what ingest and external
//! producers publish; the stage is [`stage::SensorMonitorStage`].

pub mod checks;
pub mod stage;
pub mod summary;

use pipeline_runtime::Validate;
use pipeline_runtime::{Issues, ProcessSettings};
use serde::{Deserialize, Serialize};

/// Largest cloud a producer may publish (the contract's limit, as the test producer's).
pub const MAX_POINTS: usize = 4_000_000;

/// Settings of `sensor_monitor` (`kind = "sensor_monitor"`): a sink for every sensor
/// service that validates each message, counts accepted and rejected ones by reason, and forwards
/// end of stream.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct SensorMonitorSettings {
    /// Buoy ids a range may name (unset: any).
    pub known_buoy_ids: Option<Vec<u32>>,
    /// Largest accepted cloud.
    pub max_cloud_points: usize,
    /// Send our own end of stream (once) when the first upstream one arrives.
    pub forward_end_of_stream: bool,
}

impl Default for SensorMonitorSettings {
    fn default() -> Self {
        Self { known_buoy_ids: None, max_cloud_points: MAX_POINTS, forward_end_of_stream: true }
    }
}

impl Validate for SensorMonitorSettings {
    fn validate(&self, issues: &mut Issues) {
        issues.check(
            (1..=MAX_POINTS).contains(&self.max_cloud_points),
            "max_cloud_points",
            format!("must be 1..={MAX_POINTS}"),
        );
    }
}

impl ProcessSettings for SensorMonitorSettings {}
