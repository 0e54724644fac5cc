//! The bridge's part of summary.json (`bridge`), described in docs/summary.schema.json.

use std::collections::{BTreeMap, BTreeSet};
use std::path::PathBuf;

use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

use crate::counts::{InCounts, OutCounts};
use crate::relay::RelayCounts;
use crate::{CertificateInfo, ClockMode};

/// What a `bridge` stage adds to summary.json.
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
pub struct BridgePart {
    /// The bridge's run.
    pub bridge: BridgeSummary,
}

/// `bridge`: its routes, the robots' ends of stream, clocks and the link's security.
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct BridgeSummary {
    /// How the links were secured.
    pub security: SecuritySummary,
    /// The deployment's first key chunk.
    pub namespace: String,
    /// This host's robot name (`""` on a base station).
    pub robot: String,
    /// This session's Zenoh id.
    pub zid: String,
    /// Each `out` route by pipeline service.
    pub out: BTreeMap<String, OutRouteSummary>,
    /// Each `in` route by name.
    #[serde(rename = "in")]
    pub inbound: BTreeMap<String, InRouteSummary>,
    /// Robots whose end of stream came.
    pub ends_received: Vec<String>,
    /// Robots whose end of stream never came.
    pub ends_missing: Vec<String>,
    /// Whether the base station acknowledged this robot's end (`null` when not asked).
    pub end_acknowledged: Option<bool>,
    /// The clock offset to each robot's bridge.
    pub clock: BTreeMap<String, ClockSummary>,
    /// Wall time from the start to the summary, s.
    pub wall_s: f64,
}

/// An `out` route: a pipeline service sent over Zenoh.
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
#[schemars(rename = "BridgeOutRouteSummary")]
pub struct OutRouteSummary {
    /// Its Zenoh key.
    pub key: String,
    /// What happens when the link is slower than the service (`latest`, `reliable`, ...).
    pub policy: String,
    /// What it sent and dropped.
    pub counts: OutCounts,
}

/// An `in` route: a robot's service received over Zenoh into a local service.
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
#[schemars(rename = "BridgeInRouteSummary")]
pub struct InRouteSummary {
    /// The local service it publishes.
    pub local: String,
    /// The robot it comes from.
    pub from: String,
    /// The robot's service.
    pub service: String,
    /// Its Zenoh key.
    pub key: String,
    /// What arrived, was published and was refused.
    pub counts: InCounts,
    /// What the robot said it sent less what arrived (`null` before its end of stream).
    pub lost_on_the_way: Option<u64>,
    /// Messages under this route's key from a host that is not the robot, refused by the access
    /// control (`null` without TLS).
    pub refused_wrong_robot: Option<u64>,
}

/// `bridge.clock.<robot>`: how the robot's `origin_ns` is mapped onto this clock.
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct ClockSummary {
    /// The configured mode.
    pub mode: ClockMode,
    /// Whether the robot's bridge runs on this machine (`null` before its first answer).
    pub same_machine: Option<bool>,
    /// The robot's clock minus this one, ns (`null` before a measurement).
    pub offset_ns: Option<i64>,
    /// The round trip of the best measurement, ns.
    pub rtt_ns: Option<u64>,
    /// Whether the robot's `origin_ns` were shifted by the offset.
    pub shifted: bool,
    /// Clock asks sent.
    pub asked: u64,
    /// Answers received.
    pub answered: u64,
}

/// `bridge.security`. (Not `deny_unknown_fields`: serde does not support it next to a flattened
/// field; docs/summary.schema.json, which the tests check every summary against, declares the keys.)
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
pub struct SecuritySummary {
    /// `insecure` (explicit) or `mutual_tls`.
    pub mode: String,
    /// The mutual-TLS details (absent in insecure mode).
    #[serde(flatten, deserialize_with = "pipeline_runtime::summary::flattened_option")]
    pub tls: Option<TlsSummary>,
}

/// What a mutual-TLS bridge reports about its links.
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
pub struct TlsSummary {
    /// Links the TLS relays refused (nothing of theirs got in).
    pub refused_unauthenticated: Option<u64>,
    /// The relays' links, opened, expired, refused and unreachable.
    pub links: Option<RelayCounts>,
    /// Messages refused by the access control (`null` where it has no routes to guard).
    pub refused: Option<RefusalsSummary>,
    /// The limits put on what arrives.
    pub accept: AcceptSummary,
    /// This host's certificate (`null` when it cannot be read).
    pub certificate: Option<CertificateInfo>,
    /// The hosts this one sends to.
    pub receivers: Vec<String>,
    /// The access control given to Zenoh, in Zenoh's own configuration format.
    pub access_control: serde_json::Value,
    /// Host names revoked.
    pub revoked: BTreeSet<String>,
    /// The revocation list read.
    pub revocation_list: PathBuf,
}

/// `bridge.security.accept`.
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct AcceptSummary {
    /// Most messages per second a route takes.
    pub max_rate_hz: f64,
    /// The receive queue, messages.
    pub queue_messages: usize,
    /// The receive queue, MiB.
    pub queue_mib: f64,
    /// `origin_ns` at most this far ahead of now, s.
    pub max_future_s: f64,
    /// `origin_ns` at most this old, s.
    pub max_age_s: f64,
}

/// `bridge.security.refused`: messages the access control refused.
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct RefusalsSummary {
    /// Per host and route: messages sent under a robot's key by another host.
    pub refused_wrong_robot: Vec<RefusedHost>,
    /// Hosts that connected with a certificate but hold no role here.
    pub hosts_without_role: BTreeSet<String>,
}

/// One host refused on one route.
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct RefusedHost {
    /// Its Zenoh id.
    pub peer: String,
    /// Its certificate's name, if known.
    pub certificate: Option<String>,
    /// Its identity as Zenoh gave it.
    pub identity: Option<String>,
    /// The route.
    pub route: String,
    /// Messages refused.
    pub messages: u64,
}
