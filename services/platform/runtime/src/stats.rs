//! Latency accounting: per-hop and end-to-end HDR histograms per input port, and the
//! `StatsReport` every process publishes on `pipeline/stats/<process>`.
//!
//! Hop latency of a message is `receive time − publish_ns` (the transport plus the time the message
//! waited in the queue); end-to-end latency is `receive time − origin_ns` (everything since the
//! oldest sensor input entered the pipeline). Both use CLOCK_MONOTONIC, which all processes on one
//! machine share. Histograms hold nanoseconds, 3 significant digits, up to 60 s.
//!
//! The report carries the histograms serialised (HdrHistogram V2, deflate), bincode-encoded, so the
//! supervisor can merge the histograms of restarted instances exactly.

use hdrhistogram::Histogram;
use hdrhistogram::serialization::{Deserializer, Serializer, V2DeflateSerializer};
use serde::{Deserialize, Serialize};

/// Largest latency a histogram records, ns (larger values are clamped).
pub const MAX_LATENCY_NS: u64 = 60_000_000_000;

/// A latency histogram in ns.
pub fn new_histogram() -> Histogram<u64> {
    Histogram::new_with_bounds(1, MAX_LATENCY_NS, 3).expect("static histogram bounds are valid")
}

/// The reason under which a restarted instance counts the messages its killed predecessor never
/// took (they sat in its queue when it died, or were sent while no instance ran) or took and did
/// not keep (its stage still held them, [`crate::Input::set_held`]: e.g. clouds the mapper
/// inserted after its last checkpoint).
pub const LOST_IN_RESTART: &str = "lost in a restart: queued for the killed instance or not kept by it";

/// Statistics of one port of a process.
#[derive(Debug, Clone)]
pub struct PortStats {
    /// Service name.
    pub service: String,
    /// True for an input (subscriber), false for an output (publisher).
    pub input: bool,
    /// Messages received or sent.
    pub count: u64,
    /// Input messages whose header was implausible (publish/origin time in the future or zero);
    /// they are counted, not recorded.
    pub bad_header: u64,
    /// Output deliveries that failed: for each send, the registered subscribers it did not reach
    /// (not connected yet, a full queue of a live source's subscriber, a dead subscriber).
    pub undelivered: u64,
    /// `undelivered` by consumer (subscriber port name, i.e. process name; `(not connected
    /// yet)` for subscribers that had not connected).
    pub undelivered_by: std::collections::BTreeMap<String, u64>,
    /// Input messages the consuming stage received (or knows it missed) and dropped, by reason
    /// (e.g. "no pose within pose_wait_s"): counted by the stage with [`crate::Input::count_dropped`].
    pub dropped_by: std::collections::BTreeMap<String, u64>,
    /// An input's last sequence number received, per publisher: written to the restart state
    /// after every wake-up ([`crate::restart::StateStore::save_inputs`]).
    pub last_seq: std::collections::BTreeMap<u128, u64>,
    /// A restarted instance's input: per publisher, the first sequence number its killed
    /// predecessor had not received or not kept. The first later message from that publisher
    /// tells how many were lost from there (queued for the killed instance when it died, held by
    /// its stage, or sent while no instance ran): counted in `dropped_by` as [`LOST_IN_RESTART`].
    pub resume_at: std::collections::BTreeMap<u128, u64>,
    /// `last_seq` changed since it was last saved.
    pub seq_dirty: bool,
    /// The publisher of the newest message received.
    pub last_publisher: Option<u128>,
    /// Messages of this input the stage has received and still holds unprocessed (the newest
    /// ones: [`crate::Input::set_held`]); a restart resumes before them, so they count as lost.
    pub held: u64,
    /// Hop latency, ns.
    pub hop: Histogram<u64>,
    /// End-to-end latency, ns.
    pub e2e: Histogram<u64>,
}

impl PortStats {
    /// Empty statistics of a port.
    pub fn new(service: &str, input: bool) -> Self {
        Self {
            service: service.to_string(),
            input,
            count: 0,
            bad_header: 0,
            undelivered: 0,
            undelivered_by: Default::default(),
            dropped_by: Default::default(),
            last_seq: Default::default(),
            resume_at: Default::default(),
            seq_dirty: false,
            last_publisher: None,
            held: 0,
            hop: new_histogram(),
            e2e: new_histogram(),
        }
    }

    /// Notes an input message's sequence number `seq` from `publisher`; in a restarted instance
    /// the first one from where the killed instance stopped counts the messages before it as
    /// lost ([`PortStats::resume_at`]).
    pub fn note_seq(&mut self, publisher: u128, seq: u64) {
        if let Some(&next) = self.resume_at.get(&publisher) {
            if seq < next {
                return; // one the killed instance had kept (a history replayed on connecting)
            }
            self.resume_at.remove(&publisher);
            if seq > next {
                *self.dropped_by.entry(LOST_IN_RESTART.to_string()).or_default() += seq - next;
            }
        }
        self.last_seq.insert(publisher, seq);
        self.last_publisher = Some(publisher);
        self.seq_dirty = true;
    }

    /// Records one received message with header times `publish_ns` and `origin_ns` at `now_ns`.
    pub fn record_receive(&mut self, now_ns: u64, publish_ns: u64, origin_ns: u64) {
        self.count += 1;
        if publish_ns == 0 || publish_ns > now_ns || origin_ns == 0 || origin_ns > now_ns {
            self.bad_header += 1;
            return;
        }
        self.hop.saturating_record((now_ns - publish_ns).max(1));
        self.e2e.saturating_record((now_ns - origin_ns).max(1));
    }
}

/// One port in a [`StatsReport`].
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct PortReport {
    /// Service name.
    pub service: String,
    /// Input (true) or output.
    pub input: bool,
    /// Messages.
    pub count: u64,
    /// Messages with implausible headers.
    pub bad_header: u64,
    /// Output deliveries that reached no subscriber (summed over subscribers).
    pub undelivered: u64,
    /// `undelivered` by consumer name.
    pub undelivered_by: Vec<(String, u64)>,
    /// Input messages the stage dropped, by reason (empty for outputs).
    pub dropped_by: Vec<(String, u64)>,
    /// Hop histogram, V2 deflate serialised (empty for outputs).
    pub hop: Vec<u8>,
    /// End-to-end histogram, V2 deflate serialised (empty for outputs).
    pub e2e: Vec<u8>,
}

/// What a process publishes on its stats service, cumulative since the process started.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct StatsReport {
    /// Process name.
    pub process: String,
    /// OS process id (distinguishes restarted instances).
    pub pid: u32,
    /// Time since the process started, ns.
    pub uptime_ns: u64,
    /// Ports.
    pub ports: Vec<PortReport>,
    /// How much of its input a source has done, 0 to 1 ([`crate::Runtime::set_progress`]); `None`
    /// for a process that does not know (the supervisor's live view shows it as the run's progress).
    pub progress: Option<f64>,
}

/// Errors of encoding or decoding stats.
#[derive(Debug, thiserror::Error)]
pub enum StatsError {
    /// bincode failed.
    #[error("stats encoding: {0}")]
    Encode(String),
    /// The bytes are not a valid report.
    #[error("malformed stats report: {0}")]
    Decode(String),
}

fn ser(h: &Histogram<u64>) -> Vec<u8> {
    let mut out = Vec::new();
    if h.is_empty() {
        return out;
    }
    // Writing into a Vec cannot fail; an error would only drop this histogram from the report.
    let _ = V2DeflateSerializer::new().serialize(h, &mut out);
    out
}

/// Decodes a serialised histogram (empty bytes = empty histogram).
pub fn histogram_from_bytes(bytes: &[u8]) -> Result<Histogram<u64>, StatsError> {
    if bytes.is_empty() {
        return Ok(new_histogram());
    }
    let mut h: Histogram<u64> =
        Deserializer::new().deserialize(&mut &bytes[..]).map_err(|e| StatsError::Decode(format!("{e:?}")))?;
    h.auto(true);
    Ok(h)
}

impl StatsReport {
    /// Builds a report from port statistics.
    pub fn from_ports<'a>(process: &str, pid: u32, uptime_ns: u64, ports: impl Iterator<Item = &'a PortStats>) -> Self {
        Self {
            process: process.to_string(),
            pid,
            uptime_ns,
            ports: ports
                .map(|p| PortReport {
                    service: p.service.clone(),
                    input: p.input,
                    count: p.count,
                    bad_header: p.bad_header,
                    undelivered: p.undelivered,
                    undelivered_by: p.undelivered_by.iter().map(|(k, v)| (k.clone(), *v)).collect(),
                    dropped_by: p.dropped_by.iter().map(|(k, v)| (k.clone(), *v)).collect(),
                    hop: ser(&p.hop),
                    e2e: ser(&p.e2e),
                })
                .collect(),
            progress: None,
        }
    }

    /// bincode bytes of the report.
    pub fn encode(&self) -> Result<Vec<u8>, StatsError> {
        bincode::serde::encode_to_vec(self, bincode::config::standard()).map_err(|e| StatsError::Encode(e.to_string()))
    }

    /// Decodes a report from bincode bytes.
    pub fn decode(bytes: &[u8]) -> Result<Self, StatsError> {
        bincode::serde::decode_from_slice(bytes, bincode::config::standard())
            .map(|(r, _)| r)
            .map_err(|e| StatsError::Decode(e.to_string()))
    }
}

/// p50/p99/max summary of a histogram, ms.
#[derive(Debug, Clone, Copy, Serialize, Deserialize, schemars::JsonSchema, PartialEq, Default)]
pub struct LatencySummary {
    /// Samples.
    pub count: u64,
    /// Median, ms.
    pub p50: f64,
    /// 99th percentile, ms.
    pub p99: f64,
    /// 99.9th percentile, ms.
    pub p999: f64,
    /// Maximum, ms.
    pub max: f64,
}

impl LatencySummary {
    /// Summary of a histogram in ns.
    pub fn of(h: &Histogram<u64>) -> Self {
        if h.is_empty() {
            return Self::default();
        }
        let ms = |ns: u64| ns as f64 / 1e6;
        Self {
            count: h.len(),
            p50: ms(h.value_at_quantile(0.5)),
            p99: ms(h.value_at_quantile(0.99)),
            p999: ms(h.value_at_quantile(0.999)),
            max: ms(h.max()),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn report_round_trips_through_bincode_and_keeps_histograms() {
        let mut p = PortStats::new("pipeline/sensors/cloud", true);
        for i in 1..=1000u64 {
            p.record_receive(10_000_000 + i * 1000, 10_000_000, 9_000_000);
        }
        p.record_receive(5, 10, 10); // publish in the future: counted, not recorded
        let r = StatsReport::from_ports("consumer", 42, 7, [&p].into_iter());
        let back = StatsReport::decode(&r.encode().unwrap()).unwrap();
        assert_eq!(back, r);
        let hop = histogram_from_bytes(&back.ports[0].hop).unwrap();
        assert_eq!(hop.len(), 1000);
        assert_eq!(back.ports[0].count, 1001);
        assert_eq!(back.ports[0].bad_header, 1);
        let s = LatencySummary::of(&hop);
        assert!((s.p50 - 0.5).abs() < 0.01, "{s:?}");
        assert!((s.max - 1.0).abs() < 0.01, "{s:?}");
    }

    #[test]
    fn garbage_bytes_are_a_decode_error_not_a_panic() {
        assert!(StatsReport::decode(&[0xff; 7]).is_err());
        assert!(histogram_from_bytes(&[1, 2, 3]).is_err());
    }
}
