//! The producer's schedule, the same for every transport: at most one message in flight, the next
//! one started when it is due (on an absolute schedule at `--rate-hz`) and the previous one is
//! back; a message that does not come back within the timeout is counted as lost; after the
//! warm-up and the measured messages (or the case's time budget), the [`END`] message goes round
//! the chain so that every relay reports and exits.

use std::time::{Duration, Instant};

use anyhow::bail;

use super::wire::END;

/// What the producer does next.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Action {
    /// Send the message with this index now.
    Send(u64),
    /// Nothing to do until this instant (or until a message arrives).
    WaitUntil(Instant),
    /// The [`END`] message came back: the case is over.
    Done,
}

/// Schedule and end-to-end measurements of one case.
#[derive(Debug)]
pub struct Pacer {
    warmup: u64,
    samples: u64,
    period: Duration,
    timeout: Duration,
    budget: Duration,
    next_index: u64,
    in_flight: Option<(u64, Instant)>,
    due: Instant,
    measure_start: Option<Instant>,
    end_sent: bool,
    done: bool,
    /// End-to-end latency of each measured message (back at the producer − `origin_ns`), ns.
    pub e2e_ns: Vec<u64>,
    /// Latency of the last hop (into the producer) of each measured message, ns.
    pub last_hop_ns: Vec<u64>,
    /// Measured messages that did not come back within the timeout.
    pub lost: u64,
    /// Messages that came back with a torn or wrong-size payload.
    pub bad: u64,
    /// Messages that came back after they had been counted as lost.
    pub stale: u64,
    /// Messages that started more than one period after they were due.
    pub late: u64,
    /// The time budget ended the case before every measured message was sent.
    pub cut_short: bool,
}

impl Pacer {
    /// A schedule of `warmup` + `samples` messages at `rate_hz`, starting now.
    pub fn new(warmup: u64, samples: u64, rate_hz: f64, timeout: Duration, budget: Duration) -> Self {
        Self {
            warmup,
            samples,
            period: Duration::from_secs_f64(1.0 / rate_hz),
            timeout,
            budget,
            next_index: 0,
            in_flight: None,
            due: Instant::now(),
            measure_start: None,
            end_sent: false,
            done: false,
            e2e_ns: Vec::with_capacity(samples as usize),
            last_hop_ns: Vec::with_capacity(samples as usize),
            lost: 0,
            bad: 0,
            stale: 0,
            late: 0,
            cut_short: false,
        }
    }

    /// The message in flight, if any.
    pub fn in_flight(&self) -> Option<u64> {
        self.in_flight.map(|(i, _)| i)
    }

    /// Decides what to do at `now`; call [`Pacer::sent`] after sending. An [`END`] message that
    /// does not come back within the timeout is an error (a relay is stuck or gone).
    pub fn next_action(&mut self, now: Instant) -> anyhow::Result<Action> {
        if self.done {
            return Ok(Action::Done);
        }
        if let Some((index, at)) = self.in_flight {
            if now.duration_since(at) < self.timeout {
                return Ok(Action::WaitUntil(at + self.timeout));
            }
            if index == END {
                bail!("the end message did not come back round the chain within {:?}", self.timeout);
            }
            if index >= self.warmup {
                self.lost += 1;
            }
            self.in_flight = None;
        }
        let measured_all = self.next_index >= self.warmup + self.samples;
        let over_budget = self.measure_start.is_some_and(|t| now.duration_since(t) >= self.budget);
        if measured_all || over_budget {
            if !self.end_sent {
                self.cut_short = !measured_all;
                return Ok(Action::Send(END));
            }
            return Ok(Action::WaitUntil(now + self.timeout));
        }
        if now < self.due {
            return Ok(Action::WaitUntil(self.due));
        }
        Ok(Action::Send(self.next_index))
    }

    /// Records that message `index` was sent at `now`.
    pub fn sent(&mut self, index: u64, now: Instant) {
        self.in_flight = Some((index, now));
        if index == END {
            self.end_sent = true;
            return;
        }
        if index == self.warmup {
            self.measure_start = Some(now);
        }
        self.next_index = index + 1;
        self.due = if now.duration_since(self.due) > self.period {
            self.late += 1;
            now + self.period
        } else {
            self.due + self.period
        };
    }

    /// Records a message back at the producer: `index` (`None` if the payload was torn or of the
    /// wrong size), its origin and last-hop publish times and the receive time, ns.
    pub fn received(&mut self, index: Option<u64>, origin_ns: u64, publish_ns: u64, now_ns: u64) {
        let Some(index) = index else {
            self.bad += 1;
            return;
        };
        if self.in_flight.map(|(i, _)| i) != Some(index) {
            self.stale += 1;
            return;
        }
        self.in_flight = None;
        if index == END {
            self.done = true;
            return;
        }
        if index >= self.warmup && origin_ns > 0 && origin_ns <= now_ns && publish_ns <= now_ns {
            self.e2e_ns.push(now_ns - origin_ns);
            self.last_hop_ns.push(now_ns - publish_ns);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn one_in_flight_warmup_excluded_losses_counted_and_end_sent_last() {
        let mut p = Pacer::new(1, 2, 1000.0, Duration::from_millis(50), Duration::from_secs(10));
        let t0 = Instant::now();
        assert_eq!(p.next_action(t0).unwrap(), Action::Send(0));
        p.sent(0, t0);
        assert!(matches!(p.next_action(t0).unwrap(), Action::WaitUntil(_)), "one in flight only");
        p.received(Some(0), 100, 150, 200);
        assert!(p.e2e_ns.is_empty(), "warm-up recorded");
        let t1 = t0 + Duration::from_millis(2);
        assert_eq!(p.next_action(t1).unwrap(), Action::Send(1));
        p.sent(1, t1);
        p.received(Some(1), 1000, 1500, 1700);
        assert_eq!((p.e2e_ns.clone(), p.last_hop_ns.clone()), (vec![700], vec![200]));
        let t2 = t1 + Duration::from_millis(2);
        assert_eq!(p.next_action(t2).unwrap(), Action::Send(2));
        p.sent(2, t2);
        // Message 2 never comes back: lost after the timeout, then END.
        let t3 = t2 + Duration::from_millis(60);
        assert_eq!(p.next_action(t3).unwrap(), Action::Send(END));
        assert_eq!(p.lost, 1);
        p.sent(END, t3);
        p.received(Some(2), 1, 1, 2);
        assert_eq!(p.stale, 1, "a message back after its timeout is stale");
        p.received(None, 0, 0, 0);
        assert_eq!(p.bad, 1);
        p.received(Some(END), 0, 0, 0);
        assert_eq!(p.next_action(t3).unwrap(), Action::Done);
        assert!(!p.cut_short);
    }

    #[test]
    fn the_time_budget_cuts_a_slow_case_short_and_a_lost_end_is_an_error() {
        let t0 = Instant::now();
        let mut p = Pacer::new(0, 100, 1000.0, Duration::from_millis(50), Duration::from_millis(5));
        p.sent(0, t0);
        p.received(Some(0), 1, 1, 2);
        assert_eq!(p.next_action(t0 + Duration::from_millis(6)).unwrap(), Action::Send(END));
        assert!(p.cut_short);
        p.sent(END, t0 + Duration::from_millis(6));
        assert!(p.next_action(t0 + Duration::from_millis(100)).is_err());
    }
}
