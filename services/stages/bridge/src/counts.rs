//! What the bridge counts per route (messages, gaps, refusals) with a digest of what passed, and
//! the snapshot of those counts a restarted bridge takes over.

use std::collections::BTreeMap;
use std::time::Duration;

/// Counters of one `out` route.
#[derive(Debug, Default, Clone, Copy, serde::Serialize, serde::Deserialize, schemars::JsonSchema)]
#[schemars(rename = "BridgeOutCounts")]
pub struct OutCounts {
    /// Messages taken from the local service.
    pub received: u64,
    /// Handed to Zenoh.
    pub sent: u64,
    /// Not sent: over the route's `max_rate_hz`.
    pub rate_dropped: u64,
    /// Not sent: Zenoh refused them.
    pub send_errors: u64,
    /// Missed on the local service before the bridge took them (sequence gaps per publisher).
    pub missed_locally: u64,
    /// Sent while no subscriber on the other side matched the key: lost.
    pub no_subscriber: u64,
    /// XXH64 folded over the bytes of every message sent, in order: equal on the receiving side
    /// (`in.digest`) when the same messages arrived.
    #[serde(serialize_with = "hex", deserialize_with = "unhex")]
    #[schemars(with = "String")]
    pub digest: u64,
}

/// The digest of no message.
pub(crate) const DIGEST0: u64 = 0;

/// Folds one message into a digest: XXH64 of the message seeded with the digest so far, so the
/// digest depends on every byte and on the order (the message may come in parts: a header and a
/// payload hash as their concatenation). (Fast enough for the hot path: a 3.6 MB cloud
/// takes well under a millisecond, where a byte-wise FNV took several.)
pub(crate) fn fold(h: u64, parts: &[&[u8]]) -> u64 {
    use std::hash::Hasher as _;
    let mut x = twox_hash::XxHash64::with_seed(h);
    for p in parts {
        x.write(p);
    }
    x.finish()
}

pub(crate) fn hex<S: serde::Serializer>(v: &u64, s: S) -> Result<S::Ok, S::Error> {
    s.serialize_str(&format!("{v:016x}"))
}

pub(crate) fn unhex<'de, D: serde::Deserializer<'de>>(d: D) -> Result<u64, D::Error> {
    let text = <String as serde::Deserialize>::deserialize(d)?;
    u64::from_str_radix(&text, 16).map_err(serde::de::Error::custom)
}

/// The restart snapshot of the counts (see [`Kept`]).
pub(crate) const KEPT: &str = "bridge_counts";

/// Shortest time between two snapshots of the counts.
pub(crate) const KEEP_EVERY: Duration = Duration::from_millis(100);

/// What a restarted bridge takes over from the killed instance (a snapshot at most
/// [`KEEP_EVERY`] old): every route's counts and last sequence numbers, so that its summary, its
/// end marker's counts and its gap counting cover the whole run, and the ends of stream already
/// received.
#[derive(Debug, Default, serde::Serialize, serde::Deserialize)]
pub(crate) struct Kept {
    pub(crate) out: BTreeMap<String, KeptOut>,
    #[serde(rename = "in")]
    pub(crate) inbound: BTreeMap<String, KeptIn>,
    pub(crate) ends: BTreeMap<String, Option<BTreeMap<String, u64>>>,
    pub(crate) published: u64,
}

#[derive(Debug, Default, serde::Serialize, serde::Deserialize)]
pub(crate) struct KeptOut {
    pub(crate) counts: OutCounts,
    /// Per local publisher (its port id, in decimal): the last sequence number taken.
    pub(crate) last_seq: BTreeMap<String, u64>,
}

#[derive(Debug, Default, serde::Serialize, serde::Deserialize)]
pub(crate) struct KeptIn {
    pub(crate) counts: InCounts,
    pub(crate) last_seq: Option<u64>,
}

/// Counters of one `in` route.
#[derive(Debug, Default, Clone, Copy, serde::Serialize, serde::Deserialize, schemars::JsonSchema)]
#[schemars(rename = "BridgeInCounts")]
pub struct InCounts {
    /// Messages that arrived from Zenoh.
    pub received: u64,
    /// Published into the local pipeline.
    pub published: u64,
    /// Refused: the wire signature (version, types) differs from this side's.
    pub wrong_type: u64,
    /// Refused: the length is not a message of the service's types.
    pub bad_length: u64,
    /// Dropped: the bridge's receive queue was full.
    pub queue_dropped: u64,
    /// Published but not delivered to a local subscriber (its queue was full or it died).
    pub undelivered: u64,
    /// Gaps in the sender's sequence numbers (lost on the way, before or over the link).
    pub seq_gaps: u64,
    /// Published with `origin_ns` on the sender's clock because the offset to another machine's
    /// clock was not measured yet (their end-to-end latency is off by that offset).
    pub origin_unaligned: u64,
    /// Dropped on arrival: over the route's rate (`accept.max_rate_hz`), a flood.
    #[serde(default)]
    pub rate_dropped: u64,
    /// Refused: a NaN or an infinity in the message.
    #[serde(default)]
    pub refused_non_finite: u64,
    /// Refused: `origin_ns` unset, later than now by more than `accept.max_future_s`, or older
    /// than `accept.max_age_s`.
    #[serde(default)]
    pub refused_time: u64,
    /// Refused: a sequence number not after the last one (a repeated or replayed message).
    #[serde(default)]
    pub refused_going_back: u64,
    /// The sender's sequence numbers started again from the beginning (its publisher restarted):
    /// accepted, counted.
    #[serde(default)]
    pub sender_restarts: u64,
    /// XXH64 folded over the bytes of every message published, in order (as they came over the
    /// link): equal to the sender's `out.digest` when the same messages arrived.
    #[serde(serialize_with = "hex", deserialize_with = "unhex")]
    #[schemars(with = "String")]
    pub digest: u64,
}
