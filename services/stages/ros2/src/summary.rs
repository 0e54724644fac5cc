//! The ROS 2 gateway's part of summary.json (`ros2.<name>`), described in
//! docs/summary.schema.json.

use std::collections::BTreeMap;

use ros2_interop::bag_sink::BagReport;
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

use crate::inbound::{InRouteSummary, LatencyMs};
use crate::outbound::OutCounts;

/// What a `ros2` stage adds to summary.json: its gateway under `ros2.<process name>`.
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
pub struct Ros2Part {
    /// Each gateway by process name.
    pub ros2: BTreeMap<String, GatewaySummary>,
}

/// `ros2.<name>`: the node, its routes and what they carried.
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct GatewaySummary {
    /// Whether the gateway ran to the end of stream (false: stopped).
    pub completed: bool,
    /// Always true: DDS traffic is not authenticated or encrypted (docs/security.md).
    pub insecure: bool,
    /// The node's full name.
    pub node: String,
    /// The ROS 2 domain.
    pub domain_id: u16,
    /// Each `in` route by ROS topic.
    #[serde(rename = "in")]
    pub inbound: BTreeMap<String, InRouteSummary>,
    /// Each `out` route by ROS topic.
    pub out: BTreeMap<String, OutRouteSummary>,
    /// Static transforms published on `/tf_static`.
    pub static_transforms: usize,
    /// Pipeline messages the out routes took.
    pub pipeline_messages_taken: u64,
    /// Voxel-stream messages missed (the cloud restarts at the next full set).
    pub voxel_messages_missed: u64,
    /// Voxel deltas left unused while waiting for a full set.
    pub voxel_deltas_waiting_for_a_full_set: u64,
    /// Messages not carried (undecodable, invalid, lost in DDS, a port that failed; per route above).
    pub not_carried: u64,
    /// Remote endpoints that matched no route (QoS or type).
    pub endpoints_unmatched: u64,
    /// The ROS 2 bag written beside the topics (`bag`), `null` without one.
    pub bag: Option<BagReport>,
}

/// An `out` route: a pipeline service onto a ROS 2 topic.
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
#[schemars(rename = "Ros2OutRouteSummary")]
pub struct OutRouteSummary {
    /// What the route did.
    #[serde(flatten)]
    pub counts: OutCounts,
    /// The ROS 2 message type.
    #[serde(rename = "type")]
    pub ros_type: String,
    /// From a pipeline message's origin to its ROS 2 message written, ms.
    pub latency_ms: LatencyMs,
}
