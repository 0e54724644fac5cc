//! Counting and warning about messages refused from producers the pipeline does not control
//! (external drivers, replays, other stages): a [`Guard`] per input counts what it accepted, what
//! it refused by reason ([`Rejection`]) and what it missed (sequence gaps), refuses stamps going
//! back per publisher, and warns at most once per [`WARN_EVERY`] per reason; nothing panics and
//! nothing else is lost. The checks of each wire type are the consumers' own (the sensor
//! monitor's `checks` module, the stages' inputs).

use std::collections::{BTreeMap, HashMap};
use std::fmt::Display;
use std::time::{Duration, Instant};

use serde::Serialize;

/// Shortest interval between two warnings of the same reason on one input.
pub const WARN_EVERY: Duration = Duration::from_secs(5);

/// Why a message was rejected.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Rejection {
    /// Short machine-readable reason (a counter key), e.g. `non_finite`.
    pub reason: &'static str,
    /// What exactly was wrong.
    pub detail: String,
}

pub(crate) fn reject<T>(reason: &'static str, detail: impl Display) -> Result<T, Rejection> {
    Err(Rejection { reason, detail: detail.to_string() })
}

/// Counters and rate-limited warnings for one input.
#[derive(Debug)]
pub struct Guard {
    service: String,
    accepted: u64,
    rejected: BTreeMap<&'static str, u64>,
    last_stamp: HashMap<u128, u64>,
    last_seq: HashMap<u128, u64>,
    missed: u64,
    last_warn: HashMap<&'static str, (Instant, u64)>,
}

/// A guard's counters, for summaries.
#[derive(Debug, Clone, Serialize, serde::Deserialize, schemars::JsonSchema, PartialEq, Eq)]
pub struct GuardReport {
    /// Messages accepted.
    pub accepted: u64,
    /// Messages rejected, by reason.
    pub rejected: BTreeMap<String, u64>,
    /// Messages never received: gaps in the publishers' sequence numbers.
    pub missed: u64,
}

impl Guard {
    /// A guard for the input on `service`.
    pub fn new(service: &str) -> Self {
        Self {
            service: service.to_string(),
            accepted: 0,
            rejected: BTreeMap::new(),
            last_stamp: HashMap::new(),
            last_seq: HashMap::new(),
            missed: 0,
            last_warn: HashMap::new(),
        }
    }

    /// Checks that `stamp_ns` increases for the publisher `publisher_id`; a stamp that goes
    /// backwards or repeats is rejected (`stamp_not_increasing`).
    pub fn check_stamp(&mut self, publisher_id: u128, stamp_ns: u64) -> Result<(), Rejection> {
        match self.last_stamp.get(&publisher_id) {
            Some(&last) if stamp_ns <= last => {
                reject("stamp_not_increasing", format!("stamp {stamp_ns} ns after {last} ns from the same publisher"))
            }
            _ => {
                self.last_stamp.insert(publisher_id, stamp_ns);
                Ok(())
            }
        }
    }

    /// Notes the sequence number of a message from `publisher_id`; a gap counts as missed
    /// messages (lost before they reached this subscriber).
    pub fn note_seq(&mut self, publisher_id: u128, seq: u64) {
        if let Some(last) = self.last_seq.insert(publisher_id, seq)
            && seq > last + 1
        {
            self.missed += seq - last - 1;
        }
    }

    /// Counts the outcome of a check; logs a rejection at most once per [`WARN_EVERY`] per reason
    /// (with the number suppressed since). Returns true when accepted.
    pub fn admit(&mut self, result: Result<(), Rejection>) -> bool {
        match result {
            Ok(()) => {
                self.accepted += 1;
                true
            }
            Err(r) => {
                *self.rejected.entry(r.reason).or_default() += 1;
                let now = Instant::now();
                let entry = self.last_warn.entry(r.reason).or_insert((now - WARN_EVERY * 2, 0));
                if now - entry.0 >= WARN_EVERY {
                    tracing::warn!(service = %self.service, reason = r.reason, suppressed = entry.1, "rejected message: {}", r.detail);
                    *entry = (now, 0);
                } else {
                    entry.1 += 1;
                }
                false
            }
        }
    }

    /// Messages accepted so far.
    pub fn accepted(&self) -> u64 {
        self.accepted
    }

    /// Messages rejected so far (all reasons).
    pub fn rejected(&self) -> u64 {
        self.rejected.values().sum()
    }

    /// The counters.
    pub fn report(&self) -> GuardReport {
        GuardReport {
            accepted: self.accepted,
            rejected: self.rejected.iter().map(|(k, n)| (k.to_string(), *n)).collect(),
            missed: self.missed,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stamps_must_increase_per_publisher() {
        let mut g = Guard::new("s");
        assert!(g.check_stamp(1, 10).is_ok());
        assert!(g.check_stamp(2, 5).is_ok(), "another publisher has its own clock");
        assert_eq!(g.check_stamp(1, 10).unwrap_err().reason, "stamp_not_increasing");
        assert_eq!(g.check_stamp(1, 9).unwrap_err().reason, "stamp_not_increasing");
        assert!(g.check_stamp(1, 11).is_ok());
    }
}
