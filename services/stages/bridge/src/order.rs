//! The order of one `in` route's messages: sequence numbers that go on, skip (a gap, counted) or
//! start again (the sender restarted).

use pipeline_runtime::topics::Origin;

/// A sequence number below this after a higher one: the sender's publisher restarted (its
/// numbers start again from 0), not a replay.
pub(crate) const RESTART_SEQ_BELOW: u64 = 64;

/// The order of one route's messages: the last sequence number seen. (Not the stamps: a
/// service may go back in `stamp_ns` by design, e.g. fusion's poses re-published for a past
/// segment once it is aligned.)
#[derive(Debug, Default, Clone, Copy, PartialEq)]
pub(crate) struct Order {
    pub(crate) last_seq: Option<u64>,
}

/// What [`Order::admit`] says of a message.
#[derive(Debug, PartialEq)]
pub(crate) enum Verdict {
    /// Accepted, after `gap` missing messages; `restarted`: the sender's numbers started again.
    Accepted { gap: u64, restarted: bool },
    /// A sequence number not after the last (repeated or replayed).
    GoingBack(String),
    /// `origin_ns` unset or outside the accepted window.
    OutOfTime(String),
}

impl Order {
    /// Checks a message's header ([`crate::Accept`]): its sequence number goes forward (a repeat
    /// or a step back is refused; a restart from below [`RESTART_SEQ_BELOW`] is accepted), and
    /// its `origin_ns`, once on this machine's clock (`origin`), lies within `accept`'s window
    /// around `now_ns`. The sequence number of a message refused for its time still counts (it
    /// was sent; no gap after it).
    pub(crate) fn admit(
        &mut self,
        h: &shared_types::MsgHeader,
        origin: Option<Origin>,
        accept: &crate::Accept,
        now_ns: u64,
    ) -> Verdict {
        let (mut gap, mut restarted) = (0, false);
        if let Some(last) = self.last_seq {
            if h.seq <= last {
                if h.seq < last && h.seq < RESTART_SEQ_BELOW {
                    restarted = true;
                } else {
                    return Verdict::GoingBack(format!("sequence number {} after {last}: repeated or replayed", h.seq));
                }
            } else {
                gap = h.seq - last - 1;
            }
        }
        self.last_seq = Some(h.seq);
        if let Some(o) = origin {
            let at = match o {
                Origin::Shift(d) => h.origin_ns.saturating_add_signed(d),
                _ => h.origin_ns,
            };
            let ahead_s = (at as f64 - now_ns as f64) / 1e9;
            if h.origin_ns == 0 {
                return Verdict::OutOfTime("origin_ns is not set".into());
            } else if ahead_s > accept.max_future_s {
                return Verdict::OutOfTime(format!("origin_ns {ahead_s:.3} s in the future (accept.max_future_s)"));
            } else if -ahead_s > accept.max_age_s {
                return Verdict::OutOfTime(format!("origin_ns {:.1} s old (accept.max_age_s)", -ahead_s));
            }
        }
        Verdict::Accepted { gap, restarted }
    }
}
