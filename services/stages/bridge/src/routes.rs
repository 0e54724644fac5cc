//! The bridge's routes and how they open: the `out` routes (a local tap, a Zenoh publisher) and
//! the `in` routes (a Zenoh subscriber into the inbox, a local publisher), the receive queue, the
//! clock answers, the revocation list's watch and the access control's refusals.

use std::collections::{BTreeMap, BTreeSet, HashMap, VecDeque};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use pipeline_runtime::topics::{Emit, Tap};
use pipeline_runtime::{Delivery, Runtime, StageError};
use shared_types::services;
use wire_topics::{Topic, topic};
use zenoh::Wait;
use zenoh::qos::CongestionControl;

use crate::buffers::*;
use crate::clock::{ClockProbe, ClockState};
use crate::clock::{boot_id, encode_answer};
use crate::counts::*;
use crate::inbox::*;
use crate::order::*;
use crate::session::*;
use crate::zenoh_err;
use crate::{BridgeSettings, Policy, WhenFull, clock_answer_key, clock_ask_key, key, signature};
use pipeline_runtime::monotonic_ns;
use pipeline_runtime::topics::Origin;

pub(crate) struct OutRoute {
    pub(crate) topic: &'static Topic,
    pub(crate) tap: Box<dyn Tap>,
    pub(crate) publisher: zenoh::pubsub::Publisher<'static>,
    pub(crate) policy: Policy,
    pub(crate) min_interval: Option<Duration>,
    pub(crate) next_send: Option<Instant>,
    pub(crate) signature: Vec<u8>,
    pub(crate) counts: OutCounts,
    pub(crate) last_seq: HashMap<u128, u64>,
    pub(crate) warned: bool,
    /// Whether a subscriber on the other side matches the key (kept by a matching listener).
    pub(crate) matched: Arc<AtomicBool>,
    pub(crate) _matching: zenoh::matching::MatchingListener<()>,
    /// Send buffers, reused (a fresh multi-megabyte allocation per message costs its page faults).
    pub(crate) buffers: SendBuffers,
}

pub(crate) struct InRoute {
    pub(crate) from: String,
    pub(crate) service: String,
    pub(crate) local: &'static str,
    /// The route's name in summary.json: the local service, prefixed with `<from>:` when
    /// several robots publish on it.
    pub(crate) route_name: String,
    pub(crate) topic: &'static Topic,
    pub(crate) signature: Vec<u8>,
    /// Index of the route (into the inbox's counters).
    pub(crate) index: usize,
    /// Publishing may wait for a full local subscriber (`when_full = wait` on a service that
    /// does not overwrite).
    pub(crate) may_wait: bool,
    /// Index into the stage's emitters (routes of several robots may share one local service).
    pub(crate) emitter: usize,
    pub(crate) counts: InCounts,
    /// The last sequence number and stamp (see [`Order`]).
    pub(crate) order: Order,
    pub(crate) warned: bool,
    /// Reasons of refusal already warned about (once per route and reason).
    pub(crate) warned_refusals: BTreeSet<&'static str>,
    /// The clock of the sending robot (`None` under `clock = "keep"`).
    pub(crate) clock: Option<Arc<Mutex<ClockState>>>,
    pub(crate) warned_clock: bool,
    /// Receive-queue drops of the killed instances before this one (restored counts).
    pub(crate) queue_dropped_before: u64,
    /// Rate drops of the killed instances before this one (restored counts).
    pub(crate) rate_dropped_before: u64,
    /// Messages dropped here (rate, queue) not yet matched by a gap in the sequence numbers.
    pub(crate) drop_credit: u64,
    pub(crate) _subscriber: zenoh::pubsub::Subscriber<()>,
}

impl InRoute {
    /// Warns about a refusal of `reason`, once per route and reason.
    pub(crate) fn warn_refusal(&mut self, reason: &'static str, detail: &str) {
        if self.warned_refusals.insert(reason) {
            tracing::warn!(from = %self.from, route = %self.route_name, reason = %reason,
                "refused a message from the robot: {detail} (counted in summary.json bridge.in; warned once per route \
                 and reason)");
        }
    }

    /// The checks on a message's header before it is published ([`Order::admit`]): counts a
    /// refusal and warns once; returns the messages missing before this one (a sequence gap), or
    /// why it is dropped.
    pub(crate) fn admit(
        &mut self,
        h: &shared_types::MsgHeader,
        origin: Option<Origin>,
        accept: &crate::Accept,
    ) -> Result<u64, &'static str> {
        let last = self.order.last_seq;
        match self.order.admit(h, origin, accept, monotonic_ns()) {
            Verdict::Accepted { gap, restarted } => {
                if restarted {
                    self.counts.sender_restarts += 1;
                    tracing::warn!(from = %self.from, route = %self.route_name, seq = h.seq, ?last,
                        "the sender's sequence numbers started again: its publisher restarted (counted in summary.json \
                         bridge.in as sender_restarts)");
                }
                // Messages this bridge dropped itself (rate, queue) show as a gap too: not lost.
                let dropped_here = gap.min(self.drop_credit);
                self.drop_credit -= dropped_here;
                let lost = gap - dropped_here;
                self.counts.seq_gaps += lost;
                Ok(lost)
            }
            Verdict::GoingBack(detail) => {
                self.counts.refused_going_back += 1;
                self.warn_refusal("going_back", &detail);
                Err("refused: a sequence number not after the last")
            }
            Verdict::OutOfTime(detail) => {
                self.counts.refused_time += 1;
                self.warn_refusal("time", &detail);
                Err("refused: origin_ns out of the accepted window")
            }
        }
    }
}

/// The revocation list as it is now, and its watch (TLS only): a bridge whose own certificate is
/// revoked refuses to start.
pub(crate) fn revocation_state(
    settings: &BridgeSettings,
) -> Result<(BTreeSet<String>, Option<RevocationWatch>), StageError> {
    let Some(t) = &settings.zenoh.tls else { return Ok((BTreeSet::new(), None)) };
    let revoked = t.read_revoked().map_err(|e| StageError::Settings(format!("zenoh.tls.revoked: {e}")))?;
    let own = crate::read_certificate(&t.certificate).ok().map(|c| c.common_name);
    if let Some(p) = crate::revocation_problem(own.as_deref(), &revoked) {
        return Err(StageError::Settings(format!("{}: {p}", t.revocation_list().display())));
    }
    if let Some(gap) = crate::revocation_gap(settings, &revoked) {
        tracing::warn!("{gap}");
    }
    if !revoked.is_empty() {
        tracing::warn!(?revoked, list = %t.revocation_list().display(),
            "revoked hosts: everything from them is refused, nothing goes to them");
    }
    Ok((revoked.clone(), Some(RevocationWatch::start(t.revocation_list(), revoked)?)))
}

/// The access control's refusals, counted per route (when there is an access control to count).
pub(crate) fn watch_refusals(settings: &BridgeSettings) -> Option<crate::refusals::Refusals> {
    crate::refusals_counted(settings).then(|| {
        let revoked = settings.zenoh.tls.as_ref().and_then(|t| t.read_revoked().ok()).unwrap_or_default();
        crate::refusals::Refusals::watch(
            revoked,
            settings.inbound.iter().map(|r| {
                let shared = settings.inbound.iter().filter(|o| o.local_service() == r.local_service()).count() > 1;
                let name =
                    if shared { format!("{}:{}", r.from, r.local_service()) } else { r.local_service().to_string() };
                (key(&settings.namespace, &r.from, &r.service), name)
            }),
        )
    })
}

/// Logs the open session and how its links are secured.
pub(crate) fn log_session(settings: &BridgeSettings, session: &zenoh::Session) {
    tracing::info!(zid = %session.zid(), mode = %settings.zenoh.mode, listen = ?settings.zenoh.listen,
        connect = ?settings.zenoh.connect, "zenoh session open");
    match &settings.zenoh.tls {
        None => tracing::warn!(
            "insecure: the link is plain TCP: anyone on the network reads it, connects, and publishes under any robot's name"
        ),
        Some(t) => match crate::read_certificate(&t.certificate) {
            Ok(c) => tracing::info!(name = %c.common_name, not_after_unix_s = c.not_after_unix_s,
                "mutual TLS: only hosts whose certificate the CA signed get in, each only under its own name"),
            Err(e) => tracing::warn!("mutual TLS, but the certificate cannot be read back: {e}"),
        },
    }
}

/// One Zenoh publisher per `out` route, with a listener for whether anyone receives it.
pub(crate) fn open_out_routes(
    settings: &BridgeSettings,
    session: &zenoh::Session,
    rt: &mut Runtime,
) -> Result<Vec<OutRoute>, StageError> {
    let mut outs = vec![];
    for r in &settings.out {
        let t = topic(&r.service).ok_or_else(|| StageError::Settings(format!("out: unknown service {}", r.service)))?;
        let k = key(&settings.namespace, &settings.robot, t.service);
        let cc = match r.policy {
            Policy::Reliable => CongestionControl::Block,
            Policy::DropOldest => CongestionControl::Drop,
        };
        let publisher = session
            .declare_publisher(k.clone())
            .congestion_control(cc)
            .wait()
            .map_err(|e| zenoh_err(format!("publisher on {k}"), e))?;
        let matched = Arc::new(AtomicBool::new(publisher.matching_status().wait().is_ok_and(|m| m.matching())));
        let flag = matched.clone();
        let matching = publisher
            .matching_listener()
            .callback(move |m| flag.store(m.matching(), Ordering::Relaxed))
            .wait()
            .map_err(|e| zenoh_err(format!("matching listener on {k}"), e))?;
        outs.push(OutRoute {
            matched,
            _matching: matching,
            buffers: SendBuffers::default(),
            topic: t,
            tap: t.tap(rt)?,
            publisher,
            policy: r.policy,
            min_interval: (r.max_rate_hz > 0.0).then(|| Duration::from_secs_f64(1.0 / r.max_rate_hz)),
            next_send: None,
            signature: signature(t).into_bytes(),
            counts: OutCounts { digest: DIGEST0, ..Default::default() },
            last_seq: HashMap::new(),
            warned: false,
        });
    }
    Ok(outs)
}

/// The receive queue Zenoh's callbacks fill (bounded in messages and bytes, rate-limited per route).
pub(crate) fn new_inbox(settings: &BridgeSettings, rt: &mut Runtime) -> Result<Arc<Inbox>, StageError> {
    let waker = if settings.inbound.is_empty() { None } else { Some(rt.waker()?) };
    let n_in = settings.inbound.len();
    Ok(Arc::new(Inbox {
        queue: Mutex::new(Queue { items: VecDeque::new(), count: vec![0; n_in], bytes: vec![0; n_in] }),
        space: std::sync::Condvar::new(),
        capacity: settings.queue_messages,
        max_bytes: (settings.accept.queue_mib * 1024.0 * 1024.0) as usize,
        dropped: settings.inbound.iter().map(|_| AtomicU64::new(0)).collect(),
        buckets: settings
            .inbound
            .iter()
            .map(|r| {
                let hz = r.max_rate_hz.unwrap_or(settings.accept.max_rate_hz);
                (hz > 0.0).then(|| Mutex::new(Bucket::new(hz)))
            })
            .collect(),
        rate_dropped: settings.inbound.iter().map(|_| AtomicU64::new(0)).collect(),
        waker,
    }))
}

/// Answers the receiving bridges' clock asks (a sending bridge; see crate::clock).
pub(crate) fn answer_clock_asks(
    settings: &BridgeSettings,
    session: &zenoh::Session,
) -> Result<zenoh::pubsub::Subscriber<()>, StageError> {
    let (ask_k, answer_k, boot) = (
        clock_ask_key(&settings.namespace, &settings.robot),
        clock_answer_key(&settings.namespace, &settings.robot),
        boot_id(),
    );
    let answer = session
        .declare_publisher(answer_k.clone())
        .congestion_control(CongestionControl::Drop)
        .express(true)
        .wait()
        .map_err(|e| zenoh_err(format!("publisher on {answer_k}"), e))?;
    session
        .declare_subscriber(&ask_k)
        .callback(move |ask| {
            let stamp = monotonic_ns();
            let Some(nonce) = ask.payload().to_bytes().get(..8).and_then(|b| b.try_into().ok()) else {
                return;
            };
            // `Drop`: on a congested link the answer is dropped at once (it would be a wrong one),
            // and Zenoh's receive thread that runs this goes on.
            if let Err(e) = answer.put(encode_answer(u64::from_le_bytes(nonce), stamp, &boot)).wait() {
                tracing::debug!("clock ask not answered: {e}");
            }
        })
        .wait()
        .map_err(|e| zenoh_err(format!("subscriber on {ask_k}"), e))
}

/// The local publishers of the `in` routes (routes that share a local service share one).
pub(crate) type Emitters = Vec<Box<dyn Emit>>;

/// One Zenoh subscriber per `in` route (into the inbox) and one local publisher per local
/// service (routes that share one share its publisher).
pub(crate) fn open_in_routes(
    settings: &BridgeSettings,
    session: &zenoh::Session,
    rt: &mut Runtime,
    inbox: &Arc<Inbox>,
    clocks: &BTreeMap<String, ClockProbe>,
) -> Result<(Vec<InRoute>, Emitters), StageError> {
    let mut ins = vec![];
    let mut emitters: Vec<Box<dyn Emit>> = vec![];
    let mut emitter_of: HashMap<String, usize> = HashMap::new();
    for (i, r) in settings.inbound.iter().enumerate() {
        let t = topic(&r.service).ok_or_else(|| StageError::Settings(format!("in: unknown service {}", r.service)))?;
        let local: &'static str = Box::leak(r.local_service().to_string().into_boxed_str());
        let qos = services::service_spec(t.service)
            .map(|s| s.qos)
            .ok_or_else(|| StageError::Settings(format!("in: {} has no QoS in the contract", t.service)))?;
        let emitter = match emitter_of.get(local) {
            Some(&e) => e,
            None => {
                let delivery = match r.when_full {
                    WhenFull::Wait => Delivery::WaitWhenFull { max_wait: None },
                    WhenFull::Drop => Delivery::DiscardWhenFull,
                };
                emitters.push(t.emitter_on(rt, local, &qos, delivery)?);
                emitter_of.insert(local.to_string(), emitters.len() - 1);
                emitters.len() - 1
            }
        };
        let k = key(&settings.namespace, &r.from, t.service);
        let inbox_cb = inbox.clone();
        let subscriber = session
            .declare_subscriber(k.clone())
            .callback(move |sample| {
                inbox_cb.push_data(i, sample.payload().clone(), sample.attachment().cloned());
            })
            .wait()
            .map_err(|e| zenoh_err(format!("subscriber on {k}"), e))?;
        let shared = settings.inbound.iter().filter(|o| o.local_service() == local).count() > 1;
        ins.push(InRoute {
            index: i,
            may_wait: r.when_full == WhenFull::Wait && !qos.safe_overflow,
            route_name: if shared { format!("{}:{local}", r.from) } else { local.to_string() },
            from: r.from.clone(),
            service: r.service.clone(),
            local,
            topic: t,
            signature: signature(t).into_bytes(),
            emitter,
            counts: InCounts { digest: DIGEST0, ..Default::default() },
            order: Order::default(),
            warned: false,
            warned_refusals: BTreeSet::new(),
            clock: clocks.get(&r.from).map(|p: &ClockProbe| p.state.clone()),
            warned_clock: false,
            queue_dropped_before: 0,
            rate_dropped_before: 0,
            drop_credit: 0,
            _subscriber: subscriber,
        });
    }
    Ok((ins, emitters))
}
