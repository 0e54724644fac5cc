//! Test-only pipeline processes. Until the real stages exist they let the supervisor, restarts and
//! latency accounting be exercised for real: a point-cloud producer of configurable size and rate
//! (which can also crash or stall on purpose) and a consumer that verifies every point it receives.
//! The logic is here as pure functions; the binaries are thin wiring around them. (The sensor
//! monitor, a process kind users run, is the `sensor_monitor_stage` crate.)

use pipeline_runtime::Validate;
use pipeline_runtime::{Issues, ProcessSettings};
use serde::{Deserialize, Serialize};
use shared_types::CloudPoint;
use shared_types::services::{CLOUD, service_spec};

/// Settings of `test_producer` (`kind = "test_producer"`).
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct ProducerSettings {
    /// Points per cloud.
    pub points: usize,
    /// Clouds per second.
    pub rate_hz: f64,
    /// Clouds to send before end of stream (0 = until stopped).
    pub frames: u64,
    /// Abort (SIGABRT) after this many clouds, to test crash handling.
    pub abort_after_frames: Option<u64>,
    /// Stop heartbeating (hang) after this many clouds, to test the heartbeat deadline.
    pub stall_after_frames: Option<u64>,
}

impl Default for ProducerSettings {
    fn default() -> Self {
        Self { points: 10_000, rate_hz: 10.0, frames: 0, abort_after_frames: None, stall_after_frames: None }
    }
}

/// Most points a test cloud may have.
pub const MAX_POINTS: usize = 4_000_000;

impl ProcessSettings for ProducerSettings {
    fn shm_estimate_bytes(&self, extra_subscribers: usize) -> u64 {
        let qos = service_spec(CLOUD).expect("cloud service is in the contract").qos;
        let chunk = (self.points * size_of::<CloudPoint>()).next_power_of_two() as u64;
        chunk * qos.with_extra(extra_subscribers).chunks_per_publisher() as u64
    }
}

impl Validate for ProducerSettings {
    fn validate(&self, issues: &mut Issues) {
        issues.check(
            (1..=MAX_POINTS).contains(&self.points),
            "points",
            format!("must be 1..={MAX_POINTS}, got {}", self.points),
        );
        issues.check(
            self.rate_hz.is_finite() && self.rate_hz > 0.0 && self.rate_hz <= 10_000.0,
            "rate_hz",
            format!("must be in (0, 10000], got {}", self.rate_hz),
        );
    }
}

/// Settings of `test_consumer` (`kind = "test_consumer"`).
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct ConsumerSettings {
    /// Points every cloud must have (unset: any).
    pub expect_points: Option<usize>,
    /// Send our own end of stream when an upstream one arrives.
    pub forward_end_of_stream: bool,
    /// Also take stereo frames, spending this long on each, ms (0: no stereo subscription): a
    /// slow consumer for back-pressure tests.
    pub stereo_delay_ms: u64,
}

impl Default for ConsumerSettings {
    fn default() -> Self {
        Self { expect_points: None, forward_end_of_stream: true, stereo_delay_ms: 0 }
    }
}

impl Validate for ConsumerSettings {
    fn validate(&self, issues: &mut Issues) {
        issues.check(self.stereo_delay_ms <= 2000, "stereo_delay_ms", "must be <= 2000 (the heartbeat)");
        if let Some(n) = self.expect_points {
            issues.check((1..=MAX_POINTS).contains(&n), "expect_points", format!("must be 1..={MAX_POINTS}"));
        }
    }
}

impl ProcessSettings for ConsumerSettings {}

/// The deterministic content of point `i` of cloud `seq`.
pub fn cloud_point(seq: u64, i: usize) -> CloudPoint {
    CloudPoint {
        x_m: (i % 1024) as f32 * 0.01,
        y_m: (i / 1024) as f32 * 0.01,
        z_m: (seq % 4096) as f32 + (i % 7) as f32,
    }
}

/// Counters of the verifying consumer (written to `parts/<name>.json` as `test_consumer`).
#[derive(Debug, Clone, Default, Serialize, Deserialize, PartialEq)]
pub struct ConsumerCounters {
    /// Clouds whose every point matched.
    pub frames_ok: u64,
    /// Clouds with a wrong point or size.
    pub frames_bad: u64,
    /// Sequence numbers skipped (lost to overflow or a restart of either side).
    pub frames_missed: u64,
    /// Points checked.
    pub points_checked: u64,
    /// Last sequence number seen.
    pub last_seq: Option<u64>,
    /// End-of-stream messages received from upstream.
    pub end_of_stream_seen: u64,
    /// Stereo frames received (with `stereo_delay_ms`).
    pub stereo_frames: u64,
    /// Stereo sequence numbers skipped.
    pub stereo_missed: u64,
}

/// The verifying consumer's part of summary.json: its counters under `test_consumer`. A test
/// program, not a stage: docs/summary.schema.json does not list it.
#[derive(Debug, Clone, Default, Serialize, Deserialize, PartialEq)]
pub struct ConsumerPart {
    /// The counters.
    pub test_consumer: ConsumerCounters,
}

/// Why a cloud failed verification.
#[derive(Debug, Clone, PartialEq)]
pub enum CloudFault {
    /// Wrong number of points.
    Size {
        /// Expected.
        expected: usize,
        /// Received.
        got: usize,
    },
    /// A point differs.
    Point {
        /// Index of the first wrong point.
        index: usize,
    },
}

/// Verifies one cloud and updates the counters: the consumer's `step`.
pub fn verify_cloud(
    counters: &mut ConsumerCounters,
    expect_points: Option<usize>,
    seq: u64,
    points: &[CloudPoint],
) -> Result<(), CloudFault> {
    if let Some(last) = counters.last_seq
        && seq > last + 1
    {
        counters.frames_missed += seq - last - 1;
    }
    counters.last_seq = Some(seq);
    let result = match expect_points {
        Some(n) if n != points.len() => Err(CloudFault::Size { expected: n, got: points.len() }),
        _ => match points.iter().enumerate().position(|(i, p)| *p != cloud_point(seq, i)) {
            Some(index) => Err(CloudFault::Point { index }),
            None => Ok(()),
        },
    };
    counters.points_checked += points.len() as u64;
    match result {
        Ok(()) => counters.frames_ok += 1,
        Err(_) => counters.frames_bad += 1,
    }
    result
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_correct_cloud_verifies_and_a_corrupted_one_does_not() {
        let mut c = ConsumerCounters::default();
        let mut pts: Vec<_> = (0..5000).map(|i| cloud_point(3, i)).collect();
        assert_eq!(verify_cloud(&mut c, Some(5000), 3, &pts), Ok(()));
        pts[4321].y_m += 1.0;
        assert_eq!(verify_cloud(&mut c, Some(5000), 4, &pts), Err(CloudFault::Point { index: 0 }));
        let good: Vec<_> = (0..5000).map(|i| cloud_point(9, i)).collect();
        let mut bad = good.clone();
        bad[4321].y_m += 1.0;
        assert_eq!(verify_cloud(&mut c, Some(5000), 9, &bad), Err(CloudFault::Point { index: 4321 }));
        assert_eq!(verify_cloud(&mut c, Some(10), 10, &good), Err(CloudFault::Size { expected: 10, got: 5000 }));
        assert_eq!((c.frames_ok, c.frames_bad, c.frames_missed), (1, 3, 4));
    }

    #[test]
    fn settings_are_validated_with_their_keys() {
        let s = ProducerSettings { points: 0, rate_hz: -1.0, ..Default::default() };
        let mut issues = Issues::at("processes.p.settings");
        s.validate(&mut issues);
        let keys: Vec<_> = issues.iter().map(|i| i.key.as_str()).collect();
        assert_eq!(keys, ["processes.p.settings.points", "processes.p.settings.rate_hz"]);
    }

    #[test]
    fn shm_estimate_grows_with_the_cloud_size() {
        let small = ProducerSettings { points: 1000, ..Default::default() }.shm_estimate_bytes(0);
        let big = ProducerSettings { points: 300_000, ..Default::default() }.shm_estimate_bytes(0);
        assert!(big > 100 * small, "{small} {big}");
        assert!(big >= 300_000 * 12);
    }
}
