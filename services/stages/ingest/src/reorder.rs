//! Clouds a little later than the rest, in a replay as fast as possible.
//!
//! Replaying as fast as possible, the source publishes as fast as its slowest consumer takes
//! messages. The octree mapper takes a depth cloud in tens of milliseconds; while the source
//! waits to publish one, everything after it in data order waits too, including the odometry a
//! SLAM frame published just before needs (FastSLAM predicts to a frame's stamp with the
//! odometry up to it). [`CloudLag`] publishes each cloud after every other message up to
//! `lag_ns` later in data time, so a cloud that holds the source back holds back only messages
//! that are not due yet. Each stream keeps its own order; two streams move by at most the lag.

use std::collections::VecDeque;

use crate::Item;

/// Reorders a data-ordered item stream so that each cloud comes after the other items up to
/// `lag_ns` later (see the module docs). Holds at most the clouds of one lag window.
#[derive(Debug, Default)]
pub struct CloudLag {
    lag_ns: u64,
    held: VecDeque<Item>,
    ahead: Option<Item>,
    last_read_ns: u64,
    source_done: bool,
    /// Most clouds held at once.
    pub max_held: usize,
}

impl CloudLag {
    /// A reorder with `lag_ns` (0: items pass unchanged).
    pub fn new(lag_ns: u64) -> Self {
        Self { lag_ns, ..Self::default() }
    }

    /// The next item, reading from `read` (the data-ordered source) as needed; `None` at the end.
    pub fn next<E>(&mut self, mut read: impl FnMut() -> Result<Option<Item>, E>) -> Result<Option<Item>, E> {
        if self.lag_ns == 0 {
            return read();
        }
        while self.ahead.is_none() && !self.source_done {
            if self.held.front().is_some_and(|c| c.stamp_ns().saturating_add(self.lag_ns) < self.last_read_ns) {
                break; // the oldest cloud is due whatever comes next
            }
            match read()? {
                Some(item) => {
                    self.last_read_ns = self.last_read_ns.max(item.stamp_ns());
                    if matches!(item, Item::Cloud { .. }) {
                        self.held.push_back(item);
                        self.max_held = self.max_held.max(self.held.len());
                    } else {
                        self.ahead = Some(item);
                    }
                }
                None => self.source_done = true,
            }
        }
        let cloud_first = match (self.held.front(), &self.ahead) {
            (Some(c), Some(a)) => c.stamp_ns().saturating_add(self.lag_ns) < a.stamp_ns(),
            (Some(_), None) => true,
            (None, _) => false,
        };
        Ok(if cloud_first { self.held.pop_front() } else { self.ahead.take() })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn odo(t_ms: u64) -> Item {
        Item::Depth { stamp_ns: t_ms * 1_000_000, reading: Default::default() }
    }

    fn cloud(t_ms: u64) -> Item {
        Item::Cloud { stamp_ns: t_ms * 1_000_000, world_from_sensor: None, points: vec![[1.0, 2.0, 3.0]] }
    }

    fn run(lag_ms: u64, items: Vec<Item>) -> Vec<(bool, u64)> {
        let mut src = items.into_iter();
        let mut r = CloudLag::new(lag_ms * 1_000_000);
        let mut out = vec![];
        while let Some(i) = r.next(|| Ok::<_, ()>(src.next())).unwrap() {
            out.push((matches!(i, Item::Cloud { .. }), i.stamp_ns() / 1_000_000));
        }
        out
    }

    #[test]
    fn a_cloud_comes_after_the_other_items_within_the_lag_and_nothing_is_lost() {
        let items =
            vec![odo(0), cloud(0), odo(20), odo(40), cloud(50), odo(60), odo(80), odo(100), odo(200), cloud(210)];
        let out = run(50, items);
        assert_eq!(
            out,
            vec![
                (false, 0),
                (false, 20),
                (false, 40),
                (true, 0),
                (false, 60),
                (false, 80),
                (false, 100),
                (true, 50),
                (false, 200),
                (true, 210),
            ]
        );
        // Without a lag the order is the source's.
        let items = vec![odo(0), cloud(0), odo(20), cloud(25)];
        assert_eq!(run(0, items), vec![(false, 0), (true, 0), (false, 20), (true, 25)]);
    }

    #[test]
    fn clouds_alone_pass_in_order_holding_at_most_one_lag_window() {
        let items: Vec<Item> = (0..100).map(|i| cloud(i * 10)).collect();
        let mut src = items.into_iter();
        let mut r = CloudLag::new(30_000_000);
        let mut got = vec![];
        while let Some(i) = r.next(|| Ok::<_, ()>(src.next())).unwrap() {
            got.push(i.stamp_ns() / 1_000_000);
        }
        assert_eq!(got, (0..100).map(|i| i * 10).collect::<Vec<u64>>());
        assert!(r.max_held <= 5, "held {}", r.max_held);
    }
}
