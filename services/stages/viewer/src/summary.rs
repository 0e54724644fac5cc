//! The viewer's part of summary.json (`viewer`), described in docs/summary.schema.json.

use std::collections::BTreeMap;

use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

/// What the `viewer` stage adds to summary.json.
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
pub struct ViewerPart {
    /// The live view's run.
    pub viewer: ViewerSummary,
}

/// `viewer`: the server, its clients and what each channel carried.
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct ViewerSummary {
    /// How the stage ended (`EndOfStream` or `Stopped`).
    pub ending: String,
    /// The address it listened on.
    pub host: String,
    /// Whether it ran without TLS and token off loopback (`insecure = true`).
    pub insecure: bool,
    /// The port it listened on.
    pub port: u16,
    /// Whether clients connected through TLS.
    pub tls: bool,
    /// The TLS gate's admissions and refusals (`null` without TLS).
    pub gate: Option<GateSummary>,
    /// Most clients connected at once.
    pub clients_max: usize,
    /// Times the Foxglove SDK reported a client's outbox full (messages it dropped for that client).
    pub sdk_outbox_full_reports: u64,
    /// Each Foxglove channel by topic.
    pub channels: BTreeMap<String, ChannelCounts>,
    /// Inputs the view does not show, with why.
    pub not_shown: BTreeMap<String, String>,
    /// Poses thinned out of each trajectory channel (paths longer than `path_max_poses`).
    pub path_poses_thinned: BTreeMap<String, u64>,
    /// Voxel deltas that came before the first full set (dropped; a full set was asked for).
    pub octree_deltas_before_a_full_set: u64,
    /// Full voxel sets asked of the mapper.
    pub octree_snapshots_asked: u64,
    /// Ground-truth lines that did not parse.
    pub ground_truth_bad_lines: u64,
    /// Wall time from the start to the summary, s.
    pub seconds: f64,
}

/// Per channel: messages received for it, logged to Foxglove, skipped (over its rate, or
/// nobody subscribed).
#[derive(Debug, Default, Clone, Copy, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct ChannelCounts {
    /// Messages received for the channel.
    pub received: u64,
    /// Logged to Foxglove.
    pub logged: u64,
    /// Skipped: over the channel's rate.
    pub skipped_rate: u64,
    /// Skipped: no client subscribed.
    pub skipped_unwatched: u64,
}

/// `viewer.gate`: TLS connections admitted and refused.
#[derive(Debug, Default, Clone, Copy, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct GateSummary {
    /// Connections admitted (TLS and the token).
    pub admitted: u64,
    /// Refused: no or a wrong token.
    pub refused_token: u64,
    /// Refused: the TLS handshake failed.
    pub refused_tls: u64,
    /// Refused: not a WebSocket upgrade request.
    pub refused_request: u64,
}
