//! The offset between two hosts' `CLOCK_MONOTONIC` clocks, so that a forwarded message's
//! `origin_ns` (stamped on the sender's clock) can be put on the receiver's, and end-to-end latency
//! spans both hosts.
//!
//! Every bridge that sends (`out`) answers the asks it gets on `<namespace>/<robot>/_bridge/clock/ask`
//! (a nonce) on `<namespace>/<robot>/_bridge/clock/answer` with the nonce, its `CLOCK_MONOTONIC` and
//! its boot id (`/proc/sys/kernel/random/boot_id`). Both are plain publications with congestion
//! control `Drop` (a late answer is a wrong one): no Zenoh query, whose answer would be pushed
//! from Zenoh's receive thread and block it on a congested link (after a link outage the link then
//! stopped reading and never resumed: tests/tests/bridge.rs, the link cut). A receiving bridge asks
//! each robot it receives from (every 200 ms for the first 2 s, then every second) and estimates
//! the offset NTP-style: for a query sent at local `t0`, answered at remote `r` and received at
//! local `t1`, `offset = r − (t0 + t1) / 2` with an error of at most half the round trip
//! (`t1 − t0`) under asymmetric delays. Of the last [`WINDOW`] answers it keeps the one with the
//! shortest round trip (the least queued). Two processes with the same boot id share one clock:
//! then the offset is exactly 0 and nothing is shifted (`clock = "auto"`).
//!
//! Clock drift between hosts (typically below 50 ppm) moves the offset by < 1 ms over the window.

use crate::{ClockMode, clock_answer_key, clock_ask_key};
use crate::{lock, zenoh_err};
use pipeline_runtime::StageError;
use pipeline_runtime::monotonic_ns;
use pipeline_runtime::topics::Origin;
use std::collections::VecDeque;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use zenoh::Wait;
use zenoh::qos::CongestionControl;

/// Answers kept for the estimate.
pub const WINDOW: usize = 16;

/// One answered query.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
pub struct ClockSample {
    /// Remote clock minus local clock, ns.
    pub offset_ns: i64,
    /// Round trip of the query, ns (twice the bound on the offset's error).
    pub rtt_ns: u64,
}

/// The offset estimate from the recent answers.
#[derive(Debug, Clone, Default)]
pub struct OffsetEstimator {
    recent: VecDeque<ClockSample>,
}

impl OffsetEstimator {
    /// Adds an answer: query sent at local `t0_ns`, answered at remote `remote_ns`, received at
    /// local `t1_ns`. Returns the sample, or `None` when the local stamps go back.
    pub fn add(&mut self, t0_ns: u64, remote_ns: u64, t1_ns: u64) -> Option<ClockSample> {
        let rtt_ns = t1_ns.checked_sub(t0_ns)?;
        let mid = t0_ns as i128 + rtt_ns as i128 / 2;
        let offset_ns = i64::try_from(remote_ns as i128 - mid).ok()?;
        let s = ClockSample { offset_ns, rtt_ns };
        if self.recent.len() == WINDOW {
            self.recent.pop_front();
        }
        self.recent.push_back(s);
        Some(s)
    }

    /// The recent answer with the shortest round trip.
    pub fn estimate(&self) -> Option<ClockSample> {
        self.recent.iter().copied().min_by_key(|s| s.rtt_ns)
    }
}

/// This machine's boot id (equal for every process on one running kernel, and different after a
/// reboot or on another host), or an empty string where the kernel does not tell.
pub fn boot_id() -> String {
    std::fs::read_to_string("/proc/sys/kernel/random/boot_id").map(|s| s.trim().to_string()).unwrap_or_default()
}

/// The answer to the ask with `nonce`: the nonce and the remote `CLOCK_MONOTONIC` (8 bytes each,
/// little-endian), then its boot id.
pub fn encode_answer(nonce: u64, monotonic_ns: u64, boot_id: &str) -> Vec<u8> {
    let mut v = nonce.to_le_bytes().to_vec();
    v.extend_from_slice(&monotonic_ns.to_le_bytes());
    v.extend_from_slice(boot_id.as_bytes());
    v
}

/// Reads an answer made by [`encode_answer`]: (nonce, remote stamp, boot id).
pub fn decode_answer(bytes: &[u8]) -> Option<(u64, u64, String)> {
    let nonce = u64::from_le_bytes(bytes.get(..8)?.try_into().ok()?);
    let stamp = u64::from_le_bytes(bytes.get(8..16)?.try_into().ok()?);
    Some((nonce, stamp, String::from_utf8_lossy(&bytes[16..]).into_owned()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn offset_from_the_shortest_round_trip() {
        let mut e = OffsetEstimator::default();
        assert_eq!(e.estimate(), None);
        // Remote is 5 s ahead. A slow answer (queued 3 ms on the way back) and a quick one.
        let s = e.add(1_000_000_000, 6_001_500_000, 1_003_000_000).unwrap();
        assert_eq!(s, ClockSample { offset_ns: 5_000_000_000, rtt_ns: 3_000_000 });
        e.add(2_000_000_000, 7_000_100_000, 2_000_200_000).unwrap();
        let best = e.estimate().unwrap();
        assert_eq!(best, ClockSample { offset_ns: 5_000_000_000, rtt_ns: 200_000 });
        // Stamps going back are refused.
        assert_eq!(e.add(10, 5, 9), None);
        // Remote behind: negative offsets.
        let mut e = OffsetEstimator::default();
        e.add(9_000_000_000, 1_000_000_000, 9_000_000_100).unwrap();
        assert_eq!(e.estimate().unwrap().offset_ns, -8_000_000_050);
    }

    #[test]
    fn window_forgets_old_answers() {
        let mut e = OffsetEstimator::default();
        e.add(0, 1_000, 10).unwrap(); // rtt 10: the best, but it falls out of the window
        for k in 0..WINDOW as u64 {
            e.add(1_000 * (k + 1), 2_000 * (k + 1), 1_000 * (k + 1) + 100).unwrap();
        }
        assert_eq!(e.estimate().unwrap().rtt_ns, 100);
    }

    #[test]
    fn answers_round_trip() {
        let a = encode_answer(7 << 32 | 3, 123_456_789, "3f0c-boot");
        assert_eq!(decode_answer(&a), Some((7 << 32 | 3, 123_456_789, "3f0c-boot".to_string())));
        assert_eq!(decode_answer(&a[..12]), None);
        assert!(!boot_id().contains('\n'));
    }
}

/// What is known of a sending robot's clock (kept by its [`ClockProbe`]).
#[derive(Debug, Default)]
pub(crate) struct ClockState {
    pub(crate) mode: ClockMode,
    /// Whether the robot's bridge runs on this machine (same boot id), once it answered.
    pub(crate) same_machine: Option<bool>,
    pub(crate) estimator: OffsetEstimator,
    pub(crate) asked: u64,
    pub(crate) answered: u64,
}

impl ClockState {
    /// What becomes of a message's `origin_ns`; `None`: the offset is needed but not known yet
    /// (the message keeps the sender's clock).
    pub(crate) fn origin(&self) -> Option<Origin> {
        if self.mode == ClockMode::Auto && self.same_machine == Some(true) {
            return Some(Origin::Keep);
        }
        self.estimator.estimate().map(|e| Origin::Shift(-e.offset_ns))
    }

    pub(crate) fn summary(&self) -> crate::summary::ClockSummary {
        let e = self.estimator.estimate();
        crate::summary::ClockSummary {
            mode: self.mode,
            same_machine: self.same_machine,
            offset_ns: e.map(|e| e.offset_ns),
            rtt_ns: e.map(|e| e.rtt_ns),
            shifted: self.origin().is_some_and(|o| o != Origin::Keep),
            asked: self.asked,
            answered: self.answered,
        }
    }
}

/// A thread that asks a robot's bridge for its clock (see [`crate::clock`]).
pub(crate) struct ClockProbe {
    pub(crate) state: Arc<Mutex<ClockState>>,
    pub(crate) stop: Arc<AtomicBool>,
    pub(crate) thread: Option<std::thread::JoinHandle<()>>,
    pub(crate) _answers: zenoh::pubsub::Subscriber<()>,
}

/// Nonces of different probes (of this process and, by the process id, of others) differ.
static PROBES: AtomicU64 = AtomicU64::new(0);

impl ClockProbe {
    pub(crate) fn start(
        session: &zenoh::Session,
        namespace: &str,
        robot: String,
        mode: ClockMode,
    ) -> Result<Self, StageError> {
        let state = Arc::new(Mutex::new(ClockState { mode, ..Default::default() }));
        let stop = Arc::new(AtomicBool::new(false));
        let (st, sp) = (state.clone(), stop.clone());
        let local_boot = boot_id();
        let (ask_k, answer_k) = (clock_ask_key(namespace, &robot), clock_answer_key(namespace, &robot));
        // Answers (with the local time they came) go to the thread; the callback never waits.
        let (tx, rx) = std::sync::mpsc::sync_channel::<(u64, zenoh::bytes::ZBytes)>(64);
        let answers = session
            .declare_subscriber(&answer_k)
            .callback(move |s| {
                let _ = tx.try_send((monotonic_ns(), s.payload().clone()));
            })
            .wait()
            .map_err(|e| zenoh_err(format!("subscriber on {answer_k}"), e))?;
        let ask = session
            .declare_publisher(ask_k.clone())
            .congestion_control(CongestionControl::Drop)
            .express(true)
            .wait()
            .map_err(|e| zenoh_err(format!("publisher on {ask_k}"), e))?;
        let probe = (u64::from(std::process::id()) << 16 | PROBES.fetch_add(1, Ordering::Relaxed) & 0xffff) << 32;
        let thread = std::thread::Builder::new()
            .name("clock".into())
            .spawn(move || {
                let mut known = false;
                let mut k = 0u32;
                while !sp.load(Ordering::Relaxed) {
                    let nonce = probe | u64::from(k);
                    let t0 = monotonic_ns();
                    lock(&st).asked += 1;
                    if ask.put(nonce.to_le_bytes().to_vec()).wait().is_ok() {
                        let deadline = Instant::now() + Duration::from_millis(500);
                        // Answers to other probes (or late ones to earlier asks) are skipped.
                        while let Ok((t1, payload)) =
                            rx.recv_timeout(deadline.saturating_duration_since(Instant::now()))
                        {
                            let Some((n, remote, boot)) = decode_answer(&payload.to_bytes()) else { continue };
                            if n != nonce {
                                continue;
                            }
                            let mut s = lock(&st);
                            s.answered += 1;
                            s.same_machine = Some(!boot.is_empty() && boot == local_boot);
                            let sample = s.estimator.add(t0, remote, t1);
                            if !known && let Some(ClockSample { offset_ns, rtt_ns }) = sample {
                                known = true;
                                tracing::info!(
                                    %robot,
                                    same_machine = s.same_machine,
                                    offset_ms = offset_ns as f64 / 1e6,
                                    error_ms = rtt_ns as f64 / 2e6,
                                    "clock of the sending robot measured (its CLOCK_MONOTONIC minus ours)"
                                );
                            }
                            break;
                        }
                    }
                    k += 1;
                    let pause = if k < 10 { Duration::from_millis(200) } else { Duration::from_secs(1) };
                    let until = Instant::now() + pause;
                    while !sp.load(Ordering::Relaxed) && Instant::now() < until {
                        std::thread::sleep(Duration::from_millis(20));
                    }
                }
            })
            .map_err(|e| StageError::Settings(format!("clock thread: {e}")))?;
        Ok(Self { state, stop, thread: Some(thread), _answers: answers })
    }
}

impl Drop for ClockProbe {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}
