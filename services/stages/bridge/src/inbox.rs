//! The queue between the Zenoh callbacks and the stage: received messages with each route's share,
//! a token bucket per route, back-pressure on the link when full.

use crate::lock;
use std::collections::VecDeque;
use std::sync::Mutex;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

/// What the Zenoh callbacks hand to the stage.
pub(crate) enum Incoming {
    /// A message as Zenoh received it (not copied: Zenoh's buffers are reference counted).
    Data {
        route: usize,
        payload: zenoh::bytes::ZBytes,
        attachment: Option<zenoh::bytes::ZBytes>,
    },
    End {
        from: String,
        body: Vec<u8>,
    },
}

/// The queue between the Zenoh callbacks and the stage.
pub(crate) struct Inbox {
    pub(crate) queue: Mutex<Queue>,
    /// Signalled when the stage has taken the queue.
    pub(crate) space: std::sync::Condvar,
    /// Most messages queued per route.
    pub(crate) capacity: usize,
    /// Most bytes queued per route (a route always may queue one message).
    pub(crate) max_bytes: usize,
    /// Per `in` route: dropped because its queue stayed full for [`BLOCK_AT_MOST`].
    pub(crate) dropped: Vec<AtomicU64>,
    /// Per `in` route: the rate limit ([`Bucket`]), `None`: none.
    pub(crate) buckets: Vec<Option<Mutex<Bucket>>>,
    /// Per `in` route: dropped on arrival over the rate limit.
    pub(crate) rate_dropped: Vec<AtomicU64>,
    pub(crate) waker: Option<pipeline_runtime::Waker>,
}

/// What is queued, with each route's share.
#[derive(Default)]
pub(crate) struct Queue {
    pub(crate) items: VecDeque<Incoming>,
    /// Per route: messages and bytes queued.
    pub(crate) count: Vec<usize>,
    pub(crate) bytes: Vec<usize>,
}

/// A token bucket: `rate` tokens a second, holding at most one second's worth (at least one).
pub(crate) struct Bucket {
    pub(crate) rate: f64,
    pub(crate) tokens: f64,
    pub(crate) last: Instant,
}

impl Bucket {
    pub(crate) fn new(rate: f64) -> Self {
        Self { rate, tokens: rate.max(1.0), last: Instant::now() }
    }

    /// Takes a token if there is one.
    pub(crate) fn take(&mut self, now: Instant) -> bool {
        let dt = now.saturating_duration_since(self.last).as_secs_f64();
        self.last = now;
        self.tokens = (self.tokens + dt * self.rate).min(self.rate.max(1.0));
        if self.tokens >= 1.0 {
            self.tokens -= 1.0;
            true
        } else {
            false
        }
    }
}

/// Longest a Zenoh callback waits for room in a full receive queue (back-pressure on the link)
/// before it drops the oldest message: half of Zenoh's default 10 s lease, so that the session's
/// keep-alives are still read in time.
pub(crate) const BLOCK_AT_MOST: Duration = Duration::from_secs(5);

impl Inbox {
    /// Queues a message of `route` unless it is over the route's rate (then it is dropped and
    /// counted); when the route's queue is full, waits (up to [`BLOCK_AT_MOST`]) for the stage
    /// to take it, which holds the link back (a reliable sender blocks), then drops the route's
    /// oldest messages until it fits.
    pub(crate) fn push_data(
        &self,
        route: usize,
        payload: zenoh::bytes::ZBytes,
        attachment: Option<zenoh::bytes::ZBytes>,
    ) {
        if let Some(b) = &self.buckets[route]
            && !lock(b).take(Instant::now())
        {
            self.rate_dropped[route].fetch_add(1, Ordering::Relaxed);
            return;
        }
        let len = payload.len();
        {
            let mut q = lock(&self.queue);
            let t0 = Instant::now();
            let full = |q: &Queue| {
                q.count[route] > 0 && (q.count[route] >= self.capacity || q.bytes[route] + len > self.max_bytes)
            };
            while full(&q) {
                let left = BLOCK_AT_MOST.saturating_sub(t0.elapsed());
                if left.is_zero() {
                    let Some(pos) =
                        q.items.iter().position(|i| matches!(i, Incoming::Data { route: r, .. } if *r == route))
                    else {
                        break;
                    };
                    if let Some(Incoming::Data { payload, .. }) = q.items.remove(pos) {
                        q.count[route] -= 1;
                        q.bytes[route] -= payload.len();
                        self.dropped[route].fetch_add(1, Ordering::Relaxed);
                    }
                    continue;
                }
                if let Some(w) = &self.waker {
                    w.wake();
                }
                q = self.space.wait_timeout(q, left).unwrap_or_else(|p| p.into_inner()).0;
            }
            q.count[route] += 1;
            q.bytes[route] += len;
            q.items.push_back(Incoming::Data { route, payload, attachment });
        }
        if let Some(w) = &self.waker {
            w.wake();
        }
    }

    /// Queues a robot's end marker (one per robot: a repeated one replaces the queued one).
    pub(crate) fn push_end(&self, from: String, body: Vec<u8>) {
        {
            let mut q = lock(&self.queue);
            q.items.retain(|i| !matches!(i, Incoming::End { from: f, .. } if *f == from));
            q.items.push_back(Incoming::End { from, body });
        }
        if let Some(w) = &self.waker {
            w.wake();
        }
    }

    pub(crate) fn take(&self) -> VecDeque<Incoming> {
        let items = {
            let mut q = lock(&self.queue);
            q.count.iter_mut().for_each(|c| *c = 0);
            q.bytes.iter_mut().for_each(|b| *b = 0);
            std::mem::take(&mut q.items)
        };
        self.space.notify_all();
        items
    }

    pub(crate) fn is_empty(&self) -> bool {
        lock(&self.queue).items.is_empty()
    }
}

/// The first 32 bytes of a message held in pieces (its [`shared_types::MsgHeader`]), fewer if
/// it is shorter.
pub(crate) fn gather_head(parts: &[&[u8]]) -> [u8; 32] {
    let mut head = [0u8; 32];
    let mut at = 0;
    for p in parts {
        let n = p.len().min(32 - at);
        head[at..at + n].copy_from_slice(&p[..n]);
        at += n;
        if at == 32 {
            break;
        }
    }
    head
}
